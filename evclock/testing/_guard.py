"""The guard around an ``async def`` test function, whichever plugin runs it: it checks the test
runs on evclock's loop, enforces the sim-time limit (``sim_timeout``), is what the wall-time
budget cancels, and reports either overrun with where the test's tasks were."""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, Final, Literal, TypeVar

from evclock._errors import PluginUsageError, SimTimeLimitError
from evclock.hosts._loop import SimEventLoop
from evclock.testing._budget import BUDGET_HINT, WallTimeBudgetError
from evclock.testing._describe import describe_tasks

if TYPE_CHECKING:
    from evclock.testing._state import ItemState

_T = TypeVar("_T")

_SIM_HINT: Final = (
    "Raise the limit with @pytest.mark.evclock(sim_timeout=...) or --evclock-sim-timeout "
    "(0 disables it)."
)


class CallGuard:
    """The running test function: what the budgets cancel, and how it is reported."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        task: asyncio.Task[Any],
        coro: Coroutine[Any, Any, Any],
    ) -> None:
        self.loop = loop
        self.task = task
        self.coro = coro
        self.reason: Literal["wall", "sim"] | None = None
        self.where: tuple[str, ...] = ()
        self.limit = 0.0
        self.at = 0.0
        #: How many times the budgets cancelled the test's task.
        self.cancels = 0

    def request_expiry(self, seconds: float) -> None:
        """From the watchdog thread: cancel the test on its loop's thread."""
        with contextlib.suppress(RuntimeError):  # the loop just closed
            self.loop.call_soon_threadsafe(self._expire, "wall", seconds)

    def sim_deadline(self, seconds: float) -> None:
        # Run after everything else due at the limit, then decide: a loop with nothing left to
        # do is a deadlock, which the loop itself reports (DeadlockError) rather than us.
        self.loop.call_soon(self._check_sim_deadline, seconds)

    def _check_sim_deadline(self, seconds: float) -> None:
        if not _would_deadlock(self.loop):
            self._expire("sim", seconds)

    def _expire(self, reason: Literal["wall", "sim"], seconds: float) -> None:
        if self.task.done():
            return
        if self.reason is not None:  # the test swallowed the cancellation: cancel it again
            self.cancels += 1
            self.task.cancel(f"evclock: {self.reason}-time budget exceeded")
            return
        self.cancels = 1
        self.reason = reason
        self.limit = seconds
        self.at = self.loop.time()
        self.where = describe_tasks(self.loop, self.task)
        self.task.cancel(f"evclock: {reason}-time budget exceeded")

    def error(self) -> Exception:
        where = "\n".join(f"  {line}" for line in self.where) or "  (no task)"
        sim = isinstance(self.loop, SimEventLoop)
        at = f" (at sim time {self.at:g} s)" if sim else ""
        if self.reason == "sim":
            of = "sim time" if sim else "wall time (--evclock-wall)"
            return SimTimeLimitError(
                f"evclock: sim-time limit exceeded: the test was still running after "
                f"{self.limit:g} s of {of}{at} and was cancelled. Its tasks were at:\n{where}\n"
                f"{_SIM_HINT}"
            )
        return WallTimeBudgetError(
            f"evclock: wall-time budget exceeded: the test was still running after "
            f"{self.limit:g} s of wall time{at} and was cancelled. Its tasks were at:\n{where}\n"
            f"{BUDGET_HINT}"
        )


def _would_deadlock(loop: asyncio.AbstractEventLoop) -> bool:
    """Whether a simulation loop has nothing left that could ever wake a task."""
    return isinstance(loop, SimEventLoop) and loop._would_deadlock()


# The names ``evclock_test`` and ``_run_guarded`` are hidden from task descriptions
# (``_describe._MACHINERY_CODE_NAMES``): keep them in step.


def guard(
    func: Callable[..., Coroutine[Any, Any, _T]], state: ItemState
) -> Callable[..., Coroutine[Any, Any, _T]]:
    """The test function ``func``, each call of which runs under the test's guard."""

    @functools.wraps(func, updated=())
    async def evclock_test(*args: Any, **kwargs: Any) -> _T:
        __tracebackhide__ = True
        return await _run_guarded(func(*args, **kwargs), state)

    return evclock_test


async def _run_guarded(coro: Coroutine[Any, Any, _T], state: ItemState) -> _T:
    __tracebackhide__ = True
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    if task is None or (state.expect_sim and not isinstance(loop, SimEventLoop)):
        coro.close()
        raise PluginUsageError(wrong_loop_message(state, loop))
    if state.pybullet_source is not None and not state.source_adopted:
        coro.close()
        raise PluginUsageError(
            "evclock: the PyBullet world of this test is not stepped by its loop: the loop was "
            "created before the evclock_pybullet fixture (a loop shared with other tests?); "
            "use a function-scoped loop for tests that use evclock_pybullet"
        )
    call = state.call = CallGuard(loop, task, coro)
    cancelling = task.cancelling()
    sim_limit = state.options.sim_timeout
    handle = loop.call_later(sim_limit, call.sim_deadline, sim_limit) if sim_limit else None
    budget = state.budget
    if budget is not None:
        budget.enter_call(call)
    try:
        result = await coro
    except asyncio.CancelledError as exc:
        if call.reason is not None and _uncancel(task, call.cancels) <= cancelling:
            # Keep the traceback through the test: the report shows where it was stopped.
            raise call.error().with_traceback(exc.__traceback__) from None
        raise
    finally:
        if handle is not None:
            handle.cancel()
        if budget is not None:
            budget.leave_call(call)
    if call.reason is not None:  # the test swallowed our cancellation and then returned
        _uncancel(task, call.cancels)
        raise call.error()
    return result


def _uncancel(task: asyncio.Task[Any], times: int) -> int:
    """Withdraw the budgets' cancellation requests; the number of requests left."""
    left = task.cancelling()
    for _ in range(times):
        left = task.uncancel()
    return left


def wrong_loop_message(state: ItemState, loop: asyncio.AbstractEventLoop) -> str:
    """Why a test that needs evclock's loop runs on ``loop`` instead, and what to do."""
    what = f"evclock: this test uses evclock but runs on {type(loop).__name__}, not a SimEventLoop"
    if state.kind == "anyio":
        return (
            f"{what}: anyio runs it with a plain asyncio backend. Make the anyio_backend "
            "fixture return evclock's backend:\n\n"
            "    @pytest.fixture\n"
            "    def anyio_backend(evclock_anyio_backend):\n"
            "        return evclock_anyio_backend"
        )
    if state.kind == "asyncio":
        return (
            f"{what}: pytest-asyncio did not use evclock's loop factory (it needs "
            "pytest-asyncio >= 1.4, which has the pytest_asyncio_loop_factories hook)"
        )
    return what
