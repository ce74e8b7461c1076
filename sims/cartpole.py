"""Cart-pole balanced by a discrete LQR from a seeded, perturbed start.

Three concurrent controllers:

* ``balance`` (50 Hz): full-state feedback ``u = -K x`` on
  ``x = (cart position, pole angle, cart velocity, pole rate)``;
* ``judge`` (50 Hz, the mission): returns after :attr:`CartPole.hold_time` seconds, or early
  if the pole passes :attr:`CartPole.fail_angle` or the cart leaves its track
  (:attr:`CartPole.track_limit`);
* ``monitor`` (240 Hz, every physics step): records the largest pole angle and cart excursion.

The cart-pole implements the agent protocol of :mod:`evclock.gym`: a learning agent (or a
trained policy) replaces ``balance``, observing the joint states and pushing the cart.

The gains come from the engine's own model: mass matrix and gravity terms of the URDF, linearised
at upright by finite differences, discretised with a zero-order hold and fed to the discrete
Riccati iteration (numpy only).

The controllers and the linearisation are the same on both engines; only the cart's interface
differs (:class:`PyBulletCart`, :class:`MuJoCoCart`: loading, mass matrix, gravity forces,
joint states, and the force on the cart).
"""

from __future__ import annotations

import math
from collections.abc import Coroutine, Sequence
from typing import Any

import numpy as np

from evclock._extras import import_extra

from ._base import ClockLike, Metric, Scenario, pybullet
from ._mujoco import MuJoCoWorld

SLIDER = 0
"""``slider_to_cart``, prismatic along x."""
POLE = 1
"""``cart_to_pole``, continuous about y; 0 is upright, positive tips the pole toward +x."""

SATURATED_VELOCITY = 1e6
"""A velocity no motor reaches: a velocity motor aimed at it always pushes with its force limit."""

JOINT_NAMES = ("slider_to_cart", "cart_to_pole")

OBSERVATION_BOUND = (20.0, math.pi, 100.0, 100.0)
"""The agent's observation bounds: cart position (m), pole angle (rad), cart velocity (m/s),
pole rate (rad/s)."""


class PyBulletCart:
    """The cart-pole on PyBullet: both joints freed, the cart pushed by a saturated velocity
    motor (calls go through ``scenario.pb``, see :class:`~evclock_sims.kuka.PyBulletArm`)."""

    def __init__(self, scenario: CartPole) -> None:
        p = pybullet()
        self._p = p
        self.scenario = scenario
        self.robot = scenario.load_urdf("cartpole.urdf", robot=True, useFixedBase=True)
        p.setJointMotorControlArray(
            self.robot,
            [SLIDER, POLE],
            p.VELOCITY_CONTROL,
            forces=[0.0, 0.0],
            physicsClientId=scenario.client,
        )

    def mass_matrix(self, q: Sequence[float]) -> np.ndarray:
        """The joint-space mass matrix at positions ``q``."""
        p = self._p
        cid = self.scenario.client
        return np.array(p.calculateMassMatrix(self.robot, list(q), physicsClientId=cid))

    def gravity_forces(self, q: Sequence[float]) -> np.ndarray:
        """Generalized gravity forces at positions ``q``: inverse dynamics at rest."""
        rest = [0.0] * len(q)
        forces = self._p.calculateInverseDynamics(
            self.robot, list(q), rest, rest, physicsClientId=self.scenario.client
        )
        return np.array(forces)

    def tilt(self, angle: float) -> None:
        """Set the pole's angle (radians, at rest)."""
        self._p.resetJointState(self.robot, POLE, angle, physicsClientId=self.scenario.client)

    def joint_states(self) -> tuple[float, float, float, float]:
        """Cart position, pole angle, cart velocity, pole rate."""
        scenario = self.scenario
        cart, pole = scenario.pb.getJointStates(
            self.robot, [SLIDER, POLE], physicsClientId=scenario.client
        )
        return cart[0], pole[0], cart[1], pole[1]

    def push(self, force: float) -> None:
        """Push the cart with ``force`` newtons until the next command.

        ``TORQUE_CONTROL`` would only act during the next ``stepSimulation`` (PyBullet clears it
        after every step), but the balance loop runs once per ~4.8 steps.  A velocity motor
        aimed at an unreachable velocity with force limit ``|force|`` applies exactly that
        force on every step until replaced: a zero-order hold.
        """
        scenario = self.scenario
        scenario.pb.setJointMotorControl2(
            self.robot,
            SLIDER,
            self._p.VELOCITY_CONTROL,
            targetVelocity=math.copysign(SATURATED_VELOCITY, force),
            force=abs(force),
            physicsClientId=scenario.client,
        )


class MuJoCoCart:
    """The cart-pole on MuJoCo: free joints, a force motor on the slider (its ``ctrl`` is
    the force, held until changed: a zero-order hold). The model's mass matrix and gravity
    terms are read on a scratch ``MjData``, never on the simulated one."""

    def __init__(self, scenario: CartPole, world: MuJoCoWorld) -> None:
        self.world = world
        world.load_urdf("cartpole.urdf", motor_joints=[JOINT_NAMES[SLIDER]])
        self._mj = world.mj
        self._qpos = [world.joint_index(name)[0] for name in JOINT_NAMES]
        self._dofs = [world.joint_index(name)[1] for name in JOINT_NAMES]
        self._scratch = world.scratch()

    def _at(self, q: Sequence[float]) -> Any:
        scratch = self._scratch
        scratch.qpos[self._qpos] = q
        scratch.qvel[:] = 0.0
        self._mj.mj_forward(self.world.model, scratch)
        return scratch

    def mass_matrix(self, q: Sequence[float]) -> np.ndarray:
        """The joint-space mass matrix at positions ``q``."""
        model = self.world.model
        full = np.zeros((model.nv, model.nv))
        self._mj.mj_fullM(model, self._at(q), full)
        return full[np.ix_(self._dofs, self._dofs)]

    def gravity_forces(self, q: Sequence[float]) -> np.ndarray:
        """Generalized gravity forces at positions ``q`` (the bias forces at rest)."""
        return np.array(self._at(q).qfrc_bias[self._dofs])

    def tilt(self, angle: float) -> None:
        """Set the pole's angle (radians, at rest)."""
        self.world.data.qpos[self._qpos[POLE]] = angle
        self.world.forward()

    def joint_states(self) -> tuple[float, float, float, float]:
        """Cart position, pole angle, cart velocity, pole rate."""
        data = self.world.data
        cart, pole = self._qpos
        cart_v, pole_v = self._dofs
        return (
            float(data.qpos[cart]),
            float(data.qpos[pole]),
            float(data.qvel[cart_v]),
            float(data.qvel[pole_v]),
        )

    def push(self, force: float) -> None:
        """Push the cart with ``force`` newtons until the next command."""
        self.world.data.ctrl[0] = force


def _expm(matrix: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring a Taylor series (fine for small systems)."""
    norm = float(np.linalg.norm(matrix, np.inf))
    squarings = max(0, math.ceil(math.log2(norm)) + 1) if norm > 0.0 else 0
    scaled = matrix / 2.0**squarings
    result = term = np.eye(len(matrix))
    for k in range(1, 16):
        term = term @ scaled / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


_GAINS: dict[tuple[bytes, ...], np.ndarray] = {}
"""The gains :func:`discrete_lqr` solved, by the exact bytes of its inputs."""


def discrete_lqr(
    a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, dt: float
) -> np.ndarray:
    """Gain ``K`` (``u = -K x``) of the discrete LQR for ``dx/dt = a x + b u`` held over ``dt``.

    Solved once per distinct input (bit for bit) and process: the cart-pole asks again at
    every build, with the same model (a reset in place builds it again), and the Riccati
    iteration takes tens of milliseconds. Returns a new array each time.
    """
    a, b, q, r = (np.ascontiguousarray(x, dtype=np.float64) for x in (a, b, q, r))
    key = (*(x.tobytes() + str(x.shape).encode() for x in (a, b, q, r)), np.float64(dt).tobytes())
    gain = _GAINS.get(key)
    if gain is None:
        gain = _GAINS[key] = _solve_discrete_lqr(a, b, q, r, dt)
    return gain.copy()


def _solve_discrete_lqr(
    a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, dt: float
) -> np.ndarray:
    n, m = b.shape
    augmented = np.zeros((n + m, n + m))
    augmented[:n, :n] = a
    augmented[:n, n:] = b
    exponential = _expm(augmented * dt)
    ad, bd = exponential[:n, :n], exponential[:n, n:]

    def gain_for(cost: np.ndarray) -> np.ndarray:
        return np.linalg.solve(r + bd.T @ cost @ bd, bd.T @ cost @ ad)

    cost = q
    for _ in range(10_000):
        updated = q + ad.T @ cost @ (ad - bd @ gain_for(cost))
        converged = np.allclose(updated, cost, rtol=1e-12, atol=1e-12)
        cost = updated
        if converged:
            break
    return gain_for(cost)


class CartPole(Scenario):
    """``cartpole.urdf`` held upright by LQR force control on the cart."""

    name = "cartpole"
    description = "Cart-pole balanced for 30 s by a 50 Hz discrete LQR from a seeded tilt"
    default_until = 31.0

    balance_hz = 50.0
    monitor_hz = 240.0
    hold_time = 30.0
    """Seconds the pole must stay up."""
    fail_angle = 0.2
    """Radians: the pole counts as fallen beyond this."""
    max_force = 20.0
    """Newtons: cart actuator limit."""
    track_limit = 5.0
    """Metres: the cart counts as off its track beyond this distance from the start (the
    slider itself allows 15 m)."""
    state_cost = (1.0, 10.0, 0.1, 0.1)
    """LQR weights on cart position, pole angle, cart velocity, pole rate."""
    force_cost = 0.1
    engines = ("pybullet", "mujoco")
    agent_controller = "balance"
    policy = ""
    """A trained policy in place of balance: a .npz file of evclock.gym.LinearPolicy, or
    module:callable (see evclock.gym). Empty: the LQR balances."""

    def __init__(self, world: int | MuJoCoWorld, seed: int = 0) -> None:
        """Load the cart-pole (in a PyBullet client or a MuJoCo world), free both joints, tilt
        the pole by a seeded 2-6 degrees."""
        super().__init__(world, seed)
        self.cart: PyBulletCart | MuJoCoCart
        """The engine-facing part: loading, model terms, joint states, the cart's force."""
        if isinstance(world, MuJoCoWorld):
            self.cart = MuJoCoCart(self, world)
            self.robot = -1
        else:
            self.cart = PyBulletCart(self)
            self.robot = self.cart.robot
        self.gain = self._lqr_gain()
        tilt = math.radians(float(self.rng.uniform(2.0, 6.0))) * float(self.rng.choice([-1, 1]))
        self.cart.tilt(tilt)
        self.initial_tilt = tilt
        self.max_angle = abs(tilt)
        self.max_cart_offset = 0.0
        self.balanced_for = 0.0
        """Seconds the balance loop has kept the pole up."""

    def _lqr_gain(self) -> np.ndarray:
        """The LQR gain of the engine's model: derived once per MuJoCo world (a scenario
        built again in it reuses it), solved once per process (:func:`discrete_lqr`)."""

        def solve() -> np.ndarray:
            return discrete_lqr(
                *self._linearise(),
                np.diag(self.state_cost),
                np.array([[self.force_cost]]),
                1.0 / self.balance_hz,
            )

        if self.world is None:
            return solve()
        key = ("cartpole.gain", self.state_cost, self.force_cost, self.balance_hz)
        gain: np.ndarray = self.world.derived(key, solve)
        return gain.copy()

    def _linearise(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous ``(A, B)`` at upright rest from the engine's mass matrix and gravity."""
        upright = [0.0, 0.0]
        mass = self.cart.mass_matrix(upright)

        def gravity(joint: int, offset: float) -> np.ndarray:
            """Generalized gravity forces with ``joint`` displaced."""
            q = list(upright)
            q[joint] += offset
            return self.cart.gravity_forces(q)

        eps = 1e-6
        stiffness = np.zeros((2, 2))
        for joint in (SLIDER, POLE):
            stiffness[:, joint] = (gravity(joint, eps) - gravity(joint, -eps)) / (2.0 * eps)
        a = np.zeros((4, 4))
        a[:2, 2:] = np.eye(2)
        a[2:, :2] = -np.linalg.solve(mass, stiffness)
        b = np.zeros((4, 1))
        b[2:, 0] = np.linalg.solve(mass, np.array([1.0, 0.0]))
        return a, b

    def _joint_states(self) -> tuple[float, float, float, float]:
        """Cart position, pole angle, cart velocity, pole rate."""
        return self.cart.joint_states()

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        return {"monitor": self._monitor(clock), "balance": self._balance(clock)}

    async def _monitor(self, clock: ClockLike) -> None:
        """Track the worst pole angle and cart excursion at every physics step."""
        async for _tick in clock.rate(self.monitor_hz, name="monitor"):
            cart, angle, _, _ = self._joint_states()
            self.max_angle = max(self.max_angle, abs(angle))
            self.max_cart_offset = max(self.max_cart_offset, abs(cart))

    async def _balance(self, clock: ClockLike) -> None:
        """Apply the LQR force every tick."""
        async for _tick in clock.rate(self.balance_hz, name="balance"):
            state = np.array(self._joint_states())
            force = float(np.clip(-(self.gain @ state)[0], -self.max_force, self.max_force))
            self._apply_force(force)

    async def _mission(self, clock: ClockLike) -> None:
        """Return once the hold time is up or the pole has fallen (stopping the cart)."""
        start = clock.now().nanoseconds
        hold = round(self.hold_time * 1e9)
        async for tick in clock.rate(self.balance_hz, name="judge"):
            self.balanced_for = (tick.actual.nanoseconds - start) / 1e9
            if self.terminated() or tick.actual.nanoseconds - start >= hold:
                self._apply_force(0.0)
                return

    def _apply_force(self, force: float) -> None:
        """Push the cart with ``force`` newtons until the next command (a zero-order hold)."""
        self.cart.push(force)

    # The agent protocol (evclock.gym): the agent replaces ``balance``.

    @property
    def agent_hz(self) -> float:
        """The rate of the agent's controller: :attr:`balance_hz`."""
        return self.balance_hz

    def observation_space(self) -> Any:
        """Cart position (m), pole angle (rad), cart velocity (m/s), pole rate (rad/s):
        :data:`OBSERVATION_BOUND` each (the slider's range is 15 m; the pole falls past
        :attr:`fail_angle` long before it turns over)."""
        spaces = import_extra("gymnasium.spaces", "gym", needed_by="the cart-pole's agent")
        bound = np.array(OBSERVATION_BOUND)
        return spaces.Box(-bound, bound, dtype=np.float64)

    def action_space(self) -> Any:
        """The force on the cart as a fraction of :attr:`max_force`, in [-1, 1]."""
        spaces = import_extra("gymnasium.spaces", "gym", needed_by="the cart-pole's agent")
        return spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float64)

    def observe(self) -> np.ndarray:
        """The joint states: cart position, pole angle, cart velocity, pole rate."""
        return np.array(self._joint_states(), dtype=np.float64)

    def act(self, action: np.ndarray) -> None:
        """Push the cart with ``action[0] *`` :attr:`max_force` newtons until the next
        action."""
        self._apply_force(float(action[0]) * self.max_force)

    def reward(self) -> float:
        """1 for every period the pole is still up (as Gymnasium's own cart-pole)."""
        return 0.0 if self.terminated() else 1.0

    def terminated(self) -> bool:
        """The pole has fallen past :attr:`fail_angle`, or the cart has left its track
        (:attr:`track_limit`)."""
        cart, angle, _, _ = self._joint_states()
        return bool(abs(angle) >= self.fail_angle or abs(cart) >= self.track_limit)

    def success(self) -> bool:
        """The pole stayed within :attr:`fail_angle` for :attr:`hold_time` seconds, the cart
        on its track."""
        return (
            self.balanced_for >= self.hold_time
            and self.max_angle < self.fail_angle
            and self.max_cart_offset < self.track_limit
        )

    def _metrics(self) -> dict[str, Metric]:
        return {
            "initial_tilt_rad": self.initial_tilt,
            "max_angle_rad": self.max_angle,
            "max_cart_offset_m": self.max_cart_offset,
            "balanced_for_s": self.balanced_for,
        }
