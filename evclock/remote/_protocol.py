"""The wire format: length-prefixed binary frames, versioned by the first one.

Every frame is ``u32 length`` (little-endian, bytes after this field) + ``u8 kind`` + payload.
The participant opens with HELLO (magic ``EVCLK``, protocol version, mode, name, token); the
server answers WELCOME (version, current sim time, scenario info as JSON) or REFUSE (a
reason) and closes. After that, per lockstep round only two fixed-size frames cross:
GRANT(t) to the participant and DONE(t, next deadline) back, each packed by a precompiled
``struct`` into one small ``bytes``.

Frames of one connection are handled in the order they were sent: data a participant
PUBLISHes before its DONE(t) is in the simulation's hands before that DONE is read, and data
DELIVERed before a JUMP is handled before the participant's clock jumps. Jumps are numbered;
the participant answers each with JUMPED(n), and the server ignores the DONEs it receives
between sending JUMP(n) and reading JUMPED(n) (sent before the jump was read).
"""

from __future__ import annotations

import struct
from typing import Final

from evclock._errors import ProtocolError

MAGIC: Final = b"EVCLK"
VERSION: Final = 2  # 2: JUMP / JUMPED (time jumps reach participants)
#: Frames larger than this are garbage (or a different protocol): the connection is dropped.
MAX_FRAME: Final = 16 * 1024 * 1024

# Frame kinds (one byte, printable for readable dumps).
HELLO: Final = ord("H")  # participant -> server: magic, version, mode, name, token
WELCOME: Final = ord("W")  # server -> participant: version, now, info (JSON)
REFUSE: Final = ord("X")  # server -> participant: reason (UTF-8); the server then closes
GRANT: Final = ord("G")  # server -> participant: run everything due at t
TIME: Final = ord("T")  # server -> follower: sim time is now t
DONE: Final = ord("D")  # participant -> server: finished at t, next deadline (-1: none)
PUBLISH: Final = ord("P")  # participant -> server: t, topic, data
SUBSCRIBE: Final = ord("S")  # participant -> server: topic
DELIVER: Final = ord("M")  # server -> participant: t, sender, topic, data
CALL: Final = ord("C")  # participant -> server: call id, service, data
REPLY: Final = ord("R")  # server -> participant: call id, ok, data (or error text)
BYE: Final = ord("B")  # participant -> server: leaving cleanly
CLOSING: Final = ord("Z")  # server -> participant: the server stops serving (reason)
JUMP: Final = ord("J")  # server -> participant: jump number, before, after (a time jump)
JUMPED: Final = ord("K")  # participant -> server: jump number (applied; DONEs count again)

MODE_LOCKSTEP: Final = 0
MODE_FOLLOW: Final = 1
NO_DEADLINE: Final = -1

_HEADER = struct.Struct("<IB")
_STAMP = struct.Struct("<IBq")  # GRANT, TIME
_DONE = struct.Struct("<IBqq")
_HELLO_HEAD = struct.Struct("<5sHB")
_WELCOME_HEAD = struct.Struct("<Hq")
_Q = struct.Struct("<q")
_I = struct.Struct("<I")
_IB = struct.Struct("<IB")

HEADER_SIZE: Final = _HEADER.size
_STAMP_PACK = _STAMP.pack
_DONE_PACK = _DONE.pack

# The hot path of a round: a read that is exactly one GRANT (participant) or one DONE (server)
# is unpacked in one call, header included, without going through a Reader.
#: Bytes of a GRANT/TIME frame; ``unpack_stamp(frame)`` -> ``(length, kind, t_ns)``.
STAMP_SIZE: Final = _STAMP.size
unpack_stamp: Final = _STAMP.unpack
#: Bytes of a DONE frame; ``unpack_done(frame)`` -> ``(length, kind, t_ns, next_ns)``.
DONE_SIZE: Final = _DONE.size
unpack_done: Final = _DONE.unpack


def grant(t_ns: int) -> bytes:
    """GRANT: run everything due at ``t_ns``, then answer DONE."""
    return _STAMP_PACK(9, GRANT, t_ns)


def time_frame(t_ns: int) -> bytes:
    """TIME: sim time is now ``t_ns`` (to followers)."""
    return _STAMP_PACK(9, TIME, t_ns)


def done(t_ns: int, next_ns: int) -> bytes:
    """DONE: finished everything at ``t_ns``; the next deadline (``NO_DEADLINE``: none)."""
    return _DONE_PACK(17, DONE, t_ns, next_ns)


_JUMP = struct.Struct("<Iqq")


def jump(seq: int, before_ns: int, after_ns: int) -> bytes:
    """JUMP: the simulation's time jumped (reset, restored snapshot, ``set_time``)."""
    return _frame(JUMP, _JUMP.pack(seq, before_ns, after_ns))


def jumped(seq: int) -> bytes:
    """JUMPED: the participant applied jump ``seq``; its next DONE is at the new time."""
    return _frame(JUMPED, _I.pack(seq))


def parse_jump(payload: bytes) -> tuple[int, int, int]:
    """``(seq, before_ns, after_ns)``."""
    _need(payload, _JUMP.size, "JUMP")
    seq, before, after = _JUMP.unpack_from(payload)
    return seq, before, after


def parse_jumped(payload: bytes) -> int:
    _need(payload, 4, "JUMPED")
    value: int = _I.unpack_from(payload)[0]
    return value


def _frame(kind: int, payload: bytes) -> bytes:
    if len(payload) + 1 > MAX_FRAME:
        raise ProtocolError(
            f"a frame of {len(payload)} bytes exceeds the protocol's {MAX_FRAME}-byte limit; "
            "send large data another way and its key here"
        )
    return _HEADER.pack(len(payload) + 1, kind) + payload


def _short(text: str, what: str, limit: int = 255) -> bytes:
    raw = text.encode()
    if not 0 < len(raw) <= limit:
        raise ProtocolError(f"{what} must be 1 to {limit} bytes of UTF-8, got {text!r}")
    return bytes((len(raw),)) + raw


def hello(mode: int, name: str, token: str | None, version: int = VERSION) -> bytes:
    raw_token = (token or "").encode()
    payload = (
        _HELLO_HEAD.pack(MAGIC, version, mode)
        + _short(name, "a participant name")
        + struct.pack("<H", len(raw_token))
        + raw_token
    )
    return _frame(HELLO, payload)


def welcome(now_ns: int, info: bytes) -> bytes:
    return _frame(WELCOME, _WELCOME_HEAD.pack(VERSION, now_ns) + info)


def refuse(reason: str) -> bytes:
    return _frame(REFUSE, reason.encode())


def closing(reason: str) -> bytes:
    return _frame(CLOSING, reason.encode())


def bye() -> bytes:
    return _frame(BYE, b"")


def publish(t_ns: int, topic: str, data: bytes) -> bytes:
    return _frame(PUBLISH, _Q.pack(t_ns) + _short(topic, "a topic name") + data)


def subscribe(topic: str) -> bytes:
    return _frame(SUBSCRIBE, _short(topic, "a topic name"))


def deliver(t_ns: int, sender: str, topic: str, data: bytes) -> bytes:
    return _frame(
        DELIVER, _Q.pack(t_ns) + _short(sender, "a sender name") + _short(topic, "a topic") + data
    )


def call(call_id: int, service: str, data: bytes) -> bytes:
    return _frame(CALL, _I.pack(call_id) + _short(service, "a service name") + data)


def reply(call_id: int, ok: bool, data: bytes) -> bytes:
    return _frame(REPLY, _IB.pack(call_id, 1 if ok else 0) + data)


# ------------------------------------------------------------------ decoding


class Reader:
    """Splits a byte stream into ``(kind, payload)`` frames."""

    __slots__ = ("pending",)

    def __init__(self) -> None:
        #: The bytes of a partial frame received so far: empty between frames (read as a
        #: plain attribute on every lockstep round, where a property would cost a call).
        self.pending = bytearray()

    @property
    def between_frames(self) -> bool:
        """No partial frame is buffered: the next byte received starts a frame."""
        return not self.pending

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """Append received bytes; return every frame now complete, in order."""
        buf = self.pending
        if not buf and len(data) >= 5:  # the hot path: exactly one whole frame (a GRANT, a DONE)
            length, kind = _HEADER.unpack_from(data)
            if len(data) == 4 + length and 0 < length <= MAX_FRAME:
                return [(kind, data[5:])]
        buf += data
        frames = []
        pos = 0
        end = len(buf)
        unpack = _HEADER.unpack_from
        while end - pos >= 5:
            length, kind = unpack(buf, pos)
            if length == 0 or length > MAX_FRAME:
                raise ProtocolError(
                    f"bad frame length {length} (not an evclock clock peer, or a corrupted stream)"
                )
            if end - pos - 4 < length:
                break
            frames.append((kind, bytes(buf[pos + 5 : pos + 4 + length])))
            pos += 4 + length
        if pos:
            del buf[:pos]
        return frames


def _take_short(payload: bytes, pos: int, what: str) -> tuple[str, int]:
    if pos >= len(payload):
        raise ProtocolError(f"truncated frame: {what} missing")
    size = payload[pos]
    raw = payload[pos + 1 : pos + 1 + size]
    if len(raw) != size or size == 0:
        raise ProtocolError(f"truncated frame: {what} cut short")
    try:
        return raw.decode(), pos + 1 + size
    except UnicodeDecodeError:
        raise ProtocolError(f"{what} is not UTF-8") from None


def _need(payload: bytes, size: int, what: str) -> None:
    if len(payload) < size:
        raise ProtocolError(f"truncated {what} frame ({len(payload)} bytes, needs {size})")


def parse_hello(payload: bytes) -> tuple[int, int, str, str]:
    """``(version, mode, name, token)``; ProtocolError for anything but an evclock HELLO."""
    if payload[:5] != MAGIC[: len(payload[:5])] or len(payload) < _HELLO_HEAD.size:
        raise ProtocolError("the first frame is not an evclock HELLO")
    magic, version, mode = _HELLO_HEAD.unpack_from(payload)
    if magic != MAGIC:
        raise ProtocolError("the first frame is not an evclock HELLO")
    if version != VERSION:
        return version, mode, "", ""
    name, pos = _take_short(payload, _HELLO_HEAD.size, "the participant name")
    _need(payload, pos + 2, "HELLO")
    (token_size,) = struct.unpack_from("<H", payload, pos)
    token = payload[pos + 2 : pos + 2 + token_size]
    if mode not in (MODE_LOCKSTEP, MODE_FOLLOW):
        raise ProtocolError(f"unknown participant mode {mode}")
    return version, mode, name, token.decode(errors="replace")


def parse_welcome(payload: bytes) -> tuple[int, int, bytes]:
    """``(version, now_ns, info)``."""
    _need(payload, _WELCOME_HEAD.size, "WELCOME")
    version, now_ns = _WELCOME_HEAD.unpack_from(payload)
    return version, now_ns, payload[_WELCOME_HEAD.size :]


def parse_stamp(payload: bytes) -> int:
    """The time of a GRANT or TIME frame."""
    _need(payload, 8, "GRANT/TIME")
    value: int = _Q.unpack_from(payload)[0]
    return value


def parse_done(payload: bytes) -> tuple[int, int]:
    _need(payload, 16, "DONE")
    t_ns, next_ns = struct.unpack_from("<qq", payload)
    return t_ns, next_ns


def parse_publish(payload: bytes) -> tuple[int, str, bytes]:
    _need(payload, 9, "PUBLISH")
    (t_ns,) = _Q.unpack_from(payload)
    topic, pos = _take_short(payload, 8, "the topic")
    return t_ns, topic, payload[pos:]


def parse_subscribe(payload: bytes) -> str:
    topic, _ = _take_short(payload, 0, "the topic")
    return topic


def parse_deliver(payload: bytes) -> tuple[int, str, str, bytes]:
    _need(payload, 9, "DELIVER")
    (t_ns,) = _Q.unpack_from(payload)
    sender, pos = _take_short(payload, 8, "the sender")
    topic, pos = _take_short(payload, pos, "the topic")
    return t_ns, sender, topic, payload[pos:]


def parse_call(payload: bytes) -> tuple[int, str, bytes]:
    _need(payload, 5, "CALL")
    (call_id,) = _I.unpack_from(payload)
    service, pos = _take_short(payload, 4, "the service")
    return call_id, service, payload[pos:]


def parse_reply(payload: bytes) -> tuple[int, bool, bytes]:
    _need(payload, 5, "REPLY")
    call_id, ok = _IB.unpack_from(payload)
    return call_id, bool(ok), payload[5:]
