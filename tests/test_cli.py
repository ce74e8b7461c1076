"""The `evclock` command and scenario runs: reports, errors, determinism across rtf."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from evclock._cli import app, parse_rtf, run_scenario

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


def test_run_stops_at_until_and_reports_failure() -> None:
    result = runner.invoke(app, ["run", "cartpole", "--until", "1", "--quiet"])
    assert result.exit_code == 1
    assert "cartpole (seed 0): FAILED" in result.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "nope"], "error: unknown scenario 'nope'; valid names: kuka, husky, cartpole"),
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
