"""evclock: simulation time for asyncio robot controllers.

An asyncio event loop whose ``time()`` is the simulator's clock: ``asyncio.sleep``,
timeouts and anyio all follow sim time, time advances only when every task waits, and the
same controller code runs unchanged on wall time on the real robot.
"""

from ._clock import Clock, SimClock, WallClock, clock, sim_clock
from ._config import ENV_USE_SIM_TIME
from ._driver import SimDriver
from ._errors import (
    ClockJumped,
    ClockMismatchError,
    DeadlockError,
    EvClockError,
    InvalidArgumentError,
    InvalidTypeError,
    LagError,
    LoopClosedError,
    MissingExtraError,
    NoSimulationError,
    NotRunningError,
    PacingError,
    PhysicsError,
    SimDriverError,
    SimTimeLimitError,
    StallError,
)
from ._jumps import JumpHandle, JumpThreshold, TimeJump
from ._loop import SimEventLoop
from ._rate import LoopStats, Rate, Tick, Timer
from ._runner import loop_factory, resolve_use_sim_time, run
from ._time import SIM, STEADY, SYSTEM, ClockType, Duration, DurationMsg, Time, TimeMsg
from .sources import PyBulletTimeSource, StepHook, TimeSource, VirtualTimeSource

__version__ = "0.1.0"

__all__ = [
    "ENV_USE_SIM_TIME",
    "SIM",
    "STEADY",
    "SYSTEM",
    "Clock",
    "ClockJumped",
    "ClockMismatchError",
    "ClockType",
    "DeadlockError",
    "Duration",
    "DurationMsg",
    "EvClockError",
    "InvalidArgumentError",
    "InvalidTypeError",
    "JumpHandle",
    "JumpThreshold",
    "LagError",
    "LoopClosedError",
    "LoopStats",
    "MissingExtraError",
    "NoSimulationError",
    "NotRunningError",
    "PacingError",
    "PhysicsError",
    "PyBulletTimeSource",
    "Rate",
    "SimClock",
    "SimDriver",
    "SimDriverError",
    "SimEventLoop",
    "SimTimeLimitError",
    "StallError",
    "StepHook",
    "Tick",
    "Time",
    "TimeJump",
    "TimeMsg",
    "TimeSource",
    "Timer",
    "VirtualTimeSource",
    "WallClock",
    "__version__",
    "clock",
    "loop_factory",
    "resolve_use_sim_time",
    "run",
    "sim_clock",
]
