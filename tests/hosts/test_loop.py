"""The simulation loop: time model, advancement, entry points, the controller API."""

from __future__ import annotations

import asyncio
import math
import signal
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import _paused_waits as operated
import pytest

import evclock
from evclock import Duration, InvalidArgumentError, SimEventLoop, Time


def test_time_jumps_exactly_to_the_next_deadline() -> None:
    seen: list[int] = []

    async def main() -> None:
        clock = evclock.clock()
        for d in (0.25, Duration(nanoseconds=7), 1, 0.0):
            await clock.sleep(d)
            seen.append(clock.now_ns())

    evclock.run(main())
    assert seen == [250_000_000, 250_000_007, 1_250_000_007, 1_250_000_007]


def test_loop_time_is_float_seconds_of_the_integer_clock() -> None:
    async def main() -> tuple[float, int]:
        await evclock.clock().sleep(Duration(nanoseconds=1_500_000_001))
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        return loop.time(), loop.now_ns

    t, ns = evclock.run(main())
    assert ns == 1_500_000_001
    assert t == 1_500_000_001 / 1e9


def test_run_returns_the_result_and_propagates_errors() -> None:
    async def ok() -> str:
        await asyncio.sleep(3)
        return "done"

    async def bad() -> None:
        await asyncio.sleep(1)
        raise KeyError("boom")

    assert evclock.run(ok()) == "done"
    with pytest.raises(KeyError, match="boom"):
        evclock.run(bad())


def test_loop_factory_with_asyncio_runner() -> None:
    async def main() -> float:
        await asyncio.sleep(10)
        return asyncio.get_running_loop().time()

    with asyncio.Runner(loop_factory=evclock.loop_factory(start=100)) as runner:
        assert runner.run(main()) == 110.0
        # A second run on the same runner continues the same sim clock.
        assert runner.run(main()) == 120.0


def test_sim_event_loop_class_is_itself_a_loop_factory() -> None:
    async def main() -> int:
        await asyncio.sleep(0.5)
        return evclock.clock().now_ns()

    with asyncio.Runner(loop_factory=evclock.SimEventLoop) as runner:
        assert runner.run(main()) == 500_000_000


def test_all_work_at_a_time_finishes_before_time_advances() -> None:
    log: list[tuple[str, float]] = []

    async def chatty(name: str) -> None:
        for _ in range(3):
            log.append((name, evclock.clock().now().seconds))
            await asyncio.sleep(0)  # yields, but never advances time

    async def main() -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(chatty("a"))
            tg.create_task(chatty("b"))
        await evclock.clock().sleep(1)
        log.append(("after", evclock.clock().now().seconds))

    evclock.run(main())
    assert log[-1] == ("after", 1.0)
    assert all(t == 0.0 for _, t in log[:-1])


def test_io_is_polled_once_per_move_of_time_and_handled_at_the_time_it_arrived() -> None:
    """With I/O registered, the loop polls once before time moves (so bytes that arrived
    are handled at the time they arrived), and not again before running what the move
    made due: one poll per move, as asyncio's one select per iteration."""
    polls = 0

    async def main() -> list[tuple[float, bytes]]:
        nonlocal polls
        loop = asyncio.get_running_loop()
        ours, theirs = socket.socketpair()
        got: list[tuple[float, bytes]] = []
        loop.add_reader(ours, lambda: got.append((loop.time(), ours.recv(16))))
        select = loop._selector.select  # type: ignore[attr-defined]

        def counting_select(timeout: float | None = None) -> object:
            nonlocal polls
            polls += 1
            return select(timeout)

        loop._selector.select = counting_select  # type: ignore[attr-defined]
        for _ in range(100):
            await asyncio.sleep(0.001)
        theirs.send(b"late")  # arrives at 0.1 s: handled then, before the next move
        await asyncio.sleep(0.001)
        loop.remove_reader(ours)
        ours.close()
        theirs.close()
        return got

    got = evclock.run(main())
    assert got == [(0.1, b"late")]
    # One per move (101), and the one that found the bytes (time did not move then).
    assert polls == 102  # 203 when the loop also polled before running what a move made due


def test_a_signal_that_arrives_as_outside_work_ends_is_handled_before_time_moves() -> None:
    """The loop polls right before time moves, even when its last poll (a wait for outside
    work that timed out) ran no callback: the work can end, and a signal arrive, in between
    (as when a timer signal ends an ``alarm`` hold: the signal's byte is on the self-pipe)."""
    from evclock.outside._work import EXACT

    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        handled: list[float] = []
        loop.add_signal_handler(signal.SIGUSR1, lambda: handled.append(loop.time()))
        outside = loop._outside  # type: ignore[attr-defined]
        holder = outside.holder
        checks = 0

        def work_that_ends_on_the_second_check(*, timed_waits_hold: bool = True) -> str | None:
            nonlocal checks
            checks += 1
            if checks == 1:
                return EXACT  # held: the loop waits for it (a bounded wait that times out)
            if checks == 2:
                signal.raise_signal(signal.SIGUSR1)  # it ends, and a signal comes as it does
            return holder()

        outside.holder = work_that_ends_on_the_second_check
        await asyncio.sleep(1)
        loop.remove_signal_handler(signal.SIGUSR1)
        return handled

    assert evclock.run(main()) == [0.0]


def test_sleep_until_and_now_are_sim_times() -> None:
    async def main() -> Time:
        clock = evclock.clock()
        await clock.sleep_until(clock.now() + Duration(seconds=2))
        await clock.sleep_until(Time(seconds=1))  # in the past: returns after one yield
        return clock.now()

    now = evclock.run(main())
    assert now == Time(seconds=2)
    assert now.clock_type is evclock.SIM


def test_epoch_like_start_times_do_not_spin_or_lose_timers() -> None:
    start = 1_700_000_000

    async def main() -> list[int]:
        clock = evclock.clock()
        out = []
        for _ in range(1000):
            await asyncio.sleep(0.001)
        out.append(clock.now_ns())
        for _ in range(1000):
            await clock.sleep(0.001)
        out.append(clock.now_ns())
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        loop.call_at(loop.time() + 0.5, fut.set_result, "fired")
        out.append(len(await fut))
        out.append(clock.now_ns())
        return out

    a, b, fired, c = evclock.run(main(), start=start)
    base = start * 10**9
    assert a == base + 1_000_000_000  # call_later keeps integer precision at epoch scale
    assert b == base + 2_000_000_000
    assert fired == 5
    # call_at goes through a float of ~1.7e9 s: exact to within the float's resolution.
    assert abs(c - (base + 2_500_000_000)) <= 256


def test_24_hours_of_rate_deadlines_are_exact_integers() -> None:
    # The full 86.4 million ticks through the loop run in benchmarks/day_at_1khz.py; here the
    # deadline formula (what could drift) is checked along the whole day.
    ticks = 24 * 3600 * 1000
    rate = evclock.Rate(_FakeClock(), 1000)
    rate._start = 0
    assert rate._deadline(ticks) == 86_400 * 10**9
    assert all(rate._deadline(i) == i * 1_000_000 for i in range(0, ticks, 9_999_991))
    # A period that is not a whole number of nanoseconds (240 Hz) does not drift either.
    rate240 = evclock.Rate(_FakeClock(), 240)
    rate240._start = 0
    assert rate240._deadline(240 * 86_400) == 86_400 * 10**9
    assert rate240._deadline(1) == 4_166_666


def test_ten_simulated_minutes_of_a_1khz_rate_loop_end_exactly() -> None:
    ticks = 600 * 1000

    async def main() -> tuple[int, int, int]:
        clock = evclock.clock()
        rate = clock.rate(1000)
        async for tick in rate:
            if tick.index == ticks:
                break
        return clock.now_ns(), rate.stats.ticks, rate.stats.missed

    # The subject is the rate's arithmetic over 600,000 steps: threads that earlier tests
    # left behind must not be surveyed at every one of them.
    factory = evclock.loop_factory(start=1_700_000_000, watch_threads=False)
    with asyncio.Runner(loop_factory=factory) as runner:
        now, count, missed = runner.run(main())
    assert now == (1_700_000_000 + 600) * 10**9
    assert count == ticks + 1
    assert missed == 0


class _FakeClock:
    clock_type = evclock.SIM

    def now_ns(self) -> int:
        return 0


def test_clock_on_a_plain_asyncio_loop_is_the_wall_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("EVCLOCK_USE_SIM_TIME", raising=False)

    async def main() -> evclock.Clock:
        return evclock.clock()

    clock = asyncio.run(main())
    assert isinstance(clock, evclock.WallClock)
    assert clock.clock_type is evclock.STEADY


def test_use_sim_time_false_runs_on_wall_time() -> None:
    async def main() -> tuple[str, bool]:
        clock = evclock.clock()
        t0 = clock.now()
        await clock.sleep(0.01)
        return clock.clock_type.value, (clock.now() - t0) >= Duration(seconds=0.01)

    assert evclock.run(main(), use_sim_time=False) == ("steady", True)
    assert evclock.run(main(), use_sim_time=False, wall_clock=evclock.SYSTEM)[0] == "system"


@pytest.mark.parametrize(
    ("env", "expected"), [("1", "sim"), ("true", "sim"), ("0", "steady"), ("off", "steady")]
)
def test_use_sim_time_from_the_environment(
    monkeypatch: pytest.MonkeyPatch, env: str, expected: str
) -> None:
    monkeypatch.setenv("EVCLOCK_USE_SIM_TIME", env)

    async def main() -> str:
        return evclock.clock().clock_type.value

    assert evclock.run(main()) == expected
    # The argument wins over the environment.
    assert evclock.run(main(), use_sim_time=expected != "sim") != expected


def test_until_cancels_a_program_still_running() -> None:
    async def forever() -> None:
        while True:
            await evclock.clock().sleep(1)

    with pytest.raises(evclock.SimTimeLimitError, match=r"until limit \(5 s of sim time\)"):
        evclock.run(forever(), until=5)


def test_timeout_math_is_exact_for_large_sleep_counts() -> None:
    async def main() -> int:
        clock = evclock.clock()
        for _ in range(10_000):
            await clock.sleep(0.1)
        return clock.now_ns()

    # 10,000 float additions of 0.1 would drift; integer nanoseconds do not.
    assert evclock.run(main()) == 1000 * 10**9


@pytest.mark.parametrize("debug", [False, True])
def test_a_dropped_failed_task_is_reported_at_once(debug: bool) -> None:
    """As on asyncio (test_futures2.test_task_exc_handler_correct_context): the loop keeps no
    reference to a handle it ran, so a failed task nobody holds is freed by reference
    counting and its "exception was never retrieved" reaches the handler right away, in
    debug mode too (where, on 3.12 and later, the handle used to stay in a cycle through the
    finished frame that ran it, until the cyclic GC ran)."""
    import gc

    reported: list[str] = []

    async def fail() -> None:
        raise ZeroDivisionError

    async def main() -> None:
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(lambda _loop, context: reported.append(context["message"]))
        asyncio.ensure_future(fail())  # noqa: RUF006 (the point: nobody holds the task)
        await asyncio.sleep(0)
        assert reported == ["Task exception was never retrieved"]

    gc.disable()  # only reference counting may free the task
    try:
        loop = evclock.SimEventLoop()
        loop.set_debug(debug)
        try:
            loop.run_until_complete(main())
        finally:
            loop.close()
    finally:
        gc.enable()


def test_call_later_odd_delays_behave_as_documented() -> None:
    """None is asyncio's TypeError; NaN and -inf are not times; +inf and delays beyond sim
    time's range never fire; a huge negative delay is due at once."""

    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        fired: list[str] = []
        with pytest.raises(TypeError, match=r"^delay must not be None$"):
            loop.call_later(None, fired.append, "none")  # type: ignore[arg-type]
        for bad in (math.nan, -math.inf):
            with pytest.raises(InvalidArgumentError, match="needs a finite time"):
                loop.call_later(bad, fired.append, "bad")
        never = [loop.call_later(d, fired.append, "never") for d in (math.inf, 1e12, 1e300)]
        loop.call_later(-1e12, fired.append, "at once")
        await asyncio.sleep(0)
        await asyncio.sleep(5)
        assert [h.when() for h in never][1:] == [1e12, 1e300]
        assert loop.time() == 5.0
        return fired

    assert evclock.run(main()) == ["at once"]


def test_futures_of_the_loop_are_bound_to_it_inside_and_outside_its_run() -> None:
    """create_future and clock.sleep make futures of this loop whether it runs (the fast
    construction, from the running loop) or not."""
    loop = SimEventLoop()
    try:
        outside = loop.create_future()
        assert outside.get_loop() is loop

        async def inside() -> tuple[Any, Any]:
            fut = loop.create_future()
            sleep = evclock.clock().sleep(1.0)
            await sleep
            return fut.get_loop(), sleep.get_loop()  # type: ignore[attr-defined]

        assert loop.run_until_complete(inside()) == (loop, loop)
        outside.cancel()
    finally:
        loop.close()


# ------------------------------------------- stepping a paused loop from an operator thread


def _operated_run(
    script: Callable[[operated.Operator], None],
    *,
    via: str = "directly",
    sleeper: str = "asyncio.sleep",
    start_paused: bool = True,
    prepare: Callable[[SimEventLoop], None] = lambda loop: None,
) -> tuple[list[object], list[float]]:
    """A task ticks every sim second (8 ticks) on a paused SimEventLoop on virtual time;
    once the loop first waits paused (recorded), an operator thread runs ``script``, which
    must end with ``resume()``. Returns the operator's records and every tick's time."""
    selector = operated.PausedWaits()
    loop = SimEventLoop(selector=selector, paused=start_paused, stall_timeout=10)
    operator = operated.Operator(selector, via)

    async def main() -> None:
        if not start_paused:
            loop.pause()
        prepare(loop)
        sleep = asyncio.sleep if sleeper == "asyncio.sleep" else evclock.clock().sleep
        await operator.run(loop, script, sleep, loop.time)

    return operator.outcome(lambda: loop, main)


@pytest.mark.parametrize("via", ["directly", "call_soon_threadsafe"])
@pytest.mark.parametrize("sleeper", ["asyncio.sleep", "clock.sleep"])
@pytest.mark.parametrize("start_paused", [True, False], ids=["paused=True", "pause()"])
def test_each_step_from_an_operator_thread_jumps_to_the_next_deadline(
    via: str, sleeper: str, start_paused: bool
) -> None:
    """On virtual time a step is one jump to the next deadline (one wake-up batch), after
    which the loop holds again; step(n) is n jumps; step_until(t) stops exactly at t."""

    seen, ticks = _operated_run(
        operated.step_1_1_1_2_until_6_5, via=via, sleeper=sleeper, start_paused=start_paused
    )
    assert seen == operated.STEPPED_SEEN
    assert ticks == operated.TICKS


def _end_a_step_until(how: str) -> Callable[[SimEventLoop], None]:
    def prepare(loop: SimEventLoop) -> None:
        loop.pause()
        operated.end_a_step_until(loop, how)

    return prepare


@pytest.mark.parametrize("how", ["pause", "resume", "step_until"])
def test_a_step_until_ended_early_leaves_nothing_for_a_step_to_stop_at(how: str) -> None:
    """pause(), resume() or a new step_until() end a step_until() before its target: its
    stop mark goes with it, so a later step still jumps to the next wake-up, not there."""

    seen, ticks = _operated_run(operated.step_1_three_times, prepare=_end_a_step_until(how))
    first = 0.5 if how == "step_until" else 0.0
    assert seen == [(first, []), *operated.STEPPED_SEEN[1:4]]
    assert ticks == operated.TICKS


@pytest.mark.parametrize("via", ["directly", "call_soon_threadsafe"])
@pytest.mark.parametrize("sleeper", ["asyncio.sleep", "clock.sleep"])
def test_steps_from_an_operator_that_sleeps_between_them_move_virtual_time(
    via: str, sleeper: str
) -> None:
    """The reported case: the operator spaces its steps with ``time.sleep(0.05)``. A thread
    in a timed wait holds sim time while the loop runs, but a paused loop moves only by
    steps, so the operator's own sleep must not hold the steps it asked for (it did: time
    stayed at 0 until resume()). Each step jumps to the next deadline; then time holds."""
    loop = SimEventLoop(paused=True, stall_timeout=2)
    woke: list[float] = []
    three = threading.Event()
    errors: list[BaseException] = []

    def operate() -> None:
        try:
            for _ in range(3):
                if via == "directly":
                    loop.step(1)
                else:
                    loop.call_soon_threadsafe(loop.step, 1)
                time.sleep(0.05)  # the operator's own pace: not work for the loop
            # An operator polls for the effect at its own pace (each poll a timed wait).
            deadline = time.monotonic() + 5
            while not three.is_set() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert three.is_set(), f"three steps moved sim time to {woke} only"
            time.sleep(0.05)  # paused, with no step left: nothing more may happen
        except BaseException as exc:  # reported once the loop stopped
            errors.append(exc)
        finally:
            loop.call_soon_threadsafe(loop.stop)

    async def ticker() -> None:
        sleep = asyncio.sleep if sleeper == "asyncio.sleep" else evclock.clock().sleep
        while True:
            await sleep(1)
            woke.append(loop.time())
            if len(woke) == 3:
                three.set()

    tasks: list[asyncio.Task[None]] = []

    async def main() -> None:
        tasks.append(asyncio.ensure_future(ticker()))
        thread = threading.Thread(target=operate, daemon=True)
        thread.start()

    try:
        loop.run_until_complete(main())
        loop.run_forever()  # until the operator stops it
    finally:
        for task in asyncio.all_tasks(loop):
            task.cancel()
        loop.run_until_complete(asyncio.sleep(0))
        loop.close()
    assert errors == []
    assert woke == [1.0, 2.0, 3.0]


def test_a_paused_loop_waits_as_paused_while_a_thread_polls_with_a_timeout() -> None:
    """A pause outranks a hold: a thread polling with ``time.sleep`` while the loop is
    paused with no step left does not turn the pause into a StallError after
    ``stall_timeout`` (the pause is unbounded; a control ends it)."""
    loop = SimEventLoop(paused=True, stall_timeout=0.2)
    done = threading.Event()

    def poller() -> None:
        deadline = time.monotonic() + 0.6  # three stall_timeouts of polling
        while time.monotonic() < deadline:
            time.sleep(0.01)
        loop.call_soon_threadsafe(loop.resume)
        done.wait(10)

    async def main() -> float:
        thread = threading.Thread(target=poller, daemon=True)
        thread.start()
        await asyncio.sleep(1)
        done.set()
        thread.join(10)
        return loop.time()

    try:
        assert loop.run_until_complete(main()) == 1.0
    finally:
        loop.close()


def test_get_debug_follows_set_debug_and_futures_see_it() -> None:
    """get_debug() answers what set_debug() set, and asyncio's futures ask it: with debug
    mode on, a future records where it was created; off, it does not."""
    loop = SimEventLoop()
    try:
        assert loop.get_debug() is False
        assert loop.create_future()._source_traceback is None  # type: ignore[attr-defined]
        loop.set_debug(True)
        assert loop.get_debug() is True
        assert loop.create_future()._source_traceback  # type: ignore[attr-defined]
        loop.set_debug(False)
        assert loop.get_debug() is False
        assert loop.create_future()._source_traceback is None  # type: ignore[attr-defined]
    finally:
        loop.close()
