"""Rate loops (drift-free, missed-period policies) and timers on sim time."""

from __future__ import annotations

import asyncio
import logging

import pytest

import evclock
from evclock import Duration, Time


def ns(t: Time) -> int:
    return t.nanoseconds


def test_rate_ticks_on_an_exact_grid_and_reports_expected_and_actual() -> None:
    async def main() -> list[tuple[int, int, int, int]]:
        out = []
        async for tick in evclock.clock().rate(240):
            out.append((tick.index, ns(tick.expected), ns(tick.actual), tick.missed))
            if tick.index == 4:
                break
        return out

    assert evclock.run(main()) == [
        (0, 0, 0, 0),
        (1, 4_166_666, 4_166_666, 0),
        (2, 8_333_333, 8_333_333, 0),
        (3, 12_500_000, 12_500_000, 0),
        (4, 16_666_666, 16_666_666, 0),
    ]


def _overrun(policy: evclock.kernel._rate.Policy) -> list[tuple[int, int, int, int]]:
    """10 ms period; the body of tick 1 takes 25 ms."""

    async def main() -> list[tuple[int, int, int, int]]:
        clock = evclock.clock()
        out = []
        async for tick in clock.rate(100, policy=policy):
            out.append(
                (tick.index, ns(tick.expected) // 10**6, ns(tick.actual) // 10**6, tick.missed)
            )
            if tick.index == 1 and len(out) == 2:
                await clock.sleep(0.025)
            if len(out) == 6:
                break
        return out

    return evclock.run(main())


def test_skip_policy_delivers_one_late_tick_for_the_latest_deadline() -> None:
    assert _overrun("skip") == [
        (0, 0, 0, 0),
        (1, 10, 10, 0),
        (3, 30, 35, 1),  # deadline 20 got no tick
        (4, 40, 40, 0),
        (5, 50, 50, 0),
        (6, 60, 60, 0),
    ]


@pytest.mark.parametrize("policy", ["skip", "catch_up"])
def test_a_body_that_ends_exactly_on_a_fractional_deadline_gets_that_tick(
    policy: evclock.kernel._rate.Policy,
) -> None:
    """300 Hz: the period is 10/3 ms, deadline 1 is at 3,333,333 ns. A body that runs until
    exactly the next deadline gets it at once (it was counted as not passed yet: tick 0
    again, with -1 missed, for ever)."""

    async def main() -> list[tuple[int, int, int, int]]:
        clock = evclock.clock()
        out = []
        async for tick in clock.rate(300, policy=policy):
            out.append((tick.index, tick.expected_ns, tick.actual_ns, tick.missed))
            if len(out) == 4:
                break
            await clock.sleep_until_ns((tick.index + 1) * 10_000_000 // 3)
        return out

    assert evclock.run(main()) == [
        (0, 0, 0, 0),
        (1, 3_333_333, 3_333_333, 0),
        (2, 6_666_666, 6_666_666, 0),
        (3, 10_000_000, 10_000_000, 0),
    ]


def test_a_deadline_grid_serves_the_last_deadline_passed() -> None:
    from fractions import Fraction

    from evclock.kernel._rate import DeadlineGrid

    grid = DeadlineGrid(Fraction(10_000_000, 3))  # 300 Hz
    grid.start(1_000)
    assert grid.next_ns == 1_000
    assert grid.serve(1_000) == 0
    assert grid.next_ns == 3_334_333
    assert grid.serve(3_334_333) == 0  # exactly on deadline 1
    assert grid.next_ns == 6_667_666
    assert grid.serve(10_001_000) == 1  # deadline 3, exactly; deadline 2 missed
    assert grid.next_ns == 13_334_333
    grid.start(5)  # after a jump
    assert (grid.next_ns, grid.serve(7)) == (5, 0)
    with pytest.raises(evclock.InvalidArgumentError, match=r"^a deadline grid needs a positive"):
        DeadlineGrid(0)


def test_catch_up_policy_bursts_every_missed_tick() -> None:
    assert _overrun("catch_up") == [
        (0, 0, 0, 0),
        (1, 10, 10, 0),
        (2, 20, 35, 0),
        (3, 30, 35, 0),
        (4, 40, 40, 0),
        (5, 50, 50, 0),
    ]


def test_reset_policy_re_anchors_on_the_late_time() -> None:
    assert _overrun("reset") == [
        (0, 0, 0, 0),
        (1, 10, 10, 0),
        (2, 20, 35, 1),
        (1, 45, 45, 0),  # new grid: 35 + k x 10
        (2, 55, 55, 0),
        (3, 65, 65, 0),
    ]


def test_rate_stats_and_registry() -> None:
    async def main() -> evclock.Clock:
        clock = evclock.clock()
        rate = clock.rate(50, name="drive")
        async for tick in rate:
            if tick.index == 2:
                await clock.sleep(0.05)  # 2.5 periods late
            if tick.index >= 10:
                break
        return clock

    clock = evclock.run(main())
    (rate,) = clock.rates
    assert rate.name == "drive"
    assert rate.stats.ticks == 10
    assert rate.stats.missed == 1
    assert rate.stats.max_lateness == Duration(seconds=0.01)
    assert rate.stats.as_dict()["ticks"] == 10
    assert rate.period == Duration(seconds=0.02)


def test_rate_sleep_style_and_close() -> None:
    async def main() -> list[int]:
        rate = evclock.clock().rate(10)
        out = [(await rate.sleep()).index for _ in range(3)]
        rate.close()
        out.extend([t.index async for t in rate])
        return out

    assert evclock.run(main()) == [0, 1, 2]


@pytest.mark.parametrize(
    ("hz", "message"),
    [
        (0, "rate must be positive, got 0 Hz; for a one-off delay use clock.sleep()"),
        (-5, "rate must be positive, got -5 Hz; for a one-off delay use clock.sleep()"),
        (float("nan"), "rate must be a finite number of hertz, got nan"),
        (float("inf"), "rate must be a finite number of hertz, got inf"),
        (2e9, "rate 2000000000.0 Hz is above 1 GHz: the period is under 1 ns"),
    ],
)
def test_bad_rates(hz: float, message: str) -> None:
    async def main() -> None:
        evclock.clock().rate(hz)

    with pytest.raises(evclock.InvalidArgumentError) as info:
        evclock.run(main())
    assert str(info.value) == message


def test_bad_rate_type_and_policy() -> None:
    async def main() -> None:
        clock = evclock.clock()
        with pytest.raises(
            evclock.InvalidTypeError, match=r"^rate must be a number of hertz, got str$"
        ):
            clock.rate("10")  # type: ignore[arg-type]
        with pytest.raises(evclock.InvalidTypeError):
            clock.rate(True)
        with pytest.raises(
            evclock.InvalidArgumentError,
            match=r"^policy must be one of 'skip', 'catch_up', 'reset', got 'burst'$",
        ):
            clock.rate(10, policy="burst")  # type: ignore[arg-type]

    evclock.run(main())


def test_periodic_timer_sync_callback() -> None:
    async def main() -> tuple[list[float], int]:
        clock = evclock.clock()
        calls: list[float] = []
        timer = clock.timer(0.5, lambda: calls.append(clock.now().seconds))
        await clock.sleep(2.2)
        timer.cancel()
        await clock.sleep(5)
        return calls, timer.stats.ticks

    assert evclock.run(main()) == ([0.5, 1.0, 1.5, 2.0], 4)


def test_one_shot_async_timer_and_time_until_next_call() -> None:
    async def main() -> list[object]:
        clock = evclock.clock()
        calls: list[float] = []

        async def fire() -> None:
            await clock.sleep(0.1)
            calls.append(clock.now().seconds)

        timer = clock.timer(Duration(seconds=2), fire, oneshot=True, name="once")
        out: list[object] = [timer.time_until_next_call()]
        await clock.sleep(1.5)
        out.append(timer.time_until_next_call())
        await clock.sleep(2)
        out += [timer.time_until_next_call(), calls, timer.name]
        return out

    assert evclock.run(main()) == [
        Duration(seconds=2),
        Duration(seconds=0.5),
        None,
        [2.1],
        "once",
    ]


def test_timer_reset_restarts_the_period() -> None:
    async def main() -> list[float]:
        clock = evclock.clock()
        calls: list[float] = []
        timer = clock.timer(1, lambda: calls.append(clock.now().seconds))
        await clock.sleep(1.5)
        timer.reset()  # next call at 2.5, not 2.0
        assert timer.time_until_next_call() == Duration(seconds=1)
        await clock.sleep(2.2)
        timer.cancel()
        assert timer.is_canceled
        assert timer.time_until_next_call() is None
        return calls

    assert evclock.run(main()) == [1.0, 2.5, 3.5]


def test_timer_overrun_skips_missed_periods() -> None:
    async def main() -> tuple[list[float], int]:
        clock = evclock.clock()
        calls: list[float] = []

        async def slow() -> None:
            calls.append(clock.now().seconds)
            if len(calls) == 1:
                await clock.sleep(2.5)

        timer = clock.timer(1, slow)
        await clock.sleep(5.5)
        timer.cancel()
        return calls, timer.stats.missed

    calls, missed = evclock.run(main())
    assert calls == [1.0, 4.0, 5.0]
    assert missed == 2


def test_failing_timer_callback_is_reported_and_stops(caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> evclock.Timer:
        clock = evclock.clock()

        def boom() -> None:
            raise RuntimeError("sensor unplugged")

        timer = clock.timer(1, boom, name="sensor")
        await clock.sleep(3)
        return timer

    with caplog.at_level(logging.ERROR, logger="asyncio"):
        timer = evclock.run(main())
    assert timer.is_canceled
    assert isinstance(timer.exception(), RuntimeError)
    assert "evclock timer 'sensor': callback raised; timer stopped" in caplog.text
    assert "sensor unplugged" in caplog.text


@pytest.mark.parametrize(
    ("period", "error", "message"),
    [
        (0, evclock.InvalidArgumentError, "timer period must be positive, got 0"),
        (-1.0, evclock.InvalidArgumentError, "timer period must be positive, got -1.0"),
        (float("nan"), evclock.InvalidArgumentError, "timer period must be a number, got NaN"),
        (
            "1",
            evclock.InvalidTypeError,
            "timer period must be seconds (int or float) or a Duration, got str",
        ),
    ],
)
def test_bad_timer_periods(period: object, error: type[Exception], message: str) -> None:
    async def main() -> None:
        evclock.clock().timer(period, lambda: None)  # type: ignore[arg-type]

    with pytest.raises(error) as info:
        evclock.run(main())
    assert str(info.value) == message


def test_a_rate_has_no_deadlines_before_it_starts() -> None:
    async def main() -> None:
        rate = evclock.clock().rate(10)
        with pytest.raises(
            evclock.NotRunningError, match=r"^the rate has not started: iterate it first$"
        ):
            rate._deadline(1)

    evclock.run(main())


def test_timer_needs_a_callable() -> None:
    async def main() -> None:
        evclock.clock().timer(1, "not callable")  # type: ignore[arg-type]

    with pytest.raises(
        evclock.InvalidTypeError, match=r"^timer callback must be callable, got str$"
    ):
        evclock.run(main())


def test_rates_and_timers_work_on_wall_time() -> None:
    async def main() -> tuple[list[int], int]:
        clock = evclock.clock()
        assert isinstance(clock, evclock.WallClock)
        hits: list[int] = []
        timer = clock.timer(0.005, lambda: hits.append(1))
        indices = []
        async with asyncio.timeout(60):  # wall seconds: a bound, never reached when it works
            async for tick in clock.rate(200):
                indices.append(tick.index)
                if tick.index >= 3:  # a loaded machine may skip periods (the skip policy)
                    break
        timer.cancel()
        await asyncio.sleep(0)
        return indices, len(hits)

    indices, hits = evclock.run(main(), use_sim_time=False)
    assert indices[0] == 0
    assert indices == sorted(set(indices))
    assert indices[-1] >= 3
    assert hits >= 1


def test_registry_keeps_the_latest_loop_of_each_name() -> None:
    async def main() -> evclock.Clock:
        clock = evclock.clock()
        for episode in range(3):
            rate = clock.rate(10, name="control")
            async for tick in rate:
                if tick.index == episode:
                    break
        clock.rate(5, name="planner")
        return clock

    clock = evclock.run(main())
    assert [r.name for r in clock.rates] == ["control", "planner"]
    assert clock.rates[0].stats.ticks == 3  # the last episode's loop
