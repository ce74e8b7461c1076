"""A trained policy as the controller it replaced: the same trajectory as in the environment,
in ``evclock run`` (in process, split across processes), on wall time; and its bad input."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import evclock
from evclock.gym import ActionError, LinearPolicy, PolicyController, ScenarioEnv, load_policy
from evclock.tools import run_scenario
from evclock.tools._scenarios import load_scenario, open_world

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
from _without_pybullet import CLI_WITHOUT_PYBULLET  # noqa: E402

ENGINES = ("mujoco", pytest.param("pybullet", marks=pytest.mark.pybullet))
CHILD_TIMEOUT = 300


class Recording:
    """A deterministic policy that records what it saw and did."""

    def __init__(self, size: int, observations: int) -> None:
        rng = np.random.default_rng(5)
        # Small gains: the cart-pole's pole does not fall within the test's steps.
        self.weights = rng.uniform(-0.05, 0.05, size=(size, observations))
        self.seen: list[np.ndarray] = []
        self.done: list[np.ndarray] = []

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        self.seen.append(observation.copy())
        action = np.tanh(self.weights @ observation)
        self.done.append(action)
        return action


def lqr_policy() -> LinearPolicy:
    env = ScenarioEnv("cartpole", engine="mujoco")
    env.reset(seed=0)
    scenario = env.scenario
    policy = LinearPolicy(-scenario.gain / scenario.max_force, [0.0], [-1.0], [1.0])
    env.close()
    return policy


def env_rollout(
    name: str, engine: str, policy: Any, seed: int, steps: int, controller: str | None = None
) -> dict[str, Any]:
    """``steps`` steps of ``policy`` from a reset with ``seed``, after other episodes (one cut
    short by a reset, one to its end): a reset in place is a new run."""
    env = ScenarioEnv(name, controller, engine=engine, max_episode_seconds=2.5)
    env.reset(seed=seed + 1)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.reset(seed=seed + 2)
    done = False
    while not done:
        *_, terminated, truncated, _ = env.step(np.ones(env.action_space.shape))
        done = terminated or truncated
    observation, _ = env.reset(seed=seed)
    for _ in range(steps):
        observation, _, terminated, truncated, info = env.step(policy(observation))
        assert not terminated
        assert not truncated
    state = env.scenario.state_vector()
    env.close()
    return {"state": state, "sim_time": info["sim_time"]}


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(
    ("name", "controller", "actions", "observations"),
    [("cartpole", None, 1, 4), ("kuka", None, 7, 20), ("kuka", "planner", 7, 13)],
)
def test_a_rollout_and_the_policy_as_controller_give_identical_trajectories(
    name: str, controller: str | None, actions: int, observations: int, engine: str
) -> None:
    steps = 20
    in_env = Recording(actions, observations)
    rolled = env_rollout(name, engine, in_env, seed=2, steps=steps, controller=controller)

    as_controller = Recording(actions, observations)
    source, scenario = open_world(load_scenario(name), 2, engine=engine)
    if controller is not None:
        scenario.agent_controller = controller  # the policy replaces that one
    policy_controller = PolicyController(as_controller, scenario).install()

    async def main() -> list[float]:
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(rolled["sim_time"]):
                await scenario.run(evclock.clock())
        return scenario.state_vector()

    try:
        state = evclock.run(main(), source=source)
    finally:
        source.close()
    # The controller also ran its tick at the end time, where the rollout stopped (that
    # action would act at the next physics step: none).
    assert policy_controller.steps == steps + 1
    seen, done = np.array(as_controller.seen[:steps]), np.array(as_controller.done[:steps])
    assert seen.tobytes() == np.array(in_env.seen).tobytes()
    assert done.tobytes() == np.array(in_env.done).tobytes()
    assert state == rolled["state"]


def test_evclock_run_with_the_policy_parameter_ends_where_the_environment_does(
    tmp_path: Path,
) -> None:
    policy = lqr_policy()
    policy.save(tmp_path / "lqr.npz")
    rolled = env_rollout("cartpole", "mujoco", policy, seed=4, steps=100)
    report = run_scenario(
        "cartpole",
        engine="mujoco",
        seed=4,
        until=2.0,
        params={"policy": str(tmp_path / "lqr.npz")},
    )
    assert report.error is None
    assert report.final_state == rolled["state"]
    assert [loop.stats["ticks"] for loop in report.loops if loop.name == "balance"] == [101]


def test_the_policy_controls_the_split_run_bit_identically(tmp_path: Path) -> None:
    lqr_policy().save(tmp_path / "lqr.npz")
    rolled = env_rollout("cartpole", "mujoco", load_policy(tmp_path / "lqr.npz"), 4, 100)
    address = f"unix://{tmp_path / 'sim.sock'}"
    common = ["--engine", "mujoco", "--seed", "4", "--until", "2", "--quiet"]

    def cli(*args: str) -> subprocess.Popen[str]:
        return subprocess.Popen(
            [*CLI_WITHOUT_PYBULLET, *args, *common],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    server = cli("run", "cartpole", "--serve", address, "--remote-controllers",
                 "--json", str(tmp_path / "sim.json"))  # fmt: skip
    controllers = cli("control", "cartpole", "--clock", address,
                      "--policy", str(tmp_path / "lqr.npz"))  # fmt: skip
    outputs = [proc.communicate(timeout=CHILD_TIMEOUT) for proc in (controllers, server)]
    assert (controllers.returncode, server.returncode) == (3, 3), outputs  # cut short
    served = json.loads((tmp_path / "sim.json").read_text())
    assert served["final_state"] == rolled["state"]


def test_the_policy_runs_on_wall_time(tmp_path: Path) -> None:
    lqr_policy().save(tmp_path / "lqr.npz")
    report = run_scenario(
        "cartpole",
        engine="mujoco",
        until=0.5,
        wall=True,
        params={"policy": str(tmp_path / "lqr.npz")},
    )
    assert report.error is None
    assert report.mode == "wall"
    ticks = {loop.name: loop.stats["ticks"] for loop in report.loops}
    assert 1 <= ticks["balance"] <= 26  # 50 Hz for half a wall second, at most


def test_a_policy_acting_outside_the_space_stops_the_run_with_an_action_error() -> None:
    source, scenario = open_world(load_scenario("cartpole"), 0, engine="mujoco")
    PolicyController(lambda _observation: np.array([2.0]), scenario).install()

    async def main() -> None:
        await scenario.run(evclock.clock())

    with pytest.raises(ExceptionGroup) as info:
        evclock.run(main(), source=source)
    source.close()
    error = info.value.exceptions[0]
    assert isinstance(error, ActionError)
    assert str(error).startswith(
        "the policy controlling cartpole.balance: action[0] = 2.0 is outside the action "
        "space's bounds [-1.0, 1.0]"
    )


@pytest.mark.parametrize(
    ("spec", "error", "message"),
    [
        ("nowhere.npz", evclock.InvalidArgumentError, "no policy file 'nowhere.npz'"),
        ("justaname", evclock.InvalidArgumentError,
         "a policy is a .npz file of evclock.gym.LinearPolicy or module:callable, got "
         "'justaname'"),
        ("no_such_module_x:f", evclock.tools.ScenarioError,
         "cannot import the policy's module 'no_such_module_x'"),
        ("math:nothing", evclock.tools.ScenarioError,
         "the policy's module 'math' has no 'nothing'"),
        ("math:pi", evclock.InvalidTypeError,
         "policy 'math:pi' is a float, not a callable observation -> action"),
    ],
)  # fmt: skip
def test_a_bad_policy_reference_is_refused(spec: str, error: type, message: str) -> None:
    with pytest.raises(error) as info:
        load_policy(spec)
    assert str(info.value).startswith(message)


def test_a_file_that_is_not_a_linear_policy_is_refused(tmp_path: Path) -> None:
    np.savez(tmp_path / "other.npz", something=np.zeros(3))
    with pytest.raises(evclock.InvalidArgumentError) as info:
        load_policy(tmp_path / "other.npz")
    assert str(info.value).startswith(
        f"{str(tmp_path / 'other.npz')!r} is not a LinearPolicy file (weights, bias, low, high)"
    )


def test_a_policy_for_a_scenario_without_the_protocol_is_refused() -> None:
    from test_env import WithoutAgent

    with pytest.raises(evclock.InvalidArgumentError) as info:
        run_scenario(WithoutAgent, engine="mujoco", params={"policy": "x.npz"})
    assert str(info.value).startswith("scenario 'without_agent' has no parameter 'policy'")
