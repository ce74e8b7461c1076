"""Synchronisers: group messages of several streams by time stamp, on any evclock clock.

``TimeSynchronizer`` (exact stamps), ``ApproximateTimeSynchronizer`` (ROS's ApproximateTime
policy, or ROS Python's slop matching), ``ApproximateEpsilonTimeSynchronizer`` and
``LatestTimeSynchronizer`` share one front end: messages go in with ``sync.add(stream, msg)``
(or the per-stream callable ``sync.input(stream)``, ready to be a subscription callback, or
``sync.connect_input(*filters)`` from upstream filters), stamps are read with
:func:`evclock.data.stamp_of` in the clock's domain, and matched groups come out either to a
``callback(*messages)`` or through ``async for group in sync``. Discarded messages go to
``on_drop(stream, message, reason)``; a backward jump of the clock (a simulation reset)
clears the state, as tf2_ros's ``Buffer`` clears itself (ROS's ``message_filters`` keeps its
state across a jump). The matching itself lives in ``_policies``.
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
from evclock.data._filters import weak_jump_handler
from evclock.data._policies import (
    ApproximatePolicy,
    EpsilonPolicy,
    ExactPolicy,
    Group,
    LatestPolicy,
    RateConfig,
    SlopPolicy,
)
from evclock.data._rosmath import LONG_DOUBLE_BITS, SecondsConvention, ros_seconds_to_ns
from evclock.data._stamped import StampClock, StampKey, check_stamp_clock, stamp_of
from evclock.hosts._current import clock as running_clock
from evclock.kernel._jumps import JumpHandle, TimeJump
from evclock.time._time import Duration, new_duration, to_nonnegative_nanoseconds

__all__ = [
    "ApproximateEpsilonTimeSynchronizer",
    "ApproximateTimeSynchronizer",
    "DropCallback",
    "LatestTimeSynchronizer",
    "TimeSynchronizer",
]

_logger = logging.getLogger("evclock.sync")

_Policy = ExactPolicy | ApproximatePolicy | SlopPolicy | EpsilonPolicy | LatestPolicy

DropCallback = Callable[[str, Any, str], object]
"""``on_drop(stream, message, reason)``: ``reason`` is a key of ``evclock.data.DROP_REASONS``."""


def ros_nanoseconds(value: object, what: str, convention: SecondsConvention = "ros2") -> int:
    """Seconds (or a :class:`Duration`) to nanoseconds as ROS converts them (truncating).

    A :class:`Duration` is exact; a float is converted like rclpy ``Duration(seconds=...)``
    and rclcpp ``Duration::from_seconds`` (``"ros2"``) or genpy ``Duration.from_sec``
    (``"ros1"``), see ``evclock.data._rosmath``.

    :param value: seconds (int or float) or a :class:`Duration`, not negative.
    :param what: the name used in error messages.
    :param convention: ``"ros2"`` or ``"ros1"``.
    :returns: integer nanoseconds.
    :raises InvalidArgumentError: a negative, NaN or infinite value, or an unknown convention.
    :raises InvalidTypeError: not a number nor a Duration.
    """
    if convention not in ("ros2", "ros1"):
        raise InvalidArgumentError(
            f"seconds_convention must be 'ros2' (rclpy/rclcpp) or 'ros1' (rospy), "
            f"got {convention!r}"
        )
    to_nonnegative_nanoseconds(value, what)  # validates type, sign and finiteness
    if isinstance(value, float):  # numpy.float64 too
        return ros_seconds_to_ns(float(value), convention)
    return to_nonnegative_nanoseconds(value, what)


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
        on_drop: DropCallback | None = None,
        reset_on_jump: bool = True,
    ) -> None:
        self._names = _stream_names(streams)
        self._index = {stream: i for i, stream in enumerate(self._names)}
        self.queue_size = _positive_int(queue_size, "queue_size")
        if clock is not None:
            check_stamp_clock(clock)
        if not isinstance(reset_on_jump, bool):
            raise InvalidTypeError(
                f"reset_on_jump must be a bool, got {type(reset_on_jump).__name__}"
            )
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
        if on_drop is not None and not callable(on_drop):
            raise InvalidTypeError(f"on_drop must be callable, got {type(on_drop).__name__}")
        self._on_drop = on_drop
        self._reset_on_jump = reset_on_jump
        self._jump_handle: JumpHandle | None = None
        self.resets = 0
        """How many times the state was cleared (backward jumps and ``reset()``)."""
        self._clock = clock
        self._key = key
        self._callback = callback
        self._max_pending = _positive_int(max_pending, "max_pending")
        self._diagnostics = diagnostics
        self.name = name
        self._policy: _Policy = self._new_policy()
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

    def _new_policy(self) -> _Policy:
        policy = self._make_policy()
        if self._on_drop is not None:
            policy.on_drop = self._report_drop
        return policy

    def _report_drop(self, index: int, item: object, reason: str) -> None:
        if self._on_drop is not None:
            self._on_drop(self._names[index], item, reason)

    def reset(self) -> None:
        """Forget every held message (each reported to ``on_drop`` with reason ``"reset"``).

        Done automatically when the clock jumps backwards (``reset_on_jump``), as tf2_ros
        clears its buffer when sim time goes back (ROS's ``message_filters`` does not, and
        would pair a message from before a reset with one after it). Counters are kept;
        groups already matched but not read stay queued.
        """
        old = self._policy
        held = list(old.held())
        self._policy = self._new_policy()
        for counter in ("dropped", "out_of_order", "bound_violations"):
            setattr(self._policy, counter, list(getattr(old, counter)))
        for index, item in held:
            self._policy._discard(index, item, "reset")
        self.resets += 1

    def _on_jump(self, jump: TimeJump) -> None:
        if jump.delta.nanoseconds < 0:
            _logger.info("%s: the clock jumped back by %s; state cleared", self.name, -jump.delta)
            self.reset()

    def _watch_jumps(self, clock: StampClock) -> None:
        on_jump = getattr(clock, "on_jump", None)
        if self._reset_on_jump and self._jump_handle is None and callable(on_jump):
            self._jump_handle = on_jump(post=weak_jump_handler(self._on_jump))

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
        if self._jump_handle is None:
            self._watch_jumps(self._clock)
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
        """A one-argument callable adding messages to ``stream`` (a subscription callback).

        :param stream: a stream name or index.
        :returns: ``add(message)`` for that stream.
        :raises InvalidArgumentError: an unknown stream.
        """
        index = self._stream_index(stream)

        def add(message: object) -> None:
            self.add(index, message)

        return add

    def connect_input(self, *filters: Any) -> list[Any]:
        """Feed each stream from an upstream filter, in stream order (ROS ``connectInput``).

        Each filter is anything with ``register_callback(callback)`` - a
        :class:`~evclock.data.PassThrough`, a :class:`~evclock.data.Cache`, a
        :class:`~evclock.data.TimeSequencer`, or a synchroniser's own stream.

        :param filters: one upstream filter per stream.
        :returns: the connections (``disconnect()`` each to stop).
        :raises InvalidArgumentError: not exactly one filter per stream.
        :raises InvalidTypeError: a filter without ``register_callback``.
        """
        if len(filters) != len(self._names):
            raise InvalidArgumentError(
                f"connect_input needs one filter per stream ({len(self._names)}: "
                f"{list(self._names)}), got {len(filters)}"
            )
        for upstream in filters:
            if not callable(getattr(upstream, "register_callback", None)):
                raise InvalidTypeError(
                    "connect_input takes filters with register_callback() (PassThrough, Cache, "
                    f"TimeSequencer), got {type(upstream).__name__}"
                )
        return [
            upstream.register_callback(self.input(index)) for index, upstream in enumerate(filters)
        ]

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
        if self._jump_handle is not None:
            self._jump_handle.remove()
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
            "resets": self.resets,
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
    :param on_drop: called as ``on_drop(stream, message, reason)`` for every message
        discarded without being part of a group (reasons: ``evclock.data.DROP_REASONS``).
    :param reset_on_jump: clear the state when the clock jumps backwards (a simulation
        reset), as tf2_ros's buffer does; held messages are reported with reason ``"reset"``.
    :raises InvalidArgumentError: a non-positive ``queue_size`` or ``max_pending``.
    :raises InvalidTypeError: a non-callable ``key``, ``callback`` or ``on_drop``, a coroutine
        function as ``callback``, or ``diagnostics`` that is not a :class:`StampDiagnostics`.
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
        on_drop: DropCallback | None = None,
        reset_on_jump: bool = True,
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
            on_drop=on_drop,
            reset_on_jump=reset_on_jump,
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

    Bit-exact with ROS: ``age_penalty`` weighs with rclcpp's ``Duration * double`` in
    ``long double`` (``long_double_bits``: 64 on x86-64 Linux, the default; 113 on aarch64
    Linux; 53 with MSVC and on Apple silicon), and float seconds (``slop``,
    ``max_interval``, ``lower_bounds``) are truncated to nanoseconds as rclpy and rclcpp's
    ``Duration::from_seconds`` do (``seconds_convention="ros1"``: as rospy), so ``1.001``
    is 1_000_999_999 ns. A :class:`Duration` is taken exactly.

    :param streams: the number of streams, or their names.
    :param queue_size: messages held per stream at most.
    :param slop: seconds or a :class:`Duration`: use ROS Python's matching with this
        maximum spread (None: the C++ policy).
    :param max_interval: seconds or a :class:`Duration`: the widest group the C++ policy
        emits (None: no limit).
    :param age_penalty: the C++ policy's weight of later groups (a finite number >= 0).
    :param lower_bounds: each stream's minimum interval between stamps (C++ policy only).
    :param long_double_bits: the significand of the ``long double`` whose ``age_penalty``
        arithmetic to reproduce: 64, 113 or 53.
    :param seconds_convention: how float seconds become nanoseconds: ``"ros2"`` (rclpy,
        rclcpp) or ``"ros1"`` (rospy).
    :param on_drop: called as ``on_drop(stream, message, reason)`` for every message
        discarded without being part of a group (reasons: ``evclock.data.DROP_REASONS``).
    :param reset_on_jump: clear the state when the clock jumps backwards (a simulation
        reset), as tf2_ros's buffer does.
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
        long_double_bits: int = 64,
        seconds_convention: SecondsConvention = "ros2",
        clock: StampClock | None = None,
        key: StampKey | None = None,
        callback: Callable[..., object] | None = None,
        max_pending: int = 100,
        diagnostics: StampDiagnostics | None = None,
        name: str = "ApproximateTimeSynchronizer",
        on_drop: DropCallback | None = None,
        reset_on_jump: bool = True,
    ) -> None:
        if slop is not None and (
            max_interval is not None or age_penalty != 0.0 or lower_bounds is not None
        ):
            raise InvalidArgumentError(
                "slop selects ROS Python's matching, which has no max_interval, age_penalty "
                "or lower_bounds; drop slop to use the C++ policy with them (max_interval is "
                "its counterpart of slop)"
            )
        if long_double_bits not in LONG_DOUBLE_BITS:
            raise InvalidArgumentError(
                f"long_double_bits must be 64 (x86-64), 113 (aarch64) or 53 (MSVC, Apple "
                f"silicon), got {long_double_bits!r}"
            )
        self._bits = long_double_bits
        if seconds_convention not in ("ros2", "ros1"):
            ros_nanoseconds(0, "slop", seconds_convention)  # raises, naming the choices
        self._convention = seconds_convention
        self._slop_ns = None if slop is None else ros_nanoseconds(slop, "slop", seconds_convention)
        if slop is not None and self._slop_ns == 0:
            raise InvalidArgumentError(
                "slop must be positive (groups need a spread below slop); for equal stamps "
                "use TimeSynchronizer"
            )
        self._max_interval_ns = (
            None
            if max_interval is None
            else ros_nanoseconds(max_interval, "max_interval", seconds_convention)
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
            on_drop=on_drop,
            reset_on_jump=reset_on_jump,
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
            bounds = [ros_nanoseconds(b, "lower_bounds item", self._convention) for b in raw]
        return ApproximatePolicy(
            n,
            self.queue_size,
            age_penalty=self._age_penalty,
            max_interval_ns=self._max_interval_ns,
            lower_bounds_ns=bounds,
            long_double_bits=self._bits,
        )

    @property
    def slop(self) -> Duration | None:
        """The slop of ROS Python's matching, or None for the C++ policy."""
        return None if self._slop_ns is None else new_duration(self._slop_ns)


class ApproximateEpsilonTimeSynchronizer(_Synchronizer):
    """Groups messages whose stamps lie within ``epsilon`` of the oldest: ROS 2's
    ``message_filters`` ApproximateEpsilonTime policy (C++, Jazzy and later).

    Messages wait per stream in arrival order. Once every stream has one, the oldest head
    (the first stream among equal stamps) is the reference: if every other head is at most
    ``epsilon`` after it, the heads are emitted as a group; otherwise every head within
    ``epsilon`` of the reference (itself included) is dropped (reason ``"no_partner"``) and
    the search goes on. Simpler and cheaper than ApproximateTime, with no optimality search:
    a group comes out as soon as its last message arrives. ``queue_size`` bounds a stream
    that keeps receiving while another is empty (the oldest is dropped).

    :param streams: the number of streams, or their names.
    :param queue_size: messages held per stream while another stream is empty.
    :param epsilon: seconds or a :class:`Duration`: the widest spread of a group (float
        seconds are truncated to nanoseconds as rclcpp's ``Duration::from_seconds``).
    :param clock: stamps are read in its domain (default: ``evclock.clock()`` at the first add).
    :param key: how to read a message's stamp (see :func:`evclock.data.stamp_of`).
    :param callback: called as ``callback(*messages)`` for each group; without it groups are
        read with ``async for group in sync``.
    :param max_pending: groups queued for ``async for`` at most.
    :param diagnostics: a :class:`StampDiagnostics` told every message's stamp.
    :param name: how diagnostics and ``evclock run`` label this synchronizer.
    :param on_drop: called as ``on_drop(stream, message, reason)`` for every discarded message.
    :param reset_on_jump: clear the state when the clock jumps backwards.
    :raises InvalidArgumentError: a negative ``epsilon``, or a non-positive ``queue_size``
        or ``max_pending``.
    :raises InvalidTypeError: an argument of the wrong type.

    Example::

        sync = ApproximateEpsilonTimeSynchronizer(["camera", "lidar"], 10, epsilon=0.01)
    """

    def __init__(
        self,
        streams: int | Sequence[str],
        queue_size: int = 10,
        epsilon: float | Duration = 0.0,
        *,
        clock: StampClock | None = None,
        key: StampKey | None = None,
        callback: Callable[..., object] | None = None,
        max_pending: int = 100,
        diagnostics: StampDiagnostics | None = None,
        name: str = "ApproximateEpsilonTimeSynchronizer",
        on_drop: DropCallback | None = None,
        reset_on_jump: bool = True,
    ) -> None:
        self._epsilon_ns = ros_nanoseconds(epsilon, "epsilon")
        super().__init__(
            streams,
            queue_size,
            clock=clock,
            key=key,
            callback=callback,
            max_pending=max_pending,
            diagnostics=diagnostics,
            name=name,
            on_drop=on_drop,
            reset_on_jump=reset_on_jump,
        )

    def _make_policy(self) -> _Policy:
        return EpsilonPolicy(len(self._names), self.queue_size, self._epsilon_ns)

    @property
    def epsilon(self) -> Duration:
        """The widest spread of a group."""
        return new_duration(self._epsilon_ns)


class LatestTimeSynchronizer(_Synchronizer):
    """Emits the latest message of every stream at the rate of the fastest: ROS 2's
    ``message_filters`` LatestTime policy (C++, Jazzy and later), on evclock's clock.

    Slower streams are repeated (zero-order hold, no interpolation). Each stream's arrival
    rate is estimated from the clock's ``now()`` at each ``add`` - sim time under a
    simulation, so the rates are those of sim time, never of the wall clock - and a group is
    emitted when a message arrives on the *pivot*: the fastest stream whose next message is
    not late (a stream found late, e.g. because it slowed down, hands the pivot to the next
    fastest). Nothing comes out until every stream delivered once and the pivot twice.
    Messages need no stamp. A held message replaced before any group used it is dropped
    (reason ``"replaced"``, or ``"waiting_for_all_streams"`` before every stream delivered).

    The only deliberate difference from ROS: the rate estimates are kept per stream (ROS
    indexes them by order of first arrival; the two agree when the streams first deliver
    in stream order or at one instant).

    :param streams: the number of streams, or their names.
    :param rate_config: ``(rate_ema_alpha, error_ema_alpha, rate_step_change_margin_factor)``
        for every stream, or one such triple per stream (ROS's ``setRateConfig`` and
        ``setRateConfigPerMessage``; default ``(0.9, 0.3, 10.0)``).
    :param clock: the clock whose ``now()`` times the arrivals (default: ``evclock.clock()``).
    :param callback: called as ``callback(*messages)`` for each group; without it groups are
        read with ``async for group in sync``.
    :param max_pending: groups queued for ``async for`` at most.
    :param name: how ``evclock run`` labels this synchronizer.
    :param on_drop: called as ``on_drop(stream, message, reason)`` for every discarded message.
    :param reset_on_jump: clear the state (held messages and rates) when the clock jumps
        backwards.
    :raises InvalidArgumentError: a malformed ``rate_config`` or a non-positive ``max_pending``.
    :raises InvalidTypeError: an argument of the wrong type.
    """

    def __init__(
        self,
        streams: int | Sequence[str],
        *,
        rate_config: RateConfig | Sequence[RateConfig] | None = None,
        clock: StampClock | None = None,
        callback: Callable[..., object] | None = None,
        max_pending: int = 100,
        name: str = "LatestTimeSynchronizer",
        on_drop: DropCallback | None = None,
        reset_on_jump: bool = True,
    ) -> None:
        self._rate_config = rate_config
        super().__init__(
            streams,
            1,
            clock=clock,
            key=None,
            callback=callback,
            max_pending=max_pending,
            diagnostics=None,
            name=name,
            on_drop=on_drop,
            reset_on_jump=reset_on_jump,
        )

    def _make_policy(self) -> _Policy:
        n = len(self._names)
        config = self._rate_config
        if config is None:
            return LatestPolicy(n)
        configs: list[RateConfig]
        if len(config) == 3 and all(isinstance(v, int | float) for v in config):
            configs = [_rate_config(config)] * n
        elif len(config) == n:
            configs = [_rate_config(c) for c in config]
        else:
            raise InvalidArgumentError(
                f"rate_config must be one (rate_ema_alpha, error_ema_alpha, margin_factor) "
                f"triple or one per stream ({n}), got {config!r}"
            )
        return LatestPolicy(n, configs)

    def add(self, stream: int | str, message: object) -> None:
        """Offer ``message`` on ``stream`` (a name or an index), timed by ``clock.now()``.

        :param stream: a stream name or index.
        :param message: any object (no stamp is read).
        :raises InvalidArgumentError: an unknown stream, or a closed synchroniser.
        """
        if self._closed:
            raise InvalidArgumentError(f"{self.name} is closed; no more messages can be added")
        index = self._stream_index(stream)
        now = self.clock.now()
        self._received[index] += 1
        for group in self._policy.add(index, now.nanoseconds, message):
            self._emit(group)


def _rate_config(value: object) -> RateConfig:
    if (
        not isinstance(value, tuple | list)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise InvalidArgumentError(
            "a rate config is (rate_ema_alpha, error_ema_alpha, rate_step_change_margin_factor)"
            f", three numbers, got {value!r}"
        )
    return (float(value[0]), float(value[1]), float(value[2]))
