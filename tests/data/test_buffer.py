"""Tests of TimeBuffer: exact, previous, nearest, linear and slerp lookups, bounds and errors."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evclock import (
    STEADY,
    ClockMismatchError,
    Duration,
    InvalidArgumentError,
    InvalidTypeError,
    Time,
)
from evclock.data import ExtrapolationError, TimeBuffer, TimeLookupError


def t(seconds: float) -> Time:
    return Time(seconds)


def filled(values: dict[float, object], **kwargs) -> TimeBuffer:
    buffer = TimeBuffer(100, **kwargs)
    for stamp, value in values.items():
        buffer.add(t(stamp), value)
    return buffer


def test_lookup_methods_on_a_vector_signal() -> None:
    buffer = filled({1.0: [0.0, 10.0], 2.0: [1.0, 20.0], 4.0: [3.0, 0.0]})
    np.testing.assert_allclose(buffer.at(t(1.5)), [0.5, 15.0])
    np.testing.assert_allclose(buffer.at(t(3.0)), [2.0, 10.0])
    np.testing.assert_array_equal(buffer.at(t(2.0), "exact"), [1.0, 20.0])
    np.testing.assert_array_equal(buffer.at(t(3.9), "previous"), [1.0, 20.0])
    np.testing.assert_array_equal(buffer.at(t(3.1), "nearest"), [3.0, 0.0])
    np.testing.assert_array_equal(buffer.at(t(3.0), "nearest"), [1.0, 20.0])  # tie: earlier
    np.testing.assert_array_equal(buffer.at(t(4.0)), [3.0, 0.0])
    assert buffer.shape == (2,)
    assert (buffer.oldest, buffer.newest) == (t(1.0), t(4.0))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 10**6), min_size=2, max_size=30, unique=True),
    st.lists(st.floats(-1e3, 1e3), min_size=30, max_size=30),
    st.lists(st.floats(0, 1), min_size=1, max_size=20),
)
def test_vectorised_lookups_match_a_sample_by_sample_reference(stamps, values, fractions) -> None:
    stamps.sort()
    buffer = TimeBuffer(64)
    for stamp, value in zip(stamps, values, strict=False):
        buffer.add(Time(0, stamp), value)
    queries = np.array(
        [stamps[0] + round(f * (stamps[-1] - stamps[0])) for f in fractions], dtype=np.int64
    )
    linear = buffer.at_many(queries)
    np.testing.assert_allclose(
        linear, np.interp(queries, stamps, values[: len(stamps)]), rtol=1e-9, atol=1e-6
    )
    for q, got_prev, got_near in zip(
        queries,
        buffer.at_many(queries, "previous"),
        buffer.at_many(queries, "nearest"),
        strict=True,
    ):
        before = max(i for i, s in enumerate(stamps) if s <= q)
        assert got_prev == values[before]
        nearest = min(range(len(stamps)), key=lambda i: (abs(stamps[i] - q), stamps[i]))
        assert got_near == values[nearest]
        assert buffer.at(Time(0, int(q)), "previous") == values[before]  # the scalar path
        assert buffer.at(Time(0, int(q)), "nearest") == values[nearest]
        assert buffer.at(Time(0, int(q))) == pytest.approx(linear[list(queries).index(q)])


def quat_z(angle: float) -> list[float]:
    return [0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)]


def test_slerp_interpolates_rotations_along_the_shorter_arc() -> None:
    buffer = TimeBuffer(10, interpolation="slerp")
    buffer.add(t(0), quat_z(0.0))
    buffer.add(t(1), quat_z(math.pi / 2))
    buffer.add(t(2), [-q for q in quat_z(math.pi / 2 + 0.2)])  # same rotation, other sign
    np.testing.assert_allclose(buffer.at(t(0.5)), quat_z(math.pi / 4), atol=1e-12)
    np.testing.assert_allclose(buffer.at(t(0.25)), quat_z(math.pi / 8), atol=1e-12)
    halfway = buffer.at(t(1.5))  # 0.1 rad further, not the long way round
    assert abs(float(np.dot(halfway, quat_z(math.pi / 2 + 0.1)))) == pytest.approx(1.0)
    many = buffer.at_many([t(0.1 * k) for k in range(21)])
    np.testing.assert_allclose(np.linalg.norm(many, axis=1), 1.0)


def test_slerp_needs_unit_quaternions() -> None:
    buffer = TimeBuffer(10, interpolation="slerp")
    with pytest.raises(
        InvalidArgumentError,
        match=re.escape(
            "TimeBuffer: quaternion [0.0, 0.0, 0.0, 2.0] has norm 2, not 1; normalise it before "
            "adding (q / np.linalg.norm(q))"
        ),
    ):
        buffer.add(t(0), [0, 0, 0, 2])
    with pytest.raises(InvalidArgumentError, match=r"holds quaternions \(x, y, z, w\) of shape"):
        buffer.add(t(0), [0, 0, 1])
    linear = filled({0.0: quat_z(0), 1.0: quat_z(1)})
    with pytest.raises(InvalidArgumentError, match="slerp needs a buffer made with interpol"):
        linear.at(t(0.5), "slerp")


def test_extrapolation_is_refused_beyond_the_limit() -> None:
    buffer = filled({1.0: 10.0, 2.0: 20.0}, name="odom")
    with pytest.raises(
        ExtrapolationError,
        match=re.escape(
            "odom: cannot answer at(2.500000000 s (sim)): it is 0.5 s after the newest sample "
            "2.000000000 s (sim), beyond max_extrapolation=0 s"
        ),
    ):
        buffer.at(t(2.5))
    with pytest.raises(ExtrapolationError, match=r"0\.25 s before the oldest sample"):
        buffer.at_many([t(1.5), t(0.75)])
    tolerant = filled({1.0: 10.0, 2.0: 20.0}, max_extrapolation=Duration(0.5))
    assert tolerant.at(t(2.5)) == pytest.approx(25.0)  # extends the last segment
    assert tolerant.at(t(0.5), "previous") == 10.0  # holds the end sample
    with pytest.raises(ExtrapolationError):
        tolerant.at(t(2.6))
    assert isinstance(ExtrapolationError("x"), LookupError)


def test_capacity_evicts_the_oldest_and_says_so() -> None:
    buffer = TimeBuffer(3)
    for k in range(20):  # many times the capacity: exercises compaction
        buffer.add(t(k), float(k))
    assert len(buffer) == 3
    assert buffer.evicted == 17
    np.testing.assert_array_equal(buffer.values(), [17.0, 18.0, 19.0])
    np.testing.assert_array_equal(buffer.stamps(), [17 * 10**9, 18 * 10**9, 19 * 10**9])
    assert buffer.at(t(18.5)) == pytest.approx(18.5)
    with pytest.raises(ExtrapolationError, match=r"17 older samples were evicted \(capacity 3\)"):
        buffer.at(t(16))


def test_bad_samples_and_lookups_are_explained() -> None:
    buffer = filled({1.0: [1.0, 2.0]})
    with pytest.raises(
        InvalidArgumentError,
        match=re.escape(
            "TimeBuffer: samples must be added in increasing stamp order: 1.000000000 s (sim) is "
            "not after the newest 1.000000000 s (sim)"
        ),
    ):
        buffer.add(t(1.0), [0.0, 0.0])
    with pytest.raises(InvalidArgumentError, match=r"every sample must have shape \(2,\), got"):
        buffer.add(t(2.0), [1.0])
    with pytest.raises(InvalidArgumentError, match="sample is not finite"):
        buffer.add(t(2.0), [math.nan, 0.0])
    with pytest.raises(InvalidTypeError, match="a sample must be a number or a numeric array"):
        buffer.add(t(2.0), "fast")
    with pytest.raises(ClockMismatchError, match="is a steady time but the buffer holds sim"):
        buffer.add(Time(3, clock_type=STEADY), [0.0, 0.0])
    with pytest.raises(ClockMismatchError):
        buffer.at(Time(1, clock_type=STEADY))
    with pytest.raises(TimeLookupError, match=r"no sample stamped exactly 1\.500000000 s"):
        filled({1.0: 1.0, 2.0: 2.0}).at(t(1.5), "exact")
    with pytest.raises(TimeLookupError, match="the buffer is empty"):
        TimeBuffer(4).at(t(0))
    with pytest.raises(InvalidTypeError, match=r"convert seconds with np.round\(seconds \* 1e9"):
        buffer.at_many(np.array([1.0]))
    with pytest.raises(InvalidArgumentError, match="interpolation must be one of 'exact'"):
        TimeBuffer(4, interpolation="cubic")  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="capacity must be a positive int, got 0"):
        TimeBuffer(0)
    with pytest.raises(InvalidArgumentError, match="max_extrapolation must not be negative"):
        TimeBuffer(4, max_extrapolation=-1.0)
