"""Message filters on sim time: chaining, a time-indexed cache and a time sequencer.

ROS 2's ``message_filters`` connect filters into pipelines - a subscriber feeds a cache,
the cache feeds a synchroniser - with ``connectInput`` and ``registerCallback``. Here:

* :class:`SimpleFilter` - the plumbing: ``register_callback(cb)`` (returns a
  :class:`Connection`), ``connect_input(upstream)``, ``signal_message(msg)``.
* :class:`PassThrough` - a source: ``add(msg)`` forwards (ROS ``PassThrough``; use its
  ``add`` as a subscription callback where ROS uses a ``Subscriber`` filter).
* :class:`Chain` - filters connected one after the other (ROS ``Chain``).
* :class:`Cache` - the last ``cache_size`` messages sorted by stamp, with ROS C++
  ``Cache``'s queries (interval, surrounding interval, before/after a time, oldest/newest).
* :class:`TimeSequencer` - releases messages in stamp order once ``delay`` of the clock has
  passed since their stamp, checked every ``update_rate``: sim time under a simulation
  (ROS's checks the wall clock).

Synchronisers take filters as inputs with ``sync.connect_input(*filters)``. Every filter
clears itself when the clock jumps backwards (a simulation reset), unless
``reset_on_jump=False``.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable
from typing import Any

from evclock._errors import ClockMismatchError, InvalidArgumentError, InvalidTypeError
from evclock.data._stamped import StampClock, StampKey, check_stamp_clock, stamp_of
from evclock.hosts._current import clock as running_clock
from evclock.kernel._jumps import JumpHandle, TimeJump
from evclock.time._time import Duration, Time, new_duration, to_nanoseconds

__all__ = ["Cache", "Chain", "Connection", "PassThrough", "SimpleFilter", "TimeSequencer"]

_logger = logging.getLogger("evclock.filters")

MessageCallback = Callable[[Any], object]
"""What a filter calls with each message it outputs."""


def weak_jump_handler(method: Callable[[TimeJump], None]) -> Callable[[TimeJump], None]:
    """A jump callback that does not keep ``method``'s object alive (clocks outlive filters).

    :param method: a bound method taking the :class:`TimeJump`.
    :returns: a callback calling it while its object lives, doing nothing after.
    """
    ref = weakref.WeakMethod(method)

    def handler(jump: TimeJump) -> None:
        target = ref()
        if target is not None:
            target(jump)

    return handler


class Connection:
    """A registered callback of a filter; ``disconnect()`` unregisters it.

    Made by :meth:`SimpleFilter.register_callback`, not directly.

    :param registry: the filter's callbacks, keyed by connection number.
    :param key: this connection's number in ``registry``.
    """

    def __init__(self, registry: dict[int, MessageCallback], key: int) -> None:
        self._registry = registry
        self._key = key

    @property
    def connected(self) -> bool:
        """Whether the callback is still registered."""
        return self._key in self._registry

    def disconnect(self) -> None:
        """Stop calling the callback (idempotent)."""
        self._registry.pop(self._key, None)


class SimpleFilter:
    """The base of every filter: outputs go to registered callbacks, in registration order.

    ``add(message)`` is each filter's input; :meth:`connect_input` feeds it from an upstream
    filter.
    """

    def __init__(self) -> None:
        self._callbacks: dict[int, MessageCallback] = {}
        self._next_key = 0
        self._incoming: Connection | None = None

    def register_callback(self, callback: MessageCallback) -> Connection:
        """Call ``callback(message)`` with every message this filter outputs.

        :param callback: a one-argument callable.
        :returns: the :class:`Connection` (``disconnect()`` to stop).
        :raises InvalidTypeError: ``callback`` is not callable.
        """
        if not callable(callback):
            raise InvalidTypeError(f"callback must be callable, got {type(callback).__name__}")
        key = self._next_key
        self._next_key += 1
        self._callbacks[key] = callback
        return Connection(self._callbacks, key)

    def signal_message(self, message: Any) -> None:
        """Output ``message`` to every registered callback.

        :param message: the message.
        """
        for callback in list(self._callbacks.values()):
            callback(message)

    def connect_input(self, upstream: SimpleFilter) -> Connection:
        """Take this filter's input from ``upstream`` (replacing a previous input).

        :param upstream: a filter (anything with ``register_callback``).
        :returns: the connection to ``upstream``.
        :raises InvalidTypeError: ``upstream`` has no ``register_callback``.
        """
        register = getattr(upstream, "register_callback", None)
        if not callable(register):
            raise InvalidTypeError(
                f"connect_input takes a filter with register_callback(), got "
                f"{type(upstream).__name__}"
            )
        if self._incoming is not None:
            self._incoming.disconnect()
        connection: Connection = register(self.add)
        self._incoming = connection
        return connection

    def add(self, message: Any) -> None:
        """Input ``message`` (this base forwards it unchanged).

        :param message: the message.
        """
        self.signal_message(message)


class PassThrough(SimpleFilter):
    """A source filter: ``add(message)`` outputs the message (ROS ``PassThrough``).

    Its ``add`` is the subscription callback of a pipeline.

    :param upstream: a filter to take input from, or None.
    """

    def __init__(self, upstream: SimpleFilter | None = None) -> None:
        super().__init__()
        if upstream is not None:
            self.connect_input(upstream)


class Chain(SimpleFilter):
    """Filters connected one after the other; the chain outputs what the last outputs.

    :param filters: the filters, first to last (at least one).
    :raises InvalidArgumentError: no filter.
    """

    def __init__(self, *filters: SimpleFilter) -> None:
        super().__init__()
        if not filters:
            raise InvalidArgumentError("a Chain needs at least one filter")
        self._filters = list(filters)
        for previous, current in zip(self._filters, self._filters[1:], strict=False):
            current.connect_input(previous)
        self._filters[-1].register_callback(self.signal_message)

    def add(self, message: Any) -> None:
        """Input ``message`` to the first filter.

        :param message: the message.
        """
        self._filters[0].add(message)

    def __getitem__(self, index: int) -> SimpleFilter:
        return self._filters[index]


class _Timed(SimpleFilter):
    """A filter reading stamps in its clock's domain, reset on backward jumps."""

    def __init__(
        self, clock: StampClock | None, key: StampKey | None, reset_on_jump: bool, name: str
    ) -> None:
        super().__init__()
        if clock is not None:
            check_stamp_clock(clock)
        if key is not None and not callable(key):
            raise InvalidTypeError(f"key must be callable, got {type(key).__name__}")
        if not isinstance(reset_on_jump, bool):
            raise InvalidTypeError(
                f"reset_on_jump must be a bool, got {type(reset_on_jump).__name__}"
            )
        self._clock = clock
        self._key = key
        self._reset_on_jump = reset_on_jump
        self._jump_handle: JumpHandle | None = None
        self.name = name
        self.resets = 0
        """How many times the filter was cleared (backward jumps and ``reset()``)."""

    @property
    def clock(self) -> StampClock:
        """The clock whose domain stamps are read in (``evclock.clock()`` if not given)."""
        if self._clock is None:
            self._clock = running_clock()
        if self._jump_handle is None and self._reset_on_jump:
            on_jump = getattr(self._clock, "on_jump", None)
            if callable(on_jump):
                self._jump_handle = on_jump(post=weak_jump_handler(self._on_jump))
        return self._clock

    def _on_jump(self, jump: TimeJump) -> None:
        if jump.delta.nanoseconds < 0:
            _logger.info("%s: the clock jumped back by %s; cleared", self.name, -jump.delta)
            self.reset()

    def reset(self) -> None:
        """Forget the held messages."""
        self.resets += 1

    def _stamp_ns(self, message: Any) -> int:
        return stamp_of(message, self.clock.clock_type, self._key).nanoseconds

    def _time_ns(self, value: Time | float, what: str) -> int:
        if type(value) is Time:
            if value.clock_type is not self.clock.clock_type:
                raise ClockMismatchError(
                    f"{what} is a {value.clock_type.value} time but {self.name} holds "
                    f"{self.clock.clock_type.value} stamps; query with a time of that clock"
                )
            return value.nanoseconds
        return to_nanoseconds(value, what)

    def _time(self, ns: int) -> Time:
        return Time(nanoseconds=ns, clock_type=self.clock.clock_type)

    def _stop_watching(self) -> None:
        if self._jump_handle is not None:
            self._jump_handle.remove()
            self._jump_handle = None


class Cache(_Timed):
    """The last ``cache_size`` messages, sorted by stamp (ROS C++ ``message_filters::Cache``).

    A message is inserted after those with an older or equal stamp (so out-of-order arrivals
    are sorted); when the cache is full the oldest-stamped message is evicted first (as in
    ROS, even when the new message is older still). Each added message is also output to the
    registered callbacks, so a cache sits in a pipeline. Queries take a :class:`Time` of the
    clock's domain or seconds.

    ROS equivalents: ``interval`` = ``getInterval``, ``surrounding`` =
    ``getSurroundingInterval``, ``before`` = ``getElemBeforeTime``, ``after`` =
    ``getElemAfterTime``, ``newest_time`` = ``getLatestTime``, ``oldest_time`` =
    ``getOldestTime``. (ROS Python's ``Cache`` differs: it keeps arrival order and its
    before/after include equal stamps; evclock follows C++.)

    :param upstream: a filter to take input from, or None (then call :meth:`add`).
    :param cache_size: messages kept at most (ROS's default is 1).
    :param clock: stamps are read in its domain (default: ``evclock.clock()`` at first use).
    :param key: how to read a message's stamp (see :func:`evclock.data.stamp_of`).
    :param reset_on_jump: empty the cache when the clock jumps backwards.
    :param name: a label for logs.
    :raises InvalidArgumentError: a non-positive ``cache_size``.
    :raises InvalidTypeError: a non-callable ``key`` or a bad ``clock``.

    Example::

        cache = Cache(cache_size=100)
        cache.add(msg)
        cache.interval(Time(1.0), Time(2.0))
    """

    def __init__(
        self,
        upstream: SimpleFilter | None = None,
        cache_size: int = 1,
        *,
        clock: StampClock | None = None,
        key: StampKey | None = None,
        reset_on_jump: bool = True,
        name: str = "Cache",
    ) -> None:
        super().__init__(clock, key, reset_on_jump, name)
        if type(cache_size) is not int or cache_size < 1:
            raise InvalidArgumentError(f"cache_size must be a positive int, got {cache_size!r}")
        self.cache_size = cache_size
        self._entries: list[tuple[int, Any]] = []
        self.evicted = 0
        """Messages evicted because the cache was full."""
        if upstream is not None:
            self.connect_input(upstream)

    def __len__(self) -> int:
        return len(self._entries)

    def add(self, message: Any) -> None:
        """Insert ``message`` by stamp (evicting the oldest when full), then output it.

        :param message: a stamped message.
        :raises ClockMismatchError: its stamp is a :class:`Time` of another domain.
        :raises InvalidTypeError: no stamp can be read from it.
        """
        stamp = self._stamp_ns(message)
        entries = self._entries
        while len(entries) >= self.cache_size:
            entries.pop(0)
            self.evicted += 1
        position = len(entries)
        while position > 0 and entries[position - 1][0] > stamp:
            position -= 1
        entries.insert(position, (stamp, message))
        self.signal_message(message)

    def interval(self, start: Time | float, end: Time | float) -> list[Any]:
        """The messages stamped in ``[start, end]``, oldest first.

        :param start: the first stamp included.
        :param end: the last stamp included.
        :returns: the messages (empty if none).
        """
        lo, hi = self._time_ns(start, "start"), self._time_ns(end, "end")
        return [message for stamp, message in self._entries if lo <= stamp <= hi]

    def surrounding(self, start: Time | float, end: Time | float) -> list[Any]:
        """The messages of ``[start, end]`` plus the newest at or before ``start`` and the
        oldest at or after ``end`` (ROS ``getSurroundingInterval``: what an interpolation
        over the interval needs). When no message is that old (new), the interval starts
        at the oldest (ends at the newest).

        :param start: the start of the interval.
        :param end: the end of the interval.
        :returns: the messages, oldest first (empty only when the cache is).
        """
        lo, hi = self._time_ns(start, "start"), self._time_ns(end, "end")
        entries = self._entries
        if not entries:
            return []
        first = len(entries) - 1
        while first > 0 and entries[first][0] > lo:
            first -= 1
        last = first
        while last < len(entries) - 1 and entries[last][0] < hi:
            last += 1
        return [message for _, message in entries[first : last + 1]]

    def before(self, time: Time | float) -> Any | None:
        """The newest message stamped strictly before ``time``, or None.

        :param time: the time.
        :returns: the message, or None.
        """
        t = self._time_ns(time, "time")
        found = None
        for stamp, message in self._entries:
            if stamp >= t:
                break
            found = message
        return found

    def after(self, time: Time | float) -> Any | None:
        """The oldest message stamped strictly after ``time``, or None.

        :param time: the time.
        :returns: the message, or None.
        """
        t = self._time_ns(time, "time")
        for stamp, message in self._entries:
            if stamp > t:
                return message
        return None

    @property
    def oldest_time(self) -> Time | None:
        """The oldest stamp held, or None when empty."""
        return self._time(self._entries[0][0]) if self._entries else None

    @property
    def newest_time(self) -> Time | None:
        """The newest stamp held, or None when empty."""
        return self._time(self._entries[-1][0]) if self._entries else None

    @property
    def oldest(self) -> Any | None:
        """The oldest-stamped message, or None when empty."""
        return self._entries[0][1] if self._entries else None

    @property
    def newest(self) -> Any | None:
        """The newest-stamped message, or None when empty."""
        return self._entries[-1][1] if self._entries else None

    def reset(self) -> None:
        """Empty the cache (done on a backward jump of the clock)."""
        self._entries.clear()
        super().reset()


class TimeSequencer(_Timed):
    """Releases messages in stamp order, ``delay`` after their stamp (ROS ``TimeSequencer``).

    Every ``update_rate`` of the clock (sim time under a simulation: the sequencer runs a
    timer of the running loop's clock), the messages with ``stamp + delay <= now`` are output
    oldest first. A message older than the last one released is dropped (``"late"``); beyond
    ``queue_size`` messages, every message sharing the oldest stamp is dropped
    (``"queue_full"``; ROS erases by key from its multiset) - 0 means unbounded.
    ROS's checks the wall clock (``rclcpp::Clock()``) on a wall timer; evclock's follows
    the consumer's clock, so in simulation messages come out at the right sim time.

    :param upstream: a filter to take input from, or None (then call :meth:`add`).
    :param delay: seconds or a :class:`Duration` to hold each message after its stamp.
    :param update_rate: seconds or a :class:`Duration` between release checks.
    :param queue_size: messages held at most (0: no bound).
    :param clock: stamps are read, and time measured, on it (default: ``evclock.clock()``).
    :param key: how to read a message's stamp (see :func:`evclock.data.stamp_of`).
    :param on_drop: called as ``on_drop(message, reason)`` for each dropped message.
    :param reset_on_jump: forget held messages and the last released stamp when the clock
        jumps backwards (otherwise every message after a reset would be late).
    :param name: a label for logs and the timer.
    :raises InvalidArgumentError: a negative ``delay``, a non-positive ``update_rate``, or a
        negative ``queue_size``.
    :raises InvalidTypeError: an argument of the wrong type.
    """

    _count = 0

    def __init__(
        self,
        upstream: SimpleFilter | None = None,
        delay: float | Duration = 0.0,
        update_rate: float | Duration = 0.01,
        queue_size: int = 10,
        *,
        clock: StampClock | None = None,
        key: StampKey | None = None,
        on_drop: Callable[[Any, str], object] | None = None,
        reset_on_jump: bool = True,
        name: str | None = None,
    ) -> None:
        TimeSequencer._count += 1
        super().__init__(clock, key, reset_on_jump, name or f"TimeSequencer-{self._count}")
        self._delay = to_nanoseconds(delay, "delay")
        if self._delay < 0:
            raise InvalidArgumentError(f"delay must not be negative, got {delay!r}")
        self._period = to_nanoseconds(update_rate, "update_rate")
        if self._period <= 0:
            raise InvalidArgumentError(f"update_rate must be positive, got {update_rate!r}")
        if type(queue_size) is not int or queue_size < 0:
            raise InvalidArgumentError(
                f"queue_size must be an int >= 0 (0: no bound), got {queue_size!r}"
            )
        if on_drop is not None and not callable(on_drop):
            raise InvalidTypeError(f"on_drop must be callable, got {type(on_drop).__name__}")
        self.queue_size = queue_size
        self._on_drop = on_drop
        self._messages: list[tuple[int, Any]] = []
        self._last_ns = 0
        self._timer: Any = None
        self.dropped = 0
        """Messages dropped (late, or beyond ``queue_size``)."""
        if upstream is not None:
            self.connect_input(upstream)

    @property
    def delay(self) -> Duration:
        """How long each message is held after its stamp."""
        return new_duration(self._delay)

    def __len__(self) -> int:
        return len(self._messages)

    def _drop(self, message: Any, reason: str) -> None:
        self.dropped += 1
        if self._on_drop is not None:
            self._on_drop(message, reason)

    def add(self, message: Any) -> None:
        """Hold ``message`` until ``stamp + delay``; starts the release timer on first use.

        :param message: a stamped message.
        :raises ClockMismatchError: its stamp is a :class:`Time` of another domain.
        :raises InvalidTypeError: no stamp can be read from it.
        """
        stamp = self._stamp_ns(message)
        self._ensure_timer()
        if stamp < self._last_ns:
            self._drop(message, "late")
            return
        messages = self._messages
        position = len(messages)
        while position > 0 and messages[position - 1][0] > stamp:
            position -= 1
        messages.insert(position, (stamp, message))
        if self.queue_size and len(messages) > self.queue_size:
            oldest = messages[0][0]
            while messages and messages[0][0] == oldest:
                self._drop(messages.pop(0)[1], "queue_full")

    def _ensure_timer(self) -> None:
        if self._timer is None:
            make_timer = getattr(self.clock, "timer", None)
            if callable(make_timer):
                self._timer = make_timer(new_duration(self._period), self.dispatch, name=self.name)

    def dispatch(self) -> None:
        """Output, oldest first, every held message whose ``stamp + delay`` has come.

        Called by the sequencer's timer every ``update_rate``; call it yourself with a
        clock that has no timers.
        """
        now = self.clock.now().nanoseconds
        ready: list[Any] = []
        messages = self._messages
        while messages and messages[0][0] + self._delay <= now:
            stamp, message = messages.pop(0)
            self._last_ns = stamp
            ready.append(message)
        for message in ready:
            self.signal_message(message)

    def reset(self) -> None:
        """Forget the held messages and the last released stamp (dropped as ``"reset"``)."""
        held, self._messages = self._messages, []
        self._last_ns = 0
        if self._timer is not None:  # restarted at the next add, anchored on the new time
            self._timer.cancel()
            self._timer = None
        for _, message in held:
            self._drop(message, "reset")
        super().reset()

    def close(self) -> None:
        """Stop the release timer and stop watching jumps."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._stop_watching()
