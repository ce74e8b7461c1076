"""Where wall time per wake-up goes that instruction counts do not show: one command, one run.

For evclock's ``clock.sleep`` / ``clock.rate``, ``asyncio.sleep`` on evclock's sim loop,
SimPy, stock asyncio's ``sleep(0)`` task switch and the least a future-based sleep can cost
(a plain function waking tasks parked on C futures: no event loop, no evclock code), on the
fan-out and rate-loop workloads of ``instructions.py`` (same plans, same variants:
``_peers.py``), it prints per wake-up:

* **instructions**, **D1 misses** (first-level data cache, reads + writes), **LL misses**
  (last level, data), **I1 misses**, **conditional and indirect branch mispredicts**: one
  process per variant under ``valgrind --tool=callgrind --cache-sim=yes --branch-sim=yes``
  with a fixed simulated cache (``--D1``/``--I1`` 32 KiB 8-way, ``--LL`` 1 MiB 8-way: this
  machine's per-core L1 and L2; its L3 is shared with whatever else runs), collected only
  around the workload at two repetition counts (steady state: (at N - at N/2) / (wake-ups
  at N - at N/2), as ``instructions.py``);
* an **estimated cycle count** from those, with cachegrind's documented weights (1 per
  instruction, 10 per D1/I1 miss served by LL, 100 per LL miss, 15 per mispredict): not a
  measurement, a model, to compare with the wall ratio;
* **allocator calls and bytes** per wake-up: every call to CPython's object and memory
  allocators (``PyMem_SetAllocator`` hooks in a small C library compiled at start-up),
  counted the same steady-state way in plain processes (objects served from a free list -
  floats, small tuples, frames of running coroutines - make no call);
* **wall ns** per wake-up, same method, best of ``--wall-rounds`` interleaved rounds, as a
  ratio to SimPy, with the machine's load average beside it.

``--also NAME=PATH`` (repeatable) runs evclock's variants a second time on the ``evclock``
package under ``PATH`` (first on ``PYTHONPATH``): an earlier version (``git worktree add``)
or a compiled prototype, measured in the same run.

Run: ``python benchmarks/wallgap.py [--sleeps 60 --rate-ms 1000 --jobs 2 --wall-rounds 5]``.
Needs valgrind, gcc, valgrind's headers and Python's headers. CPython's specialisation
statistics need a build configured with ``--enable-pystats``; the script says whether this
one has them.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import math
import os
import re
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass

import instructions as ins

#: The simulated caches (bytes, ways, line bytes): this machine's per-core L1s and L2.
CACHES = ("--D1=32768,8,64", "--I1=32768,8,64", "--LL=1048576,8,64")
#: cachegrind's weights for its cycle estimate (valgrind's manual, "cg_annotate").
L1_MISS_CYCLES = 10
LL_MISS_CYCLES = 100
MISPREDICT_CYCLES = 15

ALLOC_C = r"""
#include <Python.h>
/* Counts calls to the MEM and OBJ allocator domains (index 0 and 1) and the bytes asked. */
static PyMemAllocatorEx orig[2];
static unsigned long long calls[2], bytes[2];
static int active;
#define HOOKS(D) \
static void *m##D(void *c, size_t n) { if (active) { calls[D]++; bytes[D] += n; } \
    return orig[D].malloc(orig[D].ctx, n); } \
static void *c##D(void *c, size_t e, size_t s) { if (active) { calls[D]++; bytes[D] += e * s; } \
    return orig[D].calloc(orig[D].ctx, e, s); } \
static void *r##D(void *c, void *p, size_t n) { if (active) { calls[D]++; bytes[D] += n; } \
    return orig[D].realloc(orig[D].ctx, p, n); } \
static void f##D(void *c, void *p) { orig[D].free(orig[D].ctx, p); }
HOOKS(0)
HOOKS(1)
void evb_alloc_install(void) {
    PyMemAllocatorEx mem = {NULL, m0, c0, r0, f0}, obj = {NULL, m1, c1, r1, f1};
    PyMem_GetAllocator(PYMEM_DOMAIN_MEM, &orig[0]);
    PyMem_GetAllocator(PYMEM_DOMAIN_OBJ, &orig[1]);
    PyMem_SetAllocator(PYMEM_DOMAIN_MEM, &mem);
    PyMem_SetAllocator(PYMEM_DOMAIN_OBJ, &obj);
}
void evb_alloc_start(void) { calls[0] = calls[1] = bytes[0] = bytes[1] = 0; active = 1; }
void evb_alloc_stop(void) { active = 0; }
/* 0: MEM calls, 1: OBJ calls, 2: MEM bytes, 3: OBJ bytes */
unsigned long long evb_alloc_read(int i) { return i < 2 ? calls[i] : bytes[i - 2]; }
"""

FANOUT = (
    "least future-based sleep",
    "clock.sleep",
    "asyncio.sleep, sim loop",
    "asyncio.sleep, instant stock",  # stock asyncio's own timers, time jumping between them
    "SimPy env.timeout",
    "asyncio.sleep(0), stock loop",
)
RATES = (
    "clock.rate",
    # where a tick's cost sits: its deadlines alone, then in a coroutine per tick
    "rate deadlines, no Tick",
    "rate deadlines, coroutine per tick",
    "asyncio.sleep rate, sim loop",
    "SimPy rate",
    "asyncio.sleep(0) per tick, stock",
)
SIMPY = {"fanout": "SimPy env.timeout", "rates": "SimPy rate"}
#: The variants that run evclock's code (run again for each ``--also`` tree).
EVCLOCK = (
    "clock.sleep",
    "asyncio.sleep, sim loop",
    "clock.rate",
    "rate deadlines, no Tick",
    "rate deadlines, coroutine per tick",
    "asyncio.sleep rate, sim loop",
)


@dataclass(frozen=True)
class Entry:
    """A job, run on this checkout's evclock or on another tree's (``--also``)."""

    job: ins.Job
    label: str
    pythonpath: str = ""

    def env(self) -> dict[str, str]:
        env = {**os.environ, "PYTHONHASHSEED": "0"}
        if self.pythonpath:
            env["PYTHONPATH"] = self.pythonpath
        return env


EVENTS = ("Ir", "D1mr", "D1mw", "DLmr", "DLmw", "I1mr", "ILmr", "Bcm", "Bim")


def build_alloc_counter(directory: str) -> str:
    """Compile :data:`ALLOC_C` into ``directory``; return the library's path."""
    source = os.path.join(directory, "allocs.c")
    library = os.path.join(directory, "allocs.so")
    with open(source, "w") as f:
        f.write(ALLOC_C)
    include = sysconfig.get_paths()["include"]
    done = subprocess.run(
        ["gcc", "-shared", "-fPIC", "-O2", f"-I{include}", "-o", library, source],
        capture_output=True,
        text=True,
    )
    if done.returncode:
        raise SystemExit(f"could not compile the allocation counter:\n{done.stderr}")
    return library


def simulate(entry: Entry, marks: str) -> list[dict[str, int]]:
    """Each measured run's event totals under callgrind with cache and branch simulation."""
    job = entry.job
    options = ["--cache-sim=yes", "--branch-sim=yes", *CACHES]
    dumps, _ = ins.callgrind_dumps(job, marks, entry.env(), entry.label, options)
    totals = []
    for i, dump in enumerate(dumps, 1):
        events = re.search(r"^events: (.+)$", dump, re.MULTILINE)
        found = re.search(r"^totals: (.+)$", dump, re.MULTILINE)
        if events is None or found is None:
            raise RuntimeError(f"no totals in callgrind's dump {i} of {job.variant}")
        names, values = events.group(1).split(), found.group(1).split()
        totals.append(dict(zip(names, map(int, values), strict=True)))
    return totals


def count_allocations(entry: Entry, library: str) -> list[int]:
    """Allocator calls (MEM, OBJ) and bytes (MEM, OBJ) per wake-up, from a plain process."""
    job = entry.job
    done = subprocess.run(
        [*job.command(job.counts), "--alloc-counter", library],
        capture_output=True,
        text=True,
        timeout=3600,
        env=entry.env(),
    )
    if done.returncode:
        raise RuntimeError(f"{job.variant} failed:\n{done.stdout}\n{done.stderr}")
    small, big = ([int(x) for x in line.split()[1:]] for line in ins._output(done.stdout, "allocs"))
    return [round((b - s) / job.units) for s, b in zip(small, big, strict=True)]


def wall(entries: Sequence[Entry], scale: int, rounds: int) -> list[float]:
    """Wall ns per wake-up of each entry: plain runs at ``scale`` times both counts,
    ``rounds`` rounds interleaved across the entries, fastest of each count kept."""
    best = [[math.inf, math.inf] for _ in entries]
    for _round in range(rounds):
        for i, entry in enumerate(entries):
            job = entry.job
            counts = [c * scale for c in job.counts]
            done = subprocess.run(
                job.command(counts), capture_output=True, text=True, env=entry.env()
            )
            if done.returncode:
                raise RuntimeError(f"{entry.label} failed:\n{done.stdout}\n{done.stderr}")
            for line in ins._output(done.stdout, "wall"):
                count, seconds = line.split()
                k = counts.index(int(count))
                best[i][k] = min(best[i][k], float(seconds))
    return [
        (b[1] - b[0]) / (entry.job.units * scale) * 1e9
        for b, entry in zip(best, entries, strict=True)
    ]


@dataclass
class Row:
    """Per wake-up figures of one variant."""

    events: dict[str, float]
    allocs: list[int]
    wall_ns: float = 0.0

    @property
    def d1(self) -> float:
        return self.events["D1mr"] + self.events["D1mw"]

    @property
    def ll(self) -> float:
        return self.events["DLmr"] + self.events["DLmw"]

    @property
    def mispredicts(self) -> float:
        return self.events["Bcm"] + self.events["Bim"]

    @property
    def cycles(self) -> float:
        """cachegrind's cycle estimate (a model, not a measurement)."""
        e = self.events
        l1 = self.d1 + e["I1mr"]
        ll = self.ll + e["ILmr"]
        return (
            e["Ir"]
            + L1_MISS_CYCLES * (l1 - ll)
            + LL_MISS_CYCLES * ll
            + MISPREDICT_CYCLES * self.mispredicts
        )


def load() -> str:
    """The machine's load averages (1, 5, 15 min) and CPU count."""
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} CPUs"


def pystats() -> str:
    """Whether this CPython offers its specialisation statistics."""
    if hasattr(sys, "_stats_on") or "--enable-pystats" in str(
        sysconfig.get_config_var("CONFIG_ARGS")
    ):
        return "this CPython was built with --enable-pystats (not read by this script)"
    return (
        "specialisation statistics: not available (this CPython was not built with "
        "--enable-pystats)"
    )


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000, help="fan-out tasks (default 1000)")
    p.add_argument("--sleeps", type=int, default=60, help="sleeps per task; also half (60)")
    p.add_argument("--loops", type=int, default=100, help="rate loops (default 100)")
    p.add_argument("--rate-ms", type=int, default=1000, help="sim ms of rate loops; also half")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=2, help="valgrind processes at a time (2)")
    p.add_argument("--wall-scale", type=int, default=10, help="wall runs' counts, x valgrind's")
    p.add_argument("--wall-rounds", type=int, default=5, help="interleaved wall rounds (5)")
    p.add_argument("--only", choices=("fanout", "rates"), action="append")
    p.add_argument(
        "--also",
        metavar="NAME=PATH",
        action="append",
        default=[],
        help="also run evclock's variants on the evclock package under PATH (put first on "
        "PYTHONPATH), labelled NAME: another version, or a compiled prototype",
    )
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()
    parts = args.only or ["fanout", "rates"]
    tmp = tempfile.TemporaryDirectory()
    marks = ins.build_marks(tmp.name)
    allocs = build_alloc_counter(tmp.name)
    trees = [("", "")]
    for also in args.also:
        name, sep, path = also.partition("=")
        if not sep or not os.path.isdir(os.path.join(path, "evclock")):
            raise SystemExit(f"--also needs NAME=PATH with an evclock package in PATH: {also!r}")
        trees.append((f" [{name}]", os.path.abspath(path)))
    entries: dict[str, list[Entry]] = {}
    plans = []
    if "fanout" in parts:
        counts = ins._half(args.sleeps, "--sleeps")
        plans.append(("fanout", FANOUT, args.tasks, counts))
    if "rates" in parts:
        counts = ins._half(args.rate_ms, "--rate-ms")
        plans.append(("rates", RATES, args.loops, counts))
    for key, variants, n, counts in plans:
        entries[key] = [
            Entry(ins.Job(key, v, n, counts, args.seed), v + suffix, path)
            for v in variants
            for suffix, path in trees
            if not path or v in EVCLOCK
        ]
    every = [entry for es in entries.values() for entry in es]
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        sims = {entry: pool.submit(simulate, entry, marks) for entry in every}
        rows: dict[Entry, Row] = {}
        for entry in every:
            small, big = sims[entry].result()
            per = {e: (big[e] - small[e]) / entry.job.units for e in EVENTS}
            rows[entry] = Row(per, count_allocations(entry, allocs))
    load_before = load()
    for entry, ns in zip(every, wall(every, args.wall_scale, args.wall_rounds), strict=True):
        rows[entry].wall_ns = ns
    load_after = load()

    print(
        f"python {sys.version.split()[0]}; per wake-up, steady state ((at N - at N/2) / "
        "(wake-ups at N - at N/2)); every process with PYTHONHASHSEED=0"
    )
    print(
        "simulated caches: D1 and I1 32 KiB 8-way, LL 1 MiB 8-way (64-byte lines); est. "
        f"cycles = Ir + {L1_MISS_CYCLES} x L1 misses served by LL + {LL_MISS_CYCLES} x LL "
        f"misses + {MISPREDICT_CYCLES} x mispredicts (cachegrind's model)"
    )
    print(
        f"wall: plain processes at {args.wall_scale}x N, fastest of {args.wall_rounds} "
        f"interleaved rounds; {load_before} before, {load_after} after"
    )
    print(pystats())
    for key, es in entries.items():
        simpy = rows[next(e for e in es if e.label == SIMPY[key])]
        if key == "fanout":
            title = f"fanout: {args.tasks:,} tasks x N = {args.sleeps} sleeps of 1-10 ms (ns)"
        else:
            title = f"rates: {args.loops} rate loops at 10-500 Hz for N = {args.rate_ms} ms"
        print(f"\n{title}")
        print(
            f"  {'variant':<36}{'instr':>7}{'D1 miss':>8}{'LL miss':>8}{'I1 miss':>8}"
            f"{'Bc miss':>8}{'Bi miss':>8}{'est cyc':>8}{'allocs':>7}{'bytes':>6}"
            f"{'wall ns':>8}{'est/SimPy':>10}{'wall/SimPy':>11}"
        )
        for entry in es:
            r = rows[entry]
            e = r.events
            print(
                f"  {entry.label:<36}{e['Ir']:>7,.0f}{r.d1:>8.1f}{r.ll:>8.2f}{e['I1mr']:>8.1f}"
                f"{e['Bcm']:>8.1f}{e['Bim']:>8.1f}{r.cycles:>8,.0f}"
                f"{r.allocs[0] + r.allocs[1]:>7}{r.allocs[2] + r.allocs[3]:>6}"
                f"{r.wall_ns:>8,.0f}{r.cycles / simpy.cycles:>9.2f}x"
                f"{r.wall_ns / simpy.wall_ns:>10.2f}x"
            )
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
