"""KUKA reaching: evclock-driven controllers vs a hand-written synchronous loop, same work.

Usage: python benchmarks/kuka_throughput.py [--seconds 20] [--repeat 3] [--rtf-check 10]

Both variants load the same KUKA world and run the same control code (the functions below):
a joint controller (slew toward the IK goal, send position targets) at ``control_hz`` and an
IK planner at 10 Hz, over 240 Hz physics, cycling through the scenario's targets. The
synchronous loop decides which controller is due on each physics step with the same integer
deadline arithmetic as ``clock.rate``; the evclock variant runs the controllers as rate-loop
tasks on a ``PyBulletTimeSource``. Reported: physics steps per wall second for both, in the
same run, and their ratio (targets: >= 0.8 with the controller at 240 Hz, >= 0.95 at 100 Hz).
The variants alternate round by round and the best round of each is kept; throughput is
computed from the process's CPU time (what the work costs, immune to other processes and to
a virtual machine's stolen time), with the wall-time ratio printed beside it.
``--rtf-check S`` also runs S simulated seconds at rtf=1 and reports the achieved real-time
factor (target: within 1%).

On a noisy (virtual) machine, instruction counts compare the two exactly:
``valgrind --tool=callgrind python benchmarks/kuka_throughput.py --only sync --control-hz 100``
and the same with ``--only evclock``; subtract a ``--seconds 0`` run of each for start-up.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

import numpy as np
import pybullet as p
from _kuka_work import PHYSICS_HZ, PLANNER_HZ, ReachWork, clocks, due_steps

import evclock
from evclock_sims.kuka import KukaReach


class Controllers(ReachWork):
    """The control work both variants do, on one KUKA world."""

    def __init__(self, client: int, control_hz: float) -> None:
        super().__init__(KukaReach(client, seed=0, control_hz=control_hz), control_hz)
        self.forces = [self.arm.max_joint_torque] * len(self.arm.joints)

    def control(self) -> None:
        arm = self.arm
        self.command += np.clip(arm.goal - self.command, -self.max_step, self.max_step)
        p.setJointMotorControlArray(
            arm.robot,
            arm.joints,
            p.POSITION_CONTROL,
            targetPositions=self.command.tolist(),
            forces=self.forces,
            physicsClientId=arm.client,
        )


def ticks_due(hz: float, steps: int) -> list[bool]:
    """Per physics step: is a rate tick due, with clock.rate's integer deadlines (tick 0 at 0)."""
    due = [False] * steps
    for step in due_steps(hz, steps):
        due[step] = True
    return due


def run_synchronous(control_hz: float, seconds: float) -> tuple[float, float, int]:
    client = p.connect(p.DIRECT)
    try:
        ctl = Controllers(client, control_hz)
        steps = round(seconds * PHYSICS_HZ)
        control_due = ticks_due(control_hz, steps)
        plan_due = ticks_due(PLANNER_HZ, steps)
        wall0, cpu0 = clocks()
        for step in range(steps):
            if control_due[step]:
                ctl.control()
            if plan_due[step]:
                ctl.plan()
            p.stepSimulation(physicsClientId=client)
        wall1, cpu1 = clocks()
        return wall1 - wall0, cpu1 - cpu0, steps
    finally:
        p.disconnect(client)


def run_evclock(
    control_hz: float, seconds: float, rtf: float | None = None
) -> tuple[float, float, int]:
    source = evclock.sources.PyBulletTimeSource.connect()
    ctl = Controllers(source.client, control_hz)

    async def every(hz: float, work: object) -> None:
        async for _tick in evclock.clock().rate(hz):
            work()  # type: ignore[operator]

    async def main() -> tuple[float, float, int]:
        wall0, cpu0 = clocks()
        async with asyncio.TaskGroup() as tg:
            control = tg.create_task(every(control_hz, ctl.control))
            planner = tg.create_task(every(PLANNER_HZ, ctl.plan))
            await evclock.clock().sleep(seconds)
            control.cancel()
            planner.cancel()
        wall1, cpu1 = clocks()
        return wall1 - wall0, cpu1 - cpu0, source.step_index

    return evclock.run(main(), source=source, rtf=rtf)


def compare(hz: float, seconds: float, rounds: int) -> tuple[float, float, float, float]:
    """Best steps per CPU second and per wall second of each variant, alternating rounds."""
    best = {"sync": [0.0, 0.0], "evclock": [0.0, 0.0]}
    for _ in range(rounds):
        for name, fn in (("sync", run_synchronous), ("evclock", run_evclock)):
            wall, cpu, steps = fn(hz, seconds)
            best[name][0] = max(best[name][0], steps / cpu)
            best[name][1] = max(best[name][1], steps / wall)
    return best["sync"][0], best["evclock"][0], best["sync"][1], best["evclock"][1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    parser.add_argument("--repeat", type=int, default=5, help="alternating rounds (best kept)")
    parser.add_argument(
        "--rtf-check", type=float, default=10.0, help="sim seconds at rtf=1 (0: skip)"
    )
    parser.add_argument(
        "--only",
        choices=("sync", "evclock"),
        help="run one variant once at --control-hz (for instruction counting under callgrind)",
    )
    parser.add_argument("--control-hz", type=float, default=100.0)
    args = parser.parse_args()
    if args.only:
        runner = run_synchronous if args.only == "sync" else run_evclock
        wall, cpu, steps = runner(args.control_hz, args.seconds)
        print(f"{args.only} at {args.control_hz:g} Hz: {steps} steps, {cpu:.3f} s CPU")
        return 0
    print(f"KUKA, {args.seconds:g} simulated s per run, best of {args.repeat}, 240 Hz physics")
    header = ("controller", "sync steps/cpu-s", "evclock steps/cpu-s", "ratio", "wall ratio")
    print("{:>10} {:>17} {:>20} {:>7} {:>11}  target".format(*header))
    for hz, target in ((240.0, 0.8), (100.0, 0.95)):
        sync, ev, sync_wall, ev_wall = compare(hz, args.seconds, args.repeat)
        ratio = ev / sync
        verdict = "PASS" if ratio >= target else "MISS"
        print(
            f"{hz:>8g}Hz {sync:>17,.0f} {ev:>20,.0f} {ratio:>7.3f} {ev_wall / sync_wall:>11.3f}"
            f"  >= {target} {verdict}"
        )
    if args.rtf_check > 0:
        wall, _cpu, _steps = run_evclock(100.0, args.rtf_check, rtf=1.0)
        achieved = args.rtf_check / wall
        ok = abs(achieved - 1.0) <= 0.01
        print(
            f"rtf=1 for {args.rtf_check:g} simulated s: {wall:.3f} s of wall time, achieved "
            f"rtf {achieved:.4f} (target within 1%): {'PASS' if ok else 'MISS'}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
