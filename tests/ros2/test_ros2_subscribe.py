"""``evclock.ros2.subscribe``: ROS 2 topics as filters of Stamped messages, over DDS and Zenoh.

The publishers write what a ROS 2 node writes: rosbags' CDR of the message (the payload test of
``test_ros2_dds.py`` shows it is what DDS types with ROS's names serialise), on loopback only.
"""

from __future__ import annotations

import asyncio
import json
import tempfile
from collections.abc import Iterator
from typing import Any

import pytest

import evclock
from evclock import SYSTEM, InvalidArgumentError, Time
from evclock.data import ApproximateTimeSynchronizer, Stamped

pytest.importorskip("cyclonedds", reason="needs evclock[ros2] (cyclonedds)")
rosbags_typesys = pytest.importorskip("rosbags.typesys", reason="needs rosbags")

from evclock.ros2 import subscribe  # noqa: E402
from evclock.ros2._dds import DdsNode, DdsQos  # noqa: E402
from evclock.ros2._wire import WIRE_FORMATS  # noqa: E402

WAIT = 10.0  # wall seconds: a guard against hangs, never a performance assertion
STORE = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
RELIABLE = DdsQos(reliable=True, transient_local=False, depth=10)


@pytest.fixture(autouse=True)
def loopback_domain(loopback_dds: int) -> int:
    """Every test here: its own ROS domain, DDS on loopback only (tests/conftest.py)."""
    return loopback_dds


@pytest.fixture
def node(loopback_domain: int) -> Iterator[DdsNode]:
    publisher = DdsNode(loopback_domain, "sensors", WIRE_FORMATS["jazzy"])
    yield publisher
    publisher.close()


def msg(msgtype: str, /, **fields: Any) -> Any:
    return STORE.types[msgtype](**fields)


def header(sec: int, nanosec: int, frame: str = "base") -> Any:
    return msg(
        "std_msgs/msg/Header",
        stamp=msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
        frame_id=frame,
    )


def vector(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z)


def quaternion() -> Any:
    return msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)


def imu(sec: int, nanosec: int, ax: float) -> Any:
    import numpy

    zeros = numpy.zeros(9)
    return msg(
        "sensor_msgs/msg/Imu",
        header=header(sec, nanosec),
        orientation=quaternion(),
        orientation_covariance=zeros,
        angular_velocity=vector(),
        angular_velocity_covariance=zeros,
        linear_acceleration=vector(ax),
        linear_acceleration_covariance=zeros,
    )


def pose(sec: int, nanosec: int, x: float) -> Any:
    return msg(
        "geometry_msgs/msg/PoseStamped",
        header=header(sec, nanosec, "map"),
        pose=msg(
            "geometry_msgs/msg/Pose",
            position=msg("geometry_msgs/msg/Point", x=x, y=0.0, z=0.0),
            orientation=quaternion(),
        ),
    )


def examples() -> dict[str, Any]:
    import numpy

    return {
        "sensor_msgs/msg/Imu": imu(1, 5, 9.81),
        "sensor_msgs/msg/JointState": msg(
            "sensor_msgs/msg/JointState",
            header=header(2, 6),
            name=["a", "b"],
            position=numpy.array([0.5, -0.5]),
            velocity=numpy.array([0.0, 1.0]),
            effort=numpy.array([], dtype=numpy.float64),
        ),
        "sensor_msgs/msg/LaserScan": msg(
            "sensor_msgs/msg/LaserScan",
            header=header(3, 7, "laser"),
            angle_min=-1.0,
            angle_max=1.0,
            angle_increment=0.5,
            time_increment=0.0,
            scan_time=0.1,
            range_min=0.1,
            range_max=10.0,
            ranges=numpy.array([1.0, 2.0, 3.0, 4.0, 5.0], dtype=numpy.float32),
            intensities=numpy.array([], dtype=numpy.float32),
        ),
        "geometry_msgs/msg/PoseStamped": pose(4, 8, 1.5),
    }


def run_on_wall(main: Any) -> Any:
    return evclock.run(main, use_sim_time=False, wall_clock=SYSTEM)


@pytest.mark.parametrize("msgtype", list(examples()))
def test_dds_topic_arrives_as_stamped_messages(node: DdsNode, msgtype: str) -> None:
    sent = examples()[msgtype]
    writer = node.writer("/data", msgtype, RELIABLE)

    async def main() -> Stamped[Any]:
        sub = subscribe("/data", msgtype, reliable=True)
        got: asyncio.Queue[Stamped[Any]] = asyncio.Queue()
        sub.register_callback(got.put_nowait)
        async with asyncio.timeout(WAIT):
            while writer.matched() == 0:
                await asyncio.sleep(0.005)
            writer.write(bytes(STORE.serialize_cdr(sent, msgtype)))
            stamped = await got.get()
        sub.close()
        return stamped

    stamped = run_on_wall(main())
    stamp = sent.header.stamp
    assert stamped.stamp == Time(stamp.sec, stamp.nanosec, clock_type=SYSTEM)
    assert bytes(STORE.serialize_cdr(stamped.value, msgtype)) == bytes(
        STORE.serialize_cdr(sent, msgtype)
    )


def test_tf_message_is_one_stamped_per_transform(node: DdsNode) -> None:
    tf = "tf2_msgs/msg/TFMessage"
    writer = node.writer("/tf", tf, RELIABLE)
    transforms = [
        msg(
            "geometry_msgs/msg/TransformStamped",
            header=header(5, n, "world"),
            child_frame_id=f"link{n}",
            transform=msg(
                "geometry_msgs/msg/Transform", translation=vector(n), rotation=quaternion()
            ),
        )
        for n in (1, 2)
    ]

    async def main() -> list[Stamped[Any]]:
        sub = subscribe("/tf", tf, reliable=True)
        got: list[Stamped[Any]] = []
        done = asyncio.Event()

        def keep(message: Stamped[Any]) -> None:
            got.append(message)
            if len(got) == 2:
                done.set()

        sub.register_callback(keep)
        async with asyncio.timeout(WAIT):
            while writer.matched() == 0:
                await asyncio.sleep(0.005)
            writer.write(bytes(STORE.serialize_cdr(msg(tf, transforms=transforms), tf)))
            await done.wait()
        sub.close()
        return got

    got = run_on_wall(main())
    assert [(s.stamp.nanoseconds, s.value.child_frame_id) for s in got] == [
        (5_000_000_001, "link1"),
        (5_000_000_002, "link2"),
    ]


def test_two_topics_fused_by_approximate_time(node: DdsNode) -> None:
    imu_writer = node.writer("/imu", "sensor_msgs/msg/Imu", RELIABLE)
    pose_writer = node.writer("/pose", "geometry_msgs/msg/PoseStamped", RELIABLE)

    async def main() -> list[tuple[int, int]]:
        imu_sub = subscribe("/imu", "sensor_msgs/msg/Imu", reliable=True)
        pose_sub = subscribe("/pose", "geometry_msgs/msg/PoseStamped", reliable=True)
        pairs: list[tuple[int, int]] = []
        done = asyncio.Event()

        def fused(a: Stamped[Any], b: Stamped[Any]) -> None:
            pairs.append((a.stamp.nanoseconds, b.stamp.nanoseconds))
            if len(pairs) == 3:
                done.set()

        sync = ApproximateTimeSynchronizer(
            ["imu", "pose"], queue_size=10, slop=0.005, callback=fused
        )
        sync.connect_input(imu_sub, pose_sub)
        async with asyncio.timeout(WAIT):
            while imu_writer.matched() == 0 or pose_writer.matched() == 0:
                await asyncio.sleep(0.005)
            for k in range(3):
                imu_writer.write(
                    bytes(STORE.serialize_cdr(imu(10 + k, 1_000, 0.0), "sensor_msgs/msg/Imu"))
                )
                pose_writer.write(
                    bytes(
                        STORE.serialize_cdr(
                            pose(10 + k, 2_000_000, 0.0), "geometry_msgs/msg/PoseStamped"
                        )
                    )
                )
            await done.wait()
        imu_sub.close()
        pose_sub.close()
        return pairs

    assert run_on_wall(main()) == [
        ((10 + k) * 1_000_000_000 + 1_000, (10 + k) * 1_000_000_000 + 2_000_000) for k in range(3)
    ]


def test_unstamped_or_unknown_types_are_refused() -> None:
    async def main() -> None:
        with pytest.raises(InvalidArgumentError, match="has no header"):
            subscribe("/x", "std_msgs/msg/String")
        with pytest.raises(InvalidArgumentError, match="not a message type of ROS 2 jazzy"):
            subscribe("/x", "sensor_msgs/msg/Nope")
        with pytest.raises(InvalidArgumentError, match="not a ROS 2 message type name"):
            subscribe("/x", "sensor_msgs::Imu")

    run_on_wall(main())


@pytest.fixture
def zenoh_peer(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Any, str]]:
    """A plain Zenoh peer of the test listening on a Unix socket; the middleware is Zenoh."""
    zenoh = pytest.importorskip("zenoh", reason="needs evclock[ros2] (eclipse-zenoh)")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_zenoh_cpp")
    with tempfile.TemporaryDirectory(prefix="evros2") as folder:  # short: sun_path limit
        endpoint = f"unixsock-stream/{folder}/z.sock"
        config = {
            "mode": "peer",
            "connect": {"endpoints": []},
            "listen": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}},
        }
        session = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
        yield session, endpoint
        session.close()


POSE = "geometry_msgs/msg/PoseStamped"
POSE_KEY = f"0/pose/geometry_msgs::msg::dds_::PoseStamped_/{STORE.hash_rihs01(POSE)}"


def test_zenoh_topic_arrives_as_stamped_messages(zenoh_peer: tuple[Any, str]) -> None:
    session, endpoint = zenoh_peer
    publisher = session.declare_publisher(POSE_KEY)
    sent = pose(7, 9, 2.5)

    async def main() -> Stamped[Any]:
        sub = subscribe("/pose", POSE, domain_id=0, connect=[endpoint], listen=[])
        got: asyncio.Queue[Stamped[Any]] = asyncio.Queue()
        sub.register_callback(got.put_nowait)
        async with asyncio.timeout(WAIT):
            while got.empty():  # until the subscription reached the publisher
                publisher.put(bytes(STORE.serialize_cdr(sent, POSE)))
                await asyncio.sleep(0.02)
            stamped = await got.get()
        sub.close()
        return stamped

    stamped = run_on_wall(main())
    assert stamped.stamp == Time(7, 9, clock_type=SYSTEM)
    assert stamped.value.pose.position.x == 2.5


def test_zenoh_subscription_is_in_the_ros_graph(zenoh_peer: tuple[Any, str]) -> None:
    session, endpoint = zenoh_peer

    def tokens() -> list[str]:
        return sorted(str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**"))

    async def main() -> tuple[tuple[str, ...], list[str]]:
        sub = subscribe("/pose", POSE, domain_id=0, connect=[endpoint], listen=[], queue_size=5)
        async with asyncio.timeout(WAIT):
            seen = tokens()
            while len(seen) < 2:  # until the tokens reached the peer
                await asyncio.sleep(0.02)
                seen = tokens()
        sub.close()
        return sub.liveliness_tokens, seen

    declared, seen = run_on_wall(main())
    assert sorted(declared) == seen
    node, endpoint_token = declared
    assert node.endswith("/NN/%/%/evclock_listener")
    assert endpoint_token.endswith(
        f"/MS/%/%/evclock_listener/%pose/geometry_msgs::msg::dds_::PoseStamped_/"
        f"{STORE.hash_rihs01(POSE)}/2:2:,5:,:,:,,"
    )


def test_undecodable_message_is_counted_not_delivered(
    zenoh_peer: tuple[Any, str], caplog: pytest.LogCaptureFixture
) -> None:
    session, endpoint = zenoh_peer
    publisher = session.declare_publisher(POSE_KEY)

    async def main() -> tuple[int, int]:
        sub = subscribe("/pose", POSE, domain_id=0, connect=[endpoint], listen=[])
        async with asyncio.timeout(WAIT):
            while sub.rejected == 0:
                publisher.put(b"\x00\x01\x00\x00" + b"\xff" * 6)  # far too short for a pose
                await asyncio.sleep(0.02)
        sub.close()
        return sub.received, sub.rejected

    with caplog.at_level("WARNING", logger="evclock.ros2"):
        received, rejected = run_on_wall(main())
    assert received == 0
    assert rejected >= 1
    assert any("it starts 00010000ffffffffffff" in r.getMessage() for r in caplog.records)
