"""The robot as ROS tools expect it, and waiting for the ROS side: frame prefixes, the URDF on
``/robot_description``, ``--ros2-wait-for-subscribers``; what they refuse, and why.

The rclpy side of these features is in ``tests/ros2/interop``; here evclock's own checks, and a
simulation that waits for subscribers that never come.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest

import evclock
from evclock import InvalidArgumentError, InvalidTypeError, NotRunningError, Time
from evclock.ros2 import Ros2ClockPublisher, Ros2SubscribersError
from evclock.ros2._wire import check_frame_prefix
from evclock.tools._ros2_state import robot_description

pytest.importorskip("cyclonedds", reason="needs evclock[ros2] (cyclonedds)")

ROOT = Path(__file__).resolve().parents[2]
EVCLOCK_RUN = (sys.executable, "-m", "evclock", "run", "kuka", "--engine", "mujoco")


@pytest.mark.parametrize("prefix", ["", "robot1/", "arm_2", "fleet/robot1/"])
def test_frame_prefixes_robot_state_publisher_takes(prefix: str) -> None:
    assert check_frame_prefix(prefix) == prefix


@pytest.mark.parametrize("prefix", ["/robot1/", "robot 1/", "robot-1/", "a//b", "robot1/é"])
def test_an_illegal_frame_prefix_is_refused(prefix: str) -> None:
    with pytest.raises(InvalidArgumentError, match=r"invalid frame prefix .*e\.g\. 'robot1/'"):
        check_frame_prefix(prefix)


def test_a_frame_prefix_is_a_string() -> None:
    with pytest.raises(InvalidTypeError, match="frame_prefix must be a str, got int"):
        check_frame_prefix(3)


def test_robot_description_makes_mesh_paths_absolute_uris(tmp_path: Path) -> None:
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(
        '<robot name="arm"><link name="base"><visual><geometry>'
        '<mesh filename="meshes/base.stl"/></geometry></visual></link>'
        '<link name="tool"><visual><geometry><mesh filename="package://arm/tool.stl"/>'
        "</geometry></visual></link></robot>"
    )
    text = robot_description(urdf)
    assert f'filename="{(tmp_path / "meshes" / "base.stl").as_uri()}"' in text
    assert 'filename="package://arm/tool.stl"' in text  # URIs are left as they are
    assert text.startswith('<robot name="arm">')


def test_a_urdf_that_cannot_be_read_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgumentError, match=r"cannot read the URDF .*missing\.urdf"):
        robot_description(tmp_path / "missing.urdf")
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='arm'><link name='base'>")
    with pytest.raises(InvalidArgumentError, match=r"the URDF .*broken\.urdf is not XML"):
        robot_description(broken)
    sdf = tmp_path / "world.sdf"
    sdf.write_text("<sdf version='1.9'/>")
    with pytest.raises(InvalidArgumentError, match=r"its root element is <sdf>, not <robot>"):
        robot_description(sdf)


def error_line(*options: str) -> str:
    """The one error line ``evclock run kuka --engine mujoco OPTIONS`` ends with (status 2)."""
    result = subprocess.run(
        [*EVCLOCK_RUN, *options], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (("--ros2", "--ros2-frame-prefix", "robot 1/"), "invalid frame prefix 'robot 1/'"),
        (("--ros2-clock", "--ros2-frame-prefix", "r1/"), "--ros2-frame-prefix names the robot"),
        (("--ros2-clock", "--ros2-wait-for-subscribers", "0"), "must be >= 1"),
        (("--ros2-clock", "--ros2-wait-for-subscribers", "-2"), "must be >= 1"),
        (
            ("--ros2-clock", "--ros2-wait-for-subscribers", "1", "--ros2-wait-timeout", "0"),
            "--ros2-wait-timeout must be a positive number of seconds, got 0",
        ),
        (
            ("--ros2-clock", "--ros2-wait-for-subscribers", "1", "--ros2-wait-timeout", "nan"),
            "--ros2-wait-timeout must be a positive number of seconds, got nan",
        ),
        (("--ros2-clock", "--ros2-wait-timeout", "5"), "only with --ros2-wait-for-subscribers"),
        (
            (
                "--ros2-wait-for-subscribers",
                "1",
            ),
            "only with --ros2-clock or --ros2",
        ),
    ],
)
def test_cli_bad_ros2_options_are_one_error_line(options: tuple[str, ...], message: str) -> None:
    line = error_line(*options)
    assert line.startswith("error:")
    assert message in line


def test_a_simulation_without_its_subscribers_fails_saying_what_it_waited_for(
    loopback_dds: int,
) -> None:
    result = subprocess.run(
        [
            *EVCLOCK_RUN,
            "--ros2-clock",
            "--ros2-wait-for-subscribers",
            "2",
            "--ros2-wait-timeout",
            "0.5",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=ROOT,
    )
    output = result.stdout + result.stderr
    assert "0 of 2 /clock subscription(s) matched in 0.5 s" in output, output
    assert f"domain {loopback_dds}" in output
    assert result.returncode == 2, output


def test_waiting_holds_sim_time_and_publishes_the_held_time(loopback_dds: int) -> None:
    # Nobody subscribes in this domain: while the wait lasts, a sim-time sleeper never wakes
    # (sim time is held at 0: no advance, no deadlock reported although nothing else could
    # wake the loop), and the held time is published again and again.
    with Ros2ClockPublisher() as publisher:

        async def main() -> tuple[int, list[Time]]:
            clk = evclock.clock()
            woke: list[Time] = []

            async def sleeper() -> None:
                await clk.sleep(0.1)
                woke.append(clk.now())

            task = asyncio.create_task(sleeper())
            with pytest.raises(Ros2SubscribersError, match=r"0 of 1 /clock subscription"):
                await publisher.wait_for_subscribers(1, timeout=0.3)
            held = (publisher.sequence_number, list(woke))
            await task
            assert woke == [Time(0, 100_000_000)]  # released: time moves again
            return held[0], held[1]

        sent, woken = evclock.run(main())
    assert woken == []
    assert sent >= 2


def test_wait_for_subscribers_refuses_bad_input_and_foreign_loops(loopback_dds: int) -> None:
    with Ros2ClockPublisher() as publisher:

        async def wait(count: object, timeout: object) -> None:
            await publisher.wait_for_subscribers(count, timeout=timeout)  # type: ignore[arg-type]

        for count, timeout, error, match in [
            (0, 1.0, InvalidArgumentError, "count must be >= 1"),
            (True, 1.0, InvalidTypeError, "count must be an int, got bool"),
            (1, 0.0, InvalidArgumentError, "timeout must be a positive number of seconds"),
            (1, float("inf"), InvalidArgumentError, "timeout must be a positive number"),
            (1, "5", InvalidTypeError, "timeout must be a number of seconds, got str"),
        ]:
            with pytest.raises(error, match=match):
                evclock.run(wait(count, timeout))
        with pytest.raises(NotRunningError, match="await it on a simulation's loop"):
            asyncio.run(wait(1, 1.0))


def test_ros2_robot_state_in_python_names_frames_behind_a_prefix(loopback_dds: int) -> None:
    # The Python face of `evclock run --ros2 --ros2-frame-prefix`: a MuJoCo world built from
    # the KUKA's URDF, its frames behind "robot2/" and its URDF on /robot_description.
    pytest.importorskip("mujoco")
    from evclock.sources import MuJoCoTimeSource
    from evclock.tools import ros2_robot_state
    from evclock_sims._mujoco import model_path, urdf_to_mujoco

    urdf = model_path("kuka_iiwa/model.urdf")
    model = urdf_to_mujoco(urdf)
    import mujoco

    source = MuJoCoTimeSource(model, mujoco.MjData(model))
    try:
        with ros2_robot_state(source, urdf=str(urdf), frame_prefix="robot2/") as publisher:
            assert publisher.robot_description == robot_description(urdf)
            assert publisher.published == 1  # the start, at once
            frames = {t.child_frame_id for t in publisher.tf(0).transforms}
        assert frames == {f"robot2/lbr_iiwa_link_{k}" for k in range(1, 8)}  # link_0 is static
        with (
            pytest.raises(InvalidArgumentError, match="invalid frame prefix 'robot 2'"),
            ros2_robot_state(source, frame_prefix="robot 2"),
        ):
            pass
        with (
            pytest.raises(InvalidTypeError, match="urdf must be a path"),
            ros2_robot_state(source, urdf=3),  # type: ignore[arg-type]
        ):
            pass
        with (
            pytest.raises(InvalidArgumentError, match="decimation must be >= 1"),
            ros2_robot_state(source, decimation=0),
        ):
            pass
    finally:
        source.close()
