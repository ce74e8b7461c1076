"""Instruction counts per wakeup (callgrind): the simulation loop's cost, exactly.

The wall clock on a shared virtual machine swings by tens of percent; instructions executed
do not. Each variant runs in its own process under ``valgrind --tool=callgrind`` twice - with
the full workload and with an empty one (the same tasks, no waits) - and the difference,
divided by the number of wakeups, is its cost per wakeup: start-up and task creation cancel
out. Baselines are measured in the same run and every figure is printed as a ratio to them.

Workloads (seeded; durations drawn once as integer nanoseconds, passed as float seconds):

* ``fanout``: ``--tasks`` tasks x ``--sleeps`` sleeps of random durations in [1 ms, 10 ms]:
  ``clock.sleep`` and ``asyncio.sleep`` on the sim loop, SimPy's ``env.timeout`` and a
  bare ``asyncio.sleep(0)`` task switch on a stock loop (the floor of any asyncio scheduler);
* ``timeouts``: ``--tasks`` tasks x ``--waits`` waits that always time out -
  ``asyncio.timeout(d)`` around an ``Event`` never set - against SimPy's
  ``never | env.timeout(d)`` on the same plan;
* ``scale``: ``clock.sleep`` per wakeup with ``--big`` concurrent sleepers vs ``--tasks``.

Run: ``python benchmarks/instructions.py [--tasks 1000 --sleeps 300 --waits 100 --big 100000]``
(needs valgrind; a run takes minutes: each process runs about 50x slower under callgrind).
Also ``python benchmarks/instructions.py --variant NAME --count N`` runs one variant
without valgrind (what the harness runs under it).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import re
import subprocess
import sys
from collections.abc import Callable, Generator, Sequence
from typing import Any

MIN_NS = 1_000_000
MAX_NS = 10_000_000


def plan(tasks: int, count: int, seed: int) -> list[list[float]]:
    """``count`` seeded durations per task, in float seconds (drawn as integer ns)."""
    rng = random.Random(seed)
    return [[rng.randint(MIN_NS, MAX_NS) / 1e9 for _ in range(count)] for _ in range(tasks)]


# ------------------------------------------------------------------------------ variants


def clock_sleep(rows: list[list[float]]) -> None:
    import evclock

    async def worker(clock: evclock.Clock, durations: list[float]) -> None:
        sleep = clock.sleep
        for d in durations:
            await sleep(d)

    async def main() -> None:
        clock = evclock.clock()
        await asyncio.gather(*(worker(clock, row) for row in rows))

    evclock.run(main())


def asyncio_sleep_sim(rows: list[list[float]]) -> None:
    import evclock

    async def worker(durations: list[float]) -> None:
        sleep = asyncio.sleep
        for d in durations:
            await sleep(d)

    async def main() -> None:
        await asyncio.gather(*(worker(row) for row in rows))

    evclock.run(main())


def asyncio_sleep0(rows: list[list[float]]) -> None:
    async def worker(durations: list[float]) -> None:
        sleep = asyncio.sleep
        for _ in durations:
            await sleep(0)

    async def main() -> None:
        await asyncio.gather(*(worker(row) for row in rows))

    asyncio.run(main())


def simpy_timeout(rows: list[list[float]]) -> None:
    import simpy

    env = simpy.Environment()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


def asyncio_timeouts_sim(rows: list[list[float]]) -> None:
    import evclock

    async def worker(never: asyncio.Event, durations: list[float]) -> None:
        timeout = asyncio.timeout
        for d in durations:
            try:
                async with timeout(d):
                    await never.wait()
            except TimeoutError:
                pass

    async def main() -> None:
        never = asyncio.Event()
        await asyncio.gather(*(worker(never, row) for row in rows))

    evclock.run(main())


def simpy_timeouts(rows: list[list[float]]) -> None:
    import simpy

    env = simpy.Environment()
    never = env.event()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield never | timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


VARIANTS: dict[str, Callable[[list[list[float]]], None]] = {
    "clock.sleep": clock_sleep,
    "asyncio.sleep (sim loop)": asyncio_sleep_sim,
    "asyncio.sleep(0) (stock loop)": asyncio_sleep0,
    "simpy timeout": simpy_timeout,
    "asyncio.timeout (sim loop)": asyncio_timeouts_sim,
    "simpy never | timeout": simpy_timeouts,
}


# ------------------------------------------------------------------------------ harness


def instructions(variant: str, tasks: int, count: int, seed: int) -> int:
    """Instructions executed by one process running ``variant`` (callgrind's total)."""
    done = subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            "--callgrind-out-file=/dev/null",
            sys.executable,
            os.path.abspath(__file__),
            "--variant",
            variant,
            "--tasks",
            str(tasks),
            "--count",
            str(count),
            "--seed",
            str(seed),
        ],
        capture_output=True,
        text=True,
        timeout=3600,
        check=True,
    )
    found = re.search(r"Collected : (\d+)", done.stderr)
    if found is None:
        raise RuntimeError(f"no instruction count in callgrind's output:\n{done.stderr}")
    return int(found.group(1))


def per_wakeup(variant: str, tasks: int, count: int, seed: int) -> float:
    """Instructions per wakeup: (full run - empty run) / wakeups."""
    full = instructions(variant, tasks, count, seed)
    empty = instructions(variant, tasks, 0, seed)
    return (full - empty) / (tasks * count)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000)
    p.add_argument("--sleeps", type=int, default=300, help="sleeps per task (fanout)")
    p.add_argument("--waits", type=int, default=100, help="timed-out waits per task")
    p.add_argument("--big", type=int, default=100_000, help="concurrent sleepers (scale)")
    p.add_argument("--big-sleeps", type=int, default=3, help="sleeps per task at --big")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--only", choices=["fanout", "timeouts", "scale"], action="append")
    p.add_argument("--variant", choices=sorted(VARIANTS), help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.variant is not None:
        VARIANTS[args.variant](plan(args.tasks, args.count, args.seed))
        return 0
    parts = args.only or ["fanout", "timeouts", "scale"]
    print(f"python {sys.version.split()[0]}; instructions per wakeup under callgrind")
    if "fanout" in parts:
        n, k = args.tasks, args.sleeps
        print(f"\nfanout: {n} tasks x {k} sleeps (seed {args.seed})")
        costs = {
            v: per_wakeup(v, n, k, args.seed)
            for v in (
                "clock.sleep",
                "asyncio.sleep (sim loop)",
                "simpy timeout",
                "asyncio.sleep(0) (stock loop)",
            )
        }
        floor = costs["asyncio.sleep(0) (stock loop)"]
        for name, cost in costs.items():
            print(f"  {name:<32}{cost:>10,.0f}   {cost / floor:.2f}x the asyncio.sleep(0) floor")
    if "timeouts" in parts:
        n, k = args.tasks, args.waits
        print(f"\ntimeouts: {n} tasks x {k} waits that time out (seed {args.seed})")
        ours = per_wakeup("asyncio.timeout (sim loop)", n, k, args.seed)
        simpy = per_wakeup("simpy never | timeout", n, k, args.seed)
        print(f"  {'asyncio.timeout (sim loop)':<32}{ours:>10,.0f}   {ours / simpy:.2f}x SimPy")
        print(f"  {'simpy never | timeout':<32}{simpy:>10,.0f}")
    if "scale" in parts:
        small = per_wakeup("clock.sleep", args.tasks, args.big_sleeps, args.seed)
        big = per_wakeup("clock.sleep", args.big, args.big_sleeps, args.seed)
        print(f"\nscale: clock.sleep, {args.big_sleeps} sleeps per task")
        print(f"  {args.tasks:>7,} sleepers{small:>12,.0f}")
        print(f"  {args.big:>7,} sleepers{big:>12,.0f}   {big / small:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
