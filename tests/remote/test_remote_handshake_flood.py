"""An honest participant gets in while an attacker floods the handshake slots.

A real attacker process without the token keeps more connections open than the server has
handshake slots, reopening each one the server closes as fast as it can (loopback TCP,
bounded in time). A new connection evicts the oldest unauthenticated one, and one that sends
no HELLO within a second is closed: the honest participant with the token joins. The server
logs its refusals at most once a second, with a count.
"""

from __future__ import annotations

import asyncio
import logging
import re
import secrets
import time
from pathlib import Path

import pytest
from _remote_helpers import finish, read_line, spawn

import evclock
from benchmarks._handshake_attacker import ATTACKER
from evclock.remote import _admission

STEADY = """
import evclock
async def main():
    clock = evclock.clock()
    for _ in range(5):
        await clock.sleep(0.001)
    print("end", clock.now().nanoseconds, flush=True)
evclock.run(main())
"""


@pytest.mark.parametrize("how", ["silent", "hello"])
def test_an_honest_participant_joins_under_a_handshake_flood(
    tmp_path: Path, how: str, caplog: pytest.LogCaptureFixture
) -> None:
    token = secrets.token_urlsafe(32)
    stop = tmp_path / "stop"
    started: list[float] = []
    procs = {}

    async def main() -> None:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve("tcp://127.0.0.1:0", token=token) as server:
            port = server.address.rsplit(":", 1)[1]
            width = str(_admission.MAX_PENDING + 16)
            attacker = spawn(tmp_path, ATTACKER, "127.0.0.1", port, width, how, str(stop), "60")
            procs["attacker"] = attacker
            assert (await loop.run_in_executor(None, read_line, attacker)).strip() == "flooding"
            started.append(time.monotonic())
            url = f"{server.address}?token={token}&name=honest&timeout=30"
            procs["honest"] = spawn(tmp_path, STEADY, EVCLOCK_CLOCK=url)
            await server.wait_for_participants("honest", timeout=40)
            await server.wait_until_left("honest")
            stop.touch()

    with caplog.at_level(logging.WARNING, logger="evclock.remote"):
        try:
            evclock.run(main())
        finally:
            stop.touch()
        flood_seconds = time.monotonic() - started[0]
    code, out, err = finish(procs["honest"])
    assert code == 0, err
    assert out.split() == ["end", "5000000"]
    code, out, err = finish(procs["attacker"])
    assert code == 0, err
    closed = int(out.split()[-1])
    # The slots were full: the server closed more of the attacker's connections than it has.
    assert closed > _admission.MAX_PENDING
    lines = [r.getMessage() for r in caplog.records if "refused a connection" in r.getMessage()]
    # At most one line a second about them (the first at once), each with what it left out.
    assert 1 <= len(lines) <= flood_seconds + 2, lines
    left_out = sum(
        int(m.group(1)) for line in lines if (m := re.search(r"and (\d+) more connections", line))
    )
    assert len(lines) + left_out <= closed + _admission.MAX_PENDING
