"""The rmw_zenoh /clock wire format, checked against independent implementations.

CDR payloads and RIHS01 type hashes are checked against ``rosbags`` (an independent pure-Python
implementation of ROS 2 message serialisation and type hashing) with the Humble, Jazzy and
Kilted message definitions; attachments against Zenoh's own serialiser (``zenoh.ext``), the
one rmw_zenoh_cpp uses through zenoh-cpp. No Zenoh session is opened here.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest

import evclock
from evclock import InvalidArgumentError, InvalidTypeError, MissingExtraError
from evclock.ros2 import (
    CLOCK_QOS,
    CLOCK_TYPE_HASH,
    HUMBLE_TYPE_HASH,
    WIRE_FORMATS,
    Ros2MessageError,
    clock_key_expr,
    decode_clock,
    encode_attachment,
    encode_clock,
    endpoint_token,
    entity_gid,
    node_token,
    resolve_domain_id,
)
from evclock.ros2._session import require
from evclock.ros2._url import source_options
from evclock.ros2._wire import check_type_hash, clock_subscription_key_expr, resolve_topic

# The independent implementations (rosbags: the test extra; zenoh: the ros2 extra) and xxhash
# (the ros2 extra): where one is missing, the tests that need it skip; the others still run.
try:
    from rosbags.typesys import Stores, get_typestore
except ModuleNotFoundError:
    HAVE_ROSBAGS = False
else:
    HAVE_ROSBAGS = True
try:
    from zenoh import ZBytes
    from zenoh.ext import Int64, z_deserialize, z_serialize
except ModuleNotFoundError:
    HAVE_ZENOH = False
else:
    HAVE_ZENOH = True
needs_rosbags = pytest.mark.skipif(not HAVE_ROSBAGS, reason="needs rosbags (evclock[test])")
needs_zenoh = pytest.mark.skipif(not HAVE_ZENOH, reason="needs evclock[ros2] (eclipse-zenoh)")
needs_xxhash = pytest.mark.skipif(
    importlib.util.find_spec("xxhash") is None, reason="needs evclock[ros2] (xxhash)"
)

DISTROS = ["ROS2_HUMBLE", "ROS2_JAZZY", "ROS2_KILTED"]
"""The rosbags stores (``Stores`` members) of the releases checked."""
TIMES_NS = [0, 1, 999_999_999, 1_000_000_000, 12_500_000 * 7 // 3, 1_700_000_000_123_456_789]
ZID = "83916b8aa32caecaa78991b721a40e0a"
GID = bytes(range(16))


@needs_rosbags
@pytest.mark.parametrize("store", DISTROS)
def test_type_hash_is_rosbags_rihs01_of_clock(store: str) -> None:
    typestore = get_typestore(Stores[store])
    assert typestore.hash_rihs01("rosgraph_msgs/msg/Clock") == CLOCK_TYPE_HASH


@needs_rosbags
@pytest.mark.parametrize("store", DISTROS)
@pytest.mark.parametrize("time_ns", TIMES_NS)
def test_payload_is_rosbags_cdr_of_clock(store: str, time_ns: int) -> None:
    typestore = get_typestore(Stores[store])
    clock_cls = typestore.types["rosgraph_msgs/msg/Clock"]
    time_cls = typestore.types["builtin_interfaces/msg/Time"]
    msg = evclock.Time(0, time_ns).to_msg()
    expected = typestore.serialize_cdr(
        clock_cls(clock=time_cls(sec=msg.sec, nanosec=msg.nanosec)), "rosgraph_msgs/msg/Clock"
    )
    assert encode_clock(time_ns) == bytes(expected)


@needs_rosbags
@pytest.mark.parametrize("little_endian", [True, False])
def test_decode_reads_rosbags_cdr_in_both_byte_orders(little_endian: bool) -> None:
    typestore = get_typestore(Stores.ROS2_JAZZY)
    clock_cls = typestore.types["rosgraph_msgs/msg/Clock"]
    time_cls = typestore.types["builtin_interfaces/msg/Time"]
    raw = typestore.serialize_cdr(
        clock_cls(clock=time_cls(sec=42, nanosec=7)),
        "rosgraph_msgs/msg/Clock",
        little_endian=little_endian,
    )
    assert decode_clock(bytes(raw)) == 42_000_000_007


@needs_rosbags
def test_time_to_msg_and_from_msg_interoperate_with_rosbags_messages() -> None:
    typestore = get_typestore(Stores.ROS2_KILTED)
    clock_cls = typestore.types["rosgraph_msgs/msg/Clock"]
    time_cls = typestore.types["builtin_interfaces/msg/Time"]
    t = evclock.Time(12, 345)
    raw = typestore.serialize_cdr(
        clock_cls(clock=time_cls(**vars_of(t.to_msg()))), "rosgraph_msgs/msg/Clock"
    )
    back = typestore.deserialize_cdr(bytes(raw), "rosgraph_msgs/msg/Clock")
    assert evclock.Time.from_msg(back.clock) == t  # type: ignore[attr-defined]
    assert decode_clock(bytes(raw)) == t.nanoseconds


def vars_of(msg: evclock.TimeMsg) -> dict[str, int]:
    return {"sec": msg.sec, "nanosec": msg.nanosec}


def test_key_expressions_per_release() -> None:
    assert clock_key_expr(0) == f"0/clock/rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}"
    for name in ("jazzy", "kilted", "rolling", "jazzy-keyed"):
        assert clock_key_expr(7, "/clock", WIRE_FORMATS[name]).endswith(CLOCK_TYPE_HASH)
    for name in ("humble", "humble-keyed"):
        assert clock_key_expr(3, "/sim/clock", WIRE_FORMATS[name]) == (
            "3/sim/clock/rosgraph_msgs::msg::dds_::Clock_/TypeHashNotSupported"
        )
    assert clock_subscription_key_expr(5, "clock") == "5/clock/rosgraph_msgs::msg::dds_::Clock_/*"


@needs_zenoh
def test_compact_attachment_is_zenoh_serialisation_of_seq_stamp_gid() -> None:
    data = encode_attachment(3, 1_700_000_000_000_000_001, GID, WIRE_FORMATS["jazzy"])
    expected = z_serialize((Int64(3), Int64(1_700_000_000_000_000_001), GID))
    assert data == expected.to_bytes()
    assert len(data) == 8 + 8 + 1 + 16
    seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], ZBytes(data))
    assert (int(seq), int(stamp), gid) == (3, 1_700_000_000_000_000_001, GID)


@needs_zenoh
def test_keyed_attachment_names_each_field() -> None:
    data = encode_attachment(9, 123, GID, WIRE_FORMATS["jazzy-keyed"])
    expected = z_serialize(
        ("sequence_number", Int64(9), "source_timestamp", Int64(123), "source_gid", GID)
    )
    assert data == expected.to_bytes()
    assert WIRE_FORMATS["humble-keyed"].attachment == "keyed"
    assert WIRE_FORMATS["humble"].attachment == "compact"


def test_attachment_needs_a_16_byte_gid() -> None:
    with pytest.raises(InvalidArgumentError, match="a publisher GID has 16 bytes, got 3"):
        encode_attachment(1, 1, b"abc")


def test_liveliness_tokens_follow_rmw_zenoh_layout() -> None:
    assert node_token(0, ZID, 0, "evclock_clock") == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/evclock_clock"
    token = endpoint_token("MP", 0, ZID, 0, 1, "evclock_clock", "/clock")
    assert token == (
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/evclock_clock/%clock/"
        f"rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}/2:2:,1:,:,:,,"
    )
    parts = token.split("/")
    assert len(parts) == 13  # admin space .. qos, as rmw_zenoh's parser requires
    assert all(parts)  # no empty part: rmw_zenoh rejects those
    qos = CLOCK_QOS.split(":")
    assert qos[0] == "2"  # BEST_EFFORT (rclcpp's ClockQoS)
    assert qos[1] == "2"  # VOLATILE, always written (see the per-release test below)
    assert qos[2] == ",1"  # KEEP_LAST (default, empty), depth 1
    humble = endpoint_token("MS", 0, ZID, 0, 1, "n", "/a/clock", WIRE_FORMATS["humble"])
    assert f"/%a%clock/rosgraph_msgs::msg::dds_::Clock_/{HUMBLE_TYPE_HASH}/" in humble


@needs_xxhash
def test_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    import xxhash

    token = endpoint_token("MP", 0, ZID, 0, 1, "evclock_clock", "/clock")
    digest = xxhash.xxh3_128(token.encode()).digest()  # canonical form: big-endian
    assert entity_gid(token) == digest[8:][::-1] + digest[:8][::-1]


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"\x00\x01\x00\x00\x01", "at least 12 bytes"),
        (b"\x00\x02\x00\x00" + bytes(8), "encapsulation 0002"),
        (b"\x00\x01\x00\x00\xff\xff\xff\xff" + bytes(4), "sec=-1"),
        (b"\x00\x01\x00\x00" + bytes(4) + (10**9).to_bytes(4, "little"), "nanosec=1000000000"),
    ],
)
def test_unreadable_payloads_are_reported(payload: bytes, message: str) -> None:
    with pytest.raises(Ros2MessageError, match=message):
        decode_clock(payload)


def test_unknown_type_hash_is_reported() -> None:
    check_type_hash(f"0/clock/rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}")
    check_type_hash("0/clock/rosgraph_msgs::msg::dds_::Clock_/TypeHashNotSupported")
    with pytest.raises(Ros2MessageError, match="type hash 'RIHS01_00'"):
        check_type_hash("0/clock/rosgraph_msgs::msg::dds_::Clock_/RIHS01_00")


def test_encode_rejects_bad_times() -> None:
    with pytest.raises(InvalidTypeError, match="time_ns must be an int, got float"):
        encode_clock(1.5)  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="does not fit a builtin_interfaces/Time"):
        encode_clock(2**31 * 10**9)


def test_domain_id_comes_from_the_argument_then_ros_domain_id(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert resolve_domain_id() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", " 42 ")
    assert resolve_domain_id() == 42
    assert resolve_domain_id(5) == 5
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    with pytest.raises(InvalidArgumentError, match="ROS_DOMAIN_ID must be an integer"):
        resolve_domain_id()
    with pytest.raises(InvalidArgumentError, match=r"must be in \[0, 232\], got 233"):
        resolve_domain_id(233)
    with pytest.raises(InvalidTypeError, match="domain_id must be an int, got bool"):
        resolve_domain_id(True)


def test_topic_names_resolve_under_the_root_namespace() -> None:
    assert resolve_topic("clock") == "/clock"
    assert resolve_topic("/world/clock") == "/world/clock"
    for bad in ("/clock/", "//clock", "/1clock", "/clo ck"):
        with pytest.raises(InvalidArgumentError, match="invalid ROS topic name"):
            resolve_topic(bad)


def test_unknown_wire_format_lists_the_known_ones() -> None:
    from evclock.ros2._wire import wire_format

    with pytest.raises(InvalidArgumentError, match=r"unknown rmw_zenoh wire format 'iron'.*"):
        wire_format("iron")


def test_clock_urls_map_to_source_options() -> None:
    assert source_options("ros2:///clock") == {
        "topic": "/clock",
        "connect": None,  # the source's default: rmw_zenoh's router on Zenoh, an error on DDS
        "listen": None,
        "startup_timeout": None,
        "silence_timeout": 10.0,
    }
    assert source_options("ros2:///clock?rmw=dds&wire_format=humble")["rmw"] == "dds"
    assert source_options("ros2:///clock?rmw=zenoh")["rmw"] == "zenoh"
    options = source_options(
        "ros2://127.0.0.1:7450/sim/clock?domain_id=3&silence_timeout=none&startup_timeout=2"
    )
    assert options["connect"] == ("tcp/127.0.0.1:7450",)
    assert options["topic"] == "/sim/clock"
    assert options["domain_id"] == 3
    assert options["silence_timeout"] is None
    assert options["startup_timeout"] == 2.0
    two = source_options("ros2:///clock?connect=unixsock-stream/a&connect=tcp/127.0.0.1:1")
    assert two["connect"] == ("unixsock-stream/a", "tcp/127.0.0.1:1")


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("ros2://", "names no topic"),
        ("ros2:///clock?rate=3", "unknown parameter"),
        ("ros2:///clock?domain_id=x", "domain_id in .* must be an integer"),
        ("ros2:///clock?silence_timeout=soon", "must be seconds or 'none'"),
        ("ros2://127.0.0.1:1/clock?connect=tcp/127.0.0.1:2", "both a host and connect="),
        ("ros2:///clock?domain_id=1&domain_id=2", "domain_id appears 2 times"),
    ],
)
def test_bad_clock_urls_are_reported(url: str, message: str) -> None:
    with pytest.raises(InvalidArgumentError, match=message):
        source_options(url)


def test_unknown_clock_url_scheme_is_reported() -> None:
    with pytest.raises(InvalidArgumentError, match=r"unsupported clock 'udp://x'.*ros2://"):
        evclock.run(_noop(), clock="udp://x")


async def _noop() -> None:
    return None


def test_clock_url_and_wall_time_conflict() -> None:
    with pytest.raises(InvalidArgumentError, match="use_sim_time resolved to False"):
        evclock.run(_noop(), clock="ros2:///clock", use_sim_time=False)


def test_clock_url_and_source_conflict(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EVCLOCK_CLOCK", "ros2:///clock")
    with pytest.raises(InvalidArgumentError, match="EVCLOCK_CLOCK='ros2:///clock'"):
        evclock.run(_noop(), source=evclock.sources.VirtualTimeSource())


def test_missing_extra_names_the_extra() -> None:
    with pytest.raises(MissingExtraError, match=r"pip install 'evclock\[ros2\]'"):
        require("evclock_no_such_module")


def test_import_evclock_does_not_import_zenoh_or_cyclonedds() -> None:
    code = (
        "import sys, evclock, evclock.ros2; "
        "print(sorted(m for m in ('zenoh', 'xxhash', 'rosbags', 'cyclonedds', 'numpy') "
        "if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]"


# -- the QoS field, release by release ---------------------------------------------------------
#
# Data derived from each rmw_zenoh_cpp release's own sources (not copied code): the defaults its
# ``src/detail/qos.cpp`` (``RMW_ZENOH_DEFAULT_*``) fills in, and its ``keyexpr_to_qos`` rule in
# ``src/detail/liveliness_utils.cpp``: a field written empty takes the reader's default, a
# written field is read as the rmw enum value (rmw/types.h: reliability 1 RELIABLE, 2
# BEST_EFFORT; durability 1 TRANSIENT_LOCAL, 2 VOLATILE; history 1 KEEP_LAST, 2 KEEP_ALL;
# liveliness 1 AUTOMATIC). Writers since #266 (Aug 2024, before the first release) omit the
# fields equal to their own defaults. The default durability changed with #521 (backported as
# #531 to Humble 0.1.2 and #530 to Jazzy 0.2.3).

_TL, _VOLATILE = 1, 2
_INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE: {sec, nsec}

RMW_ZENOH_RELEASES: dict[str, int] = {
    # release -> its default durability; every other default is the same in all of them:
    # KEEP_LAST, depth 42, RELIABLE, infinite deadline/lifespan/lease, AUTOMATIC liveliness.
    "humble 0.1.0": _TL,
    "humble 0.1.1": _TL,
    "humble 0.1.2": _VOLATILE,
    "humble 0.1.7": _VOLATILE,
    "jazzy 0.2.0": _TL,
    "jazzy 0.2.2": _TL,
    "jazzy 0.2.3": _VOLATILE,
    "jazzy 0.2.4": _VOLATILE,
    "kilted 0.6.0": _VOLATILE,
    "rolling 0.6.0": _VOLATILE,
}


def _defaults(release: str) -> dict[str, object]:
    return {
        "reliability": 1,
        "durability": RMW_ZENOH_RELEASES[release],
        "history": 1,
        "depth": 42,
        "deadline": _INFINITE,
        "lifespan": _INFINITE,
        "liveliness": 1,
        "lease": _INFINITE,
    }


def read_qos(field: str, release: str) -> dict[str, object]:
    """How ``release`` reads a token's QoS field (a model of its keyexpr_to_qos)."""
    d = _defaults(release)
    parts = field.split(":")
    assert len(parts) >= 6  # fewer: the reader rejects the token
    history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:6])
    assert min(len(history), len(deadline), len(lifespan)) >= 2
    assert len(liveliness) >= 3

    def num(text: str, default: object) -> object:
        return default if text == "" else int(text)

    return {
        "reliability": num(parts[0], d["reliability"]),
        "durability": num(parts[1], d["durability"]),
        "history": num(history[0], d["history"]),
        "depth": num(history[1], d["depth"]),
        "deadline": d["deadline"] if deadline == ["", ""] else tuple(map(int, deadline)),
        "lifespan": d["lifespan"] if lifespan == ["", ""] else tuple(map(int, lifespan)),
        "liveliness": num(liveliness[0], d["liveliness"]),
        "lease": d["lease"] if liveliness[1:] == ["", ""] else tuple(map(int, liveliness[1:])),
    }


def write_qos(qos: dict[str, object], release: str) -> str:
    """What ``release``'s own publisher writes for ``qos`` (a model of its qos_to_keyexpr)."""
    d = _defaults(release)

    def f(key: str, value: object) -> str:
        return "" if qos[key] == d[key] else str(value)

    def pair(key: str) -> str:
        value = qos[key]
        assert isinstance(value, tuple)
        default = d[key]
        assert isinstance(default, tuple)
        sec = "" if value[0] == default[0] else str(value[0])
        nsec = "" if value[1] == default[1] else str(value[1])
        return f"{sec},{nsec}"

    return (
        f"{f('reliability', qos['reliability'])}:{f('durability', qos['durability'])}:"
        f"{f('history', qos['history'])},{f('depth', qos['depth'])}:{pair('deadline')}:"
        f"{pair('lifespan')}:{f('liveliness', qos['liveliness'])},{pair('lease')}"
    )


CLOCK_QOS_PROFILE = {  # rclcpp::ClockQoS: KEEP_LAST 1, BEST_EFFORT, VOLATILE, the rest default
    "reliability": 2,
    "durability": _VOLATILE,
    "history": 1,
    "depth": 1,
    "deadline": _INFINITE,
    "lifespan": _INFINITE,
    "liveliness": 1,
    "lease": _INFINITE,
}


@pytest.mark.parametrize("release", sorted(RMW_ZENOH_RELEASES))
def test_every_release_reads_the_clock_qos_as_clockqos(release: str) -> None:
    assert read_qos(CLOCK_QOS, release) == CLOCK_QOS_PROFILE


@pytest.mark.parametrize("release", sorted(RMW_ZENOH_RELEASES))
@pytest.mark.parametrize(("reliable", "transient_local"), [(True, False), (False, True)])
def test_every_release_reads_other_qos_fields_as_written(
    release: str, reliable: bool, transient_local: bool
) -> None:
    from evclock.ros2._wire import qos_field

    read = read_qos(qos_field(reliable=reliable, transient_local=transient_local, depth=7), release)
    assert read["reliability"] == (1 if reliable else 2)
    assert read["durability"] == (_TL if transient_local else _VOLATILE)
    assert (read["history"], read["depth"]) == (1, 7)  # KEEP_LAST 7


@pytest.mark.parametrize(
    ("release", "native"),
    [
        # Golden: the QoS field a native rclcpp ClockQoS publisher of each release writes.
        ("humble 0.1.0", "2:2:,1:,:,:,,"),
        ("humble 0.1.1", "2:2:,1:,:,:,,"),
        ("humble 0.1.2", "2::,1:,:,:,,"),
        ("jazzy 0.2.0", "2:2:,1:,:,:,,"),
        ("jazzy 0.2.2", "2:2:,1:,:,:,,"),
        ("jazzy 0.2.3", "2::,1:,:,:,,"),
        ("kilted 0.6.0", "2::,1:,:,:,,"),
        ("rolling 0.6.0", "2::,1:,:,:,,"),
    ],
)
def test_golden_native_fields_and_the_old_encoding(release: str, native: str) -> None:
    assert write_qos(CLOCK_QOS_PROFILE, release) == native
    # evclock's field and the release's own read the same everywhere...
    assert read_qos(CLOCK_QOS, release) == read_qos(native, release)
    # ...whereas the field evclock wrote before (durability omitted) reads as TRANSIENT_LOCAL
    # where that was the default.
    old = read_qos("2::,1:,:,:,,", release)["durability"]
    assert old == RMW_ZENOH_RELEASES[release]


@pytest.mark.parametrize("fmt", sorted(WIRE_FORMATS))
def test_golden_publisher_tokens_per_wire_format(fmt: str) -> None:
    type_hash = HUMBLE_TYPE_HASH if fmt.startswith("humble") else CLOCK_TYPE_HASH
    assert endpoint_token("MP", 7, ZID, 3, 4, "sim", "/clock", WIRE_FORMATS[fmt]) == (
        f"@ros2_lv/7/{ZID}/3/4/MP/%/%/sim/%clock/rosgraph_msgs::msg::dds_::Clock_/"
        f"{type_hash}/2:2:,1:,:,:,,"
    )
