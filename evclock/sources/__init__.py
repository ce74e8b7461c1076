"""Time sources for the simulation loop."""

from ._base import Gate, TimeSource
from ._virtual import VirtualTimeSource

__all__ = ["Gate", "TimeSource", "VirtualTimeSource"]
