"""One connection to the clock server: what the server knows of a peer.

A :class:`Peer` exists from a connection's accept on, and is a participant once its handshake
completed (it then has a name). ``_admission`` creates it; every part of the server reads it.
"""

from __future__ import annotations

import socket
import time

from evclock.remote import _protocol as proto
from evclock.remote._checks import shown


class Peer:
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
        "outbox_bytes",
        "pid",
        "reader",
        "server_nonce",
        "silent_reported",
        "sock",
        "stale_time",
        "subscriptions",
        "tls_waiting",
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
        self.outbox_bytes = 0  # the data bytes in outbox (Limits.round_bytes)
        self.subscriptions: set[str] = set()  # membership tests only, never iterated
        self.lost = False
        self.silent_reported = False
        self.stale_time = False
        self.jump_sent = 0  # the last JUMP sent to it, and the last it applied (JUMPED):
        self.jump_acked = 0  # until they match, its DONEs are from before the jump
        self.tls_waiting = False  # a tls:// connection whose TLS handshake is not done

    def describe(self) -> str:
        mode = "lockstep" if self.mode == proto.MODE_LOCKSTEP else "follow"
        pid = "" if self.pid is None else f", pid {self.pid}"
        return f"{shown(self.name)} ({mode}{pid})"

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
