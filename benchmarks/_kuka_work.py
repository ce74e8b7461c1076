"""The KUKA reaching work both KUKA benchmarks measure (``kuka_throughput.py`` on PyBullet,
``mujoco_kuka.py`` on MuJoCo): the IK planner, the rate schedule a hand-written loop follows,
and the clocks read around a measured run. Each benchmark adds its engine's joint controller.
"""

from __future__ import annotations

import time
from fractions import Fraction

import numpy as np

from evclock_sims.kuka import REST_POSE, KukaReach

PHYSICS_HZ = 240
PLANNER_HZ = 10


class ReachWork:
    """The planner and the controller's state on one KUKA arm; subclasses add ``control``."""

    def __init__(self, arm: KukaReach, control_hz: float) -> None:
        self.arm = arm
        self.command = np.array(REST_POSE)
        self.max_step = arm.max_joint_speed / control_hz
        self.target_index = 0
        self.plans = 0

    def plan(self) -> None:
        arm = self.arm
        target = arm.targets[self.target_index]
        if np.linalg.norm(arm.flange_position() - target) < arm.tolerance:
            self.target_index = (self.target_index + 1) % len(arm.targets)
            target = arm.targets[self.target_index]
        arm.goal = np.array(arm._inverse_kinematics(target))
        self.plans += 1


def due_steps(hz: float, steps: int) -> list[int]:
    """The physics steps (0-based, before stepping) at which a rate ticks, with clock.rate's
    integer deadlines: tick i is due at the first step whose (floor) time is >= i x period."""
    period = Fraction(10**9) / Fraction(hz)
    step_ns = Fraction(10**9, PHYSICS_HZ)
    due = []
    index = 0
    while True:
        deadline = index * period.numerator // period.denominator
        # The first step whose (floor) time is >= the deadline (sleeps quantise up).
        step = -(-deadline * step_ns.denominator // step_ns.numerator)
        while step * step_ns.numerator // step_ns.denominator < deadline:
            step += 1
        if step >= steps:
            return due
        due.append(step)
        index += 1


def clocks() -> tuple[float, float]:
    """Wall and process CPU time, read together."""
    return time.perf_counter(), time.process_time()
