"""Scenarios as Gymnasium environments, and trained policies as the controllers they replace.

* :class:`ScenarioEnv`: a scenario as a ``gymnasium.Env``; the agent replaces one controller
  while the physics, the other controllers and the timers keep running on sim time;
* ``evclock/CartPole-v0`` and ``evclock/KukaReach-v0``, registered on import
  (``gymnasium.make("evclock/CartPole-v0", engine="mujoco")``), and :func:`register` for any
  scenario;
* :class:`PolicyController`: a policy (``observation -> action``) as that controller, in
  ``evclock run`` on sim or wall time, split across processes;
* :class:`AgentScenario`: the agent protocol a scenario implements; :class:`LinearPolicy`,
  :func:`load_policy`; the errors :class:`ActionError`, :class:`EnvStateError`,
  :class:`AgentProtocolError`.

Needs the ``gym`` extra (``pip install 'evclock[gym]'``); ``import evclock`` does not import
it. Layer: above ``evclock.tools``.
"""

from __future__ import annotations

from evclock._errors import ActionError, AgentProtocolError, EnvStateError
from evclock._extras import import_extra

import_extra("gymnasium", "gym", needed_by="evclock.gym")

from evclock.gym._env import ScenarioEnv  # noqa: E402  (after the extra's check)
from evclock.gym._policy import LinearPolicy, PolicyController, load_policy  # noqa: E402
from evclock.gym._protocol import AgentScenario, check_action  # noqa: E402
from evclock.gym._registry import BUNDLED, register, register_bundled  # noqa: E402

register_bundled()

__all__ = [
    "BUNDLED",
    "ActionError",
    "AgentProtocolError",
    "AgentScenario",
    "EnvStateError",
    "LinearPolicy",
    "PolicyController",
    "ScenarioEnv",
    "check_action",
    "load_policy",
    "register",
]

for _name in ("ActionError", "AgentProtocolError", "EnvStateError"):
    globals()[_name].__module__ = __name__
del _name
