"""A controller that never knows which time it runs on.

A proportional controller drives a simulated 1-D plant (a point whose velocity is the
command: ``x' = u``, ``u = kp * (target - x)``) at a fixed rate, with a heartbeat timer
beside it. It only ever uses :func:`evclock.clock`: under ``evclock.run(...)`` with sim
time that is the simulation clock, on wall time it is the steady clock. The plant is
integrated over the *measured* time between ticks, so on virtual time the trajectory is
exact and identical on every run, and on wall time it follows the real elapsed time.

``examples/run_virtual_and_wall.py`` runs this very module both ways. On its own:
``python examples/controller.py`` (sim time unless ``EVCLOCK_USE_SIM_TIME=0``).
"""

from __future__ import annotations

from dataclasses import dataclass

import evclock


@dataclass(frozen=True)
class ControlReport:
    """What one controller run did, as measured on the clock it ran on."""

    clock: str
    elapsed_ns: int
    ticks: int
    missed: int
    heartbeats: int
    position: float

    def describe(self) -> str:
        """One line summary."""
        return (
            f"clock={self.clock} elapsed={self.elapsed_ns / 1e9:.9f} s ticks={self.ticks} "
            f"missed={self.missed} heartbeats={self.heartbeats} position={self.position:.6f}"
        )


async def control(
    duration: float = 0.3,
    hz: float = 100.0,
    kp: float = 5.0,
    target: float = 1.0,
    heartbeat_period: float = 0.1,
) -> ControlReport:
    """Run the P-controller for ``duration`` seconds of the running loop's clock."""
    clock = evclock.clock()
    beats = 0

    def heartbeat() -> None:
        nonlocal beats
        beats += 1

    timer = clock.timer(heartbeat_period, heartbeat, name="heartbeat")
    position, command = 0.0, 0.0
    last = start = clock.now()
    last_index = round(duration * hz)
    rate = clock.rate(hz)
    try:
        async for tick in rate:
            dt = (tick.actual - last).seconds
            last = tick.actual
            position += command * dt  # the plant moved at the last command since last tick
            command = kp * (target - position)
            if tick.index >= last_index:
                break
    finally:
        timer.cancel()
    return ControlReport(
        clock=clock.clock_type.value,
        elapsed_ns=(clock.now() - start).nanoseconds,
        ticks=rate.stats.ticks,
        missed=rate.stats.missed,
        heartbeats=beats,
        position=position,
    )


async def main() -> None:
    """Run the controller once and print its report."""
    report = await control()
    print(report.describe())


if __name__ == "__main__":
    evclock.run(main())
