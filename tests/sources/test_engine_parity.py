"""The same controllers on PyBullet and on MuJoCo: the physics differ, the timing must not.

* The bundled scenarios' controller files, unchanged, reach their targets on both engines
  (within the tolerances stated below).
* Rates, timers and deadlines land on the same step boundaries on both engines: the event
  order of the controllers is identical.
* Determinism on MuJoCo: the same seed gives the same trajectory bit for bit, whatever the
  real-time factor, stepping mode or process.
* ``evclock run kuka --engine mujoco`` (and cart-pole) runs to completion.

The PyBullet halves need PyBullet (wheels for CPython 3.11 only) and are skipped elsewhere;
the MuJoCo halves run on every supported Python.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
import textwrap
from collections.abc import AsyncIterator, Awaitable, Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import mujoco
import pytest

import evclock
from evclock.sources import MuJoCoTimeSource, SteppingTimeSource
from evclock.tools._scenarios import check_engine, load_scenario, open_world
from evclock_sims import CartPole, KukaReach, MuJoCoWorld

ROOT = Path(__file__).resolve().parents[2]
#: Wall seconds a child process may take (it runs a few simulated seconds of MuJoCo).
CHILD_TIMEOUT = 300

needs_pybullet = pytest.mark.pybullet
ENGINES = [pytest.param("pybullet", marks=needs_pybullet), "mujoco"]

#: Mission time on the two engines may differ by this much (seconds): the arm's servos, its
#: IK and the contact models differ, so it settles on a target a few control periods sooner
#: or later; each target is still reached within KukaReach.tolerance (2.5 cm) for the dwell.
KUKA_MISSION_TIME_TOLERANCE_S = 1.5


def run_scenario(name: str, engine: str, seed: int, until: float | None = None) -> Any:
    """Run scenario ``name`` on ``engine`` for its mission (or ``until`` sim seconds)."""
    source, scenario = open_world(load_scenario(name), seed, engine=engine)
    run_for(source, scenario, scenario.default_until if until is None else until)
    return scenario


def run_for(
    source: Any,
    scenario: Any,
    seconds: float,
    *,
    clock: Callable[[], Any] = evclock.clock,
    rtf: float | None = None,
) -> None:
    """Run ``scenario`` on ``source`` (at ``rtf``) with the clock ``clock()`` gives, for
    ``seconds`` of sim time or until its mission ends; the source is closed after."""

    async def main() -> None:
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(seconds):
                await scenario.run(clock())

    try:
        evclock.run(main(), source=source, rtf=rtf)
    finally:
        source.close()


# ------------------------------------------------------------ reaching the targets


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_kuka_controllers_reach_every_target_on_both_engines(seed: int) -> None:
    pytest.importorskip("pybullet")
    results = {engine: run_scenario("kuka", engine, seed) for engine in ("pybullet", "mujoco")}
    for engine, scenario in results.items():
        assert scenario.success(), (engine, scenario.summary())
        assert scenario.final_error <= KukaReach.tolerance, engine
        assert len(scenario.reached_at) == len(scenario.targets), engine
    # Same seed, same targets: the RNG draws do not depend on the engine.
    pybullet_targets = [t.tolist() for t in results["pybullet"].targets]
    assert [t.tolist() for t in results["mujoco"].targets] == pybullet_targets
    times = [scenario.finished_at for scenario in results.values()]
    assert abs(times[0] - times[1]) <= KUKA_MISSION_TIME_TOLERANCE_S, times


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("seed", [0, 1])
def test_the_cartpole_lqr_balances_on_each_engine(engine: str, seed: int) -> None:
    scenario = run_scenario("cartpole", engine, seed)
    summary = scenario.summary()
    assert scenario.success(), summary
    assert summary["balanced_for_s"] == CartPole.hold_time
    # The pole never tips beyond the seeded start tilt (at most 6 degrees) on either engine.
    assert summary["max_angle_rad"] == pytest.approx(abs(summary["initial_tilt_rad"]))
    assert summary["max_cart_offset_m"] < 5.0


# ------------------------------------------------------ the same event order


class RecordingClock:
    """``evclock.clock()`` for a scenario, recording every rate tick: (loop, index, ns)."""

    def __init__(self) -> None:
        self._clock = evclock.clock()
        self.events: list[tuple[str, int, int]] = []

    def now(self) -> Any:
        return self._clock.now()

    def sleep(self, seconds: float) -> Awaitable[None]:
        return self._clock.sleep(seconds)

    async def rate(self, hz: float, *, name: str) -> AsyncIterator[Any]:
        async for tick in self._clock.rate(hz, name=name):
            self.events.append((name, tick.index, tick.actual.nanoseconds))
            yield tick


def kuka_events(engine: str, seconds: float) -> list[tuple[str, int, int]]:
    source, scenario = open_world(KukaReach, 0, engine=engine)
    recorder: list[RecordingClock] = []

    def recording_clock() -> RecordingClock:
        recorder.append(RecordingClock())
        return recorder[-1]

    run_for(source, scenario, seconds, clock=recording_clock)
    return recorder[0].events


@needs_pybullet
def test_the_kuka_controllers_tick_in_the_same_order_at_the_same_steps() -> None:
    pytest.importorskip("pybullet")
    # 2 s: before any seed's mission can end, so both runs hold the same controllers.
    pybullet_events = kuka_events("pybullet", 2.0)
    mujoco_events = kuka_events("mujoco", 2.0)
    # 100 Hz and 10 Hz ticks from 0 s to 2 s; the 2 s timeout, scheduled before the ticks
    # due at 2 s, ends the run first.
    assert len(mujoco_events) == 200 + 21
    assert mujoco_events == pybullet_events


async def timing_controller(source: SteppingTimeSource[Any]) -> list[tuple[str, int]]:
    """Rates, timers, deadlines and step waits, logging (what, sim ns) in the order they run."""
    clock = evclock.clock()
    log: list[tuple[str, int]] = []

    def mark(what: str) -> None:
        log.append((what, clock.now_ns()))

    async def rate(hz: float, name: str, count: int) -> None:
        async for tick in clock.rate(hz, name=name):
            mark(f"{name}#{tick.index}")
            if tick.index + 1 == count:
                return

    async def deadline() -> None:
        try:
            async with asyncio.timeout(0.137):
                await clock.sleep(1.0)
        except TimeoutError:
            mark("deadline")

    timer = clock.timer(0.03, lambda: mark("timer"))
    asyncio.get_running_loop().call_later(0.011, lambda: mark("call_later"))
    async with asyncio.TaskGroup() as group:
        group.create_task(rate(100, "rate100", 25))
        group.create_task(rate(60, "rate60", 15))
        group.create_task(rate(7, "rate7", 2))
        group.create_task(deadline())
        await source.sleep_steps(5)
        mark("5 steps")
        await clock.sleep_until(evclock.Time(0.05, clock_type=evclock.SIM))
        mark("until 0.05")
    timer.cancel()
    return log


def empty_source(engine: str) -> Any:
    if engine == "pybullet":
        from evclock.sources import PyBulletTimeSource

        return PyBulletTimeSource.connect(time_step=1 / 240)
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
    return MuJoCoTimeSource(model, time_step=1 / 240)


@needs_pybullet
def test_rates_timers_and_deadlines_land_on_the_same_steps_on_both_engines() -> None:
    pytest.importorskip("pybullet")
    logs = {}
    for engine in ("pybullet", "mujoco"):
        source = empty_source(engine)
        try:
            logs[engine] = evclock.run(timing_controller(source), source=source)
        finally:
            source.close()
    assert logs["mujoco"] == logs["pybullet"]
    assert ("deadline", 137_500_000) in logs["mujoco"]  # quantised up to step 33
    assert ("5 steps", 20_833_333) in logs["mujoco"]


def test_the_timing_controller_on_mujoco_lands_on_step_boundaries() -> None:
    source = empty_source("mujoco")
    log = evclock.run(timing_controller(source), source=source)
    for what, ns in log:
        steps = -(-ns * 240 // 1_000_000_000)  # the step at or after ns
        assert ns == steps * 1_000_000_000 // 240, what
    assert log[:3] == [("rate100#0", 0), ("rate60#0", 0), ("rate7#0", 0)]
    # 10 ms and 11 ms are both due at step 3 (12.5 ms): a plain callback runs at once, the
    # rate's task on the next pass.
    assert log[3:5] == [("call_later", 12_500_000), ("rate100#1", 12_500_000)]


# ------------------------------------------------------------- determinism


def mujoco_kuka_final_state(seed: int, rtf: float | None, hook: bool) -> tuple[bytes, str]:
    world = MuJoCoWorld()
    scenario = KukaReach(world, seed)
    source = world.time_source()
    if hook:
        source.add_step_hook(lambda: None)  # steps one at a time instead of nstep runs
    run_for(source, scenario, 3.0, rtf=rtf)
    return world.data.qpos.tobytes() + world.data.qvel.tobytes(), json.dumps(scenario.summary())


def test_the_same_seed_gives_the_same_mujoco_trajectory_at_any_rtf_and_stepping() -> None:
    reference = mujoco_kuka_final_state(1, None, hook=False)
    assert mujoco_kuka_final_state(1, 20.0, hook=False) == reference
    assert mujoco_kuka_final_state(1, None, hook=True) == reference
    assert mujoco_kuka_final_state(2, None, hook=False) != reference


def test_the_same_seed_gives_the_same_mujoco_trajectory_in_another_process() -> None:
    code = textwrap.dedent(
        """
        import sys
        sys.modules["pybullet"] = None  # MuJoCo runs need no PyBullet
        sys.path.insert(0, sys.argv[1])
        from tests.sources.test_engine_parity import mujoco_kuka_final_state
        state, summary = mujoco_kuka_final_state(1, None, hook=False)
        print(state.hex())
        print(summary)
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(ROOT)],
        capture_output=True,
        text=True,
        timeout=CHILD_TIMEOUT,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    state_hex, summary = result.stdout.split()[0], result.stdout.split("\n", 1)[1].strip()
    state, reference_summary = mujoco_kuka_final_state(1, None, hook=False)
    assert state_hex == state.hex()
    assert summary == reference_summary


# --------------------------------------------------------- engine selection


def test_open_world_builds_the_scenario_on_the_chosen_engine() -> None:
    source, scenario = open_world(KukaReach, 0, engine="mujoco")
    assert isinstance(source, MuJoCoTimeSource)
    assert scenario.engine == "mujoco"
    assert source.model is scenario.world.model
    assert source.time_step_ns == Fraction(12_500_000, 3)  # 1/240 s
    with pytest.raises(evclock.InvalidArgumentError) as info:
        open_world(KukaReach, 0, engine="gazebo")
    assert str(info.value) == "unknown engine 'gazebo'; valid engines: pybullet, mujoco"
    with pytest.raises(evclock.InvalidArgumentError) as info:
        open_world(KukaReach, 0, engine="mujoco", gui=True)
    assert str(info.value) == (
        "--gui opens PyBullet's GUI, which MuJoCo runs do not have: drop --gui"
    )


def test_a_pybullet_only_scenario_refuses_mujoco_by_name() -> None:
    class Patrol:
        name = "patrol"

    with pytest.raises(evclock.InvalidArgumentError) as info:
        check_engine(Patrol, "mujoco")
    assert str(info.value) == (
        "scenario 'patrol' runs on pybullet only, not on mujoco: drop --engine mujoco"
    )


# ----------------------------------------------------------------- the command


def evclock_cli(*args: str, hide_pybullet: bool) -> subprocess.CompletedProcess[str]:
    code = textwrap.dedent(
        f"""
        import sys
        if {hide_pybullet!r}:
            sys.modules["pybullet"] = None
            sys.modules["pybullet_data"] = None
        from evclock.tools._cli import main
        sys.argv = ["evclock", *{list(args)!r}]
        main()
        """
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=CHILD_TIMEOUT,
        check=False,
        env={**os.environ, "COLUMNS": "200", "NO_COLOR": "1"},
    )


@pytest.mark.parametrize("name", ["kuka", "cartpole"])
def test_evclock_run_engine_mujoco_runs_without_pybullet(name: str, tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    result = evclock_cli(
        "run", name, "--engine", "mujoco", "--quiet", "--json", str(out), hide_pybullet=True
    )
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(out.read_text())
    assert report["verdict"] == "success"
    assert report["scenario"] == name
    assert report["engine"] == "mujoco"
    assert report["summary"]["success"] is True
    assert f": {name} on mujoco, seed 0, sim time" in result.stdout.splitlines()[0]


@needs_pybullet
def test_the_shipped_models_are_pybullet_datas_byte_for_byte() -> None:
    # So a MuJoCo run is the same with PyBullet's data installed (3.11) or without (3.12+).
    pybullet_data = pytest.importorskip("pybullet_data")
    from evclock_sims._mujoco import MODELS

    shipped = sorted(p for p in MODELS.rglob("*") if p.is_file() and p.name != "LICENSE.txt")
    assert len(shipped) == 10  # the two URDFs and the arm's eight collision meshes
    for path in shipped:
        original = Path(pybullet_data.getDataPath()) / path.relative_to(MODELS)
        assert path.read_bytes() == original.read_bytes(), path


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (
            ["run", "kuka", "--gui"],
            "error: --gui opens PyBullet's GUI, which MuJoCo runs do not have: drop --gui",
        ),
        pytest.param(
            ["run", "husky"],
            "error: scenario 'husky' runs on pybullet only, not on mujoco: drop --engine mujoco",
            marks=needs_pybullet,  # without it: tests/tools/test_cli_missing_engines.py
        ),
    ],
)
def test_evclock_run_engine_mujoco_refuses_what_only_pybullet_does(
    args: list[str], error: str
) -> None:
    result = evclock_cli(*args, "--engine", "mujoco", "--quiet", hide_pybullet=False)
    assert result.returncode == 2, result.stdout + result.stderr
    assert " ".join(result.stderr.split()) == error


def test_evclock_run_without_pybullet_points_to_mujoco() -> None:
    result = evclock_cli("run", "kuka", "--quiet", hide_pybullet=True)
    assert result.returncode == 2, result.stdout + result.stderr
    assert " ".join(result.stderr.split()) == (
        "error: scenario 'kuka' runs on PyBullet by default, which is not installed: pip "
        "install 'evclock[pybullet]' (PyBullet has wheels for CPython 3.11 only; on another "
        "Python pip builds it from source, which needs a C++ compiler and about half an hour); "
        "or run it on MuJoCo: --engine mujoco"
    )
