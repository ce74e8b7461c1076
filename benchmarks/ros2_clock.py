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
import json
import tempfile
from typing import Any

import zenoh
from _clock_cost import best_rounds, print_rounds

from evclock.ros2 import Ros2ClockPublisher, clock_key_expr


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
        best = best_rounds("cartpole", args.seconds, args.repeat, publisher, args.decimation)
        publisher.close()
        received = 0
        while subscriber.handler.try_recv() is not None:
            received += 1
        subscriber_session.close()

    print_rounds(best)
    print(f"samples published {publisher.sequence_number}, received {received}")


if __name__ == "__main__":
    main()
