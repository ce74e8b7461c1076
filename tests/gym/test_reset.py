"""A reset in place is a new environment: after any episodes (of any length, terminated,
truncated, cut short by a reset), an episode's observations, rewards, outcome and final state
are bit for bit those of a new environment reset with the same seed, on both engines.

(``test_policy.py`` checks that such an episode is also ``evclock run``'s with the policy as the
controller.)
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import evclock
from evclock.gym import EnvStateError, ScenarioEnv

ENGINES = ("mujoco", pytest.param("pybullet", marks=pytest.mark.pybullet))
LIMIT = 0.6  # sim seconds per episode: the LQR's cart-pole and the KUKA are truncated


def episode(env: ScenarioEnv, seed: int | None, policy: Any, steps: int = 10_000) -> dict[str, Any]:
    """Up to ``steps`` steps of ``policy(observation, rng)`` from a reset with ``seed``."""
    rng = np.random.default_rng(7)
    observation, info = env.reset(seed=seed)
    observations, rewards, outcome = [observation], [], "cut short"
    for _ in range(steps):
        observation, reward, terminated, truncated, info = env.step(policy(env, observation, rng))
        observations.append(observation)
        rewards.append(reward)
        if terminated or truncated:
            outcome = "terminated" if terminated else "truncated"
            break
    return {
        "observations": np.array(observations).tobytes(),
        "rewards": rewards,
        "outcome": outcome,
        "sim_time": info["sim_time"],
        "ticks": info["ticks"],
        "state": env.scenario.state_vector(),
        "summary": env.scenario.summary(),
    }


def random_actions(env: ScenarioEnv, _observation: Any, rng: np.random.Generator) -> Any:
    return rng.uniform(-1.0, 1.0, size=env.action_space.shape)


def full_push(env: ScenarioEnv, _observation: Any, _rng: Any) -> Any:
    return np.ones(env.action_space.shape)


def balancing(env: ScenarioEnv, observation: Any, _rng: Any) -> Any:
    """The cart-pole's own LQR as the agent (it holds the pole: the episode is truncated);
    for the KUKA, the planner's goal (normalised) as the joint targets."""
    scenario = env.scenario
    if scenario.name == "cartpole":
        return np.clip(-(scenario.gain @ observation) / scenario.max_force, -1.0, 1.0)
    lower, upper = np.array(scenario.lower), np.array(scenario.upper)
    return np.clip(2.0 * (scenario.goal - lower) / (upper - lower) - 1.0, -1.0, 1.0)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(
    ("name", "controller"), [("cartpole", None), ("kuka", None), ("kuka", "planner")]
)
def test_an_episode_after_others_is_a_new_environments(
    name: str, controller: str | None, engine: str
) -> None:
    def new_env() -> ScenarioEnv:
        return ScenarioEnv(name, controller, engine=engine, max_episode_seconds=LIMIT)

    fresh, other = new_env(), new_env()
    expected = episode(fresh, 3, random_actions)
    expected_balanced = episode(other, 4, balancing)
    fresh.close()
    other.close()

    env = new_env()
    outcomes = [
        episode(env, 5, full_push)["outcome"],  # the cart-pole falls; the KUKA runs out
        episode(env, 6, balancing)["outcome"],  # truncated
        episode(env, 6, random_actions, steps=3)["outcome"],  # reset in the middle
        episode(env, None, random_actions, steps=0)["outcome"],  # reset right after a reset
    ]
    expected_outcomes = {"cartpole": "terminated", "kuka": "truncated"}[name]
    assert outcomes == [expected_outcomes, "truncated", "cut short", "cut short"]
    assert episode(env, 3, random_actions) == expected
    assert episode(env, 4, balancing) == expected_balanced
    # And again after those: nothing accumulates from episode to episode.
    assert episode(env, 3, random_actions) == expected
    env.close()


@pytest.mark.parametrize("engine", ENGINES)
def test_a_reset_brings_sim_time_back_to_zero_with_only_the_new_episodes_loops(
    engine: str,
) -> None:
    env = ScenarioEnv("cartpole", engine=engine)
    env.reset(seed=1)
    for _ in range(10):
        env.step(np.zeros(1))
    old_scenario = env.scenario
    old_tasks = asyncio.all_tasks(env._episodes.loop)
    assert len(old_tasks) == 4  # the run, monitor, balance (the agent) and the judge
    _, info = env.reset(seed=2)
    assert all(task.cancelled() for task in old_tasks)  # cancelled, and run to their end
    assert not old_tasks & asyncio.all_tasks(env._episodes.loop)
    assert info["sim_time"] == 0.0
    assert info["ticks"] == {"monitor": 1, "judge": 1, "balance": 1}
    assert env.scenario is not old_scenario
    assert env.scenario.seed == 2
    assert old_scenario.finished_at is None  # its run was cancelled, not finished
    env.close()


def test_after_the_physics_raised_a_reset_builds_world_and_loop_anew(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warning to MUJOCO_LOG.TXT here
    from evclock_sims import CartPole

    class Faulty(CartPole):
        """A NaN force reaches MuJoCo at the 30th physics step of its second build's episode."""

        name = "faulty"
        engines = ("mujoco",)
        builds = 0

        def __init__(self, world: Any, seed: int = 0) -> None:
            super().__init__(world, seed)
            type(self).builds += 1
            self.steps = 0

        def before_step(self) -> None:
            self.steps += 1
            if type(self).builds == 2 and self.steps == 30:
                self.cart.world.data.ctrl[0] = float("nan")

    env = ScenarioEnv(Faulty)  # build 1: the spaces
    env.reset(seed=3)  # build 2
    for _ in range(6):  # 29 physics steps
        env.step(np.zeros(1))
    with pytest.raises(evclock.PhysicsError, match="mjWARN_BADCTRL"):
        env.step(np.zeros(1))
    assert env._episodes.loop is None  # closed: its state after the error is unknown
    with pytest.raises(EnvStateError, match="the simulation raised: call reset"):
        env.step(np.zeros(1))
    again = episode(env, 3, random_actions)
    env.close()
    fresh = ScenarioEnv(Faulty)
    assert episode(fresh, 3, random_actions) == again
    fresh.close()
