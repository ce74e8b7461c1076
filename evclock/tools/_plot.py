"""Plots (matplotlib, drawn off-screen with Agg): a recorded run and a sweep's histograms.

- :func:`plot_run`: each rate loop's tick lateness over sim time, and the achieved real-time
  factor over sim time (``evclock plot run.mcap -o run.png``);
- :func:`plot_fields`: any numeric fields of a recording over time, one panel each (a
  recording has no units: no two fields share an axis), in one figure
  (``evclock plot run.mcap /evclock/joints.joints[elbow].position -o f.png``);
- :func:`plot_sweep`: the histogram of every numeric report field over a sweep's runs
  (``evclock sweep ... --plot sweep.png``).

Colours come from a fixed palette, in order of first appearance, so a plot of the same data
always looks the same.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from evclock._errors import MissingExtraError, TraceError

if TYPE_CHECKING:
    from evclock.tools._sweep import SweepResult
    from evclock.tools._trace import Trace

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2")
"""Line colours: loop i is drawn in ``PALETTE[i % len(PALETTE)]``."""
RTF_COLOR = "#111111"
HISTOGRAM_COLOR = "#1f77b4"


def figure_class() -> Any:
    """``matplotlib.figure.Figure``, or a clear error naming the extra to install."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingExtraError("plots need matplotlib: pip install 'evclock[plot]'") from None
    return Figure


def plot_run(trace: Trace, output: Path) -> None:
    """One panel per rate loop (tick lateness over sim time), then the achieved rtf, as a
    PNG; all panels share the sim-time axis.

    :param trace: a recording read with :func:`read_trace`.
    :param output: the PNG file to write.
    :raises TraceError: the recording has no rate loop to plot.
    :raises MissingExtraError: matplotlib is missing (``pip install 'evclock[plot]'``).
    """
    loops = [t for t in trace.topics if t.startswith("/evclock/loop/")]
    if not loops:
        raise TraceError(f"{str(trace.path)!r} records no rate loop: nothing to plot")
    figure = figure_class()(figsize=(10, 2.2 * (len(loops) + 1)), dpi=100)
    axes = figure.subplots(len(loops) + 1, 1, sharex=True, squeeze=False)[:, 0]
    for i, (ax, topic) in enumerate(zip(axes, loops, strict=False)):
        messages = trace.topic(topic)
        ax.plot(
            [m.time_ns / 1e9 for m in messages],
            [m.data["lateness_s"] * 1e3 for m in messages],
            color=PALETTE[i % len(PALETTE)],
            linewidth=1.5,
            marker=".",
        )
        ax.set_ylabel("late (ms)")
        ax.set_title(f"{topic.removeprefix('/evclock/loop/')}: lateness of each tick", fontsize=9)
    rtf_axes = axes[-1]
    samples = [m for m in trace.topic("/evclock/clock") if m.data.get("achieved_rtf") is not None]
    rtf_axes.plot(
        [m.time_ns / 1e9 for m in samples],
        [m.data["achieved_rtf"] for m in samples],
        color=RTF_COLOR,
        linewidth=1.5,
    )
    rtf_axes.set_title("achieved real-time factor (per 0.05 s of sim time)", fontsize=9)
    rtf_axes.set_ylabel("rtf")
    rtf_axes.set_xlabel("sim time (s)")
    figure.tight_layout()
    figure.savefig(output, format="png")


def plot_fields(trace: Trace, series: list[str], output: Path) -> None:
    """Each ``TOPIC.field`` of ``series`` over time, in one figure as a PNG: one panel per
    field (palette order), all sharing the time axis. A recording does not carry its fields'
    units, so no two fields share a y-axis: a joint angle near 0.6 rad stays readable beside
    an rtf of 60. The x-axis is the recording's timeline (sim seconds, or wall seconds for a
    ``--wall`` run).

    :param trace: a recording read with :func:`read_trace`.
    :param series: the fields, as ``TOPIC.field.path`` (see :func:`evclock.tools._trace.
        series_values`).
    :param output: the PNG file to write.
    :raises TraceError: a series names no recorded topic or field, or a non-numeric field.
    :raises MissingExtraError: matplotlib is missing (``pip install 'evclock[plot]'``).
    """
    from evclock.tools._trace import series_values

    data = [(name, *series_values(trace, name)) for name in series]
    figure = figure_class()(figsize=(10, 1.0 + 2.2 * len(data)), dpi=100)
    axes = figure.subplots(len(data), 1, sharex=True, squeeze=False)[:, 0]
    for i, (ax, (name, times, values)) in enumerate(zip(axes, data, strict=True)):
        ax.plot(times, values, color=PALETTE[i % len(PALETTE)], linewidth=1.5)
        ax.set_title(name, fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel(f"{trace.timeline} time (s)")
    scenario = trace.metadata.get("evclock.run", {}).get("scenario")
    figure.suptitle(trace.path.name if scenario is None else f"{scenario}: {trace.path.name}")
    figure.tight_layout()
    figure.savefig(output, format="png")


def plot_sweep(result: SweepResult, output: Path) -> None:
    """One histogram per numeric report field over the sweep's runs, as a PNG.

    :param result: what :func:`sweep` returned.
    :param output: the PNG file to write.
    :raises TraceError: no run of the sweep reported a number.
    :raises MissingExtraError: matplotlib is missing (``pip install 'evclock[plot]'``).
    """
    from evclock.tools._sweep import numeric_fields

    fields: dict[str, list[float]] = {}
    for row in result.rows:
        for key, value in numeric_fields(row.report).items():
            fields.setdefault(key, []).append(value)
    if not fields:
        raise TraceError("no run of the sweep reported a number: nothing to plot")
    columns = min(3, len(fields))
    rows = math.ceil(len(fields) / columns)
    figure = figure_class()(figsize=(4 * columns, 3 * rows), dpi=100)
    axes = figure.subplots(rows, columns, squeeze=False)
    for ax, (key, values) in zip(axes.flat, fields.items(), strict=False):
        ax.hist(values, bins=min(30, max(5, len(values) // 3)), color=HISTOGRAM_COLOR)
        ax.set_title(key, fontsize=9)
        ax.set_ylabel("runs")
    for ax in list(axes.flat)[len(fields) :]:
        ax.set_visible(False)
    figure.suptitle(f"{result.name}: {len(result.rows)} runs")
    figure.tight_layout()
    figure.savefig(output, format="png")
