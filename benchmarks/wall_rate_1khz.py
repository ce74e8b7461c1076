"""Wall-time precision benchmark: a 1 kHz rate loop on evclock's WallClock vs plain asyncio.

Two variants, measured in the same run, on the same kind of loop (``evclock.run(main(),
use_sim_time=False)``: a standard asyncio loop, or uvloop with ``--loop uvloop``):

* ``evclock``        ``async for tick in clock.rate(1000)`` on a :class:`evclock.WallClock`
  (by default the one ``evclock.clock()`` returns, i.e. the default configuration)
* ``asyncio.sleep``  the baseline: the same drift-free deadlines (``start + i * period`` in
  integer nanoseconds, late deadlines skipped like the rate's ``"skip"`` policy), waiting
  with ``await asyncio.sleep(deadline - now)``

The loop bodies are empty. The run is split into ``--rounds`` rounds that alternate the
variants (so a change of machine load hits both alike), each in a fresh loop; every
variant runs ``--seconds`` in total. Reported per variant, tick 0 excluded:

* lateness (time the waiter resumed minus its deadline) p50 / p99 / p99.9 / max, in us;
* missed ticks (deadlines that got no tick because the previous one was too late);
* CPU time (``time.process_time``) per wall second, in percent of one core.

Then ``PASS`` or ``MISS`` against the goal: evclock's p99 lateness <= 100 us. The exit status
is 0 either way (this is a measurement, not a test). Figures depend on the machine and its
load: run it on an idle machine.

Options to evaluate the alternatives: ``--spin-margin US`` (wake that early and yield-spin
the rest), ``--timer-slack NS`` (lower the thread's timer slack while waiting),
``--no-timerfd`` (force the fallback: the loop's own timer), ``--imprecise``
(``WallClock(precise=False)``), ``--json PATH`` (write the figures).

Run: ``python benchmarks/wall_rate_1khz.py [--seconds 5 --hz 1000 --loop asyncio]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import sys
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import evclock
from evclock.kernel import _precise

GOAL_P99_US = 100.0


@dataclass
class Result:
    """Lateness samples and costs of one variant, accumulated over the rounds."""

    name: str
    lateness_ns: list[int] = field(default_factory=list)
    missed: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0

    def percentile_us(self, q: float) -> float:
        """Nearest-rank percentile ``q`` of the lateness, in microseconds."""
        data = sorted(self.lateness_ns)
        if not data:
            return math.nan
        rank = max(math.ceil(q / 100 * len(data)) - 1, 0)
        return data[rank] / 1e3

    def summary(self) -> dict[str, float | int | str]:
        """The reported figures as plain numbers."""
        return {
            "variant": self.name,
            "ticks": len(self.lateness_ns),
            "p50_us": self.percentile_us(50),
            "p99_us": self.percentile_us(99),
            "p99.9_us": self.percentile_us(99.9),
            "max_us": max(self.lateness_ns, default=0) / 1e3,
            "missed": self.missed,
            "cpu_percent": 100 * self.cpu_s / self.wall_s if self.wall_s else math.nan,
        }


async def evclock_loop(
    result: Result, hz: float, seconds: float, make_clock: Callable[[], evclock.Clock]
) -> None:
    """The rate loop under test: ``async for tick in clock.rate(hz)``."""
    clock = make_clock()
    ticks = round(seconds * hz)
    cpu0, wall0 = time.process_time(), time.monotonic()
    rate = clock.rate(hz)
    async for tick in rate:
        if tick.index:
            result.lateness_ns.append(tick.lateness.nanoseconds)
            result.missed += tick.missed
        if tick.index >= ticks:
            break
    result.cpu_s += time.process_time() - cpu0
    result.wall_s += time.monotonic() - wall0


async def asyncio_loop(result: Result, hz: float, seconds: float) -> None:
    """The baseline: drift-free deadlines, plain ``asyncio.sleep`` waits, "skip" policy.

    Deadline ``i`` is ``start + i * period`` in exact integer nanoseconds, as in
    :class:`evclock.Rate`.
    """
    period = Fraction(10**9) / Fraction(hz)
    num, den = period.numerator, period.denominator
    ticks = round(seconds * hz)
    cpu0, wall0 = time.process_time(), time.monotonic()
    start = time.monotonic_ns()  # the clock of loop.time()
    index = 0
    while index < ticks:
        index += 1
        deadline = start + index * num // den
        now = time.monotonic_ns()
        if now < deadline:
            await asyncio.sleep((deadline - now) / 1e9)
            now = time.monotonic_ns()
        else:  # late: deliver the latest passed deadline, skip the others
            passed = (now - start) * den // num
            result.missed += passed - index
            index = passed
            deadline = start + index * num // den
        result.lateness_ns.append(now - deadline)
    result.cpu_s += time.process_time() - cpu0
    result.wall_s += time.monotonic() - wall0


def run_on_loop(coro: Coroutine[Any, Any, None], loop_kind: str) -> None:
    """Run ``coro`` on wall time, on the default asyncio loop or on uvloop."""
    if loop_kind == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            runner.run(coro)
    else:
        evclock.run(coro, use_sim_time=False)


def make_clock_factory(args: argparse.Namespace) -> Callable[[], evclock.Clock]:
    """``evclock.clock()`` by default, else a WallClock configured from the options."""
    custom = args.spin_margin is not None or args.timer_slack is not None or args.imprecise
    if not custom:
        return evclock.clock
    kwargs: dict[str, Any] = {"precise": not args.imprecise}
    if args.spin_margin is not None:
        kwargs["spin_margin"] = args.spin_margin / 1e6
    if args.timer_slack is not None:
        kwargs["timer_slack"] = args.timer_slack / 1e9
    return lambda: evclock.WallClock(evclock.STEADY, **kwargs)


def describe(args: argparse.Namespace) -> str:
    """One line naming the evclock configuration measured."""
    parts = ["precise=False"] if args.imprecise else ["precise=True"]
    parts.append(
        f"spin_margin={args.spin_margin:g}us"
        if args.spin_margin is not None
        else f"spin_margin={_precise.DEFAULT_SPIN_MARGIN_NS / 1e3:g}us (default)"
    )
    if args.timer_slack is not None:
        parts.append(f"timer_slack={args.timer_slack}ns")
    if args.no_timerfd:
        parts.append("timerfd disabled")
    elif _precise._libc is None:
        parts.append("no timerfd on this platform")
    return "WallClock(" + ", ".join(parts) + ")"


def busy_cpu_s() -> float | None:
    """CPU seconds all processes spent busy since boot (``/proc/stat``), None off Linux."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            fields = [int(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def other_load(busy0: float | None, cpu0: float, wall0: float) -> str:
    """CPU used by other processes during the run, in cores (the machine should be idle)."""
    busy1 = busy_cpu_s()
    if busy0 is None or busy1 is None:
        return "n/a"
    others = (busy1 - busy0) - (time.process_time() - cpu0)
    return f"{max(others, 0.0) / (time.monotonic() - wall0):.2f} of {os.cpu_count()} cores"


def _no_timerfd(clockid: int) -> int:
    raise OSError("timerfd disabled by --no-timerfd")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="per variant (default 5)")
    parser.add_argument("--hz", type=float, default=1000.0, help="rate (default 1000)")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    parser.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    parser.add_argument("--spin-margin", type=float, metavar="US", help="WallClock spin_margin")
    parser.add_argument("--timer-slack", type=int, metavar="NS", help="WallClock timer_slack")
    parser.add_argument("--no-timerfd", action="store_true", help="force the fallback path")
    parser.add_argument("--imprecise", action="store_true", help="WallClock(precise=False)")
    parser.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = parser.parse_args(argv)
    if args.seconds <= 0 or args.hz <= 0 or args.rounds < 1:
        parser.error("--seconds and --hz must be positive, --rounds at least 1")
    if args.no_timerfd:
        _precise._timerfd_create = _no_timerfd

    busy0, cpu0, wall0 = busy_cpu_s(), time.process_time(), time.monotonic()
    make_clock = make_clock_factory(args)
    ours, base = Result("evclock"), Result("asyncio.sleep")
    per_round = args.seconds / args.rounds
    for i in range(args.rounds):
        first_base = i % 2 == 1
        order = ("base", "ours") if first_base else ("ours", "base")
        for which in order:
            if which == "ours":
                run_on_loop(evclock_loop(ours, args.hz, per_round, make_clock), args.loop)
            else:
                run_on_loop(asyncio_loop(base, args.hz, per_round), args.loop)

    load = other_load(busy0, cpu0, wall0)
    print(
        f"{args.hz:g} Hz rate loop, {args.seconds:g} s per variant in {args.rounds} alternating "
        f"rounds, loop={args.loop}, Python {sys.version.split()[0]}, {sys.platform}, "
        f"other processes' CPU load {load}"
    )
    print(f"evclock: {describe(args)}")
    header = f"{'variant':<14} {'ticks':>6} {'p50 us':>8} {'p99 us':>8} {'p99.9 us':>9}"
    print(header + f" {'max us':>9} {'missed':>6} {'CPU %':>6}")
    rows = [ours.summary(), base.summary()]
    for row in rows:
        print(
            f"{row['variant']:<14} {row['ticks']:>6} {row['p50_us']:>8.1f} {row['p99_us']:>8.1f} "
            f"{row['p99.9_us']:>9.1f} {row['max_us']:>9.1f} {row['missed']:>6} "
            f"{row['cpu_percent']:>6.1f}"
        )
    p99 = float(rows[0]["p99_us"])
    verdict = "PASS" if p99 <= GOAL_P99_US else "MISS"
    print(f"{verdict}: evclock p99 lateness {p99:.1f} us (goal <= {GOAL_P99_US:g} us)")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"config": describe(args), "other_load": load, "results": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
