"""SimDriver: sim time on event loops evclock does not own (asyncio, uvloop, a notebook's).

Most tests run twice: on the default asyncio loop and on uvloop, each through
``asyncio.Runner(loop_factory=...)``. Pacing is checked on ``FakeTimeLoop``, a plain asyncio
loop whose wall clock is fake (each iteration costs 1 us, an idle wait jumps), so paced runs
are exact and instant; on real loops only ordering and structure are asserted, never
wall-time thresholds.
"""

from __future__ import annotations

import asyncio
import itertools
import re
import selectors
import sys
from collections.abc import Awaitable, Callable, Coroutine
from pathlib import Path
from typing import Any, TypeVar

import _paused_waits as operated
import pytest
import uvloop
from _examples import run_example

import evclock
from evclock import (
    ClockJumpedError,
    ClockMismatchError,
    Duration,
    InvalidArgumentError,
    InvalidTypeError,
    LagError,
    LoopClosedError,
    NotRunningError,
    PacingError,
    SimClock,
    SimDriver,
    SimDriverError,
    Time,
    TimeJump,
)
from evclock.hosts._driver import SimDriverClock

T = TypeVar("T")
ROOT = Path(__file__).resolve().parents[2]
SIM = evclock.SIM

LOOPS: dict[str, Callable[[], asyncio.AbstractEventLoop]] = {
    "asyncio": asyncio.new_event_loop,
    "uvloop": uvloop.new_event_loop,
}


@pytest.fixture(params=sorted(LOOPS))
def run(request: pytest.FixtureRequest) -> Callable[[Coroutine[Any, Any, T]], T]:
    """Run a coroutine on a fresh loop of the parametrised kind (asyncio, uvloop)."""
    factory = LOOPS[request.param]

    def runner(coro: Coroutine[Any, Any, T]) -> T:
        with asyncio.Runner(loop_factory=factory) as r:
            return r.run(coro)

    return runner


class _FakeSelector(selectors.DefaultSelector):
    def __init__(self, loop: FakeTimeLoop) -> None:
        super().__init__()
        self._loop = loop

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None:
            raise AssertionError("FakeTimeLoop would block forever: nothing can happen")
        self._loop.fake += max(timeout, 0.0) + FakeTimeLoop.ITERATION
        result: list[Any] = super().select(0)
        return result


class FakeTimeLoop(asyncio.SelectorEventLoop):
    """A plain asyncio loop on fake wall time: each iteration costs ``ITERATION`` seconds and
    a blocking wait jumps straight to its end. Deterministic pacing without waiting."""

    ITERATION = 1e-6

    def __init__(self) -> None:
        self.fake = 1000.0
        super().__init__(_FakeSelector(self))

    def time(self) -> float:
        return self.fake


def run_fake(coro: Coroutine[Any, Any, T]) -> T:
    with asyncio.Runner(loop_factory=FakeTimeLoop) as r:
        return r.run(coro)


def fake_loop() -> FakeTimeLoop:
    loop = asyncio.get_running_loop()
    assert isinstance(loop, FakeTimeLoop)
    return loop


_BACKGROUND: set[asyncio.Task[Any]] = set()


def background(coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
    """Start a task and keep a reference to it until it is done."""
    task = asyncio.create_task(coro)
    _BACKGROUND.add(task)
    task.add_done_callback(_BACKGROUND.discard)
    return task


async def ticker(clock: evclock.Clock, hz: float, log: list[Any], name: str = "") -> None:
    async for tick in clock.rate(hz):
        log.append((name, tick.index, clock.now().nanoseconds) if name else tick)


# ------------------------------------------------------------------ sim time on the loop


def test_clock_sleep_follows_sim_time(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        before = evclock.clock()
        out: list[object] = [type(before).__name__]
        async with SimDriver(rtf=None) as sim:
            clock = evclock.clock()
            out += [clock is sim.clock, evclock.sim_clock() is sim.clock]
            out += [isinstance(clock, evclock.SimClock), clock.clock_type is SIM]
            await clock.sleep(1.5)
            out.append(clock.now())
            await clock.sleep(Duration(nanoseconds=250_000_000))
            out.append(sim.now())
            await clock.sleep_until(Time(seconds=3))
            out.append(clock.now_ns())
            await clock.sleep(0)
            out.append(sim.now_ns)
        out.append(evclock.clock() is before)
        return out

    assert run(main()) == [
        "WallClock",
        True,
        True,
        True,
        True,
        Time(seconds=1.5),
        Time(seconds=1.75),
        3_000_000_000,
        3_000_000_000,
        True,
    ]


def test_use_sim_time_from_the_environment_is_satisfied_by_a_driver(
    run: Callable[[Awaitable[Any]], Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("EVCLOCK_USE_SIM_TIME", "1")

    async def main() -> list[object]:
        with pytest.raises(evclock.NoSimulationError):
            evclock.clock()
        async with SimDriver(rtf=None) as sim:
            return [evclock.clock() is sim.clock, evclock.sim_clock() is sim.clock]

    assert run(main()) == [True, True]


def test_sleepers_wake_in_deadline_then_fifo_order(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def sleeper(clock: evclock.Clock, name: str, delay: float, log: list[str]) -> None:
        await clock.sleep(delay)
        log.append(f"{name}@{clock.now().seconds:g}")

    async def main() -> list[str]:
        log: list[str] = []
        async with SimDriver(rtf=None) as sim:
            for name, delay in [("a", 2), ("b", 1), ("c", 2), ("d", 1), ("e", 0)]:
                background(sleeper(sim.clock, name, delay, log))
            await sim.run_until(3)
        return log

    assert run(main()) == ["e@0", "b@1", "d@1", "a@2", "c@2"]


def test_rate_loop_ticks_exact(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> tuple[list[evclock.Tick], int]:
        ticks: list[evclock.Tick] = []
        async with SimDriver(rtf=None) as sim:
            background(ticker(sim.clock, 300, ticks))
            await sim.run_until(1.0)
            return ticks, sim.lockstep_overruns

    ticks, overruns = run(main())
    assert len(ticks) == 301
    for i, tick in enumerate(ticks):
        assert tick.index == i
        assert tick.expected.nanoseconds == i * 10**9 // 300
        assert tick.actual == tick.expected
        assert tick.missed == 0
    assert overruns == 0


def test_timer_fires_on_sim_time(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> tuple[list[int], evclock.Duration | None]:
        calls: list[int] = []
        async with SimDriver(rtf=None) as sim:
            timer = sim.clock.timer(0.25, lambda: calls.append(sim.now_ns))
            await sim.run_until(1.1)
            left = timer.time_until_next_call()
            timer.cancel()
        return calls, left

    calls, left = run(main())
    assert calls == [250_000_000, 500_000_000, 750_000_000, 1_000_000_000]
    assert left == Duration(nanoseconds=150_000_000)


def test_two_controllers_interleave_like_on_the_sim_loop(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def controllers(clock: evclock.Clock, log: list[Any]) -> list[asyncio.Task[None]]:
        return [
            background(ticker(clock, 3, log, "slow")),
            background(ticker(clock, 5, log, "fast")),
        ]

    async def on_driver() -> list[Any]:
        log: list[Any] = []
        async with SimDriver(rtf=None) as sim:
            await controllers(sim.clock, log)
            await sim.run_until(10)
        return [entry for entry in log if entry[2] < 10**10]

    async def on_sim_loop() -> list[Any]:
        log: list[Any] = []
        tasks = await controllers(evclock.clock(), log)
        await evclock.clock().sleep(10)
        for task in tasks:
            task.cancel()
        return [entry for entry in log if entry[2] < 10**10]

    reference = evclock.run(on_sim_loop())
    assert len(reference) == 30 + 50
    first = run(on_driver())
    assert first == reference
    assert run(on_driver()) == first


# ------------------------------------------------------------------ lockstep


def test_work_woken_at_t_settles_before_time_advances(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    """Queues, events, gather, wait_for, TaskGroup and new tasks: all run at the same sim time."""

    async def main() -> tuple[list[tuple[str, int, int]], int]:
        seen: list[tuple[str, int, int]] = []
        async with SimDriver(rtf=None) as sim:
            clock = sim.clock
            queue: asyncio.Queue[int] = asyncio.Queue()
            event = asyncio.Event()

            def note(what: str, t: int) -> None:
                seen.append((what, t, clock.now_ns()))

            async def child(t: int, yields: int) -> None:
                for _ in range(yields):
                    await asyncio.sleep(0)
                note("child", t)

            async def consumer() -> None:
                while True:
                    t = await queue.get()
                    await asyncio.sleep(0)
                    note("queue", t)

            async def listener() -> None:
                while True:
                    await event.wait()
                    event.clear()
                    note("event", clock.now_ns())

            async def controller() -> None:
                async for tick in clock.rate(10):
                    t = tick.expected.nanoseconds
                    queue.put_nowait(t)
                    event.set()
                    await asyncio.gather(child(t, 3), child(t, 1))
                    await asyncio.wait_for(asyncio.gather(child(t, 2)), timeout=10)
                    async with asyncio.TaskGroup() as group:
                        group.create_task(child(t, 4))
                    background(child(t, 5))
                    note("controller", t)
                    if tick.index == 10:
                        return

            tasks = [asyncio.create_task(f()) for f in (consumer, listener, controller)]
            await sim.run_until(2.0)
            for task in tasks:
                task.cancel()
            return seen, sim.lockstep_overruns

    seen, overruns = run(main())
    assert len(seen) == 11 * 8
    assert all(t == now for _, t, now in seen), [s for s in seen if s[1] != s[2]]
    assert overruns == 0


def test_settling_is_bounded_so_a_spinning_task_cannot_stop_sim_time(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def spinner() -> None:
        while True:
            await asyncio.sleep(0)

    async def main() -> tuple[int, int]:
        ticks: list[evclock.Tick] = []
        async with SimDriver(rtf=None, max_settle_yields=5) as sim:
            spin = asyncio.create_task(spinner())
            background(ticker(sim.clock, 10, ticks))
            await sim.run_until(1.0)
            spin.cancel()
            return len(ticks), sim.lockstep_overruns

    ticks, overruns = run(main())
    assert ticks == 11
    assert overruns >= 10


def test_hold_time_keeps_sim_time_still_during_outside_work(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> list[int]:
        async with SimDriver(rtf=None) as sim:
            ticks: list[evclock.Tick] = []
            background(ticker(sim.clock, 100, ticks))
            await sim.run_until(0.5)
            with sim.hold_time():
                await asyncio.to_thread(sum, range(1000))  # work outside the loop
                await asyncio.sleep(0.01)  # and a wall-time wait
                held = sim.now_ns
                await sim.clock.sleep(0)  # waits due now still wake while held
                after_zero_sleep = sim.now_ns
            await sim.run_until(0.6)
            return [held, after_zero_sleep, len(ticks)]

    assert run(main()) == [500_000_000, 500_000_000, 61]


# ------------------------------------------------------------------ wall time stays wall time


def test_plain_asyncio_sleep_is_wall_time_while_sim_races_on(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> tuple[int, int]:
        async with SimDriver(rtf=None) as sim:
            background(ticker(sim.clock, 100, []))
            await sim.run_until(1.0)
            before = sim.now_ns
            for _ in range(100):  # one pass, unless the machine is badly overloaded
                await asyncio.sleep(0.05)  # wall time: sim time goes on meanwhile
                if sim.now_ns > before:
                    break
            return before, sim.now_ns

    before, after = run(main())
    assert before == 1_000_000_000
    assert after > before


def test_plain_asyncio_sleep_does_not_wait_for_paced_sim_time(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> tuple[int, bool]:
        async with SimDriver(rtf=1.0) as sim:
            sleeper = asyncio.ensure_future(sim.clock.sleep(1000))
            await asyncio.sleep(0.01)  # wall time; the 1000 s sim sleep needs 1000 wall s
            return sim.now_ns, sleeper.done()

    assert run(main()) == (0, False)


def test_plain_asyncio_sleep_on_fake_wall_time_lets_many_sim_seconds_pass() -> None:
    async def main() -> tuple[float, float]:
        loop = fake_loop()
        async with SimDriver(rtf=None, wall=loop.time) as sim:
            background(ticker(sim.clock, 100, []))
            await sim.run_until(1.0)
            w0 = loop.time()
            await asyncio.sleep(0.05)
            return loop.time() - w0, sim.now().seconds

    wall, sim_seconds = run_fake(main())
    assert wall == pytest.approx(0.05, abs=1e-4)
    assert sim_seconds > 10.0  # at 1 us of fake wall time per loop iteration


# ------------------------------------------------------------------ pacing


def test_rtf_none_runs_fast_on_fake_wall_time() -> None:
    async def main() -> tuple[float, int]:
        loop = fake_loop()
        async with SimDriver(rtf=None, wall=loop.time) as sim:
            ticks: list[evclock.Tick] = []
            background(ticker(sim.clock, 100, ticks))
            w0 = loop.time()
            await sim.run_until(60.0)
            return loop.time() - w0, len(ticks)

    wall, ticks = run_fake(main())
    assert ticks == 6001
    assert wall < 0.1  # 60 sim seconds in a few thousand 1 us iterations


@pytest.mark.parametrize("rtf", [0.5, 2.0, 10.0])
def test_rtf_paces_exactly_on_fake_wall_time(rtf: float) -> None:
    async def main() -> tuple[list[tuple[int, float]], float | None]:
        loop = fake_loop()
        async with SimDriver(rtf=rtf, wall=loop.time) as sim:
            stamps: list[tuple[int, float]] = []

            async def controller() -> None:
                async for tick in sim.clock.rate(10):
                    stamps.append((tick.actual.nanoseconds, loop.time()))
                    if tick.index == 1:
                        sim.achieved_rtf()

            background(controller())
            await sim.run_until(2.0)
            return stamps, sim.achieved_rtf()

    stamps, achieved = run_fake(main())
    assert [s for s, _ in stamps] == [i * 100_000_000 for i in range(21)]
    w1 = stamps[1][1]
    for sim_ns, wall in stamps[1:]:
        assert wall - w1 == pytest.approx((sim_ns - 100_000_000) / 1e9 / rtf, abs=1e-4)
    assert achieved == pytest.approx(rtf, rel=1e-3)


def test_rtf_can_change_while_running_on_fake_wall_time() -> None:
    async def main() -> list[float]:
        loop = fake_loop()
        async with SimDriver(rtf=1.0, wall=loop.time) as sim:
            background(ticker(sim.clock, 10, []))
            w0 = loop.time()
            await sim.run_until(1.0)
            w1 = loop.time()
            sim.rtf = 4.0
            await sim.run_until(3.0)
            w2 = loop.time()
            sim.rtf = None
            await sim.run_until(100.0)
            return [w1 - w0, w2 - w1, loop.time() - w2]

    first, second, third = run_fake(main())
    assert first == pytest.approx(1.0, abs=1e-3)
    assert second == pytest.approx(0.5, abs=1e-3)
    assert third < 0.05


def test_paced_run_on_real_loops_keeps_exact_sim_times(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> tuple[list[evclock.Tick], float | None]:
        async with SimDriver(rtf=200.0) as sim:
            ticks: list[evclock.Tick] = []
            background(ticker(sim.clock, 100, ticks))
            sim.achieved_rtf()
            await sim.run_until(0.5)  # about 2.5 ms of wall time
            return ticks, sim.achieved_rtf()

    ticks, achieved = run(main())
    assert [t.actual.nanoseconds for t in ticks] == [i * 10_000_000 for i in range(51)]
    assert achieved is not None
    assert achieved > 0


def test_lagging_behind_re_anchors_without_bursting() -> None:
    async def main() -> list[tuple[int, float]]:
        loop = fake_loop()
        async with SimDriver(rtf=1.0, wall=loop.time) as sim:
            stamps: list[tuple[int, float]] = []

            async def controller() -> None:
                async for tick in sim.clock.rate(10):
                    stamps.append((tick.index, loop.time()))
                    if tick.index == 5:
                        loop.fake += 1.0  # a 1 s hiccup (heavy computation) in wall time

            background(controller())
            await sim.run_until(1.0)
            return stamps

    stamps = run_fake(main())
    walls = dict(stamps)
    assert [i for i, _ in stamps] == list(range(11))
    # After the hiccup pacing re-anchors on the late time: tick 6 comes one period after
    # it, and later ticks keep the 0.1 s spacing instead of bursting to catch up.
    assert walls[6] - walls[5] == pytest.approx(1.1, abs=1e-3)
    for i in range(7, 11):
        assert walls[i] - walls[i - 1] == pytest.approx(0.1, abs=1e-4)


def test_strict_lag_fails_run_until_and_the_pending_waits() -> None:
    async def main() -> list[str]:
        loop = fake_loop()
        out: list[str] = []
        sim = SimDriver(rtf=1.0, strict=True, wall=loop.time)
        async with sim:

            async def controller() -> None:
                async for tick in sim.clock.rate(10):
                    if tick.index == 5:
                        loop.fake += 1.0  # a 1 s hiccup in wall time: more than max_lag

            task = asyncio.create_task(controller())
            try:
                await sim.run_until(1.0)
            except LagError as exc:
                out.append(str(exc))
            with pytest.raises(LagError) as same:
                await task  # the controller's pending wait failed the same way
            out.append(f"same error: {same.value is not None and str(same.value) == out[0]}")
            out.append(f"running={sim.running}")
        with pytest.raises(LoopClosedError) as info:
            sim.clock.sleep(1)
        out.append(str(info.value))
        await sim.stop()  # run_until already raised the error: not again
        return out

    out = run_fake(main())
    assert len(out) == 4
    assert re.fullmatch(
        r"the simulation lags 0\.9\d\d s of wall time behind rtf=1 \(strict limit 0\.1 s\); "
        r"lower the rtf, lighten the controllers or pass strict=False to let it run as fast "
        r"as it can",
        out[0],
    ), out[0]
    assert out[1:3] == ["same error: True", "running=False"]
    assert out[3] == (
        "this SimDriver is stopped and cannot be used again; create a new SimDriver (it can "
        f"take over the same time source); it stopped because of LagError: {out[0]}"
    )


def test_stop_re_raises_a_failure_nobody_saw() -> None:
    async def main() -> None:
        loop = fake_loop()
        sim = SimDriver(rtf=1.0, strict=True, wall=loop.time)
        sim.start()

        async def controller() -> None:
            async for tick in sim.clock.rate(10):
                if tick.index == 2:
                    loop.fake += 1.0

        task = asyncio.create_task(controller())
        while sim.running:
            await asyncio.sleep(0.01)
        with pytest.raises(LagError):
            await task
        with pytest.raises(LagError, match=r"^the simulation lags"):
            await sim.stop()
        await sim.stop()  # reported once

    run_fake(main())


# ------------------------------------------------------------------ pause, resume, step


def test_pause_resume_step(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        out: list[object] = []
        async with SimDriver(rtf=None, paused=True) as sim:
            ticks: list[int] = []
            reached = asyncio.Event()
            goal = [4]

            async def controller() -> None:
                async for tick in sim.clock.rate(10):
                    ticks.append(tick.index)
                    if len(ticks) == goal[0]:
                        reached.set()

            background(controller())
            sim.step(3)  # tick 0 needs no step; then three jumps
            await reached.wait()
            for _ in range(20):  # and it stays paused there
                await asyncio.sleep(0)
            out += [sim.paused, sim.now(), list(ticks)]
            sim.step_until(Time(seconds=1.05))
            await sim.run_until(Time(seconds=1.05))
            out += [sim.now(), ticks[-1], sim.paused]
            sim.resume()
            with pytest.raises(PacingError) as info:
                sim.step()
            out.append(str(info.value))
            await sim.run_until(2.0)
            out += [ticks[-1], sim.paused]
            sim.pause()
            await sim.run_until(2.5)  # paused: advances to exactly 2.5 and stays paused
            out += [sim.now(), ticks[-1], sim.paused, repr(sim)]
        return out

    assert run(main()) == [
        True,
        Time(seconds=0.3),
        [0, 1, 2, 3],
        Time(seconds=1.05),
        10,
        True,
        "step() needs a paused loop, but it is running as fast as possible; call pause() "
        "first, then step",
        20,
        False,
        Time(seconds=2.5),
        25,
        True,
        "<SimDriver running paused now=2.500000000 s (sim) rtf=None source=virtual time>",
    ]


def test_paused_run_until_is_the_notebook_workflow(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        sim = SimDriver(rtf=None, paused=True)
        out: list[object] = []
        await sim.run_until(5.0)  # starts the driver
        ticks: list[evclock.Tick] = []
        background(ticker(sim.clock, 1, ticks))
        await sim.run_until(7.5)
        out += [sim.now(), len(ticks), sim.paused]
        await sim.run_until(Time(seconds=7))  # already past: returns at once
        out.append(sim.now())
        await sim.stop()
        return out

    assert run(main()) == [Time(seconds=7.5), 3, True, Time(seconds=7.5)]


def test_paced_steps_are_paced_from_the_step_call() -> None:
    async def main() -> list[float]:
        loop = fake_loop()
        async with SimDriver(rtf=1.0, paused=True, wall=loop.time) as sim:
            background(ticker(sim.clock, 10, []))
            await asyncio.sleep(5.0)  # paused for 5 s of (fake) wall time
            w0 = loop.time()
            sim.step(2)
            await sim.clock.sleep(0.2)
            return [loop.time() - w0, sim.now().seconds]

    wall, now = run_fake(main())
    assert wall == pytest.approx(0.2, abs=1e-3)
    assert now == 0.2


def _operated_driver(
    script: Callable[[operated.Operator], None],
    *,
    via: str = "directly",
    start_paused: bool = True,
    prepare: Callable[[SimDriver], None] = lambda sim: None,
) -> tuple[list[object], list[float]]:
    """A task ticks every sim second (8 ticks, ``clock.sleep(1)``) under a paused SimDriver
    on virtual time; once the driver first waits paused (recorded), an operator thread runs
    ``script``, which must end with ``resume``. Returns the operator's records and every
    tick's time."""
    selector = operated.PausedWaits()
    operator = operated.Operator(selector, via)

    async def main() -> None:
        async with SimDriver(rtf=None, paused=start_paused) as sim:
            if not start_paused:
                sim.pause()
            prepare(sim)
            await operator.run(sim, script, sim.clock.sleep, lambda: sim.now_ns / 1e9)

    return operator.outcome(lambda: asyncio.SelectorEventLoop(selector), main)


@pytest.mark.parametrize("via", ["directly", "call_soon_threadsafe"])
@pytest.mark.parametrize("start_paused", [True, False], ids=["paused=True", "pause()"])
def test_each_step_from_an_operator_thread_jumps_to_the_next_deadline(
    via: str, start_paused: bool
) -> None:
    """On virtual time a step is one jump to the next deadline (one wake-up batch), after
    which the driver holds again; step(n) is n jumps; step_until(t) stops exactly at t."""

    seen, ticks = _operated_driver(
        operated.step_1_1_1_2_until_6_5, via=via, start_paused=start_paused
    )
    assert seen == operated.STEPPED_SEEN
    assert ticks == operated.TICKS


@pytest.mark.parametrize("how", ["pause", "resume", "step_until"])
def test_a_step_until_ended_early_leaves_nothing_for_a_step_to_stop_at(how: str) -> None:
    """pause(), resume() or a new step_until() end a step_until() before its target: its
    stop mark goes with it, so a later step still jumps to the next wake-up, not there."""

    seen, ticks = _operated_driver(
        operated.step_1_three_times, prepare=lambda sim: operated.end_a_step_until(sim, how)
    )
    first = 0.5 if how == "step_until" else 0.0
    assert seen == [(first, []), *operated.STEPPED_SEEN[1:4]]
    assert ticks == operated.TICKS


# ------------------------------------------------------------------ jumps


def test_backward_jump_wakes_sleepers_with_clock_jumped(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> list[object]:
        out: list[object] = []
        async with SimDriver(rtf=None) as sim:
            source = sim.source
            assert isinstance(source, evclock.sources.VirtualTimeSource)
            sim.clock.on_jump(lambda j: out.append(("pre", j)), lambda j: out.append(("post", j)))
            ticks: list[evclock.Tick] = []

            async def sleeper() -> None:
                try:
                    await sim.clock.sleep(10)
                except ClockJumpedError as exc:
                    out.append(("sleeper", exc.jump, sim.now()))

            async def resetter() -> None:
                await sim.clock.sleep(4.5)
                source.set_time(1_000_000_000)

            background(sleeper())
            background(resetter())
            background(ticker(sim.clock, 1, ticks))
            await sim.run_until(8)  # goes on after the jump until time reaches 8 again
            out.append(sim.now())
            out.append([(t.index, t.actual.seconds) for t in ticks])
        out.append(source.now_ns)  # the source keeps the time after the driver stopped
        return out

    jump = TimeJump(Time(seconds=4.5), Time(seconds=1))
    assert run(main()) == [
        ("pre", jump),
        ("post", jump),
        ("sleeper", jump, Time(seconds=1)),
        Time(seconds=8),
        # the rate re-anchored on the new time (tick 0 again at 1 s)
        [(i, float(i)) for i in range(5)] + [(i - 1, float(i)) for i in range(1, 9)],
        8_000_000_000,
    ]


# ------------------------------------------------------------------ life cycle


def test_stop_leaves_no_pending_tasks(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        out: list[object] = []
        wall = evclock.clock()
        sim = SimDriver(rtf=None)
        driver_task = sim.start()
        controller = asyncio.create_task(ticker(sim.clock, 100, []))
        waiter = asyncio.create_task(sim.run_until(1000))
        await sim.run_until(1.0)
        await sim.stop()
        out += [driver_task.done(), controller.cancelled(), sim.running, waiter.done()]
        with pytest.raises(LoopClosedError) as info:
            await waiter
        out.append(str(info.value))
        out.append(asyncio.all_tasks() == {asyncio.current_task()})
        out.append(evclock.clock() is wall)
        await sim.stop()  # idempotent
        return out

    assert run(main()) == [
        True,
        True,
        False,
        True,
        "the SimDriver was stopped before sim time reached the run_until() target",
        True,
        True,
    ]


def test_waits_started_while_stopping_are_cancelled_then_refused(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> list[object]:
        log: list[object] = []
        async with SimDriver(rtf=None) as sim:
            loop = sim.loop

            async def stubborn() -> None:
                try:
                    await sim.clock.sleep(100)
                except asyncio.CancelledError:
                    log.append("cancelled")
                    try:
                        await sim.clock.sleep(1)
                    except asyncio.CancelledError:
                        log.append("cancelled again while stopping")
                        raise

            task = asyncio.create_task(stubborn())
            await sim.run_until(1)
        log += [task.cancelled(), loop is asyncio.get_running_loop()]
        with pytest.raises(LoopClosedError):
            sim.clock.sleep(1)
        return log

    assert run(main()) == ["cancelled", "cancelled again while stopping", True, True]


def test_a_source_can_go_on_under_a_new_driver(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[int]:
        source = evclock.sources.VirtualTimeSource()
        async with SimDriver(source, rtf=None) as sim:
            await sim.run_until(2.0)
        async with SimDriver(source, rtf=None) as again:
            first = again.now_ns
            await again.clock.sleep(1)
            return [first, again.now_ns]

    assert run(main()) == [2_000_000_000, 3_000_000_000]


def test_idle_driver_waits_for_sleeps_registered_later(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    async def main() -> list[int]:
        async with SimDriver(rtf=None) as sim:
            await asyncio.sleep(0.01)  # nothing scheduled: sim time stands still, no error
            idle = sim.now_ns
            await sim.clock.sleep(2)  # a request handler sleeping on sim time, say
            return [idle, sim.now_ns]

    assert run(main()) == [0, 2_000_000_000]


def test_driver_task_cancelled_by_loop_shutdown_cleans_up(
    run: Callable[[Awaitable[Any]], Any],
) -> None:
    sims: list[SimDriver] = []

    async def main() -> None:
        sim = SimDriver(rtf=None)
        sims.append(sim)
        sim.start()  # never stopped: the runner cancels the driver task at the end
        background(ticker(sim.clock, 10, []))

    run(main())
    assert not sims[0].running
    with pytest.raises(LoopClosedError):
        sims[0].pause()


# ------------------------------------------------------------------ errors


STOPPED = (
    "this SimDriver is stopped and cannot be used again; create a new SimDriver (it can take "
    "over the same time source)"
)


def test_errors_of_the_life_cycle(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> None:
        sim = SimDriver()
        with pytest.raises(NotRunningError) as info:
            sim.clock.sleep(1)
        assert str(info.value) == (
            "this SimDriver is not running: start it (async with evclock.SimDriver() as sim: "
            "..., or sim.start()) before waiting on its clock"
        )
        with pytest.raises(NotRunningError) as info:
            sim.pause()
        assert str(info.value) == (
            "pause() needs a running SimDriver; start it first (async with evclock.SimDriver() "
            "as sim: ..., or sim.start()), or create it with paused=True to start paused"
        )
        async with sim:
            with pytest.raises(SimDriverError) as err:
                sim.start()
            assert str(err.value) == (
                "this SimDriver is already running; a driver is started once (by async with, "
                "start() or run_until())"
            )
            with pytest.raises(SimDriverError) as err:
                await SimDriver().__aenter__()
            assert str(err.value) == (
                "another SimDriver is already running on this event loop; stop it first (one "
                "sim clock per loop)"
            )
            with pytest.raises(NotRunningError) as info:
                await asyncio.to_thread(sim.clock.sleep, 1)
            assert str(info.value) == (
                "this SimDriver's clock can only be waited on from the event loop the driver "
                "runs on (in its thread)"
            )
            # A SimClock like the loop's: its loop is the one its waits run on, its host
            # the driver that controls its time.
            assert sim.clock.loop is asyncio.get_running_loop()
            assert sim.clock.host is sim
            assert isinstance(sim.clock, SimClock)
            assert isinstance(sim.clock, SimDriverClock)
            assert sim.clock.driver is sim
        for action in (
            lambda: sim.clock.sleep(1),
            lambda: sim.clock.sleep_until(Time(seconds=9)),
            sim.start,
            sim.pause,
            sim.resume,
            sim.step,
        ):
            with pytest.raises(LoopClosedError) as closed:
                action()
            assert str(closed.value) == STOPPED
        with pytest.raises(LoopClosedError) as closed:
            await sim.run_until(1)
        assert str(closed.value) == STOPPED
        assert sim.clock.now() == Time(seconds=0)  # reading the time still works

    run(main())


def test_start_needs_a_running_loop_that_is_not_a_sim_loop() -> None:
    with pytest.raises(NotRunningError) as info:
        SimDriver().start()
    assert str(info.value) == (
        "SimDriver.start() needs a running event loop; call it from a coroutine (async with "
        "evclock.SimDriver() as sim: ...)"
    )

    async def on_sim_loop() -> None:
        SimDriver().start()

    with pytest.raises(SimDriverError) as err:
        evclock.run(on_sim_loop())
    source = evclock.sources.VirtualTimeSource()
    loop = evclock.SimEventLoop(source)

    async def source_in_use() -> None:
        SimDriver(source).start()

    try:
        with pytest.raises(evclock.sources.SourceInUseError) as base:
            asyncio.run(source_in_use())
    finally:
        loop.close()
    assert str(base.value) == (
        "VirtualTimeSource is already attached to another loop; create one time source per loop"
    )
    assert str(err.value) == (
        "SimDriver drives sim time on loops evclock does not own, but this loop is a "
        "SimEventLoop, whose time already is sim time; use evclock.clock() and the loop's "
        "pause(), step() and rtf instead"
    )


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        (
            {"source": 3},
            InvalidTypeError,
            "source must be a TimeSource (e.g. VirtualTimeSource(), PyBulletTimeSource(...)), "
            "got int",
        ),
        (
            {"rtf": 0},
            InvalidArgumentError,
            "rtf must be a positive finite real-time factor (1.0 = real time), got 0; use "
            "rtf=None to run as fast as possible",
        ),
        (
            {"max_lag": -1.0},
            InvalidArgumentError,
            "max_lag must be a positive number of seconds, got -1.0",
        ),
        ({"max_settle_yields": 0}, InvalidArgumentError, "max_settle_yields must be >= 1, got 0"),
        (
            {"max_settle_yields": 2.5},
            InvalidTypeError,
            "max_settle_yields must be an int, got float",
        ),
        ({"wall": 1.0}, InvalidTypeError, "wall must be a callable returning seconds, got float"),
    ],
)
def test_constructor_errors(kwargs: dict[str, Any], error: type[Exception], message: str) -> None:
    with pytest.raises(error) as info:
        SimDriver(**kwargs)
    assert str(info.value) == message


def test_control_and_run_until_errors(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> None:
        async with SimDriver(rtf=None) as sim:
            cases: list[tuple[Callable[[], object], type[Exception], str]] = [
                (
                    sim.step,
                    PacingError,
                    "step() needs a paused loop, but it is running as fast as possible; call "
                    "pause() first, then step",
                ),
                (
                    lambda: sim.step_until(Time(seconds=1)),
                    PacingError,
                    "step_until() needs a paused loop, but it is running as fast as possible; "
                    "call pause() first, then step",
                ),
                (lambda: sim.step(0), InvalidArgumentError, "step() count must be >= 1, got 0"),
                (lambda: sim.step(1.0), InvalidTypeError, "step() count must be an int, got float"),  # type: ignore[arg-type]
                (
                    lambda: sim.step_until(1.0),  # type: ignore[arg-type]
                    InvalidTypeError,
                    "step_until() needs a Time, got float",
                ),
                (
                    lambda: sim.step_until(Time(seconds=1, clock_type=evclock.STEADY)),
                    ClockMismatchError,
                    "step_until() needs a sim time, got a steady time",
                ),
                (
                    lambda: sim.step_until(Time(seconds=0)),
                    InvalidArgumentError,
                    "step_until() target 0.000000000 s (sim) is not after the current sim "
                    "time 0.000000000 s (sim)",
                ),
                (
                    lambda: setattr(sim, "rtf", -2),
                    InvalidArgumentError,
                    "rtf must be a positive finite real-time factor (1.0 = real time), got -2; "
                    "use rtf=None to run as fast as possible",
                ),
                (
                    lambda: sim.clock.sleep(-1.0),
                    InvalidArgumentError,
                    "sleep duration must not be negative, got -1.0; a negative sleep is a bug "
                    "in the caller; to wait until a time use sleep_until()",
                ),
            ]
            for action, error, message in cases:
                with pytest.raises(error) as info:
                    action()
                assert str(info.value) == message
            sim.pause()
            with pytest.raises(InvalidArgumentError) as bad:
                sim.step_until(Time(seconds=0))
            assert "is not after the current sim time" in str(bad.value)
            run_until_cases: list[tuple[object, type[Exception], str]] = [
                (-1, InvalidArgumentError, "run_until() time must not be negative, got -1"),
                (
                    "5",
                    InvalidTypeError,
                    "run_until() time must be seconds (int or float) or a Duration, got str",
                ),
                (
                    Duration(seconds=1),
                    InvalidTypeError,
                    "run_until() needs a sim Time or seconds since the sim epoch, got Duration; "
                    "to run for a duration use run_until(sim.now() + duration)",
                ),
                (
                    Time(seconds=1, clock_type=evclock.SYSTEM),
                    ClockMismatchError,
                    "run_until() time must be a sim time, got a system time",
                ),
            ]
            for when, error, message in run_until_cases:
                with pytest.raises(error) as info:
                    await sim.run_until(when)  # type: ignore[arg-type]
                assert str(info.value) == message

    run(main())


# ------------------------------------------------------------------ PyBullet


@pytest.mark.pybullet
def test_pybullet_source_steps_in_lockstep(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        source = evclock.sources.PyBulletTimeSource.connect()
        try:
            out: list[object] = []
            async with SimDriver(source, rtf=None) as sim:
                ticks: list[evclock.Tick] = []
                background(ticker(sim.clock, 60, ticks))
                event = asyncio.Event()
                woke: list[int] = []

                def hook() -> None:
                    if source.step_index == 100:
                        event.set()

                async def waiter() -> None:
                    await event.wait()
                    woke.append(source.step_index)  # no step taken after the hook woke us

                background(waiter())
                handle = source.add_step_hook(hook)
                await sim.run_until(1.0)
                handle.remove()
                out += [sim.now(), source.step_index, woke]
                out.append(all(t.actual == t.expected for t in ticks))
                out.append(len(ticks))
                await sim.clock.sleep(0.001)  # quantised up to the next step boundary
                out.append(source.step_index)
                out.append(sim.lockstep_overruns)
            return out
        finally:
            source.close()

    assert run(main()) == [Time(seconds=1), 240, [100], True, 61, 241, 0]


@pytest.mark.pybullet
def test_pybullet_paused_steps_whole_physics_steps(run: Callable[[Awaitable[Any]], Any]) -> None:
    async def main() -> list[object]:
        source = evclock.sources.PyBulletTimeSource.connect()
        try:
            async with SimDriver(source, rtf=None, paused=True) as sim:
                reached = asyncio.Event()

                def hook() -> None:
                    if source.step_index == 5:
                        reached.set()

                source.add_step_hook(hook)
                sim.step(5)  # nothing scheduled: physics free-runs, one step per increment
                await reached.wait()
                for _ in range(20):
                    await asyncio.sleep(0)
                out: list[object] = [source.step_index, sim.now() == source.time_of_step(0)]
                await sim.run_until(0.1)  # paused: steps to the first boundary >= 0.1 s
                out += [source.step_index, sim.paused]
            return out
        finally:
            source.close()

    assert run(main()) == [5, True, 24, True]


@pytest.mark.pybullet
def test_pybullet_free_runs_and_is_paced_step_by_step() -> None:
    async def main() -> list[object]:
        loop = fake_loop()
        source = evclock.sources.PyBulletTimeSource.connect()
        try:
            async with SimDriver(source, rtf=1.0, wall=loop.time):
                stamps: list[tuple[int, float]] = []
                source.add_step_hook(lambda: stamps.append((source.step_index, loop.time())))
                await asyncio.sleep(0.05)  # nothing scheduled: physics free-runs, paced
                return [
                    len(stamps) >= 10,
                    all(
                        b[1] - a[1] == pytest.approx(1 / 240, abs=1e-4)
                        for a, b in itertools.pairwise(stamps[1:])
                    ),
                ]
        finally:
            source.close()

    assert run_fake(main()) == [True, True]


# ------------------------------------------------------------------ the example


NOTEBOOK_STYLE = """\
kernel loop: _UnixSelectorEventLoop; a SimEventLoop: False
evclock.clock() is sim.clock: True
[sim  0.000 s] joint_control tick 0: position 0.0500
[sim  1.500 s] planner: new goal 2.0
[sim  2.000 s] joint_control tick 100: position 1.7309
[sim  3.000 s] planner: new goal 0.5
[sim  4.000 s] joint_control tick 200: position 0.6081
[sim  4.500 s] planner: new goal 1.5
[sim  5.000 s] run_until(5.0) returned; paused: True
[sim  5.060 s] step(3) done; still paused: True
[sim  5.060 s] plain asyncio.sleep(0.02) while paused: sim time moved: False
plain asyncio.sleep(0.02) while running: sim time moved on: True
every advance in lockstep: True
planner finished: True; controller cancelled: True
evclock.clock() is now a WallClock
"""


@pytest.mark.skipif(sys.platform == "win32", reason="the loop class name differs on Windows")
def test_notebook_style_example_runs_on_a_loop_it_does_not_own() -> None:
    proc = run_example("notebook_style.py")
    assert proc.stderr == ""
    assert proc.stdout == NOTEBOOK_STYLE


@pytest.mark.pybullet
def test_pybullet_wait_until_and_sleep_steps_under_the_driver(
    run: Callable[[Coroutine[Any, Any, T]], T],
) -> None:
    async def main() -> tuple[int, int, int]:
        source = evclock.sources.PyBulletTimeSource.connect()
        try:
            async with evclock.SimDriver(source, rtf=None):
                reached = await source.wait_until(lambda: source.step_index >= 37, timeout=1)
                at_predicate = source.step_index
                await source.sleep_steps(3)
                return reached.nanoseconds, at_predicate, source.step_index
        finally:
            source.close()

    reached_ns, at_predicate, after = run(main())
    assert at_predicate == 37
    assert reached_ns == 37 * 10**9 // 240
    assert after == 40
