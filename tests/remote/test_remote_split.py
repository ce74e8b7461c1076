"""Acceptance: a scenario's controllers in another process, in lockstep, end bit-identical.

``evclock run SIM --serve ADDR --remote-controllers`` runs the physics; ``evclock control SIM
--clock ADDR`` runs the controllers in a second process. Their final physical state must equal
the in-process ``evclock run`` of the same seed, bit for bit, flat out and paced.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from _remote_helpers import ROOT, WAIT, WAKE_TIMES, finish, spawn
from _without_pybullet import CLI_WITHOUT_PYBULLET

from evclock.remote import ParticipantLostError
from evclock.tools._cli import run_scenario
from evclock.tools._cli_remote import serve_scenario

CLI = [sys.executable, "-c", "from evclock.tools._cli import main; main()"]


def evclock_cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def wait(proc: subprocess.Popen[str]) -> tuple[int, str]:
    try:
        out, err = proc.communicate(timeout=WAIT * 3)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=WAIT)
    return proc.returncode, out + err


def evclock_cli_mujoco(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI_WITHOUT_PYBULLET, *args, "--engine", "mujoco"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


PYBULLET = pytest.mark.pybullet


@pytest.mark.parametrize(
    ("engine", "name", "until", "rtf"),
    [
        pytest.param("pybullet", "kuka", None, "max", marks=PYBULLET),  # the whole mission
        pytest.param("pybullet", "cartpole", "5", "max", marks=PYBULLET),
        # ray casts and contact queries across processes too
        pytest.param("pybullet", "husky", "2", "max", marks=PYBULLET),
        pytest.param("pybullet", "kuka", "1.5", "3", marks=PYBULLET),  # paced
        pytest.param("pybullet", "cartpole", "1.5", "3", marks=PYBULLET),
        ("mujoco", "kuka", None, "max"),  # without PyBullet, on either end
        ("mujoco", "cartpole", "2", "max"),
        ("mujoco", "kuka", "1.5", "3"),
    ],
)
def test_split_run_ends_bit_identical_to_the_in_process_run(
    tmp_path: Path, engine: str, name: str, until: str | None, rtf: str
) -> None:
    cli = evclock_cli_mujoco if engine == "mujoco" else evclock_cli
    limit = [] if until is None else ["--until", until]
    address = f"unix://{tmp_path / 'sim.sock'}"
    server = cli(
        "run", name, *limit, "--rtf", rtf, "--quiet", "--seed", "3",
        "--serve", address, "--remote-controllers", "--json", str(tmp_path / "sim.json"),
    )  # fmt: skip
    controllers = cli(
        "control", name, *limit, "--seed", "3", "--clock", address, "--quiet",
        "--json", str(tmp_path / "controllers.json"),
    )  # fmt: skip
    ctrl_code, ctrl_output = wait(controllers)
    sim_code, sim_output = wait(server)
    expected_code = 0 if until is None else 3  # cut short by --until: no verdict
    assert (sim_code, ctrl_code) == (expected_code, expected_code), sim_output + ctrl_output

    in_process = run_scenario(
        name, until=None if until is None else float(until), seed=3, rtf=None, engine=engine
    ).to_json()
    served = json.loads((tmp_path / "sim.json").read_text())
    joined = json.loads((tmp_path / "controllers.json").read_text())
    assert served["engine"] == joined["engine"] == in_process["engine"] == engine
    assert served["final_state"] == in_process["final_state"]  # bit for bit
    assert joined["final_state"] == in_process["final_state"]
    assert served["sim_time_s"] == joined["sim_time_s"] == in_process["sim_time_s"]
    assert served["summary"] == joined["summary"] == in_process["summary"]
    assert served["verdict"] == in_process["verdict"]
    assert [loop["stats"]["ticks"] for loop in served["loops"]] == [
        loop["stats"]["ticks"] for loop in in_process["loops"]
    ]
    # Both sides know the physics step (the simulation serves it): whether each loop's
    # deadlines fall on physics steps is the in-process run's, never unknown.
    steps = [loop["on_physics_steps"] for loop in in_process["loops"]]
    assert None not in steps
    assert [loop["on_physics_steps"] for loop in served["loops"]] == steps
    assert [loop["on_physics_steps"] for loop in joined["loops"]] == steps
    assert served["physics_step_s"] == joined["physics_step_s"] == in_process["physics_step_s"]


@pytest.mark.pybullet
@pytest.mark.parametrize(
    ("served", "joining", "says"),
    [
        (["--engine", "mujoco"], [], "runs 'kuka' on mujoco, but these controllers are for "
         "pybullet; use the same engine on both (--engine mujoco)"),
        ([], ["--engine", "mujoco"], "runs 'kuka' on pybullet, but these controllers are for "
         "mujoco; use the same engine on both (--engine pybullet)"),
    ],
)  # fmt: skip
def test_controllers_for_another_engine_are_refused(
    tmp_path: Path, served: list[str], joining: list[str], says: str
) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    server = evclock_cli("run", "kuka", *served, "--quiet", "--serve", address,
                         "--remote-controllers")  # fmt: skip
    wrong = evclock_cli("control", "kuka", *joining, "--clock", address)
    code, output = wait(wrong)
    server.kill()
    wait(server)
    assert code == 2
    assert f"error: the simulation at {address} {says}" in " ".join(output.split())


@pytest.mark.pybullet
def test_controllers_for_another_scenario_or_seed_are_refused(tmp_path: Path) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    server = evclock_cli(
        "run", "kuka", "--quiet", "--serve", address, "--remote-controllers"
    )  # fmt: skip
    wrong = evclock_cli("control", "kuka", "--seed", "1", "--clock", address)
    code, output = wait(wrong)
    server.kill()
    wait(server)
    assert code == 2
    assert (
        f"error: the simulation at {address} runs 'kuka' with seed 0, but these controllers "
        "are 'kuka' with seed 1; use the same on both" in " ".join(output.split())
    )


@pytest.mark.pybullet
def test_controllers_that_leave_without_their_report_are_a_lost_participant(
    tmp_path: Path,
) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    silent = spawn(
        tmp_path,
        "import evclock\nasync def main(): pass\nevclock.run(main())\n",
        EVCLOCK_CLOCK=f"{address}?name=controllers",
    )  # started first: it waits for the server to appear
    try:
        with pytest.raises(
            ParticipantLostError,
            match=r"^the controllers left at [0-9.e+-]+ s without handing over their report; "
            r"see the output of `evclock control` for why$",
        ) as info:
            serve_scenario("kuka", address=address, remote_controllers=True)
    finally:
        code, _, err = finish(silent)
    assert info.value.name == "controllers"
    assert code == 0, err


def test_remote_controllers_needs_serve() -> None:
    code, output = wait(evclock_cli("run", "kuka", "--remote-controllers", "--quiet"))
    assert code == 2
    assert "error: --remote-controllers needs --serve ADDR" in output


@pytest.mark.parametrize(
    ("clock", "says"),
    [
        ("ros2:///clock", "got 'ros2:///clock': only an evclock clock server runs"),
        ("tcp://127.0.0.1", "a tcp clock address is tcp://HOST:PORT"),
    ],
)
def test_control_needs_an_evclock_clock_server_address(clock: str, says: str) -> None:
    code, output = wait(evclock_cli("control", "kuka", "--clock", clock))
    assert code == 2
    assert "error: " in output
    assert says in " ".join(output.split())


@pytest.mark.pybullet
def test_a_served_in_process_run_can_be_followed(tmp_path: Path) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    # The follower is started first: it waits for the server to appear.
    follower = spawn(
        tmp_path, WAKE_TIMES, "5", "0.1", EVCLOCK_CLOCK=f"{address}?mode=follow&name=observer"
    )
    code, output = wait(evclock_cli("run", "kuka", "--until", "3", "--rtf", "1", "--quiet",
                                    "--serve", address))  # fmt: skip
    seen_code, seen = wait(follower)
    assert code == 3, output  # the mission needs more than 3 s: cut short, no verdict
    assert seen_code == 0, seen
    times = json.loads(seen.splitlines()[-1])
    step = 1_000_000_000 / 240
    assert len(times) == 5
    assert all(abs(t / step - round(t / step)) < 1e-6 for t in times)  # physics step times
    assert times == sorted(times)


def test_the_controllers_read_the_served_physics_step() -> None:
    from fractions import Fraction

    from evclock import InvalidArgumentError
    from evclock.tools._cli_remote import _served_step_ns

    assert _served_step_ns({"physics_step_ns": [12500000, 3]}, "unix:///s") == Fraction(12500000, 3)
    assert _served_step_ns({}, "unix:///s") is None  # a server that does not say (0.2)
    for bad in ([1], [0, 3], [1.5, 3], "1/240", [True, 3]):
        with pytest.raises(InvalidArgumentError) as raised:
            _served_step_ns({"physics_step_ns": bad}, "unix:///s")
        assert str(raised.value) == (
            f"the simulation at unix:///s serves a malformed physics step {bad!r}: expected "
            "[numerator, denominator] in nanoseconds, two positive integers"
        )
