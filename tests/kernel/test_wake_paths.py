"""A rate's ticks from one resumed frame (``Rate._ticks``, an async generator) against the
coroutine per tick of evclock 0.3.0 (:func:`coroutine_per_tick`, kept here as the oracle):
the same programs give the same event traces, ticks, statistics and final states on both.

The corpus is what could tell them apart: ticks whose deadlines are shared (woken in a
batch, in their turn), a ``cancel()`` or a jump of sim time between a tick's wake-up and
its task's turn, cancellation storms with messages and ``uncancel()``, ``asyncio.timeout``
reschedules, TaskGroups, ``wait_for``, a cancel from another thread, overrun policies,
several iterators and :meth:`Rate.sleep` on one rate, and a tick awaited as a future.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import sys
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any

import pytest

import evclock
from evclock import ClockJumpedError
from evclock.kernel._rate import Rate, Tick, last_deadline_index

Trace = list[Any]
Program = Callable[[Trace], Coroutine[Any, Any, object]]


async def coroutine_per_tick(self: Rate) -> Tick:
    """evclock 0.3.0's ``Rate.__anext__`` (a coroutine per tick), the oracle."""
    if self._closed:
        raise StopAsyncIteration
    clock = self._clock
    core = self._core
    now = clock.now_ns() if core is None else core.now_ns
    start = self._start
    if start is None:
        self._start, self._index = now, 0
        return self._tick(0, now, now, 0)
    index = self._index + 1
    deadline = start + index * self._num // self._den
    if now < deadline:
        try:
            await clock.sleep_until_ns(deadline)
        except ClockJumpedError:
            return self._reanchor()
        now = clock.now_ns() if core is None else core.now_ns
        if now < deadline:
            return self._reanchor()
        return self._tick(index, deadline, now, 0)
    passed = last_deadline_index(start, now, self._num, self._den)
    if self._policy == "catch_up":
        return self._tick(index, deadline, now, 0)
    if self._policy == "skip":
        return self._tick(passed, self._deadline(passed), now, passed - index)
    tick = self._tick(index, deadline, now, passed - index)
    self._start, self._index = now, 0
    return tick


@contextlib.contextmanager
def oracle() -> Iterator[None]:
    """Rates iterate with a coroutine per tick, as in 0.3.0."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Rate, "__aiter__", lambda self: self)
        patch.setattr(Rate, "__anext__", coroutine_per_tick)
        yield


def run_both(program: Program) -> Trace:
    """Run ``program`` on both paths; the traces (outcome included) must agree."""
    traces = []
    for context in (contextlib.nullcontext, oracle):
        trace: Trace = []
        with context():
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


def tick_row(tick: _rate.Tick) -> tuple[int, int, int, int]:
    return (tick.index, tick.expected_ns, tick.actual_ns, tick.missed)


def stats_row(rate: _rate.Rate) -> dict[str, float | int]:
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
    done = asyncio.Event()

    async def ticker() -> None:
        async for tick in rate:
            trace.append(("tick", *tick_row(tick), now()))
            if tick.index == 3 and len(trace) > 20:
                break
        done.set()

    async def jumper() -> None:
        await clock.sleep(0.25)  # between deadlines: the rate waits
        loop.source.set_time(5_000_000_000)
        trace.append(("jumped", now()))
        await clock.sleep(0.3)  # 5.3 s: due with the rate's tick 3 of the new schedule
        loop.source.set_time(1_000_000_000)  # back, before the ticker's turn
        trace.append(("back", now()))
        await clock.sleep(0.2)  # 1.2 s: due with a tick again
        loop.source.set_time(2_000_000_000)  # forward, before its turn
        trace.append(("forward", now()))

    task = asyncio.create_task(ticker())
    await asyncio.sleep(0)
    await jumper()
    await asyncio.wait_for(done.wait(), 10)
    await task
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
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(rate.sleep(), 0.01)
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
    await rate.sleep()
    fut = asyncio.ensure_future(rate.__anext__())
    fut.add_done_callback(lambda f: trace.append(("callback", *tick_row(f.result()), now())))
    tick = await asyncio.shield(fut)
    trace.append(("shielded", *tick_row(tick), now()))
    return stats_row(rate)


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
]


@pytest.mark.parametrize("program", PROGRAMS, ids=[p.__name__ for p in PROGRAMS])
def test_one_frame_per_rate_and_a_coroutine_per_tick_give_the_same_trace(
    program: Program,
) -> None:
    trace = run_both(program)
    assert trace[-1][1] is not None  # the program returned
    assert not any("Error" in str(row) for row in trace[-1:]), trace[-1]
    assert len(trace) > 3  # the program did something observable


@pytest.mark.parametrize("run", [asyncio.run, evclock.run], ids=["wall", "sim"])
def test_a_tick_resumes_the_rates_frame_and_makes_no_coroutine(run: Any) -> None:
    async def main() -> list[str]:
        rate = evclock.clock().rate(1000)
        kinds = [type(aiter(rate)).__name__]
        for _ in range(3):
            step = rate.__anext__()
            kinds.append(type(step).__name__)
            await step
        return kinds

    assert run(main()) == ["async_generator"] + ["async_generator_asend"] * 3


def test_a_left_iteration_schedules_no_task_and_keeps_the_threads_hooks() -> None:
    """``break`` out of ``async for``: the generator is collected with no ``aclose()``
    task (asyncio's hooks never saw it), and the loop's hooks stay installed."""

    async def main() -> tuple[int, bool, object]:
        loop: Any = asyncio.get_running_loop()
        hooks = sys.get_asyncgen_hooks()
        rate = evclock.clock().rate(100)
        async for tick in rate:
            if tick.index == 2:
                break
        tasks = len(asyncio.all_tasks())
        gc.collect()
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        return (
            len(asyncio.all_tasks()) - tasks,
            sys.get_asyncgen_hooks() == hooks,
            len(loop._asyncgens),
        )

    assert evclock.run(main()) == (0, True, 0)


def test_an_iterator_ended_by_an_exception_is_replaced_on_the_next_sleep() -> None:
    async def main() -> list[tuple[int, int]]:
        clock = evclock.clock()
        rate = clock.rate(10)
        out = [(tick.index, tick.expected_ns) for tick in [await rate.sleep()]]
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(rate.sleep(), 0.05)  # cancelled inside the generator
        out.append(((await rate.sleep()).index, clock.now_ns()))
        return out

    assert evclock.run(main()) == [(0, 0), (1, 100_000_000)]
