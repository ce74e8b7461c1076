"""Cart-pole balanced by a discrete LQR from a seeded, perturbed start.

Two concurrent controllers:

* ``balance`` (50 Hz, the mission): full-state feedback ``u = -K x`` on
  ``x = (cart position, pole angle, cart velocity, pole rate)``; returns after
  :attr:`CartPole.hold_time` seconds, or early if the pole passes :attr:`CartPole.fail_angle`.
* ``monitor`` (240 Hz, every physics step): records the largest pole angle and cart excursion.

The gains come from PyBullet's own model: mass matrix and gravity terms of the URDF, linearised
at upright by finite differences, discretised with a zero-order hold and fed to the discrete
Riccati iteration (numpy only).
"""

from __future__ import annotations

import math
from collections.abc import Coroutine
from typing import Any

import numpy as np
import pybullet as p

from ._base import ClockLike, Metric, Scenario

SLIDER = 0
"""``slider_to_cart``, prismatic along x."""
POLE = 1
"""``cart_to_pole``, continuous about y; 0 is upright, positive tips the pole toward +x."""

SATURATED_VELOCITY = 1e6
"""A velocity no motor reaches: a velocity motor aimed at it always pushes with its force limit."""


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


def discrete_lqr(
    a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, dt: float
) -> np.ndarray:
    """Gain ``K`` (``u = -K x``) of the discrete LQR for ``dx/dt = a x + b u`` held over ``dt``."""
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
    state_cost = (1.0, 10.0, 0.1, 0.1)
    """LQR weights on cart position, pole angle, cart velocity, pole rate."""
    force_cost = 0.1

    def __init__(self, client: int, seed: int = 0) -> None:
        """Load the cart-pole, free both joints, tilt the pole by a seeded 2-6 degrees."""
        super().__init__(client, seed)
        self.robot = self.load_urdf("cartpole.urdf", useFixedBase=True)
        p.setJointMotorControlArray(
            self.robot,
            [SLIDER, POLE],
            p.VELOCITY_CONTROL,
            forces=[0.0, 0.0],
            physicsClientId=client,
        )
        self.gain = discrete_lqr(
            *self._linearise(),
            np.diag(self.state_cost),
            np.array([[self.force_cost]]),
            1.0 / self.balance_hz,
        )
        tilt = math.radians(float(self.rng.uniform(2.0, 6.0))) * float(self.rng.choice([-1, 1]))
        p.resetJointState(self.robot, POLE, tilt, physicsClientId=client)
        self.initial_tilt = tilt
        self.max_angle = abs(tilt)
        self.max_cart_offset = 0.0
        self.balanced_for = 0.0
        """Seconds the balance loop has kept the pole up."""

    def _linearise(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous ``(A, B)`` at upright rest from PyBullet's mass matrix and gravity terms."""
        cid = self.client
        upright = [0.0, 0.0]
        mass = np.array(p.calculateMassMatrix(self.robot, upright, physicsClientId=cid))

        def gravity(joint: int, offset: float) -> np.ndarray:
            """Generalized gravity forces with ``joint`` displaced: inverse dynamics at rest."""
            q = list(upright)
            q[joint] += offset
            forces = p.calculateInverseDynamics(
                self.robot, q, upright, upright, physicsClientId=cid
            )
            return np.array(forces)

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
        cart, pole = self.pb.getJointStates(self.robot, [SLIDER, POLE], physicsClientId=self.client)
        return cart[0], pole[0], cart[1], pole[1]

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        return {"monitor": self._monitor(clock)}

    async def _monitor(self, clock: ClockLike) -> None:
        """Track the worst pole angle and cart excursion at every physics step."""
        async for _tick in clock.rate(self.monitor_hz, name="monitor"):
            cart, angle, _, _ = self._joint_states()
            self.max_angle = max(self.max_angle, abs(angle))
            self.max_cart_offset = max(self.max_cart_offset, abs(cart))

    async def _mission(self, clock: ClockLike) -> None:
        """Apply the LQR force every tick until the hold time is up or the pole falls."""
        start = clock.now().nanoseconds
        hold = round(self.hold_time * 1e9)
        async for tick in clock.rate(self.balance_hz, name="balance"):
            state = np.array(self._joint_states())
            self.balanced_for = (tick.actual.nanoseconds - start) / 1e9
            if abs(state[1]) >= self.fail_angle or tick.actual.nanoseconds - start >= hold:
                self._apply_force(0.0)
                return
            force = float(np.clip(-(self.gain @ state)[0], -self.max_force, self.max_force))
            self._apply_force(force)

    def _apply_force(self, force: float) -> None:
        """Push the cart with ``force`` newtons until the next command.

        ``TORQUE_CONTROL`` would only act during the next ``stepSimulation`` (PyBullet clears it
        after every step), but this loop runs once per ~4.8 steps.  A velocity motor aimed at an
        unreachable velocity with force limit ``|force|`` applies exactly that force on every
        step until replaced: a zero-order hold.
        """
        self.pb.setJointMotorControl2(
            self.robot,
            SLIDER,
            p.VELOCITY_CONTROL,
            targetVelocity=math.copysign(SATURATED_VELOCITY, force),
            force=abs(force),
            physicsClientId=self.client,
        )

    def success(self) -> bool:
        """The pole stayed within :attr:`fail_angle` for :attr:`hold_time` seconds."""
        return self.balanced_for >= self.hold_time and self.max_angle < self.fail_angle

    def _metrics(self) -> dict[str, Metric]:
        return {
            "initial_tilt_rad": self.initial_tilt,
            "max_angle_rad": self.max_angle,
            "max_cart_offset_m": self.max_cart_offset,
            "balanced_for_s": self.balanced_for,
        }
