"""Evaluating a trained policy over many seeds is a sweep: ``evclock sweep cartpole --param
policy=policy.npz --seeds 20``, on local worker processes (MuJoCo and PyBullet) and on a real
local Ray, each seed's row bit-identical to ``evclock run`` of that seed with that policy; a
``module:callable`` policy alike, and a missing policy file fails each run naming it.

The policy is trained by the example (``examples/cartpole_cem.py``, a small budget) and saved as
it saves it; the sweeps run as a user runs them, in the policy's directory with its relative
path. Wall-clock waits are bounded (subprocess timeouts); nothing asserts on durations.
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
from typing import Any

import pytest
from _cli import one_line, run_evclock
from _examples import load_module

from evclock.tools import run_scenario

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "cartpole_cem.py"
#: Short missions (2 s of balancing), so that 20 runs stay cheap.
HOLD = "hold_time=2"
needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="needs evclock[ray]")


@pytest.fixture(scope="module")
def policy_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding ``policy.npz``, trained by the example (one iteration)."""
    directory = tmp_path_factory.mktemp("policy")
    policy, _history = load_module(EXAMPLE).train(iterations=1, population=4)
    policy.save(directory / "policy.npz")
    return directory


def sweep(
    directory: Path, *args: str, engine: str = "mujoco", policy: str = "policy.npz", **env: str
) -> tuple[Any, dict[str, Any]]:
    """``evclock sweep cartpole --engine ENGINE --param policy=POLICY <args>`` run in
    ``directory`` (with ``env`` added to the environment): the finished process and its
    ``--json`` output."""
    out = directory / "sweep.json"
    environ = {**os.environ, "COLUMNS": "200", "RAY_USAGE_STATS_ENABLED": "0", **env}
    proc = run_evclock(
        "sweep", "cartpole", "--engine", engine, "--param", f"policy={policy}",
        "--param", HOLD, *args, "--json", str(out), "--quiet", cwd=directory, env=environ,
    )  # fmt: skip
    assert out.is_file(), proc.stdout + proc.stderr
    data: dict[str, Any] = json.loads(out.read_text())
    out.unlink()
    return proc, data


def single_run(policy: str, seed: int, engine: str = "mujoco") -> dict[str, Any]:
    """The report of the run of ``seed`` with ``policy``, in this process."""
    params: dict[str, Any] = {"hold_time": 2.0, "policy": policy}
    return run_scenario("cartpole", engine=engine, seed=seed, params=params).to_json()


def assert_rows_equal_single_runs(
    policy: str, rows: list[dict[str, Any]], engine: str = "mujoco"
) -> None:
    for row in rows:
        single = single_run(policy, row["seed"], engine)
        assert row["status"] == single["verdict"]
        for field in ("final_state", "summary", "sim_time_s"):  # bit for bit
            assert row["report"][field] == single[field], (row["seed"], field)


@pytest.mark.parametrize("engine", ["mujoco", pytest.param("pybullet", marks=pytest.mark.pybullet)])
def test_a_local_sweep_of_a_policy_runs_each_seed_as_evclock_run(
    policy_dir: Path, engine: str
) -> None:
    proc, data = sweep(policy_dir, "--seeds", "20", "--workers", "2", engine=engine)
    rows = data["rows"]
    assert [row["seed"] for row in rows] == list(range(20))
    assert all(row["params"]["policy"] == "policy.npz" for row in rows)
    statuses = [row["status"] for row in rows]
    assert set(statuses) <= {"success", "failed"}, proc.stdout + proc.stderr
    assert proc.returncode == (0 if statuses == ["success"] * 20 else 1), proc.stderr
    text = one_line(proc.stdout)
    header = "cartpole" if engine == "pybullet" else "cartpole on mujoco"  # PyBullet: the default
    assert f"{header}: 20/20 runs" in text
    assert f"success rate {5 * statuses.count('success'):.1f}%" in text
    assert "balanced_for_s" in text
    assert_rows_equal_single_runs(str(policy_dir / "policy.npz"), rows, engine)
    # One seed through the real command, in another process: the same figures.
    single = policy_dir / "single.json"
    run = run_evclock(
        "run", "cartpole", "--engine", engine, "--seed", "13", "--param", "policy=policy.npz",
        "--param", HOLD, "--json", str(single), "--quiet", cwd=policy_dir,
    )  # fmt: skip
    assert run.returncode in (0, 1), run.stdout + run.stderr
    expected = json.loads(single.read_text())
    for field in ("final_state", "summary", "sim_time_s"):
        assert rows[13]["report"][field] == expected[field]
    # The policy ran as the controller: the scenario's own controller balances otherwise.
    default = run_scenario("cartpole", engine=engine, seed=13, params={"hold_time": 2.0})
    assert rows[13]["report"]["final_state"] != default.to_json()["final_state"]


@needs_ray
def test_a_ray_sweep_of_a_policy_runs_each_seed_as_evclock_run(policy_dir: Path) -> None:
    proc, data = sweep(policy_dir, "--seeds", "0:6", "--backend", "ray", "--workers", "2")
    rows = sorted(data["rows"], key=lambda row: row["seed"])
    assert [row["seed"] for row in rows] == list(range(6)), proc.stdout + proc.stderr
    assert {row["status"] for row in rows} <= {"success", "failed"}, proc.stdout + proc.stderr
    assert_rows_equal_single_runs(str(policy_dir / "policy.npz"), rows)


POLICY_MODULE = """\
import numpy as np


def act(observation):
    return np.clip([3.0 * observation[1] + 0.5 * observation[3]], -1.0, 1.0)
"""


def test_a_sweep_of_a_policy_module_runs_each_seed_as_evclock_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # module:callable, importable where the runs run (PYTHONPATH), as for evclock run.
    (tmp_path / "mypolicy.py").write_text(POLICY_MODULE)
    path = os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))
    proc, data = sweep(
        tmp_path, "--seeds", "3", "--workers", "2", policy="mypolicy:act", PYTHONPATH=path
    )
    assert proc.returncode in (0, 1), proc.stdout + proc.stderr
    monkeypatch.syspath_prepend(str(tmp_path))
    assert_rows_equal_single_runs("mypolicy:act", data["rows"])


def test_a_sweep_of_a_missing_policy_fails_each_run_naming_the_file(tmp_path: Path) -> None:
    proc, data = sweep(tmp_path, "--seeds", "2")
    assert proc.returncode == 4, proc.stdout + proc.stderr
    assert [row["error"] for row in data["rows"]] == [
        "InvalidArgumentError: no policy file 'policy.npz'"
    ] * 2
    assert "reproduce: evclock run cartpole --seed 1 --param policy=policy.npz" in one_line(
        proc.stdout
    )
