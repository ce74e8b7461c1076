"""What one participant may make the clock server hold: the :class:`Limits` table.

Every structure the server keeps per participant that the participant can grow is bounded
by one field here; exceeding one is a fault of that participant (under the server's
``on_fault`` policy) with an error naming the field and its value.
"""

from __future__ import annotations

import dataclasses

from evclock._errors import InvalidArgumentError, InvalidTypeError

#: The longest topic name the protocol carries (a one-byte length).
_PROTOCOL_TOPIC_LENGTH = 255


@dataclasses.dataclass(frozen=True, slots=True)
class Limits:
    """The most one participant may make the clock server hold; give it to
    :func:`evclock.remote.serve` (``limits=Limits(...)``).

    A participant that exceeds a limit is a fault under the server's ``on_fault`` policy
    (``abort``, ``drop`` or ``pause``, as a lost participant), with an error naming the limit
    and its value (``Limits.round_bytes=67108864``). Joined participants only: before its
    handshake completes a connection may send one frame of at most 4 KiB.

    What else a participant costs the server is bounded without a field: the frame being
    read (at most ``max_frame``), its calls (each answered at once, before its next frame is
    read: its reply is unsent output) and its name (255 bytes). Participants provide no
    services: only the simulation does (:meth:`ClockServer.provide`).

    :ivar round_bytes: bytes of data a lockstep participant may publish in one round (its
        outbox, delivered when the round closes); default 64 MiB.
    :ivar round_frames: publications a lockstep participant may make in one round;
        default 10,000.
    :ivar subscriptions: topics one participant may subscribe to; default 1,024.
    :ivar topic_length: the longest topic name (UTF-8 bytes) a participant may subscribe
        to; default 255, the protocol's own maximum (1 to 255).
    :ivar unsent_bytes: bytes the server may hold unsent for one participant (the time,
        data and replies it has not read yet); default 64 MiB.
    :raises InvalidTypeError: a field is not an integer.
    :raises InvalidArgumentError: a field is not positive, or ``topic_length`` is above 255.
    """

    round_bytes: int = 64 * 1024 * 1024
    round_frames: int = 10_000
    subscriptions: int = 1024
    topic_length: int = _PROTOCOL_TOPIC_LENGTH
    unsent_bytes: int = 64 * 1024 * 1024

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidTypeError(
                    f"Limits.{field.name} must be an integer, got {type(value).__name__} {value!r}"
                )
            if value <= 0:
                raise InvalidArgumentError(f"Limits.{field.name} must be positive, got {value!r}")
        if self.topic_length > _PROTOCOL_TOPIC_LENGTH:
            raise InvalidArgumentError(
                f"Limits.topic_length must be at most {_PROTOCOL_TOPIC_LENGTH} (the protocol's "
                f"longest topic name), got {self.topic_length!r}"
            )


def exceeded(limits: Limits, name: str, what: str) -> str:
    """Why a participant is faulted: ``what`` it did beyond the limit ``name`` of ``limits``."""
    return (
        f"exceeded Limits.{name}={getattr(limits, name)} ({what}; "
        f"serve(limits=Limits({name}=...)) sets another limit)"
    )
