"""The ``evclock`` command: ``list``, ``run``, and the entry point that gathers every command.

``evclock run kuka --until 10 --rtf 1`` runs a scenario (see :mod:`evclock.tools._runs`) with a
progress bar (sim time and achieved real-time factor) and, at the end, a table of every rate
loop's ticks, missed periods and lateness. Other commands live in their own modules
(``_cli_sweep``: ``sweep``; ``_cli_trace``: ``trace diff`` and ``plot``; ``_cli_remote``:
``control`` and ``run --serve``), all on the application object of :mod:`evclock.tools._cli_app`.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from evclock._errors import EvClockError, InvalidArgumentError, MissingExtraError
from evclock.ros2 import _cli as ros2_cli
from evclock.tools import _cli_sweep, _cli_trace  # noqa: F401  (they register their commands)
from evclock.tools._cli_app import (
    EXIT_USAGE,
    app,
    check_writable,
    exit_code,
    parse_params,
    print_error,
    progress_bar,
    render_report,
)
from evclock.tools._runs import parse_rtf, run_scenario
from evclock.tools._scenarios import (
    registered_scenarios,
)


@app.command("list")
def list_scenarios() -> None:
    """List the registered scenarios (entry-point group evclock.scenarios).

    A scenario whose extra is not installed is listed with what it needs,
    and a note on stderr gives the command that installs it (exit status 0).
    A registration that cannot be imported for another reason is listed as
    broken, with its error; the exit status is 2, the others are listed.
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
        Path | None, typer.Option(help="Record the run to this MCAP file (the record extra).")
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
    """Run a scenario with its controllers on evclock time.

    Exit status: 0 the mission succeeded, 1 it failed, 2 bad input, 3 cut
    short by --until before the mission ended (no verdict).
    """
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
            from evclock.ros2._session import require

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
            from evclock.tools._record import mcap_writer_class

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
    from evclock.tools._cli_remote import serve_scenario

    return functools.partial(serve_scenario, address=address, remote_controllers=remote_controllers)


def _register_remote() -> None:
    from evclock.tools._cli_remote import control_command

    app.command("control")(control_command)


_register_remote()


def main() -> None:
    """Entry point of the ``evclock`` console script."""
    app()
