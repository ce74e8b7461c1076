"""Publishing evclock's sim time as ROS 2 ``/clock`` over Zenoh, as an rmw_zenoh node would."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

from evclock._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
)
from evclock.ros2._session import (
    DEFAULT_CONNECT,
    DEFAULT_LISTEN,
    check_endpoints,
    open_session,
    require,
)
from evclock.ros2._wire import (
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
    from evclock.sources import PyBulletTimeSource, StepHook

_NODE_ID = 0
_PUBLISHER_ID = 1


class Ros2ClockPublisher:
    """A ROS 2 node publishing ``rosgraph_msgs/msg/Clock`` on ``topic`` through Zenoh.

    It speaks rmw_zenoh's wire format (``wire_format``, default ``"jazzy"``: see
    :data:`evclock.ros2.WIRE_FORMATS`), so ROS 2 nodes on rmw_zenoh with ``use_sim_time``
    follow it, and declares the liveliness tokens of a node ``node_name`` and of its
    publisher, so ``ros2 node list`` / ``ros2 topic list`` / ``ros2 topic echo /clock`` see it.

    The session is a Zenoh peer that connects to ``connect`` (default: rmw_zenoh's router on
    ``tcp/127.0.0.1:7447``) and accepts peers on ``listen``; multicast scouting is off.
    ``domain_id`` defaults to ``ROS_DOMAIN_ID`` (else 0), as in ROS. ``wall_clock_ns`` gives
    the attachments' source timestamps (wall-clock ns since the epoch, as rmw_zenoh sends).

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
        connect: Sequence[str] = DEFAULT_CONNECT,
        listen: Sequence[str] = DEFAULT_LISTEN,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._domain_id = resolve_domain_id(domain_id)
        self._topic = resolve_topic(topic)
        self._node_name = check_node_name(node_name)
        self._wire = lookup_wire_format(wire_format)
        connect = check_endpoints(connect, "connect")
        listen = check_endpoints(listen, "listen")
        if not callable(wall_clock_ns):
            raise InvalidTypeError("wall_clock_ns must be a callable returning wall-clock ns")
        self._wall_clock_ns = wall_clock_ns
        self._key_expr = clock_key_expr(self._domain_id, self._topic, self._wire)
        zenoh = require("zenoh")
        self._session: Any = open_session(connect, listen)
        self._closed = False
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
        self._sequence_number = 0

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
        """The rmw_zenoh wire variant spoken."""
        return self._wire

    @property
    def key_expr(self) -> str:
        """The Zenoh key expression the samples are put on."""
        return self._key_expr

    @property
    def liveliness_tokens(self) -> tuple[str, ...]:
        """The declared liveliness tokens: the node's, then the publisher's."""
        return self._tokens

    @property
    def gid(self) -> bytes:
        """The publisher's 16-byte GID (sent in every attachment)."""
        return self._gid

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
        attachment = encode_attachment(
            self._sequence_number, self._wall_clock_ns(), self._gid, self._wire
        )
        self._publisher.put(payload, attachment=attachment)

    def attach(self, source: PyBulletTimeSource, *, decimation: int = 1) -> StepHook:
        """Publish ``source``'s time now and after every ``decimation``-th physics step.

        Returns the step hook (``remove()`` stops publishing). Per-step hooks make the
        source step one step at a time, which is what publishing every step needs.
        """
        from evclock.sources import PyBulletTimeSource

        if not isinstance(source, PyBulletTimeSource):
            raise InvalidTypeError(
                f"attach() takes a PyBulletTimeSource, got {type(source).__name__}; on another "
                "source publish at a sim-time rate with run(hz)"
            )
        period = _check_decimation(decimation)
        self.publish(source.now_ns)
        countdown = period

        def publish_step() -> None:
            nonlocal countdown
            countdown -= 1
            if countdown == 0:
                countdown = period
                self.publish(source.now_ns)

        return source.add_step_hook(publish_step, when="after")

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
        return f"<Ros2ClockPublisher {self._key_expr} ({self._wire.name}) {state}>"


def _check_decimation(decimation: object) -> int:
    if isinstance(decimation, bool) or not isinstance(decimation, int):
        raise InvalidTypeError(f"decimation must be an int, got {type(decimation).__name__}")
    if decimation < 1:
        raise InvalidArgumentError(
            f"decimation must be >= 1 (1 = publish every step), got {decimation}"
        )
    return decimation
