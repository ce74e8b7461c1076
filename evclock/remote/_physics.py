"""PyBullet across processes: scenario controllers in one process, the physics in another.

A scenario's controllers call PyBullet through ``scenario.pb``. In the controller process
that is a :class:`RemotePhysics`: reads (``getJointStates``, ``calculateInverseKinematics``
...) are calls answered by the simulation at once, at the current sim time; commands
(``setJointMotorControl*``, ``applyExternalForce`` ...) are published on the ordered data
channel and applied when the lockstep round closes, before physics advances - exactly
where an in-process controller's command lands. Arguments and results travel as JSON,
whose floats round-trip exactly, so a split run computes bit for bit what an in-process
run computes. Only the functions listed here are served: a participant cannot load files,
step, reset or disconnect the simulation.
"""

from __future__ import annotations

import functools
import json
from typing import Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, ProtocolError

SERVICE: Final = "pybullet"  # reads: request/reply
TOPIC: Final = "pybullet"  # commands: ordered, applied at the end of the round

READS: Final = frozenset(
    {
        "calculateInverseDynamics",
        "calculateInverseKinematics",
        "calculateJacobian",
        "calculateMassMatrix",
        "getAABB",
        "getBasePositionAndOrientation",
        "getBaseVelocity",
        "getClosestPoints",
        "getContactPoints",
        "getEulerFromQuaternion",
        "getJointInfo",
        "getJointState",
        "getJointStates",
        "getLinkState",
        "getLinkStates",
        "getNumBodies",
        "getNumJoints",
        "getQuaternionFromEuler",
        "rayTest",
        "rayTestBatch",
    }
)
WRITES: Final = frozenset(
    {
        "applyExternalForce",
        "applyExternalTorque",
        "setJointMotorControl2",
        "setJointMotorControlArray",
        "setJointMotorControlMultiDof",
        "setJointMotorControlMultiDofArray",
    }
)


def _plain(value: object) -> object:
    """numpy scalars and arrays as Python numbers and lists (exact)."""
    tolist = getattr(value, "tolist", None)
    if callable(tolist):
        return tolist()
    raise InvalidTypeError(
        f"{type(value).__name__} cannot be sent to the simulation: pass numbers, strings, "
        "lists, tuples, dicts or numpy arrays"
    )


def encode_call(name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> bytes:
    kwargs = {k: v for k, v in kwargs.items() if k != "physicsClientId"}
    return json.dumps([name, args, kwargs], default=_plain).encode()


def _decode_call(data: bytes, allowed: frozenset[str]) -> tuple[str, list[Any], dict[str, Any]]:
    try:
        name, args, kwargs = json.loads(data)
    except (ValueError, TypeError):
        raise ProtocolError("a pybullet request is not [name, args, kwargs] JSON") from None
    if not isinstance(name, str) or not isinstance(args, list) or not isinstance(kwargs, dict):
        raise ProtocolError("a pybullet request is not [name, args, kwargs] JSON")
    if name not in allowed:
        kind = "command" if allowed is WRITES else "query"
        raise InvalidArgumentError(
            f"pybullet.{name} is not served to remote controllers as a {kind}"
        )
    return name, args, kwargs


class PhysicsService:
    """Serves a PyBullet client to remote controllers (install it on a ClockServer)."""

    def __init__(self, client: int) -> None:
        import pybullet

        self._p = pybullet
        self._client = client

    def install(self, server: Any) -> None:
        """Answer reads and apply commands on ``server`` (a
        :class:`~evclock.remote.ClockServer`)."""
        server.provide(SERVICE, self.answer)
        server.subscribe(TOPIC, self.apply)

    def answer(self, data: bytes) -> bytes:
        name, args, kwargs = _decode_call(data, READS)
        result = getattr(self._p, name)(*args, **kwargs, physicsClientId=self._client)
        return json.dumps(result).encode()

    def apply(self, message: Any) -> None:
        name, args, kwargs = _decode_call(message.data, WRITES)
        getattr(self._p, name)(*args, **kwargs, physicsClientId=self._client)


class RemotePhysics:
    """Stands in for the ``pybullet`` module in a controller process (``scenario.pb``).

    ``participant`` is the process's :class:`~evclock.remote.RemoteClockSource` (see
    :func:`evclock.remote.participant`). Constants (``POSITION_CONTROL`` ...) are pybullet's own.
    """

    def __init__(self, participant: Any) -> None:
        import pybullet

        self._p = pybullet
        self._participant = participant

    def __getattr__(self, name: str) -> Any:
        if name in READS:
            return functools.partial(self._read, name)
        if name in WRITES:
            return functools.partial(self._write, name)
        if name.isupper():
            return getattr(self._p, name)
        raise AttributeError(
            f"pybullet.{name} is not available to controllers in another process; they may "
            f"query {', '.join(sorted(READS))} and command {', '.join(sorted(WRITES))}"
        )

    def _read(self, name: str, *args: Any, **kwargs: Any) -> Any:
        return json.loads(self._participant.call(SERVICE, encode_call(name, args, kwargs)))

    def _write(self, name: str, *args: Any, **kwargs: Any) -> None:
        self._participant.publish(TOPIC, encode_call(name, args, kwargs))
