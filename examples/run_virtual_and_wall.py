"""Run the same controller module on virtual time, then on wall time.

``examples/controller.py`` only asks :func:`evclock.clock` for time. Which clock it gets is
decided once, here, at launch: ``evclock.run(..., use_sim_time=True)`` runs it on a
simulation loop (virtual time: instant, exact, the same output every run) and
``use_sim_time=False`` on a standard asyncio loop with the steady wall clock (it takes
``duration`` real seconds and its figures vary slightly from run to run).

Run: ``python examples/run_virtual_and_wall.py``
"""

from __future__ import annotations

import time

from controller import ControlReport, control

import evclock

DURATION = 0.3  # seconds of the clock the controller runs on


def launch(use_sim_time: bool) -> tuple[ControlReport, float]:
    """Run the controller once; return its report and the wall seconds it took."""
    t0 = time.perf_counter()
    report = evclock.run(control(duration=DURATION), use_sim_time=use_sim_time)
    return report, time.perf_counter() - t0


def main() -> None:
    """Launch the controller on both kinds of time and print what each run saw."""
    virtual, _ = launch(use_sim_time=True)
    print(f"virtual time: {virtual.describe()}")
    wall, wall_s = launch(use_sim_time=False)
    print(f"wall time:    {wall.describe()}")
    print(f"wall run took {wall_s:.2f} s of real time; finished on the {wall.clock} clock")
    error = abs(virtual.position - wall.position)
    print(f"same controller code; position differs by {error:.4f} between the runs")


if __name__ == "__main__":
    main()
