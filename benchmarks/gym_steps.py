"""Environment steps per CPU second as a learner measures them: evclock's Gymnasium environments
against Gymnasium's own, resets included; against a minimal hand-written environment; and
async vector environments (``--vector``) - each in one run.

Usage: python benchmarks/gym_steps.py [--steps 2000] [--rounds 5]
       python benchmarks/gym_steps.py --vector [--vector-steps 200] [--rounds 5] [--workers 1 2 4]

Needs the ``bench`` extra (``pip install -e ".[bench]"``: Gymnasium, MuJoCo and what
Gymnasium's MuJoCo environments import); PyBullet where it is installed.

**Training** (the default run): what a learner measures during training - uniformly random
actions (the action space seeded), ``reset()`` whenever an episode terminates or is truncated,
one process, steps per CPU second (``time.process_time``) with the resets **included**:

* Gymnasium's own ``InvertedPendulum-v5`` (MuJoCo), the baseline, and ``CartPole-v1`` (pure
  Python);
* ``evclock/CartPole-v0`` (50 Hz agent, 240 Hz physics) and ``evclock/KukaReach-v0`` (100 Hz
  agent) on MuJoCo, and on PyBullet where it is installed (the table says so otherwise).

Every environment is built with ``gymnasium.make`` (its default wrappers and time limit); the
first reset is seeded (0), the next ones are not, as in a training loop. The environments run
round by round, interleaved; per environment: the median of the rounds' steps per CPU second
and of their ratios to ``InvertedPendulum-v5`` in the same round, the mean CPU time of a
``reset()`` after an episode (ms; the first reset, which builds the environment, is not
counted), the CPU time of a step alone (us, the resets' time taken out) and its ratio,
and the mean episode length (steps).

**Hand-written**: for each evclock environment on MuJoCo, its step alone (resets excluded,
long episodes: a fixed linear policy balancing the cart-pole, zero actions on the KUKA)
against a minimal ``gymnasium.Env`` on the same scenario object (same MuJoCo model, start
state, observation, action and reward code): ``step`` writes the action, calls ``mj_step``
for the physics steps up to the agent's next deadline (the same integer deadline arithmetic
as ``clock.rate``), and observes. Nothing else runs: no event loop, none of the scenario's
other controllers. ``+ same work`` does the other controllers' work inline at their rates
(the cart-pole's monitor at every physics step and its judge at every tick, the KUKA's IK
planner at 10 Hz): what the evclock environment does, without the loop. Reported: the
median steps per CPU second and the median of the per-round ratios to the minimal one.

**Breakdown** (printed under each evclock environment's hand-written rows): the CPU time of
one evclock step split into parts, each the median over the rounds of the difference between two
variants measured in the same round: ``mj_step only`` (the same number of ``mj_step`` calls on
the same model, nothing else: the physics), ``+ same work`` minus that (the scenario's own work:
action, observation, reward, ``terminated()``, its other controllers), ``loop only`` (the
evclock environment's loop run for one period with the same calls, no Gymnasium side) minus
``+ same work`` (the loop's wake-ups: resuming tasks, the rate loops, the clock), and the
evclock step minus ``loop only`` (the Gymnasium side: ``check_action``, ``info``, the wrappers).

**Vector** (``--vector``): ``gymnasium.make_vec(id, num_envs=N, vectorization_mode="async")``
with 1, 2 and 4 worker processes, random actions, ended episodes reset in their workers
(Gymnasium's autoreset): total steps per wall second (the median of the rounds, the worker
counts interleaved round by round), and the median of the per-round ratios to 1 worker; for
``InvertedPendulum-v5`` and the evclock environments on MuJoCo. Workers scale only on free
cores: the first line printed gives the machine's CPUs and load average.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import statistics
import time
from typing import Any

import gymnasium
import mujoco
import numpy as np

import evclock.gym  # noqa: F401  (registers the environments)
from evclock.tools._runs import import_pybullet_quietly
from evclock.tools._scenarios import load_scenario, open_world

BASELINE = "InvertedPendulum-v5"
GYMNASIUM = {BASELINE: "mujoco", "CartPole-v1": "-"}
"""Gymnasium's own environments: id -> engine."""
EVCLOCK = {"evclock/CartPole-v0": "cartpole", "evclock/KukaReach-v0": "kuka"}
"""evclock's environments: id -> scenario."""
PHYSICS_HZ = 240


def engines() -> list[str]:
    """The engines measured: MuJoCo, and PyBullet where it is installed."""
    if importlib.util.find_spec("pybullet") is None:
        return ["mujoco"]
    import_pybullet_quietly()  # without its build-time banner
    return ["mujoco", "pybullet"]


def make(env_id: str, engine: str, **kwargs: Any) -> Any:
    """``gymnasium.make`` of ``env_id``, on ``engine`` for an evclock environment."""
    if env_id in GYMNASIUM:
        return gymnasium.make(env_id)
    return gymnasium.make(env_id, engine=engine, **kwargs)


# --- training: random actions, resets included ------------------------------------------


class Training:
    """One environment stepped with random actions across rounds, reset whenever its
    episode ends: each round's steps per CPU second with its resets and without them."""

    def __init__(self, env_id: str, engine: str) -> None:
        self.env_id, self.engine = env_id, engine
        self.env = make(env_id, engine)
        self.env.action_space.seed(0)
        self.rates: list[float] = []  # steps per CPU second, resets included
        self.step_rates: list[float] = []  # steps per CPU second, resets taken out
        self.steps = self.episodes = 0
        self.reset_cpu = 0.0  # of the resets between episodes (not the first, which builds)
        self.env.reset(seed=0)

    def round(self, steps: int) -> None:
        env, sample = self.env, self.env.action_space.sample
        resets = 0.0
        start = time.process_time()
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(sample())
            if terminated or truncated:
                reset0 = time.process_time()
                env.reset()
                resets += time.process_time() - reset0
                self.episodes += 1
        cpu = time.process_time() - start
        self.rates.append(steps / cpu)
        self.step_rates.append(steps / (cpu - resets))
        self.reset_cpu += resets
        self.steps += steps


def median_ratio(values: list[float], base: list[float]) -> float:
    """The median of the per-round ratios ``values[k] / base[k]``."""
    return statistics.median(a / b for a, b in zip(values, base, strict=True))


def training(steps: int, rounds: int) -> None:
    envs = [Training(env_id, engine) for env_id, engine in GYMNASIUM.items()]
    envs += [Training(env_id, engine) for engine in engines() for env_id in EVCLOCK]
    for _ in range(rounds):
        for env in envs:
            env.round(steps)
    base = envs[0]
    print(
        f"training: random actions, resets included; {steps} steps x {rounds} rounds, "
        f"medians of the rounds; ratios to {BASELINE} in the same round"
    )
    print(
        f"{'environment':<22}{'engine':<10}{'steps/CPU s':>12}{'ratio':>8}{'reset ms':>10}"
        f"{'step us':>9}{'ratio':>8}{'episode':>9}"
    )
    for env in envs:
        ended = env.episodes  # no episode ended: no reset measured, episodes longer than that
        reset = f"{1e3 * env.reset_cpu / ended:.3f}" if ended else "-"
        episode = f"{env.steps / ended:.1f}" if ended else f">{env.steps}"
        print(
            f"{env.env_id:<22}{env.engine:<10}{statistics.median(env.rates):>12,.0f}"
            f"{median_ratio(env.rates, base.rates):>8.3f}{reset:>10}"
            f"{1e6 / statistics.median(env.step_rates):>9.1f}"
            f"{median_ratio(env.step_rates, base.step_rates):>8.3f}{episode:>9}"
        )
        env.env.close()
    if "pybullet" not in engines():
        print("PyBullet: not installed here, its rows skipped")
    print(
        "(reset ms: mean CPU time of a reset() after an episode; step us: CPU time of a step "
        f"alone, resets taken out, and the ratio of its rate to {BASELINE}'s; episode: mean "
        "steps per episode)"
    )


# --- the step alone, against a hand-written environment -----------------------------------


class HandWritten(gymnasium.Env[Any, Any]):
    """The minimal environment: action, ``mj_step`` to the next deadline, observation; with
    ``same_work``, also the scenario's other controllers' work, called inline at their rates
    (the cart-pole's monitor at every physics step and its judge at every tick, the KUKA's
    IK planner at 10 Hz)."""

    def __init__(
        self, scenario_name: str, *, same_work: bool = False, physics_only: bool = False
    ) -> None:
        self.name = scenario_name
        self.same_work = same_work
        self.physics_only = physics_only
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
        self.observation = self.scenario.observe()
        return self.observation, {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        scenario = self.scenario
        self.tick += 1
        # The k-th deadline: the first physics step at or after k / hz (exact integers).
        due = -((-self.tick * PHYSICS_HZ) // round(self.hz))
        if self.physics_only:  # the mj_step calls alone: no action, observation or reward
            mujoco.mj_step(self.model, self.data, due - self.physics_steps)
            self.physics_steps = due
            return self.observation, 0.0, False, False, {}
        scenario.act(np.asarray(action, dtype=np.float64))
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

    def close(self) -> None:
        self.source.close()


class LoopOnly:
    """An evclock environment's step without the Gymnasium side: the action written
    (unchecked), the loop run for one agent period, ``terminated()`` and ``reward()`` - the
    same calls as ``+ same work``, with the event loop doing the scheduling."""

    def __init__(self, env: Any) -> None:
        self.wrapped = env
        self.env = env.unwrapped
        self.action_space = env.action_space

    def reset(self, *, seed: int | None = None) -> tuple[Any, dict[str, Any]]:
        return self.env.reset(seed=seed)  # type: ignore[no-any-return]

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        scenario = self.env.scenario
        scenario.act(np.asarray(action, dtype=np.float64))
        observation = self.env._episodes.run_period()
        terminated = bool(scenario.terminated())
        return observation, float(scenario.reward()), terminated, False, {}

    def close(self) -> None:
        self.wrapped.close()


PARTS = {
    "physics (mj_step)": ("mj_step only", None),
    "scenario's work": ("+ same work", "mj_step only"),
    "loop wake-ups": ("loop only", "+ same work"),
    "gym side": ("evclock", "loop only"),
}
"""The parts of an evclock step: the CPU time per step of a variant minus that of the one
before it (medians of the per-round differences)."""


BALANCE = np.array([0.0, 3.0, 0.0, 0.5])
"""A linear cart-pole policy that keeps the pole up for seconds (long episodes)."""


def policy_for(env: Any) -> Any:
    """A fixed, deterministic policy: the cart-pole balanced, the KUKA's joints at mid-range."""
    if env.action_space.shape == (1,):
        return lambda observation: np.clip([BALANCE @ observation], -1.0, 1.0)
    zero = np.zeros(env.action_space.shape)
    return lambda _observation: zero


def step_rate(env: Any, steps: int) -> float:
    """Steps per CPU second over ``steps`` steps (resets excluded)."""
    act = policy_for(env)
    observation, _ = env.reset(seed=1)
    cpu = 0.0
    done = 0
    while done < steps:
        cpu0 = time.process_time()
        n = 0
        while done + n < steps:
            observation, _, terminated, truncated, _ = env.step(act(observation))
            n += 1
            if terminated or truncated:
                break
        cpu += time.process_time() - cpu0
        done += n
        if done < steps:
            observation, _ = env.reset(seed=1)
    return steps / cpu


def hand_written(steps: int, rounds: int) -> None:
    print(
        f"the step alone (resets excluded, long episodes), MuJoCo; {steps} steps x {rounds} "
        "rounds, medians; ratios to the hand-written environment in the same round"
    )
    print(f"{'environment':<22}{'variant':<14}{'steps/CPU s':>12}{'ratio':>8}")
    for env_id, name in EVCLOCK.items():
        evclock_env = make(env_id, "mujoco", max_episode_seconds=1e6)
        envs = {
            "mj_step only": HandWritten(name, physics_only=True),
            "hand-written": HandWritten(name),
            "+ same work": HandWritten(name, same_work=True),
            "loop only": LoopOnly(make(env_id, "mujoco", max_episode_seconds=1e6)),
            "evclock": evclock_env,
        }
        rates: dict[str, list[float]] = {variant: [] for variant in envs}
        for _ in range(rounds):
            for variant, env in envs.items():
                rates[variant].append(step_rate(env, steps))
        base = rates["hand-written"]
        for variant, rate in rates.items():
            ratio = median_ratio(rate, base)
            print(f"{env_id:<22}{variant:<14}{statistics.median(rate):>12,.0f}{ratio:>8.3f}")
        same = median_ratio(rates["evclock"], rates["+ same work"])
        print(f"{'':<22}evclock / hand-written with the same work: {same:.3f}")
        breakdown(env_id, rates)
        for env in envs.values():
            env.close()


def breakdown(env_id: str, rates: dict[str, list[float]]) -> None:
    """Where the CPU time of one evclock step sits: each part the difference of two measured
    variants' CPU time per step, in the same rounds."""
    us = {variant: [1e6 / rate for rate in rate_list] for variant, rate_list in rates.items()}
    total = statistics.median(us["evclock"])
    print(f"{'':<22}{env_id}'s step, by part (us per step, share of the evclock step):")
    for part, (variant, before) in PARTS.items():
        rounds = (
            us[variant]
            if before is None
            else [a - b for a, b in zip(us[variant], us[before], strict=True)]
        )
        cost = statistics.median(rounds)
        print(f"{'':<24}{part:<20}{cost:>9.1f}{cost / total:>8.1%}")
    print(f"{'':<24}{'evclock step':<20}{total:>9.1f}")


# --- async vector environments -------------------------------------------------------------


def vector_rates(env_id: str, workers: list[int], steps: int, rounds: int) -> list[list[float]]:
    """Total steps per wall second of async vector ``env_id``s with each count of ``workers``
    processes, per round (the vector environments step in turn in each round), random
    actions; Gymnasium's autoreset starts an ended episode over in its worker."""
    kwargs = {} if env_id in GYMNASIUM else {"engine": "mujoco"}
    vectors = [
        gymnasium.make_vec(env_id, num_envs=n, vectorization_mode="async", **kwargs)
        for n in workers
    ]
    for n, vector in zip(workers, vectors, strict=True):
        vector.action_space.seed(0)
        vector.reset(seed=list(range(n)))
    rates: list[list[float]] = [[] for _ in workers]
    for _ in range(rounds):
        for n, vector, rate in zip(workers, vectors, rates, strict=True):
            wall0 = time.perf_counter()
            for _ in range(steps):
                vector.step(vector.action_space.sample())
            rate.append(n * steps / (time.perf_counter() - wall0))
    for vector in vectors:
        vector.close()
    return rates


def vector(steps: int, rounds: int, workers: list[int]) -> None:
    print(
        f"async vector environments (make_vec, vectorization_mode='async'), MuJoCo: {steps} "
        f"steps x {rounds} rounds, random actions, autoreset; total steps per wall second "
        f"(median of the rounds) and the median of the per-round ratios to {workers[0]} worker(s)"
    )
    print(f"{'environment':<22}" + "".join(f"{f'{n} worker(s)':>18}" for n in workers))
    for env_id in [BASELINE, *EVCLOCK]:
        rates = vector_rates(env_id, workers, steps, rounds)
        cells = "".join(
            f"{f'{statistics.median(rate):,.0f} ({median_ratio(rate, rates[0]):.2f}x)':>18}"
            for rate in rates
        )
        print(f"{env_id:<22}{cells}")


def machine() -> str:
    """The interpreter, the CPUs and the load average, which the figures depend on."""
    load = os.getloadavg()[0]
    return f"python {platform.python_version()}, {os.cpu_count()} CPUs, load average {load:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    parser.add_argument("--vector", action="store_true", help="the async vector environments")
    parser.add_argument("--vector-steps", type=int, default=200, help="vector steps per round")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    args = parser.parse_args()
    print(machine())
    if args.vector:
        vector(args.vector_steps, args.rounds, args.workers)
        return
    training(args.steps, args.rounds)
    print()
    hand_written(args.steps, args.rounds)


if __name__ == "__main__":
    main()
