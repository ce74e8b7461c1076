"""A controller follows a ROS 2 ``/clock`` (Gazebo's, or an evclock simulation's) over Zenoh.

Run it with ``EVCLOCK_CLOCK=ros2:///clock python examples/ros2_clock_follower.py``: the
clock is chosen at launch, like ``use_sim_time``, and the controller code does not change.
It waits for the first ``/clock`` (the program starts at the publisher's time), then a 10 Hz
timer and sleeps run on that time: each timer call prints the follower's time and the newest
``/clock`` it has seen, which is never behind it. Without ``EVCLOCK_CLOCK`` it runs on virtual
time, the same code.
"""

from __future__ import annotations

import asyncio
import json

import evclock

FIRES = 10
PERIOD_S = 0.1


async def controller() -> dict[str, object]:
    clock = evclock.clock()
    loop = asyncio.get_running_loop()
    source = loop.source if isinstance(loop, evclock.SimEventLoop) else None
    start = clock.now()
    print(f"started at {start} on {source.describe() if source else 'wall time'}", flush=True)
    fires: list[dict[str, int]] = []
    done = asyncio.Event()

    def on_timer() -> None:
        latest = getattr(source, "latest", None)
        now = clock.now()
        fires.append({"t_ns": now.nanoseconds, "latest_ns": (latest or now).nanoseconds})
        print(f"timer at {now} (newest /clock {latest or now})", flush=True)
        if len(fires) == FIRES:
            done.set()

    timer = clock.timer(PERIOD_S, on_timer)
    await done.wait()
    timer.cancel()
    return {"start_ns": start.nanoseconds, "fires": fires}


if __name__ == "__main__":
    result = evclock.run(controller())
    print(json.dumps(result), flush=True)
