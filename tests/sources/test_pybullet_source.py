"""PyBulletTimeSource: exact step-counted sim time, step hooks, wait_until, resets, bad input.

Every test drives real PyBullet DIRECT clients; nothing asserts wall time. Pacing, pause
and step with this source are in ``test_pacing.py``.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import re
import struct
import subprocess
import sys
from collections.abc import Awaitable, Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import pytest
from _examples import run_example

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")
import pybullet as p

import evclock
from evclock import (
    SIM,
    ClockJumpedError,
    ClockMismatchError,
    Duration,
    InvalidArgumentError,
    InvalidTypeError,
    JumpThreshold,
    NotRunningError,
    PhysicsError,
    SimEventLoop,
    SimTimeLimitError,
    Time,
    TimeJump,
)
from evclock.sources import PyBulletTimeSource, exact_time_step

NS = 1_000_000_000
STEP_NS = Fraction(NS, 240)  # PyBullet's default time step, exactly
ROOT = Path(__file__).resolve().parents[2]


def raises_exactly(error: type[BaseException], message: str) -> Any:
    return pytest.raises(error, match="^" + re.escape(message) + "$")


def step_time(index: int, step_ns: Fraction = STEP_NS) -> int:
    return math.floor(index * step_ns)


def box_world(cid: int, height: float = 1.0) -> tuple[int, int]:
    """A plane and a 0.2 m box dropped from ``height``; returns (plane, box)."""
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    plane_shape = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
    plane = p.createMultiBody(0, plane_shape, physicsClientId=cid)
    box_shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.1] * 3, physicsClientId=cid)
    box = p.createMultiBody(1.0, box_shape, basePosition=[0, 0, height], physicsClientId=cid)
    return plane, box


def z_of(cid: int, body: int) -> float:
    return float(p.getBasePositionAndOrientation(body, physicsClientId=cid)[0][2])


def set_at_step(source: PyBulletTimeSource, event: asyncio.Event, index: int) -> Callable[[], None]:
    """A step hook that sets ``event`` after step ``index``."""

    def hook() -> None:
        if source.step_index == index:
            event.set()

    return hook


def run(main: Callable[[], Awaitable[Any]], source: PyBulletTimeSource, **kwargs: Any) -> Any:
    async def wrapper() -> Any:
        return await main()

    return evclock.run(wrapper(), source=source, **kwargs)


# ----------------------------------------------------------------------------- construction


def test_needs_at_least_one_client() -> None:
    with raises_exactly(
        InvalidArgumentError,
        "PyBulletTimeSource needs at least one connected PyBullet client id, e.g. "
        "PyBulletTimeSource(p.connect(p.DIRECT)), or use PyBulletTimeSource.connect()",
    ):
        PyBulletTimeSource()


@pytest.mark.parametrize(("bad", "name"), [("0", "str"), (True, "bool"), (0.0, "float")])
def test_client_ids_are_ints(bad: Any, name: str) -> None:
    with raises_exactly(
        InvalidTypeError, f"PyBullet clients are int ids returned by p.connect(), got {name}"
    ):
        PyBulletTimeSource(bad)


def test_client_ids_are_distinct(client: int) -> None:
    with raises_exactly(
        InvalidArgumentError,
        f"PyBullet client ids must be distinct, got {(client, client)!r}: a client listed "
        "twice would be stepped twice per step",
    ):
        PyBulletTimeSource(client, client)


def test_disconnected_client_is_refused(client: int) -> None:
    p.disconnect(client)
    with raises_exactly(
        PhysicsError,
        f"PyBullet physics client {client} is not connected; pass the id returned by "
        "p.connect(p.DIRECT) (or p.GUI) while it is connected, or let "
        "PyBulletTimeSource.connect() create one",
    ):
        PyBulletTimeSource(client)


def test_never_connected_id_is_refused() -> None:
    with pytest.raises(PhysicsError, match=r"^PyBullet physics client 999 is not connected; "):
        PyBulletTimeSource(999)


@pytest.mark.parametrize("watch", [True, False])
def test_client_disconnected_while_stepping(client: int, watch: bool) -> None:
    source = PyBulletTimeSource(client, watch_time_step=watch)

    async def main() -> None:
        await evclock.clock().sleep(0.1)
        p.disconnect(client)
        await evclock.clock().sleep(0.1)

    with raises_exactly(
        PhysicsError,
        f"PyBullet physics client {client} was disconnected while evclock was stepping it "
        "(p.disconnect() was called, or its server or GUI window went away); keep every "
        "client of a PyBulletTimeSource connected until the loop closes",
    ):
        run(main, source)
    assert source.step_index == 24


@pytest.mark.parametrize("bad", [0.0, -0.01, math.nan, math.inf])
def test_bad_engine_time_step_is_refused(client: int, bad: float) -> None:
    p.setTimeStep(bad, physicsClientId=client)
    with raises_exactly(
        PhysicsError,
        f"PyBullet physics client {client} has fixedTimeStep={bad!r}, which is not a positive "
        f"finite number of seconds; set one with p.setTimeStep(1/240, physicsClientId={client}) "
        "or source.set_time_step(1/240)",
    ):
        PyBulletTimeSource(client)


def test_bad_time_step_set_mid_run_is_detected(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> None:
        await evclock.clock().sleep(0.1)
        p.setTimeStep(-1.0, physicsClientId=client)
        await evclock.clock().sleep(0.1)

    with pytest.raises(PhysicsError, match=r"has fixedTimeStep=-1\.0, which is not a positive"):
        run(main, source)
    assert source.step_index == 24


def test_time_step_under_one_nanosecond_is_refused(client: int) -> None:
    p.setTimeStep(1e-10, physicsClientId=client)
    with raises_exactly(
        PhysicsError,
        "time step 1e-10 s is shorter than 1 ns; evclock counts time in integer nanoseconds, "
        "so each step must last at least 1 ns",
    ):
        PyBulletTimeSource(client)


@pytest.mark.parametrize(
    ("bad", "error", "message"),
    [
        (0, InvalidArgumentError, "time step must be a positive finite number of seconds, got 0"),
        (
            -0.5,
            InvalidArgumentError,
            "time step must be a positive finite number of seconds, got -0.5",
        ),
        (
            math.nan,
            InvalidArgumentError,
            "time step must be a positive finite number of seconds, got nan",
        ),
        (
            math.inf,
            InvalidArgumentError,
            "time step must be a positive finite number of seconds, got inf",
        ),
        (
            Duration(0),
            InvalidArgumentError,
            "time step must be a positive finite number of seconds, got Duration(nanoseconds=0)",
        ),
        (
            "0.01",
            InvalidTypeError,
            "time step must be seconds (a float, an int or a Fraction) or a Duration, got str",
        ),
        (
            True,
            InvalidTypeError,
            "time step must be seconds (a float, an int or a Fraction) or a Duration, got bool",
        ),
    ],
)
def test_set_time_step_rejects_bad_values(
    client: int, bad: Any, error: type[Exception], message: str
) -> None:
    source = PyBulletTimeSource(client)
    with raises_exactly(error, message):
        source.set_time_step(bad)
    assert source.time_step == 1 / 240


def test_clients_must_share_the_time_step(client: int, client2: int) -> None:
    p.setTimeStep(0.01, physicsClientId=client2)
    with raises_exactly(
        PhysicsError,
        "PyBullet clients stepped together must share one time step, but client "
        f"{client} has fixedTimeStep={1 / 240!r} and client {client2} has 0.01; give them the "
        "same with source.set_time_step(dt) (or p.setTimeStep(dt, physicsClientId=...) on each)",
    ):
        PyBulletTimeSource(client, client2)


def test_clients_diverging_mid_run_are_detected(client: int, client2: int) -> None:
    source = PyBulletTimeSource(client, client2)

    async def main() -> None:
        await evclock.clock().sleep(0.1)
        p.setTimeStep(0.01, physicsClientId=client2)
        await evclock.clock().sleep(0.1)

    with pytest.raises(PhysicsError, match=r"must share one time step"):
        run(main, source)


def test_real_time_simulation_is_refused(client: int) -> None:
    p.setRealTimeSimulation(1, physicsClientId=client)
    with raises_exactly(
        PhysicsError,
        f"PyBullet physics client {client} has real-time simulation on (the server steps "
        "itself on the wall clock); call "
        f"p.setRealTimeSimulation(0, physicsClientId={client}): evclock steps it",
    ):
        PyBulletTimeSource(client)


def test_start_ns_is_checked(client: int) -> None:
    with raises_exactly(InvalidArgumentError, "start_ns must not be negative, got -1"):
        PyBulletTimeSource(client, start_ns=-1)
    with raises_exactly(
        InvalidTypeError, "start_ns must be an int number of nanoseconds, got float"
    ):
        PyBulletTimeSource(client, start_ns=1.5)  # type: ignore[arg-type]


def test_one_source_per_loop(client: int) -> None:
    source = PyBulletTimeSource(client)
    loop = SimEventLoop(source)
    try:
        with raises_exactly(
            evclock.sources.SourceInUseError,
            "PyBulletTimeSource is already attached to another loop; create one time source "
            "per loop",
        ):
            SimEventLoop(source)
    finally:
        loop.close()


def test_describe_and_repr(client: int, client2: int) -> None:
    source = PyBulletTimeSource(client)
    assert source.describe() == f"PyBullet physics (client {client}, dt=1/240 s)"
    assert repr(source) == (
        f"<PyBulletTimeSource PyBullet physics (client {client}, dt=1/240 s) now=0.000000000 s "
        "(sim)>"
    )
    both = PyBulletTimeSource(client, client2, start_ns=5)
    assert both.describe() == f"PyBullet physics (clients {client}, {client2}, dt=1/240 s)"
    assert both.clients == (client, client2)
    assert both.client == client
    assert both.now_ns == 5
    assert both.free_running


def test_connect_owns_its_client_and_user_clients_stay_connected(client: int) -> None:
    owned = PyBulletTimeSource.connect(time_step=0.001)
    assert owned.time_step_ns == 1_000_000
    assert owned.time_step == 0.001
    run(lambda: evclock.clock().sleep(0.01), owned)
    assert owned.step_index == 10
    assert not p.isConnected(owned.client)

    borrowed = PyBulletTimeSource(client)
    run(lambda: evclock.clock().sleep(0.01), borrowed)
    assert p.isConnected(client)


def test_connect_with_a_bad_time_step_leaves_no_client_behind() -> None:
    free = p.connect(p.DIRECT)  # PyBullet hands out the lowest free id: connect() gets it
    p.disconnect(free)
    with raises_exactly(
        InvalidArgumentError, "time step must be a positive finite number of seconds, got -1.0"
    ):
        PyBulletTimeSource.connect(time_step=-1.0)
    assert not p.isConnected(free)


def test_importing_evclock_does_not_import_pybullet() -> None:
    code = "import sys, evclock; print('pybullet' in sys.modules, 'numpy' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout == "False False\n"
    assert out.stderr == ""


# ------------------------------------------------------------------------------ time model


@pytest.mark.parametrize(
    ("dt", "exact"),
    [
        (1 / 240, Fraction(1, 240)),
        (0.001, Fraction(1, 1000)),
        (1 / 3, Fraction(1, 3)),
        (0.01, Fraction(1, 100)),
        (0.25, Fraction(1, 4)),
        (2.0, Fraction(2)),
        (1e-7, Fraction(1e-7)),  # no small fraction is that float: the binary value is used
        (0.0123456789, Fraction(0.0123456789)),
    ],
)
def test_exact_time_step(dt: float, exact: Fraction) -> None:
    assert exact_time_step(dt) == exact
    assert float(exact_time_step(dt)) == dt


def test_240_steps_are_exactly_one_second(client: int) -> None:
    source = PyBulletTimeSource(client)
    seen: list[int] = []

    async def main() -> None:
        clock = evclock.clock()
        for _ in range(240):
            await source.sleep_steps(1)
            seen.append(clock.now_ns())

    run(main, source)
    assert seen == [step_time(i) for i in range(1, 241)]
    assert seen[-1] == NS
    assert source.step_index == 240
    assert source.time_step_ns == Fraction(12_500_000, 3)


def test_loop_time_is_derived_from_the_step_count(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> tuple[float, int]:
        await evclock.clock().sleep(1.0)
        return asyncio.get_running_loop().time(), evclock.clock().now_ns()

    assert run(main, source) == (1.0, NS)
    assert source.step_index == 240


def test_a_simulated_day_does_not_drift(client: int) -> None:
    # dt = 1/3 s is no whole number of nanoseconds either, and a day is only 259200 steps.
    source = PyBulletTimeSource(client)
    source.set_time_step(1 / 3)
    assert source.time_step_ns == Fraction(NS, 3)

    async def main() -> int:
        clock = evclock.clock()
        await clock.sleep(Duration(seconds=86_400))
        return clock.now_ns()

    assert run(main, source) == 86_400 * NS
    assert source.step_index == 259_200


def test_sleeps_are_quantised_up_to_step_boundaries(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> list[tuple[int, int]]:
        clock = evclock.clock()
        out = []
        for seconds in (0.001, 0.005, 0.0, 1 / 240, 0.05):
            await clock.sleep(seconds)
            out.append((clock.now_ns(), source.step_index))
        return out

    assert run(main, source) == [
        (step_time(1), 1),  # 1 ms: one step (4.17 ms)
        (step_time(3), 3),  # 5 ms from 4.17 ms: two more steps
        (step_time(3), 3),  # zero: no step
        # 1/240 s is 4166667 ns as a float: 1 ns beyond the exact step, so two steps here
        (step_time(5), 5),
        (step_time(17), 17),  # 50 ms = 12 steps, exactly on a boundary
    ]


def test_time_of_step_and_sleep_steps(client: int) -> None:
    source = PyBulletTimeSource(client)
    assert source.time_of_step(0) == Time(0, clock_type=SIM)
    assert source.time_of_step(3) == Time(nanoseconds=12_500_000, clock_type=SIM)
    with raises_exactly(InvalidArgumentError, "step count must not be negative, got -1"):
        source.time_of_step(-1)
    with raises_exactly(InvalidTypeError, "step count must be an int, got float"):
        source.time_of_step(1.0)  # type: ignore[arg-type]

    async def main() -> None:
        with raises_exactly(InvalidArgumentError, "sleep_steps() count must be >= 1, got 0"):
            await source.sleep_steps(0)
        await source.sleep_steps(7)

    run(main, source)
    assert source.step_index == 7


def test_num_sub_steps_do_not_change_the_time_per_step(client: int, client2: int) -> None:
    """One stepSimulation advances fixedTimeStep whatever numSubSteps: sub-steps split it."""
    p.setPhysicsEngineParameter(numSubSteps=4, physicsClientId=client2)
    velocities = []
    for cid in (client, client2):
        p.setGravity(0, 0, -10, physicsClientId=cid)
        shape = p.createCollisionShape(p.GEOM_SPHERE, radius=0.1, physicsClientId=cid)
        ball = p.createMultiBody(1, shape, basePosition=[0, 0, 100], physicsClientId=cid)
        p.changeDynamics(ball, -1, linearDamping=0, physicsClientId=cid)
        source = PyBulletTimeSource(cid)
        run(lambda: evclock.clock().sleep(1.0), source)
        assert source.step_index == 240
        velocities.append(p.getBaseVelocity(ball, physicsClientId=cid)[0][2])
        assert p.getPhysicsEngineParameters(physicsClientId=cid)["fixedTimeStep"] == 1 / 240
    # v = g t after t = 1 s of sim time, with and without sub-steps
    assert velocities == [pytest.approx(-10.0, abs=1e-9), pytest.approx(-10.0, abs=1e-9)]


def test_set_time_step_rebases_at_the_step_boundary(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> list[int]:
        clock = evclock.clock()
        await clock.sleep(0.5)
        at_change = clock.now_ns()
        source.set_time_step(0.001)
        await clock.sleep(0.5)
        return [at_change, clock.now_ns()]

    assert run(main, source) == [NS // 2, NS]
    assert source.step_index == 120 + 500
    assert p.getPhysicsEngineParameters(physicsClientId=client)["fixedTimeStep"] == 0.001


def test_set_time_step_takes_exact_fractions_and_durations(client: int) -> None:
    source = PyBulletTimeSource(client)
    source.set_time_step(Fraction(1, 7_000_000))  # not recoverable from the float
    assert source.time_step_ns == Fraction(NS, 7_000_000)
    source.set_time_step(Duration(nanoseconds=2_500_000))
    assert source.time_step_ns == 2_500_000
    assert source.time_step == 0.0025


def test_external_time_step_change_is_detected(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> int:
        clock = evclock.clock()
        await clock.sleep(0.5)
        p.setPhysicsEngineParameter(fixedTimeStep=0.01, physicsClientId=client)
        await clock.sleep(0.5)
        return clock.now_ns()

    assert run(main, source) == NS
    assert source.step_index == 120 + 50
    assert source.time_step == 0.01


def test_unwatched_external_change_is_not_seen(client: int) -> None:
    """The documented contract of watch_time_step=False: use set_time_step()."""
    source = PyBulletTimeSource(client, watch_time_step=False)

    async def main() -> None:
        await evclock.clock().sleep(0.5)
        p.setTimeStep(0.01, physicsClientId=client)
        await evclock.clock().sleep(0.5)

    run(main, source)
    assert source.step_index == 240
    assert source.time_step == 1 / 240


def test_set_time_step_from_a_step_hook(client: int) -> None:
    source = PyBulletTimeSource(client)

    def hook() -> None:
        if source.step_index == 12:  # 50 ms
            source.set_time_step(0.01)

    source.add_step_hook(hook)

    async def main() -> int:
        await evclock.clock().sleep(0.25)
        return evclock.clock().now_ns()

    assert run(main, source) == 250_000_000
    assert source.step_index == 12 + 20


def test_advance_contract_without_a_loop(client: int) -> None:
    source = PyBulletTimeSource(client)
    assert source.advance(None, None) == step_time(1)  # free-running: one step
    assert source.advance(0, None) == step_time(1)  # a target in the past: no step
    assert source.step_index == 1
    asked: list[int] = []

    def gate(next_ns: int) -> bool:
        asked.append(next_ns)
        return len(asked) <= 3

    assert source.advance(NS, gate) == step_time(4)
    assert asked == [step_time(i) for i in (2, 3, 4, 5)]
    assert source.step_index == 4
    # The fast path returns to the loop every 1024 steps (to poll I/O), before the target.
    assert source.advance(100 * NS, None) == step_time(4 + 1024)
    assert source.advance(step_time(1030), None) == step_time(1030)


def test_free_running_with_nothing_scheduled(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> int:
        event = asyncio.Event()
        source.add_step_hook(set_at_step(source, event, 100))
        await event.wait()  # nothing is scheduled: physics keeps stepping
        return evclock.clock().now_ns()

    assert run(main, source) == step_time(100)
    assert source.step_index == 100


def test_until_limits_a_free_running_program(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> None:
        await asyncio.Event().wait()

    with raises_exactly(
        SimTimeLimitError,
        "the program was still running at the until limit (0.5 s of sim time) and was "
        "cancelled; raise until= or let the program finish sooner",
    ):
        run(main, source, until=0.5)
    assert source.step_index == 120


@pytest.mark.parametrize("until", [0, 0.0, Time(0, clock_type=SIM)])
def test_until_in_the_past_is_refused(client: int, until: Any) -> None:
    source = PyBulletTimeSource(client)
    with raises_exactly(
        InvalidArgumentError,
        f"until={until!r} is not after the start of sim time (0 s); give a later sim time",
    ):
        run(lambda: evclock.clock().sleep(1), source, until=until)
    assert source.step_index == 0


def test_until_before_a_late_start_is_refused(client: int) -> None:
    source = PyBulletTimeSource(client, start_ns=10 * NS)
    with raises_exactly(
        InvalidArgumentError,
        "until=5.0 is not after the start of sim time (10 s); give a later sim time",
    ):
        run(lambda: evclock.clock().sleep(1), source, until=5.0)


# ------------------------------------------------------------------------------ step hooks


def test_step_hooks_run_around_each_step_in_order(client: int) -> None:
    source = PyBulletTimeSource(client)
    calls: list[tuple[str, int, int]] = []

    def recorder(name: str) -> Callable[[], None]:
        return lambda: calls.append((name, source.step_index, evclock.clock().now_ns()))

    async def main() -> None:
        b1 = source.add_step_hook(recorder("b1"), when="before")
        a1 = source.add_step_hook(recorder("a1"))
        b2 = source.add_step_hook(recorder("b2"), when="before")
        assert source.step_hooks == (b1, b2, a1)
        await source.sleep_steps(2)
        b1.remove()
        b1.remove()  # idempotent
        assert not b1.active
        assert list(source.step_hooks) == [b2, a1]
        await source.sleep_steps(1)
        a1.remove()
        b2.remove()
        await source.sleep_steps(1)

    run(main, source)
    t1, t2, t3 = step_time(1), step_time(2), step_time(3)
    assert calls == [
        ("b1", 0, 0),
        ("b2", 0, 0),
        ("a1", 1, t1),
        ("b1", 1, t1),
        ("b2", 1, t1),
        ("a1", 2, t2),
        ("b2", 2, t2),
        ("a1", 3, t3),
    ]
    assert source.step_index == 4


def test_a_hook_waking_a_task_stops_stepping_at_that_step(client: int) -> None:
    source = PyBulletTimeSource(client)
    woken: list[int] = []

    async def main() -> None:
        event = asyncio.Event()
        hook = source.add_step_hook(set_at_step(source, event, 50))

        async def waiter() -> None:
            await event.wait()
            woken.append(source.step_index)
            hook.remove()

        task = asyncio.create_task(waiter())
        await evclock.clock().sleep(1.0)  # the advance toward 1 s stops at step 50
        await task

    run(main, source)
    assert woken == [50]
    assert source.step_index == 240


def test_a_failing_hook_is_reported_and_removed(client: int) -> None:
    source = PyBulletTimeSource(client)
    errors: list[dict[str, Any]] = []

    def broken() -> None:
        if source.step_index == 2:
            raise ValueError("sensor model broke")

    async def main() -> None:
        asyncio.get_running_loop().set_exception_handler(lambda _loop, ctx: errors.append(ctx))
        hook = source.add_step_hook(broken, when="before")
        await source.sleep_steps(5)
        assert not hook.active
        assert isinstance(hook.exception(), ValueError)
        assert "removed" in repr(hook)

    run(main, source)
    assert source.step_index == 5
    assert len(errors) == 1
    assert errors[0]["message"] == (
        "evclock step hook "
        "test_a_failing_hook_is_reported_and_removed.<locals>.broken raised; hook removed"
    )
    assert str(errors[0]["exception"]) == "sensor model broke"


def test_step_hook_bad_input(client: int) -> None:
    source = PyBulletTimeSource(client)
    with raises_exactly(InvalidTypeError, "a step hook must be callable, got int"):
        source.add_step_hook(3)  # type: ignore[arg-type]
    with raises_exactly(
        InvalidArgumentError, "step hook 'when' must be 'before' or 'after', got 'during'"
    ):
        source.add_step_hook(print, when="during")  # type: ignore[arg-type]


def test_hooks_apply_forces_every_step(client: int) -> None:
    """A before-hook holding a box in the air against gravity (force = m g each step)."""
    _, box = box_world(client)
    source = PyBulletTimeSource(client)
    source.add_step_hook(
        lambda: p.applyExternalForce(
            box, -1, [0, 0, 9.81], [0, 0, 1.0], p.WORLD_FRAME, physicsClientId=client
        ),
        when="before",
    )
    run(lambda: evclock.clock().sleep(1.0), source)
    assert z_of(client, box) == pytest.approx(1.0, abs=1e-6)


# ------------------------------------------------------------------------------ wait_until


def test_wait_until_resolves_at_the_first_step_where_it_holds(client: int) -> None:
    plane, box = box_world(client)
    source = PyBulletTimeSource(client)
    contacts_before: list[int] = []
    source.add_step_hook(
        lambda: contacts_before.append(len(p.getContactPoints(box, plane, physicsClientId=client))),
        when="before",
    )

    async def main() -> Time:
        return await source.wait_until(
            lambda: bool(p.getContactPoints(box, plane, physicsClientId=client))
        )

    touched = run(main, source)
    assert touched == Time(nanoseconds=step_time(source.step_index), clock_type=SIM)
    # Before the last step there was no contact; after it there is.
    assert contacts_before[-1] == 0
    assert p.getContactPoints(box, plane, physicsClientId=client)
    assert touched.seconds == pytest.approx(math.sqrt(2 * 0.9 / 9.81), abs=0.02)


def test_wait_until_already_true_returns_at_once(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> Time:
        return await source.wait_until(lambda: True, timeout=0)

    assert run(main, source) == Time(0, clock_type=SIM)
    assert source.step_index == 0


def test_wait_until_times_out_in_sim_time(client: int) -> None:
    source = PyBulletTimeSource(client)

    def never() -> bool:
        return False

    async def main() -> None:
        with raises_exactly(
            SimTimeLimitError,
            "wait_until(test_wait_until_times_out_in_sim_time.<locals>.never) timed out: the "
            "predicate stayed false for 0.100000000 s of sim time",
        ):
            await source.wait_until(never, timeout=0.1)
        assert evclock.clock().now_ns() == 100_000_000  # 24 steps of 1/240 s, exactly
        with raises_exactly(
            SimTimeLimitError,
            "wait_until(test_wait_until_times_out_in_sim_time.<locals>.never) timed out: the "
            "predicate stayed false for 0.000000000 s of sim time",
        ):
            await source.wait_until(never, timeout=Duration(0))
        with pytest.raises(SimTimeLimitError):
            await source.wait_until(never, timeout=Duration(nanoseconds=1))

    run(main, source)
    assert issubclass(SimTimeLimitError, TimeoutError)  # wait_until's timeout stays one
    assert source.step_index == 25
    assert not source._slow  # no waiter left: the fast path is back


def test_wait_until_prefers_success_on_the_deadline_step(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> Time:
        return await source.wait_until(lambda: source.step_index >= 24, timeout=0.1)

    assert run(main, source) == Time(0.1, clock_type=SIM)


def test_wait_until_many_waiters_and_a_failing_predicate(client: int) -> None:
    source = PyBulletTimeSource(client)

    def explode() -> bool:
        if source.step_index == 3:
            raise RuntimeError("predicate failed")
        return False

    def at_step(k: int) -> Callable[[], bool]:
        return lambda: source.step_index >= k

    async def main() -> list[object]:
        waits = [source.wait_until(at_step(k)) for k in (5, 2, 5, 9)]
        return await asyncio.gather(*waits, source.wait_until(explode), return_exceptions=True)

    results = run(main, source)
    assert results[:4] == [Time(nanoseconds=step_time(k), clock_type=SIM) for k in (5, 2, 5, 9)]
    assert isinstance(results[4], RuntimeError)
    assert str(results[4]) == "predicate failed"


def test_a_cancelled_wait_until_leaves_no_waiter(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> None:
        task = asyncio.create_task(source.wait_until(lambda: False))
        await source.sleep_steps(3)
        assert source._slow
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert not source._slow
        assert source._waiters == []

    run(main, source)


def test_wait_until_bad_input(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> None:
        with raises_exactly(InvalidTypeError, "wait_until() needs a callable predicate, got bool"):
            await source.wait_until(True)  # type: ignore[arg-type]
        with raises_exactly(
            InvalidArgumentError, "wait_until() timeout must not be negative, got -1"
        ):
            await source.wait_until(lambda: True, timeout=-1)
        with raises_exactly(InvalidArgumentError, "wait_until() timeout must be a number, got NaN"):
            await source.wait_until(lambda: True, timeout=math.nan)

    run(main, source)


def test_wait_until_on_another_loop_is_refused(client: int) -> None:
    source = PyBulletTimeSource(client)
    message = (
        "{} must be awaited in a task on the sim time this PyBulletTimeSource drives: the "
        "SimEventLoop of evclock.run(main(), source=source), or the loop of an "
        "evclock.SimDriver(source)"
    )
    with raises_exactly(NotRunningError, message.format("wait_until()")):
        asyncio.run(source.wait_until(lambda: True))
    with raises_exactly(NotRunningError, message.format("sleep_steps()")):
        asyncio.run(source.sleep_steps(1))


# ------------------------------------------------------------------------ resets and jumps


def test_reset_wakes_100_sleepers_with_clock_jumped(client: int) -> None:
    source = PyBulletTimeSource(client)
    outcomes: list[tuple[int, TimeJump, int]] = []

    async def sleeper(i: int) -> None:
        clock = evclock.clock()
        try:
            await clock.sleep(2.0 + i / 100)
        except ClockJumpedError as exc:
            outcomes.append((i, exc.jump, clock.now_ns()))
            return
        raise AssertionError("a sleeper was not woken by the jump")

    async def main() -> tuple[int, int]:
        clock = evclock.clock()
        tasks = [asyncio.create_task(sleeper(i)) for i in range(100)]
        await clock.sleep(1.0)
        jump = source.reset_simulation()
        assert jump == TimeJump(Time(1.0, clock_type=SIM), Time(0, clock_type=SIM))
        await asyncio.wait_for(asyncio.gather(*tasks), timeout=0.001)  # all done at once
        assert clock.now_ns() == 0
        await clock.sleep(0.5)  # the loop goes on from the new time
        return clock.now_ns(), source.step_index

    assert run(main, source) == (NS // 2, 120)
    assert sorted(i for i, _, _ in outcomes) == list(range(100))
    for _, jump, now in outcomes:
        assert jump.delta == Duration(seconds=-1)
        assert now == 0


def test_reset_runs_jump_handlers_with_thresholds(client: int) -> None:
    source = PyBulletTimeSource(client)
    log: list[tuple[str, Duration, int]] = []

    async def main() -> None:
        clock = evclock.clock()

        def recorder(name: str) -> Callable[[TimeJump], None]:
            return lambda jump: log.append((name, jump.delta, clock.now_ns()))

        clock.on_jump(recorder("pre"), recorder("post"))
        big = clock.on_jump(
            post=recorder("big"), threshold=JumpThreshold(min_backward=Duration(seconds=2))
        )
        clock.on_jump(
            post=recorder("forward"),
            threshold=JumpThreshold(min_forward=Duration(seconds=1), min_backward=None),
        )
        await clock.sleep(1.0)
        source.reset_simulation()  # 1 s backwards: not "big"
        await clock.sleep(3.0)
        source.reset_simulation(start=Time(0.5, clock_type=SIM))  # 2.5 s backwards
        big.remove()
        source.reset_simulation(start=Duration(seconds=4))  # 3.5 s forwards

    run(main, source)
    assert log == [
        ("pre", Duration(seconds=-1), NS),
        ("post", Duration(seconds=-1), 0),
        ("pre", Duration(seconds=-2.5), 3 * NS),
        ("post", Duration(seconds=-2.5), NS // 2),
        ("big", Duration(seconds=-2.5), NS // 2),
        ("forward", Duration(seconds=3.5), 4 * NS),
    ]


def test_reset_to_the_current_time_is_no_jump(client: int) -> None:
    box_world(client)
    source = PyBulletTimeSource(client)

    async def main() -> None:
        clock = evclock.clock()
        sleeper = asyncio.ensure_future(clock.sleep(0.1))
        assert source.reset_simulation() is None  # at 0 s already: sleepers keep going
        assert p.getNumBodies(physicsClientId=client) == 0
        await sleeper
        assert clock.now_ns() == 100_000_000

    run(main, source)


def test_rates_and_timers_reanchor_after_a_reset(client: int) -> None:
    source = PyBulletTimeSource(client)
    ticks: list[tuple[int, int]] = []
    timer_calls: list[int] = []
    slept: list[int] = []

    async def main() -> None:
        clock = evclock.clock()
        clock.timer(0.1, lambda: timer_calls.append(clock.now_ns()))

        async def rate_loop() -> None:
            async for tick in clock.rate(20):
                ticks.append((tick.index, tick.actual.nanoseconds))
                if len(ticks) == 8:
                    return

        async def plain_asyncio_sleep() -> None:
            await asyncio.sleep(0.3)  # asyncio timers keep their remaining delay
            slept.append(clock.now_ns())

        task = asyncio.create_task(rate_loop())
        await clock.sleep(0.125)
        other = asyncio.create_task(plain_asyncio_sleep())
        await clock.sleep(0.1)
        source.reset_simulation()  # from 0.225 s (54 steps) back to 0
        await task
        await other

    run(main, source)
    ms = 1_000_000
    assert ticks == [
        (0, 0),
        (1, 50 * ms),
        (2, 100 * ms),
        (3, 150 * ms),
        (4, 200 * ms),
        (0, 0),  # re-anchored at the new time
        (1, 50 * ms),
        (2, 100 * ms),
    ]
    assert timer_calls[:2] == [100 * ms, 200 * ms]
    assert timer_calls[2] == 100 * ms  # one period after the reset
    # started at 0.125 s for 0.3 s: 0.2 s were left at the reset
    assert slept == [step_time(math.ceil(200 * ms / STEP_NS))]


def test_save_and_restore_move_time_and_physics_back(client: int) -> None:
    _, box = box_world(client)
    source = PyBulletTimeSource(client)
    log: list[TimeJump] = []

    async def main() -> None:
        clock = evclock.clock()
        clock.on_jump(
            post=log.append,
            threshold=JumpThreshold(min_forward=Duration(nanoseconds=1)),
        )
        await clock.sleep(0.25)
        first = source.save_state()
        first_z = z_of(client, box)
        trajectory = []
        for _ in range(10):
            await source.sleep_steps(6)
            trajectory.append(z_of(client, box))
        second = source.save_state()
        assert source.step_index == 60 + 60
        assert source.restore_state(first) == TimeJump(
            Time(0.5, clock_type=SIM), Time(0.25, clock_type=SIM)
        )
        assert clock.now_ns() == NS // 4
        assert source.step_index == 60
        assert z_of(client, box) == first_z
        replay = []
        for _ in range(10):
            await source.sleep_steps(6)
            replay.append(z_of(client, box))
        assert replay == trajectory  # bit for bit
        source.restore_state(first)
        source.restore_state(second)  # forward again
        assert clock.now_ns() == NS // 2
        assert source.restore_state(second) is None  # same time: no jump
        source.remove_state(first)
        with raises_exactly(
            InvalidArgumentError,
            f"unknown state id {first}: pass an id returned by save_state() of this source "
            "that was not removed",
        ):
            source.restore_state(first)

    run(main, source)
    assert [jump.delta for jump in log] == [
        Duration(seconds=-0.25),
        Duration(seconds=-0.25),
        Duration(seconds=0.25),
    ]


def test_restore_wakes_sleepers_and_waiters(client: int) -> None:
    source = PyBulletTimeSource(client)

    async def main() -> None:
        clock = evclock.clock()
        state = source.save_state()
        await clock.sleep(0.5)
        sleeper = asyncio.ensure_future(clock.sleep(1))
        waiter = asyncio.create_task(source.wait_until(lambda: False))
        await source.sleep_steps(1)
        source.restore_state(state)
        for task in (sleeper, waiter):
            with pytest.raises(ClockJumpedError) as info:
                await task
            assert info.value.jump.after == Time(0, clock_type=SIM)
        assert not source._slow

    run(main, source)


def test_restore_after_reset_is_a_clear_error(client: int) -> None:
    box_world(client)
    source = PyBulletTimeSource(client)
    state = source.save_state()
    source.reset_simulation()
    with raises_exactly(
        PhysicsError,
        f"PyBullet could not restore state {state} on client {client}: a snapshot only restores "
        "into the world it was taken from (same bodies, and not after reset_simulation())",
    ):
        source.restore_state(state)
    with raises_exactly(
        InvalidArgumentError,
        "unknown state id 'x': pass an id returned by save_state() of this source that was "
        "not removed",
    ):
        source.restore_state("x")  # type: ignore[arg-type]


def test_reset_from_a_step_hook_is_refused(client: int) -> None:
    source = PyBulletTimeSource(client)
    errors: list[BaseException] = []

    async def main() -> None:
        asyncio.get_running_loop().set_exception_handler(
            lambda _loop, ctx: errors.append(ctx["exception"])
        )
        source.add_step_hook(source.reset_simulation)
        await source.sleep_steps(2)

    run(main, source)
    assert [str(e) for e in errors] == [
        "reset_simulation() cannot be called from a step hook or a wait_until() predicate: "
        "the physics is in the middle of advancing; call it from a task"
    ]


def test_reset_and_time_arguments_without_a_loop(client: int) -> None:
    source = PyBulletTimeSource(client)
    source.advance(None, None)
    assert source.reset_simulation(start=2.5) is None
    assert source.now_ns == 2_500_000_000
    assert source.step_index == 0
    with raises_exactly(
        InvalidArgumentError, "reset_simulation() start must not be negative, got -1"
    ):
        source.reset_simulation(start=-1)
    with raises_exactly(
        ClockMismatchError, "reset_simulation() start must be a sim time, got a steady time"
    ):
        source.reset_simulation(start=Time(1, clock_type=evclock.STEADY))


# --------------------------------------------------------------------------- determinism


def _scenario_trajectory() -> bytes:
    """Boxes tumbling onto each other, pushed by a 50 Hz controller; every step recorded."""
    source = PyBulletTimeSource.connect()
    cid = source.client
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
    p.createMultiBody(0, plane, physicsClientId=cid)
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.1, 0.1, 0.1], physicsClientId=cid)
    boxes = [
        p.createMultiBody(
            1.0, shape, basePosition=[0.03 * i, 0.02 * i, 0.3 + 0.25 * i], physicsClientId=cid
        )
        for i in range(4)
    ]
    samples: list[float] = []

    def record() -> None:
        for body in boxes:
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            samples.extend(pos)
            samples.extend(orn)

    source.add_step_hook(record)

    async def controller() -> None:
        async for tick in evclock.clock().rate(50):
            x = p.getBasePositionAndOrientation(boxes[-1], physicsClientId=cid)[0][0]
            p.applyExternalForce(
                boxes[-1], -1, [-20 * x, 5, 0], [0, 0, 0], p.LINK_FRAME, physicsClientId=cid
            )
            if tick.index == 75:
                return

    async def main() -> None:
        await asyncio.gather(controller(), source.wait_until(lambda: source.step_index >= 300))

    evclock.run(main(), source=source)
    return struct.pack(f"{len(samples)}d", *samples)


def test_same_program_twice_gives_identical_trajectories() -> None:
    first = _scenario_trajectory()
    second = _scenario_trajectory()
    assert len(first) == 360 * 4 * 7 * 8
    assert first == second


# ------------------------------------------------------------------------------- example


def test_falling_box_example_runs() -> None:
    outputs = [run_example("pybullet_falling_box.py").stdout for _ in range(2)]
    assert outputs[0] == outputs[1]  # deterministic across processes
    lines = outputs[0].splitlines()
    assert len(lines) == 42
    assert lines[0] == "t=0.000 s  height=1.0000 m"
    assert lines[-2] == "t=2.000 s  height=0.1000 m"
    assert lines[-1] == "done: 41 samples, 480 physics steps"
    times = [float(line.split()[0][2:]) for line in lines[:-1]]
    assert times == [round(0.05 * i, 3) for i in range(41)]


def test_falling_box_example_behaviour(capsys: pytest.CaptureFixture[str]) -> None:
    from examples import pybullet_falling_box as example

    samples = example.main()
    capsys.readouterr()
    times = [t for t, _ in samples]
    heights = [h for _, h in samples]
    assert times == [i / 20 for i in range(41)]  # 12 steps each, exactly
    assert heights[0] == pytest.approx(1.0)
    # free fall until the box lands (h = 1 - g t^2 / 2), then it rests on the plane
    assert heights[4] == pytest.approx(1.0 - 9.81 * 0.2**2 / 2, abs=0.01)
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(heights[:10]))
    assert heights[-1] == pytest.approx(0.1, abs=1e-3)
