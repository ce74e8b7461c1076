"""Drift-free rate loops and timers on any clock, with missed-period accounting."""

from __future__ import annotations

import asyncio
import collections
import inspect
import math
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Literal

from evclock._errors import (
    ClockJumpedError,
    InvalidArgumentError,
    InvalidTypeError,
    NotRunningError,
)
from evclock.time._time import (
    MAX_TIME_NS,
    ClockType,
    Duration,
    Time,
    format_time_range_error,
    new_duration,
    new_time,
    real_number,
    to_nanoseconds,
    whole_number,
)

if TYPE_CHECKING:
    from fractions import Fraction

    from evclock.kernel._clock import Clock

Policy = Literal["skip", "catch_up", "reset"]
_POLICIES: tuple[str, ...] = ("skip", "catch_up", "reset")
_RECENT = 4096


def _period_fraction(hz: object) -> Fraction:
    """The exact period in nanoseconds of a rate of ``hz`` (any real number but bool)."""
    from fractions import Fraction  # at rate creation, off `import evclock`

    if isinstance(hz, Fraction):
        exact = hz
    elif (whole := whole_number(hz)) is not None:
        exact = Fraction(whole)
    elif (value := real_number(hz)) is not None:
        if not math.isfinite(value):
            raise InvalidArgumentError(f"rate must be a finite number of hertz, got {hz!r}")
        exact = Fraction(value)
    else:
        raise InvalidTypeError(f"rate must be a number of hertz, got {type(hz).__name__}")
    if exact <= 0:
        raise InvalidArgumentError(
            f"rate must be positive, got {hz!r} Hz; for a one-off delay use clock.sleep()"
        )
    period = Fraction(10**9) / exact
    if period < 1:
        raise InvalidArgumentError(f"rate {hz!r} Hz is above 1 GHz: the period is under 1 ns")
    return period


def _format_hz(hz: object) -> str:
    """A rate for a default name: ``100``, ``0.5``, ``1/3``."""
    from fractions import Fraction

    if isinstance(hz, Fraction):
        return str(hz)
    value = real_number(hz)
    return f"{value:g}" if value is not None else str(hz)


def _check_policy(policy: object) -> Policy:
    if policy not in _POLICIES:
        raise InvalidArgumentError(
            f"policy must be one of {', '.join(repr(p) for p in _POLICIES)}, got {policy!r}"
        )
    return policy  # type: ignore[return-value]


def last_deadline_index(start_ns: int, now_ns: int, num: int, den: int) -> int:
    """The index of the last deadline at or before ``now_ns`` of a schedule whose deadline
    ``i`` is ``start_ns + floor(i x num / den)`` (the period is ``num/den`` ns, exactly).

    :param start_ns: deadline 0, in integer nanoseconds (at or before ``now_ns``).
    :param now_ns: the time, in integer nanoseconds.
    :param num: the period's numerator, in nanoseconds.
    :param den: the period's denominator.
    :returns: the largest ``i`` with ``start_ns + i * num // den <= now_ns``.
    """
    # floor(i*num/den) <= n  <=>  i*num < (n+1)*den  <=>  i <= ((n+1)*den - 1) // num
    return ((now_ns - start_ns + 1) * den - 1) // num


class DeadlineGrid:
    """The drift-free deadlines of a :class:`Rate` (``start + i x period`` in exact integer
    nanoseconds) for code that is not a task awaiting them: it asks, at times of its own
    (each physics step, for the recorder), whether a deadline is due, and serves the last
    one passed (missed ones are skipped, as ``Rate``'s ``"skip"`` policy does). ``next_ns``
    is the next deadline not served yet.

    :param period_ns: the period in nanoseconds (an int or an exact ``Fraction``; positive).
    :raises InvalidArgumentError: the period is not positive.
    """

    __slots__ = ("_den", "_index", "_num", "_start", "next_ns")

    def __init__(self, period_ns: int | Fraction) -> None:
        from fractions import Fraction

        period = Fraction(period_ns)
        if period <= 0:
            raise InvalidArgumentError(f"a deadline grid needs a positive period, got {period}")
        self._num = period.numerator
        self._den = period.denominator
        self._start = 0
        self._index = 0
        self.next_ns = 0

    def start(self, start_ns: int) -> None:
        """Anchor the grid: deadline 0 is ``start_ns`` (also after a clock jump).

        :param start_ns: the first deadline, in integer nanoseconds.
        """
        self._start = self.next_ns = start_ns
        self._index = 0

    def serve(self, now_ns: int) -> int:
        """Serve the last deadline at or before ``now_ns`` (call when ``now_ns >=
        next_ns``); the next one becomes :attr:`next_ns`.

        :param now_ns: the time, in integer nanoseconds.
        :returns: how many deadlines before it were passed without being served.
        """
        passed = last_deadline_index(self._start, now_ns, self._num, self._den)
        missed = passed - self._index
        self._index = passed + 1
        self.next_ns = self._start + self._index * self._num // self._den
        return missed


class Tick:
    """One iteration of a rate loop.

    ``expected``: the deadline this tick stands for; ``actual``: when it was delivered;
    ``missed``: deadlines since the previous tick that got no tick at all. The integer
    ``expected_ns``/``actual_ns`` are there too; the ``Time`` objects are built on access
    (a 1 kHz loop should not pay for what its body does not read).

    Made by :class:`Rate`, not directly.

    :param index: the number of this deadline in the schedule (tick 0 is the start).
    :param expected_ns: the deadline, in integer nanoseconds.
    :param actual_ns: when the tick was delivered, in integer nanoseconds.
    :param missed: deadlines skipped since the previous tick.
    :param clock_type: the clock type of the ``expected``/``actual`` Time objects.
    """

    __slots__ = ("_clock_type", "actual_ns", "expected_ns", "index", "missed")

    def __init__(
        self, index: int, expected_ns: int, actual_ns: int, missed: int, clock_type: ClockType
    ) -> None:
        self.index = index
        self.expected_ns = expected_ns
        self.actual_ns = actual_ns
        self.missed = missed
        self._clock_type = clock_type

    @property
    def expected(self) -> Time:
        """The deadline this tick stands for."""
        return new_time(self.expected_ns, self._clock_type)

    @property
    def actual(self) -> Time:
        """When the tick was delivered."""
        return new_time(self.actual_ns, self._clock_type)

    @property
    def lateness(self) -> Duration:
        """``actual - expected`` (zero on an unloaded virtual clock)."""
        return new_duration(self.actual_ns - self.expected_ns)

    def _key(self) -> tuple[int, int, int, int, ClockType]:
        return (self.index, self.expected_ns, self.actual_ns, self.missed, self._clock_type)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Tick) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return (
            f"Tick(index={self.index}, expected={self.expected}, actual={self.actual}, "
            f"missed={self.missed})"
        )


_new_tick = object.__new__  # a Tick whose slots Rate.__anext__ fills


class LoopStats:
    """Running statistics of a rate loop or timer: ticks, missed periods, lateness."""

    def __init__(self) -> None:
        self.ticks = 0
        self.missed = 0
        self.max_lateness_ns = 0
        self.total_lateness_ns = 0
        self.recent_lateness_ns: collections.deque[int] = collections.deque(maxlen=_RECENT)

    def record(self, lateness_ns: int, missed: int) -> None:
        """Count one tick, ``lateness_ns`` after its deadline, with ``missed`` periods skipped."""
        self.ticks += 1
        if missed:
            self.missed += missed
        if lateness_ns:
            self.total_lateness_ns += lateness_ns
            if lateness_ns > self.max_lateness_ns:
                self.max_lateness_ns = lateness_ns
        self.recent_lateness_ns.append(lateness_ns)

    @property
    def mean_lateness(self) -> Duration:
        """Mean lateness over every tick."""
        return new_duration(self.total_lateness_ns // self.ticks if self.ticks else 0)

    @property
    def max_lateness(self) -> Duration:
        """Worst lateness seen."""
        return new_duration(self.max_lateness_ns)

    def percentile(self, q: float) -> Duration:
        """Lateness percentile ``q`` (0-100) over the most recent ticks (nearest rank)."""
        if not 0 <= q <= 100:
            raise InvalidArgumentError(f"percentile must be within [0, 100], got {q!r}")
        data = sorted(self.recent_lateness_ns)
        if not data:
            return new_duration(0)
        rank = max(math.ceil(q / 100 * len(data)) - 1, 0)
        return new_duration(data[rank])

    def as_dict(self) -> dict[str, float | int]:
        """Plain numbers (seconds) for reports and JSON."""
        return {
            "ticks": self.ticks,
            "missed": self.missed,
            "mean_lateness_s": self.mean_lateness.seconds,
            "p99_lateness_s": self.percentile(99).seconds,
            "max_lateness_s": self.max_lateness.seconds,
        }


class Rate:
    """A drift-free periodic schedule: ``async for tick in clock.rate(hz): ...``.

    Deadline ``i`` is ``start + i x period`` computed exactly in integers, so a 1 kHz loop
    run for 24 simulated hours ends on the exact nanosecond. Tick 0 is delivered at once.
    When the body overruns, ``policy`` decides: ``"skip"`` (default, like ROS) delivers one
    late tick for the latest passed deadline and skips the others; ``"catch_up"`` delivers
    every missed tick at once, in a burst; ``"reset"`` delivers one late tick and re-anchors
    the schedule on the current time. A clock jump re-anchors the schedule too.

    Create with :meth:`Clock.rate`.

    :param clock: the clock whose time the deadlines are on.
    :param hz: the frequency in hertz (a positive, finite number).
    :param policy: ``"skip"``, ``"catch_up"`` or ``"reset"``: what an overrun does.
    :param name: a label for statistics and diagnostics (default ``rate-<hz>Hz``).
    :raises InvalidTypeError: ``hz`` is not a number.
    :raises InvalidArgumentError: ``hz`` is not positive and finite, or ``policy`` is unknown.
    """

    def __init__(
        self, clock: Clock, hz: float, policy: Policy = "skip", name: str | None = None
    ) -> None:
        period = _period_fraction(hz)
        self._policy = _check_policy(policy)
        self._clock = clock
        self._num = period.numerator
        self._den = period.denominator
        self.hz = hz
        self.name = name if name is not None else f"rate-{_format_hz(hz)}Hz"
        self.stats = LoopStats()
        self._start: int | None = None
        self._index = -1
        self._closed = False
        # On sim time the kernel's clock is read as a plain attribute (the hot path of every
        # rate loop: two reads per tick); other clocks through now_ns().
        self._core = getattr(clock, "core", None)
        self._clock_type = clock.clock_type

    @property
    def period(self) -> Duration:
        """The period, rounded to the nearest nanosecond (deadlines themselves are exact)."""
        from fractions import Fraction

        return new_duration(round(Fraction(self._num, self._den)))

    @property
    def policy(self) -> Policy:
        """What an overrun does: ``"skip"``, ``"catch_up"`` or ``"reset"``."""
        return self._policy

    def _deadline(self, index: int) -> int:
        start = self._start
        if start is None:
            raise NotRunningError("the rate has not started: iterate it first")
        return start + index * self._num // self._den

    def __aiter__(self) -> Rate:
        return self

    async def __anext__(self) -> Tick:
        if self._closed:
            raise StopAsyncIteration
        clock = self._clock
        core = self._core
        now = clock.now_ns() if core is None else core.now_ns
        start = self._start
        if start is None:
            self._start, self._index = now, 0
            return self._tick(0, now, now, 0)
        index = self._index + 1
        deadline = start + index * self._num // self._den
        if now < deadline:
            try:
                await clock.sleep_until_ns(deadline)
            except ClockJumpedError:
                return self._reanchor()
            now = clock.now_ns() if core is None else core.now_ns
            if now < deadline:
                # Woken as due, then the clock jumped back before this task ran.
                return self._reanchor()
            # The common case, on time or late by less than a period: _tick and
            # LoopStats.record inlined (every rate loop's hot path).
            self._index = index
            stats = self.stats
            stats.ticks += 1
            lateness = now - deadline
            if lateness:
                stats.total_lateness_ns += lateness
                if lateness > stats.max_lateness_ns:
                    stats.max_lateness_ns = lateness
            stats.recent_lateness_ns.append(lateness)
            # Tick.__init__, inlined (one frame fewer per tick): its slots, as there.
            tick = _new_tick(Tick)
            tick.index = index
            tick.expected_ns = deadline
            tick.actual_ns = now
            tick.missed = 0
            tick._clock_type = self._clock_type
            return tick
        passed = last_deadline_index(start, now, self._num, self._den)
        if self._policy == "catch_up":
            return self._tick(index, deadline, now, 0)
        if self._policy == "skip":
            return self._tick(passed, self._deadline(passed), now, passed - index)
        tick = self._tick(index, deadline, now, passed - index)
        self._start, self._index = now, 0
        return tick

    def _reanchor(self) -> Tick:
        """After a clock jump: restart the schedule at the current time with tick 0."""
        now = self._clock.now_ns()
        self._start, self._index = now, 0
        return self._tick(0, now, now, 0)

    def _tick(self, index: int, expected: int, actual: int, missed: int) -> Tick:
        self._index = index
        self.stats.record(actual - expected, missed)
        return Tick(index, expected, actual, missed, self._clock_type)

    async def sleep(self) -> Tick:
        """Wait for the next tick (the ROS ``Rate.sleep`` style of use)."""
        return await self.__anext__()

    def close(self) -> None:
        """End the iteration: the next ``__anext__`` raises StopAsyncIteration."""
        self._closed = True

    def __repr__(self) -> str:
        return f"<Rate {self.name!r} {self.hz:g} Hz policy={self._policy}>"


TimerCallback = Callable[[], object] | Callable[[], Awaitable[object]]


class Timer:
    """Calls ``callback`` every ``period`` (or once, ``oneshot=True``) on a clock.

    Create with :meth:`Clock.timer` from a running loop. Sync and async callbacks both
    work; an async one is awaited before the next period is scheduled. Periodic deadlines
    are drift-free; an overrun skips the missed periods (counted in ``stats.missed``).
    If the callback raises, the error goes to the loop's exception handler and the timer
    stops (``exception()`` returns it).

    :param clock: the clock whose time the deadlines are on.
    :param period: the period, in seconds or as a :class:`Duration`.
    :param callback: called with no arguments each period; may be a coroutine function.
    :param oneshot: call once, after one period, then stop.
    :param name: a label for statistics and diagnostics (default: the callback's name).
    :raises InvalidTypeError: ``callback`` is not callable, or ``period`` is not a number
        or a Duration.
    :raises InvalidArgumentError: ``period`` is not positive or is out of range.
    """

    def __init__(
        self,
        clock: Clock,
        period: Duration | float,
        callback: TimerCallback,
        *,
        oneshot: bool = False,
        name: str | None = None,
    ) -> None:
        if not callable(callback):
            raise InvalidTypeError(
                f"timer callback must be callable, got {type(callback).__name__}"
            )
        period_ns = to_nanoseconds(period, "timer period")
        if period_ns > MAX_TIME_NS:
            raise InvalidArgumentError(format_time_range_error("timer period", period_ns))
        if period_ns <= 0:
            raise InvalidArgumentError(f"timer period must be positive, got {period!r}")
        self._clock = clock
        self._period_ns = period_ns
        self._callback = callback
        self.oneshot = bool(oneshot)
        self.name = name if name is not None else getattr(callback, "__name__", "timer")
        self.stats = LoopStats()
        self._loop = asyncio.get_running_loop()
        self._exception: BaseException | None = None
        self._next_ns: int | None = None
        self._task: asyncio.Task[None] | None = None
        self._canceled = False
        self._start()

    def _start(self) -> None:
        anchor = self._clock.now_ns()
        self._next_ns = anchor + self._period_ns
        self._task = self._loop.create_task(self._run(anchor), name=f"evclock-timer-{self.name}")

    async def _run(self, start: int) -> None:
        clock = self._clock
        index = 1
        if clock.now_ns() < start:
            # The clock jumped back between the timer's creation and this task's start (a
            # reset at the same instant): anchor on the time after the jump, as a jump
            # while it waits would.
            start = clock.now_ns()
        while True:
            self._next_ns = deadline = start + index * self._period_ns
            try:
                await clock.sleep_until_ns(deadline)
            except ClockJumpedError:
                start, index = clock.now_ns(), 1
                continue
            now = clock.now_ns()
            if now < deadline:  # woken as due, then the clock jumped back: re-anchor
                start, index = now, 1
                continue
            self.stats.record(now - deadline, 0)
            try:
                result = self._callback()
                if inspect.isawaitable(result):
                    await result
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self._fail(exc)
                return
            if self.oneshot:
                self._next_ns = None
                return
            # An overrunning callback skips the deadlines that passed meanwhile.
            following = max(index + 1, (clock.now_ns() - start) // self._period_ns + 1)
            self.stats.missed += following - index - 1
            index = following

    def _fail(self, exc: BaseException) -> None:
        self._exception = exc
        self._next_ns = None
        self._canceled = True
        self._loop.call_exception_handler(
            {
                "message": f"evclock timer {self.name!r}: callback raised; timer stopped",
                "exception": exc,
            }
        )

    @property
    def period(self) -> Duration:
        """The time between two calls of the callback."""
        return new_duration(self._period_ns)

    @property
    def is_canceled(self) -> bool:
        """True after :meth:`cancel` or a failing callback."""
        return self._canceled

    def exception(self) -> BaseException | None:
        """The error that stopped the timer, if its callback raised."""
        return self._exception

    def cancel(self) -> None:
        """Stop calling the callback (idempotent)."""
        self._canceled = True
        self._next_ns = None
        if self._task is not None:
            self._task.cancel()

    def reset(self) -> None:
        """Restart the schedule from now: the next call comes one full period from now."""
        if self._task is not None:
            self._task.cancel()
        self._canceled = False
        self._exception = None
        self._start()

    def time_until_next_call(self) -> Duration | None:
        """Time left before the next call; None when canceled or a fired one-shot."""
        if self._canceled or self._next_ns is None:
            return None
        return new_duration(max(self._next_ns - self._clock.now_ns(), 0))

    def __repr__(self) -> str:
        state = "canceled" if self._canceled else "active"
        return f"<Timer {self.name!r} every {self.period} {state}>"
