"""Instructions per wake-up (callgrind) against floors measured in the same run, with wall ratios.

One command prints every workload's table, a summary with ratios and the targets, each
marked met or not met::

    .venv/bin/python benchmarks/instructions.py            # about 15 min on 2 loaded cores

The wall clock on a shared virtual machine swings by tens of percent; instructions executed
do not. Method:

* **Plans first.** Every input (seeded durations as float seconds, rates, tick counts) is
  built before the measured part: a process builds the plan of the *larger* repetition
  count, then runs the workload on its first ``count`` entries; under callgrind both
  processes of a variant build the very same plan, so its cost cancels out; wall time is
  taken around the workload alone (``time.perf_counter``).
* **Steady state.** Each variant runs under ``valgrind --tool=callgrind`` at two repetition
  counts (``--sleeps`` and half of it, ...); (instructions of the larger - of the smaller)
  / (wake-ups of the larger - of the smaller) is its cost per wake-up: start-up, imports,
  plan, task creation, the first wait and the exit all cancel out.
* **Durations at nanosecond granularity** by default (seeded integers in [1 ms, 10 ms],
  almost every deadline distinct); whole-millisecond durations, where deadlines coincide,
  are their own workload (``coincident``).
* **Floors and peers in the same run**, each in its idiomatic form (see ``_peers.py``):
  a bare ``asyncio.sleep(0)`` task switch per wake-up on a stock loop; the least a
  future-based sleep can cost; SimPy with an event per waiter; for timeouts, the same
  workload on stock asyncio with instant time (a loop subclass whose ``time()`` jumps to
  its earliest timer).
* **Wall time**: after the callgrind runs, each variant runs in plain processes at
  ``--wall-scale`` times both counts, interleaved round by round (``--wall-rounds``); the
  fastest run of each count is kept and the per-wake-up difference is reported as a ratio
  to SimPy's (above 1: slower than SimPy). On a loaded machine wall ratios are indicative;
  the instruction ratios are the figures.
* **String-hash seed**: every process runs with ``PYTHONHASHSEED=0`` (a random seed changes
  dict layouts and so what Python code costs, by up to 3% per KUKA step); the KUKA
  comparison, whose targets are a few percent apart, is counted under seeds
  0 .. ``--hash-seeds``-1 and reported per seed and as the mean of the ratios.

Workloads (``--only``, repeatable; default: all but ``scale``):

* ``fanout``: ``--tasks`` tasks x ``--sleeps`` sleeps of ns-granular durations;
* ``coincident``: the same with whole-millisecond durations (1-10 ms);
* ``rates``: ``--loops`` rate loops at seeded rates in [10 Hz, 500 Hz] (deadlines almost
  never shared) for ``--rate-ms`` of sim time; ``rates-shared``: rates from 50, 100, 200,
  250 and 500 Hz (deadlines shared);
* ``timeouts``: ``--tasks`` tasks x ``--waits`` waits that time out (``asyncio.timeout`` and
  ``asyncio.wait_for`` around an ``Event`` of the task's own, never set);
* ``kuka``: per physics step, the KUKA controllers of ``kuka_throughput.py`` as evclock rate
  loops against the same controllers in a hand-written synchronous loop (final states
  asserted bit-identical), controller at 100 Hz and at 240 Hz;
* ``scale``: ``clock.sleep`` per wake-up with ``--big`` concurrent sleepers vs ``--tasks``.

``--variant NAME --workload W --count N ...`` runs one variant without valgrind (what the
harness runs, under valgrind or not).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import functools
import math
import os
import random
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import _peers as peers

MIN_NS = 1_000_000
MAX_NS = 10_000_000
SHARED_RATES = (50.0, 100.0, 200.0, 250.0, 500.0)
HERE = os.path.dirname(os.path.abspath(__file__))

# ------------------------------------------------------------------------------ plans


def sleep_plan(tasks: int, count: int, seed: int, whole_ms: bool = False) -> peers.Rows:
    """``count`` seeded durations per task in float seconds: integer ns in [1 ms, 10 ms], or
    whole milliseconds (1-10) with ``whole_ms``."""
    rng = random.Random(seed)
    if whole_ms:
        return [[rng.randint(1, 10) / 1e3 for _ in range(count)] for _ in range(tasks)]
    return [[rng.randint(MIN_NS, MAX_NS) / 1e9 for _ in range(count)] for _ in range(tasks)]


def rate_plan(loops: int, seed: int, shared: bool) -> list[float]:
    """Seeded rates in hertz: in [10, 500] (periods that almost never share a deadline), or
    drawn from :data:`SHARED_RATES` (deadlines shared)."""
    rng = random.Random(seed)
    if shared:
        return [rng.choice(SHARED_RATES) for _ in range(loops)]
    return [rng.uniform(10.0, 500.0) for _ in range(loops)]


def ticks(hz: float, ms: int) -> int:
    """Ticks of a rate loop at ``hz`` over ``ms`` of sim time (tick 0 at the start)."""
    return max(2, int(hz * ms) // 1000)


@dataclass(frozen=True)
class Workload:
    """How a workload's processes build their plan, take ``count`` of it, and count units."""

    kind: str  # "sleeps", "rates" or "kuka"
    whole_ms: bool = False
    shared: bool = False

    def build(self, tasks: int, max_count: int, seed: int) -> Any:
        if self.kind == "sleeps":
            return sleep_plan(tasks, max_count, seed, self.whole_ms)
        if self.kind == "rates":
            return rate_plan(tasks, seed, self.shared)
        return None

    def take(self, plan: Any, count: int) -> Any:
        if self.kind == "sleeps":
            return [row[:count] for row in plan]
        if self.kind == "rates":
            return [(hz, ticks(hz, count)) for hz in plan]
        return count

    def units(self, tasks: int, count: int, seed: int) -> int:
        """Wake-ups (physics steps for KUKA) at ``count``."""
        if self.kind == "sleeps":
            return tasks * count
        if self.kind == "rates":
            return sum(ticks(hz, count) for hz in rate_plan(tasks, seed, self.shared))
        return count


WORKLOADS = {
    "fanout": Workload("sleeps"),
    "coincident": Workload("sleeps", whole_ms=True),
    "timeouts": Workload("sleeps"),
    "scale": Workload("sleeps"),
    "rates": Workload("rates"),
    "rates-shared": Workload("rates", shared=True),
    "kuka": Workload("kuka"),
}

VARIANTS: dict[str, Callable[..., Any]] = {
    "asyncio.sleep(0), stock loop": peers.sleep0_fanout,
    "asyncio.sleep(0), uvloop": peers.sleep0_fanout_uvloop,
    "least future-based sleep": peers.least_future_sleep,
    "clock.sleep": peers.clock_sleep,
    "asyncio.sleep, sim loop": peers.asyncio_sleep_sim,
    "asyncio.sleep, instant stock": peers.asyncio_sleep_instant,
    "SimPy env.timeout": peers.simpy_sleep,
    "asyncio.sleep(0) per tick, stock": peers.sleep0_rates,
    "asyncio.sleep(0) per tick, uvloop": peers.sleep0_rates_uvloop,
    "clock.rate": peers.clock_rate,
    "rate deadlines, no Tick": peers.rate_deadlines,
    "rate deadlines, coroutine per tick": peers.rate_deadlines_coroutine,
    "asyncio.sleep rate, sim loop": peers.asyncio_rate_sim,
    "SimPy rate": peers.simpy_rate,
    "asyncio.timeout, instant stock": peers.timeout_instant,
    "asyncio.timeout, sim loop": peers.timeout_sim,
    "asyncio.wait_for, instant stock": peers.wait_for_instant,
    "asyncio.wait_for, sim loop": peers.wait_for_sim,
    "SimPy never | timeout": peers.simpy_timeouts,
    "kuka sync": peers.kuka_sync,
    "kuka evclock": peers.kuka_evclock,
    "kuka evclock, no time-step watch": functools.partial(
        peers.kuka_evclock, watch_time_step=False
    ),
}

# ------------------------------------------------------------------------------ one process

#: Callgrind's client requests, compiled into a small shared library that the measured
#: process loads with ctypes: instructions are collected only between ``begin`` and ``end``.
MARKS_C = """
#include <valgrind/callgrind.h>
void evb_start(void) { CALLGRIND_START_INSTRUMENTATION; }
void evb_zero(void) { CALLGRIND_ZERO_STATS; }
void evb_toggle(void) { CALLGRIND_TOGGLE_COLLECT; }
void evb_dump(void) { CALLGRIND_DUMP_STATS; }
"""


def build_marks(directory: str) -> str:
    """Compile :data:`MARKS_C` into ``directory``; return the library's path."""
    source = os.path.join(directory, "marks.c")
    library = os.path.join(directory, "marks.so")
    with open(source, "w") as f:
        f.write(MARKS_C)
    done = subprocess.run(
        ["gcc", "-shared", "-fPIC", "-O1", "-o", library, source],
        capture_output=True,
        text=True,
    )
    if done.returncode:
        raise SystemExit(
            "could not compile callgrind's client requests (needs gcc and valgrind's headers, "
            f"e.g. apt-get install gcc valgrind):\n{done.stderr}"
        )
    return library


class _Marks:
    """Collect instructions only around each measured run; dump each run's count."""

    def __init__(self, library: str) -> None:
        import ctypes

        self._lib = ctypes.CDLL(library)

    def start_instrumentation(self) -> None:
        self._lib.evb_start()

    def begin(self) -> None:
        self._lib.evb_zero()
        self._lib.evb_toggle()

    def end(self) -> None:
        self._lib.evb_toggle()
        self._lib.evb_dump()


class _AllocCounter:
    """Counts calls to CPython's memory allocators (the ``PYMEM_DOMAIN_MEM`` and
    ``PYMEM_DOMAIN_OBJ`` domains: every object and buffer not served by a free list) and
    the bytes they were asked for, between ``begin`` and ``end`` (``wallgap.py`` builds the
    library)."""

    def __init__(self, library: str) -> None:
        import ctypes

        self._lib = ctypes.PyDLL(library)  # PyDLL: called with the GIL held
        self._lib.evb_alloc_read.argtypes = [ctypes.c_int]
        self._lib.evb_alloc_read.restype = ctypes.c_ulonglong
        self._lib.evb_alloc_install()

    def begin(self) -> None:
        self._lib.evb_alloc_start()

    def end(self) -> str:
        self._lib.evb_alloc_stop()
        return " ".join(str(self._lib.evb_alloc_read(i)) for i in range(4))


def run_variant(args: argparse.Namespace) -> int:
    """Build the plan, then run (and time) the variant on its first ``count`` entries for
    each count given; print ``wall <count> <seconds>`` (and KUKA's final ``state``)."""
    workload = WORKLOADS[args.workload]
    plan = workload.build(args.tasks, args.max_count, args.seed)
    fn = VARIANTS[args.variant]
    # Imports before the clock starts.
    if workload.kind == "kuka":
        __import__("kuka_throughput")
    elif "SimPy" in args.variant:
        __import__("simpy")
    elif "sim loop" in args.variant or args.variant.startswith("clock."):
        __import__("evclock")

    def call(work: Any) -> Any:
        return fn(work, args.kuka_hz) if workload.kind == "kuka" else fn(work)

    # Warm up first (lazy imports, first-run allocations), so that no measured run pays
    # for them; under callgrind this runs uninstrumented (``--instr-atstart=no``).
    call(workload.take(plan, min(args.count)))
    marks = _Marks(args.callgrind_marks) if args.callgrind_marks else None
    if marks is not None:
        marks.start_instrumentation()
    allocs = _AllocCounter(args.alloc_counter) if args.alloc_counter else None
    for count in args.count:
        work = workload.take(plan, count)
        if marks is not None:
            marks.begin()
        if allocs is not None:
            allocs.begin()
        start = time.perf_counter()
        state = call(work)
        elapsed = time.perf_counter() - start
        if allocs is not None:
            print("allocs", count, allocs.end())
        if marks is not None:
            marks.end()
        print("wall", count, repr(elapsed))
        if workload.kind == "kuka":
            print("state", state)
    return 0


# ------------------------------------------------------------------------------ harness


@dataclass(frozen=True)
class Job:
    """One variant of one workload at two counts."""

    workload: str
    variant: str
    tasks: int
    counts: tuple[int, int]
    seed: int
    hz: float = 0.0

    def command(self, counts: Sequence[int], marks: str = "") -> list[str]:
        cmd = [sys.executable, os.path.join(HERE, "instructions.py"), "--variant", self.variant]
        cmd += ["--workload", self.workload, "--tasks", str(self.tasks), "--seed", str(self.seed)]
        cmd += ["--max-count", str(max(counts)), "--kuka-hz", repr(self.hz)]
        if marks:
            cmd += ["--callgrind-marks", marks]
        return [*cmd, "--count", *(str(c) for c in counts)]

    @property
    def units(self) -> int:
        """Wake-ups (steps) of the larger count minus those of the smaller."""
        w = WORKLOADS[self.workload]
        small, big = self.counts
        return w.units(self.tasks, big, self.seed) - w.units(self.tasks, small, self.seed)


def _output(stdout: str, key: str) -> list[str]:
    found = [line.split(" ", 2)[1:] for line in stdout.splitlines() if line.startswith(key + " ")]
    if not found:
        raise RuntimeError(f"no {key!r} line in the variant's output:\n{stdout}")
    return [" ".join(f) for f in found]


def callgrind_dumps(
    job: Job, marks: str, env: dict[str, str], label: str, options: Sequence[str] = ()
) -> tuple[list[str], str]:
    """Run ``job``'s measured runs (both counts, one process) under callgrind with
    ``options``, collecting only between the marks: the text of each run's dump, and the
    process's output. ``label`` names the job in an error."""
    with tempfile.TemporaryDirectory() as out:
        base = os.path.join(out, "callgrind.out")
        done = subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                *options,
                "--instr-atstart=no",
                "--collect-atstart=no",
                f"--callgrind-out-file={base}",
                *job.command(job.counts, marks),
            ],
            capture_output=True,
            text=True,
            timeout=3600,
            env=env,
        )
        if done.returncode:
            raise RuntimeError(f"{label} failed:\n{done.stdout}\n{done.stderr}")
        dumps = []
        for i in range(1, len(job.counts) + 1):
            with open(f"{base}.{i}") as f:
                dumps.append(f.read())
    return dumps, done.stdout


def callgrind(job: Job, marks: str, hash_seed: int = 0) -> tuple[list[int], str]:
    """Instructions executed by each of ``job``'s measured runs (both counts, one process
    under callgrind, collected only between the marks), and the process's output."""
    env = {**os.environ, "PYTHONHASHSEED": str(hash_seed)}
    dumps, stdout = callgrind_dumps(job, marks, env, job.variant)
    totals = []
    for i, dump in enumerate(dumps, 1):
        found = re.search(r"^totals: (\d+)", dump, re.MULTILINE)
        if found is None:
            raise RuntimeError(f"no totals in callgrind's dump {i} of {job.variant}")
        totals.append(int(found.group(1)))
    return totals, stdout


@dataclass
class Measured:
    """Per wake-up (per physics step for KUKA): instructions and wall nanoseconds."""

    instr: float
    ns: float = math.nan
    state: str = ""


class Harness:
    """Runs the callgrind processes ``jobs`` at a time (instruction counts do not depend on
    the load), then the plain wall-time processes one at a time, interleaved."""

    def __init__(self, jobs: int, wall_scale: int, wall_rounds: int, marks: str) -> None:
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=jobs)
        self.marks = marks
        self.wall_scale = wall_scale
        self.wall_rounds = wall_rounds
        self.pending: list[tuple[Job, int, Any, Any]] = []

    def instructions(self, job: Job, hash_seed: int = 0) -> Callable[[], Measured]:
        """Submit ``job``'s callgrind run; the returned function waits for it."""
        future = self.pool.submit(callgrind, job, self.marks, hash_seed)

        def result() -> Measured:
            (i_small, i_big), out = future.result()
            state = _output(out, "state")[-1] if job.workload == "kuka" else ""
            return Measured((i_big - i_small) / job.units, state=state)

        return result

    def wall(self, jobs: Sequence[Job]) -> list[float]:
        """Wall ns per unit of each job: its plain runs at ``wall_scale`` times both counts,
        ``wall_rounds`` rounds interleaved across ``jobs``, fastest of each count kept."""
        best = [[math.inf, math.inf] for _ in jobs]
        for _round in range(self.wall_rounds):
            for i, job in enumerate(jobs):
                counts = [c * self.wall_scale for c in job.counts]
                done = subprocess.run(
                    job.command(counts),
                    capture_output=True,
                    text=True,
                    timeout=3600,
                    env={**os.environ, "PYTHONHASHSEED": "0"} if job.workload != "kuka" else None,
                )
                if done.returncode:
                    raise RuntimeError(f"{job.variant} failed:\n{done.stdout}\n{done.stderr}")
                for line in _output(done.stdout, "wall"):
                    count, seconds = line.split()
                    k = counts.index(int(count))
                    best[i][k] = min(best[i][k], float(seconds))
        return [
            (b[1] - b[0]) / (job.units * self.wall_scale) * 1e9
            for b, job in zip(best, jobs, strict=True)
        ]


# ------------------------------------------------------------------------------ report


def _x(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.2f}x"


def print_table(title: str, rows: list[tuple[str, Measured]], floor: str, simpy: str) -> None:
    """One workload: instructions per wake-up and ratios to its floor; wall ns and ratio to
    SimPy (above 1: slower than SimPy)."""
    got = dict(rows)
    print(f"\n{title}")
    print(f"  {'variant':<34}{'instr':>9}{'vs floor':>10}{'wall ns':>9}{'vs SimPy':>10}")
    for name, m in rows:
        print(
            f"  {name:<34}{m.instr:>9,.0f}{_x(m.instr / got[floor].instr):>10}"
            f"{m.ns:>9,.0f}{_x(m.ns / got[simpy].ns):>10}"
        )


@dataclass
class Target:
    """A target of the project, met or not by a figure of this run (a ratio here)."""

    what: str
    value: float
    limit: float
    at_least: bool = False

    @property
    def met(self) -> bool:
        return self.value >= self.limit if self.at_least else self.value <= self.limit

    def line(self) -> str:
        sign = ">=" if self.at_least else "<="
        verdict = "met" if self.met else "NOT MET"
        return f"  {self.what:<70}{self.value:>7.3f}x  {sign} {self.limit:.2f}x  {verdict}"


SLEEP_VARIANTS = (
    "asyncio.sleep(0), stock loop",
    "least future-based sleep",
    "clock.sleep",
    "asyncio.sleep, sim loop",
    "SimPy env.timeout",
)
RATE_VARIANTS = (
    "asyncio.sleep(0) per tick, stock",
    "clock.rate",
    "asyncio.sleep rate, sim loop",
    "SimPy rate",
)
TIMEOUT_VARIANTS = (
    "asyncio.timeout, instant stock",
    "asyncio.timeout, sim loop",
    "asyncio.wait_for, instant stock",
    "asyncio.wait_for, sim loop",
    "SimPy never | timeout",
)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000, help="tasks (fanout, coincident, timeouts)")
    p.add_argument("--sleeps", type=int, default=120, help="sleeps per task; also run at half")
    p.add_argument("--waits", type=int, default=10, help="timed-out waits per task; also half")
    p.add_argument("--loops", type=int, default=100, help="rate loops (rates, rates-shared)")
    p.add_argument("--rate-ms", type=int, default=1000, help="sim ms of rate loops; also half")
    p.add_argument("--big", type=int, default=100_000, help="concurrent sleepers (scale)")
    p.add_argument("--big-sleeps", type=int, default=2, help="sleeps per task in scale; also half")
    p.add_argument("--kuka-steps", type=int, default=1200, help="physics steps (multiple of 12)")
    p.add_argument("--hash-seeds", type=int, default=3, help="string-hash seeds for KUKA")
    p.add_argument(
        "--kuka-no-watch",
        action="store_true",
        help="also count KUKA with PyBulletTimeSource(watch_time_step=False)",
    )
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=2, help="callgrind processes at a time")
    p.add_argument("--wall-scale", type=int, default=10, help="wall runs' counts, x callgrind's")
    p.add_argument("--wall-rounds", type=int, default=3, help="interleaved wall rounds")
    p.add_argument("--only", choices=list(WORKLOADS), action="append")
    p.add_argument("--variant", choices=sorted(VARIANTS), help=argparse.SUPPRESS)
    p.add_argument("--workload", choices=list(WORKLOADS), help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, nargs="+", help=argparse.SUPPRESS)
    p.add_argument("--max-count", type=int, help=argparse.SUPPRESS)
    p.add_argument("--kuka-hz", type=float, default=100.0, help=argparse.SUPPRESS)
    p.add_argument("--callgrind-marks", help=argparse.SUPPRESS)
    p.add_argument("--alloc-counter", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _half(n: int, name: str) -> tuple[int, int]:
    if n < 1:
        raise SystemExit(f"{name} must be at least 1 (the benchmark also runs half of it)")
    return n // 2, n


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.variant is not None:
        if args.max_count is None:
            args.max_count = max(args.count)
        return run_variant(args)
    parts = args.only or [w for w in WORKLOADS if w != "scale"]
    if args.hash_seeds < 1:
        raise SystemExit("--hash-seeds must be at least 1")
    if args.kuka_steps % 12:
        raise SystemExit("--kuka-steps must be a multiple of 12 (half of it a whole ns count)")
    started = time.monotonic()
    marks_dir = tempfile.TemporaryDirectory()
    h = Harness(args.jobs, args.wall_scale, args.wall_rounds, build_marks(marks_dir.name))
    seed = args.seed
    sleeps, waits = _half(args.sleeps, "--sleeps"), _half(args.waits, "--waits")
    rate_ms = _half(args.rate_ms, "--rate-ms")

    # Every workload's jobs, submitted to callgrind at once (results in this order): its
    # key, title, variants, tasks or loops, and both counts.
    workloads = [
        ("fanout", "fan-out", SLEEP_VARIANTS, args.tasks, sleeps),
        ("coincident", "fan-out, whole ms", SLEEP_VARIANTS, args.tasks, sleeps),
        ("rates", "rate loops", RATE_VARIANTS, args.loops, rate_ms),
        ("rates-shared", "rate loops, shared", RATE_VARIANTS, args.loops, rate_ms),
        ("timeouts", "timeouts", TIMEOUT_VARIANTS, args.tasks, waits),
    ]
    tables: list[tuple[str, str, list[Job]]] = [
        (key, title, [Job(key, v, n, counts, seed) for v in variants])
        for key, title, variants, n, counts in workloads
        if key in parts
    ]
    if "scale" in parts:
        big_sleeps = _half(args.big_sleeps, "--big-sleeps")
        jobs = [
            Job("scale", "clock.sleep", args.tasks, big_sleeps, seed),
            Job("scale", "clock.sleep", args.big, big_sleeps, seed),
        ]
        tables.append(("scale", "scale", jobs))
    kuka_variants = ["kuka sync", "kuka evclock"]
    if args.kuka_no_watch:
        kuka_variants.append("kuka evclock, no time-step watch")
    steps = (args.kuka_steps // 12 * 6, args.kuka_steps)
    kuka_jobs = {
        hz: [Job("kuka", v, 1, steps, seed, hz) for v in kuka_variants] for hz in (100.0, 240.0)
    }
    waits_for: dict[Job, list[Callable[[], Measured]]] = {}
    for _key, _label, jobs in tables:
        for job in jobs:
            waits_for[job] = [h.instructions(job)]
    if "kuka" in parts:
        for jobs in kuka_jobs.values():
            for job in jobs:
                waits_for[job] = [h.instructions(job, s) for s in range(args.hash_seeds)]

    measured = {job: [w() for w in ws] for job, ws in waits_for.items()}
    h.pool.shutdown()
    all_jobs = [job for _k, _l, jobs in tables for job in jobs]
    if "kuka" in parts:
        all_jobs += [job for jobs in kuka_jobs.values() for job in jobs[:2]]
    for job, ns in zip(all_jobs, h.wall(all_jobs), strict=True):
        measured[job][0].ns = ns

    print(
        f"python {sys.version.split()[0]}; per wake-up: instructions under callgrind, "
        f"(run at N - run at N/2) / (wake-ups at N - at N/2), plans built in both runs; wall "
        f"ns the same way from plain runs at {args.wall_scale}x N, fastest of "
        f"{args.wall_rounds} interleaved rounds; every process with PYTHONHASHSEED=0"
    )
    got: dict[tuple[str, str], Measured] = {}
    for key, _label, jobs in tables:
        rows = [(job.variant, measured[job][0]) for job in jobs]
        got.update({(key, name): m for name, m in rows})
        n = jobs[0].tasks
        if key in ("fanout", "coincident"):
            unit = "integer ns in [1 ms, 10 ms]" if key == "fanout" else "whole ms, 1-10"
            title = f"{key}: {n:,} tasks x N = {sleeps[1]} sleeps, durations {unit} (seed {seed})"
            print_table(title, rows, SLEEP_VARIANTS[0], "SimPy env.timeout")
        elif key.startswith("rates"):
            rates = "50/100/200/250/500 Hz" if key.endswith("shared") else "10-500 Hz"
            title = f"{key}: {n} rate loops at {rates} for N = {rate_ms[1]} ms of sim time"
            title += f" (seed {seed}; {jobs[0].units:,} ticks from N/2 to N)"
            print_table(title, rows, RATE_VARIANTS[0], "SimPy rate")
        elif key == "timeouts":
            title = f"timeouts: {n:,} tasks x N = {waits[1]} waits that time out (seed {seed})"
            print_table(title, rows, TIMEOUT_VARIANTS[0], "SimPy never | timeout")
        else:
            small, big = (measured[job][0] for job in jobs)
            print(f"\nscale: clock.sleep, N = {args.big_sleeps} sleeps per task (seed {seed})")
            print(f"  {jobs[0].tasks:>9,} sleepers {small.instr:>9,.0f} instr {small.ns:>7,.0f} ns")
            print(
                f"  {jobs[1].tasks:>9,} sleepers {big.instr:>9,.0f} instr {big.ns:>7,.0f} ns"
                f"   {big.instr / small.instr:.2f}x / {big.ns / small.ns:.2f}x the first"
            )
    kuka_means: dict[float, float] = {}
    if "kuka" in parts:
        print(
            f"\nkuka: {args.kuka_steps} physics steps at 240 Hz (N/2 subtracted), per step; "
            "ratio = synchronous loop's instructions / evclock's (1.0: evclock costs nothing)"
        )
        header = (
            f"  {'controller':<12}{'hash seed':>10}{'sync instr':>12}{'evclock':>10}{'ratio':>8}"
        )
        print(header + (f"{'no watch':>10}{'ratio':>8}" if args.kuka_no_watch else ""))
        for hz, jobs in kuka_jobs.items():
            sync, *ours = (measured[job] for job in jobs)
            ratios: list[list[float]] = [[] for _ in ours]
            for s in range(args.hash_seeds):
                line = f"  {hz:>7g} Hz  {s:>10}{sync[s].instr:>12,.0f}"
                for i, ev in enumerate(ours):
                    if ev[s].state != sync[s].state:
                        raise SystemExit(
                            f"KUKA at {hz:g} Hz ({jobs[i + 1].variant}): states differ"
                        )
                    ratios[i].append(sync[s].instr / ev[s].instr)
                    line += f"{ev[s].instr:>10,.0f}{ratios[i][-1]:>8.3f}"
                print(line + "   final states bit-identical")
            kuka_means[hz] = statistics.fmean(ratios[0])
            wall_ratio = sync[0].ns / ours[0][0].ns
            print(
                f"  {hz:>7g} Hz  mean of {args.hash_seeds} seeds: {kuka_means[hz]:.3f}"
                + (f", no watch {statistics.fmean(ratios[1]):.3f}" if args.kuka_no_watch else "")
                + f"; wall time (random hash seeds): {wall_ratio:.3f}"
            )

    # The summary table and the targets.
    columns = {
        "fanout": ("asyncio.sleep(0), stock loop", "clock.sleep", "asyncio.sleep, sim loop"),
        "coincident": ("asyncio.sleep(0), stock loop", "clock.sleep", "asyncio.sleep, sim loop"),
        "rates": ("asyncio.sleep(0) per tick, stock", "clock.rate", "asyncio.sleep rate, sim loop"),
        "rates-shared": (
            "asyncio.sleep(0) per tick, stock",
            "clock.rate",
            "asyncio.sleep rate, sim loop",
        ),
    }
    simpy_of = {
        "fanout": "SimPy env.timeout",
        "coincident": "SimPy env.timeout",
        "rates": "SimPy rate",
        "rates-shared": "SimPy rate",
        "timeouts": "SimPy never | timeout",
    }
    summary = [(key, label) for key, label, _jobs in tables if key in simpy_of]
    if summary:
        print(
            "\nsummary: instructions per wake-up (x the floor); wall: SimPy's wake-ups/s over"
            " evclock's (same run)"
        )
        print(
            f"  {'workload':<20}{'floor':>8}{'clock.*':>16}{'asyncio.* (sim)':>17}"
            f"{'SimPy':>16}{'wall clock.*':>14}{'wall asyncio.*':>16}"
        )

        def cell(m: Measured, floor: Measured) -> str:
            return f"{m.instr / 1000:.1f}k ({m.instr / floor.instr:.2f}x)"

        for key, label in summary:
            simpy = got[(key, simpy_of[key])]
            if key == "timeouts":
                lines = [
                    (
                        "timeouts (timeout)",
                        "asyncio.timeout, instant stock",
                        None,
                        "asyncio.timeout, sim loop",
                    ),
                    (
                        "timeouts (wait_for)",
                        "asyncio.wait_for, instant stock",
                        None,
                        "asyncio.wait_for, sim loop",
                    ),
                ]
            else:
                floor_name, clock_name, asyncio_name = columns[key]
                lines = [(label, floor_name, clock_name, asyncio_name)]
            for name, floor_name, clock_name, asyncio_name in lines:
                floor = got[(key, floor_name)]
                clock_cell = cell(got[(key, clock_name)], floor) if clock_name else "-"
                wall_clock = _x(got[(key, clock_name)].ns / simpy.ns) if clock_name else "-"
                asyncio_m = got[(key, asyncio_name)]
                print(
                    f"  {name:<20}{floor.instr / 1000:>7.1f}k{clock_cell:>16}"
                    f"{cell(asyncio_m, floor):>17}{cell(simpy, floor):>16}"
                    f"{wall_clock:>14}{_x(asyncio_m.ns / simpy.ns):>16}"
                )

    targets: list[Target] = []

    def ratio(key: str, a: str, b: str) -> float:
        return got[(key, a)].instr / got[(key, b)].instr

    for key in ("fanout", "coincident"):
        if key in parts:
            tag = "fan-out" if key == "fanout" else "fan-out, whole ms"
            targets.append(
                Target(
                    f"{tag}: clock.sleep / least future-based sleep",
                    ratio(key, "clock.sleep", "least future-based sleep"),
                    1.05,
                )
            )
            targets.append(
                Target(
                    f"{tag}: asyncio.sleep (sim loop) / asyncio.sleep(0) floor",
                    ratio(key, "asyncio.sleep, sim loop", "asyncio.sleep(0), stock loop"),
                    1.4,
                )
            )
    for key in ("rates", "rates-shared"):
        if key in parts:
            tag = "rate loops" + (", shared deadlines" if key == "rates-shared" else "")
            targets.append(
                Target(
                    f"{tag}: clock.rate / asyncio.sleep(0) floor",
                    ratio(key, "clock.rate", "asyncio.sleep(0) per tick, stock"),
                    1.5,
                )
            )
    if "timeouts" in parts:
        for api in ("asyncio.timeout", "asyncio.wait_for"):
            targets.append(
                Target(
                    f"timeouts: {api} (sim loop) / stock asyncio, instant time",
                    ratio("timeouts", f"{api}, sim loop", f"{api}, instant stock"),
                    1.2,
                )
            )
    for hz, limit in ((100.0, 0.97), (240.0, 0.95)):
        if hz in kuka_means:
            targets.append(
                Target(
                    f"KUKA {hz:g} Hz control: hand-written loop / evclock (mean of seeds)",
                    kuka_means[hz],
                    limit,
                    at_least=True,
                )
            )
    if targets:
        print("\ntargets (instructions, same run)")
        for target in targets:
            print(target.line())
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
