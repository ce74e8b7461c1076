"""A follower of a simulation whose physics runs flat out always gets the server's time.

With nothing but the clock server's own connections outside the loop, the loop skips its
poll before time moves (the server accounts for that I/O), and a flat-out PyBullet loop runs
no callback for long stretches. A follower that fell behind (its socket full of time frames)
then had one time frame left unsent until something polled the server's sockets - in some
runs for longer than the follower's ``timeout`` (it gave up with ``ClockLostError``). The
server now retries its unsent output at every physics step, and callbacks queued from
another thread (the server's keepalives) run after a poll.

Repeated, because it happened in some runs only: each run is bounded by the follower's own
``timeout`` (a starved one ends with ``ClockLostError`` within it).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _remote_helpers import finish, spawn

import evclock

#: Runs of the follower, each a join, three sleeps of 10 ms of sim time and a leave.
RUNS = 50

FOLLOWER = """
import json, sys, evclock

async def main():
    clock = evclock.clock()
    for _ in range(3):
        await clock.sleep(0.010)
    return clock.now().nanoseconds

url, runs = sys.argv[1], int(sys.argv[2])
outcomes = []
for _ in range(runs):
    try:
        outcomes.append(evclock.run(main(), clock=url))
    except evclock.ClockLostError as exc:
        outcomes.append(str(exc))
print(json.dumps(outcomes))
"""


@pytest.mark.pybullet
def test_a_flat_out_follower_is_never_starved(tmp_path: Path) -> None:
    from evclock.sources import PyBulletTimeSource

    url = f"unix://{tmp_path / 'sim.sock'}"
    follower = spawn(tmp_path, FOLLOWER, f"{url}?name=watcher&mode=follow&timeout=2", str(RUNS))
    source = PyBulletTimeSource.connect()

    async def main() -> int:
        async with evclock.remote.serve(url) as server:
            for _ in range(RUNS):
                await server.wait_for_participants("watcher", timeout=20)
                await server.wait_until_left("watcher")  # physics runs flat out meanwhile
        return evclock.clock().now().nanoseconds

    served_until = evclock.run(main(), source=source)
    code, out, err = finish(follower)
    assert code == 0, err
    outcomes = json.loads(out)
    starved = [o for o in outcomes if isinstance(o, str)]
    assert not starved, f"{len(starved)} of {RUNS} runs starved; the first: {starved[0]}"
    assert len(outcomes) == RUNS
    # Each run ended at least 30 ms of sim time after it joined, never past the server's time.
    assert all(30_000_000 <= t <= served_until for t in outcomes)
