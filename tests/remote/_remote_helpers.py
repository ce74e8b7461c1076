"""Helpers of the clock-server tests: real participant processes, bounded waits."""

from __future__ import annotations

import os
import selectors
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import evclock

ROOT = Path(__file__).resolve().parents[2]
#: Wall seconds any single process wait may take: a guard against hangs, not a timing check.
WAIT = 60.0

#: A lockstep participant: prints its start time, sleeps 1 ms of sim time argv[1] times, then
#: prints its end time.
STEADY = """
import sys, evclock
async def main():
    clock = evclock.clock()
    print("start", clock.now().nanoseconds, flush=True)
    for _ in range(int(sys.argv[1])):
        await clock.sleep(0.001)
    print("end", clock.now().nanoseconds, flush=True)
evclock.run(main())
"""

#: Sleeps argv[2] s of sim time argv[1] times and prints the times it woke at (ns), as JSON.
WAKE_TIMES = """
import json, sys, evclock
async def main():
    clock = evclock.clock()
    seen = []
    for _ in range(int(sys.argv[1])):
        await clock.sleep(float(sys.argv[2]))
        seen.append(clock.now().nanoseconds)
    print(json.dumps(seen))
evclock.run(main())
"""

#: The start of a script that joins a server by hand, without a token: connects to the Unix
#: socket argv[1]; ``frame()`` reads the next frame, ``join(mode, name)`` answers the
#: challenge with an empty proof and prints "joined" once welcome. A script adds its own
#: lines after it.
JOIN_BY_HAND = """
import socket, sys
from evclock.remote import _protocol as proto
sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
sock.settimeout(30)
sock.connect(sys.argv[1])
reader = proto.Reader()
def frame():
    got = []
    while not got:
        data = sock.recv(65536)
        assert data, "closed"
        got = reader.feed(data)
    return got[0]
def join(mode, name):
    sock.sendall(proto.hello(mode, name, proto.new_nonce()))
    assert frame()[0] == proto.CHALLENGE
    sock.sendall(proto.proof(b""))
    assert frame()[0] == proto.WELCOME
    print("joined", flush=True)
"""


def spawn(tmp_path: Path, code: str, *args: str, **env: str) -> subprocess.Popen[str]:
    """Run ``code`` (a Python script body) in a new interpreter, stdout piped."""
    script = tmp_path / f"participant_{len(list(tmp_path.glob('participant_*.py')))}.py"
    script.write_text(textwrap.dedent(code))
    environ = {
        k: v for k, v in os.environ.items() if k not in ("EVCLOCK_CLOCK", "EVCLOCK_USE_SIM_TIME")
    }
    environ.update(env)
    return subprocess.Popen(
        [sys.executable, str(script), *args],
        cwd=ROOT,
        env=environ,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    """Wait (bounded) for ``proc``; its exit code, stdout and stderr."""
    try:
        out, err = proc.communicate(timeout=WAIT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=WAIT)
        raise AssertionError(f"participant hung:\n{out}\n{err}") from None
    return proc.returncode, out, err


def read_line(proc: subprocess.Popen[str], timeout: float = WAIT, *, stderr: bool = False) -> str:
    """The next stdout line of ``proc`` (its next stderr line with ``stderr``; bounded wait)."""
    stream = proc.stderr if stderr else proc.stdout
    assert stream is not None
    with selectors.DefaultSelector() as sel:
        sel.register(stream, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while not sel.select(max(deadline - time.monotonic(), 0)):
            if time.monotonic() >= deadline:
                where = "stderr" if stderr else "stdout"
                raise AssertionError(f"no line on the {where} of pid {proc.pid} in time")
    return stream.readline()


def serve_until_left(url: str, name: str, **options: Any) -> None:
    """Serve this process's simulation on ``url`` (with the ``serve()`` ``options``) until
    the participant ``name`` has joined and every participant has left."""

    async def main() -> None:
        async with evclock.remote.serve(url, **options) as server:
            await server.wait_for_participants(name)
            await server.wait_until_left()

    evclock.run(main())
