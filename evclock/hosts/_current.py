"""The current clock: which clock the running loop's tasks read (``evclock.clock()``).

A :class:`~evclock.SimEventLoop` answers with its own sim clock; a loop evclock does not own
answers with the clock attached to it (a ``SimDriver``'s sim clock, or a wall clock made on
first use).
"""

from __future__ import annotations

import asyncio
import weakref

from evclock._errors import NoSimulationError, NotRunningError
from evclock.hosts._config import env_use_sim_time
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._clock import Clock, SimClock, WallClock
from evclock.time._time import STEADY

#: Clocks attached to loops evclock does not own (wall clocks, embedded sim drivers).
_attached: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Clock] = weakref.WeakKeyDictionary()


def attach_clock(loop: asyncio.AbstractEventLoop, clock: Clock) -> None:
    """Make ``clock`` what :func:`clock` returns on ``loop`` (used by embedding drivers)."""
    _attached[loop] = clock


def attached_clock(loop: asyncio.AbstractEventLoop) -> Clock | None:
    """The clock :func:`attach_clock` attached to ``loop``, if any."""
    return _attached.get(loop)


def detach_clock(loop: asyncio.AbstractEventLoop) -> None:
    """Undo :func:`attach_clock`."""
    _attached.pop(loop, None)


def _running_loop(what: str) -> asyncio.AbstractEventLoop:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        raise NotRunningError(
            f"{what} must be called from a coroutine or callback running on an event loop "
            "(start one with evclock.run(main()))"
        ) from None


def clock() -> Clock:
    """The clock of the running loop: sim time on a simulation loop, wall time elsewhere.

    Controller code calls this and never needs to know which one it got. On a loop without
    a simulation while ``EVCLOCK_USE_SIM_TIME`` asks for sim time, it raises
    :class:`NoSimulationError` instead of silently running on wall time.

    :returns: the running loop's :class:`SimClock`, or a :class:`WallClock`.
    :raises NoSimulationError: sim time is asked for but the loop has no simulation.
    """
    loop = _running_loop("evclock.clock()")
    if isinstance(loop, SimEventLoop):
        return loop.clock
    found = _attached.get(loop)
    if found is not None:
        return found
    if env_use_sim_time():
        raise NoSimulationError(
            "EVCLOCK_USE_SIM_TIME asks for sim time but this loop has no simulation; "
            "start the program with evclock.run() (or attach a driver), or unset "
            "EVCLOCK_USE_SIM_TIME to run on wall time"
        )
    wall = WallClock(STEADY)
    _attached[loop] = wall
    return wall


def sim_clock() -> SimClock:
    """The sim clock of the running loop; :class:`NoSimulationError` if there is none.

    :returns: the running loop's :class:`SimClock`.
    :raises NoSimulationError: the running loop has no simulation.
    """
    loop = _running_loop_or_none()
    if isinstance(loop, SimEventLoop):
        return loop.clock
    found = _attached.get(loop) if loop is not None else None
    if isinstance(found, SimClock):
        return found
    raise NoSimulationError(
        "sim time was asked for but no simulation loop is running; run the program with "
        "evclock.run(main()) or asyncio.Runner(loop_factory=evclock.loop_factory())"
    )


def _running_loop_or_none() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None
