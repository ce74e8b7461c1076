"""The participant side: a time source whose time comes from a clock server.

``evclock.run(main(), clock="unix:///tmp/sim.sock")`` (or ``EVCLOCK_CLOCK``) runs ``main`` on a
:class:`~evclock.SimEventLoop` driven by a :class:`RemoteClockSource`. It follows the
external-source contract: :meth:`RemoteClockSource.advance` never blocks; it returns the
time the server granted (lockstep) or announced (follow), or the unchanged time to say
"waiting for the server", and the loop then waits for the socket (registered with
``add_reader``). Its time is the server's, exactly: after a grant at ``t`` every local
deadline up to ``t`` fires at ``t``, as on an in-process stepping source. A jump of the
server's time (JUMP) is applied as an in-process jump (``SourceHost.jump``): handlers run,
pending sleeps raise ``ClockJumpedError``, asyncio timers keep their remaining delay.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hmac
import itertools
import json
import logging
import os
import select
import socket
import sys
import time
from collections.abc import Callable
from typing import Any

from evclock._errors import (
    ClockLostError,
    InvalidArgumentError,
    InvalidTypeError,
    JoinRefusedError,
    NoSimulationError,
    ProtocolError,
    RemoteCallError,
)
from evclock.kernel._source import Gate
from evclock.remote import _protocol as proto
from evclock.remote import _tls
from evclock.remote._address import (
    Address,
    connect,
    parse_address,
    peer_credentials,
    with_verification,
)
from evclock.remote._checks import one_line, shown
from evclock.remote._routing import Message
from evclock.remote._token import check_token
from evclock.sources import TimeSource
from evclock.time._time import SIM, new_time

log = logging.getLogger("evclock.remote")

#: Wall seconds before the first new connection attempt while the server is not up yet, its
#: listen backlog is full or it is busy with other handshakes; doubled up to ``_RETRY_MAX``.
_RETRY = 0.01
_RETRY_MAX = 0.5
#: ERROR frames kept for :attr:`RemoteClockSource.errors` (the newest).
_KEEP_ERRORS = 100

#: Frames about sim time that a pending jump holds back (replies and the server's goodbye
#: are handled at once: a call waits for its reply).
_AFTER_A_JUMP = frozenset({proto.GRANT, proto.TIME, proto.DELIVER, proto.JUMP})


def _default_name() -> str:
    program = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"
    return f"{program}-{os.getpid()}"


class RemoteClockSource(TimeSource):
    """Sim time of a simulation in another process, joined over a clock server's socket.

    :param address: the server's address, ``unix:///path.sock``, ``tcp://127.0.0.1:PORT`` or
        ``tls://HOST:PORT``, optionally with
        ``?mode=lockstep|follow&name=...&token=...&timeout=SECONDS`` (and on ``tls://``
        ``&tls_ca=PATH`` or ``&tls_fingerprint=SHA256``).
    :param tls_ca: ``tls://``: the CA file (PEM) that signed the server's certificate; the
        certificate must also name the address's host (overrides ``?tls_ca=``).
    :param tls_fingerprint: ``tls://``: the SHA-256 fingerprint of the server's certificate
        in hex, colons allowed (overrides ``?tls_fingerprint=``).

    *lockstep* (default): the simulation does not advance while this process works at
    ``t`` nor past its next deadline. *follow*: time follows the server every step; the
    simulation never waits for this process.

    Joining waits up to ``timeout`` wall seconds (default 60) for the server to appear (a
    connection refused, a full listen backlog or a busy server are retried with backoff);
    afterwards each wait for a grant, a time or a reply is bounded by the same ``timeout``
    and a dead server is reported at once: both raise :class:`~evclock.ClockLostError`.

    Joining authenticates the server: on a Unix socket it must run as this user (or
    ``?server_uid=``), and with a ``?token=`` it must prove it knows the token before this
    process proves it does (the token itself is never sent): its first answer must be a
    CHALLENGE whose proof verifies, and anything else first ends the join (a busy answer is
    retried). TCP and TLS need a token. On ``tls://`` the server's certificate is verified
    (``tls_ca`` or ``tls_fingerprint``) in the TLS handshake, before anything of the
    protocol is sent, and everything travels encrypted.

    :raises InvalidArgumentError: a TCP or TLS address without ``?token=``, a TLS address
        without ``tls_ca`` or ``tls_fingerprint``.
    :raises WeakTokenError: a token below 128 bits (fewer than 22 URL-safe characters).
    :raises JoinRefusedError: the server refused this process, or it is not who it should be
        (on TLS: its certificate does not verify).
    :raises ClockLostError: no server answered within ``timeout``.
    :raises ProtocolError: the server speaks another protocol version.
    """

    external = True
    free_running = True  # idle waits for the server's time: never a deadlock

    def __init__(
        self,
        address: str | Address,
        *,
        tls_ca: str | None = None,
        tls_fingerprint: str | None = None,
    ) -> None:
        addr = address if isinstance(address, Address) else parse_address(address)
        if addr.token is not None:
            check_token(addr.token)  # before anything is sent: a weak one is refused here too
        addr = with_verification(addr, tls_ca, tls_fingerprint)
        self._address = addr
        self._loop: Any = None  # the SimEventLoop this source drives (set by attach)
        self.name = addr.name or _default_name()
        self.mode = addr.mode
        self._lockstep = addr.mode == "lockstep"
        self._timeout = addr.timeout
        #: Frames the simulation refused (ERROR): ``(kind, reason)``, the newest last.
        self._errors: list[tuple[int, str]] = []
        self._max_frame = proto.MAX_FRAME  # the server's limit, from its WELCOME
        self._reader = proto.Reader(proto.PRE_AUTH_MAX_FRAME)  # kept: what followed the WELCOME
        # Frames read with the WELCOME (a jump, a time, data sent at once after the join),
        # handled in order once the loop runs, before anything read later.
        self._early: list[tuple[int, bytes]] = []
        self._sock, now_ns, self.info = self._join(addr)
        self._sock.setblocking(False)
        self.io_fd: int | None = self._sock.fileno()  # the loop may leave this fd to us
        self._now = now_ns
        self._latest = now_ns  # newest time the server announced (follow)
        self._granted: int | None = None
        self._working = self._lockstep  # a lockstep participant starts working at join
        self._asked = proto.NO_DEADLINE  # deadline last told the server (follow)
        self._waiting_since: float | None = None
        self._out = bytearray()
        self._held_out: list[bytes] = []  # lockstep data produced between rounds
        self._inbox: list[tuple[int, str, str, bytes]] = []
        self._subscribers: dict[str, list[Callable[[Message], object]]] = {}
        self._replies: dict[int, tuple[bool, bytes]] = {}
        self._call_ids = itertools.count(1).__next__
        self._lost: ClockLostError | None = None
        # A JUMP read while this clock is still behind the time the simulation jumped from
        # (a follower; a lockstep participant with a grant there): the clock first gets
        # there (what is due up to it runs), then jumps. Frames read meanwhile are about
        # the new time and wait, in order, for the jump.
        self._jump_pending: tuple[int, int, int] | None = None
        self._after_jump: list[tuple[int, bytes]] = []
        self._reading = False
        self._writing = False  # a writer callback is registered for the rest of _out
        self._closed = False

    # ------------------------------------------------------------ joining

    def _join(self, addr: Address) -> tuple[socket.socket, int, dict[str, Any]]:
        if addr.scheme in ("tcp", "tls") and addr.token is None:
            raise InvalidArgumentError(
                f"joining the clock server at {addr} over {addr.scheme} needs its token: add "
                f"?token=... to the clock address (any user of the machine can reach a "
                f"{addr.scheme} port, so both sides prove they know the token; it is never "
                "sent)"
            )
        tls = (
            _tls.client_context(addr.tls_ca, addr.tls_fingerprint) if addr.scheme == "tls" else None
        )
        deadline = time.monotonic() + self._timeout
        delay = _RETRY
        while True:
            try:
                sock = connect(addr, max(deadline - time.monotonic(), 0.01))
            except (FileNotFoundError, ConnectionRefusedError, BlockingIOError) as exc:
                # Not up yet, or its listen backlog is full (EAGAIN): try again shortly.
                if time.monotonic() + delay >= deadline:
                    raise ClockLostError(
                        f"no clock server at {addr} after waiting {self._timeout:g} s of wall "
                        f"time ({exc.strerror}); start the simulation with --serve {addr} "
                        "(or raise ?timeout=)"
                    ) from None
                why = "listen backlog full" if isinstance(exc, BlockingIOError) else "not up"
                log.debug("clock server at %s: %s; retrying in %.2f s", addr, why, delay)
                time.sleep(delay)
                delay = min(delay * 2, _RETRY_MAX)
                continue
            except OSError as exc:
                raise ClockLostError(
                    f"cannot connect to the clock server at {addr}: {exc}"
                ) from None
            if tls is not None:  # the server's certificate, before a byte of the protocol
                sock.settimeout(max(deadline - time.monotonic(), 0.01))
                sock = _tls.wrap_client(sock, tls, addr.host, addr.tls_fingerprint, str(addr))
            try:
                joined = self._handshake(sock, addr, deadline)
            except BaseException:
                sock.close()
                raise
            if joined is not None:
                return joined
            sock.close()  # busy: its handshake slots are full; try again shortly
            if time.monotonic() + delay >= deadline:
                raise ClockLostError(
                    f"the clock server at {addr} stayed busy with other connections for "
                    f"{self._timeout:g} s of wall time (raise ?timeout=)"
                )
            time.sleep(delay)
            delay = min(delay * 2, _RETRY_MAX)

    def _handshake(
        self, sock: socket.socket, addr: Address, deadline: float
    ) -> tuple[socket.socket, int, dict[str, Any]] | None:
        """Authenticate the server, then this process; None: the server is busy."""
        cred = peer_credentials(sock)
        if cred is not None:
            expected = os.getuid() if addr.server_uid is None else addr.server_uid
            pid, uid = cred
            if uid != expected:
                raise JoinRefusedError(
                    f"the clock server at {addr} (pid {pid}) runs as user id {uid}, not "
                    f"{expected}: it is not the simulation you meant (another user's process "
                    "listening there?); nothing was sent to it. Add ?server_uid="
                    f"{uid} to the address only if you trust that user"
                )
        mode = proto.MODE_LOCKSTEP if self._lockstep else proto.MODE_FOLLOW
        nonce = proto.new_nonce()
        self._reader = proto.Reader(proto.PRE_AUTH_MAX_FRAME)
        self._early = []
        # A server that refuses at once (busy, another user) may have closed before the
        # HELLO arrives: its REFUSE is still there to read.
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            sock.sendall(proto.hello(mode, self.name, nonce))
        kind, payload = self._read_one(sock, deadline, addr, self._reader, self._early)
        if addr.token is not None and kind != proto.CHALLENGE:
            # With a token the server must prove itself first: whatever else answers the
            # HELLO (a WELCOME, a GRANT, a REFUSE) comes from a server that has not, so it is
            # not trusted with anything more than the HELLO already sent.
            self._check_unproven_answer(addr, kind, payload)
            return None  # a busy answer: try again
        if kind == proto.CHALLENGE:
            server_nonce, server_proof = proto.parse_challenge(payload)
            transcript = proto.transcript(proto.VERSION, mode, self.name, nonce, server_nonce)
            token = addr.token
            mine = b""
            if token is not None:
                if not hmac.compare_digest(
                    server_proof, proto.prove(token, proto.SERVER_SIDE, transcript)
                ):
                    raise JoinRefusedError(
                        f"the clock server at {addr} could not prove it knows the token: it "
                        "is not the simulation you meant (or the tokens differ); the token "
                        "was not sent to it"
                    )
                mine = proto.prove(token, proto.CLIENT_SIDE, transcript)
            self._reader.limit = proto.MAX_FRAME_LIMIT  # the server proved itself
            sock.sendall(proto.proof(mine))
            kind, payload = self._read_one(sock, deadline, addr, self._reader, self._early)
        if kind == proto.REFUSE:
            code, reason = proto.parse_refuse(payload)
            if code not in (proto.REFUSE_FINAL, proto.REFUSE_BUSY):  # an older server
                code, reason = proto.REFUSE_FINAL, payload.decode(errors="replace")
            if code == proto.REFUSE_BUSY:
                return None
            raise JoinRefusedError(
                f"the clock server at {addr} refused {self.name!r}: {one_line(reason)}"
            )
        if kind != proto.WELCOME:
            raise ProtocolError(
                f"{addr} answered the handshake with frame kind {kind}, not WELCOME"
            )
        version, now_ns, max_frame, raw_info = proto.parse_welcome(payload)
        if version != proto.VERSION:
            raise ProtocolError(
                f"{addr} speaks protocol version {version}, this process {proto.VERSION}; "
                "run the same evclock version on both sides"
            )
        self._max_frame = max_frame
        try:
            info = json.loads(raw_info) if raw_info else {}
        except ValueError:
            raise ProtocolError(f"{addr} sent unreadable scenario info") from None
        return sock, now_ns, info

    def _check_unproven_answer(self, addr: Address, kind: int, payload: bytes) -> None:
        """A first answer other than a CHALLENGE, to a participant with a token: returns for
        a busy REFUSE (try again), else raises :class:`~evclock.remote.JoinRefusedError`.

        A busy answer is only retried: it gets nothing more than another HELLO, and an
        impostor that keeps answering busy delays the join no more than one that never
        answers. Anything else ends the join, naming the unauthenticated server; a REFUSE's
        reason is shown quoted and shortened, as the unproven text it is.
        """
        what = f"a frame of kind {kind} ({bytes((kind,))!r})"
        if kind == proto.REFUSE:
            code, reason = proto.parse_refuse(payload)
            if code == proto.REFUSE_BUSY:
                return None
            if code == proto.REFUSE_TLS and addr.scheme == "tcp":
                tls = dataclasses.replace(addr, scheme="tls")
                raise JoinRefusedError(
                    f"the clock server at {addr} serves TLS only: join it with {tls}, verified "
                    "with tls_ca or tls_fingerprint (evclock control: --tls-ca or "
                    "--tls-fingerprint); nothing but the HELLO was sent to it"
                )
            what = f"a REFUSE (saying {shown(reason)})"
        elif kind == proto.WELCOME:
            what = "a WELCOME"
        raise JoinRefusedError(
            f"the clock server at {addr} answered the HELLO with {what} before proving it "
            "knows the token: it is an unauthenticated server (not the simulation you "
            "meant, or not an evclock clock server); nothing but the HELLO was sent to it"
        )

    @staticmethod
    def _read_one(
        sock: socket.socket,
        deadline: float,
        addr: Address,
        reader: proto.Reader,
        rest: list[tuple[int, bytes]],
    ) -> tuple[int, bytes]:
        """The server's first frame; frames that came with it go to ``rest`` (and a part
        of the next one stays in ``reader``): nothing the server sent is dropped."""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ClockLostError(f"the clock server at {addr} did not answer the HELLO in time")
            sock.settimeout(remaining)
            try:
                data = _tls.recv(sock, 65536)
            except TimeoutError:
                continue
            except OSError as exc:
                raise ClockLostError(
                    f"the clock server at {addr} dropped the connection: {exc}"
                ) from None
            if not data:
                raise ClockLostError(f"the clock server at {addr} closed the connection at join")
            frames = reader.feed(data)
            if frames:
                rest.extend(frames[1:])
                return frames[0]

    # ------------------------------------------------------------ TimeSource

    def attach(self, loop: Any) -> None:
        """Called once by the :class:`~evclock.SimEventLoop` this source drives; any other
        host (a ``SimDriver``) is refused with :class:`~evclock.SimDriverError`."""
        from evclock.hosts._loop import SimEventLoop

        # The host is the kernel of the loop this source drives; the socket is served by
        # that loop (add_reader), so only a SimEventLoop can host a clock-server link.
        event_loop = getattr(loop, "host", None)
        if not isinstance(event_loop, SimEventLoop):
            # A SimDriver only approximates "every task has finished its work at t" (a
            # bounded settle; task inspection on uvloop) and leaves the loop's own timers
            # on wall time: a DONE it sent could come before work due at t, which lockstep
            # must never do, and a follower's asyncio timeouts would not follow the
            # server. Refuse, and leave the server cleanly (it is waiting for this DONE).
            self.close()
            raise InvalidTypeError(
                f"a RemoteClockSource (the clock server at {self._address}) can only drive a "
                f"SimEventLoop, not a {type(event_loop).__name__}: lockstep needs a host that "
                "knows exactly when every task has finished its work at the granted time, "
                "and the loop's own timers (asyncio.sleep, timeouts) on sim time. Run the "
                "joining program with evclock.run(main(), clock=...) or EVCLOCK_CLOCK, or "
                "asyncio.Runner(loop_factory=evclock.loop_factory(clock=...)), and keep "
                "your foreign loop (uvloop, a web server) in a separate process that talks "
                "to it"
            )
        super().attach(loop)
        self._loop = event_loop

    @property
    def now_ns(self) -> int:
        """The server's sim time as last granted or announced, in integer nanoseconds."""
        return self._now

    @property
    def address(self) -> str:
        """The clock server's address."""
        return str(self._address)

    @property
    def errors(self) -> tuple[str, ...]:
        """Why the simulation refused frames of this process (its newest 100 ERROR answers:
        data it could not apply, a frame out of place), oldest first."""
        return tuple(reason for _, reason in self._errors)

    def describe(self) -> str:
        """The source for messages: the server's address, the mode and the name."""
        return f"the clock server at {self._address} ({self.mode} participant {self.name!r})"

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Never blocks: the granted/announced time, or the current one ("waiting")."""
        if self._lost is not None:
            raise self._lost
        if not self._reading:
            self._start_reading()
            if self._early:  # frames that came with the WELCOME, first
                now = self._now
                early, self._early = self._early, []
                self._handle_frames(early)
                if self._now != now:
                    return self._now  # a jump: its woken tasks run before anything else
        now = self._now
        if self._lockstep:
            if self._jump_pending is not None and self._granted is None:
                self._apply_pending_jump()  # its round at the jump's time is over: now jump
                return self._now
            if self._working:  # everything at `now` is done: say so, name the next deadline
                self._working = False
                # The round's data went into _out before: one send carries data and DONE.
                self._send(proto.done(now, proto.NO_DEADLINE if target_ns is None else target_ns))
                self._waiting_since = time.monotonic()
                # The round's fast path: with nothing else outside the loop, wait for the
                # grant here and use it at once (the loop would wait for this fd next).
                if self._granted is None and not self._writing and self._loop._wait_for_source():
                    self._on_readable()
                    if self._lost is not None:
                        raise self._lost
                    if self._now != now:
                        return self._now  # a jump came with it: its woken tasks run first
            granted = self._granted
            if granted is not None:
                self._granted = None
                self._working = True
                self._waiting_since = None
                if self._held_out:
                    for frame in self._held_out:
                        self._send(frame)
                    self._held_out.clear()
                return self._move_to(granted)
            if self._inbox:
                self._schedule_dispatch()
            if self._waiting_since is not None:
                self._check_wait()
            return now
        if self._jump_pending is not None:
            before = self._jump_pending[1]
            if now < before:  # catch up with the time the simulation jumped from, exactly
                return self._move_to(before if target_ns is None else min(target_ns, before))
            self._apply_pending_jump()  # its woken tasks run before anything else
            return self._now
        if target_ns is not None and target_ns != self._asked:
            self._asked = target_ns  # the server tells the time at this deadline at the latest
            self._send(proto.done(now, target_ns))
            self._waiting_since = time.monotonic()
        if self._latest > now:
            # Time moved: the server is alive; wait again from now if the deadline is ahead.
            reached = target_ns is None or self._latest >= target_ns
            self._waiting_since = None if reached else time.monotonic()
            return self._move_to(self._latest)
        if self._inbox:
            self._schedule_dispatch()
        if target_ns is not None and self._waiting_since is not None:
            self._check_wait()
        return now

    def _move_to(self, t_ns: int) -> int:
        self._now = t_ns
        if self._inbox:
            self._schedule_dispatch()
        return t_ns

    def _check_wait(self) -> None:
        assert self._waiting_since is not None
        waited = time.monotonic() - self._waiting_since
        if waited > self._timeout:
            self._lose(
                f"the clock server at {self._address} sent no time for {waited:.1f} s of wall "
                f"time (limit {self._timeout:g} s: is it stopped or overloaded?)"
            )
            assert self._lost is not None
            raise self._lost

    def close(self) -> None:
        """Leave the server (a clean goodbye) and close the connection."""
        if self._closed:
            return
        self._closed = True
        if self._lost is None and self._sock.fileno() >= 0:
            with contextlib.suppress(OSError):
                self._sock.setblocking(True)
                self._sock.settimeout(1.0)
                self._sock.sendall(bytes(self._out) + proto.bye())
        self._sock.close()

    # ------------------------------------------------------------ the data channel

    def publish(self, topic: str, data: bytes) -> None:
        """Send ``data`` on ``topic``, stamped with the current sim time.

        In lockstep the simulation handles it at this time, before physics advances; other
        participants subscribed to ``topic`` receive it at this time as well.
        """
        if not isinstance(data, bytes | bytearray | memoryview):
            raise InvalidTypeError(f"data must be bytes, got {type(data).__name__}")
        self._check_usable()
        frame = proto.publish(self._now, topic, bytes(data), self._max_frame)
        if not self._lockstep:
            self._send(frame)
        elif self._working:
            self._out += frame  # sent with this round's DONE (or before a call): no extra wakeup
        else:
            self._held_out.append(frame)  # between rounds: goes with the next grant's work

    def subscribe(self, topic: str, callback: Callable[[Message], object]) -> None:
        """Call ``callback(message)`` (on this loop, at the message's sim time) for data
        published on ``topic`` by the simulation or other participants."""
        if not callable(callback):
            raise InvalidTypeError(f"callback must be callable, got {type(callback).__name__}")
        self._check_usable()
        frame = proto.subscribe(topic)
        if topic not in self._subscribers:
            self._subscribers[topic] = []
            self._send(frame)
        self._subscribers[topic].append(callback)

    def call(self, service: str, data: bytes = b"") -> bytes:
        """Ask the simulation's ``service`` (see ``ClockServer.provide``) and wait for the
        answer, bounded by the address's ``timeout``. Answered at the current sim time."""
        if not isinstance(data, bytes | bytearray | memoryview):
            raise InvalidTypeError(f"data must be bytes, got {type(data).__name__}")
        self._check_usable()
        call_id = self._call_ids()
        self._send(
            proto.call(call_id, service, bytes(data), self._max_frame)
        )  # with the round's data, at once
        deadline = time.monotonic() + self._timeout
        sock = self._sock
        while call_id not in self._replies:
            if self._lost is not None:
                raise self._lost
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._lose(
                    f"the clock server at {self._address} did not answer a call to "
                    f"{service!r} within {self._timeout:g} s of wall time"
                )
                assert self._lost is not None
                raise self._lost
            wants_write = [sock] if self._out else []
            readable, writable, _ = select.select([sock], wants_write, [], remaining)
            if writable:
                self._flush()
            if readable:
                self._on_readable()
        ok, payload = self._replies.pop(call_id)
        if not ok:
            raise RemoteCallError(
                f"call to {service!r} failed in the simulation: "
                f"{one_line(payload.decode(errors='replace'))}"
            )
        return payload

    def _check_usable(self) -> None:
        if self._lost is not None:
            raise self._lost
        if self._closed:
            raise ClockLostError(f"the connection to {self._address} is closed")

    def _schedule_dispatch(self) -> None:
        loop: Any = self._loop
        loop.call_soon(self._dispatch)

    def _dispatch(self) -> None:
        now = self._now
        due = [m for m in self._inbox if m[0] <= now]
        if not due:
            return
        self._inbox = [m for m in self._inbox if m[0] > now]
        self._deliver(due)

    def _deliver(self, messages: list[tuple[int, str, str, bytes]]) -> None:
        for t_ns, sender, topic, data in messages:
            message = Message(sender, topic, new_time(t_ns, SIM), data)
            for callback in self._subscribers.get(topic, ()):
                callback(message)

    # ------------------------------------------------------------ socket I/O

    def _start_reading(self) -> None:
        loop: Any = self._loop
        loop.add_reader(self._sock, self._on_readable)
        self._reading = True

    def _send(self, frame: bytes) -> None:
        if self._out:
            if self._writing:
                self._out += frame  # the writer callback sends it in order
                return
            frame = bytes(self._out + frame)
            self._out.clear()
        try:
            sent = self._sock.send(frame)
        except _tls.WOULD_BLOCK:
            sent = 0
        except ConnectionError:
            self._lose(self._closed_by_server())
            return
        except OSError as exc:
            self._lose(f"the connection to the clock server at {self._address} failed: {exc}")
            return
        if sent < len(frame):
            self._out += frame[sent:]
            if self._reading:
                loop: Any = self._loop
                loop.add_writer(self._sock, self._flush)
                self._writing = True

    def _flush(self) -> None:
        try:
            sent = self._sock.send(self._out)
        except _tls.WOULD_BLOCK:
            return
        except ConnectionError:
            self._lose(self._closed_by_server())
            return
        except OSError as exc:
            self._lose(f"the connection to the clock server at {self._address} failed: {exc}")
            return
        del self._out[:sent]
        if not self._out and self._writing:
            self._writing = False
            loop: Any = self._loop
            loop.remove_writer(self._sock)

    def _on_readable(self) -> None:
        try:
            # On TLS this also takes what the SSL object decrypted already: nothing is left
            # where the loop's poll of the socket (_wait_for_source, add_reader) cannot see it.
            data = _tls.recv(self._sock, 262144)
        except _tls.WOULD_BLOCK:
            return
        except ConnectionError:
            self._lose(self._closed_by_server())
            return
        except OSError as exc:
            self._lose(f"the connection to the clock server at {self._address} failed: {exc}")
            return
        if not data:
            self._lose(self._closed_by_server())
            return
        if len(data) == proto.STAMP_SIZE and not self._reader.pending:
            length, kind, t_ns = proto.unpack_stamp(data)
            if (
                kind == proto.GRANT
                and length == proto.STAMP_SIZE - 4
                and t_ns >= self._now
                and self._jump_pending is None
            ):
                self._granted = t_ns  # a round's GRANT alone: the hot path
                return
        if self._waiting_since is not None:
            self._waiting_since = time.monotonic()  # the server is alive (keepalives included)
        try:
            frames = self._reader.feed(data)
        except ProtocolError as exc:
            self._lose(f"the clock server at {self._address} broke the protocol: {exc}")
            return
        self._handle_frames(frames)

    def _handle_frames(self, frames: list[tuple[int, bytes]]) -> None:
        try:
            for kind, payload in frames:
                self._handle(kind, payload)
        except ProtocolError as exc:
            self._lose(f"the clock server at {self._address} broke the protocol: {exc}")

    def _handle(self, kind: int, payload: bytes) -> None:
        if self._jump_pending is not None and kind in _AFTER_A_JUMP:
            self._after_jump.append((kind, payload))  # about the new time: after the jump
            return
        if kind == proto.GRANT:
            t_ns = proto.parse_stamp(payload)
            self._check_forward(t_ns)
            self._granted = t_ns
        elif kind == proto.TIME:  # a follower's time; a keepalive for a lockstep participant
            t_ns = proto.parse_stamp(payload)
            self._check_forward(t_ns)
            self._latest = max(self._latest, t_ns)
        elif kind == proto.DELIVER:
            self._inbox.append(proto.parse_deliver(payload))
        elif kind == proto.REPLY:
            call_id, ok, data = proto.parse_reply(payload)
            self._replies[call_id] = (ok, data)
        elif kind == proto.JUMP:
            self._on_jump(*proto.parse_jump(payload))
        elif kind == proto.ERROR:
            about, reason = proto.parse_error(payload)
            log.warning("the clock server at %s: %s", self._address, one_line(reason))
            self._errors.append((about, reason))
            del self._errors[:-_KEEP_ERRORS]
        elif kind == proto.CLOSING:
            self._lose(one_line(payload.decode(errors="replace")))
        else:
            raise ProtocolError(f"unexpected frame kind {kind} from the server")

    def _on_jump(self, seq: int, before_ns: int, after_ns: int) -> None:
        """The simulation's time jumped: this clock jumps alike (evclock's jump policy:
        handlers run, pending sleeps raise ClockJumpedError, asyncio timers keep their remaining
        delay), after the data delivered before the jump, then works at the new time.

        A participant behind the simulation first moves to ``before_ns``, so it jumps from
        the time the simulation jumped from, as an in-process task would (a jump back is
        never seen as a move on, and every process's handlers see the same jump): a
        follower's deadlines up to it fire on the way; a lockstep participant granted that
        time first does its work there (the grant came before the jump); one not granted
        has nothing due until then (its next deadline is later) and moves there at once.
        """
        if self._now < before_ns:
            if not self._lockstep or self._granted is not None:
                self._jump_pending = (seq, before_ns, after_ns)
                return
            self._now = before_ns
            host: Any = self._host
            host.stepped_to(before_ns)
        self._apply_jump(seq, before_ns, after_ns)

    def _apply_pending_jump(self) -> None:
        """This clock has reached the time the simulation jumped from: jump, then handle
        the frames read meanwhile (another JUMP among them waits again)."""
        pending = self._jump_pending
        assert pending is not None
        self._jump_pending = None
        frames, self._after_jump = self._after_jump, []
        self._apply_jump(*pending)
        self._handle_frames(frames)

    def _apply_jump(self, seq: int, before_ns: int, after_ns: int) -> None:
        pending, self._inbox = self._inbox, []
        self._deliver(pending)  # everything delivered before the jump is handled before it
        self._granted = None  # a grant read before the jump is about the old time
        self._latest = after_ns
        self._asked = proto.NO_DEADLINE  # a follower names its deadline again
        self._waiting_since = None
        if self._lockstep:
            self._working = True  # granted the new time: DONE once its work there is done
        self._send(proto.jumped(seq))
        if after_ns != self._now:
            host: Any = self._host
            host.jump(self._now, after_ns, self._assign)

    def _assign(self, t_ns: int) -> None:
        self._now = t_ns

    def _check_forward(self, t_ns: int) -> None:
        if t_ns < self._now:
            raise ProtocolError(
                f"sim time went backwards ({self._now} -> {t_ns} ns) without a JUMP frame"
            )

    def _closed_by_server(self) -> str:
        return (
            f"the clock server at {self._address} closed the connection "
            "(the simulation died or was killed)"
        )

    def _lose(self, reason: str) -> None:
        if self._lost is None:
            self._lost = ClockLostError(reason)
        self._writing = False
        self.io_fd = None
        if self._reading:
            self._reading = False
            loop: Any = self._loop
            if loop is not None and not loop.is_closed():
                loop.remove_reader(self._sock)
                loop.remove_writer(self._sock)
        self._sock.close()


def participant() -> RemoteClockSource:
    """The clock-server connection of the running loop (to publish, subscribe and call).

    :returns: the :class:`RemoteClockSource` the running loop follows.
    :raises NoSimulationError: this program did not join a clock server.
    """
    import asyncio

    from evclock.hosts._loop import SimEventLoop

    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        loop = None
    source = loop.source if isinstance(loop, SimEventLoop) else None
    if not isinstance(source, RemoteClockSource):
        raise NoSimulationError(
            "this program did not join a clock server: run it with "
            "evclock.run(main(), clock='unix:///path.sock') or EVCLOCK_CLOCK=unix:///path.sock"
        )
    return source


def source_from_url(url: str) -> TimeSource:
    """The ``unix://``, ``tcp://`` and ``tls://`` entries of the clock-scheme registry."""
    if not isinstance(url, str):
        raise InvalidArgumentError(f"a clock address is a string, got {url!r}")
    return RemoteClockSource(url)
