"""Learning works: the example's cross-entropy method improves the cart-pole's return well
beyond random actions in a few iterations (on MuJoCo: every supported Python), and the saved
policy then balances as ``evclock run cartpole``'s controller."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from _examples import load_module

from evclock.gym import LinearPolicy, load_policy
from evclock.tools import run_scenario

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "cartpole_cem.py"


def example() -> Any:
    return load_module(EXAMPLE)


def test_the_cross_entropy_method_learns_to_balance(tmp_path: Path) -> None:
    cem = example()
    policy, history = cem.train(iterations=3, population=8)
    baseline = cem.random_return()
    assert history[-1] >= 2.5 * baseline, (history, baseline)
    assert history[-1] > history[0]
    policy.save(tmp_path / "policy.npz")

    loaded = load_policy(tmp_path / "policy.npz")
    assert loaded.weights.tobytes() == policy.weights.tobytes()
    untrained = LinearPolicy([[0.0, 0.0, 0.0, 0.0]], [0.0], [-1.0], [1.0])
    untrained.save(tmp_path / "untrained.npz")

    def balanced_for(name: str) -> float:
        report = run_scenario(
            "cartpole",
            engine="mujoco",
            seed=7,
            params={**cem.HOLD, "policy": str(tmp_path / name)},
        )
        assert report.error is None
        seconds: float = report.summary["balanced_for_s"]
        return seconds

    assert balanced_for("policy.npz") >= 2 * balanced_for("untrained.npz")
