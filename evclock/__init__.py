"""evclock: simulation time for asyncio robot controllers.

An asyncio event loop whose ``time()`` is the simulator's clock: ``asyncio.sleep``,
timeouts and anyio all follow sim time, time advances only when every task waits, and the
same controller code runs unchanged on wall time on the real robot.

This namespace holds what a controller author needs: :func:`run`, :func:`clock`, the time
values, rates, timers, jumps, the loop and driver, and the errors. The rest lives in named
subpackages, imported on first use so that ``import evclock`` stays light:

* :mod:`evclock.sources`: time sources (virtual, stepping, PyBullet);
* :mod:`evclock.remote`: sim time across processes (server, participants);
* :mod:`evclock.ros2`: ROS 2 ``/clock`` over Zenoh;
* :mod:`evclock.data`: stamped data, synchronisers, buffers, stamp diagnostics;
* :mod:`evclock.tools`: scenarios, sweeps, recordings, traces, plots;
* :mod:`evclock.testing`: the pytest plugin.

The layers below them (``evclock.time``, ``evclock.kernel``, ``evclock.outside``,
``evclock.hosts``) are described in the architecture guide.
"""

import importlib
from typing import TYPE_CHECKING, Any

from evclock._errors import (
    ClockJumpedError,
    ClockLostError,
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
    WrongThreadError,
)
from evclock.hosts._config import ENV_CLOCK, ENV_USE_SIM_TIME, register_clock_scheme
from evclock.hosts._current import clock, sim_clock
from evclock.hosts._driver import SimDriver
from evclock.hosts._loop import SimEventLoop
from evclock.hosts._runner import loop_factory, resolve_use_sim_time, run
from evclock.kernel._clock import Clock, SimClock, WallClock
from evclock.kernel._jumps import JumpHandle, JumpThreshold, TimeJump
from evclock.kernel._rate import LoopStats, Rate, Tick, Timer
from evclock.time._time import (
    SIM,
    STEADY,
    SYSTEM,
    ClockType,
    Duration,
    DurationMsg,
    Time,
    TimeMsg,
)

if TYPE_CHECKING:
    from evclock import (  # noqa: F401  (the subpackages, imported on first use)
        data,
        gym,
        hosts,
        kernel,
        outside,
        remote,
        ros2,
        sources,
        testing,
        time,
        tools,
    )

    __version__: str
    """The installed version of evclock (``"0.3.0"``), read from the distribution's metadata
    on first access; ``evclock --version`` prints it."""

__all__ = [
    "SIM",
    "STEADY",
    "SYSTEM",
    "Clock",
    "ClockJumpedError",
    "ClockLostError",
    "ClockMismatchError",
    "ClockType",
    "DeadlockError",
    "Duration",
    "DurationMsg",
    "ENV_CLOCK",
    "ENV_USE_SIM_TIME",
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
    "Rate",
    "SimClock",
    "SimDriver",
    "SimDriverError",
    "SimEventLoop",
    "SimTimeLimitError",
    "StallError",
    "Tick",
    "Time",
    "TimeJump",
    "TimeMsg",
    "Timer",
    "WallClock",
    "WrongThreadError",
    "__version__",
    "clock",
    "loop_factory",
    "register_clock_scheme",
    "resolve_use_sim_time",
    "run",
    "sim_clock",
]

#: Subpackages imported on first attribute access (``evclock.remote.serve``).
_SUBPACKAGES = frozenset(
    (
        "data",
        "gym",
        "hosts",
        "kernel",
        "outside",
        "remote",
        "ros2",
        "sources",
        "testing",
        "time",
        "tools",
    )
)

#: Names that left this namespace in 0.2.0, and the subpackage that holds each now.
_MOVED = {
    **dict.fromkeys(
        ("PyBulletTimeSource", "StepHook", "SteppingTimeSource", "TimeSource", "VirtualTimeSource"),
        "sources",
    ),
    **dict.fromkeys(
        (
            "ClockServer",
            "Message",
            "serve",
            "participant",
            "RemoteClockSource",
            "RemoteClockError",
            "ProtocolError",
            "RemoteCallError",
            "JoinRefusedError",
            "ParticipantLostError",
        ),
        "remote",
    ),
    **dict.fromkeys(("Ros2ClockPublisher", "Ros2ClockSource", "Ros2MessageError"), "ros2"),
    **dict.fromkeys(
        (
            "ApproximateTimeSynchronizer",
            "TimeSynchronizer",
            "StampClock",
            "Stamped",
            "StampKey",
            "stamp_of",
            "TimeBuffer",
            "Interpolation",
            "StampDiagnostics",
            "StampWarning",
            "StreamAgeStats",
            "diagnostics_report",
            "TimeLookupError",
            "ExtrapolationError",
        ),
        "data",
    ),
    **dict.fromkeys(
        (
            "run_scenario",
            "RunReport",
            "LoopReport",
            "load_scenario",
            "parameters",
            "ENTRY_POINT_GROUP",
            "sweep",
            "plan",
            "RunSpec",
            "SweepResult",
            "SweepRow",
            "record",
            "read_trace",
            "Trace",
            "TraceMessage",
            "Divergence",
            "first_divergence",
            "plot_run",
            "plot_sweep",
            "ScenarioError",
            "TraceError",
        ),
        "tools",
    ),
}
#: Names renamed in 0.2.0 (errors now all end in ``Error``).
_RENAMED = {
    "ClockJumped": "evclock.ClockJumpedError",
    "ClockLost": "evclock.ClockLostError",
    "JoinRefused": "evclock.remote.JoinRefusedError",
    "ParticipantLost": "evclock.remote.ParticipantLostError",
}


def __getattr__(name: str) -> Any:
    if name in _SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    if name == "__version__":
        # One source of the version: the installed distribution's metadata (pyproject.toml),
        # read on first use rather than on `import evclock`.
        from importlib.metadata import version

        return version("evclock")
    if name in _MOVED:
        raise AttributeError(
            f"evclock.{name} moved to evclock.{_MOVED[name]}.{name} in evclock 0.2.0: "
            f"use `from evclock.{_MOVED[name]} import {name}` (see CHANGELOG.md)"
        )
    if name in _RENAMED:
        raise AttributeError(
            f"evclock.{name} was renamed {_RENAMED[name]} in evclock 0.2.0 (see CHANGELOG.md)"
        )
    raise AttributeError(f"module 'evclock' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, *_SUBPACKAGES})


# Errors show their public name in tracebacks and reprs (evclock.InvalidArgumentError, not
# evclock._errors.InvalidArgumentError); they pickle by that name too.
for _name in __all__:
    _value = globals().get(_name)
    if isinstance(_value, type) and issubclass(_value, EvClockError):
        _value.__module__ = __name__
del _name, _value
