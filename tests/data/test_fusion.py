"""The sensor-fusion scenario (sims/fusion.py), its report in `evclock run`, the example."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from _examples import run_example
from typer.testing import CliRunner

from evclock.tools._cli import app, run_scenario

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 60  # seconds; a guard against hangs, not a performance assertion

EXAMPLE_OUTPUT = """\
[10.130000000 s (sim)] frame 0: camera 10.00 imu 10.00 lidar 10.05, spread 50 ms, yaw 0.000
[10.230000000 s (sim)] frame 1: camera 10.10 imu 10.10 lidar 10.15, spread 50 ms, yaw 0.050
[10.330000000 s (sim)] frame 2: camera 10.20 imu 10.20 lidar 10.25, spread 50 ms, yaw 0.100
[10.430000000 s (sim)] frame 3: camera 10.30 imu 10.30 lidar 10.35, spread 50 ms, yaw 0.150
  warning: stale stamp on 'camera' at 10.730000000 s (sim)
[10.730000000 s (sim)] frame 4: camera 10.40 imu 10.43 lidar 10.45, spread 50 ms, yaw 0.200
[10.760000000 s (sim)] frame 5: camera 10.50 imu 10.50 lidar 10.55, spread 50 ms, yaw 0.250
[10.760000000 s (sim)] frame 6: camera 10.73 imu 10.73 lidar 10.75, spread 20 ms, yaw 0.365
[10.930000000 s (sim)] frame 7: camera 10.80 imu 10.80 lidar 10.85, spread 50 ms, yaw 0.400
camera: 9 frames, mean age 52 ms, max 230 ms, 1 stale
dropped: {'camera': 0, 'imu': 73, 'lidar': 1}
ClockMismatchError: message.stamp is a system time but this consumer runs on sim time
  warning: future stamp on 'camera' at 10.930000000 s (sim)
future stamps flagged: 1
done at 10.930000000 s (sim), dropped: {'camera': 0, 'imu': 73, 'lidar': 1}
"""


def test_sensor_fusion_example_prints_exactly_this() -> None:
    proc = run_example("sensor_fusion.py")
    assert proc.stderr == ""
    assert proc.stdout == EXAMPLE_OUTPUT


@pytest.mark.pybullet
def test_fusion_run_reports_stamp_ages_and_succeeds(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    result = CliRunner().invoke(app, ["run", "fusion", "--quiet", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "fusion (seed 0): SUCCESS" in result.output
    assert "fusion: stamp ages" in result.output
    assert "fusion: consumer queues" in result.output
    report = json.loads(out.read_text())
    summary = report["summary"]
    assert summary["detections_fused"] == 89  # 6 s of 15 Hz frames, delivered in time
    # Interpolating odometry at each detection's stamp beats the nearest odometry message,
    # which beats using the latest pose (ignoring the 80 ms latency) by an order of magnitude.
    assert summary["worst_error_at_stamp_m"] <= 0.005
    assert summary["worst_error_at_stamp_m"] < summary["worst_error_paired_odometry_m"]
    assert 10 * summary["worst_error_paired_odometry_m"] < summary["worst_error_latest_pose_m"]
    (stamps,) = report["stamps"]
    camera, odometry = stamps["streams"]["camera"], stamps["streams"]["odometry"]
    # 80 ms of latency, delivered on the first 240 Hz physics step after it: 20 steps.
    assert abs(camera["min_age_s"] - 20 / 240) <= 1e-9
    assert abs(camera["max_age_s"] - 20 / 240) <= 1e-9
    assert (odometry["messages"], odometry["max_age_s"], odometry["stale"]) == (301, 0.0, 0)
    assert stamps["queues"]["fusion sync"]["behind"] == 0
    assert stamps["warnings"] == []


@pytest.mark.pybullet
def test_fusion_is_the_same_whatever_the_pace() -> None:
    # (Seeds giving different runs: test_sims_physics.py::test_deterministic_per_seed.)
    first, again = run_scenario("fusion", seed=2), run_scenario("fusion", seed=2, rtf=50.0)
    assert first.final_state == again.final_state  # bit for bit
    assert first.summary == again.summary
    assert first.stamps == again.stamps


def test_docs_snippet_runs_as_written() -> None:
    text = (ROOT / "docs" / "guides" / "stamped-data.md").read_text()
    section = text[text.index("# Stamped data and sync") :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match is not None
    proc = subprocess.run(
        [sys.executable, "-c", match.group(1)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        "frame 0 scan [0. 0.]",
        "frame 1 scan [0.1 0. ]",
        "frame 2 scan [0.2 0. ]",
        "frame 3 scan [0.3 0. ]",
    ]


@pytest.mark.pybullet
def test_fusion_on_wall_time_stamps_in_the_wall_clock_domain() -> None:
    report = run_scenario("fusion", wall=True, until=0.5)
    assert report.mode == "wall"
    (stamps,) = report.stamps
    assert stamps["streams"]["odometry"]["messages"] >= 2  # stamped and buffered on STEADY
    assert stamps["streams"]["odometry"]["future"] == 0
    assert not report.finished
