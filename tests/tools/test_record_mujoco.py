"""Recording MuJoCo runs (``evclock run --engine mujoco --record``, ``--wall``, split runs):
the same channels and schemas as a PyBullet recording, read back from real MCAP files, with
the world at the run's end, deterministic for a seed. The commands run without PyBullet."""

from __future__ import annotations

import base64
import importlib.util
import json
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from _without_pybullet import CLI_WITHOUT_PYBULLET
from typer.testing import CliRunner

import evclock
from evclock.tools._cli import app

pytest.importorskip("mujoco")
needs_record = pytest.mark.skipif(
    importlib.util.find_spec("mcap") is None, reason="needs evclock[record] (mcap)"
)
pytestmark = needs_record

KUKA_JOINTS = [f"lbr_iiwa_joint_{i}" for i in range(1, 8)]
KUKA_LINKS = [f"lbr_iiwa/lbr_iiwa_link_{i}" for i in range(8)]
WORLD_TOPICS = ("/evclock/state", "/evclock/joints", "/evclock/transforms", "/evclock/scene")
UNTIL_S = 1.5
TIMEOUT_S = 120
runner = CliRunner()


def evclock_mujoco(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI_WITHOUT_PYBULLET, *args, "--engine", "mujoco"],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        cwd=cwd,
        check=False,
    )


@pytest.fixture(scope="module")
def kuka(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """A MuJoCo KUKA run recorded by the real command, and its JSON report."""
    folder = tmp_path_factory.mktemp("kuka")
    path, report = folder / "kuka.mcap", folder / "report.json"
    proc = evclock_mujoco(
        "run", "kuka", "--seed", "3", "--until", str(UNTIL_S), "--record", str(path),
        "--json", str(report), "--quiet", cwd=folder,
    )  # fmt: skip
    assert proc.returncode == 3, proc.stderr  # cut short by --until: no verdict
    return path, json.loads(report.read_text())


def _kinematics(final_state: list[float]) -> Any:
    """The KUKA's MuJoCo data with the poses of ``final_state`` (qpos, qvel, act)."""
    import mujoco

    from evclock_sims import MuJoCoWorld
    from evclock_sims.kuka import KukaReach

    world = MuJoCoWorld()
    KukaReach(world, 3)
    model, data = world.model, world.data
    data.qpos[:] = final_state[: model.nq]
    data.qvel[:] = final_state[model.nq : model.nq + model.nv]
    mujoco.mj_kinematics(model, data)
    return model, data


def test_a_mujoco_recording_holds_the_world_at_the_runs_end(
    kuka: tuple[Path, dict[str, Any]],
) -> None:
    path, report = kuka
    assert report["engine"] == "mujoco"
    trace = evclock.tools.read_trace(path)
    assert set(trace.topics) == {
        "/evclock/clock",
        *WORLD_TOPICS,
        "/evclock/loop/joint_control",
        "/evclock/loop/planner",
    }
    joints = trace.topic("/evclock/joints")
    # Sampled every 0.05 s of sim time, from 0 to the end.
    assert [m.time_ns for m in joints] == [i * 50_000_000 for i in range(len(joints))]
    assert joints[-1].time_ns / 1e9 == report["sim_time_s"] == UNTIL_S
    assert joints[0].data["joints"][1]["position"] == pytest.approx(0.4)  # the rest pose
    final = report["final_state"]  # qpos (7), qvel (7): the arm's joints in order
    last = joints[-1].data["joints"]
    assert [j["name"] for j in last] == KUKA_JOINTS
    assert [j["position"] for j in last] == final[:7]
    assert [j["velocity"] for j in last] == final[7:14]
    assert all(isinstance(j["effort"], float) for j in last)
    assert any(j["effort"] != 0.0 for j in last)  # the servos hold the arm
    state = trace.topic("/evclock/state")[-1].data
    assert list(state) == ["lbr_iiwa"]  # the URDF's robot name, as on PyBullet
    arm = state["lbr_iiwa"]
    assert list(arm["joints"]) == KUKA_JOINTS
    assert [j["position"] for j in arm["joints"].values()] == final[:7]
    assert [j["velocity"] for j in arm["joints"].values()] == final[7:14]
    assert arm["position"] == {"x": 0.0, "y": 0.0, "z": 0.0}  # the fixed base
    # Every link's pose is the final state's (not the pose at the last step's start).
    _, data = _kinematics(final)
    transforms = trace.topic("/evclock/transforms")[-1].data["transforms"]
    assert [t["child_frame_id"] for t in transforms] == KUKA_LINKS
    for body, transform in enumerate(transforms, start=1):
        assert transform["parent_frame_id"] == "world"
        assert list(transform["translation"].values()) == data.xpos[body].tolist()
        w, x, y, z = data.xquat[body].tolist()
        assert transform["rotation"] == {"x": x, "y": y, "z": z, "w": w}
    assert (
        transforms[-1]["translation"]
        != trace.topic("/evclock/transforms")[0].data["transforms"][-1]["translation"]
    )  # the arm moved


def test_the_scene_draws_each_link_s_mesh_as_stl(kuka: tuple[Path, dict[str, Any]]) -> None:
    path, _ = kuka
    scenes = evclock.tools.read_trace(path).topic("/evclock/scene")
    assert len(scenes) == 1  # the robot's shapes, once
    entities = scenes[0].data["entities"]
    assert [e["frame_id"] for e in entities] == KUKA_LINKS
    assert all(e["frame_locked"] for e in entities)
    for entity in entities:
        (model,) = entity["models"]
        assert model["media_type"] == "model/stl"
        stl = base64.b64decode(model["data"])
        triangles = int.from_bytes(stl[80:84], "little")
        assert triangles > 500
        assert len(stl) == 84 + 50 * triangles  # a well-formed binary STL
    # The URDF's colours: the orange links, as PyBullet draws them.
    assert entities[3]["models"][0]["color"]["g"] == pytest.approx(0.4235, abs=1e-4)


def test_trace_info_and_the_shipped_layout_read_a_mujoco_recording(
    kuka: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    path, _ = kuka
    info = evclock_mujoco_trace("info", str(path), cwd=tmp_path)
    assert info.returncode == 0, info.stderr
    assert info.stdout.splitlines()[0] == f"recording: {path} (evclock recording format 2)"
    assert "/evclock/scene               foxglove.SceneUpdate      1" in info.stdout
    written = evclock_mujoco_trace("layout", "-o", str(tmp_path / "layout.json"), cwd=tmp_path)
    assert written.returncode == 0, written.stderr
    layout = json.loads((tmp_path / "layout.json").read_text())  # the installed package's
    panels = layout["configById"]
    paths = [p["value"] for key in ("Plot!joints", "Plot!timing") for p in panels[key]["paths"]]
    plotted = [p.split('name=="', 1)[1].split('"', 1)[0] for p in paths if "name==" in p]
    assert plotted
    assert set(plotted) <= set(KUKA_JOINTS)
    topics = {*panels["3D!evclock"]["topics"], panels["RawMessages!state"]["topicPath"]}
    topics |= {p.split(".", 1)[0] for p in paths}
    trace = evclock.tools.read_trace(path)
    assert topics - {"/evclock/log"} <= set(trace.topics)


def evclock_mujoco_trace(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI_WITHOUT_PYBULLET, "trace", *args],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        cwd=cwd,
        check=False,
    )


def test_a_mujoco_recording_is_deterministic_and_does_not_change_the_run(
    kuka: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    path, report = kuka
    # In this process, paced: the same seed records the same sim-time messages, bit for bit.
    paced = tmp_path / "paced.mcap"
    again = evclock.tools.run_scenario(
        "kuka", seed=3, until=UNTIL_S, rtf=20.0, record=paced, engine="mujoco"
    )
    assert again.final_state == report["final_state"]
    result = runner.invoke(app, ["trace", "diff", str(path), str(paced)])
    assert result.exit_code == 0, result.output
    assert "deterministic messages agree bit for bit" in result.output
    plain = evclock.tools.run_scenario("kuka", seed=3, until=UNTIL_S, engine="mujoco")
    assert plain.final_state == report["final_state"]  # recording changes nothing
    other = tmp_path / "seed4.mcap"
    evclock.tools.run_scenario("kuka", seed=4, until=UNTIL_S, record=other, engine="mujoco")
    divergence = evclock.tools.first_divergence(
        evclock.tools.read_trace(path), evclock.tools.read_trace(other)
    )
    assert divergence is not None  # another seed, other targets: the traces differ


def test_a_mujoco_wall_time_run_runs_to_until_on_the_wall_clock(tmp_path: Path) -> None:
    path, out = tmp_path / "wall.mcap", tmp_path / "report.json"
    start = time.perf_counter()
    proc = evclock_mujoco(
        "run", "kuka", "--wall", "--until", "0.5", "--record", str(path), "--json", str(out),
        "--quiet", cwd=tmp_path,
    )  # fmt: skip
    elapsed = time.perf_counter() - start
    assert proc.returncode == 3, proc.stderr  # cut short by --until
    report = json.loads(out.read_text())
    assert (report["mode"], report["engine"], report["verdict"]) == ("wall", "mujoco", "cut short")
    assert report["sim_time_s"] == report["wall_time_s"]
    assert 0.5 <= report["wall_time_s"] < elapsed
    assert report["achieved_rtf"] == 1.0
    loops = {loop["name"]: loop for loop in report["loops"]}
    # The physics steps at 240 Hz of wall time and the controller runs at 100 Hz: at most one
    # step per 1/240 s for 0.5 s (a loaded machine may miss some: ticks are skipped, never
    # bunched), and both ran on the wall clock.
    assert 2 <= loops["world (physics)"]["stats"]["ticks"] <= 122
    assert 2 <= loops["joint_control"]["stats"]["ticks"] <= 51
    trace = evclock.tools.read_trace(path)
    assert trace.timeline == "wall"
    assert trace.metadata["evclock.run"]["time"] == "wall"
    joints = trace.topic("/evclock/joints")
    assert joints
    for message in joints:
        assert [j["name"] for j in message.data["joints"]] == KUKA_JOINTS
    last = trace.topic("/evclock/state")[-1].data["lbr_iiwa"]["joints"]
    assert last["lbr_iiwa_joint_2"]["position"] != pytest.approx(0.4)  # the arm moved


def test_a_mujoco_split_run_is_recorded_by_the_simulation(
    kuka: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    in_process, _ = kuka
    address = f"unix://{tmp_path / 'sim.sock'}"
    path = tmp_path / "split.mcap"
    until = ["--until", str(UNTIL_S)]
    server = subprocess.Popen(
        [*CLI_WITHOUT_PYBULLET, "run", "kuka", "--seed", "3", *until, "--quiet", "--serve",
         address, "--remote-controllers", "--record", str(path), "--engine", "mujoco"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )  # fmt: skip
    try:
        controllers = evclock_mujoco(
            "control", "kuka", "--seed", "3", *until, "--clock", address, "--quiet", cwd=tmp_path
        )
        _, err = server.communicate(timeout=TIMEOUT_S)
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate(timeout=30)
    assert (server.returncode, controllers.returncode) == (3, 3), err + controllers.stderr
    split, alone = evclock.tools.read_trace(path), evclock.tools.read_trace(in_process)
    for topic in WORLD_TOPICS:
        assert [(m.time_ns, m.data) for m in split.topic(topic)] == [
            (m.time_ns, m.data) for m in alone.topic(topic)
        ], topic
    assert split.metadata["evclock.outcome"]["verdict"] == "cut short"


def test_a_capsule_is_drawn_as_a_cylinder_and_a_sphere_at_each_end() -> None:
    mujoco = pytest.importorskip("mujoco")
    from evclock.tools._world_mujoco import MuJoCoWorldReader

    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body name="b"><freejoint/><geom type="capsule" size="0.1 0.3" '
        'pos="1 2 3" euler="90 0 0"/></body></worldbody></mujoco>'
    )
    (entity,) = MuJoCoWorldReader(model, mujoco.MjData(model)).scene(0)["entities"]
    (cylinder,) = entity["cylinders"]
    assert cylinder["size"] == {"x": 0.2, "y": 0.2, "z": 0.6}
    # The capsule's axis (its z) turned 90 degrees about x: the caps lie along y.
    ends = [sphere["pose"]["position"] for sphere in entity["spheres"]]
    assert ends == [
        {"x": 1.0, "y": pytest.approx(1.7), "z": pytest.approx(3.0)},
        {"x": 1.0, "y": pytest.approx(2.3), "z": pytest.approx(3.0)},
    ]
    assert all(sphere["size"] == {"x": 0.2, "y": 0.2, "z": 0.2} for sphere in entity["spheres"])
