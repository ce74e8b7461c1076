"""The pacing and reset examples run and print exact sim times (wall figures are not checked)."""

from __future__ import annotations

import pytest
from _examples import output_lines
from _examples import run_example as examples_run


def run_example(name: str) -> list[str]:
    return output_lines(examples_run(name))


def test_pacing_example_pauses_steps_and_resumes_exactly() -> None:
    lines = run_example("pacing.py")
    assert lines[0].startswith("rtf=2: 1 s of sim time took ")
    assert lines[1].startswith("rtf=max: 60 s of sim time took ")
    assert lines[2:] == [
        "paused at 61.000000000 s (sim); the operator steps three times, then resumes",
        "  stepped: sim time 61.100000000 s (sim)",
        "  stepped: sim time 61.200000000 s (sim)",
        "  stepped: sim time 61.300000000 s (sim)",
        "resumed; the controller's half second ended at 61.500000000 s (sim)",
        "controller: 615 ticks, 0 missed",
    ]


@pytest.mark.pybullet
def test_reset_example_wakes_sleepers_and_re_anchors_the_rate() -> None:
    lines = run_example("reset_and_jumps.py")
    assert lines[4:] == [
        "restoring at 1.500000000 s (sim), z = 0.100 m",
        "jump handler (pre):  leaving 1.500000000 s (sim)",
        "jump handler (post): now 0.500000000 s (sim), delta -1.000000000 s",
        "restored: 0.500000000 s (sim), z = 0.791 m",
        "monitor tick 0 at 0.500000000 s (sim): z = 0.791 m",
        "slow task woken by the jump (delta -1.000000000 s); sleeping again",
        "monitor tick 5 at 1.000000000 s (sim): z = 0.100 m",
        "slow task finished its sleep at 1.300000000 s (sim)",
        "monitor tick 10 at 1.500000000 s (sim): z = 0.100 m",
    ]
    assert lines[1] == "saved state at 0.500000000 s (sim), z = 0.791 m"
