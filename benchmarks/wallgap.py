"""Where wall time per wake-up goes that instruction counts do not show: one command, one run.

For evclock's ``clock.sleep`` / ``clock.rate``, ``asyncio.sleep`` on evclock's sim loop,
SimPy and stock asyncio's ``sleep(0)`` task switch, on the fan-out and rate-loop workloads
of ``instructions.py`` (same plans, same variants: ``_peers.py``), it prints per wake-up:

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

Run: ``python benchmarks/wallgap.py [--sleeps 60 --rate-ms 1000 --jobs 2 --wall-rounds 5]``.
Needs valgrind, gcc, valgrind's headers and Python's headers. CPython's specialisation
statistics need a build configured with ``--enable-pystats``; the script says whether this
one has them.
"""

from __future__ import annotations

import argparse
import concurrent.futures
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
    "clock.sleep",
    "asyncio.sleep, sim loop",
    "SimPy env.timeout",
    "asyncio.sleep(0), stock loop",
)
RATES = (
    "clock.rate",
    "asyncio.sleep rate, sim loop",
    "SimPy rate",
    "asyncio.sleep(0) per tick, stock",
)
SIMPY = {"fanout": "SimPy env.timeout", "rates": "SimPy rate"}
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


def simulate(job: ins.Job, marks: str) -> list[dict[str, int]]:
    """Each measured run's event totals under callgrind with cache and branch simulation."""
    with tempfile.TemporaryDirectory() as out:
        base = os.path.join(out, "callgrind.out")
        done = subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                "--cache-sim=yes",
                "--branch-sim=yes",
                *CACHES,
                "--instr-atstart=no",
                "--collect-atstart=no",
                f"--callgrind-out-file={base}",
                *job.command(job.counts, marks),
            ],
            capture_output=True,
            text=True,
            timeout=3600,
            env={**os.environ, "PYTHONHASHSEED": "0"},
        )
        if done.returncode:
            raise RuntimeError(f"{job.variant} failed:\n{done.stdout}\n{done.stderr}")
        totals = []
        for i in range(1, len(job.counts) + 1):
            with open(f"{base}.{i}") as f:
                text = f.read()
            events = re.search(r"^events: (.+)$", text, re.MULTILINE)
            found = re.search(r"^totals: (.+)$", text, re.MULTILINE)
            if events is None or found is None:
                raise RuntimeError(f"no totals in callgrind's dump {i} of {job.variant}")
            names, values = events.group(1).split(), found.group(1).split()
            totals.append(dict(zip(names, map(int, values), strict=True)))
    return totals


def count_allocations(job: ins.Job, library: str) -> list[int]:
    """Allocator calls (MEM, OBJ) and bytes (MEM, OBJ) per wake-up, from a plain process."""
    done = subprocess.run(
        [*job.command(job.counts), "--alloc-counter", library],
        capture_output=True,
        text=True,
        timeout=3600,
        env={**os.environ, "PYTHONHASHSEED": "0"},
    )
    if done.returncode:
        raise RuntimeError(f"{job.variant} failed:\n{done.stdout}\n{done.stderr}")
    small, big = ([int(x) for x in line.split()[1:]] for line in ins._output(done.stdout, "allocs"))
    return [round((b - s) / job.units) for s, b in zip(small, big, strict=True)]


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
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()
    parts = args.only or ["fanout", "rates"]
    tmp = tempfile.TemporaryDirectory()
    marks = ins.build_marks(tmp.name)
    allocs = build_alloc_counter(tmp.name)
    jobs: dict[str, list[ins.Job]] = {}
    if "fanout" in parts:
        counts = ins._half(args.sleeps, "--sleeps")
        jobs["fanout"] = [ins.Job("fanout", v, args.tasks, counts, args.seed) for v in FANOUT]
    if "rates" in parts:
        counts = ins._half(args.rate_ms, "--rate-ms")
        jobs["rates"] = [ins.Job("rates", v, args.loops, counts, args.seed) for v in RATES]
    every = [job for js in jobs.values() for job in js]
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        sims = {job: pool.submit(simulate, job, marks) for job in every}
        rows: dict[ins.Job, Row] = {}
        for job in every:
            small, big = sims[job].result()
            per = {e: (big[e] - small[e]) / job.units for e in EVENTS}
            rows[job] = Row(per, count_allocations(job, allocs))
    harness = ins.Harness(1, args.wall_scale, args.wall_rounds, marks)
    load_before = load()
    for job, ns in zip(every, harness.wall(every), strict=True):
        rows[job].wall_ns = ns
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
    for key, js in jobs.items():
        simpy = rows[next(j for j in js if j.variant == SIMPY[key])]
        if key == "fanout":
            title = f"fanout: {args.tasks:,} tasks x N = {args.sleeps} sleeps of 1-10 ms (ns)"
        else:
            title = f"rates: {args.loops} rate loops at 10-500 Hz for N = {args.rate_ms} ms"
        print(f"\n{title}")
        print(
            f"  {'variant':<33}{'instr':>7}{'D1 miss':>8}{'LL miss':>8}{'I1 miss':>8}"
            f"{'Bc miss':>8}{'Bi miss':>8}{'est cyc':>8}{'allocs':>7}{'bytes':>6}"
            f"{'wall ns':>8}{'est/SimPy':>10}{'wall/SimPy':>11}"
        )
        for job in js:
            r = rows[job]
            e = r.events
            print(
                f"  {job.variant:<33}{e['Ir']:>7,.0f}{r.d1:>8.1f}{r.ll:>8.2f}{e['I1mr']:>8.1f}"
                f"{e['Bcm']:>8.1f}{e['Bim']:>8.1f}{r.cycles:>8,.0f}"
                f"{r.allocs[0] + r.allocs[1]:>7}{r.allocs[2] + r.allocs[3]:>6}"
                f"{r.wall_ns:>8,.0f}{r.cycles / simpy.cycles:>9.2f}x"
                f"{r.wall_ns / simpy.wall_ns:>10.2f}x"
            )
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
