"""A trained policy as the controller it replaces: :class:`PolicyController`, and the linear
policies of the example (:class:`LinearPolicy`, saved as ``.npz``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import numpy as np

from evclock._errors import InvalidArgumentError, InvalidTypeError, ScenarioError
from evclock.gym._protocol import check_action, check_protocol, check_rate

Policy = Callable[[Any], Any]
"""A policy: observation -> action."""


class LinearPolicy:
    """``action = clip(weights @ observation + bias, low, high)``: the policy of the
    reinforcement-learning example, saved to and loaded from ``.npz`` files.

    The clip is the policy's own output range (the action space's bounds, stored with it),
    not a correction of bad actions: the environment never clips.

    :param weights: an ``(actions, observations)`` matrix.
    :param bias: an ``(actions,)`` vector.
    :param low: the lowest action, per component.
    :param high: the highest action, per component.
    """

    def __init__(self, weights: Any, bias: Any, low: Any, high: Any) -> None:
        self.weights = np.array(weights, dtype=np.float64, ndmin=2)
        self.bias = np.array(bias, dtype=np.float64, ndmin=1)
        self.low = np.array(low, dtype=np.float64, ndmin=1)
        self.high = np.array(high, dtype=np.float64, ndmin=1)
        actions = self.weights.shape[0]
        for label, vector in (("bias", self.bias), ("low", self.low), ("high", self.high)):
            if vector.shape != (actions,):
                raise InvalidArgumentError(
                    f"LinearPolicy: {label} has shape {vector.shape}, the weights "
                    f"{self.weights.shape} ask for ({actions},)"
                )
        arrays = (self.weights, self.bias, self.low, self.high)
        if not all(np.isfinite(a).all() for a in arrays):
            raise InvalidArgumentError("LinearPolicy: weights, bias and bounds must be finite")

    def __call__(self, observation: Any) -> np.ndarray:
        """The action for ``observation``."""
        action = self.weights @ np.asarray(observation, dtype=np.float64) + self.bias
        clipped: np.ndarray = np.clip(action, self.low, self.high)
        return clipped

    def save(self, path: str | Path) -> None:
        """Write the policy to ``path`` (an ``.npz`` file)."""
        np.savez(path, weights=self.weights, bias=self.bias, low=self.low, high=self.high)

    @classmethod
    def load(cls, path: str | Path) -> LinearPolicy:
        """The policy saved at ``path`` by :meth:`save`.

        :raises InvalidArgumentError: the file does not exist or is not such a policy.
        """
        if not Path(path).is_file():
            raise InvalidArgumentError(f"no policy file {str(path)!r}")
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls(data["weights"], data["bias"], data["low"], data["high"])
        except (KeyError, ValueError, OSError) as exc:
            raise InvalidArgumentError(
                f"{str(path)!r} is not a LinearPolicy file (weights, bias, low, high): {exc}"
            ) from None


def load_policy(spec: str | Path) -> Policy:
    """The policy ``spec`` names: a ``.npz`` file of :class:`LinearPolicy`, or
    ``module:attribute`` naming a callable (a function, or an object with ``__call__``).

    :param spec: the reference.
    :returns: the policy, a callable observation -> action.
    :raises InvalidArgumentError: a missing or malformed file, or a malformed reference.
    :raises ScenarioError: the module cannot be imported or lacks the attribute.
    :raises InvalidTypeError: the attribute is not callable.
    """
    text = str(spec)
    if text.endswith(".npz"):
        return LinearPolicy.load(text)
    module_name, sep, attribute = text.partition(":")
    if not sep or not module_name or not attribute:
        raise InvalidArgumentError(
            f"a policy is a .npz file of evclock.gym.LinearPolicy or module:callable, got {text!r}"
        )
    try:
        obj: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ScenarioError(f"cannot import the policy's module {module_name!r}: {exc}") from exc
    for part in attribute.split("."):
        if not hasattr(obj, part):
            raise ScenarioError(f"the policy's module {module_name!r} has no {attribute!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise InvalidTypeError(
            f"policy {text!r} is a {type(obj).__name__}, not a callable observation -> action"
        )
    policy: Policy = obj
    return policy


class PolicyController:
    """A policy (any callable ``observation -> action``) as the controller it replaces: at
    each tick of that controller's rate, on the scenario's clock (sim or wall time), it
    observes, asks the policy and acts, through the scenario's agent protocol.

    Install it with ``scenario.replace_controller(scenario.agent_controller, controller)``
    before the scenario runs, or let the scenario do it: ``evclock run cartpole --param
    policy=policy.npz`` (any run of the scenario: sim or wall time, split across processes).

    The same policy gives the same trajectory here as in :class:`~evclock.gym.ScenarioEnv`
    stepped with its actions: both observe at the controller's tick and act before sim time
    moves on.

    :param policy: the policy, or a reference :func:`load_policy` loads.
    :param scenario: the scenario (implementing the agent protocol) it controls.
    :raises AgentProtocolError: the scenario lacks the protocol.
    :raises ActionError: (while running) the policy returned an action outside the space.
    """

    def __init__(self, policy: Policy | str | Path, scenario: Any) -> None:
        self.label = check_protocol(scenario)
        self.hz = check_rate(scenario)
        if isinstance(policy, str | Path):
            policy = load_policy(policy)
        if not callable(policy):
            raise InvalidTypeError(
                f"a policy is a callable observation -> action, got {type(policy).__name__}"
            )
        self.policy: Policy = policy
        self.scenario = scenario
        self.action_space = scenario.action_space()
        self.steps = 0
        """The actions applied so far."""

    def install(self) -> PolicyController:
        """Replace the scenario's agent controller with this one; returns ``self``."""
        self.scenario.replace_controller(self.label, self)
        return self

    def __call__(self, clock: Any) -> Coroutine[Any, Any, None]:
        """The controller's coroutine on ``clock`` (what ``replace_controller`` calls)."""
        return self.run(clock)

    async def run(self, clock: Any) -> None:
        """Observe, decide and act at every tick, until cancelled."""
        scenario, space, policy = self.scenario, self.action_space, self.policy
        who = f"the policy controlling {scenario.name}.{self.label}"
        async for _tick in clock.rate(self.hz, name=self.label):
            action = check_action(space, policy(scenario.observe()), who=who)
            scenario.act(action)
            self.steps += 1
