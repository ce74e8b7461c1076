"""Sweeps: plans, local and Ray backends for real, crashes as rows, Ctrl-C keeps what finished.

Every run is a real process with its own physics client. Wall-clock waits are bounded
(subprocess timeouts, polling deadlines); nothing asserts on durations.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _cli import interrupt_when, run_evclock
from rich.console import Console
from typer.testing import CliRunner

import evclock
from evclock.tools._cli import app
from evclock.tools._cli_sweep import SweepProgress
from evclock.tools._plot import HISTOGRAM_COLOR
from evclock.tools._sweep import SweepRow, parse_seeds, quantiles

ROOT = Path(__file__).resolve().parents[2]
SHUTTLE = str(ROOT / "examples" / "shuttle_scenario.py")
#: Wall seconds: a guard against hangs on a loaded machine, not a timing check; below the
#: suite's per-test pytest-timeout (300 s), so that a hang fails its test with the child's
#: output instead of ending the whole session.
TIMEOUT = 240
runner = CliRunner()
#: Tests that need an optional extra skip where it is not installed (the others still run).
needs_plot = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="needs evclock[plot] (matplotlib)"
)
needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="needs evclock[ray]")

FRAGILE = """\
import os
import signal
import time
from pathlib import Path

from evclock_sims.cartpole import CartPole


class Fragile(CartPole):
    name = "fragile"
    description = "cart-pole for 0.1 s; seed 1 kills its process, seed 2 raises"
    default_until = 1.0
    hold_time = 0.1
    marker_dir = ""

    def __init__(self, client: int, seed: int = 0) -> None:
        if seed == 1:
            os.kill(os.getpid(), signal.SIGKILL)
        if seed == 2:
            raise RuntimeError("boom at seed 2")
        if seed >= 5 and self.marker_dir:
            # Written whole, then renamed: a reader never sees the file empty.
            part = Path(self.marker_dir, f".started-{seed}.part")
            part.write_text(str(os.getpid()))
            os.replace(part, Path(self.marker_dir, f"started-{seed}"))
            time.sleep(600)  # held until the sweep is interrupted
        super().__init__(client, seed)
"""


@pytest.fixture
def fragile(tmp_path: Path) -> str:
    path = tmp_path / "fragile.py"
    path.write_text(FRAGILE)
    return str(path)


@pytest.fixture
def markers(tmp_path: Path) -> Path:
    """The folder a fragile run of seed 5 and up writes its ``started-SEED`` marker in."""
    path = tmp_path / "markers"
    path.mkdir()
    return path


def test_parse_seeds() -> None:
    assert parse_seeds("0:4") == [0, 1, 2, 3]
    assert parse_seeds("7") == [7]  # --seed 7: that seed
    assert parse_seeds("7", count=True) == [0, 1, 2, 3, 4, 5, 6]  # --seeds 7: seven seeds
    assert parse_seeds("3,1,2") == [3, 1, 2]
    assert parse_seeds("3,1,2", count=True) == [3, 1, 2]
    assert parse_seeds("2:4", count=True) == [2, 3]
    for bad in ("4:2", "a:b", "1,1", "", "-1:2"):
        with pytest.raises(evclock.InvalidArgumentError) as info:
            parse_seeds(bad)
        assert "--seeds" in str(info.value)
    with pytest.raises(evclock.InvalidArgumentError) as info:
        parse_seeds("0", count=True)
    assert str(info.value) == (
        "--seeds takes N (that many seeds, 0 to N-1), START:STOP (STOP excluded, STOP > START) "
        "or S1,S2,..., got '0'"
    )
    with pytest.raises(evclock.InvalidArgumentError) as info:
        parse_seeds("-5", option="--seed")
    assert str(info.value) == "--seed: a seed is a whole number from 0 to 4294967295, got -5"


def test_plan_is_every_combination_times_every_seed() -> None:
    specs = evclock.tools.plan("kuka", [0, 1], {"tolerance": [0.01, 0.02], "dwell": [0.3]})
    assert [(s.params["tolerance"], s.seed) for s in specs] == [
        (0.01, 0),
        (0.01, 1),
        (0.02, 0),
        (0.02, 1),
    ]
    assert (
        specs[2].command() == "evclock run kuka --seed 0 --param tolerance=0.02 --param dwell=0.3"
    )


def test_quantiles() -> None:
    assert quantiles([3.0, 1.0, 2.0]) == {"p0": 1.0, "p5": 1.1, "p50": 2.0, "p95": 2.9, "p100": 3.0}
    assert quantiles([5.0]) == dict.fromkeys(("p0", "p5", "p50", "p95", "p100"), 5.0)


BAD_SWEEPS = [
    (["--workers", "0"], "error: --workers must be at least 1, got 0"),
    (["--backend", "dask"], "error: --backend takes local or ray, got 'dask'"),
    (["--address", "1.2.3.4:6379"], "error: --address is the Ray cluster's"),
    (["--seeds", "5:5"], "error: --seeds takes N (that many seeds, 0 to N-1), START:STOP"),
    (["--seed", "-5"], "error: --seed: a seed is a whole number from 0 to 4294967295, got -5"),
    (["--seed", "1", "--seeds", "2"], "error: give --seeds N (how many seeds) or --seed S"),
    (["--param", "nope=1"], "error: scenario 'shuttle' has no parameter 'nope'"),
    (["--param", "gain=x"], "error: parameter gain takes a finite float"),
    (["--json", "/no/such/dir/x.json"], "error: --json '/no/such/dir/x.json': the directory"),
    (["--csv", "/no/such/dir/x.csv"], "error: --csv '/no/such/dir/x.csv': the directory"),
    (["--until", "-1"], "error: --until must be a positive number of seconds, got -1.0"),
    (["--until", "nan"], "error: --until must be a positive number of seconds, got nan"),
    (["--run-timeout", "nan"], "error: --run-timeout must be a positive number of wall seconds"),
    (["--best", "median:x"], "error: --best takes METRIC, min:METRIC or max:METRIC"),
    (["--plot-metric", "x"], "error: --plot-metric names what --plot draws: add --plot"),
    (["--workers", "two"], "error: Invalid value for '--workers'"),
    (["--engine", "mujoco"], "error: scenario 'shuttle' runs on pybullet only, not on mujoco"),
    (["--engine", "gazebo"], "error: Invalid value for '--engine'"),
]


@pytest.mark.pybullet
def test_bad_sweep_input_exits_2_before_any_worker_starts(tmp_path: Path) -> None:
    """Through the real command: one error line on stderr, status 2, nothing run."""
    for args, message in BAD_SWEEPS:
        proc = run_evclock("sweep", SHUTTLE, "--quiet", *args, cwd=tmp_path)
        assert proc.returncode == 2, (args, proc.stdout, proc.stderr)
        assert message in " ".join(proc.stderr.split()), (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert proc.stdout == "", proc.stdout  # no run, no table


@pytest.mark.pybullet
@needs_plot
def test_local_sweep_rows_equal_single_runs_bit_for_bit(tmp_path: Path) -> None:
    from matplotlib.image import imread

    out = tmp_path / "sweep.json"
    png = tmp_path / "sweep.png"
    result = runner.invoke(
        app,
        ["sweep", SHUTTLE, "--seeds", "0:3", "--param", "gain=3,4", "--workers", "2",
         "--json", str(out), "--plot", str(png), "--quiet"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "shuttle: 6/6 runs (6 success)" in text
    assert "success rate 100.0%" in text
    assert "final_error_m" in text
    data = json.loads(out.read_text())
    rows = data["rows"]
    assert [(r["params"]["gain"], r["seed"]) for r in rows] == [
        (g, s) for g in (3.0, 4.0) for s in range(3)
    ]
    assert data["summary"]["success_rate"] == 1.0
    assert set(data["summary"]["quantiles"]) >= {"target_m", "final_error_m", "sim_time_s"}
    # Seed 2 through the real command, in another process: the same figures, bit for bit.
    single = tmp_path / "single.json"
    proc = run_evclock(
        "run", SHUTTLE, "--seed", "2", "--param", "gain=4", "--json", str(single), "--quiet"
    )
    assert proc.returncode == 0, proc.stderr
    expected = json.loads(single.read_text())
    assert rows[5]["report"]["final_state"] == expected["final_state"]
    assert rows[5]["report"]["summary"] == expected["summary"]
    assert rows[5]["report"]["sim_time_s"] == expected["sim_time_s"]
    for row in rows[:2]:
        report = evclock.tools.run_scenario(SHUTTLE, seed=row["seed"], params={"gain": 3.0})
        assert row["report"]["final_state"] == report.final_state
    # The histogram PNG: bars drawn for every numeric field.
    image = imread(png)
    rgb = np.array([int(HISTOGRAM_COLOR[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    bars = (np.abs(image[:, :, :3] - rgb).max(axis=2) < 0.02).sum()
    assert bars > 5000


def test_a_mujoco_sweep_runs_each_seed_as_evclock_run_engine_mujoco(tmp_path: Path) -> None:
    out = tmp_path / "sweep.json"
    command = [
        "sweep", "kuka", "--engine", "mujoco", "--seeds", "0:2", "--until", "0.5",
        "--workers", "2", "--json", str(out), "--out", str(tmp_path / "out"), "--quiet",
    ]  # fmt: skip
    proc = run_evclock(*command, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 1, proc.stdout + proc.stderr  # cut short by --until: no verdict
    text = " ".join(proc.stdout.split())
    assert "kuka on mujoco: 2/2 runs (2 cut short)" in text
    assert "reproduce: evclock run kuka --seed 1 --until 0.5 --engine mujoco" in text
    data = json.loads(out.read_text())
    assert data["engine"] == data["summary"]["engine"] == "mujoco"
    assert [row["seed"] for row in data["rows"]] == [0, 1]
    for row in data["rows"]:
        assert row["report"]["engine"] == "mujoco"
        single = evclock.tools.run_scenario("kuka", seed=row["seed"], until=0.5, engine="mujoco")
        assert row["report"]["final_state"] == single.final_state  # bit for bit
        assert row["report"]["summary"] == single.to_json()["summary"]
    # The same command resumes from --out: every run is there already, on this engine.
    again = run_evclock(*command)
    assert "kuka on mujoco: 2/2 runs (2 cut short), 2 from the earlier sweep in --out" in " ".join(
        again.stdout.split()
    ), again.stdout + again.stderr


def test_an_out_directory_holding_another_engine_is_refused(tmp_path: Path) -> None:
    from evclock.tools._sweep import RUNS_FILE, RunSpec, SweepDirectory

    directory = SweepDirectory(tmp_path)
    old = SweepRow(RunSpec("kuka", 0, {}, 0.5), "cut short").to_json()
    # A row written before sweeps named their engine: PyBullet's.
    (tmp_path / RUNS_FILE).write_text(json.dumps({"scenario": "kuka", "until": 0.5, **old}) + "\n")
    assert list(directory.finished([RunSpec("kuka", 0, {}, 0.5)])) == [0]
    with pytest.raises(evclock.InvalidArgumentError) as info:
        directory.finished([RunSpec("kuka", 0, {}, 0.5, "mujoco")])
    assert str(info.value) == (
        f"--out {str(tmp_path)!r} holds a sweep on pybullet, not on mujoco; give another directory"
    )


def _rows_by_seed(path: Path) -> dict[int, dict[str, object]]:
    return {row["seed"]: row for row in json.loads(path.read_text())["rows"]}


@pytest.mark.pybullet
def test_a_crash_and_an_exception_are_failed_rows(fragile: str, tmp_path: Path) -> None:
    out = tmp_path / "sweep.json"
    result = runner.invoke(
        app, ["sweep", fragile, "--seeds", "0:4", "--workers", "2", "--json", str(out), "--quiet"]
    )
    assert result.exit_code == 4, result.output  # a run raised
    rows = _rows_by_seed(out)
    assert [rows[s]["status"] for s in range(4)] == ["success", "error", "error", "success"]
    assert rows[1]["error"] == "worker process died without a result (killed by signal 9)"
    assert rows[2]["error"] == "RuntimeError: boom at seed 2"
    text = " ".join(result.output.split())
    assert "fragile: 4/4 runs (2 error, 2 success)" in text
    assert "error seed 1: worker process died without a result (killed by signal 9)" in text
    assert f"reproduce: evclock run {fragile} --seed 2" in text


def _gone(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True
    return "State:\tZ" in status


def _kill_workers(markers: Path) -> None:
    """Kill the workers that wrote a marker (they sleep 600 s): left behind by a sweep that was
    killed, they would hold its output pipes open."""
    for marker in sorted(markers.glob("started-*")):
        with contextlib.suppress(ValueError, ProcessLookupError):
            os.kill(int(marker.read_text()), signal.SIGKILL)


@pytest.mark.pybullet
def test_ctrl_c_stops_the_workers_and_writes_what_finished(
    fragile: str, markers: Path, tmp_path: Path
) -> None:
    out = tmp_path / "sweep.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "evclock", "sweep", fragile, "--seeds", "3,4,5,6",
         "--param", f"marker_dir={markers}", "--workers", "1", "--json", str(out), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    # The sweep stops its worker (terminate, then kill after 5 s) and exits.
    stdout, stderr = interrupt_when(markers / "started-5", proc, lambda: _kill_workers(markers))
    worker = int((markers / "started-5").read_text())
    assert proc.returncode == 130, stderr
    data = json.loads(out.read_text())
    assert data["summary"]["interrupted"] is True
    assert data["summary"]["planned"] == 4
    assert [(r["seed"], r["status"]) for r in data["rows"]] == [(3, "success"), (4, "success")]
    assert "fragile: 2/4 runs (2 success) interrupted" in " ".join(stdout.split())
    deadline = time.monotonic() + 30
    while not _gone(worker) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _gone(worker)


def _ray_sweep(*args: str, out: Path) -> subprocess.CompletedProcess[str]:
    """``evclock sweep <args>`` on a local Ray cluster of 2 workers, rows to ``out``."""
    args = (*args, "--backend", "ray", "--workers", "2", "--json", str(out), "--quiet")
    return run_evclock("sweep", *args, env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})


@pytest.mark.pybullet
@needs_ray
def test_ray_backend_runs_for_real(fragile: str, tmp_path: Path) -> None:
    out = tmp_path / "ray.json"
    proc = _ray_sweep(fragile, "--seeds", "0:3", out=out)
    assert proc.returncode == 4, proc.stdout + proc.stderr
    rows = _rows_by_seed(out)
    assert [rows[s]["status"] for s in range(3)] == ["success", "error", "error"]
    assert str(rows[1]["error"]).startswith("ray task failed: ")
    assert rows[2]["error"] == "RuntimeError: boom at seed 2"
    report = evclock.tools.run_scenario(fragile, seed=0)
    assert rows[0]["report"]["final_state"] == report.final_state  # type: ignore[index]


@needs_ray
def test_ray_backend_runs_mujoco_runs_for_real(tmp_path: Path) -> None:
    out = tmp_path / "ray.json"
    proc = _ray_sweep("kuka", "--engine", "mujoco", "--seeds", "0:2", "--until", "0.5", out=out)
    assert proc.returncode == 1, proc.stdout + proc.stderr  # cut short by --until: no verdict
    data = json.loads(out.read_text())
    assert data["engine"] == "mujoco"
    assert sorted(_rows_by_seed(out)) == [0, 1]
    for seed, row in sorted(_rows_by_seed(out).items()):
        single = evclock.tools.run_scenario("kuka", seed=seed, until=0.5, engine="mujoco")
        assert row["report"]["engine"] == "mujoco"  # type: ignore[index]
        assert row["report"]["final_state"] == single.final_state  # type: ignore[index]


@pytest.mark.pybullet
def test_a_run_over_its_wall_timeout_is_stopped_and_failed(
    fragile: str, markers: Path, tmp_path: Path
) -> None:
    out = tmp_path / "sweep.json"
    # Seed 0 finishes well inside 10 s even on a loaded machine (start-up and PyBullet
    # included); seed 5 sleeps 600 s.
    result = runner.invoke(
        app,
        ["sweep", fragile, "--seeds", "0,5", "--param", f"marker_dir={markers}",
         "--run-timeout", "10", "--workers", "2", "--json", str(out), "--quiet"],
    )  # fmt: skip
    assert result.exit_code == 4, result.output
    rows = _rows_by_seed(out)
    assert rows[0]["status"] == "success"
    assert rows[5]["error"] == "timed out after 10 s of wall time (--run-timeout); stopped"
    worker = int((markers / "started-5").read_text())
    deadline = time.monotonic() + 30
    while not _gone(worker) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _gone(worker)
    bad = runner.invoke(app, ["sweep", fragile, "--run-timeout", "0", "--quiet"])
    assert bad.exit_code == 2
    assert "--run-timeout must be a positive number of wall seconds, got 0.0" in bad.output


def test_sweep_progress_counts_done_failed_and_aggregate_rtf() -> None:
    console = Console(file=io.StringIO(), width=120)
    display = SweepProgress(console, total=3, quiet=False)
    spec = evclock.tools.RunSpec("shuttle", 0, {})
    with display.progress:
        display.row_done(SweepRow(spec, "success", report={"sim_time_s": 2.0}))
        display.row_done(SweepRow(spec, "error", error="boom"))
    (task,) = display.progress.tasks
    assert (task.completed, task.total) == (2, 3)
    assert task.fields["failed"] == 1
    assert float(task.fields["rtf"]) > 0  # 2 sim seconds over the elapsed wall time
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert "2/3" in text
    assert "failed 1" in text
    assert "ETA" in text
