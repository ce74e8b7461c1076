"""Time sources for the simulation loop."""

from ._base import Gate, SourceHost, TimeSource
from ._pybullet import PyBulletTimeSource
from ._stepping import StepHook, SteppingTimeSource, exact_time_step
from ._virtual import VirtualTimeSource

__all__ = [
    "Gate",
    "SourceHost",
    "PyBulletTimeSource",
    "StepHook",
    "SteppingTimeSource",
    "TimeSource",
    "VirtualTimeSource",
    "exact_time_step",
]
