"""Liveness, faults and hostile input of the clock server, with real processes and signals.

Every wait is bounded: detection of a killed peer is immediate (its socket closes), a stopped
or silent one is caught by a short ``step_timeout`` / ``?timeout=``, and every process wait
goes through :func:`finish` or :func:`read_line` with a wall limit.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import signal
import socket
import struct
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from _remote_helpers import STEADY, finish, read_line, serve_until_left, spawn

import evclock
from evclock.remote import _admission
from evclock.remote import _protocol as proto

#: Joins, says "working" at 10 ms of sim time and then blocks inside that step.
STUCK = """
import sys, time, evclock
async def main():
    clock = evclock.clock()
    await clock.sleep(0.010)
    print("working", clock.now().nanoseconds, flush=True)
    time.sleep(float(sys.argv[1]))
evclock.run(main())
"""


def url_in(tmp_path: Path) -> str:
    return f"unix://{tmp_path / 'sim.sock'}"


def on_output(proc: subprocess.Popen[str], action: Callable[[str], None]) -> threading.Thread:
    """Run ``action(line)`` from a helper thread once ``proc`` prints its next line."""
    thread = threading.Thread(target=lambda: action(read_line(proc)), daemon=True)
    thread.start()
    return thread


def reap(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
    finish(proc)


def test_a_killed_participant_aborts_the_simulation_naming_it(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    victim = spawn(tmp_path, STUCK, "60", EVCLOCK_CLOCK=f"{url}?name=victim")
    on_output(victim, lambda _line: victim.send_signal(signal.SIGKILL))

    with pytest.raises(evclock.remote.ParticipantLostError) as caught:
        serve_until_left(url, "victim")
    assert caught.value.name == "victim"
    assert re.fullmatch(
        rf"participant 'victim' \(lockstep, pid {victim.pid}\) closed its connection without "
        r"leaving \(killed or crashed\) at 0\.010000 s of sim time \(it was last granted "
        r"0\.010000 s of sim time and had not answered for [0-9.]+ s of wall time\); the "
        r"simulation was aborted \(on_fault='abort'; 'drop' continues without it, 'pause' "
        r"waits for it\)",
        str(caught.value),
    )
    reap(victim)


def test_a_stopped_participant_hits_the_step_timeout(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    victim = spawn(tmp_path, STUCK, "5", EVCLOCK_CLOCK=f"{url}?name=frozen")
    on_output(victim, lambda _line: victim.send_signal(signal.SIGSTOP))

    try:
        with pytest.raises(
            evclock.remote.ParticipantLostError,
            match=rf"participant 'frozen' \(lockstep, pid {victim.pid}\) did not finish its "
            r"step within step_timeout=0\.5 s of wall time \(stopped or stuck\) at 0\.010000 s "
            r"of sim time \(it was last granted 0\.010000 s of sim time and had not answered "
            r"for 0\.[5-9][0-9]* s of wall time\)",
        ):
            serve_until_left(url, "frozen", step_timeout=0.5)
    finally:
        victim.send_signal(signal.SIGKILL)
        reap(victim)


def test_drop_policy_continues_without_a_silent_participant(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    sleeper = spawn(tmp_path, STUCK, "60", EVCLOCK_CLOCK=f"{url}?name=sleeper")

    async def main() -> tuple[tuple[tuple[str, str], ...], int, subprocess.Popen[str]]:
        # The limit applies to the healthy participant's steps too: room for a loaded machine.
        async with evclock.remote.serve(url, on_fault="drop", step_timeout=2) as server:
            await server.wait_for_participants("sleeper")
            steady = spawn(tmp_path, STEADY, "30", EVCLOCK_CLOCK=f"{url}?name=steady")
            await server.wait_for_participants("steady")
            await server.wait_until_left()
            return server.dropped, evclock.clock().now().nanoseconds, steady

    try:
        dropped, end, steady = evclock.run(main())
    finally:
        reap(sleeper)
    code, out, err = finish(steady)
    assert code == 0, err
    assert dropped == (
        (
            "sleeper",
            "did not finish its step within step_timeout=2 s of wall time (stopped or stuck)",
        ),
    )
    start = int(out.split()[1])
    assert out.split()[2:] == ["end", str(start + 30_000_000)]
    assert end == start + 30_000_000  # sim time went on after the drop


class PausedFor(logging.Handler):
    """Sets ``seen`` when the server reports sim time paused for the participant ``name``."""

    def __init__(self, name: str) -> None:
        super().__init__()
        self.seen = threading.Event()
        self._text = f"sim time is paused until a participant named {name!r} joins"

    def emit(self, record: logging.LogRecord) -> None:
        if self._text in record.getMessage():
            self.seen.set()


def test_pause_policy_holds_time_until_a_replacement_joins(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    victim = spawn(tmp_path, STUCK, "60", EVCLOCK_CLOCK=f"{url}?name=worker")
    replacement: list[subprocess.Popen[str]] = []
    paused = PausedFor("worker")

    def kill_and_replace(_line: str) -> None:
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=30)
        # The replacement joins once the server has seen the death (before it, the name is
        # still taken and a join is refused).
        if paused.seen.wait(30):
            replacement.append(spawn(tmp_path, STEADY, "3", EVCLOCK_CLOCK=f"{url}?name=worker"))

    on_output(victim, kill_and_replace)

    async def main() -> int:
        async with evclock.remote.serve(url, on_fault="pause") as server:
            await server.wait_for_participants("worker")
            await server.wait_until_left()
            return evclock.clock().now().nanoseconds

    remote_log = logging.getLogger("evclock.remote")
    remote_log.addHandler(paused)
    try:
        end = evclock.run(main())
    finally:
        remote_log.removeHandler(paused)
        reap(victim)
    code, out, err = finish(replacement[0])
    assert code == 0, err
    # Sim time stayed at the moment the first worker died until the second took over.
    assert out.split() == ["start", "10000000", "end", "13000000"]
    assert end == 13_000_000


PARTICIPANT_UNTIL_LOST = """
import os, signal, sys, evclock
async def main():
    clock = evclock.clock()
    for i in range(1000):
        await clock.sleep(0.001)
        if i == 2:
            os.kill(int(sys.argv[1]), int(sys.argv[2]))
evclock.run(main())
"""

SERVER_FOREVER = """
import sys, evclock
async def main():
    async with evclock.remote.serve(sys.argv[1]) as server:
        await server.wait_for_participants("p")
        await server.wait_until_left()
evclock.run(main())
"""


@pytest.mark.parametrize(
    ("sig", "query", "message"),
    [
        (signal.SIGKILL, "", r"closed the connection \(the simulation died or was killed\)"),
        (signal.SIGSTOP, "&timeout=0.5", r"sent no time for \d+\.\d s of wall time \(limit 0\.5 s"),
    ],
)
def test_the_server_dying_or_stopping_is_clock_lost_in_the_participant(
    tmp_path: Path, sig: signal.Signals, query: str, message: str
) -> None:
    url = url_in(tmp_path)
    server = spawn(tmp_path, SERVER_FOREVER, url)
    participant = spawn(
        tmp_path,
        PARTICIPANT_UNTIL_LOST,
        str(server.pid),
        str(int(sig)),
        EVCLOCK_CLOCK=f"{url}?name=p{query}",
    )
    try:
        code, _, err = finish(participant)
    finally:
        server.send_signal(signal.SIGKILL)
        reap(server)
    assert code == 1
    last = err.strip().splitlines()[-1]
    assert last.startswith("evclock.ClockLostError: the clock server at unix://")
    assert re_search(message, last)


def re_search(pattern: str, text: str) -> bool:
    import re

    return re.search(pattern, text) is not None


def test_duplicate_names_are_refused_and_the_server_keeps_running(tmp_path: Path) -> None:
    url = url_in(tmp_path)

    async def main() -> tuple[str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            first = spawn(tmp_path, STEADY, "5", EVCLOCK_CLOCK=f"{url}?name=twin")
            await server.wait_for_participants("twin")
            second = spawn(tmp_path, STEADY, "5", EVCLOCK_CLOCK=f"{url}?name=twin")
            code, _, refused = await loop.run_in_executor(None, finish, second)
            assert code == 1
            await server.wait_until_left()
        code, out, err = finish(first)
        assert code == 0, err
        return refused.strip().splitlines()[-1], out

    refused, out = evclock.run(main())
    assert refused == (
        f"evclock.remote.JoinRefusedError: the clock server at {url} refused 'twin': a participant "
        "named 'twin' is already joined; give this process another name (?name=... in the "
        "clock address)"
    )
    assert out.split() == ["start", "0", "end", "5000000"]


#: A HELLO of protocol version 2 (which carried its token in clear, here empty).
_V2_PAYLOAD = b"EVCLK" + struct.pack("<HB", 2, proto.MODE_LOCKSTEP) + b"\x03old" + b"\x00\x00"
V2_HELLO = struct.pack("<IB", len(_V2_PAYLOAD) + 1, proto.HELLO) + _V2_PAYLOAD


def raw_exchange(address: str, payload: bytes) -> bytes:
    """Send ``payload`` on a fresh connection; everything the server answers until it closes."""
    path = address.removeprefix("unix://")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(30)
        sock.connect(path)
        sock.sendall(payload)
        received = b""
        while chunk := sock.recv(4096):
            received += chunk
    return received


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (
            proto.hello(proto.MODE_LOCKSTEP, "old", bytes(32), version=99),
            "protocol version 99 is not supported: this clock server speaks version 3; run the "
            "same evclock version on both sides",
        ),
        (  # a participant of evclock's previous protocol (its token in clear)
            V2_HELLO,
            "protocol version 2 is not supported: this clock server speaks version 3; run the "
            "same evclock version on both sides",
        ),
        (
            b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
            "not an evclock clock client: bad frame length 542393671: the limit of this "
            "connection is 4096 bytes (not an evclock clock peer, a frame too large for the "
            "server's max_frame, or a corrupted stream)",
        ),
        (
            proto.grant(5),
            "not an evclock clock client: the first frame must be HELLO",
        ),
    ],
)
def test_bad_clients_are_refused_and_the_server_keeps_serving(
    tmp_path: Path, payload: bytes, reason: str
) -> None:
    url = url_in(tmp_path)

    async def main() -> bytes:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            answer = await loop.run_in_executor(None, raw_exchange, server.address, payload)
            good = spawn(tmp_path, STEADY, "2", EVCLOCK_CLOCK=f"{url}?name=good")
            await server.wait_for_participants("good")
            await server.wait_until_left()
        code, out, err = finish(good)
        assert code == 0, err
        assert out.split() == ["start", "0", "end", "2000000"]
        return answer

    answer = evclock.run(main())
    frames = proto.Reader().feed(answer)
    assert frames == [(proto.REFUSE, bytes((proto.REFUSE_FINAL,)) + reason.encode())]


def test_a_connection_that_never_greets_is_closed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_admission, "HELLO_TIMEOUT", 0.3)
    url = url_in(tmp_path)

    async def main() -> bytes:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            return await loop.run_in_executor(None, raw_exchange, server.address, b"")

    assert proto.Reader().feed(evclock.run(main())) == [
        (proto.REFUSE, b"\x00no complete handshake within 0.3 s")
    ]


def test_waiting_for_participants_that_never_come_is_bounded(tmp_path: Path) -> None:
    async def main() -> None:
        async with evclock.remote.serve(url_in(tmp_path)) as server:
            await server.wait_for_participants("ghost", timeout=0.3)

    with pytest.raises(evclock.remote.ParticipantLostError, match="'ghost' did not join unix://"):
        evclock.run(main())


def test_a_participant_leaving_cleanly_is_forgotten(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    proc = spawn(tmp_path, STEADY, "4", EVCLOCK_CLOCK=f"{url}?name=brief")

    async def main() -> tuple[tuple[str, ...], tuple[str, ...], int]:
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("brief")
            during = server.participants
            await server.wait_until_left()
            return during, server.participants, evclock.clock().now().nanoseconds

    assert evclock.run(main()) == (("brief",), (), 4_000_000)
    assert finish(proc)[0] == 0


def test_bad_server_options_are_refused(tmp_path: Path) -> None:
    async def main(**options: object) -> None:
        async with evclock.remote.serve(url_in(tmp_path), **options):  # type: ignore[arg-type]
            pass

    with pytest.raises(evclock.InvalidArgumentError, match="on_fault must be one of abort, drop"):
        evclock.run(main(on_fault="ignore"))
    with pytest.raises(evclock.InvalidArgumentError, match="step_timeout must be a positive"):
        evclock.run(main(step_timeout=0))
    with pytest.raises(evclock.InvalidArgumentError, match="info must be JSON-serialisable"):
        evclock.run(main(info={"x": object()}))
    assert json.dumps({}) == "{}"
