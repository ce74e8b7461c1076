"""ROS 2 message types from a maintained definition library (rosbags' type stores): CDR payloads,
DDS type names and RIHS01 type hashes, per distribution. No middleware here.

rmw_zenoh and the DDS rmw implementations carry the same payload: the message in plain CDR
(XCDR1) with its 4-byte encapsulation header, which rosbags writes and reads.
"""

from __future__ import annotations

import functools
import re
from typing import Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, Ros2MessageError
from evclock.ros2._session import require
from evclock.ros2._wire import HUMBLE_TYPE_HASH, WireFormat

#: The rosbags type store holding each distribution's message definitions, by wire format.
_STORES: Final = {
    "humble": "ros2_humble",
    "humble-keyed": "ros2_humble",
    "jazzy": "ros2_jazzy",
    "jazzy-keyed": "ros2_jazzy",
    "kilted": "ros2_kilted",
    "rolling": "latest",
}
_ROS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9]*)")
#: How many payload bytes an error message quotes (peer input: never the whole sample).
QUOTE_BYTES: Final = 32


def store_name(wire: WireFormat) -> str:
    """The rosbags type store of ``wire``'s distribution."""
    return _STORES[wire.name]


@functools.cache
def typestore(name: str) -> Any:
    """rosbags' type store ``name`` (``ros2_jazzy``...), loaded once."""
    typesys = require("rosbags.typesys")
    return typesys.get_typestore(typesys.Stores(name))


def check_ros_type(msgtype: object, wire: WireFormat) -> str:
    """``msgtype`` as ROS names it (``sensor_msgs/msg/Imu``), known to ``wire``'s distribution."""
    if not isinstance(msgtype, str):
        raise InvalidTypeError(
            f"a message type is a str such as 'sensor_msgs/msg/Imu', got {type(msgtype).__name__}"
        )
    if not _ROS_TYPE.fullmatch(msgtype):
        raise InvalidArgumentError(
            f"{msgtype[:80]!r} is not a ROS 2 message type name; write PACKAGE/msg/NAME, "
            "e.g. sensor_msgs/msg/Imu"
        )
    if msgtype not in typestore(store_name(wire)).fielddefs:
        raise InvalidArgumentError(
            f"{msgtype} is not a message type of ROS 2 {wire.name} as rosbags defines it; "
            "check the name (PACKAGE/msg/NAME)"
        )
    return msgtype


def dds_type_name(msgtype: str) -> str:
    """The DDS type name rosidl gives a ROS message: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``
    (rosidl_typesupport_fastrtps and rmw_cyclonedds_cpp's ``create_type_name``)."""
    package, _, name = msgtype.split("/")
    return f"{package}::msg::dds_::{name}_"


def type_hash(msgtype: str, wire: WireFormat) -> str | None:
    """The RIHS01 hash of ``msgtype`` in ``wire``'s distribution; None on Humble (no hashes)."""
    if wire.type_hash == HUMBLE_TYPE_HASH:
        return None
    hashed: str = typestore(store_name(wire)).hash_rihs01(msgtype)
    return hashed


def serialize(message: Any, msgtype: str, wire: WireFormat) -> bytes:
    """``message`` (a rosbags message object) as little-endian CDR with its header."""
    data = typestore(store_name(wire)).serialize_cdr(message, msgtype)
    return bytes(data)


def deserialize(payload: bytes, msgtype: str, wire: WireFormat) -> Any:
    """The rosbags message object a CDR payload (peer input) holds.

    :raises Ros2MessageError: the payload is not a valid ``msgtype`` message.
    """
    try:
        return typestore(store_name(wire)).deserialize_cdr(payload, msgtype)
    except Exception as exc:  # rosbags raises struct, index, value and unicode errors alike
        raise Ros2MessageError(
            f"a {msgtype} message of {len(payload)} bytes could not be read ({type(exc).__name__}"
            f"); it starts {bytes(payload[:QUOTE_BYTES]).hex()}"
        ) from None


def message_class(msgtype: str, wire: WireFormat) -> Any:
    """The rosbags class building a ``msgtype`` message (``cls(field=...)``)."""
    return typestore(store_name(wire)).types[msgtype]
