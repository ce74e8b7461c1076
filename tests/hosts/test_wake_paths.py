"""The futureless wake-up (a parked task, evclock/kernel/_park.py) against the future path:
the same programs give the same event traces and final states on both, cancellation
included (``Task.cancel()``'s return value, ``cancelling()``, messages, timing)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Coroutine
from typing import Any

import pytest

import evclock
from evclock import ClockJumpedError, SimEventLoop

Trace = list[Any]


def both(program: Callable[[Trace], Coroutine[Any, Any, object]]) -> Trace:
    """Run ``program`` on the park path and on the future path; the traces must agree."""
    traces = []
    for park in (True, False):
        trace: Trace = []
        SimEventLoop._park_tasks = park
        try:
            result = evclock.run(program(trace))
        except BaseException as exc:  # the outcome is part of the trace
            result = repr(exc)
        finally:
            SimEventLoop._park_tasks = True
        trace.append(("result", result))
        traces.append(trace)
    assert traces[0] == traces[1]
    return traces[0]


def now() -> int:
    return evclock.clock().now_ns()


async def cancellation_storm(trace: Trace) -> object:
    clock = evclock.clock()

    async def sleeper(i: int) -> None:
        try:
            await clock.sleep(10)
            trace.append(("woke", i, now()))
        except asyncio.CancelledError as exc:
            task = asyncio.current_task()
            assert task is not None
            trace.append(("cancelled", i, now(), exc.args, task.cancelling()))
            raise

    tasks = [asyncio.create_task(sleeper(i)) for i in range(6)]
    await clock.sleep(1)
    trace.append(("twice", tasks[1].cancel("m"), tasks[1].cancelling(), tasks[1].cancel()))
    trace.append(("uncancel", tasks[2].cancel("a"), tasks[2].uncancel(), tasks[2].cancelling()))
    trace.append(("msgs", tasks[3].cancel(), tasks[3].cancel("b"), tasks[3].cancelling()))
    await asyncio.sleep(0)
    trace.append(("late", tasks[0].cancel(), tasks[5].cancel("x")))
    await asyncio.gather(*tasks, return_exceptions=True)
    return [(t.cancelled(), t.cancel()) for t in tasks]


async def self_cancel_and_timeouts(trace: Trace) -> object:
    clock = evclock.clock()

    async def self_cancel() -> None:
        task = asyncio.current_task()
        assert task is not None
        task.cancel("self")
        try:
            await clock.sleep(5)
        except asyncio.CancelledError as exc:
            trace.append(("self", now(), exc.args))

    await asyncio.create_task(self_cancel())
    async with asyncio.timeout(2.5) as scope:
        scope.reschedule(asyncio.get_running_loop().time() + 1.5)
        await clock.sleep(1)
        trace.append(("inside", now()))
        try:
            await clock.sleep(3)
        except asyncio.CancelledError:
            trace.append(("timed out", now()))
            raise
    return now()


async def task_groups(trace: Trace) -> object:
    clock = evclock.clock()

    async def child(i: int) -> None:
        await clock.sleep(0.1 * (i + 1))
        trace.append(("child", i, now()))
        if i == 2:
            raise ValueError(i)

    try:
        async with asyncio.TaskGroup() as group:
            for i in range(5):
                group.create_task(child(i))
    except* ValueError as errors:
        trace.append(("group", [e.args for e in errors.exceptions], now()))
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(clock.sleep(5), 1)
    shared = asyncio.ensure_future(clock.sleep(1))
    await asyncio.gather(shared, shared, clock.sleep(0.5), asyncio.sleep(0.25))
    return now()


async def rates_and_timers(trace: Trace) -> object:
    clock = evclock.clock()
    timer = clock.timer(0.03, lambda: trace.append(("timer", now())))
    async for tick in clock.rate(50):
        trace.append(("tick", tick.index, tick.expected_ns, tick.actual_ns))
        if tick.index == 5:
            break
    timer.cancel()
    return now()


async def cancel_from_another_thread(trace: Trace) -> object:
    loop = asyncio.get_running_loop()
    clock = evclock.clock()

    async def sleeper() -> None:
        try:
            await clock.sleep(100)
        except asyncio.CancelledError:
            trace.append(("cancelled", now()))
            raise

    task = asyncio.create_task(sleeper())
    await clock.sleep(1)
    thread = threading.Thread(target=loop.call_soon_threadsafe, args=(task.cancel,))
    with loop.hold_time():
        thread.start()
        await asyncio.to_thread(thread.join, 10)
    await asyncio.gather(task, return_exceptions=True)
    return (task.cancelled(), now())


async def time_jumps(trace: Trace) -> object:
    clock = evclock.clock()
    loop: Any = asyncio.get_running_loop()

    async def sleeper(i: int) -> None:
        try:
            await clock.sleep(5 + i)
        except ClockJumpedError:
            trace.append(("jumped", i, now()))

    tasks = [asyncio.create_task(sleeper(i)) for i in range(3)]
    await clock.sleep(1)
    tasks[1].cancel()
    loop.source.set_time(500_000_000)
    await asyncio.gather(*tasks, return_exceptions=True)
    return [t.cancelled() for t in tasks]


@pytest.mark.parametrize(
    "program",
    [
        cancellation_storm,
        self_cancel_and_timeouts,
        task_groups,
        rates_and_timers,
        cancel_from_another_thread,
        time_jumps,
    ],
)
def test_the_park_path_and_the_future_path_give_the_same_trace(
    program: Callable[[Trace], Coroutine[Any, Any, object]],
) -> None:
    trace = both(program)
    assert len(trace) > 1  # the program did something observable


def test_tasks_the_loop_makes_park_and_others_do_not() -> None:
    async def main() -> tuple[str, str]:
        loop = asyncio.get_running_loop()
        parked = type(asyncio.current_task()).__module__
        loop.set_task_factory(lambda loop, coro, **kw: asyncio.Task(coro, loop=loop, **kw))

        async def module() -> str:
            return type(asyncio.current_task()).__module__

        return parked, await loop.create_task(module())

    assert evclock.run(main()) == ("evclock.kernel._park", "_asyncio")
