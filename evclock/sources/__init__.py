"""Time sources: what owns "now" for a simulation.

``from evclock.sources import PyBulletTimeSource``. :class:`VirtualTimeSource` (the default)
jumps straight to the next deadline; :class:`SteppingTimeSource` moves in whole steps of an
engine (exact step clock, step hooks, predicate waits, snapshots as time jumps), and
:class:`PyBulletTimeSource` and :class:`MuJoCoTimeSource` are its thin engine adapters. A
new engine implements the :class:`TimeSource` contract (:class:`SourceHost` is what the
kernel offers a source).

Layer: above ``evclock.kernel`` (whose source contract and virtual source it re-exports);
below the hosts. Importing it does not import PyBullet or MuJoCo.
"""

from evclock._errors import SourceInUseError
from evclock.kernel._source import Gate, SourceHost, TimeSource
from evclock.kernel._virtual import VirtualTimeSource
from evclock.sources._mujoco import MuJoCoTimeSource
from evclock.sources._pybullet import PyBulletTimeSource
from evclock.sources._stepping import StepHook, SteppingTimeSource, exact_time_step

__all__ = [
    "Gate",
    "MuJoCoTimeSource",
    "SourceHost",
    "SourceInUseError",
    "PyBulletTimeSource",
    "StepHook",
    "SteppingTimeSource",
    "TimeSource",
    "VirtualTimeSource",
    "exact_time_step",
]

SourceInUseError.__module__ = __name__
