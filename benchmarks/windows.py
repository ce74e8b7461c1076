"""Is a variant's cost per wake-up steady over a run? Instructions per wake-up by window.

Runs fan-out variants of ``instructions.py`` (same plan, same process, same callgrind client
requests around each run) at several sleep counts and prints, for each window between two
consecutive counts, (instructions at the larger - at the smaller) / (wake-ups between):
a steady variant costs the same in every window.

Usage: ``python benchmarks/windows.py [--tasks 1000] [--counts 0 15 30 60] [--workload fanout]``
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from collections.abc import Sequence

import instructions as ins

VARIANTS = ("asyncio.sleep(0), stock loop", "least future-based sleep", "clock.sleep")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000)
    p.add_argument("--counts", type=int, nargs="+", default=[0, 15, 30, 60])
    p.add_argument("--workload", choices=["fanout", "coincident"], default="fanout")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    counts = sorted(args.counts)
    if len(counts) < 2:
        raise SystemExit("--counts needs at least two counts")
    windows = list(itertools.pairwise(counts))
    with tempfile.TemporaryDirectory() as marks_dir:
        marks = ins.build_marks(marks_dir)
        print(
            f"{args.workload}: {args.tasks:,} tasks; instructions per wake-up by window of sleeps"
        )
        print(f"  {'variant':<32}" + "".join(f"{f'{a}-{b}':>10}" for a, b in windows))
        for variant in VARIANTS:
            job = ins.Job(args.workload, variant, args.tasks, tuple(counts), args.seed)  # type: ignore[arg-type]
            totals, _ = ins.callgrind(job, marks)
            cells = [
                (totals[i + 1] - totals[i]) / (args.tasks * (b - a))
                for i, (a, b) in enumerate(windows)
            ]
            print(f"  {variant:<32}" + "".join(f"{c:>10,.0f}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
