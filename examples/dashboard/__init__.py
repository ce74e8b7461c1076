"""A live dashboard for a PyBullet simulation run on sim time inside a web server.

A Starlette app served by uvicorn embeds one of the ``evclock_sims`` scenarios (KUKA arm by
default): a :class:`evclock.SimDriver` paces a :class:`evclock.sources.PyBulletTimeSource` on the
server's own event loop, the scenario's controllers run there as ordinary tasks on sim time,
and the page shows a live view of the scene, sim time, the achieved real-time factor and
each rate loop's tick and lateness statistics, with plots and controls (pause, step, resume,
real-time factor).

Run it from any working directory: ``python path/to/examples/dashboard [--scenario kuka]
[--port 8000] [--rtf 1]``. Modules: :mod:`.config` (settings), :mod:`.sim` (the simulation
service), :mod:`.scene` (the live view, rendered in a worker process), :mod:`.app` (routes
and JSON API), :mod:`.server` (in-process serving for tests).
"""

from .app import create_app
from .config import DashboardConfig
from .scene import SceneView
from .server import BackgroundServer
from .sim import SimService, StepNotCompleted

__all__ = [
    "BackgroundServer",
    "DashboardConfig",
    "SceneView",
    "SimService",
    "StepNotCompleted",
    "create_app",
]
