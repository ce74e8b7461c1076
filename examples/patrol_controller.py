"""A patrol controller: a robot base visits waypoints in turn, at a fixed control rate.

Each leg is driven by a 20 Hz rate loop and bounded by a leg timeout (``asyncio.timeout``): a
blocked leg is abandoned and the patrol goes on to the next waypoint. At each waypoint the base
dwells a while. A safety monitor can stop the base (an obstacle) for some time.

The controller only uses :func:`evclock.clock` and asyncio's own timeouts, so the same code
runs on sim time (``evclock.run``, the pytest plugin) and on the real robot's wall clock.
``examples/test_controller_in_virtual_time.py`` tests a one-minute patrol in milliseconds.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from dataclasses import dataclass, field

import evclock

#: The patrol route: a 4 m square, visited B, C, D, A, B, ... from A at (0, 0).
ROUTE: tuple[tuple[str, float, float], ...] = (
    ("B", 4.0, 0.0),
    ("C", 4.0, 4.0),
    ("D", 0.0, 4.0),
    ("A", 0.0, 0.0),
)


@dataclass
class Base:
    """The plant: a point robot that moves at the commanded velocity unless it is stopped."""

    x: float = 0.0
    y: float = 0.0
    stopped: bool = False
    odometer: float = 0.0

    def drive(self, vx: float, vy: float, dt: float) -> None:
        """Move for ``dt`` seconds at (``vx``, ``vy``) m/s (not at all while stopped)."""
        if self.stopped:
            return
        self.x += vx * dt
        self.y += vy * dt
        self.odometer += math.hypot(vx, vy) * dt


@dataclass
class PatrolLog:
    """What a patrol did, in seconds of the clock it ran on since it started."""

    arrivals: list[tuple[str, float]] = field(default_factory=list)
    timeouts: list[tuple[str, float]] = field(default_factory=list)
    ticks: int = 0
    missed: int = 0


class Patrol:
    """Drive ``base`` around ``route`` at ``speed`` m/s with a ``hz`` control loop.

    A leg that takes longer than ``leg_timeout`` seconds is abandoned; the base dwells
    ``dwell`` seconds at each waypoint it reaches.
    """

    def __init__(
        self,
        base: Base,
        route: tuple[tuple[str, float, float], ...] = ROUTE,
        *,
        speed: float = 0.5,
        hz: float = 20.0,
        leg_timeout: float = 12.0,
        dwell: float = 2.0,
    ) -> None:
        self.base = base
        self.route = route
        self.speed = speed
        self.hz = hz
        self.leg_timeout = leg_timeout
        self.dwell = dwell
        self.log = PatrolLog()

    async def run(self, duration: float) -> PatrolLog:
        """Patrol for ``duration`` seconds, then stop the base where it is."""
        clock = evclock.clock()
        start = clock.now()

        def since_start() -> float:
            return round((clock.now() - start).seconds, 6)

        try:
            async with asyncio.timeout(duration):
                for name, x, y in itertools.cycle(self.route):
                    try:
                        async with asyncio.timeout(self.leg_timeout):
                            await self._drive_to(x, y)
                    except TimeoutError:
                        self.log.timeouts.append((name, since_start()))
                        continue
                    self.log.arrivals.append((name, since_start()))
                    await clock.sleep(self.dwell)
        except TimeoutError:
            pass  # the patrol is over
        return self.log

    async def _drive_to(self, x: float, y: float) -> None:
        """Servo the base to (x, y): each tick, command a velocity toward it, no faster than
        ``speed`` and slow enough not to overshoot within one period."""
        base = self.base
        period = 1.0 / self.hz
        vx = vy = 0.0
        last: evclock.Time | None = None
        rate = evclock.clock().rate(self.hz, name="patrol")
        async for tick in rate:
            if last is not None:
                base.drive(vx, vy, (tick.actual - last).seconds)
            last = tick.actual
            self.log.ticks += 1
            self.log.missed += tick.missed
            dx, dy = x - base.x, y - base.y
            distance = math.hypot(dx, dy)
            if distance < 1e-6:
                return
            speed = min(self.speed, distance / period)
            vx, vy = dx / distance * speed, dy / distance * speed


async def obstacle(base: Base, appears: float, clears: float) -> None:
    """A safety monitor: an obstacle stops the base from ``appears`` to ``clears`` seconds
    after the monitor starts."""
    clock = evclock.clock()
    start = clock.now()
    await clock.sleep_until(start + evclock.Duration.from_seconds(appears))
    base.stopped = True
    await clock.sleep_until(start + evclock.Duration.from_seconds(clears))
    base.stopped = False


async def main() -> None:
    """Patrol for a minute with an obstacle in the way, and print the log."""
    base = Base()
    async with asyncio.TaskGroup() as tasks:
        tasks.create_task(obstacle(base, appears=12.0, clears=19.0))
        log = await Patrol(base).run(60.0)
    print(f"arrivals: {log.arrivals}")
    print(f"timeouts: {log.timeouts}")
    print(f"ticks: {log.ticks}, missed: {log.missed}, at ({base.x:.3f}, {base.y:.3f})")


if __name__ == "__main__":
    evclock.run(main())
