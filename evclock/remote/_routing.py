"""Routing: publications and subscriptions, and the delivery of a round's data.

Data lockstep participants publish during a round is held in their outbox and delivered when
the round closes - to the simulation's subscribers, then to subscribed participants,
lockstep participants in join order - still at ``t``, before physics advances; a lockstep
participant that receives data is granted ``t`` again so it handles the data at ``t`` too.
Deterministic: nothing depends on arrival order. Outside a round, data is delivered at once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from evclock._errors import InvalidTypeError, ProtocolError
from evclock.remote import _protocol as proto
from evclock.remote._checks import shown
from evclock.remote._core import ServerCore
from evclock.remote._limits import exceeded
from evclock.remote._peer import Peer
from evclock.time._time import SIM, Time, new_time


@dataclasses.dataclass(frozen=True, slots=True)
class Message:
    """Data published on a topic: who sent it, at which sim time, and its bytes.

    :ivar sender: the name of the participant that published it (``"simulation"`` for
        :meth:`ClockServer.publish`).
    :ivar topic: the topic it was published on.
    :ivar time: the sim time it was published at.
    :ivar data: the payload.
    """

    sender: str
    topic: str
    time: Time
    data: bytes


class Routing(ServerCore):
    """The clock server's publications, subscriptions and round delivery."""

    def subscribe(self, topic: str, callback: Callable[[Message], object]) -> None:
        """Call ``callback(message)`` for data published on ``topic``, at its sim time,
        before physics advances past it."""
        if not callable(callback):
            raise InvalidTypeError(f"callback must be callable, got {type(callback).__name__}")
        proto.subscribe(topic)  # validates the name
        self._subscribers.setdefault(topic, []).append(callback)

    def publish(self, topic: str, data: bytes) -> None:
        """Send ``data`` on ``topic`` to the participants subscribed to it, stamped now."""
        if not isinstance(data, bytes | bytearray | memoryview):
            raise InvalidTypeError(f"data must be bytes, got {type(data).__name__}")
        proto.subscribe(topic)
        entry = ("simulation", self._kernel.now_ns, topic, bytes(data))
        if self._working:
            self._outbox.append(entry)
            self._round_has_data = True
        else:
            regrant: list[Peer] = []
            self._route(*entry, regrant)
            self._grant_all(regrant)

    def _on_publish(self, peer: Peer, payload: bytes) -> None:
        sent_at, topic, data = proto.parse_publish(payload)
        if peer.mode == proto.MODE_FOLLOW:
            raise ProtocolError(
                "a follower only reads time and data: it cannot publish to the simulation "
                "(join with ?mode=lockstep to take part)"
            )
        if peer.mode == proto.MODE_LOCKSTEP:
            if peer.working_at is None:
                raise ProtocolError("PUBLISH from a lockstep participant that is not working")
            # Sent before it read a JUMP: delivered with the round, stamped as sent.
            stamp = peer.working_at if peer.jump_acked == peer.jump_sent else sent_at
            limits = self._limits
            if len(peer.outbox) >= limits.round_frames:
                self._lost(
                    peer,
                    exceeded(limits, "round_frames", "published more often in one round"),
                )
                return
            held = peer.outbox_bytes + len(data)
            if held > limits.round_bytes:
                self._lost(
                    peer,
                    exceeded(limits, "round_bytes", f"published {held} bytes in one round"),
                )
                return
            peer.outbox_bytes = held
            peer.outbox.append((stamp, topic, data))
            self._round_has_data = True
        elif self._working:
            self._outbox.append((peer.name, self._kernel.now_ns, topic, data))
            self._round_has_data = True
        else:
            regrant: list[Peer] = []
            self._route(peer.name, self._kernel.now_ns, topic, data, regrant)
            self._grant_all(regrant)

    def _on_subscribe(self, peer: Peer, payload: bytes) -> None:
        topic = proto.parse_subscribe(payload)
        limits = self._limits
        length = len(topic.encode())
        if length > limits.topic_length:
            self._lost(
                peer,
                exceeded(limits, "topic_length", f"subscribed to a topic of {length} bytes"),
            )
        elif topic not in peer.subscriptions:
            if len(peer.subscriptions) >= limits.subscriptions:
                self._lost(
                    peer,
                    exceeded(limits, "subscriptions", "subscribed to one topic more"),
                )
                return
            peer.subscriptions.add(topic)

    def _close_round(self) -> None:
        """Deliver the round's data in a fixed order, still at this time."""
        if not self._round_has_data:
            return  # the common case: a round without data costs nothing here
        self._round_has_data = False
        regrant: list[Peer] = []
        self._deliver_round(regrant)
        self._grant_all(regrant)

    def _deliver_round(self, regrant: list[Peer]) -> None:
        while True:
            senders = sorted([*self._peers, *self._departed], key=lambda peer: peer.index)
            self._departed = []
            batch = [(peer.name, *entry) for peer in senders for entry in peer.outbox]
            for peer in senders:
                peer.outbox = []
                peer.outbox_bytes = 0
            batch += self._outbox
            self._outbox = []
            if not batch:
                break
            for sender, t_ns, topic, data in batch:
                self._route(sender, t_ns, topic, data, regrant)

    def _route(self, sender: str, t_ns: int, topic: str, data: bytes, regrant: list[Peer]) -> None:
        callbacks = self._subscribers.get(topic)
        if callbacks:
            message = Message(sender, topic, new_time(t_ns, SIM), data)
            for callback in callbacks:
                try:
                    callback(message)
                except Exception as exc:
                    origin = self._peer_named(sender)
                    if origin is not None:  # the participant's data was refused: tell it
                        self._bad_frame(
                            origin,
                            proto.PUBLISH,
                            f"the simulation refused data on topic {shown(topic)}: "
                            f"{type(exc).__name__}: {exc}",
                        )
                        continue
                    self._loop.call_exception_handler(
                        {
                            "message": f"subscriber {callback!r} of topic {shown(topic)} raised",
                            "exception": exc,
                        }
                    )
        frame = None
        for peer in self._peers:
            if topic in peer.subscriptions and peer.name != sender and not peer.lost:
                frame = frame or proto.deliver(t_ns, sender, topic, data)
                self._send(peer, frame)
                if peer.mode == proto.MODE_LOCKSTEP and peer not in regrant:
                    regrant.append(peer)

    def _peer_named(self, name: str) -> Peer | None:
        for peer in self._peers:
            if peer.name == name and not peer.lost:
                return peer
        return None

    def _grant_all(self, peers: list[Peer]) -> None:
        now = self._kernel.now_ns
        for peer in peers:
            if peer.working_at is None and not peer.lost and peer in self._peers:
                self._start_work(peer, now)
                self._send(peer, proto.grant(now))
