"""Tests of evclock.time._time: Duration, Time, clock domains, messages and conversions."""

from __future__ import annotations

import copy
import math
import operator
import pickle
import re
from dataclasses import FrozenInstanceError
from fractions import Fraction
from types import SimpleNamespace

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from evclock._errors import (
    ClockMismatchError,
    EvClockError,
    InvalidArgumentError,
    InvalidTypeError,
)
from evclock.time._time import (
    SIM,
    STEADY,
    SYSTEM,
    ClockType,
    Duration,
    DurationMsg,
    Time,
    TimeMsg,
    new_duration,
    new_time,
    to_nanoseconds,
    to_nonnegative_nanoseconds,
)

I64_MIN = -(2**63)
I64_MAX = 2**63 - 1
NS = 1_000_000_000

# Strategies -----------------------------------------------------------------------------------

any_ns = st.integers(min_value=I64_MIN, max_value=I64_MAX)
small_ns = st.integers(min_value=-(2**60), max_value=2**60)  # sums of three cannot overflow
time_ns = st.integers(min_value=0, max_value=I64_MAX)
domains = st.sampled_from(list(ClockType))
durations = any_ns.map(Duration.from_nanoseconds)
small_durations = small_ns.map(Duration.from_nanoseconds)
nonzero_durations = small_ns.filter(bool).map(Duration.from_nanoseconds)
finite_floats = st.floats(allow_nan=False, allow_infinity=False)


def mismatch_message(action: str) -> str:
    return re.escape(
        f"cannot {action}: times from different clocks are not comparable; "
        "convert explicitly with Time(nanoseconds=t.nanoseconds, clock_type=...)"
    )


# Clock types ----------------------------------------------------------------------------------


def test_clock_types() -> None:
    assert (SIM, SYSTEM, STEADY) == (ClockType.SIM, ClockType.SYSTEM, ClockType.STEADY)
    assert [c.value for c in ClockType] == ["sim", "system", "steady"]


def test_public_names() -> None:
    import evclock.time._time as mod

    assert set(mod.__all__) == {
        "ClockType",
        "SIM",
        "SYSTEM",
        "STEADY",
        "Duration",
        "Time",
        "TimeMsg",
        "DurationMsg",
    }
    for name in mod.__all__:
        assert getattr(mod, name).__doc__ or name in {"SIM", "SYSTEM", "STEADY"}


def test_errors_are_evclock_and_builtin_errors() -> None:
    with pytest.raises(ValueError, match="NaN") as info:
        Duration(math.nan)
    assert isinstance(info.value, EvClockError)
    with pytest.raises(TypeError):
        Duration("1")  # type: ignore[arg-type]


# Duration construction ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seconds", "nanoseconds", "expected"),
    [
        (0, 0, 0),
        (1, 0, NS),
        (1.5, 0, 1_500_000_000),
        (-1.5, 0, -1_500_000_000),
        (0.1, 0, 100_000_000),
        (1 / 240, 0, 4_166_667),
        (2, 5, 2 * NS + 5),
        (0.5, -1, 499_999_999),
        (0, I64_MAX, I64_MAX),
        (0, I64_MIN, I64_MIN),
        (9_223_372_036, 854_775_807, I64_MAX),
    ],
)
def test_duration_construction(seconds: float, nanoseconds: int, expected: int) -> None:
    d = Duration(seconds, nanoseconds)
    assert d.nanoseconds == expected
    assert type(d.nanoseconds) is int
    assert Duration(seconds=seconds, nanoseconds=nanoseconds) == d


def test_duration_int_seconds_are_exact() -> None:
    # 9_000_000_000 s as a float would be exact too, but huge ints must not go through floats
    assert Duration(9_223_372_035).nanoseconds == 9_223_372_035 * NS
    assert Duration(-9_223_372_036).nanoseconds == -9_223_372_036 * NS


@given(finite_floats.filter(lambda x: abs(x) < 9e9))
def test_duration_float_seconds_round_to_nearest(x: float) -> None:
    assert Duration(x).nanoseconds == round(x * 1e9)
    assert Duration.from_seconds(x) == Duration(x)


@given(any_ns)
def test_from_nanoseconds_is_exact(n: int) -> None:
    d = Duration.from_nanoseconds(n)
    assert d.nanoseconds == n
    assert Duration(nanoseconds=n) == d
    assert new_duration(n) == d
    assert d.seconds == n / NS


def test_from_seconds_accepts_int() -> None:
    assert Duration.from_seconds(3).nanoseconds == 3 * NS


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (math.nan, "Duration seconds must be a number, got NaN"),
        (math.inf, "Duration seconds must be finite, got inf"),
        (-math.inf, "Duration seconds must be finite, got -inf"),
    ],
)
def test_duration_rejects_nan_and_inf(value: float, message: str) -> None:
    with pytest.raises(InvalidArgumentError, match=re.escape(message)):
        Duration(value)
    with pytest.raises(InvalidArgumentError, match=re.escape(message)):
        Duration.from_seconds(value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"seconds": True}, "Duration seconds must be an int or a float, got bool"),
        ({"seconds": "1"}, "Duration seconds must be an int or a float, got str"),
        ({"seconds": None}, "Duration seconds must be an int or a float, got NoneType"),
        ({"nanoseconds": 1.0}, "Duration nanoseconds must be an int, got float"),
        ({"nanoseconds": False}, "Duration nanoseconds must be an int, got bool"),
        ({"nanoseconds": "5"}, "Duration nanoseconds must be an int, got str"),
    ],
)
def test_duration_rejects_bad_types(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(InvalidTypeError, match=re.escape(message)):
        Duration(**kwargs)  # type: ignore[arg-type]


def test_duration_of_duration_has_a_hint() -> None:
    with pytest.raises(InvalidTypeError, match=re.escape("pass nanoseconds=d.nanoseconds")):
        Duration(Duration(1))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("seconds", "nanoseconds"),
    [
        (0, I64_MAX + 1),
        (0, I64_MIN - 1),
        (9_223_372_037, 0),
        (-9_223_372_037, 0),
        (9_223_372_036, 854_775_808),
        (1e10, 0),
        (-1e10, 0),
        (1e300, 0),
    ],
)
def test_duration_overflow(seconds: float, nanoseconds: int) -> None:
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(seconds, nanoseconds)


def test_from_nanoseconds_validates() -> None:
    with pytest.raises(InvalidTypeError, match="must be an int, got float"):
        Duration.from_nanoseconds(1.5)  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration.from_nanoseconds(2**63)


def test_numpy_scalars_are_accepted() -> None:
    np = pytest.importorskip("numpy")
    assert Duration(np.float64(0.25)).nanoseconds == 250_000_000
    assert Duration(np.int64(3)).nanoseconds == 3 * NS
    assert Duration(nanoseconds=np.int64(7)).nanoseconds == 7
    assert (Duration(1) * np.int32(3)).nanoseconds == 3 * NS
    assert to_nanoseconds(np.float32(0.5), "x") == 500_000_000
    assert to_nanoseconds(np.int16(2), "x") == 2 * NS


# Duration arithmetic --------------------------------------------------------------------------


@given(small_durations, small_durations, small_durations)
def test_addition_is_associative_and_commutative(a: Duration, b: Duration, c: Duration) -> None:
    assert (a + b) + c == a + (b + c)
    assert a + b == b + a
    assert (a + b).nanoseconds == a.nanoseconds + b.nanoseconds
    assert a + Duration() == a
    assert a - b == a + (-b)
    assert (a - b) + b == a


@given(durations, durations)
def test_addition_is_exact_or_overflows(a: Duration, b: Duration) -> None:
    total = a.nanoseconds + b.nanoseconds
    if I64_MIN <= total <= I64_MAX:
        assert (a + b).nanoseconds == total
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            a + b


@given(durations)
def test_neg_pos_abs(d: Duration) -> None:
    n = d.nanoseconds
    assert +d is d
    if n == I64_MIN:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            d.__neg__()
        with pytest.raises(InvalidArgumentError, match="overflows"):
            abs(d)
    else:
        assert (-d).nanoseconds == -n
        assert (-d).__neg__() == d
        assert abs(d).nanoseconds == abs(n)
        assert abs(d) >= Duration()
        assert abs(-d) == abs(d)


@given(small_durations, st.integers(min_value=-100, max_value=100))
def test_multiplication_by_int_is_exact(d: Duration, k: int) -> None:
    product = d.nanoseconds * k
    if I64_MIN <= product <= I64_MAX:
        assert (d * k).nanoseconds == product
        assert k * d == d * k
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            d * k


@given(
    st.integers(min_value=-(2**53), max_value=2**53),
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
)
def test_multiplication_by_float_rounds_exactly(n: int, x: float) -> None:
    exact = Fraction(n) * Fraction(x)
    expected = round(exact)  # Fraction rounding: nearest, ties to even
    if I64_MIN <= expected <= I64_MAX:
        assert (Duration(nanoseconds=n) * x).nanoseconds == expected
        assert (x * Duration(nanoseconds=n)).nanoseconds == expected
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            Duration(nanoseconds=n) * x


@given(any_ns, st.integers(min_value=-(10**12), max_value=10**12).filter(bool))
def test_division_by_int_rounds_half_even(n: int, k: int) -> None:
    expected = round(Fraction(n, k))
    if I64_MIN <= expected <= I64_MAX:
        assert (Duration(nanoseconds=n) / k).nanoseconds == expected
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            Duration(nanoseconds=n) / k


@given(small_ns, finite_floats.filter(lambda x: x != 0 and abs(x) > 1e-6))
def test_division_by_float_rounds_exactly(n: int, x: float) -> None:
    expected = round(Fraction(n) / Fraction(x))
    if I64_MIN <= expected <= I64_MAX:
        assert (Duration(nanoseconds=n) / x).nanoseconds == expected
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            Duration(nanoseconds=n) / x


def test_division_examples() -> None:
    assert (Duration(nanoseconds=5) / 2).nanoseconds == 2  # 2.5 -> 2 (ties to even)
    assert (Duration(nanoseconds=7) / 2).nanoseconds == 4  # 3.5 -> 4
    assert (Duration(nanoseconds=-5) / 2).nanoseconds == -2
    assert (Duration(nanoseconds=5) / -2).nanoseconds == -2
    assert (Duration(nanoseconds=10) / 3).nanoseconds == 3
    assert (Duration(1) / 240).nanoseconds == 4_166_667
    assert (Duration(1) / 0.5).nanoseconds == 2 * NS
    assert (Duration(3) * 0.5).nanoseconds == 1_500_000_000
    assert Duration(3) / Duration(2) == 1.5
    assert Duration(-3) // Duration(2) == -2
    assert Duration(-3) % Duration(2) == Duration(1)
    assert Duration(nanoseconds=7) // 2 == Duration(nanoseconds=3)
    assert Duration(nanoseconds=-7) // 2 == Duration(nanoseconds=-4)


@given(small_durations, nonzero_durations)
def test_duration_division_identities(a: Duration, b: Duration) -> None:
    q = a // b
    r = a % b
    assert type(q) is int
    assert type(r) is Duration
    assert divmod(a, b) == (q, r)
    assert b * q + r == a
    assert q == a.nanoseconds // b.nanoseconds
    assert r.nanoseconds == a.nanoseconds % b.nanoseconds
    ratio = a / b
    assert type(ratio) is float
    assert ratio == a.nanoseconds / b.nanoseconds


@pytest.mark.parametrize(
    "operation",
    [
        lambda d: d / 0,
        lambda d: d / 0.0,
        lambda d: d / Duration(),
        lambda d: d // Duration(),
        lambda d: d // 0,
        lambda d: d % Duration(),
        lambda d: divmod(d, Duration()),
    ],
)
def test_division_by_zero(operation: object) -> None:
    with pytest.raises(InvalidArgumentError, match="zero"):
        operation(Duration(1))  # type: ignore[operator]


@pytest.mark.parametrize(("x", "text"), [(math.nan, "NaN"), (math.inf, "inf"), (-math.inf, "-inf")])
def test_scaling_by_nan_or_inf(x: float, text: str) -> None:
    with pytest.raises(InvalidArgumentError, match=f"^cannot multiply a Duration by {text}$"):
        Duration(1) * x
    with pytest.raises(InvalidArgumentError, match=f"^cannot multiply a Duration by {text}$"):
        x * Duration(1)
    with pytest.raises(InvalidArgumentError, match=f"^cannot divide a Duration by {text}$"):
        Duration(1) / x


def test_scaling_overflow() -> None:
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(nanoseconds=I64_MAX) * 2
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(1) * 1e300
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(1) / 1e-300
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(nanoseconds=I64_MIN) / -1
    with pytest.raises(InvalidArgumentError, match="overflows"):
        Duration(nanoseconds=I64_MIN) // -1


@pytest.mark.parametrize(
    ("operation", "message"),
    [
        (lambda d: d + 1, "unsupported operand types for +: Duration and int; convert"),
        (lambda d: 1.5 + d, "unsupported operand types for +: float and Duration; convert"),
        (lambda d: sum([d, d]), "to sum Durations use sum(durations, Duration())"),
        (lambda d: d - 1, "unsupported operand types for -: Duration and int"),
        (lambda d: 1 - d, "unsupported operand types for -: int and Duration"),
        (lambda d: d - Time(1), "a Time cannot be subtracted from a Duration"),
        (lambda d: d * d, "two Durations cannot be multiplied"),
        (lambda d: d * True, "unsupported operand types for *: Duration and bool"),
        (lambda d: d / True, "unsupported operand types for /: Duration and bool"),
        (lambda d: 1 / d, "for a frequency use 1 / d.seconds"),
        (lambda d: d // 0.5, "use d / x"),
        (lambda d: d % 2, "the modulus must be a Duration"),
        (lambda d: divmod(d, 2), "the divisor must be a Duration"),
        (lambda d: d < 1, "unsupported operand types for <: Duration and int"),
        (lambda d: d >= 0.5, "compare with a Duration, or use d.seconds"),
        (lambda d: d <= Time(1), "unsupported operand types for <=: Duration and Time"),
    ],
)
def test_duration_mixed_type_errors(operation: object, message: str) -> None:
    with pytest.raises(InvalidTypeError, match=re.escape(message)):
        operation(Duration(1))  # type: ignore[operator]


@pytest.mark.parametrize(
    "operation",
    [
        lambda d: d + "1",
        lambda d: d * "1",
        lambda d: "1" * d,
        lambda d: d / "1",
        lambda d: d // "1",
        lambda d: d % "1",
        lambda d: d > "1",
        lambda d: d * Time(1),
    ],
)
def test_duration_unsupported_types_raise_type_error(operation: object) -> None:
    with pytest.raises(TypeError):
        operation(Duration(1))  # type: ignore[operator]


def test_sum_with_a_duration_start() -> None:
    assert sum([Duration(1), Duration(2)], Duration()) == Duration(3)


# Duration ordering, equality, hashing, immutability ---------------------------------------------


def assert_compare_alike(a: object, b: object, x: int, y: int) -> None:
    """Each of the six comparisons of ``a`` and ``b`` answers as for ``x`` and ``y``."""
    for compare in (operator.lt, operator.le, operator.gt, operator.ge, operator.eq, operator.ne):
        assert compare(a, b) == compare(x, y), compare


@given(durations, durations)
def test_duration_ordering_matches_nanoseconds(a: Duration, b: Duration) -> None:
    x, y = a.nanoseconds, b.nanoseconds
    assert_compare_alike(a, b, x, y)
    assert sorted([a, b]) == [Duration(nanoseconds=v) for v in sorted([x, y])]


@given(any_ns)
def test_duration_hash_and_equality(n: int) -> None:
    a, b = Duration(nanoseconds=n), new_duration(n)
    assert a == b
    assert hash(a) == hash(b)
    assert len({a, b}) == 1
    assert bool(a) == (n != 0)


def test_duration_not_equal_to_numbers() -> None:
    assert Duration(1) != 1
    assert Duration(0) != 0
    assert Duration(1) != NS
    assert Duration(1) != Time(1)
    assert not bool(Duration())
    assert bool(Duration(nanoseconds=-1))


def test_duration_is_immutable() -> None:
    d = Duration(1)
    with pytest.raises(AttributeError, match="immutable"):
        d._ns = 5
    with pytest.raises(AttributeError, match="immutable"):
        d.foo = 5  # type: ignore[attr-defined]
    with pytest.raises(AttributeError, match="immutable"):
        del d._ns
    assert not hasattr(d, "__dict__")
    assert d.nanoseconds == NS


@given(durations)
def test_duration_pickle_and_copy(d: Duration) -> None:
    assert pickle.loads(pickle.dumps(d)) == d
    assert copy.copy(d) is d
    assert copy.deepcopy(d) is d


@pytest.mark.parametrize(
    ("d", "text", "representation"),
    [
        (Duration(1.5), "1.500000000 s", "Duration(nanoseconds=1500000000)"),
        (Duration(-1.5), "-1.500000000 s", "Duration(nanoseconds=-1500000000)"),
        (Duration(nanoseconds=-1), "-0.000000001 s", "Duration(nanoseconds=-1)"),
        (Duration(), "0.000000000 s", "Duration(nanoseconds=0)"),
        (
            Duration(nanoseconds=I64_MIN),
            "-9223372036.854775808 s",
            "Duration(nanoseconds=-9223372036854775808)",
        ),
    ],
)
def test_duration_str_and_repr(d: Duration, text: str, representation: str) -> None:
    assert str(d) == text
    assert repr(d) == representation
    assert eval(repr(d)) == d


@given(durations)
def test_duration_repr_round_trips(d: Duration) -> None:
    assert eval(repr(d)) == d


# Duration messages ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("ns", "sec", "nanosec"),
    [
        (0, 0, 0),
        (1_500_000_000, 1, 500_000_000),
        (-1_500_000_000, -2, 500_000_000),
        (-1, -1, 999_999_999),
        (-NS, -1, 0),
        ((2**31 - 1) * NS + NS - 1, 2**31 - 1, NS - 1),
        (-(2**31) * NS, -(2**31), 0),
    ],
)
def test_duration_to_msg(ns: int, sec: int, nanosec: int) -> None:
    msg = Duration(nanoseconds=ns).to_msg()
    assert msg == DurationMsg(sec=sec, nanosec=nanosec)
    assert Duration.from_msg(msg).nanoseconds == ns


@given(st.integers(min_value=-(2**31) * NS, max_value=2**31 * NS - 1))
def test_duration_msg_round_trip(n: int) -> None:
    d = Duration(nanoseconds=n)
    msg = d.to_msg()
    assert 0 <= msg.nanosec < NS
    assert -(2**31) <= msg.sec < 2**31
    assert msg.sec * NS + msg.nanosec == n
    assert Duration.from_msg(msg) == d
    assert Duration.from_msg({"sec": msg.sec, "nanosec": msg.nanosec}) == d
    assert Duration.from_msg(SimpleNamespace(sec=msg.sec, nanosec=msg.nanosec)) == d


@pytest.mark.parametrize("ns", [2**31 * NS, -(2**31) * NS - 1, I64_MAX, I64_MIN])
def test_duration_to_msg_outside_int32(ns: int) -> None:
    with pytest.raises(InvalidArgumentError, match="int32"):
        Duration(nanoseconds=ns).to_msg()


def test_msg_classes_are_frozen() -> None:
    msg = DurationMsg(sec=1, nanosec=2)
    with pytest.raises(FrozenInstanceError):
        msg.sec = 3  # type: ignore[misc]
    assert hash(msg) == hash(DurationMsg(1, 2))
    assert TimeMsg(1, 2) == TimeMsg(sec=1, nanosec=2)


@pytest.mark.parametrize(
    ("msg", "error", "message"),
    [
        ({"sec": 0, "nanosec": NS}, InvalidArgumentError, "'nanosec' must be in [0, 1000000000)"),
        ({"sec": 0, "nanosec": -1}, InvalidArgumentError, "'nanosec' must be in [0, 1000000000)"),
        ({"sec": 1.5, "nanosec": 0}, InvalidTypeError, "Duration message 'sec' must be an int"),
        ({"sec": 0, "nanosec": True}, InvalidTypeError, "'nanosec' must be an int, got bool"),
        ({"sec": 0}, InvalidTypeError, "expected a builtin_interfaces/Duration message"),
        (SimpleNamespace(sec=1), InvalidTypeError, "got SimpleNamespace"),
        (42, InvalidTypeError, "got int"),
        ({"sec": 2**40, "nanosec": 0}, InvalidArgumentError, "overflows"),
    ],
)
def test_duration_from_bad_msg(msg: object, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=re.escape(message)):
        Duration.from_msg(msg)


# Time ---------------------------------------------------------------------------------------


def test_time_construction() -> None:
    t = Time(12)
    assert t.nanoseconds == 12 * NS
    assert t.seconds == 12.0
    assert t.clock_type is SIM
    assert Time(1.5, 1, SYSTEM).nanoseconds == 1_500_000_001
    assert Time(nanoseconds=5, clock_type=STEADY).clock_type is STEADY
    assert Time(0, I64_MAX).nanoseconds == I64_MAX
    assert new_time(7, SYSTEM) == Time(nanoseconds=7, clock_type=SYSTEM)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"seconds": -1}, InvalidArgumentError, "Time must not be negative, got -1000000000 ns"),
        ({"nanoseconds": -1}, InvalidArgumentError, "Time must not be negative, got -1 ns"),
        ({"seconds": -1e-9}, InvalidArgumentError, "Time must not be negative"),
        ({"nanoseconds": I64_MAX + 1}, InvalidArgumentError, "Time overflows"),
        ({"seconds": 1e10}, InvalidArgumentError, "Time overflows"),
        ({"seconds": math.nan}, InvalidArgumentError, "Time seconds must be a number, got NaN"),
        ({"seconds": math.inf}, InvalidArgumentError, "Time seconds must be finite, got inf"),
        ({"seconds": True}, InvalidTypeError, "Time seconds must be an int or a float, got bool"),
        ({"seconds": "1"}, InvalidTypeError, "Time seconds must be an int or a float, got str"),
        ({"nanoseconds": 1.0}, InvalidTypeError, "Time nanoseconds must be an int, got float"),
        ({"clock_type": "sim"}, InvalidTypeError, "clock_type must be a ClockType"),
    ],
)
def test_time_bad_input(kwargs: dict[str, object], error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=re.escape(message)):
        Time(**kwargs)  # type: ignore[arg-type]


@given(time_ns, small_durations, domains)
def test_time_plus_duration_minus_time(n: int, d: Duration, domain: ClockType) -> None:
    t = Time(nanoseconds=n, clock_type=domain)
    total = n + d.nanoseconds
    if 0 <= total <= I64_MAX:
        later = t + d
        assert later.clock_type is domain
        assert later.nanoseconds == total
        assert d + t == later
        assert later - t == d
        assert (later - d) == t
    elif total < 0:
        with pytest.raises(InvalidArgumentError, match="must not be negative"):
            t + d
    else:
        with pytest.raises(InvalidArgumentError, match="overflows"):
            t + d


@given(time_ns, small_durations, domains)
def test_time_minus_duration_plus_duration(n: int, d: Duration, domain: ClockType) -> None:
    t = Time(nanoseconds=n, clock_type=domain)
    assume(0 <= n - d.nanoseconds <= I64_MAX)
    earlier = t - d
    assert earlier.nanoseconds == n - d.nanoseconds
    assert earlier + d == t
    assert t - earlier == d


@given(time_ns, time_ns, domains)
def test_time_difference(a: int, b: int, domain: ClockType) -> None:
    ta = Time(nanoseconds=a, clock_type=domain)
    tb = Time(nanoseconds=b, clock_type=domain)
    diff = ta - tb
    assert type(diff) is Duration
    assert diff.nanoseconds == a - b
    assert tb + diff == ta
    assert ta - ta == Duration()


@given(time_ns, time_ns, domains)
def test_time_ordering_matches_nanoseconds(a: int, b: int, domain: ClockType) -> None:
    ta = Time(nanoseconds=a, clock_type=domain)
    tb = Time(nanoseconds=b, clock_type=domain)
    assert_compare_alike(ta, tb, a, b)
    assert max(ta, tb).nanoseconds == max(a, b)


@given(time_ns, domains, domains)
def test_time_equality_and_hash_include_domain(n: int, d1: ClockType, d2: ClockType) -> None:
    t1 = Time(nanoseconds=n, clock_type=d1)
    t2 = new_time(n, d2)
    assert (t1 == t2) == (d1 is d2)
    assert (t1 != t2) == (d1 is not d2)
    if d1 is d2:
        assert hash(t1) == hash(t2)
        assert len({t1, t2}) == 1
    else:
        assert len({t1, t2}) == 2


def test_time_not_equal_to_other_types() -> None:
    assert Time(1) != 1
    assert Time(1) != Duration(1)
    assert Time(0) != 0


@pytest.mark.parametrize(
    ("a", "b"),
    [(SIM, SYSTEM), (SYSTEM, SIM), (SIM, STEADY), (STEADY, SYSTEM)],
)
def test_domain_mismatch_subtraction(a: ClockType, b: ClockType) -> None:
    ta, tb = Time(2, clock_type=a), Time(1, clock_type=b)
    action = f"subtract a {b.value} time from a {a.value} time"
    with pytest.raises(ClockMismatchError, match=mismatch_message(action)):
        ta - tb


def test_domain_mismatch_exact_message() -> None:
    expected = (
        "cannot subtract a system time from a sim time: times from different clocks are not "
        "comparable; convert explicitly with Time(nanoseconds=t.nanoseconds, clock_type=...)"
    )
    with pytest.raises(ClockMismatchError, match=f"^{re.escape(expected)}$"):
        Time(1, clock_type=SIM) - Time(1, clock_type=SYSTEM)


@pytest.mark.parametrize(
    "compare",
    [
        lambda a, b: a < b,
        lambda a, b: a <= b,
        lambda a, b: a > b,
        lambda a, b: a >= b,
    ],
)
def test_domain_mismatch_ordering(compare: object) -> None:
    ta, tb = Time(1, clock_type=SIM), Time(1, clock_type=STEADY)
    message = mismatch_message("compare a sim time with a steady time")
    with pytest.raises(ClockMismatchError, match=f"^{message}$"):
        compare(ta, tb)  # type: ignore[operator]
    message = mismatch_message("compare a steady time with a sim time")
    with pytest.raises(ClockMismatchError, match=f"^{message}$"):
        compare(tb, ta)  # type: ignore[operator]


def test_explicit_domain_conversion() -> None:
    t = Time(5, clock_type=SYSTEM)
    converted = Time(nanoseconds=t.nanoseconds, clock_type=SIM)
    assert converted - Time(2) == Duration(3)


@pytest.mark.parametrize(
    ("operation", "error", "message"),
    [
        (lambda t: t + t, InvalidTypeError, "two Times cannot be added"),
        (lambda t: t + 1, InvalidTypeError, "unsupported operand types for +: Time and int"),
        (lambda t: 1.0 + t, InvalidTypeError, "unsupported operand types for +: float and Time"),
        (lambda t: t - 1, InvalidTypeError, "unsupported operand types for -: Time and int"),
        (lambda t: 1 - t, InvalidTypeError, "unsupported operand types for -: int and Time"),
        (lambda t: t < 1, InvalidTypeError, "compare with a Time, or use t.seconds"),
        (lambda t: t < Duration(1), InvalidTypeError, "for <: Time and Duration"),
        (lambda t: t - Duration(2), InvalidArgumentError, "Time must not be negative"),
        (lambda t: t + Duration(nanoseconds=I64_MAX), InvalidArgumentError, "Time overflows"),
    ],
)
def test_time_bad_arithmetic(operation: object, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=re.escape(message)):
        operation(Time(1))  # type: ignore[operator]


@pytest.mark.parametrize(
    "operation",
    [lambda t: t * 2, lambda t: t / 2, lambda t: t + "x", lambda t: -t, lambda t: t > "x"],
)
def test_time_unsupported_operations(operation: object) -> None:
    with pytest.raises(TypeError):
        operation(Time(1))  # type: ignore[operator]


def test_time_is_immutable() -> None:
    t = Time(1)
    with pytest.raises(AttributeError, match="immutable"):
        t._ns = 5
    with pytest.raises(AttributeError, match="immutable"):
        t._clock_type = SYSTEM
    assert t == Time(1)


@given(time_ns, domains)
def test_time_pickle_copy_repr(n: int, domain: ClockType) -> None:
    t = Time(nanoseconds=n, clock_type=domain)
    assert pickle.loads(pickle.dumps(t)) == t
    assert copy.deepcopy(t) is t
    assert eval(repr(t)) == t


def test_time_str_and_repr() -> None:
    assert str(Time(12)) == "12.000000000 s (sim)"
    assert str(Time(nanoseconds=1, clock_type=SYSTEM)) == "0.000000001 s (system)"
    assert repr(Time(12)) == "Time(nanoseconds=12000000000, clock_type=ClockType.SIM)"
    assert repr(Time(0, 3, STEADY)) == "Time(nanoseconds=3, clock_type=ClockType.STEADY)"


# Time messages ------------------------------------------------------------------------------


def test_time_msg_epoch_like() -> None:
    t = Time(1_700_000_000, 123_456_789, SYSTEM)
    msg = t.to_msg()
    assert msg == TimeMsg(sec=1_700_000_000, nanosec=123_456_789)
    assert Time.from_msg(msg, SYSTEM) == t
    assert Time.from_msg(msg) == Time(1_700_000_000, 123_456_789)
    assert Time.from_msg(msg).clock_type is SIM


@given(st.integers(min_value=0, max_value=2**31 * NS - 1), domains)
def test_time_msg_round_trip(n: int, domain: ClockType) -> None:
    t = Time(nanoseconds=n, clock_type=domain)
    msg = t.to_msg()
    assert 0 <= msg.nanosec < NS
    assert 0 <= msg.sec < 2**31
    assert Time.from_msg(msg, domain) == t
    assert Time.from_msg({"sec": msg.sec, "nanosec": msg.nanosec}, domain) == t
    assert Time.from_msg(SimpleNamespace(sec=msg.sec, nanosec=msg.nanosec), domain) == t


@given(st.integers(min_value=1_600_000_000 * NS, max_value=1_800_000_000 * NS))
def test_epoch_like_time_msg_round_trip(n: int) -> None:
    t = Time(nanoseconds=n, clock_type=SYSTEM)
    assert Time.from_msg(t.to_msg(), SYSTEM) == t


def test_time_to_msg_outside_int32() -> None:
    with pytest.raises(InvalidArgumentError, match="int32"):
        Time(2**31).to_msg()


@pytest.mark.parametrize(
    ("msg", "error", "message"),
    [
        ({"sec": -1, "nanosec": 0}, InvalidArgumentError, "Time must not be negative"),
        ({"sec": 0, "nanosec": NS}, InvalidArgumentError, "Time message 'nanosec' must be in"),
        ({"sec": "1", "nanosec": 0}, InvalidTypeError, "Time message 'sec' must be an int"),
        (object(), InvalidTypeError, "expected a builtin_interfaces/Time message"),
    ],
)
def test_time_from_bad_msg(msg: object, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=re.escape(message)):
        Time.from_msg(msg)


# to_nanoseconds ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (0.5, 500_000_000),
        (-0.5, -500_000_000),
        (2, 2 * NS),
        (-2, -2 * NS),
        (0, 0),
        (1e-9, 1),
        (Duration(nanoseconds=-7), -7),
        (10**12, 10**21),  # no range check: callers decide
    ],
)
def test_to_nanoseconds(value: object, expected: int) -> None:
    result = to_nanoseconds(value, "sleep duration")
    assert result == expected
    assert type(result) is int


@given(finite_floats.filter(lambda x: abs(x) < 1e290))
def test_to_nanoseconds_float(x: float) -> None:
    assert to_nanoseconds(x, "x") == round(x * 1e9)


@given(any_ns)
def test_to_nanoseconds_duration(n: int) -> None:
    assert to_nanoseconds(Duration(nanoseconds=n), "x") == n


TYPE_MESSAGE = "sleep duration must be seconds (int or float) or a Duration, got "


@pytest.mark.parametrize(
    ("value", "error", "message"),
    [
        ("1", InvalidTypeError, TYPE_MESSAGE + "str"),
        (True, InvalidTypeError, TYPE_MESSAGE + "bool"),
        (None, InvalidTypeError, TYPE_MESSAGE + "NoneType"),
        (Time(1), InvalidTypeError, TYPE_MESSAGE + "Time"),
        (math.nan, InvalidArgumentError, "sleep duration must be a number, got NaN"),
        (math.inf, InvalidArgumentError, "sleep duration must be finite, got inf"),
        (-math.inf, InvalidArgumentError, "sleep duration must be finite, got -inf"),
        (
            1e300,
            InvalidArgumentError,
            "sleep duration overflows: 1e+300 s is too large in nanoseconds",
        ),
    ],
)
def test_to_nanoseconds_errors(value: object, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        to_nanoseconds(value, "sleep duration")
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        to_nonnegative_nanoseconds(value, "sleep duration")


@pytest.mark.parametrize(
    ("value", "hint", "message"),
    [
        (-1, "", "timeout must not be negative, got -1"),
        (-0.5, "", "timeout must not be negative, got -0.5"),
        (
            Duration(nanoseconds=-3),
            "",
            "timeout must not be negative, got Duration(nanoseconds=-3)",
        ),
        (-2.0, "use None to wait forever", "timeout must not be negative, got -2.0; use None"),
    ],
)
def test_to_nonnegative_nanoseconds_rejects_negatives(
    value: object, hint: str, message: str
) -> None:
    assert to_nanoseconds(value, "timeout") < 0  # the plain conversion does not reject them
    with pytest.raises(InvalidArgumentError, match=f"^{re.escape(message)}"):
        to_nonnegative_nanoseconds(value, "timeout", hint)


def test_to_nonnegative_nanoseconds_exact_message_without_hint() -> None:
    with pytest.raises(InvalidArgumentError, match=r"^timeout must not be negative, got -1$"):
        to_nonnegative_nanoseconds(-1, "timeout")


@pytest.mark.parametrize(
    ("value", "expected"),
    [(0, 0), (0.0, 0), (-0.0, 0), (-1e-12, 0), (1.25, 1_250_000_000), (Duration(3), 3 * NS)],
)
def test_to_nonnegative_nanoseconds_accepts(value: object, expected: int) -> None:
    assert to_nonnegative_nanoseconds(value, "timeout") == expected
