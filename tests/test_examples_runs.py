"""The scenario, sweep and recording examples run as documented and print what they claim."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from _examples import output_lines
from _examples import run_example as examples_run


def run_example(name: str, *args: str) -> list[str]:
    return output_lines(examples_run(name, *args))


@pytest.mark.pybullet
def test_shuttle_scenario_runs_from_python() -> None:
    assert run_example("shuttle_scenario.py") == [
        "shuttle seed 3: success",
        "target -0.360 m, error 0.0017 m",
    ]


@pytest.mark.pybullet
@pytest.mark.skipif(
    any(importlib.util.find_spec(name) is None for name in ("mcap", "matplotlib")),
    reason="needs evclock[record] (mcap) and evclock[plot] (matplotlib)",
)
def test_sweep_record_plot_example(tmp_path: Path) -> None:
    lines = run_example("sweep_record_plot.py", str(tmp_path))
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
