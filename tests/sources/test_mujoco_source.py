"""MuJoCoTimeSource: exact step-counted sim time over ``mj_step``, nstep runs, step hooks,
wait_until, snapshots and resets as jumps, time-step changes, and MuJoCo's failures as
evclock errors.

Every test steps real MuJoCo models; nothing asserts wall time. MuJoCo is in the ``test``
extra on every supported Python, so these tests are never skipped.
"""

from __future__ import annotations

import asyncio
import math
import re
import subprocess
import sys
import textwrap
from collections.abc import Awaitable, Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

import evclock
from evclock import (
    SIM,
    ClockJumpedError,
    Duration,
    InvalidArgumentError,
    InvalidTypeError,
    PhysicsError,
    Time,
    TimeJump,
)
from evclock.sources import MuJoCoTimeSource

NS = 1_000_000_000
STEP_NS = Fraction(NS, 240)

#: A pendulum on a hinge (about y) and a slider pushed by a motor; named keyframe "tilted".
PENDULUM = """
<mujoco model="pendulum">
  <option timestep="{dt}"/>
  <worldbody>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.01"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/>
    </body>
    <body name="cart" pos="2 0 0">
      <joint name="slide" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor name="push" joint="slide"/></actuator>
  <keyframe><key name="tilted" qpos="0.8 0.25"/></keyframe>
</mujoco>
"""


def pendulum(dt: str = "0.004166666666666667", tilt: float = 0.5) -> MuJoCoTimeSource:
    model = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=dt))
    source = MuJoCoTimeSource(model)
    source.data.qpos[0] = tilt
    mujoco.mj_forward(model, source.data)
    return source


def run(main: Callable[[], Awaitable[Any]], source: MuJoCoTimeSource, **kwargs: Any) -> Any:
    return evclock.run(main(), source=source, **kwargs)


def raises_exactly(error: type[BaseException], message: str) -> Any:
    return pytest.raises(error, match="^" + re.escape(message) + "$")


def step_time(index: int, step_ns: Fraction = STEP_NS) -> int:
    return math.floor(index * step_ns)


def count_mj_step_calls(source: MuJoCoTimeSource) -> list[int]:
    """Record the ``nstep`` of every ``mj_step`` call the source makes."""
    calls: list[int] = []
    real = source._mj_step

    def counting(model: Any, data: Any, nstep: int = 1) -> None:
        calls.append(nstep)
        real(model, data, nstep)

    source._mj_step = counting
    return calls


# ------------------------------------------------------------------- construction


def test_the_source_needs_a_model_and_its_own_data() -> None:
    with raises_exactly(
        InvalidTypeError,
        "MuJoCoTimeSource needs a mujoco.MjModel, got str; load one with "
        "mujoco.MjModel.from_xml_path(path) or use MuJoCoTimeSource.load(path)",
    ):
        MuJoCoTimeSource("model.xml")
    model = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=0.01))
    with raises_exactly(
        InvalidTypeError, "MuJoCoTimeSource's data must be a mujoco.MjData, got int"
    ):
        MuJoCoTimeSource(model, 3)
    other = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
    with raises_exactly(
        InvalidArgumentError,
        "this MjData was not made for this MjModel (its qpos, qvel, act or ctrl sizes differ); "
        "pass mujoco.MjData(model) of the same model",
    ):
        MuJoCoTimeSource(model, mujoco.MjData(other))
    data = mujoco.MjData(model)
    source = MuJoCoTimeSource(model, data)
    assert source.model is model
    assert source.data is data
    assert source.time_step == 0.01
    assert source.time_step_ns == Fraction(10_000_000)


@pytest.mark.parametrize("timestep", ["0", "-0.01"])
def test_a_model_without_a_time_step_is_refused(timestep: str) -> None:
    model = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=timestep))
    with raises_exactly(
        PhysicsError,
        f"the MuJoCo model has opt.timestep={float(timestep)!r}, which is not a positive finite "
        'number of seconds; set one in the model (<option timestep="0.002"/>), with '
        "MuJoCoTimeSource(model, time_step=1/240) or source.set_time_step(1/240)",
    ):
        MuJoCoTimeSource(model)
    # The way out the message gives.
    source = MuJoCoTimeSource(model, time_step=Fraction(1, 240))
    assert model.opt.timestep == 1 / 240
    assert source.time_step_ns == STEP_NS


def test_load_reads_a_model_file(tmp_path: Path) -> None:
    path = tmp_path / "pendulum.xml"
    path.write_text(PENDULUM.format(dt=0.002))
    source = MuJoCoTimeSource.load(path, time_step=1 / 240, start_ns=5)
    assert source.model.nq == 2
    assert source.time_step_ns == STEP_NS
    assert source.now_ns == 5
    assert source.describe() == "MuJoCo physics (model 'pendulum', dt=1/240 s)"
    assert repr(source) == (
        "<MuJoCoTimeSource MuJoCo physics (model 'pendulum', dt=1/240 s) now=0.000000005 s (sim)>"
    )


def test_a_model_file_that_does_not_load_names_the_path_and_mujocos_reason(
    tmp_path: Path,
) -> None:
    missing = tmp_path / "missing.xml"
    with raises_exactly(
        PhysicsError,
        f"MuJoCo could not load the model file {str(missing)!r}: ParseXML: Error opening file "
        f"'{missing}'; check that the file exists and is valid MJCF (or URDF), and the paths "
        "of its meshes",
    ):
        MuJoCoTimeSource.load(missing)
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody/><bogus/></mujoco>")
    with raises_exactly(
        PhysicsError,
        f"MuJoCo could not load the model file {str(broken)!r}: XML Error: Schema violation: "
        "unrecognized element Element 'bogus', line 1; check that the file exists and is "
        "valid MJCF (or URDF), and the paths of its meshes",
    ):
        MuJoCoTimeSource.load(broken)
    with raises_exactly(InvalidTypeError, "MuJoCoTimeSource.load() takes a file path, got int"):
        MuJoCoTimeSource.load(3)  # type: ignore[arg-type]


def test_importing_evclock_sources_does_not_import_mujoco() -> None:
    code = "import sys, evclock.sources; print('mujoco' in sys.modules, 'numpy' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout == "False False\n"


def test_without_mujoco_the_error_names_the_extra() -> None:
    code = textwrap.dedent(
        """
        import sys
        sys.modules["mujoco"] = None
        import evclock
        try:
            evclock.sources.MuJoCoTimeSource.load("x.xml")
        except evclock.MissingExtraError as exc:
            print(exc)
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == (
        "MuJoCoTimeSource needs 'mujoco', which is not installed; install it with: "
        "pip install 'evclock[mujoco]'"
    )


# --------------------------------------------------------------------------- time


def test_240_steps_are_exactly_one_second_and_data_time_is_never_the_clock() -> None:
    source = pendulum()
    source.data.time = 1000.0  # MuJoCo's own float time: evclock never reads it

    async def main() -> tuple[int, int]:
        await evclock.clock().sleep(0.5)
        source.data.time = -3.0
        await evclock.clock().sleep(0.5)
        return evclock.clock().now_ns(), source.step_index

    assert run(main, source) == (NS, 240)


def test_a_simulated_day_does_not_drift_where_mujocos_float_time_does() -> None:
    # 0.1 s is not a binary fraction: MuJoCo's data.time accumulates its rounding.
    source = pendulum(dt="0.1")
    day = 24 * 3600

    async def main() -> int:
        await evclock.clock().sleep(day)
        return evclock.clock().now_ns()

    assert run(main, source) == day * NS
    assert source.step_index == day * 10
    assert source.data.time != day  # the float sum drifted; evclock's count did not


def test_runs_of_steps_are_one_mj_step_call_when_nothing_is_due_between() -> None:
    source = pendulum()
    calls = count_mj_step_calls(source)

    async def main() -> None:
        await evclock.clock().sleep(1.0)

    run(main, source)
    assert calls == [240]


def test_nstep_runs_and_single_steps_give_the_same_trajectory_bit_for_bit() -> None:
    chunked, single = pendulum(), pendulum()
    calls = count_mj_step_calls(single)
    single.add_step_hook(lambda: None)  # a hook: one step at a time

    async def main() -> None:
        await evclock.clock().sleep(2.0)

    run(main, chunked)
    run(main, single)
    assert calls == [1] * 480
    assert chunked.data.qpos.tobytes() == single.data.qpos.tobytes()
    assert chunked.data.qvel.tobytes() == single.data.qvel.tobytes()


def test_sleeps_are_quantised_up_to_step_boundaries() -> None:
    source = pendulum()

    async def main() -> list[int]:
        clock = evclock.clock()
        woke = []
        for seconds in (0.001, 0.01, 1 / 240):
            await clock.sleep(seconds)
            woke.append(clock.now_ns())
        await source.sleep_steps(3)
        woke.append(clock.now_ns())
        return woke

    # 1 ms -> up to step 1; 10 ms more -> up to step 4 (16.67 ms); 1/240 s more ends at
    # 20833333 ns, exactly step 5's time; then 3 whole steps.
    assert run(main, source) == [step_time(1), step_time(4), step_time(5), step_time(8)]


# ------------------------------------------------------------------- the time step


def test_a_time_step_changed_on_the_model_is_detected_and_rebases_time() -> None:
    source = pendulum()

    async def main() -> tuple[int, int]:
        clock = evclock.clock()
        await source.sleep_steps(24)  # 0.1 s
        source.model.opt.timestep = 0.01
        await clock.sleep(0.05)
        return clock.now_ns(), source.step_index

    assert run(main, source) == (NS // 10 + 50_000_000, 29)
    assert source.time_step_ns == Fraction(10_000_000)


def test_an_unwatched_model_change_is_not_seen_but_set_time_step_is() -> None:
    model = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=0.01))
    source = MuJoCoTimeSource(model, watch_time_step=False)

    async def main() -> tuple[int, int]:
        clock = evclock.clock()
        model.opt.timestep = 0.02  # not watched: the source still counts 10 ms steps
        await clock.sleep(0.1)
        source.set_time_step(Duration(seconds=0.005))
        await clock.sleep(0.1)
        return clock.now_ns(), source.step_index

    assert run(main, source) == (200_000_000, 30)
    assert model.opt.timestep == 0.005


def test_a_time_step_set_to_zero_mid_run_is_a_clear_error() -> None:
    source = pendulum()

    async def main() -> None:
        await evclock.clock().sleep(0.1)
        source.model.opt.timestep = 0.0
        await evclock.clock().sleep(0.1)

    with pytest.raises(PhysicsError, match=r"^the MuJoCo model has opt.timestep=0.0, which"):
        run(main, source)


# ---------------------------------------------------------- hooks and predicate waits


def test_step_hooks_run_around_each_step_and_can_apply_controls() -> None:
    source = pendulum()
    seen: list[tuple[str, int]] = []

    def push() -> None:
        source.data.ctrl[0] = 1.0  # 1 N on a 1 kg cart, from the first step

    async def main() -> None:
        clock = evclock.clock()
        before = source.add_step_hook(lambda: seen.append(("before", clock.now_ns())), "before")
        source.add_step_hook(push, "before")
        source.add_step_hook(lambda: seen.append(("after", clock.now_ns())))
        await source.sleep_steps(2)
        before.remove()
        await source.sleep_steps(1)

    run(main, source)
    assert seen == [
        ("before", 0),
        ("after", step_time(1)),
        ("before", step_time(1)),
        ("after", step_time(2)),
        ("after", step_time(3)),
    ]
    assert source.data.qvel[1] == pytest.approx(3 / 240, rel=1e-9)  # v = a t, a = 1 m/s^2


def test_wait_until_resolves_at_the_first_step_where_the_predicate_holds() -> None:
    source = pendulum()
    calls = count_mj_step_calls(source)

    async def main() -> tuple[Time, int]:
        # The pendulum released at 0.5 rad swings through the bottom.
        at = await source.wait_until(lambda: source.data.qpos[0] <= 0.0, timeout=5.0)
        return at, source.step_index

    at, index = run(main, source)
    assert at == Time(nanoseconds=step_time(index), clock_type=SIM)
    assert source.data.qpos[0] <= 0.0
    assert 1 <= index < 240
    assert calls == [1] * index  # predicate waits step one at a time


def test_wait_until_times_out_in_sim_time() -> None:
    source = pendulum()

    async def main() -> int:
        with pytest.raises(evclock.SimTimeLimitError, match=r"stayed false for 0\.5"):
            await source.wait_until(lambda: source.data.qpos[0] > 1.0, timeout=0.5)
        return evclock.clock().now_ns()

    assert run(main, source) == step_time(120)


# ------------------------------------------------------------ snapshots and resets


def test_restore_replays_bit_for_bit_and_is_a_jump_that_wakes_sleepers() -> None:
    source = pendulum()
    log: list[TimeJump] = []

    async def main() -> None:
        clock = evclock.clock()
        clock.on_jump(post=log.append)
        await clock.sleep(0.5)
        saved = source.save_state()
        await clock.sleep(0.5)
        first = (source.data.qpos.tobytes(), source.data.qvel.tobytes())
        sleeper = asyncio.ensure_future(clock.sleep(10.0))
        await asyncio.sleep(0)
        jump = source.restore_state(saved)
        assert jump == TimeJump(Time(1.0, clock_type=SIM), Time(0.5, clock_type=SIM))
        with pytest.raises(ClockJumpedError):
            await sleeper
        assert clock.now_ns() == NS // 2
        assert source.step_index == 120
        await clock.sleep(0.5)
        assert (source.data.qpos.tobytes(), source.data.qvel.tobytes()) == first
        source.remove_state(saved)
        with pytest.raises(InvalidArgumentError, match=r"^unknown state id 1"):
            source.restore_state(saved)

    run(main, source)
    assert [jump.delta for jump in log] == [Duration(seconds=-0.5)]


def test_restore_recomputes_positions_for_controllers() -> None:
    source = pendulum()

    async def main() -> None:
        saved = source.save_state()
        before = source.data.xipos[1].copy()
        await evclock.clock().sleep(0.5)
        assert not np.array_equal(source.data.xipos[1], before)
        source.restore_state(saved)
        assert np.array_equal(source.data.xipos[1], before)  # no step needed to see it

    run(main, source)


def test_reset_goes_back_to_the_model_defaults_or_a_keyframe() -> None:
    source = pendulum()

    async def main() -> None:
        clock = evclock.clock()
        await clock.sleep(1.0)
        jump = source.reset_simulation()
        assert jump is not None
        assert jump.delta == Duration(seconds=-1)
        assert clock.now_ns() == 0
        assert source.step_index == 0
        assert source.data.qpos.tolist() == [0.0, 0.0]
        await clock.sleep(0.5)
        source.reset_simulation(start=Time(2.0, clock_type=SIM), keyframe="tilted")
        assert clock.now_ns() == 2 * NS
        assert source.data.qpos.tolist() == [0.8, 0.25]
        assert source.reset_simulation(start=2.0, keyframe=0) is None  # same time: no jump
        with raises_exactly(InvalidArgumentError, "the MuJoCo model has no keyframe named 'nope'"):
            source.reset_simulation(keyframe="nope")
        with raises_exactly(
            InvalidArgumentError, "keyframe index 1 is out of range: the model has 1"
        ):
            source.reset_simulation(keyframe=1)

    run(main, source)


def test_snapshots_and_resets_are_refused_inside_a_step_hook() -> None:
    source = pendulum()
    errors: list[BaseException | None] = []

    async def main() -> None:
        hook = source.add_step_hook(lambda: source.reset_simulation())
        await source.sleep_steps(2)
        errors.append(hook.exception())

    evclock.run(main(), source=source)
    assert isinstance(errors[0], PhysicsError)
    assert str(errors[0]).startswith("reset_simulation() cannot be called from a step hook")


# ------------------------------------------------------------- MuJoCo's bad states


@pytest.fixture
def in_tmp_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """MuJoCo appends its warnings to MUJOCO_LOG.TXT in the working directory: not ours."""
    monkeypatch.chdir(tmp_path)


@pytest.mark.usefixtures("in_tmp_path")
def test_a_nan_force_in_a_run_of_steps_names_the_failing_step() -> None:
    source = pendulum()

    async def main() -> None:
        clock = evclock.clock()
        await source.sleep_steps(240)
        source.data.qfrc_applied[0] = math.nan  # the next step's acceleration is NaN
        await clock.sleep(1.0)

    calls = count_mj_step_calls(source)
    with raises_exactly(
        PhysicsError,
        "MuJoCo reported mjWARN_BADQACC in step 241 (from sim time 1 s to 1.004166666 s): a "
        "NaN, infinite or huge acceleration (qacc) at DOF 0. The simulation is unstable and "
        "MuJoCo reset its data; lower the time step, add joint damping or armature, or check "
        "the controls and forces applied before that step",
    ):
        run(main, source)
    assert calls == [240, 240, 1]  # found inside a run of 240 steps: its first step


#: A hinge whose spring is far too stiff for explicit Euler at 4 ms: the motion blows up
#: in step 4, MuJoCo resets the data (time included), and it blows up again, and again.
UNSTABLE = """
<mujoco model="unstable">
  <option timestep="0.004" integrator="Euler"/>
  <worldbody>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 1 0" stiffness="1e6" springref="1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.usefixtures("in_tmp_path")
@pytest.mark.parametrize("stepping", ["one run of mj_step", "one step at a time"])
def test_a_model_that_goes_bad_again_and_again_is_reported_at_its_first_failing_step(
    stepping: str,
) -> None:
    # By hand, one mj_step at a time: the first failure is in step 4...
    model = mujoco.MjModel.from_xml_string(UNSTABLE)
    by_hand = mujoco.MjData(model)
    steps = 0
    while not by_hand.warning.number.any():
        mujoco.mj_step(model, by_hand)
        steps += 1
    assert steps == 4
    # ...and a run of 250 steps ends with MuJoCo's time reset by a later failure.
    whole_run = mujoco.MjData(model)
    mujoco.mj_step(model, whole_run, 250)
    assert whole_run.time < 0.1

    source = MuJoCoTimeSource(mujoco.MjModel.from_xml_string(UNSTABLE))

    async def main() -> None:
        if stepping == "one step at a time":
            source.add_step_hook(lambda: None)
        await evclock.clock().sleep(1.0)

    calls = count_mj_step_calls(source)
    with raises_exactly(
        PhysicsError,
        "MuJoCo reported mjWARN_BADQACC in step 4 (from sim time 0.012 s to 0.016 s): a "
        "NaN, infinite or huge acceleration (qacc) at DOF 0. The simulation is unstable and "
        "MuJoCo reset its data; lower the time step, add joint damping or armature, or check "
        "the controls and forces applied before that step",
    ):
        run(main, source)
    if stepping == "one run of mj_step":
        assert calls == [250, 1, 1, 1, 1]  # the run, then again one step at a time to step 4
    else:
        assert calls == [1, 1, 1, 1]
    # Either way the data is left as stepping by hand left it.
    assert source.data.time == by_hand.time
    assert source.data.qpos.tolist() == by_hand.qpos.tolist()
    assert source.data.qvel.tolist() == by_hand.qvel.tolist()
    # The bad-state counters, once reported, are zeroed (every failure must show again).
    assert by_hand.warning.number[mujoco.mjtWarning.mjWARN_BADQACC] == 1
    assert not source.data.warning.number.any()


@pytest.mark.usefixtures("in_tmp_path")
@pytest.mark.parametrize("before", ["stepped by hand until it failed", "a source reported it"])
def test_a_failure_is_seen_in_data_that_failed_before(before: str) -> None:
    # MuJoCo's counter of a bad-state warning reads 1 after every failure: a source taking
    # over data that failed before (stepped by hand, or under a source that reported it)
    # must still see the next failure.
    model = mujoco.MjModel.from_xml_string(UNSTABLE)
    data = mujoco.MjData(model)

    async def until_it_fails() -> None:
        await evclock.clock().sleep(1.0)

    if before == "stepped by hand until it failed":
        mujoco.mj_step(model, data, 4)  # fails in step 4: MuJoCo resets, counts 1
    else:
        with pytest.raises(PhysicsError):
            run(until_it_fails, MuJoCoTimeSource(model, data))
    with raises_exactly(
        PhysicsError,
        "MuJoCo reported mjWARN_BADQACC in step 3 (from sim time 0.008 s to 0.012 s): a NaN, "
        "infinite or huge acceleration (qacc) at DOF 0. The simulation is unstable and MuJoCo "
        "reset its data; lower the time step, add joint damping or armature, or check the "
        "controls and forces applied before that step",
    ):
        run(until_it_fails, MuJoCoTimeSource(model, data))


@pytest.mark.usefixtures("in_tmp_path")
def test_a_nan_control_is_reported_at_the_step_that_used_it() -> None:
    source = pendulum()

    def bad_control() -> None:
        if source.step_index == 5:
            source.data.ctrl[0] = math.nan

    async def main() -> None:
        source.add_step_hook(bad_control, "before")
        await evclock.clock().sleep(1.0)

    with pytest.raises(PhysicsError) as info:
        run(main, source)
    assert str(info.value) == (
        "MuJoCo reported mjWARN_BADCTRL in step 6 (from sim time 0.020833333 s to 0.025 s): "
        "a NaN, infinite or huge control (ctrl) at actuator 0. MuJoCo zeroed the controls; "
        "check the controls set before that step"
    )


def test_other_warnings_and_earlier_ones_are_not_errors() -> None:
    model = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=0.01))
    data = mujoco.MjData(model)
    data.warning.number[int(mujoco.mjtWarning.mjWARN_BADQACC)] = 2  # before evclock took over
    source = MuJoCoTimeSource(model, data)
    contact_full = int(mujoco.mjtWarning.mjWARN_CONTACTFULL)

    def buffer_full() -> None:  # a warning that leaves a valid state
        data.warning.number[contact_full] += 1

    async def main() -> int:
        hook = source.add_step_hook(buffer_full)
        await evclock.clock().sleep(0.05)
        hook.remove()
        await evclock.clock().sleep(0.05)
        return source.step_index

    assert run(main, source) == 10
    assert data.warning.number[contact_full] == 5
