"""The cost of publishing ROS 2 /clock every physics step, against the same run without it.

Usage: python benchmarks/ros2_clock.py [--seconds 20] [--repeat 3] [--decimation 1]

Both variants run the cartpole scenario (LQR balance at 50 Hz, monitor at 240 Hz, 240 Hz
physics) as fast as possible for ``--seconds`` of sim time. The second also publishes /clock
through a :class:`evclock.ros2.Ros2ClockPublisher` after every ``--decimation``-th step, to a
subscriber session of this process connected over a Unix socket (so every sample really
crosses Zenoh; it is read on Zenoh's side, into a channel, and counted at the end).
Reported: physics steps per CPU second of this process for both (immune to other processes),
the wall-time figures beside them, their ratio, and how many samples arrived. Variants
alternate round by round; the best round of each is kept.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import tempfile
import time
from typing import Any

import zenoh

import evclock
from evclock.ros2 import Ros2ClockPublisher, clock_key_expr
from evclock_sims import get_scenario


def run_once(
    seconds: float, publisher: Ros2ClockPublisher | None, decimation: int
) -> tuple[float, float, int]:
    """Run the scenario for ``seconds`` of sim time; return (CPU s, wall s, steps)."""
    source = evclock.sources.PyBulletTimeSource.connect()
    scenario = get_scenario("cartpole")(source.client, 0)
    if publisher is not None:
        publisher.attach(source, decimation=decimation)

    async def main() -> None:
        try:
            async with asyncio.timeout(seconds):
                await scenario.run(evclock.clock())
        except TimeoutError:
            pass

    cpu0, wall0 = time.process_time(), time.perf_counter()
    evclock.run(main(), source=source)
    return time.process_time() - cpu0, time.perf_counter() - wall0, source.step_index


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--decimation", type=int, default=1)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="evros2") as folder:
        endpoint = f"unixsock-stream/{folder}/bench.sock"
        config = {
            "mode": "peer",
            "listen": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}},
        }
        subscriber_session: Any = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
        subscriber = subscriber_session.declare_subscriber(
            clock_key_expr(0), zenoh.handlers.FifoChannel(1 << 20)
        )
        publisher = Ros2ClockPublisher(rmw="zenoh", connect=[endpoint], listen=[])
        best: dict[str, tuple[float, float, int]] = {}
        for _ in range(args.repeat):
            for name, pub in (("plain", None), ("with /clock", publisher)):
                gc.collect()
                cpu, wall, steps = run_once(args.seconds, pub, args.decimation)
                if name not in best or cpu < best[name][0]:
                    best[name] = (cpu, wall, steps)
        publisher.close()
        received = 0
        while subscriber.handler.try_recv() is not None:
            received += 1
        subscriber_session.close()

    print(f"{'variant':<14}{'steps':>8}{'steps/CPU s':>14}{'steps/wall s':>14}")
    for name, (cpu, wall, steps) in best.items():
        print(f"{name:<14}{steps:>8}{steps / cpu:>14,.0f}{steps / wall:>14,.0f}")
    plain, clocked = best["plain"], best["with /clock"]
    ratio = (clocked[2] / clocked[0]) / (plain[2] / plain[0])
    wall_ratio = (clocked[2] / clocked[1]) / (plain[2] / plain[1])
    print(f"ratio (with /clock / plain): {ratio:.3f} (CPU), {wall_ratio:.3f} (wall)")
    print(f"samples published {publisher.sequence_number}, received {received}")


if __name__ == "__main__":
    main()
