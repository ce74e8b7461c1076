"""Stamped data on sim time: stamps, synchronisers, time-indexed buffers, stamp diagnostics.

``from evclock.data import ApproximateTimeSynchronizer, TimeBuffer``. Messages carry stamps
in a clock domain; synchronisers group streams by stamp (exact, ROS's ApproximateTime,
ApproximateEpsilonTime and LatestTime policies, bit-exact with ROS 2's ``message_filters``);
filters chain into pipelines (:class:`PassThrough` -> :class:`Cache` -> synchroniser,
:class:`TimeSequencer`); a :class:`TimeBuffer` answers "the value at time t";
:class:`StampDiagnostics` shows stamp age and consumers falling behind.

Layer: above the hosts (it reads the running loop's clock). ``TimeBuffer`` needs numpy and is
imported on first use.
"""

from typing import TYPE_CHECKING, Any

from evclock._errors import ExtrapolationError, TimeLookupError
from evclock.data._diagnostics import (
    StampDiagnostics,
    StampWarning,
    StreamAgeStats,
    diagnostics_report,
)
from evclock.data._filters import (
    Cache,
    Chain,
    Connection,
    PassThrough,
    SimpleFilter,
    TimeSequencer,
)
from evclock.data._policies import DROP_REASONS
from evclock.data._stamped import StampClock, Stamped, StampKey, stamp_of
from evclock.data._sync import (
    ApproximateEpsilonTimeSynchronizer,
    ApproximateTimeSynchronizer,
    LatestTimeSynchronizer,
    TimeSynchronizer,
)

if TYPE_CHECKING:
    from evclock.data._buffer import Interpolation, TimeBuffer

__all__ = [
    "DROP_REASONS",
    "ApproximateEpsilonTimeSynchronizer",
    "ApproximateTimeSynchronizer",
    "Cache",
    "Chain",
    "Connection",
    "ExtrapolationError",
    "Interpolation",
    "LatestTimeSynchronizer",
    "PassThrough",
    "SimpleFilter",
    "StampClock",
    "StampDiagnostics",
    "StampKey",
    "StampWarning",
    "Stamped",
    "StreamAgeStats",
    "TimeBuffer",
    "TimeLookupError",
    "TimeSequencer",
    "TimeSynchronizer",
    "diagnostics_report",
    "stamp_of",
]


for _name in ("ExtrapolationError", "TimeLookupError"):
    globals()[_name].__module__ = __name__
del _name


def __getattr__(name: str) -> Any:
    # TimeBuffer needs numpy: imported on first use, so that importing this package stays light.
    if name in ("Interpolation", "TimeBuffer"):
        from evclock.data import _buffer

        return getattr(_buffer, name)
    raise AttributeError(f"module 'evclock.data' has no attribute {name!r}")
