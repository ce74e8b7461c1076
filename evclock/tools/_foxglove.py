"""What Foxglove shows of a run: the world's named state, Foxglove's well-known schemas, and
the live view (``evclock run kuka --foxglove``).

Foxglove recognises its well-known schemas by name in any encoding; evclock writes them as
JSON (schema encoding ``jsonschema``, message encoding ``json``), so the same bytes go to the
MCAP file, to the live WebSocket and back through ``evclock trace``:

- ``foxglove.FrameTransforms``: every link's pose in the ``world`` frame (frame
  ``<body>/<link>``);
- ``foxglove.JointStates``: every moving joint's position, velocity and effort, by name;
- ``foxglove.SceneUpdate``: the robot's visual shapes (boxes, spheres, cylinders and the URDF's
  meshes, embedded) attached to the link frames, so the 3D panel draws the robot;
- ``foxglove.Log``: the controllers' :mod:`logging` records.

:class:`World` reads all of this from a PyBullet client by name (bodies, links and joints as
the URDF names them; :class:`~evclock.tools._world_mujoco.MuJoCoWorldReader` from a MuJoCo
model, in the same messages); :class:`LiveView` serves the channels with the ``foxglove-sdk``
WebSocket server, broadcasting sim time so Foxglove's timeline follows the simulation.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import json
import logging
import socket
import threading
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from evclock._errors import InvalidArgumentError, InvalidTypeError, NotRunningError

DEFAULT_ADDRESS = "127.0.0.1:8765"
"""Where ``--foxglove`` serves when given no address: loopback, Foxglove's default port."""
WORLD_FRAME = "world"
"""The fixed frame every link pose is given in."""
LAYOUT_FILE = Path(__file__).with_name("foxglove_layout.json")
"""The saved Foxglove layout shipped with evclock (3D panel, joint plots, log, timing)."""
SCENE_TOPIC = "/evclock/scene"
"""The robot's shapes, written once: the live view sends them again to each subscriber."""


# ---------------------------------------------------------------------------------------------
# JSON schemas: Foxglove's well-known ones (by name), and those derived from user types


def object_schema(title: str | None, properties: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON schema of an object with these ``properties`` (titled unless None)."""
    schema: dict[str, Any] = {"type": "object", "properties": dict(properties)}
    if title is not None:
        schema = {"title": title, **schema}
    return schema


_NUMBER = {"type": "number"}
_STRING = {"type": "string"}
_TIME = object_schema("time", {"sec": {"type": "integer"}, "nsec": {"type": "integer"}})
_DURATION = object_schema("duration", {"sec": {"type": "integer"}, "nsec": {"type": "integer"}})
_VECTOR3 = object_schema("foxglove.Vector3", {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER})
_QUATERNION = object_schema(
    "foxglove.Quaternion", {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER}
)
_POSE = object_schema("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION})
_COLOR = object_schema("foxglove.Color", {"r": _NUMBER, "g": _NUMBER, "b": _NUMBER, "a": _NUMBER})


def _array(items: Mapping[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": dict(items)}


FRAME_TRANSFORMS_SCHEMA = object_schema(
    "foxglove.FrameTransforms",
    {
        "transforms": _array(
            object_schema(
                "foxglove.FrameTransform",
                {
                    "timestamp": _TIME,
                    "parent_frame_id": _STRING,
                    "child_frame_id": _STRING,
                    "translation": _VECTOR3,
                    "rotation": _QUATERNION,
                },
            )
        )
    },
)
"""``foxglove.FrameTransforms`` as JSON Schema."""
JOINT_STATES_SCHEMA = object_schema(
    "foxglove.JointStates",
    {
        "timestamp": _TIME,
        "joints": _array(
            object_schema(
                "foxglove.JointState",
                {"name": _STRING, "position": _NUMBER, "velocity": _NUMBER, "effort": _NUMBER},
            )
        ),
    },
)
"""``foxglove.JointStates`` as JSON Schema."""
LOG_SCHEMA = object_schema(
    "foxglove.Log",
    {
        "timestamp": _TIME,
        "level": {
            "type": "integer",
            "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal",
        },
        "message": _STRING,
        "name": _STRING,
        "file": _STRING,
        "line": {"type": "integer"},
    },
)
"""``foxglove.Log`` as JSON Schema."""
_SIZED = {"pose": _POSE, "size": _VECTOR3, "color": _COLOR}
SCENE_UPDATE_SCHEMA = object_schema(
    "foxglove.SceneUpdate",
    {
        "deletions": _array(object_schema("foxglove.SceneEntityDeletion", {"id": _STRING})),
        "entities": _array(
            object_schema(
                "foxglove.SceneEntity",
                {
                    "timestamp": _TIME,
                    "frame_id": _STRING,
                    "id": _STRING,
                    "lifetime": _DURATION,
                    "frame_locked": {"type": "boolean"},
                    "cubes": _array(object_schema("foxglove.CubePrimitive", _SIZED)),
                    "spheres": _array(object_schema("foxglove.SpherePrimitive", _SIZED)),
                    "cylinders": _array(
                        object_schema(
                            "foxglove.CylinderPrimitive",
                            {**_SIZED, "bottom_scale": _NUMBER, "top_scale": _NUMBER},
                        )
                    ),
                    "models": _array(
                        object_schema(
                            "foxglove.ModelPrimitive",
                            {
                                "pose": _POSE,
                                "scale": _VECTOR3,
                                "color": _COLOR,
                                "override_color": {"type": "boolean"},
                                "url": _STRING,
                                "media_type": _STRING,
                                "data": {"type": "string", "contentEncoding": "base64"},
                            },
                        )
                    ),
                },
            )
        ),
    },
)
"""``foxglove.SceneUpdate`` as JSON Schema (the primitives evclock draws with)."""

LOG_LEVELS = ((logging.CRITICAL, 5), (logging.ERROR, 4), (logging.WARNING, 3), (logging.INFO, 2))
"""Python logging level -> ``foxglove.LogLevel`` (at or above the level; DEBUG otherwise)."""


def scene_entity(frame: str, time_ns: int) -> dict[str, Any]:
    """An empty ``foxglove.SceneEntity`` locked to ``frame`` (its shapes are added after),
    stamped ``time_ns``, shown until replaced."""
    return {
        "timestamp": stamp(time_ns),
        "frame_id": frame,
        "id": frame,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": True,
        "cubes": [],
        "spheres": [],
        "cylinders": [],
        "models": [],
    }


def stamp(time_ns: int) -> dict[str, int]:
    """A time in integer nanoseconds as Foxglove's ``{sec, nsec}``."""
    sec, nsec = divmod(time_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _type_schema(annotation: Any, seen: tuple[Any, ...]) -> dict[str, Any]:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is Any or annotation is object:
        return {}
    if annotation is type(None):
        return {"type": "null"}
    if origin in (typing.Union, types.UnionType):
        options = [_type_schema(a, seen) for a in args]
        kinds = [o.get("type") for o in options]
        if all(isinstance(k, str) for k in kinds) and all(len(o) == 1 for o in options):
            return {"type": kinds}
        return {"anyOf": options}
    if origin is typing.Literal:
        return {"enum": list(args)}
    if annotation is bool:
        return {"type": "boolean"}
    if annotation is int:
        return {"type": "integer"}
    if annotation is float:
        return {"type": "number"}
    if annotation is str:
        return {"type": "string"}
    if origin in (list, tuple, set, frozenset) or annotation in (list, tuple):
        item: Any = args[0] if args else Any
        if origin is tuple and args and args[-1] is not Ellipsis and len(set(args)) != 1:
            item = Any  # a mixed tuple: items of any type
        return {"type": "array", "items": _type_schema(item, seen)}
    if origin is dict or annotation is dict or origin is Mapping:
        value = args[1] if len(args) == 2 else Any
        return {"type": "object", "additionalProperties": _type_schema(value, seen)}
    if isinstance(annotation, type) and (
        dataclasses.is_dataclass(annotation) or typing.is_typeddict(annotation)
    ):
        if annotation in seen:
            raise InvalidTypeError(
                f"record(): {annotation.__qualname__} refers to itself; a recorded message "
                "type must be a tree of fields"
            )
        hints = typing.get_type_hints(annotation)
        names = (
            [f.name for f in dataclasses.fields(annotation)]
            if dataclasses.is_dataclass(annotation)
            else list(hints)
        )
        return object_schema(
            None, {name: _type_schema(hints[name], (*seen, annotation)) for name in names}
        )
    raise InvalidTypeError(
        f"record(): cannot describe the field type {annotation!r} as JSON; use bool, int, "
        "float, str, lists, dicts, dataclasses or TypedDicts"
    )


def schema_of_type(message_type: type[Any], title: str) -> dict[str, Any]:
    """The JSON Schema of a dataclass or TypedDict: its fields and their types.

    :param message_type: a dataclass or a TypedDict class.
    :param title: the schema's name.
    :returns: a JSON Schema object with one property per field.
    :raises InvalidTypeError: ``message_type`` is neither, or has a field of a type JSON
        cannot describe.
    """
    if not (
        isinstance(message_type, type)
        and (dataclasses.is_dataclass(message_type) or typing.is_typeddict(message_type))
    ):
        raise InvalidTypeError(
            f"record() message types are dataclasses or TypedDicts, got {message_type!r}"
        )
    schema = _type_schema(message_type, ())
    return {"title": title, **schema}


def _value_schema(value: Any) -> dict[str, Any]:
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    if value is None:
        return {}
    if isinstance(value, Mapping):
        return object_schema(None, {str(k): _value_schema(v) for k, v in value.items()})
    if isinstance(value, list | tuple):
        return {"type": "array", "items": _value_schema(value[0]) if value else {}}
    return {}


def schema_of_message(message: Mapping[str, Any], title: str) -> dict[str, Any]:
    """The JSON Schema of a plain JSON object, inferred from its values (the first message
    written on a channel describes the channel).

    :param message: a JSON-serialisable mapping.
    :param title: the schema's name.
    :returns: a JSON Schema object with one property per key.
    """
    return {"title": title, **_value_schema(message)}


# ---------------------------------------------------------------------------------------------
# The world, by name


@dataclasses.dataclass(frozen=True)
class _Link:
    body: int
    index: int  # -1: the base
    frame: str
    name: str  # the URDF's link name


@dataclasses.dataclass(frozen=True)
class _Joint:
    body: int
    index: int
    name: str


def _text(raw: bytes | str) -> str:
    return raw.decode(errors="replace") if isinstance(raw, bytes) else str(raw)


def unique_name(name: str, taken: dict[str, int]) -> str:
    """``name``, or ``name_2``, ``name_3``... when it was taken before (``taken`` counts)."""
    count = taken.get(name, 0)
    taken[name] = count + 1
    return name if count == 0 else f"{name}_{count + 1}"


def vector3(values: typing.Sequence[float]) -> dict[str, float]:
    """A ``foxglove.Vector3`` of the first three values."""
    return {"x": float(values[0]), "y": float(values[1]), "z": float(values[2])}


def quaternion_xyzw(values: typing.Sequence[float]) -> dict[str, float]:
    """A ``foxglove.Quaternion`` of ``(x, y, z, w)`` values (PyBullet's order)."""
    return {
        "x": float(values[0]),
        "y": float(values[1]),
        "z": float(values[2]),
        "w": float(values[3]),
    }


class World:
    """A PyBullet world read by name: bodies, links and joints as their URDF names them.

    :param client: the PyBullet physics client id.
    :param pybullet: the ``pybullet`` module (passed in: this module does not import it).
    """

    def __init__(self, client: int, pybullet: Any) -> None:
        self._p = pybullet
        self._client = client
        p, cid = pybullet, client
        bodies: dict[str, int] = {}
        taken: dict[str, int] = {}
        self.links: list[_Link] = []
        joints: list[_Joint] = []
        for i in range(p.getNumBodies(physicsClientId=cid)):
            body = p.getBodyUniqueId(i, physicsClientId=cid)
            base, robot = (_text(x) for x in p.getBodyInfo(body, physicsClientId=cid))
            name = unique_name(robot or base or f"body{body}", taken)
            bodies[name] = body
            self.links.append(_Link(body, -1, f"{name}/{base or 'base'}", base or "base"))
            for j in range(p.getNumJoints(body, physicsClientId=cid)):
                info = p.getJointInfo(body, j, physicsClientId=cid)
                link = _text(info[12])
                self.links.append(_Link(body, j, f"{name}/{link}", link))
                if info[2] != p.JOINT_FIXED:
                    joints.append(_Joint(body, j, _text(info[1])))
        self.bodies = bodies
        """Body name -> PyBullet body id, in body-id order (names made unique)."""
        counts: dict[str, int] = {}
        for joint in joints:
            counts[joint.name] = counts.get(joint.name, 0) + 1
        names = {b: n for n, b in bodies.items()}
        self.joints = [
            joint
            if counts[joint.name] == 1
            else _Joint(joint.body, joint.index, f"{names[joint.body]}/{joint.name}")
            for joint in joints
        ]
        self._all_joints = {
            body: [
                _text(p.getJointInfo(body, j, physicsClientId=cid)[1])
                for j in range(p.getNumJoints(body, physicsClientId=cid))
            ]
            for body in bodies.values()
        }

    @property
    def joint_names(self) -> list[str]:
        """Every moving (non-fixed) joint's name, in body then joint order."""
        return [joint.name for joint in self.joints]

    @property
    def link_names(self) -> dict[str, str]:
        """Each link frame (``<body>/<link>``) -> the link's name in its URDF."""
        return {link.frame: link.name for link in self.links}

    def state(self) -> dict[str, Any]:
        """The full physical state by name: per body its base pose and velocities and each
        joint's position and velocity (the same numbers as ``Scenario.state_vector``)."""
        p, cid = self._p, self._client
        state: dict[str, Any] = {}
        for name, body in self.bodies.items():
            position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            linear, angular = p.getBaseVelocity(body, physicsClientId=cid)
            joints: dict[str, dict[str, float]] = {}
            for j, joint in enumerate(self._all_joints[body]):
                pos, vel = p.getJointState(body, j, physicsClientId=cid)[:2]
                joints[joint] = {"position": pos, "velocity": vel}
            state[name] = {
                "position": vector3(position),
                "orientation": quaternion_xyzw(orientation),
                "linear_velocity": vector3(linear),
                "angular_velocity": vector3(angular),
                "joints": joints,
            }
        return state

    def joint_states(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.JointStates`` message: each moving joint's position, velocity and
        effort (the motor's applied torque or force)."""
        p, cid = self._p, self._client
        joints = []
        for joint in self.joints:
            position, velocity, _forces, effort = p.getJointState(
                joint.body, joint.index, physicsClientId=cid
            )
            joints.append(
                {"name": joint.name, "position": position, "velocity": velocity, "effort": effort}
            )
        return {"timestamp": stamp(time_ns), "joints": joints}

    def _link_pose(self, link: _Link) -> tuple[Any, Any]:
        p, cid = self._p, self._client
        if link.index >= 0:
            state = p.getLinkState(
                link.body, link.index, computeForwardKinematics=True, physicsClientId=cid
            )
            return state[4], state[5]
        position, orientation = p.getBasePositionAndOrientation(link.body, physicsClientId=cid)
        info = p.getDynamicsInfo(link.body, -1, physicsClientId=cid)
        inverse = p.invertTransform(info[3], info[4])
        pose: tuple[Any, Any] = p.multiplyTransforms(position, orientation, *inverse)
        return pose

    def transforms(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.FrameTransforms`` message: every link frame in the world frame."""
        stamped = stamp(time_ns)
        transforms = []
        for link in self.links:
            position, orientation = self._link_pose(link)
            transforms.append(
                {
                    "timestamp": stamped,
                    "parent_frame_id": WORLD_FRAME,
                    "child_frame_id": link.frame,
                    "translation": vector3(position),
                    "rotation": quaternion_xyzw(orientation),
                }
            )
        return {"transforms": transforms}

    def fixed_transforms(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.FrameTransforms`` message: each link on a fixed joint in its parent
        link's frame, which never changes (what ROS puts on ``/tf_static``)."""
        p, cid = self._p, self._client
        frames = {(link.body, link.index): link for link in self.links}
        stamped = stamp(time_ns)
        transforms = []
        for link in self.links:
            if link.index < 0:
                continue
            info = p.getJointInfo(link.body, link.index, physicsClientId=cid)
            if info[2] != p.JOINT_FIXED:
                continue
            parent = frames[(link.body, int(info[16]))]
            inverse = p.invertTransform(*self._link_pose(parent))
            position, orientation = p.multiplyTransforms(*inverse, *self._link_pose(link))
            transforms.append(
                {
                    "timestamp": stamped,
                    "parent_frame_id": parent.frame,
                    "child_frame_id": link.frame,
                    "translation": vector3(position),
                    "rotation": quaternion_xyzw(orientation),
                }
            )
        return {"transforms": transforms}

    def scene(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.SceneUpdate`` message: one entity per link with its visual shapes,
        locked to the link's frame (meshes embedded, so a recording is self-contained)."""
        p, cid = self._p, self._client
        frames = {(link.body, link.index): link.frame for link in self.links}
        entities: dict[str, dict[str, Any]] = {}
        for body in self.bodies.values():
            for shape in p.getVisualShapeData(body, physicsClientId=cid):
                frame = frames.get((body, shape[1]))
                if frame is None:
                    continue
                entity = entities.get(frame)
                if entity is None:
                    entity = entities[frame] = scene_entity(frame, time_ns)
                _add_shape(entity, shape, p)
        return {"deletions": [], "entities": list(entities.values())}


_MESHES: dict[str, tuple[str, str]] = {}


def _mesh(filename: str) -> tuple[str, str] | None:
    """(media type, base64 data) of a mesh file, preferring an STL beside an OBJ."""
    if filename in _MESHES:
        return _MESHES[filename]
    path = Path(filename)
    stl = path.with_suffix(".stl")
    if path.suffix.lower() != ".stl" and stl.is_file():
        path = stl
    media = {".stl": "model/stl", ".obj": "model/obj", ".dae": "model/vnd.collada+xml"}.get(
        path.suffix.lower()
    )
    if media is None or not path.is_file():
        return None
    _MESHES[filename] = (media, base64.b64encode(path.read_bytes()).decode())
    return _MESHES[filename]


def _add_shape(entity: dict[str, Any], shape: Any, p: Any) -> None:
    geometry, dims, filename = shape[2], shape[3], _text(shape[4])
    pose = {"position": vector3(shape[5]), "orientation": quaternion_xyzw(shape[6])}
    r, g, b, a = (float(c) for c in shape[7])
    color = {"r": r, "g": g, "b": b, "a": a}
    if geometry == p.GEOM_BOX:
        entity["cubes"].append({"pose": pose, "size": vector3(dims), "color": color})
    elif geometry == p.GEOM_SPHERE:
        d = 2 * float(dims[0])
        entity["spheres"].append({"pose": pose, "size": vector3((d, d, d)), "color": color})
    elif geometry in (p.GEOM_CYLINDER, p.GEOM_CAPSULE):
        d = 2 * float(dims[1])
        entity["cylinders"].append(
            {
                "pose": pose,
                "size": vector3((d, d, float(dims[0]))),
                "bottom_scale": 1.0,
                "top_scale": 1.0,
                "color": color,
            }
        )
    elif geometry == p.GEOM_MESH:
        mesh = _mesh(filename)
        if mesh is not None:
            entity["models"].append(
                {
                    "pose": pose,
                    "scale": vector3(dims),
                    "color": color,
                    "override_color": True,
                    "url": "",
                    "media_type": mesh[0],
                    "data": mesh[1],
                }
            )


# ---------------------------------------------------------------------------------------------
# The live view


def parse_address(address: str) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT`` or ``HOST`` -> (host, port); defaults from
    :data:`DEFAULT_ADDRESS`.

    :param address: what ``--foxglove`` was given.
    :returns: the host and port to serve on (port 0: any free port).
    :raises InvalidArgumentError: the port is not a number in 0..65535.
    """
    default_host, _, default_port = DEFAULT_ADDRESS.rpartition(":")
    text = address.strip()
    if text.startswith("ws://"):
        text = text.removeprefix("ws://").rstrip("/")
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = text, default_port
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise InvalidArgumentError(
            f"--foxglove-addr takes HOST:PORT (default {DEFAULT_ADDRESS}), got {address!r}"
        )
    return host or default_host, port


class LiveView:
    """Serves a run's channels live to Foxglove over its WebSocket protocol.

    Sim time is broadcast (Foxglove's timeline follows it); Foxglove's playback controls (play,
    pause, speed: the real-time factor) and the services ``/evclock/pause``,
    ``/evclock/resume`` and ``/evclock/step`` pause, resume and single-step the simulation;
    the scenario's parameters are visible in the Parameters panel.

    :param address: ``HOST:PORT`` to listen on (see :func:`parse_address`).
    :param name: the server name Foxglove shows.
    :param parameters: values shown as parameters (read-only).
    :param until_ns: the run's sim-time limit (the playback range Foxglove shows), or None for
        a wall-time run, which cannot be paused: then no controls are offered.
    :param channels: the channels known before the run (topic -> schema and metadata): they
        exist before the server accepts a client, so every client learns them when it
        connects. A channel created later is advertised to the clients connected then, and
        foxglove-sdk (0.30) sends that advertisement before it accepts subscriptions to the
        channel: a client that subscribes at once may be refused ("Unknown channel ID") and
        Foxglove does not ask again.
    :raises MissingExtraError: ``foxglove-sdk`` is not installed (``evclock[record]``).
    :raises InvalidArgumentError: the address is malformed or cannot be listened on.
    """

    def __init__(
        self,
        address: str,
        name: str,
        parameters: Mapping[str, Any],
        *,
        until_ns: int | None = None,
        channels: Mapping[str, tuple[Mapping[str, Any], Mapping[str, str]]] | None = None,
    ) -> None:
        from evclock._extras import import_extra

        foxglove = import_extra("foxglove", "record", needed_by="evclock run --foxglove")
        from foxglove.websocket import (
            Capability,
            MessageSchema,
            Parameter,
            PlaybackCommand,
            PlaybackState,
            PlaybackStatus,
            Service,
            ServiceSchema,
        )

        self._foxglove = foxglove
        host, port = parse_address(address)
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        for topic, (schema_of_topic, metadata) in (channels or {}).items():
            self.channel(topic, schema_of_topic, metadata)
        self._controls: Any = None  # the loop's pause/resume/step, once attached
        self._now_ns = 0  # the last time broadcast
        self._wake_read: socket.socket | None = None
        self._wake_write: socket.socket | None = None
        self._scene: bytes | None = None  # the scene as sent, for later subscribers
        self._parameters = [
            Parameter(f"/scenario/{key}", value=_parameter_value(value))
            for key, value in parameters.items()
        ]
        empty = foxglove.Schema(name="evclock.Empty", encoding="jsonschema", data=b"{}")
        step_schema = foxglove.Schema(
            name="evclock.Step",
            encoding="jsonschema",
            data=json.dumps(object_schema("evclock.Step", {"steps": {"type": "integer"}})).encode(),
        )

        def schema(request: Any) -> Any:
            return ServiceSchema(
                "evclock.Control",
                request=MessageSchema(encoding="json", schema=request),
                response=MessageSchema(encoding="json", schema=empty),
            )

        services = [
            Service("/evclock/pause", schema=schema(empty), handler=self._service),
            Service("/evclock/resume", schema=schema(empty), handler=self._service),
            Service("/evclock/step", schema=schema(step_schema), handler=self._service),
        ]
        view = self

        def playback(request: Any) -> Any:
            controls = view._controls
            if controls is None:
                return None
            if request.playback_speed > 0 and request.playback_speed != controls.rtf:
                controls.rtf = float(request.playback_speed)
            play = request.playback_command == PlaybackCommand.Play
            if play and controls.paused:
                controls.resume()
            elif not play and not controls.paused:
                controls.pause()
            view._wake()
            return PlaybackState(
                PlaybackStatus.Playing if play else PlaybackStatus.Paused,
                view._now_ns,
                float(request.playback_speed),
                False,  # sim time does not seek: the timeline goes where the simulation goes
                request.request_id,
            )

        class Listener:
            def on_playback_control_request(self, request: Any) -> Any:
                return playback(request)

            def on_subscribe(self, client: Any, channel: Any) -> None:
                if channel.topic == SCENE_TOPIC:
                    view._send_scene_again()

            def on_get_parameters(
                self, client: Any, param_names: list[str], request_id: str | None = None
            ) -> list[Any]:
                wanted = set(param_names)
                return [p for p in view._parameters if not wanted or p.name in wanted]

        try:
            self.server = foxglove.start_server(
                name=name,
                host=host,
                port=port,
                capabilities=[Capability.Time, Capability.Parameters]
                + ([Capability.Services] if until_ns is not None else []),
                server_listener=Listener(),
                services=services if until_ns is not None else None,
                context=self._context,
                supported_encodings=["json"],
                playback_time_range=None if until_ns is None else (0, until_ns),
            )
        except Exception as exc:  # the SDK raises its own error type for a busy port
            raise InvalidArgumentError(
                f"--foxglove cannot listen on {host}:{port}: {exc}; pick another port "
                "(--foxglove-addr 127.0.0.1:PORT, port 0 for any free one)"
            ) from None
        self.host = host
        self.port: int = self.server.port

    @property
    def url(self) -> str:
        """The ``ws://`` address a Foxglove client connects to."""
        return f"ws://{self.host}:{self.port}"

    def control(self, controls: Any) -> None:
        """Route the pause/resume/step services to ``controls`` (the running loop's
        thread-safe ``pause()``, ``resume()`` and ``step(n)``).

        Call on the running loop: it also registers a wake-up socket there, so the loop
        knows a paused run can be resumed from outside (the SDK's server threads are native
        threads the loop cannot see); each service call writes a byte to it.

        :param controls: the running :class:`~evclock.SimEventLoop`.
        """
        self._controls = controls
        self._wake_read, self._wake_write = socket.socketpair()
        self._wake_read.setblocking(False)
        self._wake_write.setblocking(False)
        controls.add_reader(self._wake_read.fileno(), self._drain)

    def _drain(self) -> None:
        if self._wake_read is not None:
            with contextlib.suppress(BlockingIOError, OSError):
                self._wake_read.recv(4096)

    def _wake(self) -> None:
        if self._wake_write is not None:
            with contextlib.suppress(BlockingIOError, OSError):
                self._wake_write.send(b"\0")

    def _service(self, request: Any) -> bytes:
        controls = self._controls
        if controls is None:
            raise NotRunningError("the simulation is not running yet: call again once it runs")
        name = request.service_name
        if name == "/evclock/pause":
            controls.pause()
        elif name == "/evclock/resume":
            controls.resume()
        else:
            payload = json.loads(request.payload or b"{}") if request.payload else {}
            steps = int(payload.get("steps", 1)) if isinstance(payload, dict) else 1
            if not controls.paused:
                controls.pause()
            controls.step(max(1, steps))
        self._wake()
        return b"{}"

    def channel(self, topic: str, schema: Mapping[str, Any], metadata: Mapping[str, str]) -> Any:
        """The live channel of ``topic`` (created on first use)."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._foxglove.Channel(
                topic, schema=dict(schema), context=self._context, metadata=dict(metadata)
            )
            self._channels[topic] = channel
        return channel

    def log(
        self,
        topic: str,
        schema: Mapping[str, Any],
        metadata: Mapping[str, str],
        time_ns: int,
        payload: bytes,
    ) -> None:
        """Send one JSON message, stamped ``time_ns`` (sim time)."""
        if topic == SCENE_TOPIC:
            self._scene = payload  # before it is sent: a subscriber gets it either way
        self.channel(topic, schema, metadata).log(payload, log_time=time_ns)

    def _send_scene_again(self) -> None:
        """Send the scene to a new subscriber (on the server's thread: a paused run takes
        no samples), stamped with the last sim time broadcast; before the first scene was
        sent, the subscriber gets that one. Live only: never into a recording."""
        scene, channel = self._scene, self._channels.get(SCENE_TOPIC)
        if scene is not None and channel is not None:
            channel.log(scene, log_time=self._now_ns)

    def tick(self, time_ns: int) -> None:
        """Broadcast the current sim time (Foxglove's timeline follows it).

        :param time_ns: the sim time, in integer nanoseconds.
        """
        self._now_ns = time_ns
        self.server.broadcast_time(time_ns)

    def close(self) -> None:
        """Stop serving."""
        self.server.stop()
        if self._wake_read is not None:
            self._wake_read.close()
        if self._wake_write is not None:
            self._wake_write.close()


def _parameter_value(value: Any) -> Any:
    if isinstance(value, bool | int | float | str):
        return value
    return json.dumps(value)


def logging_handler(write: Callable[[logging.LogRecord], None]) -> logging.Handler:
    """A :mod:`logging` handler calling ``write`` for each record made on this thread."""
    owner = threading.get_ident()

    class _Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if threading.get_ident() == owner:
                write(record)

    return _Handler(logging.DEBUG)


def log_message(record: logging.LogRecord, time_ns: int) -> dict[str, Any]:
    """A ``foxglove.Log`` message for a :mod:`logging` record, stamped ``time_ns``."""
    level = next((fox for py, fox in LOG_LEVELS if record.levelno >= py), 1)
    return {
        "timestamp": stamp(time_ns),
        "level": level,
        "message": record.getMessage(),
        "name": record.name,
        "file": record.pathname,
        "line": record.lineno,
    }
