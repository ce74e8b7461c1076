"""Wall-time wake-ups per second: evclock, SimPy, stock asyncio and uvloop, one command.

Per workload, every variant runs ``--rounds`` times, interleaved round by round (so a burst
of load from elsewhere hits all of them alike), each run a fresh process (the variants of
``instructions.py``, on the same seeded plans, built before the clock starts). A run warms
up on a tenth of the workload, then times the whole of it: its rate is wake-ups at N /
seconds at N (creating the tasks included: under 1% of it). KUKA's rate is physics steps
per second in the steady state, (steps at N - at N/2) / (seconds at N - at N/2), so that
connecting to PyBullet and loading the robot cancel out. Printed per variant: the best
rate, the median and the spread of the rounds ((max - min) / median), and the ratio to
SimPy two ways - best against best, and the median of the per-round ratios (each round's
runs are seconds apart, so a change of load between rounds cancels out). The machine's
load average is printed before and after each workload. Each target of the project
(docs/performance.md, "Wall time per wake-up") is marked met or not met on the median of
the per-round ratios.

Workloads (``--only``, repeatable; default all, KUKA only where PyBullet is installed):

* ``fanout``: ``--tasks`` tasks x N = ``--sleeps`` sleeps of seeded ns durations in
  [1 ms, 10 ms]: ``clock.sleep`` and ``asyncio.sleep`` on the sim loop, SimPy
  ``env.timeout``, and the bare task switch ``asyncio.sleep(0)`` on stock asyncio and on
  uvloop (the floor of any scheduler built on asyncio tasks; uvloop if installed);
* ``rates``: ``--loops`` rate loops at seeded rates in [10 Hz, 500 Hz] for N = ``--rate-ms``
  of sim time: ``clock.rate``, an ``asyncio.sleep`` rate loop on the sim loop, SimPy, and
  ``asyncio.sleep(0)`` per tick on stock asyncio and uvloop;
* ``kuka``: the KUKA controllers on PyBullet (``kuka_throughput.py``) as evclock rate loops
  against the same controllers in a hand-written synchronous loop, physics steps per second,
  control at 100 Hz and at 240 Hz (final states asserted bit-identical).

Run: ``python benchmarks/wall.py [--rounds 7 --only fanout --only rates]``
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import instructions as ins

FANOUT = (
    "clock.sleep",
    "asyncio.sleep, sim loop",
    "asyncio.sleep, instant stock",  # stock asyncio's own timers, time jumping between them
    "SimPy env.timeout",
    "asyncio.sleep(0), stock loop",
    "asyncio.sleep(0), uvloop",
)
RATES = (
    "clock.rate",
    "asyncio.sleep rate, sim loop",
    "SimPy rate",
    "asyncio.sleep(0) per tick, stock",
    "asyncio.sleep(0) per tick, uvloop",
)
KUKA = ("kuka sync", "kuka evclock")
#: The targets (issue: "the scheduler at stock asyncio's task-switch speed"):
#: (workload, variant, baseline, at least this ratio of the baseline's rate).
TARGETS = (
    ("fanout", "clock.sleep", "SimPy env.timeout", 0.9),
    ("rates", "clock.rate", "SimPy rate", 0.9),
    ("fanout", "asyncio.sleep, sim loop", "SimPy env.timeout", 0.55),
    ("kuka 100 Hz", "kuka evclock", "kuka sync", 0.97),
    ("kuka 240 Hz", "kuka evclock", "kuka sync", 0.93),
)


def load() -> str:
    """The machine's load averages (1, 5 and 15 minutes)."""
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} {five:.2f} {fifteen:.2f}"


def run_once(job: ins.Job) -> tuple[float, str]:
    """One fresh process: the steady-state rate (units per wall second) and KUKA's state."""
    done = subprocess.run(job.command(job.counts), capture_output=True, text=True, timeout=3600)
    if done.returncode:
        raise RuntimeError(f"{job.variant} failed:\n{done.stdout}\n{done.stderr}")
    seconds = dict(line.split() for line in ins._output(done.stdout, "wall"))
    small, big = (float(seconds[str(c)]) for c in job.counts)
    if job.workload == "kuka":
        return job.units / (big - small), ins._output(done.stdout, "state")[-1]
    w = ins.WORKLOADS[job.workload]
    return w.units(job.tasks, job.counts[1], job.seed) / big, ""


@dataclass
class Runs:
    """One variant's rates, round by round."""

    rates: list[float]

    @property
    def best(self) -> float:
        return max(self.rates)

    @property
    def median(self) -> float:
        return statistics.median(self.rates)

    @property
    def spread(self) -> float:
        return (max(self.rates) - min(self.rates)) / self.median


def measure(jobs: Sequence[ins.Job], rounds: int) -> list[Runs]:
    """Every job ``rounds`` times, interleaved; KUKA's final states must agree."""
    runs = [Runs([]) for _ in jobs]
    for _ in range(rounds):
        states = set()
        for job, r in zip(jobs, runs, strict=True):
            rate, state = run_once(job)
            r.rates.append(rate)
            states.add(state)
        if len(states) > 1:
            raise SystemExit(f"KUKA: final states differ between {[j.variant for j in jobs]}")
    return runs


def per_round_ratio(a: Runs, b: Runs) -> float:
    """The median over rounds of a's rate / b's rate in the same round."""
    return statistics.median(x / y for x, y in zip(a.rates, b.rates, strict=True))


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000, help="fan-out tasks (default 1000)")
    p.add_argument("--sleeps", type=int, default=400, help="N sleeps per task; also N/2 (400)")
    p.add_argument("--loops", type=int, default=100, help="rate loops (default 100)")
    p.add_argument("--rate-ms", type=int, default=4000, help="N ms of rate loops; also N/2")
    p.add_argument("--kuka-steps", type=int, default=4800, help="N physics steps (x of 12)")
    p.add_argument("--rounds", type=int, default=7, help="interleaved rounds (default 7)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--only", choices=("fanout", "rates", "kuka"), action="append")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.kuka_steps % 12:
        p.error("--rounds must be >= 1 and --kuka-steps a multiple of 12")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()
    has_uvloop = importlib.util.find_spec("uvloop") is not None
    has_pybullet = importlib.util.find_spec("pybullet") is not None
    parts = args.only or ["fanout", "rates", *(["kuka"] if has_pybullet else [])]
    if min(args.sleeps, args.rate_ms) < 10:
        raise SystemExit("--sleeps and --rate-ms must be at least 10 (a tenth warms up)")
    sleeps = (args.sleeps // 10, args.sleeps)
    rate_ms = (args.rate_ms // 10, args.rate_ms)
    steps = (args.kuka_steps // 2, args.kuka_steps)
    workloads: list[tuple[str, str, list[ins.Job]]] = []
    if "fanout" in parts:
        title = f"fanout: {args.tasks:,} tasks x N = {args.sleeps} sleeps of 1-10 ms (ns)"
        variants = [v for v in FANOUT if has_uvloop or "uvloop" not in v]
        jobs = [ins.Job("fanout", v, args.tasks, sleeps, args.seed) for v in variants]
        workloads.append(("fanout", title, jobs))
    if "rates" in parts:
        title = f"rates: {args.loops} rate loops at 10-500 Hz for N = {args.rate_ms} ms"
        variants = [v for v in RATES if has_uvloop or "uvloop" not in v]
        jobs = [ins.Job("rates", v, args.loops, rate_ms, args.seed) for v in variants]
        workloads.append(("rates", title, jobs))
    if "kuka" in parts:
        for hz in (100.0, 240.0):
            title = f"kuka {hz:g} Hz: N = {args.kuka_steps} physics steps at 240 Hz, per step"
            jobs = [ins.Job("kuka", v, 1, steps, args.seed, hz) for v in KUKA]
            workloads.append((f"kuka {hz:g} Hz", title, jobs))

    print(
        f"python {sys.version.split()[0]} on {os.cpu_count()} CPUs; wake-ups (KUKA: physics "
        f"steps) per wall second; {args.rounds} rounds interleaved, "
        "a fresh process per run" + ("" if has_uvloop else "; uvloop not installed")
    )
    results: dict[tuple[str, str], tuple[Runs, Runs]] = {}
    for key, title, jobs in workloads:
        before = load()
        runs = measure(jobs, args.rounds)
        base_name = "kuka sync" if key.startswith("kuka") else SIMPY_OF[key]
        base = runs[[j.variant for j in jobs].index(base_name)]
        print(f"\n{title}; load average {before} before, {load()} after")
        print(
            f"  {'variant':<34}{'best/s':>11}{'median/s':>11}{'spread':>8}"
            f"{'best vs':>9}{'per-round':>11}   vs {base_name}"
        )
        for job, r in zip(jobs, runs, strict=True):
            results[(key, job.variant)] = (r, base)
            print(
                f"  {job.variant:<34}{r.best:>11,.0f}{r.median:>11,.0f}{r.spread:>7.0%}"
                f"{r.best / base.best:>8.2f}x{per_round_ratio(r, base):>10.2f}x"
            )
    print("\ntargets (median of per-round ratios, same run)")
    for key, variant, baseline, limit in TARGETS:
        if (key, variant) not in results:
            continue
        r, base = results[(key, variant)]
        value = per_round_ratio(r, base)
        verdict = "met" if value >= limit else "NOT MET"
        what = f"{key}: {variant} / {baseline}"
        print(f"  {what:<52}{value:>6.2f}x  >= {limit:.2f}x  {verdict}")
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    return 0


SIMPY_OF = {"fanout": "SimPy env.timeout", "rates": "SimPy rate"}

if __name__ == "__main__":
    sys.exit(main())
