"""Numbers and the range of sim time: one converter, [0, 2**63 - 1] ns, huge asyncio delays.

evclock's own APIs reject a time outside sim time's range with InvalidArgumentError;
asyncio-level calls with huge delays behave as on stock asyncio (the timer never fires).
numpy scalars and Fractions are accepted wherever Python numbers are.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
from fractions import Fraction

import anyio
import numpy as np
import pytest

import evclock
from evclock import Duration, InvalidArgumentError, SimEventLoop, Time
from evclock.sources import VirtualTimeSource

MAX_NS = 2**63 - 1
RANGE = f"outside sim time's range [0, {MAX_NS}] ns (64-bit nanoseconds, about 292 years)"


def exactly(message: str) -> str:
    return "^" + re.escape(message) + "$"


def test_evclock_waits_beyond_the_range_are_rejected() -> None:
    async def main() -> None:
        clock = evclock.clock()
        with pytest.raises(
            InvalidArgumentError,
            match=exactly(
                f"sleep duration would reach {10**19} ns, {RANGE}; use a shorter duration or an "
                "earlier time"
            ),
        ):
            clock.sleep(1e10)
        with pytest.raises(
            InvalidArgumentError,
            match=exactly(
                f"the wait would reach {2**62 + 5 * 10**18} ns, {RANGE}; use a shorter duration or "
                "an earlier time"
            ),
        ):
            clock.sleep(5e9)
        with pytest.raises(InvalidArgumentError, match=r"^sleep duration would reach 10{39} ns"):
            clock.sleep(10**30)
        with pytest.raises(
            InvalidArgumentError,
            match=exactly(
                f"timer period would reach {10**39} ns, {RANGE}; use a shorter duration or an "
                "earlier time"
            ),
        ):
            clock.timer(10**30, lambda: None)
        await clock.sleep(1)  # the loop is still fine

    evclock.run(main(), start=2**62 / 1e9)


def test_starts_beyond_the_range_are_rejected() -> None:
    with pytest.raises(
        InvalidArgumentError,
        match=exactly(
            f"start would reach {10**39} ns, {RANGE}; use a shorter duration or an earlier time"
        ),
    ):
        evclock.loop_factory(start=10**30)
    with pytest.raises(
        InvalidArgumentError,
        match=exactly(
            f"start_ns would reach {2**63} ns, {RANGE}; use a shorter duration or an earlier time"
        ),
    ):
        VirtualTimeSource(2**63)


def test_asyncio_level_huge_delays_never_fire_as_on_stock_asyncio() -> None:
    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        fired: list[str] = []
        loop.call_later(1e300, fired.append, "call_later")
        loop.call_at(1e18, fired.append, "call_at")
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asyncio.sleep(1e300), 1)
        async with asyncio.timeout(1e300):
            await asyncio.sleep(2)
        assert loop.time() == 3.0
        return fired

    assert evclock.run(main()) == []


def test_anyio_fail_after_a_huge_delay_is_no_limit() -> None:
    async def main() -> float:
        with anyio.fail_after(1e300):
            await anyio.sleep(1)
        return anyio.current_time()

    assert anyio.run(main, backend_options={"loop_factory": evclock.loop_factory()}) == 1.0


def test_numpy_scalars_and_fractions_are_numbers() -> None:
    async def main() -> list[int]:
        clock = evclock.clock()
        seen = []
        await clock.sleep(np.float64(0.5))
        seen.append(clock.now_ns())
        await clock.sleep(np.int64(2))
        seen.append(clock.now_ns())
        await clock.sleep(np.float32(0.25))
        seen.append(clock.now_ns())
        await clock.sleep(Fraction(1, 3))  # exact: 333333333.3 ns rounds to 333333333
        seen.append(clock.now_ns())
        ticks = []
        async for tick in clock.rate(np.int64(4)):
            ticks.append(tick.expected.nanoseconds - seen[-1])
            if tick.index == 2:
                break
        return seen + ticks

    assert evclock.run(main()) == [
        500_000_000,
        2_500_000_000,
        2_750_000_000,
        3_083_333_333,
        0,
        250_000_000,
        500_000_000,
    ]
    loop = SimEventLoop(VirtualTimeSource(np.int64(7)), rtf=np.float64(2.0), max_lag=np.int64(1))
    try:
        assert (loop.now_ns, loop.rtf) == (7, 2.0)
    finally:
        loop.close()
    assert Duration(seconds=Fraction(1, 3)).nanoseconds == 333_333_333


def test_a_rate_of_a_fraction_of_a_hertz() -> None:
    async def main() -> tuple[str, list[Time]]:
        rate = evclock.clock().rate(Fraction(1, 3))
        ticks = []
        async for tick in rate:
            ticks.append(tick.expected)
            if tick.index == 2:
                break
        return rate.name, ticks

    name, ticks = evclock.run(main())
    assert name == "rate-1/3Hz"
    assert ticks == [Time(seconds=0), Time(seconds=3), Time(seconds=6)]


def test_achieved_rtf_is_known_after_a_single_sleep() -> None:
    async def main() -> float | None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        await evclock.clock().sleep(10)
        return loop.achieved_rtf()

    achieved = evclock.run(main())
    assert achieved is not None
    assert achieved > 0


@pytest.mark.parametrize(
    "arguments", ["rtf=-1", "stall_timeout='x'", "max_lag=0", "source=VirtualTimeSource(), x=1"]
)
def test_a_rejected_loop_prints_nothing(arguments: str) -> None:
    code = (
        "import gc, evclock\n"
        "from evclock import SimEventLoop\nfrom evclock.sources import VirtualTimeSource\n"
        "try:\n"
        f"    SimEventLoop({arguments})\n"
        "except (evclock.EvClockError, TypeError) as exc:\n"
        "    print(type(exc).__name__)\n"
        "gc.collect()\n"
    )
    done = subprocess.run(
        [sys.executable, "-X", "dev", "-W", "always", "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert done.stderr == ""
    assert done.stdout in ("InvalidArgumentError\n", "InvalidTypeError\n", "TypeError\n")


def test_clock_sleep_goes_wherever_a_future_does() -> None:
    async def main() -> list[float]:
        clock = evclock.clock()
        loop = asyncio.get_running_loop()
        seen = []
        await asyncio.gather(clock.sleep(1), clock.sleep(2))
        seen.append(loop.time())
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(clock.sleep(10), 1)
        seen.append(loop.time())
        await asyncio.ensure_future(clock.sleep(1))
        seen.append(loop.time())

        async def pause() -> None:  # create_task takes coroutines: wrap it
            await clock.sleep(1)

        async with asyncio.TaskGroup() as group:
            group.create_task(pause())
        seen.append(loop.time())
        return seen

    assert evclock.run(main()) == [2.0, 3.0, 4.0, 5.0]
