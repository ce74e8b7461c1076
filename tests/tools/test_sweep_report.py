"""Sweeps a user can read: --seeds N vs --seed S, the per-configuration summary (count, success
rate, mean, std, 95 % interval), the best configuration, CSV and JSON-lines exports, the
per-parameter plot of a metric, and resume in the same output directory - through the real
command, in a subprocess."""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _cli import interrupt_when, run_evclock
from rich.console import Console

import evclock
from evclock.tools._cli_sweep import METRIC_COLOR, SweepProgress
from evclock.tools._sweep import SweepResult, SweepRow, describe, t975

ROOT = Path(__file__).resolve().parents[2]
SHUTTLE = str(ROOT / "examples" / "shuttle_scenario.py")
TIMEOUT = 240  # wall seconds: a guard against hangs, not a timing check
needs_plot = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="needs evclock[plot] (matplotlib)"
)

#: A scenario whose run can be held (seed >= 5 waits for a file) and whose controllers raise
#: at seed 7: every run appends its seed to ``log`` in ``marker_dir`` first.
STEPPED = """\
import os
import time
from pathlib import Path

from evclock_sims.cartpole import CartPole


class Stepped(CartPole):
    name = "stepped"
    description = "cart-pole for 0.1 s; seed 5 and up wait for a file; seed 7 raises"
    default_until = 1.0
    hold_time = 0.1
    marker_dir = ""

    def __init__(self, client: int, seed: int = 0) -> None:
        marker = Path(self.marker_dir)
        with open(marker / "log", "a") as log:
            log.write(f"{seed}\\n")
        if seed >= 5 and not (marker / "go").exists():
            part = marker / f".held-{seed}.part"
            part.write_text(str(os.getpid()))
            os.replace(part, marker / f"held-{seed}")
            time.sleep(600)  # held until the sweep is interrupted
        super().__init__(client, seed)

    async def _mission(self, clock):
        if self.seed == 7:
            await clock.sleep(0.05)
            raise ValueError(f"controller failed at seed {self.seed}")
        await super()._mission(clock)
"""


def test_describe_gives_the_student_t_interval_of_the_mean() -> None:
    d = describe([1.0, 2.0, 3.0])
    assert (d["n"], d["mean"], d["std"], d["min"], d["max"]) == (3, 2.0, 1.0, 1.0, 3.0)
    half = 4.303 * 1.0 / math.sqrt(3)  # t(0.975, 2 dof) * s / sqrt(n)
    assert d["ci95"] == [2.0 - half, 2.0 + half]
    single = describe([5.0])
    assert (single["std"], single["ci95"]) == (None, None)
    assert t975(30) == 2.042
    assert t975(1000) == 1.959964
    assert 2.021 > t975(50) > 2.000  # between the tabulated 40 and 60


def test_groups_and_best_on_known_rows() -> None:
    def row(gain: float, seed: int, status: str, time_s: float | None) -> SweepRow:
        summary = {} if time_s is None else {"mission_time_s": time_s}
        report = {"summary": summary, "sim_time_s": 1.0, "verdict": status}
        return SweepRow(evclock.tools.RunSpec("x", seed, {"gain": gain}), status, report=report)

    rows = [
        row(1.0, 0, "success", 2.0),
        row(1.0, 1, "failed", 4.0),
        row(2.0, 0, "success", 1.0),
        row(2.0, 1, "success", 1.0),
        row(3.0, 0, "error", None),
    ]
    result = SweepResult("x", "x", 5, rows, interrupted=False, wall_time_s=1.0, swept=("gain",))
    groups = result.groups(["mission_time_s"])
    assert [g["params"] for g in groups] == [{"gain": 1.0}, {"gain": 2.0}, {"gain": 3.0}]
    assert [g["runs"] for g in groups] == [2, 2, 1]
    assert [g["success_rate"] for g in groups] == [0.5, 1.0, 0.0]
    assert groups[0]["metrics"]["mission_time_s"]["mean"] == 3.0
    assert groups[1]["metrics"]["mission_time_s"]["std"] == 0.0
    assert groups[2]["metrics"] == {}
    assert result.best("mission_time_s")["params"] == {"gain": 2.0}  # type: ignore[index]
    assert result.best("mission_time_s", maximize=True)["params"] == {"gain": 1.0}  # type: ignore[index]
    assert result.best("nope") is None
    lines = list(csv.reader(io.StringIO(result.to_csv())))
    assert lines[0] == ["seed", "gain", "status", "error", "mission_time_s", "sim_time_s"]
    assert lines[1] == ["0", "1.0", "success", "", "2.0", "1.0"]
    assert lines[5] == ["0", "3.0", "error", "", "", "1.0"]


@pytest.mark.pybullet
@needs_plot
def test_sweep_summary_best_exports_and_plot(tmp_path: Path) -> None:
    from matplotlib.image import imread

    png = tmp_path / "gain.png"
    proc = run_evclock(
        "sweep", SHUTTLE, "--seeds", "3", "--param", "gain=3,4", "--workers", "2",
        "--best", "mission_time_s", "--csv", "runs.csv", "--jsonl", "runs.jsonl",
        "--json", "sweep.json", "--plot", str(png), "--plot-metric", "mission_time_s",
        "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "pybullet build time" not in proc.stdout + proc.stderr  # no library banner
    text = " ".join(proc.stdout.split())
    assert "shuttle: 6/6 runs (6 success)" in text  # --seeds 3: seeds 0, 1, 2 per gain
    data = json.loads((tmp_path / "sweep.json").read_text())
    assert [(r["params"]["gain"], r["seed"]) for r in data["rows"]] == [
        (g, s) for g in (3.0, 4.0) for s in range(3)
    ]
    groups = data["summary"]["groups"]
    assert [g["params"] for g in groups] == [{"gain": 3.0}, {"gain": 4.0}]
    assert [(g["runs"], g["success_rate"]) for g in groups] == [(3, 1.0), (3, 1.0)]
    for group in groups:
        times = [
            r["report"]["summary"]["mission_time_s"]
            for r in data["rows"]
            if r["params"] == group["params"]
        ]
        assert group["metrics"]["mission_time_s"] == describe(times)
    faster = min(groups, key=lambda g: g["metrics"]["mission_time_s"]["mean"])
    assert faster["params"] == {"gain": 4.0}
    d = faster["metrics"]["mission_time_s"]
    assert (
        f"best by lowest mean mission_time_s: gain=4.0 (mean {d['mean']:.4g}, 95% interval "
        f"{d['ci95'][0]:.4g} .. {d['ci95'][1]:.4g}, 3 runs, success 100%)" in text
    )
    assert "shuttle: metrics by gain" in text
    assert f"{d['mean']:.3g} ± {(d['ci95'][1] - d['ci95'][0]) / 2:.2g}" in text
    # The exports: a CSV line and a JSON line per run, the same figures.
    lines = list(csv.DictReader((tmp_path / "runs.csv").read_text().splitlines()))
    assert [(float(r["gain"]), int(r["seed"]), r["status"]) for r in lines] == [
        (g, s, "success") for g in (3.0, 4.0) for s in range(3)
    ]
    records = [json.loads(x) for x in (tmp_path / "runs.jsonl").read_text().splitlines()]
    assert [r["report"]["final_state"] for r in records] == [
        r["report"]["final_state"] for r in data["rows"]
    ]
    assert [float(r["mission_time_s"]) for r in lines] == [
        r["report"]["summary"]["mission_time_s"] for r in records
    ]
    # The per-parameter plot: the means and their intervals drawn in METRIC_COLOR.
    image = imread(png)
    rgb = np.array([int(METRIC_COLOR[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    assert (np.abs(image[:, :, :3] - rgb).max(axis=2) < 0.02).sum() > 200


@pytest.mark.pybullet
def test_an_unknown_plot_metric_names_the_reported_ones(tmp_path: Path) -> None:
    proc = run_evclock(
        "sweep", SHUTTLE, "--seed", "4", "--plot", "x.png", "--plot-metric", "speed",
        "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "error: --plot-metric 'speed': no run reported it; the numeric fields: " in proc.stderr
    assert "mission_time_s" in proc.stderr
    assert "shuttle: 1/1 runs (1 success)" in proc.stdout  # --seed 4: that one seed


@pytest.mark.pybullet
def test_an_interrupted_sweep_resumes_in_the_same_directory(tmp_path: Path) -> None:
    scenario = tmp_path / "stepped.py"
    scenario.write_text(STEPPED)
    markers = tmp_path / "markers"
    markers.mkdir()
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "evclock", "sweep", str(scenario), "--seed", "3,4,5,6,7",
        "--param", f"marker_dir={markers}", "--out", str(out), "--quiet",
    ]  # fmt: skip
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = interrupt_when(markers / "held-5", proc)  # seeds 3 and 4 done, 5 held
    assert proc.returncode == 130, stderr
    assert "stepped: 2/5 runs (2 success) interrupted" in " ".join(stdout.split())
    done = [json.loads(line) for line in (out / "runs.jsonl").read_text().splitlines()]
    assert [(r["seed"], r["status"]) for r in done] == [(3, "success"), (4, "success")]
    # Again, with the same directory: only seeds 5, 6 and 7 run.
    (markers / "go").write_text("")
    again = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    assert again.returncode == 4, again.stdout + again.stderr  # seed 7's controllers raise
    assert (markers / "log").read_text().split() == ["3", "4", "5", "5", "6", "7"]
    text = " ".join(again.stdout.split())
    assert "stepped: 5/5 runs (1 error, 4 success), 2 from the earlier sweep in --out" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["summary"]["resumed"] == 2
    rows = {row["seed"]: row for row in summary["rows"]}
    assert sorted(rows) == [3, 4, 5, 6, 7]
    # The row names the root exception and where it came from, not the TaskGroup's group.
    assert rows[7]["error"] == "ValueError: controller failed at seed 7"
    assert "Stepped._mission" in rows[7]["report"]["error_where"]
    assert "error seed 7: ValueError: controller failed at seed 7" in text
    assert "ExceptionGroup" not in again.stdout + again.stderr
    lines = (out / "runs.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in lines[1:]] == ["3", "4", "5", "6", "7"]
    # A third time: nothing left to run.
    third = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    assert third.returncode == 4
    assert (markers / "log").read_text().split() == ["3", "4", "5", "5", "6", "7"]


@pytest.mark.pybullet
def test_a_directory_of_another_sweep_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs.jsonl").write_text('{"scenario": "kuka", "seed": 0, "params": {}, '
                                    '"until": null, "status": "success", "report": null, '
                                    '"error": null}\n')  # fmt: skip
    proc = run_evclock("sweep", SHUTTLE, "--seeds", "2", "--out", str(out), cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f"error: --out {str(out)!r} holds a sweep of 'kuka', not {SHUTTLE!r}; give another "
        "directory"
    )


def test_sweep_progress_resumes_its_count_and_shows_an_eta() -> None:
    console = Console(file=io.StringIO(), width=120)
    display = SweepProgress(console, total=5, quiet=False, done=2)
    spec = evclock.tools.RunSpec("shuttle", 0, {})
    with display.progress:
        display.row_done(SweepRow(spec, "success", report={"sim_time_s": 2.0}))
    (task,) = display.progress.tasks
    assert (task.completed, task.total) == (3, 5)
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert "3/5" in text
    assert "ETA" in text


@pytest.mark.pybullet
def test_a_sweep_with_a_failed_criterion_is_1(tmp_path: Path) -> None:
    proc = run_evclock(
        "sweep", "cartpole", "--seeds", "2", "--param", "fail_angle=0.01,0.5",
        "--until", "0.5", "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stdout + proc.stderr
    text = " ".join(proc.stdout.split())
    assert "cartpole: 4/4 runs (2 cut short, 2 failed)" in text
    assert "failed seed 0: failed" in text
    assert proc.stderr == ""


def test_groups_by_one_parameter_pool_the_others() -> None:
    def row(gain: float, tol: float, seed: int, time_s: float) -> SweepRow:
        report = {"summary": {"mission_time_s": time_s}, "verdict": "success"}
        spec = evclock.tools.RunSpec("x", seed, {"gain": gain, "tol": tol})
        return SweepRow(spec, "success", report=report)

    rows = [row(g, t, 0, g * 10 + t) for g in (1.0, 2.0) for t in (0.1, 0.2)]
    result = SweepResult("x", "x", 4, rows, False, 1.0, swept=("gain", "tol"))
    by_gain = result.groups(["mission_time_s"], by=["gain"])
    assert [(g["params"], g["runs"]) for g in by_gain] == [({"gain": 1.0}, 2), ({"gain": 2.0}, 2)]
    assert by_gain[0]["metrics"]["mission_time_s"] == describe([10.1, 10.2])
    summary = result.summary()
    assert set(summary["by_parameter"]) == {"gain", "tol"}
    assert [g["params"] for g in summary["by_parameter"]["tol"]] == [{"tol": 0.1}, {"tol": 0.2}]
    assert len(summary["groups"]) == 4
