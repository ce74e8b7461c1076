"""Your own engine as the clock: a fixed-step integrator plugged in as a SteppingTimeSource.

A mass on a spring integrated at 1 kHz (semi-implicit Euler) owns sim time exactly as
PyBullet would: a controller samples it at 50 Hz, a step hook counts the steps, a predicate
wait resolves at the first step where the mass comes back, and a snapshot restored mid-run
is a time jump. Run: ``python examples/custom_stepping_source.py``.
"""

from __future__ import annotations

import asyncio
from fractions import Fraction

import evclock
from evclock import ClockJumpedError
from evclock.sources import SteppingTimeSource


class Spring(SteppingTimeSource[tuple[float, float]]):
    """x'' = -k x: the whole adapter is these few methods."""

    def __init__(self, k: float = 4.0, dt: Fraction = Fraction(1, 1000)) -> None:
        self.k, self.x, self.v = k, 1.0, 0.0
        self._h = float(dt)
        super().__init__(dt)

    def _step_engine(self, count: int) -> None:
        for _ in range(count):
            self.v -= self.k * self.x * self._h
            self.x += self.v * self._h

    def _set_engine_time_step(self, dt: float) -> float:
        self._h = dt
        return dt

    def _save_engine_state(self) -> tuple[float, float]:
        return (self.x, self.v)

    def _restore_engine_state(self, state: tuple[float, float], state_id: int) -> None:
        self.x, self.v = state


async def main(spring: Spring) -> None:
    clock = evclock.clock()
    steps = 0

    def count() -> None:
        nonlocal steps
        steps += 1

    spring.add_step_hook(count)
    async for tick in clock.rate(50):
        if tick.index % 10 == 0:
            print(f"{tick.actual}: x = {spring.x:+.3f}")
        if tick.index == 30:
            break
    print(f"{steps} steps in {clock.now()}")
    back = await spring.wait_until(lambda: spring.x > 0.99)
    print(f"the mass came back at {back}")
    snapshot = spring.save_state()

    async def sleeper() -> None:
        try:
            await clock.sleep(5)
        except ClockJumpedError as jumped:
            print(f"a sleeper was woken by the jump: {jumped.jump.delta}")

    async with asyncio.TaskGroup() as group:
        group.create_task(sleeper())
        await clock.sleep(1)
        spring.restore_state(snapshot)
    print(f"restored to {clock.now()}, x = {spring.x:+.3f}")


if __name__ == "__main__":
    source = Spring()
    evclock.run(main(source), source=source)
