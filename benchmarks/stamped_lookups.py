"""Time-indexed lookups and synchroniser throughput, against baselines measured in the same run.

Usage: python benchmarks/stamped_lookups.py [--samples 10000] [--lookups 100000] [--repeat 5]

1. ``TimeBuffer.at_many``: ``--lookups`` random times (seeded) over a buffer of ``--samples``
   stamped 3-vectors (linear) and quaternions (slerp), one vectorised call each. Baselines:
   the same lookups one by one with ``TimeBuffer.at`` and with a plain-Python ``bisect``
   interpolation over lists (what hand-written code does). Results are checked equal
   (1e-9) before timing is reported.
2. Synchronisers: a 100 Hz and a 30 Hz stream with jittered stamps (seeded) through the C++
   ApproximateTime policy and through ROS Python's slop matching; messages per wall second.

Timing: ``time.perf_counter()``; each variant runs ``--repeat`` times, interleaved round by
round, and the best run is reported (the one least disturbed by the rest of the machine).
Target (soft, printed PASS/MISS): 100,000 linear lookups in at most 20 ms.
"""

from __future__ import annotations

import argparse
import bisect
import gc
import random
import time
from collections.abc import Callable

import numpy as np

import evclock
from evclock import Time
from evclock.data import TimeBuffer
from evclock.data._policies import ApproximatePolicy, SlopPolicy


def best_of(repeat: int, variants: dict[str, Callable[[], object]]) -> dict[str, float]:
    """Best wall time (seconds) of each variant, the variants interleaved round by round."""
    best = dict.fromkeys(variants, float("inf"))
    for _ in range(repeat):
        for name, run in variants.items():
            gc.collect()
            began = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - began)
    return best


def bisect_linear(stamps: list[int], values: list[list[float]], t: int) -> list[float]:
    """The hand-written baseline: bisect, then interpolate component by component."""
    i = min(max(bisect.bisect_right(stamps, t) - 1, 0), len(stamps) - 2)
    w = (t - stamps[i]) / (stamps[i + 1] - stamps[i])
    return [a + w * (b - a) for a, b in zip(values[i], values[i + 1], strict=True)]


def lookups(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(args.seed)
    stamps = np.cumsum(rng.integers(5_000_000, 15_000_000, args.samples)).astype(np.int64)
    vectors = rng.normal(size=(args.samples, 3))
    angles = np.cumsum(rng.normal(0, 0.01, args.samples))
    quats = np.stack(
        [np.zeros_like(angles), np.zeros_like(angles), np.sin(angles / 2), np.cos(angles / 2)], 1
    )
    linear = TimeBuffer(args.samples)
    slerp = TimeBuffer(args.samples, interpolation="slerp")
    for ns, v, q in zip(stamps.tolist(), vectors, quats, strict=True):
        linear.add(Time(0, ns), v)
        slerp.add(Time(0, ns), q)
    queries = rng.integers(int(stamps[0]), int(stamps[-1]), args.lookups).astype(np.int64)
    stamp_list, value_list = stamps.tolist(), vectors.tolist()
    query_list = queries.tolist()
    one_by_one = [Time(0, t) for t in query_list[: args.lookups // 10]]

    expected = np.array([bisect_linear(stamp_list, value_list, t) for t in query_list])
    np.testing.assert_allclose(linear.at_many(queries), expected, atol=1e-9)
    times = best_of(
        args.repeat,
        {
            "at_many linear": lambda: linear.at_many(queries),
            "at_many slerp": lambda: slerp.at_many(queries),
            "bisect loop (baseline)": lambda: [
                bisect_linear(stamp_list, value_list, t) for t in query_list
            ],
            "at() one by one, 1/10": lambda: [linear.at(t) for t in one_by_one],
        },
    )
    times["at() one by one, 1/10"] *= 10  # scaled to the full count
    base = times["bisect loop (baseline)"]
    print(f"{args.lookups:,} lookups over {args.samples:,} samples (best of {args.repeat}):")
    print(f"{'variant':<24} {'ms':>9} {'lookups/s':>14} {'vs bisect loop':>15}")
    for name, seconds in times.items():
        print(
            f"{name:<24} {seconds * 1e3:9.2f} {args.lookups / seconds:14,.0f} "
            f"{base / seconds:14.1f}x"
        )
    verdict = "PASS" if times["at_many linear"] <= 0.020 else "MISS"
    print(f"{verdict}: at_many linear {times['at_many linear'] * 1e3:.2f} ms (goal <= 20 ms)")


def synchronisers(args: argparse.Namespace) -> None:
    rng = random.Random(args.seed)
    count = args.messages
    fast = [(0, round(k * 10_000_000 + rng.uniform(-1e6, 1e6))) for k in range(count)]
    slow = [(1, round(k * 33_333_333 + rng.uniform(-2e6, 2e6))) for k in range(count * 3 // 10)]
    arrivals = sorted(fast + slow, key=lambda m: m[1])
    groups: dict[str, int] = {}

    def run(policy: ApproximatePolicy | SlopPolicy, name: str) -> None:
        made = 0
        for stream, stamp in arrivals:
            made += len(policy.add(stream, stamp, stamp))
        groups[name] = made

    times = best_of(
        args.repeat,
        {
            "ApproximateTime (C++)": lambda: run(ApproximatePolicy(2, 50), "ApproximateTime (C++)"),
            "slop (ROS Python)": lambda: run(SlopPolicy(2, 50, 5_000_000), "slop (ROS Python)"),
        },
    )
    print(f"\n{len(arrivals):,} messages, 100 Hz + 30 Hz, jittered (best of {args.repeat}):")
    print(f"{'policy':<24} {'groups':>7} {'messages/s':>14}")
    for name, seconds in times.items():
        print(f"{name:<24} {groups[name]:7,} {len(arrivals) / seconds:14,.0f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--lookups", type=int, default=100_000)
    parser.add_argument("--messages", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print(f"evclock {evclock.__version__}, numpy {np.__version__}")
    lookups(args)
    synchronisers(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
