"""``evclock run SCENARIO --ros2``: the simulated robot on ROS 2 topics, stamped with sim time.

Besides ``/clock`` (:mod:`evclock.ros2`), every published step writes ``sensor_msgs/JointState``
on ``/joint_states`` (each moving joint's position, velocity and effort) and
``tf2_msgs/TFMessage`` on ``/tf`` (every link frame that can move, in the ``world`` frame);
``/tf_static`` holds, once and transient-local, the frames that cannot (a link on a fixed
joint in its parent link's frame, a MuJoCo body without joints in its parent's), as
robot_state_publisher splits them. Frames are named as robot_state_publisher names them:
the URDF's link name behind the frame prefix (``frame_prefix + link``, no separator added;
``world`` is never prefixed), and the robot's URDF is on ``/robot_description``
(``std_msgs/String``, reliable, transient local, keep last 1: robot_state_publisher's QoS),
so RViz2's RobotModel display finds it. All read by name from
the world with the recorder's readers (PyBullet's :class:`~evclock.tools._foxglove.World`,
MuJoCo's :class:`~evclock.tools._world_mujoco.MuJoCoWorldReader`), so RViz2, ``ros2 topic echo``
and ``ros2 bag record`` show the robot on sim time. The messages are rosbags' classes of the
distribution spoken, serialised by rosbags; the topics' QoS are those of ROS's own publishers:
``/tf`` as tf2_ros' ``DynamicBroadcasterQoS`` (reliable, volatile, keep last 100),
``/tf_static`` as its ``StaticBroadcasterQoS`` (reliable, transient local, keep last 1) and
``/joint_states`` as joint_state_publisher's (reliable, volatile, keep last 10).
"""

from __future__ import annotations

import contextlib
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.ros2._dds import DdsNode, DdsQos
from evclock.ros2._publisher import publish_every
from evclock.ros2._types import message_class, serialize
from evclock.ros2._wire import DEFAULT_WIRE_FORMAT, check_frame_prefix, resolve_domain_id
from evclock.ros2._wire import wire_format as lookup_wire_format

if TYPE_CHECKING:
    from evclock.ros2._cli import Ros2ClockOptions

JOINT_STATE: Final = "sensor_msgs/msg/JointState"
TF_MESSAGE: Final = "tf2_msgs/msg/TFMessage"
TF_QOS: Final = DdsQos(reliable=True, transient_local=False, depth=100)
"""tf2_ros ``DynamicBroadcasterQoS`` (``tf2_ros/include/tf2_ros/qos.hpp``): reliable, volatile,
keep last 100."""
TF_STATIC_QOS: Final = DdsQos(reliable=True, transient_local=True, depth=1)
"""tf2_ros ``StaticBroadcasterQoS`` (``qos.hpp``): reliable, transient local, keep last 1."""
JOINT_STATES_QOS: Final = DdsQos(reliable=True, transient_local=False, depth=10)
"""joint_state_publisher's and robot_state_publisher's ``/joint_states``: reliable, depth 10."""
STRING: Final = "std_msgs/msg/String"
ROBOT_DESCRIPTION_QOS: Final = DdsQos(reliable=True, transient_local=True, depth=1)
"""robot_state_publisher's ``/robot_description`` (``rclcpp::QoS(1).transient_local()``)."""


def robot_description(urdf: Path) -> str:
    """The URDF text robot_state_publisher would publish for the file ``urdf``, with each
    relative mesh file name made an absolute ``file://`` URI (RViz2 resolves no path relative
    to a file it never saw)."""
    try:
        root = ElementTree.fromstring(urdf.read_bytes())
    except OSError as exc:
        raise InvalidArgumentError(f"cannot read the URDF {urdf}: {exc.strerror}") from None
    except ElementTree.ParseError as exc:
        raise InvalidArgumentError(f"the URDF {urdf} is not XML: {exc}") from None
    if root.tag != "robot":
        raise InvalidArgumentError(
            f"the URDF {urdf} is not a robot description: its root element is <{root.tag}>, "
            "not <robot>"
        )
    for mesh in root.iter("mesh"):
        filename = mesh.get("filename")
        if filename is not None and "://" not in filename:
            mesh.set("filename", (urdf.parent / filename).resolve().as_uri())
    return ElementTree.tostring(root, encoding="unicode")


class RobotStatePublisher:
    """Publishes a world's joint states and link frames as ROS 2 messages over DDS.

    :param reader: the world's reader (``joint_states(ns)`` and ``transforms(ns)`` dicts).
    :param options: the validated ``--ros2`` options (domain, wire format, frame prefix).
    :param urdf: the robot's URDF file, published on ``/robot_description`` (None: no
        description, and no such topic).
    """

    def __init__(self, reader: Any, options: Ros2ClockOptions, urdf: Path | None = None) -> None:
        self._reader = reader
        self._wire = lookup_wire_format(options.wire_format)
        self._frames = _ros_frames(reader.link_names, check_frame_prefix(options.frame_prefix))
        description = None if urdf is None else robot_description(urdf)
        self._node = DdsNode(options.domain_id, "evclock_robot_state", self._wire)
        try:
            self._joint_states = self._node.writer("/joint_states", JOINT_STATE, JOINT_STATES_QOS)
            self._tf = self._node.writer("/tf", TF_MESSAGE, TF_QOS)
            self._tf_static = self._node.writer("/tf_static", TF_MESSAGE, TF_STATIC_QOS)
            if description is not None:
                writer = self._node.writer("/robot_description", STRING, ROBOT_DESCRIPTION_QOS)
                message = message_class(STRING, self._wire)(data=description)
                writer.write(serialize(message, STRING, self._wire))
        except BaseException:
            self._node.close()
            raise
        self.robot_description = description
        """The URDF text on ``/robot_description`` (None: none published)."""
        self._cls = {
            name: message_class(name, self._wire)
            for name in (
                JOINT_STATE,
                TF_MESSAGE,
                "std_msgs/msg/Header",
                "builtin_interfaces/msg/Time",
                "geometry_msgs/msg/TransformStamped",
                "geometry_msgs/msg/Transform",
                "geometry_msgs/msg/Vector3",
                "geometry_msgs/msg/Quaternion",
            )
        }
        self.published = 0
        self._static: frozenset[str] | None = None  # the child frames on /tf_static

    def _header(self, time_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(time_ns, 1_000_000_000)
        stamp = self._cls["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        return self._cls["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def joint_state(self, time_ns: int) -> Any:
        """The ``sensor_msgs/JointState`` message of the world now, stamped ``time_ns``."""
        import numpy

        joints = self._reader.joint_states(time_ns)["joints"]

        def column(key: str) -> Any:
            return numpy.array([float(j[key]) for j in joints], dtype=numpy.float64)

        return self._cls[JOINT_STATE](
            header=self._header(time_ns, ""),
            name=[str(j["name"]) for j in joints],
            position=column("position"),
            velocity=column("velocity"),
            effort=column("effort"),
        )

    def tf(self, time_ns: int) -> Any:
        """The ``tf2_msgs/TFMessage`` of every link frame that can move, stamped ``time_ns``."""
        static = self._static or frozenset()
        frames = self._reader.transforms(time_ns)["transforms"]
        moving = [f for f in frames if f["child_frame_id"] not in static]
        return self._tf_message(moving, time_ns)

    def _tf_message(self, frames: list[dict[str, Any]], time_ns: int) -> Any:
        cls = self._cls
        transforms = []
        names = self._frames
        for frame in frames:
            t, r = frame["translation"], frame["rotation"]
            parent = frame["parent_frame_id"]
            transforms.append(
                cls["geometry_msgs/msg/TransformStamped"](
                    header=self._header(time_ns, names.get(parent, parent)),
                    child_frame_id=names[frame["child_frame_id"]],
                    transform=cls["geometry_msgs/msg/Transform"](
                        translation=cls["geometry_msgs/msg/Vector3"](x=t["x"], y=t["y"], z=t["z"]),
                        rotation=cls["geometry_msgs/msg/Quaternion"](
                            x=r["x"], y=r["y"], z=r["z"], w=r["w"]
                        ),
                    ),
                )
            )
        return cls[TF_MESSAGE](transforms=transforms)

    def publish(self, time_ns: int) -> None:
        """Write the joint states and the link frames at ``time_ns`` (the first time also the
        static frames)."""
        if self._static is None:
            fixed = self._reader.fixed_transforms(time_ns)["transforms"]
            self._static = frozenset(frame["child_frame_id"] for frame in fixed)
            if fixed:  # as tf2_ros' static broadcaster: nothing static, no message
                static = self._tf_message(fixed, time_ns)
                self._tf_static.write(serialize(static, TF_MESSAGE, self._wire))
        self._joint_states.write(serialize(self.joint_state(time_ns), JOINT_STATE, self._wire))
        self._tf.write(serialize(self.tf(time_ns), TF_MESSAGE, self._wire))
        self.published += 1

    def close(self) -> None:
        """Withdraw the node from the ROS graph."""
        self._node.close()


@contextlib.contextmanager
def publishing_robot_state(
    source: Any, options: Ros2ClockOptions | None, urdf: Path | None = None
) -> Iterator[RobotStatePublisher | None]:
    """Publish the robot state every ``options.decimation`` physics steps while the block runs
    (nothing unless ``--ros2`` asked for it)."""
    if options is None or not options.robot_state:
        yield None
        return
    if options.middleware != "dds":
        raise InvalidArgumentError(
            "--ros2 publishes the robot state over DDS only for now; drop --rmw zenoh (or use "
            "--ros2-clock for /clock alone over Zenoh)"
        )
    from evclock.tools._record import world_reader

    reader = world_reader(getattr(source, "client", source))
    if reader is None:
        raise InvalidArgumentError("--ros2 needs a PyBullet or MuJoCo world to read the robot from")
    publisher = RobotStatePublisher(reader, options, urdf)
    hook = publish_every(source, options.decimation, publisher.publish)
    try:
        yield publisher
    finally:
        hook.remove()
        publisher.close()


@contextlib.contextmanager
def ros2_robot_state(
    source: Any,
    *,
    urdf: str | Path | None = None,
    frame_prefix: str = "",
    domain_id: int | None = None,
    decimation: int = 1,
    wire_format: str = DEFAULT_WIRE_FORMAT,
) -> Iterator[RobotStatePublisher]:
    """Publish a simulation's robot on ROS 2 (DDS) while the block runs, as ``evclock run
    --ros2`` does: ``/joint_states``, ``/tf`` and ``/tf_static`` now and every ``decimation``
    physics steps, stamped with sim time, frames named ``frame_prefix + link`` after the
    URDF's links (as robot_state_publisher's ``frame_prefix``; ``world`` is never prefixed),
    and the ``urdf`` file's robot on ``/robot_description`` (reliable, transient local).

    :param source: the stepping source of a PyBullet or MuJoCo world.
    :param urdf: the robot's URDF file (None: no ``/robot_description``).
    :param frame_prefix: prepended to every link frame, e.g. ``"robot1/"`` for several robots.
    :param domain_id: the ROS domain (default ``ROS_DOMAIN_ID``, else 0).
    :param decimation: publish every this many physics steps (>= 1).
    :param wire_format: the distribution spoken (``"jazzy"``, ``"kilted"``, ``"humble"``...).
    :returns: the publisher (its ``robot_description`` and ``published`` count).
    :raises InvalidArgumentError: an illegal frame prefix, a URDF that cannot be read, a
        source that is not a PyBullet or MuJoCo world, a decimation below 1.

    Example::

        with ros2_robot_state(source, urdf="arm.urdf", frame_prefix="robot1/"):
            evclock.run(main(), source=source)
    """
    from evclock.ros2._cli import Ros2ClockOptions
    from evclock.ros2._publisher import check_decimation

    if urdf is not None and not isinstance(urdf, str | Path):
        raise InvalidTypeError(f"urdf must be a path (str or Path), got {type(urdf).__name__}")
    options = Ros2ClockOptions(
        domain_id=resolve_domain_id(domain_id),
        decimation=check_decimation(decimation),
        wire_format=lookup_wire_format(wire_format).name,
        connect=None,
        listen=None,
        robot_state=True,
        frame_prefix=check_frame_prefix(frame_prefix),
    )
    with publishing_robot_state(source, options, None if urdf is None else Path(urdf)) as published:
        assert published is not None
        yield published


def _ros_frames(link_names: dict[str, str], prefix: str) -> dict[str, str]:
    """The reader's frames (``<body>/<link>``) -> ROS frame names (``prefix + link``); two
    bodies naming a link alike would make one frame of two: an error."""
    frames: dict[str, str] = {}
    owner: dict[str, str] = {}
    for frame, link in link_names.items():
        name = prefix + link
        if name in owner:
            raise InvalidArgumentError(
                f"two links are named {link!r} ({owner[name]} and {frame}): their ROS frames "
                "would be one; give the bodies' links distinct names in their URDFs"
            )
        owner[name] = frame
        frames[frame] = name
    return frames
