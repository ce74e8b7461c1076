"""An environment ends quietly however a training script leaves it: dropped without
``close()``, reset in the middle of an episode, stopped by a controller's exception, still open
when the interpreter exits. Each case runs in a real interpreter under ``-W error`` (a warning,
a "Task was destroyed but it is pending!", an "Exception ignored" would show on stderr)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

ENGINES = ("mujoco", pytest.param("pybullet", marks=pytest.mark.pybullet))
TIMEOUT = 120

FAILING = """
from evclock_sims import CartPole

class Failing(CartPole):
    name = "failing"

    async def _monitor(self, clock):
        async for tick in clock.rate(self.monitor_hz, name="monitor"):
            if tick.index == 30:
                raise RuntimeError("the monitor broke")
"""


def run(code: str, engine: str = "mujoco") -> subprocess.CompletedProcess[str]:
    """``code`` in a new interpreter under ``-W error``, with its imports done.

    The engine is imported first: MuJoCo keeps the traceback of an ImportError it catches
    while it is imported (no ``glfw``), and with it every frame of the stack that imported
    it: imported inside ``ScenarioEnv()``, it would keep that environment alive to the end.
    """
    prelude = (
        "import asyncio, gc, sys\nimport numpy as np\n"
        + (
            "import mujoco\n"
            if engine == "mujoco"
            else "import evclock.tools._runs as r\nr.import_pybullet_quietly()\n"
        )  # without its banner
        + "from evclock.gym import ScenarioEnv\n"
    )
    return subprocess.run(
        [sys.executable, "-W", "error", "-c", prelude + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )


def quiet(out: subprocess.CompletedProcess[str], stdout: str, returncode: int = 0) -> None:
    assert (out.returncode, out.stderr, out.stdout) == (returncode, "", stdout)


@pytest.mark.parametrize("engine", ENGINES)
def test_an_environment_dropped_in_the_middle_of_an_episode_ends_quietly(engine: str) -> None:
    out = run(
        f"""
        env = ScenarioEnv("kuka", engine="{engine}")
        env.reset(seed=0)
        for _ in range(5):
            env.step(np.zeros(7))
        loop = env._episodes.loop
        del env  # freed at once: its finalizer ends the episode
        print(loop.is_closed(), asyncio.all_tasks(loop))
    """,
        engine,
    )
    quiet(out, "True set()\n")


def test_an_environment_in_a_reference_cycle_ends_quietly_when_collected() -> None:
    out = run("""
        class Trainer:
            pass

        trainer = Trainer()
        trainer.env = ScenarioEnv("cartpole")
        trainer.env.trainer = trainer  # a cycle: only the garbage collector frees it
        trainer.env.reset(seed=0)
        trainer.env.step(np.zeros(1))
        loop = trainer.env._episodes.loop
        del trainer
        print(loop.is_closed())
        gc.collect()
        print(loop.is_closed(), asyncio.all_tasks(loop))
    """)
    quiet(out, "False\nTrue set()\n")


@pytest.mark.parametrize("engine", ENGINES)
def test_an_environment_open_at_exit_ends_quietly(engine: str) -> None:
    out = run(
        f"""
        import gymnasium
        env = gymnasium.make("evclock/CartPole-v0", engine="{engine}")
        env.reset(seed=0)
        env.step(np.zeros(1))
        env.reset(seed=1)  # a reset in the middle of an episode
        env.step(np.zeros(1))
        print("exiting")
    """,
        engine,
    )
    quiet(out, "exiting\n")


def test_a_controllers_exception_reaches_step_and_nothing_else_is_printed() -> None:
    out = run(
        FAILING
        + """
env = ScenarioEnv(Failing)
env.reset(seed=0)
try:
    for _ in range(100):
        env.step(np.zeros(1))
except RuntimeError as exc:
    print(type(exc).__name__, exc)
env.reset(seed=0)  # the environment goes on
env.step(np.zeros(1))
sys.exit(3)
"""
    )
    quiet(out, "RuntimeError the monitor broke\n", returncode=3)


def test_a_controllers_exception_left_uncaught_prints_its_traceback_only() -> None:
    out = run(
        FAILING
        + """
env = ScenarioEnv(Failing)
env.reset(seed=0)
while True:
    env.step(np.zeros(1))
"""
    )
    assert out.returncode == 1
    assert out.stdout == ""
    lines = out.stderr.splitlines()
    assert lines[0] == "Traceback (most recent call last):"
    assert lines[-1] == "RuntimeError: the monitor broke"
    assert out.stderr.count("Traceback") == 1
    assert "Task" not in out.stderr
    assert "Exception ignored" not in out.stderr
