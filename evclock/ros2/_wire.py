"""The rmw_zenoh wire format of ROS 2 ``/clock``: bytes only, no Zenoh and no ROS needed.

Everything here follows rmw_zenoh_cpp's sources (``src/detail/liveliness_utils.cpp``,
``attachment_helpers.cpp``, ``rmw_publisher_data.cpp``, ``qos.cpp``) release by release:

* data key expression ``<domain_id>/<topic without its outer slashes>/<DDS type name>/<type
  hash>``, the type hash being ``RIHS01_<sha256>`` (Jazzy and later) or the literal
  ``TypeHashNotSupported`` (Humble, which has no type hashes);
* payload: plain CDR (XCDR1) with its 4-byte encapsulation header, for ``rosgraph_msgs/msg/
  Clock`` an ``int32 sec`` and a ``uint32 nanosec``;
* attachment (Zenoh's own serialisation, little-endian): ``int64 sequence_number``, ``int64
  source_timestamp`` (wall-clock ns since the epoch), then the 16-byte publisher GID as a
  sequence (LEB128 length 16, then the bytes). Early releases prefixed each field with its
  name as a string (the "keyed" layout, see :data:`WIRE_FORMATS`);
* liveliness tokens ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<type hash>/<qos>]`` with ``/`` inside names replaced by
  ``%``; an entity's GID is the XXH3-128 of its token (low 64 bits first).
"""

from __future__ import annotations

import dataclasses
import os
import re
import struct
from typing import Final, Literal

from evclock._errors import InvalidArgumentError, InvalidTypeError, Ros2MessageError

CLOCK_TYPE: Final = "rosgraph_msgs/msg/Clock"
"""The ROS 2 type of ``/clock`` messages."""
CLOCK_DDS_TYPE: Final = "rosgraph_msgs::msg::dds_::Clock_"
""":data:`CLOCK_TYPE`'s DDS-mangled name, as rmw_zenoh writes it into key expressions."""
CLOCK_TYPE_HASH: Final = "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564"
"""RIHS01 hash of rosgraph_msgs/msg/Clock (identical for Humble, Jazzy and Kilted definitions;
the tests recompute it with an independent implementation)."""
HUMBLE_TYPE_HASH: Final = "TypeHashNotSupported"
"""What rmw_zenoh_cpp on Humble writes where later releases put the type hash."""
ENV_ROS_DOMAIN_ID: Final = "ROS_DOMAIN_ID"
"""The environment variable ROS reads its domain id from."""
#: The largest domain id ROS 2 documents as valid.
MAX_DOMAIN_ID: Final = 232

_NS_PER_S: Final = 1_000_000_000
_CDR_BE: Final = b"\x00\x00"
_CDR_LE: Final = b"\x00\x01"
_GID_SIZE: Final = 16
CLOCK_QOS: Final = "2:2:,1:,:,:,,"
"""rclcpp's ClockQoS (BEST_EFFORT, VOLATILE, KEEP_LAST 1) in the QoS field of liveliness tokens.

rmw_zenoh writes only the fields that differ from its defaults and its readers fill an empty
field with *their* defaults: KEEP_LAST 42, RELIABLE, infinite deadline/lifespan/lease and
AUTOMATIC liveliness in every release, but the default durability changed between patch
releases - TRANSIENT_LOCAL in Humble 0.1.0-0.1.1 and Jazzy 0.2.0-0.2.2, VOLATILE from
Humble 0.1.2, Jazzy 0.2.3 and in every Kilted and Rolling release (0.6.0+). So the durability
is always written (``2``: VOLATILE), which every release reads as VOLATILE; reliability
(``2``: BEST_EFFORT) and depth (``1``) differ from every default and are written anyway.
Fields: ``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease
s,ns``."""

_NAME_SEGMENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_FRAME_PREFIX = re.compile(r"(?:[A-Za-z0-9_]+/)*[A-Za-z0-9_]*")


@dataclasses.dataclass(frozen=True)
class WireFormat:
    """One distribution's wire variant: on Zenoh, how rmw_zenoh_cpp writes the type hash and
    the attachment; on DDS, only the distribution counts (Humble: no type hashes, 24-byte
    graph GIDs; the others: RIHS01 hashes, 16-byte GIDs).

    :ivar name: the variant's name (``"jazzy"``, ``"humble"``).
    :ivar type_hash: the type-hash segment of key expressions and liveliness tokens.
    :ivar attachment: ``"compact"``: int64, int64, GID; ``"keyed"``: each preceded by its
        field name.
    :ivar releases: the rmw_zenoh_cpp releases that speak it (for messages and the docs).
    """

    name: str
    #: The type-hash segment of key expressions and liveliness tokens.
    type_hash: str
    #: ``"compact"``: int64, int64, GID; ``"keyed"``: each preceded by its field name.
    attachment: Literal["compact", "keyed"]
    #: The rmw_zenoh_cpp releases that speak it (for messages and the docs).
    releases: str


WIRE_FORMATS: Final[dict[str, WireFormat]] = {
    "jazzy": WireFormat(
        "jazzy",
        CLOCK_TYPE_HASH,
        "compact",
        "Jazzy 0.2.4+, Kilted 0.6.x, Rolling 0.6.0+ (and Lyrical)",
    ),
    "kilted": WireFormat("kilted", CLOCK_TYPE_HASH, "compact", "Kilted 0.6.x"),
    "rolling": WireFormat("rolling", CLOCK_TYPE_HASH, "compact", "Rolling 0.6.0+"),
    "humble": WireFormat("humble", HUMBLE_TYPE_HASH, "compact", "Humble 0.1.2+"),
    "jazzy-keyed": WireFormat(
        "jazzy-keyed", CLOCK_TYPE_HASH, "keyed", "Jazzy 0.2.0-0.2.3, Rolling 0.3.0-0.5.0"
    ),
    "humble-keyed": WireFormat("humble-keyed", HUMBLE_TYPE_HASH, "keyed", "Humble 0.1.0-0.1.1"),
}
"""The wire variants, by name. ``jazzy`` (the default) is also what Kilted and Rolling speak."""
DEFAULT_WIRE_FORMAT: Final = "jazzy"
"""The wire variant a publisher writes unless told (``--ros2-wire-format``, ``wire_format=``)."""


def wire_format(name: object) -> WireFormat:
    """The :class:`WireFormat` called ``name`` (see :data:`WIRE_FORMATS`)."""
    if isinstance(name, WireFormat):
        return name
    if not isinstance(name, str):
        raise InvalidTypeError(f"wire_format must be a name (str), got {type(name).__name__}")
    try:
        return WIRE_FORMATS[name]
    except KeyError:
        known = ", ".join(f"{n} ({f.releases})" for n, f in WIRE_FORMATS.items())
        raise InvalidArgumentError(
            f"unknown rmw_zenoh wire format {name!r}; choose one of: {known}"
        ) from None


def resolve_domain_id(domain_id: object = None) -> int:
    """The ROS domain id: the argument, else ``ROS_DOMAIN_ID`` (as ROS reads it), else 0.

    :param domain_id: an int in [0, 232], or None to read the environment.
    :returns: the domain id.
    :raises InvalidTypeError: ``domain_id`` is neither an int nor None.
    :raises InvalidArgumentError: the id (given or from ``ROS_DOMAIN_ID``) is out of range or
        not an integer.
    """
    if domain_id is None:
        raw = os.environ.get(ENV_ROS_DOMAIN_ID, "").strip()
        if not raw:
            return 0
        if not raw.isdigit():
            raise InvalidArgumentError(
                f"{ENV_ROS_DOMAIN_ID} must be an integer in [0, {MAX_DOMAIN_ID}], got {raw!r}"
            )
        domain_id = int(raw)
    if isinstance(domain_id, bool) or not isinstance(domain_id, int):
        raise InvalidTypeError(f"domain_id must be an int, got {type(domain_id).__name__}")
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise InvalidArgumentError(
            f"a ROS domain id must be in [0, {MAX_DOMAIN_ID}], got {domain_id}"
        )
    return domain_id


def resolve_topic(topic: object) -> str:
    """A fully qualified ROS topic name: relative names resolve under the root namespace."""
    if not isinstance(topic, str):
        raise InvalidTypeError(f"topic must be a str such as '/clock', got {type(topic).__name__}")
    name = topic if topic.startswith("/") else "/" + topic
    segments = name[1:].split("/")
    if not all(_NAME_SEGMENT.fullmatch(s) for s in segments):
        raise InvalidArgumentError(
            f"invalid ROS topic name {topic!r}: use segments of letters, digits and '_' "
            "(not starting with a digit) separated by single '/', e.g. '/clock'"
        )
    return name


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def clock_key_expr(domain_id: int, topic: str = "/clock", wire: WireFormat | None = None) -> str:
    """The Zenoh key expression rmw_zenoh publishes ``topic`` (a Clock topic) on.

    :param domain_id: the ROS domain id.
    :param topic: the Clock topic (a relative name resolves under the root namespace).
    :param wire: the wire format (default: Jazzy's).
    :returns: the key expression, such as ``0/clock/rosgraph_msgs::msg::dds_::Clock_/RIHS01_...``.
    :raises InvalidArgumentError: ``topic`` is not a valid ROS topic name.
    :raises InvalidTypeError: ``topic`` is not a string.
    """
    fmt = wire or WIRE_FORMATS[DEFAULT_WIRE_FORMAT]
    return f"{domain_id}/{resolve_topic(topic)[1:]}/{CLOCK_DDS_TYPE}/{fmt.type_hash}"


def clock_subscription_key_expr(domain_id: int, topic: str = "/clock") -> str:
    """The key expression a follower subscribes to: any type hash, checked on arrival."""
    return f"{domain_id}/{resolve_topic(topic)[1:]}/{CLOCK_DDS_TYPE}/*"


def check_type_hash(key_expr: str) -> None:
    """Refuse a sample whose key names a Clock type hash evclock does not know."""
    type_hash = key_expr.rsplit("/", 1)[-1]
    if type_hash not in (CLOCK_TYPE_HASH, HUMBLE_TYPE_HASH):
        raise Ros2MessageError(
            f"a /clock sample arrived on {key_expr!r} with type hash {type_hash!r}, which is "
            f"neither rosgraph_msgs/msg/Clock's ({CLOCK_TYPE_HASH}) nor Humble's "
            f"{HUMBLE_TYPE_HASH!r}; the publisher uses another Clock definition"
        )


# ------------------------------------------------------------------------------- payload


def encode_clock(time_ns: int) -> bytes:
    """A ``rosgraph_msgs/msg/Clock`` message at ``time_ns``, CDR little-endian with header.

    :param time_ns: the time, in integer nanoseconds.
    :returns: the serialised message.
    :raises InvalidTypeError: ``time_ns`` is not an int.
    :raises InvalidArgumentError: the time does not fit a ``builtin_interfaces/Time``.
    """
    if isinstance(time_ns, bool) or not isinstance(time_ns, int):
        raise InvalidTypeError(f"time_ns must be an int, got {type(time_ns).__name__}")
    sec, nanosec = divmod(time_ns, _NS_PER_S)
    if not 0 <= sec <= 0x7FFFFFFF:
        raise InvalidArgumentError(
            f"{time_ns} ns does not fit a builtin_interfaces/Time (sec must be an int32 >= 0)"
        )
    return _CDR_LE + b"\x00\x00" + struct.pack("<iI", sec, nanosec)


def decode_clock(payload: bytes) -> int:
    """The time in ns of a CDR ``rosgraph_msgs/msg/Clock`` message (either byte order).

    :param payload: the serialised message, CDR header included.
    :returns: the message's time, in integer nanoseconds.
    :raises Ros2MessageError: the payload is too short, not plain CDR, or holds an invalid time.
    """
    if len(payload) < 12:
        raise Ros2MessageError(
            f"a /clock message must hold at least 12 bytes (CDR header, sec, nanosec), got "
            f"{len(payload)}: {bytes(payload[:16]).hex()}"
        )
    header = bytes(payload[:2])
    if header == _CDR_LE:
        sec, nanosec = struct.unpack_from("<iI", payload, 4)
    elif header == _CDR_BE:
        sec, nanosec = struct.unpack_from(">iI", payload, 4)
    else:
        raise Ros2MessageError(
            f"a /clock message has encapsulation {header.hex()}; evclock reads plain CDR "
            "(0000 big-endian, 0001 little-endian) as rmw_zenoh sends it"
        )
    if sec < 0 or nanosec >= _NS_PER_S:
        raise Ros2MessageError(
            f"a /clock message holds an invalid time sec={sec}, nanosec={nanosec}; sim time "
            "must be non-negative with nanosec < 1000000000"
        )
    return int(sec) * _NS_PER_S + int(nanosec)


# ---------------------------------------------------------------------------- attachment


def _zenoh_str(text: str) -> bytes:
    data = text.encode()
    return _leb128(len(data)) + data


def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def encode_attachment(
    sequence_number: int, source_timestamp: int, gid: bytes, wire: WireFormat | None = None
) -> bytes:
    """The attachment rmw_zenoh puts on every sample (see the module docstring).

    :param sequence_number: the sample's sequence number (int64).
    :param source_timestamp: the publication time in wall nanoseconds (int64).
    :param gid: the publisher's 16-byte GID.
    :param wire: the wire format (default: Jazzy's).
    :returns: the attachment bytes.
    :raises InvalidArgumentError: ``gid`` is not 16 bytes long.
    """
    if len(gid) != _GID_SIZE:
        raise InvalidArgumentError(f"a publisher GID has 16 bytes, got {len(gid)}")
    fmt = wire or WIRE_FORMATS[DEFAULT_WIRE_FORMAT]
    seq = struct.pack("<q", sequence_number)
    stamp = struct.pack("<q", source_timestamp)
    gid_field = _leb128(_GID_SIZE) + bytes(gid)
    if fmt.attachment == "compact":
        return seq + stamp + gid_field
    return (
        _zenoh_str("sequence_number")
        + seq
        + _zenoh_str("source_timestamp")
        + stamp
        + _zenoh_str("source_gid")
        + gid_field
    )


# ---------------------------------------------------------------------------- liveliness


def node_token(domain_id: int, zid: str, node_id: int, node_name: str) -> str:
    """The liveliness token of a node in the root namespace and the default enclave.

    :param domain_id: the ROS domain id.
    :param zid: the Zenoh session id.
    :param node_id: the node's id within the session.
    :param node_name: the node's name.
    :returns: the token's key expression.
    """
    return f"@ros2_lv/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/%/{node_name}"


def endpoint_token(
    kind: Literal["MP", "MS"],
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    node_name: str,
    topic: str,
    wire: WireFormat | None = None,
    *,
    type_name: str = CLOCK_DDS_TYPE,
    type_hash: str | None = None,
    qos: str = CLOCK_QOS,
) -> str:
    """The liveliness token of a publisher (``MP``) or subscription (``MS``), of a Clock topic
    unless ``type_name``, ``type_hash`` and ``qos`` say otherwise.

    :param kind: ``"MP"`` for a publisher, ``"MS"`` for a subscription.
    :param domain_id: the ROS domain id.
    :param zid: the Zenoh session id.
    :param node_id: the id of the node the endpoint belongs to.
    :param entity_id: the endpoint's id within the session.
    :param node_name: the name of the node the endpoint belongs to.
    :param topic: the Clock topic.
    :param wire: the wire format (default: Jazzy's).
    :param type_name: the DDS type name (default Clock's).
    :param type_hash: the type's RIHS01 hash (default: the wire format's Clock hash, or
        Humble's ``TypeHashNotSupported``).
    :param qos: the QoS field (default :data:`CLOCK_QOS`; see :func:`qos_field`).
    :returns: the token's key expression.
    :raises InvalidArgumentError: ``topic`` is not a valid ROS topic name.
    :raises InvalidTypeError: ``topic`` is not a string.
    """
    fmt = wire or WIRE_FORMATS[DEFAULT_WIRE_FORMAT]
    hashed = fmt.type_hash if type_hash is None or fmt.type_hash == HUMBLE_TYPE_HASH else type_hash
    return (
        f"@ros2_lv/{domain_id}/{zid}/{node_id}/{entity_id}/{kind}/%/%/{node_name}/"
        f"{_mangle(resolve_topic(topic))}/{type_name}/{hashed}/{qos}"
    )


def qos_field(*, reliable: bool, transient_local: bool, depth: int) -> str:
    """A liveliness token's QoS field for KEEP_LAST ``depth`` with this reliability and
    durability, the rest default (see :data:`CLOCK_QOS`): reliability and durability are
    always written (their defaults changed between releases), history left to KEEP_LAST,
    the default of every release."""
    return f"{1 if reliable else 2}:{1 if transient_local else 2}:,{depth}:,:,:,,"


def entity_gid(token: str) -> bytes:
    """An entity's GID as rmw_zenoh derives it: XXH3-128 of its token, low 64 bits first.

    :param token: the entity's liveliness token (see :func:`endpoint_token`).
    :returns: the 16-byte GID.
    :raises MissingExtraError: the ``ros2`` extra (xxhash) is missing.
    """
    from evclock.ros2._session import require

    xxhash = require("xxhash")
    digest: int = xxhash.xxh3_128_intdigest(token.encode())
    return digest.to_bytes(_GID_SIZE, "little")


def check_node_name(name: object) -> str:
    """A valid ROS node name (one segment)."""
    if not isinstance(name, str):
        raise InvalidTypeError(f"node_name must be a str, got {type(name).__name__}")
    if not _NAME_SEGMENT.fullmatch(name):
        raise InvalidArgumentError(
            f"invalid ROS node name {name!r}: letters, digits and '_', not starting with a digit"
        )
    return name


def check_frame_prefix(prefix: object) -> str:
    """A TF frame prefix as robot_state_publisher's ``frame_prefix`` takes it (prepended to
    each link name as is, e.g. ``robot1/``): letters, digits, ``_`` and ``/`` (not first and
    never doubled: tf2 refuses frame ids that start with ``/``), or empty for none."""
    if not isinstance(prefix, str):
        raise InvalidTypeError(f"frame_prefix must be a str, got {type(prefix).__name__}")
    if not _FRAME_PREFIX.fullmatch(prefix):
        raise InvalidArgumentError(
            f"invalid frame prefix {prefix[:80]!r}: letters, digits, '_' and '/' (not first, "
            "not doubled), e.g. 'robot1/'"
        )
    return prefix
