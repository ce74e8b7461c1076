"""ROS 2 /clock over DDS through real Cyclone DDS participants, on the loopback interface only.

Every test runs in a DDS domain of its own (``ROS_DOMAIN_ID``) with ``CYCLONEDDS_URI`` naming a
configuration that binds the loopback interface, disables multicast and finds peers by unicast
on 127.0.0.1 (``loopback_dds`` in ``tests/conftest.py``). The other side of each exchange is a
plain Cyclone DDS participant of the test, with the ROS type names written here from the
message definitions (what a node on rmw_cyclonedds_cpp announces), or evclock in another
process. Every wait is bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from _ros2_helpers import jumps_on_reset, repeating, run_draining

import evclock
from evclock import ClockJumpedError, ClockLostError, InvalidArgumentError, Time
from evclock.ros2 import Ros2ClockPublisher, Ros2ClockSource, encode_clock

cyclonedds = pytest.importorskip("cyclonedds", reason="needs evclock[ros2] (cyclonedds)")
rosbags_typesys = pytest.importorskip("rosbags.typesys", reason="needs rosbags")

from cyclonedds.builtin import (  # noqa: E402
    BuiltinDataReader,
    BuiltinTopicDcpsParticipant,
    BuiltinTopicDcpsPublication,
)
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.idl import make_idl_struct  # noqa: E402
from cyclonedds.idl import types as t  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.qos import Policy, Qos  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

WAIT = 10.0  # wall seconds: a guard against hangs, never a performance assertion
S = 1_000_000_000
ROOT = Path(__file__).resolve().parents[2]


# The ROS types as rosidl names them for DDS, written from the .msg definitions (built with
# make_idl_struct: this module's postponed annotations are strings the binding cannot resolve).
Time_ = make_idl_struct(
    "Time_", "builtin_interfaces::msg::dds_::Time_", {"sec": t.int32, "nanosec": t.uint32}
)
Clock_ = make_idl_struct("Clock_", "rosgraph_msgs::msg::dds_::Clock_", {"clock": Time_})


def participant_entities_info(gid_size: int, suffix: str = "") -> Any:
    """rmw_dds_common's ParticipantEntitiesInfo with ``gid_size``-byte gids (16 from Iron on,
    24 on Humble); ``suffix`` tells the Python classes apart."""
    gid = make_idl_struct(
        f"Gid{suffix}_", "rmw_dds_common::msg::dds_::Gid_", {"data": t.array[t.uint8, gid_size]}
    )
    node = make_idl_struct(
        f"NodeEntitiesInfo{suffix}_",
        "rmw_dds_common::msg::dds_::NodeEntitiesInfo_",
        {
            "node_namespace": t.bounded_str[256],
            "node_name": t.bounded_str[256],
            "reader_gid_seq": t.sequence[gid],
            "writer_gid_seq": t.sequence[gid],
        },
    )
    return make_idl_struct(
        f"ParticipantEntitiesInfo{suffix}_",
        "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_",
        {"gid": gid, "node_entities_info_seq": t.sequence[node]},
    )


ParticipantEntitiesInfo_ = participant_entities_info(16)


BEST_EFFORT = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1))
RELIABLE = Qos(
    Policy.Reliability.Reliable(max_blocking_time=100_000_000), Policy.History.KeepLast(1)
)


def graph_reader(participant: DomainParticipant, info_type: Any = ParticipantEntitiesInfo_) -> Any:
    """A reader of the graph announcements, as ``ros2 node list`` reads them (a late joiner:
    transient local gives it the current announcement)."""
    qos = Qos(
        Policy.Reliability.Reliable(max_blocking_time=100_000_000),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(1),
    )
    return DataReader(participant, Topic(participant, "ros_discovery_info", info_type), qos=qos)


@pytest.fixture(autouse=True)
def loopback_domain(loopback_dds: int) -> int:
    """Every test here: its own ROS domain, DDS on loopback only (tests/conftest.py)."""
    return loopback_dds


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def take_all(reader: Any) -> list[Any]:
    return [s for s in reader.take(64) if getattr(s.sample_info, "valid_data", True)]


def clock_ns(sample: Any) -> int:
    return int(sample.clock.sec) * S + int(sample.clock.nanosec)


# ------------------------------------------------------------------ middleware choice


@pytest.mark.parametrize(
    ("value", "middleware"),
    [
        (None, "dds"),
        ("rmw_fastrtps_cpp", "dds"),
        ("rmw_cyclonedds_cpp", "dds"),
        ("rmw_connextdds", "dds"),
        ("rmw_zenoh_cpp", "zenoh"),
    ],
)
def test_middleware_is_chosen_as_ros_chooses_it(
    value: str | None, middleware: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from evclock.ros2._rmw import resolve_middleware

    if value is None:
        monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    else:
        monkeypatch.setenv("RMW_IMPLEMENTATION", value)
    assert resolve_middleware() == middleware
    assert resolve_middleware("zenoh") == "zenoh"  # an explicit choice wins


def test_unknown_middleware_names_the_valid_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    from evclock.ros2._rmw import resolve_middleware

    with pytest.raises(InvalidArgumentError, match=r"unknown ROS 2 middleware 'fast'.*dds, zenoh"):
        resolve_middleware("fast")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_opendds_cpp")
    with pytest.raises(InvalidArgumentError, match=r"'rmw_opendds_cpp'.*rmw_fastrtps_cpp"):
        resolve_middleware()


def test_cli_unknown_rmw_is_one_error_line() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "evclock", "run", "kuka", "--ros2-clock", "--rmw", "ddx"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error:")
    assert "'ddx'" in lines[0]
    assert "dds, zenoh" in lines[0]


def test_zenoh_endpoints_on_dds_are_refused() -> None:
    with pytest.raises(
        InvalidArgumentError, match="name Zenoh endpoints, but the middleware is DDS"
    ):
        Ros2ClockPublisher(connect=["tcp/127.0.0.1:7447"])
    with pytest.raises(InvalidArgumentError, match="name Zenoh endpoints"):
        Ros2ClockSource(listen=["tcp/127.0.0.1:0"], startup_timeout=0.1)


# ------------------------------------------------------------------ publisher


@pytest.fixture
def plain() -> Iterator[DomainParticipant]:
    """The test's own participant: what a ROS 2 node on rmw_cyclonedds_cpp would be."""
    participant = DomainParticipant(int(os.environ["ROS_DOMAIN_ID"]))
    yield participant
    participant.__del__()


def test_publisher_speaks_ros_names_types_qos_and_user_data(plain: DomainParticipant) -> None:
    store = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    clock_hash = store.hash_rihs01("rosgraph_msgs/msg/Clock")
    reader = DataReader(plain, Topic(plain, "rt/clock", Clock_), qos=BEST_EFFORT)
    publications = BuiltinDataReader(plain, BuiltinTopicDcpsPublication)
    participants = BuiltinDataReader(plain, BuiltinTopicDcpsParticipant)
    with Ros2ClockPublisher(node_name="evclock_sim") as publisher:
        assert publisher.middleware == "dds"
        wait_for(lambda: publisher._writer.matched() == 1, "the publisher to match the reader")
        publisher.publish(Time(12, 345_678_901))
        received: list[Any] = []
        wait_for(lambda: bool(received.extend(take_all(reader)) or received), "a Clock sample")
        assert [clock_ns(s) for s in received] == [12_345_678_901]
        # The bytes: evclock's payload is rosbags' CDR of the same message.
        message = store.types["rosgraph_msgs/msg/Clock"](
            clock=store.types["builtin_interfaces/msg/Time"](sec=12, nanosec=345_678_901)
        )
        assert encode_clock(12_345_678_901) == bytes(
            store.serialize_cdr(message, "rosgraph_msgs/msg/Clock")
        )
        assert received[0].serialize() == encode_clock(12_345_678_901)

        found: dict[str, Any] = {}

        def discovered() -> bool:
            for sample in publications.take(64):
                if sample.topic_name in ("rt/clock", "ros_discovery_info"):
                    found[sample.topic_name] = sample
            return len(found) == 2

        wait_for(discovered, "evclock's two writers")
        clock_writer = found["rt/clock"]
        assert clock_writer.type_name == "rosgraph_msgs::msg::dds_::Clock_"
        assert clock_writer.qos[Policy.Reliability] == Policy.Reliability.BestEffort
        assert clock_writer.qos[Policy.Durability] == Policy.Durability.Volatile
        assert clock_writer.qos[Policy.History] == Policy.History.KeepLast(1)
        assert clock_writer.qos[Policy.Userdata].data == f"typehash={clock_hash};".encode()
        assert clock_writer.qos[Policy.DataRepresentation].use_cdrv0_representation
        assert clock_writer.key.bytes == publisher.gid
        graph_writer = found["ros_discovery_info"]
        assert graph_writer.type_name == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
        assert graph_writer.qos[Policy.Reliability] == Policy.Reliability.Reliable(
            max_blocking_time=graph_writer.qos[Policy.Reliability].max_blocking_time
        )
        assert graph_writer.qos[Policy.Durability] == Policy.Durability.TransientLocal

        def enclave() -> bool:
            return any(
                p.key == clock_writer.participant_key
                and p.qos[Policy.Userdata].data == b"enclave=/;"
                for p in participants.take(64)
            )

        wait_for(enclave, "evclock's participant with enclave=/;")

        graph = graph_reader(plain)
        infos: list[Any] = []
        wait_for(lambda: bool(infos.extend(take_all(graph)) or infos), "the graph announcement")
        info = infos[-1]
        assert bytes(info.gid.data) == clock_writer.participant_key.bytes
        (node,) = info.node_entities_info_seq
        assert (node.node_namespace, node.node_name) == ("/", "evclock_sim")
        assert node.reader_gid_seq == []
        assert [bytes(g.data) for g in node.writer_gid_seq] == [publisher.gid]


def test_reliable_subscription_is_not_fed_and_evclock_says_so(
    plain: DomainParticipant, caplog: pytest.LogCaptureFixture
) -> None:
    reliable = DataReader(plain, Topic(plain, "rt/clock", Clock_), qos=RELIABLE)
    with Ros2ClockPublisher() as publisher:
        wait_for(lambda: bool(publisher.diagnostics()), "the QoS mismatch to be reported")
        (problem,) = publisher.diagnostics()
        assert "requested a QoS this publisher (best effort, volatile, keep last 1)" in problem
        assert "RELIABILITY" in problem
        with caplog.at_level("WARNING", logger="evclock.ros2"):
            publisher.publish(1 * S)  # the first publish reports it in the log too
        assert any("RELIABILITY" in r.getMessage() for r in caplog.records)
        assert publisher._writer.matched() == 0
    assert take_all(reliable) == []


def test_cli_run_publishes_exact_step_times_to_a_ros_subscriber(plain: DomainParticipant) -> None:
    pytest.importorskip("pybullet", reason="the kuka scenario needs PyBullet")
    reader = DataReader(plain, Topic(plain, "rt/clock", Clock_), qos=BEST_EFFORT)
    times: list[int] = []
    status, out, err = run_draining(
        [sys.executable, "-m", "evclock", "run", "kuka", "--ros2-clock", "--until", "0.5"],
        lambda: times.extend(clock_ns(s) for s in take_all(reader)),
        ROOT,
    )
    assert status == 3, err  # status 3: cut short by --until, as asked
    assert "CUT SHORT at --until 0.5 s" in out
    assert "publishing /clock every step over DDS (rt/clock) in domain" in out
    assert times, "no /clock sample reached the subscriber"
    step = 12_500_000 / 3  # 240 Hz, as evclock rounds each step time (floor)
    assert all(round(ns / step) * 12_500_000 // 3 == ns for ns in times)
    assert times == sorted(times)
    assert times[-1] <= S // 2


# ------------------------------------------------------------------ follower


class PlainClock:
    """A plain Cyclone DDS /clock publisher with ROS's names (reliable or best effort)."""

    def __init__(self, participant: DomainParticipant, qos: Qos = RELIABLE) -> None:
        self._writer = DataWriter(participant, Topic(participant, "rt/clock", Clock_), qos=qos)

    def __call__(self, time_ns: int) -> None:
        sec, nanosec = divmod(time_ns, S)
        self._writer.write(Clock_(clock=Time_(sec=sec, nanosec=nanosec)))


def start_follower(feed: PlainClock, first_ns: int, **options: Any) -> Ros2ClockSource:
    """Open a follower while the outside clock repeats ``first_ns``."""
    options.setdefault("startup_timeout", WAIT)
    with repeating(feed, first_ns, WAIT):
        return Ros2ClockSource(**options)


def test_follower_of_a_reliable_plain_publisher_fires_timers_exactly(
    plain: DomainParticipant,
) -> None:
    feed = PlainClock(plain, RELIABLE)  # a reliable publisher feeds the best-effort follower
    source = start_follower(feed, 1 * S)
    assert source.middleware == "dds"
    assert source.now_ns == 1 * S

    async def main() -> list[int]:
        clk = evclock.clock()
        fired: list[int] = []
        timer = clk.timer(0.25, lambda: fired.append(clk.now().nanoseconds))
        feed(1_600_000_000)
        await clk.sleep_until(Time(0, 1_600_000_000))
        timer.cancel()
        return fired

    assert evclock.run(main(), source=source) == [1_250_000_000, 1_500_000_000]


def test_follower_announces_its_node_and_subscription(plain: DomainParticipant) -> None:
    feed = PlainClock(plain)
    graph = graph_reader(plain)
    source = start_follower(feed, 0, node_name="evclock_ctl")
    try:
        nodes: list[Any] = []

        def announced() -> bool:
            for info in take_all(graph):
                nodes.extend(info.node_entities_info_seq)
            return any(n.node_name == "evclock_ctl" and n.reader_gid_seq for n in nodes)

        wait_for(announced, "the follower's announcement")
        node = next(n for n in nodes if n.node_name == "evclock_ctl")
        assert len(node.reader_gid_seq) == 1
        assert node.writer_gid_seq == []
        assert bytes(node.reader_gid_seq[0].data) == source._dds_reader.gid
    finally:
        source.close()


def test_backward_clock_is_a_jump(plain: DomainParticipant) -> None:
    feed = PlainClock(plain)
    source = start_follower(feed, 10 * S)
    (jump,) = evclock.run(jumps_on_reset(feed), source=source)
    assert (jump.before, jump.after) == (Time(10), Time(3))


def test_domains_are_isolated(plain: DomainParticipant) -> None:
    # A domain no other test uses (tests/conftest.py hands out 20..229), one per worker.
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]
    other = DomainParticipant(5 + (int(worker) if worker.isdigit() else 0) % 15)
    try:
        with (
            repeating(PlainClock(other), 5 * S, WAIT),
            pytest.raises(ClockLostError, match=r"no /clock message arrived within"),
        ):
            Ros2ClockSource(startup_timeout=0.5)
    finally:
        other.__del__()


def test_best_effort_publisher_and_reliable_follower_mismatch_is_named() -> None:
    from evclock.ros2._dds import DdsNode, DdsQos
    from evclock.ros2._wire import WIRE_FORMATS

    jazzy = WIRE_FORMATS["jazzy"]
    node = DdsNode(int(os.environ["ROS_DOMAIN_ID"]), "strict", jazzy)
    try:
        strict = DdsQos(reliable=True, transient_local=False, depth=1)
        reader = node.reader("/clock", "rosgraph_msgs/msg/Clock", strict, lambda _: None, print)
        with Ros2ClockPublisher():
            wait_for(lambda: reader.incompatible() is not None, "the reader's QoS report")
        problem = reader.incompatible()
        assert problem is not None
        assert "RELIABILITY" in problem
        assert "(reliable, volatile, keep last 1) cannot accept" in problem
    finally:
        node.close()


def test_evclock_publisher_and_follower_in_separate_processes() -> None:
    """An evclock publisher in another process, steered line by line; the follower here."""
    script = (
        "import sys, threading\n"
        "from evclock.ros2 import Ros2ClockPublisher\n"
        "pub = Ros2ClockPublisher()\n"
        "value = [int(sys.stdin.readline())]\n"
        "done = threading.Event()\n"
        "def repeat():\n"
        "    while not done.wait(0.01):\n"
        "        pub.publish(value[0])\n"
        "threading.Thread(target=repeat, daemon=True).start()\n"
        "for line in sys.stdin:\n"
        "    value[0] = int(line)\n"
        "done.set()\n"
        "pub.close()\n"
    )
    publisher = subprocess.Popen(
        [sys.executable, "-c", script], stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert publisher.stdin is not None
    stdin = publisher.stdin

    def publish(time_ns: int) -> None:
        stdin.write(f"{time_ns}\n")
        stdin.flush()

    try:
        publish(2 * S)
        source = Ros2ClockSource(startup_timeout=30)
        assert source.now_ns == 2 * S

        async def main() -> tuple[list[int], list[evclock.TimeJump]]:
            clk = evclock.clock()
            fired: list[int] = []
            jumps: list[evclock.TimeJump] = []
            clk.on_jump(post=jumps.append)
            timer = clk.timer(0.1, lambda: fired.append(clk.now().nanoseconds))
            publish(2_350_000_000)
            await clk.sleep_until(Time(0, 2_350_000_000))
            timer.cancel()
            publish(1 * S)  # the simulation was reset
            with contextlib.suppress(ClockJumpedError):
                await clk.sleep(10)
            return fired, jumps

        fired, jumps = evclock.run(main(), source=source)
        assert fired == [2_100_000_000, 2_200_000_000, 2_300_000_000]
        assert [(j.before, j.after) for j in jumps] == [(Time(0, 2_350_000_000), Time(1))]
        source.close()
    finally:
        stdin.close()
        publisher.wait(WAIT)
        assert publisher.stderr is not None
        with publisher.stderr:
            err = publisher.stderr.read()
    assert publisher.returncode == 0, err


def test_humble_graph_messages_carry_24_byte_gids_and_no_type_hash() -> None:
    from evclock.ros2._dds import DdsNode, user_data
    from evclock.ros2._wire import WIRE_FORMATS

    humble = WIRE_FORMATS["humble"]
    assert user_data("rosgraph_msgs/msg/Clock", humble) == b""
    node = DdsNode(int(os.environ["ROS_DOMAIN_ID"]), "old", humble)
    try:
        info = node.graph_message()
        assert len(info.gid.data) == 24  # rmw_dds_common 1.6 (Humble): char[24]
        assert bytes(info.gid.data)[16:] == bytes(8)
        assert info.node_entities_info_seq[0].node_name == "old"
    finally:
        node.close()


def test_unreadable_clock_sample_ends_the_run(plain: DomainParticipant) -> None:
    from evclock.ros2 import Ros2MessageError
    from evclock.ros2._dds import write_raw

    feed = PlainClock(plain)
    source = start_follower(feed, 1 * S)

    async def main() -> None:
        write_raw(feed._writer, b"\x00\x03\x00\x00" + bytes(8))  # not plain CDR
        await asyncio.sleep(10)

    with pytest.raises(Ros2MessageError, match="encapsulation 0003"):
        evclock.run(main(), source=source)


def test_a_bad_cyclonedds_configuration_is_reported(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CYCLONEDDS_URI", "<CycloneDDS><Domain><Nonsense/></Domain></CycloneDDS>")
    with pytest.raises(InvalidArgumentError, match=r"could not join ROS domain .*<Nonsense/>"):
        Ros2ClockPublisher()


def test_a_publisher_the_follower_cannot_accept_is_named_when_it_gives_up(
    plain: DomainParticipant,
) -> None:
    xcdr2_only = Qos(
        Policy.Reliability.BestEffort,
        Policy.History.KeepLast(1),
        Policy.DataRepresentation(use_xcdrv2_representation=True),
    )
    feed = PlainClock(plain, xcdr2_only)  # rmw_cyclonedds_cpp reads XCDR1 only, as evclock
    with repeating(feed, 1 * S, WAIT), pytest.raises(ClockLostError) as lost:
        Ros2ClockSource(startup_timeout=1.0)
    message = str(lost.value)
    assert "no /clock message arrived within startup_timeout=1 s" in message
    assert "publisher(s) of /clock offered a QoS this subscription" in message
    assert "DATA_REPRESENTATION" in message


def test_humble_publisher_announces_24_byte_gids_without_type_hashes(
    plain: DomainParticipant,
) -> None:
    info24 = participant_entities_info(24, "24")
    publications = BuiltinDataReader(plain, BuiltinTopicDcpsPublication)
    graph = graph_reader(plain, info24)
    with Ros2ClockPublisher(wire_format="humble") as publisher:
        found: list[Any] = []

        def discovered() -> bool:
            found.extend(p for p in publications.take(64) if p.topic_name == "rt/clock")
            return bool(found)

        wait_for(discovered, "the Humble writer")
        assert found[0].qos[Policy.Userdata] is None  # Humble has no type hashes
        infos: list[Any] = []
        wait_for(lambda: bool(infos.extend(take_all(graph)) or infos), "the announcement")
        (node,) = infos[-1].node_entities_info_seq
        assert [bytes(g.data) for g in node.writer_gid_seq] == [publisher.gid]
        assert len(publisher.gid) == 24
        assert publisher.gid == found[0].key.bytes + bytes(8)
