"""``evclock trace diff A B`` (the first divergence of two recorded runs) and
``evclock plot RUN.mcap -o RUN.png`` (lateness per loop and achieved rtf over sim time).

``trace diff`` exits 0 when the recordings agree on every deterministic channel, 1 when they
diverge, 2 on bad input.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from evclock._errors import EvClockError
from evclock.tools._cli_app import (
    EXIT_FAILED,
    EXIT_SUCCESS,
    EXIT_USAGE,
    app,
    check_writable,
    print_error,
)

trace_app = typer.Typer(help="Inspect recorded runs (MCAP files from evclock run --record).")
app.add_typer(trace_app, name="trace")


@trace_app.command("diff")
def diff_command(
    a: Annotated[Path, typer.Argument(help="A recording (evclock run ... --record a.mcap).")],
    b: Annotated[Path, typer.Argument(help="Another recording to compare with.")],
) -> None:
    """Print the first divergence of two recorded runs (sim time, channel, field).

    Exit status: 0 the runs are identical, 1 they diverge, 2 bad input.
    """
    from evclock.tools._trace import first_divergence, read_trace

    console = Console(highlight=False)
    try:
        left, right = read_trace(a), read_trace(b)
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
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
) -> None:
    """Plot a recorded run: each rate loop's tick lateness and the achieved rtf over sim time."""
    from evclock.tools._plot import figure_class, plot_run
    from evclock.tools._trace import read_trace

    try:
        check_writable(output, "-o")
        figure_class()
        plot_run(read_trace(recording), output)
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    Console().print(f"wrote {output}")
