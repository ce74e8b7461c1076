"""The dashboard's settings, shared by the command line, the app factory and the tests."""

from __future__ import annotations

import dataclasses

from evclock_sims import get_scenario


@dataclasses.dataclass(frozen=True, slots=True)
class DashboardConfig:
    """What to simulate and how to serve it.

    ``rtf`` is the initial real-time factor (None: as fast as possible) and ``paused``
    starts the simulation paused; both can be changed at run time through the API.
    """

    scenario: str = "kuka"
    """Name of a scenario in :data:`evclock_sims.SCENARIOS`."""
    seed: int = 0
    """Seed of the first episode; each following episode uses the next seed."""
    rtf: float | None = 1.0
    paused: bool = False
    repeat: bool = True
    """Start a new episode (reset world, next seed) when a mission ends; False: run one
    mission, then keep stepping the physics with the controllers stopped."""
    episode_gap: float = 1.0
    """Simulated seconds between the end of a mission and the reset for the next one."""
    episode_limit: float = 3.0
    """A mission still running after ``episode_limit x scenario.default_until`` simulated
    seconds is stopped and recorded as a failure."""
    sample_period: float = 0.25
    """Wall seconds between two samples of the plotted history."""
    history_size: int = 480
    """Samples kept for the plots (480 x 0.25 s: the last two minutes)."""
    step_timeout: float = 30.0
    """Wall seconds ``POST /api/step`` may take; steps not taken by then are cancelled and
    the request answers 504."""
    scene_fps: float = 5.0
    """Most frames of the scene view rendered per wall second (in a worker process)."""
    scene_size: tuple[int, int] = (320, 240)
    """Width and height of the scene view, pixels."""

    def __post_init__(self) -> None:
        get_scenario(self.scenario)  # ValueError listing the valid names
        for name in ("episode_gap", "episode_limit", "sample_period", "step_timeout", "scene_fps"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name} must be positive, got {value!r}")
        if self.history_size < 2:
            raise ValueError(f"history_size must be at least 2, got {self.history_size!r}")
        width, height = self.scene_size
        if not (16 <= width <= 1920 and 16 <= height <= 1080):
            raise ValueError(
                f"scene_size must be (width, height) within 16x16 .. 1920x1080, "
                f"got {self.scene_size!r}"
            )
