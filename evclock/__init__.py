"""evclock: simulation time for asyncio robot controllers.

An asyncio event loop whose ``time()`` is the simulator's clock: ``asyncio.sleep``,
timeouts and anyio all follow sim time, time advances only when every task waits, and the
same controller code runs unchanged on wall time on the real robot.
"""

from typing import TYPE_CHECKING, Any

from ._clock import Clock, SimClock, WallClock, clock, sim_clock
from ._config import ENV_CLOCK, ENV_USE_SIM_TIME, register_clock_scheme
from ._diagnostics import StampDiagnostics, StampWarning, StreamAgeStats, diagnostics_report
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
    ProtocolError,
    RemoteCallError,
    RemoteClockError,
    Ros2MessageError,
    ScenarioError,
    SimDriverError,
    SimTimeLimitError,
    StallError,
    TimeLookupError,
    TraceError,
    WrongThreadError,
)
from ._jumps import JumpHandle, JumpThreshold, TimeJump
from ._loop import SimEventLoop
from ._plot import plot_run, plot_sweep
from ._rate import LoopStats, Rate, Tick, Timer
from ._record import record
from ._remote._participant import RemoteClockSource, participant
from ._remote._server import ClockServer, Message, serve
from ._runner import loop_factory, resolve_use_sim_time, run
from ._runs import LoopReport, RunReport, run_scenario
from ._scenarios import ENTRY_POINT_GROUP, load_scenario, parameters
from ._stamped import StampClock, Stamped, StampKey, stamp_of
from ._sweep import RunSpec, SweepResult, SweepRow, plan, sweep
from ._sync import ApproximateTimeSynchronizer, TimeSynchronizer
from ._time import SIM, STEADY, SYSTEM, ClockType, Duration, DurationMsg, Time, TimeMsg
from ._trace import Divergence, Trace, TraceMessage, first_divergence, read_trace
from .ros2 import Ros2ClockPublisher, Ros2ClockSource
from .sources import (
    PyBulletTimeSource,
    StepHook,
    SteppingTimeSource,
    TimeSource,
    VirtualTimeSource,
)

if TYPE_CHECKING:
    from ._buffer import Interpolation, TimeBuffer

    __version__: str

__all__ = [
    "ApproximateTimeSynchronizer",
    "Clock",
    "ClockJumped",
    "ClockLost",
    "ClockMismatchError",
    "ClockServer",
    "ClockType",
    "DeadlockError",
    "Divergence",
    "Duration",
    "DurationMsg",
    "ENTRY_POINT_GROUP",
    "ENV_CLOCK",
    "ENV_USE_SIM_TIME",
    "EvClockError",
    "ExtrapolationError",
    "Interpolation",
    "InvalidArgumentError",
    "InvalidTypeError",
    "JoinRefused",
    "JumpHandle",
    "JumpThreshold",
    "LagError",
    "LoopClosedError",
    "LoopReport",
    "LoopStats",
    "Message",
    "MissingExtraError",
    "NoSimulationError",
    "NotRunningError",
    "WrongThreadError",
    "PacingError",
    "ParticipantLost",
    "PhysicsError",
    "ProtocolError",
    "PyBulletTimeSource",
    "Rate",
    "RemoteCallError",
    "RemoteClockError",
    "RemoteClockSource",
    "Ros2ClockPublisher",
    "Ros2ClockSource",
    "Ros2MessageError",
    "RunReport",
    "RunSpec",
    "SIM",
    "STEADY",
    "SYSTEM",
    "ScenarioError",
    "SimClock",
    "SimDriver",
    "SimDriverError",
    "SimEventLoop",
    "SimTimeLimitError",
    "StallError",
    "StampClock",
    "StampDiagnostics",
    "StampKey",
    "StampWarning",
    "Stamped",
    "StepHook",
    "SteppingTimeSource",
    "StreamAgeStats",
    "SweepResult",
    "SweepRow",
    "Tick",
    "Time",
    "TimeBuffer",
    "TimeJump",
    "TimeLookupError",
    "TimeMsg",
    "TimeSource",
    "TimeSynchronizer",
    "Timer",
    "Trace",
    "TraceError",
    "TraceMessage",
    "VirtualTimeSource",
    "WallClock",
    "__version__",
    "clock",
    "diagnostics_report",
    "first_divergence",
    "load_scenario",
    "loop_factory",
    "parameters",
    "participant",
    "plan",
    "plot_run",
    "plot_sweep",
    "read_trace",
    "record",
    "register_clock_scheme",
    "resolve_use_sim_time",
    "run",
    "run_scenario",
    "serve",
    "sim_clock",
    "stamp_of",
    "sweep",
]


def __getattr__(name: str) -> Any:
    # The version has one source, the installed distribution's metadata (pyproject.toml);
    # importlib.metadata is read on first use, not on `import evclock`.
    if name == "__version__":
        from importlib.metadata import version

        return version("evclock")
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
