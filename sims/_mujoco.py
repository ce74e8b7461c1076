"""The MuJoCo side of the scenarios: URDF -> actuated MuJoCo model, and a world to build into.

:func:`urdf_to_mujoco` turns a URDF (PyBullet's own ``kuka_iiwa/model.urdf``, ``cartpole.urdf``)
into a MuJoCo model a controller can drive: position actuators (or force motors) on the joints
it names, joint armature, contact exclusions between adjacent links, optional gravity
compensation, and the scenarios' physics settings (1/240 s steps, gravity). A scenario given
a :class:`MuJoCoWorld` instead of a PyBullet client builds its robot with
:meth:`MuJoCoWorld.load_urdf`; :meth:`MuJoCoWorld.time_source` then drives it on evclock's sim
time.

The URDFs come from ``pybullet_data`` when it is installed, else from byte-identical copies
shipped in the package's ``models`` folder (see its LICENSE.txt), so the MuJoCo scenarios run -
and give the same trajectories - with or without PyBullet (which has wheels for CPython 3.11
only).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

from evclock._extras import import_extra

MODELS = Path(__file__).resolve().parent / "models"
"""The robot descriptions shipped with the scenarios (copies of ``pybullet_data`` files)."""

PHYSICS_HZ = 240
GRAVITY = -9.81


def mujoco() -> Any:
    """The ``mujoco`` module, or MissingExtraError naming the ``mujoco`` extra."""
    return import_extra("mujoco", "mujoco", needed_by="the MuJoCo scenarios (evclock_sims)")


def model_path(relative: str) -> Path:
    """A robot description by its ``pybullet_data`` path: ``pybullet_data``'s file when
    PyBullet's data is installed, else the copy shipped in :data:`MODELS`.

    :param relative: the path inside ``pybullet_data`` (``"kuka_iiwa/model.urdf"``).
    :returns: the absolute path of the file.
    :raises FileNotFoundError: neither has the file.
    """
    try:
        import pybullet_data
    except ImportError:
        pass
    else:
        candidate = Path(pybullet_data.getDataPath()) / relative
        if candidate.is_file():
            return candidate
    shipped = MODELS / relative
    if not shipped.is_file():
        raise FileNotFoundError(
            f"no robot description {relative!r}: neither pybullet_data nor evclock_sims/models "
            "has it; install evclock[pybullet] for PyBullet's full data set"
        )
    return shipped


def urdf_to_mujoco(
    path: str | Path,
    *,
    position_joints: Sequence[str] = (),
    motor_joints: Sequence[str] = (),
    kp: float = 2000.0,
    kv: float = 100.0,
    force_limit: float | None = None,
    armature: float = 0.0,
    exclude_adjacent: bool = True,
    gravity_compensation: bool = False,
    time_step: float | Fraction = Fraction(1, PHYSICS_HZ),
    gravity: float = GRAVITY,
) -> Any:
    """Turn a URDF into an actuated MuJoCo model (``mujoco.MjModel``).

    MuJoCo reads URDF natively but gives it no actuators, and a URDF says nothing of the
    rotor inertia or the contacts an arm's own links make where they join. This adds:

    * a **position actuator** (``kp``, ``kv``: a PD servo, like PyBullet's
      ``POSITION_CONTROL``) on each joint of ``position_joints``, whose ``ctrl`` is the target
      position, and a **force motor** on each joint of ``motor_joints``, whose ``ctrl`` is the
      force or torque (a zero-order hold: it stays until changed);
    * their force limit: ``force_limit``, else the joint's URDF ``effort`` limit;
    * **armature** (reflected rotor inertia) on those joints: it keeps stiff servos stable at
      1/240 s steps;
    * **contact exclusions** between each link and its parent (adjacent links touch at their
      joint: without this they push each other apart, and a mesh arm steps several times
      slower);
    * optional **gravity compensation** of every link (as a real arm's controller does, so
      that a position servo holds its target without a steady-state sag);
    * the time step, gravity, and the ``implicitfast`` integrator (servo damping integrated
      implicitly).

    :param path: the URDF file (meshes relative to it).
    :param position_joints: joints (URDF names) driven by position actuators, in ``ctrl`` order.
    :param motor_joints: joints driven by force motors, after the position actuators.
    :param kp: position gain of the position actuators (N m/rad or N/m).
    :param kv: velocity gain of the position actuators (N m s/rad or N s/m).
    :param force_limit: the actuators' force limit (default: each joint's URDF effort limit).
    :param armature: armature added to each actuated joint (kg m^2 or kg).
    :param exclude_adjacent: exclude contacts between each link and its parent.
    :param gravity_compensation: compensate gravity on every link.
    :param time_step: the model's time step in seconds (default 1/240).
    :param gravity: gravity along z, in m/s^2.
    :returns: the compiled ``mujoco.MjModel``.
    :raises ValueError: MuJoCo cannot read the file, or a named joint does not exist.
    """
    mj = mujoco()
    spec = mj.MjSpec.from_file(str(path))
    spec.option.timestep = float(time_step)
    spec.option.gravity = [0.0, 0.0, gravity]
    spec.option.integrator = mj.mjtIntegrator.mjINT_IMPLICITFAST
    joints = {joint.name: joint for joint in spec.joints}
    limits = _effort_limits(Path(path))
    for kind, names in (("position", position_joints), ("motor", motor_joints)):
        for name in names:
            if name not in joints:
                raise ValueError(f"{path}: no joint named {name!r}; joints: {', '.join(joints)}")
            joints[name].armature = armature
            actuator = spec.add_actuator(name=f"{name}_{kind}", target=name)
            actuator.trntype = mj.mjtTrn.mjTRN_JOINT
            if kind == "position":
                actuator.set_to_position(kp=kp, kv=kv)
            else:
                actuator.set_to_motor()
            limit = force_limit if force_limit is not None else limits.get(name)
            if limit is not None:
                actuator.forcelimited = mj.mjtLimited.mjLIMITED_TRUE
                actuator.forcerange = [-limit, limit]
    if exclude_adjacent:
        for body in spec.bodies:
            parent = body.parent
            if parent is not None and parent.name != body.name and body.name != "world":
                spec.add_exclude(bodyname1=parent.name, bodyname2=body.name)
    if gravity_compensation:
        for body in spec.bodies:
            if body.name != "world":
                body.gravcomp = 1.0
    return spec.compile()


def _effort_limits(path: Path) -> dict[str, float]:
    """Each joint's URDF ``<limit effort=...>``, by joint name."""
    import xml.etree.ElementTree as ElementTree

    limits: dict[str, float] = {}
    for joint in ElementTree.parse(path).getroot().iter("joint"):
        limit = joint.find("limit")
        if limit is not None and limit.get("effort") is not None:
            limits[joint.get("name", "")] = float(limit.get("effort", "0"))
    return limits


class MuJoCoWorld:
    """An empty MuJoCo world a scenario builds its robot into (the MuJoCo stand-in for a
    connected PyBullet client): ``scenario = KukaReach(MuJoCoWorld(), seed)``, then
    ``evclock.run(scenario.run(evclock.clock()), source=world.time_source())``.

    One robot per world: :meth:`load_urdf` compiles the model (MuJoCo compiles a whole model
    at once, so the world is fixed once loaded).
    """

    def __init__(self) -> None:
        self.model: Any = None
        """The ``mujoco.MjModel``, once loaded."""
        self.data: Any = None
        """Its ``mujoco.MjData``, once loaded. The engine-facing code of a scenario reads
        and writes the simulated state through this attribute only (never a reference kept
        aside): in the controller process of a split run (``evclock control --engine
        mujoco``) it is replaced by a stand-in that forwards those reads and writes to the
        simulation process, while :attr:`model` stays this process's own."""
        self.mj: Any = mujoco()
        """The ``mujoco`` module."""
        self.urdf: Path | None = None
        """The URDF file the world was built from, once loaded."""
        self._source: Any = None
        self._loaded: tuple[str, dict[str, Any]] | None = None  # load_urdf's arguments
        self._reload = False
        self._scratch: Any = None
        self._derived: dict[Any, Any] = {}

    def clear(self) -> None:
        """Empty the world for another scenario of the same robot, keeping the compiled model:
        the next :meth:`load_urdf` with the same arguments resets the data (``mj_resetData``,
        the state of a new ``MjData``) instead of compiling the URDF again. How a scenario is
        built again in place (``evclock.gym.ScenarioEnv``'s reset); the time source, which
        owns the clock, stays this world's."""
        self._reload = self.model is not None

    def load_urdf(self, relative: str, **options: Any) -> None:
        """Build the world from a ``pybullet_data`` URDF (see :func:`model_path`) through
        :func:`urdf_to_mujoco` with ``options``.

        :param relative: the URDF's path inside ``pybullet_data``.
        :param options: keyword arguments of :func:`urdf_to_mujoco`.
        :raises RuntimeError: the world already holds a model (and was not :meth:`clear`-ed
            for the same one).
        """
        loaded = (relative, options)
        if self.model is not None:
            if not (self._reload and loaded == self._loaded):
                raise RuntimeError("this MuJoCoWorld already holds a model: one robot per world")
            self._reload = False
            self.mj.mj_resetData(self.model, self.data)
            return
        self.urdf = model_path(relative)
        self.model = urdf_to_mujoco(self.urdf, **options)
        self.data = self.mj.MjData(self.model)
        self._loaded = loaded

    def scratch(self) -> Any:
        """A scratch ``MjData`` of the model, for computations that must not touch the
        simulated data (kinematics, model terms): made once per world (a new ``MjData`` costs
        a fraction of a millisecond), shared by the scenarios built in it. Its users set every
        input they read (``qpos``, ``qvel``) before each computation."""
        if self._scratch is None:
            self._scratch = self.mj.MjData(self.model)
        return self._scratch

    def derived(self, key: Any, compute: Callable[[], Any]) -> Any:
        """``compute()``, once per world and ``key``: what a scenario derives from the model
        alone (the cart-pole's LQR gain), kept when the world is :meth:`clear`-ed and the
        scenario built again. ``key`` names everything else the value depends on."""
        if key not in self._derived:
            self._derived[key] = compute()
        return self._derived[key]

    def joint_index(self, name: str) -> tuple[int, int]:
        """``(qpos address, dof address)`` of the joint named ``name``."""
        mj = self.mj
        joint = int(mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_JOINT, name))
        if joint < 0:
            raise ValueError(f"the model has no joint named {name!r}")
        return int(self.model.jnt_qposadr[joint]), int(self.model.jnt_dofadr[joint])

    def body_index(self, name: str) -> int:
        """The id of the body named ``name``."""
        body = int(self.mj.mj_name2id(self.model, self.mj.mjtObj.mjOBJ_BODY, name))
        if body < 0:
            raise ValueError(f"the model has no body named {name!r}")
        return body

    def forward(self) -> None:
        """Recompute what derives from the state (poses) after changing it directly."""
        self.mj.mj_forward(self.model, self.data)

    def time_source(self) -> Any:
        """The :class:`~evclock.sources.MuJoCoTimeSource` stepping this world (one per world)."""
        if self.model is None:
            raise RuntimeError("the world is empty: create the scenario in it first")
        if self._source is None:
            from evclock.sources import MuJoCoTimeSource

            self._source = MuJoCoTimeSource(
                self.model, self.data, time_step=Fraction(1, PHYSICS_HZ)
            )
        return self._source

    def state_vector(self) -> list[float]:
        """Joint positions, then velocities, then actuator activations (bit-exact)."""
        data = self.data
        return [*data.qpos.tolist(), *data.qvel.tolist(), *data.act.tolist()]
