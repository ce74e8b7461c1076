"""Publishing evclock's sim time as ROS 2 ``/clock`` over DDS or Zenoh, as a ROS 2 node would."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

from evclock._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
    NotRunningError,
    Ros2SubscribersError,
)
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
    clock_key_expr,
    encode_attachment,
    encode_clock,
    endpoint_token,
    entity_gid,
    node_token,
    resolve_domain_id,
    resolve_topic,
)
from evclock.ros2._wire import wire_format as lookup_wire_format
from evclock.time._time import SIM, Time

if TYPE_CHECKING:
    from evclock.ros2._dds import DdsNode
    from evclock.sources import StepHook, SteppingTimeSource

logger = logging.getLogger("evclock.ros2")

_NODE_ID = 0
_PUBLISHER_ID = 1
WAIT_REPUBLISH_S = 0.02
"""How often (wall seconds) :meth:`Ros2ClockPublisher.wait_for_subscribers` publishes the held
time while it waits."""
WAIT_SETTLE_S = 0.25
"""Wall seconds :meth:`Ros2ClockPublisher.wait_for_subscribers` goes on publishing the held
time once the subscriptions matched: DDS tells a writer when it matched a reader, not when the
reader matched the writer, and a best-effort reader drops samples until it has (Fast DDS 3's
readers, Kilted's, took up to about 30 ms on loopback here)."""


class Ros2ClockPublisher:
    """A ROS 2 node publishing ``rosgraph_msgs/msg/Clock`` on ``topic`` over DDS or Zenoh.

    ``rmw`` chooses the middleware as a ROS node does (``"dds"`` or ``"zenoh"``; default:
    from ``RMW_IMPLEMENTATION``, DDS when unset). ``wire_format`` names the distribution
    spoken (default ``"jazzy"``, also Kilted's and Rolling's; ``"humble"``: see
    :data:`evclock.ros2.WIRE_FORMATS`).

    **DDS**: a Cyclone DDS participant (configured by ``CYCLONEDDS_URI`` as under ROS) writes
    ``rt/clock`` with rclcpp's ClockQoS (best effort, volatile, keep last 1) and announces the
    node ``node_name`` and its publisher on ``ros_discovery_info``, so nodes on any DDS rmw
    (Fast DDS, Cyclone DDS, Connext) with ``use_sim_time`` follow it and ``ros2 node list``
    shows it. A subscription asking for a QoS the publisher cannot offer (a reliable one) is
    reported by :meth:`diagnostics` and logged.

    **Zenoh**: rmw_zenoh's wire format, with the liveliness tokens of the node and its
    publisher. The session is a Zenoh peer that connects to ``connect`` (default: rmw_zenoh's
    router on ``tcp/127.0.0.1:7447``) and accepts peers on ``listen``; multicast scouting is
    off. ``wall_clock_ns`` gives the attachments' source timestamps (wall-clock ns since the
    epoch, as rmw_zenoh sends). ``connect``/``listen`` on DDS are an error.

    ``domain_id`` defaults to ``ROS_DOMAIN_ID`` (else 0), as in ROS.

    Publish with :meth:`publish`, every physics step with :meth:`attach`, or at a sim-time
    rate with :meth:`run`. Close it (or use it as a context manager) to withdraw it from the
    ROS graph.
    """

    def __init__(
        self,
        *,
        domain_id: int | None = None,
        topic: str = "/clock",
        node_name: str = "evclock_clock",
        wire_format: str | WireFormat = DEFAULT_WIRE_FORMAT,
        rmw: str | None = None,
        connect: Sequence[str] | None = None,
        listen: Sequence[str] | None = None,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._domain_id = resolve_domain_id(domain_id)
        self._topic = resolve_topic(topic)
        self._node_name = check_node_name(node_name)
        self._wire = lookup_wire_format(wire_format)
        self._middleware: Middleware = resolve_middleware(rmw)
        if not callable(wall_clock_ns):
            raise InvalidTypeError("wall_clock_ns must be a callable returning wall-clock ns")
        self._wall_clock_ns = wall_clock_ns
        self._sequence_number = 0
        self._closed = False
        self._dds: DdsNode | None = None
        if self._middleware == "dds":
            self._open_dds(connect, listen)
        else:
            self._open_zenoh(
                check_endpoints(DEFAULT_CONNECT if connect is None else connect, "connect"),
                check_endpoints(DEFAULT_LISTEN if listen is None else listen, "listen"),
            )

    def _open_dds(self, connect: object, listen: object) -> None:
        from evclock.ros2._dds import CLOCK_PUBLISHER_QOS, DdsNode, check_no_zenoh_endpoints

        check_no_zenoh_endpoints(connect, listen)
        node = DdsNode(self._domain_id, self._node_name, self._wire)
        try:
            self._writer = node.writer(self._topic, CLOCK_TYPE, CLOCK_PUBLISHER_QOS)
        except BaseException:
            node.close()
            raise
        self._dds = node
        self._gid = self._writer.gid
        self._incompatible_reported: str | None = None

    def _open_zenoh(self, connect: Sequence[str], listen: Sequence[str]) -> None:
        self._key_expr = clock_key_expr(self._domain_id, self._topic, self._wire)
        zenoh = require("zenoh")
        self._session: Any = open_session(connect, listen)
        try:
            zid = str(self._session.zid())
            self._tokens = (
                node_token(self._domain_id, zid, _NODE_ID, self._node_name),
                endpoint_token(
                    "MP",
                    self._domain_id,
                    zid,
                    _NODE_ID,
                    _PUBLISHER_ID,
                    self._node_name,
                    self._topic,
                    self._wire,
                ),
            )
            self._gid = entity_gid(self._tokens[1])
            # rmw_zenoh's mapping of ClockQoS (best effort): best-effort, dropping samples
            # rather than blocking the simulation when a link is congested.
            self._publisher: Any = self._session.declare_publisher(
                self._key_expr,
                reliability=zenoh.Reliability.BEST_EFFORT,
                congestion_control=zenoh.CongestionControl.DROP,
            )
            liveliness = self._session.liveliness()
            self._declared = [liveliness.declare_token(token) for token in self._tokens]
        except BaseException:
            self._session.close()
            raise

    # ------------------------------------------------------------------ facts

    @property
    def domain_id(self) -> int:
        """The ROS domain id."""
        return self._domain_id

    @property
    def topic(self) -> str:
        """The fully qualified topic name, e.g. ``/clock``."""
        return self._topic

    @property
    def wire_format(self) -> WireFormat:
        """The distribution's wire variant spoken."""
        return self._wire

    @property
    def middleware(self) -> Middleware:
        """The middleware spoken: ``"dds"`` or ``"zenoh"``."""
        return self._middleware

    @property
    def key_expr(self) -> str:
        """The Zenoh key expression the samples are put on (Zenoh only)."""
        self._zenoh_only("key_expr")
        return self._key_expr

    @property
    def liveliness_tokens(self) -> tuple[str, ...]:
        """The declared liveliness tokens: the node's, then the publisher's (Zenoh only)."""
        self._zenoh_only("liveliness_tokens")
        return self._tokens

    @property
    def gid(self) -> bytes:
        """The publisher's GID: on Zenoh the 16 bytes sent in every attachment, on DDS the
        writer's GUID as ``ros_discovery_info`` announces it (24 bytes on Humble)."""
        return self._gid

    def diagnostics(self) -> list[str]:
        """What went wrong with subscriptions so far, for people: on DDS, subscriptions whose
        requested QoS this publisher cannot offer (a reliable ``/clock`` subscription, say)."""
        if self._dds is None or self._closed:
            return []
        problem = self._writer.incompatible()
        return [] if problem is None else [problem]

    def _zenoh_only(self, what: str) -> None:
        if self._middleware != "zenoh":
            raise InvalidArgumentError(
                f"{what} is a Zenoh fact; this publisher speaks {self._middleware.upper()}"
            )

    @property
    def sequence_number(self) -> int:
        """The sequence number of the last sample sent (0 before the first)."""
        return self._sequence_number

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    # ------------------------------------------------------------------ publishing

    def publish(self, time: Time | int) -> None:
        """Send one Clock message holding ``time`` (a sim :class:`Time` or integer ns)."""
        if self._closed:
            raise LoopClosedError("this Ros2ClockPublisher is closed; create a new one")
        if isinstance(time, Time):
            if time.clock_type is not SIM:
                raise ClockMismatchError(
                    f"/clock carries sim time, got a {time.clock_type.value} time; publish "
                    "clock.now() of a simulation"
                )
            time_ns = time.nanoseconds
        elif isinstance(time, int) and not isinstance(time, bool):
            time_ns = time
        else:
            raise InvalidTypeError(
                f"publish() takes a sim Time or int nanoseconds, got {type(time).__name__}"
            )
        payload = encode_clock(time_ns)
        self._sequence_number += 1
        if self._dds is not None:
            self._writer.write(payload)
            if self._sequence_number & 0x3FF == 1:  # now and then: a status read is a C call
                self._report_incompatible()
            return
        attachment = encode_attachment(
            self._sequence_number, self._wall_clock_ns(), self._gid, self._wire
        )
        self._publisher.put(payload, attachment=attachment)

    def _report_incompatible(self) -> None:
        problem = self._writer.incompatible()
        if problem is not None and problem != self._incompatible_reported:
            self._incompatible_reported = problem
            logger.warning("%s", problem)

    def attach(self, source: SteppingTimeSource[Any], *, decimation: int = 1) -> StepHook:
        """Publish ``source``'s time now and after every ``decimation``-th physics step.

        Returns the step hook (``remove()`` stops publishing). Per-step hooks make the
        source step one step at a time, which is what publishing every step needs.
        """
        from evclock.sources import SteppingTimeSource

        if not isinstance(source, SteppingTimeSource):
            raise InvalidTypeError(
                f"attach() takes a stepping source (PyBullet's, MuJoCo's), got "
                f"{type(source).__name__}; on another source publish at a sim-time rate with "
                "run(hz)"
            )
        return publish_every(source, check_decimation(decimation), self.publish)

    async def wait_for_subscribers(self, count: int, *, timeout: float = 60.0) -> int:
        """Hold sim time until ``count`` subscriptions matched this publisher (DDS).

        Sim time stays where it is (an explicit hold of the running simulation loop: it
        neither advances nor reports a deadlock meanwhile), and the held time is published
        every 20 ms of wall time, and for 0.25 s more once they matched (DDS tells a writer
        when it matched a reader, not when the reader matched the writer), so the first
        ``/clock`` sample a new subscription takes is that time (a DDS reader drops samples
        from a writer it has not finished discovering). Returns how many subscriptions
        matched.

        :param count: how many subscriptions to wait for (an int >= 1).
        :param timeout: wall seconds to wait at most (> 0).
        :raises Ros2SubscribersError: ``timeout`` passed with fewer subscriptions matched.
        :raises NotRunningError: not awaited on a simulation's loop (``evclock.run``).
        """
        from evclock.hosts._current import sim_clock
        from evclock.hosts._loop import SimEventLoop

        count = check_subscriber_count(count)
        timeout = check_wait_timeout(timeout)
        if self._dds is None:
            raise InvalidArgumentError(
                "wait_for_subscribers() counts DDS readers; this publisher speaks Zenoh"
            )
        loop = asyncio.get_running_loop()
        if not isinstance(loop, SimEventLoop):
            raise NotRunningError(
                "wait_for_subscribers() holds sim time: await it on a simulation's loop "
                "(evclock.run)"
            )
        held = sim_clock().now()
        deadline = time.monotonic() + timeout
        settled: float | None = None  # when the subscriptions' side has had its time
        with loop.hold_time():
            while settled is None or time.monotonic() < settled:
                matched = self._writer.matched()
                if matched < count:
                    settled = None
                    if time.monotonic() >= deadline:
                        raise Ros2SubscribersError(
                            f"{matched} of {count} {self._topic} subscription(s) matched in "
                            f"{timeout:g} s; start the ROS nodes (use_sim_time) in domain "
                            f"{self._domain_id}, or raise the timeout"
                        )
                elif settled is None:
                    settled = time.monotonic() + WAIT_SETTLE_S
                self.publish(held)
                loop._restart_stall_bound()  # this wait is bounded by its own timeout
                await loop.run_in_executor(None, time.sleep, WAIT_REPUBLISH_S)
        return matched

    async def run(self, hz: float) -> None:
        """Publish the running loop's sim time at ``hz`` of sim time, until cancelled."""
        from evclock.hosts._current import sim_clock

        async for tick in sim_clock().rate(hz, name=f"ros2 {self._topic} publisher"):
            self.publish(tick.actual)

    # ------------------------------------------------------------------ closing

    def close(self) -> None:
        """Withdraw the liveliness tokens and close the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._dds is not None:
            self._report_incompatible()
            self._dds.close()
            return
        try:
            for token in self._declared:
                token.undeclare()
            self._publisher.undeclare()
        finally:
            self._session.close()

    def __enter__(self) -> Ros2ClockPublisher:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"seq {self._sequence_number}"
        where = "rt" + self._topic if self._dds is not None else self._key_expr
        return f"<Ros2ClockPublisher {self._middleware} {where} ({self._wire.name}) {state}>"


def publish_every(
    source: SteppingTimeSource[Any], period: int, publish: Callable[[int], None]
) -> StepHook:
    """Call ``publish`` with ``source``'s time in ns now and after every ``period``-th physics
    step; returns the step hook (``remove()`` stops it)."""
    publish(source.now_ns)
    countdown = period

    def publish_step() -> None:
        nonlocal countdown
        countdown -= 1
        if countdown == 0:
            countdown = period
            publish(source.now_ns)

    return source.add_step_hook(publish_step, when="after")


def _check_at_least_one(value: object, what: str, meaning: str) -> int:
    """``value``, an int >= 1 (``meaning`` says what it counts, for the error)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidTypeError(f"{what} must be an int, got {type(value).__name__}")
    if value < 1:
        raise InvalidArgumentError(f"{what} must be >= 1 ({meaning}), got {value}")
    return value


def check_decimation(decimation: object) -> int:
    """A ``/clock`` decimation: an int >= 1."""
    return _check_at_least_one(decimation, "decimation", "1 = publish every step")


def check_subscriber_count(count: object, what: str = "count") -> int:
    """A number of subscribers to wait for: an int >= 1."""
    return _check_at_least_one(count, what, "the /clock subscriptions to wait for")


def check_wait_timeout(timeout: object, what: str = "timeout") -> float:
    """A wall-time bound in seconds: a finite number > 0."""
    if isinstance(timeout, bool) or not isinstance(timeout, int | float):
        raise InvalidTypeError(f"{what} must be a number of seconds, got {type(timeout).__name__}")
    if not (math.isfinite(timeout) and timeout > 0):
        raise InvalidArgumentError(f"{what} must be a positive number of seconds, got {timeout}")
    return float(timeout)
