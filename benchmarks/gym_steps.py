"""Environment steps per second: evclock's Gymnasium environments against a minimal
hand-written one, and async vector environments with 1 and 2 workers - one run.

Usage: python benchmarks/gym_steps.py [--steps 2000] [--repeat 3] [--vector-steps 500]

For each bundled environment on MuJoCo (``evclock/CartPole-v0``: 50 Hz agent, 240 Hz physics;
``evclock/KukaReach-v0``: 100 Hz agent):

* **hand-written**: a minimal ``gymnasium.Env`` on the same scenario object (same MuJoCo
  model, start state, observation, action and reward code): ``step`` writes the action, calls
  ``mj_step`` for the physics steps up to the agent's next deadline (the same integer deadline
  arithmetic as ``clock.rate``), and observes. Nothing else runs: no event loop, none of the
  scenario's other controllers (the cart-pole's 240 Hz monitor and 50 Hz judge, the KUKA's
  10 Hz IK planner);
* **+ same work**: the same, also doing the other controllers' work inline at their rates (the
  cart-pole's monitor at every physics step and its judge at every tick, the KUKA's IK planner
  at 10 Hz): what the evclock environment does, without the loop;
* **evclock**: ``gymnasium.make(id, engine="mujoco")``: the scenario's other controllers, timers
  and the physics on an evclock loop, one period of the agent's controller per step.

Reported: steps per CPU second and per wall second (best of the alternating rounds), the
ratios to the minimal environment, and evclock's CPU ratio to the one doing the same work.
Then an async vector environment of the cart-pole with 1 and 2 worker processes: total steps
per wall second (its ended episodes reset in the workers). The policy: a fixed linear one
balancing the cart-pole; zero actions (mid-range joints) on the KUKA.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import gymnasium
import mujoco
import numpy as np

import evclock.gym  # noqa: F401  (registers the environments)
from evclock.tools._scenarios import load_scenario, open_world

PHYSICS_HZ = 240
ENVS = {"evclock/CartPole-v0": "cartpole", "evclock/KukaReach-v0": "kuka"}


class HandWritten(gymnasium.Env[Any, Any]):
    """The minimal environment: action, ``mj_step`` to the next deadline, observation; with
    ``same_work``, also the scenario's other controllers' work, called inline at their rates
    (the cart-pole's monitor at every physics step and its judge at every tick, the KUKA's
    IK planner at 10 Hz)."""

    def __init__(self, scenario_name: str, *, same_work: bool = False) -> None:
        self.name = scenario_name
        self.same_work = same_work
        self.scenario: Any = None
        self.reset(seed=0)
        self.observation_space = self.scenario.observation_space()
        self.action_space = self.scenario.action_space()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        if self.scenario is not None:
            self.source.close()
        self.source, self.scenario = open_world(
            load_scenario(self.name), seed or 0, engine="mujoco"
        )
        world = self.scenario.world
        self.model, self.data = world.model, world.data
        self.hz = float(self.scenario.agent_hz)
        self.tick = 0
        self.physics_steps = 0
        return self.scenario.observe(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        scenario = self.scenario
        scenario.act(np.asarray(action, dtype=np.float64))
        self.tick += 1
        # The k-th deadline: the first physics step at or after k / hz (exact integers).
        due = -((-self.tick * PHYSICS_HZ) // round(self.hz))
        if not self.same_work:
            mujoco.mj_step(self.model, self.data, due - self.physics_steps)
        elif self.name == "cartpole":
            for _ in range(due - self.physics_steps):
                mujoco.mj_step(self.model, self.data)
                cart, angle, _, _ = scenario._joint_states()  # the monitor's work
                scenario.max_angle = max(scenario.max_angle, abs(angle))
                scenario.max_cart_offset = max(scenario.max_cart_offset, abs(cart))
            scenario.terminated()  # the judge's work
        else:
            for step in range(self.physics_steps, due):
                if step % (PHYSICS_HZ // 10) == 0:  # the planner's 10 Hz deadlines
                    target = scenario.targets[scenario.index]
                    scenario.final_error = float(
                        np.linalg.norm(scenario.flange_position() - target)
                    )
                    scenario.goal = np.array(scenario._inverse_kinematics(target))
                mujoco.mj_step(self.model, self.data)
        self.physics_steps = due
        terminated = bool(scenario.terminated())
        return scenario.observe(), float(scenario.reward()), terminated, False, {}


BALANCE = np.array([0.0, 3.0, 0.0, 0.5])
"""A linear cart-pole policy that keeps the pole up for seconds (long episodes)."""


def policy_for(env: Any) -> Any:
    """A fixed, deterministic policy: the cart-pole balanced, the KUKA's joints at mid-range."""
    if env.action_space.shape == (1,):
        return lambda observation: np.clip([BALANCE @ observation], -1.0, 1.0)
    zero = np.zeros(env.action_space.shape)
    return lambda _observation: zero


def measure(env: Any, steps: int) -> tuple[float, float]:
    """Steps per CPU second and per wall second over ``steps`` steps (resets excluded)."""
    act = policy_for(env)
    observation, _ = env.reset(seed=1)
    cpu = wall = 0.0
    done = 0
    while done < steps:
        cpu0, wall0 = time.process_time(), time.perf_counter()
        n = 0
        while done + n < steps:
            observation, _, terminated, truncated, _ = env.step(act(observation))
            n += 1
            if terminated or truncated:
                break
        cpu += time.process_time() - cpu0
        wall += time.perf_counter() - wall0
        done += n
        if done < steps:
            observation, _ = env.reset(seed=1)
    return steps / cpu, steps / wall


def vector_rate(workers: int, steps: int) -> float:
    """Total steps per wall second of an async vector cart-pole with ``workers`` processes."""
    vector = gymnasium.make_vec(
        "evclock/CartPole-v0", num_envs=workers, vectorization_mode="async", engine="mujoco"
    )
    observations, _ = vector.reset(seed=list(range(workers)))
    wall0 = time.perf_counter()
    for _ in range(steps):
        actions = np.clip(observations @ BALANCE, -1.0, 1.0)[:, None]
        # Autoreset: an ended episode starts over in its worker.
        observations, *_ = vector.step(actions)
    wall = time.perf_counter() - wall0
    vector.close()
    return workers * steps / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="steps per round")
    parser.add_argument("--repeat", type=int, default=3, help="alternating rounds")
    parser.add_argument("--vector-steps", type=int, default=500, help="vector steps")
    args = parser.parse_args()
    print(f"{args.steps} steps x {args.repeat} rounds, best of the rounds")
    header = (
        f"{'environment':<22}{'variant':<14}{'steps/CPU s':>13}{'ratio':>8}"
        f"{'steps/wall s':>14}{'ratio':>8}"
    )
    print(header)
    for env_id, name in ENVS.items():
        envs = {
            "hand-written": HandWritten(name),
            "+ same work": HandWritten(name, same_work=True),
            "evclock": gymnasium.make(env_id, engine="mujoco", max_episode_seconds=1e6),
        }
        best = {variant: (0.0, 0.0) for variant in envs}
        for _ in range(args.repeat):
            for variant, env in envs.items():
                cpu, wall = measure(env, args.steps)
                best[variant] = (max(best[variant][0], cpu), max(best[variant][1], wall))
        base = best["hand-written"]
        same = best["+ same work"]
        for variant, (cpu, wall) in best.items():
            print(
                f"{env_id:<22}{variant:<14}{cpu:>13,.0f}{cpu / base[0]:>8.3f}"
                f"{wall:>14,.0f}{wall / base[1]:>8.3f}"
            )
        evclock_cpu = best["evclock"][0]
        print(f"{'':<22}evclock / hand-written with the same work: {evclock_cpu / same[0]:.3f}")
        for env in envs.values():
            env.close()
    rates = {workers: vector_rate(workers, args.vector_steps) for workers in (1, 2)}
    for workers, rate in rates.items():
        print(
            f"async vector evclock/CartPole-v0, {workers} worker(s): {rate:,.0f} steps/wall s "
            f"({rate / rates[1]:.2f}x)"
        )
    assert all(math.isfinite(rate) for rate in rates.values())


if __name__ == "__main__":
    main()
