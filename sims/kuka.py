"""KUKA iiwa reaching a seeded sequence of Cartesian targets.

Two concurrent controllers:

* ``planner`` (10 Hz, the mission): inverse kinematics toward the current target; advances to the
  next target once the end effector has stayed within :attr:`KukaReach.tolerance` of it for
  :attr:`KukaReach.dwell` seconds.
* ``joint_control`` (100 Hz by default, ``control_hz``): slews the commanded joint positions toward
  the IK solution at a bounded joint speed and sends them as position-control targets.

The KUKA implements the agent protocol of :mod:`evclock.gym`: a learning agent (or a trained
policy) replaces ``joint_control`` (by default), observing the joints, the planner's goal, the
flange and its target, and commanding the joint positions, while the planner keeps planning; or
it replaces the ``planner``, observing the joints, the flange and its target, and choosing the
joint goal the joint controller slews toward, while the mission keeps tracking the targets (in
a 10 Hz loop then named ``targets``).

The controllers are the same on both engines; only the arm's interface differs
(:class:`PyBulletArm`: ``POSITION_CONTROL`` motors and PyBullet's IK; :class:`MuJoCoArm`:
position actuators from :func:`~evclock_sims._mujoco.urdf_to_mujoco`, with gravity
compensation, and a damped-least-squares IK with the same null-space preference).
"""

from __future__ import annotations

import math
from collections.abc import Coroutine, Sequence
from typing import Any

import numpy as np

from evclock._extras import import_extra

from ._base import ClockLike, Metric, Scenario, pybullet
from ._mujoco import MuJoCoWorld

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

JOINT_NAMES = tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8))
FLANGE_BODY = "lbr_iiwa_link_7"
FLANGE_DOWN = (math.pi, 0.0, 0.0)
"""The flange's orientation at every target: roll pi (pointing down), as Euler angles."""

MUJOCO_SERVO = {"kp": 2000.0, "kv": 100.0, "armature": 0.1}
"""The MuJoCo arm's position servos: gains (N m/rad, N m s/rad) and joint armature (kg m^2)."""


class PyBulletArm:
    """The KUKA on PyBullet: ``POSITION_CONTROL`` motors and ``calculateInverseKinematics``.

    Calls go through ``scenario.pb`` (the ``pybullet`` module, or the stand-in of
    ``evclock control`` that forwards them to the simulation process).
    """

    def __init__(self, scenario: KukaReach) -> None:
        p = pybullet()
        self._p = p
        self.scenario = scenario
        client = scenario.client
        self.robot = scenario.load_urdf("kuka_iiwa/model.urdf", robot=True, useFixedBase=True)
        self.joints = list(range(p.getNumJoints(self.robot, physicsClientId=client)))
        infos = [p.getJointInfo(self.robot, j, physicsClientId=client) for j in self.joints]
        self.lower = [info[8] for info in infos]
        self.upper = [info[9] for info in infos]
        for joint, angle in zip(self.joints, REST_POSE, strict=True):
            p.resetJointState(self.robot, joint, angle, physicsClientId=client)
        self.orientation = p.getQuaternionFromEuler(FLANGE_DOWN)
        self.forces = [scenario.max_joint_torque] * len(self.joints)

    def flange_position(self) -> np.ndarray:
        """World position of the flange link frame."""
        scenario = self.scenario
        link = scenario.pb.getLinkState(
            self.robot,
            END_EFFECTOR_LINK,
            computeForwardKinematics=True,
            physicsClientId=scenario.client,
        )
        return np.array(link[4])

    def joint_positions(self) -> np.ndarray:
        """The joint angles (radians)."""
        scenario = self.scenario
        states = scenario.pb.getJointStates(
            self.robot, self.joints, physicsClientId=scenario.client
        )
        return np.array([state[0] for state in states])

    def command(self, positions: Sequence[float]) -> None:
        """Send joint position targets (radians), each motor limited to the maximum torque."""
        scenario = self.scenario
        scenario.pb.setJointMotorControlArray(
            self.robot,
            self.joints,
            self._p.POSITION_CONTROL,
            targetPositions=list(positions),
            forces=self.forces,
            physicsClientId=scenario.client,
        )

    def inverse_kinematics(self, target: np.ndarray) -> list[float]:
        """Joint positions putting the flange at ``target``, pointing down, near the rest pose."""
        scenario = self.scenario
        solution: list[float] = scenario.pb.calculateInverseKinematics(
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
            physicsClientId=scenario.client,
        )
        return solution


class MuJoCoArm:
    """The KUKA on MuJoCo: position actuators (``ctrl`` = target angles) with gravity
    compensation, and a damped-least-squares IK toward the flange position and orientation
    with the rest pose as null-space preference (as PyBullet's ``restPoses``).

    Kinematics for the controllers (flange position, IK) run on a scratch ``MjData``: they
    never touch the simulated data, so they cannot change the trajectory.
    """

    ik_damping = 1e-4
    """Damping of the least-squares IK step (the square of the usual lambda)."""
    ik_null_gain = 0.1
    """Fraction of the distance to the rest pose taken per IK iteration in the null space."""
    ik_iterations = 20
    """Iterations per IK call at most: each call starts from the previous solution (the
    planner re-solves every tick), so a few usually suffice."""

    def __init__(self, scenario: KukaReach, world: MuJoCoWorld) -> None:
        self.world = world
        world.load_urdf(
            "kuka_iiwa/model.urdf",
            position_joints=JOINT_NAMES,
            force_limit=scenario.max_joint_torque,
            gravity_compensation=True,
            **MUJOCO_SERVO,
        )
        mj, model, data = world.mj, world.model, world.data
        self._mj = mj
        self.joints = [world.joint_index(name)[0] for name in JOINT_NAMES]
        self.lower = [float(model.jnt_range[j][0]) for j in range(len(JOINT_NAMES))]
        self.upper = [float(model.jnt_range[j][1]) for j in range(len(JOINT_NAMES))]
        data.qpos[self.joints] = REST_POSE
        data.ctrl[:] = REST_POSE
        world.forward()
        self.flange = world.body_index(FLANGE_BODY)
        self._scratch = world.scratch()
        self._down = np.zeros(4)
        mj.mju_euler2Quat(self._down, np.array(FLANGE_DOWN), "xyz")
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))
        self._last: np.ndarray | None = None

    def _kinematics(self, q: np.ndarray) -> Any:
        scratch = self._scratch
        scratch.qpos[self.joints] = q
        self._mj.mj_kinematics(self.world.model, scratch)
        return scratch

    def flange_position(self) -> np.ndarray:
        """World position of the flange link frame."""
        scratch = self._kinematics(self.world.data.qpos[self.joints])
        position: np.ndarray = scratch.xpos[self.flange].copy()
        return position

    def joint_positions(self) -> np.ndarray:
        """The joint angles (radians)."""
        return np.array(self.world.data.qpos[self.joints], dtype=np.float64)

    def command(self, positions: Sequence[float]) -> None:
        """Set the position actuators' targets (radians); they hold until the next command."""
        self.world.data.ctrl[:] = positions

    def inverse_kinematics(self, target: np.ndarray) -> list[float]:
        """Joint positions putting the flange at ``target``, pointing down, near the rest pose."""
        mj, model = self._mj, self.world.model
        # Warm start from the last solution (the arm lags behind it while it slews): a few
        # iterations then suffice, where starting from the arm's pose takes many.
        start = self._last if self._last is not None else self.world.data.qpos[self.joints]
        q = np.array(start, dtype=float)
        rest = np.array(REST_POSE)
        lower, upper = np.array(self.lower), np.array(self.upper)
        error = np.zeros(6)
        turn, conjugate = np.zeros(4), np.zeros(4)
        identity = np.eye(len(q))
        for _ in range(self.ik_iterations):
            scratch = self._kinematics(q)
            error[:3] = target - scratch.xpos[self.flange]
            mj.mju_negQuat(conjugate, scratch.xquat[self.flange])
            mj.mju_mulQuat(turn, self._down, conjugate)
            mj.mju_quat2Vel(error[3:], turn, 1.0)
            if float(np.linalg.norm(error)) < 1e-5:
                break
            mj.mj_comPos(model, scratch)
            mj.mj_jacBody(model, scratch, self._jacp, self._jacr, self.flange)
            jacobian = np.vstack((self._jacp, self._jacr))[:, self.joints]
            inverse = jacobian.T @ np.linalg.inv(
                jacobian @ jacobian.T + self.ik_damping * np.eye(6)
            )
            # The exact (undamped) null-space projector: the pull toward the rest pose does
            # not disturb the task.
            null = identity - jacobian.T @ np.linalg.solve(jacobian @ jacobian.T, jacobian)
            q = np.clip(q + inverse @ error + null @ (self.ik_null_gain * (rest - q)), lower, upper)
        self._last = q
        solution: list[float] = q.tolist()
        return solution


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
    engines = ("pybullet", "mujoco")
    agent_controller = "joint_control"
    agent_controllers = ("joint_control", "planner")
    policy = ""
    """A trained policy in place of joint_control: a .npz file of evclock.gym.LinearPolicy, or
    module:callable (see evclock.gym). Empty: the joint
    controller slews toward the planner's goal."""

    def __init__(
        self, world: int | MuJoCoWorld, seed: int = 0, *, control_hz: float = 100.0
    ) -> None:
        """Load the arm at :data:`REST_POSE` (in a PyBullet client or a MuJoCo world) and
        choose the targets; ``control_hz`` sets the rate of the joint controller."""
        super().__init__(world, seed)
        self.control_hz = control_hz
        self.arm: PyBulletArm | MuJoCoArm
        """The engine-facing part: the arm's sensors, motors and IK."""
        if isinstance(world, MuJoCoWorld):
            self.arm = MuJoCoArm(self, world)
            self.robot = -1
        else:
            self.arm = PyBulletArm(self)
            self.robot = self.arm.robot
            self.orientation = self.arm.orientation
        self.joints = self.arm.joints
        self.lower = self.arm.lower
        self.upper = self.arm.upper

        count = int(self.rng.integers(3, 5))
        chosen = self.rng.choice(len(CANDIDATE_TARGETS), size=count, replace=False)
        jitter = self.rng.uniform(-self.target_jitter, self.target_jitter, size=(count, 3))
        self.targets = [
            np.array(CANDIDATE_TARGETS[i]) + d for i, d in zip(chosen, jitter, strict=True)
        ]
        self.reached_at: list[float] = []
        self.goal = np.array(REST_POSE)
        """Joint positions the planner asks for (latest IK solution)."""
        self._set_goal: tuple[int, np.ndarray] | None = None  # an agent's: (sim ns, goal before)
        self._clock: ClockLike | None = None
        self.final_error = float("inf")
        self.index = 0
        """The index of the target the planner heads for."""

    def flange_position(self) -> np.ndarray:
        """World position of the flange link frame."""
        return self.arm.flange_position()

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        return {"joint_control": self._joint_control(clock)}

    def _controllers(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        """The background controllers, and the one replacing the planner when one does (the
        planner is the mission's: the mission then only tracks the targets)."""
        planner = self.replaced.get("planner")
        if planner is None:
            return super()._controllers(clock)
        replaced = self.replaced
        self.replaced = {label: other for label, other in replaced.items() if label != "planner"}
        try:
            services = super()._controllers(clock)
        finally:
            self.replaced = replaced
        services["planner"] = planner(clock)
        return services

    async def _joint_control(self, clock: ClockLike) -> None:
        """Slew the position command toward :attr:`goal` and send it every tick."""
        command = np.array(REST_POSE)
        max_step = self.max_joint_speed / self.control_hz
        self._clock = clock
        async for tick in clock.rate(self.control_hz, name="joint_control"):
            goal = self.goal
            if self._set_goal is not None and self._set_goal[0] == tick.actual.nanoseconds:
                goal = self._set_goal[1]  # an agent's goal of this instant: from the next tick
            command += np.clip(goal - command, -max_step, max_step)
            self.arm.command(command.tolist())

    async def _mission(self, clock: ClockLike) -> None:
        """Plan toward each target in turn (unless the planner is replaced); return once the
        last one is reached."""
        within_since: float | None = None
        planning = "planner" not in self.replaced
        name = "planner" if planning else "targets"
        async for tick in clock.rate(self.planner_hz, name=name):
            index = self.index
            target = self.targets[index]
            self.final_error = float(np.linalg.norm(self.flange_position() - target))
            now = tick.actual.seconds
            if self.final_error > self.tolerance:
                within_since = None
            elif within_since is None:
                within_since = now
            elif now - within_since >= self.dwell:
                self.reached_at.append(now)
                index = self.index = index + 1
                within_since = None
                if index == len(self.targets):
                    return
                target = self.targets[index]
            if planning:
                self.goal = np.array(self._inverse_kinematics(target))

    def _inverse_kinematics(self, target: np.ndarray) -> list[float]:
        """Joint positions putting the flange at ``target``, pointing down, near the rest pose."""
        return self.arm.inverse_kinematics(target)

    # The agent protocol (evclock.gym): the agent replaces ``joint_control`` (default) or
    # the ``planner`` (set ``agent_controller`` on the instance).

    @property
    def agent_hz(self) -> float:
        """The rate of the agent's controller: :attr:`control_hz` (``joint_control``) or
        :attr:`planner_hz` (``planner``)."""
        return self.planner_hz if self.agent_controller == "planner" else self.control_hz

    def observation_space(self) -> Any:
        """For ``joint_control``: joint angles (7, rad), the planner's goal angles (7, rad),
        the flange position (3, m) and the current target (3, m); for the ``planner``: the
        same without the goal. Within +-pi rad (every joint's range is narrower) and +-2 m
        (the arm reaches 1.3 m)."""
        spaces = import_extra("gymnasium.spaces", "gym", needed_by="the KUKA's agent")
        angles = 7 if self.agent_controller == "planner" else 14
        bound = np.array([math.pi] * angles + [2.0] * 6)
        return spaces.Box(-bound, bound, dtype=np.float64)

    def action_space(self) -> Any:
        """Joint positions, each joint's range mapped onto [-1, 1] (-1: its lower limit, 1:
        its upper limit): the joints' position targets (``joint_control``), or the goal the
        joint controller slews toward (``planner``)."""
        spaces = import_extra("gymnasium.spaces", "gym", needed_by="the KUKA's agent")
        return spaces.Box(-1.0, 1.0, shape=(len(self.joints),), dtype=np.float64)

    def observe(self) -> np.ndarray:
        """Joint angles, planner goal (for ``joint_control`` only), flange position and
        current target, concatenated."""
        target = self.targets[min(self.index, len(self.targets) - 1)]
        joints, flange = self.arm.joint_positions(), self.flange_position()
        if self.agent_controller == "planner":
            parts: tuple[np.ndarray, ...] = (joints, flange, target)
        else:
            parts = (joints, self.goal, flange, target)
        return np.concatenate(parts).astype(np.float64)

    def act(self, action: np.ndarray) -> None:
        """Apply ``action`` (see :meth:`action_space`): the joints' position targets, or the
        planner's goal."""
        lower, upper = np.array(self.lower), np.array(self.upper)
        positions = lower + (action + 1.0) * 0.5 * (upper - lower)
        if self.agent_controller == "planner":
            # The joint controller takes it from its next tick, also when it ticks at this
            # same instant after the agent: the same in an environment (which acts once the
            # tick's other work is done) as under a policy acting within the tick.
            assert self._clock is not None
            self._set_goal = (self._clock.now().nanoseconds, self.goal)
            self.goal = positions
        else:
            self.arm.command(positions.tolist())

    def reward(self) -> float:
        """Minus the flange's distance to the current target, in metres (0 once all are
        reached)."""
        if self.terminated():
            return 0.0
        target = self.targets[self.index]
        return -float(np.linalg.norm(self.flange_position() - target))

    def terminated(self) -> bool:
        """Every target has been reached."""
        return self.success()

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
