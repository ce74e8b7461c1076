"""What the ROS 2 tests share: an outside clock repeating its time and a reset seen as a jump
(the followers over Zenoh, ``test_ros2_clock.py``, and DDS, ``test_ros2_dds.py``), and a run
of ``evclock`` whose messages a subscriber of the test drains while it runs."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import evclock
from evclock import ClockJumpedError, Time


@contextlib.contextmanager
def repeating(feed: Callable[[int], None], time_ns: int, wait: float) -> Iterator[None]:
    """Publish ``time_ns`` through ``feed`` every 10 ms of wall time while the block runs (a
    follower waits for its first message during construction); join within ``wait`` s."""
    stop = threading.Event()

    def repeat() -> None:
        while not stop.wait(0.01):
            feed(time_ns)

    feeder = threading.Thread(target=repeat, daemon=True)
    feeder.start()
    try:
        yield
    finally:
        stop.set()
        feeder.join(wait)


async def jumps_on_reset(feed: Callable[[int], None]) -> list[evclock.TimeJump]:
    """From 10 s, sleep 5 s while the outside clock goes back to 3 s (the simulator was
    reset): the sleep fails with ClockJumpedError and the clock reads 3 s. The jumps seen."""
    clk = evclock.clock()
    jumps: list[evclock.TimeJump] = []
    clk.on_jump(post=jumps.append)
    sleeper = asyncio.ensure_future(clk.sleep(5))
    await asyncio.sleep(0)
    feed(3 * 1_000_000_000)
    with pytest.raises(ClockJumpedError):
        await sleeper
    assert clk.now() == Time(3)
    return jumps


def run_draining(command: list[str], drain: Callable[[], None], cwd: Path) -> tuple[int, str, str]:
    """Run ``command`` while calling ``drain`` every 2 ms of wall time (the readers keep few
    samples), and once more after it ends (killed after 60 s): its status, stdout and stderr."""
    run = subprocess.Popen(
        command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 60
        while run.poll() is None and time.monotonic() < deadline:
            drain()
            time.sleep(0.002)
        out, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    drain()
    return run.returncode, out, err
