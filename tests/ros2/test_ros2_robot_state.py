"""``evclock run SCENARIO --ros2``: the robot on /joint_states, /tf and /robot_description over
DDS, on sim time.

A plain Cyclone DDS participant of the test reads the topics with ROS's type names, written
here from the message definitions; every wait is bounded. Loopback only, a test-unique domain
(``loopback_dds`` in ``tests/conftest.py``).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

cyclonedds = pytest.importorskip("cyclonedds", reason="needs evclock[ros2] (cyclonedds)")
rosbags_typesys = pytest.importorskip("rosbags.typesys", reason="needs rosbags")

from _ros2_helpers import run_draining  # noqa: E402
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.idl import make_idl_struct  # noqa: E402
from cyclonedds.idl import types as t  # noqa: E402
from cyclonedds.qos import Policy, Qos  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

S = 1_000_000_000
EVCLOCK_RUN = (sys.executable, "-m", "evclock", "run")
ROOT = Path(__file__).resolve().parents[2]

Time_ = make_idl_struct(
    "Time_", "builtin_interfaces::msg::dds_::Time_", {"sec": t.int32, "nanosec": t.uint32}
)
Header_ = make_idl_struct(
    "Header_", "std_msgs::msg::dds_::Header_", {"stamp": Time_, "frame_id": str}
)
JointState_ = make_idl_struct(
    "JointState_",
    "sensor_msgs::msg::dds_::JointState_",
    {
        "header": Header_,
        "name": t.sequence[str],
        "position": t.sequence[t.float64],
        "velocity": t.sequence[t.float64],
        "effort": t.sequence[t.float64],
    },
)
Vector3_ = make_idl_struct(
    "Vector3_",
    "geometry_msgs::msg::dds_::Vector3_",
    {"x": t.float64, "y": t.float64, "z": t.float64},
)
Quaternion_ = make_idl_struct(
    "Quaternion_",
    "geometry_msgs::msg::dds_::Quaternion_",
    {"x": t.float64, "y": t.float64, "z": t.float64, "w": t.float64},
)
Transform_ = make_idl_struct(
    "Transform_",
    "geometry_msgs::msg::dds_::Transform_",
    {"translation": Vector3_, "rotation": Quaternion_},
)
TransformStamped_ = make_idl_struct(
    "TransformStamped_",
    "geometry_msgs::msg::dds_::TransformStamped_",
    {"header": Header_, "child_frame_id": str, "transform": Transform_},
)
TFMessage_ = make_idl_struct(
    "TFMessage_", "tf2_msgs::msg::dds_::TFMessage_", {"transforms": t.sequence[TransformStamped_]}
)
String_ = make_idl_struct("String_", "std_msgs::msg::dds_::String_", {"data": str})
RELIABLE = Qos(Policy.Reliability.Reliable(max_blocking_time=100_000_000), Policy.History.KeepAll)
#: tf2_ros' StaticListenerQoS: a late joiner still gets the static frames.
STATIC = Qos(
    Policy.Reliability.Reliable(max_blocking_time=100_000_000),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(100),
)


@pytest.fixture
def plain(loopback_dds: int) -> Iterator[DomainParticipant]:
    """The test's own participant, in its own domain on loopback only (tests/conftest.py)."""
    participant = DomainParticipant(loopback_dds)
    yield participant
    participant.__del__()


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * S + int(header.stamp.nanosec)


@pytest.mark.parametrize("engine", ["pybullet", "mujoco"])
def test_run_publishes_joint_states_and_tf_on_sim_time(
    engine: str, plain: DomainParticipant
) -> None:
    pytest.importorskip("pybullet" if engine == "pybullet" else "mujoco")
    joints = DataReader(plain, Topic(plain, "rt/joint_states", JointState_), qos=RELIABLE)
    tf = DataReader(plain, Topic(plain, "rt/tf", TFMessage_), qos=RELIABLE)
    tf_static = DataReader(plain, Topic(plain, "rt/tf_static", TFMessage_), qos=STATIC)
    states: list[Any] = []
    frames: list[Any] = []

    def drain() -> None:
        states.extend(joints.take(256))
        frames.extend(tf.take(256))

    status, out, err = run_draining(
        [*EVCLOCK_RUN, "kuka", "--ros2", "--engine", engine, "--until", "0.25"], drain, ROOT
    )
    # The writers' end arrives as sample-less notifications (InvalidSample): data only.
    states = [s for s in states if isinstance(s, JointState_)]
    frames = [f for f in frames if isinstance(f, TFMessage_)]
    assert status == 3, err  # cut short by --until, as asked
    assert (
        "publishing /clock, /joint_states, /tf every step over DDS "
        "(rt/clock, rt/joint_states, rt/tf)" in out
    )
    assert states, "no JointState reached the subscriber"
    assert frames, "no TFMessage reached the subscriber"
    step = 12_500_000 / 3  # 240 Hz, each step time floored to ns
    for state in states:
        ns = stamp_ns(state.header)
        assert round(ns / step) * 12_500_000 // 3 == ns  # stamped with a step's sim time
        assert len(state.name) == len(state.position) == len(state.velocity) == len(state.effort)
        assert len(state.name) >= 7  # the KUKA arm's joints, by name
    stamps = [stamp_ns(s.header) for s in states]
    assert stamps == sorted(stamps)
    assert stamps[-1] <= S // 4
    for message in frames:
        assert message.transforms
        assert {f.header.frame_id for f in message.transforms} <= {"world"}
        assert len({stamp_ns(f.header) for f in message.transforms}) == 1
    # The frames that cannot move are on /tf_static (once), the others on /tf: MuJoCo's KUKA
    # base is a body without joints under the world body; PyBullet's arm has no fixed joint.
    statics = [m for m in tf_static.take(16) if isinstance(m, TFMessage_)]
    moving = {f.child_frame_id for m in frames for f in m.transforms}
    if engine == "mujoco":
        (static,) = statics
        assert [(f.header.frame_id, f.child_frame_id) for f in static.transforms] == [
            ("world", "lbr_iiwa_link_0")
        ]
        assert stamp_ns(static.transforms[0].header) == 0
    else:
        assert statics == []
    static_frames = {f.child_frame_id for m in statics for f in m.transforms}
    assert not moving & static_frames
    # Named after the URDF's links, as robot_state_publisher names them (no prefix asked).
    assert moving | static_frames == {f"lbr_iiwa_link_{k}" for k in range(8)}
    # The payload layout is rosbags' (the message definitions of ROS 2 Jazzy).
    store = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    last = states[-1]
    rebuilt = store.deserialize_cdr(last.serialize(), "sensor_msgs/msg/JointState")
    assert list(rebuilt.name) == list(last.name)
    assert list(rebuilt.position) == list(last.position)
    assert bytes(store.serialize_cdr(rebuilt, "sensor_msgs/msg/JointState")) == last.serialize()


def test_frame_prefix_and_robot_description(plain: DomainParticipant) -> None:
    # Two robots in one ROS graph: --ros2-frame-prefix puts each one's frames apart, as
    # robot_state_publisher's frame_prefix does (world, the fixed frame, is shared); the URDF
    # reaches a subscriber on /robot_description as robot_state_publisher's subscribers take it.
    pytest.importorskip("mujoco")
    from evclock.tools._ros2_state import robot_description
    from evclock_sims._mujoco import model_path

    tf = DataReader(plain, Topic(plain, "rt/tf", TFMessage_), qos=RELIABLE)
    tf_static = DataReader(plain, Topic(plain, "rt/tf_static", TFMessage_), qos=STATIC)
    urdf = DataReader(plain, Topic(plain, "rt/robot_description", String_), qos=STATIC)
    frames: list[Any] = []
    descriptions: list[Any] = []

    def drain() -> None:
        frames.extend(m for m in tf.take(256) + tf_static.take(16) if isinstance(m, TFMessage_))
        descriptions.extend(m for m in urdf.take(4) if isinstance(m, String_))

    options = ["--ros2", "--ros2-frame-prefix", "robot1/", "--until", "0.05"]
    status, _out, err = run_draining(
        [*EVCLOCK_RUN, "kuka", "--engine", "mujoco", *options], drain, ROOT
    )
    assert status == 3, err
    names = {(f.header.frame_id, f.child_frame_id) for m in frames for f in m.transforms}
    assert names == {("world", f"robot1/lbr_iiwa_link_{k}") for k in range(8)}
    (description,) = descriptions
    assert description.data == robot_description(model_path("kuka_iiwa/model.urdf"))


def test_a_fixed_joint_is_a_static_frame_in_its_parents_frame() -> None:
    pybullet = pytest.importorskip("pybullet")
    from evclock.tools._foxglove import World

    client = pybullet.connect(pybullet.DIRECT)
    try:
        box = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[0.1] * 3)
        pybullet.createMultiBody(
            baseMass=1.0,
            baseCollisionShapeIndex=box,
            basePosition=[1.0, 2.0, 3.0],
            linkMasses=[0.5],
            linkCollisionShapeIndices=[box],
            linkVisualShapeIndices=[-1],
            linkPositions=[[0.0, 0.0, 0.5]],
            linkOrientations=[[0, 0, 0, 1]],
            linkInertialFramePositions=[[0, 0, 0]],
            linkInertialFrameOrientations=[[0, 0, 0, 1]],
            linkParentIndices=[0],
            linkJointTypes=[pybullet.JOINT_FIXED],
            linkJointAxis=[[0, 0, 1]],
            physicsClientId=client,
        )
        world = World(client, pybullet)
        base, link = (frame.frame for frame in world.links)
        (fixed,) = world.fixed_transforms(7)["transforms"]
    finally:
        pybullet.disconnect(client)
    assert (fixed["parent_frame_id"], fixed["child_frame_id"]) == (base, link)
    assert fixed["translation"] == pytest.approx({"x": 0.0, "y": 0.0, "z": 0.5}, abs=1e-9)
    assert fixed["rotation"] == pytest.approx({"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, abs=1e-9)
