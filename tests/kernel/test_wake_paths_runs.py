"""Whole programs with the kernel's wake-up in place and through asyncio's own path (see
tests/kernel/test_wake_paths.py): every bundled scenario on each of its engines, recorded
(every deterministic message, bit for bit) with its report, and the examples that run
sleeps, rates and timers, by what they print."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from _examples import run_example
from test_wake_paths import wake_in_place

from evclock.tools._runs import RunReport, run_scenario
from evclock.tools._scenarios import (
    engines_of,
    installed_engines,
    load_scenario,
    registered_scenarios,
)
from evclock.tools._trace import first_divergence, read_trace

#: Sim seconds of each scenario run: every loop of every scenario ticks many times.
UNTIL = 3.0


def scenario_cases() -> list[Any]:
    cases = []
    for scenario in registered_scenarios():
        for engine in engines_of(load_scenario(scenario.name)):
            marks = [pytest.mark.pybullet] if engine == "pybullet" else []
            cases.append(
                pytest.param(scenario.name, engine, id=f"{scenario.name}-{engine}", marks=marks)
            )
    return cases


def outcome(report: RunReport) -> dict[str, Any]:
    """What a run reports that depends on sim time alone (not wall time)."""
    return {
        "success": report.success,
        "finished": report.finished,
        "sim_time_s": report.sim_time_s,
        "summary": report.summary,
        "loops": [(loop.name, loop.hz, loop.stats, loop.on_physics_steps) for loop in report.loops],
        "final_state": list(report.final_state),
    }


@pytest.mark.parametrize(("scenario", "engine"), scenario_cases())
def test_a_scenario_runs_the_same_with_wake_ups_in_place_or_not(
    scenario: str, engine: str, tmp_path: Path
) -> None:
    if engine not in installed_engines():
        pytest.skip(f"{engine} is not installed for this Python")
    outcomes, traces = [], []
    for on in (True, False):
        path = tmp_path / f"{scenario}-{engine}-{on}.mcap"
        with wake_in_place(on):
            report = run_scenario(scenario, seed=7, until=UNTIL, engine=engine, record=path)
        outcomes.append(outcome(report))
        traces.append(read_trace(path))
    assert outcomes[0] == outcomes[1]
    assert first_divergence(traces[0], traces[1]) is None
    assert len([m for m in traces[0].messages if m.deterministic]) > 100


#: Examples that run sleeps, rates, timers or jumps on sim time and print only what sim
#: time decides (some on PyBullet).
EXAMPLES = [
    "sleep_and_rate.py",
    "controller.py",
    "custom_stepping_source.py",
    "patrol_controller.py",
    *(
        pytest.param(name, marks=pytest.mark.pybullet)
        for name in ("reset_and_jumps.py", "shuttle_scenario.py", "fusion_pipeline.py")
    ),
]

#: Sets the kernel's switch in an example's process, before the example runs.
SWITCH = "from evclock.kernel._core import SimCore; SimCore.wake_in_place = {on}"


def example_output(name: str, on: bool) -> str:
    return run_example(name, before=SWITCH.format(on=on)).stdout


@pytest.mark.parametrize("name", EXAMPLES)
def test_an_example_prints_the_same_with_wake_ups_in_place_or_not(name: str) -> None:
    printed = example_output(name, True)
    assert printed == example_output(name, False)
    assert printed.strip()
