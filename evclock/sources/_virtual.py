"""Pure virtual time: a discrete-event source that jumps straight to the next deadline."""

from __future__ import annotations

from .._errors import InvalidArgumentError, InvalidTypeError
from ._base import Gate, TimeSource


class VirtualTimeSource(TimeSource):
    """Discrete-event time: when every task waits, time jumps exactly to the next deadline.

    ``start_ns`` sets the initial time (for example an epoch-like ``1_700_000_000 * 10**9``).
    With nothing scheduled time cannot move, so an idle program is a deadlock.
    """

    free_running = False

    def __init__(self, start_ns: int = 0) -> None:
        if type(start_ns) is not int:
            raise InvalidTypeError(
                f"start_ns must be an int number of nanoseconds, got {type(start_ns).__name__}"
            )
        if start_ns < 0:
            raise InvalidArgumentError(f"start_ns must not be negative, got {start_ns}")
        self._now = start_ns

    @property
    def now_ns(self) -> int:
        return self._now

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        if target_ns is not None and target_ns > self._now and (gate is None or gate(target_ns)):
            self._now = target_ns
        return self._now

    def set_time(self, new_ns: int) -> None:
        """Move time to ``new_ns`` (backwards or forwards) as a jump, like a simulator reset.

        Jump handlers run and pending sim-time sleeps are woken with :class:`ClockJumped`.
        """
        if type(new_ns) is not int or new_ns < 0:
            raise InvalidArgumentError(
                f"set_time() needs a non-negative int of nanoseconds, got {new_ns!r}"
            )
        host = self._host
        if host is None:
            self._now = new_ns
            return
        host.jump(self._now, new_ns, self._assign)

    def _assign(self, new_ns: int) -> None:
        self._now = new_ns

    def describe(self) -> str:
        return "virtual time"
