"""Physics and control tests of the ``sims`` scenarios, driven by a tiny stand-in clock.

``StepClock`` plays the part evclock's clock will play: simulated time is the number of physics
steps times 1/240 s (exact integer nanoseconds), ``sleep``/``rate`` park the caller on a future,
and :meth:`StepClock.run` alternates "let every woken task run until it waits again" with "step
the physics once and wake whoever is due".
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import heapq
import itertools
import math
from collections import Counter
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import pytest

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")
import pybullet as p

from evclock_sims import PHYSICS_HZ, SCENARIOS, ClockLike, get_scenario

NS_PER_S = 1_000_000_000

RATES: dict[str, dict[str, float]] = {
    "kuka": {"joint_control": 100.0, "planner": 10.0},
    "husky": {"drive": 50.0, "lidar": 20.0},
    "cartpole": {"balance": 50.0, "judge": 50.0, "monitor": 240.0},
    "fusion": {"odometry": 50.0, "camera": 15.0, "drive": 50.0},
}
"""The named rate loops each scenario must run, and their rates."""


@dataclass(frozen=True)
class SimTime:
    """A simulated instant in integer nanoseconds."""

    nanoseconds: int

    @property
    def seconds(self) -> float:
        """The instant in seconds."""
        return self.nanoseconds / NS_PER_S


@dataclass(frozen=True)
class Tick:
    """One iteration of :meth:`StepClock.rate`."""

    expected: SimTime
    actual: SimTime
    missed: int
    index: int


class StepClock:
    """Minimal discrete-event clock over plain asyncio whose time is PyBullet's step count."""

    _MIN_YIELDS = 4
    """Event-loop passes per settle, enough for new tasks to start and finished ones to unwind."""

    def __init__(self, client: int) -> None:
        """A clock at t = 0 that steps PyBullet client ``client``."""
        self._client = client
        self.steps = 0
        """Physics steps taken so far."""
        self._sleepers: list[tuple[int, int, asyncio.Future[None]]] = []
        self._order = itertools.count()
        self._waking = 0
        """Sleepers whose future was resolved but which have not resumed yet."""
        self.ticks: Counter[str] = Counter()
        """Ticks delivered per rate-loop name."""

    def now(self) -> SimTime:
        """Steps times 1/240 s, in exact integer nanoseconds."""
        return SimTime(self.steps * NS_PER_S // PHYSICS_HZ)

    async def sleep(self, seconds: float) -> None:
        """Wake at the first physics step at or after ``seconds`` from now."""
        await self._sleep_until(self.now().nanoseconds + round(seconds * NS_PER_S))

    async def rate(self, hz: float, *, name: str) -> AsyncIterator[Tick]:
        """Drift-free ticks at ``start + floor(k / hz)``; late ticks are skipped and counted."""
        period = Fraction(NS_PER_S) / Fraction(hz)
        start = self.now().nanoseconds
        index = 0
        while True:
            await self._sleep_until(start + math.floor(index * period))
            actual = self.now().nanoseconds
            due = math.ceil((actual - start + 1) / period) - 1  # last k with deadline <= actual
            self.ticks[name] += 1
            expected = SimTime(start + math.floor(due * period))
            yield Tick(expected, SimTime(actual), missed=due - index, index=due)
            index = due + 1

    async def _sleep_until(self, deadline: int) -> None:
        if deadline <= self.now().nanoseconds:
            await asyncio.sleep(0)
            return
        future = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (deadline, next(self._order), future))
        try:
            await future
        finally:
            if future.done() and not future.cancelled():
                self._waking -= 1

    async def _settle(self) -> None:
        """Yield until every woken sleeper has run up to its next wait, then a few passes more."""
        while self._waking:
            await asyncio.sleep(0)
        for _ in range(self._MIN_YIELDS):
            await asyncio.sleep(0)

    def _step(self) -> None:
        """Step the physics once and resolve every sleeper now due."""
        p.stepSimulation(physicsClientId=self._client)
        self.steps += 1
        now = self.now().nanoseconds
        while self._sleepers and self._sleepers[0][0] <= now:
            _, _, future = heapq.heappop(self._sleepers)
            if not future.done():
                future.set_result(None)
                self._waking += 1

    async def run(self, main: Coroutine[Any, Any, None], until: float) -> None:
        """Run ``main`` until it returns or ``until`` simulated seconds have passed."""
        task = asyncio.create_task(main)
        limit = round(until * NS_PER_S)
        await self._settle()
        while not task.done() and self.now().nanoseconds < limit:
            self._step()
            await self._settle()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@dataclass(frozen=True)
class Outcome:
    """What one scenario run left behind (the client is gone by then)."""

    success: bool
    summary: dict[str, float | int | bool | str]
    state: list[float]
    sim_seconds: float
    ticks: Counter[str]


def simulate(name: str, seed: int, **options: Any) -> Outcome:
    """Run scenario ``name`` in a fresh DIRECT client for at most its ``default_until``."""
    client = p.connect(p.DIRECT)
    try:
        scenario = get_scenario(name)(client, seed, **options)
        clock = StepClock(client)
        asyncio.run(clock.run(scenario.run(clock), scenario.default_until))
        return Outcome(
            scenario.success(),
            scenario.summary(),
            scenario.state_vector(),
            clock.now().seconds,
            clock.ticks,
        )
    finally:
        p.disconnect(client)


@functools.cache
def outcome(name: str, seed: int) -> Outcome:
    """:func:`simulate` with default options, run once per (name, seed) per session."""
    return simulate(name, seed)


def test_step_clock_rate_and_sleep() -> None:
    """The stand-in's ticks land on exact step times, and late ticks are reported as missed."""
    client = p.connect(p.DIRECT)
    try:
        clock = StepClock(client)
        seen: list[tuple[int, int, int, int]] = []

        async def loop(hz: float) -> None:
            async for tick in clock.rate(hz, name="probe"):
                seen.append((tick.index, tick.missed, tick.expected.nanoseconds, clock.steps))
                if tick.index >= 4:
                    return

        async def main() -> None:
            await clock.sleep(0.01)  # 2.4 steps: wakes after step 3
            assert clock.steps == 3
            await loop(100.0)
            await loop(1000.0)  # faster than the physics: every other tick is skipped

        asyncio.run(clock.run(main(), until=1.0))
        assert seen[:5] == [
            (0, 0, 12_500_000, 3),
            (1, 0, 22_500_000, 6),
            (2, 0, 32_500_000, 8),
            (3, 0, 42_500_000, 11),
            (4, 0, 52_500_000, 13),
        ]
        assert [(index, missed) for index, missed, _, _ in seen[5:]] == [(0, 0), (4, 3)]
    finally:
        p.disconnect(client)


def test_step_clock_is_a_clocklike() -> None:
    """The stand-in satisfies the interface the scenarios are typed against."""
    clock: ClockLike = StepClock(client=0)
    assert clock.now().nanoseconds == 0


def test_registry() -> None:
    """Every scenario is registered under its name; unknown names list the valid ones."""
    assert list(SCENARIOS) == ["kuka", "husky", "cartpole", "fusion"]
    assert all(get_scenario(name).name == name for name in SCENARIOS)
    with pytest.raises(ValueError, match="valid names: kuka, husky, cartpole, fusion"):
        get_scenario("segway")


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_reaches_success(name: str, seed: int) -> None:
    """Each scenario accomplishes its mission within ``default_until``."""
    result = outcome(name, seed)
    assert result.success, result.summary


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_rate_loops_run_at_their_rates(name: str) -> None:
    """The named controllers ticked at their nominal rates for the whole mission."""
    result = outcome(name, 0)
    assert set(result.ticks) == set(RATES[name])
    for loop_name, hz in RATES[name].items():
        assert abs(result.ticks[loop_name] - hz * result.sim_seconds) <= 2, loop_name


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_deterministic_per_seed(name: str) -> None:
    """Same seed: bit-identical final state; another seed: a different one."""
    assert simulate(name, 0).state == outcome(name, 0).state
    assert outcome(name, 1).state != outcome(name, 0).state


def test_kuka_joint_control_at_physics_rate() -> None:
    """The benchmark configuration (joint control at 240 Hz) reaches every target too."""
    result = simulate("kuka", 0, control_hz=240.0)
    assert result.success, result.summary
    assert abs(result.ticks["joint_control"] - 240.0 * result.sim_seconds) <= 2
