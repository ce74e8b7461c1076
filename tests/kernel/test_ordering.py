"""Ordering fidelity: SimEventLoop runs callbacks and wakes tasks in exactly stock asyncio's order.

The reference is a stock asyncio loop (its own ``_run_once``) on a fake monotonic clock: its
selector lets the requested timeout pass instead of waiting, and its timers break ties in
scheduling order (asyncio's heap leaves equal deadlines in arbitrary order; evclock, like
every discrete-event simulator, fires them FIFO). Random programs of ``call_at``,
``call_soon``, ``asyncio.sleep``, ``clock.sleep``, ``asyncio.timeout`` and ``Event``
interactions must produce identical traces (what ran, at what time) on both loops.
"""

from __future__ import annotations

import asyncio
import selectors
from asyncio import events, futures
from collections.abc import Callable, Coroutine
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

import evclock
from evclock import SimEventLoop

TICK = 0.125  # every time in these programs is a multiple of 1/8 s: exact in binary and in ns
_SET_RESULT_UNLESS_CANCELLED: Callable[..., None] = futures._set_result_unless_cancelled  # type: ignore[attr-defined]


class _FakeTimeSelector(selectors.DefaultSelector):
    """``select(timeout)`` lets ``timeout`` seconds of the loop's fake clock pass."""

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None:
            raise AssertionError("the reference loop would block forever (a deadlock)")
        self.now += timeout
        return list(super().select(0))


class _FifoTimerHandle(events.TimerHandle):
    """A TimerHandle ordered by (when, scheduling order), as evclock orders its timers."""

    _seq = 0

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        _FifoTimerHandle._seq += 1
        self.order = _FifoTimerHandle._seq

    def __lt__(self, other: object) -> bool:
        assert isinstance(other, _FifoTimerHandle)
        return (self._when, self.order) < (other._when, other.order)


class ReferenceLoop(asyncio.SelectorEventLoop):
    """Stock asyncio on a fake clock, with FIFO ties among equal deadlines."""

    def __init__(self) -> None:
        self._fake = _FakeTimeSelector()
        super().__init__(self._fake)

    def time(self) -> float:
        return self._fake.now

    def call_at(  # type: ignore[override]
        self, when: float, callback: Callable[..., object], *args: Any, context: Any = None
    ) -> asyncio.TimerHandle:
        self._check_closed()  # type: ignore[attr-defined]
        timer = _FifoTimerHandle(when, callback, args, self, context)
        import heapq

        heapq.heappush(self._scheduled, timer)  # type: ignore[attr-defined]
        timer._scheduled = True  # type: ignore[attr-defined]
        return timer


# ---------------------------------------------------------------------------- programs

# One task is a list of operations:
#   ("sleep", k)          await asyncio.sleep(k * TICK)
#   ("csleep", k)         await clock.sleep(k * TICK)   (on the reference: a future resolved
#                         by a timer, which is what asyncio.sleep does for k > 0)
#   ("yield",)            await asyncio.sleep(0)
#   ("set", e)            events[e].set()
#   ("clear", e)          events[e].clear()
#   ("wait", e, k)        async with asyncio.timeout(k * TICK): await events[e].wait()
#   ("call_at", k, n)     loop.call_at(now + k * TICK, cb) - cb does call_soon n times
#   ("call_soon", n)      loop.call_soon(cb) - cb does call_soon n times
#   ("cancel", j)         tasks[j].cancel() (often while j was woken at the same instant)
EVENTS = 3
ticks = st.integers(min_value=0, max_value=4)
op = st.one_of(
    st.tuples(st.just("sleep"), ticks),
    st.tuples(st.just("csleep"), ticks),
    st.tuples(st.just("yield")),
    st.tuples(st.just("set"), st.integers(0, EVENTS - 1)),
    st.tuples(st.just("clear"), st.integers(0, EVENTS - 1)),
    st.tuples(st.just("wait"), st.integers(0, EVENTS - 1), st.integers(1, 4)),
    st.tuples(st.just("call_at"), ticks, st.integers(0, 2)),
    st.tuples(st.just("call_soon"), st.integers(0, 2)),
    st.tuples(st.just("cancel"), st.integers(0, 4)),
)
programs = st.lists(st.lists(op, max_size=8), min_size=1, max_size=5)


def make_main(
    program: list[list[tuple[Any, ...]]], trace: list[tuple[str, float]], sim: bool
) -> Callable[[], Coroutine[Any, Any, None]]:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        events_ = [asyncio.Event() for _ in range(EVENTS)]
        sleep = evclock.clock().sleep if sim else timer_sleep

        def record(label: str) -> None:
            trace.append((label, loop.time()))

        def callback(label: str, soon: int) -> None:
            record(label)
            for j in range(soon):
                loop.call_soon(record, f"{label}.soon{j}")

        tasks: list[asyncio.Task[None]] = []

        async def task(index: int, ops: list[tuple[Any, ...]]) -> None:
            try:
                await run_ops(index, ops)
            except asyncio.CancelledError:
                record(f"t{index} cancelled")
                raise

        async def run_ops(index: int, ops: list[tuple[Any, ...]]) -> None:
            for step, operation in enumerate(ops):
                name = f"t{index}.{step}"
                kind = operation[0]
                if kind == "sleep":
                    await asyncio.sleep(operation[1] * TICK)
                elif kind == "csleep":
                    await sleep(operation[1] * TICK)
                elif kind == "yield":
                    await asyncio.sleep(0)
                elif kind == "set":
                    events_[operation[1]].set()
                elif kind == "clear":
                    events_[operation[1]].clear()
                elif kind == "wait":
                    try:
                        async with asyncio.timeout(operation[2] * TICK):
                            await events_[operation[1]].wait()
                    except TimeoutError:
                        record(f"{name} timeout")
                elif kind == "cancel":
                    if operation[1] < len(tasks) and operation[1] != index:
                        tasks[operation[1]].cancel()
                elif kind == "call_at":
                    loop.call_at(loop.time() + operation[1] * TICK, callback, name, operation[2])
                else:
                    loop.call_soon(callback, name, operation[1])
                record(name)

        tasks.extend(asyncio.create_task(task(i, ops)) for i, ops in enumerate(program))
        await asyncio.gather(*tasks, return_exceptions=True)
        record("end")

    return main


async def timer_sleep(delay: float) -> None:
    """What clock.sleep is in asyncio terms: a future resolved by a timer (also for 0)."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[None] = loop.create_future()
    handle = loop.call_later(delay, _SET_RESULT_UNLESS_CANCELLED, fut, None)
    try:
        await fut
    finally:
        handle.cancel()


def run_reference(program: list[list[tuple[Any, ...]]]) -> list[tuple[str, float]]:
    trace: list[tuple[str, float]] = []
    with asyncio.Runner(loop_factory=ReferenceLoop) as runner:
        runner.run(make_main(program, trace, sim=False)())
    return trace


def run_sim(program: list[list[tuple[Any, ...]]]) -> list[tuple[str, float]]:
    trace: list[tuple[str, float]] = []
    with asyncio.Runner(loop_factory=SimEventLoop) as runner:
        runner.run(make_main(program, trace, sim=True)())
    return trace


@settings(max_examples=150, deadline=None, derandomize=True)
@given(programs)
def test_random_programs_run_in_stock_asyncio_order(program: list[list[tuple[Any, ...]]]) -> None:
    assert run_sim(program) == run_reference(program)


# ----------------------------------------------------------------- named cases


def test_a_callback_scheduling_a_callback_runs_before_a_sleeper_due_with_it() -> None:
    """call_at A (which call_soon's X) and a sleep due at the same instant: A, X, task."""

    async def main(sim: bool) -> list[str]:
        loop = asyncio.get_running_loop()
        order: list[str] = []
        loop.call_at(1.0, lambda: (order.append("A"), loop.call_soon(order.append, "X")))
        await (evclock.clock().sleep(1.0) if sim else asyncio.sleep(1.0))
        order.append("task")
        return order

    with asyncio.Runner(loop_factory=SimEventLoop) as runner:
        on_sim = runner.run(main(True))
    with asyncio.Runner(loop_factory=ReferenceLoop) as runner:
        on_reference = runner.run(main(False))
    assert on_sim == on_reference == ["A", "X", "task"]


def test_a_sleep_future_awaited_by_two_tasks_wakes_both() -> None:
    async def main() -> list[str]:
        woke: list[str] = []
        shared = evclock.clock().sleep(1.0)

        async def waiter(name: str) -> None:
            await shared
            woke.append(name)

        await asyncio.gather(waiter("a"), waiter("b"), waiter("c"))
        return woke

    assert evclock.run(main()) == ["a", "b", "c"]


def test_a_pure_python_future_due_by_timer_wakes_every_waiter() -> None:
    """asyncio.sleep's timer resolving a pure-Python future (``_PyFuture``) awaited by two
    tasks: both wake, once each, in the order they started waiting."""

    async def main() -> tuple[list[str], float]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = futures._PyFuture(loop=loop)  # type: ignore[attr-defined]
        loop.call_later(2.0, _SET_RESULT_UNLESS_CANCELLED, fut, None)
        woke: list[str] = []

        async def waiter(name: str) -> None:
            await fut
            woke.append(name)

        await asyncio.gather(waiter("a"), waiter("b"))
        return woke, loop.time()

    assert evclock.run(main()) == (["a", "b"], 2.0)


def test_a_future_subclass_woken_in_place_resolves_through_its_own_methods() -> None:
    """The in-place wake-up calls the C future's methods unbound only on futures of exactly
    that type: a subclass's own set_result and remove_done_callback run (one waiter, woken
    by a timer: the short path), and the value and time are exact."""
    calls: list[str] = []

    class Traced(asyncio.Future[int]):
        def set_result(self, result: int) -> None:
            calls.append(f"set_result({result})")
            super().set_result(result)

        def remove_done_callback(self, fn: Callable[..., object]) -> int:
            calls.append("remove_done_callback")
            return super().remove_done_callback(fn)

    async def main() -> tuple[int, int]:
        loop = asyncio.get_running_loop()
        fut = Traced()
        loop.call_later(0.25, _SET_RESULT_UNLESS_CANCELLED, fut, 7)
        value = await fut
        return value, evclock.clock().now_ns()

    assert evclock.run(main()) == (7, 250_000_000)
    assert calls == ["remove_done_callback", "set_result(7)"]


def test_sleep_timers_whose_futures_ended_elsewhere_fire_as_on_stock_asyncio() -> None:
    """The timer asyncio.sleep uses, next due, with its future already ended by something
    else (resolved by hand, cancelled, awaited by nobody): time moves to it and it fires as
    asyncio's does (the resolved one reports InvalidStateError at its time), and a sleep due
    after it still wakes exactly once, at its time."""

    async def main() -> list[Any]:
        loop = asyncio.get_running_loop()
        seen: list[Any] = []
        loop.set_exception_handler(
            lambda _loop, ctx: seen.append((loop.time(), type(ctx.get("exception")).__name__))
        )
        resolved: asyncio.Future[str] = loop.create_future()
        cancelled: asyncio.Future[None] = loop.create_future()
        unawaited: asyncio.Future[None] = loop.create_future()
        handles = [
            loop.call_later(1.0, _SET_RESULT_UNLESS_CANCELLED, resolved, None),
            loop.call_later(2.0, _SET_RESULT_UNLESS_CANCELLED, cancelled, None),
            loop.call_later(2.5, _SET_RESULT_UNLESS_CANCELLED, unawaited, "late"),
        ]
        resolved.set_result("by hand")
        cancelled.cancel()
        await asyncio.sleep(3.0)
        seen.append(("woke", loop.time(), resolved.result(), unawaited.result()))
        for handle in handles:
            handle.cancel()
        await asyncio.sleep(1.0)
        seen.append(("end", loop.time(), [h.cancelled() for h in handles]))
        return seen

    with asyncio.Runner(loop_factory=SimEventLoop) as runner:
        on_sim = runner.run(main())
    with asyncio.Runner(loop_factory=ReferenceLoop) as runner:
        on_reference = runner.run(main())
    assert on_sim == on_reference
    assert on_sim[0] == (1.0, "InvalidStateError")


def test_a_clock_sleep_nobody_awaits_yet_still_ends_at_its_time() -> None:
    """A sim-time wait created now and awaited later (no task waits on it when it is due)."""

    async def main() -> tuple[float, bool, float]:
        clock = evclock.clock()
        early = clock.sleep(1.0)
        await clock.sleep(2.0)
        done_at_two = early.done()
        await early  # already over: no wait
        return clock.now().seconds, done_at_two, 2.0

    now, done_at_two, expected = evclock.run(main())
    assert done_at_two is True
    assert now == expected


def _instant(loop: asyncio.AbstractEventLoop) -> asyncio.AbstractEventLoop:
    """A stock ``asyncio.new_event_loop()`` on instant time: its clock is fake and a wait
    for ``timeout`` lets that much of it pass at once (no FIFO ties: asyncio's own heap)."""
    selector: Any = loop._selector  # type: ignore[attr-defined]
    poll = selector.select
    now = [0.0]

    def select(timeout: float | None = None) -> list[Any]:
        if timeout is None:
            raise AssertionError("the stock loop would block forever (a deadlock)")
        now[0] += timeout
        return list(poll(0))

    selector.select = select
    loop.time = lambda: now[0]  # type: ignore[method-assign]
    return loop


class _LoopTimeClock(evclock.Clock):
    """``clock.sleep`` and ``clock.timer`` on a plain loop's own time, as what they are in
    asyncio terms: a future resolved by a timer."""

    clock_type = evclock.SIM

    def now_ns(self) -> int:
        return round(asyncio.get_running_loop().time() * 1e9)

    def sleep(self, duration: float | evclock.Duration) -> Coroutine[Any, Any, None]:
        assert isinstance(duration, float)
        return timer_sleep(duration)

    async def sleep_until_ns(self, when_ns: int) -> None:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        handle = loop.call_at(when_ns / 1e9, _SET_RESULT_UNLESS_CANCELLED, fut, None)
        try:
            await fut
        finally:
            handle.cancel()


async def _all_due_at_one_instant(clock: evclock.Clock) -> list[str]:
    """call_at, call_later, asyncio.sleep, clock.sleep and a clock.timer all due at 1 s,
    scheduled interleaved: what ran there, in order."""
    loop = asyncio.get_running_loop()
    order: list[str] = []

    async def sleeper(label: str, sleep: Callable[[float], Any]) -> None:
        await sleep(1.0)
        order.append(label)

    tasks = [asyncio.ensure_future(sleeper("clock.sleep A", clock.sleep))]
    await asyncio.sleep(0)  # the task schedules its wait before the next entry is scheduled
    loop.call_at(1.0, order.append, "call_at A")
    clock.timer(1.0, lambda: order.append("clock.timer"), oneshot=True)  # a task: waits now
    await asyncio.sleep(0)
    tasks.append(asyncio.ensure_future(sleeper("asyncio.sleep", asyncio.sleep)))
    await asyncio.sleep(0)
    loop.call_later(1.0, order.append, "call_later")
    tasks.append(asyncio.ensure_future(sleeper("clock.sleep B", clock.sleep)))
    await asyncio.sleep(0)
    loop.call_at(1.0, order.append, "call_at B")
    await asyncio.gather(*tasks)
    assert loop.time() == 1.0
    return order


def test_at_one_instant_callbacks_run_before_the_tasks_resumed_there() -> None:
    """What the docs say of one instant: the plain callbacks due at t (call_at,
    call_later) run before the tasks resumed at t (asyncio.sleep, clock.sleep), each group
    in scheduling order, with clock.timer callbacks among the tasks. The grouping is stock
    asyncio's (checked on ``asyncio.new_event_loop()`` on instant time); the order within a
    group is FIFO, where stock asyncio's heap leaves ties in no particular order (checked on
    the FIFO reference)."""
    callbacks = ["call_at A", "call_later", "call_at B"]
    tasks = ["clock.sleep A", "clock.timer", "asyncio.sleep", "clock.sleep B"]

    async def on_sim() -> list[str]:
        return await _all_due_at_one_instant(evclock.clock())

    with asyncio.Runner(loop_factory=SimEventLoop) as runner:
        sim = runner.run(on_sim())
    with asyncio.Runner(loop_factory=ReferenceLoop) as runner:
        fifo = runner.run(_all_due_at_one_instant(_LoopTimeClock()))
    with asyncio.Runner(loop_factory=lambda: _instant(asyncio.new_event_loop())) as runner:
        stock = runner.run(_all_due_at_one_instant(_LoopTimeClock()))
    assert sim == fifo == callbacks + tasks
    assert sorted(stock[:3]) == sorted(callbacks)
    assert sorted(stock[3:]) == sorted(tasks)
