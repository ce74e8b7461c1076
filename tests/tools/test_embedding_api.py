"""Scenario and embedding API: a scenario's per-physics-step hooks (a force applied every step,
which PyBullet clears after each one) and ``await SimDriver.step(n)``."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest

import evclock
from evclock.tools import run_scenario

TIMEOUT = 240  # wall seconds: a guard against hangs, not a timing check

#: A cart on a rail, its motor off: ``pushed`` applies a 5 N force before every step (or only
#: once, in the mission, with ``every_step = false``). Records the time the clock reads in
#: each hook.
PUSHED = """\
import pybullet as p

from evclock_sims import Scenario


class Pushed(Scenario):
    name = "pushed"
    description = "a cart pushed by 5 N for 1 s"
    default_until = 5.0
    every_step = True
    force_n = 5.0

    def __init__(self, client, seed=0):
        super().__init__(client, seed)
        self.cart = self.load_urdf("cartpole.urdf", useFixedBase=True)
        for joint in (0, 1):
            p.setJointMotorControl2(self.cart, joint, p.VELOCITY_CONTROL, force=0,
                                    physicsClientId=client)
        self.before: list[int] = []
        self.after: list[int] = []
        self.clock = None

    def _push(self):
        p.applyExternalForce(self.cart, 0, [self.force_n, 0, 0], [0, 0, 0], p.LINK_FRAME,
                             physicsClientId=self.client)

    def before_step(self):
        self.before.append(self.clock.now().nanoseconds)
        if self.every_step:
            self._push()

    def after_step(self):
        self.after.append(self.clock.now().nanoseconds)

    def _services(self, clock):
        return {}

    async def _mission(self, clock):
        if not self.every_step:
            self._push()
        await clock.sleep(1.0)

    async def run(self, clock):
        self.clock = clock
        await super().run(clock)

    def success(self):
        return True

    def _metrics(self):
        x = p.getJointState(self.cart, 0, physicsClientId=self.client)[0]
        return {"cart_x_m": x, "before": len(self.before), "after": len(self.after),
                "hook_times": __import__("json").dumps([self.before[:3], self.after[:3]])}
"""


@pytest.fixture
def pushed(tmp_path: Path) -> str:
    path = tmp_path / "pushed.py"
    path.write_text(PUSHED)
    return str(path)


@pytest.mark.pybullet
def test_a_force_applied_before_every_step_moves_the_cart(pushed: str) -> None:
    hooked = run_scenario(pushed)
    once = run_scenario(pushed, params={"every_step": False})
    step_ns = 1_000_000_000 / 240
    assert hooked.sim_time_s == 1.0
    # One call per physics step, at the step's time: before reads t_k, after reads t_k+1.
    assert hooked.summary["before"] == hooked.summary["after"] == 240
    before, after = json.loads(hooked.summary["hook_times"])
    assert [round(t / step_ns) for t in before] == [0, 1, 2]
    assert [round(t / step_ns) for t in after] == [1, 2, 3]
    # PyBullet clears an external force after each step: applied once it barely moves the
    # cart; applied before every step it pushes it all along.
    assert hooked.summary["cart_x_m"] > 20 * once.summary["cart_x_m"] > 0
    assert once.summary["before"] == 240  # the hooks still run; only the push differs


@pytest.mark.pybullet
def test_step_hooks_run_in_wall_mode_and_through_the_command(pushed: str, tmp_path: Path) -> None:
    wall = run_scenario(pushed, wall=True, until=0.3)
    assert wall.summary["before"] == wall.summary["after"] > 0
    assert wall.summary["cart_x_m"] > 0
    out = tmp_path / "r.json"
    proc = subprocess.run(
        [sys.executable, "-m", "evclock", "run", pushed, "--quiet", "--json", str(out)],
        capture_output=True, text=True, timeout=TIMEOUT, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (
        json.loads(out.read_text())["summary"]["cart_x_m"]
        == run_scenario(pushed).summary["cart_x_m"]
    )


def test_awaiting_step_n_returns_after_the_steps_on_virtual_time() -> None:
    async def main() -> list[float]:
        seen: list[float] = []

        async def ticker() -> None:
            async for tick in evclock.clock().rate(10, name="ticker"):
                seen.append(tick.actual.seconds)

        async with evclock.SimDriver(paused=True, rtf=None) as sim:
            task = asyncio.create_task(ticker())
            await sim.run_until(0.0)  # the ticker's first tick, at 0
            steps = sim.step(3)
            assert repr(steps).startswith("<Steps of ")
            await steps
            # Three increments: jumps to the next three deadlines, their work settled.
            assert sim.now().seconds == pytest.approx(0.3)
            assert seen == pytest.approx([0.0, 0.1, 0.2, 0.3])
            await sim.step(1)
            assert seen == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])
            sim.step(2)  # not awaited: only requested, as before
            await sim.run_until(0.6)
            assert sim.now().seconds == pytest.approx(0.6)
            with pytest.raises(evclock.InvalidArgumentError):
                sim.step(0)
            sim.resume()
            with pytest.raises(evclock.PacingError):
                sim.step(1)
            task.cancel()
        return seen

    asyncio.run(main())


@pytest.mark.pybullet
def test_awaiting_step_n_takes_n_physics_steps() -> None:
    from evclock.sources import PyBulletTimeSource

    async def main() -> None:
        source = PyBulletTimeSource.connect()
        try:
            async with evclock.SimDriver(source, paused=True, rtf=None) as sim:
                await sim.step(5)
                assert sim.now_ns == round(5 * 1e9 / 240)
                await sim.step(235)
                assert sim.now().seconds == pytest.approx(1.0)
        finally:
            source.close()

    asyncio.run(main())


def test_awaiting_steps_of_a_stopped_driver_raises() -> None:
    async def main() -> None:
        sim = evclock.SimDriver(paused=True, rtf=None)
        sim.start()
        await asyncio.sleep(0)
        steps = sim.step(1)
        await sim.stop()
        with pytest.raises(evclock.LoopClosedError):
            await steps

    asyncio.run(main())


@pytest.mark.pybullet
def test_a_scenario_without_hooks_registers_none(pushed: str) -> None:
    import pybullet as p

    from evclock.tools._runs import step_hooks_of
    from evclock.tools._scenarios import load_scenario
    from evclock_sims.cartpole import CartPole

    client = p.connect(p.DIRECT)
    try:
        assert step_hooks_of(CartPole(client, 0)) == (None, None)
        hooked = load_scenario(pushed)(client, 0)
        before, after = step_hooks_of(hooked)
        assert (before.__func__, after.__func__) == (
            type(hooked).before_step,
            type(hooked).after_step,
        )
    finally:
        p.disconnect(client)
