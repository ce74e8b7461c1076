"""A complete user scenario: a cart shuttled to a seeded target, held there, then judged.

Run it like a bundled one, record it, sweep it::

    evclock run examples/shuttle_scenario.py --seed 3
    evclock run examples/shuttle_scenario.py --param gain=4 --record shuttle.mcap
    evclock sweep examples/shuttle_scenario.py --seeds 0:20 --param gain=2,4 --workers 2

The world (``__init__``) and the controllers (``_services``/``_mission``) are separate: the
controllers only read state and write motor commands; whoever owns the clock steps physics.
"""

from __future__ import annotations

from collections.abc import Coroutine
from typing import Any

import pybullet as p

import evclock
from evclock_sims import ClockLike, Scenario

SLIDER = 0  # cartpole.urdf: the prismatic cart joint
POLE = 1


class Shuttle(Scenario):
    """Move the cart to a seeded target with a P controller on velocity; hold it there."""

    name = "shuttle"
    description = "Cart moved to a seeded target by a 20 Hz P controller, held for 0.5 s"
    default_until = 6.0

    # Tunable parameters (``--param name=value``): public scalar class attributes.
    control_hz = 20.0
    gain = 3.0
    """1/s: commanded velocity per metre of error."""
    max_speed = 1.5
    """m/s."""
    tolerance = 0.01
    """Metres from the target that count as arrived."""
    hold_time = 0.5
    """Seconds the cart must stay within tolerance."""

    def __init__(self, client: int, seed: int = 0) -> None:
        """World set-up: the cart-pole model, pole locked, a seeded target 0.3-1 m away."""
        super().__init__(client, seed)
        self.robot = self.load_urdf("cartpole.urdf", useFixedBase=True)
        p.setJointMotorControl2(
            self.robot,
            POLE,
            p.POSITION_CONTROL,
            targetPosition=0.0,
            force=100.0,
            physicsClientId=client,
        )
        self.target = float(self.rng.uniform(0.3, 1.0)) * float(self.rng.choice([-1, 1]))
        self.arrived_at: float | None = None
        self.error = abs(self.target)

    def _position(self) -> float:
        position: float = p.getJointState(self.robot, SLIDER, physicsClientId=self.client)[0]
        return position

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        """Background controllers: a 10 Hz logger writing a user channel of the recording."""
        return {"logger": self._log(clock)}

    async def _log(self, clock: ClockLike) -> None:
        async for _tick in clock.rate(10.0, name="logger"):
            evclock.tools.record("/shuttle/error", {"error_m": self.error, "target_m": self.target})

    async def _mission(self, clock: ClockLike) -> None:
        """Drive toward the target; done once within tolerance for ``hold_time`` seconds."""
        held_since: float | None = None
        async for tick in clock.rate(self.control_hz, name="control"):
            now = tick.actual.seconds
            self.error = self.target - self._position()
            speed = max(-self.max_speed, min(self.max_speed, self.gain * self.error))
            p.setJointMotorControl2(
                self.robot,
                SLIDER,
                p.VELOCITY_CONTROL,
                targetVelocity=speed,
                force=50.0,
                physicsClientId=self.client,
            )
            if abs(self.error) > self.tolerance:
                held_since = None
                continue
            if held_since is None:
                held_since = now
                self.arrived_at = self.arrived_at if self.arrived_at is not None else now
            if now - held_since >= self.hold_time:
                return

    def success(self) -> bool:
        """Arrived and held: the mission ended within tolerance."""
        return self.finished_at is not None and abs(self.error) <= self.tolerance

    def _metrics(self) -> dict[str, float | int | bool | str]:
        """Report fields (numbers get quantiles and histograms in a sweep)."""
        return {
            "target_m": self.target,
            "final_error_m": abs(self.error),
            "arrival_s": float("nan") if self.arrived_at is None else self.arrived_at,
        }


if __name__ == "__main__":
    # The same run as `evclock run examples/shuttle_scenario.py --seed 3`, from Python.
    report = evclock.tools.run_scenario(Shuttle, seed=3)
    print(f"{report.scenario} seed {report.seed}: {report.verdict}")
    print(
        f"target {report.summary['target_m']:.3f} m, error {report.summary['final_error_m']:.4f} m"
    )
