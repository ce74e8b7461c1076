"""Sweep a scenario, record two runs, find where they diverge, plot: the Python API of
``evclock sweep``, ``evclock run --record``, ``evclock trace diff`` and ``evclock plot``.

Usage: python examples/sweep_record_plot.py [OUTPUT_DIR]   (default: a temporary directory)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import evclock

SHUTTLE = str(Path(__file__).resolve().parent / "shuttle_scenario.py")


def main(out: Path) -> None:
    # 1. Sweep: 4 seeds x 2 gains, 2 processes at a time; rows come back in plan order.
    result = evclock.tools.sweep(
        evclock.tools.plan(SHUTTLE, seeds=range(4), params={"gain": [2.0, 4.0]}), workers=2
    )
    summary = result.summary()
    print(f"sweep: {summary['done']} runs, success rate {summary['success_rate']:.0%}")
    arrival = summary["quantiles"]["arrival_s"]
    print(f"arrival_s median {arrival['p50']:.3f} s, max {arrival['p100']:.3f} s")
    evclock.tools.plot_sweep(result, out / "sweep.png")

    # 2. Record the same seed twice at different speeds, then with another parameter.
    for name, kwargs in (("a", {}), ("b", {"rtf": 10.0}), ("c", {"params": {"max_speed": 1.0}})):
        evclock.tools.run_scenario(SHUTTLE, seed=1, record=out / f"{name}.mcap", **kwargs)
    a, b, c = (evclock.tools.read_trace(out / f"{name}.mcap") for name in "abc")
    print("a vs b:", evclock.tools.first_divergence(a, b) or "identical")
    divergence = evclock.tools.first_divergence(a, c)
    assert divergence is not None
    print("a vs c:", divergence.describe().split(":")[0])

    # 3. Plot run a: lateness per loop and achieved rtf over sim time.
    evclock.tools.plot_run(a, out / "run.png")
    print("plots:", ", ".join(sorted(p.name for p in out.glob("*.png"))))


if __name__ == "__main__":
    if len(sys.argv) > 1:
        main(Path(sys.argv[1]))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            main(Path(tmp))
