"""24 simulated hours of a 1 kHz rate loop, through the real loop: the end time must be exact.

Usage: python benchmarks/day_at_1khz.py [--hours 24] [--start 1700000000]

Exits 1 if the final sim time is not exactly start + hours x 3600 s in integer nanoseconds,
or if any tick was missed. Reports ticks per wall second. CI runs it as a correctness check
(it takes a few minutes); the unit tests cover ten simulated minutes and the deadline formula
over the whole day.
"""

from __future__ import annotations

import argparse
import sys
import time

import evclock


async def rate_loop(ticks: int) -> tuple[int, int, int]:
    clock = evclock.clock()
    rate = clock.rate(1000, name="day")
    async for tick in rate:
        if tick.index == ticks:
            break
    return clock.now_ns(), rate.stats.ticks, rate.stats.missed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=24.0)
    parser.add_argument(
        "--start", type=int, default=1_700_000_000, help="start, epoch-like seconds"
    )
    args = parser.parse_args()
    ticks = round(args.hours * 3600 * 1000)
    expected = (args.start * 1000 + ticks) * 1_000_000
    began = time.perf_counter()
    end, count, missed = evclock.run(rate_loop(ticks), start=args.start)
    wall = time.perf_counter() - began
    exact = end == expected and count == ticks + 1 and missed == 0
    print(
        f"{args.hours:g} simulated hours at 1 kHz: {count:,} ticks in {wall:.1f} s of wall time "
        f"({count / wall:,.0f} ticks/s)"
    )
    print(
        f"final sim time {end} ns, expected {expected} ns, missed ticks {missed}: "
        f"{'EXACT' if exact else 'WRONG'}"
    )
    return 0 if exact else 1


if __name__ == "__main__":
    sys.exit(main())
