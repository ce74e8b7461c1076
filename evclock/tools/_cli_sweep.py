"""``evclock sweep``: a scenario over seeds and parameter values, with a live progress bar
(done / failed / ETA / aggregate real-time factor) and a summary (success rate, quantiles of
every numeric report field, the failing runs with the command reproducing each).

Exit codes: 0 every run succeeded, 1 some did not, 2 bad input, 130 interrupted (Ctrl-C;
the rows that finished are still printed and written).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from evclock._errors import EvClockError, InvalidArgumentError
from evclock.tools._cli_app import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_SUCCESS,
    EXIT_USAGE,
    app,
    check_writable,
    parse_params,
    print_error,
)
from evclock.tools._sweep import BACKENDS, SweepResult, SweepRow, parse_seeds, plan, sweep

_SHOWN_FAILURES = 20


class SweepProgress:
    """The sweep's progress bar: runs done, failed, ETA, achieved aggregate rtf."""

    def __init__(self, console: Console, total: int, quiet: bool) -> None:
        columns = (
            TextColumn("[bold]sweep"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("failed {task.fields[failed]}"),
            TextColumn("rtf {task.fields[rtf]}"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
        )
        self.progress = Progress(*columns, console=console, disable=quiet, auto_refresh=False)
        self.task = self.progress.add_task("sweep", total=total, failed=0, rtf="-")
        self.failed = 0
        self.sim_s = 0.0
        self.wall0 = 0.0

    def row_done(self, row: SweepRow) -> None:
        """Count a finished run."""
        if row.status != "success":
            self.failed += 1
        if row.report is not None:
            self.sim_s += float(row.report["sim_time_s"])
        self.progress.update(self.task, advance=1, failed=self.failed)
        self.idle()

    def idle(self) -> None:
        """Refresh the elapsed time, the ETA and the aggregate rtf."""
        elapsed = self.progress.tasks[0].elapsed or 0.0
        rtf = f"{self.sim_s / elapsed:.1f}" if elapsed > 0 and self.sim_s > 0 else "-"
        self.progress.update(self.task, rtf=rtf)
        self.progress.refresh()


def render_sweep(result: SweepResult, console: Console) -> None:
    """Print the success rate, the quantile table and the failing runs."""
    summary = result.summary()
    rate = summary["success_rate"]
    counts = ", ".join(f"{n} {status}" for status, n in summary["status_counts"].items())
    head = f"{result.name}: {summary['done']}/{summary['planned']} runs ({counts})"
    if result.interrupted:
        head += " [yellow]interrupted[/yellow]"
    console.print(head)
    if rate is not None:
        console.print(f"success rate {rate:.1%}, wall time {result.wall_time_s:.1f} s")
    table = Table(title="report fields over the runs")
    table.add_column("field", no_wrap=True)
    for q in ("min", "p5", "median", "p95", "max"):
        table.add_column(q, justify="right")
    for field, values in summary["quantiles"].items():
        table.add_row(field, *(f"{v:.4g}" for v in values.values()))
    console.print(table)
    failed = result.failed
    for row in failed[:_SHOWN_FAILURES]:
        reason = row.error or row.status
        console.print(f"[red]{row.status}[/red] seed {row.spec.seed}: {reason}", soft_wrap=True)
        console.print(f"  reproduce: {row.spec.command()}", soft_wrap=True, highlight=False)
    if len(failed) > _SHOWN_FAILURES:
        console.print(f"... and {len(failed) - _SHOWN_FAILURES} more (see --json)")


@app.command("sweep")
def sweep_command(
    scenario: Annotated[
        str, typer.Argument(help="A registered name, a file path.py[:Class] or module:Class.")
    ],
    seeds: Annotated[
        str, typer.Option(help="Seeds: START:STOP (STOP excluded), N, or N1,N2,...")
    ] = "0:10",
    param: Annotated[
        list[str] | None,
        typer.Option("--param", help="name=v1,v2,...: values to sweep (repeatable)."),
    ] = None,
    until: Annotated[
        float | None, typer.Option(help="Sim seconds per run (default: the scenario's).")
    ] = None,
    backend: Annotated[str, typer.Option(help="local (process pool) or ray.")] = "local",
    workers: Annotated[int, typer.Option(help="Runs at the same time.")] = 1,
    address: Annotated[
        str | None,
        typer.Option(help="Ray cluster address (ray backend; default: start a local Ray)."),
    ] = None,
    run_timeout: Annotated[
        float | None,
        typer.Option(help="Wall seconds a run may take; a run still going is stopped (a row)."),
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the summary and every row as JSON.")
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(help="Draw a histogram of every numeric report field to this PNG."),
    ] = None,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
) -> None:
    """Run a scenario over many seeds and parameter values, each run in its own process.

    Exit status: 0 every run succeeded, 1 some did not, 2 bad input, 130
    interrupted (the finished rows are printed and written, marked so).
    """
    console = Console()
    try:
        if backend not in BACKENDS:
            raise InvalidArgumentError(f"--backend takes local or ray, got {backend!r}")
        for path, option in ((json_out, "--json"), (plot, "--plot")):
            if path is not None:
                check_writable(path, option)
        if plot is not None:
            from evclock.tools._plot import figure_class

            figure_class()
        specs = plan(scenario, parse_seeds(seeds), parse_params(scenario, param or []), until)
        display = SweepProgress(console, len(specs), quiet)
        with display.progress:
            result = sweep(
                specs,
                backend=backend,
                workers=workers,
                address=address,
                run_timeout=run_timeout,
                on_row=display.row_done,
                on_idle=display.idle,
            )
    except EvClockError as exc:
        print_error(exc)
        raise typer.Exit(EXIT_USAGE) from None
    render_sweep(result, console)
    if json_out is not None:
        json_out.write_text(json.dumps(result.to_json(), indent=2))
    if plot is not None:
        from evclock.tools._plot import plot_sweep

        plot_sweep(result, plot)
    if result.interrupted:
        raise typer.Exit(EXIT_INTERRUPTED)
    raise typer.Exit(EXIT_SUCCESS if not result.failed else EXIT_FAILED)
