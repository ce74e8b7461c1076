"""Launching: ``evclock.run()``, loop factories, and the once-per-launch ``use_sim_time``."""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from evclock._errors import InvalidArgumentError, InvalidTypeError, SimTimeLimitError
from evclock.hosts._config import (
    ENV_CLOCK,
    ENV_USE_SIM_TIME,
    clock_source,
    env_clock,
    env_use_sim_time,
)
from evclock.hosts._current import attach_clock
from evclock.hosts._loop import DEFAULT_STALL_TIMEOUT, SimEventLoop, check_stall_timeout
from evclock.kernel._clock import WallClock
from evclock.kernel._pacing import DEFAULT_MAX_LAG, check_max_lag, check_rtf
from evclock.kernel._source import TimeSource
from evclock.kernel._virtual import VirtualTimeSource
from evclock.time._time import STEADY, SYSTEM, ClockType, Duration, Time, to_sim_time_ns

_T = TypeVar("_T")


def resolve_use_sim_time(use_sim_time: bool | None = None, *, default: bool = True) -> bool:
    """Decide sim or wall time once, at launch: the argument, else the environment, else
    ``default``.

    :param use_sim_time: True or False decides; None defers to ``EVCLOCK_USE_SIM_TIME``.
    :param default: the answer when both the argument and the environment are unset.
    :returns: True for sim time, False for wall time.
    :raises InvalidTypeError: ``use_sim_time`` is not a bool or None.
    :raises InvalidArgumentError: ``EVCLOCK_USE_SIM_TIME`` holds an unrecognised value.
    """
    if use_sim_time is not None:
        if not isinstance(use_sim_time, bool):
            raise InvalidTypeError(
                f"use_sim_time must be True, False or None, got {type(use_sim_time).__name__}"
            )
        return use_sim_time
    from_env = env_use_sim_time()
    return default if from_env is None else from_env


def _start_ns(start: float | Time | Duration) -> int:
    return to_sim_time_ns(start, "start")


RTF_MAX = "max"
"""``rtf="max"``: as fast as possible, the same as ``rtf=None`` (and the CLI's ``--rtf max``)."""


def _rtf(rtf: float | str | None) -> float | None:
    """``"max"`` -> None (as fast as possible); anything else is validated by the loop."""
    if isinstance(rtf, str):
        if rtf.strip().lower() == RTF_MAX:
            return None
        raise InvalidArgumentError(
            f"rtf takes 'max' or None (as fast as possible) or a positive number, got {rtf!r}"
        )
    return rtf


def _check_remote_options(where: str, url: str, *, rtf: float | None, paused: bool) -> None:
    if rtf is not None or paused:
        raise InvalidArgumentError(
            f"{where}{url!r} joins a simulation served by another process: pacing (rtf, "
            "paused) belongs to that simulation; drop rtf/paused here"
        )


def loop_factory(
    *,
    source: Callable[[], TimeSource] | None = None,
    start: float | Time = 0,
    rtf: float | str | None = None,
    strict: bool = False,
    max_lag: float = DEFAULT_MAX_LAG,
    stall_timeout: float | None = DEFAULT_STALL_TIMEOUT,
    paused: bool = False,
    watch_threads: bool = True,
    clock: str | None = None,
) -> Callable[[], SimEventLoop]:
    """A zero-argument factory of fresh :class:`SimEventLoop` objects, for
    ``asyncio.Runner(loop_factory=...)``, pytest-asyncio or anyio.

    ``source`` is a factory too (each loop needs its own time source); by default each loop
    gets a :class:`VirtualTimeSource` starting at ``start`` seconds. ``clock`` (a URL such
    as ``unix:///tmp/sim.sock``) makes each loop join that clock server instead (see
    :func:`run`); unlike :func:`run`, a loop factory does not read ``EVCLOCK_CLOCK``.
    The other options are passed to every :class:`SimEventLoop` the factory makes; they
    are validated once, here.

    :param source: a zero-argument callable returning a new time source for each loop.
    :param start: sim seconds (or a Time) where the default virtual time starts.
    :param rtf: real-time factor: None or ``"max"`` = as fast as possible, 1.0 = real time.
    :param strict: raise :class:`LagError` when lagging more than ``max_lag`` behind ``rtf``.
    :param max_lag: wall seconds a paced run may fall behind before re-anchoring (or raising).
    :param stall_timeout: wall seconds sim time may be held by outside work or I/O waits
        before :class:`StallError`; None waits forever.
    :param paused: start each loop paused.
    :param watch_threads: hold sim time while other non-daemon threads are busy (default).
    :param clock: a clock-server URL each loop joins instead of using ``source``.
    :returns: a callable taking no arguments and returning a new :class:`SimEventLoop`.
    :raises InvalidArgumentError: both ``source`` and ``clock``; ``start`` with a custom
        source or clock; ``rtf``/``paused`` with ``clock``; an out-of-range ``rtf``,
        ``max_lag`` or ``stall_timeout``; an unsupported clock URL (when a loop is made).
    :raises InvalidTypeError: ``source`` is not callable, or an option has the wrong type.

    Example::

        with asyncio.Runner(loop_factory=evclock.loop_factory(rtf=1.0)) as runner:
            runner.run(main())
    """
    rtf = _rtf(rtf)
    if clock is not None:
        if source is not None:
            raise InvalidArgumentError(
                "loop_factory() takes a source or a clock URL, not both; drop one"
            )
        url = clock
        _check_remote_options("clock=", url, rtf=rtf, paused=paused)

        def remote_source() -> TimeSource:
            return clock_source(url)

        source = remote_source
    if source is not None and not callable(source):
        raise InvalidTypeError(
            "loop_factory(source=...) takes a callable that returns a new TimeSource "
            f"(e.g. lambda: PyBulletTimeSource(client)), got {type(source).__name__}"
        )
    start_ns = _start_ns(start)
    if source is not None and start_ns:
        raise InvalidArgumentError(
            "start= applies to virtual time only; a custom source sets its own time"
        )
    make_source = source or functools.partial(VirtualTimeSource, start_ns)
    # Validate the options once, now, rather than at the first loop creation.
    check_rtf(rtf)
    check_max_lag(max_lag)
    check_stall_timeout(stall_timeout)

    def new_loop() -> SimEventLoop:
        return SimEventLoop(
            make_source(),
            rtf=rtf,
            strict=strict,
            max_lag=max_lag,
            stall_timeout=stall_timeout,
            paused=paused,
            watch_threads=watch_threads,
        )

    return new_loop


async def _limited(main: Coroutine[Any, Any, _T], until_ns: int) -> _T:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    assert isinstance(loop, SimEventLoop)
    expired = False

    def expire() -> None:
        nonlocal expired
        expired = True
        task.cancel("evclock: the until limit was reached")

    handle = loop.call_at_ns(until_ns, expire)
    try:
        return await main
    except asyncio.CancelledError:
        if expired:
            raise SimTimeLimitError(
                f"the program was still running at the until limit ({until_ns / 1e9:g} s of "
                "sim time) and was cancelled; raise until= or let the program finish sooner"
            ) from None
        raise
    finally:
        handle.cancel()


def run(
    main: Coroutine[Any, Any, _T],
    *,
    use_sim_time: bool | None = None,
    source: TimeSource | None = None,
    start: float | Time = 0,
    until: float | Time | None = None,
    rtf: float | str | None = None,
    strict: bool = False,
    max_lag: float = DEFAULT_MAX_LAG,
    stall_timeout: float | None = DEFAULT_STALL_TIMEOUT,
    paused: bool = False,
    wall_clock: ClockType = STEADY,
    debug: bool | None = None,
    clock: str | None = None,
) -> _T:
    """Run ``main`` to completion, like :func:`asyncio.run`, on sim or wall time.

    ``use_sim_time`` is decided here, once: the argument, else ``EVCLOCK_USE_SIM_TIME``,
    else True. On sim time ``main`` runs on a :class:`SimEventLoop` driven by ``source``
    (default: virtual time from ``start``); ``until`` (sim seconds or a Time) cancels a
    program still running then and raises :class:`SimTimeLimitError`. On wall time it runs
    on a standard asyncio loop and :func:`evclock.clock` returns the ``wall_clock`` clock.

    ``clock`` (else ``EVCLOCK_CLOCK``) joins the sim time of a simulation in another process:
    ``unix:///tmp/sim.sock`` or ``tcp://127.0.0.1:PORT``, with ``?mode=lockstep`` (default)
    or ``follow``, ``name=``, ``token=`` and ``timeout=`` (wall seconds) options; other
    schemes come from :func:`evclock.register_clock_scheme`. It excludes ``source``,
    ``start``, pacing and wall time: a conflicting combination is an error, not a guess.

    :param main: the coroutine object to run (``main()``, not ``main``).
    :param use_sim_time: True/False, or None to read ``EVCLOCK_USE_SIM_TIME`` (default True).
    :param source: the :class:`~evclock.sources.TimeSource` driving sim time.
    :param start: sim seconds (or a Time) where the default virtual time starts.
    :param until: sim seconds (or a Time) after which a still running ``main`` is cancelled.
    :param rtf: real-time factor: None or ``"max"`` = as fast as possible, 1.0 = real time.
    :param strict: raise :class:`LagError` when lagging more than ``max_lag`` behind ``rtf``.
    :param max_lag: wall seconds a paced run may fall behind before re-anchoring (or raising).
    :param stall_timeout: wall seconds sim time may be held by outside work or I/O waits
        before :class:`StallError`; None waits forever.
    :param paused: start paused (resume through ``clock().host``).
    :param wall_clock: ``STEADY`` or ``SYSTEM``: the clock used on wall time.
    :param debug: asyncio debug mode, as for :func:`asyncio.run` (None: the default).
    :param clock: a clock URL to join another process's simulation (else ``EVCLOCK_CLOCK``).
    :returns: what ``main`` returns.
    :raises InvalidTypeError: ``main`` is not a coroutine, ``source`` is not a TimeSource,
        ``clock`` is not a string, or an option has the wrong type.
    :raises InvalidArgumentError: conflicting options (a source or clock on wall time,
        ``start`` with a source or clock, pacing with a clock), an out-of-range option,
        an ``until`` not after the start, or an unsupported clock URL.
    :raises SimTimeLimitError: ``main`` was still running at ``until``.
    :raises RemoteClockError: joining or keeping the clock server failed (``clock=``).

    Example::

        async def main() -> None:
            await evclock.clock().sleep(2.0)

        evclock.run(main(), rtf=None)  # two sim seconds, as fast as possible
    """
    if not asyncio.iscoroutine(main):
        raise InvalidTypeError(
            f"run() needs a coroutine object such as main(), got {type(main).__name__}"
            + ("; call the function: run(main())" if callable(main) else "")
        )
    url: str | None = None
    try:
        if clock is not None and not isinstance(clock, str):
            raise InvalidTypeError(
                f"clock must be a URL string such as 'unix:///tmp/sim.sock', got "
                f"{type(clock).__name__}"
            )
        url = clock if clock is not None else env_clock()
        where = "clock=" if clock is not None else f"{ENV_CLOCK}="
        sim = resolve_use_sim_time(use_sim_time)
        if url is not None and not sim:
            raise InvalidArgumentError(
                f"{where}{url!r} asks for a simulation's sim time but use_sim_time resolved "
                f"to False (argument or {ENV_USE_SIM_TIME}); choose one"
            )
        if wall_clock not in (STEADY, SYSTEM):
            raise InvalidArgumentError(f"wall_clock must be STEADY or SYSTEM, got {wall_clock!r}")
        if not sim:
            if source is not None:
                raise InvalidArgumentError(
                    "a time source was given but use_sim_time resolved to False (argument or "
                    f"{ENV_USE_SIM_TIME}); drop the source or enable sim time"
                )
            wall = WallClock(wall_clock)

            def wall_loop() -> asyncio.AbstractEventLoop:
                # The launch decision is recorded on the loop, so it wins over the environment.
                loop = asyncio.new_event_loop()
                attach_clock(loop, wall)
                return loop

            with asyncio.Runner(debug=debug, loop_factory=wall_loop) as runner:
                return runner.run(main)
        if source is not None and not isinstance(source, TimeSource):
            raise InvalidTypeError(f"source must be a TimeSource, got {type(source).__name__}")
        start_ns = _start_ns(start)
        rtf = _rtf(rtf)
        if url is not None:
            if source is not None or start_ns:
                raise InvalidArgumentError(
                    f"{where}{url!r} joins a simulation in another process, which owns sim "
                    "time; drop source=/start= (or unset the clock)"
                )
            _check_remote_options(where, url, rtf=rtf, paused=paused)
            source = clock_source(url)
        if source is None:
            source = VirtualTimeSource(start_ns)
        elif start_ns:
            raise InvalidArgumentError(
                "start= applies to virtual time only; the source sets its own time"
            )
        loop = SimEventLoop(
            source,
            rtf=rtf,
            strict=strict,
            max_lag=max_lag,
            stall_timeout=stall_timeout,
            paused=paused,
        )
    except BaseException:
        main.close()
        if url is not None and source is not None:
            source.close()  # the connection to the clock server, if it was opened
        raise
    coro: Coroutine[Any, Any, _T] = main
    if until is not None:
        until_ns = _start_ns(until)
        if until_ns <= loop.now_ns:
            main.close()
            loop.close()
            raise InvalidArgumentError(
                f"until={until!r} is not after the start of sim time "
                f"({loop.now_ns / 1e9:g} s); give a later sim time"
            )
        coro = _limited(main, until_ns)
    with asyncio.Runner(debug=debug, loop_factory=lambda: loop) as runner:
        return runner.run(coro)
