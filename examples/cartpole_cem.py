"""Learn to balance the cart-pole on sim time, then run the policy as its controller.

The cross-entropy method over a linear policy (``action = clip(W @ observation)``), a few
lines of numpy on ``evclock/CartPole-v0``: the agent replaces the scenario's ``balance``
controller (50 Hz) while the physics (240 Hz) and the scenario's other controllers keep
running on sim time. The trained policy is saved as ``.npz`` and runs, unchanged, as the
``balance`` controller of ``evclock run cartpole``.

The mission here: balance for 10 s (``hold_time=10``); an episode ends when the pole falls
or the cart leaves its track (terminated) or after 10 s (truncated); the reward is 1 per
50 Hz step, 500 at most.

Usage: python examples/cartpole_cem.py [POLICY.npz] [--iterations N] [--population N]
       evclock run cartpole --engine mujoco --param hold_time=10 --param policy=POLICY.npz
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import gymnasium
import numpy as np

import evclock.gym  # registers evclock/CartPole-v0
import evclock.tools
from evclock.gym import LinearPolicy

HOLD = {"hold_time": 10.0}
"""The mission: balance for 10 s (the scenario's default is 30 s)."""


def episode_return(env: gymnasium.Env, policy: LinearPolicy, seed: int) -> float:
    """The return of one episode of ``policy`` from the start ``seed`` draws."""
    observation, _ = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        observation, reward, terminated, truncated, _ = env.step(policy(observation))
        total += float(reward)
        done = terminated or truncated
    return total


def score(env: gymnasium.Env, weights: np.ndarray, seeds: list[int]) -> float:
    """The mean return of the linear policy ``weights`` over the episodes of ``seeds``."""
    policy = LinearPolicy(weights[None, :], [0.0], [-1.0], [1.0])
    return float(np.mean([episode_return(env, policy, seed) for seed in seeds]))


def train(
    iterations: int = 4, population: int = 8, elite: int = 2
) -> tuple[LinearPolicy, list[float]]:
    """The cross-entropy method: sample weights, keep the elite, refit, repeat.

    The search runs on observations scaled by the observation space's bounds (so that one
    spread suits every component); the policy folds the scaling into its weights. Each
    iteration scores its candidates on one episode, all from the same start (a seed per
    iteration); the mean weights are scored on three held-out starts after each iteration.

    :returns: the policy of the final mean weights, and the mean weights' held-out score
        before the first iteration (the all-zero policy's) and after each.
    """
    env = gymnasium.make("evclock/CartPole-v0", engine="mujoco", params=HOLD)
    scale = env.observation_space.high
    rng = np.random.default_rng(0)
    held_out = [101, 102, 103]
    mean, std = np.zeros(4), np.full(4, 10.0)
    history = [score(env, mean / scale, held_out)]
    for iteration in range(iterations):
        candidates = mean + std * rng.standard_normal((population, 4))
        scores = [score(env, weights / scale, [iteration]) for weights in candidates]
        best = candidates[np.argsort(scores)[-elite:]]
        mean, std = best.mean(axis=0), best.std(axis=0) + 0.1
        history.append(score(env, mean / scale, held_out))
    env.close()
    return LinearPolicy((mean / scale)[None, :], [0.0], [-1.0], [1.0]), history


def random_return() -> float:
    """The mean return of uniformly random actions on the held-out starts (the baseline)."""
    env = gymnasium.make("evclock/CartPole-v0", engine="mujoco", params=HOLD)
    env.action_space.seed(0)
    total = 0.0
    for seed in (101, 102, 103):
        env.reset(seed=seed)
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            done = terminated or truncated
    env.close()
    return total / 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", nargs="?", type=Path, help="where to save the policy")
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--population", type=int, default=8)
    args = parser.parse_args()
    out = args.policy or Path(tempfile.mkdtemp()) / "cartpole_policy.npz"
    policy, history = train(args.iterations, args.population)
    print(f"random actions: mean return {random_return():.0f}")
    print("trained policy: mean return " + ", ".join(f"{value:.0f}" for value in history))
    policy.save(out)
    print(f"saved {out}")
    # The same policy as the cart-pole's balance controller, for a whole mission.
    report = evclock.tools.run_scenario(
        "cartpole", engine="mujoco", seed=7, params={**HOLD, "policy": str(out)}
    )
    command = (
        f"evclock run cartpole --engine mujoco --seed 7 --param hold_time=10 --param policy={out}"
    )
    print(f"{command}: {report.verdict}, balanced for {report.summary['balanced_for_s']:g} s")


if __name__ == "__main__":
    main()
