"""Time values: :class:`Time` and :class:`Duration` (exact integer nanoseconds) and the clock
domains they belong to (``SIM``, ``SYSTEM``, ``STEADY``), with their ROS message layouts.

Layer: the lowest of evclock's own (it imports only ``evclock._errors``). Everything else may
import it. The names here are also in the top-level ``evclock`` namespace.
"""

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

__all__ = ["SIM", "STEADY", "SYSTEM", "ClockType", "Duration", "DurationMsg", "Time", "TimeMsg"]
