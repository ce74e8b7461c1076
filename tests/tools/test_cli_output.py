"""What the ``evclock`` command prints: clean usage errors whatever parses an option, the file a
``--record`` wrote, a progress bar only on a terminal's stderr, a wall-time summary labelled as
such, the quantisation of a loop's deadlines to the physics step, an unknown ``trace echo``
field refused, and a plot with one axis per unit.

Each case runs the real command in a subprocess (PyBullet hidden where MuJoCo runs it, so
the tests run on every supported Python).
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import pytest
from _cli import TIMEOUT, one_line, run_command
from _without_pybullet import CLI_WITHOUT_PYBULLET

EVCLOCK = [sys.executable, "-m", "evclock"]


def evclock(
    command: list[str], *args: str, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    return run_command(command, *args, cwd=cwd, columns=200)


@pytest.mark.parametrize("command", ["run", "sweep", "control"])
def test_a_value_outside_the_choices_is_named_without_the_parsers_words(command: str) -> None:
    result = evclock(EVCLOCK, command, "kuka", "--engine", "bullet")
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    assert result.stderr == (
        "error: Invalid value for '--engine': 'bullet' is not one of 'pybullet', 'mujoco'; "
        f"see 'evclock {command} --help'\n"
    )


@pytest.fixture(scope="module")
def recording(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """Half a second of ``kuka`` on MuJoCo, recorded (no ``--quiet``: stderr is a pipe)."""
    directory = tmp_path_factory.mktemp("recording")
    result = evclock(
        CLI_WITHOUT_PYBULLET, "run", "kuka", "--engine", "mujoco", "--until", "0.5",
        "--record", "kuka.mcap", cwd=directory,
    )  # fmt: skip
    assert result.returncode == 3, result.stdout + result.stderr  # cut short by --until
    return directory / "kuka.mcap", result


def test_record_names_the_file_and_no_progress_bar_reaches_a_pipe(
    recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, result = recording
    assert path.is_file()
    assert result.stdout.splitlines()[-1] == "wrote the recording to kuka.mcap"
    assert result.stderr == ""  # the bar is for a terminal only
    assert "0.50/0.5 s" not in result.stdout  # and never on stdout
    assert result.stdout.startswith("evclock ")


def test_the_progress_bar_is_drawn_on_a_terminals_stderr(tmp_path: Path) -> None:
    import pty
    import threading

    main, terminal = pty.openpty()
    drawn: list[bytes] = []

    def read() -> None:
        while True:
            try:
                chunk = os.read(main, 4096)
            except OSError:  # the terminal's last holder closed it
                return
            if not chunk:
                return
            drawn.append(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        process = subprocess.run(
            [*CLI_WITHOUT_PYBULLET, "run", "kuka", "--engine", "mujoco", "--until", "0.5"],
            stdout=subprocess.PIPE,
            stderr=terminal,
            text=True,
            timeout=TIMEOUT,
            check=False,
            cwd=tmp_path,
            env={**os.environ, "COLUMNS": "120", "TERM": "xterm"},
        )
    finally:
        os.close(terminal)
        reader.join(timeout=30)
        os.close(main)
    assert process.returncode == 3, process.stdout
    bar = b"".join(drawn).decode(errors="replace")
    assert "kuka" in bar
    assert "0.50/0.5 s" in bar
    assert "0.50/0.5 s" not in process.stdout
    assert process.stdout.startswith("evclock ")


def test_a_wall_time_run_is_not_reported_in_sim_time(tmp_path: Path) -> None:
    result = evclock(
        CLI_WITHOUT_PYBULLET, "run", "kuka", "--engine", "mujoco", "--wall", "--until", "0.3",
        "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 3, result.stdout + result.stderr
    assert "kuka on mujoco, seed 0, wall time" in result.stdout.splitlines()[0]
    summary = [line for line in result.stdout.splitlines() if line.startswith("│")]
    labels = [line.strip("│").split("│")[0].strip() for line in summary]
    assert "wall time s" in labels
    assert "sim time s" not in labels
    assert "achieved rtf" not in labels
    assert "sim time" not in result.stdout


def test_a_loop_between_physics_steps_is_marked_with_the_step(tmp_path: Path) -> None:
    result = evclock(
        CLI_WITHOUT_PYBULLET, "run", "kuka", "--engine", "mujoco", "--until", "0.5", "--quiet",
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 3, result.stdout + result.stderr
    rows = {
        line.strip("│").split("│")[0].strip(): line
        for line in result.stdout.splitlines()
        if line.startswith("│")
    }
    # 100 Hz on 240 Hz physics: 2.4 steps a period; 10 Hz: 24 steps, on time.
    assert "joint_control *" in rows
    assert "planner" in rows
    assert one_line(result.stdout).count(" * deadlines between physics steps") == 1
    assert (
        "* deadlines between physics steps (one step: 4.167 ms): a tick runs at the first step "
        "at or after its deadline, so its lateness, up to 4.167 ms, is that quantisation, not a "
        "delay (docs: guides/rates-timers-jumps.md, 'Deadlines between physics steps')"
    ) in one_line(result.stdout)
    guide = Path(__file__).resolve().parents[2] / "docs" / "guides" / "rates-timers-jumps.md"
    assert "### Deadlines between physics steps\n" in guide.read_text()


@pytest.mark.parametrize(
    ("field", "why"),
    [
        (
            "joints[bogus].position",
            "joints has no item [bogus]; its items: [lbr_iiwa_joint_1], [lbr_iiwa_joint_2], "
            "[lbr_iiwa_joint_3], [lbr_iiwa_joint_4], [lbr_iiwa_joint_5], [lbr_iiwa_joint_6], "
            "[lbr_iiwa_joint_7]",
        ),
        ("joints[9].position", "joints has 7 items ([0] to [6]), no [9]"),
        (
            "joints[lbr_iiwa_joint_2].pos",
            "joints[lbr_iiwa_joint_2] has no field 'pos'; its fields: name, position, velocity, "
            "effort",
        ),
        ("jnts", "the message has no field 'jnts'; its fields: timestamp, joints"),
        ("joints[1].position.x", "joints[1].position is 0.4, which has no field 'x'"),
    ],
)
def test_trace_echo_refuses_an_unknown_field_naming_those_that_exist(
    recording: tuple[Path, subprocess.CompletedProcess[str]], field: str, why: str
) -> None:
    path, _ = recording
    result = evclock(EVCLOCK, "trace", "echo", str(path), "/evclock/joints", "--field", field)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stdout == ""
    assert result.stderr == (
        f"error: no message of /evclock/joints has the field {field!r}: {why}\n"
    )
    known = evclock(
        EVCLOCK, "trace", "echo", str(path), "/evclock/joints", "--field",
        "joints[lbr_iiwa_joint_2].position", "--to", "0.1",
    )  # fmt: skip
    assert known.returncode == 0, known.stderr
    assert len(known.stdout.splitlines()) == 3  # at 0, 0.05 and 0.1 s


def test_plot_gives_each_field_its_own_axis(
    recording: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path
) -> None:
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread

    from evclock.tools._plot import PALETTE

    path, _ = recording
    png = tmp_path / "fields.png"
    series = (
        "/evclock/joints.joints[lbr_iiwa_joint_2].position",  # rad, about 0.4
        "/evclock/clock.achieved_rtf",  # tens to thousands
        "/evclock/loop/joint_control.lateness_s",  # seconds, up to 1/240
    )
    result = evclock(EVCLOCK, "plot", str(path), *series, "-o", str(png))
    assert result.returncode == 0, result.stderr
    image = imread(png)
    assert image.shape[:2] == (760, 1000)  # one figure, three panels
    bands = []
    for color in PALETTE[:3]:  # three series, in palette order, each in its own panel
        rgb = [int(color[i : i + 2], 16) / 255 for i in (1, 3, 5)]
        rows = (abs(image[:, :, :3] - rgb).max(axis=2) < 0.02).any(axis=1).nonzero()[0]
        assert len(rows) > 0, color
        bands.append((rows.min(), rows.max()))
    assert bands == sorted(bands)
    for (_, bottom), (top, _) in itertools.pairwise(bands):
        assert bottom < top  # the panels do not overlap: no two fields share an axis


def test_stamp_diagnostics_keep_the_brackets_of_their_names() -> None:
    import io

    from rich.console import Console

    from evclock.data._diagnostics import render_diagnostics_report

    console = Console(file=io.StringIO(), width=200)
    ages = {"mean_age_s": 0.001, "p99_age_s": 0.002, "max_age_s": 0.003}
    report = {
        "name": "camera[left]",
        "streams": {"image[0]": {"messages": 3, "stale": 0, "future": 0, **ages}},
        "queues": {"fuser[b]": {"depth": 1, "max_depth": 2, "behind": 0}},
        "warnings": ["install it: pip install 'evclock[record]'"],
    }
    render_diagnostics_report([report], console)
    text = console.file.getvalue()  # type: ignore[attr-defined]
    for shown in (
        "camera[left]: stamp ages",
        "image[0]",
        "camera[left]: consumer queues",
        "fuser[b]",
        "warning install it: pip install 'evclock[record]'",
    ):
        assert shown in text, shown
