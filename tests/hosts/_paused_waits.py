"""A selector that tells an operator thread when a paused loop waits for a control."""

from __future__ import annotations

import concurrent.futures
import selectors
import threading
from collections.abc import Callable
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
