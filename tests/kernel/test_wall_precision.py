"""Precise wall-time waits (``WallClock(precise=True)``): functional properties only.

No timing thresholds here: how precise the waits are is measured by
``benchmarks/wall_rate_1khz.py``. These tests check what must hold on any machine: a wait
never returns before its deadline, rates tick in order, other tasks keep running, the
validation is unchanged, and the Linux-only parts degrade to no-ops elsewhere.
"""

from __future__ import annotations

import asyncio
import gc
import math
import os
import sys
import time
from collections.abc import Coroutine
from typing import Any, TypeVar

import pytest

import evclock
from evclock.kernel import _precise
from evclock.time._time import Duration

_T = TypeVar("_T")

# Short, medium, and long enough to take the coarse phase (> 5 ms) first.
DURATIONS_NS = (0, 1, 10_000, 100_000, 999_999, 1_000_000, 2_500_000, 7_000_000)
MARGINS = (0.0, 50e-6, 2e-3)
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux only")


def run_wall(coro: Coroutine[Any, Any, _T]) -> _T:
    """Run ``coro`` on wall time, as ``evclock.run(..., use_sim_time=False)`` does."""
    return evclock.run(coro, use_sim_time=False)


@pytest.fixture
def no_timerfd(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the timerfd unavailable, as on a non-Linux system (forces the fallback)."""

    def unavailable(clockid: int) -> int:
        raise OSError("timerfd unavailable (simulated)")

    monkeypatch.setattr(_precise, "_timerfd_create", unavailable)


@pytest.fixture
def no_prctl(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ctypes' libc unavailable, as on a non-Linux system: no timerfd, no prctl."""
    monkeypatch.setattr(_precise, "_libc", None)


# --------------------------------------------------------------------------------------
# Never early


async def _check_never_early(clock: evclock.WallClock) -> None:
    for ns in DURATIONS_NS:
        deadline = clock.now_ns() + ns
        await clock.sleep_until_ns(deadline)
        assert clock.now_ns() >= deadline, ns
        # The public forms: sleep_until(Time) and sleep(seconds | Duration).
        when = clock.now() + Duration(nanoseconds=ns)
        await clock.sleep_until(when)
        assert clock.now() >= when, ns
        before = time.monotonic_ns()
        await clock.sleep(Duration(nanoseconds=ns))
        assert time.monotonic_ns() >= before + ns, ns
        before = time.monotonic_ns()
        await clock.sleep(ns / 1e9)
        assert time.monotonic_ns() >= before + round(ns / 1e9 * 1e9), ns


@pytest.mark.parametrize("margin", MARGINS)
@pytest.mark.parametrize("clock_type", [evclock.STEADY, evclock.SYSTEM])
def test_precise_sleep_never_returns_before_its_deadline(
    margin: float, clock_type: evclock.ClockType
) -> None:
    run_wall(_check_never_early(evclock.WallClock(clock_type, spin_margin=margin)))


@pytest.mark.usefixtures("no_timerfd")
@pytest.mark.parametrize("margin", MARGINS)
def test_fallback_without_timerfd_never_returns_early(margin: float) -> None:
    async def main() -> None:
        clock = evclock.WallClock(spin_margin=margin)
        await _check_never_early(clock)
        assert _precise.precise_timer(asyncio.get_running_loop(), 1, time.monotonic_ns) is None

    run_wall(main())


def test_the_default_clock_of_a_wall_run_is_precise() -> None:
    async def main() -> evclock.Clock:
        clock = evclock.clock()
        await _check_never_early(clock)  # type: ignore[arg-type]
        return clock

    clock = run_wall(main())
    assert isinstance(clock, evclock.WallClock)
    assert clock.precise
    assert clock.spin_margin == Duration(nanoseconds=_precise.DEFAULT_SPIN_MARGIN_NS)


def test_many_concurrent_sleepers_each_wake_at_or_after_their_own_deadline() -> None:
    async def main() -> list[tuple[int, int]]:
        clock = evclock.WallClock()
        base = clock.now_ns()
        # Out of order, duplicates, and one already past: the shared timer's heap.
        offsets = [3_000_000, 500_000, 1_500_000, 500_000, -1, 2_000_000, 100_000, 4_200_000]

        async def sleeper(offset: int) -> tuple[int, int]:
            await clock.sleep_until_ns(base + offset)
            return base + offset, clock.now_ns()

        return list(await asyncio.gather(*(sleeper(o) for o in offsets)))

    for deadline, woke in run_wall(main()):
        assert woke >= deadline


@linux_only
def test_a_cancelled_sleeper_does_not_disturb_the_others() -> None:
    async def main() -> tuple[bool, int, int]:
        clock = evclock.WallClock(spin_margin=0)
        start = clock.now_ns()
        doomed = asyncio.ensure_future(clock.sleep_until_ns(start + 1_000_000))
        survivor_deadline = start + 3_000_000
        survivor = asyncio.ensure_future(clock.sleep_until_ns(survivor_deadline))
        await asyncio.sleep(0)
        doomed.cancel()
        await survivor
        woke = clock.now_ns()
        # The timer keeps serving new sleepers after a cancellation.
        later = clock.now_ns() + 200_000
        await clock.sleep_until_ns(later)
        assert clock.now_ns() >= later
        return doomed.cancelled(), woke, survivor_deadline

    cancelled, woke, deadline = run_wall(main())
    assert cancelled
    assert woke >= deadline


def test_a_past_deadline_still_yields_once() -> None:
    async def main() -> list[str]:
        clock = evclock.WallClock()
        order: list[str] = []
        asyncio.get_running_loop().call_soon(order.append, "other")
        await clock.sleep_until_ns(clock.now_ns() - 1_000_000)
        order.append("sleeper")
        asyncio.get_running_loop().call_soon(order.append, "other again")
        await clock.sleep(0)
        order.append("sleeper again")
        return order

    assert run_wall(main()) == ["other", "sleeper", "other again", "sleeper again"]


# --------------------------------------------------------------------------------------
# Rates, other tasks


@pytest.mark.parametrize("margin", [0.0, 50e-6])
def test_a_wall_rate_ticks_in_order_with_correct_indices(margin: float) -> None:
    async def main() -> tuple[list[evclock.Tick], evclock.Rate]:
        clock = evclock.WallClock(spin_margin=margin)
        rate = clock.rate(1000)
        ticks: list[evclock.Tick] = []
        async for tick in rate:
            ticks.append(tick)
            if len(ticks) == 50:
                break
        return ticks, rate

    ticks, rate = run_wall(main())
    first = ticks[0]
    assert first.index == 0
    assert first.expected == first.actual
    start = first.expected.nanoseconds
    previous = first
    for tick in ticks[1:]:
        # Skipped deadlines (a loaded machine) are counted, never silently lost.
        assert tick.index == previous.index + 1 + tick.missed
        assert tick.expected.nanoseconds == start + tick.index * 1_000_000
        assert tick.actual >= tick.expected
        assert tick.actual >= previous.actual
        assert tick.lateness >= Duration(0)
        previous = tick
    assert rate.stats.ticks == len(ticks)


@pytest.mark.parametrize("margin", [0.0, 50e-6, 60.0])
def test_other_tasks_run_while_a_precise_sleeper_waits(margin: float) -> None:
    # With a 60 s margin the whole 30 s wait is the spin phase: it must yield too. The test
    # ends (and cancels the sleeper) once the other tasks have run: no wall-time window.
    async def main() -> tuple[int, bool]:
        clock = evclock.WallClock(spin_margin=margin)
        sleeper = asyncio.create_task(clock.sleep_until_ns(clock.now_ns() + 30 * 10**9))
        await asyncio.sleep(0)  # the sleeper is waiting
        counter = 0
        ticked = asyncio.Event()

        async def busy() -> None:
            nonlocal counter
            while True:
                counter += 1
                await asyncio.sleep(0)

        async def periodic() -> None:
            for _ in range(3):
                await asyncio.sleep(0.001)
            ticked.set()

        tasks = [asyncio.create_task(busy()), asyncio.create_task(periodic())]
        await asyncio.wait_for(ticked.wait(), 20)
        still_waiting = not sleeper.done()
        for task in (sleeper, *tasks):
            task.cancel()
        await asyncio.gather(sleeper, *tasks, return_exceptions=True)
        return counter, still_waiting

    counted, still_waiting = run_wall(main())
    assert counted > 0
    assert still_waiting


def test_a_wall_timer_fires_on_the_precise_clock() -> None:
    async def main() -> list[int]:
        clock = evclock.WallClock()
        lateness: list[int] = []
        done = asyncio.Event()

        def callback() -> None:
            lateness.append(timer.stats.recent_lateness_ns[-1])
            if len(lateness) == 5:
                done.set()

        timer = clock.timer(0.002, callback)
        await done.wait()
        timer.cancel()
        return lateness

    assert all(late >= 0 for late in run_wall(main()))


# --------------------------------------------------------------------------------------
# Validation and configuration


BAD_DURATIONS: list[object] = [-1, -0.5, math.nan, math.inf, -math.inf, "1", None, True, []]


def _sleep_error(clock: evclock.WallClock, duration: object) -> BaseException:
    async def main() -> None:
        await clock.sleep(duration)  # type: ignore[arg-type]

    with pytest.raises(evclock.EvClockError) as info:
        run_wall(main())
    return info.value


@pytest.mark.parametrize("duration", BAD_DURATIONS, ids=repr)
def test_sleep_validation_errors_are_unchanged(duration: object) -> None:
    precise = _sleep_error(evclock.WallClock(), duration)
    plain = _sleep_error(evclock.WallClock(precise=False), duration)
    assert type(precise) is type(plain)
    assert str(precise) == str(plain)


def test_sleep_until_validation_errors_are_unchanged() -> None:
    async def main() -> None:
        clock = evclock.WallClock()
        with pytest.raises(evclock.InvalidTypeError, match=r"^sleep_until\(\) needs a Time"):
            await clock.sleep_until(1.0)  # type: ignore[arg-type]
        with pytest.raises(evclock.ClockMismatchError, match="but this is a steady clock"):
            await clock.sleep_until(evclock.Time(seconds=1, clock_type=evclock.SYSTEM))

    run_wall(main())


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"precise": 1}, evclock.InvalidTypeError, r"^precise must be True or False, got int$"),
        ({"spin_margin": -1e-6}, evclock.InvalidArgumentError, r"^spin_margin must not be"),
        ({"spin_margin": math.nan}, evclock.InvalidArgumentError, "spin_margin"),
        ({"spin_margin": "1"}, evclock.InvalidTypeError, "spin_margin"),
        ({"timer_slack": 0}, evclock.InvalidArgumentError, r"^timer_slack must be positive"),
        ({"timer_slack": -1.0}, evclock.InvalidArgumentError, r"^timer_slack must be positive"),
    ],
)
def test_constructor_validation(
    kwargs: dict[str, Any], error: type[Exception], message: str
) -> None:
    with pytest.raises(error, match=message):
        evclock.WallClock(**kwargs)


def test_constructor_keeps_its_clock_type_check() -> None:
    with pytest.raises(evclock.InvalidArgumentError, match="a wall clock is STEADY or SYSTEM"):
        evclock.WallClock(evclock.SIM)


def test_configuration_is_readable() -> None:
    clock = evclock.WallClock(evclock.SYSTEM, spin_margin=Duration(nanoseconds=120_000))
    assert clock.precise
    assert clock.spin_margin == Duration(nanoseconds=120_000)
    assert clock.clock_type is evclock.SYSTEM
    assert not evclock.WallClock(precise=False).precise


def test_imprecise_clock_keeps_the_old_behaviour() -> None:
    async def main() -> bool:
        clock = evclock.WallClock(precise=False)
        before = time.monotonic_ns()
        await clock.sleep(0.002)
        return time.monotonic_ns() > before

    assert run_wall(main())


# --------------------------------------------------------------------------------------
# uvloop


def test_precise_waits_work_under_uvloop() -> None:
    uvloop = pytest.importorskip("uvloop")

    async def main() -> list[evclock.Tick]:
        clock = evclock.clock()
        assert isinstance(clock, evclock.WallClock)
        assert clock.precise
        await _check_never_early(clock)
        ticks: list[evclock.Tick] = []
        async for tick in clock.rate(1000):
            ticks.append(tick)
            if len(ticks) == 20:
                break
        counter = 0

        async def busy() -> None:
            nonlocal counter
            while True:
                counter += 1
                await asyncio.sleep(0)

        task = asyncio.create_task(busy())
        await clock.sleep(0.02)
        task.cancel()
        assert counter > 0
        return ticks

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        ticks = runner.run(main())
    assert [t.index for t in ticks] == sorted({t.index for t in ticks})
    assert all(t.actual >= t.expected for t in ticks)


# --------------------------------------------------------------------------------------
# Linux parts: timerfd lifetime, prctl guard


@linux_only
def test_the_timerfd_is_shared_and_closed_with_its_loop() -> None:
    async def main() -> int:
        clock = evclock.WallClock()
        await clock.sleep(0.001)
        loop = asyncio.get_running_loop()
        timer = _precise.precise_timer(loop, _precise.CLOCK_MONOTONIC, time.monotonic_ns)
        assert timer is not None
        await evclock.WallClock().sleep(0.001)  # another clock, same loop: same timer
        assert _precise.precise_timer(loop, _precise.CLOCK_MONOTONIC, time.monotonic_ns) is timer
        return timer._fd

    loop = asyncio.new_event_loop()
    try:
        fd = loop.run_until_complete(main())
        os.fstat(fd)  # open while the loop lives
    finally:
        loop.close()
    del loop
    gc.collect()
    with pytest.raises(OSError, match="Bad file descriptor"):
        os.fstat(fd)


@pytest.mark.usefixtures("no_prctl")
def test_prctl_guard_is_a_no_op_when_unavailable() -> None:
    assert _precise.get_timer_slack() is None
    assert _precise.set_timer_slack(1) is None
    slack = _precise.TimerSlack(1)
    slack.acquire()
    slack.release()

    async def main() -> None:
        clock = evclock.WallClock(timer_slack=1e-9)
        await _check_never_early(clock)

    run_wall(main())


def test_prctl_failure_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    class FailingLibc:
        def prctl(self, *args: object) -> int:
            return -1

    monkeypatch.setattr(_precise, "_libc", FailingLibc())
    assert _precise.get_timer_slack() is None
    assert _precise.set_timer_slack(1) is None


def test_timer_slack_must_be_positive() -> None:
    message = "^timer slack must be a positive number of nanoseconds, got {}$"
    with pytest.raises(evclock.InvalidArgumentError, match=message.format(0)):
        _precise.set_timer_slack(0)
    with pytest.raises(evclock.InvalidArgumentError, match=message.format(0)):
        _precise.TimerSlack(0)
    with pytest.raises(evclock.InvalidArgumentError, match=message.format("True")):
        _precise.TimerSlack(True)


def test_timer_slack_is_lowered_only_while_waiting_and_restored() -> None:
    original = _precise.get_timer_slack()
    if original is None:
        pytest.skip("prctl(PR_GET_TIMERSLACK) is not available here")
    wanted = 1_000 if original != 1_000 else 2_000

    async def main() -> tuple[int | None, int | None, int | None, int | None]:
        clock = evclock.WallClock(timer_slack=Duration(nanoseconds=wanted), spin_margin=0)
        before = _precise.get_timer_slack()
        first = asyncio.create_task(clock.sleep(0.002))
        second = asyncio.create_task(clock.sleep(0.004))
        await asyncio.sleep(0)  # both are now waiting on the timer
        during = _precise.get_timer_slack()
        await first
        # Still lowered while the second wait is pending (if the loop was not held up
        # long enough for it to be over already).
        between = _precise.get_timer_slack() if not second.done() else wanted
        await second
        return before, during, between, _precise.get_timer_slack()

    before, during, between, after = run_wall(main())
    assert before == original
    assert during == wanted
    assert between == wanted
    assert after == original
    assert _precise.get_timer_slack() == original
