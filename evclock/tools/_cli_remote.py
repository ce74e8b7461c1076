"""``evclock run SIM --serve ADDR [--remote-controllers]`` and ``evclock control SIM --clock ADDR``.

``--serve`` runs a scenario as ``evclock run`` does and serves its sim time. With
``--remote-controllers`` the simulation process runs only the world and its physics and
waits for the scenario's controllers, which ``evclock control`` runs in another process in
lockstep: they build the same scenario object (on a private copy of the world, only for its
attributes), then drive the served physics through :class:`RemotePhysics`. At the end the
controllers publish their report to the simulation, so both ends report the same run.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from evclock._errors import EvClockError, InvalidArgumentError, ParticipantLostError
from evclock._extras import import_extra
from evclock.hosts._current import clock
from evclock.hosts._loop import SimEventLoop
from evclock.hosts._runner import run as evclock_run
from evclock.remote._address import parse_address
from evclock.remote._participant import participant
from evclock.remote._physics import PhysicsService, RemotePhysics
from evclock.remote._server import DEFAULT_STEP_TIMEOUT, Message, serve

if TYPE_CHECKING:
    from rich.progress import Progress

    from evclock.tools._runs import RunReport

#: The participant name of a scenario's controllers.
CONTROLLERS = "controllers"
#: Topic on which the controllers hand their report to the simulation when they finish.
REPORT_TOPIC = "evclock.report"
#: Service answering the full physical state (``Scenario.state_vector``) as JSON.
STATE_SERVICE = "evclock.state"


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
) -> RunReport:
    """Run scenario ``name`` serving its sim time at ``address`` (see the module docstring)."""
    from evclock.sources import PyBulletTimeSource
    from evclock.tools._runs import RunReport, _loop_reports, scenario_class

    if wall:
        raise InvalidArgumentError("--serve serves sim time: drop --wall")
    cls = scenario_class(name, {})
    limit = _limit(cls, until)
    source = PyBulletTimeSource.connect(gui=gui)
    scenario = cls(source.client, seed)
    info = {"scenario": cls.name, "seed": seed, "until": limit}
    handed: dict[str, Any] = {}

    def receive_report(message: Message) -> None:
        handed.update(json.loads(message.data))

    async def main() -> RunReport:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        clk = clock()
        async with serve(
            address, info=info, on_fault=on_fault, step_timeout=step_timeout
        ) as server:
            PhysicsService(source.client).install(server)
            server.provide(STATE_SERVICE, lambda _: json.dumps(scenario.state_vector()).encode())
            server.subscribe(REPORT_TOPIC, receive_report)
            if progress is not None:
                progress.console.print(f"serving {cls.name}'s sim time at {server.address}")
            finished = True
            if remote_controllers:
                await server.wait_for_participants(CONTROLLERS)
                wall0 = time.perf_counter()
                await server.wait_until_left()
            else:
                wall0 = time.perf_counter()
                try:
                    async with asyncio.timeout(limit):
                        await scenario.run(clk)
                except TimeoutError:
                    finished = False
            wall_s = time.perf_counter() - wall0
        sim_s = loop.time()
        if remote_controllers and not handed:
            raise ParticipantLostError(
                f"the controllers left at {sim_s:g} s without handing over their report; "
                "see the output of `evclock control` for why",
                CONTROLLERS,
            )
        summary = handed["summary"] if remote_controllers else scenario.summary()
        return RunReport(
            scenario=cls.name,
            seed=seed,
            mode="sim",
            success=handed["success"] if remote_controllers else scenario.success(),
            finished=handed["finished"] if remote_controllers else finished,
            sim_time_s=sim_s,
            wall_time_s=wall_s,
            achieved_rtf=sim_s / wall_s if wall_s > 0 else None,
            summary=summary,
            loops=_loops_from(handed["loops"]) if remote_controllers else _loop_reports(clk),
            final_state=scenario.state_vector(),
            until_s=limit,
        )

    return evclock_run(main(), source=source, rtf=rtf)


def _loops_from(data: list[dict[str, Any]]) -> list[Any]:
    from evclock.tools._runs import LoopReport

    return [LoopReport(d["name"], d["hz"], d["stats"]) for d in data]


def _with_name(url: str, name: str) -> str:
    """``url`` with ``name=`` added to its query unless it names the participant already."""
    query = urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)
    if "name" in query:
        return url
    return f"{url}{'&' if '?' in url else '?'}{urllib.parse.urlencode({'name': name})}"


def control_scenario(
    name: str, *, clock_url: str, seed: int = 0, until: float | None = None
) -> RunReport:
    """Run scenario ``name``'s controllers against the simulation served at ``clock_url``."""
    from evclock.tools._runs import RunReport, _loop_reports, scenario_class

    scheme = urllib.parse.urlsplit(clock_url).scheme if isinstance(clock_url, str) else None
    if scheme not in ("unix", "tcp"):
        raise InvalidArgumentError(
            f"evclock control joins a simulation served by `evclock run SIM --serve ADDR "
            f"--remote-controllers` (unix:///path/sim.sock or tcp://127.0.0.1:PORT), got "
            f"{clock_url!r}: only an evclock clock server runs the scenario's physics for its "
            "controllers in lockstep"
        )
    parse_address(clock_url)  # the address's own errors, before anything is built
    cls = scenario_class(name, {})
    p = import_extra("pybullet", "pybullet", needed_by="evclock control")
    limit = _limit(cls, until)
    local = p.connect(p.DIRECT)  # a private copy of the world: builds the scenario object only
    try:
        scenario = cls(local, seed)
    finally:
        p.disconnect(local)

    async def main() -> RunReport:
        link = participant()
        served = (link.info.get("scenario"), link.info.get("seed"))
        if served != (cls.name, seed):
            raise InvalidArgumentError(
                f"the simulation at {link.address} runs {served[0]!r} with seed {served[1]}, "
                f"but these controllers are {cls.name!r} with seed {seed}; use the same on both"
            )
        scenario.pb = RemotePhysics(link)
        clk = clock()
        wall0 = time.perf_counter()
        finished = True
        try:
            async with asyncio.timeout(limit):
                await scenario.run(clk)
        except TimeoutError:
            finished = False
        wall_s = time.perf_counter() - wall0
        sim_s = clk.now().seconds
        report = RunReport(
            scenario=cls.name,
            seed=seed,
            mode="sim",
            success=scenario.success(),
            finished=finished,
            sim_time_s=sim_s,
            wall_time_s=wall_s,
            achieved_rtf=None,
            summary=scenario.summary(),
            loops=_loop_reports(clk),
            final_state=json.loads(link.call(STATE_SERVICE)),
            until_s=limit,
        )
        link.publish(REPORT_TOPIC, json.dumps(report.to_json()).encode())
        return report

    return evclock_run(main(), clock=_with_name(clock_url, CONTROLLERS))


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
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON to this file.")
    ] = None,
    quiet: Annotated[bool, typer.Option(help="Print only errors.")] = False,
) -> None:
    """Run a scenario's controllers in lockstep with a simulation served by another process.

    Exit status: 0 the mission succeeded, 1 it failed, 2 bad input, 3 cut
    short by --until before the mission ended (no verdict).
    """
    from rich.console import Console

    from evclock.tools._cli_app import exit_code, print_error, render_report

    console = Console()
    try:
        report = control_scenario(sim, clock_url=clock_url, seed=seed, until=until)
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(2) from None
    if not quiet:
        render_report(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_json(), indent=2))
    raise typer.Exit(exit_code(report))
