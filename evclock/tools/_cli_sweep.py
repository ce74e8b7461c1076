"""``evclock sweep``: a scenario over seeds and parameter values, with a live progress bar
(done / failed / ETA / aggregate real-time factor) and a summary (success rate, quantiles of
every numeric report field, per configuration the count, success rate, mean, standard
deviation and 95 % interval of each metric, the best configuration by a named metric, the
failing runs with the command reproducing each), exports (JSON, CSV, JSON lines) and resume
(``--out DIR``).

Exit codes: 0 every run succeeded, 1 some failed or were cut short, 2 bad input, 4 some run
raised, 130 interrupted (Ctrl-C; the rows that finished are still printed and written).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from evclock._errors import InvalidArgumentError
from evclock.tools._cli_app import (
    EXIT_ERROR,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_SUCCESS,
    app,
    check_until,
    check_writable,
    parse_params,
    progress_console,
    usage_errors,
    with_exit_statuses,
)
from evclock.tools._scenarios import ParamValue, check_engine, load_scenario, require_engine
from evclock.tools._sweep import (
    BACKENDS,
    SweepDirectory,
    SweepResult,
    SweepRow,
    parse_seeds,
    plan,
    sweep,
)

_SHOWN_FAILURES = 20
_WALL_FIELDS = ("wall_time_s", "achieved_rtf")


class SweepProgress:
    """The sweep's progress bar: runs done, failed, ETA, achieved aggregate rtf (on
    ``console``, by default stderr and only on a terminal: see ``progress_console``)."""

    def __init__(self, console: Console | None, total: int, quiet: bool, done: int = 0) -> None:
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
        # By default on stderr, and only on a terminal.
        console, off = progress_console(console, quiet)
        self.progress = Progress(*columns, console=console, disable=off, auto_refresh=False)
        self.task = self.progress.add_task("sweep", total=total, completed=done, failed=0, rtf="-")
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


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.3g}"


def parse_best(text: str) -> tuple[str, bool]:
    """``"METRIC"`` or ``"min:METRIC"`` -> (METRIC, False); ``"max:METRIC"`` -> (METRIC, True)."""
    mode, sep, metric = text.partition(":")
    if not sep:
        mode, metric = "min", text
    if mode not in ("min", "max") or not metric.strip():
        raise InvalidArgumentError(
            f"--best takes METRIC, min:METRIC or max:METRIC (a numeric report field), got {text!r}"
        )
    return metric.strip(), mode == "max"


def _params_text(params: dict[str, object], names: tuple[str, ...]) -> list[str]:
    return [str(params.get(name, "")) for name in names]


def render_groups(
    result: SweepResult,
    console: Console,
    metrics: list[str] | None,
    by: tuple[str, ...] | None = None,
) -> None:
    """The per-configuration table (``by``: per value of these parameters only): runs,
    success rate, then per metric its mean with the half-width of the 95 % interval of the
    mean (Student t; the bounds are in the JSON summary) and its standard deviation."""
    if metrics is None:  # the wall-clock figures vary from run to run: named ones only
        metrics = [m for m in result.metric_names() if m not in _WALL_FIELDS]
    names = result.swept if by is None else by
    groups = result.groups(metrics, by=names)
    if not groups:
        return
    title = "by " + ", ".join(names) if names else "over the runs"
    table = Table(title=escape(f"{result.name}: metrics {title}"))
    for name in names:
        table.add_column(escape(name), no_wrap=True)
    table.add_column("runs ok", justify="right", no_wrap=True)
    table.add_column("metric", no_wrap=True)
    table.add_column("mean ± 95% interval", justify="right", no_wrap=True)
    table.add_column("std", justify="right", no_wrap=True)
    for group in groups:
        ok = group["statuses"].get("success", 0)
        head = [*map(escape, _params_text(group["params"], names)), f"{ok}/{group['runs']}"]
        blank = [""] * len(head)
        shown = {m: group["metrics"][m] for m in metrics if m in group["metrics"]}
        if not shown:
            table.add_row(*head, "-", "-", "-")
        for i, (metric, d) in enumerate(shown.items()):
            mean = f"{d['mean']:.3g}"
            if d["ci95"] is not None:
                mean += f" ± {(d['ci95'][1] - d['ci95'][0]) / 2:.2g}"
            label = metric if d["n"] == group["runs"] else f"{metric} (of {d['n']})"
            table.add_row(*(head if i == 0 else blank), escape(label), mean, _number(d["std"]))
        table.add_section()
    console.print(table)


def render_best(result: SweepResult, console: Console, metric: str, maximize: bool) -> None:
    """The configuration with the lowest (highest) mean of ``metric``, and its command."""
    best = result.best(metric, maximize=maximize)
    way = "highest" if maximize else "lowest"
    if best is None:
        console.print(f"best: no run reported {metric!r}", markup=False)
        return
    d = best["metrics"][metric]
    config = ", ".join(f"{k}={v}" for k, v in best["params"].items()) or "the defaults"
    interval = (
        "" if d["ci95"] is None else f", 95% interval {d['ci95'][0]:.4g} .. {d['ci95'][1]:.4g}"
    )
    console.print(
        f"best by {way} mean {metric}: {config} (mean {d['mean']:.4g}{interval}, "
        f"{d['n']} runs, success {best['success_rate']:.0%})",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )


def render_sweep(
    result: SweepResult,
    console: Console,
    metrics: list[str] | None = None,
    best: tuple[str, bool] | None = None,
) -> None:
    """Print the success rate, the quantile table, the per-configuration table, the best
    configuration (``best``: metric and whether to maximize) and the failing runs."""
    summary = result.summary()
    rate = summary["success_rate"]
    counts = ", ".join(f"{n} {status}" for status, n in summary["status_counts"].items())
    engine = "" if result.engine == "pybullet" else f" on {result.engine}"
    head = escape(f"{result.name}{engine}: {summary['done']}/{summary['planned']} runs ({counts})")
    if result.resumed:
        head += f", {result.resumed} from the earlier sweep in --out"
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
        table.add_row(escape(field), *(f"{v:.4g}" for v in values.values()))
    console.print(table)
    render_groups(result, console, metrics)
    if len(result.swept) > 1:  # then each parameter on its own, over the others' values
        for name in result.swept:
            render_groups(result, console, metrics, by=(name,))
    if best is not None:
        render_best(result, console, *best)
    failed = result.failed
    for row in failed[:_SHOWN_FAILURES]:
        reason = row.error or row.status
        console.print(
            f"[red]{row.status}[/red] seed {row.spec.seed}: {escape(reason)}", soft_wrap=True
        )
        console.print(
            f"  reproduce: {row.spec.command()}", soft_wrap=True, highlight=False, markup=False
        )
    if len(failed) > _SHOWN_FAILURES:
        console.print(f"... and {len(failed) - _SHOWN_FAILURES} more (see --json)")


METRIC_COLOR = "#d62728"
"""The colour of the means and their 95 % intervals in :func:`plot_metric_by_parameter`."""
RUN_COLOR = "#1f77b4"
"""The colour of the single runs in :func:`plot_metric_by_parameter`."""


def plot_metric_by_parameter(result: SweepResult, metric: str, output: Path) -> None:
    """One panel per swept parameter: ``metric`` of every run (dots) and, per value, its
    mean with the 95 % interval of the mean (bars), as a PNG. Without a swept parameter,
    one panel over the seeds.

    :param result: what :func:`sweep` returned.
    :param metric: a numeric report field (``mission_time_s``...).
    :param output: the PNG file to write.
    :raises InvalidArgumentError: no run reported ``metric`` (the message lists those reported).
    :raises MissingExtraError: matplotlib is missing (``pip install 'evclock[plot]'``).
    """
    from evclock.tools._plot import figure_class
    from evclock.tools._sweep import describe, numeric_fields

    points = [
        (row, numeric_fields(row.report)[metric])
        for row in result.rows
        if metric in numeric_fields(row.report)
    ]
    if not points:
        known = ", ".join(result.metric_names()) or "none"
        raise InvalidArgumentError(
            f"--plot-metric {metric!r}: no run reported it; the numeric fields: {known}"
        )
    axes_of = list(result.swept) or ["seed"]
    figure = figure_class()(figsize=(5 * len(axes_of), 4), dpi=100)
    axes = figure.subplots(1, len(axes_of), squeeze=False)[0]
    for ax, name in zip(axes, axes_of, strict=True):

        def value_of(row: SweepRow, name: str = name) -> ParamValue:
            return row.spec.seed if name == "seed" else row.spec.params[name]

        values = list(dict.fromkeys(value_of(row) for row, _ in points))
        numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        position = {v: (float(v) if numeric else float(i)) for i, v in enumerate(values)}
        ax.plot(
            [position[value_of(row)] for row, _ in points],
            [y for _, y in points],
            linestyle="none",
            marker="o",
            markersize=4,
            alpha=0.5,
            color=RUN_COLOR,
            label="runs",
        )
        if name != "seed":
            means, lows, highs = [], [], []
            for v in values:
                d = describe([y for row, y in points if value_of(row) == v])
                means.append(d["mean"])
                low, high = d["ci95"] or (d["mean"], d["mean"])
                lows.append(d["mean"] - low)
                highs.append(high - d["mean"])
            ax.errorbar(
                [position[v] for v in values],
                means,
                yerr=[lows, highs],
                color=METRIC_COLOR,
                marker="s",
                capsize=5,
                linewidth=2,
                label="mean, 95% interval",
            )
            ax.legend(fontsize=8)
        if not numeric:
            ax.set_xticks([position[v] for v in values], [str(v) for v in values])
        ax.set_xlabel(name)
        ax.set_ylabel(metric)
        ax.set_title(f"{metric} by {name}", fontsize=9)
    figure.suptitle(f"{result.name}: {len(points)} runs")
    figure.tight_layout()
    figure.savefig(output, format="png")


@app.command("sweep")
@with_exit_statuses
def sweep_command(
    scenario: Annotated[
        str, typer.Argument(help="A registered name, a file path.py[:Class] or module:Class.")
    ],
    seeds: Annotated[
        str | None,
        typer.Option(
            help="How many seeds: N runs seeds 0 to N-1 (default 10); also START:STOP "
            "(STOP excluded) or S1,S2,..."
        ),
    ] = None,
    seed: Annotated[
        str | None,
        typer.Option(
            help="Which seeds: S (that one seed), START:STOP (STOP excluded) or S1,S2,... "
            "(instead of --seeds)."
        ),
    ] = None,
    param: Annotated[
        list[str] | None,
        typer.Option("--param", help="name=v1,v2,...: values to sweep (repeatable)."),
    ] = None,
    until: Annotated[
        float | None, typer.Option(help="Sim seconds per run (default: the scenario's).")
    ] = None,
    engine: Annotated[
        Literal["pybullet", "mujoco"],
        typer.Option(help="Physics engine of every run: PyBullet, or MuJoCo (kuka, cartpole)."),
    ] = "pybullet",
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
    metric: Annotated[
        list[str] | None,
        typer.Option(
            "--metric",
            help="A numeric report field to summarise per configuration (repeatable; "
            "default: every one).",
        ),
    ] = None,
    best: Annotated[
        str | None,
        typer.Option(
            help="Name the configuration with the lowest mean of METRIC (max:METRIC: the highest)."
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Directory: runs.jsonl gets each run as it finishes, and the summary, "
            "CSV and JSON lines at the end; run again with it to resume (finished runs "
            "are skipped)."
        ),
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the summary and every row as JSON.")
    ] = None,
    csv_out: Annotated[
        Path | None,
        typer.Option("--csv", help="Write a line per run (seed, parameters, status, metrics)."),
    ] = None,
    jsonl_out: Annotated[
        Path | None, typer.Option("--jsonl", help="Write a JSON object per run, one a line.")
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(
            help="Draw to this PNG a histogram of every numeric report field, or with "
            "--plot-metric that metric per parameter value."
        ),
    ] = None,
    plot_metric: Annotated[
        str | None,
        typer.Option(
            help="With --plot: draw METRIC against each swept parameter (every run, the "
            "mean and its 95% interval)."
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
) -> None:
    """Run a scenario over many seeds and parameter values, each run in its own process.

    --seeds N runs N seeds (0 to N-1); --seed S runs seed S only. Ctrl-C stops
    the sweep: the finished rows are printed and written, marked interrupted;
    with --out DIR the same command resumes it.
    """
    console = Console()
    with usage_errors():
        if seeds is not None and seed is not None:
            raise InvalidArgumentError(
                "give --seeds N (how many seeds) or --seed S (which seeds), not both"
            )
        if backend not in BACKENDS:
            raise InvalidArgumentError(f"--backend takes local or ray, got {backend!r}")
        if workers < 1:
            raise InvalidArgumentError(f"--workers must be at least 1, got {workers}")
        if address is not None and backend != "ray":
            raise InvalidArgumentError("--address is the Ray cluster's: use it with --backend ray")
        check_until(until)
        if run_timeout is not None and not (math.isfinite(run_timeout) and run_timeout > 0):
            raise InvalidArgumentError(
                f"--run-timeout must be a positive number of wall seconds, got {run_timeout!r}"
            )
        wanted = parse_best(best) if best is not None else None
        if plot_metric is not None and plot is None:
            raise InvalidArgumentError("--plot-metric names what --plot draws: add --plot FILE.png")
        outputs = (
            (json_out, "--json"),
            (plot, "--plot"),
            (csv_out, "--csv"),
            (jsonl_out, "--jsonl"),
        )
        for path, option in outputs:
            if path is not None:
                check_writable(path, option)
        directory = None if out is None else SweepDirectory(out)
        if directory is not None:
            directory.check()
        if plot is not None:
            from evclock.tools._plot import figure_class

            figure_class()
        chosen = (
            parse_seeds(seed, option="--seed")
            if seed is not None
            else parse_seeds(seeds or "10", count=True)
        )
        specs = plan(scenario, chosen, parse_params(scenario, param or []), until, engine)
        if backend == "ray":  # the backend's extra, as every other extra, before the engine
            from evclock.tools._sweep import _ray

            _ray()
        # Before anything runs: the engine, installed here unless a Ray cluster runs the runs.
        (require_engine if address is None else check_engine)(load_scenario(scenario), engine)
        done = 0 if directory is None else len(directory.finished(specs))
        display = SweepProgress(None, len(specs), quiet, done=done)
        with display.progress:
            result = sweep(
                specs,
                backend=backend,
                workers=workers,
                address=address,
                run_timeout=run_timeout,
                on_row=display.row_done,
                on_idle=display.idle,
                out_dir=out,
            )
    render_sweep(result, console, metric, wanted)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text(json.dumps(result.to_json(), indent=2))
        (out / "runs.csv").write_text(result.to_csv())
    if json_out is not None:
        json_out.write_text(json.dumps(result.to_json(), indent=2))
    if csv_out is not None:
        csv_out.write_text(result.to_csv())
    if jsonl_out is not None:
        jsonl_out.write_text(result.to_jsonl())
    if plot is not None:
        with usage_errors():
            if plot_metric is not None:
                plot_metric_by_parameter(result, plot_metric, plot)
            else:
                from evclock.tools._plot import plot_sweep

                plot_sweep(result, plot)
    raise typer.Exit(sweep_exit_code(result))


def sweep_exit_code(result: SweepResult) -> int:
    """130 interrupted, 4 a run raised, 1 a run failed or was cut short, else 0."""
    if result.interrupted:
        return EXIT_INTERRUPTED
    if any(row.status == "error" for row in result.rows):
        return EXIT_ERROR
    return EXIT_SUCCESS if not result.failed else EXIT_FAILED
