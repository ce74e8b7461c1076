"""Scenarios whose controllers are asyncio coroutines driven by a simulation clock.

Usage::

    scenario = get_scenario("kuka")(client, seed=0)   # client: a connected PyBullet client id
    await scenario.run(clock)                         # clock: a ClockLike, e.g. evclock.clock()
    scenario.success(), scenario.summary(), scenario.state_vector()

The clock's owner steps the physics (one step per 1/240 s); scenarios never do. ``kuka`` and
``cartpole`` also run on MuJoCo: build them in a :class:`MuJoCoWorld` instead of a PyBullet
client, and step ``world.time_source()``. Importing this package needs neither engine; the
PyBullet-only scenarios (``husky``, ``fusion``) are imported on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

from ._base import ENGINES, PHYSICS_HZ, ClockLike, Scenario, TickLike, TimeLike
from ._mujoco import MuJoCoWorld, model_path, urdf_to_mujoco
from .cartpole import CartPole
from .kuka import KukaReach

_WHERE = {
    "kuka": ("kuka", "KukaReach"),
    "husky": ("husky", "HuskyPatrol"),
    "cartpole": ("cartpole", "CartPole"),
    "fusion": ("fusion", "LandmarkFusion"),
}
_LAZY = {cls_name: module for module, cls_name in _WHERE.values()}


def __getattr__(name: str) -> Any:
    # The PyBullet-only scenarios import PyBullet: load them on first use only.
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    if name == "SCENARIOS":
        return {key: get_scenario(key) for key in _WHERE}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def get_scenario(name: str) -> type[Scenario]:
    """The scenario class registered as ``name``; ValueError listing the valid names otherwise.

    ``SCENARIOS`` (every scenario class by its ``name``) imports them all, PyBullet included.
    """
    try:
        module, cls_name = _WHERE[name]
    except KeyError:
        valid = ", ".join(_WHERE)
        raise ValueError(f"unknown scenario {name!r}; valid names: {valid}") from None
    cls: type[Scenario] = getattr(importlib.import_module(f".{module}", __name__), cls_name)
    return cls


__all__ = [
    "ENGINES",
    "PHYSICS_HZ",
    "SCENARIOS",
    "CartPole",
    "ClockLike",
    "HuskyPatrol",
    "KukaReach",
    "LandmarkFusion",
    "MuJoCoWorld",
    "Scenario",
    "TickLike",
    "TimeLike",
    "get_scenario",
    "model_path",
    "urdf_to_mujoco",
]
