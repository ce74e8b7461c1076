"""The clock server: a simulation serves its sim time to processes that join it.

It lives on the simulation's :class:`~evclock.SimEventLoop` and uses nothing but the loop's
own machinery (``add_reader``, the loop's hold count, its timer heap). The server is
assembled from one part per trust boundary (see ``_core``): ``_admission`` (connecting and
joining), ``_rounds`` (holds, deadlines, jumps, followers' time), ``_routing`` (publications
and subscriptions) and ``_services`` (calls). This module is the public class that puts them
together: its options, what reaches it from a joined participant's socket, the fault
policies (``abort``, ``drop``, ``pause``) and the watchdog that enforces wall-time limits.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Iterable, Mapping
from typing import Any, Final

from evclock._errors import (
    EvClockError,
    InvalidArgumentError,
    InvalidTypeError,
    ParticipantLostError,
    ProtocolError,
)
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._jumps import JumpThreshold
from evclock.outside._threads import mark_internal
from evclock.remote import _admission, _tls
from evclock.remote import _protocol as proto
from evclock.remote._address import bound_address, listen, parse_address, private_dir
from evclock.remote._admission import Admission
from evclock.remote._checks import one_line, shown
from evclock.remote._limits import Limits
from evclock.remote._peer import Peer
from evclock.remote._rounds import Rounds
from evclock.remote._routing import Message, Routing
from evclock.remote._services import Services
from evclock.remote._token import check_token
from evclock.time._time import Duration

__all__ = ["DEFAULT_STEP_TIMEOUT", "ClockServer", "Message", "default_address", "serve"]

log = logging.getLogger("evclock.remote")

FAULT_POLICIES: Final = ("abort", "drop", "pause")
#: Wall seconds a participant may work on one step before the fault policy applies.
DEFAULT_STEP_TIMEOUT: Final = 30.0
#: Wall seconds the simulation waits for its participants to join, by default.
DEFAULT_JOIN_TIMEOUT: Final = 60.0
#: Wall seconds between keepalives to waiting participants (their ``timeout`` must be longer).
KEEPALIVE: Final = 0.2
#: Bad frames answered with ERROR per participant before it is treated as lost (a flood).
MAX_ERRORS: Final = 10_000


def default_address() -> str:
    """A per-process Unix socket in the user's private directory (see ``private_dir``)."""
    return f"unix://{private_dir()}/sim-{os.getpid()}.sock"


class ClockServer(Admission, Rounds, Routing, Services):
    """Serves a :class:`~evclock.SimEventLoop`'s sim time; create it with
    :func:`evclock.remote.serve`.

    Participants join in *lockstep* (the simulation waits for them every step they have a
    deadline in) or *follow* (they receive every step's time and never hold the simulation).

    The options are those of :func:`~evclock.remote.serve`, which documents them in full.

    :param loop: the :class:`~evclock.SimEventLoop` whose sim time is served.
    :param address: ``unix:///path.sock``, ``tcp://HOST:PORT`` or ``tls://HOST:PORT`` to
        listen on.
    :param on_fault: ``abort``, ``drop`` or ``pause``: what a lost lockstep participant causes.
    :param step_timeout: wall seconds a lockstep participant may work on one step (None: no
        limit).
    :param token: the shared secret participants must present (default: the address's
        ``?token=``).
    :param info: JSON-serialisable facts given to every participant at join.
    :param allow_remote: allow listening on a non-loopback address (which needs a token).
    :param max_frame: the largest frame (bytes) a joined participant may send.
    :param peer_uids: user ids allowed to join over a Unix socket (default: this user's).
    :param limits: what one participant may make the server hold (default: ``Limits()``).
    :param tls_cert: ``tls://``: the server's certificate chain (PEM file).
    :param tls_key: ``tls://``: the certificate's private key (PEM file).
    :raises InvalidArgumentError: an unknown ``on_fault``, a bad ``step_timeout`` or
        ``max_frame``, an invalid or unusable address, a TCP or TLS address without a
        token, a TLS address without a certificate and key (or a certificate elsewhere), a
        non-loopback address without ``allow_remote`` or on plain TCP, or ``info`` that is
        not JSON-serialisable.
    :raises InvalidTypeError: ``token`` is not a non-empty string, ``address`` is not a
        string, ``peer_uids`` holds something other than integers, or ``limits`` is not a
        :class:`~evclock.remote.Limits`.
    :raises WeakTokenError: ``token`` is below 128 bits (fewer than 22 URL-safe characters).
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
        limits: Limits | None = None,
        tls_cert: str | None = None,
        tls_key: str | None = None,
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
        if limits is not None and not isinstance(limits, Limits):
            raise InvalidTypeError(
                f"limits must be an evclock.remote.Limits, got {type(limits).__name__}"
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
        if token is not None:
            check_token(token)  # its proof goes to anyone who connects: an offline oracle
        if parsed.scheme in ("tcp", "tls") and token is None:
            raise InvalidArgumentError(
                f"serving on {parsed} needs a shared token (token=... or ?token=... in the "
                f"address): any user of the machine can reach a {parsed.scheme} port, so "
                "participants must prove they know it (it is never sent); or serve on a "
                "unix:// socket"
            )
        tls = None
        if parsed.scheme == "tls":
            if tls_cert is None or tls_key is None:
                raise InvalidArgumentError(
                    f"serving on {parsed} needs the server's certificate and key: "
                    "tls_cert='cert.pem', tls_key='key.pem' (CLI: --tls-cert, --tls-key)"
                )
            tls = _tls.server_context(tls_cert, tls_key)
        elif tls_cert is not None or tls_key is not None:
            raise InvalidArgumentError(
                f"tls_cert and tls_key are for a tls:// address, not {parsed}"
            )
        try:
            info_bytes = json.dumps(dict(info or {}), sort_keys=True).encode()
        except (TypeError, ValueError) as exc:
            raise InvalidArgumentError(f"info must be JSON-serialisable: {exc}") from None
        listener = listen(parsed, allow_remote=allow_remote)
        super().__init__(
            loop,
            listener,
            bound_address(listener, parsed),
            policy=on_fault,
            step_timeout=None if step_timeout is None else float(step_timeout),
            token=token,
            info=info_bytes,
            max_frame=max_frame,
            peer_uids=uids,
            limits=Limits() if limits is None else limits,
            tls=tls,
        )
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
        loop._account_fd(self._listener.fileno(), True)
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

    async def wait_for_participants(
        self, *names: str, count: int | None = None, timeout: float = DEFAULT_JOIN_TIMEOUT
    ) -> None:
        """Wait until the named participants (or ``count`` of them) have joined.

        Sim time is held meanwhile: the simulation does not start without them. After
        ``timeout`` wall seconds :class:`~evclock.remote.ParticipantLostError` names who is
        missing (its ``name``: the first missing name, or empty when a ``count`` is short).
        """
        for name in names:
            if not isinstance(name, str):
                raise InvalidTypeError(f"participant names are strings, got {name!r}")
        if not (isinstance(timeout, int | float) and timeout > 0):
            raise InvalidArgumentError(f"timeout must be positive wall seconds, got {timeout!r}")

        def ready() -> bool:
            joined = self.participants
            return all(n in joined for n in names) and len(joined) >= (count or 0)

        def missing() -> tuple[str, str]:
            absent = [n for n in names if n not in self.participants]
            if absent:  # the error's name: the first missing, bare
                return ", ".join(shown(n) for n in absent), absent[0]
            return f"{count} participants ({len(self.participants)} joined)", ""

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
        self._refusals.flush()
        frame = proto.closing(f"the clock server at {self._address} stopped: {reason}")
        for peer in [*self._peers, *self._pending]:
            if peer.tls_waiting:  # no TLS session yet: nothing can be said to it
                self._disconnect(peer)
                continue
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
        self._loop._account_fd(self._listener.fileno(), False)
        if not self._loop.is_closed():
            self._loop.remove_reader(self._listener)
        self._listener.close()
        if self._address.scheme == "unix":
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._address.path)

    # ------------------------------------------------------------ a joined participant's frames

    def _on_readable(self, peer: Peer) -> None:
        if peer.tls_waiting and not self._tls_handshake(peer):
            return
        try:
            # Before the handshake a read never exceeds the pre-authentication frame limit
            # (on TLS: one record, 16 KiB at most). On TLS it takes what the SSL object
            # decrypted already: nothing stays where the loop's poll cannot see it.
            data = _tls.recv(peer.sock, 262144 if peer.name else proto.PRE_AUTH_MAX_FRAME + 5)
        except _tls.WOULD_BLOCK:
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
            elif data[0] == _tls.TLS_RECORD_HANDSHAKE and self._tls is None:
                self._refuse(
                    peer,
                    f"a TLS client: this clock server serves plain {self._address.scheme}:// "
                    "(join it with that scheme, or serve on tls://)",
                )
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

    def _bad_frame(self, peer: Peer, kind: int, reason: str) -> None:
        """A well-framed frame the simulation refuses: the participant is told why, the
        frame is ignored, and the simulation goes on (a flood of them is a fault)."""
        if peer.lost or peer not in self._peers:
            return
        peer.errors += 1
        reason = one_line(reason)  # it may quote what the peer sent: one bounded line
        label = chr(kind) if 32 < kind < 127 else str(kind)
        log.warning(
            "clock server: refused a frame of kind %s from %s: %s", label, peer.describe(), reason
        )
        if peer.errors > MAX_ERRORS:
            self._lost(peer, f"sent more than {MAX_ERRORS} invalid frames")
            return
        self._send(peer, proto.error(kind, f"frame of kind {label!r} refused: {reason}"))

    def _handle(self, peer: Peer, kind: int, payload: bytes) -> None:
        if kind == proto.DONE:
            self._on_done(peer, *proto.parse_done(payload))
        elif kind == proto.PUBLISH:
            self._on_publish(peer, payload)
        elif kind == proto.CALL:
            self._on_call(peer, *proto.parse_call(payload))
        elif kind == proto.SUBSCRIBE:
            self._on_subscribe(peer, payload)
        elif kind == proto.JUMPED:
            self._on_jumped(peer, proto.parse_jumped(payload))
        elif kind == proto.BYE:
            log.info("clock server: participant %s left at %s", peer.describe(), self._now())
            self._remove(peer, clean=True)
        else:
            raise ProtocolError(f"unexpected frame kind {kind!r} from a participant")

    # ------------------------------------------------------------ faults

    def _lost(self, peer: Peer, reason: str) -> None:
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

    def _fault(self, peer: Peer, reason: str, *, dead: bool) -> None:
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
            peer.outbox_bytes = 0
            if peer.working_at is None:  # it must hold the simulation until replaced
                self._start_work(peer, self._kernel.now_ns)
        elif not peer.silent_reported:
            peer.silent_reported = True
            log.warning(
                "clock server: %s; sim time stays paused until it answers (on_fault='pause')",
                what,
            )

    def _remove(self, peer: Peer, *, clean: bool = False) -> None:
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
            peer.outbox_bytes = 0
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
        hello = _admission.HELLO_TIMEOUT
        interval = min(hello / 8, (limit or hello) / 8, KEEPALIVE)
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
            late = self._handshake_late(now)
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

    def _check_timeouts(self) -> None:
        self._check_scheduled = False
        now = time.monotonic()
        self._expire_handshakes(now)
        if self._join_deadline is not None and now > self._join_deadline:
            self._join_deadline = None
            missing, first = self._join_missing()
            error = ParticipantLostError(
                f"{missing} did not join {self._address} in time; start them "
                f"with clock='{self._address}' (or EVCLOCK_CLOCK)",
                first,
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
    limits: Limits | None = None,
    tls_cert: str | None = None,
    tls_key: str | None = None,
) -> AsyncIterator[ClockServer]:
    """Serve the running :class:`~evclock.SimEventLoop`'s sim time while the block runs::

        async with evclock.remote.serve("unix:///tmp/sim.sock") as server:
            await server.wait_for_participants("controller")
            ...

    :param address: ``unix:///path.sock`` (default: a per-process socket in the user's
        private directory, ``$XDG_RUNTIME_DIR/evclock`` or ``evclock-UID`` in the temp dir,
        mode 0700), ``tcp://127.0.0.1:PORT?token=...`` (port 0: any free port; see
        :attr:`ClockServer.address`), or ``tls://HOST:PORT?token=...`` (the same protocol
        inside TLS 1.3, with ``tls_cert`` and ``tls_key``: between machines).
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
        never sent); ``?token=`` in the participants' address. Required on TCP and TLS.
    :param info: JSON-serialisable facts given to every participant at join (scenario, seed).
    :param allow_remote: allow serving on a non-loopback address (``tls://0.0.0.0:PORT``):
        only on ``tls://``, with a token (plain TCP stays on this machine).
    :param max_frame: the largest frame in bytes a joined participant may send (default
        16 MiB; 4 KiB to 256 MiB); before the handshake completes the limit is 4 KiB.
    :param peer_uids: user ids that may join over a Unix socket (``SO_PEERCRED``; default:
        only the user running the simulation).
    :param limits: what one participant may make the server hold: its round's publications,
        subscriptions and unsent output (default: :class:`~evclock.remote.Limits` ``()``, its
        documented defaults); a participant beyond one is a fault under ``on_fault``.
    :param tls_cert: on ``tls://``: the server's certificate chain, a PEM file (participants
        verify it with ``?tls_ca=`` or ``?tls_fingerprint=``).
    :param tls_key: on ``tls://``: the certificate's private key, a PEM file.
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
        limits=limits,
        tls_cert=tls_cert,
        tls_key=tls_key,
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
