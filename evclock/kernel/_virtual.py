"""Pure virtual time: a discrete-event source that jumps straight to the next deadline."""

from __future__ import annotations

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.kernel._source import Gate, TimeSource
from evclock.time._time import MAX_TIME_NS, format_time_range_error, whole_number


class VirtualTimeSource(TimeSource):
    """Discrete-event time: when every task waits, time jumps exactly to the next deadline.

    ``start_ns`` sets the initial time (for example an epoch-like ``1_700_000_000 * 10**9``).
    With nothing scheduled time cannot move, so an idle program is a deadlock.
    """

    free_running = False
    #: The current time in integer nanoseconds. A plain attribute: the kernel, which owns
    #: the schedule, moves it itself on its hot path (exactly to a later deadline, as
    #: :meth:`advance` would).
    now_ns: int = 0

    def __init__(self, start_ns: int = 0) -> None:
        start = whole_number(start_ns)
        if start is None:
            raise InvalidTypeError(
                f"start_ns must be an int number of nanoseconds, got {type(start_ns).__name__}"
            )
        if start < 0:
            raise InvalidArgumentError(f"start_ns must not be negative, got {start_ns}")
        if start > MAX_TIME_NS:
            raise InvalidArgumentError(format_time_range_error("start_ns", start))
        self.now_ns = start

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Jump straight to ``target_ns`` (if ``gate`` allows it); return the new time."""
        if target_ns is not None and target_ns > self.now_ns and (gate is None or gate(target_ns)):
            self.now_ns = target_ns
        return self.now_ns

    def set_time(self, new_ns: int) -> None:
        """Move time to ``new_ns`` (backwards or forwards) as a jump, like a simulator reset.

        Jump handlers run and pending sim-time sleeps are woken with :class:`ClockJumpedError`.
        """
        if whole_number(new_ns) is None:
            raise InvalidTypeError(
                f"set_time() needs an int number of nanoseconds, got {type(new_ns).__name__}"
            )
        new_ns = int(new_ns)
        if not 0 <= new_ns <= MAX_TIME_NS:
            raise InvalidArgumentError(
                f"set_time() needs a non-negative int of nanoseconds, got {new_ns!r}"
            )
        host = self._host
        if host is None:
            self.now_ns = new_ns
            return
        host.jump(self.now_ns, new_ns, self._assign)

    def _assign(self, new_ns: int) -> None:
        self.now_ns = new_ns

    def describe(self) -> str:
        """``"virtual time"``, for messages."""
        return "virtual time"


def source_or_virtual(source: object) -> TimeSource:
    """``source`` if it is a :class:`TimeSource`, a new :class:`VirtualTimeSource` for
    ``None``; anything else is an :class:`InvalidTypeError`."""
    if source is None:
        return VirtualTimeSource()
    if not isinstance(source, TimeSource):
        raise InvalidTypeError(
            f"source must be a TimeSource (e.g. VirtualTimeSource(), PyBulletTimeSource(...)), "
            f"got {type(source).__name__}"
        )
    return source
