"""The synchronisers' shared front end: streams by index or name, messages in with
``add``/``input``/``connect_input``, stamps read in the clock's domain, groups out to a
callback or ``async for``, drops reported, and the state cleared on a backward jump. Each
synchroniser in ``_sync`` adds its matching policy (from ``_policies``).
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
    SlopPolicy,
)
from evclock.data._rosmath import SecondsConvention, ros_seconds_to_ns
from evclock.data._stamped import StampClock, StampKey, check_stamp_clock, stamp_of
from evclock.hosts._current import clock as running_clock
from evclock.kernel._jumps import JumpHandle, TimeJump
from evclock.time._time import to_nonnegative_nanoseconds

__all__ = ["DropCallback", "Policy", "Synchronizer", "ros_nanoseconds"]

_logger = logging.getLogger("evclock.sync")

Policy = ExactPolicy | ApproximatePolicy | SlopPolicy | EpsilonPolicy | LatestPolicy

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


class Synchronizer(abc.ABC):
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
        self._policy: Policy = self._new_policy()
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
    def _make_policy(self) -> Policy:
        """The matching policy, built from the validated arguments."""

    def _new_policy(self) -> Policy:
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

    def __aiter__(self) -> Synchronizer:
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
