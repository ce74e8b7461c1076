"""Time jumps on virtual time: handlers, sleepers woken with ClockJumpedError, re-anchoring."""

from __future__ import annotations

import asyncio

import pytest

import evclock
from evclock import Duration, JumpThreshold, Time, TimeJump


def source() -> evclock.sources.VirtualTimeSource:
    loop = asyncio.get_running_loop()
    assert isinstance(loop, evclock.SimEventLoop)
    src = loop.source
    assert isinstance(src, evclock.sources.VirtualTimeSource)
    return src


def test_backward_jump_wakes_100_sleepers_with_clock_jumped() -> None:
    async def sleeper(results: list[object]) -> None:
        try:
            await evclock.clock().sleep(10)
            results.append("slept")
        except evclock.ClockJumpedError as exc:
            results.append(exc.jump)

    async def main() -> tuple[list[object], float]:
        results: list[object] = []
        tasks = [asyncio.create_task(sleeper(results)) for _ in range(100)]
        await evclock.clock().sleep(5)
        source().set_time(1_000_000_000)
        await asyncio.gather(*tasks)
        return results, evclock.clock().now().seconds

    results, now = evclock.run(main())
    jump = TimeJump(Time(seconds=5), Time(seconds=1))
    assert results == [jump] * 100
    assert jump.delta == Duration(seconds=-4)
    assert now == 1.0


def test_clock_jumped_message_says_what_to_do() -> None:
    jump = TimeJump(Time(seconds=5), Time(seconds=1))
    assert str(evclock.ClockJumpedError(jump)) == (
        "sim time jumped from 5.000000000 s (sim) to 1.000000000 s (sim) while sleeping; "
        "the sleep was cancelled: re-compute the deadline from clock.now()"
    )


def test_jump_handlers_with_thresholds() -> None:
    async def main() -> list[tuple[str, str, float]]:
        clock = evclock.clock()
        log: list[tuple[str, str, float]] = []

        def record(name: str, phase: str) -> object:
            return lambda jump: log.append((name, phase, jump.delta.seconds))

        clock.on_jump(record("back", "pre"), record("back", "post"))  # default: backward only
        clock.on_jump(
            post=record("big-forward", "post"),
            threshold=JumpThreshold(min_forward=Duration(seconds=10), min_backward=None),
        )
        handle = clock.on_jump(post=record("removed", "post"))
        handle.remove()
        src = source()
        src.set_time(3 * 10**9)  # forward 3 s: nobody asked for small forward jumps
        src.set_time(1 * 10**9)  # backward 2 s
        src.set_time(20 * 10**9)  # forward 19 s
        return log

    assert evclock.run(main()) == [
        ("back", "pre", -2.0),
        ("back", "post", -2.0),
        ("big-forward", "post", 19.0),
    ]


def test_pre_handler_sees_the_old_time_post_handler_the_new_one() -> None:
    async def main() -> list[float]:
        clock = evclock.clock()
        seen: list[float] = []
        clock.on_jump(
            lambda j: seen.append(clock.now().seconds), lambda j: seen.append(clock.now().seconds)
        )
        await clock.sleep(7)
        source().set_time(2 * 10**9)
        return seen

    assert evclock.run(main()) == [7.0, 2.0]


def test_rates_and_timers_re_anchor_after_a_jump() -> None:
    async def main() -> tuple[list[tuple[int, float]], list[float]]:
        clock = evclock.clock()
        ticks: list[tuple[int, float]] = []
        calls: list[float] = []
        clock.timer(1, lambda: calls.append(clock.now().seconds))

        async def jumper() -> None:
            await clock.sleep(2.5)
            source().set_time(10 * 10**9)

        jumping = asyncio.create_task(jumper())
        async for tick in clock.rate(1):
            ticks.append((tick.index, tick.actual.seconds))
            if len(ticks) == 5:
                break
        await jumping
        return ticks, calls

    ticks, calls = evclock.run(main())
    assert ticks == [(0, 0.0), (1, 1.0), (2, 2.0), (0, 10.0), (1, 11.0)]
    assert calls == [1.0, 2.0, 11.0]  # the program ends at 11 s


def test_asyncio_timers_keep_their_remaining_delay_across_a_jump() -> None:
    async def main() -> float:
        loop = asyncio.get_running_loop()

        async def jumper() -> None:
            await evclock.clock().sleep(1)
            source().set_time(100 * 10**9)

        jumping = asyncio.create_task(jumper())
        await asyncio.sleep(3)  # 2 s were left at the jump
        await jumping
        return loop.time()

    assert evclock.run(main()) == 102.0


def test_jump_threshold_validation() -> None:
    with pytest.raises(
        evclock.InvalidArgumentError,
        match=r"^JumpThreshold.min_forward must be a positive Duration or None, got 5$",
    ):
        JumpThreshold(min_forward=5)  # type: ignore[arg-type]


def test_on_jump_needs_a_callback() -> None:
    async def main() -> None:
        evclock.clock().on_jump()

    with pytest.raises(
        evclock.InvalidArgumentError,
        match=r"^on_jump\(\) needs a pre or a post callback \(or both\)$",
    ):
        evclock.run(main())


def test_a_tick_due_at_the_instant_of_a_backward_jump_re_anchors() -> None:
    async def main() -> list[tuple[int, int, int]]:
        clock = evclock.clock()
        ticks: list[tuple[int, int, int]] = []

        async def jumper() -> None:
            await clock.sleep(2)  # due at the same instant as the rate's tick 2
            source().set_time(500_000_000)

        jumping = asyncio.create_task(jumper())
        await asyncio.sleep(0)
        async for tick in clock.rate(1):
            ticks.append((tick.index, tick.expected_ns, tick.actual_ns))
            if len(ticks) == 4:
                break
        await jumping
        return ticks

    ticks = evclock.run(main())
    # Tick 2 was already due when time jumped back to 0.5 s: the schedule restarts there
    # instead of delivering a tick whose actual time precedes its deadline.
    assert ticks == [
        (0, 0, 0),
        (1, 10**9, 10**9),
        (0, 5 * 10**8, 5 * 10**8),
        (1, 15 * 10**8, 15 * 10**8),
    ]
    assert all(actual >= expected for _, expected, actual in ticks)


def test_a_timer_created_at_the_instant_of_a_backward_jump_follows_the_new_time() -> None:
    """Created, then the clock jumps back before the timer's task first runs: its period
    counts from the time after the jump, not from before it (it would wait 4 s more)."""

    async def main() -> list[float]:
        clock = evclock.clock()
        await clock.sleep(5)
        calls: list[float] = []
        timer = clock.timer(0.5, lambda: calls.append(clock.now().seconds))
        source().set_time(1_000_000_000)
        await clock.sleep(1.2)
        timer.cancel()
        return calls

    assert evclock.run(main()) == [1.5, 2.0]
