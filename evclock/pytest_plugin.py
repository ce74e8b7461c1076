"""evclock's pytest plugin: run tests and their async fixtures on simulation time.

Installed with evclock (entry point ``pytest11``) and inactive until a test opts in, either with
the marker or by requesting one of the fixtures::

    @pytest.mark.evclock(sim_timeout=120)
    async def test_patrol(evclock_clock):
        await patrol(laps=3)                      # minutes of sim time, milliseconds of wall time
        assert evclock_clock.now().seconds == 90.0

Who runs an opted-in ``async def`` test:

* **pytest-asyncio** (1.x), when it handles the test (``@pytest.mark.asyncio`` or auto mode):
  evclock answers its ``pytest_asyncio_loop_factories`` hook with an ``"evclock"`` loop factory;
  ``@pytest.mark.asyncio(loop_factories=["evclock"])`` selects it explicitly.
* **anyio**'s plugin, when the test uses ``anyio_backend``: make that fixture return the
  ``evclock_anyio_backend`` fixture's value.
* **evclock itself** otherwise: a fresh simulation loop per test, shared by the test's async
  fixtures (which must then be function-scoped).

Each test is handled by exactly one of them, and ``@pytest.mark.evclock(...)`` is the single place
for per-test options whichever runs it: ``rtf``, ``start``, ``stall_timeout``, ``wall_timeout``
(a wall-clock budget for setup, call and teardown) and ``sim_timeout`` (a sim-time limit for the
test function). A deadlock fails at once with :class:`~evclock.DeadlockError` naming the waiting
tasks; an overrun fails with :class:`WallTimeBudgetError` or :class:`~evclock.SimTimeLimitError`.

Command line and ini: ``--evclock-wall`` (run evclock tests on wall time: a plain asyncio loop on
which :func:`evclock.clock` is the wall clock), ``--evclock-rtf`` / ``evclock_rtf``,
``--evclock-wall-timeout`` / ``evclock_wall_timeout`` (default 60 s), ``--evclock-sim-timeout``
/ ``evclock_sim_timeout`` (default none).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import ctypes
import dataclasses
import functools
import inspect
import math
import os
import sys
import threading
import time
import traceback
import weakref
from collections.abc import Callable, Coroutine, Generator, Iterator, Mapping
from types import FrameType, TracebackType
from typing import Any, Final, Literal, TypeVar

import pytest

from ._clock import Clock, WallClock, _attached, attach_clock
from ._errors import DeadlockError, EvClockError, SimTimeLimitError
from ._loop import _SLEEP, DEFAULT_STALL_TIMEOUT, SimEventLoop, _check_stall_timeout, _short
from ._pacing import check_rtf
from ._runner import _start_ns, resolve_use_sim_time
from ._time import Time
from .sources import PyBulletTimeSource, TimeSource, VirtualTimeSource

__all__ = [
    "EVCLOCK_LOOP_FACTORY_NAME",
    "PyBulletWorld",
    "WallTimeBudgetError",
    "WallTimeBudgetInterrupt",
    "evclock_anyio_backend",
    "evclock_clock",
    "evclock_loop",
    "evclock_pybullet",
]

_T = TypeVar("_T")

#: The name under which evclock's loop factory is offered to pytest-asyncio:
#: ``@pytest.mark.asyncio(loop_factories=["evclock"])``.
EVCLOCK_LOOP_FACTORY_NAME: Final = "evclock"

_MARKER = "evclock"
_MARKER_ARGS: Final = ("rtf", "wall_timeout", "sim_timeout", "start", "stall_timeout")
#: Fixtures whose use opts a test in, like the marker (a module whose ``anyio_backend`` is
#: evclock's opts in all its anyio tests).
_LOOP_FIXTURES: Final = frozenset(
    {"evclock_loop", "evclock_clock", "evclock_pybullet", "evclock_anyio_backend"}
)
_RUNNER_FIXTURE: Final = "_evclock_runner"
_PYBULLET_FIXTURE: Final = "evclock_pybullet"
_ANYIO_LOOP_FIXTURE: Final = "_evclock_anyio_loop"
_DEFAULT_WALL_TIMEOUT: Final = "60"
#: After a wall-time budget expires and the test was cancelled, how long (wall seconds, bounded
#: by the budget itself) the loop gets to react before evclock interrupts its thread.
_GRACE_MIN, _GRACE_MAX = 0.1, 2.0
_BUDGET_HINT: Final = (
    "Raise the budget with @pytest.mark.evclock(wall_timeout=...) or --evclock-wall-timeout "
    "(0 disables it)."
)
_SIM_HINT: Final = (
    "Raise the limit with @pytest.mark.evclock(sim_timeout=...) or --evclock-sim-timeout "
    "(0 disables it)."
)

Kind = Literal["evclock", "asyncio", "anyio"]


class WallTimeBudgetError(EvClockError, TimeoutError):
    """A test overran its wall-time budget (``wall_timeout``) and was cancelled."""


class WallTimeBudgetInterrupt(BaseException):
    """Raised asynchronously in the test thread when a test overran its wall-time budget and
    did not stop when cancelled (synchronous code blocked the event loop, or the test swallowed
    ``CancelledError``).

    It derives from ``BaseException`` so that ``except Exception`` in the code under test does
    not swallow it; an ``async def`` test reports it as :class:`WallTimeBudgetError`.
    """

    message = "evclock: wall-time budget exceeded"

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else self.message


# --------------------------------------------------------------------------- options


def _parse_seconds(value: object, what: str) -> float | None:
    """A timeout: None, 0, "none" or "off" disable it; else a positive finite number."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "none", "off", "0"):
            return None
        try:
            value = float(text)
        except ValueError:
            raise ValueError(
                f"{what} must be a number of seconds or 'none', got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number of seconds or None, got {type(value).__name__}")
    if value == 0:
        return None
    if not math.isfinite(value) or value < 0:
        raise ValueError(
            f"{what} must be a positive number of seconds (0 or None disables it), got {value!r}"
        )
    return float(value)


def _parse_rtf(value: object, what: str) -> float | None:
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "none"):
            return None
        try:
            value = float(text)
        except ValueError:
            raise ValueError(
                f"{what} must be a positive real-time factor or 'none', got {value!r}"
            ) from None
    try:
        return check_rtf(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: {exc}") from None


@dataclasses.dataclass(frozen=True)
class _Options:
    wall: bool
    rtf: float | None
    wall_timeout: float | None
    sim_timeout: float | None
    start_ns: int = 0
    stall_timeout: float | None = DEFAULT_STALL_TIMEOUT


def _config_options(config: pytest.Config) -> _Options:
    def pick(option: str, ini: str) -> object:
        value = config.getoption(option)
        return config.getini(ini) if value is None else value

    try:
        wall = bool(config.getoption("evclock_wall")) or not resolve_use_sim_time(None)
        return _Options(
            wall=wall,
            rtf=_parse_rtf(pick("evclock_rtf", "evclock_rtf"), "--evclock-rtf"),
            wall_timeout=_parse_seconds(
                pick("evclock_wall_timeout", "evclock_wall_timeout"), "--evclock-wall-timeout"
            ),
            sim_timeout=_parse_seconds(
                pick("evclock_sim_timeout", "evclock_sim_timeout"), "--evclock-sim-timeout"
            ),
        )
    except ValueError as exc:
        raise pytest.UsageError(f"evclock: {exc}") from None


def _marker_options(item: pytest.Item, defaults: _Options) -> _Options:
    merged: dict[str, object] = {}
    for mark in item.iter_markers(_MARKER):  # closest first: a test's own marker wins
        if mark.args:
            raise ValueError(
                f"@pytest.mark.evclock takes keyword arguments only ({', '.join(_MARKER_ARGS)}), "
                f"got positional {mark.args!r}"
            )
        for key, value in mark.kwargs.items():
            if key not in _MARKER_ARGS:
                raise ValueError(
                    f"@pytest.mark.evclock got an unexpected argument {key!r}; "
                    f"it accepts {', '.join(_MARKER_ARGS)}"
                )
            merged.setdefault(key, value)
    options = defaults
    if "rtf" in merged:
        options = dataclasses.replace(options, rtf=_parse_rtf(merged["rtf"], "evclock(rtf=...)"))
    for key in ("wall_timeout", "sim_timeout"):
        if key in merged:
            seconds = _parse_seconds(merged[key], f"evclock({key}=...)")
            if key == "wall_timeout":
                options = dataclasses.replace(options, wall_timeout=seconds)
            else:
                options = dataclasses.replace(options, sim_timeout=seconds)
    if "stall_timeout" in merged:
        try:
            stall = _check_stall_timeout(merged["stall_timeout"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"evclock(stall_timeout=...): {exc}") from None
        options = dataclasses.replace(options, stall_timeout=stall)
    if "start" in merged:
        start = merged["start"]
        if not isinstance(start, int | float | Time):
            raise ValueError(
                f"evclock(start=...) must be sim seconds or a sim Time, got {type(start).__name__}"
            )
        try:
            options = dataclasses.replace(options, start_ns=_start_ns(start))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"evclock(start=...): {exc}") from None
    return options


def _asyncio_selection(item: pytest.Item) -> tuple[str, ...] | None:
    """The factory names ``@pytest.mark.asyncio(loop_factories=...)`` selects, if any."""
    mark = item.get_closest_marker("asyncio")
    if mark is None:
        return None
    names = mark.kwargs.get("loop_factories")
    if names is None or isinstance(names, str):
        return None
    return tuple(str(name) for name in names)


def _wants_evclock(item: pytest.Item) -> bool:
    """Whether a test opted in: the marker, a loop fixture, or pytest-asyncio's selection."""
    if not isinstance(item, pytest.Function):
        return False
    if item.get_closest_marker(_MARKER) is not None:
        return True
    if not _LOOP_FIXTURES.isdisjoint(item.fixturenames):
        return True
    return EVCLOCK_LOOP_FACTORY_NAME in (_asyncio_selection(item) or ())


def _test_function(item: pytest.Function) -> tuple[Any, str]:
    """Where the test's coroutine function lives: (holder, attribute name)."""
    obj = item.obj
    hypothesis = getattr(obj, "hypothesis", None)
    if hypothesis is not None and inspect.iscoroutinefunction(
        getattr(hypothesis, "inner_test", None)
    ):
        return hypothesis, "inner_test"
    return item, "obj"


def _is_async(item: pytest.Function) -> bool:
    holder, name = _test_function(item)
    return inspect.iscoroutinefunction(getattr(holder, name))


def _kind(item: pytest.Function) -> Kind:
    """Which plugin runs the test: pytest-asyncio, anyio, or evclock's own runner."""
    if "pytest_asyncio" in sys.modules:
        from pytest_asyncio import is_async_test

        if is_async_test(item):
            return "asyncio"
    if "anyio_backend" in item.fixturenames and _is_async(item):
        return "anyio"
    return "evclock"


# --------------------------------------------------------------------------- per-test state


class _ItemState:
    """What evclock knows about one opted-in test."""

    def __init__(self, item: pytest.Function, options: _Options, kind: Kind) -> None:
        self.item = item
        self.options = options
        self.kind = kind
        self.is_async = _is_async(item)
        self.loops: list[asyncio.AbstractEventLoop] = []
        self.pybullet_source: TimeSource | None = None
        self.source_adopted = False
        self.budget: _Budget | None = None
        self.call: _CallGuard | None = None
        # An explicit multi-factory selection may deliberately run variants on other loops.
        self.expect_sim = not options.wall and _asyncio_selection(item) in (
            None,
            (EVCLOCK_LOOP_FACTORY_NAME,),
        )


_ITEM_STATE = pytest.StashKey[_ItemState]()


def _state_of(item: pytest.Item) -> _ItemState | None:
    return item.stash.get(_ITEM_STATE, None)


class _Session:
    """Plugin state for one pytest run (one ``Config``)."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.defaults = _config_options(config)
        self.current_item: pytest.Item | None = None
        self.asyncio_hooked = False
        #: Every loop evclock's factory made (the budgets look for the one running).
        self.loops: weakref.WeakSet[asyncio.AbstractEventLoop] = weakref.WeakSet()
        # One stable object: pytest-asyncio parametrizes with it and anyio receives it.
        self.loop_factory: Callable[[], asyncio.AbstractEventLoop] = self._new_loop

    def _new_loop(self) -> asyncio.AbstractEventLoop:
        """Create the loop of the test being run, with its marker's options."""
        item = self.current_item
        state = _state_of(item) if item is not None else None
        options = state.options if state is not None else self.defaults
        loop: asyncio.AbstractEventLoop
        if options.wall:
            loop = asyncio.new_event_loop()
            attach_clock(loop, WallClock())
        else:
            source: TimeSource
            if state is not None and state.pybullet_source is not None and not state.source_adopted:
                source = state.pybullet_source
                state.source_adopted = True
            else:
                source = VirtualTimeSource(options.start_ns)
            loop = SimEventLoop(source, rtf=options.rtf, stall_timeout=options.stall_timeout)
        if state is not None:
            state.loops.append(loop)
        self.loops.add(loop)
        return loop

    def asyncio_factories(
        self,
        item: pytest.Item,
        result: Mapping[str, Callable[[], asyncio.AbstractEventLoop]] | None,
    ) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
        """Answer ``pytest_asyncio_loop_factories`` for ``item`` given other plugins' answer."""
        if not _wants_evclock(item):
            # Leave other tests alone: someone else's answer, else asyncio's default loop.
            return result if result is not None else {"asyncio": asyncio.new_event_loop}
        selected = _asyncio_selection(item)
        if selected is None:
            return {EVCLOCK_LOOP_FACTORY_NAME: self.loop_factory}
        if EVCLOCK_LOOP_FACTORY_NAME not in selected:
            pytest.fail(
                f"{item.nodeid}: the test uses evclock but "
                f"@pytest.mark.asyncio(loop_factories={list(selected)!r}) does not select "
                f"{EVCLOCK_LOOP_FACTORY_NAME!r}; add it to the list",
                pytrace=False,
            )
        return {**(result or {}), EVCLOCK_LOOP_FACTORY_NAME: self.loop_factory}


_SESSION = pytest.StashKey[_Session]()


def _session(config: pytest.Config) -> _Session:
    return config.stash[_SESSION]


class _AsyncioHooks:
    """The pytest-asyncio integration, registered only when pytest-asyncio declares its hook."""

    def __init__(self, session: _Session) -> None:
        self._session = session

    @pytest.hookimpl(wrapper=True)
    def pytest_asyncio_loop_factories(
        self, config: pytest.Config, item: pytest.Item
    ) -> Generator[None, Any, Mapping[str, Callable[[], asyncio.AbstractEventLoop]]]:
        result = yield
        return self._session.asyncio_factories(item, result)


# --------------------------------------------------------------------------- wall-time budget


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


class _CallGuard:
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
        self.thrown = False

    def request_expiry(self, seconds: float) -> None:
        """From the watchdog thread: cancel the test on its loop's thread."""
        with contextlib.suppress(RuntimeError):  # the loop just closed
            self.loop.call_soon_threadsafe(self._expire, "wall", seconds)

    def request_interrupt(self, seconds: float) -> None:
        """From the watchdog thread: raise WallTimeBudgetInterrupt in the test task."""
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(self._interrupt, seconds)

    def _interrupt(self, seconds: float) -> None:
        task = self.task
        if task.done():
            return
        frames = [f for f in _coroutine_frames(task.get_coro()) if _is_user_code(f)]
        where = "".join(
            traceback.format_list(traceback.StackSummary.extract((f, f.f_lineno) for f in frames))
        ).rstrip("\n")
        exc = WallTimeBudgetInterrupt(
            f"evclock: wall-time budget exceeded: the test was still running after {seconds:g} s "
            "of wall time and did not stop when cancelled: it swallows CancelledError; evclock "
            f"interrupted it in:\n{where}\n{_BUDGET_HINT}"
        )
        waiter = getattr(task, "_fut_waiter", None)
        if waiter is None or waiter.done():
            # The task is about to run again: raise at its suspension point now; the guard
            # turns it into the failure and yields once, so the task resumes as scheduled.
            self.thrown = True
            with contextlib.suppress(BaseException):
                task.get_coro().throw(exc)
        elif not isinstance(waiter, asyncio.Task):
            waiter.set_exception(exc)  # the task waits on this future: wake it with the error

    def sim_deadline(self, seconds: float) -> None:
        # Run after everything else due at the limit, then decide: a loop with nothing left to
        # do is a deadlock, which the loop itself reports (DeadlockError) rather than us.
        self.loop.call_soon(self._check_sim_deadline, seconds)

    def _check_sim_deadline(self, seconds: float) -> None:
        if not _would_deadlock(self.loop):
            self._expire("sim", seconds)

    def _expire(self, reason: Literal["wall", "sim"], seconds: float) -> None:
        if self.reason is not None or self.task.done():
            return
        self.reason = reason
        self.limit = seconds
        self.at = self.loop.time()
        self.where = _describe_tasks(self.loop, self.task)
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
            f"{_BUDGET_HINT}"
        )


def _coroutine_frames(coro: object) -> list[FrameType]:
    """The frames of a suspended coroutine's await chain, outermost first."""
    frames: list[FrameType] = []
    while coro is not None:
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is None:
            break
        frames.append(frame)
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
    return frames


#: Frames of the machinery between a task and the test (this plugin, anyio's test runner).
_MACHINERY_CODE_NAMES: Final = frozenset(
    {"evclock_test", "_run_guarded", "_run_tests_and_fixtures"}
)


def _describe_task(task: asyncio.Task[Any], test_task: asyncio.Task[Any] | None) -> str:
    """``Task-3 (the test): test_x() at f.py:12 -> helper() at g.py:4, waiting on <...>``."""
    frames = [
        f"{frame.f_code.co_qualname.rpartition('<locals>.')[2]}() at "
        f"{frame.f_code.co_filename}:{frame.f_lineno}"
        for frame in _coroutine_frames(task.get_coro())
        if frame.f_code.co_name not in _MACHINERY_CODE_NAMES
    ]
    waiter = getattr(task, "_fut_waiter", None)
    waits_on = f", waiting on {_short(waiter)}" if waiter is not None else ""
    label = " (the test)" if task is test_task else ""
    running = getattr(task.get_coro(), "cr_running", False)
    where = " -> ".join(frames) or ("running" if running else repr(task.get_coro()))
    return f"{task.get_name()}{label}: {where}{waits_on}"


def _describe_tasks(
    loop: asyncio.AbstractEventLoop, test_task: asyncio.Task[Any] | None
) -> tuple[str, ...]:
    tasks = sorted((t for t in asyncio.all_tasks(loop) if not t.done()), key=lambda t: t.get_name())
    return tuple(_describe_task(t, test_task) for t in tasks)


def _suspended_traceback(coro: object) -> TracebackType | None:
    """A traceback through the lines where a suspended coroutine chain waits (for reports)."""
    tb: TracebackType | None = None
    for frame in reversed(_coroutine_frames(coro)):
        if frame.f_code.co_name not in _MACHINERY_CODE_NAMES and _is_user_code(frame):
            tb = TracebackType(tb, frame, frame.f_lasti, frame.f_lineno)
    return tb


def _explain_deadlock(exc: DeadlockError, call: _CallGuard) -> DeadlockError:
    """The loop's DeadlockError, retold from the test's side: each task's whole await chain
    (the test's own line included) and a traceback that points at where the test waits."""
    if call.loop.is_closed() or getattr(call.coro, "cr_frame", None) is None:
        return exc
    tasks = _describe_tasks(call.loop, call.task)
    head = str(exc).split("\n", 1)[0]
    better = DeadlockError(head + "\n" + "\n".join(f"  {line}" for line in tasks), tasks)
    return better.with_traceback(_suspended_traceback(call.coro))


def _would_deadlock(loop: asyncio.AbstractEventLoop) -> bool:
    """Whether a simulation loop has nothing left that could ever wake a task."""
    if not isinstance(loop, SimEventLoop) or loop.source.free_running:
        return False
    if loop._ready or loop._holds or len(loop._io_map) > 1:
        return False
    for _, _, kind, obj in loop._scheduled:
        if (not obj.done()) if kind == _SLEEP else (not obj._cancelled):
            return False
    return True


class _Budget:
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

    def __init__(self, seconds: float, state: _ItemState, session: _Session) -> None:
        self.seconds = seconds
        self._grace = min(max(seconds, _GRACE_MIN), _GRACE_MAX)
        self._state = state
        self._session = session
        self._cond = threading.Condition()
        self._deadline = time.monotonic() + seconds
        self._call: _CallGuard | None = None
        self._cancelled: _CallGuard | None = None
        self._interrupted: _CallGuard | None = None
        self._tasks_cancelled = False
        self._where: tuple[str, ...] = ()
        self._phase = ""
        self._finished = False
        self._injected = False
        self._thread_id = threading.get_ident()
        self._thread = threading.Thread(
            target=self._watch, name=f"evclock-budget[{state.item.name}]", daemon=True
        )
        self._thread.start()

    def enter_call(self, call: _CallGuard) -> None:
        with self._cond:
            self._call = call

    def leave_call(self, call: _CallGuard) -> None:
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
            f"{_format_stack(frame)}\n{_BUDGET_HINT}"
        )
        exc_type = type(
            "WallTimeBudgetInterrupt",
            (WallTimeBudgetInterrupt,),
            {"message": message, "__module__": __name__, "__qualname__": "WallTimeBudgetInterrupt"},
        )
        _set_async_exc(self._thread_id, exc_type)
        self._injected = True
        for loop in loops:  # wake a loop blocked in select()
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_noop)

    def _cancel_tasks(self, loop: asyncio.AbstractEventLoop) -> None:
        """On the loop's thread: cancel what runs there (a fixture, or a sync test's run)."""
        self._where += _describe_tasks(loop, None)
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
            f"{where}\n{_BUDGET_HINT}"
        )


_PACKAGE_DIR: Final = os.path.dirname(os.path.abspath(__file__)).replace("\\", "/") + "/"
_MACHINERY_PATHS: Final = ("/_pytest/", "/pluggy/", "/asyncio/", "/anyio/", _PACKAGE_DIR)


def _is_machinery(path: str) -> bool:
    """Whether code at ``path`` belongs to pytest, asyncio, anyio or evclock itself."""
    path = path.replace("\\", "/")
    return any(part in path for part in _MACHINERY_PATHS)


def _is_user_code(frame: FrameType) -> bool:
    return not _is_machinery(frame.f_code.co_filename)


def _format_stack(frame: FrameType, limit: int = 3) -> str:
    """Where a thread is: its innermost frames up to the first of pytest's, asyncio's or
    evclock's own (the innermost frame is always shown)."""
    entries = traceback.extract_stack(frame)
    shown = [entries[-1]]
    for entry in reversed(entries[:-1]):
        if len(shown) >= limit or _is_machinery(entry.filename):
            break
        shown.append(entry)
    return "".join(traceback.format_list(shown[::-1])).rstrip("\n")


def _noop() -> None:
    pass


# --------------------------------------------------------------------------- the test guard


def _guard(
    func: Callable[..., Coroutine[Any, Any, _T]], state: _ItemState
) -> Callable[..., Coroutine[Any, Any, _T]]:
    @functools.wraps(func, updated=())
    async def evclock_test(*args: Any, **kwargs: Any) -> _T:
        __tracebackhide__ = True
        return await _run_guarded(func(*args, **kwargs), state)

    return evclock_test


async def _run_guarded(coro: Coroutine[Any, Any, _T], state: _ItemState) -> _T:
    __tracebackhide__ = True
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    if task is None or (state.expect_sim and not isinstance(loop, SimEventLoop)):
        coro.close()
        raise EvClockError(_wrong_loop_message(state, loop))
    if state.pybullet_source is not None and not state.source_adopted:
        coro.close()
        raise EvClockError(
            "evclock: the PyBullet world of this test is not stepped by its loop: the loop was "
            "created before the evclock_pybullet fixture (a loop shared with other tests?); "
            "use a function-scoped loop for tests that use evclock_pybullet"
        )
    call = state.call = _CallGuard(loop, task, coro)
    cancelling = task.cancelling()
    sim_limit = state.options.sim_timeout
    handle = loop.call_later(sim_limit, call.sim_deadline, sim_limit) if sim_limit else None
    budget = state.budget
    if budget is not None:
        budget.enter_call(call)
    try:
        result = await coro
    except asyncio.CancelledError as exc:
        if call.reason is not None and task.uncancel() <= cancelling:
            # Keep the traceback through the test: the report shows where it was stopped.
            raise call.error().with_traceback(exc.__traceback__) from None
        raise
    except WallTimeBudgetInterrupt as exc:
        error = WallTimeBudgetError(str(exc)).with_traceback(exc.__traceback__)
        if call.thrown:
            await asyncio.sleep(0)  # thrown in from a callback: let the task resume first
        raise error from None
    finally:
        if handle is not None:
            handle.cancel()
        if budget is not None:
            budget.leave_call(call)
    if call.reason is not None:  # the test swallowed our cancellation and then returned
        task.uncancel()
        raise call.error()
    return result


def _wrong_loop_message(state: _ItemState, loop: asyncio.AbstractEventLoop) -> str:
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
            "pytest-asyncio >= 1.x with the pytest_asyncio_loop_factories hook)"
        )
    return what


# --------------------------------------------------------------------------- evclock's runner


@contextlib.contextmanager
def _budget_errors(state: _ItemState) -> Iterator[None]:
    """Report a CancelledError caused by an expired wall-time budget as the budget's error."""
    __tracebackhide__ = True
    try:
        yield
    except asyncio.CancelledError as exc:
        error = state.budget.error_for(exc) if state.budget is not None else None
        if error is None:
            raise
        raise error.with_traceback(exc.__traceback__) from None


class _Runner:
    """evclock's own runner for a test: one loop and one context for the test and its async
    fixtures (context variables set by a fixture are seen by the test)."""

    def __init__(self, factory: Callable[[], asyncio.AbstractEventLoop]) -> None:
        self._runner = asyncio.Runner(loop_factory=factory)
        self.loop = self._runner.get_loop()
        self._context = contextvars.copy_context()

    def run(self, coro: Coroutine[Any, Any, _T]) -> _T:
        return self._runner.run(coro, context=self._context)

    def close(self) -> None:
        self._runner.close()


@pytest.fixture(name=_RUNNER_FIXTURE)
def _evclock_runner(request: pytest.FixtureRequest) -> Iterator[_Runner]:
    _ensure_pybullet_first(request)
    runner = _Runner(_session(request.config).loop_factory)
    try:
        yield runner
    finally:
        runner.close()


def _ensure_pybullet_first(request: pytest.FixtureRequest) -> None:
    """The PyBullet world must exist before the loop that steps it."""
    if _PYBULLET_FIXTURE in request.fixturenames and request.fixturename != _PYBULLET_FIXTURE:
        request.getfixturevalue(_PYBULLET_FIXTURE)


def _wrap_async_fixture(
    func: Callable[..., Any], request: pytest.FixtureRequest
) -> Callable[..., Any]:
    """Make an async fixture a sync one that runs on the test's evclock runner."""
    instance = request.instance
    if instance is not None and inspect.ismethod(func) and type(func.__self__) is type(instance):
        func = func.__func__.__get__(instance)

    def runner() -> _Runner:
        value: _Runner = request.getfixturevalue(_RUNNER_FIXTURE)
        return value

    if inspect.isasyncgenfunction(func):

        @functools.wraps(func, updated=())
        def evclock_asyncgen_fixture(**kwargs: Any) -> Iterator[Any]:
            run = runner().run
            agen = func(**kwargs)
            value = run(agen.__anext__())
            yield value
            run(_finish_asyncgen(agen, request.fixturename))

        return evclock_asyncgen_fixture

    @functools.wraps(func, updated=())
    def evclock_async_fixture(**kwargs: Any) -> Any:
        return runner().run(func(**kwargs))

    return evclock_async_fixture


async def _finish_asyncgen(agen: Any, name: str | None) -> None:
    try:
        await agen.__anext__()
    except StopAsyncIteration:
        return
    await agen.aclose()
    raise ValueError(f"async generator fixture {name!r} yielded more than once")


# --------------------------------------------------------------------------- hooks


def pytest_addoption(parser: pytest.Parser) -> None:
    """Register evclock's command-line options and ini keys."""
    group = parser.getgroup("evclock", "evclock: simulation time for asyncio tests")
    group.addoption(
        "--evclock-wall",
        action="store_true",
        default=False,
        dest="evclock_wall",
        help="run evclock tests on wall time: a plain asyncio loop where evclock.clock() is "
        "the wall clock (also: EVCLOCK_USE_SIM_TIME=0)",
    )
    group.addoption(
        "--evclock-rtf",
        dest="evclock_rtf",
        default=None,
        metavar="FACTOR",
        help="default real-time factor of evclock tests: 'none' (as fast as possible, the "
        "default), 1 (real time), k (k x real time)",
    )
    group.addoption(
        "--evclock-wall-timeout",
        dest="evclock_wall_timeout",
        default=None,
        metavar="SECONDS",
        help=f"wall-time budget of each evclock test, setup to teardown (default "
        f"{_DEFAULT_WALL_TIMEOUT}; 0 or 'none' disables it)",
    )
    group.addoption(
        "--evclock-sim-timeout",
        dest="evclock_sim_timeout",
        default=None,
        metavar="SECONDS",
        help="sim-time limit of each evclock test function (default none)",
    )
    parser.addini("evclock_rtf", "default for --evclock-rtf", default="none")
    parser.addini(
        "evclock_wall_timeout", "default for --evclock-wall-timeout", default=_DEFAULT_WALL_TIMEOUT
    )
    parser.addini("evclock_sim_timeout", "default for --evclock-sim-timeout", default="none")


def pytest_configure(config: pytest.Config) -> None:
    """Register the marker, validate the options, hook into pytest-asyncio if present."""
    config.addinivalue_line(
        "markers",
        "evclock(rtf=None, wall_timeout=60, sim_timeout=None, start=0, stall_timeout=60): run "
        "the test and its async fixtures on evclock's simulation loop (virtual time)",
    )
    session = _Session(config)
    config.stash[_SESSION] = session
    caller = getattr(config.hook, "pytest_asyncio_loop_factories", None)
    if caller is not None and caller.has_spec():
        config.pluginmanager.register(_AsyncioHooks(session), "evclock-asyncio")
        session.asyncio_hooked = True


def pytest_report_header(config: pytest.Config) -> str:
    """One line: the time base and the default budgets."""
    options = _session(config).defaults

    def seconds(value: float | None) -> str:
        return "none" if value is None else f"{value:g} s"

    if options.wall:
        why = "--evclock-wall" if config.getoption("evclock_wall") else "EVCLOCK_USE_SIM_TIME"
        return (
            f"evclock: wall time ({why}), wall-timeout={seconds(options.wall_timeout)}, "
            f"sim-timeout={seconds(options.sim_timeout)}"
        )
    rtf = "none" if options.rtf is None else f"{options.rtf:g}"
    return (
        f"evclock: sim time, rtf={rtf}, wall-timeout={seconds(options.wall_timeout)}, "
        f"sim-timeout={seconds(options.sim_timeout)}"
    )


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, object, object]:
    """Track the running test (loop factories read its options) and end its budget."""
    session = _session(item.config)
    session.current_item = item
    try:
        return (yield)
    finally:
        state = _state_of(item)
        if state is not None and state.budget is not None:
            state.budget.finish()
        session.current_item = None


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Resolve an opted-in test's options, pick its runner and start its wall-time budget."""
    if not isinstance(item, pytest.Function) or not _wants_evclock(item):
        return
    session = _session(item.config)
    try:
        options = _marker_options(item, session.defaults)
    except ValueError as exc:
        pytest.fail(f"{item.nodeid}: {exc}", pytrace=False)
    kind = _kind(item)
    if kind == "asyncio" and not session.asyncio_hooked:
        pytest.fail(
            f"{item.nodeid}: pytest-asyncio runs this test but has no "
            "pytest_asyncio_loop_factories hook; upgrade pytest-asyncio, or drop the asyncio "
            "marker to let evclock run the test",
            pytrace=False,
        )
    state = _ItemState(item, options, kind)
    item.stash[_ITEM_STATE] = state
    # evclock's runner, or a lease on anyio's: the loop then lives until teardown, so that a
    # failure can still be reported from the test's suspended frames.
    extra = (
        _RUNNER_FIXTURE if kind == "evclock" else _ANYIO_LOOP_FIXTURE if kind == "anyio" else None
    )
    if extra is not None and state.is_async and extra not in item.fixturenames:
        item.fixturenames.append(extra)
    if options.wall_timeout is not None:
        state.budget = _Budget(options.wall_timeout, state, session)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item) -> Generator[None, object, object]:
    """End the wall-time budget once the test's fixtures are torn down."""
    state = _state_of(item)
    try:
        if state is None:
            return (yield)
        with _budget_errors(state):
            return (yield)
    finally:
        state = _state_of(item)
        if state is not None and state.budget is not None:
            state.budget.finish()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, object, object]:
    """Put the budgets around the test function, whichever plugin runs it."""
    state = _state_of(item)
    if state is None or not isinstance(item, pytest.Function):
        return (yield)
    if not state.is_async:
        with _budget_errors(state):  # a sync test driving the loop itself
            return (yield)
    holder, name = _test_function(item)
    original = getattr(holder, name)
    wrapped: Callable[..., Any] = _guard(original, state)
    if state.kind == "evclock" and holder is not item:  # hypothesis: run each example on our loop
        runner: _Runner = item.funcargs[_RUNNER_FIXTURE]  # type: ignore[assignment]
        guarded = wrapped

        @functools.wraps(original, updated=())
        def evclock_example(*args: Any, **kwargs: Any) -> None:
            runner.run(guarded(*args, **kwargs))

        wrapped = evclock_example
    setattr(holder, name, wrapped)
    try:
        return (yield)
    except DeadlockError as exc:
        if state.call is None:
            raise
        raise _explain_deadlock(exc, state.call) from None
    finally:
        setattr(holder, name, original)


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """Run an opted-in ``async def`` test that no other plugin handles on evclock's runner."""
    state = _state_of(pyfuncitem)
    if state is None or state.kind != "evclock" or not state.is_async:
        return None
    if not inspect.iscoroutinefunction(pyfuncitem.obj):
        return None  # hypothesis: pytest calls the (sync) test, which runs each example
    runner: _Runner = pyfuncitem.funcargs[_RUNNER_FIXTURE]  # type: ignore[assignment]
    funcargs = pyfuncitem.funcargs
    testargs = {arg: funcargs[arg] for arg in pyfuncitem._fixtureinfo.argnames}
    runner.run(pyfuncitem.obj(**testargs))
    return True


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_fixture_setup(
    fixturedef: pytest.FixtureDef[Any], request: pytest.FixtureRequest
) -> Generator[None, object, object]:
    """Run the async fixtures of a test evclock runs on that test's loop."""
    func = fixturedef.func
    if not (inspect.iscoroutinefunction(func) or inspect.isasyncgenfunction(func)):
        return (yield)
    item = _session(request.config).current_item
    state = _state_of(item) if item is not None else None
    if state is None:
        return (yield)
    if fixturedef.scope == "function":
        _ensure_pybullet_first(request)
    if state.kind != "evclock":
        # pytest-asyncio or anyio run it, on the loop evclock gave them.
        with _budget_errors(state):
            return (yield)
    if fixturedef.scope != "function":
        pytest.fail(
            f"{state.item.nodeid}: async fixture {fixturedef.argname!r} is {fixturedef.scope}-"
            "scoped, but evclock runs each test on its own loop; make it function-scoped, or "
            "let pytest-asyncio run these tests (@pytest.mark.asyncio(loop_scope=...)) on "
            "evclock's loop factory",
            pytrace=False,
        )
    fixturedef.func = _wrap_async_fixture(func, request)  # type: ignore[misc]
    try:
        with _budget_errors(state):
            return (yield)
    finally:
        fixturedef.func = func  # type: ignore[misc]


# --------------------------------------------------------------------------- fixtures


def _loop_of_test(request: pytest.FixtureRequest) -> asyncio.AbstractEventLoop:
    item = request.node
    state = _state_of(item)
    if state is None or not isinstance(item, pytest.Function):
        raise EvClockError(
            f"evclock fixtures are function-scoped; {request.fixturename} was requested by {item!r}"
        )
    _ensure_pybullet_first(request)
    if state.kind == "asyncio":
        scope = getattr(item, "_loop_scope", "function")
        asyncio_runner: asyncio.Runner = request.getfixturevalue(f"_{scope}_scoped_runner")
        return asyncio_runner.get_loop()
    if state.kind == "anyio":
        anyio_loop: asyncio.AbstractEventLoop = request.getfixturevalue(_ANYIO_LOOP_FIXTURE)
        return anyio_loop
    runner: _Runner = request.getfixturevalue(_RUNNER_FIXTURE)
    return runner.loop


@pytest.fixture
def evclock_loop(request: pytest.FixtureRequest) -> asyncio.AbstractEventLoop:
    """The event loop the test runs on: a :class:`~evclock.SimEventLoop` (a plain asyncio loop
    under ``--evclock-wall``). Use it for ``pause()``, ``step()``, ``rtf`` or, in a sync test,
    ``run_until_complete()``. Requesting it opts the test in, like the marker."""
    return _loop_of_test(request)


@pytest.fixture
def evclock_clock(evclock_loop: asyncio.AbstractEventLoop) -> Clock:
    """The clock the test runs on - what :func:`evclock.clock` returns inside it: the loop's
    :class:`~evclock.SimClock`, or the wall clock under ``--evclock-wall``."""
    if isinstance(evclock_loop, SimEventLoop):
        return evclock_loop.clock
    clock = _attached.get(evclock_loop)
    if clock is None:
        clock = WallClock()
        attach_clock(evclock_loop, clock)
    return clock


@pytest.fixture(scope="session")
def evclock_anyio_backend(request: pytest.FixtureRequest) -> tuple[str, dict[str, Any]]:
    """anyio's asyncio backend on evclock's loop (with the marker's options), for::

    @pytest.fixture
    def anyio_backend(evclock_anyio_backend):
        return evclock_anyio_backend
    """
    return ("asyncio", {"loop_factory": _session(request.config).loop_factory})


@pytest.fixture(name=_ANYIO_LOOP_FIXTURE)
def _evclock_anyio_loop(request: pytest.FixtureRequest) -> Iterator[asyncio.AbstractEventLoop]:
    """Hold a lease on anyio's test runner (the one the test will run on) and give its loop."""
    from anyio.pytest_plugin import extract_backend_and_options, get_runner

    backend = request.getfixturevalue("anyio_backend")
    name, options = extract_backend_and_options(backend)
    if name != "asyncio":
        raise EvClockError(
            f"evclock needs anyio's asyncio backend with evclock's loop, got {backend!r}; make "
            "the anyio_backend fixture return the evclock_anyio_backend fixture's value"
        )
    with get_runner(name, options) as runner:
        loop: asyncio.AbstractEventLoop = runner.get_loop()  # type: ignore[attr-defined]
        state = _state_of(request.node)
        if state is not None and state.expect_sim and not isinstance(loop, SimEventLoop):
            pytest.fail(_wrong_loop_message(state, loop), pytrace=False)
        yield loop


@dataclasses.dataclass(frozen=True)
class PyBulletWorld:
    """A PyBullet physics client whose time is the test's sim time.

    ``client`` is the ``physicsClientId`` to pass to every ``pybullet`` call; ``source`` is the
    :class:`~evclock.PyBulletTimeSource` that steps it (``source.set_time_step(...)``,
    ``source.add_step_hook(...)``, ``await source.wait_until(...)``). Gravity is -9.81 m/s^2
    along z, the time step PyBullet's default 1/240 s, and ``pybullet_data`` is on the search
    path: ``p.loadURDF("plane.urdf", physicsClientId=world.client)``.
    """

    client: int
    source: PyBulletTimeSource


@pytest.fixture
def evclock_pybullet(request: pytest.FixtureRequest) -> Iterator[PyBulletWorld]:
    """A PyBullet world (a DIRECT client) stepped by the test's loop: physics advances only when
    every task waits, in whole steps, in lockstep with the code under test.

    The world is created before the test's loop, which is then built around it; the client is
    disconnected after the loop closes. Requesting it opts the test in, like the marker.
    Skipped under ``--evclock-wall`` (a PyBullet world needs sim time).
    """
    state = _state_of(request.node)
    if state is None:
        raise EvClockError("evclock_pybullet is a function-scoped fixture of an evclock test")
    if state.options.wall:
        pytest.skip("evclock_pybullet needs sim time; --evclock-wall runs tests on wall time")
    loop_scope = getattr(state.item, "_loop_scope", "function")
    if state.kind == "asyncio" and loop_scope != "function":
        raise EvClockError(
            f"evclock_pybullet needs a loop of its own, but this test shares a {loop_scope}-"
            "scoped loop; drop loop_scope from its asyncio marker"
        )
    if state.loops:
        raise EvClockError(
            "evclock_pybullet must be set up before the test's loop is created, but a fixture "
            "set up earlier already created it"
        )
    if state.options.start_ns:
        raise EvClockError(
            "evclock(start=...) applies to virtual time only; a PyBullet world starts at 0"
        )
    import pybullet
    import pybullet_data

    source = PyBulletTimeSource.connect()
    try:
        client = source.client
        pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        state.pybullet_source = source
        yield PyBulletWorld(client, source)
    finally:
        source.close()  # disconnects the client (already done if the loop closed it)
