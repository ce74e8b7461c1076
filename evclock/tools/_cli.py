"""The ``evclock`` command: ``list``, ``run``, and the entry point that gathers every command.

``evclock run kuka --until 10 --rtf 1`` runs a scenario (see :mod:`evclock.tools._runs`) with a
progress bar (sim time and achieved real-time factor) and, at the end, a table of every rate
loop's ticks, missed periods and lateness. Other commands live in their own modules
(``_cli_sweep``: ``sweep``; ``_cli_trace``: ``trace diff`` and ``plot``; ``_cli_remote``:
``control``, ``token`` and ``run --serve``), all on the application object of
:mod:`evclock.tools._cli_app`.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import inspect
import json
import sys
import textwrap
import traceback
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Literal

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from evclock._errors import EvClockError, InvalidArgumentError, MissingExtraError
from evclock.ros2 import _cli as ros2_cli
from evclock.tools import _cli_sweep, _cli_trace  # noqa: F401  (they register their commands)
from evclock.tools._cli_app import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    app,
    check_seed,
    check_until,
    check_writable,
    exit_code,
    parse_params,
    print_error,
    print_run_error,
    progress_bar,
    render_report,
    with_exit_statuses,
)
from evclock.tools._cli_remote import TOKEN_FILE_HELP
from evclock.tools._runs import parse_rtf, run_scenario
from evclock.tools._scenarios import (
    ENGINE_LABELS,
    PYBULLET_WHEELS,
    engines_of,
    installed_engines,
    load_scenario,
    parameters,
    registered_scenarios,
    require_engine,
)


@app.command("list")
def list_scenarios(
    verbose: Annotated[
        bool,
        typer.Option(
            "--verbose", "-v", help="Also list each scenario's parameters (as evclock params)."
        ),
    ] = False,
) -> None:
    """List the registered scenarios (entry-point group evclock.scenarios), the engines
    each runs on and whether it runs here (yes, on the installed engine, or no).

    A scenario none of whose engines is installed, or whose extra is not,
    is listed with what it needs, and a note on stderr gives the command that
    installs it (exit status 0). A registration that cannot be imported for
    another reason is listed as broken, with its error; the exit status is 2,
    the others are listed.
    """
    table = Table(title="scenarios")
    table.add_column("name", no_wrap=True)
    table.add_column("sim seconds", justify="right")
    table.add_column("engines", min_width=8)
    table.add_column("runs here", no_wrap=True)
    table.add_column("description", min_width=12)
    table.add_column("from", no_wrap=True)
    try:
        entries = registered_scenarios()
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    installed = installed_engines()
    missing: dict[str, list[str]] = {}  # error message -> scenario names (insertion order)
    loaded: list[type[Any]] = []
    broken: list[str] = []
    for entry in entries:
        try:
            cls = entry.load()
        except MissingExtraError as exc:
            need = f"evclock[{exc.extra}]" if exc.extra else "an optional dependency"
            table.add_row(
                escape(entry.name),
                "-",
                "-",
                "-",
                escape(f"(needs {need})"),
                escape(entry.distribution),
            )
            missing.setdefault(str(exc), []).append(entry.name)
        except Exception as exc:  # a third-party registration must not hide the others
            table.add_row(
                escape(entry.name),
                "-",
                "-",
                "-",
                "(broken: see the error below)",
                escape(entry.distribution),
            )
            detail = str(exc) if isinstance(exc, EvClockError) else f"{type(exc).__name__}: {exc}"
            broken.append(f"scenario {entry.name!r} ({entry.target}) cannot be loaded: {detail}")
        else:
            engines = engines_of(cls)
            here = [engine for engine in engines if engine in installed]
            table.add_row(
                escape(entry.name),
                f"{cls.default_until:g}",
                escape(", ".join(engines)),
                _runs_here(engines, here),
                escape(str(cls.description)),
                escape(entry.distribution),
            )
            if not here:
                missing.setdefault(_no_engine_note(engines), []).append(entry.name)
            if verbose:
                loaded.append(cls)
    Console().print(table)
    for cls in loaded:
        print_parameters(cls)
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


def _runs_here(engines: tuple[str, ...], installed: list[str]) -> str:
    """``yes`` (every engine of the scenario is installed), ``no`` (none is) or ``on ENGINE``
    (the installed ones only)."""
    if len(installed) == len(engines):
        return "yes"
    return f"on {', '.join(installed)}" if installed else "no"


def _no_engine_note(engines: tuple[str, ...]) -> str:
    """Why a scenario running on ``engines``, none of them installed, cannot run, and how to
    install one."""
    labels = " nor ".join(ENGINE_LABELS.get(engine, engine) for engine in engines)
    # MuJoCo first: it has wheels on every supported Python, PyBullet on 3.11 only.
    ordered = [*(e for e in engines if e == "mujoco"), *(e for e in engines if e != "mujoco")]
    hints = " or ".join(f"pip install 'evclock[{engine}]'" for engine in ordered)
    status = f"neither {labels} is installed" if len(engines) > 1 else f"{labels} is not installed"
    note = f"{status}: {hints}"
    return f"{note} ({PYBULLET_WHEELS})" if "pybullet" in engines else note


def parameter_help(cls: type[Any]) -> dict[str, str]:
    """The help of each tunable parameter of scenario class ``cls``: the first line of the
    string literal that follows its assignment in the class body (an attribute docstring),
    read from the source of ``cls`` and its bases; ``""`` where there is none."""
    found: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue  # built in, generated (a --param subclass), or no source
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for statement, following in zip(body, [*body[1:], None], strict=True):
            if isinstance(statement, ast.Assign) and len(statement.targets) == 1:
                target = statement.targets[0]
            elif isinstance(statement, ast.AnnAssign):
                target = statement.target
            else:
                continue
            if not isinstance(target, ast.Name):
                continue
            text = ""
            if (
                isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)
            ):
                text = inspect.cleandoc(following.value.value).split("\n\n")[0]
            found[target.id] = " ".join(text.split())
    return found


@app.command("params")
def params_command(
    scenario: Annotated[
        str,
        typer.Argument(help="A registered name, a file path.py[:Class] or package.module:Class."),
    ],
) -> None:
    """List a scenario's parameters (what --param NAME=VALUE sets): name, type, default
    and help. Exit status 0, or 2 for an unknown scenario."""
    try:
        cls = load_scenario(scenario)
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    print_parameters(cls)


def print_parameters(cls: type[Any]) -> None:
    """The table of scenario class ``cls``'s parameters: name, type, default and help."""
    helps = parameter_help(cls)
    table = Table(title=f"{cls.name}: parameters (--param NAME=VALUE)")
    for column in ("name", "type", "default", "help"):
        table.add_column(column, no_wrap=column != "help")
    for name, default in parameters(cls).items():
        shown = ("true" if default else "false") if isinstance(default, bool) else repr(default)
        table.add_row(
            escape(name), type(default).__name__, escape(shown), escape(helps.get(name, ""))
        )
    Console().print(table)


@app.command("run")
@with_exit_statuses
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
    engine: Annotated[
        Literal["pybullet", "mujoco"],
        typer.Option(help="Physics engine: PyBullet, or MuJoCo (kuka, cartpole)."),
    ] = "pybullet",
    wall: Annotated[
        bool, typer.Option(help="Run the controllers on wall time; physics steps in real time.")
    ] = False,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON to this file.")
    ] = None,
    record: Annotated[
        Path | None,
        typer.Option(help="Record the run to this MCAP file (pip install 'evclock[record]')."),
    ] = None,
    foxglove: Annotated[
        bool,
        typer.Option(
            help="Serve the run live to Foxglove over WebSocket (the record extra); "
            "real time unless --rtf K is given."
        ),
    ] = False,
    foxglove_addr: Annotated[
        str,
        typer.Option(help="Where --foxglove listens: HOST:PORT (port 0: any free port)."),
    ] = "127.0.0.1:8765",
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
    verbose: Annotated[
        bool,
        typer.Option(help="If the scenario raises, print its full traceback, not one line."),
    ] = False,
    serve: Annotated[
        str | None,
        typer.Option(
            help="Serve this run's sim time at ADDR (unix:///path.sock, tcp://HOST:PORT, or "
            "tls://HOST:PORT with --tls-cert and --tls-key, between machines: TCP and TLS "
            "always need a token, from --token-file or EVCLOCK_TOKEN, else a fresh one is "
            "written to a private file whose path is printed)."
        ),
    ] = None,
    token_file: Annotated[
        Path | None,
        typer.Option(help=f"With --serve only. {TOKEN_FILE_HELP}"),
    ] = None,
    tls_cert: Annotated[
        Path | None,
        typer.Option(help="With --serve tls://...: the server's certificate chain (PEM)."),
    ] = None,
    tls_key: Annotated[
        Path | None,
        typer.Option(help="With --serve tls://...: the certificate's private key (PEM)."),
    ] = None,
    allow_remote: Annotated[
        bool,
        typer.Option(
            help="With --serve tls://...: listen beyond loopback (e.g. tls://0.0.0.0:PORT), "
            "for participants on other machines."
        ),
    ] = False,
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
    rmw: ros2_cli.Rmw = None,
    ros2: ros2_cli.Ros2Flag = False,
    ros2_frame_prefix: ros2_cli.Ros2FramePrefix = "",
    ros2_wait_for_subscribers: ros2_cli.Ros2WaitForSubscribers = None,
    ros2_wait_timeout: ros2_cli.Ros2WaitTimeout = ros2_cli.DEFAULT_WAIT_TIMEOUT,
) -> None:
    """Run a scenario with its controllers on evclock time.

    With --serve ADDR (and no --remote-controllers) the controllers run in
    this process and other processes may follow its sim time; with
    --remote-controllers they run in `evclock control`.
    """
    console = Console()
    try:
        check_seed(seed)
        check_until(until)
        pace = parse_rtf(rtf)
        # Usage errors first (the arguments alone decide them), then what this machine lacks
        # (an extra, the engine), all before any output.
        scenario_cls = load_scenario(scenario)
        ros2_options = ros2_cli.options_from_cli(
            ros2_clock,
            ros_domain_id,
            ros2_clock_decimation,
            ros2_wire_format,
            ros2_connect,
            ros2_listen,
            rmw,
            ros2,
            ros2_frame_prefix,
            ros2_wait_for_subscribers,
            ros2_wait_timeout,
        )
        if ros2_options is not None:
            if serve is not None:
                raise InvalidArgumentError("--ros2-clock with --serve is not supported; pick one")
            from evclock.ros2._session import require

            for module in ros2_options.extras:  # the ros2 extra: fail before any run
                require(module)
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
        if token_file is not None and serve is None:
            raise InvalidArgumentError("--token-file needs --serve ADDR (it is the clock's)")
        if (tls_cert is not None or tls_key is not None or allow_remote) and serve is None:
            raise InvalidArgumentError(
                "--tls-cert, --tls-key and --allow-remote need --serve tls://HOST:PORT"
            )
        served_scheme = None if serve is None else urllib.parse.urlsplit(serve).scheme
        if allow_remote and served_scheme in ("tcp", "unix"):
            raise InvalidArgumentError(
                f"--allow-remote is for --serve tls://HOST:PORT, not {served_scheme}://: "
                + (
                    "a unix:// socket is reached from this machine only; drop --allow-remote"
                    if served_scheme == "unix"
                    else "plain tcp:// stays on this machine (unencrypted, and any host could "
                    "pose as the server); serve across machines on tls://HOST:PORT with "
                    "--tls-cert and --tls-key"
                )
            )
        if serve is not None and values:
            raise InvalidArgumentError(
                "--serve runs the scenario as registered: drop --param "
                "(the joined controllers could not know about them)"
            )
        given_token = None
        if serve is not None:
            from evclock.tools._cli_remote import cli_token

            given_token = cli_token(serve, "--serve", token_file)
        if record is not None:
            from evclock.tools._record import mcap_writer_class

            mcap_writer_class()
        require_engine(scenario_cls, engine)
        if ros2_options is not None:
            console.print(ros2_options.describe(), soft_wrap=True)
        from evclock.tools._record import foxglove_option

        live, pace = foxglove_option(foxglove, foxglove_addr, pace, serve=serve)
        token, written = _serve_token(serve, given_token)
        recorded_before = file_identity(record)
        with _removed(written), progress_bar(None, quiet) as progress, live:
            if serve is not None:
                report = _served(serve, remote_controllers, tls_cert, tls_key, allow_remote)(
                    scenario,
                    token=token,
                    until=until,
                    rtf=pace,
                    seed=seed,
                    gui=gui,
                    wall=wall,
                    progress=progress,
                    record=record,
                    engine=engine,
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
                    ros2_clock=ros2_options,
                    engine=engine,
                )
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    except KeyboardInterrupt:
        print_error("interrupted (Ctrl-C) before the run started: nothing to report")
        raise typer.Exit(EXIT_INTERRUPTED) from None
    render_report(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_json(), indent=2))
    if record is not None and file_identity(record) not in (None, recorded_before):
        console.print(f"wrote the recording to {record}", markup=False, highlight=False)
    if report.error is not None:
        print_run_error(report, verbose)
    raise typer.Exit(exit_code(report))


def _serve_token(serve: str | None, given: str | None) -> tuple[str | None, Path | None]:
    """The token ``--serve`` serves with (``given``, from --token-file or EVCLOCK_TOKEN, or a
    fresh one whose file is announced on stderr)."""
    if serve is None:
        return None, None
    from evclock.tools._cli_remote import serve_token

    token, written = serve_token(serve, given)
    if written is not None:
        typer.echo(
            f"evclock: the clock token of {serve} is in {written} (mode 0600, removed when "
            f"this run ends); join with --token-file {written}",
            err=True,
        )
    return token, written


@contextlib.contextmanager
def _removed(path: Path | None) -> Iterator[None]:
    """Remove the file at ``path`` (if any) when the block ends, however it ends."""
    try:
        yield
    finally:
        if path is not None:
            path.unlink(missing_ok=True)


def file_identity(path: Path | None) -> tuple[int, int, int] | None:
    """What changes when ``path`` is written (inode, size, modification time in ns), or None
    when there is no such file: a run that ended before its recorder opened wrote nothing."""
    try:
        found = path.stat() if path is not None else None
    except OSError:
        return None
    return None if found is None else (found.st_ino, found.st_size, found.st_mtime_ns)


def _served(
    address: str,
    remote_controllers: bool,
    tls_cert: Path | None,
    tls_key: Path | None,
    allow_remote: bool,
) -> Any:
    from evclock.tools._cli_remote import serve_scenario

    return functools.partial(
        serve_scenario,
        address=address,
        remote_controllers=remote_controllers,
        tls_cert=None if tls_cert is None else str(tls_cert),
        tls_key=None if tls_key is None else str(tls_key),
        allow_remote=allow_remote,
    )


def _register_remote() -> None:
    from evclock.tools._cli_remote import control_command, token_command

    app.command("control")(with_exit_statuses(control_command))
    app.command("token")(token_command)


_register_remote()


def _usage_message(exc: Exception) -> str:
    """The message of click usage error ``exc``, without what a validator's parser adds: the
    typer versions that validate through pydantic prefix the message of a ``ValueError`` (an
    unknown ``--engine``) with pydantic's ``Value error, ``."""
    cause = exc.__cause__
    found = getattr(cause, "errors", None)
    details = found() if callable(found) else []
    message = getattr(exc, "message", None)
    if details and details[0].get("type") == "value_error" and isinstance(message, str):
        exc.message = message.removeprefix("Value error, ")  # type: ignore[attr-defined]
    return str(exc.format_message())  # type: ignore[attr-defined]


def main(args: list[str] | None = None) -> None:
    """Entry point of the ``evclock`` console script: runs the command and exits with its
    status (see :data:`EXIT_STATUS_HELP`).

    A usage error is one ``error:`` line and status 2; Ctrl-C outside a run is status 130;
    an unexpected exception is one ``error:`` line naming it and where it was raised (the
    traceback too with ``--verbose``) and status 4. PyBullet is imported first, without the
    build-time banner it prints on import.

    :param args: the command line without the program name (default: ``sys.argv[1:]``).
    """
    from evclock.tools._runs import describe_exception, exception_origin, import_pybullet_quietly

    # click's exceptions, wherever this typer takes them from (click, or its own copy).
    errors = sys.modules[typer.BadParameter.__module__]
    # (an empty tuple catches nothing: this click may not have the class)
    no_args: tuple[type[Exception], ...] = tuple(
        cls for cls in (getattr(errors, "NoArgsIsHelpError", None),) if cls is not None
    )
    argv = sys.argv[1:] if args is None else args
    import_pybullet_quietly()
    try:
        status = app(args=argv, prog_name="evclock", standalone_mode=False)
    except no_args as exc:
        exc.show()  # type: ignore[attr-defined]
        sys.exit(exc.exit_code)  # type: ignore[attr-defined]
    except errors.UsageError as exc:
        hint = f"; see '{exc.ctx.command_path} --help'" if exc.ctx is not None else ""
        print_error(f"{_usage_message(exc).rstrip('.')}{hint}")
        sys.exit(EXIT_USAGE)
    except errors.ClickException as exc:
        print_error(exc.format_message())
        sys.exit(exc.exit_code)
    except typer.Abort:  # Ctrl-C (or end of input) outside a run
        print_error("interrupted (Ctrl-C)")
        sys.exit(EXIT_INTERRUPTED)
    except Exception as exc:
        if "--verbose" in argv:
            traceback.print_exception(exc)
        print_error(
            f"{describe_exception(exc)} (raised in {exception_origin(exc)}); "
            "rerun with --verbose for the traceback"
            if "--verbose" not in argv
            else f"{describe_exception(exc)} (raised in {exception_origin(exc)})"
        )
        sys.exit(EXIT_ERROR)
    sys.exit(status if isinstance(status, int) else 0)
