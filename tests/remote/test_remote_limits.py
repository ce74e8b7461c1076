"""Every structure a participant can grow in the clock server is bounded (``Limits``).

A real adversary process joins a real server process by hand (no evclock client: it sends
what it likes) and floods one limit; the server's resident memory (``/proc/PID/status``)
stays within that limit's bound in the table of the remote guide, the adversary is dropped
with an error naming the limit, and an honest participant's run is unaffected.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _remote_helpers import JOIN_BY_HAND, ROOT, WAIT, finish, read_line, spawn

import evclock
from evclock.remote import Limits

MIB = 1024 * 1024
#: The server's frame limit in these tests: one publication of 1 MiB fits.
MAX_FRAME = MIB + 4096
#: What a Python process's memory may move by without anyone flooding it (allocator pages,
#: the honest participant's traffic): added to each bound.
SLACK = 8 * MIB

#: The simulation: serves argv[1] with the limits of argv[2] (JSON), drops a faulty
#: participant, answers calls to "big" with 1 MiB; after the honest participant left it
#: prints who was dropped and waits for a line on stdin (the test reads its memory first).
SERVER = """
import json, sys, evclock
from evclock.remote import Limits

async def main():
    limits = Limits(**json.loads(sys.argv[2]))
    async with evclock.remote.serve(
        sys.argv[1], on_fault="drop", limits=limits, max_frame=int(sys.argv[3])
    ) as server:
        server.provide("big", lambda _request: bytes(1024 * 1024))
        server.subscribe("data", lambda message: None)
        print("ready", flush=True)
        await server.wait_for_participants("honest", timeout=60)
        await server.wait_until_left("honest")
        return server.dropped

print(json.dumps(evclock.run(main())), flush=True)
sys.stdin.readline()
"""

#: Joins argv[1] by hand in lockstep as "adversary" (so it works at time 0 and never says
#: DONE), then sends argv[3] frames of kind argv[2] (of argv[4] bytes) as fast as it can,
#: never reading, until the server hangs up.
ADVERSARY = (
    JOIN_BY_HAND
    + """
kind, count, size = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
join(proto.MODE_LOCKSTEP, "adversary")
payload = bytes(size)
try:
    for i in range(count):
        if kind == "publish":
            sock.sendall(proto.publish(0, "data", payload))
        elif kind == "subscribe":
            sock.sendall(proto.subscribe(f"{i:x}".rjust(size, "t")))
        else:
            sock.sendall(proto.call(i, "big", b""))
    sock.settimeout(WAIT := 30)
    while sock.recv(65536):
        pass
except OSError:
    pass  # the server hung up on it
print("dropped", flush=True)
"""
)

#: An honest lockstep participant: 20 steps of 1 ms, publishing in each.
HONEST = """
import evclock
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    for i in range(20):
        await clock.sleep(0.001)
        link.publish("data", str(i).encode())
    print("end", clock.now().nanoseconds, flush=True)
evclock.run(main())
"""


def _status_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def _bound(limits: Limits, limit: str) -> int:
    """The limit's row of the remote guide's table, in bytes (one participant)."""
    per_publication = 512  # its tuple, stamp, topic name (<= 255 bytes) and bytes header
    per_subscription = limits.topic_length + 128  # the name and its place in the set
    rows = {
        "round_bytes": limits.round_bytes + limits.round_frames * per_publication,
        "round_frames": limits.round_bytes + limits.round_frames * per_publication,
        "subscriptions": limits.subscriptions * per_subscription,
        "topic_length": limits.subscriptions * per_subscription,
        "unsent_bytes": limits.unsent_bytes + MAX_FRAME,
    }
    return rows[limit] + MAX_FRAME  # plus the frame being read


FLOODS = [
    # limit, the Limits of the run, the flood: kind, frames, size, and the reason's detail
    ("round_bytes", {"round_bytes": 16 * MIB}, ("publish", 400, MIB), r"published \d+ bytes"),
    ("round_frames", {"round_frames": 5000}, ("publish", 1_000_000, 1), "published more often"),
    ("subscriptions", {}, ("subscribe", 600_000, 8), "subscribed to one topic more"),
    ("topic_length", {"topic_length": 64}, ("subscribe", 1, 200), "a topic of 200 bytes"),
    ("unsent_bytes", {"unsent_bytes": 16 * MIB}, ("call", 400, 0), r"\d+ bytes unsent"),
]


@pytest.mark.parametrize(("limit", "given", "flood", "detail"), FLOODS, ids=[f[0] for f in FLOODS])
def test_a_flood_of_each_limit_is_bounded_and_only_its_sender_is_dropped(
    tmp_path: Path, limit: str, given: dict[str, int], flood: tuple[str, int, int], detail: str
) -> None:
    limits = Limits(**given)
    path = tmp_path / "sim.sock"
    url = f"unix://{path}"
    script = tmp_path / "server.py"
    script.write_text(textwrap.dedent(SERVER))
    server = subprocess.Popen(
        [sys.executable, str(script), url, json.dumps(given), str(MAX_FRAME)],
        cwd=ROOT,
        env={k: v for k, v in os.environ.items() if k != "EVCLOCK_CLOCK"},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    others: list[subprocess.Popen[str]] = []
    try:
        assert read_line(server).strip() == "ready"
        before = _status_kib(server.pid, "VmRSS")
        kind, count, size = flood
        adversary = spawn(tmp_path, ADVERSARY, str(path), kind, str(count), str(size))
        others.append(adversary)
        assert read_line(adversary).strip() == "joined"
        honest = spawn(tmp_path, HONEST, EVCLOCK_CLOCK=f"{url}?name=honest")
        others.append(honest)
        code, out, err = finish(honest)
        assert code == 0, err
        assert out.split() == ["end", "20000000"]  # its run, as without the adversary
        dropped = json.loads(read_line(server))
        peak = _status_kib(server.pid, "VmHWM")
    finally:
        for proc in others:
            proc.kill()
            finish(proc)
        server.communicate("\n", timeout=WAIT)  # it exits on the line
    grown = (peak - before) * 1024
    assert grown <= _bound(limits, limit) + SLACK, (
        f"the server grew {grown / MIB:.1f} MiB under a flood of {limit}"
    )
    ((name, reason),) = dropped
    assert name == "adversary"
    value = getattr(limits, limit)
    assert re.fullmatch(
        rf"(does not read its connection: )?exceeded Limits\.{limit}={value} \(.*{detail}.*; "
        rf"serve\(limits=Limits\({limit}=\.\.\.\)\) sets another limit\)",
        reason,
    ), reason


@pytest.mark.parametrize(
    ("fields", "error", "message"),
    [
        (
            {"round_bytes": 0},
            evclock.InvalidArgumentError,
            "Limits.round_bytes must be positive, got 0",
        ),
        (
            {"subscriptions": -1},
            evclock.InvalidArgumentError,
            "Limits.subscriptions must be positive, got -1",
        ),
        (
            {"round_frames": 1.5},
            evclock.InvalidTypeError,
            "Limits.round_frames must be an integer, got float 1.5",
        ),
        (
            {"unsent_bytes": True},
            evclock.InvalidTypeError,
            "Limits.unsent_bytes must be an integer, got bool True",
        ),
        (
            {"topic_length": 256},
            evclock.InvalidArgumentError,
            "Limits.topic_length must be at most 255 (the protocol's longest topic name), got 256",
        ),
    ],
)
def test_bad_limits_are_refused(
    fields: dict[str, object], error: type[Exception], message: str
) -> None:
    with pytest.raises(error) as caught:
        Limits(**fields)  # type: ignore[arg-type]
    assert str(caught.value) == message


def test_serve_refuses_limits_of_another_type() -> None:
    async def main() -> None:
        async with evclock.remote.serve(limits={"round_bytes": 1}):  # type: ignore[arg-type]
            pass

    with pytest.raises(evclock.InvalidTypeError) as caught:
        evclock.run(main())
    assert str(caught.value) == "limits must be an evclock.remote.Limits, got dict"


def test_the_defaults_are_the_documented_ones() -> None:
    assert Limits() == Limits(
        round_bytes=64 * MIB,
        round_frames=10_000,
        subscriptions=1024,
        topic_length=255,
        unsent_bytes=64 * MIB,
    )
