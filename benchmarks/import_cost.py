"""What ``import evclock`` costs beyond ``import asyncio``, which it needs anyway.

Each import runs in a fresh interpreter with ``-X importtime`` (bytecode caching on, after
one warm-up run that writes the caches); the figure is the ``evclock`` (or ``asyncio``) line's
cumulative time, the minimum over ``--runs`` runs, the two interleaved so that both see the
same machine. It also lists the modules ``import evclock`` loads beyond asyncio's.

    python benchmarks/import_cost.py --runs 10
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys


def cumulative_us(module: str) -> int:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    out = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", f"import {module}"],
        capture_output=True,
        text=True,
        check=True,
        env=env,
        timeout=60,
    ).stderr
    for line in out.splitlines():
        fields = [field.strip() for field in line.split("|")]
        if len(fields) == 3 and fields[2] == module:
            return int(fields[1])
    raise RuntimeError(f"no importtime line for {module}")


def extra_modules() -> list[str]:
    code = (
        "import sys, asyncio; before = set(sys.modules); import evclock; "
        "print('\\n'.join(sorted(set(sys.modules) - before)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    return out.stdout.split()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="runs of each (default 10)")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    cumulative_us("asyncio"), cumulative_us("evclock")  # warm-up: bytecode caches
    best = {"asyncio": float("inf"), "evclock": float("inf")}
    for _ in range(args.runs):
        for module in best:
            best[module] = min(best[module], cumulative_us(module))
    extra = extra_modules()
    own = [m for m in extra if m == "evclock" or m.startswith("evclock.")]
    other = [m for m in extra if m not in own]
    print(f"import asyncio: {best['asyncio'] / 1000:.1f} ms (minimum of {args.runs})")
    print(f"import evclock: {best['evclock'] / 1000:.1f} ms (asyncio included)")
    print(f"evclock beyond asyncio: {(best['evclock'] - best['asyncio']) / 1000:.1f} ms")
    print(f"modules beyond asyncio's: {len(extra)} ({len(own)} of evclock)")
    print(f"  others: {', '.join(other)}")


if __name__ == "__main__":
    main()
