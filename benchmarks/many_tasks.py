"""Many-tasks benchmark: 100,000 concurrent tasks, each sleeping once, on the sim loop.

Each task sleeps one seeded random duration in [1 ms, 10 ms] (integer nanoseconds from
``random.Random(seed)``, passed as float seconds) and exits. Variants:

* ``clock.sleep``    ``await evclock.clock().sleep(d)`` on the sim loop
* ``asyncio.sleep``  ``await asyncio.sleep(d)`` on the sim loop (one TimerHandle per sleeper)
* ``stock asyncio``  ``await asyncio.sleep(d)`` on a standard asyncio loop, for reference
  (its wall time includes real sleeping of up to 10 ms and is not comparable)

Measurements, each in a fresh child process so one cannot inherit another's freed memory:

* ``wall``: wall time of the whole ``run()`` call (loop creation, creating the N tasks, all
  sleeping, all exiting), best of ``--repeat``; on the sim loop the final sim time is checked
  to equal the largest duration exactly (exit status 1 if not).
* ``memory`` (all asleep at once): after creating the N tasks the main task yields once, so
  every task has started and is parked in its sleep; there it reads

  - the RSS delta (``/proc/self/statm`` resident pages x page size, before creating the
    tasks vs. all asleep) divided by N, in a run without tracemalloc;
  - the tracemalloc peak (traced from just before the tasks are created) divided by N, in a
    separate run (tracemalloc itself inflates RSS and slows everything down).

Run: ``python benchmarks/many_tasks.py [--tasks 100000 --seed 1 --repeat 3 --json out.json]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable, Coroutine, Sequence
from typing import Any

import evclock

MIN_NS = 1_000_000
MAX_NS = 10_000_000
VARIANTS = ("clock.sleep", "asyncio.sleep", "stock asyncio")
PAGE_SIZE = os.sysconf("SC_PAGE_SIZE")


def durations(tasks: int, seed: int) -> list[int]:
    """One seeded random duration per task, integer nanoseconds in [1 ms, 10 ms]."""
    rng = random.Random(seed)
    return [rng.randint(MIN_NS, MAX_NS) for _ in range(tasks)]


def rss_bytes() -> int:
    """Current resident set size, from ``/proc/self/statm`` (Linux)."""
    with open("/proc/self/statm", encoding="ascii") as fh:
        return int(fh.read().split()[1]) * PAGE_SIZE


def sleeper_factory(variant: str) -> Callable[[float, list[int]], Coroutine[Any, Any, None]]:
    """The task body for ``variant``: count itself as asleep, sleep ``d`` seconds, exit."""
    if variant == "clock.sleep":

        async def sleeper(d: float, asleep: list[int]) -> None:
            clock = evclock.clock()
            asleep[0] += 1
            await clock.sleep(d)

    else:

        async def sleeper(d: float, asleep: list[int]) -> None:
            asleep[0] += 1
            await asyncio.sleep(d)

    return sleeper


async def scenario(variant: str, seconds: list[float], mode: str) -> dict[str, Any]:
    """Create every task, optionally measure memory once all sleep, then wait for them all."""
    sleeper = sleeper_factory(variant)
    loop = asyncio.get_running_loop()
    asleep = [0]
    out: dict[str, Any] = {}
    if mode == "tracemalloc":
        tracemalloc.start()
    rss0 = rss_bytes()
    tasks = [loop.create_task(sleeper(d, asleep)) for d in seconds]
    await asyncio.sleep(0)  # every task runs up to its sleep before we resume
    if asleep[0] != len(seconds):
        raise RuntimeError(f"only {asleep[0]} of {len(seconds)} tasks were asleep")
    if mode == "rss":
        out["rss_delta"] = rss_bytes() - rss0
    elif mode == "tracemalloc":
        current, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        out["traced_current"], out["traced_peak"] = current, peak
    await asyncio.gather(*tasks)
    if isinstance(loop, evclock.SimEventLoop):
        out["final_ns"] = loop.now_ns
    return out


def child(variant: str, mode: str, tasks: int, seed: int) -> dict[str, Any]:
    """One measurement in this (fresh) process."""
    ns = durations(tasks, seed)
    seconds = [n / 1e9 for n in ns]
    sim = variant != "stock asyncio"
    t0 = time.perf_counter()
    out = evclock.run(scenario(variant, seconds, mode), use_sim_time=sim)
    out["wall_s"] = time.perf_counter() - t0
    out["expected_ns"] = max(ns)
    return out


def spawn(variant: str, mode: str, args: argparse.Namespace) -> dict[str, Any]:
    """Run one measurement in a fresh child process and return its JSON result."""
    cmd = [sys.executable, __file__, "--tasks", str(args.tasks), "--seed", str(args.seed)]
    cmd += ["--child", variant, mode]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--tasks", type=int, default=100_000, help="concurrent tasks (100000)")
    p.add_argument("--seed", type=int, default=1, help="random seed for durations (default 1)")
    p.add_argument("--repeat", type=int, default=3, help="wall-time runs; best kept (3)")
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    p.add_argument("--child", nargs=2, metavar=("VARIANT", "MODE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.tasks < 1 or args.repeat < 1:
        p.error("--tasks and --repeat must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Measure every variant in child processes and print the table; return the exit code."""
    args = parse_args(argv)
    if args.child:
        variant, mode = args.child
        print(json.dumps(child(variant, mode, args.tasks, args.seed)))
        return 0

    n = args.tasks
    print(f"many_tasks: {n:,} concurrent tasks, one sleep each of 1-10 ms (seed {args.seed})")
    print(f"wall: best of {args.repeat}; memory: all {n:,} tasks asleep at once\n")
    header = f"{'variant':<16}{'wall s':>9}{'RSS/task':>12}{'traced peak/task':>18}  sim time"
    print(header)
    rows: list[dict[str, Any]] = []
    exact_ok = True
    for variant in VARIANTS:
        walls = [spawn(variant, "wall", args) for _ in range(args.repeat)]
        rss = spawn(variant, "rss", args)
        traced = spawn(variant, "tracemalloc", args)
        best = min(w["wall_s"] for w in walls)
        row: dict[str, Any] = {
            "variant": variant,
            "wall_s_best": best,
            "wall_s_all": [w["wall_s"] for w in walls],
            "rss_per_task_bytes": rss["rss_delta"] / n,
            "traced_peak_per_task_bytes": traced["traced_peak"] / n,
            "traced_current_per_task_bytes": traced["traced_current"] / n,
        }
        check = ""
        if "final_ns" in walls[0]:
            finals = {w["final_ns"] for w in [*walls, rss, traced]}
            exact = finals == {walls[0]["expected_ns"]}
            exact_ok &= exact
            row["final_ns"] = sorted(finals)
            check = f"{walls[0]['final_ns']} ns {'exact' if exact else 'NOT EXACT'}"
        rows.append(row)
        print(
            f"{variant:<16}{best:>9.3f}{row['rss_per_task_bytes']:>10,.0f} B"
            f"{row['traced_peak_per_task_bytes']:>16,.0f} B  {check}"
        )
    print("\n(stock asyncio: wall time includes real sleeping; memory is the reference point)")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"args": vars(args), "rows": rows}, fh, indent=2)
        print(f"wrote {args.json}")
    if not exact_ok:
        print("FAIL: final sim time is not exact", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
