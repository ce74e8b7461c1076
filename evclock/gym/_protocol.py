"""The agent protocol: what a scenario implements so that an agent can replace a controller.

A scenario that hosts a learning agent (``evclock_sims.CartPole``, ``evclock_sims.KukaReach``)
names the background controller the agent replaces (``agent_controller``, a label of its
``_services``), that controller's rate (``agent_hz``), and six methods: the spaces, what the
agent observes, how its action is applied, the reward and whether the state is terminal.

A scenario whose agent may replace one of several controllers lists them in
``agent_controllers`` (``agent_controller`` is the default); an environment or a policy that
replaces another one sets the scenario's ``agent_controller`` (an instance attribute) to it
before anything else, and the rate, spaces, ``observe`` and ``act`` are then that controller's.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from evclock._errors import ActionError, AgentProtocolError
from evclock._extras import import_extra

Box = import_extra("gymnasium.spaces", "gym", needed_by="evclock.gym").Box

PROTOCOL_METHODS = ("observation_space", "action_space", "observe", "act", "reward", "terminated")
"""The methods of the agent protocol, in the order :class:`AgentScenario` lists them."""


@runtime_checkable
class AgentScenario(Protocol):
    """A scenario that hosts a learning agent in place of one of its controllers.

    ``observe()`` and ``act()`` run inside the replaced controller's rate loop, at each of its
    ticks, on the scenario's clock: ``act`` writes commands (motor targets, forces) that the
    physics reads at its next step, as the replaced controller did. ``reward()`` and
    ``terminated()`` read the state after a period has run.
    """

    agent_controller: ClassVar[str | None]
    """The label of the background controller (of ``_services``) the agent replaces by
    default (set on an instance: the one it replaces there, one of ``agent_controllers``)."""

    agent_controllers: ClassVar[tuple[str, ...]]
    """Optional: every controller an agent may replace (default: ``agent_controller`` only)."""

    @property
    def agent_hz(self) -> float:
        """The rate of that controller, in hertz: one environment step per period."""
        ...

    def observation_space(self) -> Any:
        """The ``gymnasium.spaces.Space`` of :meth:`observe`'s values."""
        ...

    def action_space(self) -> Any:
        """The ``gymnasium.spaces.Space`` of the actions :meth:`act` takes."""
        ...

    def observe(self) -> Any:
        """What the agent observes now (an element of :meth:`observation_space`)."""
        ...

    def act(self, action: Any) -> None:
        """Apply ``action`` (an element of :meth:`action_space`) as the replaced controller
        would."""
        ...

    def reward(self) -> float:
        """The reward of the period that just ran."""
        ...

    def terminated(self) -> bool:
        """Whether the state is terminal (the pole fell, every target was reached)."""
        ...

    def replace_controller(self, label: str, controller: Any) -> None:
        """Run ``controller(clock)`` instead of background controller ``label``."""
        ...


def agent_controllers(scenario: Any) -> tuple[str, ...]:
    """The controllers an agent may replace in ``scenario`` (a class or an instance): its
    ``agent_controllers``, else its ``agent_controller`` alone (empty when it names none)."""
    choices = getattr(scenario, "agent_controllers", None)
    if choices is None:
        label = getattr(scenario, "agent_controller", None)
        return (label,) if isinstance(label, str) else ()
    return tuple(choices)


def check_protocol(scenario: Any, controller: str | None = None) -> str:
    """Check that ``scenario`` (a scenario class or instance) implements the agent protocol
    and that ``controller`` is one its agent may replace.

    :param scenario: a scenario class or instance.
    :param controller: the controller the caller wants to replace (None: the scenario's
        ``agent_controller``).
    :returns: the label of the replaced controller.
    :raises AgentProtocolError: a method or attribute of the protocol is missing, or
        ``controller`` is not one the scenario lets an agent replace (the message names
        those).
    """
    cls = scenario if isinstance(scenario, type) else type(scenario)
    name = getattr(cls, "name", cls.__name__)
    missing = [m for m in PROTOCOL_METHODS if not callable(getattr(cls, m, None))]
    for attribute in ("agent_controller", "agent_hz", "replace_controller"):
        if not hasattr(cls, attribute):
            missing.append(attribute)
    if missing:
        raise AgentProtocolError(
            f"scenario {name!r} does not implement the agent protocol of evclock.gym: it "
            f"lacks {', '.join(missing)}; implement them (see the guide 'Reinforcement "
            "learning', 'The agent protocol')"
        )
    label = getattr(scenario, "agent_controller", None)
    if not isinstance(label, str):
        raise AgentProtocolError(
            f"scenario {name!r} names no controller an agent can replace: set its class "
            "attribute agent_controller to the label of one of its background controllers"
        )
    if controller is None:
        return label
    choices = agent_controllers(scenario)
    if controller not in choices:
        raise AgentProtocolError(
            f"scenario {name!r} has no controller {controller!r} an agent can replace; "
            f"choose one of: {', '.join(map(repr, choices))}"
        )
    return controller


def check_rate(scenario: Any) -> float:
    """The scenario's ``agent_hz``: a finite positive number, else AgentProtocolError."""
    hz = scenario.agent_hz
    if (
        isinstance(hz, bool)
        or not isinstance(hz, int | float)
        or not (math.isfinite(hz) and hz > 0)
    ):
        raise AgentProtocolError(
            f"scenario {scenario.name!r}'s agent_hz must be a positive number of hertz, got {hz!r}"
        )
    return float(hz)


def check_action(space: Any, action: Any, *, who: str) -> Any:
    """``action`` checked against ``space`` and converted to its dtype, never clipped.

    A ``Box`` action must be real numbers of exactly the box's shape (no broadcasting), none
    NaN, each within the box's bounds; any other
    space's action must be one its ``contains`` accepts.

    :param space: the action space.
    :param action: the action.
    :param who: how the message names where the action came from (``"step()"``).
    :returns: the action, a new array of the box's dtype for a ``Box``.
    :raises ActionError: the action is not in the space; the message says why.
    """
    if not isinstance(space, Box):
        if not space.contains(action):
            raise ActionError(f"{who}: action {action!r} is not in the action space {space}")
        return action
    try:
        array = np.asarray(action)
    except (TypeError, ValueError) as exc:
        raise ActionError(f"{who}: the action is not an array of numbers ({exc})") from None
    if array.dtype.kind not in "iuf":
        raise ActionError(
            f"{who}: the action must be real numbers, got dtype {array.dtype} ({action!r})"
        )
    if array.shape != space.shape:
        raise ActionError(
            f"{who}: the action has shape {array.shape}, the action space {space} has shape "
            f"{space.shape}"
        )
    values = array.astype(space.dtype)
    inside = (values >= space.low) & (values <= space.high)  # False for NaN too
    if inside.all():
        return values
    if np.isnan(values).any():
        raise ActionError(f"{who}: the action holds NaN: {array.tolist()!r}")
    outside = np.flatnonzero(~inside)
    i = int(outside[0])
    value, low, high = float(values.flat[i]), float(space.low.flat[i]), float(space.high.flat[i])
    raise ActionError(
        f"{who}: action[{i}] = {value!r} is outside the action space's bounds "
        f"[{low!r}, {high!r}] ({outside.size} value(s) outside; actions are never "
        "clipped: clip them in the policy, or wrap the environment in "
        "gymnasium.wrappers.ClipAction)"
    )
