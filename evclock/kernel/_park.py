"""A sim-time wait without a future, for the tasks a :class:`~evclock.SimEventLoop` makes.

A ``clock.sleep`` on the future path allocates a future, registers the task's wake-up on it,
resolves it when due, schedules the wake-up and steps the task. A *park* does none of that:

1. the waiting coroutine (``_core.park``) notes on the loop "this task parks until
   ``when_ns``" (``loop._parking``, ``loop._park_when``) and yields ``None`` - a bare
   ``yield``, which asyncio's ``Task`` answers by scheduling its own next step with
   ``loop.call_soon(step)``, as for ``asyncio.sleep(0)``;
2. the loop's ``call_soon`` sees that very call (the noted task's own step, the first call
   after the note) and files the step in the kernel's schedule at ``when_ns`` instead of
   the ready queue, in a :class:`Parked` entry (one per task, reused while not cancelled);
3. when due, the kernel runs the step in place, or queues it, exactly where the future's
   wake-up would have run.

The task must be a :class:`SimTask` (the loop's default task factory makes them): its
``cancel()`` moves a parked step to the ready queue at once and then cancels as asyncio's
does, so ``CancelledError`` arrives at the same sim time and in the same order as on the
future path. Any other task (a user's task factory, eager tasks, a loop evclock does not
own) keeps the future path. A jump of sim time wakes a parked task with the error it would
have received through its future (:class:`~evclock.ClockJumpedError`).
"""

from __future__ import annotations

import asyncio
from typing import Any

_TimerHandle = asyncio.TimerHandle
_CancelledError = asyncio.CancelledError


class Parked(_TimerHandle):
    """The kernel's entry for a parked task's step: a ``TimerHandle`` (so that the
    schedule's purge and head checks treat it as one) whose callback is the task's step.

    ``error``: what the task's wait raises when it resumes (a jump, the host ending),
    else None. Fields are asyncio's ``Handle``/``TimerHandle`` slots, set as there.
    """

    __slots__ = ("error",)

    def __init__(self, loop: Any, context: Any) -> None:
        self._context = context
        self._loop = loop
        self._callback: Any = None
        self._args = ()
        self._cancelled = False
        self._repr = None
        self._source_traceback = None
        self._when = 0.0
        self._scheduled = False
        self.error: BaseException | None = None

    def wake_now(self, error: BaseException | None) -> None:
        """Take the step out of the schedule (cancelled there) and queue it on the ready
        queue now; the wait raises ``error`` (None: it returns) when the task resumes."""
        step, context = self._callback, self._context
        self.error = error
        self.cancel()  # stays in the schedule, counted among its cancelled timers
        self._loop.call_soon(step, context=context)


class SimTask(asyncio.Task):  # type: ignore[type-arg]
    """asyncio's (C) ``Task``, whose ``cancel()`` also wakes a parked step first: what a
    :class:`~evclock.SimEventLoop` makes by default. Everything else is asyncio's."""

    #: The task's :class:`Parked` entry (None until it first parks, and after a cancel).
    parked: Parked | None = None

    def cancel(self, msg: Any = None) -> bool:
        """As ``asyncio.Task.cancel``. A task parked in a sim-time wait is first queued to
        run at once, its wait raising ``CancelledError(msg)``: what the wait's cancelled
        future would do. Until it runs, a further cancel keeps that message (as the
        future's error does), and an ``uncancel()`` does not take it back."""
        entry = self.parked
        if entry is not None:
            if entry._scheduled and not entry._cancelled:  # parked now
                entry.wake_now(_CancelledError() if msg is None else _CancelledError(msg))
            elif type(error := entry.error) is _CancelledError:  # woken so, not yet run
                msg = error.args[0] if error.args else None
        return super().cancel(msg)


# Named as asyncio's class in reprs and in "Task exception was never retrieved".
SimTask.__name__ = SimTask.__qualname__ = "Task"
