"""Clocks: the sim clock of a simulation loop, wall clocks, and the current-clock lookup."""

from __future__ import annotations

import abc
import asyncio
import asyncio.futures
import time
import weakref
from collections.abc import Awaitable
from heapq import heappush
from typing import TYPE_CHECKING

from ._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    NoSimulationError,
    NotRunningError,
)
from ._jumps import JumpCallback, JumpHandle, JumpThreshold
from ._rate import Policy, Rate, Timer, TimerCallback
from ._time import SIM, STEADY, SYSTEM, ClockType, Duration, Time, to_nanoseconds

if TYPE_CHECKING:
    from ._loop import SimEventLoop

_Future = asyncio.futures.Future
_NEGATIVE_HINT = "a negative sleep is a bug in the caller; to wait until a time use sleep_until()"


def _sleep_ns(duration: object) -> int:
    """Fast validated conversion of a sleep duration to nanoseconds."""
    if type(duration) is float:
        if duration == duration and duration not in (float("inf"), float("-inf")):
            ns = round(duration * 1e9)
        else:
            ns = to_nanoseconds(duration, "sleep duration")
    elif type(duration) is Duration:
        ns = duration.nanoseconds
    else:
        ns = to_nanoseconds(duration, "sleep duration")
    if ns < 0:
        raise InvalidArgumentError(
            f"sleep duration must not be negative, got {duration!r}; {_NEGATIVE_HINT}"
        )
    return ns


class Clock(abc.ABC):
    """What controllers use to read time and wait: the same API on sim and wall time.

    Get the clock of the running loop with :func:`evclock.clock`.
    """

    clock_type: ClockType

    def __init__(self) -> None:
        self._rates: list[Rate] = []
        self._timers: list[Timer] = []

    @abc.abstractmethod
    def now_ns(self) -> int:
        """Current time of this clock in integer nanoseconds."""

    def now(self) -> Time:
        """Current time of this clock."""
        return Time._from_ns(self.now_ns(), self.clock_type)

    @abc.abstractmethod
    def sleep(self, duration: float | Duration) -> Awaitable[None]:
        """Wait ``duration`` (seconds or a :class:`Duration`) of this clock's time.

        Negative, NaN and infinite durations raise :class:`InvalidArgumentError`.
        """

    @abc.abstractmethod
    def _sleep_until_ns(self, when_ns: int) -> Awaitable[None]:
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
        return self._sleep_until_ns(when.nanoseconds)

    def rate(self, hz: float, *, policy: Policy = "skip", name: str | None = None) -> Rate:
        """A drift-free rate loop: ``async for tick in clock.rate(100): ...``; see :class:`Rate`."""
        rate = Rate(self, hz, policy, name)
        self._rates.append(rate)
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
        self._timers.append(timer)
        return timer

    @property
    def rates(self) -> tuple[Rate, ...]:
        """Every rate loop created on this clock, in creation order (for reports)."""
        return tuple(self._rates)

    @property
    def timers(self) -> tuple[Timer, ...]:
        """Every timer created on this clock, in creation order."""
        return tuple(self._timers)

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
    """The clock of a :class:`SimEventLoop`: simulation time, exact integer nanoseconds."""

    clock_type = SIM

    def __init__(self, loop: SimEventLoop) -> None:
        super().__init__()
        self._loop = loop

    @property
    def loop(self) -> SimEventLoop:
        """The simulation loop this clock reads."""
        return self._loop

    def now_ns(self) -> int:
        return self._loop._now_ns

    def now(self) -> Time:
        return Time._from_ns(self._loop._now_ns, SIM)

    def sleep(self, duration: float | Duration) -> asyncio.Future[None]:
        # The hot path of every controller: keep it flat.
        if type(duration) is float and 0.0 <= duration < 1e9:
            ns = round(duration * 1e9)
        elif type(duration) is Duration:
            ns = duration._ns
            if ns < 0:
                ns = _sleep_ns(duration)
        else:
            ns = _sleep_ns(duration)
        return self._sleep_until_ns(self._loop._now_ns + ns)

    def _sleep_until_ns(self, when_ns: int) -> asyncio.Future[None]:
        loop = self._loop
        if loop._closed:
            loop._check_closed()
        fut: asyncio.Future[None] = _Future(loop=loop)
        now = loop._now_ns
        heappush(loop._scheduled, (when_ns if when_ns > now else now, loop._seq(), 0, fut))
        return fut

    def _jump_registry(self) -> list[JumpHandle]:
        return self._loop._jump_handlers

    def __repr__(self) -> str:
        return f"<SimClock now={self.now()} source={self._loop.source.describe()}>"


class WallClock(Clock):
    """Wall time: ``STEADY`` (monotonic, default) or ``SYSTEM`` (calendar time).

    The same API as :class:`SimClock`, for the real robot; works on any asyncio loop.
    """

    def __init__(self, clock_type: ClockType = STEADY) -> None:
        if clock_type not in (STEADY, SYSTEM):
            raise InvalidArgumentError(
                f"a wall clock is STEADY or SYSTEM, got {clock_type!r}; sim time comes from "
                "a simulation loop (evclock.run)"
            )
        super().__init__()
        self.clock_type = clock_type
        self._read = time.monotonic_ns if clock_type is STEADY else time.time_ns

    def now_ns(self) -> int:
        return self._read()

    async def sleep(self, duration: float | Duration) -> None:
        await asyncio.sleep(_sleep_ns(duration) / 1e9)

    async def _sleep_until_ns(self, when_ns: int) -> None:
        delay = when_ns - self._read()
        await asyncio.sleep(delay / 1e9 if delay > 0 else 0)

    def __repr__(self) -> str:
        return f"<WallClock {self.clock_type.value}>"


#: Clocks attached to loops evclock does not own (wall clocks, embedded sim drivers).
_attached: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Clock] = weakref.WeakKeyDictionary()


def attach_clock(loop: asyncio.AbstractEventLoop, clock: Clock) -> None:
    """Make ``clock`` what :func:`clock` returns on ``loop`` (used by embedding drivers)."""
    _attached[loop] = clock


def detach_clock(loop: asyncio.AbstractEventLoop) -> None:
    """Undo :func:`attach_clock`."""
    _attached.pop(loop, None)


def _running_loop(what: str) -> asyncio.AbstractEventLoop:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        raise NotRunningError(
            f"{what} must be called from a coroutine or callback running on an event loop "
            "(start one with evclock.run(main()))"
        ) from None


def clock() -> Clock:
    """The clock of the running loop: sim time on a simulation loop, wall time elsewhere.

    Controller code calls this and never needs to know which one it got. On a loop without
    a simulation while ``EVCLOCK_USE_SIM_TIME`` asks for sim time, it raises
    :class:`NoSimulationError` instead of silently running on wall time.
    """
    from ._loop import SimEventLoop
    from ._runner import env_use_sim_time

    loop = _running_loop("evclock.clock()")
    if isinstance(loop, SimEventLoop):
        return loop.clock
    found = _attached.get(loop)
    if found is not None:
        return found
    if env_use_sim_time():
        raise NoSimulationError(
            "EVCLOCK_USE_SIM_TIME asks for sim time but this loop has no simulation; "
            "start the program with evclock.run() (or attach a driver), or unset "
            "EVCLOCK_USE_SIM_TIME to run on wall time"
        )
    wall = WallClock(STEADY)
    _attached[loop] = wall
    return wall


def sim_clock() -> SimClock:
    """The sim clock of the running loop; :class:`NoSimulationError` if there is none."""
    from ._loop import SimEventLoop

    loop = _running_loop_or_none()
    if isinstance(loop, SimEventLoop):
        return loop.clock
    found = _attached.get(loop) if loop is not None else None
    if isinstance(found, SimClock):
        return found
    raise NoSimulationError(
        "sim time was asked for but no simulation loop is running; run the program with "
        "evclock.run(main()) or asyncio.Runner(loop_factory=evclock.loop_factory())"
    )


def _running_loop_or_none() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None
