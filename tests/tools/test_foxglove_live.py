"""The live view (``evclock run kuka --foxglove``) checked with a real WebSocket client
speaking Foxglove's protocol: the subprotocol, the channels advertised with their schemas,
messages stamped with sim time, the sim-time broadcast and the pause/step/resume services."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import re
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any
from xml.etree import ElementTree

import pytest
from _cli import run_evclock

if TYPE_CHECKING:
    from websockets.sync.client import ClientConnection

needs_live = pytest.mark.skipif(
    importlib.util.find_spec("foxglove") is None or importlib.util.find_spec("websockets") is None,
    reason="needs evclock[record] (foxglove-sdk) and websockets",
)
KUKA_JOINTS = [f"lbr_iiwa_joint_{i}" for i in range(1, 8)]
SUBPROTOCOL = "foxglove.sdk.v1"
WAIT_S = 30.0  # bound on every wait for the server


class Client:
    """A minimal Foxglove WebSocket client: JSON text ops and the binary frames."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.ops: dict[str, list[dict[str, Any]]] = {}
        self.data: list[tuple[int, int, Any]] = []  # (subscription, log time, message)
        self.times: list[int] = []
        self.responses: dict[int, bytes] = {}
        self.playback: dict[str, tuple[int, int, float]] = {}  # request id: status, time, speed

    def receive(self) -> None:
        frame = self.ws.recv(timeout=WAIT_S)
        if isinstance(frame, str):
            message = json.loads(frame)
            self.ops.setdefault(message["op"], []).append(message)
            return
        opcode = frame[0]
        if opcode == 1:
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            self.data.append((subscription, log_time, json.loads(frame[13:])))
        elif opcode == 2:
            self.times.append(struct.unpack_from("<Q", frame, 1)[0])
        elif opcode == 3:
            _service, call, length = struct.unpack_from("<III", frame, 1)
            self.responses[call] = frame[13 + length :]
        elif opcode == 5:  # playback state
            status, now, speed, _seek, length = struct.unpack_from("<BQfBI", frame, 1)
            self.playback[frame[19 : 19 + length].decode()] = (status, now, speed)

    def until(self, condition: Any) -> None:
        while not condition():
            self.receive()

    def control_playback(self, play: bool, speed: float, request: str) -> tuple[int, int, float]:
        frame = struct.pack("<BBfBQI", 3, 0 if play else 1, speed, 0, 0, len(request))
        self.ws.send(frame + request.encode())
        self.until(lambda: request in self.playback)
        return self.playback[request]

    def channels(self) -> dict[str, dict[str, Any]]:
        return {c["topic"]: c for op in self.ops.get("advertise", []) for c in op["channels"]}

    def call(self, service_id: int, call_id: int, payload: dict[str, Any]) -> dict[str, Any]:
        body = json.dumps(payload).encode()
        self.ws.send(struct.pack("<BIII", 2, service_id, call_id, 4) + b"json" + body)
        self.until(lambda: call_id in self.responses or "serviceCallFailure" in self.ops)
        assert "serviceCallFailure" not in self.ops, self.ops["serviceCallFailure"]
        answer: dict[str, Any] = json.loads(self.responses[call_id])
        return answer


@contextlib.contextmanager
def _live_view(cwd: Path, *args: str) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``evclock *args`` with a live view on a free loopback port: the process and the
    view's URL; the process is killed if it still runs on the way out."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "evclock", *args, "--foxglove", "--foxglove-addr", "127.0.0.1:0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # the announcement comes before the run starts
        match = re.search(r"live view at (ws://127\.0\.0\.1:\d+)", line)
        assert match is not None, line + proc.stderr.read()
        yield proc, match.group(1)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=WAIT_S)


@pytest.fixture
def live_run(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    run = ["run", "kuka", "--seed", "1", "--until", "10", "--param", "tolerance=0.03"]
    with _live_view(tmp_path, *run, "--json", "report.json", "--quiet") as live:
        yield live


@pytest.mark.pybullet
@needs_live
def test_a_foxglove_client_sees_the_channels_on_sim_time(
    live_run: tuple[subprocess.Popen[str], str], tmp_path: Path
) -> None:
    from websockets.sync.client import connect

    proc, url = live_run
    with connect(url, subprotocols=[SUBPROTOCOL], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
        last_time_ns = _watch(proc, Client(ws))
    report = json.loads((tmp_path / "report.json").read_text())  # the run's, in its cwd
    # The run's end is broadcast last, but the Foxglove SDK's stop drops what it has not sent
    # yet: a viewer sees the end or a sample before it, never a time after it.
    end_ns = round(report["sim_time_s"] * 1e9)
    assert 0 < last_time_ns <= end_ns


def _watch(proc: subprocess.Popen[str], client: Client) -> int:
    from websockets.exceptions import ConnectionClosedOK

    assert client.ws.subprotocol == SUBPROTOCOL
    client.until(lambda: "serverInfo" in client.ops and "advertiseServices" in client.ops)
    info = client.ops["serverInfo"][0]
    assert info["name"] == "evclock kuka"
    assert {"time", "services", "parameters", "playbackControl"} <= set(info["capabilities"])
    # The playback range Foxglove's timeline shows: sim time 0 to the --until limit.
    assert info["dataStartTime"] == {"sec": 0, "nsec": 0}
    assert info["dataEndTime"] == {"sec": 10, "nsec": 0}
    # The scenario's parameters (with --param applied) and the seed, read-only.
    client.ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "p"}))
    client.until(lambda: "parameterValues" in client.ops)
    values = {p["name"]: p["value"] for p in client.ops["parameterValues"][0]["parameters"]}
    assert values["/scenario/seed"] == 1
    assert values["/scenario/tolerance"] == 0.03
    assert values["/scenario/planner_hz"] == 10.0
    client.until(lambda: {"/evclock/clock", "/evclock/joints"} <= set(client.channels()))
    channels = client.channels()
    assert channels["/evclock/joints"]["schemaName"] == "foxglove.JointStates"
    assert channels["/evclock/joints"]["encoding"] == "json"
    assert channels["/evclock/transforms"]["schemaName"] == "foxglove.FrameTransforms"
    assert channels["/evclock/clock"]["schemaName"] == "evclock.Clock"
    subscriptions = {1: "/evclock/clock", 2: "/evclock/joints"}
    client.ws.send(
        json.dumps(
            {
                "op": "subscribe",
                "subscriptions": [
                    {"id": i, "channelId": channels[t]["id"]} for i, t in subscriptions.items()
                ],
            }
        )
    )
    client.until(lambda: sum(s == 2 for s, _, _ in client.data) >= 5 and len(client.times) >= 5)
    for subscription, log_time, message in client.data:
        # Every message's timestamp is sim time, in integer ns, on the 0.05 s sample grid.
        assert log_time % 50_000_000 == 0
        if subscription == 1:
            assert round(message["sim_time_s"] * 1e9) == log_time
        else:
            assert message["timestamp"] == {"sec": log_time // 10**9, "nsec": log_time % 10**9}
            assert [j["name"] for j in message["joints"]] == KUKA_JOINTS
    assert all(t % 50_000_000 == 0 for t in client.times)
    assert client.times == sorted(client.times)

    services = {s["name"]: s["id"] for s in client.ops["advertiseServices"][0]["services"]}
    assert set(services) == {"/evclock/pause", "/evclock/resume", "/evclock/step"}
    assert client.call(services["/evclock/pause"], 1, {}) == {}
    assert client.call(services["/evclock/step"], 2, {"steps": 24}) == {}
    assert client.call(services["/evclock/resume"], 3, {}) == {}
    # Foxglove's playback controls: pause, then play at 20x real time (its speed sets the
    # real-time factor); status 1 is paused, 0 playing.
    assert client.control_playback(False, 1.0, "pause")[0] == 1
    status, _now, speed = client.control_playback(True, 20.0, "play")
    assert (status, speed) == (0, 20.0)
    # Playing, the mission goes on to its end (success: status 0), where the server says
    # goodbye.
    with pytest.raises(ConnectionClosedOK):
        client.until(lambda: False)
    assert proc.wait(timeout=WAIT_S) == 0
    return client.times[-1]


@needs_live
def test_what_a_late_viewer_is_sent_never_goes_into_the_recording(tmp_path: Path) -> None:
    """A viewer subscribing to the scene mid-run is sent it again, live only: the recording
    of the watched run is the unwatched one's, bit for bit (and holds the scene once)."""
    from mcap.reader import make_reader
    from websockets.exceptions import ConnectionClosedOK
    from websockets.sync.client import connect

    run = ["run", "kuka", "--engine", "mujoco", "--seed", "3", "--until", "2", "--quiet"]
    with _live_view(tmp_path, *run, "--record", "watched.mcap") as (proc, url):
        with connect(url, subprotocols=[SUBPROTOCOL], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
            client = Client(ws)
            client.until(lambda: any(t > 0 for t in client.times))  # the run is under way
            scene = client.channels()["/evclock/scene"]["id"]
            client.ws.send(
                json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": scene}]})
            )
            client.until(lambda: any(s == 7 for s, _, _ in client.data))
            assert all(m["entities"] and t > 0 for s, t, m in client.data if s == 7)
            with pytest.raises(ConnectionClosedOK):
                client.until(lambda: False)
        watched = proc.wait(timeout=WAIT_S)
    plain = run_evclock(*run, "--record", "plain.mcap", cwd=tmp_path)
    # 2 s is too short for the mission: both runs end at the limit (exit status 3).
    assert (watched, plain.returncode) == (3, 3), plain.stderr
    with (tmp_path / "watched.mcap").open("rb") as f:
        scenes = [
            m.log_time for _, c, m in make_reader(f).iter_messages() if c.topic == "/evclock/scene"
        ]
    assert scenes == [0]
    diff = run_evclock("trace", "diff", "watched.mcap", "plain.mcap", cwd=tmp_path)
    assert diff.returncode == 0, diff.stdout + diff.stderr


def _drawn_links() -> set[str]:
    """The frames of the KUKA model's links that have a visual (``robot/link``), read from
    the URDF both engines load."""
    from evclock_sims._mujoco import model_path  # the installed scenarios' copy, as CI runs

    robot = ElementTree.parse(model_path("kuka_iiwa/model.urdf")).getroot()
    return {
        f"{robot.get('name')}/{link.get('name')}"
        for link in robot.iter("link")
        if link.find("visual") is not None
    }


class Viewer(Client):
    """A client as Foxglove is one: it subscribes to every channel once, when it is
    advertised, and never asks again."""

    def __init__(self, ws: ClientConnection) -> None:
        super().__init__(ws)
        self.topics: dict[int, str] = {}  # subscription id -> topic

    def receive(self) -> None:
        advertised = len(self.ops.get("advertise", []))
        super().receive()
        for op in self.ops.get("advertise", [])[advertised:]:
            subscriptions = []
            for channel in op["channels"]:
                self.topics[len(self.topics) + 1] = channel["topic"]
                subscriptions.append({"id": len(self.topics), "channelId": channel["id"]})
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def scenes(self) -> list[tuple[int, Any]]:
        return [(t, m) for s, t, m in self.data if self.topics[s] == "/evclock/scene"]


def _sees_the_robot(viewer: Viewer, joined_at_ns: int = 0) -> None:
    """``viewer`` is sent the scene, drawing every link of the model with a visual, stamped
    at or after ``joined_at_ns``."""
    # Told of the world's channels as it connects, whenever that is.
    viewer.until(lambda: "advertise" in viewer.ops)
    first = {c["topic"] for c in viewer.ops["advertise"][0]["channels"]}
    assert {"/evclock/scene", "/evclock/joints", "/evclock/transforms"} <= first, first
    viewer.until(lambda: bool(viewer.scenes()))
    refused = [op["message"] for op in viewer.ops.get("status", [])]
    scene_id = viewer.channels()["/evclock/scene"]["id"]
    assert f"Unknown channel ID: {scene_id}" not in refused, refused
    stamp, scene = viewer.scenes()[0]
    assert stamp >= joined_at_ns
    entities = {e["id"]: e for e in scene["entities"]}
    assert set(entities) == _drawn_links()
    for frame, entity in entities.items():
        assert entity["frame_id"] == frame
        assert entity["frame_locked"] is True
        assert entity["models"] or entity["cubes"] or entity["cylinders"], frame


@contextlib.contextmanager
def _viewer(url: str) -> Iterator[Viewer]:
    from websockets.sync.client import connect

    with connect(url, subprotocols=[SUBPROTOCOL], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
        yield Viewer(ws)


ENGINES = [pytest.param("pybullet", marks=pytest.mark.pybullet), "mujoco"]
LONG_RUN = ["--seed", "1", "--until", "60", "--param", "dwell=60", "--quiet"]  # no early end


@needs_live
@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(
    "options", [[], ["--rtf", "2", "--record", "run.mcap"]], ids=["live", "live-record"]
)
def test_every_viewer_sees_the_robot(engine: str, options: list[str], tmp_path: Path) -> None:
    """A viewer connecting as the run starts is sent the scene: the model's links, drawn;
    so is one connecting later, while the run is paused (it takes no samples then)."""
    run = ["run", "kuka", "--engine", engine, *LONG_RUN, *options]
    with _live_view(tmp_path, *run) as (_proc, url), _viewer(url) as early:
        _sees_the_robot(early)
        early.until(lambda: any(t > 0 for t in early.times))  # the run is under way
        services = {s["name"]: s["id"] for s in early.ops["advertiseServices"][0]["services"]}
        assert early.call(services["/evclock/pause"], 1, {}) == {}
        with _viewer(url) as late:
            _sees_the_robot(late, joined_at_ns=early.times[-1])


@needs_live
@pytest.mark.parametrize("engine", ENGINES)
def test_a_viewer_of_a_split_run_sees_the_robot(engine: str, tmp_path: Path) -> None:
    """The simulation of a split run serves the live view: its viewers see the robot while
    the controllers run in another process."""
    address = f"unix://{tmp_path / 'sim.sock'}"
    # --serve runs the scenario as registered (no --param): its mission, at real time, lasts
    # seconds of wall time after the controllers join, long after both viewers saw the scene.
    run = ["--seed", "1", "--quiet"]
    sim = ["run", "kuka", "--engine", engine, *run, "--serve", address, "--remote-controllers"]
    with _live_view(tmp_path, *sim) as (_proc, url):
        controllers = subprocess.Popen(
            [sys.executable, "-m", "evclock", "control", "kuka", "--engine", engine, *run,
             "--clock", address],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        )  # fmt: skip
        try:
            with _viewer(url) as early:
                _sees_the_robot(early)
                early.until(lambda: bool(early.times))
                with _viewer(url) as late:
                    _sees_the_robot(late, joined_at_ns=early.times[-1])
        finally:
            controllers.kill()
            controllers.communicate(timeout=WAIT_S)
