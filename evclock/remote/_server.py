"""The clock server: a simulation serves its sim time to processes that join it.

It lives on the simulation's :class:`~evclock.SimEventLoop` and uses nothing but the loop's
own machinery: sockets are registered with ``add_reader``; while lockstep participants work
at time ``t`` the server holds sim time exactly like an executor job does (the loop's hold
count), and their next deadlines are ordinary entries of the loop's timer heap. So physics
cannot advance while a participant works, nor past a participant's deadline, and a
participant with no deadline due in a step costs nothing in that step.

Participants' deadlines are grouped by time: one loop timer per distinct deadline grants
every participant due then, in join order (so a round of N participants costs one timer, not
N), and the round holds sim time once, however many participants work in it.

A *round* at time ``t`` is open while some lockstep participant works at ``t``. Data
participants publish during a round is delivered when the round closes - to the simulation's
subscribers, then to subscribed participants, lockstep participants in join order - still at
``t``, before physics advances; a lockstep participant that receives data is granted ``t``
again so it handles the data at ``t`` too. Deterministic: nothing depends on arrival order.

A time jump of the simulation (a jump handler on its clock) delivers the open round's data,
cancels every participant's deadline and sends a numbered JUMP to all of them: each clock
jumps alike, lockstep participants work at the new time, and DONEs sent before a
participant read the JUMP (until its JUMPED) are ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hmac
import json
import logging
import operator
import os
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from typing import Any, Final

from evclock._errors import (
    EvClockError,
    InvalidArgumentError,
    InvalidTypeError,
    ParticipantLostError,
    ProtocolError,
)
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._jumps import JumpThreshold, TimeJump
from evclock.outside._threads import mark_internal
from evclock.remote import _protocol as proto
from evclock.remote._address import (
    bound_address,
    listen,
    parse_address,
    peer_credentials,
    private_dir,
)
from evclock.time._time import SIM, Duration, Time, new_time

log = logging.getLogger("evclock.remote")
_BY_INDEX: Final = operator.attrgetter("index")

FAULT_POLICIES: Final = ("abort", "drop", "pause")
#: Wall seconds a participant may work on one step before the fault policy applies.
DEFAULT_STEP_TIMEOUT: Final = 30.0
#: Wall seconds the simulation waits for its participants to join, by default.
DEFAULT_JOIN_TIMEOUT: Final = 60.0
#: Wall seconds between keepalives to waiting participants (their ``timeout`` must be longer).
KEEPALIVE: Final = 0.2
#: Wall seconds a new connection has to complete its handshake (HELLO and PROOF).
HELLO_TIMEOUT: Final = 5.0
#: Connections in their handshake at once; more are refused as busy (the participant retries).
MAX_PENDING: Final = 64
#: A peer whose unsent backlog grows past this many bytes is not reading: a fault.
_MAX_BACKLOG: Final = 64 * 1024 * 1024
#: Bad frames answered with ERROR per participant before it is treated as lost (a flood).
MAX_ERRORS: Final = 10_000


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


class _Peer:
    """One connection: a participant once its HELLO was accepted."""

    __slots__ = (
        "accepted_at",
        "client_nonce",
        "deadline",
        "errors",
        "greeted",
        "index",
        "jump_acked",
        "jump_sent",
        "lost",
        "mode",
        "name",
        "out",
        "outbox",
        "pid",
        "reader",
        "server_nonce",
        "silent_reported",
        "sock",
        "stale_time",
        "subscriptions",
        "working_at",
        "working_since",
    )

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.reader = proto.Reader(proto.PRE_AUTH_MAX_FRAME)  # until the handshake completes
        self.out = bytearray()
        self.accepted_at = time.monotonic()
        self.pid: int | None = None  # SO_PEERCRED, on a Unix socket
        self.greeted = ""  # the name its HELLO gave (its PROOF is awaited)
        self.client_nonce = b""
        self.server_nonce = b""
        self.errors = 0  # bad frames answered with ERROR so far
        self.name = ""  # empty until the handshake completed
        self.mode = proto.MODE_LOCKSTEP
        self.index = -1
        self.working_at: int | None = None
        self.working_since: float | None = None
        self.deadline: int | None = None  # sim ns it asked to be granted (told) at
        self.outbox: list[tuple[int, str, bytes]] = []
        self.subscriptions: set[str] = set()  # membership tests only, never iterated
        self.lost = False
        self.silent_reported = False
        self.stale_time = False
        self.jump_sent = 0  # the last JUMP sent to it, and the last it applied (JUMPED):
        self.jump_acked = 0  # until they match, its DONEs are from before the jump

    def describe(self) -> str:
        mode = "lockstep" if self.mode == proto.MODE_LOCKSTEP else "follow"
        pid = "" if self.pid is None else f", pid {self.pid}"
        return f"{self.name!r} ({mode}{pid})"

    def last_did(self) -> str:
        """What it was last seen doing, for the message that reports it lost."""
        if self.working_at is not None:
            since = self.working_since
            waited = 0.0 if since is None else time.monotonic() - since
            return (
                f"it was last granted {self.working_at / 1e9:.6f} s of sim time and had not "
                f"answered for {waited:.1f} s of wall time"
            )
        if self.deadline is not None:
            return (
                f"it had finished its step and asked to run again at "
                f"{self.deadline / 1e9:.6f} s of sim time"
            )
        if self.mode == proto.MODE_LOCKSTEP:
            return "it had finished its step with no deadline ahead"
        return "it was following the simulation's time"


def default_address() -> str:
    """A per-process Unix socket in the user's private directory (see ``private_dir``)."""
    return f"unix://{private_dir()}/sim-{os.getpid()}.sock"


class ClockServer:
    """Serves a :class:`~evclock.SimEventLoop`'s sim time; create it with
    :func:`evclock.remote.serve`.

    Participants join in *lockstep* (the simulation waits for them every step they have a
    deadline in) or *follow* (they receive every step's time and never hold the simulation).

    The options are those of :func:`~evclock.remote.serve`, which documents them in full.

    :param loop: the :class:`~evclock.SimEventLoop` whose sim time is served.
    :param address: ``unix:///path.sock`` or ``tcp://HOST:PORT`` to listen on.
    :param on_fault: ``abort``, ``drop`` or ``pause``: what a lost lockstep participant causes.
    :param step_timeout: wall seconds a lockstep participant may work on one step (None: no
        limit).
    :param token: the shared secret participants must present (default: the address's
        ``?token=``).
    :param info: JSON-serialisable facts given to every participant at join.
    :param allow_remote: allow listening on a non-loopback address (which needs a token).
    :param max_frame: the largest frame (bytes) a joined participant may send.
    :param peer_uids: user ids allowed to join over a Unix socket (default: this user's).
    :raises InvalidArgumentError: an unknown ``on_fault``, a bad ``step_timeout`` or
        ``max_frame``, an invalid or unusable address, a TCP address without a token, a
        non-loopback address without ``allow_remote``, or ``info`` that is not
        JSON-serialisable.
    :raises InvalidTypeError: ``token`` is not a non-empty string, ``address`` is not a
        string, or ``peer_uids`` holds something other than integers.
    """

    def __init__(
        self,
        loop: SimEventLoop,
        address: str,
        *,
        on_fault: str = "abort",
        step_timeout: float | None = DEFAULT_STEP_TIMEOUT,
        token: str | None = None,
        info: Mapping[str, Any] | None = None,
        allow_remote: bool = False,
        max_frame: int = proto.MAX_FRAME,
        peer_uids: Iterable[int] | None = None,
    ) -> None:
        if (
            isinstance(max_frame, bool)
            or not isinstance(max_frame, int)
            or not proto.MIN_FRAME_LIMIT <= max_frame <= proto.MAX_FRAME_LIMIT
        ):
            raise InvalidArgumentError(
                f"max_frame must be a number of bytes from {proto.MIN_FRAME_LIMIT} to "
                f"{proto.MAX_FRAME_LIMIT}, got {max_frame!r}"
            )
        uids = (os.getuid(),) if peer_uids is None else tuple(peer_uids)
        if not all(isinstance(u, int) and not isinstance(u, bool) for u in uids):
            raise InvalidTypeError(f"peer_uids must be integer user ids, got {peer_uids!r}")
        if on_fault not in FAULT_POLICIES:
            raise InvalidArgumentError(
                f"on_fault must be one of {', '.join(FAULT_POLICIES)}, got {on_fault!r}"
            )
        if step_timeout is not None and (
            isinstance(step_timeout, bool)
            or not isinstance(step_timeout, int | float)
            or not step_timeout > 0
        ):
            raise InvalidArgumentError(
                f"step_timeout must be a positive number of wall seconds or None, "
                f"got {step_timeout!r}"
            )
        if token is not None and (not isinstance(token, str) or not token):
            raise InvalidTypeError("token must be a non-empty string or None")
        parsed = parse_address(address, participant=False)
        token = token if token is not None else parsed.token
        if parsed.scheme == "tcp" and token is None:
            raise InvalidArgumentError(
                f"serving on {parsed} needs a shared token (token=... or ?token=... in the "
                "address): any user of the machine can reach a tcp port, so participants "
                "must prove they know it (it is never sent); or serve on a unix:// socket"
            )
        try:
            self._info = json.dumps(dict(info or {}), sort_keys=True).encode()
        except (TypeError, ValueError) as exc:
            raise InvalidArgumentError(f"info must be JSON-serialisable: {exc}") from None
        self._loop = loop
        # Its kernel (SimClock.core): sim time read as a plain attribute on every round.
        self._kernel = loop.clock.core
        self._policy = on_fault
        self._step_timeout = None if step_timeout is None else float(step_timeout)
        self._token = token
        self._max_frame = max_frame
        self._peer_uids = uids
        self._listener = listen(parsed, allow_remote=allow_remote)
        self._address = bound_address(self._listener, parsed)
        self._pending: list[_Peer] = []  # connected, HELLO not yet accepted
        self._peers: list[_Peer] = []  # joined, in join order
        self._departed: list[_Peer] = []  # left cleanly with data still to deliver
        self._joined = 0
        self._working = 0  # lockstep participants working at the current time
        self._holds = 0  # holds on the loop's sim time that this server owns
        # Deadline (sim ns) -> its loop timer and the participants due then.
        self._due: dict[int, tuple[asyncio.TimerHandle, list[_Peer]]] = {}
        self._outbox: list[tuple[str, int, str, bytes]] = []  # from the simulation/followers
        self._round_has_data = False  # anything queued for the end of the round
        self._subscribers: dict[str, list[Callable[[Message], object]]] = {}
        self._services: dict[str, Callable[[bytes], bytes]] = {}
        self._dropped: list[tuple[str, str]] = []
        self._waiters: list[tuple[Callable[[], bool], asyncio.Future[None]]] = []
        self._failure: EvClockError | None = None
        self._owner: asyncio.Task[Any] | None = None
        self._step_hook: Any = None
        self._closed = False
        self._check_scheduled = False
        self._join_deadline: float | None = None
        self._join_missing: Callable[[], str] = str
        self._jumps = 0  # time jumps of the simulation so far (JUMP frames are numbered)
        # Every jump, either way, reaches the participants (their clocks jump alike).
        self._jump_handle = loop.clock.on_jump(
            self._before_jump,
            self._after_jump,
            threshold=JumpThreshold(min_forward=Duration(nanoseconds=1)),
        )
        loop.add_reader(self._listener, self._on_accept)
        # A listening socket carries no bytes in flight, nor is it a terminal: the server
        # accounts for it (the loop neither asks it for queued bytes nor polls it for tty
        # input before time moves).
        loop.account_fd(self._listener.fileno(), True)
        self._stop_watch = threading.Event()
        self._watchdog = threading.Thread(
            target=self._watch, name="evclock-clock-server-watchdog", daemon=True
        )
        mark_internal(self._watchdog)
        self._watchdog.start()

    # ------------------------------------------------------------ public API

    @property
    def address(self) -> str:
        """The address participants join (``unix:///...`` or ``tcp://host:port``)."""
        return str(self._address)

    @property
    def participants(self) -> tuple[str, ...]:
        """Names of the joined participants, in join order."""
        return tuple(p.name for p in self._peers if not p.lost)

    @property
    def dropped(self) -> tuple[tuple[str, str], ...]:
        """``(name, reason)`` of every participant dropped by the ``drop`` policy."""
        return tuple(self._dropped)

    def subscribe(self, topic: str, callback: Callable[[Message], object]) -> None:
        """Call ``callback(message)`` for data published on ``topic``, at its sim time,
        before physics advances past it."""
        if not callable(callback):
            raise InvalidTypeError(f"callback must be callable, got {type(callback).__name__}")
        proto.subscribe(topic)  # validates the name
        self._subscribers.setdefault(topic, []).append(callback)

    def provide(self, service: str, handler: Callable[[bytes], bytes]) -> None:
        """Answer participants' ``call(service, data)`` with ``handler(data)``, at once."""
        if not callable(handler):
            raise InvalidTypeError(f"handler must be callable, got {type(handler).__name__}")
        proto.call(0, service, b"")  # validates the name
        if service in self._services:
            raise InvalidArgumentError(f"a service named {service!r} is already provided")
        self._services[service] = handler

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
            regrant: list[_Peer] = []
            self._route(*entry, regrant)
            self._grant_all(regrant)

    async def wait_for_participants(
        self, *names: str, count: int | None = None, timeout: float = DEFAULT_JOIN_TIMEOUT
    ) -> None:
        """Wait until the named participants (or ``count`` of them) have joined.

        Sim time is held meanwhile: the simulation does not start without them. After
        ``timeout`` wall seconds :class:`~evclock.remote.ParticipantLostError` names who is missing.
        """
        for name in names:
            if not isinstance(name, str):
                raise InvalidTypeError(f"participant names are strings, got {name!r}")
        if not (isinstance(timeout, int | float) and timeout > 0):
            raise InvalidArgumentError(f"timeout must be positive wall seconds, got {timeout!r}")

        def ready() -> bool:
            joined = self.participants
            return all(n in joined for n in names) and len(joined) >= (count or 0)

        def missing() -> str:
            absent = [n for n in names if n not in self.participants]
            if absent:
                return ", ".join(repr(n) for n in absent)
            return f"{count} participants ({len(self.participants)} joined)"

        self._join_deadline = time.monotonic() + timeout
        self._join_missing = missing
        try:
            with self._loop.hold_time():
                await self._wait(ready)
        finally:
            self._join_deadline = None

    async def wait_until_left(self, *names: str) -> None:
        """Wait until the named participants (default: every participant) have left or were
        dropped.

        :param names: the participants to wait for; a follower that stays joined does not
            keep a simulation waiting for its lockstep participants.
        """
        for name in names:
            if not isinstance(name, str):
                raise InvalidTypeError(f"participant names are strings, got {name!r}")
        if names:
            await self._wait(lambda: not any(p.name in names for p in self._peers))
        else:
            await self._wait(lambda: not self._peers)

    def close(self, reason: str = "the simulation ended") -> None:
        """Stop serving: every participant gets :class:`~evclock.ClockLostError` naming
        ``reason``."""
        if self._closed:
            return
        self._closed = True
        self._stop_watch.set()
        frame = proto.closing(f"the clock server at {self._address} stopped: {reason}")
        for peer in [*self._peers, *self._pending]:
            with contextlib.suppress(OSError):
                peer.sock.setblocking(True)
                peer.sock.settimeout(0.5)
                peer.sock.sendall(bytes(peer.out) + frame)
            self._disconnect(peer)
        self._peers.clear()
        self._pending.clear()
        self._working = 0
        self._release_all_holds()
        self._remove_step_hook()
        self._jump_handle.remove()
        self._loop.account_fd(self._listener.fileno(), False)
        if not self._loop.is_closed():
            self._loop.remove_reader(self._listener)
        self._listener.close()
        if self._address.scheme == "unix":
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._address.path)

    # ------------------------------------------------------------ holds

    def _hold(self) -> None:
        # The loop's exact hold count (SimEventLoop.add_hold): sim time
        # stays put while a participant works, as for an executor job.
        self._loop.add_hold()
        self._holds += 1

    def _release(self) -> None:
        self._holds -= 1
        self._loop.release_hold(None)

    def _release_all_holds(self) -> None:
        while self._holds:
            self._release()

    # ------------------------------------------------------------ waiting

    async def _wait(self, ready: Callable[[], bool]) -> None:
        if self._failure is not None:
            raise self._failure
        if ready():
            return
        fut: asyncio.Future[None] = self._loop.create_future()
        self._waiters.append((ready, fut))
        try:
            await fut
        finally:
            self._waiters = [(r, f) for r, f in self._waiters if f is not fut]

    def _wake_waiters(self) -> None:
        for ready, fut in list(self._waiters):
            if not fut.done() and ready():
                fut.set_result(None)

    # ------------------------------------------------------------ connections

    def _on_accept(self) -> None:
        for _ in range(16):
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. out of file descriptors: keep serving the others
                log.warning("clock server: accept failed: %s", exc)
                return
            sock.setblocking(False)
            if sock.family != socket.AF_UNIX:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            peer = _Peer(sock)
            try:
                cred = peer_credentials(sock)
            except OSError as exc:
                log.warning("clock server: cannot read a connection's credentials: %s", exc)
                sock.close()
                continue
            if cred is not None:
                peer.pid, uid = cred
                if uid not in self._peer_uids:
                    self._refuse(
                        peer,
                        f"user id {uid} may not join this clock server (it admits user ids "
                        f"{', '.join(map(str, self._peer_uids))}; serve with peer_uids=...)",
                    )
                    continue
            if len(self._pending) >= MAX_PENDING:
                self._refuse(
                    peer,
                    f"busy: {MAX_PENDING} connections are in their handshake; try again",
                    proto.REFUSE_BUSY,
                )
                continue
            self._pending.append(peer)
            self._loop.add_reader(sock, self._on_readable, peer)
            # The server holds sim time exactly while a peer's traffic matters (a working
            # participant): the loop must not also infer held time from its unread bytes
            # (a follower that reads late must never hold the simulation).
            self._loop.account_fd(sock.fileno(), True)

    def _on_readable(self, peer: _Peer) -> None:
        try:
            # Before the handshake a read never exceeds the pre-authentication frame limit.
            data = peer.sock.recv(262144 if peer.name else proto.PRE_AUTH_MAX_FRAME + 5)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._lost(peer, f"lost its connection ({exc})")
            return
        if not data:
            self._lost(peer, "closed its connection without leaving (killed or crashed)")
            return
        if len(data) == proto.DONE_SIZE and not peer.reader.pending and peer.name:
            length, kind, t_ns, next_ns = proto.unpack_done(data)
            if kind == proto.DONE and length == proto.DONE_SIZE - 4:  # a round's DONE alone
                try:
                    self._on_done(peer, t_ns, next_ns)
                except ProtocolError as exc:
                    self._bad_frame(peer, kind, str(exc))
                return
        try:
            frames = peer.reader.feed(data)
        except ProtocolError as exc:  # the framing is broken: nothing after it can be read
            if peer.name:
                self._lost(peer, f"broke the protocol framing ({exc})")
            else:
                self._refuse(peer, f"not an evclock clock client: {exc}")
            return
        for kind, payload in frames:
            if peer.sock.fileno() < 0:
                return  # removed by an earlier frame of this batch
            if not peer.name:
                try:
                    self._handshake(peer, kind, payload)
                except ProtocolError as exc:
                    self._refuse(peer, f"not an evclock clock client: {exc}")
                continue
            try:
                self._handle(peer, kind, payload)
            except (ProtocolError, ValueError, TypeError) as exc:
                self._bad_frame(peer, kind, str(exc))

    def _bad_frame(self, peer: _Peer, kind: int, reason: str) -> None:
        """A well-framed frame the simulation refuses: the participant is told why, the
        frame is ignored, and the simulation goes on (a flood of them is a fault)."""
        if peer.lost or peer not in self._peers:
            return
        peer.errors += 1
        label = chr(kind) if 32 < kind < 127 else str(kind)
        log.warning(
            "clock server: refused a frame of kind %s from %s: %s", label, peer.describe(), reason
        )
        if peer.errors > MAX_ERRORS:
            self._lost(peer, f"sent more than {MAX_ERRORS} invalid frames")
            return
        self._send(peer, proto.error(kind, f"frame of kind {label!r} refused: {reason}"))

    def _handle(self, peer: _Peer, kind: int, payload: bytes) -> None:
        if kind == proto.DONE:
            self._on_done(peer, *proto.parse_done(payload))
        elif kind == proto.PUBLISH:
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
                peer.outbox.append((stamp, topic, data))
                self._round_has_data = True
            elif self._working:
                self._outbox.append((peer.name, self._kernel.now_ns, topic, data))
                self._round_has_data = True
            else:
                regrant: list[_Peer] = []
                self._route(peer.name, self._kernel.now_ns, topic, data, regrant)
                self._grant_all(regrant)
        elif kind == proto.CALL:
            self._on_call(peer, *proto.parse_call(payload))
        elif kind == proto.SUBSCRIBE:
            peer.subscriptions.add(proto.parse_subscribe(payload))
        elif kind == proto.JUMPED:
            seq = proto.parse_jumped(payload)
            if not peer.jump_acked < seq <= peer.jump_sent:
                raise ProtocolError(f"JUMPED {seq}, but jump {peer.jump_sent} was the last sent")
            peer.jump_acked = seq
        elif kind == proto.BYE:
            log.info("clock server: participant %s left at %s", peer.describe(), self._now())
            self._remove(peer, clean=True)
        else:
            raise ProtocolError(f"unexpected frame kind {kind!r} from a participant")

    # ------------------------------------------------------------ the handshake

    def _transcript(self, peer: _Peer) -> bytes:
        return proto.transcript(
            proto.VERSION, peer.mode, peer.greeted, peer.client_nonce, peer.server_nonce
        )

    def _handshake(self, peer: _Peer, kind: int, payload: bytes) -> None:
        """HELLO -> CHALLENGE (the server's proof first), PROOF -> WELCOME or REFUSE."""
        if not peer.greeted:
            if kind != proto.HELLO:
                raise ProtocolError("the first frame must be HELLO")
            version, mode, name, nonce = proto.parse_hello(payload)
            if version != proto.VERSION:
                self._refuse(
                    peer,
                    f"protocol version {version} is not supported: this clock server speaks "
                    f"version {proto.VERSION}; run the same evclock version on both sides",
                )
                return
            peer.greeted, peer.mode, peer.client_nonce = name, mode, nonce
            peer.server_nonce = proto.new_nonce()
            token = self._token
            mine = (
                b""
                if token is None
                else proto.prove(token, proto.SERVER_SIDE, self._transcript(peer))
            )
            self._send(peer, proto.challenge(peer.server_nonce, mine))
            return
        if kind != proto.PROOF:
            raise ProtocolError("the second frame must be PROOF")
        token = self._token
        if token is not None and not hmac.compare_digest(
            payload, proto.prove(token, proto.CLIENT_SIDE, self._transcript(peer))
        ):
            self._refuse(peer, "wrong or missing token: join with ?token=... in the clock address")
            return
        self._on_hello(peer, peer.mode, peer.greeted)

    def _on_hello(self, peer: _Peer, mode: int, name: str) -> None:
        replaced = None
        for other in self._peers:
            if other.name == name:
                if not other.lost:
                    self._refuse(
                        peer,
                        f"a participant named {name!r} is already joined; give this process "
                        "another name (?name=... in the clock address)",
                    )
                    return
                replaced = other
        self._pending.remove(peer)
        now = self._kernel.now_ns
        peer.name = name
        peer.mode = mode
        peer.reader.limit = self._max_frame  # authenticated: the documented frame limit
        self._send(peer, proto.welcome(now, self._max_frame, self._info))
        if replaced is not None:
            # A paused simulation waited for this name: the newcomer takes its place (and
            # the hold the lost one kept).
            peer.index = replaced.index
            self._peers[self._peers.index(replaced)] = peer
            if replaced.working_at is not None:
                self._working -= 1
                if not self._working:
                    self._release()
            log.warning("clock server: %s rejoined at %s", peer.describe(), self._now())
        else:
            self._joined += 1
            peer.index = self._joined
            self._peers.append(peer)
            log.info("clock server: %s joined at %s", peer.describe(), self._now())
        if mode == proto.MODE_LOCKSTEP:
            self._start_work(peer, now)  # its program starts now: the simulation waits
        else:
            self._add_step_hook()
        self._wake_waiters()

    def _refuse(self, peer: _Peer, reason: str, code: int = proto.REFUSE_FINAL) -> None:
        pid = "" if peer.pid is None else f" (pid {peer.pid})"
        log.warning("clock server: refused a connection%s: %s", pid, reason)
        with contextlib.suppress(OSError):
            peer.sock.send(proto.refuse(reason, code))
        if peer in self._pending:
            self._pending.remove(peer)
        self._disconnect(peer)

    def _disconnect(self, peer: _Peer) -> None:
        self._unschedule(peer)
        if peer.sock.fileno() >= 0:
            self._loop.account_fd(peer.sock.fileno(), False)
            if not self._loop.is_closed():
                self._loop.remove_reader(peer.sock)
                self._loop.remove_writer(peer.sock)
            peer.sock.close()

    # ------------------------------------------------------------ lockstep rounds

    def _start_work(self, peer: _Peer, now: int) -> None:
        peer.working_at = now
        peer.working_since = time.monotonic()
        peer.silent_reported = False
        if not self._working:
            self._hold()  # one hold per round, however many participants work in it
        self._working += 1

    def _stop_work(self, peer: _Peer) -> None:
        peer.working_at = peer.working_since = None
        self._working -= 1
        if not self._working:
            self._close_round()  # may grant again (data arrived): the round then goes on
            self._release()  # after the round closed: physics cannot move in between

    def _on_deadline(self, t_ns: int) -> None:
        _, peers = self._due.pop(t_ns)
        if len(peers) > 1:
            peers.sort(key=_BY_INDEX)  # join order, whatever the DONEs' order
        now = self._kernel.now_ns
        grant = None
        wall = time.monotonic()
        for peer in peers:
            peer.deadline = None
            if peer.mode == proto.MODE_LOCKSTEP:
                if peer.working_at is not None:
                    continue  # already granted now (data arrived): its DONE names its next one
                # _start_work, inline (the hot path of a round)
                peer.working_at = now
                peer.working_since = wall
                peer.silent_reported = False
                if not self._working:
                    self._hold()  # one hold per round, however many participants work in it
                self._working += 1
                if grant is None:
                    grant = proto.grant(now)
                self._send(peer, grant)
            else:
                self._send_time(peer, now)

    def _on_done(self, peer: _Peer, t_ns: int, next_ns: int) -> None:
        if peer.jump_acked != peer.jump_sent:
            return  # sent before it read the JUMP: about a time that no longer exists
        now = self._kernel.now_ns
        if peer.mode == proto.MODE_FOLLOW:
            self._schedule(peer, next_ns, now)
            return
        if peer.working_at != t_ns:
            raise ProtocolError(f"DONE at {t_ns} ns, but the participant was granted {now} ns")
        if next_ns != proto.NO_DEADLINE and next_ns <= t_ns:
            raise ProtocolError(f"next deadline {next_ns} ns is not after {t_ns} ns")
        if peer.deadline is None and next_ns > now:  # _schedule's common case, inline
            peer.deadline = next_ns
            due = self._due.get(next_ns)
            if due is not None:
                due[1].append(peer)
            else:
                # SimEventLoop.call_at_ns: exact integer ns, no float round trip.
                timer = self._loop.call_at_ns(next_ns, self._on_deadline, next_ns)
                self._due[next_ns] = (timer, [peer])
        else:
            self._schedule(peer, next_ns, now)
        peer.working_at = peer.working_since = None  # _stop_work, inline
        self._working -= 1
        if not self._working:
            self._close_round()  # may grant again (data arrived): the round then goes on
            self._release()  # after the round closed: physics cannot move in between

    def _schedule(self, peer: _Peer, next_ns: int, now: int) -> None:
        if peer.deadline is not None:  # superseded by the deadline the participant just named
            self._unschedule(peer)
        if next_ns == proto.NO_DEADLINE:
            return
        if next_ns <= now:  # a follower behind the simulation: tell it the time now
            self._send_time(peer, now)
            return
        peer.deadline = next_ns
        due = self._due.get(next_ns)
        if due is not None:
            due[1].append(peer)
            return
        # SimEventLoop.call_at_ns: exact integer ns, no float round trip.
        timer = self._loop.call_at_ns(next_ns, self._on_deadline, next_ns)
        self._due[next_ns] = (timer, [peer])

    def _unschedule(self, peer: _Peer) -> None:
        if peer.deadline is None:
            return
        timer, peers = self._due[peer.deadline]
        peers.remove(peer)
        if not peers:
            timer.cancel()
            del self._due[peer.deadline]
        peer.deadline = None

    def _close_round(self) -> None:
        """Deliver the round's data in a fixed order, still at this time."""
        if not self._round_has_data:
            return  # the common case: a round without data costs nothing here
        self._round_has_data = False
        regrant: list[_Peer] = []
        self._deliver_round(regrant)
        self._grant_all(regrant)

    def _deliver_round(self, regrant: list[_Peer]) -> None:
        while True:
            senders = sorted([*self._peers, *self._departed], key=lambda peer: peer.index)
            self._departed = []
            batch = [(peer.name, *entry) for peer in senders for entry in peer.outbox]
            for peer in senders:
                peer.outbox = []
            batch += self._outbox
            self._outbox = []
            if not batch:
                break
            for sender, t_ns, topic, data in batch:
                self._route(sender, t_ns, topic, data, regrant)

    def _route(self, sender: str, t_ns: int, topic: str, data: bytes, regrant: list[_Peer]) -> None:
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
                            f"the simulation refused data on topic {topic!r}: "
                            f"{type(exc).__name__}: {exc}",
                        )
                        continue
                    self._loop.call_exception_handler(
                        {
                            "message": f"subscriber {callback!r} of topic {topic!r} raised",
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

    def _peer_named(self, name: str) -> _Peer | None:
        for peer in self._peers:
            if peer.name == name and not peer.lost:
                return peer
        return None

    def _grant_all(self, peers: list[_Peer]) -> None:
        now = self._kernel.now_ns
        for peer in peers:
            if peer.working_at is None and not peer.lost and peer in self._peers:
                self._start_work(peer, now)
                self._send(peer, proto.grant(now))

    # ------------------------------------------------------------ time jumps

    def _before_jump(self, jump: TimeJump) -> None:
        """Data of the open round is delivered before the jump, at the time it was sent
        (as an in-process subscriber would have received it before the jump)."""
        if self._round_has_data:
            self._round_has_data = False
            self._deliver_round([])  # everyone runs again after the jump anyway

    def _after_jump(self, jump: TimeJump) -> None:
        """Every participant's clock jumps alike, in order with the data sent before it:
        a lockstep participant works at the new time (its sleeps were woken with
        ClockJumpedError, as in-process), a follower asks for its deadline again."""
        self._jumps += 1
        seq = self._jumps
        after = self._kernel.now_ns
        frame = proto.jump(seq, jump.before.nanoseconds, after)
        for timer, _ in self._due.values():
            timer.cancel()
        self._due.clear()
        for peer in self._peers:
            peer.deadline = None
            if peer.lost:
                continue
            peer.jump_sent = seq
            self._send(peer, frame)
            if peer.mode == proto.MODE_LOCKSTEP:
                if peer.working_at is None:
                    self._start_work(peer, after)
                else:
                    peer.working_at = after
                    peer.working_since = time.monotonic()
        log.info("clock server: sim time jumped %s", jump)

    # ------------------------------------------------------------ followers

    def _send_time(self, peer: _Peer, now: int) -> None:
        if peer.out:
            peer.stale_time = True  # it is behind: it gets the newest time once it reads
        else:
            self._send(peer, proto.time_frame(now))

    def _tick_followers(self) -> None:
        now = self._kernel.now_ns
        for peer in self._peers:
            if peer.mode == proto.MODE_FOLLOW and not peer.lost:
                self._send_time(peer, now)

    def _add_step_hook(self) -> None:
        # A stepping source (PyBullet) tells every step; on virtual time followers get the
        # time at their own deadlines and whenever they ask (DONE with a past deadline).
        add = getattr(self._loop.source, "add_step_hook", None)
        if add is not None and self._step_hook is None:
            self._step_hook = add(self._tick_followers, when="after")

    def _remove_step_hook(self) -> None:
        if self._step_hook is not None:
            self._step_hook.remove()
            self._step_hook = None

    # ------------------------------------------------------------ calls

    def _on_call(self, peer: _Peer, call_id: int, service: str, data: bytes) -> None:
        handler = self._services.get(service)
        if handler is None:
            known = ", ".join(sorted(self._services)) or "none"
            self._send(
                peer,
                proto.reply(call_id, False, f"no service {service!r} (known: {known})".encode()),
            )
            return
        try:
            result = handler(data)
        except Exception as exc:
            self._send(peer, proto.reply(call_id, False, f"{type(exc).__name__}: {exc}".encode()))
            return
        self._send(peer, proto.reply(call_id, True, result))

    # ------------------------------------------------------------ sending

    def _send(self, peer: _Peer, frame: bytes) -> None:
        if peer.out:
            peer.out += frame
            if len(peer.out) > _MAX_BACKLOG:
                self._lost(peer, f"does not read its connection ({len(peer.out)} bytes unsent)")
            return
        try:
            sent = peer.sock.send(frame)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError:
            # The peer closed its end: its reader sees the goodbye (or the bare EOF) next
            # and decides between a clean leave and a fault; nothing more is sent to it.
            peer.out += b"\0"
            return
        if sent < len(frame):
            peer.out += frame[sent:]
            self._loop.add_writer(peer.sock, self._on_writable, peer)

    def _on_writable(self, peer: _Peer) -> None:
        try:
            sent = peer.sock.send(peer.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._loop.remove_writer(peer.sock)  # closed: the reader reports how it ended
            return
        del peer.out[:sent]
        if not peer.out:
            self._loop.remove_writer(peer.sock)
            if peer.stale_time:
                peer.stale_time = False
                self._send(peer, proto.time_frame(self._kernel.now_ns))

    # ------------------------------------------------------------ faults

    def _now(self) -> str:
        return f"{self._kernel.now_ns / 1e9:.6f} s of sim time"

    def _lost(self, peer: _Peer, reason: str) -> None:
        if self._closed or peer.lost:
            return
        if not peer.name:
            if peer in self._pending:
                self._pending.remove(peer)
            self._disconnect(peer)
            return
        if peer not in self._peers:
            return
        self._fault(peer, reason, dead=True)

    def _fault(self, peer: _Peer, reason: str, *, dead: bool) -> None:
        what = f"participant {peer.describe()} {reason} at {self._now()} ({peer.last_did()})"
        if peer.mode == proto.MODE_FOLLOW:  # it never holds the simulation: just forget it
            log.warning("clock server: %s; removed it (followers never hold sim time)", what)
            self._remove(peer)
        elif self._policy == "abort":
            self._abort(
                ParticipantLostError(
                    f"{what}; the simulation was aborted (on_fault='abort'; 'drop' continues "
                    "without it, 'pause' waits for it)",
                    peer.name,
                )
            )
        elif self._policy == "drop":
            log.warning("clock server: %s; dropped it (on_fault='drop')", what)
            self._dropped.append((peer.name, reason))
            self._remove(peer)
        elif dead:
            log.warning(
                "clock server: %s; sim time is paused until a participant named %r joins "
                "(on_fault='pause')",
                what,
                peer.name,
            )
            peer.lost = True
            self._disconnect(peer)
            peer.outbox = []
            if peer.working_at is None:  # it must hold the simulation until replaced
                self._start_work(peer, self._kernel.now_ns)
        elif not peer.silent_reported:
            peer.silent_reported = True
            log.warning(
                "clock server: %s; sim time stays paused until it answers (on_fault='pause')",
                what,
            )

    def _remove(self, peer: _Peer, *, clean: bool = False) -> None:
        """Forget ``peer``; what it published before leaving cleanly is still delivered."""
        self._disconnect(peer)
        if peer in self._peers:
            self._peers.remove(peer)
            if clean and peer.outbox:
                self._departed.append(peer)
        if peer.mode == proto.MODE_FOLLOW and not any(
            p.mode == proto.MODE_FOLLOW for p in self._peers
        ):
            self._remove_step_hook()
        if not clean:
            peer.outbox = []
        if peer.working_at is not None:
            self._stop_work(peer)
        self._wake_waiters()

    def _abort(self, error: EvClockError) -> None:
        if self._failure is not None:
            return
        self._failure = error
        log.error("clock server: %s", error)
        for _, fut in self._waiters:
            if not fut.done():
                fut.set_exception(error)
        self.close(str(error))
        if self._owner is not None and not self._owner.done():
            self._owner.cancel()

    # ------------------------------------------------------------ watchdog

    def _watch(self) -> None:
        """A daemon thread: wakes the loop when a wall deadline passed or a keepalive is due
        (it never blocks the loop)."""
        limit = self._step_timeout
        interval = min(HELLO_TIMEOUT / 8, (limit or HELLO_TIMEOUT) / 8, KEEPALIVE)
        next_keepalive = time.monotonic() + KEEPALIVE
        while not self._stop_watch.wait(interval):
            now = time.monotonic()
            if now >= next_keepalive and (
                self._peers or self._holds or self._join_deadline is not None
            ):
                next_keepalive = now + KEEPALIVE
                try:
                    self._loop.call_soon_threadsafe(self._keepalive)
                except RuntimeError:  # the loop closed under us
                    return
            late = any(now - p.accepted_at > HELLO_TIMEOUT for p in list(self._pending))
            join_deadline = self._join_deadline
            late = late or (join_deadline is not None and now > join_deadline)
            if limit is not None and not late:
                late = any(
                    p.working_since is not None
                    and not p.silent_reported
                    and not p.lost
                    and now - p.working_since > limit
                    for p in list(self._peers)
                )
            if late and not self._check_scheduled:
                self._check_scheduled = True
                try:
                    self._loop.call_soon_threadsafe(self._check_timeouts)
                except RuntimeError:  # the loop closed under us
                    return

    def _keepalive(self) -> None:
        """Tell every waiting participant the time: a stopped server is one that goes quiet.

        The server's own holds are bounded by the server (the join timeout, ``step_timeout``,
        the ``pause`` policy waiting for a replacement): they are not a stall of the loop, so
        the loop's ``stall_timeout`` starts again while one of them is what holds time.
        """
        if self._join_deadline is not None or (
            self._holds and (self._step_timeout is not None or any(p.lost for p in self._peers))
        ):
            self._loop_bound_restarts()
        now = self._kernel.now_ns
        frame = proto.time_frame(now)
        for peer in self._peers:
            if peer.working_at is None and not peer.lost and not peer.out:
                self._send(peer, frame)

    def _loop_bound_restarts(self) -> None:
        # The server's holds in force are bounded by the server: not a stall of the loop.
        self._loop.restart_stall_bound()

    def _check_timeouts(self) -> None:
        self._check_scheduled = False
        now = time.monotonic()
        for peer in list(self._pending):
            if now - peer.accepted_at > HELLO_TIMEOUT:
                self._refuse(peer, f"no complete handshake within {HELLO_TIMEOUT:g} s")
        if self._join_deadline is not None and now > self._join_deadline:
            self._join_deadline = None
            error = ParticipantLostError(
                f"{self._join_missing()} did not join {self._address} in time; start them "
                f"with clock='{self._address}' (or EVCLOCK_CLOCK)",
                self._join_missing(),
            )
            for _, fut in self._waiters:
                if not fut.done():
                    fut.set_exception(error)
        limit = self._step_timeout
        if limit is None:
            return
        for peer in list(self._peers):
            since = peer.working_since
            expired = since is not None and now - since > limit
            if expired and not peer.lost and not peer.silent_reported:
                self._fault(
                    peer,
                    f"did not finish its step within step_timeout={limit:g} s of wall time "
                    "(stopped or stuck)",
                    dead=False,
                )
                if self._failure is not None:
                    return


@contextlib.asynccontextmanager
async def serve(
    address: str | None = None,
    *,
    on_fault: str = "abort",
    step_timeout: float | None = DEFAULT_STEP_TIMEOUT,
    token: str | None = None,
    info: Mapping[str, Any] | None = None,
    allow_remote: bool = False,
    max_frame: int = proto.MAX_FRAME,
    peer_uids: Iterable[int] | None = None,
) -> AsyncIterator[ClockServer]:
    """Serve the running :class:`~evclock.SimEventLoop`'s sim time while the block runs::

        async with evclock.remote.serve("unix:///tmp/sim.sock") as server:
            await server.wait_for_participants("controller")
            ...

    :param address: ``unix:///path.sock`` (default: a per-process socket in the user's
        private directory, ``$XDG_RUNTIME_DIR/evclock`` or ``evclock-UID`` in the temp dir,
        mode 0700) or ``tcp://127.0.0.1:PORT?token=...`` (port 0: any free port; see
        :attr:`ClockServer.address`).
    :param on_fault: what a dead, stopped or silent lockstep participant causes: ``abort``
        (default: :class:`~evclock.remote.ParticipantLostError` naming it and what it last
        did is raised from this block),
        ``drop`` (continue without it) or ``pause`` (hold sim time, without limit - the
        loop's ``stall_timeout`` does not apply - until it answers or a participant of the
        same name joins).
    :param step_timeout: wall seconds a lockstep participant may work on one step before
        the policy applies (None: no limit of the server's own, so the loop's
        ``stall_timeout`` applies; a killed one is detected at once regardless).
    :param token: a shared secret both sides prove they know (HMAC challenge-response, it is
        never sent); ``?token=`` in the participants' address. Required on TCP; a
        non-loopback address also needs ``allow_remote``.
    :param info: JSON-serialisable facts given to every participant at join (scenario, seed).
    :param allow_remote: allow serving on a non-loopback address (``tcp://0.0.0.0:PORT``).
    :param max_frame: the largest frame in bytes a joined participant may send (default
        16 MiB; 4 KiB to 256 MiB); before the handshake completes the limit is 4 KiB.
    :param peer_uids: user ids that may join over a Unix socket (``SO_PEERCRED``; default:
        only the user running the simulation).
    :returns: an async context manager yielding the :class:`ClockServer`.
    :raises InvalidTypeError: the running loop is not a :class:`~evclock.SimEventLoop`.
    :raises InvalidArgumentError: an invalid option or address (see :class:`ClockServer`).
    :raises ParticipantLostError: with ``on_fault="abort"``, a lockstep participant was lost.
    """
    loop = asyncio.get_running_loop()
    if not isinstance(loop, SimEventLoop):
        raise InvalidTypeError(
            "evclock.remote.serve() serves the sim time of a SimEventLoop; run the simulation with "
            "evclock.run(...) (or a SimEventLoop) first"
        )
    server = ClockServer(
        loop,
        address if address is not None else default_address(),
        on_fault=on_fault,
        step_timeout=step_timeout,
        token=token,
        info=info,
        allow_remote=allow_remote,
        max_frame=max_frame,
        peer_uids=peer_uids,
    )
    owner = server._owner = asyncio.current_task()
    try:
        yield server
    except asyncio.CancelledError:
        if server._failure is not None and owner is not None:
            owner.uncancel()
            raise server._failure from None
        raise
    finally:
        server.close()
    if server._failure is not None:
        raise server._failure
