"""Admission: who may connect, and who may join - everything before authentication.

A new connection is *pending* until its handshake completes: it is read with the
pre-authentication frame limit (``proto.PRE_AUTH_MAX_FRAME``), it has ``PRE_HELLO_TIMEOUT``
wall seconds to send its HELLO and ``HELLO_TIMEOUT`` to finish, and at most ``MAX_PENDING``
connections are pending at once: a new one then evicts the oldest pending one that has sent
no HELLO, else the oldest (told busy, it retries), so that connections that never finish
cannot keep an honest participant out. On a
Unix socket the peer's user id (``SO_PEERCRED``) must be one the server admits. The handshake
is HELLO -> CHALLENGE (the server's proof first) -> PROOF -> WELCOME or REFUSE; a
participant that passed it joins (``_on_hello``) and is read with the documented frame
limit from then on. On ``tls://`` a TLS handshake comes first (``_tls_handshake``, never
blocking the loop), within the same ``HELLO_TIMEOUT`` and pending slots.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import socket
import ssl
import time
from typing import Any, Final

from evclock._errors import ProtocolError
from evclock.remote import _protocol as proto
from evclock.remote import _tls
from evclock.remote._address import peer_credentials
from evclock.remote._checks import one_line, shown
from evclock.remote._core import ServerCore
from evclock.remote._peer import Peer

log = logging.getLogger("evclock.remote")

#: Wall seconds a new connection has to complete its handshake (HELLO and PROOF).
HELLO_TIMEOUT: Final = 5.0
#: Wall seconds a new connection has to send its HELLO (an honest one sends it at once).
PRE_HELLO_TIMEOUT: Final = 1.0
#: Connections in their handshake at once; a new one beyond evicts the oldest (told busy: the
#: participant retries).
MAX_PENDING: Final = 64
#: Wall seconds between two log lines about refused connections (a flood logs a count).
REFUSALS_LOGGED_EVERY: Final = 1.0


class RefusalLog:
    """Logs refused and evicted connections at most once every ``REFUSALS_LOGGED_EVERY``
    wall seconds; a line says how many were not logged since the previous one."""

    __slots__ = ("_next", "_unlogged")

    def __init__(self) -> None:
        self._next = 0.0
        self._unlogged = 0

    def refused(self, what: str, *args: object) -> None:
        """Log ``what % args`` now, or count it for the next line."""
        now = time.monotonic()
        if now < self._next:
            self._unlogged += 1
            return
        self._next = now + REFUSALS_LOGGED_EVERY
        if self._unlogged:
            log.warning(
                "clock server: " + what + " (and %d more connections refused or evicted "
                "since the previous line)",
                *args,
                self._unlogged,
            )
            self._unlogged = 0
        else:
            log.warning("clock server: " + what, *args)

    def flush(self) -> None:
        """Log the count of what was not logged yet (the server stops)."""
        if self._unlogged:
            log.warning(
                "clock server: %d more connections refused or evicted since the previous line",
                self._unlogged,
            )
            self._unlogged = 0


class Admission(ServerCore):
    """The clock server's accepting, handshake and joining of participants."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._refusals = RefusalLog()

    def _on_accept(self) -> None:
        for _ in range(16):
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. out of file descriptors: keep serving the others
                self._refusals.refused("accept failed: %s", exc)
                return
            sock.setblocking(False)
            if sock.family != socket.AF_UNIX:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            peer = Peer(sock)
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
                # The oldest that has not sent its HELLO goes first: a flood of silent
                # connections, however fast, never evicts one that is in its handshake.
                silent = next((other for other in self._pending if not other.greeted), None)
                self._refuse(
                    self._pending[0] if silent is None else silent,
                    f"evicted: {MAX_PENDING} connections were in their handshake and this was "
                    f"the oldest{'' if silent is None else ' that had sent no HELLO'}; try again",
                    proto.REFUSE_BUSY,
                )
            peer.tls_waiting = self._tls is not None
            self._pending.append(peer)
            self._loop.add_reader(sock, self._on_readable, peer)
            # The server holds sim time exactly while a peer's traffic matters (a working
            # participant): the loop must not also infer held time from its unread bytes
            # (a follower that reads late must never hold the simulation).
            self._loop._account_fd(sock.fileno(), True)

    def _tls_handshake(self, peer: Peer) -> bool:
        """The server's side of a TLS handshake, as far as the bytes allow (never blocks):
        True once it is done. A client whose first byte does not start TLS is refused in
        plain text, so that a plain evclock participant reads why."""
        sock = peer.sock
        context = self._tls
        assert context is not None
        if not isinstance(sock, ssl.SSLSocket):
            try:
                first = sock.recv(1, socket.MSG_PEEK)
            except _tls.WOULD_BLOCK:
                return False
            except OSError as exc:
                self._lost(peer, f"lost its connection ({exc})")
                return False
            if not first:
                self._lost(peer, "closed its connection in the TLS handshake")
                return False
            if first[0] != _tls.TLS_RECORD_HANDSHAKE:
                self._refuse(
                    peer,
                    f"this clock server speaks TLS: join it with {self._address} (and "
                    "?tls_ca= or ?tls_fingerprint= to verify it), not plain tcp://",
                    proto.REFUSE_TLS,
                )
                return False
            self._loop.remove_reader(sock)
            sock = peer.sock = context.wrap_socket(
                sock, server_side=True, do_handshake_on_connect=False
            )
            self._loop.add_reader(sock, self._on_readable, peer)
        try:
            sock.do_handshake()
        except ssl.SSLWantReadError:
            return False
        except ssl.SSLWantWriteError:  # its send buffer is full: go on once it drains
            self._loop.add_writer(sock, self._tls_writable, peer)
            return False
        except (ssl.SSLError, OSError) as exc:
            reason = getattr(exc, "reason", None) or exc
            self._refuse(peer, f"TLS handshake failed ({reason})")
            return False
        peer.tls_waiting = False
        return True

    def _tls_writable(self, peer: Peer) -> None:
        self._loop.remove_writer(peer.sock)
        self._on_readable(peer)

    def _transcript(self, peer: Peer) -> bytes:
        return proto.transcript(
            proto.VERSION, peer.mode, peer.greeted, peer.client_nonce, peer.server_nonce
        )

    def _handshake(self, peer: Peer, kind: int, payload: bytes) -> None:
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
            self._refuse(
                peer,
                "wrong or missing token: join with ?token=... in the clock address (evclock "
                "control: --token-file PATH or EVCLOCK_TOKEN)",
            )
            return
        self._on_hello(peer, peer.mode, peer.greeted)

    def _on_hello(self, peer: Peer, mode: int, name: str) -> None:
        replaced = None
        for other in self._peers:
            if other.name == name:
                if not other.lost:
                    self._refuse(
                        peer,
                        f"a participant named {shown(name)} is already joined; give this process "
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

    def _refuse(self, peer: Peer, reason: str, code: int = proto.REFUSE_FINAL) -> None:
        pid = "" if peer.pid is None else f" (pid {peer.pid})"
        reason = one_line(reason)
        self._refusals.refused("refused a connection%s: %s", pid, reason)
        with contextlib.suppress(OSError):
            peer.sock.send(proto.refuse(reason, code))
        if peer in self._pending:
            self._pending.remove(peer)
        self._disconnect(peer)

    def _handshake_late(self, now: float) -> bool:
        """Whether a pending connection ran out of time (read by the watchdog's thread)."""
        return any(_late(p, now) for p in list(self._pending))

    def _expire_handshakes(self, now: float) -> None:
        for peer in list(self._pending):
            late = _late(peer, now)
            if late:
                self._refuse(peer, late)


def _late(peer: Peer, now: float) -> str:
    """Why ``peer``, pending, ran out of time ("" if it did not)."""
    waited = now - peer.accepted_at
    if waited > HELLO_TIMEOUT:
        return f"no complete handshake within {HELLO_TIMEOUT:g} s"
    if not peer.greeted and waited > PRE_HELLO_TIMEOUT:
        return f"no HELLO within {PRE_HELLO_TIMEOUT:g} s"
    return ""
