"""The ``evclock`` command: ``list``, ``run`` and the root options (``--version``).

``evclock run kuka --until 10 --rtf 1`` runs a scenario (see :mod:`evclock._runs`) with a
progress bar (sim time and achieved real-time factor) and, at the end, a table of every rate
loop's ticks, missed periods and lateness. Other command groups live in their own modules
(``_cli_sweep``: ``sweep``; ``_cli_trace``: ``trace diff`` and ``plot``) and register on
:data:`app` when imported at the bottom of this one.

Exit codes: 0 success, 1 the mission failed, 2 bad input, 3 the run was cut short by
``--until`` before the mission ended.
"""

from __future__ import annotations

import functools
import json
import math
import os
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ._diagnostics import render_diagnostics_report
from ._errors import EvClockError, InvalidArgumentError, MissingExtraError
from ._runs import RunReport, parse_rtf, run_scenario
from ._scenarios import ParamValue, load_scenario, parse_param_values, registered_scenarios
from .ros2 import _cli as ros2_cli

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
        from . import __version__

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
    """Print the per-loop table, the scenario summary and the verdict."""
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


@app.command("list")
def list_scenarios() -> None:
    """List the registered scenarios (entry-point group evclock.scenarios).

    A scenario whose extra is not installed is listed with what it needs, and a note on stderr
    gives the command that installs it (exit 0: nothing is broken). A registration that cannot
    be imported for another reason is listed as broken, its error printed, and the exit status
    is 2; every other scenario is still listed.
    """
    table = Table(title="scenarios")
    table.add_column("name")
    table.add_column("sim seconds", justify="right")
    table.add_column("description")
    table.add_column("from")
    try:
        entries = registered_scenarios()
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    missing: dict[str, list[str]] = {}  # error message -> scenario names (insertion order)
    broken: list[str] = []
    for entry in entries:
        try:
            cls = entry.load()
        except MissingExtraError as exc:
            need = f"evclock[{exc.extra}]" if exc.extra else "an optional dependency"
            table.add_row(
                escape(entry.name), "-", escape(f"(needs {need})"), escape(entry.distribution)
            )
            missing.setdefault(str(exc), []).append(entry.name)
        except Exception as exc:  # a third-party registration must not hide the others
            table.add_row(
                escape(entry.name), "-", "(broken: see the error below)", escape(entry.distribution)
            )
            detail = str(exc) if isinstance(exc, EvClockError) else f"{type(exc).__name__}: {exc}"
            broken.append(f"scenario {entry.name!r} ({entry.target}) cannot be loaded: {detail}")
        else:
            table.add_row(
                escape(entry.name),
                f"{cls.default_until:g}",
                escape(str(cls.description)),
                escape(entry.distribution),
            )
    Console().print(table)
    stderr = Console(stderr=True)
    for message, names in missing.items():
        stderr.print(
            f"[yellow]note:[/yellow] {escape(', '.join(names))} cannot run here: {escape(message)}",
            soft_wrap=True,
        )
    for message in broken:
        stderr.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    if broken:
        raise typer.Exit(EXIT_USAGE)


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


@app.command("run")
def run_command(
    scenario: Annotated[
        str,
        typer.Argument(
            help="A registered name (see `evclock list`), a file path.py[:Class] or "
            "package.module:Class."
        ),
    ],
    until: Annotated[
        float | None, typer.Option(help="Stop after this many seconds (default: the scenario's).")
    ] = None,
    rtf: Annotated[
        str, typer.Option(help="Real-time factor: 'max' (as fast as possible), 1, or K.")
    ] = "max",
    seed: Annotated[int, typer.Option(help="Seed of the scenario's random choices.")] = 0,
    param: Annotated[
        list[str] | None,
        typer.Option("--param", help="Set a scenario parameter: name=value (repeatable)."),
    ] = None,
    gui: Annotated[bool, typer.Option(help="Open PyBullet's GUI (needs a display).")] = False,
    wall: Annotated[
        bool, typer.Option(help="Run the controllers on wall time; physics steps in real time.")
    ] = False,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON to this file.")
    ] = None,
    record: Annotated[
        Path | None, typer.Option(help="Record the run to this MCAP file (needs evclock[record]).")
    ] = None,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
    serve: Annotated[
        str | None,
        typer.Option(
            help="Serve this run's sim time at ADDR (unix:///path.sock, tcp://HOST:PORT)."
        ),
    ] = None,
    remote_controllers: Annotated[
        bool,
        typer.Option(help="With --serve: physics only; `evclock control` runs the controllers."),
    ] = False,
    ros2_clock: ros2_cli.Ros2ClockFlag = False,
    ros_domain_id: ros2_cli.RosDomainId = None,
    ros2_clock_decimation: ros2_cli.Ros2ClockDecimation = 1,
    ros2_wire_format: ros2_cli.Ros2WireFormat = ros2_cli.DEFAULT_WIRE_FORMAT,
    ros2_connect: ros2_cli.Ros2Connect = None,
    ros2_listen: ros2_cli.Ros2Listen = None,
) -> None:
    """Run a scenario with its controllers on evclock time."""
    console = Console()
    try:
        pace = parse_rtf(rtf)
        ros2 = ros2_cli.options_from_cli(
            ros2_clock,
            ros_domain_id,
            ros2_clock_decimation,
            ros2_wire_format,
            ros2_connect,
            ros2_listen,
        )
        if ros2 is not None:
            if serve is not None:
                raise InvalidArgumentError("--ros2-clock with --serve is not supported; pick one")
            from .ros2._session import require

            for module in ("zenoh", "xxhash"):  # the ros2 extra: fail before any run
                require(module)
            console.print(ros2.describe(), soft_wrap=True)
        if wall and pace is not None:
            raise InvalidArgumentError("--wall runs in real time: drop --rtf (or use --rtf max)")
        for path, option in ((json_out, "--json"), (record, "--record")):
            if path is not None:
                check_writable(path, option)
        values = parse_params(scenario, param or [])
        multi = [name for name, vals in values.items() if len(vals) != 1]
        if multi:
            raise InvalidArgumentError(
                f"evclock run takes one value per --param ({', '.join(multi)}); "
                "use evclock sweep for several"
            )
        if remote_controllers and serve is None:
            raise InvalidArgumentError("--remote-controllers needs --serve ADDR")
        if serve is not None and (values or record is not None):
            raise InvalidArgumentError(
                "--serve runs the scenario as registered: drop --param and --record "
                "(the joined controllers could not know about them)"
            )
        if record is not None:
            from ._record import mcap_writer_class

            mcap_writer_class()
        with progress_bar(console, quiet) as progress:
            if serve is not None:
                report = _served(serve, remote_controllers)(
                    scenario,
                    until=until,
                    rtf=pace,
                    seed=seed,
                    gui=gui,
                    wall=wall,
                    progress=progress,
                )
            else:
                report = run_scenario(
                    scenario,
                    until=until,
                    rtf=pace,
                    seed=seed,
                    params={name: vals[0] for name, vals in values.items()},
                    gui=gui,
                    wall=wall,
                    record=record,
                    progress=progress,
                    ros2_clock=ros2,
                )
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    render_report(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_json(), indent=2))
    raise typer.Exit(exit_code(report))


def _served(address: str, remote_controllers: bool) -> Any:
    from ._remote._commands import serve_scenario

    return functools.partial(serve_scenario, address=address, remote_controllers=remote_controllers)


def _register_remote() -> None:
    from ._remote._commands import control_command

    app.command("control")(control_command)


_register_remote()


def main() -> None:
    """Entry point of the ``evclock`` console script."""
    app()


# Command groups defined in their own modules register on ``app`` when imported.
from . import _cli_sweep, _cli_trace  # noqa: E402, F401
