"""A selector that tells an operator thread when a paused loop waits for a control, and the
operator thread that steps such a loop."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import selectors
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from evclock import Time


class PausedWaits(selectors.DefaultSelector):
    """Reports each wait with no timeout - paused with nothing left to step, nothing ready,
    no timer (``stall_timeout`` bounds every other wait) - as ``snapshot()``, taken on the
    loop's thread, to the concurrent future of :meth:`expect`. The operator thread waits on
    that future: a wait that never holds sim time, whatever its timeout, and no fixed delay."""

    def __init__(self) -> None:
        super().__init__()
        self.snapshot: Callable[[], object] = lambda: None
        self._next: concurrent.futures.Future[object] | None = None
        self._lock = threading.Lock()

    def expect(self) -> concurrent.futures.Future[object]:
        """The snapshot at the loop's next paused wait (ask before calling the control)."""
        future: concurrent.futures.Future[object] = concurrent.futures.Future()
        with self._lock:
            self._next = future
        return future

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None:
            with self._lock:
                future, self._next = self._next, None
            if future is not None:
                future.set_result(self.snapshot())
        return list(super().select(timeout))


class Operator:
    """An operator thread's view of a paused loop (or SimDriver) while a task ticks every
    sim second: :meth:`control` calls a control (directly, or handed over with
    ``call_soon_threadsafe``), :meth:`paused_wait` waits for the next paused wait and records
    ``(sim time, tick times so far)`` in :attr:`seen`; :attr:`ticks` holds every tick's time."""

    def __init__(self, selector: PausedWaits, via: str) -> None:
        self.via = via
        self.seen: list[object] = []
        self.ticks: list[float] = []
        self._errors: list[BaseException] = []
        self._selector = selector
        self._next = selector.expect()  # the first paused wait
        self._target: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def paused_wait(self) -> None:
        self.seen.append(self._next.result(10))
        self._next = self._selector.expect()

    def control(self, name: str, *args: object) -> None:
        assert self._loop is not None
        action = getattr(self._target, name)
        if self.via == "directly":
            action(*args)
        else:
            self._loop.call_soon_threadsafe(action, *args)

    async def run(
        self,
        target: object,
        script: Callable[[Operator], None],
        sleep: Callable[[float], Awaitable[object]],
        now: Callable[[], float],
    ) -> None:
        """On the running loop: 8 ticks (``await sleep(1)``, each recording ``now()``) while
        this operator's thread waits for the first paused wait, then runs ``script(self)``,
        which must end with ``resume``; the controls are ``target``'s. A script that fails
        stops the loop (see :meth:`outcome`)."""
        loop = self._loop = asyncio.get_running_loop()
        self._target = target
        self._selector.snapshot = lambda: (now(), list(self.ticks))

        def operate() -> None:
            try:
                self.paused_wait()
                script(self)
            except BaseException as exc:  # raised by outcome(), once the loop stopped
                self._errors.append(exc)
                with contextlib.suppress(RuntimeError):  # the loop may be closed already
                    loop.call_soon_threadsafe(loop.stop)

        async def ticker() -> None:
            while len(self.ticks) < 8:
                await sleep(1)
                self.ticks.append(now())

        task = asyncio.ensure_future(ticker())
        thread = threading.Thread(target=operate, daemon=True)
        thread.start()
        try:
            await task
        finally:
            thread.join(10)

    def outcome(
        self,
        loop_factory: Callable[[], asyncio.AbstractEventLoop],
        main: Callable[[], Coroutine[Any, Any, None]],
    ) -> tuple[list[object], list[float]]:
        """Run ``main()`` (which awaits :meth:`run`) on a loop of ``loop_factory``; what the
        script failed with is raised once the loop stopped. The records and the ticks."""
        try:
            with asyncio.Runner(loop_factory=loop_factory) as runner:
                runner.run(main())
        finally:
            if self._errors:
                raise self._errors[0]
        return self.seen, self.ticks


#: Every tick's time in a run an operator script steps and then resumes.
TICKS = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]


def step_1_1_1_2_until_6_5(op: Operator) -> None:
    """Step 1 three times, step 2, step_until 6.5 s (waiting for the pause after each), then
    resume: what :data:`STEPPED_SEEN` records."""
    for _ in range(3):
        op.control("step", 1)
        op.paused_wait()
    op.control("step", 2)
    op.paused_wait()
    op.control("step_until", Time(seconds=6.5))
    op.paused_wait()
    op.control("resume")


#: On virtual time each step is one jump to the next deadline, then time holds.
STEPPED_SEEN = [
    (0.0, []),
    (1.0, [1.0]),
    (2.0, [1.0, 2.0]),
    (3.0, [1.0, 2.0, 3.0]),  # and no further until the next control
    (5.0, [1.0, 2.0, 3.0, 4.0, 5.0]),
    (6.5, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
]


def step_1_three_times(op: Operator) -> None:
    """Step 1 three times (waiting for the pause after each), then resume."""
    for _ in range(3):
        op.control("step", 1)
        op.paused_wait()
    op.control("resume")


def end_a_step_until(target: Any, how: str) -> None:
    """On ``target``'s thread: place a step_until(2.5 s), never reached, and end it with
    ``how``: ``"pause"``, ``"resume"`` (then pause again) or a nearer ``"step_until"`` (0.5 s)."""
    target.step_until(Time(seconds=2.5))
    if how == "pause":
        target.pause()
    elif how == "resume":
        target.resume()
        target.pause()
    else:
        target.step_until(Time(seconds=0.5))
