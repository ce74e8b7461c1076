"""The registered environments (``evclock/CartPole-v0``, ``evclock/KukaReach-v0``) and
:func:`register`, which makes any scenario an environment ``gymnasium.make`` builds."""

from __future__ import annotations

from typing import Any

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock._extras import import_extra

ENTRY_POINT = "evclock.gym._env:ScenarioEnv"

BUNDLED = {"evclock/CartPole-v0": "cartpole", "evclock/KukaReach-v0": "kuka"}
"""The environments ``import evclock.gym`` registers, and the scenario of each."""


def register(env_id: str, scenario: str | type[Any], **defaults: Any) -> None:
    """Register ``scenario`` as the Gymnasium environment ``env_id``: then
    ``gymnasium.make(env_id, engine=..., ...)`` builds a :class:`ScenarioEnv` of it.

    :param env_id: the environment's id (``"myproject/Reach-v0"``).
    :param scenario: a registered scenario name, ``module:Class``, a file, or a class.
    :param defaults: default keyword arguments of :class:`ScenarioEnv` (``engine``,
        ``params``, ``max_episode_seconds``...); ``make``'s own override them.
    :raises InvalidTypeError: ``env_id`` is not a string.
    :raises InvalidArgumentError: ``env_id`` is registered already.

    Example::

        evclock.gym.register("mine/Reach-v0", "mypkg.scenarios:Reach", engine="mujoco")
    """
    gymnasium = import_extra("gymnasium", "gym", needed_by="evclock.gym")
    if not isinstance(env_id, str):
        raise InvalidTypeError(f"an environment id is a string, got {type(env_id).__name__}")
    if env_id in gymnasium.registry:
        raise InvalidArgumentError(f"the environment {env_id!r} is registered already")
    # order_enforce=False: ScenarioEnv reports a step() before reset() itself, naming it.
    gymnasium.register(
        id=env_id,
        entry_point=ENTRY_POINT,
        kwargs={"scenario": scenario, **defaults},
        order_enforce=False,
    )


def register_bundled() -> None:
    """Register :data:`BUNDLED` (once per process)."""
    gymnasium = import_extra("gymnasium", "gym", needed_by="evclock.gym")
    for env_id, scenario in BUNDLED.items():
        if env_id not in gymnasium.registry:
            register(env_id, scenario)
