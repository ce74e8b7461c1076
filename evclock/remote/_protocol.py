"""The wire format: length-prefixed binary frames, versioned by the first one.

Every frame is ``u32 length`` (little-endian, bytes after this field) + ``u8 kind`` + payload.

The handshake authenticates both sides without ever sending the token:

1. participant -> HELLO: magic ``EVCLK``, protocol version, mode, name, a fresh 32-byte nonce;
2. server -> CHALLENGE: its own fresh nonce and, when it has a token, its proof
   ``HMAC-SHA256(token, "evclock-server" + transcript)``;
3. participant -> PROOF: ``HMAC-SHA256(token, "evclock-client" + transcript)`` (empty without
   a token), sent only after it checked the server's proof;
4. server -> WELCOME (version, current sim time, its frame limit, scenario info as JSON) or
   REFUSE (a code - final or busy - and a reason), and then closes.

The transcript binds both nonces, the version, the mode and the name, so neither side's proof
can be replayed to another connection nor reflected to the other side. Until the handshake
completes a connection may send frames of :data:`PRE_AUTH_MAX_FRAME` bytes at most.

After that, per lockstep round only two fixed-size frames cross: GRANT(t) to the participant
and DONE(t, next deadline) back, each packed by a precompiled ``struct`` into one small
``bytes``. A well-framed but invalid frame from a participant is answered with ERROR (the
kind it was about and why) and otherwise ignored; a broken framing ends the connection.

Frames of one connection are handled in the order they were sent: data a participant
PUBLISHes before its DONE(t) is in the simulation's hands before that DONE is read, and data
DELIVERed before a JUMP is handled before the participant's clock jumps. Jumps are numbered;
the participant answers each with JUMPED(n), and the server ignores the DONEs it receives
between sending JUMP(n) and reading JUMPED(n) (sent before the jump was read).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct
from typing import Final

from evclock._errors import ProtocolError

MAGIC: Final = b"EVCLK"
VERSION: Final = 3  # 2: JUMP / JUMPED; 3: mutual challenge-response, ERROR, frame limits
#: The default limit on a frame after the handshake (``serve(max_frame=...)`` changes it).
MAX_FRAME: Final = 16 * 1024 * 1024
#: The largest ``max_frame`` a server accepts.
MAX_FRAME_LIMIT: Final = 256 * 1024 * 1024
#: The smallest ``max_frame`` a server accepts (a HELLO, a CALL of a few numbers).
MIN_FRAME_LIMIT: Final = 4096
#: Frames before the handshake completed (HELLO, PROOF; CHALLENGE, REFUSE) are at most this.
PRE_AUTH_MAX_FRAME: Final = 4096
#: Bytes of a nonce and of an HMAC-SHA256 proof.
NONCE_SIZE: Final = 32
PROOF_SIZE: Final = 32

# Frame kinds (one byte, printable for readable dumps).
HELLO: Final = ord("H")  # participant -> server: magic, version, mode, name, nonce
CHALLENGE: Final = ord("A")  # server -> participant: nonce, proof (empty: no token)
PROOF: Final = ord("Y")  # participant -> server: proof (empty: no token)
WELCOME: Final = ord("W")  # server -> participant: version, now, max frame, info (JSON)
REFUSE: Final = ord("X")  # server -> participant: code, reason (UTF-8); the server then closes
ERROR: Final = ord("E")  # server -> participant: the kind it is about, reason (UTF-8)
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
#: REFUSE codes: final (wrong token, name taken, version), busy (try again shortly), or TLS
#: (a plain connection reached a server that serves TLS only).
REFUSE_FINAL: Final = 0
REFUSE_BUSY: Final = 1
REFUSE_TLS: Final = 2

_HEADER = struct.Struct("<IB")
_STAMP = struct.Struct("<IBq")  # GRANT, TIME
_DONE = struct.Struct("<IBqq")
_HELLO_HEAD = struct.Struct("<5sHB")
_WELCOME_HEAD = struct.Struct("<HqI")
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


def _frame(kind: int, payload: bytes, limit: int = MAX_FRAME_LIMIT) -> bytes:
    if len(payload) + 1 > limit:
        raise ProtocolError(
            f"a frame of {len(payload) + 1} bytes exceeds the {limit}-byte frame limit of "
            "this connection; send large data another way and its key here"
        )
    return _HEADER.pack(len(payload) + 1, kind) + payload


def _short(text: str, what: str, limit: int = 255) -> bytes:
    raw = text.encode()
    if not 0 < len(raw) <= limit:
        raise ProtocolError(f"{what} must be 1 to {limit} bytes of UTF-8, got {text!r}")
    return bytes((len(raw),)) + raw


def new_nonce() -> bytes:
    """A fresh random nonce for one handshake."""
    return os.urandom(NONCE_SIZE)


def hello(mode: int, name: str, nonce: bytes, version: int = VERSION) -> bytes:
    """HELLO: who joins, how, and the participant's nonce (never a token)."""
    payload = _HELLO_HEAD.pack(MAGIC, version, mode) + _short(name, "a participant name") + nonce
    return _frame(HELLO, payload, PRE_AUTH_MAX_FRAME)


def transcript(
    version: int, mode: int, name: str, client_nonce: bytes, server_nonce: bytes
) -> bytes:
    """What both proofs cover: the version, the mode, the name and both nonces."""
    return (
        struct.pack("<HB", version, mode)
        + _short(name, "a participant name")
        + client_nonce
        + server_nonce
    )


def prove(token: str, side: bytes, transcript_bytes: bytes) -> bytes:
    """``HMAC-SHA256(token, side + transcript)``; ``side`` is b"evclock-server" or
    b"evclock-client", so a proof of one side is never valid for the other."""
    return hmac.new(token.encode(), side + transcript_bytes, hashlib.sha256).digest()


SERVER_SIDE: Final = b"evclock-server"
CLIENT_SIDE: Final = b"evclock-client"


def challenge(nonce: bytes, proof: bytes) -> bytes:
    """CHALLENGE: the server's nonce and its proof (empty when it has no token)."""
    return _frame(CHALLENGE, nonce + proof, PRE_AUTH_MAX_FRAME)


def parse_challenge(payload: bytes) -> tuple[bytes, bytes]:
    """``(server nonce, server proof)``; the proof is empty when the server has no token."""
    if len(payload) not in (NONCE_SIZE, NONCE_SIZE + PROOF_SIZE):
        raise ProtocolError(f"a CHALLENGE of {len(payload)} bytes (expected 32 or 64)")
    return payload[:NONCE_SIZE], payload[NONCE_SIZE:]


def proof(value: bytes) -> bytes:
    """PROOF: the participant's proof (empty without a token)."""
    return _frame(PROOF, value, PRE_AUTH_MAX_FRAME)


def welcome(now_ns: int, max_frame: int, info: bytes) -> bytes:
    """WELCOME: joined; the current sim time, the server's frame limit, its scenario info."""
    return _frame(WELCOME, _WELCOME_HEAD.pack(VERSION, now_ns, max_frame) + info)


def refuse(reason: str, code: int = REFUSE_FINAL) -> bytes:
    """REFUSE: not joined (``REFUSE_BUSY``: try again shortly); the server then closes."""
    return _frame(
        REFUSE, bytes((code,)) + reason.encode()[: PRE_AUTH_MAX_FRAME - 16], PRE_AUTH_MAX_FRAME
    )


def parse_refuse(payload: bytes) -> tuple[int, str]:
    """``(code, reason)``."""
    if not payload:
        return REFUSE_FINAL, "no reason given"
    return payload[0], payload[1:].decode(errors="replace")


def error(about: int, reason: str) -> bytes:
    """ERROR: a frame of kind ``about`` from the participant was refused, and why."""
    return _frame(ERROR, bytes((about & 0xFF,)) + reason.encode()[:65536])


def parse_error(payload: bytes) -> tuple[int, str]:
    """``(kind the error is about, reason)``."""
    _need(payload, 1, "ERROR")
    return payload[0], payload[1:].decode(errors="replace")


def closing(reason: str) -> bytes:
    return _frame(CLOSING, reason.encode())


def bye() -> bytes:
    return _frame(BYE, b"")


def publish(t_ns: int, topic: str, data: bytes, limit: int = MAX_FRAME_LIMIT) -> bytes:
    return _frame(PUBLISH, _Q.pack(t_ns) + _short(topic, "a topic name") + data, limit)


def subscribe(topic: str) -> bytes:
    return _frame(SUBSCRIBE, _short(topic, "a topic name"))


def deliver(t_ns: int, sender: str, topic: str, data: bytes) -> bytes:
    return _frame(
        DELIVER, _Q.pack(t_ns) + _short(sender, "a sender name") + _short(topic, "a topic") + data
    )


def call(call_id: int, service: str, data: bytes, limit: int = MAX_FRAME_LIMIT) -> bytes:
    return _frame(CALL, _I.pack(call_id) + _short(service, "a service name") + data, limit)


def reply(call_id: int, ok: bool, data: bytes) -> bytes:
    return _frame(REPLY, _IB.pack(call_id, 1 if ok else 0) + data)


# ------------------------------------------------------------------ decoding


class Reader:
    """Splits a byte stream into ``(kind, payload)`` frames of at most ``limit`` bytes.

    A frame whose header announces more than ``limit`` bytes is a :class:`ProtocolError`
    before any of it is buffered: a reader never holds more than ``limit + 4`` bytes of a
    partial frame (plus the one read being split).
    """

    __slots__ = ("limit", "pending")

    def __init__(self, limit: int = MAX_FRAME) -> None:
        #: The bytes of a partial frame received so far: empty between frames (read as a
        #: plain attribute on every lockstep round, where a property would cost a call).
        self.pending = bytearray()
        #: The largest frame accepted (length field: kind byte + payload).
        self.limit = limit

    @property
    def between_frames(self) -> bool:
        """No partial frame is buffered: the next byte received starts a frame."""
        return not self.pending

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """Append received bytes; return every frame now complete, in order."""
        buf = self.pending
        if not buf and len(data) >= 5:  # the hot path: exactly one whole frame (a GRANT, a DONE)
            length, kind = _HEADER.unpack_from(data)
            if len(data) == 4 + length and 0 < length <= self.limit:
                return [(kind, data[5:])]
        buf += data
        frames = []
        pos = 0
        end = len(buf)
        unpack = _HEADER.unpack_from
        limit = self.limit
        while end - pos >= 5:
            length, kind = unpack(buf, pos)
            if length == 0 or length > limit:
                buf.clear()
                raise ProtocolError(
                    f"bad frame length {length}: the limit of this connection is {limit} "
                    "bytes (not an evclock clock peer, a frame too large for the server's "
                    "max_frame, or a corrupted stream)"
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


def parse_hello(payload: bytes) -> tuple[int, int, str, bytes]:
    """``(version, mode, name, nonce)``; ProtocolError for anything but an evclock HELLO.

    A HELLO of another version returns its version with an empty name and nonce (its layout
    after the version may differ): the caller refuses it naming both versions.
    """
    if payload[:5] != MAGIC[: len(payload[:5])] or len(payload) < _HELLO_HEAD.size:
        raise ProtocolError("the first frame is not an evclock HELLO")
    magic, version, mode = _HELLO_HEAD.unpack_from(payload)
    if magic != MAGIC:
        raise ProtocolError("the first frame is not an evclock HELLO")
    if version != VERSION:
        return version, mode, "", b""
    name, pos = _take_short(payload, _HELLO_HEAD.size, "the participant name")
    nonce = payload[pos:]
    if len(nonce) != NONCE_SIZE:
        raise ProtocolError(f"a HELLO nonce of {len(nonce)} bytes (expected {NONCE_SIZE})")
    if mode not in (MODE_LOCKSTEP, MODE_FOLLOW):
        raise ProtocolError(f"unknown participant mode {mode}")
    return version, mode, name, nonce


def parse_welcome(payload: bytes) -> tuple[int, int, int, bytes]:
    """``(version, now_ns, max_frame, info)``."""
    if len(payload) >= 2 and struct.unpack_from("<H", payload)[0] != VERSION:
        return struct.unpack_from("<H", payload)[0], 0, 0, b""
    _need(payload, _WELCOME_HEAD.size, "WELCOME")
    version, now_ns, max_frame = _WELCOME_HEAD.unpack_from(payload)
    return version, now_ns, max_frame, payload[_WELCOME_HEAD.size :]


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
