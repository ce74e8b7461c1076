"""The wall-time budget of a test (``wall_timeout``): what stops a test that overruns it, and the
error that reports it.

Two layers, neither of which ever raises an exception into arbitrary code:

* **On the loop.** A watchdog thread waits for the deadline, then hands the expiry to the test's
  loop as a thread-safe callback, which the loop runs between two callbacks: it cancels the
  test (or, in a fixture or a sync test driving the loop, every task of the loop), and the test
  fails with :class:`WallTimeBudgetError` listing where each task waits.
* **Outside the loop.** Code that blocks the loop (synchronous code) or ignores the cancellation
  cannot be stopped safely from inside the process. That is pytest-timeout's job: when it is
  installed, evclock gives each evclock test a pytest-timeout limit of the budget plus a grace
  period (:func:`hard_limit`), unless a stricter one applies. pytest-timeout then fails the test
  with every thread's stack (its ``signal`` method, the default on POSIX: the session goes on)
  or dumps the stacks and ends the whole session (its ``thread`` method).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
from collections.abc import Generator, Iterator
from typing import TYPE_CHECKING, Final

import pytest

from evclock._errors import EvClockError
from evclock.outside._threads import mark_internal
from evclock.testing._describe import describe_tasks

if TYPE_CHECKING:
    from evclock.testing._guard import CallGuard
    from evclock.testing._state import ItemState, Session

#: Where users import these from, and what reports name them by.
_PUBLIC_MODULE: Final = "evclock.testing.plugin"

#: How long after the budget pytest-timeout stops a test the loop could not: the budget itself,
#: at least 1 s and at most 10 s (wall seconds).
_GRACE_MIN, _GRACE_MAX = 1.0, 10.0

#: How often a test that swallows the budget's cancellation is cancelled again (wall seconds):
#: often enough to stop it well before pytest-timeout's hard stop (at least 1 s later).
_RECANCEL_PERIOD: Final = 0.1

BUDGET_HINT: Final = (
    "Raise the budget with @pytest.mark.evclock(wall_timeout=...) or --evclock-wall-timeout "
    "(0 disables it)."
)


class WallTimeBudgetError(EvClockError, TimeoutError):
    """A test overran its wall-time budget (``wall_timeout``) and was cancelled."""

    __module__ = _PUBLIC_MODULE


def hard_limit(seconds: float) -> float:
    """The pytest-timeout limit that backs a wall-time budget of ``seconds``: the budget plus
    a grace period for the cancelled test to unwind."""
    return seconds + min(max(seconds, _GRACE_MIN), _GRACE_MAX)


def default_timeout_of(config: pytest.Config) -> float | None:
    """The per-test limit pytest-timeout applies without a marker (its option, then the
    ``PYTEST_TIMEOUT`` variable, then its ini key), None if none; pytest-timeout validates it."""
    sources = (config.getoption("timeout", None), os.environ.get("PYTEST_TIMEOUT"))
    for value in (*sources, config.getini("timeout")):
        if value is None or value == "":
            continue
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            return None  # pytest-timeout reports the bad value itself
        return seconds if seconds > 0 else None
    return None


class Budget:
    """A wall-time budget for one test (setup, call and teardown), watched by a daemon thread.

    At the deadline the watchdog hands the expiry to the loop (``call_soon_threadsafe``); on
    the loop's thread, between two callbacks, the test function's task is cancelled (or every
    task of the loop, when the budget expires in a fixture or a sync test driving the loop).
    """

    def __init__(self, seconds: float, state: ItemState, session: Session) -> None:
        self.seconds = seconds
        self._session = session
        self._cond = threading.Condition()
        self._deadline = time.monotonic() + seconds
        self._call: CallGuard | None = None
        self._expired_phase: str | None = None
        self._tasks_cancelled = False
        self._where: tuple[str, ...] = ()
        self._phase = "setup"
        self._finished = False
        self._thread = threading.Thread(
            target=self._watch, name=f"evclock-budget[{state.item.name}]", daemon=True
        )
        mark_internal(self._thread)  # it never resumes a paused test's loop
        self._thread.start()

    def enter_phase(self, phase: str) -> None:
        """The test enters ``setup``, ``call`` or ``teardown`` (for the report)."""
        with self._cond:
            self._phase = phase

    def enter_call(self, call: CallGuard) -> None:
        with self._cond:
            self._call = call

    def leave_call(self, call: CallGuard) -> None:
        with self._cond:
            if self._call is call:
                self._call = None

    def finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify()

    def _watch(self) -> None:
        with self._cond:
            while not self._finished:
                now = time.monotonic()
                if now < self._deadline:
                    self._cond.wait(self._deadline - now)
                    continue
                self._expire()
                # A test that swallows the cancellation is cancelled again, every 0.1 s.
                self._deadline = now + _RECANCEL_PERIOD

    def _expire(self) -> None:
        """At the deadline (watchdog thread, lock held): hand the expiry to the loop(s)."""
        if self._expired_phase is None:
            self._expired_phase = self._phase
        elif self._call is None:
            return  # fixtures and sync tests: their tasks were cancelled once
        call = self._call
        if call is not None:
            call.request_expiry(self.seconds)
            return
        for loop in self._session.open_loops():
            with contextlib.suppress(RuntimeError):  # closed meanwhile
                loop.call_soon_threadsafe(self._cancel_tasks, loop)

    def _cancel_tasks(self, loop: asyncio.AbstractEventLoop) -> None:
        """On a loop's thread: cancel what runs there (a fixture, or a sync test's run)."""
        with self._cond:
            if self._finished:
                return  # the test is over: this loop now runs another test
            self._tasks_cancelled = True
        self._where += describe_tasks(loop, None)
        for task in asyncio.all_tasks(loop):
            task.cancel("evclock: wall-time budget exceeded")

    @property
    def expired(self) -> bool:
        """Whether the deadline has passed (whatever happened then)."""
        return self._expired_phase is not None

    def error_for(self, exc: BaseException) -> WallTimeBudgetError | None:
        """The report for a CancelledError that cancelling the loop's tasks caused, if so."""
        if not (self._tasks_cancelled and isinstance(exc, asyncio.CancelledError)):
            return None
        where = "\n".join(f"  {line}" for line in self._where) or "  (no task)"
        phase = self._expired_phase or "call"
        within = "" if phase == "call" else f" (in {phase})"
        return WallTimeBudgetError(
            f"evclock: wall-time budget exceeded: the test was still running after "
            f"{self.seconds:g} s of wall time{within} and was cancelled. Its tasks were at:\n"
            f"{where}\n{BUDGET_HINT}"
        )

    def blocked_note(self) -> str | None:
        """For the report of a test the loop could not stop in time, what evclock saw."""
        if not self.expired:
            return None
        return (
            f"evclock: the wall-time budget ({self.seconds:g} s) expired in {self._expired_phase} "
            "and the test was asked to stop between two callbacks of its loop; if it failed "
            "with pytest-timeout's 'Timeout' instead, it did not get back to its loop in time: "
            "synchronous code blocked the loop, or the test swallowed CancelledError."
        )


class PytestTimeoutHooks:
    """evclock's side of pytest-timeout, registered only when pytest-timeout is installed."""

    @pytest.hookimpl(wrapper=True)
    def pytest_timeout_set_timer(
        self, item: pytest.Item, settings: object
    ) -> Generator[None, object, object]:
        """pytest-timeout's ``thread`` method starts a timer thread per test: declare it one
        that never calls a loop back, so that a paused loop nobody else can resume is still
        reported as a deadlock (it would otherwise wait for that thread)."""
        before = threading.enumerate()
        try:
            return (yield)
        finally:
            for thread in threading.enumerate():
                if thread not in before:
                    mark_internal(thread)


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
