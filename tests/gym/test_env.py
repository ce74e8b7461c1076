"""The bundled scenarios as Gymnasium environments: Gymnasium's own checker, its wrappers and
vector environments, determinism, and bad input.

The MuJoCo halves run on every supported Python; the PyBullet halves need PyBullet.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import evclock.gym
from evclock.gym import ActionError, AgentProtocolError, EnvStateError, ScenarioEnv
from evclock_sims import Scenario

ENVS = ("evclock/CartPole-v0", "evclock/KukaReach-v0")
ENGINES = ("mujoco", pytest.param("pybullet", marks=pytest.mark.pybullet))


def rollout(env: Any, seed: int, steps: int, actions_seed: int = 7) -> dict[str, Any]:
    """Observations, rewards and the final state of ``steps`` seeded random actions."""
    rng = np.random.default_rng(actions_seed)
    observation, _ = env.reset(seed=seed)
    observations, rewards = [observation], []
    for _ in range(steps):
        action = rng.uniform(-1.0, 1.0, size=env.action_space.shape)
        observation, reward, terminated, truncated, _ = env.step(action)
        observations.append(observation)
        rewards.append(reward)
        if terminated or truncated:
            break
    return {
        "observations": np.array(observations),
        "rewards": rewards,
        "state": env.unwrapped.scenario.state_vector(),
    }


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("env_id", ENVS)
def test_gymnasiums_checker_passes_without_a_warning(env_id: str, engine: str) -> None:
    env = gymnasium.make(env_id, engine=engine)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    env.close()


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("env_id", ENVS)
def test_a_step_runs_exactly_one_period_of_the_replaced_controller(
    env_id: str, engine: str
) -> None:
    env = gymnasium.make(env_id, engine=engine)
    _, info = env.reset(seed=0)
    assert info["sim_time"] == 0.0
    hz = env.unwrapped.hz
    controller = env.unwrapped.controller
    for k in range(1, 6):
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape))
        # The controller's k-th deadline, at the first physics step (1/240 s) at or after it.
        deadline_ns = round(k * 1e9 / hz)
        step_ns = 1e9 / 240
        expected = int(np.ceil(deadline_ns / step_ns - 1e-9)) * step_ns
        assert abs(info["sim_time"] * 1e9 - expected) < 1.0
        assert info["ticks"][controller] == k + 1
    # The other controllers kept running at their own rates.
    others = set(info["ticks"]) - {controller}
    assert others
    assert all(info["ticks"][name] >= 1 for name in others)
    env.close()


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("env_id", ENVS)
def test_same_seed_and_actions_give_bit_identical_episodes(env_id: str, engine: str) -> None:
    first_env = gymnasium.make(env_id, engine=engine)
    first = rollout(first_env, seed=3, steps=40)
    first_env.close()
    env = gymnasium.make(env_id, engine=engine)
    rollout(env, seed=5, steps=10)  # another episode first: reset leaves nothing behind
    second = rollout(env, seed=3, steps=40)
    assert first["observations"].tobytes() == second["observations"].tobytes()
    assert first["rewards"] == second["rewards"]
    assert first["state"] == second["state"]
    other = rollout(env, seed=4, steps=40)  # another seed: another start or other targets
    env.close()
    assert other["observations"][0].tobytes() != first["observations"][0].tobytes()


def test_unseeded_resets_continue_the_seeded_generator() -> None:
    def seeds(env: Any) -> list[int]:
        found = [env.reset(seed=11)[1]["seed"]]
        found += [env.reset()[1]["seed"] for _ in range(3)]
        return found

    envs = [ScenarioEnv("cartpole"), ScenarioEnv("cartpole"), ScenarioEnv("cartpole", seed=9)]
    try:
        a, b = seeds(envs[0]), seeds(envs[1])
        assert a == b
        assert a[0] == 11
        assert len(set(a)) == 4
        assert envs[2].reset()[1]["seed"] == 9
    finally:
        for env in envs:
            env.close()


def test_the_standard_wrappers_work() -> None:
    from gymnasium.wrappers import (
        FlattenObservation,
        NormalizeObservation,
        RecordEpisodeStatistics,
        TimeLimit,
    )

    env = gymnasium.make("evclock/KukaReach-v0", engine="mujoco")
    env = RecordEpisodeStatistics(
        TimeLimit(NormalizeObservation(FlattenObservation(env)), max_episode_steps=15)
    )
    observation, _ = env.reset(seed=0)
    assert observation.shape == (20,)
    steps = 0
    while True:
        observation, _, terminated, truncated, info = env.step(env.action_space.sample())
        steps += 1
        if terminated or truncated:
            break
    assert steps == 15
    assert truncated
    assert info["episode"]["l"] == 15
    assert abs(float(np.mean(observation))) < 10.0  # normalized
    env.close()


def test_the_time_limit_truncates_on_sim_time() -> None:
    env = ScenarioEnv("kuka", max_episode_seconds=0.05)
    env.reset(seed=0)
    outcomes = [env.step(np.zeros(7))[2:4] for _ in range(5)]
    assert outcomes == [(False, False)] * 4 + [(False, True)]
    with pytest.raises(EnvStateError) as info:
        env.step(np.zeros(7))
    env.close()
    assert str(info.value) == (
        "step() needs a running episode, but the episode ended (truncated) at sim time "
        "0.05 s: call reset()"
    )


def test_the_mission_ending_without_a_terminal_state_truncates() -> None:
    # The cart-pole's judge ends the run after the hold time: truncated, not terminated.
    env = ScenarioEnv("cartpole", params={"hold_time": 0.1}, max_episode_seconds=5.0)
    env.reset(seed=0)
    lqr = env.scenario.gain
    done = False
    steps = 0
    while not done:
        state = env.scenario.observe()
        action = np.clip(-(lqr @ state) / env.scenario.max_force, -1.0, 1.0)
        _, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        steps += 1
    env.close()
    assert (terminated, truncated, reward) == (False, True, 1.0)
    assert steps == 5
    assert info["sim_time"] == pytest.approx(0.1, abs=1 / 240)
    assert info["loops"]["judge"]["ticks"] == 6  # the statistics, at the episode's end
    assert info["loops"]["balance"]["missed"] == 0


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_vector_environments_match_single_ones_with_the_same_seeds(mode: str) -> None:
    seeds = [21, 22]
    vector = gymnasium.make_vec(
        "evclock/CartPole-v0", num_envs=2, vectorization_mode=mode, engine="mujoco"
    )
    singles = [gymnasium.make("evclock/CartPole-v0", engine="mujoco") for _ in seeds]
    try:
        observations, _ = vector.reset(seed=seeds)
        expected = np.array([env.reset(seed=s)[0] for env, s in zip(singles, seeds, strict=True)])
        assert observations.tobytes() == expected.tobytes()
        actions = np.array([[0.3], [-0.2]])
        for _ in range(5):
            observations, rewards, terminated, truncated, _ = vector.step(actions)
            results = [env.step(a) for env, a in zip(singles, actions, strict=True)]
            assert observations.tobytes() == np.array([r[0] for r in results]).tobytes()
            assert rewards.tolist() == [r[1] for r in results]
            assert not terminated.any()
            assert not truncated.any()
    finally:
        vector.close()
        for env in singles:
            env.close()


# ---------------------------------------------------------------- bad input


@pytest.fixture
def cartpole() -> Any:
    env = ScenarioEnv("cartpole", engine="mujoco")
    yield env
    env.close()


def test_step_before_reset_is_refused(cartpole: Any) -> None:
    with pytest.raises(EnvStateError) as info:
        cartpole.step(np.zeros(1))
    assert str(info.value) == "step() needs a running episode, but reset() was not called yet"


def test_step_after_termination_is_refused(cartpole: Any) -> None:
    cartpole.reset(seed=0)
    terminated = False
    while not terminated:
        _, _, terminated, _, info = cartpole.step(np.ones(1))
    with pytest.raises(EnvStateError) as error:
        cartpole.step(np.zeros(1))
    assert str(error.value) == (
        "step() needs a running episode, but the episode ended (terminated) at sim time "
        f"{info['sim_time']:g} s: call reset()"
    )
    cartpole.reset(seed=0)
    cartpole.step(np.zeros(1))  # a reset starts over


def test_step_after_close_is_refused(cartpole: Any) -> None:
    cartpole.reset(seed=0)
    cartpole.close()
    with pytest.raises(EnvStateError, match="the environment is closed"):
        cartpole.step(np.zeros(1))
    with pytest.raises(EnvStateError, match="reset\\(\\) on a closed environment"):
        cartpole.reset()


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (
            np.array([1.5]),
            "step(): action[0] = 1.5 is outside the action space's bounds [-1.0, 1.0] "
            "(1 value(s) outside; actions are never clipped: clip them in the policy, or "
            "wrap the environment in gymnasium.wrappers.ClipAction)",
        ),
        (
            np.array([0.1, 0.2]),
            "step(): the action has shape (2,), the action space Box(-1.0, 1.0, (1,), "
            "float64) has shape (1,)",
        ),
        (
            0.5,
            "step(): the action has shape (), the action space Box(-1.0, 1.0, (1,), "
            "float64) has shape (1,)",
        ),
        (np.array([np.nan]), "step(): the action holds NaN: [nan]"),
        (np.array(["a"]), "step(): the action must be real numbers, got dtype <U1 (array(['a']"),
        (np.array([True]), "step(): the action must be real numbers, got dtype bool"),
    ],
)
def test_a_bad_action_is_refused_naming_what_is_wrong(
    cartpole: Any, action: Any, message: str
) -> None:
    cartpole.reset(seed=0)
    before = cartpole.scenario.state_vector()
    with pytest.raises(ActionError) as info:
        cartpole.step(action)
    assert str(info.value).startswith(message)
    assert cartpole.scenario.state_vector() == before  # nothing was applied nor stepped
    cartpole.step(np.zeros(1))  # the episode goes on


class WithoutAgent(Scenario):
    """A scenario on MuJoCo without the agent protocol."""

    name = "without_agent"
    description = "no agent protocol"
    default_until = 1.0
    engines = ("mujoco",)

    def _services(self, clock: Any) -> dict[str, Any]:
        return {}

    async def _mission(self, clock: Any) -> None:
        return None

    def success(self) -> bool:
        return True

    def _metrics(self) -> dict[str, Any]:
        return {}


def test_a_scenario_without_the_protocol_is_refused() -> None:
    with pytest.raises(AgentProtocolError) as info:
        ScenarioEnv(WithoutAgent)
    assert str(info.value) == (
        "scenario 'without_agent' does not implement the agent protocol of evclock.gym: it "
        "lacks observation_space, action_space, observe, act, reward, terminated, agent_hz; "
        "implement them (see the guide 'Reinforcement learning', 'The agent protocol')"
    )


@pytest.mark.parametrize(
    ("name", "controller", "choices"),
    [
        ("kuka", "gripper", "'joint_control', 'planner'"),  # no such controller
        ("cartpole", "monitor", "'balance'"),  # a controller, but not a replaceable one
    ],
)
def test_a_controller_an_agent_cannot_replace_is_refused_naming_those_it_can(
    name: str, controller: str, choices: str
) -> None:
    with pytest.raises(AgentProtocolError) as info:
        ScenarioEnv(name, controller=controller)
    assert isinstance(info.value, evclock.EvClockError)
    assert str(info.value) == (
        f"scenario {name!r} has no controller {controller!r} an agent can replace; choose "
        f"one of: {choices}"
    )


@pytest.mark.parametrize("engine", ENGINES)
def test_the_agent_replaces_the_kukas_planner_at_its_own_rate(engine: str) -> None:
    env = gymnasium.make("evclock/KukaReach-v0", engine=engine, controller="planner")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    assert env.unwrapped.hz == 10.0
    assert env.observation_space.shape == (13,)  # joints, flange, target: no planner's goal
    assert env.action_space.shape == (7,)
    observation, info = env.reset(seed=0)
    assert observation.shape == (13,)
    goal = np.linspace(-0.5, 0.5, 7)
    for k in range(1, 4):
        _, reward, terminated, truncated, info = env.step(goal)
        assert info["sim_time"] == pytest.approx(k / 10, abs=1e-9)
        assert not terminated
        assert not truncated
        assert reward < 0.0
    # The agent is the 10 Hz planner; the mission still tracks the targets at 10 Hz.
    assert info["ticks"] == {"joint_control": 31, "planner": 4, "targets": 4}
    scenario = env.unwrapped.scenario
    lower, upper = np.array(scenario.lower), np.array(scenario.upper)
    assert scenario.goal.tolist() == (lower + (goal + 1.0) * 0.5 * (upper - lower)).tolist()
    env.close()


def test_reset_options_and_render_modes_are_refused() -> None:
    env = ScenarioEnv("cartpole")
    with pytest.raises(evclock.InvalidArgumentError, match="takes no options, got \\['x'\\]"):
        env.reset(options={"x": 1})
    env.close()
    with pytest.raises(evclock.InvalidArgumentError, match="renders nothing itself"):
        ScenarioEnv("cartpole", render_mode="human")


def test_import_evclock_gym_registers_the_bundled_environments() -> None:
    for env_id in ENVS:
        assert env_id in gymnasium.registry
    with pytest.raises(evclock.InvalidArgumentError, match="registered already"):
        evclock.gym.register("evclock/CartPole-v0", "cartpole")


def test_record_writes_each_episode_to_its_own_mcap_file(tmp_path: Path) -> None:
    from evclock.tools import read_trace

    env = ScenarioEnv("cartpole", record=tmp_path / "runs" / "cartpole.mcap")
    (tmp_path / "runs").mkdir()
    for seed in (1, 2):
        env.reset(seed=seed)
        for _ in range(10):
            env.step(np.zeros(1))
    env.close()
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [
        "cartpole-0.mcap",
        "cartpole-1.mcap",
    ]
    for index, seed in enumerate((1, 2)):
        trace = read_trace(tmp_path / "runs" / f"cartpole-{index}.mcap")
        assert trace.metadata["evclock.run"]["seed"] == seed
        assert trace.metadata["evclock.run"]["scenario"] == "cartpole"
        assert trace.topic("/evclock/state")


def test_a_scenario_becomes_an_environment_with_one_call() -> None:
    from evclock_sims import CartPole

    evclock.gym.register("tests/ShortCartPole-v0", CartPole, params={"hold_time": 0.1})
    env = gymnasium.make("tests/ShortCartPole-v0", engine="mujoco")
    env.reset(seed=0)
    steps = 0
    truncated = False
    while not truncated:
        _, _, terminated, truncated, _ = env.step(np.zeros(1))
        assert not terminated
        steps += 1
    assert steps == 5  # the mission's 0.1 s at 50 Hz
    env.close()


def test_without_gymnasium_evclock_gym_names_the_extra() -> None:
    import subprocess
    import sys

    code = (
        "import sys\n"
        "sys.modules['gymnasium'] = None\n"
        "import evclock\n"
        "try:\n"
        "    import evclock.gym\n"
        "except evclock.MissingExtraError as exc:\n"
        "    print(exc.extra, exc)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout == (
        "gym evclock.gym needs 'gymnasium', which is not installed; install it with: "
        "pip install 'evclock[gym]'\n"
    )
