"""What both /clock cost benchmarks share (``ros2_clock.py`` over Zenoh, ``ros2_dds.py`` over
DDS): a scenario timed with and without a publisher attached, alternating round by round and
keeping each variant's best round, and the table they print."""

from __future__ import annotations

import asyncio
import gc
import time

import evclock
from evclock.ros2 import Ros2ClockPublisher
from evclock_sims import get_scenario

Best = dict[str, tuple[float, float, int]]
"""Each variant's best round: (CPU s, wall s, physics steps)."""


def run_once(
    scenario_name: str, seconds: float, publisher: Ros2ClockPublisher | None, decimation: int
) -> tuple[float, float, int]:
    """Run the scenario for ``seconds`` of sim time; return (CPU s, wall s, steps)."""
    source = evclock.sources.PyBulletTimeSource.connect()
    scenario = get_scenario(scenario_name)(source.client, 0)
    hook = publisher.attach(source, decimation=decimation) if publisher is not None else None

    async def main() -> None:
        try:
            async with asyncio.timeout(seconds):
                await scenario.run(evclock.clock())
        except TimeoutError:
            pass

    cpu0, wall0 = time.process_time(), time.perf_counter()
    evclock.run(main(), source=source)
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    if hook is not None:
        hook.remove()
    source.close()
    return cpu, wall, source.step_index


def best_rounds(
    scenario_name: str,
    seconds: float,
    repeat: int,
    publisher: Ros2ClockPublisher,
    decimation: int = 1,
) -> Best:
    """``repeat`` rounds of "plain" then "with /clock"; the lowest-CPU round of each."""
    best: Best = {}
    for _ in range(repeat):
        for name, pub in (("plain", None), ("with /clock", publisher)):
            gc.collect()
            cpu, wall, steps = run_once(scenario_name, seconds, pub, decimation)
            if name not in best or cpu < best[name][0]:
                best[name] = (cpu, wall, steps)
    return best


def print_rounds(best: Best) -> None:
    """Steps per CPU and per wall second of each variant, and their ratio."""
    print(f"{'variant':<14}{'steps':>8}{'steps/CPU s':>14}{'steps/wall s':>14}")
    for name, (cpu, wall, steps) in best.items():
        print(f"{name:<14}{steps:>8}{steps / cpu:>14,.0f}{steps / wall:>14,.0f}")
    plain, clocked = best["plain"], best["with /clock"]
    ratio = (clocked[2] / clocked[0]) / (plain[2] / plain[0])
    wall_ratio = (clocked[2] / clocked[1]) / (plain[2] / plain[1])
    print(f"ratio (with /clock / plain): {ratio:.3f} (CPU), {wall_ratio:.3f} (wall)")
