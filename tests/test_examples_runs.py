"""The scenario, sweep and recording examples run as documented and print what they claim."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT = 300  # wall seconds: a guard against hangs on a loaded machine, not a timing check


def run_example(*args: str) -> list[str]:
    proc = subprocess.run(
        [sys.executable, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return [line for line in proc.stdout.splitlines() if not line.startswith("pybullet build")]


@pytest.mark.pybullet
def test_shuttle_scenario_runs_from_python() -> None:
    assert run_example("examples/shuttle_scenario.py") == [
        "shuttle seed 3: success",
        "target -0.360 m, error 0.0017 m",
    ]


@pytest.mark.pybullet
@pytest.mark.skipif(
    any(importlib.util.find_spec(name) is None for name in ("mcap", "matplotlib")),
    reason="needs evclock[record] (mcap) and evclock[plot] (matplotlib)",
)
def test_sweep_record_plot_example(tmp_path: Path) -> None:
    lines = run_example("examples/sweep_record_plot.py", str(tmp_path))
    assert lines[0] == "sweep: 8 runs, success rate 100%"
    assert lines[1].startswith("arrival_s median ")
    assert lines[2] == "a vs b: identical"
    assert (
        lines[3] == "a vs c: first divergence at sim time 0.050000 s on /evclock/state (message 8)"
    )
    assert lines[4] == "plots: run.png, sweep.png"
    assert {p.name for p in tmp_path.iterdir()} == {
        "a.mcap",
        "b.mcap",
        "c.mcap",
        "run.png",
        "sweep.png",
    }
