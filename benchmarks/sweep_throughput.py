"""Sweep throughput: runs per wall second of ``evclock sweep`` with 1 and 2 workers, against
the same runs done one after the other in this process (the baseline, measured in the same
invocation).

Usage: python benchmarks/sweep_throughput.py [--scenario cartpole] [--runs 8] [--until S]
       [--json out.json]

- sequential: ``run_scenario(scenario, seed=k)`` for k in 0..runs-1, in this process (no
  process start-up at all: the floor a sweep's per-run process has to pay for);
- local, 1 worker / 2 workers: ``sweep(plan(...), workers=N)``, a fresh process per run.

Reported: runs per wall second of each, and each sweep's ratio to sequential. The ratio of
the 1-worker sweep measures the per-run process cost; the 2-worker one is bounded by the
cores the machine really has free (2 on CI, shared). Results are also checked: every row of
each sweep must equal the sequential run of its seed bit for bit.
"""

from __future__ import annotations

import argparse
import json
import time

import evclock


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="cartpole")
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--until", type=float, default=None, help="sim seconds per run")
    parser.add_argument("--json", default=None, help="also write the figures here")
    args = parser.parse_args()
    seeds = list(range(args.runs))

    wall0 = time.perf_counter()
    sequential = [
        evclock.tools.run_scenario(args.scenario, seed=seed, until=args.until) for seed in seeds
    ]
    figures = {"sequential": args.runs / (time.perf_counter() - wall0)}
    specs = evclock.tools.plan(args.scenario, seeds, until=args.until)
    for workers in (1, 2):
        wall0 = time.perf_counter()
        result = evclock.tools.sweep(specs, workers=workers)
        figures[f"local x{workers}"] = args.runs / (time.perf_counter() - wall0)
        for row, single in zip(result.rows, sequential, strict=True):
            assert row.report is not None, row.error
            assert row.report["final_state"] == single.final_state, f"seed {row.spec.seed}"
    sim_s = sum(r.sim_time_s for r in sequential) / args.runs
    print(f"{args.scenario}: {args.runs} runs of {sim_s:.2f} sim s each")
    base = figures["sequential"]
    for name, rate in figures.items():
        print(f"{name:>12}: {rate:7.2f} runs/s   ratio to sequential {rate / base:5.2f}")
    if args.json:
        with open(args.json, "w") as out:
            json.dump({"scenario": args.scenario, "runs": args.runs, "runs_per_s": figures}, out)


if __name__ == "__main__":
    main()
