"""evclock: simulation time for asyncio robot controllers.

An asyncio event loop whose ``time()`` is the simulator's clock: ``asyncio.sleep``,
timeouts and anyio all follow sim time, time advances only when every task waits, and the
same controller code runs unchanged on wall time on the real robot.
"""

from typing import TYPE_CHECKING, Any

from ._clock import Clock, SimClock, WallClock, clock, sim_clock
from ._config import ENV_USE_SIM_TIME
from ._diagnostics import StampDiagnostics, StampWarning, StreamAgeStats, diagnostics_report
from ._config import ENV_CLOCK, ENV_USE_SIM_TIME, register_clock_scheme
from ._driver import SimDriver
from ._errors import (
    ClockJumped,
    ClockLost,
    ClockMismatchError,
    DeadlockError,
    EvClockError,
    ExtrapolationError,
    InvalidArgumentError,
    InvalidTypeError,
    JoinRefused,
    LagError,
    LoopClosedError,
    MissingExtraError,
    NoSimulationError,
    NotRunningError,
    PacingError,
    ParticipantLost,
    PhysicsError,
    ScenarioError,
    ProtocolError,
    RemoteCallError,
    RemoteClockError,
    SimDriverError,
    SimTimeLimitError,
    StallError,
    TimeLookupError,
    TraceError,
)
from ._jumps import JumpHandle, JumpThreshold, TimeJump
from ._loop import SimEventLoop
from ._plot import plot_run, plot_sweep
from ._rate import LoopStats, Rate, Tick, Timer
from ._record import record
from ._remote._participant import RemoteClockSource, participant
from ._remote._server import ClockServer, Message, serve
from ._runner import loop_factory, resolve_use_sim_time, run
from ._stamped import StampClock, Stamped, StampKey, stamp_of
from ._sync import ApproximateTimeSynchronizer, TimeSynchronizer
from ._runs import LoopReport, RunReport, run_scenario
from ._scenarios import ENTRY_POINT_GROUP, load_scenario, parameters
from ._sweep import RunSpec, SweepResult, SweepRow, plan, sweep
from ._time import SIM, STEADY, SYSTEM, ClockType, Duration, DurationMsg, Time, TimeMsg
from ._trace import Divergence, Trace, TraceMessage, first_divergence, read_trace
from .sources import PyBulletTimeSource, StepHook, TimeSource, VirtualTimeSource

if TYPE_CHECKING:
    from ._buffer import Interpolation, TimeBuffer

__version__ = "0.1.0"

__all__ = [
    "ENTRY_POINT_GROUP",
    "Divergence",
    "LoopReport",
    "MissingExtraError",
    "RunReport",
    "RunSpec",
    "ScenarioError",
    "SweepResult",
    "SweepRow",
    "Trace",
    "TraceError",
    "TraceMessage",
    "first_divergence",
    "load_scenario",
    "parameters",
    "plan",
    "plot_run",
    "plot_sweep",
    "read_trace",
    "record",
    "run_scenario",
    "sweep",
    "ENV_CLOCK",
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
    "ApproximateTimeSynchronizer",
    "ExtrapolationError",
    "Interpolation",
    "StampClock",
    "StampDiagnostics",
    "StampKey",
    "StampWarning",
    "Stamped",
    "StreamAgeStats",
    "TimeBuffer",
    "TimeLookupError",
    "TimeSynchronizer",
    "diagnostics_report",
    "stamp_of",
    "__version__",
    "clock",
    "loop_factory",
    "resolve_use_sim_time",
    "run",
    "sim_clock",
    # sim time across processes
    "ClockLost",
    "ClockServer",
    "JoinRefused",
    "Message",
    "ParticipantLost",
    "ProtocolError",
    "RemoteCallError",
    "RemoteClockError",
    "RemoteClockSource",
    "participant",
    "register_clock_scheme",
    "serve",
]


def __getattr__(name: str) -> Any:
    # TimeBuffer needs numpy: it is imported on first use, so `import evclock` stays light.
    if name in ("Interpolation", "TimeBuffer"):
        from . import _buffer

        return getattr(_buffer, name)
    raise AttributeError(f"module 'evclock' has no attribute {name!r}")
# Errors show their public name in tracebacks and reprs (evclock.InvalidArgumentError, not
# evclock._errors.InvalidArgumentError); they pickle by that name too.
for _name in __all__:
    _value = globals().get(_name)
    if isinstance(_value, type) and issubclass(_value, EvClockError):
        _value.__module__ = __name__
del _name, _value
