"""Matching policies of the synchronisers, on integer-nanosecond stamps (no clocks, no asyncio).

Each policy receives ``add(stream, stamp_ns, item)`` calls, returns the groups (one item per
stream, in stream order) that the call completed, and counts the items it discarded unused in
``dropped`` (per stream). Their memory is bounded by ``queue_size`` per stream.

* :class:`ExactPolicy` - ROS ``message_filters`` ExactTime (C++): a group is the set of items
  sharing one stamp.
* :class:`ApproximatePolicy` - ROS ``message_filters`` ApproximateTime (C++), the pivot
  algorithm with age penalty, ``max_interval`` and inter-message lower bounds.
* :class:`SlopPolicy` - ROS Python's ``ApproximateTimeSynchronizer(fs, queue_size, slop)``.
"""

from __future__ import annotations

import itertools
from collections import deque
from typing import Final

__all__ = ["ApproximatePolicy", "ExactPolicy", "Group", "SlopPolicy"]

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
        if slots[stream] is not None:
            self.dropped[stream] += 1
        slots[stream] = (stamp_ns, item)
        groups: list[Group] = []
        if all(slot is not None for slot in slots):
            del self._sets[stamp_ns]
            groups.append(tuple(slot[1] for slot in slots if slot is not None))
            for older in sorted(s for s in self._sets if s < stamp_ns):
                self._drop(older)
        excess = len(self._sets) - self._queue_size
        if excess > 0:
            for older in sorted(self._sets)[:excess]:
                self._drop(older)
        return groups

    def _drop(self, stamp_ns: int) -> None:
        for index, slot in enumerate(self._sets.pop(stamp_ns)):
            if slot is not None:
                self.dropped[index] += 1


_NO_PIVOT: Final = -1


class ApproximatePolicy(_Counters):
    """ROS ApproximateTime (C++ ``approximate_time.hpp``), state for state.

    Per stream a deque of waiting items and a ``past`` list of items moved aside during the
    search for the best set around a *pivot* (the latest head when the candidate was made).
    A candidate is published once no later set can be smaller (using, when given, each
    stream's inter-message lower bound to rule out sets made of not-yet-arrived items).
    ``age_penalty`` makes later sets look bigger by ``1 + age_penalty``; sets longer than
    ``max_interval_ns`` are never formed. Ties resolve as in C++: the earliest head is the
    lowest stream index among equal stamps, the latest head the highest.
    """

    def __init__(
        self,
        streams: int,
        queue_size: int,
        *,
        age_penalty: float = 0.0,
        max_interval_ns: int | None = None,
        lower_bounds_ns: list[int] | None = None,
    ) -> None:
        super().__init__(streams)
        self._n = streams
        self._queue_size = queue_size
        self._factor = 1.0 + age_penalty
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
            queue.popleft()
            self.dropped[stream] += 1
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

    def _delete_front(self, index: int) -> None:
        queue = self._deques[index]
        queue.popleft()
        self.dropped[index] += 1
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
            self.dropped[index] += len(past)
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

    def _scaled(self, ns: int) -> int:
        # rclcpp::Duration * double truncates toward zero.
        return ns if self._factor == 1.0 else int(ns * self._factor)

    def _process(self) -> None:
        while self._non_empty == self._n:
            start_index, start, end_index, end = self._boundaries(
                [queue[0][0] for queue in self._deques]
            )
            for index in range(self._n):
                if index != end_index:
                    self._has_dropped[index] = False
            if self._pivot == _NO_PIVOT:
                too_long = self._max_interval is not None and end - start > self._max_interval
                if too_long or self._has_dropped[end_index]:
                    self._delete_front(start_index)
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

    def add(self, stream: int, stamp_ns: int, item: object) -> list[Group]:
        """Offer ``item`` stamped ``stamp_ns`` on ``stream``; return the group it completed."""
        if stamp_ns < self._last[stream]:
            self.out_of_order[stream] += 1
        self._last[stream] = max(self._last[stream], stamp_ns)
        mine = self._queues[stream]
        if stamp_ns in mine:
            self.dropped[stream] += 1
        mine[stamp_ns] = item
        while len(mine) > self._queue_size:
            del mine[min(mine)]
            self.dropped[stream] += 1
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
