"""What ``evclock`` tells a machine without an engine: every command and option takes the same
check (one ``error:`` line naming the extra, exit status 2, nothing run and nothing on stdout),
``evclock list`` says which engines each scenario runs on and which are installed, and a
message that names an extra in brackets keeps them on the terminal.

Each case runs the real command in a fresh interpreter where the engine's modules are made
unimportable (``sys.modules[name] = None``), as on a machine without them.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from _cli import one_line, run_command
from _without_pybullet import CLI_WITHOUT_ENGINES, CLI_WITHOUT_PYBULLET

_WHEELS = (
    "(PyBullet has wheels for CPython 3.11 only; on another Python pip builds it from source, "
    "which needs a C++ compiler and about half an hour)"
)
_KUKA = (
    "error: scenario '{name}' runs on PyBullet by default, which is not installed: pip install "
    f"'evclock[pybullet]' {_WHEELS}; or run it on MuJoCo: --engine mujoco"
)


def evclock(
    command: list[str], *args: str, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    return run_command(command, *args, cwd=cwd, columns=250)


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (["sweep", "kuka", "--seeds", "2"], _KUKA.format(name="kuka")),
        (["sweep", "cartpole", "--seeds", "2", "--workers", "2"], _KUKA.format(name="cartpole")),
        (["run", "kuka"], _KUKA.format(name="kuka")),
        (["run", "cartpole", "--wall"], _KUKA.format(name="cartpole")),
        (["run", "kuka", "--wall"], _KUKA.format(name="kuka")),
        (
            ["run", "kuka", "--serve", "unix:///tmp/evclock-no-engine.sock"],
            _KUKA.format(name="kuka"),
        ),
        (
            ["run", "husky", "--engine", "mujoco"],
            "error: scenario 'husky' runs on PyBullet only, not on MuJoCo, and PyBullet is not "
            f"installed here: pip install 'evclock[pybullet]' {_WHEELS}",
        ),
        (
            ["run", "husky", "--wall"],
            "error: scenario 'husky' runs on PyBullet only, which is not installed: pip install "
            f"'evclock[pybullet]' {_WHEELS}",
        ),
        (
            ["sweep", "fusion", "--seeds", "2"],
            "error: scenario 'fusion' runs on PyBullet only, which is not installed: pip install "
            f"'evclock[pybullet]' {_WHEELS}",
        ),
    ],
)
def test_without_pybullet_every_path_is_one_error_line_and_2_before_anything_runs(
    args: list[str], error: str
) -> None:
    # No --quiet: not even the progress bar starts.
    result = evclock(CLI_WITHOUT_PYBULLET, *args)
    assert result.returncode == 2, result.stdout + result.stderr
    assert one_line(result.stderr) == error
    assert result.stdout == ""


def test_without_any_engine_run_names_both_and_writes_nothing_to_stdout() -> None:
    result = evclock(CLI_WITHOUT_ENGINES, "run", "kuka")
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stdout == ""
    assert one_line(result.stderr) == (
        "error: scenario 'kuka' runs on PyBullet by default, which is not installed: pip install "
        f"'evclock[pybullet]' {_WHEELS}; or run it on MuJoCo: pip install 'evclock[mujoco]', "
        "then --engine mujoco"
    )
    result = evclock(CLI_WITHOUT_ENGINES, "run", "kuka", "--engine", "mujoco", "--wall")
    assert result.returncode == 2, result.stdout + result.stderr
    assert one_line(result.stderr) == (
        "error: --engine mujoco: MuJoCo is not installed: pip install 'evclock[mujoco]'"
    )


def table_rows(stdout: str) -> dict[str, list[str]]:
    """The cells of each row of a rich table, by the first cell."""
    rows = [
        [cell.strip() for cell in line.strip("│").split("│")]
        for line in stdout.splitlines()
        if line.startswith("│")
    ]
    return {row[0]: row[1:] for row in rows}


def test_list_without_any_engine_says_which_engines_each_scenario_needs() -> None:
    result = evclock(CLI_WITHOUT_ENGINES, "list")
    assert result.returncode == 0, result.stderr
    header = next(line for line in result.stdout.splitlines() if line.startswith("┃"))
    assert [cell.strip() for cell in header.strip("┃").split("┃")] == [
        "name",
        "sim seconds",
        "engines",
        "runs here",
        "description",
        "from",
    ]
    rows = table_rows(result.stdout)
    assert {name: row[1:3] for name, row in rows.items()} == {
        "cartpole": ["pybullet, mujoco", "no"],
        "fusion": ["pybullet", "no"],
        "husky": ["pybullet", "no"],
        "kuka": ["pybullet, mujoco", "no"],
    }
    assert one_line(result.stderr) == (
        "note: cartpole, kuka cannot run here: neither PyBullet nor MuJoCo is installed: pip "
        f"install 'evclock[mujoco]' or pip install 'evclock[pybullet]' {_WHEELS} "
        "note: fusion, husky cannot run here: PyBullet is not installed: pip install "
        f"'evclock[pybullet]' {_WHEELS}"
    )


def test_list_without_pybullet_says_what_runs_on_mujoco() -> None:
    result = evclock(CLI_WITHOUT_PYBULLET, "list")
    assert result.returncode == 0, result.stderr
    rows = table_rows(result.stdout)
    assert rows["kuka"][2] == "on mujoco"
    assert rows["cartpole"][2] == "on mujoco"
    assert rows["husky"][2] == "no"
    assert one_line(result.stderr).startswith("note: fusion, husky cannot run here:")


_RAISES = """
from evclock_sims.kuka import KukaReach


class Raises(KukaReach):
    name = "raises"

    async def _mission(self, clock):
        raise RuntimeError("install it: pip install 'evclock[record]' [then rerun]")
"""


def test_messages_with_brackets_reach_the_terminal_intact(tmp_path: Path) -> None:
    (tmp_path / "raises.py").write_text(_RAISES)
    result = evclock(
        CLI_WITHOUT_PYBULLET,
        "sweep",
        "raises.py",
        "--seeds",
        "1",
        "--engine",
        "mujoco",
        "--quiet",
        cwd=tmp_path,
    )
    assert result.returncode == 4, result.stdout + result.stderr
    assert (
        "error seed 0: RuntimeError: install it: pip install 'evclock[record]' [then rerun]"
        in one_line(result.stdout)
    )
    result = evclock(
        CLI_WITHOUT_PYBULLET, "run", "raises.py", "--engine", "mujoco", "--quiet", cwd=tmp_path
    )
    assert result.returncode == 4, result.stdout + result.stderr
    assert (
        "raises (seed 0): ERROR RuntimeError: install it: pip install 'evclock[record]' "
        "[then rerun] at 0 s" in one_line(result.stdout)
    )
