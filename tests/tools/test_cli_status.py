"""A CLI that says what happened: every exit status and error message of ``evclock run``
through the real command in a subprocess (0 success, 1 failed criterion, 2 usage error, 3 cut
short, 4 the scenario or a controller raised, 130 Ctrl-C with the partial report), help texts
that render intact, ``evclock params``, and no library banner on the terminal."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from _cli import interrupt_when, run_evclock

import evclock
from evclock.tools._cli_app import EXIT_STATUS_HELP

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 240  # wall seconds: a guard against hangs on a loaded machine, not a timing check

pytestmark = pytest.mark.pybullet

#: Raises while setting up its world (``where=setup``) or in its mission (``where=run``);
#: with ``marker`` set, its mission writes that file and then waits 1000 s of sim time.
RAISING = """\
from pathlib import Path

from evclock_sims.cartpole import CartPole


class Raising(CartPole):
    name = "raising"
    description = "raises in set-up or in its mission"
    default_until = 2000.0
    where = "run"
    marker = ""

    def __init__(self, client: int, seed: int = 0) -> None:
        if self.where == "setup":
            raise RuntimeError("broken world")
        super().__init__(client, seed)

    async def _mission(self, clock):
        await clock.sleep(0.5)
        if self.marker:
            Path(self.marker).write_text("started")
            await clock.sleep(1000.0)
        raise ValueError("controller blew up\\nsecond line of the message")
"""


def line_of(text: str) -> int:
    """The line of RAISING that holds ``text``."""
    return next(i for i, line in enumerate(RAISING.splitlines(), 1) if text in line)


@pytest.fixture
def raising(tmp_path: Path) -> str:
    path = tmp_path / "raising.py"
    path.write_text(RAISING)
    return str(path)


def evclock_cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return run_evclock(*args, cwd=cwd)


def test_success_is_0_and_no_banner_reaches_the_terminal(tmp_path: Path) -> None:
    proc = evclock_cli("run", "kuka", "--quiet", "--json", str(tmp_path / "r.json"))
    assert proc.returncode == 0, proc.stderr
    assert "kuka (seed 0): SUCCESS" in proc.stdout
    assert proc.stderr == ""  # not even PyBullet's "pybullet build time" line
    assert "pybullet build time" not in proc.stdout
    assert json.loads((tmp_path / "r.json").read_text())["verdict"] == "success"


def test_a_failed_criterion_is_1() -> None:
    proc = evclock_cli("run", "cartpole", "--param", "fail_angle=0.01", "--quiet")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "cartpole (seed 0): FAILED" in proc.stdout


def test_cut_short_is_3() -> None:
    proc = evclock_cli("run", "cartpole", "--until", "0.2", "--quiet")
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert "cartpole (seed 0): CUT SHORT at --until 0.2 s" in " ".join(proc.stdout.split())


USAGE_ERRORS = [
    (["--seed", "-5"], "error: --seed takes a whole number from 0 to 4294967295, got -5"),
    (["--seed", "x"], "error: Invalid value for '--seed'"),
    (["--until", "-1"], "error: --until must be a positive number of seconds, got -1.0"),
    (["--until", "nan"], "error: --until must be a positive number of seconds, got nan"),
    (["--rtf", "0"], "error: --rtf takes 'max' (as fast as possible) or a positive number"),
    (["--rtf", "nan"], "error: --rtf takes 'max' (as fast as possible) or a positive number"),
    (["--param", "nope=1"], "error: scenario 'kuka' has no parameter 'nope'; its parameters:"),
    (["--param", "dwell=x"], "error: parameter dwell takes a finite float"),
    (["--param", "dwell=1,2"], "error: evclock run takes one value per --param (dwell)"),
    (["--sede", "1"], "error: No such option: --sede (Possible options: --seed"),
    (["--remote-controllers"], "error: --remote-controllers needs --serve ADDR"),
    (
        ["--tls-cert", "c.pem"],
        "error: --tls-cert, --tls-key and --allow-remote need --serve tls://",
    ),
]


def test_usage_errors_are_one_line_and_2() -> None:
    for args, message in USAGE_ERRORS:
        proc = evclock_cli("run", "kuka", "--quiet", *args)
        assert proc.returncode == 2, (args, proc.stdout, proc.stderr)
        assert proc.stderr.startswith(message), (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert proc.stdout == "", proc.stdout
    unknown = evclock_cli("run", "nope")
    assert unknown.returncode == 2
    assert unknown.stdout == ""
    assert unknown.stderr == (
        "error: unknown scenario 'nope'; registered names: cartpole, fusion, husky, kuka "
        "(or give a file path.py or a module:Class)\n"
    )
    missing = evclock_cli("run")
    assert missing.returncode == 2
    assert missing.stderr == "error: Missing argument 'scenario'; see 'evclock run --help'\n"


def test_a_controller_that_raises_is_4_with_one_line_and_the_traceback_in_the_report(
    raising: str, tmp_path: Path
) -> None:
    out = tmp_path / "r.json"
    proc = evclock_cli("run", raising, "--quiet", "--json", str(out))
    assert proc.returncode == 4, proc.stdout + proc.stderr
    assert proc.stderr == (
        "error: raising (seed 0) raised ValueError: controller blew up while running the "
        f"controllers, in Raising._mission ({raising}:{line_of('raise ValueError')}); the "
        "traceback is in the --json "
        "report and with --verbose\n"
    )
    assert "raising (seed 0): ERROR ValueError: controller blew up at 0.5 s" in proc.stdout
    assert "Traceback" not in proc.stdout + proc.stderr
    report = json.loads(out.read_text())
    assert report["verdict"] == "error"
    assert report["error"] == "ValueError: controller blew up"
    assert report["sim_time_s"] == 0.5
    assert 'raise ValueError("controller blew up' in report["traceback"]
    verbose = evclock_cli("run", raising, "--quiet", "--verbose")
    assert verbose.returncode == 4
    assert "Traceback (most recent call last)" in verbose.stderr
    assert verbose.stderr.splitlines()[-1] == (
        "error: raising (seed 0) raised ValueError: controller blew up while running the "
        f"controllers, in Raising._mission ({raising}:{line_of('raise ValueError')})"
    )


def test_a_scenario_that_raises_in_its_set_up_is_4(raising: str) -> None:
    proc = evclock_cli("run", raising, "--quiet", "--param", "where=setup")
    assert proc.returncode == 4, proc.stdout + proc.stderr
    assert proc.stderr == (
        "error: raising (seed 0) raised RuntimeError: broken world while setting up the "
        f"world, in Raising.__init__ ({raising}:{line_of('raise RuntimeError')}); the "
        "traceback is in the --json report "
        "and with --verbose\n"
    )


def test_ctrl_c_prints_the_partial_report_and_exits_130(raising: str, tmp_path: Path) -> None:
    marker = tmp_path / "started"
    out = tmp_path / "r.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "evclock", "run", raising, "--rtf", "1", "--quiet",
         "--param", f"marker={marker}", "--json", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    stdout, stderr = interrupt_when(marker, proc)
    assert proc.returncode == 130, stdout + stderr
    text = " ".join(stdout.split())
    assert "raising (seed 0): INTERRUPTED by Ctrl-C at " in text
    assert "(no verdict; the figures above are partial)" in text
    assert "balance" in text  # the rate-loop table of what ran
    report = json.loads(out.read_text())
    assert report["verdict"] == "interrupted"
    assert report["interrupted"] is True
    assert 0.5 <= report["sim_time_s"] < 1000.5
    assert "Traceback" not in stderr


def test_help_texts_render_intact() -> None:
    root = evclock_cli("--help")
    assert root.returncode == 0
    shown = [line.strip() for line in root.stdout.splitlines()]
    table = [line.strip() for line in EXIT_STATUS_HELP.splitlines()[1:]]
    start = shown.index("Exit status:")
    assert shown[start : start + len(table)] == table  # the table, line for line
    run = evclock_cli("run", "--help")
    assert run.returncode == 0
    assert "pip install 'evclock[record]'" in " ".join(run.stdout.split())
    assert "130  interrupted by Ctrl-C" in run.stdout
    sweep = evclock_cli("sweep", "--help")
    assert "4    error: the scenario or a controller raised" in sweep.stdout


def test_params_lists_type_default_and_help() -> None:
    proc = evclock_cli("params", "kuka")
    assert proc.returncode == 0, proc.stderr
    lines = [" ".join(line.replace("│", " ").split()) for line in proc.stdout.splitlines()]
    assert "tolerance float 0.025 Metres: the flange counts as 'at' a" in lines
    assert "planner_hz float 10.0" in lines  # no help text: an empty cell
    shuttle = evclock_cli("params", str(ROOT / "examples" / "shuttle_scenario.py"))
    assert "gain float 3.0 1/s: commanded velocity per metre of error." in [
        " ".join(line.replace("│", " ").split()) for line in shuttle.stdout.splitlines()
    ]
    unknown = evclock_cli("params", "nope")
    assert unknown.returncode == 2
    assert unknown.stderr.startswith("error: unknown scenario 'nope'")


def test_serve_without_remote_controllers_is_announced_and_control_is_refused(
    tmp_path: Path,
) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    server = subprocess.Popen(
        [sys.executable, "-m", "evclock", "run", "cartpole", "--rtf", "1", "--until", "60",
         "--quiet", "--serve", address],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        assert server.stdout is not None
        line = server.stdout.readline()  # the announcement, before the run
        assert line.strip() == (
            f"serving cartpole's sim time at {address}: its controllers run in this process; "
            "other processes may follow this sim time (`evclock control` needs "
            "--remote-controllers)"
        )
        control = evclock_cli("control", "cartpole", "--clock", address)
        assert control.returncode == 2, control.stdout + control.stderr
        assert control.stderr.startswith(
            f"error: the simulation at {address} runs 'cartpole''s controllers itself (it was "
            "started without --remote-controllers); these would be a second controller stack"
        )
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.communicate(timeout=TIMEOUT / 4)
        except subprocess.TimeoutExpired:
            server.kill()
            server.communicate(timeout=10)


def test_the_version_is_the_installed_one() -> None:
    proc = evclock_cli("--version")
    assert (proc.returncode, proc.stdout) == (0, f"evclock {evclock.__version__}\n")


def test_split_controllers_that_raise_are_4_on_both_ends(raising: str, tmp_path: Path) -> None:
    address = f"unix://{tmp_path / 'sim.sock'}"
    sim_json = tmp_path / "sim.json"
    server = subprocess.Popen(
        [sys.executable, "-m", "evclock", "run", raising, "--quiet", "--serve", address,
         "--remote-controllers", "--json", str(sim_json)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        control = evclock_cli("control", raising, "--clock", address, "--quiet")
        stdout, stderr = server.communicate(timeout=TIMEOUT / 2)
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate(timeout=10)
    assert control.returncode == 4, control.stdout + control.stderr
    assert control.stderr.startswith(
        "error: raising (seed 0) raised ValueError: controller blew up while running the "
        "controllers, in Raising._mission"
    )
    assert server.returncode == 4, stdout + stderr
    assert "raising (seed 0): ERROR ValueError: controller blew up at 0.5 s" in stdout
    report = json.loads(sim_json.read_text())
    assert (report["verdict"], report["error"]) == ("error", "ValueError: controller blew up")
    assert "Traceback" in report["traceback"]


def test_list_verbose_lists_the_parameters_too() -> None:
    proc = evclock_cli("list", "-v")
    assert proc.returncode == 0, proc.stderr
    assert "kuka: parameters (--param NAME=VALUE)" in proc.stdout
    assert "cartpole: parameters (--param NAME=VALUE)" in proc.stdout
    plain = evclock_cli("list")
    assert "parameters (--param" not in plain.stdout
