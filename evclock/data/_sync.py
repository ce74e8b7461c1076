"""Synchronisers: group messages of several streams by time stamp, on any evclock clock.

``TimeSynchronizer`` (exact stamps), ``ApproximateTimeSynchronizer`` (ROS's ApproximateTime
policy, or ROS Python's slop matching), ``ApproximateEpsilonTimeSynchronizer`` and
``LatestTimeSynchronizer`` share one front end (``_synchronizer``): messages go in with
``sync.add(stream, msg)`` (or the per-stream callable ``sync.input(stream)``, ready to be a
subscription callback, or ``sync.connect_input(*filters)`` from upstream filters), stamps
are read with :func:`evclock.data.stamp_of` in the clock's domain, and matched groups come
out either to a ``callback(*messages)`` or through ``async for group in sync``. Discarded
messages go to ``on_drop(stream, message, reason)``; a backward jump of the clock (a
simulation reset) clears the state, as tf2_ros's ``Buffer`` clears itself (ROS's
``message_filters`` keeps its state across a jump). The matching itself lives in
``_policies``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.data._diagnostics import StampDiagnostics
from evclock.data._policies import (
    ApproximatePolicy,
    EpsilonPolicy,
    ExactPolicy,
    LatestPolicy,
    RateConfig,
    SlopPolicy,
)
from evclock.data._rosmath import LONG_DOUBLE_BITS, SecondsConvention
from evclock.data._stamped import StampClock, StampKey
from evclock.data._synchronizer import (
    DropCallback,
    Policy,
    Synchronizer,
    ros_nanoseconds,
)
from evclock.time._time import Duration, new_duration

__all__ = [
    "ApproximateEpsilonTimeSynchronizer",
    "ApproximateTimeSynchronizer",
    "DropCallback",
    "LatestTimeSynchronizer",
    "TimeSynchronizer",
]


class TimeSynchronizer(Synchronizer):
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

    def _make_policy(self) -> Policy:
        return ExactPolicy(len(self._names), self.queue_size)


class ApproximateTimeSynchronizer(Synchronizer):
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

    def _make_policy(self) -> Policy:
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


class ApproximateEpsilonTimeSynchronizer(Synchronizer):
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

    def _make_policy(self) -> Policy:
        return EpsilonPolicy(len(self._names), self.queue_size, self._epsilon_ns)

    @property
    def epsilon(self) -> Duration:
        """The widest spread of a group."""
        return new_duration(self._epsilon_ns)


class LatestTimeSynchronizer(Synchronizer):
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

    def _make_policy(self) -> Policy:
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
