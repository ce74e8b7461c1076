"""The ``evclock`` command's application object, exit statuses and shared rendering.

Every command module (``_cli``: ``list``, ``run``; ``_cli_sweep``; ``_cli_trace``;
``_cli_remote``) registers on :data:`app` and uses the helpers here; :mod:`evclock.tools._cli`
imports them all and holds the entry point.

Exit codes: 0 success, 1 the mission failed, 2 bad input, 3 the run was cut short by
``--until`` before the mission ended, 130 interrupted.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from evclock._errors import EvClockError, InvalidArgumentError
from evclock.data._diagnostics import render_diagnostics_report
from evclock.tools._runs import RunReport
from evclock.tools._scenarios import (
    ParamValue,
    load_scenario,
    parse_param_values,
)

EXIT_SUCCESS = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_CUT_SHORT = 3
EXIT_INTERRUPTED = 130

app = typer.Typer(
    help="evclock: asyncio robot controllers on simulation time.",
    no_args_is_help=True,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        from evclock import __version__

        typer.echo(f"evclock {__version__}")
        raise typer.Exit(EXIT_SUCCESS)


@app.callback()
def root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Print evclock's version and exit."
        ),
    ] = False,
) -> None:
    """evclock: asyncio robot controllers on simulation time."""


def check_writable(path: Path, option: str) -> None:
    """Fail now, before any run, if ``path`` (the file of ``option``) cannot be written."""
    target = path.expanduser()
    parent = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise InvalidArgumentError(f"{option} {str(path)!r} is a directory; give a file name")
    if not parent.is_dir():
        raise InvalidArgumentError(
            f"{option} {str(path)!r}: the directory {str(parent)!r} does not exist"
        )
    if target.exists() and not os.access(target, os.W_OK):
        raise InvalidArgumentError(f"{option} {str(path)!r} exists and is not writable")
    if not target.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise InvalidArgumentError(
            f"{option} {str(path)!r}: the directory {str(parent)!r} is not writable"
        )


def parse_params(scenario: str, assignments: list[str]) -> dict[str, list[ParamValue]]:
    """``["a=1,2", "b=x"]`` -> ``{"a": [1, 2], "b": ["x"]}`` (checked against the scenario)."""
    if not assignments:
        return {}
    cls = load_scenario(scenario)
    values: dict[str, list[ParamValue]] = {}
    for assignment in assignments:
        name, parsed = parse_param_values(cls, assignment)
        if name in values:
            raise InvalidArgumentError(f"--param {name} is given twice; list values: {name}=a,b")
        values[name] = parsed
    return values


def print_error(exc: EvClockError) -> None:
    """Print ``error: <message>`` on stderr (the message verbatim, never read as markup)."""
    Console(stderr=True).print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)


def _ms(seconds: float | int) -> str:
    return f"{seconds * 1e3:.3f}"


def _format_value(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else "-"
    return str(value)


def render_report(report: RunReport, console: Console) -> None:
    """Print which evclock ran what, the per-loop table, the scenario summary and the
    verdict."""
    console.print(
        f"evclock {report.evclock_version}: {report.scenario}, seed {report.seed}, "
        f"{report.mode} time",
        soft_wrap=True,
        highlight=False,
        markup=False,
    )
    if report.setup_output:
        console.print(
            f"[dim]the physics engine printed while loading the world: "
            f"{escape('; '.join(report.setup_output))}[/dim]",
            soft_wrap=True,
            highlight=False,
            markup=True,
        )
    table = Table(title=f"{report.scenario}: rate loops ({report.mode} time)")
    for column in ("loop", "Hz", "ticks", "missed", "mean late ms", "p99 late ms", "max late ms"):
        if column == "loop":
            table.add_column(column, no_wrap=True, min_width=16)
        else:
            table.add_column(column, justify="right")
    for loop in report.loops:
        s = loop.stats
        table.add_row(
            loop.name,
            f"{loop.hz:g}",
            str(s["ticks"]),
            str(s["missed"]),
            _ms(s["mean_lateness_s"]),
            _ms(s["p99_lateness_s"]),
            _ms(s["max_lateness_s"]),
        )
    console.print(table)
    render_diagnostics_report(report.stamps, console)
    summary = Table(title="summary", show_header=False)
    summary.add_column("metric")
    summary.add_column("value", justify="right")
    for key, value in report.summary.items():
        summary.add_row(key, _format_value(value))
    for key, value in report.params.items():
        summary.add_row(f"param {key}", _format_value(value))
    rtf = "-" if report.achieved_rtf is None else f"{report.achieved_rtf:.2f}"
    summary.add_row("sim time s", f"{report.sim_time_s:.3f}")
    summary.add_row("wall time s", f"{report.wall_time_s:.3f}")
    summary.add_row("achieved rtf", rtf)
    console.print(summary)
    head = f"{report.scenario} (seed {report.seed})"
    if not report.finished:
        console.print(
            f"{head}: [yellow]CUT SHORT[/yellow] at --until {report.until_s:g} s, before the "
            "mission ended (no verdict); raise --until or drop it to use the scenario's "
            "own limit"
        )
    elif report.success:
        console.print(f"{head}: [green]SUCCESS[/green]")
    else:
        console.print(f"{head}: [red]FAILED[/red]")


def exit_code(report: RunReport) -> int:
    """The exit status of ``evclock run`` for ``report``."""
    if not report.finished:
        return EXIT_CUT_SHORT
    return EXIT_SUCCESS if report.success else EXIT_FAILED


def progress_bar(console: Console, quiet: bool) -> Progress:
    """The single-run progress bar (refreshed by the run: no background thread)."""
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.2f}/{task.total:g} s"),
        TextColumn("rtf {task.fields[rtf]}"),
        TimeElapsedColumn(),
    )
    return Progress(*columns, console=console, disable=quiet, auto_refresh=False)
