"""Tools around runs: scenarios, sweeps, recordings, traces, plots and the ``evclock`` command.

``from evclock.tools import run_scenario, sweep, record, read_trace``. A scenario (world,
controllers, success criterion, report) is a unit a user writes and evclock runs: once
(:func:`run_scenario`, ``evclock run``), many times (:func:`sweep`, ``evclock sweep``),
recorded (:func:`record`, MCAP), compared (:func:`first_divergence`) and plotted.

Layer: the top (with ``evclock.testing``): it may import every other layer; nothing imports it.
Optional dependencies (PyBullet, mcap, matplotlib, Ray) are imported where they are used.
"""

from evclock._errors import ScenarioError, TraceError
from evclock.tools._plot import plot_run, plot_sweep
from evclock.tools._record import record
from evclock.tools._ros2_state import ros2_robot_state
from evclock.tools._runs import LoopReport, RunReport, run_scenario
from evclock.tools._scenarios import ENTRY_POINT_GROUP, load_scenario, parameters
from evclock.tools._sweep import RunSpec, SweepResult, SweepRow, plan, sweep
from evclock.tools._trace import Divergence, Trace, TraceMessage, first_divergence, read_trace

__all__ = [
    "ENTRY_POINT_GROUP",
    "Divergence",
    "LoopReport",
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
    "ros2_robot_state",
    "run_scenario",
    "sweep",
]

for _name in ("ScenarioError", "TraceError"):
    globals()[_name].__module__ = __name__
del _name
