"""The clock server's shared state, and its one way to send to a peer.

:class:`~evclock.remote.ClockServer` (``_server``) is assembled from one part per trust
boundary, each a mixin over :class:`ServerCore`, so that a reviewer reads one module per
boundary:

* ``_admission``: who may connect and join (credentials, the handshake slots, HELLO,
  CHALLENGE and PROOF) - everything a peer can reach before it is authenticated;
* ``_rounds``: sim time held while lockstep participants work, their deadlines, time jumps
  and the followers' time - how a joined participant can hold or move the simulation;
* ``_routing``: publications and subscriptions, and the end-of-round delivery of data;
* ``_services``: calls answered by the simulation's own code (the physics services of
  ``_physics`` and ``_mujoco_physics`` are installed through it);
* ``_server``: the public class, what reaches it from a socket, the fault policies and the
  watchdog.

This core owns the state the parts share and sends frames: a send never blocks the loop;
what a socket does not take at once waits in the peer's ``out`` and goes when it is
writable.
"""

from __future__ import annotations

import asyncio
import socket
import ssl
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from evclock._errors import EvClockError
from evclock.hosts._loop import SimEventLoop
from evclock.remote import _protocol as proto
from evclock.remote import _tls
from evclock.remote._address import Address
from evclock.remote._limits import Limits, exceeded
from evclock.remote._peer import Peer

if TYPE_CHECKING:
    from evclock.remote._routing import Message


class ServerCore:
    """The state every part of the clock server shares (see the module docstring)."""

    def __init__(
        self,
        loop: SimEventLoop,
        listener: socket.socket,
        address: Address,
        *,
        policy: str,
        step_timeout: float | None,
        token: str | None,
        info: bytes,
        max_frame: int,
        peer_uids: tuple[int, ...],
        limits: Limits,
        tls: ssl.SSLContext | None = None,
    ) -> None:
        self._loop = loop
        # Its kernel (SimClock.core): sim time read as a plain attribute on every round.
        self._kernel = loop.clock.core
        self._policy = policy
        self._step_timeout = step_timeout
        self._token = token
        self._info = info
        self._max_frame = max_frame
        self._peer_uids = peer_uids
        self._limits = limits
        self._tls = tls  # tls://: every connection is a TLS session first (_admission)
        self._listener = listener
        self._address = address
        self._pending: list[Peer] = []  # connected, HELLO not yet accepted
        self._peers: list[Peer] = []  # joined, in join order
        self._departed: list[Peer] = []  # left cleanly with data still to deliver
        self._joined = 0
        self._working = 0  # lockstep participants working at the current time
        self._holds = 0  # holds on the loop's sim time that this server owns
        # Deadline (sim ns) -> its loop timer and the participants due then.
        self._due: dict[int, tuple[asyncio.TimerHandle, list[Peer]]] = {}
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
        self._join_missing: Callable[[], tuple[str, str]] = lambda: ("", "")
        self._jumps = 0  # time jumps of the simulation so far (JUMP frames are numbered)

    if TYPE_CHECKING:  # one part calls another's: each is defined in the module named

        def _on_readable(self, peer: Peer) -> None: ...  # _server
        def _bad_frame(self, peer: Peer, kind: int, reason: str) -> None: ...  # _server
        def _lost(self, peer: Peer, reason: str) -> None: ...  # _server
        def _start_work(self, peer: Peer, now: int) -> None: ...  # _rounds
        def _release(self) -> None: ...  # _rounds
        def _unschedule(self, peer: Peer) -> None: ...  # _rounds
        def _add_step_hook(self) -> None: ...  # _rounds
        def _send_time(self, peer: Peer, now: int) -> None: ...  # _rounds
        def _close_round(self) -> None: ...  # _routing
        def _deliver_round(self, regrant: list[Peer]) -> None: ...  # _routing
        def _grant_all(self, peers: list[Peer]) -> None: ...  # _routing

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

    # ------------------------------------------------------------ sending

    def _send(self, peer: Peer, frame: bytes) -> None:
        if peer.out:
            peer.out += frame
            if len(peer.out) > self._limits.unsent_bytes:
                self._lost(
                    peer,
                    "does not read its connection: "
                    + exceeded(self._limits, "unsent_bytes", f"{len(peer.out)} bytes unsent"),
                )
            return
        try:
            sent = peer.sock.send(frame)
        except _tls.WOULD_BLOCK:
            sent = 0
        except OSError:
            # The peer closed its end: its reader sees the goodbye (or the bare EOF) next
            # and decides between a clean leave and a fault; nothing more is sent to it.
            peer.out += b"\0"
            return
        if sent < len(frame):
            peer.out += frame[sent:]
            self._loop.add_writer(peer.sock, self._on_writable, peer)

    def _on_writable(self, peer: Peer) -> None:
        try:
            sent = peer.sock.send(peer.out)
        except _tls.WOULD_BLOCK:
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

    def _disconnect(self, peer: Peer) -> None:
        self._unschedule(peer)
        if peer.sock.fileno() >= 0:
            self._loop._account_fd(peer.sock.fileno(), False)
            if not self._loop.is_closed():
                self._loop.remove_reader(peer.sock)
                self._loop.remove_writer(peer.sock)
            peer.sock.close()

    def _now(self) -> str:
        return f"{self._kernel.now_ns / 1e9:.6f} s of sim time"
