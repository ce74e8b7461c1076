"""A selector that tells an operator thread when a paused loop waits for a control, and the
operator thread that steps such a loop."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import selectors
import threading
from collections.abc import Awaitable, Callable
from typing import Any


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
        stops the loop: call :meth:`raise_error` once the runner is done."""
        loop = self._loop = asyncio.get_running_loop()
        self._target = target
        self._selector.snapshot = lambda: (now(), list(self.ticks))

        def operate() -> None:
            try:
                self.paused_wait()
                script(self)
            except BaseException as exc:  # reported by raise_error, once the loop stopped
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

    def raise_error(self) -> None:
        """Raise what the script raised, if it failed."""
        if self._errors:
            raise self._errors[0]
