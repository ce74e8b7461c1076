"""A MuJoCo world read by name, for recordings and the Foxglove live view: the MuJoCo
counterpart of :class:`evclock.tools._foxglove.World` (PyBullet's), writing the same messages.

What PyBullet calls a body (a robot: a base and its links) is a kinematic tree of the MuJoCo
model: a child of the world body and everything under it. A tree is named by the model's name
(a URDF's robot name) when the model has one tree, else by its root body's name; each MuJoCo
body is a link, framed ``<tree>/<body>`` as PyBullet's ``<body>/<link>``. Hinge and slide
joints are the moving joints (a free joint is the tree's base pose and velocities; ball joints
have no single position and are left out). The scene draws the geoms MuJoCo's viewer shows by
default (groups 0 to 2): boxes, spheres, ellipsoids, cylinders, capsules (a cylinder and two
spheres), planes (a thin box) and meshes (the compiled mesh, embedded as binary STL).

Poses and velocities are computed for the current state (``qpos``, ``qvel``) in a scratch
``MjData``: after ``mj_step``, ``data.xpos`` still holds the poses of the step's start, and
the recorder never writes to the run's data. ``mujoco`` (and numpy) is used through the model
passed in: importing this module loads neither.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from typing import Any

from evclock._extras import import_extra
from evclock.tools._foxglove import (
    WORLD_FRAME,
    quaternion_xyzw,
    scene_entity,
    stamp,
    unique_name,
    vector3,
)

_HINGE_SLIDE = (2, 3)  # mjJNT_SLIDE, mjJNT_HINGE
_FREE = 0  # mjJNT_FREE
_VISIBLE_GROUPS = 3  # MuJoCo's viewer shows geom groups 0, 1 and 2 by default
_INFINITE_PLANE_M = 20.0  # the side drawn for an infinite plane (size 0)
_DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # a geom's rgba when it sets none (its material's then)


def _name(mj: Any, model: Any, kind: Any, index: int, fallback: str) -> str:
    text = mj.mj_id2name(model, kind, index)
    return str(text) if text else fallback


def _wxyz(values: Sequence[float]) -> dict[str, float]:
    """MuJoCo's ``(w, x, y, z)`` quaternion as a ``foxglove.Quaternion``."""
    return quaternion_xyzw((values[1], values[2], values[3], values[0]))


class MuJoCoWorldReader:
    """A MuJoCo model and its data read by name: the state, joint states, link transforms and
    scene messages :class:`~evclock.tools._foxglove.World` writes for PyBullet.

    :param model: the ``mujoco.MjModel``.
    :param data: its ``mujoco.MjData`` (read, never written).
    """

    def __init__(self, model: Any, data: Any) -> None:
        mj = import_extra("mujoco", "mujoco", needed_by="recording a MuJoCo run")
        self._mj = mj
        self._model = model
        self._data = data
        self._scratch = mj.MjData(model)
        body_kind = mj.mjtObj.mjOBJ_BODY
        roots = [b for b in range(1, model.nbody) if int(model.body_parentid[b]) == 0]
        model_name = bytes(model.names[: bytes(model.names).index(b"\0")]).decode(errors="replace")
        taken: dict[str, int] = {}
        self.bodies: dict[str, int] = {}
        """Tree name -> its root body's id, in body-id order (names made unique)."""
        for root in roots:
            own = _name(mj, model, body_kind, root, f"body{root}")
            name = model_name if len(roots) == 1 and model_name else own
            self.bodies[unique_name(name, taken)] = root
        tree_of = {root: name for name, root in self.bodies.items()}
        self._frames: list[tuple[int, str]] = []  # body id, frame name
        self._links: dict[str, str] = {}  # frame name -> body (a URDF's link) name
        for b in range(1, model.nbody):
            tree = tree_of[int(model.body_rootid[b])]
            link = _name(mj, model, body_kind, b, f"body{b}")
            self._frames.append((b, f"{tree}/{link}"))
            self._links[f"{tree}/{link}"] = link
        joint_kind = mj.mjtObj.mjOBJ_JOINT
        self._joints: list[tuple[str, int, int, int]] = []  # name, tree root, qpos, dof
        for j in range(model.njnt):
            if int(model.jnt_type[j]) in _HINGE_SLIDE:
                self._joints.append(
                    (
                        _name(mj, model, joint_kind, j, f"joint{j}"),
                        int(model.body_rootid[model.jnt_bodyid[j]]),
                        int(model.jnt_qposadr[j]),
                        int(model.jnt_dofadr[j]),
                    )
                )
        self._meshes: dict[int, str] = {}

    @property
    def joint_names(self) -> list[str]:
        """Every moving (hinge or slide) joint's name, in joint order."""
        return [joint[0] for joint in self._joints]

    @property
    def link_names(self) -> dict[str, str]:
        """Each body frame (``<tree>/<body>``) -> the body's name (a URDF's link name)."""
        return dict(self._links)

    def _current(self) -> Any:
        """The scratch data with the poses and velocities of the run's current state."""
        mj, model, data, scratch = self._mj, self._model, self._data, self._scratch
        scratch.qpos[:] = data.qpos
        scratch.qvel[:] = data.qvel
        if model.nmocap:
            scratch.mocap_pos[:] = data.mocap_pos
            scratch.mocap_quat[:] = data.mocap_quat
        mj.mj_kinematics(model, scratch)
        mj.mj_comPos(model, scratch)
        mj.mj_comVel(model, scratch)
        return scratch

    def state(self) -> dict[str, Any]:
        """The physical state by name: per tree its root body's pose and velocities (world
        frame) and each hinge or slide joint's position and velocity."""
        import numpy

        mj, model = self._mj, self._model
        current = self._current()
        velocity = numpy.zeros(6)
        state: dict[str, Any] = {}
        for name, root in self.bodies.items():
            mj.mj_objectVelocity(model, current, mj.mjtObj.mjOBJ_BODY, root, velocity, 0)
            state[name] = {
                "position": vector3(current.xpos[root]),
                "orientation": _wxyz(current.xquat[root]),
                "linear_velocity": vector3(velocity[3:].tolist()),
                "angular_velocity": vector3(velocity[:3].tolist()),
                "joints": {
                    joint: {"position": float(current.qpos[q]), "velocity": float(current.qvel[d])}
                    for joint, tree, q, d in self._joints
                    if tree == root
                },
            }
        return state

    def joint_states(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.JointStates`` message: each moving joint's position, velocity and
        effort (the actuators' force on it in the last step, ``qfrc_actuator``)."""
        data = self._data
        joints = [
            {
                "name": name,
                "position": float(data.qpos[q]),
                "velocity": float(data.qvel[d]),
                "effort": float(data.qfrc_actuator[d]),
            }
            for name, _, q, d in self._joints
        ]
        return {"timestamp": stamp(time_ns), "joints": joints}

    def transforms(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.FrameTransforms`` message: every body's frame in the world frame."""
        current = self._current()
        stamped = stamp(time_ns)
        return {
            "transforms": [
                {
                    "timestamp": stamped,
                    "parent_frame_id": WORLD_FRAME,
                    "child_frame_id": frame,
                    "translation": vector3(current.xpos[body]),
                    "rotation": _wxyz(current.xquat[body]),
                }
                for body, frame in self._frames
            ]
        }

    def fixed_transforms(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.FrameTransforms`` message: each body without joints (and not a mocap
        body) in its parent body's frame (the world frame under the world body): the model's
        ``body_pos``/``body_quat``, which never change (what ROS puts on ``/tf_static``)."""
        model = self._model
        names = dict(self._frames)
        stamped = stamp(time_ns)
        transforms = []
        for body, frame in self._frames:
            if int(model.body_jntnum[body]) != 0 or int(model.body_mocapid[body]) != -1:
                continue
            parent = int(model.body_parentid[body])
            transforms.append(
                {
                    "timestamp": stamped,
                    "parent_frame_id": WORLD_FRAME if parent == 0 else names[parent],
                    "child_frame_id": frame,
                    "translation": vector3(model.body_pos[body]),
                    "rotation": _wxyz(model.body_quat[body]),
                }
            )
        return {"transforms": transforms}

    def scene(self, time_ns: int) -> dict[str, Any]:
        """A ``foxglove.SceneUpdate`` message: one entity per body with its visible geoms,
        locked to the body's frame (the world body's geoms in the world frame; meshes
        embedded, so a recording is self-contained)."""
        model = self._model
        frames = {0: WORLD_FRAME, **dict(self._frames)}
        entities: dict[int, dict[str, Any]] = {}
        for geom in range(model.ngeom):
            if int(model.geom_group[geom]) >= _VISIBLE_GROUPS:
                continue
            rgba = self._rgba(geom)
            if rgba[3] <= 0:
                continue
            body = int(model.geom_bodyid[geom])
            entity = entities.get(body)
            if entity is None:
                entity = entities[body] = scene_entity(frames[body], time_ns)
            self._add_geom(entity, geom, rgba)
        return {"deletions": [], "entities": [entities[b] for b in sorted(entities)]}

    def _rgba(self, geom: int) -> tuple[float, float, float, float]:
        model = self._model
        r, g, b, a = (float(c) for c in model.geom_rgba[geom])
        material = int(model.geom_matid[geom])
        if material >= 0 and (r, g, b, a) == _DEFAULT_RGBA:
            r, g, b, a = (float(c) for c in model.mat_rgba[material])
        return r, g, b, a

    def _add_geom(
        self, entity: dict[str, Any], geom: int, rgba: tuple[float, float, float, float]
    ) -> None:
        mj, model = self._mj, self._model
        kind = int(model.geom_type[geom])
        size = [float(s) for s in model.geom_size[geom]]
        position = [float(c) for c in model.geom_pos[geom]]
        quat = [float(c) for c in model.geom_quat[geom]]
        pose = {"position": vector3(position), "orientation": _wxyz(quat)}
        color = {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]}
        types = mj.mjtGeom
        if kind == types.mjGEOM_BOX:
            box = (2 * size[0], 2 * size[1], 2 * size[2])
            entity["cubes"].append({"pose": pose, "size": vector3(box), "color": color})
        elif kind == types.mjGEOM_PLANE:
            x, y = (2 * s if s > 0 else _INFINITE_PLANE_M for s in size[:2])
            entity["cubes"].append({"pose": pose, "size": vector3((x, y, 0.001)), "color": color})
        elif kind in (types.mjGEOM_SPHERE, types.mjGEOM_ELLIPSOID):
            radii = size if kind == types.mjGEOM_ELLIPSOID else [size[0]] * 3
            diameters = (2 * radii[0], 2 * radii[1], 2 * radii[2])
            entity["spheres"].append({"pose": pose, "size": vector3(diameters), "color": color})
        elif kind in (types.mjGEOM_CYLINDER, types.mjGEOM_CAPSULE):
            d = 2 * size[0]
            entity["cylinders"].append(
                {
                    "pose": pose,
                    "size": vector3((d, d, 2 * size[1])),
                    "bottom_scale": 1.0,
                    "top_scale": 1.0,
                    "color": color,
                }
            )
            if kind == types.mjGEOM_CAPSULE:  # the caps: a sphere at each end
                import numpy

                for sign in (1.0, -1.0):
                    offset = numpy.zeros(3)  # the axis end, turned into the body's frame
                    axis_end = numpy.array([0.0, 0.0, sign * size[1]])
                    mj.mju_rotVecQuat(offset, axis_end, model.geom_quat[geom])
                    end = model.geom_pos[geom] + offset
                    entity["spheres"].append(
                        {
                            "pose": {"position": vector3(end), "orientation": _wxyz(quat)},
                            "size": vector3((d, d, d)),
                            "color": color,
                        }
                    )
        elif kind == types.mjGEOM_MESH and int(model.geom_dataid[geom]) >= 0:
            entity["models"].append(
                {
                    "pose": pose,
                    "scale": vector3((1.0, 1.0, 1.0)),
                    "color": color,
                    "override_color": True,
                    "url": "",
                    "media_type": "model/stl",
                    "data": self._mesh_stl(int(model.geom_dataid[geom])),
                }
            )
        # height fields and signed-distance geoms are not drawn

    def _mesh_stl(self, mesh: int) -> str:
        """The compiled mesh ``mesh`` (in its geom's frame) as base64 binary STL."""
        cached = self._meshes.get(mesh)
        if cached is not None:
            return cached
        import numpy

        model = self._model
        start, count = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        vertices = numpy.asarray(model.mesh_vert[start : start + count], dtype=numpy.float32)
        first, faces = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        triangles = vertices[numpy.asarray(model.mesh_face[first : first + faces])]
        normals = numpy.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        lengths = numpy.linalg.norm(normals, axis=1, keepdims=True)
        normals = numpy.divide(normals, lengths, out=numpy.zeros_like(normals), where=lengths > 0)
        record = numpy.dtype(
            [("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")]
        )
        table = numpy.zeros(faces, dtype=record)
        table["normal"] = normals
        table["vertices"] = triangles
        header = b"evclock: a MuJoCo mesh".ljust(80, b" ")
        data = header + numpy.uint32(faces).tobytes() + table.tobytes()
        self._meshes[mesh] = base64.b64encode(data).decode()
        return self._meshes[mesh]
