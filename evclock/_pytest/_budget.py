"""The wall-time budget of a test (``wall_timeout``): a watchdog thread that stops a test which
overruns it, and the errors that report it."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import sys
import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import TYPE_CHECKING, Any, Final

from .._errors import EvClockError
from .._threads import mark_internal
from ._describe import describe_tasks, format_stack

if TYPE_CHECKING:
    from ._guard import CallGuard
    from ._state import ItemState, Session

#: Where users import these from, and what reports name them by.
_PUBLIC_MODULE: Final = "evclock.pytest_plugin"

#: After a wall-time budget expires and the test was cancelled, how long (wall seconds, bounded
#: by the budget itself) the loop gets to react before evclock interrupts its thread.
_GRACE_MIN, _GRACE_MAX = 0.1, 2.0
BUDGET_HINT: Final = (
    "Raise the budget with @pytest.mark.evclock(wall_timeout=...) or --evclock-wall-timeout "
    "(0 disables it)."
)


class WallTimeBudgetError(EvClockError, TimeoutError):
    """A test overran its wall-time budget (``wall_timeout``) and was cancelled."""

    __module__ = _PUBLIC_MODULE


class WallTimeBudgetInterrupt(BaseException):
    """Raised asynchronously in the test thread when a test overran its wall-time budget and
    did not stop when cancelled (synchronous code blocked the event loop, or the test swallowed
    ``CancelledError``).

    It derives from ``BaseException`` so that ``except Exception`` in the code under test does
    not swallow it; an ``async def`` test reports it as :class:`WallTimeBudgetError`.
    """

    __module__ = _PUBLIC_MODULE
    message = "evclock: wall-time budget exceeded"

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else self.message


def _phase_codes() -> dict[Any, str]:
    try:
        from _pytest import runner
    except ImportError:  # pragma: no cover - pytest always has it
        return {}
    return {
        runner.pytest_runtest_setup.__code__: "setup",
        runner.pytest_runtest_call.__code__: "call",
        runner.pytest_runtest_teardown.__code__: "teardown",
    }


_PHASES: Final = _phase_codes()


def _phase_of(frame: FrameType | None) -> str | None:
    """The test phase (setup, call, teardown) a thread is in, from its stack; None between."""
    while frame is not None:
        phase = _PHASES.get(frame.f_code)
        if phase is not None:
            return phase
        frame = frame.f_back
    return None


def _set_async_exc(thread_id: int, exc_type: type[BaseException] | None) -> None:
    set_async_exc = ctypes.pythonapi.PyThreadState_SetAsyncExc
    set_async_exc(ctypes.c_ulong(thread_id), ctypes.py_object(exc_type) if exc_type else None)


class Budget:
    """A wall-time budget for one test (setup, call and teardown), watched by a daemon thread.

    No signals: what happens when it expires depends on where the test is.

    1. In the test function: the test task is cancelled through ``call_soon_threadsafe``,
       which works however busy the test keeps the loop; in an async fixture, every task of
       the running loop is (the fixture fails with :class:`WallTimeBudgetError`).
    2. If the test does not stop (it swallows the cancellation) but the loop still runs
       callbacks: :class:`WallTimeBudgetInterrupt` is raised in the test task, at the ``await``
       where it waits (``except Exception`` and ``except CancelledError`` do not catch it).
    3. If the loop does not run callbacks any more (synchronous code blocks it), or no loop
       runs (a sync test or fixture): the exception is raised asynchronously in the test
       thread, wherever it is.

    Each step gets a grace period (the budget, at least 0.1 s, at most 2 s) to work.
    """

    def __init__(self, seconds: float, state: ItemState, session: Session) -> None:
        self.seconds = seconds
        self._grace = min(max(seconds, _GRACE_MIN), _GRACE_MAX)
        self._state = state
        self._session = session
        self._cond = threading.Condition()
        self._deadline = time.monotonic() + seconds
        self._call: CallGuard | None = None
        self._cancelled: CallGuard | None = None
        self._interrupted: CallGuard | None = None
        self._tasks_cancelled = False
        self._where: tuple[str, ...] = ()
        self._phase = ""
        self._finished = False
        self._injected = False
        self._thread_id = threading.get_ident()
        self._thread = threading.Thread(
            target=self._watch, name=f"evclock-budget[{state.item.name}]", daemon=True
        )
        mark_internal(self._thread)  # it never resumes a paused test's loop
        self._thread.start()

    def enter_call(self, call: CallGuard) -> None:
        with self._cond:
            self._call = call

    def leave_call(self, call: CallGuard) -> None:
        with self._cond:
            self._call = None
            if call is self._cancelled:
                # The test has been stopped: teardown gets a fresh budget.
                self._deadline = time.monotonic() + self.seconds
                self._cond.notify()

    def finish(self) -> None:
        with self._cond:
            if self._finished:
                return
            self._finished = True
            if self._injected:
                _set_async_exc(self._thread_id, None)  # drop an interrupt not delivered yet
            self._cond.notify()

    def _watch(self) -> None:
        with self._cond:
            while not self._finished:
                now = time.monotonic()
                if now < self._deadline:
                    self._cond.wait(self._deadline - now)
                    continue
                self._deadline = now + self._grace
                self._act()

    def _act(self) -> None:
        call = self._call
        if call is not None and call is not self._cancelled:
            self._cancelled = call  # 1. cancel the test task
            call.request_expiry(self.seconds)
            return
        if call is not None and call.reason is not None and call is not self._interrupted:
            self._interrupted = call  # 2. the loop runs callbacks: raise in the task
            call.request_interrupt(self.seconds)
            return
        frame = sys._current_frames().get(self._thread_id)
        phase = _phase_of(frame)
        if frame is None or phase is None:
            return  # between phases: look again after the grace period
        loops = [
            loop
            for loop in list(self._session.loops)
            if getattr(loop, "_thread_id", None) == self._thread_id and not loop.is_closed()
        ]
        if call is None and loops and not self._tasks_cancelled:
            self._tasks_cancelled = True  # 1. (fixtures) cancel every task of the loop
            self._phase = phase
            for loop in loops:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(self._cancel_tasks, loop)
            return
        # 3. raise in the test thread, wherever it is
        if phase == "call" and call is not None:
            detail = (
                " and did not stop when cancelled: synchronous code blocks its event loop"
                if call.reason is None
                else " and did not stop when cancelled or interrupted"
            )
        else:
            detail = "" if phase == "call" else f" (in {phase})"
        message = (
            f"evclock: wall-time budget exceeded: the test was still running after "
            f"{self.seconds:g} s of wall time{detail}; evclock interrupted it in:\n"
            f"{format_stack(frame)}\n{BUDGET_HINT}"
        )
        exc_type = type(
            "WallTimeBudgetInterrupt",
            (WallTimeBudgetInterrupt,),
            {
                "message": message,
                "__module__": _PUBLIC_MODULE,
                "__qualname__": "WallTimeBudgetInterrupt",
            },
        )
        _set_async_exc(self._thread_id, exc_type)
        self._injected = True
        for loop in loops:  # wake a loop blocked in select()
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_noop)

    def _cancel_tasks(self, loop: asyncio.AbstractEventLoop) -> None:
        """On the loop's thread: cancel what runs there (a fixture, or a sync test's run)."""
        self._where += describe_tasks(loop, None)
        for task in asyncio.all_tasks(loop):
            task.cancel("evclock: wall-time budget exceeded")

    def error_for(self, exc: BaseException) -> WallTimeBudgetError | None:
        """The report for a CancelledError that cancelling the loop's tasks caused, if so."""
        if not (self._tasks_cancelled and isinstance(exc, asyncio.CancelledError)):
            return None
        where = "\n".join(f"  {line}" for line in self._where) or "  (no task)"
        phase = "" if self._phase == "call" else f" (in {self._phase})"
        return WallTimeBudgetError(
            f"evclock: wall-time budget exceeded: the test was still running after "
            f"{self.seconds:g} s of wall time{phase} and was cancelled. Its tasks were at:\n"
            f"{where}\n{BUDGET_HINT}"
        )


@contextlib.contextmanager
def budget_errors(state: ItemState) -> Iterator[None]:
    """Report a CancelledError caused by an expired wall-time budget as the budget's error."""
    __tracebackhide__ = True
    try:
        yield
    except asyncio.CancelledError as exc:
        error = state.budget.error_for(exc) if state.budget is not None else None
        if error is None:
            raise
        raise error.with_traceback(exc.__traceback__) from None


def _noop() -> None:
    pass
