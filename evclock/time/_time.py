"""Time and Duration: immutable, exact, integer-nanosecond values, and the clock domains.

Every value is an integer number of nanoseconds; floats only appear at the edges (``.seconds``,
constructors and conversions from float seconds, multiplication or division by a float). A
``Duration`` is a signed span that fits in a signed 64-bit integer of nanoseconds. A ``Time`` is
a point in one clock domain (``SIM``, ``SYSTEM`` or ``STEADY``): a non-negative number of
nanoseconds since that clock's origin. Times of different domains cannot be subtracted or
ordered; they are never equal.

The message layout of ``to_msg()``/``from_msg()`` is ROS 2's ``builtin_interfaces/Time`` and
``builtin_interfaces/Duration``: ``sec`` (int32, floor of the value in seconds) and ``nanosec``
(in ``[0, 1_000_000_000)``), so -1.5 s is ``sec=-2, nanosec=500_000_000``.
"""

from __future__ import annotations

import enum
import math
import numbers
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, NoReturn, final, overload

from evclock._errors import ClockMismatchError, InvalidArgumentError, InvalidTypeError

if TYPE_CHECKING:
    from typing import Self

__all__ = [
    "ClockType",
    "SIM",
    "SYSTEM",
    "STEADY",
    "Duration",
    "Time",
    "DurationMsg",
    "TimeMsg",
]

_NS_PER_S: Final = 1_000_000_000
_I64_MIN: Final = -(2**63)
_I64_MAX: Final = 2**63 - 1
#: The largest sim time (and any Time): sim time lives in [0, MAX_TIME_NS] nanoseconds.
MAX_TIME_NS: Final = _I64_MAX
_I32_MIN: Final = -(2**31)
_I32_MAX: Final = 2**31 - 1


class ClockType(enum.Enum):
    """The clock domain a :class:`Time` belongs to (ROS's ROS_TIME, SYSTEM_TIME, STEADY_TIME)."""

    SIM = "sim"
    """Simulation time, owned by evclock (ROS_TIME with ``use_sim_time``)."""
    SYSTEM = "system"
    """Wall-clock time since the Unix epoch; can jump when the system clock is set."""
    STEADY = "steady"
    """Monotonic time from an arbitrary origin; never jumps."""


SIM: Final = ClockType.SIM
"""Simulation time (:attr:`ClockType.SIM`): the domain of the times of a simulation loop."""
SYSTEM: Final = ClockType.SYSTEM
"""Wall-clock time since the Unix epoch (:attr:`ClockType.SYSTEM`)."""
STEADY: Final = ClockType.STEADY
"""Monotonic wall time (:attr:`ClockType.STEADY`): the domain of :class:`WallClock` times."""


@final
@dataclass(frozen=True, slots=True)
class DurationMsg:
    """A duration in the ``builtin_interfaces/Duration`` layout.

    ``sec`` is the floor of the duration in seconds (int32) and ``nanosec`` the remainder in
    ``[0, 1_000_000_000)``: -1.5 s is ``DurationMsg(sec=-2, nanosec=500_000_000)``.
    """

    sec: int
    nanosec: int


@final
@dataclass(frozen=True, slots=True)
class TimeMsg:
    """A point in time in the ``builtin_interfaces/Time`` layout (``sec`` int32, ``nanosec``)."""

    sec: int
    nanosec: int


# --------------------------------------------------------------------------------------------
# Conversion helpers
# --------------------------------------------------------------------------------------------


def _float_error(value: float, what: str) -> InvalidArgumentError:
    """The error for a float number of seconds that cannot be converted to nanoseconds."""
    if math.isnan(value):
        return InvalidArgumentError(f"{what} must be a number, got NaN")
    if math.isinf(value):
        return InvalidArgumentError(f"{what} must be finite, got {value!r}")
    return InvalidArgumentError(f"{what} overflows: {value!r} s is too large in nanoseconds")


def _type_error(value: object, what: str) -> InvalidTypeError:
    return InvalidTypeError(
        f"{what} must be seconds (int or float) or a Duration, got {type(value).__name__}"
    )


def _float_seconds_to_ns(value: float, what: str) -> int:
    try:
        return round(value * 1e9)
    except (OverflowError, ValueError):
        raise _float_error(value, what) from None


def _number_seconds_to_ns(value: object, what: str) -> int | None:
    """Convert a number of seconds that is not exactly an int or float; None if not a number."""
    if isinstance(value, bool):
        return None
    if isinstance(value, float):  # float subclasses, e.g. numpy.float64
        return _float_seconds_to_ns(float(value), what)
    if isinstance(value, int):  # int subclasses (not bool)
        return int(value) * _NS_PER_S
    if isinstance(value, numbers.Integral):  # e.g. numpy.int64
        return operator.index(value) * _NS_PER_S
    if isinstance(value, numbers.Rational):  # fractions.Fraction: exact, ties to even
        from fractions import Fraction  # only for exact rationals: off `import evclock`

        exact = Fraction(operator.index(value.numerator), operator.index(value.denominator))
        return round(exact * _NS_PER_S)
    if isinstance(value, numbers.Real):  # e.g. numpy.float32
        return _float_seconds_to_ns(float(value), what)
    return None


def to_nanoseconds(value: object, what: str) -> int:
    """Convert seconds or a :class:`Duration` to integer nanoseconds: the one converter.

    Seconds are any real number but ``bool``: ``int``, ``float``, ``fractions.Fraction``
    (exact, ties to even) and numpy integer and float scalars. Floats are rounded to the
    nearest nanosecond (``round(value * 1e9)``); ints are exact.
    Negative values are returned as they are: callers decide whether they are allowed. There is
    no range check beyond float overflow: callers that build a ``Time``/``Duration`` check the
    range of the result.

    ``what`` names the value in error messages (e.g. ``"sleep duration"``).

    Raises:
        InvalidTypeError: ``value`` is not an int, a float or a Duration (bools are rejected).
        InvalidArgumentError: ``value`` is NaN or infinite (or a float too large to convert).
    """
    if type(value) is float:
        try:
            return round(value * 1e9)
        except (OverflowError, ValueError):
            raise _float_error(value, what) from None
    if type(value) is Duration:
        return value._ns
    if type(value) is int:
        return value * _NS_PER_S
    ns = _number_seconds_to_ns(value, what)
    if ns is None:
        raise _type_error(value, what)
    return ns


def to_nonnegative_nanoseconds(value: object, what: str, hint: str = "") -> int:
    """Like :func:`to_nanoseconds`, but also reject negative values.

    A value is negative if it is below zero after rounding to whole nanoseconds (so ``-1e-12``
    seconds is accepted as zero). ``hint`` is appended to the error message when given.

    Raises:
        InvalidTypeError: ``value`` is not an int, a float or a Duration.
        InvalidArgumentError: ``value`` is NaN, infinite or negative.
    """
    ns = to_nanoseconds(value, what)
    if ns < 0:
        message = f"{what} must not be negative, got {value!r}"
        if hint:
            message += f"; {hint}"
        raise InvalidArgumentError(message)
    return ns


def to_sim_time_ns(value: object, what: str, hint: str = "") -> int:
    """Convert a point in sim time - a sim :class:`Time` or seconds since the sim epoch (any
    real number, see :func:`to_nanoseconds`) - to integer nanoseconds in sim time's range.

    Raises:
        ClockMismatchError: ``value`` is a Time of another clock.
        InvalidTypeError: ``value`` is neither a Time nor seconds.
        InvalidArgumentError: NaN, infinite, negative or beyond ``MAX_TIME_NS``.
    """
    if type(value) is Time:
        if value._clock_type is not ClockType.SIM:
            raise ClockMismatchError(
                f"{what} must be a sim time, got a {value._clock_type.value} time"
            )
        return value._ns
    ns = to_nonnegative_nanoseconds(value, what, hint)
    if ns > _I64_MAX:
        raise InvalidArgumentError(format_time_range_error(what, ns))
    return ns


def to_span_ns(value: object, what: str, hint: str = "") -> int:
    """Convert a non-negative span (seconds or a :class:`Duration`) to integer nanoseconds
    within the time range ``[0, MAX_TIME_NS]``."""
    ns = to_nonnegative_nanoseconds(value, what, hint)
    if ns > _I64_MAX:
        raise InvalidArgumentError(format_time_range_error(what, ns))
    return ns


_NEGATIVE_SLEEP_HINT: Final = (
    "a negative sleep is a bug in the caller; to wait until a time use sleep_until()"
)


def sleep_duration_ns(duration: object) -> int:
    """A sleep duration (seconds or a Duration, not negative) in integer nanoseconds."""
    return to_span_ns(duration, "sleep duration", _NEGATIVE_SLEEP_HINT)


def real_number(value: object) -> float | None:
    """``value`` as a float if it is a real number (not ``bool``; numpy scalars and
    ``Fraction`` included), else None: for callers that word their own errors."""
    if type(value) is float or type(value) is int:
        return float(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    return float(value)


def whole_number(value: object) -> int | None:
    """``value`` as an int if it is an integer (not ``bool``; numpy integers included)."""
    if type(value) is int:
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        return None
    return operator.index(value)


def _seconds_arg_to_ns(value: object, what: str) -> int:
    """Convert a ``seconds=`` constructor argument (int or float, not bool, not Duration)."""
    if type(value) is float:
        return _float_seconds_to_ns(value, what)
    if type(value) is int:
        return value * _NS_PER_S
    ns = _number_seconds_to_ns(value, what)
    if ns is None:
        name = type(value).__name__
        hint = "; pass nanoseconds=d.nanoseconds to copy a Duration" if name == "Duration" else ""
        raise InvalidTypeError(f"{what} must be an int or a float, got {name}{hint}")
    return ns


def _int_arg(value: object, what: str) -> int:
    """Validate an integer argument (``nanoseconds=``, ``sec``, ``nanosec``): not bool/float."""
    if type(value) is int:
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        extra = "; use seconds= for fractional values" if isinstance(value, float) else ""
        raise InvalidTypeError(f"{what} must be an int, got {type(value).__name__}{extra}")
    return operator.index(value)


def _overflow(what: str, ns: int, low: int = _I64_MIN) -> InvalidArgumentError:
    return InvalidArgumentError(
        f"{what} overflows: {ns} ns is outside [{low}, {_I64_MAX}] (64-bit nanoseconds)"
    )


def _check_duration_ns(ns: int, what: str = "Duration") -> int:
    if _I64_MIN <= ns <= _I64_MAX:
        return ns
    raise _overflow(what, ns)


def _time_range_error(ns: int) -> InvalidArgumentError:
    if ns < 0:
        return InvalidArgumentError(f"Time must not be negative, got {ns} ns")
    return _overflow("Time", ns, 0)


def format_time_range_error(what: str, ns: int) -> str:
    """The message for a sim time ``ns`` outside ``[0, MAX_TIME_NS]``."""
    return (
        f"{what} would reach {ns} ns, outside sim time's range [0, {_I64_MAX}] ns "
        "(64-bit nanoseconds, about 292 years); use a shorter duration or an earlier time"
    )


def _check_time_ns(ns: int) -> int:
    if 0 <= ns <= _I64_MAX:
        return ns
    raise _time_range_error(ns)


def _div_round_half_even(n: int, d: int) -> int:
    """``n / d`` rounded to the nearest integer, ties to even, exactly. ``d`` must not be 0."""
    if d < 0:
        n, d = -n, -d
    q, r = divmod(n, d)
    twice = 2 * r
    if twice > d or (twice == d and q & 1):
        q += 1
    return q


def _as_factor(value: object) -> int | float | None:
    """A multiplier/divisor as an exact int or a float; None if it is not a real number."""
    if type(value) is int or type(value) is float:
        return value
    if isinstance(value, bool):
        return None
    if isinstance(value, float):
        return float(value)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, numbers.Integral):
        return operator.index(value)
    if isinstance(value, numbers.Real):
        return float(value)
    return None


def _check_finite_factor(x: float, op: str) -> None:
    if math.isnan(x):
        raise InvalidArgumentError(f"cannot {op} a Duration by NaN")
    if math.isinf(x):
        raise InvalidArgumentError(f"cannot {op} a Duration by {x!r}")


def _format_ns(ns: int) -> str:
    sign = "-" if ns < 0 else ""
    sec, nsec = divmod(abs(ns), _NS_PER_S)
    return f"{sign}{sec}.{nsec:09d} s"


def _read_msg(msg: object, kind: str) -> tuple[int, int]:
    """Read ``sec`` and ``nanosec`` from a message-like object or a mapping, validated."""
    sec: object
    nanosec: object
    try:
        if isinstance(msg, Mapping):
            sec, nanosec = msg["sec"], msg["nanosec"]
        else:
            sec, nanosec = msg.sec, msg.nanosec  # type: ignore[attr-defined]
    except (KeyError, AttributeError):
        raise InvalidTypeError(
            f"expected a builtin_interfaces/{kind} message (an object or a mapping with int "
            f"'sec' and 'nanosec'), got {type(msg).__name__}"
        ) from None
    sec_i = _int_arg(sec, f"{kind} message 'sec'")
    nanosec_i = _int_arg(nanosec, f"{kind} message 'nanosec'")
    if not 0 <= nanosec_i < _NS_PER_S:
        raise InvalidArgumentError(
            f"{kind} message 'nanosec' must be in [0, 1000000000), got {nanosec_i}"
        )
    return sec_i, nanosec_i


def _to_msg_fields(ns: int, kind: str) -> tuple[int, int]:
    sec, nanosec = divmod(ns, _NS_PER_S)
    if not _I32_MIN <= sec <= _I32_MAX:
        raise InvalidArgumentError(
            f"{_format_ns(ns)} does not fit a builtin_interfaces/{kind} message: "
            f"sec={sec} is outside the int32 range [{_I32_MIN}, {_I32_MAX}]"
        )
    return sec, nanosec


def _mix_error(op: str, a: object, b: object, hint: str = "") -> NoReturn:
    message = f"unsupported operand types for {op}: {type(a).__name__} and {type(b).__name__}"
    if hint:
        message += f"; {hint}"
    raise InvalidTypeError(message)


def _is_plain_number(value: object) -> bool:
    return not isinstance(value, bool) and isinstance(value, numbers.Real)


_object_new = object.__new__


# --------------------------------------------------------------------------------------------
# Duration
# --------------------------------------------------------------------------------------------


@final
class Duration:
    """A signed span of time: an exact integer number of nanoseconds (signed 64-bit range).

    ``Duration(seconds=0, nanoseconds=0)`` adds both parts: int seconds are exact, float seconds
    are rounded to the nearest nanosecond. Immutable, hashable and totally ordered.

    Arithmetic: ``d + d``, ``d - d``, ``-d``, ``abs(d)``, ``d * number``, ``d / number`` (both
    rounded to the nearest nanosecond, ties to even), ``d / d`` (float), ``d // d`` (int),
    ``d % d``, ``divmod(d, d)``; a Duration added to or subtracted from a :class:`Time` gives a
    Time. Results outside the range raise :class:`~evclock._errors.InvalidArgumentError`.
    """

    __slots__ = ("_ns",)
    _ns: int

    def __new__(cls, seconds: int | float = 0, nanoseconds: int = 0) -> Self:
        """Create ``seconds + nanoseconds`` (see the class docstring)."""
        if type(seconds) is int and type(nanoseconds) is int:
            ns = seconds * _NS_PER_S + nanoseconds
        else:
            ns = _seconds_arg_to_ns(seconds, "Duration seconds") + _int_arg(
                nanoseconds, "Duration nanoseconds"
            )
        self = _object_new(cls)
        _set_duration_ns(self, _check_duration_ns(ns))
        return self

    @classmethod
    def from_seconds(cls, seconds: int | float) -> Duration:
        """A Duration of ``seconds`` (int exact, float rounded to the nearest nanosecond)."""
        return cls(seconds)

    @classmethod
    def from_nanoseconds(cls, nanoseconds: int) -> Duration:
        """A Duration of exactly ``nanoseconds`` (an int)."""
        return cls(0, nanoseconds)

    @classmethod
    def from_msg(cls, msg: object) -> Duration:
        """Build from a ``builtin_interfaces/Duration``-like message or mapping.

        Any object with int attributes ``sec`` and ``nanosec`` works (a ROS message, a
        :class:`DurationMsg`), as does a mapping with those keys. ``nanosec`` must be in
        ``[0, 1_000_000_000)``.
        """
        sec, nanosec = _read_msg(msg, "Duration")
        return _duration_checked(sec * _NS_PER_S + nanosec)

    def to_msg(self) -> DurationMsg:
        """This duration in the ``builtin_interfaces/Duration`` layout (``sec`` must fit int32)."""
        sec, nanosec = _to_msg_fields(self._ns, "Duration")
        return DurationMsg(sec=sec, nanosec=nanosec)

    @property
    def nanoseconds(self) -> int:
        """The exact duration in nanoseconds."""
        return self._ns

    @property
    def seconds(self) -> float:
        """The duration in seconds, as the nearest float."""
        return self._ns / _NS_PER_S

    # -- immutability, copying, pickling ---------------------------------------------------

    if not TYPE_CHECKING:

        def __setattr__(self, name: str, value: object) -> None:
            raise AttributeError(f"Duration is immutable: cannot set {name!r}")

        def __delattr__(self, name: str) -> None:
            raise AttributeError(f"Duration is immutable: cannot delete {name!r}")

    def __reduce__(self) -> tuple[Any, ...]:
        return (Duration, (0, self._ns))

    def __copy__(self) -> Duration:
        return self

    def __deepcopy__(self, memo: object) -> Duration:
        return self

    # -- representation ----------------------------------------------------------------------

    def __repr__(self) -> str:
        return f"Duration(nanoseconds={self._ns})"

    def __str__(self) -> str:
        return _format_ns(self._ns)

    def __bool__(self) -> bool:
        return self._ns != 0

    def __hash__(self) -> int:
        return hash(self._ns)

    # -- comparisons -------------------------------------------------------------------------

    def __eq__(self, other: object) -> bool:
        if type(other) is Duration:
            return self._ns == other._ns
        return NotImplemented

    def __ne__(self, other: object) -> bool:
        if type(other) is Duration:
            return self._ns != other._ns
        return NotImplemented

    def _order_error(self, op: str, other: object) -> NoReturn:
        if _is_plain_number(other):
            _mix_error(op, self, other, "compare with a Duration, or use d.seconds")
        _mix_error(op, self, other)

    def __lt__(self, other: Duration) -> bool:
        if type(other) is Duration:
            return self._ns < other._ns
        self._order_error("<", other)

    def __le__(self, other: Duration) -> bool:
        if type(other) is Duration:
            return self._ns <= other._ns
        self._order_error("<=", other)

    def __gt__(self, other: Duration) -> bool:
        if type(other) is Duration:
            return self._ns > other._ns
        self._order_error(">", other)

    def __ge__(self, other: Duration) -> bool:
        if type(other) is Duration:
            return self._ns >= other._ns
        self._order_error(">=", other)

    # -- additive arithmetic -----------------------------------------------------------------

    def __add__(self, other: Duration) -> Duration:
        if type(other) is Duration:
            return _duration_checked(self._ns + other._ns)
        if _is_plain_number(other):
            _mix_error("+", self, other, "convert the number with Duration(seconds=...)")
        return NotImplemented  # Time.__radd__ handles Duration + Time

    def __radd__(self, other: Duration) -> Duration:
        if _is_plain_number(other):
            _mix_error(
                "+",
                other,
                self,
                "convert the number with Duration(seconds=...); "
                "to sum Durations use sum(durations, Duration())",
            )
        return NotImplemented

    def __sub__(self, other: Duration) -> Duration:
        if type(other) is Duration:
            return _duration_checked(self._ns - other._ns)
        if _is_plain_number(other):
            _mix_error("-", self, other, "convert the number with Duration(seconds=...)")
        if type(other) is Time:
            _mix_error("-", self, other, "a Time cannot be subtracted from a Duration")
        return NotImplemented

    def __rsub__(self, other: Duration) -> Duration:
        if _is_plain_number(other):
            _mix_error("-", other, self, "convert the number with Duration(seconds=...)")
        return NotImplemented

    def __neg__(self) -> Duration:
        return _duration_checked(-self._ns)

    def __pos__(self) -> Duration:
        return self

    def __abs__(self) -> Duration:
        return _duration_checked(abs(self._ns))

    # -- scaling -----------------------------------------------------------------------------

    def __mul__(self, other: int | float) -> Duration:
        factor = _as_factor(other)
        if factor is None:
            if isinstance(other, Duration):
                _mix_error("*", self, other, "two Durations cannot be multiplied")
            if isinstance(other, bool):
                _mix_error("*", self, other)
            return NotImplemented
        if type(factor) is int:
            return _duration_checked(self._ns * factor)
        assert isinstance(factor, float)
        _check_finite_factor(factor, "multiply")
        p, q = factor.as_integer_ratio()
        return _duration_checked(_div_round_half_even(self._ns * p, q))

    __rmul__ = __mul__

    @overload
    def __truediv__(self, other: Duration) -> float: ...
    @overload
    def __truediv__(self, other: float) -> Duration: ...

    def __truediv__(self, other: object) -> Duration | float:
        """``d / d`` is a float; ``d / number`` is a Duration rounded to the nearest ns."""
        if type(other) is Duration:
            if other._ns == 0:
                raise InvalidArgumentError("cannot divide a Duration by a zero Duration")
            return self._ns / other._ns
        factor = _as_factor(other)
        if factor is None:
            if isinstance(other, bool):
                _mix_error("/", self, other)
            return NotImplemented
        if type(factor) is int:
            if factor == 0:
                raise InvalidArgumentError("cannot divide a Duration by zero")
            return _duration_checked(_div_round_half_even(self._ns, factor))
        assert isinstance(factor, float)
        _check_finite_factor(factor, "divide")
        if factor == 0.0:
            raise InvalidArgumentError("cannot divide a Duration by zero")
        p, q = factor.as_integer_ratio()
        return _duration_checked(_div_round_half_even(self._ns * q, p))

    def __rtruediv__(self, other: object) -> Duration:
        if _is_plain_number(other):
            _mix_error("/", other, self, "for a frequency use 1 / d.seconds")
        return NotImplemented

    @overload
    def __floordiv__(self, other: Duration) -> int: ...
    @overload
    def __floordiv__(self, other: int) -> Duration: ...

    def __floordiv__(self, other: object) -> Duration | int:
        """``d // d`` is an int (floor); ``d // int`` is a Duration (floor)."""
        if type(other) is Duration:
            if other._ns == 0:
                raise InvalidArgumentError("cannot divide a Duration by a zero Duration")
            return self._ns // other._ns
        if type(other) is int or (
            not isinstance(other, bool) and isinstance(other, numbers.Integral)
        ):
            k = operator.index(other)
            if k == 0:
                raise InvalidArgumentError("cannot divide a Duration by zero")
            return _duration_checked(self._ns // k)
        if _is_plain_number(other) or isinstance(other, bool):
            _mix_error("//", self, other, "use d / x for a Duration rounded to the nearest ns")
        return NotImplemented

    def __mod__(self, other: Duration) -> Duration:
        if type(other) is Duration:
            if other._ns == 0:
                raise InvalidArgumentError("cannot take a Duration modulo a zero Duration")
            return _new_duration(self._ns % other._ns)
        if _is_plain_number(other) or isinstance(other, bool):
            _mix_error("%", self, other, "the modulus must be a Duration")
        return NotImplemented

    def __divmod__(self, other: Duration) -> tuple[int, Duration]:
        if type(other) is Duration:
            if other._ns == 0:
                raise InvalidArgumentError("cannot divide a Duration by a zero Duration")
            q, r = divmod(self._ns, other._ns)
            return q, _new_duration(r)
        if _is_plain_number(other) or isinstance(other, bool):
            _mix_error("divmod()", self, other, "the divisor must be a Duration")
        return NotImplemented


_set_duration_ns: Final[Callable[[Duration, int], None]] = Duration.__dict__["_ns"].__set__


def _new_duration(
    ns: int,
    new: Callable[[type[Duration]], Duration] = _object_new,
    set_ns: Callable[[Duration, int], None] = _set_duration_ns,
) -> Duration:
    """A Duration of ``ns`` without any check (the internal hot path)."""
    self = new(Duration)
    set_ns(self, ns)
    return self


def _duration_checked(ns: int) -> Duration:
    """A Duration of ``ns``, range-checked."""
    if _I64_MIN <= ns <= _I64_MAX:
        return _new_duration(ns)
    raise _overflow("Duration", ns)


# --------------------------------------------------------------------------------------------
# Time
# --------------------------------------------------------------------------------------------

_CONVERT_HINT: Final = (
    "times from different clocks are not comparable; "
    "convert explicitly with Time(nanoseconds=t.nanoseconds, clock_type=...)"
)


def _mismatch(action: str) -> ClockMismatchError:
    return ClockMismatchError(f"cannot {action}: {_CONVERT_HINT}")


@final
class Time:
    """A point in time of one clock domain: exact non-negative integer nanoseconds.

    ``Time(seconds=0, nanoseconds=0, clock_type=ClockType.SIM)``; the value must be in
    ``[0, 2**63 - 1]`` ns. Immutable and hashable (the domain is part of the hash).

    ``t - t`` is a :class:`Duration`; ``t + d``, ``d + t`` and ``t - d`` are Times. Subtracting
    or ordering Times of different domains raises
    :class:`~evclock._errors.ClockMismatchError`; such Times are never equal.
    """

    __slots__ = ("_clock_type", "_ns")
    _ns: int
    _clock_type: ClockType

    def __new__(
        cls,
        seconds: int | float = 0,
        nanoseconds: int = 0,
        clock_type: ClockType = ClockType.SIM,
    ) -> Self:
        """Create the Time ``seconds + nanoseconds`` of ``clock_type``."""
        if type(seconds) is int and type(nanoseconds) is int:
            ns = seconds * _NS_PER_S + nanoseconds
        else:
            ns = _seconds_arg_to_ns(seconds, "Time seconds") + _int_arg(
                nanoseconds, "Time nanoseconds"
            )
        if type(clock_type) is not ClockType:
            raise InvalidTypeError(
                f"Time clock_type must be a ClockType (SIM, SYSTEM or STEADY), "
                f"got {type(clock_type).__name__}"
            )
        self = _object_new(cls)
        _set_time_ns(self, _check_time_ns(ns))
        _set_time_clock_type(self, clock_type)
        return self

    @classmethod
    def from_msg(cls, msg: object, clock_type: ClockType = ClockType.SIM) -> Time:
        """Build from a ``builtin_interfaces/Time``-like message or mapping.

        Any object with int attributes ``sec`` and ``nanosec`` works (a ROS message, a
        :class:`TimeMsg`), as does a mapping with those keys.
        """
        sec, nanosec = _read_msg(msg, "Time")
        return cls(0, sec * _NS_PER_S + nanosec, clock_type)

    def to_msg(self) -> TimeMsg:
        """This time in the ``builtin_interfaces/Time`` layout (``sec`` must fit int32)."""
        sec, nanosec = _to_msg_fields(self._ns, "Time")
        return TimeMsg(sec=sec, nanosec=nanosec)

    @property
    def nanoseconds(self) -> int:
        """The exact time in nanoseconds since the clock's origin."""
        return self._ns

    @property
    def seconds(self) -> float:
        """The time in seconds since the clock's origin, as the nearest float."""
        return self._ns / _NS_PER_S

    @property
    def clock_type(self) -> ClockType:
        """The clock domain of this time."""
        return self._clock_type

    # -- immutability, copying, pickling ---------------------------------------------------

    if not TYPE_CHECKING:

        def __setattr__(self, name: str, value: object) -> None:
            raise AttributeError(f"Time is immutable: cannot set {name!r}")

        def __delattr__(self, name: str) -> None:
            raise AttributeError(f"Time is immutable: cannot delete {name!r}")

    def __reduce__(self) -> tuple[Any, ...]:
        return (Time, (0, self._ns, self._clock_type))

    def __copy__(self) -> Time:
        return self

    def __deepcopy__(self, memo: object) -> Time:
        return self

    # -- representation ----------------------------------------------------------------------

    def __repr__(self) -> str:
        return f"Time(nanoseconds={self._ns}, clock_type=ClockType.{self._clock_type.name})"

    def __str__(self) -> str:
        return f"{_format_ns(self._ns)} ({self._clock_type.value})"

    def __hash__(self) -> int:
        return hash((self._ns, self._clock_type))

    # -- comparisons -------------------------------------------------------------------------

    def __eq__(self, other: object) -> bool:
        if type(other) is Time:
            return self._ns == other._ns and self._clock_type is other._clock_type
        return NotImplemented

    def __ne__(self, other: object) -> bool:
        if type(other) is Time:
            return self._ns != other._ns or self._clock_type is not other._clock_type
        return NotImplemented

    def _order_error(self, op: str, other: object) -> NoReturn:
        if type(other) is Time:
            raise _mismatch(
                f"compare a {self._clock_type.value} time with a {other._clock_type.value} time"
            )
        if _is_plain_number(other):
            _mix_error(op, self, other, "compare with a Time, or use t.seconds")
        _mix_error(op, self, other)

    def __lt__(self, other: Time) -> bool:
        if type(other) is Time and self._clock_type is other._clock_type:
            return self._ns < other._ns
        self._order_error("<", other)

    def __le__(self, other: Time) -> bool:
        if type(other) is Time and self._clock_type is other._clock_type:
            return self._ns <= other._ns
        self._order_error("<=", other)

    def __gt__(self, other: Time) -> bool:
        if type(other) is Time and self._clock_type is other._clock_type:
            return self._ns > other._ns
        self._order_error(">", other)

    def __ge__(self, other: Time) -> bool:
        if type(other) is Time and self._clock_type is other._clock_type:
            return self._ns >= other._ns
        self._order_error(">=", other)

    # -- arithmetic --------------------------------------------------------------------------

    def __add__(self, other: Duration) -> Time:
        if type(other) is Duration:
            return _time_checked(self._ns + other._ns, self._clock_type)
        if type(other) is Time:
            _mix_error("+", self, other, "two Times cannot be added; add a Duration to a Time")
        if _is_plain_number(other):
            _mix_error("+", self, other, "convert the number with Duration(seconds=...)")
        return NotImplemented

    def __radd__(self, other: Duration) -> Time:
        if type(other) is Duration:
            return _time_checked(self._ns + other._ns, self._clock_type)
        if _is_plain_number(other):
            _mix_error("+", other, self, "convert the number with Duration(seconds=...)")
        return NotImplemented

    @overload
    def __sub__(self, other: Time) -> Duration: ...
    @overload
    def __sub__(self, other: Duration) -> Time: ...

    def __sub__(self, other: object) -> Duration | Time:
        """``t - t`` is a Duration (same domain only); ``t - d`` is a Time."""
        if type(other) is Duration:
            return _time_checked(self._ns - other._ns, self._clock_type)
        if type(other) is Time:
            if self._clock_type is not other._clock_type:
                raise _mismatch(
                    f"subtract a {other._clock_type.value} time "
                    f"from a {self._clock_type.value} time"
                )
            return _new_duration(self._ns - other._ns)
        if _is_plain_number(other):
            _mix_error("-", self, other, "convert the number with Duration(seconds=...)")
        return NotImplemented

    def __rsub__(self, other: object) -> Time:
        if _is_plain_number(other):
            _mix_error("-", other, self, "subtract Times or Durations, not numbers")
        return NotImplemented


_set_time_ns: Final[Callable[[Time, int], None]] = Time.__dict__["_ns"].__set__
_set_time_clock_type: Final[Callable[[Time, ClockType], None]] = Time.__dict__[
    "_clock_type"
].__set__


def _new_time(
    ns: int,
    clock_type: ClockType,
    new: Callable[[type[Time]], Time] = _object_new,
    set_ns: Callable[[Time, int], None] = _set_time_ns,
    set_clock_type: Callable[[Time, ClockType], None] = _set_time_clock_type,
) -> Time:
    """A Time of ``ns`` in ``clock_type`` without any check (the internal hot path)."""
    self = new(Time)
    set_ns(self, ns)
    set_clock_type(self, clock_type)
    return self


def _time_checked(ns: int, clock_type: ClockType) -> Time:
    """A Time of ``ns`` in ``clock_type``, range-checked (negative or overflow: an error)."""
    if 0 <= ns <= _I64_MAX:
        return _new_time(ns, clock_type)
    raise _time_range_error(ns)


#: Fast constructors for evclock's own hot paths (rates, clocks, the kernel): exact integer
#: nanoseconds with no type or range check. Not public API: user code builds ``Time`` and
#: ``Duration`` through their constructors, which validate.
new_time = _new_time
new_duration = _new_duration
#: A Duration's integer nanoseconds, read in C (the sleep hot path; ``.nanoseconds`` is a
#: property, a Python frame).
duration_ns: Callable[[Duration], int] = operator.attrgetter("_ns")
