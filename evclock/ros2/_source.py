"""Following a ROS 2 ``/clock`` over DDS or Zenoh: an external time source for the simulation loop.

A controller launched with ``EVCLOCK_CLOCK=ros2:///clock`` (or ``clock=``) runs on the time
of a ROS 2 simulator (Gazebo through ``ros_gz_bridge``, or an evclock simulation publishing
``/clock``) as an rclpy node with ``use_sim_time`` would: sleeps, rates, timers and asyncio
timeouts follow it.

How it fits the loop (the external-source contract): a daemon thread reads samples into
an inbox and wakes the loop with ``call_soon_threadsafe``; on the loop thread, ``advance()``
reads the inbox and moves time toward the newest ``/clock`` value, never past the loop's next
deadline, or returns the time unchanged - "waiting for the outside" - and the loop waits for
I/O. A backward step of ``/clock`` below the loop's time (a simulator reset) is a jump with
evclock's jump policy. Liveness is the source's job: after ``silence_timeout`` wall seconds
without a sample it raises :class:`~evclock.ClockLostError` from ``advance()``.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Sequence
from typing import Any, Final

from evclock._errors import ClockLostError, InvalidArgumentError, InvalidTypeError, Ros2MessageError
from evclock.outside._threads import mark_internal
from evclock.ros2._rmw import Middleware, resolve_middleware
from evclock.ros2._session import (
    DEFAULT_CONNECT,
    DEFAULT_LISTEN,
    check_endpoints,
    open_session,
    require,
)
from evclock.ros2._wire import (
    CLOCK_TYPE,
    DEFAULT_WIRE_FORMAT,
    WireFormat,
    check_node_name,
    check_type_hash,
    clock_subscription_key_expr,
    decode_clock,
    endpoint_token,
    node_token,
    resolve_domain_id,
    resolve_topic,
)
from evclock.ros2._wire import wire_format as lookup_wire_format
from evclock.sources import Gate, TimeSource
from evclock.time._time import SIM, Time, new_time

logger = logging.getLogger("evclock.ros2")

DEFAULT_SILENCE_TIMEOUT: Final = 10.0
"""Default wall seconds without a ``/clock`` sample before the source gives up (ClockLostError)."""
#: Samples buffered between the Zenoh network and the reader thread, and between the reader
#: thread and the loop (the oldest are dropped beyond that; only the newest time matters).
_CHANNEL_CAPACITY: Final = 1024
#: How long close() waits for the reader thread to see its channel closed (wall seconds).
_JOIN_TIMEOUT: Final = 5.0
_NODE_ID = 0
_SUBSCRIPTION_ID = 1


def _check_timeout(value: object, what: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidTypeError(f"{what} must be wall seconds or None, got {type(value).__name__}")
    if math.isnan(value) or value <= 0:
        raise InvalidArgumentError(
            f"{what} must be a positive number of seconds or None, got {value!r}"
        )
    return float(value)


class Ros2ClockSource(TimeSource):
    """Sim time that follows a ROS 2 ``rosgraph_msgs/msg/Clock`` topic over DDS or Zenoh.

    ``rmw`` chooses the middleware as a ROS node does (``"dds"``/``"zenoh"``; default: from
    ``RMW_IMPLEMENTATION``, DDS when unset). On **DDS** construction opens a Cyclone DDS
    participant (``CYCLONEDDS_URI`` configures it), reads ``rt/clock`` with the QoS of rclcpp's
    time source (best effort, keep last 1, which every publisher feeds) and announces the node
    and its subscription on ``ros_discovery_info`` (``wire_format``: ``"jazzy"``, or
    ``"humble"`` for Humble's graph messages); a publisher whose QoS it cannot accept is
    logged and named in the errors. On **Zenoh** it opens a peer session
    (``connect``/``listen`` endpoints as for :class:`~evclock.ros2.Ros2ClockPublisher`) and
    reads any rmw_zenoh wire format (Humble's or Jazzy's key). Either way it subscribes to
    ``topic`` in ``domain_id`` (default ``ROS_DOMAIN_ID``, else 0), declares a node and a
    subscription in the ROS graph, and **waits for the first message**: the program starts
    at the publisher's time, as an rclcpp node waiting with
    ``Clock::wait_until_started()``. ``startup_timeout`` bounds that wait (None: wait as long
    as it takes, logging a warning every ``silence_timeout``).

    Once running, time moves toward each newer ``/clock`` value, firing local deadlines in
    order; a ``/clock`` older than the loop's time is a backward jump (jump handlers run,
    ``clock.sleep`` sleepers get :class:`~evclock.ClockJumpedError`, rates and timers re-anchor).
    If no sample arrives for ``silence_timeout`` wall seconds while the loop waits for one,
    :class:`~evclock.ClockLostError` ends the run (None: wait forever).

    :param domain_id: the ROS domain id (default ``ROS_DOMAIN_ID``, else 0).
    :param topic: the Clock topic to follow.
    :param node_name: the name of the node evclock declares in the ROS graph.
    :param rmw: ``"dds"`` or ``"zenoh"`` (default: ``RMW_IMPLEMENTATION``, else DDS).
    :param wire_format: the distribution's variant for DDS graph messages (``"jazzy"``).
    :param connect: Zenoh endpoints to connect to (the rmw_zenoh router by default; Zenoh only).
    :param listen: Zenoh endpoints to accept peer connections on (Zenoh only).
    :param startup_timeout: wall seconds to wait for the first message (None: no limit).
    :param silence_timeout: wall seconds without a message before :class:`~evclock.ClockLostError`
        (None: wait forever).
    :raises InvalidArgumentError: an invalid domain id, topic, node name, endpoint or timeout.
    :raises InvalidTypeError: an argument of the wrong type.
    :raises MissingExtraError: the ``ros2`` extra is missing (``pip install 'evclock[ros2]'``).
    :raises ClockLostError: no message arrived within ``startup_timeout``.
    :raises Ros2MessageError: the first message is not a valid Clock message.

    Example::

        evclock.run(main(), source=Ros2ClockSource(domain_id=0, startup_timeout=30.0))
    """

    external = True
    free_running = True  # idle is not a deadlock: time comes from outside

    def __init__(
        self,
        *,
        domain_id: int | None = None,
        topic: str = "/clock",
        node_name: str = "evclock_follower",
        rmw: str | None = None,
        wire_format: str | WireFormat = DEFAULT_WIRE_FORMAT,
        connect: Sequence[str] | None = None,
        listen: Sequence[str] | None = None,
        startup_timeout: float | None = None,
        silence_timeout: float | None = DEFAULT_SILENCE_TIMEOUT,
    ) -> None:
        self._domain_id = resolve_domain_id(domain_id)
        self._topic = resolve_topic(topic)
        node_name = check_node_name(node_name)
        wire = lookup_wire_format(wire_format)
        self._middleware: Middleware = resolve_middleware(rmw)
        startup = _check_timeout(startup_timeout, "startup_timeout")
        self._silence_timeout = _check_timeout(silence_timeout, "silence_timeout")
        self._connect: tuple[str, ...] = ()
        self._dds: Any = None
        self._dds_reader: Any = None
        self._now = 0
        self._latest: int | None = None
        self._received = 0
        self._inbox: collections.deque[tuple[str | None, bytes]] = collections.deque(
            maxlen=_CHANNEL_CAPACITY
        )
        self._first = threading.Event()
        self._last_arrival: float | None = None
        self._error: BaseException | None = None
        self._closing = False
        self._wake_lock = threading.Lock()
        self._wake_pending = False
        self._loop_wakeable = False
        self._loop: Any = None  # the SimEventLoop this source drives (set by attach)
        if self._middleware == "dds":
            self._open_dds(node_name, wire, connect, listen)
        else:
            self._connect = check_endpoints(
                DEFAULT_CONNECT if connect is None else connect, "connect"
            )
            self._open_zenoh(
                node_name,
                check_endpoints(DEFAULT_LISTEN if listen is None else listen, "listen"),
            )
        try:
            self._wait_for_first(startup)
        except BaseException:
            self.close()
            raise

    def _open_dds(self, node_name: str, wire: WireFormat, connect: object, listen: object) -> None:
        from evclock.ros2._dds import CLOCK_SUBSCRIPTION_QOS, DdsNode, check_no_zenoh_endpoints

        check_no_zenoh_endpoints(connect, listen)
        self._dds = DdsNode(self._domain_id, node_name, wire)
        try:
            self._dds_reader = self._dds.reader(
                self._topic,
                CLOCK_TYPE,
                CLOCK_SUBSCRIPTION_QOS,
                lambda payload: self._arrive(None, payload),
                self._fail,
            )
        except BaseException:
            self._dds.close()
            raise

    def _open_zenoh(self, node_name: str, listen: Sequence[str]) -> None:
        self._key_expr = clock_subscription_key_expr(self._domain_id, self._topic)
        self._zenoh = require("zenoh")
        self._session: Any = open_session(self._connect, listen)
        try:
            zid = str(self._session.zid())
            liveliness = self._session.liveliness()
            self._tokens = [
                liveliness.declare_token(token)
                for token in (
                    node_token(self._domain_id, zid, _NODE_ID, node_name),
                    endpoint_token(
                        "MS",
                        self._domain_id,
                        zid,
                        _NODE_ID,
                        _SUBSCRIPTION_ID,
                        node_name,
                        self._topic,
                    ),
                )
            ]
            # A channel, not a Python callback: zenoh runs callbacks on non-daemon threads
            # of its own, which the loop would take for busy work holding sim time.
            self._subscriber: Any = self._session.declare_subscriber(
                self._key_expr, self._zenoh.handlers.RingChannel(_CHANNEL_CAPACITY)
            )
            self._reader = threading.Thread(
                target=self._read, name=f"evclock ros2 {self._topic} reader", daemon=True
            )
            # The source's own delivery (it wakes the loop through the source): neither work
            # that holds sim time nor a thread that could resume a paused loop.
            mark_internal(self._reader)
            self._reader.start()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ facts

    @property
    def now_ns(self) -> int:
        """The followed time in integer nanoseconds."""
        return self._now

    @property
    def latest(self) -> Time | None:
        """The newest ``/clock`` time received (the loop may still be behind it)."""
        return None if self._latest is None else new_time(self._latest, SIM)

    @property
    def received(self) -> int:
        """How many ``/clock`` samples the loop has read."""
        return self._received

    @property
    def key_expr(self) -> str:
        """The Zenoh key expression subscribed to (any type hash; Zenoh only)."""
        if self._middleware != "zenoh":
            raise InvalidArgumentError("key_expr is a Zenoh fact; this source speaks DDS")
        return self._key_expr

    @property
    def middleware(self) -> Middleware:
        """The middleware spoken: ``"dds"`` or ``"zenoh"``."""
        return self._middleware

    def diagnostics(self) -> list[str]:
        """What went wrong with publishers so far, for people: on DDS, publishers of the topic
        whose QoS this subscription cannot accept."""
        reader = self._dds_reader
        if reader is None or reader.closed:
            return []
        problem = reader.incompatible()
        return [] if problem is None else [problem]

    def describe(self) -> str:
        """The source for messages: topic, domain and endpoints."""
        if self._middleware == "dds":
            problems = "".join(f"; {problem}" for problem in self.diagnostics())
            return f"ROS 2 {self._topic} (domain {self._domain_id}) over DDS{problems}"
        return (
            f"ROS 2 {self._topic} (domain {self._domain_id}) over Zenoh via "
            f"{', '.join(self._connect) or 'listen only'}"
        )

    # ------------------------------------------------------------------ the contract

    def attach(self, loop: Any) -> None:
        """Called once by the :class:`~evclock.SimEventLoop` this source drives; a
        ``SimDriver`` is refused with :class:`~evclock.SimDriverError`."""
        from evclock._errors import SimDriverError
        from evclock.hosts._loop import SimEventLoop

        # The host is the kernel of the loop this source drives; Zenoh's arrivals wake that
        # loop with call_soon_threadsafe, so only a SimEventLoop hosts a /clock follower.
        event_loop = getattr(loop, "host", None)
        if not isinstance(event_loop, SimEventLoop):
            raise SimDriverError(
                f"{self.describe()} follows an outside clock, which SimDriver cannot host "
                "yet; run the program with evclock.run(main(), source=...) instead"
            )
        super().attach(loop)
        self._loop = event_loop

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Never blocks: move toward the newest ``/clock`` received, never past it nor past
        ``target_ns``, and return the new time (the same time when nothing new arrived)."""
        self._loop_wakeable = True  # from now on the loop is running: wake it on arrival
        jumped = self._drain()
        if self._error is not None:
            raise self._error
        now = self._now
        if jumped:
            return now  # the jump moved the deadlines: the host asks again with a new target
        latest = self._latest
        if latest is not None and latest > now:
            new = latest if target_ns is None else min(target_ns, latest)
            if new > now and (gate is None or gate(new)):
                self._now = new
                return new
            return now
        self._check_silence()
        return now

    def _check_silence(self) -> None:
        limit = self._silence_timeout
        last = self._last_arrival
        if limit is None or last is None:
            return
        silent = time.monotonic() - last
        if silent > limit:
            raise ClockLostError(
                f"no {self._topic} message for {silent:.1f} s of wall time (the last one said "
                f"{self._now / 1e9:.9f} s) from {self.describe()}; the publisher stopped or the "
                f"connection is lost; raise silence_timeout (now {limit:g} s) or pass None to "
                "wait forever"
            )

    # ------------------------------------------------------------------ arrival

    def _read(self) -> None:
        """Reader thread: move samples from Zenoh's channel to the inbox, wake the loop."""
        handler = self._subscriber.handler
        while True:
            try:
                sample = handler.recv()
            except self._zenoh.ZError as exc:
                if not self._closing:
                    self._error = ClockLostError(
                        f"the Zenoh subscription to {self._key_expr} failed: {exc}"
                    )
                return
            if not self._arrive(str(sample.key_expr), sample.payload.to_bytes()):
                return

    def _fail(self, exc: BaseException) -> None:
        """A reader thread failed: the loop raises it on its next advance."""
        self._error = ClockLostError(f"reading {self._topic} failed: {exc}")
        self._first.set()
        self._wake()

    def _arrive(self, key_expr: str | None, payload: bytes) -> bool:
        """On a reader thread: queue one sample and wake the loop; False once the loop closed.
        ``key_expr`` is Zenoh's (its type hash is checked), None on DDS (typed by topic)."""
        self._inbox.append((key_expr, payload))
        self._last_arrival = time.monotonic()
        self._first.set()
        return self._wake()

    def _wake(self) -> bool:
        loop = self._loop
        if loop is None or not self._loop_wakeable:
            return True  # the loop reads the inbox on its first advance
        with self._wake_lock:
            if self._wake_pending:
                return True
            self._wake_pending = True
        try:
            loop.call_soon_threadsafe(self._drain_woken)
        except RuntimeError:
            return False  # the loop closed under us: nobody is following any more
        return True

    def _drain_woken(self) -> None:
        with self._wake_lock:
            self._wake_pending = False
        self._drain()

    def _drain(self) -> bool:
        """On the loop's thread: read the inbox in arrival order; True if time jumped."""
        inbox = self._inbox
        jumped = False
        while inbox:
            key_expr, payload = inbox.popleft()
            try:
                if key_expr is not None:
                    check_type_hash(key_expr)
                time_ns = decode_clock(payload)
            except Ros2MessageError as exc:
                self._error = exc
                return jumped
            self._received += 1
            loop = self._loop
            if loop is None:
                self._now = time_ns  # not running yet: the start follows the newest time
            elif time_ns < self._now:
                # The simulator went back (a reset): a jump, with evclock's jump policy.
                host = self._host
                assert host is not None
                host.jump(self._now, time_ns, self._assign)
                jumped = True
            self._latest = time_ns
        return jumped

    def _assign(self, new_ns: int) -> None:
        self._now = new_ns

    def _wait_for_first(self, timeout: float | None) -> None:
        waited = 0.0
        report_every = self._silence_timeout or DEFAULT_SILENCE_TIMEOUT
        while True:
            step = report_every if timeout is None else min(report_every, timeout - waited)
            if self._first.wait(step):
                break
            waited += step
            if self._error is not None:
                raise self._error
            if timeout is not None and waited >= timeout:
                reach = (
                    "found by DDS discovery (CYCLONEDDS_URI)"
                    if self._middleware == "dds"
                    else "reachable through those endpoints"
                )
                raise ClockLostError(
                    f"no {self._topic} message arrived within startup_timeout={timeout:g} s "
                    f"from {self.describe()}; is the simulator publishing, in domain "
                    f"{self._domain_id}, {reach}?"
                )
            logger.warning(
                "still waiting for the first %s message after %.1f s (%s)",
                self._topic,
                waited,
                self.describe(),
            )
        self._drain()
        if self._error is not None:
            raise self._error

    # ------------------------------------------------------------------ closing

    def close(self) -> None:
        """Withdraw from the ROS graph, stop the reader thread and close the session."""
        if self._closing:
            return
        self._closing = True
        if self._dds is not None:
            self._dds.close()
            return
        try:
            for token in getattr(self, "_tokens", ()):
                token.undeclare()
            subscriber = getattr(self, "_subscriber", None)
            if subscriber is not None:
                subscriber.undeclare()  # closes the channel: the reader thread returns
        finally:
            self._session.close()
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(_JOIN_TIMEOUT)
