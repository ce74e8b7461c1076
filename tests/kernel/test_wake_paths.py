"""The kernel's wake-up in place against asyncio's own path: the same programs give the
same event traces and final states both ways.

The kernel wakes a task waiting on a sim-time wait in place: it resolves the future, takes
the task's wake-up off it and runs it at once, with no ``Handle`` and no trip through the
ready queue (``SimCore.wake_next`` and ``SimCore.fire``; docs/architecture.md, "How a wake-up
travels"). With ``SimCore.wake_in_place`` off, every wake-up takes asyncio's own path: the
future's callbacks scheduled with ``call_soon`` and run from the ready queue, as on a stock
loop. The shortcut must not be observable.

The corpus is what could tell the two apart: deadlines shared (a batch woken in order),
``clock.sleep``, ``asyncio.sleep`` and rate loops together, a ``cancel()`` or a jump of sim
time between a wake-up and its task's turn, cancellation storms with messages and
``uncancel()`` (``Task.cancel()``'s return value and ``cancelling()`` recorded),
``asyncio.timeout`` reschedules, TaskGroups, ``wait_for``, a cancel from another thread,
overrun policies, several iterators on one rate, and a wait's future shared by several
waiters. The bundled scenarios on both engines and the examples are compared whole in
tests/kernel/test_wake_paths_runs.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any

import pytest

import evclock
from evclock import ClockJumpedError
from evclock.kernel._core import SimCore
from evclock.kernel._rate import Rate, Tick

Trace = list[Any]
Program = Callable[[Trace], Coroutine[Any, Any, object]]


@contextlib.contextmanager
def wake_in_place(on: bool) -> Iterator[None]:
    """Loops made inside wake tasks in place (``on``) or through asyncio's own path."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SimCore, "wake_in_place", on)
        yield


def run_both(program: Program) -> Trace:
    """Run ``program`` both ways; the traces (outcome included) must agree."""
    traces = []
    for on in (True, False):
        trace: Trace = []
        with wake_in_place(on):
            try:
                result = evclock.run(program(trace))
            except BaseException as exc:  # the outcome is part of the trace
                result = repr(exc)
        trace.append(("result", result))
        traces.append(trace)
    assert traces[0] == traces[1]
    return traces[0]


def now() -> int:
    return evclock.clock().now_ns()


def tick_row(tick: Tick) -> tuple[int, int, int, int]:
    return (tick.index, tick.expected_ns, tick.actual_ns, tick.missed)


def stats_row(rate: Rate) -> dict[str, float | int]:
    return {**rate.stats.as_dict(), "recent": list(rate.stats.recent_lateness_ns)}


async def shared_deadlines(trace: Trace) -> object:
    """Rates whose deadlines coincide (a batch: ticks resumed in their turn), with a
    sleeper and a timer due at the same instants."""
    clock = evclock.clock()

    async def loop(hz: int, name: str, last: int) -> dict[str, float | int]:
        rate = clock.rate(hz, name=name)
        async for tick in rate:
            trace.append((name, *tick_row(tick), now()))
            if tick.index == last:
                break
        return stats_row(rate)

    async def sleeper() -> None:
        for _ in range(4):
            await clock.sleep(0.1)
            trace.append(("sleeper", now()))

    timer = clock.timer(0.05, lambda: trace.append(("timer", now())))
    results = await asyncio.gather(
        loop(10, "a", 5), loop(20, "b", 9), loop(10, "c", 4), loop(40, "d", 17), sleeper()
    )
    timer.cancel()
    return results


async def cancel_between_wake_and_turn(trace: Trace) -> object:
    """A supervisor woken in the same batch, before the loop's turn, cancels it: the loop
    gets CancelledError, not the tick, and the rate counts no tick for it; the loop then
    carries on (uncancel) and the rate delivers that deadline late."""
    clock = evclock.clock()
    rate = clock.rate(10, name="victim")

    async def victim() -> None:
        rate_iter = aiter(rate)
        while True:
            try:
                tick = await anext(rate_iter)
            except asyncio.CancelledError as exc:
                task = asyncio.current_task()
                assert task is not None
                trace.append(("cancelled", now(), exc.args, task.cancelling(), stats_row(rate)))
                task.uncancel()
                continue
            trace.append(("tick", *tick_row(tick), now()))
            if tick.index >= 6:
                return

    async def supervisor(task: asyncio.Task[None]) -> None:
        await clock.sleep(0.3)  # scheduled at 0, before the victim's wait for 0.3 s
        trace.append(("cancel", task.cancel("now"), task.cancelling(), now()))

    task = asyncio.create_task(victim())
    await asyncio.sleep(0)  # the victim takes tick 0 and waits for tick 1
    await asyncio.gather(task, supervisor(task))
    return stats_row(rate)


async def cancel_then_uncancel_before_the_turn(trace: Trace) -> object:
    """cancel() then uncancel() between a tick's wake-up and its task's turn: on 3.13 the
    cancellation is withdrawn (the task gets its tick), before 3.13 it still arrives."""
    clock = evclock.clock()
    rate = clock.rate(10)

    async def loop() -> None:
        try:
            async for tick in rate:
                trace.append(("tick", *tick_row(tick), now()))
                if tick.index == 4:
                    return
        except asyncio.CancelledError:
            trace.append(("cancelled", now(), stats_row(rate)))

    async def meddler(task: asyncio.Task[None]) -> None:
        await clock.sleep(0.2)
        trace.append(("cancel", task.cancel(), task.uncancel(), task.cancelling()))

    task = asyncio.create_task(loop())
    await asyncio.sleep(0)
    await asyncio.gather(task, meddler(task))
    return (sys.version_info[:2] >= (3, 13), stats_row(rate))


async def jumps_around_ticks(trace: Trace) -> object:
    """Time jumps: while a rate waits (it restarts at the new time), and between a tick's
    wake-up and its task's turn, back (restart) and forward (a late tick)."""
    clock = evclock.clock()
    loop: Any = asyncio.get_running_loop()
    rate = clock.rate(10, name="jumped")
    stop = False

    async def ticker() -> None:
        async for tick in rate:
            trace.append(("tick", *tick_row(tick), now()))
            if stop:
                return

    async def jumper() -> None:
        nonlocal stop
        await clock.sleep(0.25)  # between deadlines: the rate waits
        loop.source.set_time(5_000_000_000)
        trace.append(("jumped", now()))
        await clock.sleep(0.3)  # 5.3 s: due with the rate's tick 3 of the new schedule
        loop.source.set_time(1_000_000_000)  # back, before the ticker's turn
        trace.append(("back", now()))
        await clock.sleep(0.2)  # 1.2 s: due with a tick again
        loop.source.set_time(2_000_000_000)  # forward, before its turn
        trace.append(("forward", now()))
        await clock.sleep(0.35)
        stop = True

    await asyncio.gather(ticker(), jumper())
    return stats_row(rate)


async def jump_ends_the_wait_of_a_rate_and_a_sleeper(trace: Trace) -> object:
    clock = evclock.clock()
    loop: Any = asyncio.get_running_loop()

    async def sleeper() -> None:
        try:
            await clock.sleep(10)
        except ClockJumpedError:
            trace.append(("sleeper jumped", now()))

    async def ticker() -> None:
        async for tick in clock.rate(2):
            trace.append(("tick", *tick_row(tick), now()))
            if len(trace) > 6:
                return

    tasks = [asyncio.create_task(sleeper()), asyncio.create_task(ticker())]
    await clock.sleep(1.2)
    loop.source.set_time(100_000_000)
    await asyncio.gather(*tasks)
    return now()


async def cancellation_storm(trace: Trace) -> object:
    clock = evclock.clock()

    async def looper(i: int) -> None:
        try:
            async for tick in clock.rate(4 + i):
                trace.append(("tick", i, *tick_row(tick)))
        except asyncio.CancelledError as exc:
            task = asyncio.current_task()
            assert task is not None
            trace.append(("cancelled", i, now(), exc.args, task.cancelling()))
            raise

    tasks = [asyncio.create_task(looper(i)) for i in range(6)]
    await clock.sleep(1)
    trace.append(("twice", tasks[1].cancel("m"), tasks[1].cancelling(), tasks[1].cancel()))
    trace.append(("uncancel", tasks[2].cancel("a"), tasks[2].uncancel(), tasks[2].cancelling()))
    trace.append(("msgs", tasks[3].cancel(), tasks[3].cancel("b"), tasks[3].cancelling()))
    await asyncio.sleep(0)
    trace.append(("late", tasks[0].cancel(), tasks[5].cancel("x")))
    await clock.sleep(1)
    tasks[2].cancel()
    tasks[4].cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return [(t.cancelled(), t.cancel()) for t in tasks]


async def timeouts_and_groups(trace: Trace) -> object:
    clock = evclock.clock()
    rate = clock.rate(20, name="timed")

    async def child(i: int) -> None:
        async for tick in clock.rate(10 * (i + 1)):
            if tick.index == 3:
                trace.append(("child", i, *tick_row(tick)))
                if i == 2:
                    raise ValueError(i)
                return

    try:
        async with asyncio.TaskGroup() as group:
            for i in range(4):
                group.create_task(child(i))
    except* ValueError as errors:
        trace.append(("group", [e.args for e in errors.exceptions], now()))
    try:
        async with asyncio.timeout(1.0) as scope:  # a deadline shared with the rate's
            scope.reschedule(asyncio.get_running_loop().time() + 0.5)
            async for tick in rate:
                trace.append(("timed", *tick_row(tick)))
    except TimeoutError:
        trace.append(("timed out", now(), stats_row(rate)))
    trace.append(("caught up", *tick_row(await rate.sleep()), now()))
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(rate.sleep(), 0.01)  # the next deadline is 50 ms away
    trace.append(("after wait_for", now(), stats_row(rate)))
    tick = await asyncio.wait_for(rate.sleep(), 1)
    trace.append(("wait_for", *tick_row(tick)))
    return stats_row(rate)


async def cancel_from_another_thread(trace: Trace) -> object:
    loop = asyncio.get_running_loop()
    clock = evclock.clock()

    async def looper() -> None:
        try:
            async for tick in clock.rate(1):
                trace.append(("tick", *tick_row(tick)))
        except asyncio.CancelledError:
            trace.append(("cancelled", now()))
            raise

    task = asyncio.create_task(looper())
    await clock.sleep(2.5)
    thread = threading.Thread(target=loop.call_soon_threadsafe, args=(task.cancel,))
    with loop.hold_time():  # type: ignore[attr-defined]
        thread.start()
        await asyncio.to_thread(thread.join, 10)
    await asyncio.gather(task, return_exceptions=True)
    return (task.cancelled(), now())


async def policies_and_sharing(trace: Trace) -> object:
    """Overruns under each policy, two iterators and sleep() on one rate, close()."""
    clock = evclock.clock()
    out = {}
    for policy in ("skip", "catch_up", "reset"):
        rate = clock.rate(100, policy=policy, name=policy)  # type: ignore[arg-type]
        async for tick in rate:
            trace.append((policy, *tick_row(tick), now()))
            if tick.index in (2, 9):
                await clock.sleep(0.035)  # overrun three periods and a half
            if len(rate.stats.recent_lateness_ns) >= 12:
                break
        out[policy] = stats_row(rate)
    shared = clock.rate(50, name="shared")

    async def reader(name: str, count: int) -> None:
        for _ in range(count):
            tick = await shared.sleep()
            trace.append((name, *tick_row(tick), now()))

    async for tick in shared:
        trace.append(("for", *tick_row(tick)))
        if tick.index == 2:
            break
    await asyncio.gather(reader("r1", 4), reader("r2", 3))
    async for tick in shared:  # a second iteration carries on
        trace.append(("again", *tick_row(tick)))
        if tick.index >= 8:
            shared.close()
    out["shared"] = stats_row(shared)
    return out


async def a_tick_future_used_as_a_future(trace: Trace) -> object:
    """``rate.__anext__()`` awaited by no task of its own: a callback on it, shielded."""
    clock = evclock.clock()
    rate = clock.rate(10)
    for _ in range(3):
        trace.append(("sleep", *tick_row(await rate.sleep()), now()))
    fut = asyncio.ensure_future(rate.__anext__())
    fut.add_done_callback(lambda f: trace.append(("callback", *tick_row(f.result()), now())))
    tick = await asyncio.shield(fut)
    trace.append(("shielded", *tick_row(tick), now()))
    return stats_row(rate)


async def sleepers_of_every_kind(trace: Trace) -> object:
    """clock.sleep, sleep_until, asyncio.sleep, call_later and a future shared by several
    waiters, due alone and together."""
    clock = evclock.clock()
    loop = asyncio.get_running_loop()

    async def sleeper(name: str, delays: list[float]) -> None:
        for i, delay in enumerate(delays):
            if i % 3 == 0:
                await clock.sleep(delay)
            elif i % 3 == 1:
                await asyncio.sleep(delay)
            else:
                await clock.sleep_until(clock.now() + evclock.Duration(seconds=delay))
            trace.append((name, i, now()))

    for i in range(3):
        loop.call_later(0.01 * (i + 1), trace.append, ("call_later", i))
    shared = asyncio.ensure_future(clock.sleep(0.02))

    async def on_shared(i: int) -> None:
        await shared
        trace.append(("shared", i, now()))

    await asyncio.gather(
        sleeper("a", [0.01, 0.01, 0.005, 0.02, 0.01, 0.01]),
        sleeper("b", [0.005, 0.015, 0.01, 0.01, 0.03]),
        sleeper("c", [0.02, 0.02, 0.02]),
        on_shared(0),
        on_shared(1),
    )
    return now()


async def self_cancel_and_timeouts(trace: Trace) -> object:
    clock = evclock.clock()

    async def self_cancel() -> None:
        task = asyncio.current_task()
        assert task is not None
        trace.append(("self", task.cancel("self"), task.cancelling()))
        try:
            await clock.sleep(5)
        except asyncio.CancelledError as exc:
            trace.append(("self", now(), exc.args))

    await asyncio.create_task(self_cancel())
    try:
        async with asyncio.timeout(2.5) as scope:
            scope.reschedule(asyncio.get_running_loop().time() + 1.5)
            await clock.sleep(1)
            trace.append(("inside", now()))
            await clock.sleep(3)
    except TimeoutError:
        trace.append(("timed out", now()))
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(clock.sleep(5), 1)
    trace.append(("wait_for", now()))
    return now()


async def time_jumps(trace: Trace) -> object:
    clock = evclock.clock()
    loop: Any = asyncio.get_running_loop()

    async def sleeper(i: int) -> None:
        try:
            await clock.sleep(5 + i)
            trace.append(("woke", i, now()))
        except ClockJumpedError:
            trace.append(("jumped", i, now()))

    async def timer_sleeper() -> None:
        await asyncio.sleep(2)  # an asyncio timer keeps its remaining delay
        trace.append(("timer", now()))

    tasks = [asyncio.create_task(sleeper(i)) for i in range(3)]
    tasks.append(asyncio.create_task(timer_sleeper()))
    await clock.sleep(1)
    trace.append(("cancel", tasks[1].cancel()))
    loop.source.set_time(500_000_000)
    await asyncio.gather(*tasks, return_exceptions=True)
    return [t.cancelled() for t in tasks]


PROGRAMS = [
    shared_deadlines,
    cancel_between_wake_and_turn,
    cancel_then_uncancel_before_the_turn,
    jumps_around_ticks,
    jump_ends_the_wait_of_a_rate_and_a_sleeper,
    cancellation_storm,
    timeouts_and_groups,
    cancel_from_another_thread,
    policies_and_sharing,
    a_tick_future_used_as_a_future,
    sleepers_of_every_kind,
    self_cancel_and_timeouts,
    time_jumps,
]


@pytest.mark.parametrize("program", PROGRAMS, ids=[p.__name__ for p in PROGRAMS])
def test_in_place_wake_ups_and_asyncios_path_give_the_same_trace(program: Program) -> None:
    trace = run_both(program)
    outcome = trace[-1][1]
    assert not (isinstance(outcome, str) and "Error" in outcome), outcome  # it ran through
    assert len(trace) > 4  # the program did something observable


def test_the_switch_takes_asyncios_path() -> None:
    """Off, a wake-up is a Handle run from the ready queue; on, it runs in place."""

    def handles_run(on: bool) -> int:
        runs = 0
        handle_run = asyncio.Handle._run

        def counted(self: asyncio.Handle) -> None:
            nonlocal runs
            runs += 1
            handle_run(self)

        async def main() -> None:
            clock = evclock.clock()
            for _ in range(50):
                await clock.sleep(0.01)

        with wake_in_place(on), pytest.MonkeyPatch.context() as patch:
            patch.setattr(asyncio.Handle, "_run", counted)
            evclock.run(main())
        return runs

    assert handles_run(False) >= handles_run(True) + 50
