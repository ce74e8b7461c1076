"""Clocks: the sim clock of a simulation host and wall clocks (the same API on both)."""

from __future__ import annotations

import abc
import asyncio
import time
from collections.abc import Awaitable
from typing import TYPE_CHECKING

from evclock._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
)
from evclock.kernel._core import clock_sleep, clock_sleep_until
from evclock.kernel._jumps import JumpCallback, JumpHandle, JumpThreshold
from evclock.kernel._rate import Policy, Rate, Timer, TimerCallback
from evclock.time._time import (
    SIM,
    STEADY,
    SYSTEM,
    ClockType,
    Duration,
    Time,
    new_duration,
    new_time,
    sleep_duration_ns,
    to_nanoseconds,
)

if TYPE_CHECKING:
    from evclock.kernel._core import SimCore
    from evclock.kernel._pacing import PacingControls


class Clock(abc.ABC):
    """What controllers use to read time and wait: the same API on sim and wall time.

    Get the clock of the running loop with :func:`evclock.clock`.
    """

    clock_type: ClockType

    def __init__(self) -> None:
        # Latest rate loop / timer of each name: a controller restarted under the same name
        # replaces its predecessor, so a long-running app does not accumulate them.
        self._rates: dict[str, Rate] = {}
        self._timers: dict[str, Timer] = {}

    @abc.abstractmethod
    def now_ns(self) -> int:
        """Current time of this clock in integer nanoseconds."""

    def now(self) -> Time:
        """Current time of this clock."""
        return new_time(self.now_ns(), self.clock_type)

    @abc.abstractmethod
    def sleep(self, duration: float | Duration) -> Awaitable[None]:
        """Wait ``duration`` (seconds or a :class:`Duration`) of this clock's time.

        Negative, NaN and infinite durations raise :class:`InvalidArgumentError`.
        """

    @abc.abstractmethod
    def sleep_until_ns(self, when_ns: int) -> Awaitable[None]:
        """Wait until this clock reads at least ``when_ns`` (no validation)."""

    def sleep_until(self, when: Time) -> Awaitable[None]:
        """Wait until this clock reads ``when`` (returns after one yield if already past)."""
        if not isinstance(when, Time):
            raise InvalidTypeError(
                f"sleep_until() needs a Time (e.g. clock.now() + Duration(seconds=1)), "
                f"got {type(when).__name__}"
            )
        if when.clock_type is not self.clock_type:
            raise ClockMismatchError(
                f"sleep_until() got a {when.clock_type.value} time but this is a "
                f"{self.clock_type.value} clock; compute deadlines from this clock's now()"
            )
        return self.sleep_until_ns(when.nanoseconds)

    def rate(self, hz: float, *, policy: Policy = "skip", name: str | None = None) -> Rate:
        """A drift-free rate loop: ``async for tick in clock.rate(100): ...``; see :class:`Rate`."""
        rate = Rate(self, hz, policy, name)
        self._rates.pop(rate.name, None)
        self._rates[rate.name] = rate
        return rate

    def timer(
        self,
        period: float | Duration,
        callback: TimerCallback,
        *,
        oneshot: bool = False,
        name: str | None = None,
    ) -> Timer:
        """Start calling ``callback`` every ``period`` (or once after it); see :class:`Timer`."""
        timer = Timer(self, period, callback, oneshot=oneshot, name=name)
        self._timers.pop(timer.name, None)
        self._timers[timer.name] = timer
        return timer

    def _forget_loops(self) -> None:
        """Forget every rate loop and timer made so far (a scenario reset in place on the same
        loop: :attr:`rates` and :attr:`timers` then list the new episode's only, as in a new
        run)."""
        self._rates.clear()
        self._timers.clear()

    @property
    def rates(self) -> tuple[Rate, ...]:
        """The latest rate loop of each name created on this clock, oldest first (for reports).

        A new rate with the name of an earlier one replaces it: give loops distinct names.
        """
        return tuple(self._rates.values())

    @property
    def timers(self) -> tuple[Timer, ...]:
        """The latest timer of each name created on this clock, oldest first."""
        return tuple(self._timers.values())

    def on_jump(
        self,
        pre: JumpCallback | None = None,
        post: JumpCallback | None = None,
        *,
        threshold: JumpThreshold | None = None,
    ) -> JumpHandle:
        """Register callbacks run before and after a time jump matching ``threshold``.

        Only sim clocks jump (reset, restored snapshot); on wall clocks the callbacks are
        kept but never called (evclock does not watch the system clock for NTP steps).
        """
        if pre is None and post is None:
            raise InvalidArgumentError("on_jump() needs a pre or a post callback (or both)")
        for cb in (pre, post):
            if cb is not None and not callable(cb):
                raise InvalidTypeError(f"jump callbacks must be callable, got {type(cb).__name__}")
        registry = self._jump_registry()
        handle = JumpHandle(registry, pre, post, threshold or JumpThreshold())
        registry.append(handle)
        return handle

    def _jump_registry(self) -> list[JumpHandle]:
        registry: list[JumpHandle] = self.__dict__.setdefault("_jump_handles", [])
        return registry


class SimClock(Clock):
    """Simulation time, exact integer nanoseconds: the clock of a :class:`SimEventLoop`, or of
    a :class:`~evclock.SimDriver` on a loop evclock does not own.

    Its waits must be awaited on :attr:`loop`; :attr:`host` is what controls its time
    (``pause()``, ``resume()``, ``step()``, ``rtf``).

    Made by the loop or driver that owns the time; get it with :func:`evclock.clock`.

    :param core: the kernel whose time this is (its schedule serves the sleeps).
    :param host: what controls this time: the :class:`SimEventLoop` or the ``SimDriver``.
    """

    clock_type = SIM

    def __init__(self, core: SimCore, host: PacingControls) -> None:
        super().__init__()
        #: The kernel whose time this is (the sleeps read its schedule directly).
        self.core = core
        self._host = host

    @property
    def host(self) -> PacingControls:
        """What owns this sim time: the :class:`SimEventLoop` or the ``SimDriver``."""
        return self._host

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop this clock's waits run on (the SimEventLoop itself, or the loop a
        SimDriver runs on)."""
        host = self._host
        assert isinstance(host, asyncio.AbstractEventLoop)  # a SimEventLoop
        return host

    def now_ns(self) -> int:
        """Current sim time in integer nanoseconds."""
        return self.core.now_ns

    def now(self) -> Time:
        """Current sim time, a :class:`Time` of the ``SIM`` domain."""
        return new_time(self.core.now_ns, SIM)

    sleep = clock_sleep  # the kernel's: every controller's hot path, in one frame

    sleep_until_ns = clock_sleep_until  # the kernel's: rates' and timers' hot path

    def _jump_registry(self) -> list[JumpHandle]:
        return self.core.jump_handlers

    def __repr__(self) -> str:
        return f"<SimClock now={self.now()} source={self.core.source.describe()}>"


class WallClock(Clock):
    """Wall time: ``STEADY`` (monotonic, default) or ``SYSTEM`` (calendar time).

    The same API as :class:`SimClock`, for the real robot; works on any asyncio loop
    (the default loop, uvloop, ...).

    Waits are precise by default (``precise=True``): the stock loop rounds its selector
    timeout up to whole milliseconds (and Linux adds timer slack), so a plain
    ``asyncio.sleep`` based 1 kHz loop is about half a period late. A precise wait
    sleeps on the loop's own timer until 5 ms before the deadline, then, on Linux, on a
    ``timerfd`` armed at the absolute time ``deadline - spin_margin`` and watched by the
    loop (``loop.add_reader``): no millisecond rounding and no timer slack. It finishes the
    last ``spin_margin`` by yielding to the loop (``asyncio.sleep(0)``) until the clock
    reads the deadline: other tasks keep running, but it costs CPU; a larger margin absorbs
    more wake-up latency for more CPU (docs/performance.md, "Precise wall time", shows measured
    trade-offs; ``benchmarks/wall_rate_1khz.py`` measures them on your machine). A precise
    wait never returns before the clock reads the deadline. Where there is no timerfd
    (other systems, loops without ``add_reader``) the loop's timer is used, with its
    granularity; a margin above it restores precision at the cost of spinning the whole
    time. Works on uvloop too.

    Args:
        clock_type: ``STEADY`` or ``SYSTEM``. Relative sleeps (:meth:`sleep`) are always
            measured on the monotonic clock; deadlines (``sleep_until``, rates, timers) on
            this clock.
        precise: False restores plain ``asyncio.sleep`` waits (millisecond granularity).
        spin_margin: seconds or a :class:`Duration` (default 100 us): how long before the
            deadline the timer wakes the waiter, which then yields to the loop until the
            deadline. It absorbs the wake-up latency (the kernel's, the loop's, Python's)
            and costs about ``spin_margin`` of CPU per wait. 0 disables spinning.
        timer_slack: seconds or a :class:`Duration`, or None (default: leave it alone):
            on Linux, lower the loop thread's timer slack (``prctl(PR_SET_TIMERSLACK)``,
            50 us by default) to this while precise waits are pending, and restore it when
            the last one ends. timerfd timers have no slack, so only the fallback path can
            gain (none measured: the loop's millisecond rounding dominates). A no-op where
            prctl is unavailable.
    """

    def __init__(
        self,
        clock_type: ClockType = STEADY,
        *,
        precise: bool = True,
        spin_margin: float | Duration = 100e-6,
        timer_slack: float | Duration | None = None,
    ) -> None:
        if clock_type not in (STEADY, SYSTEM):
            raise InvalidArgumentError(
                f"a wall clock is STEADY or SYSTEM, got {clock_type!r}; sim time comes from "
                "a simulation loop (evclock.run)"
            )
        if not isinstance(precise, bool):
            raise InvalidTypeError(f"precise must be True or False, got {type(precise).__name__}")
        margin_ns = to_nanoseconds(spin_margin, "spin_margin")
        if margin_ns < 0:
            raise InvalidArgumentError(f"spin_margin must not be negative, got {spin_margin!r}")
        # The precise waits (ctypes, timerfd) load with the first wall clock, not with
        # `import evclock`.
        from evclock.kernel import _precise

        slack: _precise.TimerSlack | None = None
        if timer_slack is not None:
            slack_ns = to_nanoseconds(timer_slack, "timer_slack")
            if slack_ns <= 0:
                raise InvalidArgumentError(f"timer_slack must be positive, got {timer_slack!r}")
            slack = _precise.TimerSlack(slack_ns)
        super().__init__()
        self.clock_type = clock_type
        self._read = time.monotonic_ns if clock_type is STEADY else time.time_ns
        self._clockid = (
            _precise.CLOCK_MONOTONIC if clock_type is STEADY else _precise.CLOCK_REALTIME
        )
        self._precise = precise
        self._waits = _precise
        self._spin_margin_ns = margin_ns
        self._slack = slack

    @property
    def precise(self) -> bool:
        """Whether waits are precise (see the class docstring)."""
        return self._precise

    @property
    def spin_margin(self) -> Duration:
        """How long before a deadline a precise wait starts yielding instead of sleeping."""
        return new_duration(self._spin_margin_ns)

    def now_ns(self) -> int:
        """Current wall time of this clock's domain in integer nanoseconds."""
        return self._read()

    async def sleep(self, duration: float | Duration) -> None:
        """Wait ``duration`` (seconds or a :class:`Duration`) of wall time, precisely.

        Never returns before the deadline; see the class for how (timerfd, spin margin).
        """
        ns = sleep_duration_ns(duration)
        if not self._precise:
            await asyncio.sleep(ns / 1e9)
            return
        # A relative sleep is measured on the monotonic clock, even on a SYSTEM clock.
        waits = self._waits
        await waits.sleep_until_ns(
            time.monotonic_ns() + ns,
            time.monotonic_ns,
            waits.CLOCK_MONOTONIC,
            self._spin_margin_ns,
            self._slack,
        )

    async def sleep_until_ns(self, when_ns: int) -> None:
        """Wait until this clock reads at least ``when_ns``, precisely (no validation)."""
        if not self._precise:
            delay = when_ns - self._read()
            await asyncio.sleep(delay / 1e9 if delay > 0 else 0)
            return
        await self._waits.sleep_until_ns(
            when_ns, self._read, self._clockid, self._spin_margin_ns, self._slack
        )

    def __repr__(self) -> str:
        return f"<WallClock {self.clock_type.value}>"
