"""Stamped data: reading the time stamp of a message, in the clock domain of its consumer.

Three shapes of message are understood, tried in this order:

1. a ``key`` function given by the consumer, returning a :class:`Time` (or a
   ``builtin_interfaces/Time``-like object with ``sec``/``nanosec``);
2. an object with a ``stamp`` attribute: a :class:`Time` (e.g. :class:`Stamped`) or a
   ``sec``/``nanosec`` message;
3. a ROS-style message with ``header.stamp`` (``sec``/``nanosec``, or a :class:`Time`).

A :class:`Time` carries its clock domain; one that differs from the consumer's domain raises
:class:`ClockMismatchError` (a wall-clock stamp fed to a sim-time synchroniser is the classic
"sim and real time mixed up" mistake). A ``sec``/``nanosec`` stamp carries no domain (ROS
messages do not say which clock stamped them): it is read in the consumer's domain, and
:class:`~evclock.data.StampDiagnostics` flags stamps from the future, which is what a wall stamp on
sim time looks like.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from evclock._errors import ClockMismatchError, InvalidTypeError
from evclock.time._time import ClockType, Time

__all__ = ["StampClock", "StampKey", "Stamped", "check_stamp_clock", "stamp_of"]

T = TypeVar("T")

StampKey = Callable[[Any], object]
"""A function returning a message's stamp: a :class:`Time` or a ``sec``/``nanosec`` object."""


class StampClock(Protocol):
    """What stamp consumers need from a clock: its domain and ``now()``.

    Every evclock :class:`~evclock.Clock` is one; so is a small adapter around another
    simulator's or framework's clock.
    """

    @property
    def clock_type(self) -> ClockType:
        """The clock domain stamps are read in."""
        ...

    def now(self) -> Time:
        """The current time, a :class:`Time` of ``clock_type``."""
        ...


def check_stamp_clock(clock: object) -> None:
    """Raise :class:`InvalidTypeError` unless ``clock`` has a ``clock_type`` and ``now()``."""
    if not (
        isinstance(getattr(clock, "clock_type", None), ClockType)
        and callable(getattr(clock, "now", None))
    ):
        raise InvalidTypeError(
            f"clock must be an evclock Clock (e.g. evclock.clock()) or have a clock_type "
            f"(ClockType) and now() returning a Time, got {type(clock).__name__}"
        )


@dataclass(frozen=True, slots=True)
class Stamped(Generic[T]):
    """A value with a time stamp: the simplest message evclock's synchronisers accept."""

    stamp: Time
    """When the value was measured (in the clock domain of the clock that stamped it)."""
    value: T
    """The payload."""

    def __post_init__(self) -> None:
        if type(self.stamp) is not Time:
            raise InvalidTypeError(
                f"Stamped.stamp must be an evclock.Time, got {type(self.stamp).__name__}; "
                "build one with clock.now() or Time.from_msg(msg, clock_type)"
            )


def _has_sec_nanosec(value: object) -> bool:
    return hasattr(value, "sec") and hasattr(value, "nanosec")


def _convert(raw: object, clock_type: ClockType, origin: str) -> Time:
    if type(raw) is Time:
        if raw.clock_type is not clock_type:
            raise ClockMismatchError(
                f"{origin} is a {raw.clock_type.value} time but this consumer runs on "
                f"{clock_type.value} time: sim and wall stamps are mixed up; stamp messages "
                f"with the consumer's clock (evclock.clock().now()) or give the consumer the "
                f"clock the producer uses"
            )
        return raw
    if _has_sec_nanosec(raw):
        return Time.from_msg(raw, clock_type)
    raise InvalidTypeError(
        f"{origin} must be an evclock.Time or have sec and nanosec "
        f"(builtin_interfaces/Time), got {type(raw).__name__}"
    )


def stamp_of(message: object, clock_type: ClockType, key: StampKey | None = None) -> Time:
    """The stamp of ``message`` as a :class:`Time` of ``clock_type`` (see the module docstring).

    :returns: the stamp, as a :class:`Time`.
    :raises ClockMismatchError: the stamp is a :class:`Time` of another clock domain.
    :raises InvalidTypeError: the message has no stamp evclock can read; pass ``key=``.
    """
    if key is not None:
        return _convert(key(message), clock_type, f"the stamp key's result for {message!r:.80}")
    stamp = getattr(message, "stamp", None)
    if stamp is not None:
        return _convert(stamp, clock_type, "message.stamp")
    header = getattr(message, "header", None)
    if header is not None and hasattr(header, "stamp"):
        return _convert(header.stamp, clock_type, "message.header.stamp")
    raise InvalidTypeError(
        f"cannot read a time stamp from a {type(message).__name__}: give it a 'stamp' "
        "(evclock.Time), a ROS 'header.stamp' (sec/nanosec), wrap it in "
        "evclock.data.Stamped(stamp, value), or pass key=lambda msg: <its Time>"
    )
