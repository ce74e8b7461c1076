"""The examples run as documented (``python examples/X.py``) and print what they claim.

Each example runs in a subprocess from the repository root, without
``EVCLOCK_USE_SIM_TIME`` in its environment unless a test sets it. Virtual-time output is
exact and asserted line by line; wall-time runs are only checked for what they report
(the steady clock, completion), never for wall-time thresholds.
"""

from __future__ import annotations

import re

import _examples as examples


def run_example(name: str, **env: str) -> str:
    """Run ``examples/<name>``; its stdout (fails on a non-zero exit or any stderr)."""
    proc = examples.run_example(name, **env)
    assert proc.stderr == "", proc.stderr
    return proc.stdout


SLEEP_AND_RATE = """\
[t=  0.000000000 s] start on sim time
[t=  0.500000000 s] after clock.sleep(0.5)
[t=  0.750000000 s] after asyncio.sleep(0.25): asyncio follows sim time too
[t=  0.750000000 s] tick 0: expected 0.750 s, actual 0.750 s, missed 0
[t=  0.850000000 s] tick 1: expected 0.850 s, actual 0.850 s, missed 0
[t=  0.950000000 s] tick 2: expected 0.950 s, actual 0.950 s, missed 0
[t=  1.000000000 s]   timer: heartbeat #1
[t=  1.050000000 s] tick 3: expected 1.050 s, actual 1.050 s, missed 0
[t=  1.250000000 s]   timer: heartbeat #2
[t=  1.280000000 s] tick 5: expected 1.250 s, actual 1.280 s, missed 1
[t=  1.350000000 s] tick 6: expected 1.350 s, actual 1.350 s, missed 0
[t=  1.450000000 s] tick 7: expected 1.450 s, actual 1.450 s, missed 0
[t=  1.500000000 s]   timer: heartbeat #3
[t=  1.550000000 s] tick 8: expected 1.550 s, actual 1.550 s, missed 0
[t=  1.550000000 s] rate loop done: 8 ticks, 1 missed, max lateness 30 ms; 3 heartbeats
[t=  2.050000000 s] asyncio.timeout(0.5) fired after 500000000 ns of sim time
[t=  2.050000000 s] done
"""

VIRTUAL_REPORT = "clock=sim elapsed=0.300000000 s ticks=31 missed=0 heartbeats=3 position=0.785361"
WALL_REPORT = re.compile(
    r"clock=steady elapsed=(?P<elapsed>\d+\.\d{9}) s ticks=(?P<ticks>\d+) "
    r"missed=(?P<missed>\d+) heartbeats=(?P<beats>\d+) position=(?P<pos>\d+\.\d{6})"
)


def test_sleep_and_rate_prints_exact_sim_times() -> None:
    assert run_example("sleep_and_rate.py") == SLEEP_AND_RATE


def test_sleep_and_rate_is_deterministic() -> None:
    assert run_example("sleep_and_rate.py") == run_example("sleep_and_rate.py")


def test_controller_alone_runs_on_sim_time_by_default() -> None:
    assert run_example("controller.py") == VIRTUAL_REPORT + "\n"


def test_controller_follows_the_launch_setting_to_wall_time() -> None:
    out = run_example("controller.py", EVCLOCK_USE_SIM_TIME="0").strip()
    match = WALL_REPORT.fullmatch(out)
    assert match, out
    assert int(match["ticks"]) >= 1
    assert int(match["elapsed"].replace(".", "")) > 0


def test_run_virtual_and_wall_runs_the_same_controller_both_ways() -> None:
    lines = run_example("run_virtual_and_wall.py").splitlines()
    assert len(lines) == 4, lines
    assert lines[0] == f"virtual time: {VIRTUAL_REPORT}"
    prefix = "wall time:    "
    assert lines[1].startswith(prefix), lines[1]
    wall = WALL_REPORT.fullmatch(lines[1].removeprefix(prefix))
    assert wall, lines[1]
    # The wall run ticked on the steady clock, time moved, and the plant moved toward 1.
    assert int(wall["elapsed"].replace(".", "")) > 0
    assert int(wall["ticks"]) >= 1
    assert 0.0 < float(wall["pos"]) < 1.0
    assert re.fullmatch(
        r"wall run took \d+\.\d\d s of real time; finished on the steady clock", lines[2]
    ), lines[2]
    assert lines[3].startswith("same controller code; position differs by ")


def test_controller_on_forced_sim_time_matches_the_default() -> None:
    assert run_example("controller.py", EVCLOCK_USE_SIM_TIME="1") == VIRTUAL_REPORT + "\n"


def test_explicit_use_sim_time_wins_over_the_environment() -> None:
    # sleep_and_rate.py passes use_sim_time=True: the launch argument beats the variable.
    assert run_example("sleep_and_rate.py", EVCLOCK_USE_SIM_TIME="0") == SLEEP_AND_RATE
