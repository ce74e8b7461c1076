"""KUKA iiwa reaching a seeded sequence of Cartesian targets.

Two concurrent controllers:

* ``planner`` (10 Hz, the mission): inverse kinematics toward the current target; advances to the
  next target once the end effector has stayed within :attr:`KukaReach.tolerance` of it for
  :attr:`KukaReach.dwell` seconds.
* ``joint_control`` (100 Hz by default, ``control_hz``): slews the commanded joint positions toward
  the IK solution at a bounded joint speed and sends them as position-control targets.
"""

from __future__ import annotations

from collections.abc import Coroutine
from typing import Any

import numpy as np
import pybullet as p

from ._base import ClockLike, Metric, Scenario

END_EFFECTOR_LINK = 6
"""``lbr_iiwa_link_7``, the flange."""

REST_POSE = (0.0, 0.4, 0.0, -1.4, 0.0, 1.2, 0.0)
"""Start configuration (elbow up, flange pointing down) and the IK null-space preference."""

CANDIDATE_TARGETS = (
    (0.50, 0.20, 0.40),
    (0.55, -0.25, 0.50),
    (0.40, 0.00, 0.65),
    (0.60, 0.10, 0.30),
    (0.45, -0.35, 0.35),
    (0.35, 0.35, 0.55),
    (0.65, -0.05, 0.45),
    (0.50, 0.30, 0.60),
)
"""Reachable flange positions (metres, world frame); each run picks a seeded subset."""


class KukaReach(Scenario):
    """KUKA iiwa (fixed base) visiting 3-4 seeded Cartesian targets, flange pointing down."""

    name = "kuka"
    description = "KUKA iiwa reaching seeded Cartesian targets: 10 Hz IK planner, joint control"
    default_until = 10.0

    planner_hz = 10.0
    tolerance = 0.025
    """Metres: the flange counts as 'at' a target within this distance."""
    dwell = 0.3
    """Seconds the flange must stay within tolerance before the next target."""
    max_joint_speed = 1.0
    """rad/s: the joint controller slews its command toward the IK solution at most this fast."""
    max_joint_torque = 300.0
    """N m: motor force limit, the URDF's effort limit."""
    target_jitter = 0.02
    """Metres: seeded uniform jitter added to each chosen candidate target."""

    def __init__(self, client: int, seed: int = 0, *, control_hz: float = 100.0) -> None:
        """Load the arm at :data:`REST_POSE` and choose the targets; ``control_hz`` sets the rate
        of the joint controller."""
        super().__init__(client, seed)
        self.control_hz = control_hz
        self.robot = self.load_urdf("kuka_iiwa/model.urdf", useFixedBase=True)
        self.joints = list(range(p.getNumJoints(self.robot, physicsClientId=client)))
        infos = [p.getJointInfo(self.robot, j, physicsClientId=client) for j in self.joints]
        self.lower = [info[8] for info in infos]
        self.upper = [info[9] for info in infos]
        for joint, angle in zip(self.joints, REST_POSE, strict=True):
            p.resetJointState(self.robot, joint, angle, physicsClientId=client)

        count = int(self.rng.integers(3, 5))
        chosen = self.rng.choice(len(CANDIDATE_TARGETS), size=count, replace=False)
        jitter = self.rng.uniform(-self.target_jitter, self.target_jitter, size=(count, 3))
        self.targets = [
            np.array(CANDIDATE_TARGETS[i]) + d for i, d in zip(chosen, jitter, strict=True)
        ]
        self.orientation = p.getQuaternionFromEuler([np.pi, 0.0, 0.0])
        self.reached_at: list[float] = []
        self.goal = np.array(REST_POSE)
        """Joint positions the planner asks for (latest IK solution)."""
        self.final_error = float("inf")

    def flange_position(self) -> np.ndarray:
        """World position of the flange link frame."""
        link = self.pb.getLinkState(
            self.robot,
            END_EFFECTOR_LINK,
            computeForwardKinematics=True,
            physicsClientId=self.client,
        )
        return np.array(link[4])

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        return {"joint_control": self._joint_control(clock)}

    async def _joint_control(self, clock: ClockLike) -> None:
        """Slew the position command toward :attr:`goal` and send it every tick."""
        command = np.array(REST_POSE)
        max_step = self.max_joint_speed / self.control_hz
        forces = [self.max_joint_torque] * len(self.joints)
        async for _tick in clock.rate(self.control_hz, name="joint_control"):
            command += np.clip(self.goal - command, -max_step, max_step)
            self.pb.setJointMotorControlArray(
                self.robot,
                self.joints,
                p.POSITION_CONTROL,
                targetPositions=command.tolist(),
                forces=forces,
                physicsClientId=self.client,
            )

    async def _mission(self, clock: ClockLike) -> None:
        """Plan toward each target in turn; return once the last one is reached."""
        index = 0
        within_since: float | None = None
        async for tick in clock.rate(self.planner_hz, name="planner"):
            target = self.targets[index]
            self.final_error = float(np.linalg.norm(self.flange_position() - target))
            now = tick.actual.seconds
            if self.final_error > self.tolerance:
                within_since = None
            elif within_since is None:
                within_since = now
            elif now - within_since >= self.dwell:
                self.reached_at.append(now)
                index += 1
                within_since = None
                if index == len(self.targets):
                    return
                target = self.targets[index]
            self.goal = np.array(self._inverse_kinematics(target))

    def _inverse_kinematics(self, target: np.ndarray) -> list[float]:
        """Joint positions putting the flange at ``target``, pointing down, near the rest pose."""
        solution: list[float] = self.pb.calculateInverseKinematics(
            self.robot,
            END_EFFECTOR_LINK,
            target.tolist(),
            self.orientation,
            lowerLimits=self.lower,
            upperLimits=self.upper,
            jointRanges=[hi - lo for lo, hi in zip(self.lower, self.upper, strict=True)],
            restPoses=list(REST_POSE),
            maxNumIterations=100,
            residualThreshold=1e-5,
            physicsClientId=self.client,
        )
        return solution

    def success(self) -> bool:
        """All targets were reached."""
        return len(self.reached_at) == len(self.targets)

    def _metrics(self) -> dict[str, Metric]:
        return {
            "targets": len(self.targets),
            "targets_reached": len(self.reached_at),
            "final_error_m": self.final_error,
            "control_hz": self.control_hz,
        }
