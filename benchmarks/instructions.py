"""Instruction counts per wakeup (callgrind): the simulation loop's cost, exactly.

The wall clock on a shared virtual machine swings by tens of percent; instructions executed
do not. Each variant runs in its own process under ``valgrind --tool=callgrind`` twice - with
the full workload and with an empty one (the same tasks, no waits) - and the difference,
divided by the number of wakeups, is its cost per wakeup: start-up and task creation cancel
out. Baselines are measured in the same run and every figure is printed as a ratio to them.

Workloads (seeded; durations drawn once as integer nanoseconds, passed as float seconds):

* ``fanout``: ``--tasks`` tasks x ``--sleeps`` sleeps of random durations in [1 ms, 10 ms]:
  ``clock.sleep`` and ``asyncio.sleep`` on the sim loop, SimPy's ``env.timeout`` and a
  bare ``asyncio.sleep(0)`` task switch on a stock loop (the floor of any asyncio scheduler);
* ``timeouts``: ``--tasks`` tasks x ``--waits`` waits that always time out -
  ``asyncio.timeout(d)`` around an ``Event`` never set - against SimPy's
  ``never | env.timeout(d)`` on the same plan;
* ``scale``: ``clock.sleep`` per wakeup with ``--big`` concurrent sleepers vs ``--tasks``;
* ``kuka``: per physics step, the KUKA controllers of ``kuka_throughput.py`` as evclock rate
  loops against the same controllers in a hand-written synchronous loop (final states
  bit-identical), at 100 Hz and at 240 Hz, under ``--hash-seeds`` string-hash seeds.

Every process runs with one string-hash seed (``PYTHONHASHSEED``): a random one changes dict
layouts and so what the Python code costs (the synchronous KUKA loop's cost per step moved by
3% across seeds); with one seed two runs agree to one instruction in a million. A figure with
one seed is that of one layout, so the KUKA comparison, whose targets are a few percent
apart, is counted under seeds 0 .. N-1 and reported per seed and as the mean of the ratios.

Run: ``python benchmarks/instructions.py [--tasks 1000 --sleeps 300 --waits 100 --big 100000]``
(needs valgrind; a run takes minutes: each process runs about 50x slower under callgrind).
Also ``python benchmarks/instructions.py --variant NAME --count N`` runs one variant
without valgrind (what the harness runs under it).
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import heapq
import itertools
import math
import os
import random
import re
import statistics
import subprocess
import sys
import time
import types
from collections.abc import Callable, Coroutine, Generator, Sequence
from typing import Any

MIN_NS = 1_000_000
MAX_NS = 10_000_000
#: Plain (wall-time) runs of each process; the fastest is kept.
WALL_REPEAT = 3


def plan(tasks: int, count: int, seed: int) -> list[list[float]]:
    """``count`` seeded durations per task, in float seconds (drawn as integer ns)."""
    rng = random.Random(seed)
    return [[rng.randint(MIN_NS, MAX_NS) / 1e9 for _ in range(count)] for _ in range(tasks)]


# ------------------------------------------------------------------------------ variants


def clock_sleep(rows: list[list[float]]) -> None:
    import evclock

    async def worker(clock: evclock.Clock, durations: list[float]) -> None:
        sleep = clock.sleep
        for d in durations:
            await sleep(d)

    async def main() -> None:
        clock = evclock.clock()
        await asyncio.gather(*(worker(clock, row) for row in rows))

    evclock.run(main())


def asyncio_sleep_sim(rows: list[list[float]]) -> None:
    import evclock

    async def worker(durations: list[float]) -> None:
        sleep = asyncio.sleep
        for d in durations:
            await sleep(d)

    async def main() -> None:
        await asyncio.gather(*(worker(row) for row in rows))

    evclock.run(main())


def asyncio_sleep0(rows: list[list[float]]) -> None:
    async def worker(durations: list[float]) -> None:
        sleep = asyncio.sleep
        for _ in durations:
            await sleep(0)

    async def main() -> None:
        await asyncio.gather(*(worker(row) for row in rows))

    asyncio.run(main())


def _run_minimal(
    loop: asyncio.AbstractEventLoop,
    rows: list[list[float]],
    worker: Callable[[list[float]], Coroutine[Any, Any, None]],
    drive: Callable[[], None],
) -> None:
    """Start one ``worker`` task per row on ``loop``, let each reach its first wait, then
    ``drive()`` them all to their end (the minimal variants' shared harness)."""

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


def future_wake_minimal(rows: list[list[float]]) -> None:
    """The least a future-based sleep can cost: each task parks on a C ``asyncio.Future``; a
    plain function pops the earliest int deadline (a heap of distinct deadlines with what is
    due beside it, as the kernel's), resolves the future and runs the task's wake-up in place.
    No event-loop iteration, no time source, no validation: a bound on any design of
    evclock's shape, not a scheduler."""
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

    def wake(fut: asyncio.Future[None]) -> None:
        ((callback, ctx),) = fut._callbacks  # type: ignore[attr-defined]
        fut.remove_done_callback(callback)
        fut.set_result(None)
        ctx.run(callback, fut)

    async def worker(durations: list[float]) -> None:
        for d in durations:
            await sleep(d)

    def drive() -> None:
        pop = at.pop
        while heap:
            now[0] = when = heappop(heap)
            entry = pop(when)
            if type(entry) is list:
                for fut in entry:
                    wake(fut)
                continue
            # wake(entry), inlined as the kernel wakes a lone waiter (no call per wakeup)
            ((callback, ctx),) = entry._callbacks
            entry.remove_done_callback(callback)
            entry.set_result(None)
            ctx.run(callback, entry)

    _run_minimal(loop, rows, worker, drive)


def duck_future_minimal(rows: list[list[float]]) -> None:
    """The least a sleep costs that parks the task on a *Future-compatible object* (asyncio's
    ``_asyncio_future_blocking`` protocol) instead of a C future: a slotted Python object
    whose ``add_done_callback`` keeps the task's wake-up, and whose ``result`` is a C
    callable. Cancellable in principle (the task calls its ``cancel``), but the task takes
    its generic path for such objects (attribute lookups, a Python ``add_done_callback``).
    Same harness as :func:`future_wake_minimal`: no loop, time source or validation."""
    loop = asyncio.new_event_loop()
    heap: list[int] = []
    at: dict[int, Any] = {}
    now = [0]
    heappush, heappop = heapq.heappush, heapq.heappop

    class Waiter:
        __slots__ = ("_asyncio_future_blocking", "_callback", "_context")
        _loop = loop  # read by the task when there is no get_loop()
        result = itertools.repeat(None).__next__  # a C callable: no frame on wake-up

        def add_done_callback(self, callback: Any, *, context: Any = None) -> None:
            self._callback = callback
            self._context = context

    new = object.__new__

    @types.coroutine
    def sleep(seconds: float) -> Generator[Any, None, None]:
        waiter = new(Waiter)
        waiter._asyncio_future_blocking = True
        when = now[0] + round(seconds * 1e9)
        present = at.setdefault(when, waiter)
        if present is waiter:
            heappush(heap, when)
        elif type(present) is list:
            present.append(waiter)
        else:
            at[when] = [present, waiter]
        yield waiter

    async def worker(durations: list[float]) -> None:
        for d in durations:
            await sleep(d)

    def drive() -> None:
        pop = at.pop
        while heap:
            now[0] = when = heappop(heap)
            entry = pop(when)
            if type(entry) is list:
                for waiter in entry:
                    waiter._context.run(waiter._callback, waiter)
                continue
            entry._context.run(entry._callback, entry)

    _run_minimal(loop, rows, worker, drive)


def park_minimal(rows: list[list[float]]) -> None:
    """The least a sleep costs that parks the task without a future: a bare ``yield`` (as
    ``asyncio.sleep(0)`` does) makes the task's step hand itself to ``loop.call_soon``,
    which files it under the sleep's deadline instead of running it next; a plain
    function pops the earliest deadline and runs the step in place. Not a scheduler:
    nothing here can cancel a parked task (``Task.cancel`` of a task waiting on no future
    only sets a flag), and there is no loop, time source or validation."""
    heap: list[int] = []
    at: dict[int, Any] = {}
    now = [0]
    parking: list[int | None] = [None]
    heappush, heappop = heapq.heappush, heapq.heappop

    class ParkingLoop(asyncio.SelectorEventLoop):
        def call_soon(self, callback: Any, *args: Any, context: Any = None) -> Any:  # type: ignore[override]
            when = parking[0]
            if when is None:
                return super().call_soon(callback, *args, context=context)
            parking[0] = None
            entry = (callback, context)
            present = at.setdefault(when, entry)
            if present is entry:
                heappush(heap, when)
            elif type(present) is list:
                present.append(entry)
            else:
                at[when] = [present, entry]
            return None

    loop = ParkingLoop()

    @types.coroutine
    def sleep(seconds: float) -> Generator[None, None, None]:
        parking[0] = now[0] + round(seconds * 1e9)
        yield

    async def worker(durations: list[float]) -> None:
        for d in durations:
            await sleep(d)

    def drive() -> None:
        pop = at.pop
        while heap:
            now[0] = when = heappop(heap)
            entry = pop(when)
            if type(entry) is list:
                for step, ctx in entry:
                    ctx.run(step)
                continue
            step, ctx = entry
            ctx.run(step)

    _run_minimal(loop, rows, worker, drive)


def simpy_timeout(rows: list[list[float]]) -> None:
    import simpy

    env = simpy.Environment()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


def asyncio_timeouts_sim(rows: list[list[float]]) -> None:
    import evclock

    async def worker(never: asyncio.Event, durations: list[float]) -> None:
        timeout = asyncio.timeout
        for d in durations:
            try:
                async with timeout(d):
                    await never.wait()
            except TimeoutError:
                pass

    async def main() -> None:
        never = asyncio.Event()
        await asyncio.gather(*(worker(never, row) for row in rows))

    evclock.run(main())


def simpy_timeouts(rows: list[list[float]]) -> None:
    import simpy

    env = simpy.Environment()
    never = env.event()

    def proc(durations: list[float]) -> Generator[Any, Any, None]:
        timeout = env.timeout
        for d in durations:
            yield never | timeout(d)

    for row in rows:
        env.process(proc(row))
    env.run()


# KUKA (PyBullet): the controllers of benchmarks/kuka_throughput.py, run by evclock rate
# loops or by a hand-written synchronous loop; ``count`` is the number of physics steps. Each
# prints the arm's final joint state, which must be bit-identical between the two.

KUKA_HZ = 100.0  # set by --kuka-hz in the process that runs a KUKA variant


def _kuka_state(ctl: Any) -> str:
    import pybullet as pb

    arm = ctl.arm
    states = pb.getJointStates(arm.robot, arm.joints, physicsClientId=arm.client)
    return repr([(s[0], s[1]) for s in states] + [ctl.plans, ctl.target_index])


def kuka_sync(rows: list[list[float]]) -> None:
    import kuka_throughput as k
    import pybullet as pb

    steps = len(rows[0])
    client = pb.connect(pb.DIRECT)
    try:
        ctl = k.Controllers(client, KUKA_HZ)
        control_due = k.ticks_due(KUKA_HZ, steps)
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
        print("state", _kuka_state(ctl))
    finally:
        pb.disconnect(client)


def kuka_evclock(rows: list[list[float]], watch_time_step: bool = True) -> None:
    import kuka_throughput as k

    import evclock

    steps = len(rows[0])
    source = evclock.sources.PyBulletTimeSource.connect(watch_time_step=watch_time_step)
    ctl = k.Controllers(source.client, KUKA_HZ)

    async def every(hz: float, work: Callable[[], None]) -> None:
        async for _tick in evclock.clock().rate(hz):
            work()

    async def main() -> None:
        clock = evclock.clock()
        async with asyncio.TaskGroup() as tg:
            control = tg.create_task(every(KUKA_HZ, ctl.control))
            planner = tg.create_task(every(k.PLANNER_HZ, ctl.plan))
            # Main's wait ends first at that instant (scheduled first): the ticks due then are
            # cancelled, as the synchronous loop stops before its step `steps`.
            await clock.sleep(steps / k.PHYSICS_HZ)  # exact: steps is a multiple of 6
            control.cancel()
            planner.cancel()
        assert source.step_index == steps, (source.step_index, steps)
        print("state", _kuka_state(ctl))

    evclock.run(main(), source=source)


VARIANTS: dict[str, Callable[[list[list[float]]], None]] = {
    "kuka sync": kuka_sync,
    "kuka evclock": kuka_evclock,
    "kuka evclock, no time-step watch": functools.partial(kuka_evclock, watch_time_step=False),
    "clock.sleep": clock_sleep,
    "asyncio.sleep (sim loop)": asyncio_sleep_sim,
    "asyncio.sleep(0) (stock loop)": asyncio_sleep0,
    "simpy timeout": simpy_timeout,
    "future wake, minimal (no loop)": future_wake_minimal,
    "duck-typed future, minimal (no loop)": duck_future_minimal,
    "bare-yield park, minimal (no loop)": park_minimal,
    "asyncio.timeout (sim loop)": asyncio_timeouts_sim,
    "simpy never | timeout": simpy_timeouts,
}


# ------------------------------------------------------------------------------ harness


def _command(variant: str, tasks: int, count: int, seed: int, hz: float) -> list[str]:
    return [
        sys.executable,
        os.path.abspath(__file__),
        "--variant",
        variant,
        "--tasks",
        str(tasks),
        "--count",
        str(count),
        "--seed",
        str(seed),
        "--kuka-hz",
        repr(hz),
    ]


def _output(stdout: str, key: str) -> str:
    for line in stdout.splitlines():
        if line.startswith(key + " "):
            return line[len(key) + 1 :]
    raise RuntimeError(f"no {key!r} line in the variant's output:\n{stdout}")


def instructions(
    variant: str, tasks: int, count: int, seed: int, hz: float, hash_seed: int = 0
) -> tuple[int, str]:
    """Instructions executed by one process running ``variant`` (callgrind's total) with
    string-hash seed ``hash_seed``, and the process's output."""
    done = subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            "--callgrind-out-file=/dev/null",
            *_command(variant, tasks, count, seed, hz),
        ],
        capture_output=True,
        text=True,
        timeout=7200,
        check=True,
        # One string-hash seed for every process (see the module's docstring).
        env={**os.environ, "PYTHONHASHSEED": str(hash_seed)},
    )
    found = re.search(r"Collected : (\d+)", done.stderr)
    if found is None:
        raise RuntimeError(f"no instruction count in callgrind's output:\n{done.stderr}")
    return int(found.group(1)), done.stdout


def wall(variant: str, tasks: int, count: int, seed: int, hz: float) -> float:
    """Wall seconds of the workload in one plain process (the best of ``WALL_REPEAT``)."""
    best = math.inf
    for _ in range(WALL_REPEAT):
        done = subprocess.run(
            _command(variant, tasks, count, seed, hz),
            capture_output=True,
            text=True,
            timeout=3600,
            check=True,
        )
        best = min(best, float(_output(done.stdout, "wall")))
    return best


class Cost:
    """Per unit (wakeup, physics step): (full run - empty run) / units, in instructions
    (under string-hash seed ``hash_seed``) and, unless ``timed`` is false, in wall
    nanoseconds (NaN then); ``out`` is the full run's output."""

    def __init__(
        self,
        variant: str,
        tasks: int,
        count: int,
        seed: int,
        hz: float = 0.0,
        hash_seed: int = 0,
        timed: bool = True,
    ):
        full, self.out = instructions(variant, tasks, count, seed, hz, hash_seed)
        empty, _ = instructions(variant, tasks, 0, seed, hz, hash_seed)
        units = tasks * count
        self.instr = (full - empty) / units
        self.ns = wall_ns(variant, tasks, count, seed, hz) if timed else math.nan


def wall_ns(variant: str, tasks: int, count: int, seed: int, hz: float = 0.0) -> float:
    """Wall nanoseconds per unit: (full run - empty run) / units, in plain processes."""
    full = wall(variant, tasks, count, seed, hz)
    empty = wall(variant, tasks, 0, seed, hz)
    return (full - empty) / (tasks * count) * 1e9


def _row(name: str, cost: Cost, base: Cost, against: str) -> str:
    return (
        f"  {name:<36}{cost.instr:>10,.0f}{cost.instr / base.instr:>8.2f}x"
        f"{cost.ns:>10,.0f}{cost.ns / base.ns:>8.2f}x   (vs {against})"
    )


HEADER = f"  {'':<36}{'instr':>10}{'ratio':>9}{'wall ns':>10}{'ratio':>9}"


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--tasks", type=int, default=1000)
    p.add_argument("--sleeps", type=int, default=300, help="sleeps per task (fanout)")
    p.add_argument("--waits", type=int, default=100, help="timed-out waits per task")
    p.add_argument("--big", type=int, default=100_000, help="concurrent sleepers (scale)")
    p.add_argument("--big-sleeps", type=int, default=3, help="sleeps per task at --big")
    p.add_argument("--kuka-steps", type=int, default=2400, help="physics steps (multiple of 6)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument(
        "--hash-seeds",
        type=int,
        default=3,
        help="string-hash seeds 0 .. N-1 the KUKA comparison is counted under (mean reported)",
    )
    p.add_argument("--only", choices=["fanout", "timeouts", "scale", "kuka"], action="append")
    p.add_argument("--variant", choices=sorted(VARIANTS), help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, help=argparse.SUPPRESS)
    p.add_argument("--kuka-hz", type=float, default=KUKA_HZ, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    global KUKA_HZ
    args = parse_args(argv)
    if args.variant is not None:
        KUKA_HZ = args.kuka_hz
        rows = plan(args.tasks, args.count, args.seed)
        # Imports happen before the wall clock starts (callgrind's count subtracts them).
        __import__("kuka_throughput" if args.variant.startswith("kuka") else "evclock")
        if args.variant.startswith("simpy"):
            __import__("simpy")
        start = time.perf_counter()
        VARIANTS[args.variant](rows)
        print("wall", repr(time.perf_counter() - start))
        return 0
    parts = args.only or ["fanout", "timeouts", "scale", "kuka"]
    if args.hash_seeds < 1:
        raise SystemExit("--hash-seeds must be at least 1")
    print(
        f"python {sys.version.split()[0]}; per wakeup: instructions under callgrind and wall "
        f"ns (best of {WALL_REPEAT} plain runs), (full run - empty run) / wakeups"
    )
    if "fanout" in parts:
        n, k, seed = args.tasks, args.sleeps, args.seed
        print(f"\nfanout: {n} tasks x {k} sleeps (seed {seed})\n{HEADER}")
        floor = Cost("asyncio.sleep(0) (stock loop)", n, k, seed)
        for name in (
            "clock.sleep",
            "asyncio.sleep (sim loop)",
            "simpy timeout",
            "future wake, minimal (no loop)",
            "duck-typed future, minimal (no loop)",
            "bare-yield park, minimal (no loop)",
        ):
            print(_row(name, Cost(name, n, k, seed), floor, "the asyncio.sleep(0) floor"))
        print(_row("asyncio.sleep(0) (stock loop)", floor, floor, "itself"))
    if "timeouts" in parts:
        n, k, seed = args.tasks, args.waits, args.seed
        print(f"\ntimeouts: {n} tasks x {k} waits that time out (seed {seed})\n{HEADER}")
        simpy = Cost("simpy never | timeout", n, k, seed)
        ours = Cost("asyncio.timeout (sim loop)", n, k, seed)
        print(_row("asyncio.timeout (sim loop)", ours, simpy, "SimPy"))
        print(_row("simpy never | timeout", simpy, simpy, "itself"))
    if "scale" in parts:
        k, seed = args.big_sleeps, args.seed
        print(f"\nscale: clock.sleep, {k} sleeps per task (seed {seed})\n{HEADER}")
        small = Cost("clock.sleep", args.tasks, k, seed)
        big = Cost("clock.sleep", args.big, k, seed)
        print(_row(f"{args.tasks:,} sleepers", small, small, "itself"))
        print(_row(f"{args.big:,} sleepers", big, small, f"{args.tasks:,} sleepers"))
    if "kuka" in parts:
        steps = args.kuka_steps
        if steps % 6:
            raise SystemExit("--kuka-steps must be a multiple of 6 (a whole number of ns)")
        print(
            f"\nkuka: {steps} physics steps at 240 Hz, per step; throughput ratio = "
            "synchronous loop's cost / evclock's"
        )
        # "no watch": PyBulletTimeSource(watch_time_step=False), what the time-step watch
        # (one getPhysicsEngineParameters call per advance, on by default) costs.
        variants = ("kuka evclock", "kuka evclock, no time-step watch")
        print(
            f"  {'controller':<12}{'hash seed':>10}{'sync instr':>12}{'evclock':>12}{'ratio':>8}"
            f"{'no watch':>12}{'ratio':>8}"
        )
        for hz in (100.0, 240.0):
            ratios: dict[str, list[float]] = {name: [] for name in variants}
            for hash_seed in range(args.hash_seeds):
                sync = Cost("kuka sync", 1, steps, args.seed, hz, hash_seed, timed=False)
                row = f"  {hz:>7g} Hz  {hash_seed:>10}{sync.instr:>12,.0f}"
                for name in variants:
                    ev = Cost(name, 1, steps, args.seed, hz, hash_seed, timed=False)
                    if _output(sync.out, "state") != _output(ev.out, "state"):
                        raise SystemExit(f"KUKA at {hz:g} Hz ({name}): the final states differ")
                    ratios[name].append(sync.instr / ev.instr)
                    row += f"{ev.instr:>12,.0f}{ratios[name][-1]:>8.3f}"
                print(row + "   final states bit-identical")
            # Wall time once per variant, in plain runs (random string-hash seeds).
            wall_ratio = wall_ns("kuka sync", 1, steps, args.seed, hz) / wall_ns(
                "kuka evclock", 1, steps, args.seed, hz
            )
            means = [statistics.fmean(ratios[name]) for name in variants]
            print(
                f"  {hz:>7g} Hz  mean of {args.hash_seeds} seeds: {means[0]:.3f} (from "
                f"{min(ratios[variants[0]]):.3f} to {max(ratios[variants[0]]):.3f}), no watch "
                f"{means[1]:.3f}; wall time (evclock): {wall_ratio:.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
