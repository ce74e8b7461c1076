"""The workloads of ``instructions.py``, each in the idiomatic form of each scheduler.

Every function here runs one workload on an input built beforehand (a *plan*: seeded
durations in float seconds, or ``(hz, ticks)`` per rate loop, or a number of physics
steps) and returns when it is done. Nothing here builds or reads a plan: the harness builds
it before its clock starts, and under callgrind both repetition counts build the very same
plan, so its cost cancels out.

The baselines (floors) are here too:

* :func:`sleep0_fanout` / :func:`sleep0_rates`: a bare ``asyncio.sleep(0)`` task switch on a
  stock loop, as many per task as the workload has wake-ups (the floor of any scheduler
  built on asyncio tasks);
* :func:`least_future_sleep`: the least a future-based sleep can cost - each task parks on
  a C ``asyncio.Future``; a plain function pops the earliest int deadline (a heap of
  distinct deadlines with what is due beside it, as evclock's kernel) and wakes the task in
  place: no event-loop iteration, no time source, no validation, no cancellation;
* :class:`InstantTimeLoop`: stock asyncio whose ``time()`` jumps to the earliest timer
  when the loop would block, so timers run back to back with all of asyncio's own timer
  machinery (``call_at``, ``TimerHandle``, cancellation): the floor of timeouts.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import selectors
from collections.abc import Callable, Coroutine, Generator
from typing import Any

Rows = list[list[float]]
Loops = list[tuple[float, int]]

# ----------------------------------------------------------------------------- sleeps


def clock_sleep(rows: Rows) -> None:
    """``await clock.sleep(d)`` on evclock's sim loop."""
    import evclock

    async def worker(clock: evclock.Clock, durations: list[float]) -> None:
        sleep = clock.sleep
        for d in durations:
            await sleep(d)

    async def main() -> None:
        clock = evclock.clock()
        await asyncio.gather(*(worker(clock, row) for row in rows))

    evclock.run(main())


def asyncio_sleep_sim(rows: Rows) -> None:
    """``await asyncio.sleep(d)`` on evclock's sim loop."""
    _gather_on(_sim_run, _asyncio_sleep_worker, rows)


def asyncio_sleep_instant(rows: Rows) -> None:
    """``await asyncio.sleep(d)`` on stock asyncio with instant time (:class:`InstantTimeLoop`):
    what stock asyncio's own timers cost a timed sleep, with no waiting in between."""
    _gather_on(_instant_run, _asyncio_sleep_worker, rows)


async def _asyncio_sleep_worker(durations: list[float]) -> None:
    sleep = asyncio.sleep
    for d in durations:
        await sleep(d)


def sleep0_fanout(rows: Rows) -> None:
    """The floor: ``await asyncio.sleep(0)`` once per duration, on a stock loop."""
    _gather_on(asyncio.run, _sleep0_worker, rows)


def sleep0_fanout_uvloop(rows: Rows) -> None:
    """The floor on uvloop (compiled with Cython on libuv): ``await asyncio.sleep(0)``."""
    _gather_on(_uvloop_run, _sleep0_worker, rows)


async def _sleep0_worker(durations: list[float]) -> None:
    sleep = asyncio.sleep
    for _ in durations:
        await sleep(0)


def _uvloop_run(coro: Coroutine[Any, Any, Any]) -> None:
    import uvloop

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(coro)


def simpy_sleep(rows: Rows) -> None:
    """SimPy: a process per task, ``yield env.timeout(d)`` (an event per waiter)."""
    import simpy

    env = simpy.Environment()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


def least_future_sleep(rows: Rows) -> None:
    """The least a future-based sleep can cost (see the module's docstring)."""
    loop = asyncio.new_event_loop()
    heap: list[int] = []
    at: dict[int, Any] = {}
    now = [0]
    heappush, heappop = heapq.heappush, heapq.heappop

    def sleep(seconds: float) -> asyncio.Future[None]:
        fut: asyncio.Future[None] = asyncio.Future()  # on the running loop
        when = now[0] + round(seconds * 1e9)
        present = at.setdefault(when, fut)
        if present is fut:
            heappush(heap, when)
        elif type(present) is list:
            present.append(fut)
        else:
            at[when] = [present, fut]
        return fut

    async def worker(durations: list[float]) -> None:
        for d in durations:
            await sleep(d)

    def wake(fut: Any) -> None:
        # The task's wake-up, run in place (as evclock's kernel wakes a lone waiter).
        ((callback, ctx),) = fut._callbacks
        fut.remove_done_callback(callback)
        fut.set_result(None)
        ctx.run(callback, fut)

    def drive() -> None:
        pop = at.pop
        while heap:
            now[0] = when = heappop(heap)
            entry = pop(when)
            if type(entry) is list:
                for fut in entry:
                    wake(fut)
                continue
            ((callback, ctx),) = entry._callbacks  # wake(entry), inlined
            entry.remove_done_callback(callback)
            entry.set_result(None)
            ctx.run(callback, entry)

    _run_minimal(loop, rows, worker, drive)


def _run_minimal(
    loop: asyncio.AbstractEventLoop,
    rows: Rows,
    worker: Callable[[list[float]], Coroutine[Any, Any, None]],
    drive: Callable[[], None],
) -> None:
    """Start one ``worker`` task per row on ``loop``, let each reach its first wait, then
    ``drive()`` them all to their end."""

    async def start() -> list[asyncio.Task[None]]:
        tasks = [loop.create_task(worker(row)) for row in rows]
        await asyncio.sleep(0)  # every task runs to its first wait
        return tasks

    try:
        tasks = loop.run_until_complete(start())
        # The tasks resume on ``loop`` as if it ran them (a future made with no loop= is
        # bound to the running loop, as evclock's are).
        asyncio.events._set_running_loop(loop)
        try:
            drive()
        finally:
            asyncio.events._set_running_loop(None)
        for task in tasks:
            task.result()  # each ran to its end
    finally:
        loop.close()


# ----------------------------------------------------------------------------- rate loops


def clock_rate(loops: Loops) -> None:
    """``async for tick in clock.rate(hz)`` on evclock's sim loop, ``ticks`` ticks each."""
    import evclock

    async def every(clock: evclock.Clock, hz: float, ticks: int) -> None:
        async for _tick in clock.rate(hz):
            ticks -= 1
            if not ticks:
                break

    async def main() -> None:
        clock = evclock.clock()
        await asyncio.gather(*(every(clock, hz, ticks) for hz, ticks in loops))

    evclock.run(main())


def rate_deadlines(loops: Loops) -> None:
    """What a ``clock.rate`` tick costs without its ``Tick`` and statistics: each task
    awaits ``clock.sleep_until_ns`` at the rate's exact deadlines (tick 0 at the start)."""
    _rate_deadlines(loops, per_tick_coroutine=False)


def rate_deadlines_coroutine(loops: Loops) -> None:
    """:func:`rate_deadlines` with each wait inside a coroutine of its own, made per tick
    (as ``Rate.__anext__`` is): what that coroutine costs."""
    _rate_deadlines(loops, per_tick_coroutine=True)


def _rate_deadlines(loops: Loops, per_tick_coroutine: bool) -> None:
    from fractions import Fraction

    import evclock

    async def every(clock: evclock.Clock, hz: float, ticks: int) -> None:
        period = Fraction(10**9) / Fraction(hz)  # Rate's exact period
        num, den = period.numerator, period.denominator
        start = clock.now_ns()
        sleep_until_ns = clock.sleep_until_ns

        async def in_a_coroutine(deadline: int) -> None:
            await sleep_until_ns(deadline)

        wait = in_a_coroutine if per_tick_coroutine else sleep_until_ns
        for index in range(1, ticks):
            await wait(start + index * num // den)

    async def main() -> None:
        clock = evclock.clock()
        await asyncio.gather(*(every(clock, hz, ticks) for hz, ticks in loops))

    evclock.run(main())


def asyncio_rate_sim(loops: Loops) -> None:
    """A drift-free rate loop written with ``asyncio.sleep`` and ``loop.time()``, on
    evclock's sim loop (tick 0 at the start, tick k at ``start + k / hz``)."""
    import evclock

    async def every(hz: float, ticks: int) -> None:
        time = asyncio.get_running_loop().time
        sleep = asyncio.sleep
        period = 1.0 / hz
        start = time()
        for k in range(1, ticks):
            await sleep(start + k * period - time())

    async def main() -> None:
        await asyncio.gather(*(every(hz, ticks) for hz, ticks in loops))

    evclock.run(main())


def sleep0_rates(loops: Loops) -> None:
    """The floor: ``await asyncio.sleep(0)`` once per tick, on a stock loop."""
    _sleep0_rates_on(asyncio.run, loops)


def sleep0_rates_uvloop(loops: Loops) -> None:
    """The floor on uvloop: ``await asyncio.sleep(0)`` once per tick."""
    _sleep0_rates_on(_uvloop_run, loops)


def _sleep0_rates_on(run: Callable[[Coroutine[Any, Any, Any]], Any], loops: Loops) -> None:
    async def every(ticks: int) -> None:
        sleep = asyncio.sleep
        for _ in range(ticks):
            await sleep(0)

    async def main() -> None:
        await asyncio.gather(*(every(ticks) for _hz, ticks in loops))

    run(main())


def simpy_rate(loops: Loops) -> None:
    """SimPy: a process per loop, ``yield env.timeout(start + k / hz - env.now)``."""
    import simpy

    env = simpy.Environment()

    def every(hz: float, ticks: int) -> Generator[Any, Any, None]:
        timeout = env.timeout
        period = 1.0 / hz
        start = env.now
        for k in range(1, ticks):
            yield timeout(start + k * period - env.now)

    for hz, ticks in loops:
        env.process(every(hz, ticks))
    env.run()


# ----------------------------------------------------------------------------- timeouts


class _JumpingSelector(selectors.DefaultSelector):  # type: ignore[misc,valid-type]
    """Polls without blocking; where the loop would block until its earliest timer, moves
    the loop's time to that timer's deadline instead."""

    loop: InstantTimeLoop

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None or timeout > 0:
            loop = self.loop
            if not loop._scheduled:  # type: ignore[attr-defined]
                raise RuntimeError("InstantTimeLoop: nothing to wait for (would block forever)")
            loop.now = loop._scheduled[0]._when  # type: ignore[attr-defined]
        return super().select(0)  # type: ignore[no-any-return]


class InstantTimeLoop(asyncio.SelectorEventLoop):
    """Stock asyncio with instant time: ``time()`` is a number that jumps to the earliest
    timer's deadline whenever the loop would block waiting for it. Everything else is the
    stock loop (its ``_run_once``, ``call_at``, ``TimerHandle``, cancellation, the poll)."""

    def __init__(self) -> None:
        selector = _JumpingSelector()
        selector.loop = self
        self.now = 0.0
        super().__init__(selector)

    def time(self) -> float:
        return self.now


async def _timeout_worker(durations: list[float]) -> None:
    never = asyncio.Event()  # one per waiter, never set
    timeout = asyncio.timeout
    for d in durations:
        try:
            async with timeout(d):
                await never.wait()
        except TimeoutError:
            pass


async def _wait_for_worker(durations: list[float]) -> None:
    never = asyncio.Event()  # one per waiter, never set
    wait_for = asyncio.wait_for
    for d in durations:
        with contextlib.suppress(TimeoutError):
            await wait_for(never.wait(), d)


def _gather_on(run: Callable[[Coroutine[Any, Any, Any]], Any], worker: Any, rows: Rows) -> None:
    async def main() -> None:
        await asyncio.gather(*(worker(row) for row in rows))

    run(main())


def _sim_run(coro: Coroutine[Any, Any, Any]) -> None:
    import evclock

    evclock.run(coro)


def _instant_run(coro: Coroutine[Any, Any, Any]) -> None:
    with asyncio.Runner(loop_factory=InstantTimeLoop) as runner:
        runner.run(coro)


def timeout_sim(rows: Rows) -> None:
    """``async with asyncio.timeout(d): await never.wait()`` on evclock's sim loop."""
    _gather_on(_sim_run, _timeout_worker, rows)


def timeout_instant(rows: Rows) -> None:
    """The same on :class:`InstantTimeLoop` (the floor)."""
    _gather_on(_instant_run, _timeout_worker, rows)


def wait_for_sim(rows: Rows) -> None:
    """``await asyncio.wait_for(never.wait(), d)`` on evclock's sim loop."""
    _gather_on(_sim_run, _wait_for_worker, rows)


def wait_for_instant(rows: Rows) -> None:
    """The same on :class:`InstantTimeLoop` (the floor)."""
    _gather_on(_instant_run, _wait_for_worker, rows)


def simpy_timeouts(rows: Rows) -> None:
    """SimPy: ``yield never | env.timeout(d)``, each process with its own ``never``."""
    import simpy

    env = simpy.Environment()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        never = env.event()
        timeout = env.timeout
        for d in durations:
            yield never | timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


# ----------------------------------------------------------------------------- KUKA
# The controllers of benchmarks/kuka_throughput.py (joint controller at ``hz``, IK planner
# at 10 Hz, 240 Hz physics), run by evclock rate loops or by a hand-written synchronous
# loop, for ``steps`` physics steps. Each returns the arm's final joint state, which must be
# bit-identical between the two.


def _kuka_state(ctl: Any) -> str:
    import pybullet as pb

    arm = ctl.arm
    states = pb.getJointStates(arm.robot, arm.joints, physicsClientId=arm.client)
    return repr([(s[0], s[1]) for s in states] + [ctl.plans, ctl.target_index])


def kuka_sync(steps: int, hz: float) -> str:
    """The hand-written synchronous loop."""
    import kuka_throughput as k
    import pybullet as pb

    client = pb.connect(pb.DIRECT)
    try:
        ctl = k.Controllers(client, hz)
        control_due = k.ticks_due(hz, steps)
        plan_due = k.ticks_due(k.PLANNER_HZ, steps)
        # When both are due at one step, the one that ran (and so re-armed) first goes
        # first, as equal deadlines fire in scheduling order on the sim loop.
        control_first = True
        for step in range(steps):
            control, plan_ = control_due[step], plan_due[step]
            if control and plan_:
                if not control_first:
                    ctl.plan()
                ctl.control()
                if control_first:
                    ctl.plan()
            elif control:
                ctl.control()
                control_first = False
            elif plan_:
                ctl.plan()
                control_first = True
            pb.stepSimulation(physicsClientId=client)
        return _kuka_state(ctl)
    finally:
        pb.disconnect(client)


def kuka_evclock(steps: int, hz: float, **source_options: Any) -> str:
    """The same controllers as evclock rate loops on a ``PyBulletTimeSource``."""
    import kuka_throughput as k

    import evclock

    source = evclock.sources.PyBulletTimeSource.connect(**source_options)
    ctl = k.Controllers(source.client, hz)

    async def every(rate_hz: float, work: Callable[[], None]) -> None:
        async for _tick in evclock.clock().rate(rate_hz):
            work()

    async def main() -> str:
        clock = evclock.clock()
        async with asyncio.TaskGroup() as tg:
            control = tg.create_task(every(hz, ctl.control))
            planner = tg.create_task(every(k.PLANNER_HZ, ctl.plan))
            # Main's wait ends first at that instant (scheduled first): the ticks due then are
            # cancelled, as the synchronous loop stops before its step `steps`.
            await clock.sleep(steps / k.PHYSICS_HZ)  # exact: steps is a multiple of 6
            control.cancel()
            planner.cancel()
        if source.step_index != steps:
            raise RuntimeError(f"ran {source.step_index} physics steps, not {steps}")
        return _kuka_state(ctl)

    return evclock.run(main(), source=source)
