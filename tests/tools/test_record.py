"""Recording runs to MCAP, reading them back, trace diff and plots (the files are read back)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

import evclock
from evclock.tools._cli import app
from evclock.tools._plot import PALETTE, RTF_COLOR

ROOT = Path(__file__).resolve().parents[2]
SHUTTLE = str(ROOT / "examples" / "shuttle_scenario.py")
runner = CliRunner()
#: Tests that need an optional extra skip where it is not installed (the others still run).
needs_record = pytest.mark.skipif(
    importlib.util.find_spec("mcap") is None, reason="needs evclock[record] (mcap)"
)
needs_plot = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="needs evclock[plot] (matplotlib)"
)


Recorded = tuple[Path, evclock.tools.RunReport]


def _record(path: Path, **options: Any) -> evclock.tools.RunReport:
    """Run the shuttle scenario with seed 1 and ``options``, recorded to ``path``."""
    return evclock.tools.run_scenario(SHUTTLE, seed=1, record=path, **options)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    path = tmp_path_factory.mktemp("rec") / "shuttle.mcap"
    return path, _record(path)


@pytest.fixture
def recording(recorded: Recorded) -> Path:
    """The file of :func:`recorded`."""
    return recorded[0]


@pytest.mark.pybullet
@needs_record
def test_channels_use_json_schema_and_json_messages(recording: Path) -> None:
    from mcap.reader import make_reader

    with recording.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "evclock"
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        for channel in topics.values():
            assert channel.message_encoding == "json"
            assert summary.schemas[channel.schema_id].encoding == "jsonschema"
            json.loads(summary.schemas[channel.schema_id].data)
    assert set(topics) == {
        "/evclock/clock",
        "/evclock/state",
        "/evclock/joints",
        "/evclock/transforms",
        "/evclock/scene",
        "/evclock/loop/control",
        "/evclock/loop/logger",
        "/shuttle/error",
    }
    # A user channel's schema names its fields and their types (inferred from the message).
    user_schema = json.loads(summary.schemas[topics["/shuttle/error"].schema_id].data)
    assert user_schema == {
        "title": "shuttle.error",
        "type": "object",
        "properties": {"error_m": {"type": "number"}, "target_m": {"type": "number"}},
    }
    assert topics["/evclock/clock"].metadata == {"deterministic": "false"}
    assert topics["/evclock/loop/control"].metadata == {"deterministic": "true"}


@pytest.mark.pybullet
@needs_record
def test_every_tick_is_recorded_at_its_sim_time(
    recorded: Recorded,
) -> None:
    path, report = recorded
    trace = evclock.tools.read_trace(path)
    stats = {loop.name: loop.stats for loop in report.loops}
    for name, hz in (("control", 20.0), ("logger", 10.0)):
        ticks = trace.topic(f"/evclock/loop/{name}")
        assert len(ticks) == stats[name]["ticks"]
        # Tick i of a rate at hz runs on the first physics step at or after i / hz.
        steps = [round(m.time_ns * 240 / 1e9) for m in ticks]
        assert steps == [-(-i * 240 // int(hz)) for i in range(len(ticks))]
        lateness = [m.data["lateness_s"] for m in ticks]
        assert max(lateness) == pytest.approx(stats[name]["max_lateness_s"])
    clock = trace.topic("/evclock/clock")
    assert [m.time_ns for m in clock][:3] == [0, 50_000_000, 100_000_000]
    assert all(m.data["sim_time_s"] == m.time_ns / 1e9 for m in clock)
    user = trace.topic("/shuttle/error")
    assert len(user) == stats["logger"]["ticks"]
    assert user[0].data == {
        "error_m": report.summary["target_m"],
        "target_m": report.summary["target_m"],
    }
    assert trace.metadata["evclock.run"]["seed"] == 1
    assert trace.metadata["evclock.run"]["params"] == {}
    assert trace.metadata["evclock.outcome"]["verdict"] == "success"


@pytest.mark.pybullet
@needs_record
def test_recording_does_not_change_the_run(recorded: Recorded) -> None:
    path, report = recorded
    plain = evclock.tools.run_scenario(SHUTTLE, seed=1)
    assert plain.final_state == report.final_state
    assert plain.sim_time_s == report.sim_time_s
    last_state = evclock.tools.read_trace(path).topic("/evclock/state")[-1]
    # Named fields, the same numbers in the same order as the scenario's state vector.
    assert list(last_state.data) == ["physics"]  # the cart-pole URDF's robot name
    assert _flatten(last_state.data) == report.final_state
    assert last_state.time_ns / 1e9 == report.sim_time_s


@pytest.mark.pybullet
@needs_record
def test_trace_diff_identical_runs_whatever_the_rtf(recording: Path, tmp_path: Path) -> None:
    paced = tmp_path / "paced.mcap"
    _record(paced, rtf=20.0)
    result = runner.invoke(app, ["trace", "diff", str(recording), str(paced)])
    assert result.exit_code == 0, result.output
    assert "identical: " in result.output
    assert "deterministic messages agree bit for bit" in result.output


@pytest.mark.pybullet
@needs_record
def test_trace_diff_names_the_first_divergence(recording: Path, tmp_path: Path) -> None:
    other = tmp_path / "slower.mcap"
    _record(other, params={"max_speed": 1.0})
    a, b = evclock.tools.read_trace(recording), evclock.tools.read_trace(other)
    divergence = evclock.tools.first_divergence(a, b)
    assert divergence is not None
    # Same seed, same world, a lower speed limit from the first control tick: the first
    # difference is the cart's state in the sample at 0.05 s (ticks agree: same schedule).
    assert divergence.time_s == 0.05
    assert divergence.topic == "/evclock/state"
    assert divergence.detail.startswith("physics.joints.slider_to_cart.position: ")
    assert " != " in divergence.detail
    result = runner.invoke(app, ["trace", "diff", str(recording), str(other)])
    assert result.exit_code == 1
    assert " ".join(result.output.split()) == divergence.describe()
    assert evclock.tools.first_divergence(a, a) is None


@pytest.mark.pybullet
@needs_record
def test_trace_diff_reports_a_shorter_run(recording: Path, tmp_path: Path) -> None:
    short = tmp_path / "short.mcap"
    _record(short, until=0.5)
    full = evclock.tools.read_trace(recording)
    divergence = evclock.tools.first_divergence(evclock.tools.read_trace(short), full)
    assert divergence is not None
    # Cut at 0.5 s before the control tick due then ran: the short run's last state sample
    # stands where the full run has that tick.
    assert divergence.time_s == 0.5
    assert divergence.detail == (
        "a has /evclock/state at 0.500000 s, b has /evclock/loop/control at 0.500000 s"
    )
    prefix = evclock.tools.Trace(short, {}, full.messages[:40])
    divergence = evclock.tools.first_divergence(full, prefix)
    assert divergence is not None
    assert divergence.detail == "b ends here; the other goes on"


@needs_record
def test_reading_something_else_fails_clearly(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(evclock.tools.TraceError) as info:
        evclock.tools.read_trace(junk)
    assert f"cannot read '{junk}' as an MCAP recording" in str(info.value)
    result = runner.invoke(app, ["trace", "diff", str(junk), str(tmp_path / "none.mcap")])
    assert result.exit_code == 2
    assert "error: cannot read" in " ".join(result.output.split())


def test_user_channels_are_checked() -> None:
    with pytest.raises(evclock.InvalidArgumentError) as info:
        evclock.tools.record("/evclock/state", {})
    assert "topic '/evclock/state' is reserved for evclock's own channels" in str(info.value)
    with pytest.raises(evclock.InvalidTypeError) as type_info:
        evclock.tools.record("/mine", [1, 2])  # type: ignore[arg-type]
    assert (
        "record() needs a mapping (a JSON object) or a dataclass instance as message, got list"
        in str(type_info.value)
    )
    evclock.tools.record("/mine", {"x": 1})  # no recording: nothing to write, no error


@pytest.mark.pybullet  # the scenario (examples/shuttle_scenario.py) is a PyBullet one
def test_recording_without_mcap_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "mcap.writer", None)
    result = runner.invoke(app, ["run", SHUTTLE, "--record", "x.mcap", "--quiet"])
    assert result.exit_code == 2
    assert "recording needs the mcap package: pip install 'evclock[record]'" in result.output


def _flatten(value: object) -> list[float]:
    if isinstance(value, dict):
        return [x for item in value.values() for x in _flatten(item)]
    assert isinstance(value, float)
    return [value]


def _pixels_of(image: np.ndarray, color: str) -> int:
    rgb = np.array([int(color[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    return int((np.abs(image[:, :, :3] - rgb).max(axis=2) < 0.02).sum())


@pytest.mark.pybullet
@needs_record
@needs_plot
def test_plot_draws_each_loop_and_the_rtf(recording: Path, tmp_path: Path) -> None:
    from matplotlib.image import imread

    png = tmp_path / "run.png"
    result = runner.invoke(app, ["plot", str(recording), "-o", str(png)])
    assert result.exit_code == 0, result.output
    image = imread(png)
    assert image.shape[:2] == (660, 1000)  # two loop panels and the rtf panel
    # Loops are drawn in palette order of first appearance, each in its panel, plus rtf.
    assert _pixels_of(image, PALETTE[0]) > 500
    assert _pixels_of(image, PALETTE[1]) > 500
    assert _pixels_of(image, RTF_COLOR) > 500
    assert _pixels_of(image, PALETTE[2]) == 0  # no third loop


@needs_record
@needs_plot
def test_plot_refuses_a_recording_without_loops(tmp_path: Path) -> None:
    empty = tmp_path / "empty.mcap"
    from evclock.tools._record import Recorder

    Recorder(empty, {}).close()
    result = runner.invoke(app, ["plot", str(empty), "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 2
    assert "records no rate loop: nothing to plot" in " ".join(result.output.split())
