"""Synchronisers: group messages of several streams by time stamp, on any evclock clock.

``TimeSynchronizer`` (exact stamps) and ``ApproximateTimeSynchronizer`` (ROS's ApproximateTime
policy, or ROS Python's slop matching) share one front end: messages go in with
``sync.add(stream, msg)`` (or the per-stream callable ``sync.input(stream)``, ready to be a
subscription callback), stamps are read with :func:`evclock.data.stamp_of` in the clock's domain,
and matched groups come out either to a ``callback(*messages)`` or through
``async for group in sync``. The matching itself lives in ``_sync_policies``.
"""

from __future__ import annotations

import abc
import asyncio
import inspect
import logging
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.data._diagnostics import StampDiagnostics
from evclock.data._policies import ApproximatePolicy, ExactPolicy, Group, SlopPolicy
from evclock.data._stamped import StampClock, StampKey, check_stamp_clock, stamp_of
from evclock.hosts._current import clock as running_clock
from evclock.time._time import Duration, new_duration, to_nonnegative_nanoseconds

__all__ = ["ApproximateTimeSynchronizer", "TimeSynchronizer"]

_logger = logging.getLogger("evclock.sync")

_Policy = ExactPolicy | ApproximatePolicy | SlopPolicy


def _stream_names(streams: object) -> tuple[str, ...]:
    if isinstance(streams, int) and not isinstance(streams, bool):
        if streams < 2:
            raise InvalidArgumentError(
                f"a synchroniser needs at least 2 streams, got {streams}; with one stream "
                "there is nothing to match"
            )
        return tuple(str(i) for i in range(streams))
    if isinstance(streams, str) or not isinstance(streams, Sequence):
        raise InvalidTypeError(
            f"streams must be a number of streams or a sequence of names, got "
            f"{type(streams).__name__}"
        )
    names = tuple(streams)
    if len(names) < 2:
        raise InvalidArgumentError(f"a synchroniser needs at least 2 streams, got {names!r}")
    for name in names:
        if not isinstance(name, str) or not name:
            raise InvalidTypeError(f"stream names must be non-empty strings, got {name!r}")
    if len(set(names)) != len(names):
        raise InvalidArgumentError(f"stream names must be distinct, got {names!r}")
    return names


def _positive_int(value: object, what: str) -> int:
    if type(value) is not int or value < 1:
        raise InvalidArgumentError(f"{what} must be a positive int, got {value!r}")
    return value


class _Synchronizer(abc.ABC):
    """The shared front end (see the module docstring); subclasses choose the policy."""

    def __init__(
        self,
        streams: int | Sequence[str],
        queue_size: int,
        *,
        clock: StampClock | None,
        key: StampKey | None,
        callback: Callable[..., object] | None,
        max_pending: int,
        diagnostics: StampDiagnostics | None,
        name: str,
    ) -> None:
        self._names = _stream_names(streams)
        self._index = {stream: i for i, stream in enumerate(self._names)}
        self.queue_size = _positive_int(queue_size, "queue_size")
        if clock is not None:
            check_stamp_clock(clock)
        if key is not None and not callable(key):
            raise InvalidTypeError(f"key must be callable, got {type(key).__name__}")
        if callback is not None and not callable(callback):
            raise InvalidTypeError(f"callback must be callable, got {type(callback).__name__}")
        if callback is not None and inspect.iscoroutinefunction(callback):
            raise InvalidTypeError(
                "callback must be a plain function: it runs inside add(); for async "
                "processing iterate instead: async for group in sync: ..."
            )
        if diagnostics is not None and not isinstance(diagnostics, StampDiagnostics):
            raise InvalidTypeError(
                "diagnostics must be an evclock.data.StampDiagnostics, "
                f"got {type(diagnostics).__name__}"
            )
        self._clock = clock
        self._key = key
        self._callback = callback
        self._max_pending = _positive_int(max_pending, "max_pending")
        self._diagnostics = diagnostics
        self.name = name
        self._policy: _Policy = self._make_policy()
        self._pending: deque[Group] = deque()
        self._waiter: asyncio.Future[None] | None = None
        self._closed = False
        self._warned: set[tuple[str, str]] = set()
        self._received = [0] * len(self._names)
        self.groups = 0
        """Groups matched so far."""
        self.groups_dropped = 0
        """Groups discarded because the async consumer had ``max_pending`` unread ones."""

    @abc.abstractmethod
    def _make_policy(self) -> _Policy:
        """The matching policy, built from the validated arguments."""

    # -- input --

    @property
    def streams(self) -> tuple[str, ...]:
        """The stream names, in the order of the messages of each group."""
        return self._names

    def _stream_index(self, stream: int | str) -> int:
        if isinstance(stream, str):
            index = self._index.get(stream)
            if index is None:
                raise InvalidArgumentError(
                    f"unknown stream {stream!r}; this synchroniser has {list(self._names)}"
                )
            return index
        if type(stream) is not int:
            raise InvalidTypeError(
                f"stream must be a name or an index, got {type(stream).__name__}"
            )
        if not 0 <= stream < len(self._names):
            raise InvalidArgumentError(
                f"stream index {stream} out of range: this synchroniser has "
                f"{len(self._names)} streams (0..{len(self._names) - 1})"
            )
        return stream

    @property
    def clock(self) -> StampClock:
        """The clock whose domain stamps are read in (``evclock.clock()`` if not given)."""
        if self._clock is None:
            self._clock = running_clock()
        return self._clock

    def add(self, stream: int | str, message: object) -> None:
        """Offer ``message`` on ``stream`` (a name or an index); may emit groups.

        Call it on the loop's thread (from another thread, hand it over with
        ``loop.call_soon_threadsafe(sync.add, stream, message)``).

        Raises:
            ClockMismatchError: the message's stamp is a :class:`Time` of another domain.
            InvalidTypeError: no stamp can be read from the message (see ``stamp_of``).
        """
        if self._closed:
            raise InvalidArgumentError(f"{self.name} is closed; no more messages can be added")
        index = self._stream_index(stream)
        stamp = stamp_of(message, self.clock.clock_type, self._key)
        self._received[index] += 1
        if self._diagnostics is not None:
            self._diagnostics.observe(self._names[index], stamp)
        groups = self._policy.add(index, stamp.nanoseconds, message)
        self._report_anomalies(index)
        for group in groups:
            self._emit(group)

    def input(self, stream: int | str) -> Callable[[object], None]:
        """A one-argument callable adding messages to ``stream`` (a subscription callback)."""
        index = self._stream_index(stream)

        def add(message: object) -> None:
            self.add(index, message)

        return add

    def _report_anomalies(self, index: int) -> None:
        # Like ROS, warn once per stream and kind; every occurrence is counted in stats().
        for kind, counts, text in (
            ("out_of_order", self._policy.out_of_order, "arrived out of stamp order"),
            (
                "bound",
                self._policy.bound_violations,
                "arrived closer together than its declared lower bound",
            ),
        ):
            key = (kind, self._names[index])
            if counts[index] and key not in self._warned:
                self._warned.add(key)
                _logger.warning(
                    "%s: a message on stream %r %s; the match may be suboptimal "
                    "(counted in stats())",
                    self.name,
                    self._names[index],
                    text,
                )

    # -- output --

    def _emit(self, group: Group) -> None:
        self.groups += 1
        if self._callback is not None:
            self._callback(*group)
            return
        if len(self._pending) >= self._max_pending:
            self._pending.popleft()
            self.groups_dropped += 1
        self._pending.append(group)
        if self._diagnostics is not None:
            self._diagnostics.observe_queue(self.name, len(self._pending))
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def __aiter__(self) -> _Synchronizer:
        if self._callback is not None:
            raise InvalidArgumentError(
                f"{self.name} delivers its groups to its callback; iterate a synchroniser "
                "made without callback="
            )
        return self

    async def __anext__(self) -> Group:
        while not self._pending:
            if self._closed:
                raise StopAsyncIteration
            if self._waiter is not None and not self._waiter.done():
                raise InvalidArgumentError(
                    f"{self.name} is already being iterated by another task; one consumer "
                    "per synchroniser"
                )
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        group = self._pending.popleft()
        if self._diagnostics is not None:
            self._diagnostics.observe_queue(self.name, len(self._pending))
        return group

    def close(self) -> None:
        """No more input: ``async for`` ends once the queued groups have been read."""
        self._closed = True
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    @property
    def pending_groups(self) -> int:
        """Groups matched but not yet read by ``async for``."""
        return len(self._pending)

    def stats(self) -> dict[str, Any]:
        """Counters: per stream received/dropped/out-of-order, and groups (plain numbers)."""
        policy = self._policy
        return {
            "streams": {
                stream: {
                    "received": self._received[i],
                    "dropped": policy.dropped[i],
                    "out_of_order": policy.out_of_order[i],
                    "bound_violations": policy.bound_violations[i],
                }
                for i, stream in enumerate(self._names)
            },
            "groups": self.groups,
            "groups_dropped": self.groups_dropped,
            "held": policy.pending,
            "pending_groups": len(self._pending),
        }

    @property
    def dropped(self) -> dict[str, int]:
        """Messages discarded without being part of a group, by stream."""
        return dict(zip(self._names, self._policy.dropped, strict=True))


class TimeSynchronizer(_Synchronizer):
    """Groups messages whose stamps are exactly equal (ROS ``message_filters`` ExactTime).

    A group is emitted as soon as every stream has a message with the same stamp; incomplete
    sets older than an emitted one are dropped, and at most ``queue_size`` incomplete stamps
    are held (the oldest is dropped first). Dropped messages are counted in :attr:`dropped`.

    :param streams: the number of streams, or their names.
    :param queue_size: incomplete stamps held at most.
    :param clock: stamps are read in its domain (default: ``evclock.clock()`` at the first add).
    :param key: how to read a message's stamp (see :func:`evclock.data.stamp_of`).
    :param callback: called as ``callback(*messages)`` for each group; without it groups are
        read with ``async for group in sync`` (a tuple of messages, in stream order).
    :param max_pending: groups queued for ``async for`` at most; beyond, the oldest is dropped
        and counted in :attr:`groups_dropped`.
    :param diagnostics: a :class:`StampDiagnostics` told every message's stamp and the depth
        of the group queue.
    :param name: how diagnostics and ``evclock run`` label this synchronizer.
    :raises InvalidArgumentError: a non-positive ``queue_size`` or ``max_pending``.
    :raises InvalidTypeError: a non-callable ``key`` or ``callback``, a coroutine function as
        ``callback``, or ``diagnostics`` that is not a :class:`StampDiagnostics`.
    """

    def __init__(
        self,
        streams: int | Sequence[str],
        queue_size: int = 10,
        *,
        clock: StampClock | None = None,
        key: StampKey | None = None,
        callback: Callable[..., object] | None = None,
        max_pending: int = 100,
        diagnostics: StampDiagnostics | None = None,
        name: str = "TimeSynchronizer",
    ) -> None:
        super().__init__(
            streams,
            queue_size,
            clock=clock,
            key=key,
            callback=callback,
            max_pending=max_pending,
            diagnostics=diagnostics,
            name=name,
        )

    def _make_policy(self) -> _Policy:
        return ExactPolicy(len(self._names), self.queue_size)


class ApproximateTimeSynchronizer(_Synchronizer):
    """Groups messages with nearby stamps: ROS's ApproximateTime policy, or slop matching.

    Without ``slop``, the C++ ``message_filters`` ApproximateTime policy: each message is used
    at most once, groups do not cross (per stream, stamps increase from group to group), and
    each group has the smallest spread (latest minus earliest stamp) among the groups that
    start right after the previous one; the groups depend only on the stamps, not on the
    arrival order across streams (as long as no queue overflows). A group is emitted once no
    later message can make a smaller one: declaring each stream's minimum stamp interval
    (``lower_bounds``) lets it be emitted sooner. ``max_interval`` refuses groups wider than
    that. ``age_penalty`` weighs later groups by ``1 + age_penalty`` (ROS 2's C++ code
    defaults to 0.1, the ROS wiki documents 0; evclock defaults to 0: exact minimal spread).

    With ``slop`` (seconds or a :class:`Duration`), ROS Python's
    ``ApproximateTimeSynchronizer(fs, queue_size, slop)``: on each arrival, the nearest
    combination of queued messages whose spread is below ``slop`` is emitted at once. Older
    unmatched messages stay queued, so groups may cross; ``max_interval``, ``age_penalty``
    and ``lower_bounds`` do not apply.

    ``queue_size`` bounds the messages held per stream (waiting or set aside during the
    search); overflow drops the oldest, counted in :attr:`dropped`. Other arguments as
    :class:`TimeSynchronizer`.

    :param streams: the number of streams, or their names.
    :param queue_size: messages held per stream at most.
    :param slop: seconds or a :class:`Duration`: use ROS Python's matching with this
        maximum spread (None: the C++ policy).
    :param max_interval: seconds or a :class:`Duration`: the widest group the C++ policy
        emits (None: no limit).
    :param age_penalty: the C++ policy's weight of later groups (a finite number >= 0).
    :param lower_bounds: each stream's minimum interval between stamps (C++ policy only).
    :param clock: stamps are read in its domain (default: ``evclock.clock()`` at the first add).
    :param key: how to read a message's stamp (see :func:`evclock.data.stamp_of`).
    :param callback: called as ``callback(*messages)`` for each group; without it groups are
        read with ``async for group in sync`` (a tuple of messages, in stream order).
    :param max_pending: groups queued for ``async for`` at most; beyond, the oldest is
        dropped and counted in :attr:`groups_dropped`.
    :param diagnostics: a :class:`StampDiagnostics` told every message's stamp and the
        depth of the group queue.
    :param name: how diagnostics and ``evclock run`` label this synchronizer.
    :raises InvalidArgumentError: ``slop`` combined with a C++-policy option, a zero
        ``slop``, a negative interval, a negative or infinite ``age_penalty``, a
        ``lower_bounds`` of the wrong length, or a non-positive ``queue_size``/``max_pending``.
    :raises InvalidTypeError: a non-callable ``key`` or ``callback``, a coroutine function
        as ``callback``, ``diagnostics`` that is not a :class:`StampDiagnostics`, or an
        argument of the wrong type.

    Example::

        sync = ApproximateTimeSynchronizer(["camera", "lidar"], max_interval=0.02)
        sync.add("camera", image)
        sync.add("lidar", scan)
        async for camera, lidar in sync:
            ...
    """

    def __init__(
        self,
        streams: int | Sequence[str],
        queue_size: int = 10,
        slop: float | Duration | None = None,
        *,
        max_interval: float | Duration | None = None,
        age_penalty: float = 0.0,
        lower_bounds: Sequence[float | Duration] | None = None,
        clock: StampClock | None = None,
        key: StampKey | None = None,
        callback: Callable[..., object] | None = None,
        max_pending: int = 100,
        diagnostics: StampDiagnostics | None = None,
        name: str = "ApproximateTimeSynchronizer",
    ) -> None:
        if slop is not None and (
            max_interval is not None or age_penalty != 0.0 or lower_bounds is not None
        ):
            raise InvalidArgumentError(
                "slop selects ROS Python's matching, which has no max_interval, age_penalty "
                "or lower_bounds; drop slop to use the C++ policy with them (max_interval is "
                "its counterpart of slop)"
            )
        self._slop_ns = None if slop is None else to_nonnegative_nanoseconds(slop, "slop")
        if slop is not None and self._slop_ns == 0:
            raise InvalidArgumentError(
                "slop must be positive (groups need a spread below slop); for equal stamps "
                "use TimeSynchronizer"
            )
        self._max_interval_ns = (
            None
            if max_interval is None
            else to_nonnegative_nanoseconds(max_interval, "max_interval")
        )
        if isinstance(age_penalty, bool) or not isinstance(age_penalty, int | float):
            raise InvalidTypeError(
                f"age_penalty must be a number, got {type(age_penalty).__name__}"
            )
        if not 0.0 <= age_penalty < float("inf"):
            raise InvalidArgumentError(
                f"age_penalty must be a finite number >= 0, got {age_penalty!r}"
            )
        self._age_penalty = float(age_penalty)
        self._lower_bounds_raw = lower_bounds
        super().__init__(
            streams,
            queue_size,
            clock=clock,
            key=key,
            callback=callback,
            max_pending=max_pending,
            diagnostics=diagnostics,
            name=name,
        )

    def _make_policy(self) -> _Policy:
        n = len(self._names)
        if self._slop_ns is not None:
            return SlopPolicy(n, self.queue_size, self._slop_ns)
        bounds: list[int] | None = None
        if self._lower_bounds_raw is not None:
            raw = list(self._lower_bounds_raw)
            if len(raw) != n:
                raise InvalidArgumentError(
                    f"lower_bounds needs one bound per stream ({n}), got {len(raw)}"
                )
            bounds = [to_nonnegative_nanoseconds(b, "lower_bounds item") for b in raw]
        return ApproximatePolicy(
            n,
            self.queue_size,
            age_penalty=self._age_penalty,
            max_interval_ns=self._max_interval_ns,
            lower_bounds_ns=bounds,
        )

    @property
    def slop(self) -> Duration | None:
        """The slop of ROS Python's matching, or None for the C++ policy."""
        return None if self._slop_ns is None else new_duration(self._slop_ns)
