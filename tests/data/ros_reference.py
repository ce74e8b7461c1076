"""Reference MODELS of ROS 2 ``message_filters`` algorithms, for differential tests.

These are not ROS code and not the ROS binaries: each class is a plain-Python model written
for evclock's tests from a reading of the ROS sources named in its docstring, kept literal
(same state, same control flow, same comparisons) so that a disagreement with evclock points
at a semantic difference. No ROS source is copied here; nothing here is shipped.

Modelled releases: ``ros2/message_filters`` 4.3.x (Humble), 4.11.x (Jazzy), 6.x (Rolling);
``ros2/rclcpp`` ``Duration::operator*(double)`` of 16.x (Humble) to 29.x and Rolling; rclpy's
``Duration(seconds=...)``; genpy's ``Duration.from_sec``.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

NS = 1_000_000_000


# -- arithmetic ------------------------------------------------------------------------------


def round_to_bits(x: Fraction, bits: int) -> Fraction:
    """``x`` rounded to ``bits`` significant binary digits, to nearest, ties to even."""
    if x == 0:
        return x
    sign = -1 if x < 0 else 1
    a = abs(x)
    e = 0  # find e with 2**(bits-1) <= a / 2**e < 2**bits
    while a / Fraction(2) ** e >= 2**bits:
        e += 1
    while a / Fraction(2) ** e < 2 ** (bits - 1):
        e -= 1
    scaled = a / Fraction(2) ** e
    floor = scaled.numerator // scaled.denominator
    frac = scaled - floor
    if frac > Fraction(1, 2) or (frac == Fraction(1, 2) and floor % 2 == 1):
        floor += 1
    return sign * floor * Fraction(2) ** e


def trunc(x: Fraction) -> int:
    """C++ ``static_cast<int64_t>``: toward zero."""
    return int(x)  # Fraction.__int__ truncates toward zero


def rclcpp_duration_times(ns: int, scale: float, bits: int = 64) -> int:
    """``rclcpp::Duration(ns) * scale``: ``int64(long double(ns) * long double(scale))``."""
    left = Fraction(ns) if bits > 53 else Fraction(float(ns))
    return trunc(round_to_bits(left * Fraction(scale), bits))


def rclpy_duration_ns(seconds: float) -> int:
    """rclpy ``Duration(seconds=s).nanoseconds``: ``int(s * S_TO_NS)``, S_TO_NS an int."""
    return int(seconds * (1000 * 1000 * 1000))


def genpy_duration_ns(seconds: float) -> int:
    """genpy ``Duration.from_sec(s).to_nsec()``: whole seconds and fraction truncated apart."""
    secs = int(seconds)
    nsecs = int((seconds - secs) * 1000000000)
    return secs * NS + nsecs


# -- ExactTime ---------------------------------------------------------------------------------


class RosExactTime:
    """Model of ``sync_policies::ExactTime`` (``exact_time.h``, Humble/Jazzy): a map from stamp
    to a tuple of slots, ``checkTuple`` after each add, ``clearOldTuples`` after a signal, and
    the oldest tuples dropped beyond ``queue_size``."""

    def __init__(self, n: int, queue_size: int) -> None:
        self.n = n
        self.queue_size = queue_size
        self.tuples: dict[int, list[Any]] = {}
        self.last_signal_time = 0
        self.dropped_sets: list[list[Any]] = []  # what the drop signal is called with
        self.overwritten: list[Any] = []  # slots assigned over (ROS does so silently)

    def add(self, i: int, stamp: int, payload: Any) -> list[tuple[Any, ...]]:
        out: list[tuple[Any, ...]] = []
        t = self.tuples.setdefault(stamp, [None] * self.n)
        if t[i] is not None:
            self.overwritten.append(t[i])
        t[i] = payload
        if all(slot is not None for slot in t):
            out.append(tuple(t))
            self.last_signal_time = stamp
            del self.tuples[stamp]
            for key in sorted(self.tuples):  # clearOldTuples: the map is ordered by time
                if key <= self.last_signal_time:
                    self.dropped_sets.append(self.tuples.pop(key))
                else:
                    break
        if self.queue_size > 0:
            while len(self.tuples) > self.queue_size:
                self.dropped_sets.append(self.tuples.pop(min(self.tuples)))
        return out


# -- ApproximateTime ---------------------------------------------------------------------------


class RosApproximateTime:
    """Model of ``sync_policies::ApproximateTime`` (``approximate_time.h``, Humble/Jazzy).

    Items are ``(stamp_ns, payload)``. ``age_penalty`` is applied with
    :func:`rclcpp_duration_times` (x86-64: 64-bit ``long double`` significand).
    """

    NO_PIVOT = -1

    def __init__(
        self,
        n: int,
        queue_size: int,
        age_penalty: float = 0.1,
        max_interval_ns: int | None = None,
        lower_bounds: list[int] | None = None,
        bits: int = 64,
    ) -> None:
        self.n = n
        self.queue_size = queue_size
        self.age_penalty = age_penalty
        self.bits = bits
        # Duration(INT32_MAX s, 999999999 ns) is the C++ default max interval
        self.max_interval = (
            (2**31 - 1) * NS + 999_999_999 if max_interval_ns is None else max_interval_ns
        )
        self.lower = lower_bounds or [0] * n
        self.deques: list[list[tuple[int, Any]]] = [[] for _ in range(n)]
        self.past: list[list[tuple[int, Any]]] = [[] for _ in range(n)]
        self.num_non_empty = 0
        self.pivot = self.NO_PIVOT
        self.pivot_time = 0
        self.candidate: list[tuple[int, Any]] | None = None
        self.candidate_start = 0
        self.candidate_end = 0
        self.has_dropped = [False] * n
        self.out: list[tuple[Any, ...]] = []

    def times(self, d: int) -> int:
        return rclcpp_duration_times(d, 1 + self.age_penalty, self.bits)

    def add(self, i: int, stamp: int, payload: Any) -> list[tuple[Any, ...]]:
        dq = self.deques[i]
        dq.append((stamp, payload))
        if len(dq) == 1:
            self.num_non_empty += 1
            if self.num_non_empty == self.n:
                self.process()
        if len(dq) + len(self.past[i]) > self.queue_size:
            self.num_non_empty = 0
            for k in range(self.n):
                self.recover_all(k)
            dq.pop(0)
            self.has_dropped[i] = True
            if self.pivot != self.NO_PIVOT:
                self.candidate = None
                self.pivot = self.NO_PIVOT
                self.process()
        out, self.out = self.out, []
        return out

    def recover_all(self, k: int) -> None:
        while self.past[k]:
            self.deques[k].insert(0, self.past[k].pop())
        if self.deques[k]:
            self.num_non_empty += 1

    def recover(self, k: int, count: int) -> None:
        for _ in range(count):
            self.deques[k].insert(0, self.past[k].pop())
        if self.deques[k]:
            self.num_non_empty += 1

    def recover_and_delete(self, k: int) -> None:
        while self.past[k]:
            self.deques[k].insert(0, self.past[k].pop())
        self.deques[k].pop(0)
        if self.deques[k]:
            self.num_non_empty += 1

    def delete_front(self, k: int) -> None:
        self.deques[k].pop(0)
        if not self.deques[k]:
            self.num_non_empty -= 1

    def move_front_to_past(self, k: int) -> None:
        self.past[k].append(self.deques[k].pop(0))
        if not self.deques[k]:
            self.num_non_empty -= 1

    def make_candidate(self) -> None:
        self.candidate = [dq[0] for dq in self.deques]
        for v in self.past:
            v.clear()

    def publish_candidate(self) -> None:
        assert self.candidate is not None
        self.out.append(tuple(p for _, p in self.candidate))
        self.candidate = None
        self.pivot = self.NO_PIVOT
        self.num_non_empty = 0
        for k in range(self.n):
            self.recover_and_delete(k)

    @staticmethod
    def boundary(times: list[int], end: bool) -> tuple[int, int]:
        # checkBoundary: index 0 always taken, then (t < time) XOR end
        index, time = 0, times[0]
        for k in range(1, len(times)):
            if (times[k] < time) != end:
                index, time = k, times[k]
        return index, time

    def virtual_time(self, k: int) -> int:
        if not self.deques[k]:
            bound = self.past[k][-1][0] + self.lower[k]
            return bound if bound > self.pivot_time else self.pivot_time
        return self.deques[k][0][0]

    def process(self) -> None:
        while self.num_non_empty == self.n:
            heads = [dq[0][0] for dq in self.deques]
            end_index, end_time = self.boundary(heads, True)
            start_index, start_time = self.boundary(heads, False)
            for k in range(self.n):
                if k != end_index:
                    self.has_dropped[k] = False
            if self.pivot == self.NO_PIVOT:
                if end_time - start_time > self.max_interval:
                    self.delete_front(start_index)
                    continue
                if self.has_dropped[end_index]:
                    self.delete_front(start_index)
                    continue
                self.make_candidate()
                self.candidate_start, self.candidate_end = start_time, end_time
                self.pivot, self.pivot_time = end_index, end_time
                self.move_front_to_past(start_index)
            else:
                if self.times(end_time - self.candidate_end) >= start_time - self.candidate_start:
                    self.move_front_to_past(start_index)
                else:
                    self.make_candidate()
                    self.candidate_start, self.candidate_end = start_time, end_time
                    self.move_front_to_past(start_index)
            age_check = self.times(end_time - self.candidate_end)
            if start_index == self.pivot or age_check >= self.pivot_time - self.candidate_start:
                self.publish_candidate()
            elif self.num_non_empty < self.n:
                moves = [0] * self.n
                while True:
                    vt = [self.virtual_time(k) for k in range(self.n)]
                    _, v_end = self.boundary(vt, True)
                    v_start_index, v_start = self.boundary(vt, False)
                    if (
                        self.times(v_end - self.candidate_end)
                        >= self.pivot_time - self.candidate_start
                    ):
                        self.publish_candidate()
                        break
                    if self.times(v_end - self.candidate_end) < v_start - self.candidate_start:
                        self.num_non_empty = 0
                        for k in range(self.n):
                            self.recover(k, moves[k])
                        break
                    self.move_front_to_past(v_start_index)
                    moves[v_start_index] += 1


# -- ApproximateEpsilonTime ------------------------------------------------------------------


class RosApproximateEpsilonTime:
    """Model of ``sync_policies::ApproximateEpsilonTime`` (``approximate_epsilon_time.h``,
    Jazzy 4.11.x; absent from Humble)."""

    def __init__(self, n: int, queue_size: int, epsilon_ns: int) -> None:
        self.n = n
        self.queue_size = queue_size
        self.eps = epsilon_ns
        self.events: list[list[tuple[int, Any]]] = [[] for _ in range(n)]
        self.non_empty = 0

    def add(self, i: int, stamp: int, payload: Any) -> list[tuple[Any, ...]]:
        out: list[tuple[Any, ...]] = []
        if len(self.events[i]) == 0:
            self.non_empty += 1
        self.events[i].append((stamp, payload))
        if self.non_empty == self.n:
            while self.non_empty == self.n:
                # get_older_timestamp: start at (int64 max, SIZE_MAX), replace when strictly older
                older, older_index = 2**63 - 1, -1
                for k in range(self.n):
                    if self.events[k] and older > self.events[k][0][0]:
                        older, older_index = self.events[k][0][0], k
                valid = True
                for k in range(self.n):
                    if k == older_index:
                        continue
                    if not self.events[k] or not (older + self.eps >= self.events[k][0][0]):
                        valid = False
                if valid:
                    out.append(tuple(v[0][1] for v in self.events))
                    for k in range(self.n):
                        if self.events[k]:
                            self.events[k].pop(0)
                            if not self.events[k]:
                                self.non_empty -= 1
                else:
                    for k in range(self.n):
                        if not self.events[k]:
                            continue
                        if older + self.eps < self.events[k][0][0]:
                            continue
                        self.events[k].pop(0)
                        if not self.events[k]:
                            self.non_empty -= 1
        elif len(self.events[i]) > self.queue_size:
            self.events[i].pop(0)
            if not self.events[i]:
                self.non_empty -= 1
        return out


# -- LatestTime --------------------------------------------------------------------------------


class _RosRate:
    """Model of ``LatestTime::Rate`` (``latest_time.h``, Jazzy 4.11.x)."""

    def __init__(
        self, start: int, rate_alpha: float = 0.9, error_alpha: float = 0.3, margin: float = 10.0
    ) -> None:
        self.prev = start
        self.hz = 0.0
        self.error = 0.0
        self.rate_ema_alpha = rate_alpha
        self.error_ema_alpha = error_alpha
        self.rate_step_change_margin_factor = margin
        self.do_hz_init = True
        self.do_error_init = True

    @staticmethod
    def seconds(ns: int) -> float:
        # std::chrono::duration<double>(nanoseconds(ns)).count(): double(ns) / 1e9
        return float(ns) / 1e9

    def compute_hz(self, now: int) -> bool:
        step_change_detected = False
        first = True
        while first or step_change_detected:  # do { ... } while (step_change_detected)
            first = False
            period = self.seconds(now - self.prev)
            if period <= 0.0:
                return False
            if self.do_hz_init:
                self.hz = 1.0 / period
                self.do_hz_init = False
                step_change_detected = False
            else:
                if self.do_error_init:
                    self.error = abs(self.hz - 1.0 / period)
                    self.do_error_init = False
                else:
                    if (
                        abs(self.hz - 1.0 / period)
                        > self.rate_step_change_margin_factor * self.error
                    ):
                        self.do_hz_init = True
                        self.do_error_init = True
                        step_change_detected = True
                        continue
                    self.error = (
                        self.error_ema_alpha * abs(self.hz - 1.0 / period)
                        + (1.0 - self.error_ema_alpha) * self.error
                    )
                self.hz = self.rate_ema_alpha / period + (1.0 - self.rate_ema_alpha) * self.hz
        self.prev = now
        return True


class RosLatestTime:
    """Model of ``sync_policies::LatestTime`` (``latest_time.h``, Jazzy 4.11.x).

    ``add(i, now, payload)``: ``now`` is the subscriber clock's time at arrival. Like ROS,
    ``rates`` is appended in order of first arrival and read by stream index: callers keep
    the first arrivals in stream index order (otherwise ROS reads past its vector).
    """

    NO_PIVOT = 9

    def __init__(self, n: int) -> None:
        self.n = n
        self.events: list[Any] = [None] * n
        self.rates: list[_RosRate] = []

    def add(self, i: int, now: int, payload: Any) -> list[tuple[Any, ...]]:
        if self.events[i] is None:
            self.rates.append(_RosRate(now))
            self.events[i] = payload
            return []
        self.events[i] = payload
        valid = self.rates[i].compute_hz(now)
        if valid and i == self.find_pivot(now) and all(e is not None for e in self.events):
            return [tuple(self.events)]
        return []

    def find_pivot(self, now: int) -> int:
        idx = list(range(len(self.rates)))
        # std::stable_sort with comparator v[a] > v[b] (Rate::operator> compares hz)
        import functools

        def cmp(a: int, b: int) -> int:
            if self.rates[a].hz > self.rates[b].hz:
                return -1
            if self.rates[b].hz > self.rates[a].hz:
                return 1
            return 0

        idx.sort(key=functools.cmp_to_key(cmp))
        for pivot in idx:
            r = self.rates[pivot]
            period = _RosRate.seconds(now - r.prev)
            if period == 0.0:
                if r.hz > 0.0:
                    return pivot
                continue
            if not r.do_error_init:
                rate_delta = r.hz - 1.0 / period
                margin = r.rate_step_change_margin_factor * r.error
                if rate_delta > margin:
                    continue
            if r.hz > 0.0:
                return pivot
        return self.NO_PIVOT


# -- Python ApproximateTimeSynchronizer (slop) ----------------------------------------------


class RosPythonSlop:
    """Model of rclpy ``message_filters.ApproximateTimeSynchronizer.add`` (4.3.x / 4.11.x).

    ``slop`` is given in float seconds and converted like ``Duration(seconds=slop)``.
    """

    def __init__(self, n: int, queue_size: int, slop_seconds: float) -> None:
        self.queues: list[dict[int, Any]] = [{} for _ in range(n)]
        self.queue_size = queue_size
        self.slop = rclpy_duration_ns(slop_seconds)

    def add(self, i: int, stamp: int, payload: Any) -> list[tuple[Any, ...]]:
        import itertools

        my_queue = self.queues[i]
        my_queue[stamp] = payload
        while len(my_queue) > self.queue_size:
            del my_queue[min(my_queue)]
        search = self.queues[:i] + self.queues[i + 1 :]
        stamps = []
        for queue in search:
            topic = []
            for s in queue:
                delta = abs(s - stamp)
                if delta > self.slop:
                    continue
                topic.append((s, delta))
            if not topic:
                return []
            topic = sorted(topic, key=lambda x: x[1])
            stamps.append(topic)
        for vv in itertools.product(*[[t for t, _ in s] for s in stamps]):
            vv = list(vv)
            vv.insert(i, stamp)
            qt = list(zip(self.queues, vv, strict=False))
            if (max(vv) - min(vv)) < self.slop and all(t in q for q, t in qt):
                msgs = tuple(q[t] for q, t in qt)
                for q, t in qt:
                    del q[t]
                return [msgs]
        return []


# -- Cache --------------------------------------------------------------------------------


class RosCache:
    """Model of C++ ``message_filters::Cache`` (``cache.h``, Humble/Jazzy)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.cache: list[tuple[int, Any]] = []

    def add(self, stamp: int, payload: Any) -> None:
        while len(self.cache) >= self.size:
            self.cache.pop(0)
        pos = len(self.cache)
        while pos > 0 and self.cache[pos - 1][0] > stamp:
            pos -= 1
        self.cache.insert(pos, (stamp, payload))

    def interval(self, start: int, end: int) -> list[Any]:
        i = 0
        while i < len(self.cache) and self.cache[i][0] < start:
            i += 1
        j = i
        while j < len(self.cache) and self.cache[j][0] <= end:
            j += 1
        return [p for _, p in self.cache[i:j]]

    def surrounding(self, start: int, end: int) -> list[Any]:
        s = len(self.cache) - 1
        while s > 0 and self.cache[s][0] > start:
            s -= 1
        e = s
        while e < len(self.cache) - 1 and self.cache[e][0] < end:
            e += 1
        return [p for _, p in self.cache[s : e + 1]] if self.cache else []

    def before(self, t: int) -> Any:
        out = None
        for stamp, p in self.cache:
            if not stamp < t:
                break
            out = p
        return out

    def after(self, t: int) -> Any:
        out = None
        for stamp, p in reversed(self.cache):
            if not stamp > t:
                break
            out = p
        return out


# -- TimeSequencer ----------------------------------------------------------------------------


class RosTimeSequencer:
    """Model of C++ ``message_filters::TimeSequencer`` (``time_sequencer.h``, Humble/Jazzy):
    a multiset ordered by stamp (equal stamps in insertion order), ``dispatch(now)`` on a
    timer. ``erase(*begin())`` on a multiset erases every element with the oldest stamp."""

    def __init__(self, delay_ns: int, queue_size: int) -> None:
        self.delay = delay_ns
        self.queue_size = queue_size
        self.messages: list[tuple[int, Any]] = []
        self.last_time = 0

    def add(self, stamp: int, payload: Any) -> None:
        if stamp < self.last_time:
            return
        pos = len(self.messages)
        while pos > 0 and self.messages[pos - 1][0] > stamp:
            pos -= 1
        self.messages.insert(pos, (stamp, payload))
        if self.queue_size != 0 and len(self.messages) > self.queue_size:
            oldest = self.messages[0][0]
            self.messages = [m for m in self.messages if m[0] != oldest]

    def dispatch(self, now: int) -> list[Any]:
        out = []
        while self.messages:
            stamp, payload = self.messages[0]
            if stamp + self.delay <= now:
                self.last_time = stamp
                out.append(payload)
                self.messages.pop(0)
            else:
                break
        return out
