"""The ``evclock`` command: run a PyBullet scenario on simulation time (or on wall time).

``evclock run kuka --until 10 --rtf 1`` steps the physics from evclock's loop while the
scenario's controllers run as tasks on sim time, with a progress bar (sim time and achieved
real-time factor) and, at the end, a table of every rate loop's ticks, missed periods and
lateness. ``--wall`` runs the same controllers on wall time while a "world" task steps the
physics in real time, the stand-in for real hardware.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ._clock import Clock, clock
from ._errors import EvClockError, InvalidArgumentError
from ._loop import SimEventLoop
from ._pacing import check_rtf
from ._runner import run as evclock_run

if TYPE_CHECKING:
    from evclock_sims import Scenario

PHYSICS_HZ = 240
_PROGRESS_PERIOD = 0.05  # sim seconds between progress refreshes

app = typer.Typer(
    help="evclock: asyncio robot controllers on simulation time.",
    no_args_is_help=True,
    add_completion=False,
)


@dataclasses.dataclass
class LoopReport:
    """One rate loop's figures at the end of a run."""

    name: str
    hz: float
    stats: dict[str, float | int]


@dataclasses.dataclass
class RunReport:
    """What a scenario run produced: success, timing, per-loop statistics, final state."""

    scenario: str
    seed: int
    mode: str
    success: bool
    finished: bool
    sim_time_s: float
    wall_time_s: float
    achieved_rtf: float | None
    summary: dict[str, Any]
    loops: list[LoopReport]
    final_state: list[float]

    def to_json(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["summary"] = {k: _jsonable(v) for k, v in self.summary.items()}
        return data


def _jsonable(value: object) -> object:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def parse_rtf(text: str) -> float | None:
    """``max`` (as fast as possible) or a positive real-time factor."""
    if text.strip().lower() == "max":
        return None
    try:
        return check_rtf(float(text))
    except (ValueError, EvClockError):
        raise InvalidArgumentError(
            f"--rtf takes 'max' (as fast as possible) or a positive number (1 = real time), "
            f"got {text!r}"
        ) from None


def _loop_reports(clk: Clock) -> list[LoopReport]:
    return [LoopReport(rate.name, float(rate.hz), rate.stats.as_dict()) for rate in clk.rates]


def _report(
    scenario: Scenario,
    mode: str,
    clk: Clock,
    finished: bool,
    sim_s: float,
    wall_s: float,
    achieved_rtf: float | None,
    summary: dict[str, Any],
) -> RunReport:
    return RunReport(
        scenario=scenario.name,
        seed=scenario.seed,
        mode=mode,
        success=scenario.success(),
        finished=finished,
        sim_time_s=sim_s,
        wall_time_s=wall_s,
        achieved_rtf=achieved_rtf,
        summary=summary,
        loops=_loop_reports(clk),
        final_state=scenario.state_vector(),
    )


def _scenario_class(name: str) -> type[Scenario]:
    import evclock_sims as sims

    try:
        cls: type[Scenario] = sims.get_scenario(name)
    except ValueError as exc:
        raise InvalidArgumentError(str(exc)) from None
    return cls


def run_scenario(
    name: str,
    *,
    until: float | None = None,
    rtf: float | None = None,
    seed: int = 0,
    gui: bool = False,
    wall: bool = False,
    progress: Progress | None = None,
) -> RunReport:
    """Run scenario ``name`` and report. On sim time unless ``wall`` (see module docstring)."""
    cls = _scenario_class(name)
    limit = cls.default_until if until is None else until
    if not (isinstance(limit, int | float) and math.isfinite(limit) and limit > 0):
        raise InvalidArgumentError(f"--until must be a positive number of seconds, got {until!r}")
    if wall:
        return _run_on_wall_time(cls, limit, seed, gui, progress)
    return _run_on_sim_time(cls, limit, rtf, seed, gui, progress)


def _run_on_sim_time(
    cls: type[Scenario],
    limit: float,
    rtf: float | None,
    seed: int,
    gui: bool,
    progress: Progress | None,
) -> RunReport:
    from .sources import PyBulletTimeSource

    source = PyBulletTimeSource.connect(gui=gui)
    scenario = cls(source.client, seed)
    task_id = progress.add_task(cls.name, total=limit, rtf="-") if progress else None

    async def show_progress(loop: SimEventLoop) -> None:
        assert progress is not None
        assert task_id is not None
        while True:
            achieved = loop.achieved_rtf()
            progress.update(
                task_id,
                completed=min(loop.time(), limit),
                rtf="-" if achieved is None else f"{achieved:.2f}",
            )
            await asyncio.sleep(_PROGRESS_PERIOD)

    async def main() -> RunReport:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        clk = clock()
        shower = asyncio.create_task(show_progress(loop)) if progress else None
        wall0 = time.perf_counter()
        loop.achieved_rtf()
        finished = True
        try:
            async with asyncio.timeout(limit):
                await scenario.run(clk)
        except TimeoutError:
            finished = False
        finally:
            if shower is not None:
                shower.cancel()
        wall_s = time.perf_counter() - wall0
        sim_s = loop.time()
        if progress is not None and task_id is not None:
            progress.update(task_id, completed=min(sim_s, limit))
        achieved = sim_s / wall_s if wall_s > 0 else None
        return _report(scenario, "sim", clk, finished, sim_s, wall_s, achieved, scenario.summary())

    return evclock_run(main(), source=source, rtf=rtf)


def _run_on_wall_time(
    cls: type[Scenario], limit: float, seed: int, gui: bool, progress: Progress | None
) -> RunReport:
    import pybullet as p

    cid = p.connect(p.GUI if gui else p.DIRECT)
    try:
        scenario = cls(cid, seed)
        task_id = progress.add_task(cls.name, total=limit, rtf="1 (wall)") if progress else None

        async def world() -> None:
            # The stand-in for real hardware: physics advances with the wall clock.
            async for _tick in clock().rate(PHYSICS_HZ, name="world (physics)"):
                p.stepSimulation(physicsClientId=cid)
                if progress is not None and task_id is not None:
                    progress.update(task_id, completed=min(time.perf_counter() - wall0, limit))

        async def main() -> RunReport:
            clk = clock()
            start = clk.now().seconds
            physics = asyncio.create_task(world())
            finished = True
            try:
                async with asyncio.timeout(limit):
                    await scenario.run(clk)
            except TimeoutError:
                finished = False
            finally:
                physics.cancel()
            wall_s = time.perf_counter() - wall0
            summary = scenario.summary()
            if scenario.finished_at is not None:
                summary["mission_time_s"] = scenario.finished_at - start
            return _report(scenario, "wall", clk, finished, wall_s, wall_s, 1.0, summary)

        wall0 = time.perf_counter()
        return evclock_run(main(), use_sim_time=False)
    finally:
        p.disconnect(cid)


def _ms(seconds: float | int) -> str:
    return f"{seconds * 1e3:.3f}"


def render_report(report: RunReport, console: Console) -> None:
    """Print the per-loop table and the scenario summary."""
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
    summary = Table(title="summary", show_header=False)
    summary.add_column("metric")
    summary.add_column("value", justify="right")
    for key, value in report.summary.items():
        summary.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    rtf = "-" if report.achieved_rtf is None else f"{report.achieved_rtf:.2f}"
    summary.add_row("sim time s", f"{report.sim_time_s:.3f}")
    summary.add_row("wall time s", f"{report.wall_time_s:.3f}")
    summary.add_row("achieved rtf", rtf)
    console.print(summary)
    verdict = "[green]SUCCESS[/green]" if report.success else "[red]FAILED[/red]"
    console.print(f"{report.scenario} (seed {report.seed}): {verdict}")


@app.command("list")
def list_scenarios() -> None:
    """List the scenarios in sims/."""
    import evclock_sims as sims

    table = Table(title="scenarios")
    table.add_column("name")
    table.add_column("sim seconds", justify="right")
    table.add_column("description")
    for name, cls in sims.SCENARIOS.items():
        table.add_row(name, f"{cls.default_until:g}", cls.description)
    Console().print(table)


@app.command("run")
def run_command(
    sim: Annotated[str, typer.Argument(help="Scenario name (see `evclock list`).")],
    until: Annotated[
        float | None, typer.Option(help="Stop after this many seconds (default: the scenario's).")
    ] = None,
    rtf: Annotated[
        str, typer.Option(help="Real-time factor: 'max' (as fast as possible), 1, or K.")
    ] = "max",
    seed: Annotated[int, typer.Option(help="Seed of the scenario's random choices.")] = 0,
    gui: Annotated[bool, typer.Option(help="Open PyBullet's GUI (needs a display).")] = False,
    wall: Annotated[
        bool, typer.Option(help="Run the controllers on wall time; physics steps in real time.")
    ] = False,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON to this file.")
    ] = None,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
) -> None:
    """Run a PyBullet scenario with its controllers on evclock time."""
    console = Console()
    try:
        pace = parse_rtf(rtf)
        if wall and pace is not None:
            raise InvalidArgumentError("--wall runs in real time: drop --rtf (or use --rtf max)")
        columns = (
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.2f}/{task.total:g} s"),
            TextColumn("rtf {task.fields[rtf]}"),
            TimeElapsedColumn(),
        )
        with Progress(*columns, console=console, disable=quiet, transient=False) as progress:
            report = run_scenario(
                sim, until=until, rtf=pace, seed=seed, gui=gui, wall=wall, progress=progress
            )
    except EvClockError as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")  # [extra] is not markup
        raise typer.Exit(2) from None
    render_report(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_json(), indent=2))
    raise typer.Exit(0 if report.success else 1)


def main() -> None:
    """Entry point of the ``evclock`` console script."""
    app()
