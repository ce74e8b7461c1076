"""Foxglove-native recordings (well-known schemas, named joints, sim-time log times), the
``evclock trace info|echo`` and field-plot commands run as real subprocesses, and reading
older, newer and broken recordings."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import TypedDict

import pytest

import evclock
from evclock.tools._foxglove import parse_address, schema_of_message, schema_of_type

needs_record = pytest.mark.skipif(
    importlib.util.find_spec("mcap") is None, reason="needs evclock[record] (mcap)"
)
needs_plot = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="needs evclock[plot] (matplotlib)"
)
KUKA_JOINTS = [f"lbr_iiwa_joint_{i}" for i in range(1, 8)]
KUKA_LINKS = [f"lbr_iiwa/lbr_iiwa_link_{i}" for i in range(8)]
UNTIL_S = 1.5

#: A KUKA variant whose controllers log (``logging``) and write a typed user channel.
LOGGING_KUKA = """
import dataclasses
import logging

import evclock
from evclock_sims.kuka import KukaReach


@dataclasses.dataclass
class Progress:
    target: int
    error_m: float
    reached: bool


class LoggingKuka(KukaReach):
    name = "logging-kuka"

    async def _mission(self, clock):
        logging.getLogger("kuka.mission").warning("mission starts at %.2f s", clock.now().seconds)
        async def report():
            async for _ in clock.rate(5.0, name="reporter"):
                evclock.tools.record(
                    "/kuka/progress",
                    Progress(len(self.reached_at), self.final_error, False),
                )
        import asyncio
        task = asyncio.create_task(report())
        try:
            await super()._mission(clock)
        finally:
            task.cancel()
"""


def evclock_command(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "evclock", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        check=False,
    )


@pytest.fixture(scope="module")
def kuka(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A KUKA run recorded by the real command."""
    folder = tmp_path_factory.mktemp("kuka")
    scenario = folder / "logging_kuka.py"
    scenario.write_text(LOGGING_KUKA)
    path = folder / "kuka.mcap"
    proc = evclock_command(
        "run", f"{scenario}:LoggingKuka", "--seed", "3", "--until", str(UNTIL_S),
        "--record", str(path), "--quiet", cwd=folder,
    )  # fmt: skip
    assert proc.returncode == 3, proc.stderr  # cut short by --until: no verdict
    return path


@pytest.mark.pybullet
@needs_record
def test_kuka_recording_uses_foxglove_schemas_named_joints_and_sim_time(kuka: Path) -> None:
    from mcap.reader import make_reader

    with kuka.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        schema_of = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert schema_of["/evclock/joints"] == "foxglove.JointStates"
        assert schema_of["/evclock/transforms"] == "foxglove.FrameTransforms"
        assert schema_of["/evclock/scene"] == "foxglove.SceneUpdate"
        assert schema_of["/evclock/log"] == "foxglove.Log"
        for channel in summary.channels.values():
            assert channel.message_encoding == "json"
            assert summary.schemas[channel.schema_id].encoding == "jsonschema"
        messages = [
            (channel.topic, message.log_time, message.publish_time, json.loads(message.data))
            for _, channel, message in reader.iter_messages(log_time_order=False)
        ]
    joints = [(t, data) for topic, t, _, data in messages if topic == "/evclock/joints"]
    # Sampled every 0.05 s of sim time, from 0 to the end: log time = sim time in ns.
    assert [t for t, _ in joints] == [i * 50_000_000 for i in range(len(joints))]
    assert len(joints) == round(UNTIL_S / 0.05) + 1
    for t, data in joints:
        assert [j["name"] for j in data["joints"]] == KUKA_JOINTS
        assert data["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}
        assert all(isinstance(j["effort"], float) for j in data["joints"])
    # The rest pose (REST_POSE in sims/kuka.py) is where joint 2 starts.
    assert joints[0][1]["joints"][1]["position"] == pytest.approx(0.4)
    assert all(log == publish for _, log, publish, _ in messages)
    transforms = next(data for topic, _, _, data in messages if topic == "/evclock/transforms")
    frames = [f["child_frame_id"] for f in transforms["transforms"]]
    assert frames == KUKA_LINKS
    assert {f["parent_frame_id"] for f in transforms["transforms"]} == {"world"}
    scenes = [data for topic, _, _, data in messages if topic == "/evclock/scene"]
    assert len(scenes) == 1  # the robot's shapes, once
    entities = scenes[0]["entities"]
    assert [e["frame_id"] for e in entities] == KUKA_LINKS
    model = entities[1]["models"][0]
    assert model["media_type"] == "model/stl"
    assert len(model["data"]) > 1000  # the link's mesh, embedded (base64)
    logs = [(t, data) for topic, t, _, data in messages if topic == "/evclock/log"]
    assert [(t, d["level"], d["name"], d["message"]) for t, d in logs] == [
        (0, 3, "kuka.mission", "mission starts at 0.00 s")
    ]


@pytest.mark.pybullet
@needs_record
def test_a_typed_user_channel_has_the_dataclass_schema(kuka: Path) -> None:
    trace = evclock.tools.read_trace(kuka)
    assert trace.schemas["/kuka/progress"] == "kuka.progress"
    progress = trace.topic("/kuka/progress")
    assert [m.time_ns for m in progress] == [i * 200_000_000 for i in range(len(progress))]
    assert set(progress[0].data) == {"target", "error_m", "reached"}
    from mcap.reader import make_reader

    with kuka.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    schema = next(
        json.loads(summary.schemas[c.schema_id].data)
        for c in summary.channels.values()
        if c.topic == "/kuka/progress"
    )
    assert schema["properties"] == {
        "target": {"type": "integer"},
        "error_m": {"type": "number"},
        "reached": {"type": "boolean"},
    }


@pytest.mark.pybullet
@needs_record
def test_trace_info_names_the_run_its_duration_and_topics(kuka: Path) -> None:
    proc = evclock_command("trace", "info", str(kuka), cwd=kuka.parent)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == f"recording: {kuka} (evclock recording format 2)"
    assert "scenario:  logging-kuka (LoggingKuka)" in lines
    assert "seed:      3" in lines
    assert "params:    none" in lines
    assert f"evclock:   {evclock.__version__}" in lines
    assert "outcome:   cut short" in lines
    assert f"duration:  {UNTIL_S:.6f} s of sim time (0.000000 s to {UNTIL_S:.6f} s)" in lines
    rows = {line.split()[0]: line.split()[1:] for line in lines if line.startswith("/")}
    samples = str(round(UNTIL_S / 0.05) + 1)
    assert rows["/evclock/joints"] == ["foxglove.JointStates", samples]
    assert rows["/evclock/transforms"] == ["foxglove.FrameTransforms", samples]
    assert rows["/evclock/scene"] == ["foxglove.SceneUpdate", "1"]
    assert rows["/evclock/log"] == ["foxglove.Log", "1"]
    assert rows["/evclock/loop/planner"] == ["evclock.Tick", "15"]  # 10 Hz over 1.5 s


@pytest.mark.pybullet
@needs_record
def test_trace_echo_prints_messages_fields_and_a_time_window(kuka: Path) -> None:
    trace = evclock.tools.read_trace(kuka)
    proc = evclock_command(
        "trace", "echo", str(kuka), "/evclock/joints",
        "--field", "joints[lbr_iiwa_joint_2].position", "--from", "0.1", "--to", "0.2",
        cwd=kuka.parent,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    expected = [
        m.data["joints"][1]["position"]
        for m in trace.topic("/evclock/joints")
        if 100_000_000 <= m.time_ns <= 200_000_000
    ]
    assert proc.stdout.splitlines() == [
        f"{s} {json.dumps(v)}"
        for s, v in zip(("0.100000000", "0.150000000", "0.200000000"), expected, strict=True)
    ]
    whole = evclock_command("trace", "echo", str(kuka), "/kuka/progress", cwd=kuka.parent)
    assert whole.returncode == 0, whole.stderr
    first = whole.stdout.splitlines()[0]
    assert first.startswith("0.000000000 {")
    assert json.loads(first.split(" ", 1)[1]) == trace.topic("/kuka/progress")[0].data
    scene = evclock_command("trace", "echo", str(kuka), "/evclock/scene", cwd=kuka.parent)
    assert '"data": "<' in scene.stdout  # embedded meshes shown by their size
    unknown = evclock_command("trace", "echo", str(kuka), "/nope", cwd=kuka.parent)
    assert unknown.returncode == 2
    assert unknown.stderr.startswith(f"error: no topic '/nope' in '{kuka}'; its topics: ")
    assert "Traceback" not in unknown.stderr


@pytest.mark.pybullet
@needs_record
@needs_plot
def test_plot_draws_any_numeric_fields_in_one_figure(kuka: Path, tmp_path: Path) -> None:
    from matplotlib.image import imread

    from evclock.tools._plot import PALETTE

    png = tmp_path / "fields.png"
    proc = evclock_command(
        "plot", str(kuka),
        "/evclock/joints.joints[lbr_iiwa_joint_2].position",
        "/evclock/state.lbr_iiwa.joints.lbr_iiwa_joint_4.velocity",
        "/kuka/progress.error_m",
        "-o", str(png), cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    image = imread(png)
    assert image.shape[:2] == (760, 1000)  # one figure, a panel per field
    for color in PALETTE[:3]:  # three series, in palette order
        rgb = [int(color[i : i + 2], 16) / 255 for i in (1, 3, 5)]
        close = (abs(image[:, :, :3] - rgb).max(axis=2) < 0.02).sum()
        assert close > 300, color
    text = evclock_command(
        "plot", str(kuka), "/evclock/scene.entities", "-o", str(png), cwd=tmp_path
    )
    assert text.returncode == 2
    assert text.stderr.startswith("error: /evclock/scene.entities is not a number")
    missing = evclock_command(
        "plot", str(kuka), "/evclock/joints.joints[elbow].position", "-o", str(png), cwd=tmp_path
    )
    assert missing.returncode == 2
    assert missing.stderr.startswith(
        "error: no message of /evclock/joints has the field 'joints[elbow].position': joints "
        "has no item [elbow]; its items: [lbr_iiwa_joint_1], "
    )


@pytest.mark.pybullet
@needs_record
def test_a_wall_time_run_records_on_the_wall_clock(tmp_path: Path) -> None:
    path = tmp_path / "wall.mcap"
    proc = evclock_command(
        "run", "kuka", "--wall", "--until", "0.5", "--record", str(path), "--quiet", cwd=tmp_path
    )
    assert proc.returncode == 3, proc.stderr
    trace = evclock.tools.read_trace(path)
    assert trace.timeline == "wall"
    assert trace.metadata["evclock.run"]["time"] == "wall"
    joints = trace.topic("/evclock/joints")
    assert joints, trace.topics
    for message in joints:
        assert [j["name"] for j in message.data["joints"]] == KUKA_JOINTS
        stamp = message.data["timestamp"]
        assert stamp["sec"] * 10**9 + stamp["nsec"] == message.time_ns
    times = [m.time_ns for m in trace.messages]
    assert times == sorted(times)  # the wall clock's time, in the order things happened
    info = evclock_command("trace", "info", str(path), cwd=tmp_path)
    assert "s of wall time (" in info.stdout


@needs_record
@pytest.mark.parametrize("cut", [0, 9, 300, -200])
def test_a_truncated_or_corrupt_file_gives_one_line(tmp_path: Path, cut: int) -> None:
    from evclock.tools._record import Recorder

    good = tmp_path / "good.mcap"
    Recorder(good, {"scenario": "none"}).close()
    data = good.read_bytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[:cut] if cut > 0 else b"" if cut == 0 else data[:cut] + b"\xff" * 8)
    commands = [["trace", "info"]]
    if cut == 300:  # every command reading a file says it the same way
        commands += [["trace", "echo"], ["plot"]]
    for command in commands:
        extra = ["/x"] if command == ["trace", "echo"] else []
        if command == ["plot"]:
            extra = ["-o", str(tmp_path / "p.png")]
        proc = evclock_command(*command, str(broken), *extra, cwd=tmp_path)
        assert proc.returncode == 2, (command, proc.stderr)
        assert proc.stderr.count("\n") == 1, proc.stderr
        assert proc.stderr.startswith(f"error: cannot read '{broken}' as an MCAP recording: ")
        assert "Traceback" not in proc.stderr


def _write_mcap(path: Path, metadata: dict[str, dict[str, str]], state: list[float]) -> None:
    from mcap.writer import Writer

    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="evclock", library="evclock")
        for name, values in metadata.items():
            writer.add_metadata(name, values)
        schema = writer.register_schema("evclock.State", "jsonschema", b'{"type": "object"}')
        channel = writer.register_channel(
            "/evclock/state", "json", schema, {"deterministic": "true"}
        )
        writer.add_message(channel, 50_000_000, json.dumps({"state": state}).encode(), 0, 0)
        writer.finish()  # type: ignore[no-untyped-call]


@needs_record
def test_older_recordings_are_read_and_newer_ones_refused(tmp_path: Path) -> None:
    old = tmp_path / "old.mcap"  # format 1: no format record, the state an unnamed array
    _write_mcap(old, {"evclock.run": {"scenario": '"kuka"', "seed": "1"}}, [1.0, 2.0])
    trace = evclock.tools.read_trace(old)
    assert trace.format_version == 1
    assert trace.topic("/evclock/state")[0].data == {"state": [1.0, 2.0]}
    proc = evclock_command("trace", "echo", str(old), "/evclock/state", "--field", "state[1]",
                           cwd=tmp_path)  # fmt: skip
    assert proc.stdout == "0.050000000 2.0\n"
    info = evclock_command("trace", "info", str(old), cwd=tmp_path)
    assert "evclock recording format 1" in info.stdout
    assert "evclock:   unknown (format 1)" in info.stdout
    new = tmp_path / "new.mcap"
    _write_mcap(
        new,
        {"evclock.format": {"version": "3"}, "evclock.run": {"evclock_version": '"9.0"'}},
        [],
    )
    with pytest.raises(evclock.tools.TraceError) as error:
        evclock.tools.read_trace(new)
    assert str(error.value) == (
        f"'{new}' is an evclock recording of format version 3 (made by evclock 9.0); this "
        "evclock reads versions 1 to 2: upgrade evclock (pip install -U evclock)"
    )
    proc = evclock_command("trace", "info", str(new), cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr == f"error: {error.value}\n"


class Pose(TypedDict):
    x: float
    tags: list[str]


@dataclasses.dataclass
class Sample:
    index: int
    pose: Pose
    note: str | None
    values: dict[str, float]


def test_schemas_come_from_dataclasses_typeddicts_or_the_first_message() -> None:
    assert schema_of_type(Sample, "s") == {
        "title": "s",
        "type": "object",
        "properties": {
            "index": {"type": "integer"},
            "pose": {
                "type": "object",
                "properties": {
                    "x": {"type": "number"},
                    "tags": {"type": "array", "items": {"type": "string"}},
                },
            },
            "note": {"type": ["string", "null"]},
            "values": {"type": "object", "additionalProperties": {"type": "number"}},
        },
    }
    assert schema_of_message({"a": 1, "b": [0.5], "c": {"d": True}}, "m") == {
        "title": "m",
        "type": "object",
        "properties": {
            "a": {"type": "integer"},
            "b": {"type": "array", "items": {"type": "number"}},
            "c": {"type": "object", "properties": {"d": {"type": "boolean"}}},
        },
    }
    with pytest.raises(evclock.InvalidTypeError) as error:
        schema_of_type(int, "x")
    assert str(error.value) == (
        "record() message types are dataclasses or TypedDicts, got <class 'int'>"
    )

    @dataclasses.dataclass
    class Odd:
        when: complex

    with pytest.raises(evclock.InvalidTypeError) as odd:
        schema_of_type(Odd, "x")
    assert str(odd.value).startswith("record(): cannot describe the field type <class 'complex'>")


def test_foxglove_addresses_are_checked() -> None:
    assert parse_address("127.0.0.1:9000") == ("127.0.0.1", 9000)
    assert parse_address(":0") == ("127.0.0.1", 0)
    assert parse_address("ws://localhost:8766/") == ("localhost", 8766)
    with pytest.raises(evclock.InvalidArgumentError) as error:
        parse_address("localhost:http")
    assert str(error.value) == (
        "--foxglove-addr takes HOST:PORT (default 127.0.0.1:8765), got 'localhost:http'"
    )


@pytest.mark.pybullet
@needs_record
def test_the_shipped_layout_shows_what_a_kuka_recording_has(kuka: Path, tmp_path: Path) -> None:
    out = tmp_path / "layout.json"
    proc = evclock_command("trace", "layout", "-o", str(out), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == f"wrote {out}\n"
    layout = json.loads(out.read_text())
    panels = layout["configById"]
    assert set(panels) == {"3D!evclock", "Plot!joints", "Plot!timing", "RosOut!log",
                           "RawMessages!state"}  # fmt: skip
    trace = evclock.tools.read_trace(kuka)
    paths = [p["value"] for key in ("Plot!joints", "Plot!timing") for p in panels[key]["paths"]]
    topics = [*panels["3D!evclock"]["topics"], panels["RosOut!log"]["topicToRender"]]
    topics += [panels["RawMessages!state"]["topicPath"]]
    topics += [path.split(".", 1)[0] for path in paths]
    assert set(topics) <= set(trace.topics)
    # Each joint plotted is one the recording names.
    plotted = [p.split('name=="', 1)[1].split('"', 1)[0] for p in paths if "name==" in p]
    assert plotted == [
        "lbr_iiwa_joint_1",
        "lbr_iiwa_joint_2",
        "lbr_iiwa_joint_4",
        "lbr_iiwa_joint_6",
    ]
    assert set(plotted) <= set(KUKA_JOINTS)
    # Every panel of the configuration is placed in the layout tree, once.
    placed: list[str] = []

    def walk(node: object) -> None:
        if isinstance(node, str):
            placed.append(node)
        else:
            assert isinstance(node, dict)
            walk(node["first"])
            walk(node["second"])

    walk(layout["layout"])
    assert sorted(placed) == sorted(panels)


@pytest.mark.pybullet
@needs_record
def test_a_split_process_run_is_recorded_by_the_simulation(kuka: Path, tmp_path: Path) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    path = tmp_path / "split.mcap"
    until = ["--until", str(UNTIL_S)]
    server = subprocess.Popen(
        [sys.executable, "-m", "evclock", "run", "kuka", "--seed", "3", *until, "--quiet",
         "--serve", address, "--remote-controllers", "--record", str(path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )  # fmt: skip
    try:
        controllers = evclock_command(
            "control", "kuka", "--seed", "3", *until, "--clock", address, "--quiet", cwd=tmp_path
        )
        _, err = server.communicate(timeout=120)
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate(timeout=30)
    assert (server.returncode, controllers.returncode) == (3, 3), err + controllers.stderr
    split = evclock.tools.read_trace(path)
    # The controllers ran in another process, in lockstep: the world the simulation recorded
    # is the in-process run's, message for message, bit for bit (its controllers' logging and
    # channels stay in their own process).
    in_process = evclock.tools.read_trace(kuka)  # the same seed and limit, in one process
    for topic in ("/evclock/state", "/evclock/joints", "/evclock/transforms", "/evclock/scene"):
        assert [(m.time_ns, m.data) for m in split.topic(topic)] == [
            (m.time_ns, m.data) for m in in_process.topic(topic)
        ], topic
    assert split.metadata["evclock.run"]["scenario"] == "kuka"
    assert split.metadata["evclock.outcome"]["verdict"] == "cut short"


@pytest.mark.pybullet
def test_the_live_view_without_foxglove_sdk_names_the_extra(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from typer.testing import CliRunner

    import evclock.tools._cli  # noqa: F401  (it registers every command on the app)
    from evclock.tools._cli_app import app

    monkeypatch.setitem(sys.modules, "foxglove", None)
    result = CliRunner().invoke(app, ["run", "kuka", "--foxglove", "--quiet"])
    assert result.exit_code == 2
    assert (
        "error: evclock run --foxglove needs 'foxglove', which is not installed; install it "
        "with: pip install 'evclock[record]'" in " ".join(result.output.split())
    )
    bad = CliRunner().invoke(app, ["run", "kuka", "--foxglove", "--foxglove-addr", "h:x"])
    assert bad.exit_code == 2
    assert "error: --foxglove-addr takes HOST:PORT (default 127.0.0.1:8765), got 'h:x'" in (
        " ".join(bad.output.split())
    )
