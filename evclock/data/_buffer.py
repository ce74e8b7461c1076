"""A bounded, time-indexed buffer of stamped numeric samples: "the value at time t".

Samples (numpy arrays of one fixed shape, or numbers) are added in increasing stamp order and
kept in two numpy arrays (integer-nanosecond stamps, float64 values), so a batch of lookups is
a handful of vectorised numpy operations (``np.searchsorted`` plus arithmetic). When full, the
oldest sample is evicted. Lookups:

* ``"exact"``: the sample stamped exactly ``t``;
* ``"previous"``: the latest sample at or before ``t`` (zero-order hold);
* ``"nearest"``: the sample with the nearest stamp (the earlier one on a tie);
* ``"linear"``: linear interpolation between the samples around ``t``;
* ``"slerp"``: spherical linear interpolation of unit quaternions ``(x, y, z, w)`` (the
  ROS/PyBullet order), along the shorter arc.

A ``t`` outside ``[oldest, newest]`` is answered only within ``max_extrapolation`` (default
0: never), by holding the end sample (``previous``/``nearest``) or extending the end segment
(``linear``/``slerp``); beyond it raises :class:`ExtrapolationError`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final, Literal, get_args

import numpy as np
import numpy.typing as npt

from evclock._errors import (
    ClockMismatchError,
    ExtrapolationError,
    InvalidArgumentError,
    InvalidTypeError,
    TimeLookupError,
)
from evclock.time._time import (
    ClockType,
    Duration,
    Time,
    new_duration,
    new_time,
    to_nonnegative_nanoseconds,
)

__all__ = ["Interpolation", "TimeBuffer"]

Interpolation = Literal["exact", "previous", "nearest", "linear", "slerp"]
"""How :meth:`TimeBuffer.at` answers between samples: ``"exact"`` (a sample stamped exactly t),
``"previous"`` (zero-order hold), ``"nearest"``, ``"linear"`` or ``"slerp"`` (unit quaternions
``(x, y, z, w)``, shorter arc)."""
_METHODS: Final = get_args(Interpolation)
_UNIT_TOLERANCE: Final = 1e-6


class TimeBuffer:
    """A bounded buffer of stamped samples answering ``at(t)`` (see the module docstring).

    Args:
        capacity: samples kept; the oldest is evicted beyond it (counted in ``evicted``).
        interpolation: the default lookup method (``"linear"``).
        max_extrapolation: seconds or a :class:`Duration` a lookup may lie beyond the oldest
            or newest sample (default 0).
        clock_type: the stamps' clock domain (default: the first sample's).
        name: used in error messages.
    """

    def __init__(
        self,
        capacity: int,
        *,
        interpolation: Interpolation = "linear",
        max_extrapolation: float | Duration = 0,
        clock_type: ClockType | None = None,
        name: str = "TimeBuffer",
    ) -> None:
        if type(capacity) is not int or capacity < 1:
            raise InvalidArgumentError(f"capacity must be a positive int, got {capacity!r}")
        self._check_method(interpolation)
        if clock_type is not None and type(clock_type) is not ClockType:
            raise InvalidTypeError(
                f"clock_type must be a ClockType (SIM, SYSTEM, STEADY), got "
                f"{type(clock_type).__name__}"
            )
        self.capacity = capacity
        self.interpolation: Interpolation = interpolation
        self.max_extrapolation = new_duration(
            to_nonnegative_nanoseconds(max_extrapolation, "max_extrapolation")
        )
        self.name = name
        self._clock_type = clock_type
        self._stamps = np.empty(0, dtype=np.int64)
        self._values = np.empty(0, dtype=np.float64)
        self._shape: tuple[int, ...] | None = None
        self._start = 0
        self._end = 0
        self.evicted = 0
        """Samples evicted because the buffer was full."""

    @staticmethod
    def _check_method(method: object) -> None:
        if method not in _METHODS:
            raise InvalidArgumentError(
                f"interpolation must be one of {', '.join(map(repr, _METHODS))}, got {method!r}"
            )

    # -- contents --

    def __len__(self) -> int:
        return self._end - self._start

    @property
    def clock_type(self) -> ClockType | None:
        """The stamps' clock domain (None until given or set by the first sample)."""
        return self._clock_type

    @property
    def shape(self) -> tuple[int, ...] | None:
        """The shape of every sample (None before the first)."""
        return self._shape

    @property
    def oldest(self) -> Time | None:
        """The oldest stamp kept, or None if empty."""
        return self._time(int(self._stamps[self._start])) if len(self) else None

    @property
    def newest(self) -> Time | None:
        """The newest stamp, or None if empty."""
        return self._time(int(self._stamps[self._end - 1])) if len(self) else None

    def _time(self, ns: int) -> Time:
        assert self._clock_type is not None
        return new_time(ns, self._clock_type)

    def stamps(self) -> npt.NDArray[np.int64]:
        """The kept stamps in nanoseconds, oldest first (a read-only view)."""
        view = self._stamps[self._start : self._end]
        view.flags.writeable = False
        return view

    def values(self) -> npt.NDArray[np.float64]:
        """The kept samples, oldest first (a read-only view, shape ``(len, *shape)``)."""
        view = self._values[self._start : self._end]
        view.flags.writeable = False
        return view

    def _check_domain(self, stamp: Time, what: str) -> None:
        if self._clock_type is not None and stamp.clock_type is not self._clock_type:
            raise ClockMismatchError(
                f"{self.name}: {what} {stamp} is a {stamp.clock_type.value} time but the buffer "
                f"holds {self._clock_type.value} stamps; sim and wall stamps are mixed up"
            )

    def add(self, stamp: Time, value: npt.ArrayLike) -> None:
        """Append a sample; stamps must increase strictly.

        Raises:
            ClockMismatchError: ``stamp`` is of another clock domain than the buffer's.
            InvalidArgumentError: a stamp not after the newest, a value of another shape, a
                non-finite value, or (``"slerp"`` buffers) not a unit quaternion.
        """
        if type(stamp) is not Time:
            raise InvalidTypeError(
                f"{self.name}: stamp must be an evclock.Time, got {type(stamp).__name__}"
            )
        self._check_domain(stamp, "stamp")
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidTypeError(
                f"{self.name}: a sample must be a number or a numeric array, got "
                f"{type(value).__name__}"
            ) from None
        if self._shape is not None and array.shape != self._shape:
            raise InvalidArgumentError(
                f"{self.name}: every sample must have shape {self._shape}, got {array.shape}"
            )
        if not np.all(np.isfinite(array)):
            raise InvalidArgumentError(f"{self.name}: sample is not finite: {array!r}")
        if self.interpolation == "slerp":
            if array.shape != (4,):
                raise InvalidArgumentError(
                    f"{self.name}: a slerp buffer holds quaternions (x, y, z, w) of shape (4,), "
                    f"got shape {array.shape}"
                )
            norm = float(np.linalg.norm(array))
            if abs(norm - 1.0) > _UNIT_TOLERANCE:
                raise InvalidArgumentError(
                    f"{self.name}: quaternion {array.tolist()} has norm {norm:.9g}, not 1; "
                    "normalise it before adding (q / np.linalg.norm(q))"
                )
        ns = stamp.nanoseconds
        if len(self) and ns <= self._stamps[self._end - 1]:
            raise InvalidArgumentError(
                f"{self.name}: samples must be added in increasing stamp order: {stamp} is not "
                f"after the newest {self.newest}; reorder them first (e.g. through a "
                "synchroniser), or use one buffer per source"
            )
        if self._shape is None:
            self._shape = array.shape
            self._clock_type = stamp.clock_type
            self._stamps = np.empty(2 * self.capacity, dtype=np.int64)
            self._values = np.empty((2 * self.capacity, *array.shape), dtype=np.float64)
        if len(self) == self.capacity:
            self._start += 1
            self.evicted += 1
        if self._end == len(self._stamps):
            count = len(self)
            self._stamps[:count] = self._stamps[self._start : self._end]
            self._values[:count] = self._values[self._start : self._end]
            self._start, self._end = 0, count
        self._stamps[self._end] = ns
        self._values[self._end] = array
        self._end += 1

    # -- lookups --

    def at(self, t: Time, method: Interpolation | None = None) -> npt.NDArray[np.float64]:
        """The value at ``t`` (a new array of the samples' shape) by ``method``.

        Raises:
            ExtrapolationError: ``t`` lies further than ``max_extrapolation`` outside the
                kept samples.
            TimeLookupError: the buffer is empty, or ``"exact"`` found no sample stamped ``t``.
            ClockMismatchError: ``t`` is of another clock domain than the buffer's.
        """
        if type(t) is not Time:
            raise InvalidTypeError(
                f"{self.name}: t must be an evclock.Time, got {type(t).__name__}"
            )
        self._check_domain(t, "lookup time")
        method = self.interpolation if method is None else method
        if method == "slerp":
            result: npt.NDArray[np.float64] = self._lookup(
                np.array([t.nanoseconds], dtype=np.int64), method
            )[0]
            return result
        # One time: the same rules as _lookup, with Python scalars instead of numpy arrays.
        self._check_method(method)
        stamps, values = self._kept()
        ns, n = t.nanoseconds, len(stamps)
        limit = self.max_extrapolation.nanoseconds
        if not int(stamps[0]) - limit <= ns <= int(stamps[-1]) + limit:
            self._check_range(np.array([ns], dtype=np.int64), stamps)
        after = int(stamps.searchsorted(ns, side="right"))
        before = max(after - 1, 0)
        if method == "exact" and stamps[before] != ns:
            raise self._no_exact_sample(ns)
        if method in ("exact", "previous"):
            return _row(values, before)
        if method == "nearest":
            later = min(after, n - 1)
            return _row(values, later if stamps[later] - ns < ns - stamps[before] else before)
        if n == 1:
            return _row(values, 0)
        i0 = min(before, n - 2)
        s0, s1 = int(stamps[i0]), int(stamps[i0 + 1])
        linear: npt.NDArray[np.float64] = values[i0] + (ns - s0) / (s1 - s0) * (
            values[i0 + 1] - values[i0]
        )
        return linear

    def at_many(
        self, times: npt.ArrayLike | Sequence[Time], method: Interpolation | None = None
    ) -> npt.NDArray[np.float64]:
        """Values at many times at once, shape ``(len(times), *shape)``: vectorised ``at``.

        ``times`` is a sequence of :class:`Time` or an integer array of nanoseconds in the
        buffer's clock domain. Errors as :meth:`at` (for the first offending time).
        """
        if isinstance(times, Sequence) and len(times) and type(times[0]) is Time:
            stamps: list[int] = []
            for t in times:
                if type(t) is not Time:
                    raise InvalidTypeError(f"{self.name}: times mixes Time and {type(t).__name__}")
                self._check_domain(t, "lookup time")
                stamps.append(t.nanoseconds)
            ns = np.array(stamps, dtype=np.int64)
        else:
            array = np.asarray(times)
            if array.ndim != 1 or not (array.size == 0 or np.issubdtype(array.dtype, np.integer)):
                raise InvalidTypeError(
                    f"{self.name}: times must be a sequence of evclock.Time or a 1-D integer "
                    f"array of nanoseconds, got dtype {array.dtype} shape {array.shape}; "
                    "convert seconds with np.round(seconds * 1e9).astype(np.int64)"
                )
            ns = array.astype(np.int64, copy=False)
        return self._lookup(ns, method)

    def _lookup(
        self, ts: npt.NDArray[np.int64], method: Interpolation | None
    ) -> npt.NDArray[np.float64]:
        method = self.interpolation if method is None else method
        self._check_method(method)
        if method == "slerp" and self.interpolation != "slerp":
            raise InvalidArgumentError(
                f"{self.name}: slerp needs a buffer made with interpolation='slerp' (it checks "
                "that every sample is a unit quaternion)"
            )
        stamps, values = self._kept()
        n = len(stamps)
        if ts.size == 0:
            return np.empty((0, *values.shape[1:]), dtype=np.float64)
        self._check_range(ts, stamps)
        after = np.searchsorted(stamps, ts, side="right")  # first sample stamped > t
        before = np.clip(after - 1, 0, n - 1)  # latest sample stamped <= t (or the oldest)
        if method == "exact":
            found = stamps[before] == ts
            if not found.all():
                raise self._no_exact_sample(int(ts[np.argmin(found)]))
            return values[before].copy()
        if method == "previous":
            return values[before].copy()
        if method == "nearest":
            later = np.minimum(after, n - 1)
            take_later = (stamps[later] - ts) < (ts - stamps[before])
            return values[np.where(take_later, later, before)].copy()
        if n == 1:
            return np.repeat(values[:1], ts.size, axis=0)
        i0 = np.clip(after - 1, 0, n - 2)
        i1 = i0 + 1
        weight = (ts - stamps[i0]).astype(np.float64) / (stamps[i1] - stamps[i0])
        v0, v1 = values[i0], values[i1]
        if method == "linear":
            w = weight.reshape((-1,) + (1,) * (values.ndim - 1))
            return v0 + w * (v1 - v0)
        return _slerp(v0, v1, weight)

    def _kept(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """The kept stamps and values (views); TimeLookupError if there are none."""
        if not len(self):
            raise TimeLookupError(f"{self.name}: the buffer is empty; add samples before at()")
        return self._stamps[self._start : self._end], self._values[self._start : self._end]

    def _no_exact_sample(self, ns: int) -> TimeLookupError:
        return TimeLookupError(
            f"{self.name}: no sample stamped exactly {self._time(ns)}; use 'nearest', "
            "'previous' or 'linear' for stamps between samples"
        )

    def _check_range(self, ts: npt.NDArray[np.int64], stamps: npt.NDArray[np.int64]) -> None:
        oldest, newest = int(stamps[0]), int(stamps[-1])
        limit = self.max_extrapolation.nanoseconds
        if int(ts.min()) >= oldest - limit and int(ts.max()) <= newest + limit:
            return
        beyond = np.maximum(oldest - ts, ts - newest)
        if (beyond > limit).any():
            worst = int(ts[np.argmax(beyond > limit)])
            side = (
                f"{(oldest - worst) / 1e9:.9g} s before the oldest sample {self._time(oldest)}"
                if worst < oldest
                else f"{(worst - newest) / 1e9:.9g} s after the newest sample {self._time(newest)}"
            )
            evicted = (
                f"; {self.evicted} older samples were evicted (capacity {self.capacity})"
                if worst < oldest and self.evicted
                else ""
            )
            raise ExtrapolationError(
                f"{self.name}: cannot answer at({self._time(worst)}): it is {side}, beyond "
                f"max_extrapolation={self.max_extrapolation.seconds:g} s{evicted}"
            )


def _row(values: npt.NDArray[np.float64], index: int) -> npt.NDArray[np.float64]:
    """A copy of sample ``index`` (so callers never hold a view into the ring)."""
    row: npt.NDArray[np.float64] = values[index].copy()
    return row


def _slerp(
    q0: npt.NDArray[np.float64], q1: npt.NDArray[np.float64], u: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Row-wise slerp of unit quaternions from ``q0`` (u=0) to ``q1`` (u=1), shorter arc."""
    dot = np.einsum("ij,ij->i", q0, q1)
    q1 = np.where((dot < 0)[:, None], -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    close = sin_theta < 1e-9
    safe = np.where(close, 1.0, sin_theta)
    a = np.where(close, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    b = np.where(close, u, np.sin(u * theta) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    norm: Any = np.linalg.norm(q, axis=1, keepdims=True)
    result: npt.NDArray[np.float64] = q / norm
    return result
