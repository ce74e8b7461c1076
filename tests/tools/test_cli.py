"""The `evclock` command and scenario runs: reports, errors, determinism across rtf."""

from __future__ import annotations

import io
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

import evclock
from evclock.tools._cli import app, parse_rtf, progress_bar, run_scenario

# Every scenario is a PyBullet world.
pytestmark = pytest.mark.pybullet

runner = CliRunner()


def test_list_shows_every_scenario() -> None:
    result = runner.invoke(app, ["list"])
    assert result.exit_code == 0
    for name in ("kuka", "husky", "cartpole"):
        assert name in result.output


def test_run_kuka_reports_loops_and_succeeds(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    result = runner.invoke(app, ["run", "kuka", "--quiet", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "kuka (seed 0): SUCCESS" in result.output
    assert "joint_control" in result.output
    assert "planner" in result.output
    report = json.loads(out.read_text())
    assert report["success"] is True
    assert report["mode"] == "sim"
    loops = {loop["name"]: loop for loop in report["loops"]}
    assert set(loops) == {"joint_control", "planner"}
    sim_s = report["sim_time_s"]
    # Rates on sim time tick exactly as often as the sim time says (tick 0 is at start).
    assert loops["planner"]["stats"]["ticks"] == int(sim_s * 10) + 1
    assert loops["joint_control"]["stats"]["missed"] == 0


def test_until_shorter_than_the_mission_says_the_run_was_cut_short(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    result = runner.invoke(app, ["run", "cartpole", "--until", "1", "--quiet", "--json", str(out)])
    assert result.exit_code == 3
    text = " ".join(result.output.split())
    assert "cartpole (seed 0): CUT SHORT at --until 1 s, before the mission ended" in text
    assert "FAILED" not in text
    assert "nan" not in text
    assert "│ mission_time_s │ - │" in text
    report = json.loads(out.read_text())
    assert report["verdict"] == "cut short"
    assert report["finished"] is False
    assert report["summary"]["mission_time_s"] is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["run", "nope"],
            "error: unknown scenario 'nope'; registered names: cartpole, fusion, husky, kuka",
        ),
        (["run", "kuka", "--rtf", "0"], "error: --rtf takes 'max' (as fast as possible) or a"),
        (["run", "kuka", "--rtf", "fast"], "error: --rtf takes 'max' (as fast as possible) or a"),
        (["run", "kuka", "--wall", "--rtf", "2"], "error: --wall runs in real time: drop --rtf"),
        (["run", "kuka", "--until", "-1"], "error: --until must be a positive number of seconds"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(args: list[str], message: str) -> None:
    result = runner.invoke(app, [*args, "--quiet"])
    assert result.exit_code == 2
    assert message in " ".join(result.output.split())


def test_parse_rtf() -> None:
    assert parse_rtf("max") is None
    assert parse_rtf("MAX") is None
    assert parse_rtf("1") == 1.0
    assert parse_rtf("2.5") == 2.5


def test_wall_mode_runs_the_same_controllers_on_wall_time() -> None:
    report = run_scenario("cartpole", wall=True, until=0.3)
    assert report.mode == "wall"
    names = [loop.name for loop in report.loops]
    assert names[0] == "world (physics)"
    assert "balance" in names
    balance = next(loop for loop in report.loops if loop.name == "balance")
    assert balance.stats["ticks"] >= 2  # it ran on the wall clock
    assert not report.finished


@pytest.mark.parametrize(
    ("name", "fast_rtf"), [("kuka", 40.0), ("husky", 60.0), ("cartpole", 150.0)]
)
def test_same_seed_same_final_state_whatever_the_rtf(name: str, fast_rtf: float) -> None:
    flat_out = run_scenario(name, seed=3)
    paced = run_scenario(name, seed=3, rtf=fast_rtf)
    assert flat_out.success
    assert paced.success
    assert flat_out.final_state == paced.final_state  # bit for bit
    assert flat_out.sim_time_s == paced.sim_time_s
    other = run_scenario(name, seed=4)
    assert other.final_state != flat_out.final_state


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.output == f"evclock {evclock.__version__}\n"


@pytest.mark.parametrize("option", ["--json", "--record"])
def test_unwritable_output_is_refused_before_the_run(tmp_path: Path, option: str) -> None:
    missing_dir = tmp_path / "no" / "such" / "dir" / "out.file"
    result = runner.invoke(app, ["run", "cartpole", option, str(missing_dir)])
    assert result.exit_code == 2
    text = " ".join(result.output.split())
    assert f"error: {option} '{missing_dir}': the directory '{missing_dir.parent}' does not" in text
    assert "rate loops" not in text  # nothing ran
    result = runner.invoke(app, ["run", "cartpole", option, str(tmp_path)])
    assert result.exit_code == 2
    assert "is a directory; give a file name" in " ".join(result.output.split())
    read_only = tmp_path / "ro"
    read_only.mkdir()
    read_only.chmod(0o500)
    try:
        if os.access(read_only, os.W_OK):
            pytest.skip("running as a user who can write anywhere (root)")
        result = runner.invoke(app, ["run", "cartpole", option, str(read_only / "x")])
        assert result.exit_code == 2
        assert "is not writable" in " ".join(result.output.split())
    finally:
        read_only.chmod(0o700)


def test_progress_bar_is_full_when_the_mission_ends_early() -> None:
    console = Console(file=io.StringIO(), width=100)
    with progress_bar(console, quiet=False) as progress:
        report = run_scenario("kuka", progress=progress)
    assert report.finished
    assert report.sim_time_s < 10.0  # the mission ended before the scenario's limit
    (task,) = progress.tasks
    assert task.completed == task.total == report.sim_time_s
    assert task.finished


def test_progress_bar_stops_at_until_when_cut_short() -> None:
    console = Console(file=io.StringIO(), width=100)
    with progress_bar(console, quiet=False) as progress:
        report = run_scenario("cartpole", until=0.5, progress=progress)
    (task,) = progress.tasks
    assert not report.finished
    assert task.completed == task.total == 0.5


def test_gui_without_a_display_fails_clearly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    result = runner.invoke(app, ["run", "kuka", "--gui", "--quiet"])
    assert result.exit_code == 2
    text = " ".join(result.output.split())
    assert "error: --gui needs a display, but DISPLAY is not set" in text
    assert "xvfb-run evclock run ... --gui" in text


def test_engine_chatter_is_collected_not_printed_through_the_bar() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "evclock", "run", "husky", "--until", "0.5"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 3, proc.stderr
    assert "b3Warning" not in proc.stdout
    text = " ".join(proc.stdout.split())
    assert (
        "the physics engine printed while loading the world: 6x No inertial data for link" in text
    )
    assert "base_footprint; imu_link" in text
    report = run_scenario("husky", until=0.1)
    assert report.setup_output[0].startswith("6x No inertial data for link")


@pytest.mark.pybullet
def test_the_report_starts_with_the_evclock_that_ran_it(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    result = CliRunner().invoke(
        app, ["run", "cartpole", "--until", "0.2", "--seed", "3", "--quiet", "--json", str(out)]
    )
    first = result.output.splitlines()[0]
    assert first == f"evclock {evclock.__version__}: cartpole, seed 3, sim time"
    assert json.loads(out.read_text())["evclock_version"] == evclock.__version__


def test_errors_show_their_public_name() -> None:
    assert evclock.InvalidArgumentError.__module__ == "evclock"
    assert repr(evclock.InvalidArgumentError("x")) == "InvalidArgumentError('x')"
    proc = subprocess.run(
        [sys.executable, "-c", "import evclock; evclock.Duration.from_seconds(float('nan'))"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert "\nevclock.InvalidArgumentError: " in proc.stderr
    assert "evclock._errors" not in proc.stderr
    error = pickle.loads(pickle.dumps(evclock.tools.ScenarioError("lost")))
    assert type(error) is evclock.tools.ScenarioError


def test_run_accepts_rtf_max() -> None:
    async def main() -> float:
        await evclock.clock().sleep(5)
        return evclock.clock().now().seconds

    assert evclock.run(main(), rtf="max") == 5.0
    with pytest.raises(evclock.InvalidArgumentError) as info:
        evclock.run(main(), rtf="fast")
    assert "rtf takes 'max' or None (as fast as possible) or a positive number" in str(info.value)
    loop = evclock.loop_factory(rtf="MAX")()
    try:
        assert loop.rtf is None
    finally:
        loop.close()
