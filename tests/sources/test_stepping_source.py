"""A second, non-PyBullet stepping source: a plain Python fixed-step integrator.

It proves that another engine plugs into :class:`evclock.sources.SteppingTimeSource` with a few
methods (step, set the time step, snapshots), and gets the exact step clock, step hooks,
predicate waits and snapshots-as-jumps, on both hosts (SimEventLoop and SimDriver).
"""

from __future__ import annotations

import asyncio
from fractions import Fraction

import pytest

import evclock
from evclock import ClockJumpedError, PhysicsError, SimDriver, Time
from evclock.sources import SteppingTimeSource


class Oscillator(SteppingTimeSource[tuple[float, float]]):
    """x'' = -x, semi-implicit Euler with a fixed time step: the whole adapter."""

    def __init__(self, dt: float | Fraction = Fraction(1, 300), *, start_ns: int = 0) -> None:
        self.x, self.v = 1.0, 0.0
        self.steps_taken = 0
        self._engine_dt = float(dt)
        super().__init__(dt, start_ns=start_ns)

    def _step_engine(self, count: int) -> None:
        h = self._engine_dt
        for _ in range(count):
            self.v -= self.x * h
            self.x += self.v * h
        self.steps_taken += count

    def _set_engine_time_step(self, dt: float) -> float:
        self._engine_dt = dt
        return dt

    def _save_engine_state(self) -> tuple[float, float]:
        return (self.x, self.v)

    def _restore_engine_state(self, state: tuple[float, float], state_id: int) -> None:
        self.x, self.v = state


class NoSnapshots(Oscillator):
    _save_engine_state = SteppingTimeSource._save_engine_state  # type: ignore[assignment]


def reference_trajectory(steps: int, h: float) -> tuple[float, float]:
    x, v = 1.0, 0.0
    for _ in range(steps):
        v -= x * h
        x += v * h
    return x, v


def test_exact_step_clock_and_quantised_sleeps() -> None:
    source = Oscillator()

    async def main() -> list[int]:
        clock = evclock.clock()
        seen = []
        await clock.sleep(0.001)  # less than a step: quantised up to one step
        seen.append(clock.now_ns())
        await clock.sleep(1.0)
        seen.append(clock.now_ns())
        return seen

    assert evclock.run(main(), source=source) == [3_333_333, 1_003_333_333]
    assert source.step_index == 301
    assert source.steps_taken == 301
    # 300 steps of 1/300 s are exactly one second: no drift.
    assert source.time_of_step(299) == Time(seconds=2)
    assert (source.x, source.v) == reference_trajectory(301, 1 / 300)


def test_step_hooks_and_predicate_waits_wake_tasks() -> None:
    source = Oscillator()

    async def main() -> tuple[Time, int, Time]:
        crossed = asyncio.Event()
        hook = source.add_step_hook(lambda: source.x < 0 and crossed.set())
        await crossed.wait()
        hook.remove()
        at_hook = evclock.clock().now()
        step = source.step_index
        back = await source.wait_until(lambda: source.x > 0)
        return at_hook, step, back

    at_hook, step, back = evclock.run(main(), source=source)
    # The hook woke the task right after the first step where x turned negative.
    first_negative = next(k for k in range(1, 1000) if reference_trajectory(k, 1 / 300)[0] < 0)
    assert step == first_negative
    assert at_hook == Time(nanoseconds=step * 1_000_000_000 // 300)
    # ... and the predicate resolved at the first step where x was positive again.
    assert reference_trajectory(round(back.seconds * 300), 1 / 300)[0] > 0
    assert reference_trajectory(round(back.seconds * 300) - 1, 1 / 300)[0] <= 0


def test_snapshots_are_time_jumps() -> None:
    source = Oscillator()

    async def main() -> tuple[str, float, float]:
        clock = evclock.clock()
        await clock.sleep(0.5)
        state = source.save_state()
        saved = (source.x, source.v)
        await clock.sleep(0.5)

        async def sleeper() -> str:
            try:
                await clock.sleep(10)
            except ClockJumpedError as jumped:
                return str(jumped.jump.delta)
            return "not woken"

        task = asyncio.create_task(sleeper())
        await asyncio.sleep(0)
        jump = source.restore_state(state)
        assert jump is not None
        assert jump.after == Time(seconds=0.5)
        assert (source.x, source.v) == saved
        source.remove_state(state)
        return await task, source.x, clock.now().seconds

    delta, x, now = evclock.run(main(), source=source)
    assert delta == "-0.500000000 s"
    assert now == 0.5
    assert x == reference_trajectory(150, 1 / 300)[0]


def test_an_adapter_without_snapshots_says_so() -> None:
    source = NoSnapshots()
    with pytest.raises(PhysicsError, match=r"^NoSnapshots does not support snapshots$"):
        source.save_state()


def test_time_step_change_rebases_exactly() -> None:
    source = Oscillator(Fraction(1, 100))

    async def main() -> int:
        clock = evclock.clock()
        await source.sleep_steps(3)
        source.set_time_step(Fraction(1, 3))
        await source.sleep_steps(3)
        return clock.now_ns()

    assert evclock.run(main(), source=source) == 30_000_000 + 1_000_000_000
    assert source.time_step_ns == Fraction(1_000_000_000, 3)


def test_same_trajectory_on_a_simdriver() -> None:
    async def on_driver() -> tuple[int, float]:
        source = Oscillator()
        async with SimDriver(source, rtf=None) as sim:

            async def controller() -> None:
                async for _ in sim.clock.rate(50):
                    if sim.clock.now() >= Time(seconds=2):
                        return

            await asyncio.wait_for(controller(), timeout=30)
            return sim.now_ns, source.x

    async def on_loop() -> tuple[int, float]:
        source = evclock.clock()
        async for _ in source.rate(50):
            if source.now() >= Time(seconds=2):
                break
        return source.now_ns(), loop_source.x

    loop_source = Oscillator()
    assert asyncio.run(on_driver()) == evclock.run(on_loop(), source=loop_source)
