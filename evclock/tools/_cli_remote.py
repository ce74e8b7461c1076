"""``evclock run SIM --serve ADDR [--remote-controllers]`` and ``evclock control SIM --clock ADDR``.

``--serve`` runs a scenario as ``evclock run`` does and serves its sim time. With
``--remote-controllers`` the simulation process runs only the world and its physics and
waits for the scenario's controllers, which ``evclock control`` runs in another process in
lockstep: they build the same scenario object (on a private copy of the world, only for its
attributes), then drive the served physics: on PyBullet through :class:`RemotePhysics`
(``scenario.pb``), on MuJoCo through :class:`RemoteMjData` (the world's ``data``; their copy
of the model serves their own kinematics). At the end the
controllers hand their verdict (success, summary, loop statistics) to the simulation, so
both ends report the same run. The simulation process alone writes its report and exit
status: it accepts that verdict only from the lockstep participant it waited for, once and
well-formed (anything else is answered with an error to its sender), measures sim time,
wall time and the final state itself, and stops when the controllers leave (a follower that
stays joined changes nothing).

Tokens never ride on the command line (any user of the machine reads a process's arguments):
both commands read one from ``--token-file PATH`` or ``EVCLOCK_TOKEN``
(:func:`evclock.remote._token.token_from`), refuse ``token=`` in an address, and ``--serve
tcp://...`` without one writes a fresh token to a private file (:func:`serve_token`).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import time
import urllib.parse
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer
from rich.console import Console

from evclock._errors import EvClockError, InvalidArgumentError, ParticipantLostError
from evclock._extras import import_extra
from evclock.hosts._current import clock
from evclock.hosts._loop import SimEventLoop
from evclock.hosts._runner import run as evclock_run
from evclock.remote._address import parse_address
from evclock.remote._mujoco_physics import MjDataService, RemoteMjData
from evclock.remote._participant import participant
from evclock.remote._physics import PhysicsService, RemotePhysics
from evclock.remote._server import DEFAULT_STEP_TIMEOUT, Message, serve
from evclock.remote._token import (
    ENV_TOKEN,
    check_token,
    new_token,
    token_from,
    write_token_file,
)

if TYPE_CHECKING:
    from rich.progress import Progress

    from evclock.tools._runs import RunReport

#: The participant name of a scenario's controllers.
CONTROLLERS = "controllers"
#: Topic on which the controllers hand their report to the simulation when they finish.
REPORT_TOPIC = "evclock.report"
#: Service answering the full physical state (``Scenario.state_vector``) as JSON.
STATE_SERVICE = "evclock.state"


#: ``--token-file``'s help, for both commands.
TOKEN_FILE_HELP = (
    "Read the clock token from this file (yours, chmod 600), or set EVCLOCK_TOKEN; never "
    "put token= in the address (every user can read a command line)."
)


def cli_token(address: str, option: str, token_file: Path | None) -> str | None:
    """The token for ``address`` given to ``option``: from ``--token-file`` or
    ``EVCLOCK_TOKEN`` (see :func:`~evclock.remote._token.token_from`), or None.

    :raises InvalidArgumentError: the address carries ``token=`` (the message does not show
        it), or the token file or variable is refused.
    """
    query = urllib.parse.parse_qs(
        urllib.parse.urlsplit(address).query if isinstance(address, str) else "",
        keep_blank_values=True,
    )
    if "token" in query:
        raise InvalidArgumentError(
            f"{option}: a token in the address (token=...) is readable by every user of the "
            "machine (a command line is public, /proc/PID/cmdline); drop it from the address "
            f"and pass it with --token-file PATH (a file only you can read: chmod 600) or in "
            f"the {ENV_TOKEN} environment variable"
        )
    token = token_from(token_file)
    if token is not None:
        check_token(token)  # a weak one is a usage error here, before anything is built
    return token


def serve_token(address: str, token: str | None) -> tuple[str | None, Path | None]:
    """The token ``evclock run --serve ADDR`` serves with, and the file it wrote it to.

    ``token`` (from ``--token-file`` or ``EVCLOCK_TOKEN``: :func:`cli_token`) if given, no
    file written; otherwise, on TCP and TLS, a fresh 256-bit token written to a new 0600 file
    of the private directory (the caller prints its path and removes the file when the run
    ends); on a Unix socket, none.
    """
    if token is not None or urllib.parse.urlsplit(address).scheme not in ("tcp", "tls"):
        return token, None
    token = new_token()
    return token, write_token_file(token, f"sim-{os.getpid()}")


def token_command() -> None:
    """Print a fresh random clock token (256 bits, URL-safe) for --token-file or
    EVCLOCK_TOKEN; write it to a private file with `(umask 077; evclock token > FILE)`."""
    typer.echo(new_token())


def _limit(cls: Any, until: float | None) -> float:
    limit = cls.default_until if until is None else until
    if not (isinstance(limit, int | float) and math.isfinite(limit) and limit > 0):
        raise InvalidArgumentError(f"--until must be a positive number of seconds, got {until!r}")
    return float(limit)


def serve_scenario(
    name: str,
    *,
    address: str,
    remote_controllers: bool = False,
    until: float | None = None,
    rtf: float | None = None,
    seed: int = 0,
    gui: bool = False,
    wall: bool = False,
    progress: Progress | None = None,
    on_fault: str = "abort",
    step_timeout: float | None = DEFAULT_STEP_TIMEOUT,
    record: Path | None = None,
    engine: str = "pybullet",
    token: str | None = None,
    tls_cert: str | None = None,
    tls_key: str | None = None,
    allow_remote: bool = False,
) -> RunReport:
    """Run scenario ``name`` serving its sim time at ``address`` (see the module docstring).

    ``token``: the clock token participants must prove they know (needed on TCP and TLS);
    ``tls_cert`` and ``tls_key``: the certificate and key a ``tls://`` address serves with;
    ``allow_remote``: listen beyond loopback (``tls://`` only, see ``serve()``).

    ``record`` (and a live view, see :func:`evclock.tools._record.live_view`): the simulation
    writes the world's channels (state, joints, transforms, scene) and, when the controllers
    run here, their loops and channels too. ``engine``: ``"pybullet"`` (default) or
    ``"mujoco"`` (see :func:`~evclock.tools._scenarios.open_engine`); the served info names
    it, and ``evclock control`` refuses to join with another.
    """
    from evclock.tools._runs import (
        RunReport,
        _loop_reports,
        _Outcome,
        install_step_hooks,
        scenario_class,
    )
    from evclock.tools._scenarios import open_world, require_engine

    if wall:
        raise InvalidArgumentError("--serve serves sim time: drop --wall")
    cls = scenario_class(name, {})
    require_engine(cls, engine)
    limit = _limit(cls, until)
    opened, scenario = open_world(cls, seed, engine=engine, gui=gui)
    source: Any = opened  # PyBullet's or MuJoCo's: a stepping source either way
    install_step_hooks(scenario, source)  # the world's per-step hooks run with the physics
    from evclock.tools._record import open_recorder, world_of  # --record/--foxglove: the sim's

    recorder = open_recorder(record, cls, seed, {}, limit, world=world_of(source))
    info = {
        "scenario": cls.name,
        "seed": seed,
        "engine": engine,
        "until": limit,
        "remote_controllers": remote_controllers,
        # exact, so the controllers' loop reports know their deadlines' quantisation
        "physics_step_ns": [source.time_step_ns.numerator, source.time_step_ns.denominator],
    }
    handed: dict[str, Any] = {}

    def receive_report(message: Message) -> None:
        if message.sender != CONTROLLERS:
            raise InvalidArgumentError(
                f"only the controllers ({CONTROLLERS!r}) hand over the run's report, not "
                f"{message.sender!r}"
            )
        if handed:
            raise InvalidArgumentError("the controllers' report was handed over already")
        handed.update(_checked_report(message.data))

    async def main() -> RunReport:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        clk = clock()
        if recorder is not None:
            recorder.attach(source, clk, scenario.state_vector)
        async with serve(
            address,
            info=info,
            on_fault=on_fault,
            step_timeout=step_timeout,
            token=token,
            tls_cert=tls_cert,
            tls_key=tls_key,
            allow_remote=allow_remote,
        ) as server:
            if engine == "mujoco":
                MjDataService(scenario.world.data).install(server)
            else:
                PhysicsService(source.client).install(server)
            server.provide(STATE_SERVICE, lambda _: json.dumps(scenario.state_vector()).encode())
            server.subscribe(REPORT_TOPIC, receive_report)
            if progress is not None:
                where = (
                    "its controllers join with `evclock control`"
                    if remote_controllers
                    else "its controllers run in this process; other processes may follow "
                    "this sim time (`evclock control` needs --remote-controllers)"
                )
                Console().print(  # on stdout (the progress bar is on stderr)
                    f"serving {cls.name}'s sim time at {server.address}: {where}",
                    soft_wrap=True,
                    markup=False,
                    highlight=False,
                )
            outcome = _Outcome()
            if remote_controllers:
                await server.wait_for_participants(CONTROLLERS)
                wall0 = time.perf_counter()
                await server.wait_until_left(CONTROLLERS)
            else:
                wall0 = time.perf_counter()
                await outcome.run(scenario, clk, limit)
            finished = outcome.finished and outcome.error is None and not outcome.interrupted
            wall_s = time.perf_counter() - wall0
        sim_s = loop.time()
        if recorder is not None:
            recorder.observe()  # the final sample, as the in-process run records it
        if remote_controllers and not handed:
            raise ParticipantLostError(
                f"the controllers left at {sim_s:g} s without handing over their report; "
                "see the output of `evclock control` for why",
                CONTROLLERS,
            )
        summary = handed["summary"] if remote_controllers else scenario.summary()
        report = RunReport(
            scenario=cls.name,
            seed=seed,
            mode="sim",
            engine=engine,
            success=handed["success"]
            if remote_controllers
            else outcome.error is None and scenario.success(),
            finished=handed["finished"] if remote_controllers else finished,
            sim_time_s=sim_s,
            wall_time_s=wall_s,
            achieved_rtf=sim_s / wall_s if wall_s > 0 else None,
            summary=summary,
            loops=_loops_from(handed["loops"], source.time_step_ns)
            if remote_controllers
            else _loop_reports(clk, source.time_step_ns),
            final_state=scenario.state_vector(),
            until_s=limit,
            physics_step_s=source.time_step,
        )
        if remote_controllers:  # the controllers' error, as they handed it over
            report.error = handed.get("error")
            report.error_where = handed.get("error_where")
            report.traceback = handed.get("traceback")
            return report
        return outcome.apply(report)

    report: RunReport | None = None
    try:
        report = evclock_run(main(), source=source, rtf=rtf)
    finally:
        if recorder is not None:
            from evclock.tools._runs import _outcome

            recorder.close(None if report is None else _outcome(report))
    return report


def _checked_report(data: bytes) -> dict[str, Any]:
    """The controllers' verdict, if it is one: ``success``/``finished`` booleans, a
    ``summary`` object and ``loops`` as ``{name, hz, stats}`` objects."""
    try:
        report = json.loads(data)
    except ValueError:
        raise InvalidArgumentError("the controllers' report is not JSON") from None
    if not isinstance(report, dict):
        raise InvalidArgumentError("the controllers' report is not a JSON object")
    for key in ("success", "finished"):
        if not isinstance(report.get(key), bool):
            raise InvalidArgumentError(f"the controllers' report has no boolean {key!r}")
    if not isinstance(report.get("summary"), dict):
        raise InvalidArgumentError("the controllers' report has no 'summary' object")
    loops = report.get("loops")
    if not isinstance(loops, list) or not all(
        isinstance(d, dict) and {"name", "hz", "stats"} <= d.keys() for d in loops
    ):
        raise InvalidArgumentError("the controllers' report has no 'loops' list")
    checked = {key: report[key] for key in ("success", "finished", "summary", "loops")}
    for key in ("error", "error_where", "traceback"):  # a controller that raised: why
        if isinstance(report.get(key), str):
            checked[key] = report[key]
    return checked


def _loops_from(data: list[dict[str, Any]], step_ns: Fraction) -> list[Any]:
    """The controllers' loop reports, each checked against this simulation's physics step."""
    from evclock.tools._runs import loop_report

    return [loop_report(d["name"], d["hz"], d["stats"], step_ns) for d in data]


def _served_step_ns(info: dict[str, Any], address: str) -> Fraction | None:
    """The physics step a simulation serves (``physics_step_ns``: numerator and denominator,
    in ns), or None from a server that does not say (evclock 0.2)."""
    served = info.get("physics_step_ns")
    if served is None:
        return None
    if (
        not isinstance(served, list)
        or len(served) != 2
        or not all(type(n) is int and n > 0 for n in served)
    ):
        raise InvalidArgumentError(
            f"the simulation at {address} serves a malformed physics step {served!r}: "
            "expected [numerator, denominator] in nanoseconds, two positive integers"
        )
    return Fraction(served[0], served[1])


def _joining(url: str, name: str, token: str | None) -> str:
    """``url`` with ``name=`` added to its query unless it names the participant already,
    and ``token=`` if given (a string in this process, never on a command line)."""
    query = urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)
    added = {} if "name" in query else {"name": name}
    if token is not None:
        added["token"] = token
    if not added:
        return url
    return f"{url}{'&' if '?' in url else '?'}{urllib.parse.urlencode(added)}"


def _private_copy(cls: type[Any], seed: int, engine: str) -> Any:
    """Scenario ``cls`` built on a private copy of its world: the controllers' attributes
    (targets, gains...) and, on MuJoCo, the model their own kinematics run on."""
    if engine == "mujoco":
        from evclock.tools._scenarios import open_engine

        _, world = open_engine(cls, engine)
        return cls(world, seed)
    p = import_extra("pybullet", "pybullet", needed_by="evclock control")
    local = p.connect(p.DIRECT)
    try:
        return cls(local, seed)
    finally:
        p.disconnect(local)


def control_scenario(
    name: str,
    *,
    clock_url: str,
    seed: int = 0,
    until: float | None = None,
    engine: str = "pybullet",
    token: str | None = None,
    policy: str | None = None,
    tls_ca: str | None = None,
    tls_fingerprint: str | None = None,
) -> RunReport:
    """Run scenario ``name``'s controllers against the simulation served at ``clock_url``
    (which must run the same scenario, seed and ``engine``), proving ``token`` if given;
    ``policy`` (a scenario's ``policy`` parameter: a trained policy, see ``evclock.gym``)
    replaces its agent's controller; ``tls_ca`` or ``tls_fingerprint`` verify a ``tls://``
    server (added to the address's query: neither is a secret)."""
    from evclock.tools._runs import RunReport, _loop_reports, _Outcome, scenario_class
    from evclock.tools._scenarios import require_engine

    scheme = urllib.parse.urlsplit(clock_url).scheme if isinstance(clock_url, str) else None
    if scheme not in ("unix", "tcp", "tls"):
        raise InvalidArgumentError(
            f"evclock control joins a simulation served by `evclock run SIM --serve ADDR "
            f"--remote-controllers` (unix:///path/sim.sock, tcp://127.0.0.1:PORT or "
            f"tls://HOST:PORT), got "
            f"{clock_url!r}: only an evclock clock server runs the scenario's physics for its "
            "controllers in lockstep"
        )
    verify = {"tls_ca": tls_ca, "tls_fingerprint": tls_fingerprint}
    given = {key: value for key, value in verify.items() if value is not None}
    if len(given) == 2:
        raise InvalidArgumentError(
            "--tls-ca and --tls-fingerprint are two ways to verify the simulation: give one "
            "(--tls-ca for a certificate your CA signed, --tls-fingerprint for a self-signed one)"
        )
    if given and scheme != "tls":
        raise InvalidArgumentError(
            f"--tls-ca and --tls-fingerprint verify a simulation served on tls://, not "
            f"{scheme}://: drop the option, or join it with --clock tls://HOST:PORT"
        )
    if given:
        clock_url = f"{clock_url}{'&' if '?' in clock_url else '?'}{urllib.parse.urlencode(given)}"
    parsed = parse_address(clock_url)  # the address's own errors, before anything is built
    if parsed.scheme == "tls" and parsed.tls_ca is None and parsed.tls_fingerprint is None:
        raise InvalidArgumentError(
            f"joining the simulation at {parsed} needs a way to verify it: --tls-ca FILE (the "
            "CA that signed its certificate) or --tls-fingerprint SHA256 (its certificate's "
            "fingerprint)"
        )
    if parsed.scheme in ("tcp", "tls") and token is None and parsed.token is None:
        raise InvalidArgumentError(
            f"joining the simulation at {parsed} over {parsed.scheme} needs its token: pass "
            "the file "
            f"`evclock run --serve` printed with --token-file PATH, or set {ENV_TOKEN}"
        )
    cls = scenario_class(name, {} if policy is None else {"policy": policy})
    require_engine(cls, engine)
    limit = _limit(cls, until)
    scenario = _private_copy(cls, seed, engine)

    async def main() -> RunReport:
        link = participant()
        served = (link.info.get("scenario"), link.info.get("seed"))
        if link.info.get("remote_controllers") is False:
            raise InvalidArgumentError(
                f"the simulation at {link.address} runs {served[0]!r}'s controllers itself "
                "(it was started without --remote-controllers); these would be a second "
                f"controller stack: restart it with `evclock run {cls.name} --serve ADDR "
                "--remote-controllers`, or only follow its sim time (EVCLOCK_CLOCK="
                "ADDR?mode=follow)"
            )
        if served != (cls.name, seed):
            raise InvalidArgumentError(
                f"the simulation at {link.address} runs {served[0]!r} with seed {served[1]}, "
                f"but these controllers are {cls.name!r} with seed {seed}; use the same on both"
            )
        served_engine = link.info.get("engine", "pybullet")  # (servers before MuJoCo: none)
        if served_engine != engine:
            raise InvalidArgumentError(
                f"the simulation at {link.address} runs {served[0]!r} on {served_engine}, but "
                f"these controllers are for {engine}; use the same engine on both (--engine "
                f"{served_engine})"
            )
        if engine == "mujoco":  # the world's data is the simulation's; its model stays here
            scenario.world.data = RemoteMjData(link, scenario.world.data)
        else:
            scenario.pb = RemotePhysics(link)
        step_ns = _served_step_ns(link.info, link.address)
        clk = clock()
        wall0 = time.perf_counter()
        outcome = _Outcome()
        await outcome.run(scenario, clk, limit)
        finished = outcome.finished and outcome.error is None and not outcome.interrupted
        wall_s = time.perf_counter() - wall0
        sim_s = clk.now().seconds
        report = RunReport(
            scenario=cls.name,
            seed=seed,
            mode="sim",
            engine=engine,
            success=outcome.error is None and scenario.success(),
            finished=finished,
            sim_time_s=sim_s,
            wall_time_s=wall_s,
            achieved_rtf=None,
            summary=scenario.summary(),
            loops=_loop_reports(clk, step_ns),
            final_state=json.loads(link.call(STATE_SERVICE)),
            until_s=limit,
            physics_step_s=None if step_ns is None else float(step_ns / 1_000_000_000),
        )
        outcome.apply(report)
        link.publish(REPORT_TOPIC, json.dumps(report.to_json()).encode())
        return report

    return evclock_run(main(), clock=_joining(clock_url, CONTROLLERS, token))


def control_command(
    sim: Annotated[str, typer.Argument(help="Scenario name (the one the simulation runs).")],
    clock_url: Annotated[
        str,
        typer.Option(
            "--clock", help="The simulation's address (from `evclock run SIM --serve ADDR`)."
        ),
    ],
    until: Annotated[
        float | None, typer.Option(help="Stop after this many seconds (default: the scenario's).")
    ] = None,
    seed: Annotated[int, typer.Option(help="The seed the simulation was started with.")] = 0,
    engine: Annotated[
        Literal["pybullet", "mujoco"],
        typer.Option(help="The physics engine the simulation runs (its --engine)."),
    ] = "pybullet",
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON to this file.")
    ] = None,
    quiet: Annotated[bool, typer.Option(help="Print only errors.")] = False,
    token_file: Annotated[Path | None, typer.Option(help=TOKEN_FILE_HELP)] = None,
    policy: Annotated[
        str | None,
        typer.Option(
            help="A trained policy in place of the scenario's agent controller: a .npz of "
            "evclock.gym.LinearPolicy or module:callable (the scenario's policy parameter)."
        ),
    ] = None,
    tls_ca: Annotated[
        Path | None,
        typer.Option(help="--clock tls://...: the CA file (PEM) that signed its certificate."),
    ] = None,
    tls_fingerprint: Annotated[
        str | None,
        typer.Option(help="--clock tls://...: the SHA-256 fingerprint of its certificate."),
    ] = None,
) -> None:
    """Run a scenario's controllers in lockstep with a simulation served by another process
    (`evclock run SIM --serve ADDR --remote-controllers`; one started without
    --remote-controllers runs its own controllers and is refused)."""
    from rich.console import Console

    from evclock.tools._cli_app import (
        check_seed,
        check_until,
        exit_code,
        print_error,
        print_run_error,
        render_report,
    )

    console = Console()
    try:
        check_seed(seed)
        check_until(until)
        token = cli_token(clock_url, "--clock", token_file)
        report = control_scenario(
            sim,
            clock_url=clock_url,
            seed=seed,
            until=until,
            engine=engine,
            token=token,
            policy=policy,
            tls_ca=None if tls_ca is None else str(tls_ca),
            tls_fingerprint=tls_fingerprint,
        )
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(2) from None
    if not quiet:
        render_report(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_json(), indent=2))
    if report.error is not None:
        print_run_error(report, verbose=False)
    raise typer.Exit(exit_code(report))
