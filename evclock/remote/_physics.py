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

Every request is checked in the simulation process before it reaches the engine (PyBullet's
C code trusts its caller: an out-of-range link index can crash it): only the parameters
listed in :data:`SIGNATURES`, body ids of existing bodies, joint and link indices within
that body, finite numbers, vectors of the right length, lists of bounded size, known
control modes and frames. A request that fails is answered with an error to the participant
that sent it (:class:`~evclock.RemoteCallError` for a read, an ERROR frame for a command);
the simulation goes on.
"""

from __future__ import annotations

import functools
import json
from typing import Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, ProtocolError
from evclock.remote._checks import (
    all_finite_numbers,
    decode_request,
    is_finite_number,
    is_int,
    shown,
    shown_name,
)

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


#: The longest list a request may carry (joint lists, rays, IK limits).
MAX_LIST: Final = 16384

#: Each served function's parameters, in PyBullet's positional order, as ``name:kind``
#: (``@other``: a link/joint index of the body named by parameter ``other``).
SIGNATURES: Final[dict[str, tuple[str, ...]]] = {
    "calculateInverseDynamics": (
        "bodyUniqueId:body",
        "objPositions:dofs",
        "objVelocities:dofs",
        "objAccelerations:dofs",
        "flags:int",
    ),
    "calculateInverseKinematics": (
        "bodyUniqueId:body",
        "endEffectorLinkIndex:link0",
        "targetPosition:vec3",
        "targetOrientation:quat",
        "lowerLimits:floats",
        "upperLimits:floats",
        "jointRanges:floats",
        "restPoses:floats",
        "jointDamping:floats",
        "solver:int",
        "currentPositions:floats",
        "maxNumIterations:int",
        "residualThreshold:float",
    ),
    "calculateJacobian": (
        "bodyUniqueId:body",
        "linkIndex:link0",
        "localPosition:vec3",
        "objPositions:dofs",
        "objVelocities:dofs",
        "objAccelerations:dofs",
    ),
    "calculateMassMatrix": ("bodyUniqueId:body", "objPositions:dofs", "flags:int"),
    "getAABB": ("bodyUniqueId:body", "linkIndex:link"),
    "getBasePositionAndOrientation": ("bodyUniqueId:body",),
    "getBaseVelocity": ("bodyUniqueId:body",),
    "getClosestPoints": (
        "bodyA:body",
        "bodyB:body",
        "distance:float",
        "linkIndexA:link@bodyA",
        "linkIndexB:link@bodyB",
    ),
    "getContactPoints": (
        "bodyA:body",
        "bodyB:body",
        "linkIndexA:link@bodyA",
        "linkIndexB:link@bodyB",
    ),
    "getEulerFromQuaternion": ("quaternion:quat",),
    "getJointInfo": ("bodyUniqueId:body", "jointIndex:joint"),
    "getJointState": ("bodyUniqueId:body", "jointIndex:joint"),
    "getJointStates": ("bodyUniqueId:body", "jointIndices:joints"),
    "getLinkState": (
        "bodyUniqueId:body",
        "linkIndex:link0",
        "computeLinkVelocity:flag",
        "computeForwardKinematics:flag",
    ),
    "getLinkStates": (
        "bodyUniqueId:body",
        "linkIndices:links0",
        "computeLinkVelocity:flag",
        "computeForwardKinematics:flag",
    ),
    "getNumBodies": (),
    "getNumJoints": ("bodyUniqueId:body",),
    "getQuaternionFromEuler": ("eulerAngles:vec3",),
    "rayTest": ("rayFromPosition:vec3", "rayToPosition:vec3"),
    "rayTestBatch": (
        "rayFromPositions:vec3s",
        "rayToPositions:vec3s",
        "parentObjectUniqueId:body",
        "parentLinkIndex:link@parentObjectUniqueId",
        "numThreads:int",
        "reportHitNumber:int",
        "collisionFilterMask:int",
        "fractionEpsilon:float",
    ),
    "applyExternalForce": (
        "objectUniqueId:body",
        "linkIndex:link",
        "forceObj:vec3",
        "posObj:vec3",
        "flags:frame",
    ),
    "applyExternalTorque": (
        "objectUniqueId:body",
        "linkIndex:link",
        "torqueObj:vec3",
        "flags:frame",
    ),
    "setJointMotorControl2": (
        "bodyUniqueId:body",
        "jointIndex:joint",
        "controlMode:mode",
        "targetPosition:float",
        "targetVelocity:float",
        "force:float",
        "positionGain:float",
        "velocityGain:float",
        "maxVelocity:float",
    ),
    "setJointMotorControlArray": (
        "bodyUniqueId:body",
        "jointIndices:joints",
        "controlMode:mode",
        "targetPositions:perjoint",
        "targetVelocities:perjoint",
        "forces:perjoint",
        "positionGains:perjoint",
        "velocityGains:perjoint",
    ),
    "setJointMotorControlMultiDof": (
        "bodyUniqueId:body",
        "jointIndex:joint",
        "controlMode:mode",
        "targetPosition:floats",
        "targetVelocity:floats",
        "force:floats",
        "positionGain:float",
        "velocityGain:float",
        "maxVelocity:float",
    ),
    "setJointMotorControlMultiDofArray": (
        "bodyUniqueId:body",
        "jointIndices:joints",
        "controlMode:mode",
        "targetPositions:floatss",
        "targetVelocities:floatss",
        "forces:floatss",
        "positionGains:perjoint",
        "velocityGains:perjoint",
        "maxVelocities:perjoint",
    ),
}
#: Other names PyBullet accepts for a parameter.
_ALIASES: Final = {"bodyIndex": "bodyUniqueId"}


def _bad(name: str, param: str, reason: str) -> InvalidArgumentError:
    return InvalidArgumentError(f"pybullet.{name}: {param} {reason}")


class _Checker:
    """Checks one request's arguments against the engine's current bodies."""

    def __init__(self, p: Any, client: int, name: str) -> None:
        self._p = p
        self._client = client
        self._name = name

    def _joints(self, body: int) -> int:
        count: int = self._p.getNumJoints(body, physicsClientId=self._client)
        return count

    def _dofs(self, body: int) -> int:
        p, cid = self._p, self._client
        return sum(
            1
            for j in range(self._joints(body))
            if p.getJointInfo(body, j, physicsClientId=cid)[2] != p.JOINT_FIXED
        )

    def _list(self, param: str, value: object, size: int | None = None) -> list[Any]:
        if not isinstance(value, list):
            raise _bad(self._name, param, f"must be a list, got {type(value).__name__}")
        if len(value) > MAX_LIST:
            raise _bad(self._name, param, f"has {len(value)} items (at most {MAX_LIST})")
        if size is not None and len(value) != size:
            raise _bad(self._name, param, f"must have {size} items, got {len(value)}")
        return value

    def _floats(self, param: str, value: object, size: int | None = None) -> None:
        items = self._list(param, value, size)
        if all_finite_numbers(items):
            return
        for item in items:
            if not is_finite_number(item):
                raise _bad(self._name, param, f"must hold finite numbers, got {shown(item)}")

    def _index(self, param: str, value: object, low: int, count: int, what: str) -> None:
        if not is_int(value):
            raise _bad(self._name, param, f"must be an integer {what}, got {shown(value)}")
        assert isinstance(value, int)
        if not low <= value < count:
            raise _bad(
                self._name,
                param,
                f"{shown(value)} is not a {what} of that body (valid: {low} to {count - 1})",
            )

    def check(self, kinds: dict[str, str], values: dict[str, Any]) -> None:
        """Raise InvalidArgumentError for the first argument that is not acceptable."""
        p = self._p
        bodies = {
            p.getBodyUniqueId(i, physicsClientId=self._client)
            for i in range(p.getNumBodies(physicsClientId=self._client))
        }
        for param, value in values.items():
            if kinds[param] == "body" and (not is_int(value) or value not in bodies):
                raise _bad(self._name, param, f"{shown(value)} is not the id of a body")
        main = next((v for k, v in values.items() if kinds[k] == "body"), None)
        for param, value in values.items():
            kind, _, owner = kinds[param].partition("@")
            body = values.get(owner, main) if owner else main
            if kind in ("body",):
                continue
            if kind in ("joint", "joints", "link", "link0", "links0", "perjoint", "dofs"):
                if body is None:
                    raise _bad(self._name, param, "needs the body it belongs to")
                joints = self._joints(body)
            if kind == "joint":
                self._index(param, value, 0, joints, "joint index")
            elif kind == "joints":
                for item in self._list(param, value):
                    self._index(param, item, 0, joints, "joint index")
            elif kind == "link":
                self._index(param, value, -1, joints, "link index (-1: the base)")
            elif kind == "link0":
                self._index(param, value, 0, joints, "link index")
            elif kind == "links0":
                for item in self._list(param, value):
                    self._index(param, item, 0, joints, "link index")
            elif kind == "perjoint":
                selected = values.get("jointIndices")
                self._floats(param, value, len(selected) if isinstance(selected, list) else None)
            elif kind == "dofs":
                assert body is not None
                self._floats(param, value, self._dofs(body))
            elif kind == "floats":
                self._floats(param, value)
            elif kind == "floatss":
                for item in self._list(param, value):
                    self._floats(param, item)
            elif kind == "vec3":
                self._floats(param, value, 3)
            elif kind == "quat":
                self._floats(param, value, 4)
            elif kind == "vec3s":
                for item in self._list(param, value):
                    self._floats(param, item, 3)
            elif kind == "float":
                if not is_finite_number(value):
                    raise _bad(self._name, param, f"must be a finite number, got {shown(value)}")
            elif kind in ("int", "flag"):
                if not is_int(value) and not isinstance(value, bool):
                    raise _bad(self._name, param, f"must be an integer, got {shown(value)}")
                if not -(2**31) <= int(value) < 2**31:
                    raise _bad(self._name, param, f"{shown(value)} is out of range")
            elif kind == "mode":
                modes = (p.POSITION_CONTROL, p.VELOCITY_CONTROL, p.TORQUE_CONTROL, p.PD_CONTROL)
                if not is_int(value) or value not in modes:
                    raise _bad(self._name, param, f"{shown(value)} is not a control mode")
            elif kind == "frame" and (
                not is_int(value) or value not in (p.WORLD_FRAME, p.LINK_FRAME)
            ):
                raise _bad(self._name, param, f"{shown(value)} is not WORLD_FRAME or LINK_FRAME")


#: Per served function: its parameters' kinds by name, and their names in order.
_PARAMETERS: Final[dict[str, tuple[dict[str, str], list[str]]]] = {
    name: (
        dict(param.split(":", 1) for param in params),
        [param.split(":", 1)[0] for param in params],
    )
    for name, params in SIGNATURES.items()
}


def _bind(
    name: str, args: list[Any], kwargs: dict[str, Any]
) -> tuple[dict[str, str], dict[str, Any]]:
    """The request's arguments by parameter name; unknown or doubled ones are refused."""
    kinds, order = _PARAMETERS[name]
    if len(args) > len(order):
        raise InvalidArgumentError(
            f"pybullet.{name} takes at most {len(order)} arguments here, got {len(args)}"
        )
    values = dict(zip(order, args, strict=False))
    for key, value in kwargs.items():
        key = _ALIASES.get(key, key)
        if key not in kinds:
            raise InvalidArgumentError(
                f"pybullet.{name} has no parameter {shown(key)} served to remote controllers "
                f"(served: {', '.join(order) or 'none'})"
            )
        if key in values:
            raise InvalidArgumentError(f"pybullet.{name} got {key!r} twice")
        values[key] = value
    return kinds, values


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
    shape = "[name, args, kwargs] JSON"
    request = decode_request(data, "a pybullet request", shape)
    if not isinstance(request, list) or len(request) != 3:
        raise ProtocolError(f"a pybullet request is not {shape}")
    name, args, kwargs = request
    if not isinstance(name, str) or not isinstance(args, list) or not isinstance(kwargs, dict):
        raise ProtocolError(f"a pybullet request is not {shape}")
    if name not in allowed:
        kind = "command" if allowed is WRITES else "query"
        raise InvalidArgumentError(
            f"pybullet.{shown_name(name)} is not served to remote controllers as a {kind}"
        )
    return name, args, kwargs


class PhysicsService:
    """Serves a PyBullet client to remote controllers (install it on a ClockServer).

    Every request is validated before it reaches the engine (see the module docstring).
    """

    def __init__(self, client: int) -> None:
        import pybullet

        self._p = pybullet
        self._client = client

    def install(self, server: Any) -> None:
        """Answer reads and apply commands on ``server`` (a
        :class:`~evclock.remote.ClockServer`)."""
        server.provide(SERVICE, self.answer)
        server.subscribe(TOPIC, self.apply)

    def _checked(self, data: bytes, allowed: frozenset[str]) -> tuple[str, dict[str, Any]]:
        name, args, kwargs = _decode_call(data, allowed)
        if "physicsClientId" in kwargs:
            raise InvalidArgumentError(
                f"pybullet.{name}: physicsClientId is not served: the simulation calls its own "
                "client (a RemotePhysics leaves it out of its requests)"
            )
        kinds, values = _bind(name, args, kwargs)
        _Checker(self._p, self._client, name).check(kinds, values)
        return name, values

    def answer(self, data: bytes) -> bytes:
        """Answer a read request (validated first).

        :param data: the request, ``[name, args, kwargs]`` as JSON.
        :returns: the result as JSON.
        :raises InvalidArgumentError: the function is not served or an argument is invalid.
        :raises ProtocolError: the request is not such JSON.
        """
        name, values = self._checked(data, READS)
        result = getattr(self._p, name)(**values, physicsClientId=self._client)
        return json.dumps(result, allow_nan=True).encode()

    def apply(self, message: Any) -> None:
        """Apply a command (validated first; an invalid one raises and is not applied).

        :param message: the :class:`~evclock.remote.Message` carrying the command.
        :raises InvalidArgumentError: the function is not served or an argument is invalid.
        :raises ProtocolError: the request is not such JSON.
        """
        name, values = self._checked(message.data, WRITES)
        getattr(self._p, name)(**values, physicsClientId=self._client)


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
