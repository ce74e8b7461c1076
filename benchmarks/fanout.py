"""Fan-out benchmark: many tasks, each sleeping many short random durations.

Workload: ``--tasks`` tasks (default 1,000), each awaiting ``--sleeps`` sleeps (default 300)
of seeded random durations in [1 ms, 10 ms]. Durations are drawn once, as integer
nanoseconds, from ``random.Random(seed)`` and passed to the sleep calls as float seconds
(``ns / 1e9``). Measured, in the same run:

* ``evclock clock.sleep``    ``await clock.sleep(d)`` on the sim loop (``evclock.run``)
* ``evclock asyncio.sleep``  ``await asyncio.sleep(d)`` on the same sim loop
* ``simpy env.timeout``      SimPy, ``yield env.timeout(d)``, same tasks and durations
* ``asyncio sleep(0)``       a standard asyncio loop, ``await asyncio.sleep(0)`` x sleeps per
  task (the cost of a bare task switch: an upper bound for any asyncio-based scheduler)

Throughput is wakeups (completed sleeps) per wall second, timed with ``perf_counter`` from
just before the tasks/processes are created to just after the last one finishes (loop
creation and teardown are excluded). Each measurement is repeated ``--repeat`` times (default
3) and the best (fastest) run is reported; the runs are interleaved round by round (a, b,
SimPy, sleep(0), a, b, ...) and the garbage collector runs before each one.

Exactness check: on the sim loop the final sim time must equal, to the nanosecond, the
largest per-task sum of durations (computed in integers). A mismatch exits with status 1.
Performance targets are printed as PASS/MISS for the record; a miss still exits 0.

Run: ``python benchmarks/fanout.py [--tasks 1000 --sleeps 300 --seed 1 --json out.json]``
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import platform
import random
import sys
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import evclock

MIN_NS = 1_000_000
MAX_NS = 10_000_000

#: Performance targets (wakeups per wall second, and ratio to SimPy).
TARGET_CLOCK_SLEEP = 500_000
TARGET_CLOCK_VS_SIMPY = 0.5
TARGET_ASYNCIO_SLEEP = 200_000


@dataclass(frozen=True)
class Workload:
    """Precomputed sleep durations: ``durations_ns[task][i]`` and the same as float seconds."""

    durations_ns: list[list[int]]
    durations_s: list[list[float]]

    @property
    def wakeups(self) -> int:
        """Total number of sleeps over all tasks."""
        return sum(len(d) for d in self.durations_ns)

    @property
    def expected_end_ns(self) -> int:
        """The exact sim time at which the last task finishes."""
        return max(sum(d) for d in self.durations_ns)


@dataclass(frozen=True)
class Result:
    """Best-of-N timing of one variant."""

    name: str
    wakeups: int
    best_s: float
    all_s: list[float]
    final_ns: int | None = None

    @property
    def rate(self) -> float:
        """Wakeups per wall second of the best run."""
        return self.wakeups / self.best_s


def make_workload(tasks: int, sleeps: int, seed: int) -> Workload:
    """Draw every duration up front with ``random.Random(seed)`` (integer nanoseconds)."""
    rng = random.Random(seed)
    ns = [[rng.randint(MIN_NS, MAX_NS) for _ in range(sleeps)] for _ in range(tasks)]
    return Workload(ns, [[n / 1e9 for n in row] for row in ns])


# ----------------------------------------------------------------------------- variants


def run_clock_sleep(work: Workload) -> tuple[float, int]:
    """(a) ``await clock.sleep(d)`` on the sim loop; returns (wall seconds, final now_ns)."""

    async def worker(clock: evclock.Clock, durations: list[float]) -> None:
        sleep = clock.sleep
        for d in durations:
            await sleep(d)

    async def main() -> tuple[float, int]:
        clock = evclock.clock()
        t0 = time.perf_counter()
        await asyncio.gather(*(worker(clock, row) for row in work.durations_s))
        elapsed = time.perf_counter() - t0
        return elapsed, clock.now_ns()

    return evclock.run(main(), use_sim_time=True)


def run_asyncio_sleep_sim(work: Workload) -> tuple[float, int]:
    """(b) ``await asyncio.sleep(d)`` on the sim loop; returns (wall seconds, final now_ns)."""

    async def worker(durations: list[float]) -> None:
        sleep = asyncio.sleep
        for d in durations:
            await sleep(d)

    async def main() -> tuple[float, int]:
        t0 = time.perf_counter()
        await asyncio.gather(*(worker(row) for row in work.durations_s))
        elapsed = time.perf_counter() - t0
        return elapsed, evclock.clock().now_ns()

    return evclock.run(main(), use_sim_time=True)


def run_simpy(work: Workload) -> tuple[float, float]:
    """SimPy baseline, same durations (float seconds); returns (wall seconds, final env.now)."""
    import simpy

    env = simpy.Environment()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield timeout(d)

    t0 = time.perf_counter()
    for row in work.durations_s:
        env.process(proc(row))
    env.run()
    return time.perf_counter() - t0, env.now


def run_asyncio_sleep0(tasks: int, sleeps: int) -> float:
    """Plain asyncio baseline: ``await asyncio.sleep(0)`` x ``sleeps`` per task (wall seconds)."""

    async def worker() -> None:
        sleep = asyncio.sleep
        for _ in range(sleeps):
            await sleep(0)

    async def main() -> float:
        t0 = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(tasks)))
        return time.perf_counter() - t0

    return asyncio.run(main())


# ----------------------------------------------------------------------------- harness


def measure(
    variants: dict[str, Callable[[], float | tuple[float, float | int]]], wakeups: int, repeat: int
) -> tuple[list[Result], dict[str, float | int | None]]:
    """Run every variant ``repeat`` times, interleaved round by round (so a burst of load
    from elsewhere hits all of them alike), collecting garbage before each run; keep each
    variant's fastest run and its last final sim time (``None`` if it reports none)."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    finals: dict[str, float | int | None] = dict.fromkeys(variants)
    for _ in range(repeat):
        for name, fn in variants.items():
            gc.collect()
            out = fn()
            if isinstance(out, tuple):
                elapsed, finals[name] = out
            else:
                elapsed = out
            times[name].append(elapsed)
    results = []
    for name, runs in times.items():
        final = finals[name]
        final_ns = final if isinstance(final, int) else None
        results.append(Result(name, wakeups, min(runs), runs, final_ns))
    return results, finals


def verdict(ok: bool) -> str:
    """PASS or MISS."""
    return "PASS" if ok else "MISS"


def workload_parser(doc: str | None) -> argparse.ArgumentParser:
    """A parser described by ``doc``'s first line, with the workload's options (also
    profile_hot_path.py's)."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0] if doc else None)
    p.add_argument("--tasks", type=int, default=1000, help="concurrent tasks (default 1000)")
    p.add_argument("--sleeps", type=int, default=300, help="sleeps per task (default 300)")
    p.add_argument("--seed", type=int, default=1, help="random seed for durations (default 1)")
    return p


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = workload_parser(__doc__)
    p.add_argument("--repeat", type=int, default=3, help="runs per variant; best kept (3)")
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = p.parse_args(argv)
    if args.tasks < 1 or args.sleeps < 1 or args.repeat < 1:
        p.error("--tasks, --sleeps and --repeat must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run every variant, print the table, ratios, checks and targets; return the exit code."""
    args = parse_args(argv)
    work = make_workload(args.tasks, args.sleeps, args.seed)
    n = work.wakeups
    expected = work.expected_end_ns
    print(
        f"fanout: {args.tasks} tasks x {args.sleeps} sleeps = {n:,} wakeups, durations "
        f"{MIN_NS / 1e6:g}-{MAX_NS / 1e6:g} ms (seed {args.seed}), best of {args.repeat}"
    )
    print(
        f"python {platform.python_version()} on {platform.machine()}, evclock {evclock.__version__}"
    )

    variants: dict[str, Callable[[], float | tuple[float, float | int]]] = {
        "evclock clock.sleep": lambda: run_clock_sleep(work),
        "evclock asyncio.sleep": lambda: run_asyncio_sleep_sim(work),
        "simpy env.timeout": lambda: run_simpy(work),
        "asyncio sleep(0)": lambda: run_asyncio_sleep0(args.tasks, args.sleeps),
    }
    results, finals = measure(variants, n, args.repeat)
    a, b, simpy_res, zero = results
    a_end, b_end = a.final_ns, b.final_ns
    simpy_end = finals["simpy env.timeout"]

    print()
    print(f"{'variant':<24}{'wakeups/s':>14}{'best s':>10}   all runs (s)")
    for r in results:
        runs = ", ".join(f"{t:.3f}" for t in r.all_s)
        print(f"{r.name:<24}{r.rate:>14,.0f}{r.best_s:>10.3f}   {runs}")

    ratios = {
        "a/simpy": a.rate / simpy_res.rate,
        "b/simpy": b.rate / simpy_res.rate,
        "a/asyncio_sleep0": a.rate / zero.rate,
        "b/asyncio_sleep0": b.rate / zero.rate,
    }
    print()
    print("ratios: " + "  ".join(f"{k} = {v:.2f}x" for k, v in ratios.items()))

    print()
    exact = {"clock.sleep": a_end == expected, "asyncio.sleep": b_end == expected}
    print(f"sim-time check: expected final now_ns = {expected}")
    print(f"  clock.sleep   final now_ns = {a_end}  {'OK' if exact['clock.sleep'] else 'WRONG'}")
    print(f"  asyncio.sleep final now_ns = {b_end}  {'OK' if exact['asyncio.sleep'] else 'WRONG'}")
    if isinstance(simpy_end, float):
        print(f"  (simpy, float seconds: env.now = {simpy_end!r}, exact {expected / 1e9!r})")

    targets = {
        f"(a) >= {TARGET_CLOCK_SLEEP:,} wakeups/s": a.rate >= TARGET_CLOCK_SLEEP,
        f"(a) >= {TARGET_CLOCK_VS_SIMPY}x SimPy": ratios["a/simpy"] >= TARGET_CLOCK_VS_SIMPY,
        f"(b) >= {TARGET_ASYNCIO_SLEEP:,} wakeups/s": b.rate >= TARGET_ASYNCIO_SLEEP,
    }
    print()
    print("targets (informational; a miss does not fail the run):")
    for label, ok in targets.items():
        print(f"  {verdict(ok)}  {label}")

    if args.json:
        payload = {
            "args": vars(args),
            "python": platform.python_version(),
            "expected_end_ns": expected,
            "results": [asdict(r) | {"wakeups_per_s": r.rate} for r in results],
            "ratios": ratios,
            "exact": exact,
            "targets": targets,
        }
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(payload, fh, indent=2)
        print(f"\nwrote {args.json}")

    if not all(exact.values()):
        print("FAIL: final sim time is not exact", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
