"""Time sources for the simulation loop."""

from ._base import Gate, SourceHost, TimeSource
from ._pybullet import PyBulletTimeSource, StepHook, exact_time_step
from ._virtual import VirtualTimeSource

__all__ = [
    "Gate",
    "SourceHost",
    "PyBulletTimeSource",
    "StepHook",
    "TimeSource",
    "VirtualTimeSource",
    "exact_time_step",
]
