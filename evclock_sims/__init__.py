"""PyBullet scenarios whose controllers are asyncio coroutines driven by a simulation clock.

Usage::

    scenario = get_scenario("kuka")(client, seed=0)   # client: a connected PyBullet client id
    await scenario.run(clock)                         # clock: a ClockLike, e.g. evclock.clock()
    scenario.success(), scenario.summary(), scenario.state_vector()

The clock's owner steps the physics (one ``stepSimulation`` per 1/240 s); scenarios never do.
"""

from __future__ import annotations

from ._base import PHYSICS_HZ, ClockLike, Scenario, TickLike, TimeLike
from .cartpole import CartPole
from .fusion import LandmarkFusion
from .husky import HuskyPatrol
from .kuka import KukaReach

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls for cls in (KukaReach, HuskyPatrol, CartPole, LandmarkFusion)
}
"""Every scenario class by its ``name``."""


def get_scenario(name: str) -> type[Scenario]:
    """The scenario class registered as ``name``; ValueError listing the valid names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        valid = ", ".join(SCENARIOS)
        raise ValueError(f"unknown scenario {name!r}; valid names: {valid}") from None


__all__ = [
    "PHYSICS_HZ",
    "SCENARIOS",
    "CartPole",
    "ClockLike",
    "HuskyPatrol",
    "KukaReach",
    "LandmarkFusion",
    "Scenario",
    "TickLike",
    "TimeLike",
    "get_scenario",
]
