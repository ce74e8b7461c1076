"""Profile the sim loop's hot path: the fan-out workload (a) under cProfile.

Runs ``await clock.sleep(d)`` fan-out (see ``fanout.py``: tasks x sleeps of seeded random
1-10 ms durations) once under :mod:`cProfile` and prints the top functions by ``tottime``
(time spent in the function itself, excluding callees), which is where to look when the
wakeup rate drops. cProfile slows Python code several-fold and C code hardly at all, so read
the table for proportions, not absolute speed.

Run: ``python benchmarks/profile_hot_path.py [--tasks 1000 --sleeps 300 --seed 1 --top 15]``
Add ``--out prof.out`` to keep the raw profile (``python -m pstats prof.out``, snakeviz...).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
from collections.abc import Sequence

from fanout import make_workload, run_clock_sleep, workload_parser


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = workload_parser(__doc__)
    p.add_argument("--top", type=int, default=15, help="functions to list (default 15)")
    p.add_argument("--out", metavar="PATH", help="also dump the raw profile here")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Profile one fan-out (a) run and print the top functions by tottime."""
    args = parse_args(argv)
    work = make_workload(args.tasks, args.sleeps, args.seed)
    profiler = cProfile.Profile()
    profiler.enable()
    elapsed, final_ns = run_clock_sleep(work)
    profiler.disable()
    print(
        f"fanout (a) clock.sleep under cProfile: {work.wakeups:,} wakeups in {elapsed:.3f} s "
        f"(profiled), final now_ns = {final_ns} "
        f"({'exact' if final_ns == work.expected_end_ns else 'NOT EXACT'})"
    )
    if args.out:
        profiler.dump_stats(args.out)
    stats = pstats.Stats(profiler, stream=sys.stdout)
    stats.strip_dirs().sort_stats(pstats.SortKey.TIME).print_stats(args.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
