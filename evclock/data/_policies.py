"""Matching policies of the synchronisers, on integer-nanosecond stamps (no clocks, no asyncio).

Each policy receives ``add(stream, stamp_ns, item)`` calls, returns the groups (one item per
stream, in stream order) that the call completed, and counts the items it discarded unused in
``dropped`` (per stream). Their memory is bounded by ``queue_size`` per stream.

* :class:`ExactPolicy` - ROS ``message_filters`` ExactTime (C++): a group is the set of items
  sharing one stamp.
* :class:`ApproximatePolicy` - ROS ``message_filters`` ApproximateTime (C++), the pivot
  algorithm with age penalty, ``max_interval`` and inter-message lower bounds.
* :class:`SlopPolicy` - ROS Python's ``ApproximateTimeSynchronizer(fs, queue_size, slop)``.
* :class:`EpsilonPolicy` - ROS ``message_filters`` ApproximateEpsilonTime (C++, Jazzy and
  later): the oldest heads are grouped when every other head is within ``epsilon`` of it.
* :class:`LatestPolicy` - ROS ``message_filters`` LatestTime (C++, Jazzy and later): a
  group is published at the rate of the fastest stream, the others held (zero-order hold);
  its "time" is the arrival time on the consumer's clock, not the stamp.

Every discarded item is reported to ``on_drop(stream, item, reason)`` when a hook is set,
``reason`` one of :data:`DROP_REASONS`.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Iterator
from typing import Final, Literal

from evclock.data._rosmath import duration_scaler

__all__ = [
    "DROP_REASONS",
    "ApproximatePolicy",
    "DropReason",
    "EpsilonPolicy",
    "ExactPolicy",
    "Group",
    "LatestPolicy",
    "SlopPolicy",
]

DropReason = Literal[
    "queue_full",
    "replaced",
    "superseded",
    "not_selected",
    "interval_too_wide",
    "stream_dropped",
    "no_partner",
    "waiting_for_all_streams",
    "late",
    "reset",
]
"""Why an item was discarded without being part of a group (see :data:`DROP_REASONS`)."""

DROP_REASONS: Final[dict[str, str]] = {
    "queue_full": "its stream's queue was full (queue_size); the oldest item goes",
    "replaced": "a later item with the same stamp on the same stream replaced it",
    "superseded": "a newer group was emitted: this older incomplete set can never complete",
    "not_selected": "a better group was formed without it (it sits between groups)",
    "interval_too_wide": "every group it could be part of is wider than max_interval",
    "stream_dropped": "it would pair with a stream that just dropped items (ROS's pivot rule)",
    "no_partner": "no item of another stream lies within epsilon after it",
    "waiting_for_all_streams": "a newer item of its stream replaced it before every stream "
    "had delivered one (LatestTime publishes only once all have)",
    "late": "its stamp is older than the last item released (TimeSequencer)",
    "reset": "the filter was reset (a backward time jump, or reset())",
}
"""Each drop reason and what it means."""

DropHook = Callable[[int, object, str], None]
"""``on_drop(stream index, item, reason)``."""

Group = tuple[object, ...]
"""One matched item per stream, in stream order."""

_Entry = tuple[int, object]
"""``(stamp_ns, item)``."""


class _Counters:
    """What every policy reports: per-stream drops and the out-of-order arrivals it saw."""

    def __init__(self, streams: int) -> None:
        self.dropped = [0] * streams
        """Items discarded without being part of a group, per stream."""
        self.out_of_order = [0] * streams
        """Items whose stamp was older than the previous item's on the same stream."""
        self.bound_violations = [0] * streams
        """Items closer to their predecessor than the stream's declared lower bound."""
        self.on_drop: DropHook | None = None
        """Called for every discarded item, with its stream index, the item and the reason."""

    def _discard(self, stream: int, item: object, reason: DropReason) -> None:
        self.dropped[stream] += 1
        if self.on_drop is not None:
            self.on_drop(stream, item, reason)


class ExactPolicy(_Counters):
    """ROS ExactTime (C++): emit when every stream has an item with the same stamp.

    On emission, every incomplete set with an older stamp is dropped (it can never complete in
    order); more than ``queue_size`` incomplete stamps drop the oldest. A second item with the
    same stamp on the same stream replaces the first (which counts as dropped).
    """

    def __init__(self, streams: int, queue_size: int) -> None:
        super().__init__(streams)
        self._streams = streams
        self._queue_size = queue_size
        # stamp -> one slot per stream; dict keeps insertion order, ordered lookups sort keys.
        self._sets: dict[int, list[_Entry | None]] = {}
        self._last = [-(2**63)] * streams

    @property
    def pending(self) -> int:
        """Items held while waiting for their set to complete."""
        return sum(slot is not None for slots in self._sets.values() for slot in slots)

    def add(self, stream: int, stamp_ns: int, item: object) -> list[Group]:
        """Offer ``item`` stamped ``stamp_ns`` on ``stream``; return the completed groups."""
        if stamp_ns < self._last[stream]:
            self.out_of_order[stream] += 1
        self._last[stream] = max(self._last[stream], stamp_ns)
        slots = self._sets.setdefault(stamp_ns, [None] * self._streams)
        previous = slots[stream]
        slots[stream] = (stamp_ns, item)
        if previous is not None:
            self._discard(stream, previous[1], "replaced")
        groups: list[Group] = []
        if all(slot is not None for slot in slots):
            del self._sets[stamp_ns]
            groups.append(tuple(slot[1] for slot in slots if slot is not None))
            for older in sorted(s for s in self._sets if s < stamp_ns):
                self._drop(older, "superseded")
        excess = len(self._sets) - self._queue_size
        if excess > 0:
            for older in sorted(self._sets)[:excess]:
                self._drop(older, "queue_full")
        return groups

    def held(self) -> Iterator[tuple[int, object]]:
        """The items held, as ``(stream index, item)``, oldest stamp first."""
        for stamp in sorted(self._sets):
            for index, slot in enumerate(self._sets[stamp]):
                if slot is not None:
                    yield index, slot[1]

    def _drop(self, stamp_ns: int, reason: DropReason) -> None:
        for index, slot in enumerate(self._sets.pop(stamp_ns)):
            if slot is not None:
                self._discard(index, slot[1], reason)


_NO_PIVOT: Final = -1


class ApproximatePolicy(_Counters):
    """ROS ApproximateTime (C++ ``approximate_time.hpp``), state for state.

    Per stream a deque of waiting items and a ``past`` list of items moved aside during the
    search for the best set around a *pivot* (the latest head when the candidate was made).
    A candidate is published once no later set can be smaller (using, when given, each
    stream's inter-message lower bound to rule out sets made of not-yet-arrived items).
    ``age_penalty`` makes later sets look bigger by ``1 + age_penalty``; sets longer than
    ``max_interval_ns`` are never formed. Ties resolve as in C++: the earliest head is the
    lowest stream index among equal stamps, the latest head the highest. The weighting is
    ``rclcpp::Duration * double`` bit for bit, with a ``long double`` of
    ``long_double_bits`` significant bits (64: x86-64 Linux, see ``_rosmath``).
    """

    def __init__(
        self,
        streams: int,
        queue_size: int,
        *,
        age_penalty: float = 0.0,
        max_interval_ns: int | None = None,
        lower_bounds_ns: list[int] | None = None,
        long_double_bits: int = 64,
    ) -> None:
        super().__init__(streams)
        self._n = streams
        self._queue_size = queue_size
        # C++ (end - candidate_end) * (1 + age_penalty_): rclcpp::Duration * double.
        self._scaled = duration_scaler(1 + age_penalty, long_double_bits)
        self._max_interval = max_interval_ns
        self._lower_bounds = lower_bounds_ns or [0] * streams
        self._deques: list[deque[_Entry]] = [deque() for _ in range(streams)]
        self._past: list[list[_Entry]] = [[] for _ in range(streams)]
        self._non_empty = 0
        self._has_dropped = [False] * streams
        self._candidate: list[_Entry] | None = None
        self._candidate_start = 0
        self._candidate_end = 0
        self._pivot = _NO_PIVOT
        self._pivot_time = 0
        self._output: list[Group] = []

    @property
    def pending(self) -> int:
        """Items held (waiting, or set aside during the search for the best set)."""
        return sum(len(q) for q in self._deques) + sum(len(v) for v in self._past)

    def add(self, stream: int, stamp_ns: int, item: object) -> list[Group]:
        """Offer ``item`` stamped ``stamp_ns`` on ``stream``; return the groups it completed."""
        queue = self._deques[stream]
        queue.append((stamp_ns, item))
        if len(queue) == 1:
            self._non_empty += 1
            if self._non_empty == self._n:
                self._process()
        else:
            self._check_inter_message_bound(stream)
        past = self._past[stream]
        if len(queue) + len(past) > self._queue_size:
            # Cancel the ongoing search, then drop the oldest item of the offending stream.
            self._non_empty = 0
            for index in range(self._n):
                self._recover(index, len(self._past[index]))
            self._discard(stream, queue.popleft()[1], "queue_full")
            self._has_dropped[stream] = True
            if self._pivot != _NO_PIVOT:
                self._candidate = None
                self._pivot = _NO_PIVOT
                self._process()
        output, self._output = self._output, []
        return output

    def _check_inter_message_bound(self, stream: int) -> None:
        # C++ warns once per stream; evclock counts every occurrence (reported by the caller).
        queue = self._deques[stream]
        stamp = queue[-1][0]
        if len(queue) >= 2:
            previous = queue[-2][0]
        elif self._past[stream]:
            previous = self._past[stream][-1][0]
        else:
            return
        if stamp < previous:
            self.out_of_order[stream] += 1
        elif stamp - previous < self._lower_bounds[stream]:
            self.bound_violations[stream] += 1

    # -- deque moves (C++ dequeDeleteFront, dequeMoveFrontToPast, recover, recoverAndDelete) --

    def held(self) -> Iterator[tuple[int, object]]:
        """The items held, as ``(stream index, item)``, stream by stream, oldest first."""
        for index in range(self._n):
            for entry in (*self._past[index], *self._deques[index]):
                yield index, entry[1]

    def _delete_front(self, index: int, reason: DropReason) -> None:
        queue = self._deques[index]
        self._discard(index, queue.popleft()[1], reason)
        if not queue:
            self._non_empty -= 1

    def _move_front_to_past(self, index: int) -> None:
        queue = self._deques[index]
        self._past[index].append(queue.popleft())
        if not queue:
            self._non_empty -= 1

    def _recover(self, index: int, count: int) -> None:
        queue, past = self._deques[index], self._past[index]
        for _ in range(count):
            queue.appendleft(past.pop())
        if queue:
            self._non_empty += 1

    def _recover_and_delete(self, index: int) -> None:
        queue, past = self._deques[index], self._past[index]
        while past:
            queue.appendleft(past.pop())
        queue.popleft()  # the candidate's own item: published, not dropped
        if queue:
            self._non_empty += 1

    def _make_candidate(self) -> None:
        self._candidate = [queue[0] for queue in self._deques]
        for index, past in enumerate(self._past):
            for entry in past:
                self._discard(index, entry[1], "not_selected")
            past.clear()

    def _publish_candidate(self) -> None:
        assert self._candidate is not None
        self._output.append(tuple(entry[1] for entry in self._candidate))
        self._candidate = None
        self._pivot = _NO_PIVOT
        self._non_empty = 0
        for index in range(self._n):
            self._recover_and_delete(index)

    # -- interval boundaries --

    def _boundaries(self, times: list[int]) -> tuple[int, int, int, int]:
        """(start index, start time, end index, end time) with C++'s tie-breaking."""
        start_index, start = 0, times[0]
        end_index, end = 0, times[0]
        for index in range(1, self._n):
            t = times[index]
            if t < start:
                start_index, start = index, t
            if t >= end:
                end_index, end = index, t
        return start_index, start, end_index, end

    def _virtual_time(self, index: int) -> int:
        queue = self._deques[index]
        if queue:
            return queue[0][0]
        bound = self._past[index][-1][0] + self._lower_bounds[index]
        return max(bound, self._pivot_time)

    def _process(self) -> None:
        while self._non_empty == self._n:
            start_index, start, end_index, end = self._boundaries(
                [queue[0][0] for queue in self._deques]
            )
            for index in range(self._n):
                if index != end_index:
                    self._has_dropped[index] = False
            if self._pivot == _NO_PIVOT:
                if self._max_interval is not None and end - start > self._max_interval:
                    self._delete_front(start_index, "interval_too_wide")
                    continue
                if self._has_dropped[end_index]:
                    self._delete_front(start_index, "stream_dropped")
                    continue
                self._make_candidate()
                self._candidate_start, self._candidate_end = start, end
                self._pivot, self._pivot_time = end_index, end
                self._move_front_to_past(start_index)
            else:
                if self._scaled(end - self._candidate_end) >= start - self._candidate_start:
                    self._move_front_to_past(start_index)
                else:
                    self._make_candidate()
                    self._candidate_start, self._candidate_end = start, end
                    self._move_front_to_past(start_index)
            # Publish when every set around the pivot was tried (the pivot is now the
            # start), or when any later set must span [pivot, end] and so be larger.
            if start_index == self._pivot or (
                self._scaled(end - self._candidate_end) >= self._pivot_time - self._candidate_start
            ):
                self._publish_candidate()
            elif self._non_empty < self._n:
                self._virtual_search()

    def _virtual_search(self) -> None:
        """Try to prove the candidate optimal assuming the earliest possible future items."""
        moves = [0] * self._n
        while True:
            start_index, start, _, end = self._boundaries(
                [self._virtual_time(index) for index in range(self._n)]
            )
            if self._scaled(end - self._candidate_end) >= self._pivot_time - self._candidate_start:
                self._publish_candidate()
                return
            if self._scaled(end - self._candidate_end) < start - self._candidate_start:
                self._non_empty = 0
                for index in range(self._n):
                    self._recover(index, moves[index])
                return
            self._move_front_to_past(start_index)
            moves[start_index] += 1


class SlopPolicy(_Counters):
    """ROS Python's ``ApproximateTimeSynchronizer(fs, queue_size, slop)``.

    Each stream keeps up to ``queue_size`` items keyed by stamp (a second item with the same
    stamp replaces the first; beyond ``queue_size`` the oldest stamp is dropped). On each
    arrival, the other streams' items within ``slop`` of the new stamp are ranked by distance;
    the first combination (nearest first, last stream varying fastest) whose spread is below
    ``slop`` is emitted and its items removed. Older unmatched items stay queued until the
    queue bound pushes them out, so, unlike the C++ policy, successive groups may cross.
    """

    def __init__(self, streams: int, queue_size: int, slop_ns: int) -> None:
        super().__init__(streams)
        self._queue_size = queue_size
        self._slop = slop_ns
        self._queues: list[dict[int, object]] = [{} for _ in range(streams)]
        self._last = [-(2**63)] * streams

    @property
    def pending(self) -> int:
        """Items held while waiting for partners."""
        return sum(len(queue) for queue in self._queues)

    def held(self) -> Iterator[tuple[int, object]]:
        """The items held, as ``(stream index, item)``, stream by stream, oldest first."""
        for index, queue in enumerate(self._queues):
            for stamp in sorted(queue):
                yield index, queue[stamp]

    def add(self, stream: int, stamp_ns: int, item: object) -> list[Group]:
        """Offer ``item`` stamped ``stamp_ns`` on ``stream``; return the group it completed."""
        if stamp_ns < self._last[stream]:
            self.out_of_order[stream] += 1
        self._last[stream] = max(self._last[stream], stamp_ns)
        mine = self._queues[stream]
        if stamp_ns in mine:
            self._discard(stream, mine[stamp_ns], "replaced")
        mine[stamp_ns] = item
        while len(mine) > self._queue_size:
            self._discard(stream, mine.pop(min(mine)), "queue_full")
        ranked: list[list[int]] = []
        for index, queue in enumerate(self._queues):
            if index == stream:
                continue
            near = [s for s in queue if abs(s - stamp_ns) <= self._slop]
            if not near:
                return []
            ranked.append(sorted(near, key=lambda s: abs(s - stamp_ns)))
        for combination in itertools.product(*ranked):
            stamps = [*combination[:stream], stamp_ns, *combination[stream:]]
            if max(stamps) - min(stamps) < self._slop and all(
                s in queue for s, queue in zip(stamps, self._queues, strict=True)
            ):
                group = tuple(queue.pop(s) for s, queue in zip(stamps, self._queues, strict=True))
                return [group]
        return []


class EpsilonPolicy(_Counters):
    """ROS ApproximateEpsilonTime (C++ ``approximate_epsilon_time.h``, Jazzy and later).

    Each stream keeps its items in arrival order. Once every stream holds one, the oldest
    head (the lowest stream index among equal stamps) is taken as reference: if every other
    head is at most ``epsilon_ns`` after it, the heads form a group; otherwise every head
    within ``epsilon_ns`` of the reference (the reference included) is dropped, and the
    search repeats while every stream still holds an item. A stream that alone holds more
    than ``queue_size`` items while another is empty drops its oldest.
    """

    def __init__(self, streams: int, queue_size: int, epsilon_ns: int) -> None:
        super().__init__(streams)
        self._n = streams
        self._queue_size = queue_size
        self._epsilon = epsilon_ns
        self._queues: list[deque[_Entry]] = [deque() for _ in range(streams)]
        self._non_empty = 0

    @property
    def pending(self) -> int:
        """Items held while waiting for partners."""
        return sum(len(queue) for queue in self._queues)

    def held(self) -> Iterator[tuple[int, object]]:
        """The items held, as ``(stream index, item)``, stream by stream, oldest first."""
        for index, queue in enumerate(self._queues):
            for entry in queue:
                yield index, entry[1]

    def add(self, stream: int, stamp_ns: int, item: object) -> list[Group]:
        """Offer ``item`` stamped ``stamp_ns`` on ``stream``; return the groups it completed."""
        queue = self._queues[stream]
        if queue and stamp_ns < queue[-1][0]:
            self.out_of_order[stream] += 1
        if not queue:
            self._non_empty += 1
        queue.append((stamp_ns, item))
        if self._non_empty == self._n:
            return self._process()
        if len(queue) > self._queue_size:
            self._pop(stream, "queue_full")
        return []

    def _pop(self, index: int, reason: DropReason | None) -> object:
        queue = self._queues[index]
        item = queue.popleft()[1]
        if not queue:
            self._non_empty -= 1
        if reason is not None:
            self._discard(index, item, reason)
        return item

    def _process(self) -> list[Group]:
        groups: list[Group] = []
        while self._non_empty == self._n:
            heads = [queue[0][0] for queue in self._queues]
            reference = min(heads)  # the first index among equal stamps: min() keeps it
            limit = reference + self._epsilon
            if all(head <= limit for head in heads):
                groups.append(tuple(self._pop(index, None) for index in range(self._n)))
            else:
                for index, head in enumerate(heads):
                    if head <= limit:
                        self._pop(index, "no_partner")
        return groups


RateConfig = tuple[float, float, float]
"""LatestTime's ``(rate_ema_alpha, error_ema_alpha, rate_step_change_margin_factor)``."""

DEFAULT_RATE_CONFIG: Final[RateConfig] = (0.9, 0.3, 10.0)
"""ROS's defaults for :data:`RateConfig`."""


class _RateEstimate:
    """One stream's arrival rate, as LatestTime's ``Rate`` computes it (double for double)."""

    __slots__ = (
        "do_error_init",
        "do_hz_init",
        "error",
        "error_alpha",
        "hz",
        "margin",
        "prev",
        "rate_alpha",
    )

    def __init__(self, start_ns: int, config: RateConfig) -> None:
        self.prev = start_ns
        self.hz = 0.0
        self.error = 0.0
        self.rate_alpha, self.error_alpha, self.margin = config
        self.do_hz_init = True
        self.do_error_init = True

    def update(self, now_ns: int) -> bool:
        """Fold the arrival at ``now_ns`` in; False when time has not advanced since the last."""
        while True:
            period = (now_ns - self.prev) / 1e9  # rclcpp Duration::seconds(): double(ns) / 1e9
            if period <= 0.0:
                return False
            step_change = False
            if self.do_hz_init:
                self.hz = 1.0 / period
                self.do_hz_init = False
            else:
                if self.do_error_init:
                    self.error = abs(self.hz - 1.0 / period)
                    self.do_error_init = False
                else:
                    if abs(self.hz - 1.0 / period) > self.margin * self.error:
                        # A step change of the rate: start the estimate again.
                        self.do_hz_init = True
                        self.do_error_init = True
                        step_change = True
                    else:
                        self.error = (
                            self.error_alpha * abs(self.hz - 1.0 / period)
                            + (1.0 - self.error_alpha) * self.error
                        )
                if not step_change:
                    self.hz = self.rate_alpha / period + (1.0 - self.rate_alpha) * self.hz
            if not step_change:
                self.prev = now_ns
                return True


class LatestPolicy(_Counters):
    """ROS LatestTime (C++ ``latest_time.h``, Jazzy and later): zero-order hold at the
    rate of the fastest stream.

    Each stream holds its latest item. The first item of a stream only starts its rate
    estimate; from its second item on, an arrival updates the stream's rate (an exponential
    moving average of ``1/period``, restarted on a step change larger than the margin times
    the mean error) and publishes the held items of every stream when this stream is the
    *pivot*: the fastest stream whose next item is not late. ``now_ns`` - the arrival time
    on the consumer's clock, not the stamp - drives it. An item replaced before any group
    used it is dropped.

    One deliberate difference: ROS keeps the rate estimates in the order the streams
    delivered their first item, and reads them by stream index (so a stream whose first item
    came first in a different order starts from another stream's first arrival time, and a
    stream delivering twice before every stream delivered once reads past the end of the
    vector); evclock keys each estimate by its stream. Both agree when the streams first
    deliver in index order.
    """

    def __init__(self, streams: int, rate_configs: list[RateConfig] | None = None) -> None:
        super().__init__(streams)
        self._n = streams
        self._configs = rate_configs or [DEFAULT_RATE_CONFIG] * streams
        self._latest: list[_Entry | None] = [None] * streams
        self._used = [False] * streams
        self._rates: list[_RateEstimate | None] = [None] * streams

    @property
    def pending(self) -> int:
        """Held items no group has used yet."""
        return sum(
            entry is not None and not used
            for entry, used in zip(self._latest, self._used, strict=True)
        )

    def held(self) -> Iterator[tuple[int, object]]:
        """The held items no group used yet, as ``(stream index, item)``."""
        for index, entry in enumerate(self._latest):
            if entry is not None and not self._used[index]:
                yield index, entry[1]

    def add(self, stream: int, now_ns: int, item: object) -> list[Group]:
        """Offer ``item`` arriving at ``now_ns`` on ``stream``; return the group it published."""
        previous = self._latest[stream]
        self._latest[stream] = (now_ns, item)
        if previous is not None and not self._used[stream]:
            full = all(entry is not None for entry in self._latest)
            self._discard(stream, previous[1], "replaced" if full else "waiting_for_all_streams")
        self._used[stream] = False
        rate = self._rates[stream]
        if rate is None:
            self._rates[stream] = _RateEstimate(now_ns, self._configs[stream])
            return []
        valid = rate.update(now_ns)
        if not (valid and self._pivot(now_ns) == stream):
            return []
        if any(entry is None for entry in self._latest):
            return []
        self._used = [True] * self._n
        return [tuple(entry[1] for entry in self._latest if entry is not None)]

    def _pivot(self, now_ns: int) -> int:
        rates = [(index, rate) for index, rate in enumerate(self._rates) if rate is not None]
        # Fastest first; equal rates keep the stream order (ROS's stable sort).
        rates.sort(key=lambda pair: pair[1].hz, reverse=True)
        for index, rate in rates:
            period = (now_ns - rate.prev) / 1e9
            if period == 0.0:
                if rate.hz > 0.0:
                    return index  # just updated, and the fastest
                continue
            if not rate.do_error_init and rate.hz - 1.0 / period > rate.margin * rate.error:
                continue  # this stream's next item is late
            if rate.hz > 0.0:
                return index
        return -1
