"""Sleeps, a rate loop, a timer and a timeout, all on virtual (simulation) time.

Everything below waits on sim time, so the program finishes instantly in wall time and
prints the same exact times on every run:

* ``await clock.sleep(...)`` and plain ``await asyncio.sleep(...)`` both follow sim time;
* ``async for tick in clock.rate(10)``: a drift-free 10 Hz loop whose ticks carry their
  expected and actual times and how many periods were missed (one iteration overruns on
  purpose, and the default ``skip`` policy drops the missed deadlines);
* ``clock.timer(0.25, callback)``: a periodic timer running alongside the loop;
* ``asyncio.timeout(0.5)``: fires after exactly 0.5 s of sim time.

Run: ``python examples/sleep_and_rate.py``
"""

from __future__ import annotations

import asyncio

import evclock


def stamp(clock: evclock.Clock) -> str:
    """The clock's current time as ``[t=  1.250000000 s]``."""
    return f"[t={clock.now().nanoseconds / 1e9:13.9f} s]"


async def main() -> None:
    """Walk through sleeps, a rate loop with a timer beside it, and a timeout."""
    clock = evclock.clock()
    print(f"{stamp(clock)} start on {clock.clock_type.value} time")

    await clock.sleep(0.5)
    print(f"{stamp(clock)} after clock.sleep(0.5)")
    await asyncio.sleep(0.25)
    print(f"{stamp(clock)} after asyncio.sleep(0.25): asyncio follows sim time too")

    beats: list[int] = []

    def heartbeat() -> None:
        beats.append(clock.now().nanoseconds)
        print(f"{stamp(clock)}   timer: heartbeat #{len(beats)}")

    timer = clock.timer(0.25, heartbeat, name="heartbeat")
    rate = clock.rate(10)
    async for tick in rate:
        print(
            f"{stamp(clock)} tick {tick.index}: expected {tick.expected.seconds:.3f} s, "
            f"actual {tick.actual.seconds:.3f} s, missed {tick.missed}"
        )
        if tick.index == 3:
            # Overrun: deadlines 4 and 5 pass; `skip` delivers 5 late, counts 4 as missed.
            await clock.sleep(0.23)
        if tick.index >= 8:
            break
    timer.cancel()
    print(
        f"{stamp(clock)} rate loop done: {rate.stats.ticks} ticks, {rate.stats.missed} "
        f"missed, max lateness {rate.stats.max_lateness.nanoseconds / 1e6:g} ms; "
        f"{len(beats)} heartbeats"
    )

    start = clock.now()
    try:
        async with asyncio.timeout(0.5):
            await clock.sleep(10)
    except TimeoutError:
        waited = clock.now() - start
        print(
            f"{stamp(clock)} asyncio.timeout(0.5) fired after {waited.nanoseconds} ns of sim time"
        )

    print(f"{stamp(clock)} done")


if __name__ == "__main__":
    evclock.run(main(), use_sim_time=True)
