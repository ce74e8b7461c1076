"""KUKA reaching on MuJoCo: evclock-driven controllers vs a hand-written ``mj_step`` loop, and
MuJoCo vs PyBullet steps per second - all measured in the same run.

Usage: python benchmarks/mujoco_kuka.py [--seconds 20] [--repeat 5]

Both MuJoCo variants build the same KUKA world (``KukaReach`` in a ``MuJoCoWorld``: the
URDF from pybullet_data with position servos, armature and adjacent-link contact exclusions)
and run the same control code (the functions below): a joint controller (slew toward the IK
goal, set the servo targets) at ``control_hz`` and, unless ``--no-planner``, the IK planner
at 10 Hz, over 240 Hz physics, cycling through the scenario's targets.

* **hand-written loop**: plain Python deciding which controller is due on each step with the
  same integer deadline arithmetic as ``clock.rate``, and one ``mj_step(model, data, n)`` call
  for each run of ``n`` steps with nothing due in between - the fastest loop one would write;
* **evclock**: the controllers as rate-loop tasks on a ``MuJoCoTimeSource``.

Reported per controller rate: physics steps per CPU second of each (best of the alternating
rounds), their ratio (goal: >= 0.9 at 100 Hz control), and the wall-time ratio beside it.
Then the raw step rate of the arm on MuJoCo and on PyBullet (same URDF, holding its pose) and
the whole scenario under evclock on each engine, with the MuJoCo/PyBullet ratios (PyBullet
rows are skipped when PyBullet is not installed).

On a noisy (virtual) machine, instruction counts compare the two MuJoCo loops exactly:
``valgrind --tool=callgrind python benchmarks/mujoco_kuka.py --only sync --control-hz 100``
and the same with ``--only evclock``; subtract a ``--seconds 0`` run of each for start-up.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import sys
import time
from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np
from _kuka_work import PHYSICS_HZ, PLANNER_HZ, ReachWork, clocks, due_steps

import evclock
from evclock_sims import KukaReach, MuJoCoWorld
from evclock_sims.kuka import REST_POSE


class Controllers(ReachWork):
    """The control work both MuJoCo variants do, on one KUKA world."""

    def __init__(self, control_hz: float) -> None:
        self.world = MuJoCoWorld()
        super().__init__(KukaReach(self.world, seed=0, control_hz=control_hz), control_hz)

    def control(self) -> None:
        arm = self.arm
        self.command += np.clip(arm.goal - self.command, -self.max_step, self.max_step)
        arm.arm.command(self.command.tolist())


def run_hand_written(control_hz: float, seconds: float, planner: bool) -> tuple[float, float, int]:
    ctl = Controllers(control_hz)
    model, data = ctl.world.model, ctl.world.data
    steps = round(seconds * PHYSICS_HZ)
    work: dict[int, list[Callable[[], None]]] = {}
    for step in due_steps(control_hz, steps):
        work.setdefault(step, []).append(ctl.control)
    if planner:
        for step in due_steps(PLANNER_HZ, steps):
            work.setdefault(step, []).append(ctl.plan)
    marks = sorted(work)
    step_fn = mujoco.mj_step
    wall0, cpu0 = clocks()
    done = 0
    for step in marks:
        if step > done:
            step_fn(model, data, step - done)  # one call per run of steps with nothing due
            done = step
        for fn in work[step]:
            fn()
    if done < steps:
        step_fn(model, data, steps - done)
    wall1, cpu1 = clocks()
    return wall1 - wall0, cpu1 - cpu0, steps


def run_evclock(control_hz: float, seconds: float, planner: bool) -> tuple[float, float, int]:
    ctl = Controllers(control_hz)
    source = ctl.world.time_source()

    async def every(hz: float, work: Callable[[], None]) -> None:
        async for _tick in evclock.clock().rate(hz):
            work()

    async def main() -> tuple[float, float, int]:
        wall0, cpu0 = clocks()
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(every(control_hz, ctl.control))]
            if planner:
                tasks.append(tg.create_task(every(PLANNER_HZ, ctl.plan)))
            await evclock.clock().sleep(seconds)
            for task in tasks:
                task.cancel()
        wall1, cpu1 = clocks()
        return wall1 - wall0, cpu1 - cpu0, source.step_index

    result: tuple[float, float, int] = evclock.run(main(), source=source)
    return result


def compare(
    hz: float, seconds: float, rounds: int, planner: bool
) -> tuple[float, float, float, float]:
    """Best steps per CPU second and per wall second of each variant, alternating rounds."""
    best = {"sync": [0.0, 0.0], "evclock": [0.0, 0.0]}
    for _ in range(rounds):
        for name, fn in (("sync", run_hand_written), ("evclock", run_evclock)):
            wall, cpu, steps = fn(hz, seconds, planner)
            best[name][0] = max(best[name][0], steps / max(cpu, 1e-9))
            best[name][1] = max(best[name][1], steps / max(wall, 1e-9))
    return best["sync"][0], best["evclock"][0], best["sync"][1], best["evclock"][1]


def raw_steps_per_second(engine: str, steps: int, rounds: int) -> float:
    """Steps per CPU second of the arm holding its rest pose, no controller (best round)."""
    best = 0.0
    for _ in range(rounds):
        if engine == "mujoco":
            world = MuJoCoWorld()
            KukaReach(world, seed=0)
            model, data = world.model, world.data
            cpu0 = time.process_time()
            mujoco.mj_step(model, data, steps)
            cpu = time.process_time() - cpu0
        else:
            import pybullet as p

            client = p.connect(p.DIRECT)
            try:
                arm = KukaReach(client, seed=0)
                arm.arm.command(list(REST_POSE))
                cpu0 = time.process_time()
                for _ in range(steps):
                    p.stepSimulation(physicsClientId=client)
                cpu = time.process_time() - cpu0
            finally:
                p.disconnect(client)
        best = max(best, steps / max(cpu, 1e-9))
    return best


def scenario_steps_per_second(engine: str, rounds: int) -> tuple[float, float]:
    """Steps per CPU second of the whole kuka scenario under evclock (best round), and the
    mission time of the last round."""
    from evclock.tools._scenarios import open_world

    best, mission = 0.0, 0.0
    for _ in range(rounds):
        source, scenario = open_world(KukaReach, 0, engine=engine)

        async def main(scenario: Any = scenario) -> float:
            cpu0 = time.process_time()
            await scenario.run(evclock.clock())
            return time.process_time() - cpu0

        try:
            cpu = evclock.run(main(), source=source)
        finally:
            source.close()
        best = max(best, source.step_index / max(cpu, 1e-9))
        mission = scenario.finished_at
    return best, mission


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    parser.add_argument("--repeat", type=int, default=5, help="alternating rounds (best kept)")
    parser.add_argument(
        "--only",
        choices=("sync", "evclock"),
        help="run one MuJoCo variant once at --control-hz (for callgrind instruction counts)",
    )
    parser.add_argument("--control-hz", type=float, default=100.0)
    parser.add_argument("--no-planner", action="store_true", help="the joint controller only")
    args = parser.parse_args()
    planner = not args.no_planner
    if args.only:
        runner = run_hand_written if args.only == "sync" else run_evclock
        _wall, cpu, steps = runner(args.control_hz, args.seconds, planner)
        print(f"{args.only} at {args.control_hz:g} Hz: {steps} steps, {cpu:.3f} s CPU")
        return 0
    print(
        f"KUKA on MuJoCo, {args.seconds:g} simulated s per run, best of {args.repeat}, "
        f"{PHYSICS_HZ} Hz physics"
    )
    header = ("work", "loop steps/cpu-s", "evclock steps/cpu-s", "ratio", "wall ratio")
    print("{:>28} {:>17} {:>20} {:>7} {:>11}  goal".format(*header))
    cases = [(100.0, True, 0.9), (100.0, False, 0.9), (240.0, False, None)]
    for hz, with_planner, goal in cases:
        label = f"{hz:g} Hz control" + (" + 10 Hz IK" if with_planner else "")
        sync, ev, sync_wall, ev_wall = compare(hz, args.seconds, args.repeat, with_planner)
        ratio = ev / sync
        verdict = "" if goal is None else f">= {goal} {'PASS' if ratio >= goal else 'MISS'}"
        print(
            f"{label:>28} {sync:>17,.0f} {ev:>20,.0f} {ratio:>7.3f} "
            f"{ev_wall / sync_wall:>11.3f}  {verdict}"
        )
    have_pybullet = importlib.util.find_spec("pybullet") is not None
    steps = round(args.seconds * PHYSICS_HZ)
    raw_mj = raw_steps_per_second("mujoco", steps, args.repeat)
    print(f"\nthe arm alone, {steps} steps holding its pose (steps per CPU second):")
    print(f"  MuJoCo   {raw_mj:>12,.0f}")
    scenario_mj, mission_mj = scenario_steps_per_second("mujoco", args.repeat)
    if have_pybullet:
        raw_pb = raw_steps_per_second("pybullet", steps, args.repeat)
        print(f"  PyBullet {raw_pb:>12,.0f}   MuJoCo/PyBullet: {raw_mj / raw_pb:.2f}x")
    print("the kuka scenario (seed 0) under evclock, to mission end (steps per CPU second):")
    print(f"  MuJoCo   {scenario_mj:>12,.0f}   (mission {mission_mj:.1f} s)")
    if have_pybullet:
        scenario_pb, mission_pb = scenario_steps_per_second("pybullet", args.repeat)
        print(
            f"  PyBullet {scenario_pb:>12,.0f}   (mission {mission_pb:.1f} s)   "
            f"MuJoCo/PyBullet: {scenario_mj / scenario_pb:.2f}x"
        )
    else:
        print("  PyBullet: not installed (pip install 'evclock[pybullet]'), skipped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
