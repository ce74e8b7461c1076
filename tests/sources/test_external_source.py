"""The external-time source contract, on both hosts (SimEventLoop and SimDriver).

A fake external source follows time granted by a peer over a real socket pair: the peer is a
thread that answers each request of the source with the next grant. The source never blocks
(``advance`` returns the time unchanged while no grant has come), gets its messages through
the loop (``add_reader``), and raises from ``advance`` once the peer is gone.
"""

from __future__ import annotations

import asyncio
import socket
import threading

import pytest

import evclock
from evclock import EvClockError, SimDriver, SimEventLoop
from evclock.sources import Gate, TimeSource

NS = 1_000_000_000
PEER_TIMEOUT = 10.0  # wall seconds: every blocking wait of the peer thread is bounded


class ClockLostError(EvClockError):
    """The peer that grants time is gone."""


class Peer(threading.Thread):
    """Answers each request byte with the next grant (a line of nanoseconds), then hangs up."""

    def __init__(self, sock: socket.socket, grants: list[int]) -> None:
        super().__init__(name="fake-clock-peer", daemon=True)
        self.sock = sock
        self.grants = grants
        sock.settimeout(PEER_TIMEOUT)

    def run(self) -> None:
        try:
            for grant in self.grants:
                if not self.sock.recv(1):
                    return
                self.sock.sendall(f"{grant}\n".encode())
            self.sock.recv(1)  # one more request: then hang up
        finally:
            self.sock.close()


class GrantedTime(TimeSource):
    """Sim time granted by a peer: an ``external`` source."""

    external = True
    free_running = True

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.setblocking(False)
        self._now = 0
        self.granted = 0
        self.asked = False
        self.lost = False
        self.advances = 0
        self._buffer = b""

    @property
    def now_ns(self) -> int:
        return self._now

    def listen(self) -> asyncio.AbstractEventLoop:
        """Read the peer's grants on the running loop (:meth:`on_readable`); that loop."""
        loop = asyncio.get_running_loop()
        loop.add_reader(self.sock, self.on_readable)
        return loop

    def on_readable(self) -> None:
        """The reader callback: record the newest grant (or the loss of the peer)."""
        data = self.sock.recv(4096)
        if not data:
            self.lost = True  # reported by the next advance()
            asyncio.get_running_loop().remove_reader(self.sock)
            return
        self._buffer += data
        *lines, self._buffer = self._buffer.split(b"\n")
        for line in lines:
            self.granted = int(line)
            self.asked = False
        if lines and self._host is not None:
            self._host.time_arrived()

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        self.advances += 1
        if self.lost:
            raise ClockLostError("the peer granting sim time hung up")
        newest = self.granted if target_ns is None else min(self.granted, target_ns)
        if newest > self._now and (gate is None or gate(newest)):
            self._now = newest
        elif not self.asked:
            self.sock.send(b"?")  # ask for more time, once per grant
            self.asked = True
        return self._now

    def describe(self) -> str:
        return "granted time (a peer on a socket)"

    def close(self) -> None:
        self.sock.close()


def pair(grants: list[int]) -> tuple[GrantedTime, Peer]:
    ours, theirs = socket.socketpair()
    peer = Peer(theirs, grants)
    peer.start()
    return GrantedTime(ours), peer


async def controller(trace: list[tuple[str, int]]) -> None:
    clock = evclock.clock()
    for label, delay in (("a", 0.3), ("b", 0.3), ("c", 2.0)):
        await clock.sleep(delay)
        trace.append((label, clock.now_ns()))


def test_a_simeventloop_follows_granted_time_deadline_by_deadline() -> None:
    # One grant jumps past two local deadlines: the loop fires them in turn, never past.
    source, peer = pair([int(0.2 * NS), 1 * NS, 5 * NS])

    async def main() -> list[tuple[str, int]]:
        loop = source.listen()
        trace: list[tuple[str, int]] = []
        await controller(trace)
        trace.append(("done", evclock.clock().now_ns()))
        loop.remove_reader(source.sock)
        return trace

    with asyncio.Runner(loop_factory=lambda: SimEventLoop(source)) as runner:
        trace = runner.run(main())
    peer.join(PEER_TIMEOUT)
    assert trace == [
        ("a", int(0.3 * NS)),
        ("b", int(0.6 * NS)),
        ("c", int(2.6 * NS)),
        ("done", int(2.6 * NS)),
    ]


def test_idle_time_follows_the_outside_and_a_lost_peer_ends_the_run() -> None:
    # Nothing scheduled locally: time follows the newest grant (no deadlock); once the peer
    # hangs up, the source's error propagates out of run().
    source, peer = pair([1 * NS, 3 * NS])

    async def main() -> None:
        source.listen()
        await asyncio.Event().wait()  # nothing scheduled: only the outside moves time

    loop = SimEventLoop(source)
    try:
        with pytest.raises(ClockLostError, match=r"^the peer granting sim time hung up$"):
            loop.run_until_complete(main())
        assert loop.now_ns == 3 * NS
    finally:
        loop.close()
    peer.join(PEER_TIMEOUT)
    assert not peer.is_alive()


def test_a_simdriver_follows_granted_time_too() -> None:
    source, peer = pair([int(0.2 * NS), 1 * NS, 5 * NS])

    async def main() -> list[tuple[str, int]]:
        loop = source.listen()
        trace: list[tuple[str, int]] = []
        async with SimDriver(source, rtf=None):
            await asyncio.wait_for(controller(trace), timeout=PEER_TIMEOUT)
        loop.remove_reader(source.sock)
        return trace

    try:
        trace = asyncio.run(main())
    finally:
        source.close()  # a driver detaches its source, it does not close it
    assert trace == [("a", int(0.3 * NS)), ("b", int(0.6 * NS)), ("c", int(2.6 * NS))]
    peer.join(PEER_TIMEOUT)


def test_an_external_source_is_not_a_deadlock_when_idle() -> None:
    source, peer = pair([])  # the peer hangs up at the first request

    async def main() -> None:
        source.listen()
        await asyncio.Event().wait()

    loop = SimEventLoop(source)
    try:
        with pytest.raises(ClockLostError):
            loop.run_until_complete(main())
    finally:
        loop.close()
    peer.join(PEER_TIMEOUT)
