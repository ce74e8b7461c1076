"""``evclock trace info|echo|diff`` and ``evclock plot``: recorded runs from the command line.

- ``trace info RUN.mcap``: the run (scenario, seed, parameters, evclock version, outcome), its
  duration and every topic with its schema and message count;
- ``trace echo RUN.mcap TOPIC [--field PATH] [--from T] [--to T]``: one line per message;
- ``trace layout [-o FILE]``: writes the Foxglove layout shipped with evclock;
- ``trace diff A B``: the first divergence of two recorded runs; exits 0 when they agree on
  every deterministic channel, 1 when they diverge;
- ``plot RUN.mcap -o RUN.png``: lateness per loop and achieved rtf over sim time;
  ``plot RUN.mcap TOPIC.field ... -o F.png``: any numeric fields over time, a panel each.

A file that cannot be read (missing, truncated, corrupt, not a recording, a newer format)
gives one ``error:`` line and exit status 2.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console

from evclock._errors import InvalidArgumentError
from evclock.tools._cli_app import (
    EXIT_FAILED,
    EXIT_SUCCESS,
    app,
    check_writable,
    usage_errors,
)

if TYPE_CHECKING:
    from evclock.tools._trace import Trace

trace_app = typer.Typer(help="Inspect recorded runs (MCAP files from evclock run --record).")
app.add_typer(trace_app, name="trace")


def _read(path: Path) -> Trace:
    from evclock.tools._trace import read_trace

    with usage_errors():
        return read_trace(path)


@trace_app.command("info")
def info_command(
    recording: Annotated[Path, typer.Argument(help="A recording (evclock run --record).")],
) -> None:
    """Show what a recording holds: the run, its duration, each topic's schema and count."""
    from evclock.tools._trace import info_lines

    for line in info_lines(_read(recording)):
        typer.echo(line)


@trace_app.command("echo")
def echo_command(
    recording: Annotated[Path, typer.Argument(help="A recording (evclock run --record).")],
    topic: Annotated[str, typer.Argument(help="The topic to print (see evclock trace info).")],
    field: Annotated[
        str | None,
        typer.Option(
            "--field", help="Print only this field: a.b, list items as [2] or by name [elbow]."
        ),
    ] = None,
    start: Annotated[
        float | None, typer.Option("--from", help="First time to print, in seconds.")
    ] = None,
    end: Annotated[
        float | None, typer.Option("--to", help="Last time to print, in seconds.")
    ] = None,
) -> None:
    """Print a topic's messages, one per line: time in seconds, then the JSON content."""
    from evclock.tools._trace import echo_lines

    trace = _read(recording)
    with usage_errors():
        for value in (start, end):
            if value is not None and not math.isfinite(value):
                raise InvalidArgumentError(f"--from/--to take finite seconds, got {value}")
        for line in echo_lines(trace, topic, field, start, end):
            typer.echo(line)


@trace_app.command("layout")
def layout_command(
    output: Annotated[
        Path, typer.Option("-o", "--output", help="Where to write the layout (a .json file).")
    ] = Path("evclock-foxglove-layout.json"),
) -> None:
    """Write evclock's saved Foxglove layout: the 3D view of the robot, joint and timing
    plots, the controllers' log and the state (import it in Foxglove: Layouts, Import)."""
    from evclock.tools._foxglove import LAYOUT_FILE

    with usage_errors():
        check_writable(output, "-o")
    output.write_bytes(LAYOUT_FILE.read_bytes())
    typer.echo(f"wrote {output}")


@trace_app.command("diff")
def diff_command(
    a: Annotated[Path, typer.Argument(help="A recording (evclock run ... --record a.mcap).")],
    b: Annotated[Path, typer.Argument(help="Another recording to compare with.")],
) -> None:
    """Print the first divergence of two recorded runs (sim time, channel, field).

    Exit status: 0 the runs are identical, 1 they diverge, 2 bad input.
    """
    from evclock.tools._trace import first_divergence

    console = Console(highlight=False)
    left, right = _read(a), _read(b)
    divergence = first_divergence(left, right)
    if divergence is None:
        compared = sum(m.deterministic for m in left.messages)
        console.print(f"identical: {compared} deterministic messages agree bit for bit")
        raise typer.Exit(EXIT_SUCCESS)
    console.print(divergence.describe(), soft_wrap=True)
    raise typer.Exit(EXIT_FAILED)


@app.command("plot")
def plot_command(
    recording: Annotated[Path, typer.Argument(help="A recording (evclock run --record).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="The PNG file to write.")],
    series: Annotated[
        list[str] | None,
        typer.Argument(
            help="Fields to plot over time, as TOPIC.field (e.g. "
            "/evclock/joints.joints[lbr_iiwa_joint_2].position); default: lateness and rtf.",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Plot a recorded run: each rate loop's tick lateness and the achieved rtf over sim
    time, or the given numeric fields (one figure, a panel per field: no units are
    recorded, so no two fields share a y-axis)."""
    from evclock.tools._plot import figure_class, plot_fields, plot_run

    with usage_errors():
        check_writable(output, "-o")
        figure_class()
    trace = _read(recording)
    with usage_errors():
        if series:
            plot_fields(trace, series, output)
        else:
            plot_run(trace, output)
    Console().print(f"wrote {output}", markup=False, highlight=False)
