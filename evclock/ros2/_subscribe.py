"""ROS 2 topics into evclock's stamped data: ``evclock.ros2.subscribe(topic, msgtype)``.

A subscription is a filter (:class:`~evclock.data.SimpleFilter`, like message_filters'
``Subscriber``): every message arriving on the topic comes out on the running loop's thread as
a :class:`~evclock.data.Stamped` whose stamp is the message's ``header.stamp`` as a
:class:`~evclock.Time` (a ``tf2_msgs/TFMessage`` comes out as one ``Stamped`` per transform),
ready for :class:`~evclock.data.ApproximateTimeSynchronizer`, :class:`~evclock.data.Cache`
and friends. Messages are rosbags' objects of the distribution spoken; bytes from peers are
read by rosbags and a message that does not decode is counted and logged (quoted, bounded),
not delivered.

DDS: a Cyclone DDS reader of ``rt/<topic>`` with ROS's type name, announced in the ROS graph.
Zenoh: a subscriber of rmw_zenoh's key ``<domain>/<topic>/<type>/<hash>`` (Humble's or the
distribution's hash), with the liveliness tokens of the node and its subscription.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Sequence
from typing import Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, Ros2MessageError
from evclock.data import SimpleFilter, Stamped
from evclock.outside._threads import mark_internal
from evclock.ros2._rmw import Middleware, resolve_middleware
from evclock.ros2._session import (
    DEFAULT_CONNECT,
    DEFAULT_LISTEN,
    check_endpoints,
    open_session,
    require,
)
from evclock.ros2._types import check_ros_type, dds_type_name, deserialize, type_hash, typestore
from evclock.ros2._wire import (
    DEFAULT_WIRE_FORMAT,
    HUMBLE_TYPE_HASH,
    WireFormat,
    check_node_name,
    endpoint_token,
    node_token,
    qos_field,
    resolve_domain_id,
    resolve_topic,
)
from evclock.ros2._wire import wire_format as lookup_wire_format
from evclock.time._time import ClockType, Time

logger = logging.getLogger("evclock.ros2")

TF_MESSAGE: Final = "tf2_msgs/msg/TFMessage"
DEFAULT_QUEUE_SIZE: Final = 100
"""Messages kept between the network and the loop (the oldest are dropped beyond that)."""
_JOIN_TIMEOUT: Final = 5.0


class Ros2Subscription(SimpleFilter):
    """A ROS 2 topic as a filter of :class:`~evclock.data.Stamped` messages; see
    :func:`subscribe`, which opens one inside the running program.

    :param topic: the ROS topic (``/imu``).
    :param msgtype: the message type as ROS names it (``sensor_msgs/msg/Imu``), stamped (with
        a ``std_msgs/Header``) or ``tf2_msgs/msg/TFMessage`` (one ``Stamped`` per transform).
    :param rmw: ``"dds"`` or ``"zenoh"`` (default: ``RMW_IMPLEMENTATION``, else DDS).
    :param domain_id: the ROS domain id (default ``ROS_DOMAIN_ID``, else 0).
    :param wire_format: the distribution spoken (``"jazzy"``, ``"humble"``...).
    :param node_name: the node announced in the ROS graph (DDS).
    :param reliable: ask for a reliable subscription (default best effort, fed by every
        publisher).
    :param queue_size: messages kept between the network and the loop (the oldest dropped).
    :param clock_type: the clock domain of the stamps (default: the running clock's).
    :param connect: Zenoh endpoints to connect to (Zenoh only; default rmw_zenoh's router).
    :param listen: Zenoh endpoints accepting peers (Zenoh only).
    :raises InvalidArgumentError: an unknown or unstamped type, a bad topic or option, Zenoh
        endpoints on DDS.
    :raises MissingExtraError: the ``ros2`` extra is missing.
    """

    def __init__(
        self,
        topic: str,
        msgtype: str,
        *,
        rmw: str | None = None,
        domain_id: int | None = None,
        wire_format: str | WireFormat = DEFAULT_WIRE_FORMAT,
        node_name: str = "evclock_listener",
        reliable: bool = False,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        clock_type: ClockType | None = None,
        connect: Sequence[str] | None = None,
        listen: Sequence[str] | None = None,
    ) -> None:
        import asyncio

        super().__init__()
        self._wire = lookup_wire_format(wire_format)
        self.topic = resolve_topic(topic)
        self.msgtype = check_ros_type(msgtype, self._wire)
        fields = [name for name, _ in typestore_fields(self.msgtype, self._wire)]
        if self.msgtype != TF_MESSAGE and "header" not in fields:
            raise InvalidArgumentError(
                f"{self.msgtype} has no header, so its messages carry no stamp; subscribe to a "
                "stamped type (one with a std_msgs/Header) or to tf2_msgs/msg/TFMessage"
            )
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise InvalidArgumentError(f"queue_size must be an int >= 1, got {queue_size!r}")
        if clock_type is None:
            from evclock.hosts._current import clock

            clock_type = clock().clock_type  # the running program's: sim, or its wall clock
        if not isinstance(clock_type, ClockType):
            raise InvalidTypeError(f"clock_type must be a ClockType, got {clock_type!r}")
        self._clock_type = clock_type
        self._domain_id = resolve_domain_id(domain_id)
        self.middleware: Middleware = resolve_middleware(rmw)
        node_name = check_node_name(node_name)
        self._loop = asyncio.get_running_loop()  # deliveries happen on the loop's thread
        self._inbox: collections.deque[bytes] = collections.deque(maxlen=queue_size)
        self._lock = threading.Lock()
        self._wake_pending = False
        self.received = 0
        """Messages delivered so far."""
        self.rejected = 0
        """Messages that did not decode (logged, not delivered)."""
        self._closed = False
        self._dds: Any = None
        self._session: Any = None
        self._tokens: list[Any] = []
        self.liveliness_tokens: tuple[str, ...] = ()
        """The node's and the subscription's rmw_zenoh liveliness tokens (Zenoh; else empty)."""
        if self.middleware == "dds":
            from evclock.ros2._dds import DdsNode, DdsQos, check_no_zenoh_endpoints

            check_no_zenoh_endpoints(connect, listen)
            qos = DdsQos(reliable=reliable, transient_local=False, depth=queue_size)
            self._dds = DdsNode(self._domain_id, node_name, self._wire)
            try:
                self._dds.reader(self.topic, self.msgtype, qos, self._arrive, self._fail)
            except BaseException:
                self._dds.close()
                raise
        else:
            self._open_zenoh(
                check_endpoints(DEFAULT_CONNECT if connect is None else connect, "connect"),
                check_endpoints(DEFAULT_LISTEN if listen is None else listen, "listen"),
                node_name,
                reliable,
                queue_size,
            )

    def _open_zenoh(
        self,
        connect: Sequence[str],
        listen: Sequence[str],
        node_name: str,
        reliable: bool,
        depth: int,
    ) -> None:
        zenoh = require("zenoh")
        own_hash = type_hash(self.msgtype, self._wire)
        hashes = {own_hash or HUMBLE_TYPE_HASH, HUMBLE_TYPE_HASH}
        type_name = dds_type_name(self.msgtype)
        key = f"{self._domain_id}/{self.topic[1:]}/{type_name}/*"
        self._session = open_session(connect, listen)
        try:
            zid = str(self._session.zid())
            self.liveliness_tokens = (
                node_token(self._domain_id, zid, 0, node_name),
                endpoint_token(
                    "MS",
                    self._domain_id,
                    zid,
                    0,
                    1,
                    node_name,
                    self.topic,
                    self._wire,
                    type_name=type_name,
                    type_hash=own_hash,
                    qos=qos_field(reliable=reliable, transient_local=False, depth=depth),
                ),
            )
            liveliness = self._session.liveliness()
            self._tokens = [liveliness.declare_token(t) for t in self.liveliness_tokens]
            self._subscriber = self._session.declare_subscriber(
                key, zenoh.handlers.RingChannel(self._inbox.maxlen or DEFAULT_QUEUE_SIZE)
            )
        except BaseException:
            self._session.close()
            raise

        def read() -> None:
            handler = self._subscriber.handler
            while True:
                try:
                    sample = handler.recv()
                except zenoh.ZError:
                    return
                if str(sample.key_expr).rsplit("/", 1)[-1] not in hashes:
                    self.rejected += 1
                    logger.warning(
                        "%s: a sample on %.120r has another type hash; dropped",
                        self.topic,
                        str(sample.key_expr),
                    )
                    continue
                self._arrive(sample.payload.to_bytes())

        self._reader = threading.Thread(target=read, name=f"evclock ros2 {self.topic}", daemon=True)
        mark_internal(self._reader)
        self._reader.start()

    # ---------------------------------------------------------------- arrival (reader thread)

    def _arrive(self, payload: bytes) -> None:
        self._inbox.append(payload)
        with self._lock:
            if self._wake_pending or self._closed:
                return
            self._wake_pending = True
        try:
            self._loop.call_soon_threadsafe(self._deliver)
        except RuntimeError:
            self._closed = True  # the loop closed: nobody listens any more

    def _fail(self, exc: BaseException) -> None:
        logger.error("the subscription to %s failed: %s", self.topic, exc)

    # ---------------------------------------------------------------- delivery (loop thread)

    def _deliver(self) -> None:
        with self._lock:
            self._wake_pending = False
        while self._inbox and not self._closed:
            payload = self._inbox.popleft()
            try:
                message = deserialize(payload, self.msgtype, self._wire)
            except Ros2MessageError as exc:
                self.rejected += 1
                logger.warning("%s: %s", self.topic, exc)
                continue
            self.received += 1
            if self.msgtype == TF_MESSAGE:
                for transform in message.transforms:
                    self.signal_message(Stamped(self._stamp(transform.header), transform))
            else:
                self.signal_message(Stamped(self._stamp(message.header), message))

    def _stamp(self, header: Any) -> Time:
        return Time.from_msg(header.stamp, self._clock_type)

    def close(self) -> None:
        """Stop receiving and withdraw from the ROS graph (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._dds is not None:
            self._dds.close()
        elif self._session is not None:
            for token in self._tokens:
                token.undeclare()
            self._subscriber.undeclare()
            self._session.close()
            self._reader.join(_JOIN_TIMEOUT)

    def __repr__(self) -> str:
        return (
            f"<Ros2Subscription {self.topic} {self.msgtype} over {self.middleware} "
            f"received={self.received} rejected={self.rejected}>"
        )


def typestore_fields(msgtype: str, wire: WireFormat) -> list[tuple[str, Any]]:
    """The fields of ``msgtype`` in ``wire``'s distribution (rosbags' definitions)."""
    from evclock.ros2._types import store_name

    fields: list[tuple[str, Any]] = typestore(store_name(wire)).fielddefs[msgtype][1]
    return fields


def subscribe(topic: str, msgtype: str, **options: Any) -> Ros2Subscription:
    """Subscribe to a ROS 2 topic from the running program: a filter of ``Stamped`` messages.

    Call it inside the running program (``evclock.run(main())``); messages come out on the
    loop's thread, each a :class:`~evclock.data.Stamped` holding the rosbags message with its
    ``header.stamp`` as a :class:`~evclock.Time` of ``clock_type`` (default: the running
    program's clock's, sim time under ``evclock.run`` as the ROS clock of ``use_sim_time``
    nodes). Connect it to a synchroniser, a
    :class:`~evclock.data.Cache` or a callback (``register_callback``).

    :param topic: the ROS topic (``/imu``).
    :param msgtype: the message type as ROS names it (``sensor_msgs/msg/Imu``): a type with a
        ``std_msgs/Header``, or ``tf2_msgs/msg/TFMessage`` (one ``Stamped`` per transform).
    :param options: ``rmw`` (``"dds"``/``"zenoh"``, default from ``RMW_IMPLEMENTATION``, else
        DDS), ``domain_id`` (default ``ROS_DOMAIN_ID``, else 0), ``wire_format`` (the
        distribution: ``"jazzy"``, ``"humble"``...), ``node_name``, ``reliable`` (False: best
        effort, which every publisher feeds), ``queue_size``, ``clock_type``, and on Zenoh
        ``connect``/``listen``.
    :returns: the subscription (``close()`` it when done).
    :raises InvalidArgumentError: an unknown or unstamped type, a bad topic or option.
    :raises MissingExtraError: the ``ros2`` extra is missing.

    Example::

        imu = evclock.ros2.subscribe("/imu", "sensor_msgs/msg/Imu")
        odom = evclock.ros2.subscribe("/pose", "geometry_msgs/msg/PoseStamped")
        sync = ApproximateTimeSynchronizer([imu, odom], queue_size=10, slop=0.01)
    """
    return Ros2Subscription(topic, msgtype, **options)
