"""ROS 2 over DDS with Eclipse Cyclone DDS: one domain participant standing for one ROS 2 node.

What a node on a DDS rmw puts on the wire, as rmw_cyclonedds_cpp writes it (``src/rmw_node.cpp``
at tag 2.2.2, Jazzy; 1.3.4 for Humble) with rmw_dds_common's graph messages:

* the participant's USER_DATA ``enclave=/;`` (``rmw_context_impl_s::init``);
* a topic ``/clock`` is the DDS topic ``rt/clock`` (``ROS_TOPIC_PREFIX``, ``make_fqtopic``) of
  type ``rosgraph_msgs::msg::dds_::Clock_``; samples are XCDR1 (plain CDR, ``serdata.cpp``:
  ``allowed_data_representation = DDS_DATA_REPRESENTATION_FLAG_XCDR1``);
* every reader and writer carries USER_DATA ``typehash=RIHS01_<hex>;`` from Jazzy on
  (``create_readwrite_qos`` with rmw_dds_common's ``encode_type_hash_for_user_data_qos``,
  ``src/qos.cpp`` at 3.1.0), and nothing on Humble;
* writers do not auto-dispose (``dds_qset_writer_data_lifecycle(qos, false)``);
* the node is announced on ``ros_discovery_info`` (no ``rt/`` prefix:
  ``avoid_ros_namespace_conventions``), type ``rmw_dds_common::msg::dds_::
  ParticipantEntitiesInfo_``, reliable, transient-local, keep-last 1: the participant's GID
  and, per node, its name, namespace and its readers' and writers' GIDs. A GID is the entity's
  16-byte DDS GUID (``convert_guid_to_gid``), zero-padded to 24 bytes on Humble, whose
  ``rmw_dds_common/msg/Gid`` is ``char[24]`` (``char[16]`` from 2.0.0/Iron on).

Samples cross this module as raw CDR bytes (the same bytes rmw_zenoh carries): evclock writes
and reads them with the binding's raw calls (``ddspy_write``/``ddspy_take``, what its
``DataWriter.write`` and ``DataReader.take`` do around the Python (de)serialiser), so peer
bytes are only ever read by evclock's own bounded decoders. Cyclone DDS reads its own
configuration from ``CYCLONEDDS_URI`` (interfaces, peers, multicast), as under ROS.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import threading
from collections.abc import Callable
from typing import Any, Final

from evclock._errors import InvalidArgumentError, Ros2MessageError
from evclock.outside._threads import mark_internal
from evclock.ros2._session import require
from evclock.ros2._types import dds_type_name, store_name, type_hash, typestore
from evclock.ros2._wire import HUMBLE_TYPE_HASH, WireFormat

logger = logging.getLogger("evclock.ros2")

ROS_TOPIC_PREFIX: Final = "rt"
"""The DDS topic prefix of ROS topics (rmw_dds_common / rmw_cyclonedds_cpp ``ROS_TOPIC_PREFIX``)."""
DISCOVERY_TOPIC: Final = "ros_discovery_info"
"""The DDS topic on which every ROS 2 participant announces its nodes and their endpoints."""
DISCOVERY_TYPE: Final = "rmw_dds_common/msg/ParticipantEntitiesInfo"
"""The type of :data:`DISCOVERY_TOPIC`."""
ENCLAVE_USER_DATA: Final = b"enclave=/;"
"""A participant's USER_DATA in the default (root) security enclave."""
#: How many samples a reader takes per wake-up, and how long its thread waits between checks
#: of the reader's status (wall ns): the thread also notices its close within that time.
_TAKE_BATCH: Final = 64
_WAIT_NS: Final = 200_000_000
_JOIN_TIMEOUT: Final = 5.0
#: QoS policy ids as Cyclone DDS numbers them (``dds_qos_policy_id_t``) in last_policy_id.
_POLICY_NAMES: Final = {
    2: "DURABILITY",
    4: "DEADLINE",
    5: "LATENCY_BUDGET",
    6: "OWNERSHIP",
    8: "LIVELINESS",
    11: "RELIABILITY",
    12: "DESTINATION_ORDER",
    24: "TYPE_CONSISTENCY_ENFORCEMENT",
    25: "DATA_REPRESENTATION",
}


@dataclasses.dataclass(frozen=True)
class DdsQos:
    """The QoS of one ROS 2 endpoint, as rmw_cyclonedds_cpp's ``create_readwrite_qos`` maps it.

    :ivar reliable: RELIABLE (True) or BEST_EFFORT.
    :ivar transient_local: TRANSIENT_LOCAL (True) or VOLATILE durability.
    :ivar depth: KEEP_LAST depth.
    """

    reliable: bool
    transient_local: bool
    depth: int

    def describe(self) -> str:
        """``best effort, volatile, keep last 1`` style."""
        return (
            f"{'reliable' if self.reliable else 'best effort'}, "
            f"{'transient local' if self.transient_local else 'volatile'}, keep last {self.depth}"
        )


CLOCK_PUBLISHER_QOS: Final = DdsQos(reliable=False, transient_local=False, depth=1)
"""rclcpp's ``ClockQoS`` (``rclcpp/src/rclcpp/qos.cpp`` at 28.1.0, Jazzy): KeepLast(1) over
``rmw_qos_profile_sensor_data``, best effort and volatile."""
CLOCK_SUBSCRIPTION_QOS: Final = CLOCK_PUBLISHER_QOS
"""rclcpp's TimeSource subscribes to ``/clock`` with ``ClockQoS`` too (``time_source.hpp`` at
28.1.0): a best-effort reader, which every publisher feeds whatever its reliability."""
DISCOVERY_QOS: Final = DdsQos(reliable=True, transient_local=True, depth=1)
"""``ros_discovery_info``'s writer QoS (``rmw_context_impl_s::init``)."""


def ros_topic(topic: str) -> str:
    """The DDS topic of a fully qualified ROS topic: ``/clock`` -> ``rt/clock``."""
    return ROS_TOPIC_PREFIX + topic


def gid_size(wire: WireFormat) -> int:
    """The size of an ``rmw_dds_common/msg/Gid`` in ``wire``'s distribution: 24 on Humble."""
    return 24 if wire.type_hash == HUMBLE_TYPE_HASH else 16


def user_data(msgtype: str, wire: WireFormat) -> bytes:
    """An endpoint's USER_DATA: ``typehash=RIHS01_...;`` (empty on Humble)."""
    hashed = type_hash(msgtype, wire)
    return b"" if hashed is None else f"typehash={hashed};".encode()


def describe_policy(policy_id: int) -> str:
    """A DDS QoS policy's name for messages (``RELIABILITY``)."""
    return _POLICY_NAMES.get(policy_id, f"policy {policy_id}")


# ---------------------------------------------------------------------------- types


_BASE_TYPES: Final = {
    "bool": "bool",
    "byte": "byte",
    "char": "uint8",  # ROS char is an unsigned 8-bit integer (rosidl's IDL mapping)
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}


@functools.cache
def idl_type(msgtype: str, store: str) -> Any:
    """A Cyclone DDS type named as rosidl names ``msgtype`` (``pkg::msg::dds_::Name_``), with
    its fields from rosbags' store ``store``: what DDS discovery announces and matches on."""
    idl = require("cyclonedds.idl")
    types = require("cyclonedds.idl.types")
    _consts, fields = typestore(store).fielddefs[msgtype]

    def annotation(desc: tuple[Any, Any]) -> Any:
        kind, detail = desc
        kind_name = getattr(kind, "name", str(kind))
        if kind_name == "BASE":
            name, bound = detail
            if name == "string" or name == "wstring":
                return types.bounded_str[bound] if bound else str
            return bool if name == "bool" else getattr(types, _BASE_TYPES[name])
        if kind_name == "NAME":
            return idl_type(detail, store)
        inner, count = detail
        if kind_name == "ARRAY":
            return types.array[annotation(inner), count]
        return (
            types.sequence[annotation(inner), count] if count else types.sequence[annotation(inner)]
        )

    annotations = {name: annotation(desc) for name, desc in fields}
    class_name = msgtype.replace("/", "__") + "__" + store
    return idl.make_idl_struct(class_name, dds_type_name(msgtype), annotations)


# ---------------------------------------------------------------------------- the node


class DdsNode:
    """A DDS domain participant announcing one ROS 2 node, with raw-CDR writers and readers.

    :param domain_id: the ROS domain id (the DDS domain).
    :param node_name: the ROS node's name (root namespace).
    :param wire: the distribution spoken (GID size, type hashes, message definitions).
    """

    def __init__(self, domain_id: int, node_name: str, wire: WireFormat) -> None:
        self._dds = _binding()
        self._wire = wire
        self._store = store_name(wire)
        self._node_name = node_name
        self._closed = False
        self._lock = threading.Lock()
        self._readers: list[DdsReader] = []
        self._writers: list[DdsWriter] = []
        qos_mod = self._dds.qos
        try:
            self._participant = self._dds.domain.DomainParticipant(
                domain_id, qos=qos_mod.Qos(qos_mod.Policy.Userdata(ENCLAVE_USER_DATA))
            )
        except self._dds.core.DDSException as exc:
            uri = os.environ.get("CYCLONEDDS_URI", "")
            raise InvalidArgumentError(
                f"Cyclone DDS could not join ROS domain {domain_id} ({exc}); check its "
                f"configuration, CYCLONEDDS_URI={uri[:200]!r} (unset: Cyclone's defaults)"
            ) from None
        try:
            self._publisher = self._dds.pub.Publisher(self._participant)
            self._subscriber = self._dds.sub.Subscriber(self._participant)
            self._discovery = self._raw_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE, DISCOVERY_QOS)
            self._announce()
        except BaseException:
            participant, self._participant = self._participant, None
            _delete(participant)
            raise

    @property
    def gid(self) -> bytes:
        """The participant's GID (its GUID, zero-padded on Humble)."""
        return self.entity_gid(self._participant)

    @property
    def node_name(self) -> str:
        """The announced node's name."""
        return self._node_name

    def entity_gid(self, entity: Any) -> bytes:
        """A DDS entity's GID as rmw_cyclonedds_cpp derives it (``convert_guid_to_gid``)."""
        guid: bytes = entity.guid.bytes
        return guid.ljust(gid_size(self._wire), b"\x00")

    def _raw_writer(self, topic: str, msgtype: str, qos: DdsQos) -> Any:
        dds = self._dds
        data_type = idl_type(msgtype, self._store)
        dds_topic = dds.topic.Topic(self._participant, topic, data_type)
        return dds.pub.DataWriter(self._publisher, dds_topic, qos=self._qos(qos, msgtype, True))

    def _qos(self, qos: DdsQos, msgtype: str, writer: bool) -> Any:
        policy = self._dds.qos.Policy
        policies = [
            policy.Reliability.Reliable(max_blocking_time=self._dds.util.duration(seconds=0.1))
            if qos.reliable
            else policy.Reliability.BestEffort,
            policy.Durability.TransientLocal if qos.transient_local else policy.Durability.Volatile,
            policy.History.KeepLast(qos.depth),
            policy.DataRepresentation(use_cdrv0_representation=True),
            policy.Userdata(user_data(msgtype, self._wire)),
        ]
        if writer:
            policies.append(policy.WriterDataLifecycle(autodispose=False))
        if qos.transient_local:
            policies.append(
                policy.DurabilityService(
                    cleanup_delay=0,
                    history=policy.History.KeepLast(qos.depth),
                    max_samples=-1,
                    max_instances=-1,
                    max_samples_per_instance=-1,
                )
            )
        return self._dds.qos.Qos(*policies)

    def writer(self, topic: str, msgtype: str, qos: DdsQos) -> DdsWriter:
        """A writer of the fully qualified ROS ``topic`` of type ``msgtype``, announced."""
        writer = DdsWriter(self, self._raw_writer(ros_topic(topic), msgtype, qos), topic, qos)
        with self._lock:
            self._writers.append(writer)
        self._announce()
        return writer

    def reader(
        self,
        topic: str,
        msgtype: str,
        qos: DdsQos,
        deliver: Callable[[bytes], None],
        fail: Callable[[BaseException], None],
    ) -> DdsReader:
        """A reader of ``topic`` whose thread hands each sample's CDR bytes to ``deliver``
        (on its own thread) and a failure to ``fail``; announced in the graph."""
        dds = self._dds
        data_type = idl_type(msgtype, self._store)
        dds_topic = dds.topic.Topic(self._participant, ros_topic(topic), data_type)
        raw = dds.sub.DataReader(self._subscriber, dds_topic, qos=self._qos(qos, msgtype, False))
        reader = DdsReader(self, raw, topic, qos, deliver, fail)
        with self._lock:
            self._readers.append(reader)
        self._announce()
        reader.start()
        return reader

    def graph_message(self) -> Any:
        """The ``ParticipantEntitiesInfo`` this node announces (a rosbags message)."""
        store = typestore(self._store)
        gid_cls = store.types["rmw_dds_common/msg/Gid"]
        node_cls = store.types["rmw_dds_common/msg/NodeEntitiesInfo"]
        info_cls = store.types["rmw_dds_common/msg/ParticipantEntitiesInfo"]
        numpy = require("numpy")

        def gid(data: bytes) -> Any:
            return gid_cls(data=numpy.frombuffer(data, dtype=numpy.uint8).copy())

        with self._lock:
            readers = [gid(r.gid) for r in self._readers if not r.closed]
            writers = [gid(w.gid) for w in self._writers if not w.closed]
        node = node_cls(
            node_namespace="/",
            node_name=self._node_name,
            reader_gid_seq=readers,
            writer_gid_seq=writers,
        )
        return info_cls(gid=gid(self.gid), node_entities_info_seq=[node])

    def _announce(self) -> None:
        payload = typestore(self._store).serialize_cdr(self.graph_message(), DISCOVERY_TYPE)
        write_raw(self._discovery, bytes(payload))

    def forget(self, endpoint: DdsReader | DdsWriter) -> None:
        """Withdraw a closed endpoint from the graph announcement."""
        if not self._closed:
            self._announce()

    def close(self) -> None:
        """Close every endpoint and the participant (idempotent)."""
        if self._closed:
            return
        with self._lock:
            endpoints: list[DdsReader | DdsWriter] = [*self._readers, *self._writers]
        for endpoint in endpoints:
            endpoint.close()
        self._closed = True
        participant, self._participant = self._participant, None
        if participant is not None:
            # Deleting the participant deletes its children and tells its peers at once.
            _delete(participant)


def _binding() -> Any:
    """The Cyclone DDS modules evclock uses, imported together (or one MissingExtraError)."""

    class Binding:
        core = require("cyclonedds.core")
        domain = require("cyclonedds.domain")
        pub = require("cyclonedds.pub")
        qos = require("cyclonedds.qos")
        sub = require("cyclonedds.sub")
        topic = require("cyclonedds.topic")
        util = require("cyclonedds.util")
        clayer = require("cyclonedds._clayer")

    return Binding


def _delete(entity: Any) -> None:
    """Delete a DDS entity now: the binding ties an entity's life to its Python object's and
    deletes it in ``__del__``, which is idempotent (it forgets the entity first)."""
    entity.__del__()


def write_raw(writer: Any, payload: bytes) -> None:
    """Write a CDR payload (with its header) as one sample, padded to 4 bytes as the binding's
    ``DataWriter.write`` pads it."""
    clayer = require("cyclonedds._clayer")
    padded = payload.ljust((len(payload) + 3) & ~3, b"\x00")
    ret = clayer.ddspy_write(writer._ref, padded)
    if ret < 0:
        raise Ros2MessageError(f"Cyclone DDS refused to write a sample (return code {ret})")


class _DdsEndpoint:
    """What a node's writer and reader share: the raw entity, its topic, QoS and gid."""

    def __init__(self, node: DdsNode, raw: Any, topic: str, qos: DdsQos) -> None:
        self._node = node
        self._raw = raw
        self.topic = topic
        self.qos = qos
        self.gid = node.entity_gid(raw)
        self.closed = False

    @staticmethod
    def _refusals(status: Any, who_refused_what: str) -> str | None:
        """An incompatible-QoS ``status`` as a sentence (None: no refusal seen)."""
        if status.total_count == 0:
            return None
        return (
            f"{status.total_count} {who_refused_what}; the last mismatch: "
            f"{describe_policy(status.last_policy_id)}"
        )


class DdsWriter(_DdsEndpoint):
    """One ROS 2 publisher's DDS writer: raw CDR samples, and what its QoS failed to match."""

    def write(self, payload: bytes) -> None:
        """Send one sample."""
        write_raw(self._raw, payload)

    def matched(self) -> int:
        """How many readers this writer is matched with now."""
        count: int = self._raw.get_publication_matched_status().current_count
        return count

    def incompatible(self) -> str | None:
        """Why readers found on this topic were refused (None: no refusal seen)."""
        return self._refusals(
            self._raw.get_offered_incompatible_qos_status(),
            f"subscription(s) to {self.topic} requested a QoS this publisher "
            f"({self.qos.describe()}) does not offer",
        )

    def close(self) -> None:
        """Delete the writer and withdraw it from the graph (idempotent)."""
        if self.closed:
            return
        self.closed = True
        _delete(self._raw)
        self._node.forget(self)


class DdsReader(_DdsEndpoint):
    """One ROS 2 subscription's DDS reader, drained by a daemon thread of its own."""

    def __init__(
        self,
        node: DdsNode,
        raw: Any,
        topic: str,
        qos: DdsQos,
        deliver: Callable[[bytes], None],
        fail: Callable[[BaseException], None],
    ) -> None:
        super().__init__(node, raw, topic, qos)
        dds = node._dds
        self._deliver = deliver
        self._fail = fail
        self._mask = dds.core.SampleState.Any | dds.core.ViewState.Any | dds.core.InstanceState.Any
        self._waitset = dds.core.WaitSet(node._participant)
        self._data = dds.core.ReadCondition(raw, self._mask)
        self._stop = dds.core.GuardCondition(node._participant)
        self._waitset.attach(self._data)
        self._waitset.attach(self._stop)
        self._incompatible_seen = 0
        self._thread = threading.Thread(
            target=self._run, name=f"evclock ros2 {topic} dds reader", daemon=True
        )
        # The source's own delivery: neither work that holds sim time nor a thread that could
        # resume a paused loop.
        mark_internal(self._thread)

    def start(self) -> None:
        self._thread.start()

    def incompatible(self) -> str | None:
        """Why publishers found on this topic were refused (None: no refusal seen)."""
        return self._refusals(
            self._raw.get_requested_incompatible_qos_status(),
            f"publisher(s) of {self.topic} offered a QoS this subscription "
            f"({self.qos.describe()}) cannot accept",
        )

    def matched(self) -> int:
        """How many writers this reader is matched with now."""
        count: int = self._raw.get_subscription_matched_status().current_count
        return count

    def _run(self) -> None:
        clayer = require("cyclonedds._clayer")
        try:
            while not self.closed:
                self._waitset.wait(_WAIT_NS)
                if self.closed:
                    return
                samples = clayer.ddspy_take(self._raw._ref, self._mask, _TAKE_BATCH)
                if isinstance(samples, int):
                    raise Ros2MessageError(f"taking {self.topic} samples failed (code {samples})")
                for data, info in samples:
                    if info.valid_data:
                        # Whole samples (Cyclone DDS bounds their size by its configuration);
                        # evclock's decoders read them within their length.
                        self._deliver(bytes(data))
                self._report_incompatible()
        except BaseException as exc:  # the follower turns it into ClockLostError
            if not self.closed:
                self._fail(exc)

    def _report_incompatible(self) -> None:
        status = self._raw.get_requested_incompatible_qos_status()
        if status.total_count != self._incompatible_seen:
            self._incompatible_seen = status.total_count
            logger.warning("%s", self.incompatible())

    def close(self) -> None:
        """Stop the thread, delete the reader and withdraw it from the graph (idempotent)."""
        if self.closed:
            return
        self.closed = True
        self._stop.set(True)
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(_JOIN_TIMEOUT)
        for entity in (self._waitset, self._data, self._stop, self._raw):
            _delete(entity)
        self._node.forget(self)


def check_no_zenoh_endpoints(connect: object, listen: object) -> None:
    """On DDS, Zenoh endpoints are a mistake: say where DDS is configured instead."""
    pairs = (("connect", connect), ("listen", listen))
    given = [name for name, value in pairs if value is not None]
    if given:
        raise InvalidArgumentError(
            f"{' and '.join(given)} name Zenoh endpoints, but the middleware is DDS; pass "
            "rmw='zenoh' (or RMW_IMPLEMENTATION=rmw_zenoh_cpp), or configure DDS discovery "
            "with CYCLONEDDS_URI"
        )
