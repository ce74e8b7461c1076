"""Bad input gets a precise evclock error that says how to fix it (messages asserted)."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Callable
from typing import Any

import pytest

import evclock
from evclock import Duration, Time


def on_sim(fn: Callable[[evclock.Clock], object]) -> None:
    async def main() -> None:
        fn(evclock.clock())

    evclock.run(main())


def raises_exactly(error: type[Exception], message: str) -> Any:
    return pytest.raises(error, match="^" + re.escape(message) + "$")


@pytest.mark.parametrize(
    ("duration", "error", "message"),
    [
        (
            -1.0,
            evclock.InvalidArgumentError,
            "sleep duration must not be negative, got -1.0; "
            "a negative sleep is a bug in the caller; to wait until a time use sleep_until()",
        ),
        (
            Duration(seconds=-2),
            evclock.InvalidArgumentError,
            "sleep duration must not be negative, "
            "got Duration(nanoseconds=-2000000000); a negative sleep is a bug in the caller; "
            "to wait until a time use sleep_until()",
        ),
        (float("nan"), evclock.InvalidArgumentError, "sleep duration must be a number, got NaN"),
        (float("inf"), evclock.InvalidArgumentError, "sleep duration must be finite, got inf"),
        (
            "1",
            evclock.InvalidTypeError,
            "sleep duration must be seconds (int or float) or a Duration, got str",
        ),
        (
            True,
            evclock.InvalidTypeError,
            "sleep duration must be seconds (int or float) or a Duration, got bool",
        ),
        (
            None,
            evclock.InvalidTypeError,
            "sleep duration must be seconds (int or float) or a Duration, got NoneType",
        ),
    ],
)
@pytest.mark.parametrize("sim", [True, False], ids=["sim", "wall"])
def test_bad_sleep_durations(
    duration: object, error: type[Exception], message: str, sim: bool
) -> None:
    async def main() -> None:
        await evclock.clock().sleep(duration)  # type: ignore[arg-type]

    with raises_exactly(error, message):
        evclock.run(main(), use_sim_time=sim)


def test_sleep_until_needs_a_time_of_the_same_clock() -> None:
    def check(clock: evclock.Clock) -> None:
        with raises_exactly(
            evclock.InvalidTypeError,
            "sleep_until() needs a Time (e.g. clock.now() + Duration(seconds=1)), got float",
        ):
            clock.sleep_until(1.0)  # type: ignore[arg-type]
        with raises_exactly(
            evclock.ClockMismatchError,
            "sleep_until() got a system time but this is a sim clock; compute deadlines from "
            "this clock's now()",
        ):
            clock.sleep_until(Time(seconds=1, clock_type=evclock.SYSTEM))

    on_sim(check)


def test_every_error_is_an_evclock_error() -> None:
    for name in evclock.__all__:
        obj = getattr(evclock, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, evclock.EvClockError), name
    # ...and keeps its classic category.
    assert issubclass(evclock.InvalidArgumentError, ValueError)
    assert issubclass(evclock.InvalidTypeError, TypeError)
    assert issubclass(evclock.LoopClosedError, RuntimeError)


def test_sim_clock_without_a_simulation_loop() -> None:
    message = (
        "sim time was asked for but no simulation loop is running; run the program with "
        "evclock.run(main()) or asyncio.Runner(loop_factory=evclock.loop_factory())"
    )
    with raises_exactly(evclock.NoSimulationError, message):
        evclock.sim_clock()

    async def on_plain_asyncio() -> None:
        evclock.sim_clock()

    with raises_exactly(evclock.NoSimulationError, message):
        asyncio.run(on_plain_asyncio())


def test_clock_outside_any_loop() -> None:
    with raises_exactly(
        evclock.NotRunningError,
        "evclock.clock() must be called from a coroutine or callback running on an event loop "
        "(start one with evclock.run(main()))",
    ):
        evclock.clock()


def test_use_sim_time_without_a_simulation_fails_loudly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EVCLOCK_USE_SIM_TIME", "1")

    async def controller() -> None:
        evclock.clock()

    with raises_exactly(
        evclock.NoSimulationError,
        "EVCLOCK_USE_SIM_TIME asks for sim time but this loop has no simulation; start the "
        "program with evclock.run() (or attach a driver), or unset EVCLOCK_USE_SIM_TIME to run "
        "on wall time",
    ):
        asyncio.run(controller())


def test_bad_use_sim_time_values(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EVCLOCK_USE_SIM_TIME", "maybe")
    with raises_exactly(
        evclock.InvalidArgumentError,
        "EVCLOCK_USE_SIM_TIME must be one of 1/true/yes/on or 0/false/no/off, got 'maybe'",
    ):
        evclock.resolve_use_sim_time()
    with raises_exactly(
        evclock.InvalidTypeError, "use_sim_time must be True, False or None, got str"
    ):
        evclock.resolve_use_sim_time("yes")  # type: ignore[arg-type]


def test_closed_loop() -> None:
    loop = evclock.SimEventLoop()
    clock = loop.clock
    loop.close()
    message = (
        "this SimEventLoop is closed; create a new loop (evclock.run() and "
        "asyncio.Runner(loop_factory=evclock.loop_factory()) create one per run)"
    )
    coro = asyncio.sleep(1)
    with raises_exactly(evclock.LoopClosedError, message):
        loop.run_until_complete(coro)
    coro.close()
    with raises_exactly(evclock.LoopClosedError, message):
        clock.sleep(1)
    with raises_exactly(evclock.LoopClosedError, message):
        loop.call_later(1, print)


def test_run_needs_a_coroutine() -> None:
    async def main() -> None:
        pass

    with raises_exactly(
        evclock.InvalidTypeError,
        "run() needs a coroutine object such as main(), got function; "
        "call the function: run(main())",
    ):
        evclock.run(main)  # type: ignore[arg-type]


def test_until_in_the_past() -> None:
    async def main() -> None:
        pass

    with raises_exactly(
        evclock.InvalidArgumentError,
        "until=5 is not after the start of sim time (10 s); give a later sim time",
    ):
        evclock.run(main(), start=10, until=5)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        (
            {"rtf": 0},
            evclock.InvalidArgumentError,
            "rtf must be a positive finite real-time factor "
            "(1.0 = real time), got 0; use rtf=None to run as fast as possible",
        ),
        (
            {"rtf": "fast"},
            evclock.InvalidArgumentError,
            "rtf takes 'max' or None (as fast as possible) or a positive number, got 'fast'",
        ),
        (
            {"stall_timeout": -1},
            evclock.InvalidArgumentError,
            "stall_timeout must be a positive number of wall seconds or None, got -1",
        ),
        ({"start": -1.0}, evclock.InvalidArgumentError, "start must not be negative, got -1.0"),
    ],
)
def test_bad_run_options(kwargs: dict[str, Any], error: type[Exception], message: str) -> None:
    async def main() -> None:
        pass

    with raises_exactly(error, message):
        evclock.run(main(), **kwargs)
    with raises_exactly(error, message):
        evclock.loop_factory(**kwargs)


def test_pause_and_step_misuse() -> None:
    loop = evclock.SimEventLoop()
    with raises_exactly(
        evclock.NotRunningError,
        "pause() needs a running loop; call it from a task on the loop (or through "
        "loop.call_soon_threadsafe), or create the loop with paused=True to start paused",
    ):
        loop.pause()
    loop.close()

    async def main() -> None:
        running = asyncio.get_running_loop()
        assert isinstance(running, evclock.SimEventLoop)
        with raises_exactly(
            evclock.PacingError,
            "step() needs a paused loop, but it is running as fast as possible; call pause() "
            "first, then step",
        ):
            running.step()
        running.pause()
        with raises_exactly(evclock.InvalidArgumentError, "step() count must be >= 1, got 0"):
            running.step(0)
        with raises_exactly(
            evclock.InvalidArgumentError,
            "step_until() target 0.000000000 s (sim) is not after the current sim time "
            "0.000000000 s (sim)",
        ):
            running.step_until(Time())
        running.resume()

    evclock.run(main())
