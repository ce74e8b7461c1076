"""The ``evclock`` command's application object, exit statuses and shared rendering.

Every command module (``_cli``: ``list``, ``run``; ``_cli_sweep``; ``_cli_trace``;
``_cli_remote``) registers on :data:`app` and uses the helpers here; :mod:`evclock.tools._cli`
imports them all and holds the entry point.

Exit statuses (:data:`EXIT_STATUS_HELP`, also in ``evclock --help`` and docs/cli.md): 0
success, 1 the mission failed, 2 bad input, 3 the run was cut short by ``--until`` before the
mission ended, 4 the scenario or a controller raised, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import contextlib
import inspect
import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, TypeVar

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
EXIT_ERROR = 4
EXIT_INTERRUPTED = 130

#: The exit statuses, as ``evclock --help`` prints them (``\b``: click keeps the lines).
EXIT_STATUS_HELP = """\b
Exit status:
  0    success (run: the mission succeeded; sweep: every run did)
  1    failed criterion (run: the mission failed; sweep: a run failed or was cut short;
       trace diff: the recordings differ)
  2    usage error: a bad option, value, scenario or parameter (one `error:` line)
  3    cut short by --until before the mission ended (run, control: no verdict)
  4    error: the scenario or a controller raised (run: one `error:` line, the
       traceback in the --json report and with --verbose; sweep: a run raised)
  130  interrupted by Ctrl-C (the partial report is printed and written)"""

_Command = TypeVar("_Command", bound=Callable[..., None])


def with_exit_statuses(command: _Command) -> _Command:
    """``command`` with the exit-status table appended to its help (its docstring)."""
    command.__doc__ = f"{inspect.cleandoc(command.__doc__ or '')}\n\n{EXIT_STATUS_HELP}\n"
    return command


app = typer.Typer(
    help="evclock: asyncio robot controllers on simulation time.",
    epilog=EXIT_STATUS_HELP,
    no_args_is_help=True,
    add_completion=False,
    # Help texts are plain text: rich markup would swallow 'evclock[record]'.
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
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


def print_error(exc: EvClockError | str) -> None:
    """Print ``error: <message>`` on stderr (the message verbatim, never read as markup)."""
    Console(stderr=True).print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)


@contextlib.contextmanager
def usage_errors() -> Iterator[None]:
    """End the command on an :class:`EvClockError` raised inside: its ``error: <message>``
    on stderr (:func:`print_error`), exit status 2 (:data:`EXIT_USAGE`)."""
    try:
        yield
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None


def check_seed(seed: int, option: str = "--seed") -> int:
    """``seed`` if it is a valid seed (0 to 2**32 - 1), else an :class:`InvalidArgumentError`."""
    if not 0 <= seed < 2**32:
        raise InvalidArgumentError(
            f"{option} takes a whole number from 0 to {2**32 - 1}, got {seed}"
        )
    return seed


def check_until(until: float | None) -> None:
    """Refuse a ``--until`` that is not a positive, finite number of seconds."""
    if until is not None and not (math.isfinite(until) and until > 0):
        raise InvalidArgumentError(f"--until must be a positive number of seconds, got {until!r}")


def print_run_error(report: RunReport, verbose: bool) -> None:
    """The one ``error:`` line of a run that raised; with ``verbose``, its traceback first."""
    console = Console(stderr=True)
    if verbose and report.traceback:
        console.print(report.traceback.rstrip(), markup=False, highlight=False, soft_wrap=True)
    hint = "" if verbose else "; the traceback is in the --json report and with --verbose"
    print_error(
        f"{report.scenario} (seed {report.seed}) raised {report.error} while "
        f"{report.error_where}{hint}"
    )


def _ms(seconds: float | int) -> str:
    return f"{seconds * 1e3:.3f}"


def _format_value(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else "-"
    return str(value)


def render_report(report: RunReport, console: Console) -> None:
    """Print which evclock ran what, the per-loop table, the scenario summary and the
    verdict."""
    engine = "" if report.engine == "pybullet" else f" on {report.engine}"
    console.print(
        f"evclock {report.evclock_version}: {report.scenario}{engine}, seed {report.seed}, "
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
    table = Table(title=escape(f"{report.scenario}: rate loops ({report.mode} time)"))
    for column in ("loop", "Hz", "ticks", "missed", "mean late ms", "p99 late ms", "max late ms"):
        if column == "loop":
            table.add_column(column, no_wrap=True, min_width=16)
        else:
            table.add_column(column, justify="right")
    between = [loop for loop in report.loops if loop.on_physics_steps is False]
    if between and report.physics_step_s is not None:
        table.caption = escape(quantisation_note(report.physics_step_s))
        table.caption_justify = "left"
    for loop in report.loops:
        s = loop.stats
        table.add_row(
            escape(loop.name) + (" *" if loop in between else ""),
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
        summary.add_row(escape(key), escape(_format_value(value)))
    for key, value in report.params.items():
        summary.add_row(escape(f"param {key}"), escape(_format_value(value)))
    if report.mode == "wall":  # no sim time: the controllers ran on the wall clock
        summary.add_row("wall time s", f"{report.wall_time_s:.3f}")
    else:
        rtf = "-" if report.achieved_rtf is None else f"{report.achieved_rtf:.2f}"
        summary.add_row("sim time s", f"{report.sim_time_s:.3f}")
        summary.add_row("wall time s", f"{report.wall_time_s:.3f}")
        summary.add_row("achieved rtf", rtf)
    console.print(summary)
    head = escape(f"{report.scenario} (seed {report.seed})")
    if report.error is not None:
        console.print(
            f"{head}: [red]ERROR[/red] {escape(report.error)} at {report.sim_time_s:g} s",
            soft_wrap=True,
        )
    elif report.interrupted:
        console.print(
            f"{head}: [yellow]INTERRUPTED[/yellow] by Ctrl-C at {report.sim_time_s:g} s "
            "(no verdict; the figures above are partial)",
            soft_wrap=True,
        )
    elif not report.finished:
        console.print(
            f"{head}: [yellow]CUT SHORT[/yellow] at --until {report.until_s:g} s, before the "
            "mission ended (no verdict); raise --until or drop it to use the scenario's "
            "own limit"
        )
    elif report.success:
        console.print(f"{head}: [green]SUCCESS[/green]")
    else:
        console.print(f"{head}: [red]FAILED[/red]")


def quantisation_note(step_s: float) -> str:
    """The run table's note on the loops marked ``*``: deadlines between physics steps of
    ``step_s`` seconds, their lateness that quantisation."""
    step = f"{step_s * 1e3:.3f} ms"
    return (
        f"* deadlines between physics steps (one step: {step}): a tick runs at the first step "
        f"at or after its deadline, so its lateness, up to {step}, is that quantisation, not a "
        "delay (docs: guides/rates-timers-jumps.md, 'Deadlines between physics steps')"
    )


def exit_code(report: RunReport) -> int:
    """The exit status of ``evclock run`` for ``report``."""
    if report.error is not None:
        return EXIT_ERROR
    if report.interrupted:
        return EXIT_INTERRUPTED
    if not report.finished:
        return EXIT_CUT_SHORT
    return EXIT_SUCCESS if report.success else EXIT_FAILED


def progress_console(console: Console | None, quiet: bool) -> tuple[Console, bool]:
    """The console a progress bar draws on and whether the bar is off. By default (``console``
    None) stderr, so that stdout holds only the results, and off with ``quiet`` or when stderr
    is not a terminal (a bar's redraws are no use in a pipe or a log file); a given
    ``console`` is used as it is, off only with ``quiet``."""
    if console is not None:
        return console, quiet
    console = Console(stderr=True)
    return console, quiet or not console.is_terminal


def progress_bar(console: Console | None, quiet: bool) -> Progress:
    """The single-run progress bar, by default on stderr and only on a terminal (see
    :func:`progress_console`; refreshed by the run: no background thread)."""
    console, off = progress_console(console, quiet)
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.2f}/{task.total:g} s"),
        TextColumn("rtf {task.fields[rtf]}"),
        TimeElapsedColumn(),
    )
    return Progress(*columns, console=console, disable=off, auto_refresh=False)
