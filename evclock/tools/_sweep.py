"""Sweeps: one scenario over many seeds and parameter values, each run in its own process.

:func:`plan` lists the runs (every parameter combination x every seed, in a fixed order);
:func:`sweep` executes them on a backend and returns a :class:`SweepResult` whose rows keep
that order whatever order the runs finish in:

- ``local``: a fresh process per run (forked from a ``forkserver`` that has imported the
  physics engine once), at most ``workers`` at a time;
- ``ray``: one Ray task per run, on a worker process that exits after it (``max_calls=1``),
  on the cluster at ``address`` or on a local Ray started for the sweep and stopped after it.

Every run is :func:`evclock.tools._runs.run_scenario` with its own physics client (or MuJoCo
world: the specs' ``engine``), so the row of seed ``k`` equals ``evclock run SCENARIO --seed k
[--engine E]`` bit for bit. A scenario exception or a
crashed worker is a failed row with the error (the root exception, not the ``ExceptionGroup``
of the scenario's task group); Ctrl-C (``KeyboardInterrupt``) stops the running workers and
returns the rows that finished, marked ``interrupted``.

With an output directory (``out_dir``), each finished row is appended to its ``runs.jsonl``
as it finishes; a sweep started again on the same directory reuses the rows of the runs it
plans that are there, and runs only the others (resume after Ctrl-C or a crash).

:meth:`SweepResult.groups` summarises the runs per parameter configuration (count, success
rate, mean, standard deviation and 95 % interval of the mean of every numeric field) and
:meth:`SweepResult.best` picks the configuration with the lowest (or highest) mean of a metric.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import io
import itertools
import json
import math
import multiprocessing
import multiprocessing.connection
import os
import shlex
import signal
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from evclock._errors import InvalidArgumentError, InvalidTypeError, MissingExtraError
from evclock.tools._scenarios import (
    ParamValue,
    check_engine,
    is_file_reference,
    load_scenario,
    require_engine,
    split_file_reference,
)

Backend = Literal["local", "ray"]
BACKENDS: tuple[Backend, ...] = ("local", "ray")
QUANTILES = (0, 5, 50, 95, 100)
"""Percentiles the summary gives for every numeric report field."""
_POLL_S = 0.2  # wall seconds between progress refreshes while runs are in flight
_STOP_GRACE_S = 5.0  # wall seconds a stopped worker gets to exit before it is killed


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One run of a sweep: what ``evclock run`` would be given.

    :ivar scenario: the scenario (a name, a file, or ``module:Class``).
    :ivar seed: the seed of the run.
    :ivar params: the scenario parameters set for the run.
    :ivar until: sim seconds to run at most (None: the scenario's default).
    :ivar engine: the physics engine, ``"pybullet"`` (default) or ``"mujoco"``.
    """

    scenario: str
    seed: int
    params: dict[str, ParamValue]
    until: float | None = None
    engine: str = "pybullet"

    def command(self) -> str:
        """The ``evclock run`` command line that reproduces this run."""
        words = ["evclock", "run", self.scenario, "--seed", str(self.seed)]
        for name, value in self.params.items():
            words += ["--param", f"{name}={_format_param(value)}"]
        if self.until is not None:
            words += ["--until", f"{self.until!r}"]
        if self.engine != "pybullet":
            words += ["--engine", self.engine]
        return shlex.join(words)


def _format_param(value: ParamValue) -> str:
    """How ``--param`` spells ``value``: floats exactly (``repr``), bools as true/false."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


@dataclasses.dataclass
class SweepRow:
    """The outcome of one run: ``status`` is ``success``, ``failed``, ``cut short`` (the
    scenario's verdict) or ``error`` (an exception or a crashed worker, in ``error``).

    :ivar spec: the run.
    :ivar status: ``success``, ``failed``, ``cut short`` or ``error``.
    :ivar report: the run's :meth:`RunReport.to_json`, or None after an error.
    :ivar error: what went wrong, for an ``error`` row, else None.
    """

    spec: RunSpec
    status: str
    report: dict[str, Any] | None = None
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        """Plain JSON data."""
        return {
            "seed": self.spec.seed,
            "params": self.spec.params,
            "status": self.status,
            "command": self.spec.command(),
            "report": self.report,
            "error": self.error,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SweepRow:
        """The row :meth:`to_json` (with ``scenario``, ``until`` and ``engine`` added)
        describes (a row without ``engine``, written before sweeps ran on MuJoCo: PyBullet).

        :param data: a line of a sweep's ``runs.jsonl``.
        :returns: the row.
        :raises KeyError: a field is missing.
        """
        spec = RunSpec(
            str(data["scenario"]),
            int(data["seed"]),
            dict(data["params"]),
            data["until"],
            str(data.get("engine", "pybullet")),
        )
        return cls(spec, str(data["status"]), data["report"], data["error"])


@dataclasses.dataclass
class SweepResult:
    """Every finished row, in plan order, and whether the sweep was interrupted.

    :ivar scenario: the scenario as given (a name, a file, ``module:Class``).
    :ivar name: the scenario class's ``name``.
    :ivar planned: how many runs were planned.
    :ivar rows: a :class:`SweepRow` per finished run, in plan order.
    :ivar interrupted: whether the sweep was stopped (Ctrl-C) before every run finished.
    :ivar wall_time_s: wall seconds the sweep took.
    :ivar resumed: how many rows came from an earlier sweep in the same output directory.
    :ivar swept: the parameters given several values.
    :ivar engine: the physics engine every run ran on.
    """

    scenario: str
    """The scenario as given (a name, a file, module:Class)."""
    name: str
    """The scenario class's ``name``."""
    planned: int
    rows: list[SweepRow]
    interrupted: bool
    wall_time_s: float
    resumed: int = 0
    """How many rows came from an earlier, interrupted sweep in the same directory."""
    swept: tuple[str, ...] = ()
    """The parameters given several values (the configurations differ in them)."""
    engine: str = "pybullet"
    """The physics engine every run ran on: ``pybullet`` or ``mujoco``."""

    @property
    def failed(self) -> list[SweepRow]:
        """Rows that did not succeed."""
        return [row for row in self.rows if row.status != "success"]

    def summary(self) -> dict[str, Any]:
        """Success rate, counts by status, and quantiles of every numeric report field."""
        counts = collections.Counter(row.status for row in self.rows)
        done = len(self.rows)
        fields: dict[str, list[float]] = {}
        for row in self.rows:
            for key, value in numeric_fields(row.report).items():
                fields.setdefault(key, []).append(value)
        return {
            "engine": self.engine,
            "planned": self.planned,
            "done": done,
            "success_rate": counts["success"] / done if done else None,
            "status_counts": {status: counts[status] for status in sorted(counts)},
            "quantiles": {key: quantiles(values) for key, values in fields.items()},
            "interrupted": self.interrupted,
            "wall_time_s": self.wall_time_s,
            "resumed": self.resumed,
            "groups": self.groups(),
            "by_parameter": {name: self.groups(by=[name]) for name in self.swept},
        }

    def groups(
        self, metrics: Sequence[str] | None = None, by: Sequence[str] | None = None
    ) -> list[dict[str, Any]]:
        """The runs grouped by parameter configuration, in plan order.

        :param metrics: the numeric fields to summarise (None: every one a run reported).
        :param by: the parameters that make a group (None: all of them, a group per
            configuration; ``["gain"]``: a group per value of ``gain``, over the others).
        :returns: per group: ``params`` (the values of ``by``), ``runs``, ``success_rate``,
            ``statuses`` and ``metrics`` (per field: ``n``, ``mean``, ``std``, ``ci95`` - the
            95 % interval of the mean, Student t - ``min``, ``max``; None where undefined).
        """
        grouped: dict[str, tuple[dict[str, ParamValue], list[SweepRow]]] = {}
        for row in self.rows:
            params = row.spec.params
            if by is not None:
                params = {name: params[name] for name in by if name in params}
            grouped.setdefault(_params_key(params), (params, []))[1].append(row)
        out = []
        for params, rows in grouped.values():
            values: dict[str, list[float]] = {}
            for row in rows:
                for key, value in numeric_fields(row.report).items():
                    if metrics is None or key in metrics:
                        values.setdefault(key, []).append(value)
            statuses = collections.Counter(row.status for row in rows)
            out.append(
                {
                    "params": params,
                    "runs": len(rows),
                    "success_rate": statuses["success"] / len(rows),
                    "statuses": {status: statuses[status] for status in sorted(statuses)},
                    "metrics": {key: describe(v) for key, v in values.items()},
                }
            )
        return out

    def best(self, metric: str, *, maximize: bool = False) -> dict[str, Any] | None:
        """The configuration (see :meth:`groups`) with the lowest mean of ``metric`` (the
        highest with ``maximize``); ties go to the earlier one in plan order.

        :param metric: a numeric field of the runs' reports (``mission_time_s``...).
        :param maximize: pick the highest mean instead of the lowest.
        :returns: that configuration's group, or None when no run reported ``metric``.
        """
        candidates = [g for g in self.groups([metric]) if metric in g["metrics"]]
        if not candidates:
            return None
        sign = -1.0 if maximize else 1.0
        return min(candidates, key=lambda g: sign * g["metrics"][metric]["mean"])

    def metric_names(self) -> list[str]:
        """Every numeric field a run reported, in order of first appearance."""
        names: dict[str, None] = {}
        for row in self.rows:
            names.update(dict.fromkeys(numeric_fields(row.report)))
        return list(names)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON data: the summary and every row."""
        return {
            "scenario": self.scenario,
            "name": self.name,
            "engine": self.engine,
            "summary": self.summary(),
            "rows": [row.to_json() for row in self.rows],
        }

    def to_csv(self) -> str:
        """One line per run: seed, each parameter, status, error, then every numeric field
        (empty where a run did not report it)."""
        names = sorted({name for row in self.rows for name in row.spec.params})
        metrics = self.metric_names()
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(["seed", *names, "status", "error", *metrics])
        for row in self.rows:
            fields = numeric_fields(row.report)
            writer.writerow(
                [
                    row.spec.seed,
                    *(
                        _format_param(row.spec.params[n]) if n in row.spec.params else ""
                        for n in names
                    ),
                    row.status,
                    row.error or "",
                    *(repr(fields[m]) if m in fields else "" for m in metrics),
                ]
            )
        return buffer.getvalue()

    def to_jsonl(self) -> str:
        """One JSON object per run (:meth:`SweepRow.to_json`), one per line."""
        return "".join(json.dumps(_row_record(row)) + "\n" for row in self.rows)


#: Two-sided 97.5 % quantiles of Student's t distribution, by degrees of freedom.
_T975 = {
    1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
    9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131, 16: 2.120,
    17: 2.110, 18: 2.101, 19: 2.093, 20: 2.086, 21: 2.080, 22: 2.074, 23: 2.069, 24: 2.064,
    25: 2.060, 26: 2.056, 27: 2.052, 28: 2.048, 29: 2.045, 30: 2.042, 40: 2.021, 60: 2.000,
    120: 1.980,
}  # fmt: skip
_Z975 = 1.959964


def t975(dof: int) -> float:
    """The 97.5 % quantile of Student's t with ``dof`` degrees of freedom (tabulated to 3
    decimals; linear in 1/dof between the tabulated ones, the normal's beyond 120)."""
    if dof in _T975:
        return _T975[dof]
    if dof > 120:
        return _Z975
    low = max(d for d in _T975 if d < dof)
    high = min(d for d in _T975 if d > dof)
    fraction = (1 / dof - 1 / low) / (1 / high - 1 / low)
    return _T975[low] + (_T975[high] - _T975[low]) * fraction


def describe(values: Sequence[float]) -> dict[str, Any]:
    """``n``, ``mean``, ``std`` (sample, n - 1), ``ci95`` (the 95 % interval of the mean,
    Student t: ``[low, high]``), ``min`` and ``max`` of ``values``; ``std`` and ``ci95`` are
    None for a single value."""
    n = len(values)
    mean = math.fsum(values) / n
    std = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else None
    ci95 = None
    if std is not None:
        half = t975(n - 1) * std / math.sqrt(n)
        ci95 = [mean - half, mean + half]
    return {"n": n, "mean": mean, "std": std, "ci95": ci95, "min": min(values), "max": max(values)}


def _params_key(params: dict[str, ParamValue]) -> str:
    return json.dumps(params, sort_keys=True)


def _spec_key(spec: RunSpec) -> str:
    data = {"scenario": spec.scenario, "seed": spec.seed, "params": spec.params}
    return json.dumps({**data, "until": spec.until, "engine": spec.engine}, sort_keys=True)


def _row_record(row: SweepRow) -> dict[str, Any]:
    spec = row.spec
    return {"scenario": spec.scenario, "until": spec.until, "engine": spec.engine, **row.to_json()}


RUNS_FILE = "runs.jsonl"
"""The file of a sweep's output directory that holds a line per finished run."""


class SweepDirectory:
    """A sweep's output directory: ``runs.jsonl`` gets a line per finished run, as it
    finishes; the rows found there when the sweep starts are not run again.

    :param path: the directory (created if missing).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.runs = self.path / RUNS_FILE

    def check(self) -> None:
        """Refuse a path that is a file or cannot be written, before anything runs.

        :raises InvalidArgumentError: the path cannot hold the sweep's files.
        """
        if self.path.exists() and not self.path.is_dir():
            raise InvalidArgumentError(f"--out {str(self.path)!r} is a file; give a directory")
        parent = self.path if self.path.exists() else self.path.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise InvalidArgumentError(
                f"--out {str(self.path)!r}: the directory {str(parent)!r} does not exist or "
                "is not writable"
            )

    def finished(self, specs: Sequence[RunSpec]) -> dict[int, SweepRow]:
        """The rows already in the directory for ``specs``, by index in ``specs``.

        :param specs: the planned runs.
        :returns: the finished ones' rows (a run listed twice: its last line).
        :raises InvalidArgumentError: ``runs.jsonl`` holds a run of another scenario or on
            another engine, or a line that is not a run (the directory is not this sweep's).
        """
        if not self.runs.exists():
            return {}
        specs = [_absolute(spec) for spec in specs]  # as sweep() runs them
        index = {_spec_key(spec): i for i, spec in enumerate(specs)}
        found: dict[int, SweepRow] = {}
        text = self.runs.read_text()
        lines = text.splitlines()
        if lines and not text.endswith("\n"):
            lines.pop()  # a line cut short by a crash while it was written: run it again
        for number, line in enumerate(lines, 1):
            try:
                row = SweepRow.from_json(json.loads(line))
            except (ValueError, KeyError, TypeError):
                raise InvalidArgumentError(
                    f"--out {str(self.path)!r}: line {number} of {RUNS_FILE} is not a sweep run; "
                    "give another directory, or delete that file to start over"
                ) from None
            if specs and row.spec.scenario != specs[0].scenario:
                raise InvalidArgumentError(
                    f"--out {str(self.path)!r} holds a sweep of {row.spec.scenario!r}, not "
                    f"{specs[0].scenario!r}; give another directory"
                )
            if specs and row.spec.engine != specs[0].engine:
                raise InvalidArgumentError(
                    f"--out {str(self.path)!r} holds a sweep on {row.spec.engine}, not on "
                    f"{specs[0].engine}; give another directory"
                )
            where = index.get(_spec_key(row.spec))
            if where is not None:
                found[where] = row
        return found

    def append(self, row: SweepRow) -> None:
        """Add ``row`` to ``runs.jsonl`` (one whole line, flushed to the disk)."""
        self.path.mkdir(parents=True, exist_ok=True)
        with self.runs.open("a") as file:
            file.write(json.dumps(_row_record(row)) + "\n")
            file.flush()
            os.fsync(file.fileno())


def numeric_fields(report: dict[str, Any] | None) -> dict[str, float]:
    """A report's numeric figures: its summary's numbers (not bools, not the seed) and its
    sim time, wall time and achieved rtf; non-finite values are left out."""
    if report is None:
        return {}
    found: dict[str, float] = {}
    candidates = {**report.get("summary", {})}
    for key in ("sim_time_s", "wall_time_s", "achieved_rtf"):
        candidates[key] = report.get(key)
    for key, value in candidates.items():
        if key == "seed" or isinstance(value, bool) or not isinstance(value, int | float):
            continue
        if math.isfinite(value):
            found[key] = float(value)
    return found


def quantiles(values: Sequence[float]) -> dict[str, float]:
    """``{"p0": min, "p5": ..., "p100": max}`` (linear interpolation between ranks)."""
    ordered = sorted(values)
    out: dict[str, float] = {}
    for q in QUANTILES:
        position = q / 100 * (len(ordered) - 1)
        low = math.floor(position)
        high = min(low + 1, len(ordered) - 1)
        fraction = position - low
        out[f"p{q}"] = ordered[low] + (ordered[high] - ordered[low]) * fraction
    return out


_MAX_SEED = 2**32 - 1


def parse_seeds(text: str, *, count: bool = False, option: str = "--seeds") -> list[int]:
    """The seeds ``text`` lists: ``"START:STOP"`` (STOP excluded), ``"A,B,C"``, or one
    number ``"N"``: the N seeds 0 to N-1 with ``count``, else the seed N itself.

    :param text: the option's value.
    :param count: read a single number as a count of seeds (``--seeds N``), not a seed
        (``--seed S``).
    :param option: the option named in error messages.
    :returns: the seeds, in the order given.
    :raises InvalidArgumentError: another form, an empty range, a seed outside 0 to
        2**32 - 1, or a seed listed twice.
    """
    forms = "N (that many seeds, 0 to N-1)" if count else "S (that seed)"
    try:
        text = text.strip()
        if ":" in text:
            start_text, _, stop_text = text.partition(":")
            start, stop = int(start_text), int(stop_text)
            if stop <= start:
                raise InvalidArgumentError(text)  # reported below, with the expected forms
            seeds = list(range(start, stop))
        elif "," in text or not count:
            seeds = [int(part) for part in text.split(",")]
        else:
            number = int(text)
            if number < 1:
                raise InvalidArgumentError(text)  # reported below, with the expected forms
            seeds = list(range(number))
    except (ValueError, InvalidArgumentError):
        raise InvalidArgumentError(
            f"{option} takes {forms}, START:STOP (STOP excluded, STOP > START) or "
            f"S1,S2,..., got {text!r}"
        ) from None
    bad = [seed for seed in seeds if not 0 <= seed <= _MAX_SEED]
    if bad:
        raise InvalidArgumentError(
            f"{option}: a seed is a whole number from 0 to {_MAX_SEED}, got {bad[0]}"
        )
    if len(set(seeds)) != len(seeds):
        raise InvalidArgumentError(f"{option} lists a seed twice: {text!r}")
    return seeds


def _is_positive_seconds(value: object) -> bool:
    """Whether ``value`` is a positive, finite int or float (a bool is not a number here)."""
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def plan(
    scenario: str,
    seeds: Sequence[int],
    params: dict[str, list[ParamValue]] | None = None,
    until: float | None = None,
    engine: str = "pybullet",
) -> list[RunSpec]:
    """Every combination of parameter values (in the order given) times every seed.

    :param scenario: the scenario (a name, a file, or ``module:Class``).
    :param seeds: the seeds each combination runs with.
    :param params: the values to try, by parameter name (None: the defaults only).
    :param until: sim seconds each run lasts at most (None: the scenario's default).
    :param engine: the physics engine every run uses, ``"pybullet"`` (default) or
        ``"mujoco"`` (checked against the scenario by :func:`sweep`).
    :returns: one :class:`RunSpec` per combination and seed.
    :raises InvalidArgumentError: ``seeds`` is empty, or ``until`` is not a positive number.

    Example::

        specs = plan("kuka", seeds=range(10), params={"gain": [0.5, 1.0]})  # 20 runs
    """
    if not seeds:
        raise InvalidArgumentError("a sweep needs at least one seed")
    if until is not None and not _is_positive_seconds(until):
        raise InvalidArgumentError(f"--until must be a positive number of seconds, got {until!r}")
    params = params or {}
    names = list(params)
    specs = []
    for combination in itertools.product(*(params[name] for name in names)):
        values = dict(zip(names, combination, strict=True))
        specs += [RunSpec(scenario, seed, values, until, engine) for seed in seeds]
    return specs


def execute(spec: RunSpec) -> dict[str, Any]:
    """Run ``spec`` in this process: ``{"report": ...}`` or ``{"error": ...}``."""
    from evclock.tools._runs import describe_exception, import_pybullet_quietly, run_scenario

    import_pybullet_quietly()  # on a Ray worker, the first run imports it
    try:
        report = run_scenario(
            spec.scenario,
            seed=spec.seed,
            params=spec.params,
            until=spec.until,
            engine=spec.engine,
        )
    except Exception as exc:
        return {"error": describe_exception(exc), "traceback": traceback.format_exc()}
    return {"report": report.to_json()}


def _row(spec: RunSpec, outcome: dict[str, Any]) -> SweepRow:
    if "error" in outcome:
        return SweepRow(spec, "error", error=str(outcome["error"]))
    report: dict[str, Any] = outcome["report"]
    return SweepRow(spec, str(report["verdict"]), report=report, error=report.get("error"))


def _worker_main(connection: multiprocessing.connection.Connection, spec: RunSpec) -> None:
    # The parent handles Ctrl-C and stops the workers itself; a terminal sends SIGINT to
    # the whole process group, so workers ignore it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    connection.send(execute(spec))
    connection.close()


OnRow = Callable[[SweepRow], None]
OnIdle = Callable[[], None]


def _timed_out(timeout: float) -> dict[str, Any]:
    return {"error": f"timed out after {timeout:g} s of wall time (--run-timeout); stopped"}


def _stop(process: Any) -> None:
    """Terminate a worker; kill it if it does not exit within the grace period."""
    process.terminate()
    process.join(_STOP_GRACE_S)
    if process.is_alive():
        process.kill()
        process.join(_STOP_GRACE_S)


def _run_local(
    specs: list[RunSpec],
    todo: list[int],
    workers: int,
    run_timeout: float | None,
    rows: dict[int, SweepRow],
    on_row: OnRow,
    on_idle: OnIdle,
) -> None:
    context = multiprocessing.get_context("forkserver")
    # (the engine's module too: imported once, in the server every worker is forked from)
    preload = ["evclock.tools._runs", "evclock.tools._sweep", specs[0].engine]
    if not is_file_reference(specs[0].scenario):
        # The scenario's module is importable by name: import it once, in the server every
        # worker is forked from.
        preload.append(load_scenario(specs[0].scenario).__module__)
    context.set_forkserver_preload(preload)
    _start_forkserver_quietly()
    pending = collections.deque((i, specs[i]) for i in todo)
    running: dict[int, tuple[Any, multiprocessing.connection.Connection]] = {}
    started: dict[int, float] = {}
    try:
        while pending or running:
            while pending and len(running) < workers:
                index, spec = pending.popleft()
                receiver, sender = context.Pipe(duplex=False)
                process = context.Process(
                    target=_worker_main, args=(sender, spec), name=f"evclock-sweep-{index}"
                )
                process.start()
                sender.close()
                running[index] = (process, receiver)
                started[index] = time.monotonic()
            waitables = [p.sentinel for p, _ in running.values()]
            waitables += [r for _, r in running.values()]
            multiprocessing.connection.wait(waitables, timeout=_POLL_S)
            for index in sorted(running):
                process, receiver = running[index]
                outcome = _poll(process, receiver)
                if outcome is None:
                    if run_timeout is None or time.monotonic() - started[index] < run_timeout:
                        continue
                    _stop(process)
                    outcome = _timed_out(run_timeout)
                del running[index]
                receiver.close()
                process.join(_STOP_GRACE_S)
                rows[index] = _row(specs[index], outcome)
                on_row(rows[index])
            on_idle()
    finally:
        for process, _receiver in running.values():
            process.terminate()
        for process, receiver in running.values():
            _stop(process)
            receiver.close()


_BANNER = b"pybullet build time:"


def _forward_stderr(reader: int, target: int) -> None:
    """Copy the forkserver's stderr to ours, line by line, without PyBullet's banner."""
    with open(reader, "rb", buffering=0) as source:
        pending = b""
        while chunk := source.read(65536):
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                if not line.startswith(_BANNER):
                    os.write(target, line + b"\n")
        if pending and not pending.startswith(_BANNER):
            os.write(target, pending)


def _start_forkserver_quietly() -> None:
    """Start the forkserver (if it is not running) with its stderr read through a filter
    that drops PyBullet's ``pybullet build time`` banner, printed when it imports PyBullet
    for the workers; whatever else the workers write on stderr still reaches ours."""
    import threading
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    if server is None or getattr(server, "_forkserver_pid", None) is not None:
        forkserver.ensure_running()
        return
    reader, writer = os.pipe()
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        os.dup2(writer, 2)
        forkserver.ensure_running()
    finally:
        os.dup2(saved, 2)
        os.close(writer)
    threading.Thread(
        target=_forward_stderr, args=(reader, saved), name="evclock-sweep-stderr", daemon=True
    ).start()


def _poll(process: Any, receiver: multiprocessing.connection.Connection) -> dict[str, Any] | None:
    """The worker's outcome, a crash outcome if it died without one, or None if running."""
    try:
        if receiver.poll():
            outcome: dict[str, Any] = receiver.recv()
            return outcome
    except (EOFError, OSError):
        pass
    if process.exitcode is None:
        return None
    code = process.exitcode
    cause = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
    return {"error": f"worker process died without a result ({cause})"}


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise MissingExtraError("the ray backend needs Ray: pip install 'evclock[ray]'") from None
    return ray


def _run_ray(
    specs: list[RunSpec],
    todo: list[int],
    workers: int,
    run_timeout: float | None,
    address: str | None,
    rows: dict[int, SweepRow],
    on_row: OnRow,
    on_idle: OnIdle,
) -> None:
    ray = _ray()
    started_here = not ray.is_initialized()
    if started_here:
        if address is None:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    remote = ray.remote(num_cpus=1, max_calls=1, max_retries=0)(execute)
    pending = collections.deque((i, specs[i]) for i in todo)
    in_flight: dict[Any, int] = {}
    submitted: dict[Any, float] = {}
    try:
        while pending or in_flight:
            while pending and len(in_flight) < workers:
                index, spec = pending.popleft()
                ref = remote.remote(spec)
                in_flight[ref] = index
                submitted[ref] = time.monotonic()
            done, _ = ray.wait(list(in_flight), num_returns=1, timeout=_POLL_S)
            if run_timeout is not None:
                for ref in list(in_flight):
                    if ref not in done and time.monotonic() - submitted[ref] >= run_timeout:
                        ray.cancel(ref, force=True)
                        index = in_flight.pop(ref)
                        rows[index] = _row(specs[index], _timed_out(run_timeout))
                        on_row(rows[index])
            for ref in done:
                index = in_flight.pop(ref)
                try:
                    outcome = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                    outcome = {"error": f"ray task failed: {type(exc).__name__}: {first_line}"}
                rows[index] = _row(specs[index], outcome)
                on_row(rows[index])
            on_idle()
    finally:
        for ref in in_flight:
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()


def sweep(
    specs: list[RunSpec],
    *,
    backend: Backend = "local",
    workers: int = 1,
    address: str | None = None,
    run_timeout: float | None = None,
    on_row: OnRow | None = None,
    on_idle: OnIdle | None = None,
    out_dir: Path | None = None,
) -> SweepResult:
    """Run every spec (see the module docstring).

    ``run_timeout`` (wall seconds) stops a run still going after it: an ``error`` row.
    ``on_row`` sees each row as it finishes; ``on_idle`` is called at least every
    0.2 s of wall time while runs are in flight (to refresh a progress display).

    :param specs: the runs, usually from :func:`plan`.
    :param backend: ``"local"`` (worker processes) or ``"ray"`` (a Ray cluster).
    :param workers: how many runs go at once (at least 1).
    :param address: the Ray cluster's address (``backend="ray"`` only).
    :param run_timeout: wall seconds a run may take (None: no limit).
    :param on_row: called with each :class:`SweepRow` as it finishes.
    :param on_idle: called with no arguments while runs are in flight.
    :param out_dir: a directory whose ``runs.jsonl`` gets each row as it finishes; the
        planned runs already there are not run again (see :class:`SweepDirectory`).
    :returns: the :class:`SweepResult` (a Ctrl-C returns the rows finished so far).
    :raises InvalidArgumentError: an unknown ``backend``, ``workers`` below 1, ``address``
        without Ray, no ``specs``, a bad ``run_timeout``, an unknown scenario, or an engine
        the scenario does not run on (or several engines).
    :raises InvalidTypeError: ``workers`` is not an int.
    :raises ScenarioError: the scenario cannot be imported.
    :raises MissingExtraError: ``backend="ray"`` without Ray (``pip install 'evclock[ray]'``),
        or the engine is not installed here (unless ``address`` names a Ray cluster).

    Example::

        result = sweep(plan("kuka", seeds=range(20)), workers=2)
        print(result.summary()["success_rate"])
    """
    if backend not in BACKENDS:
        raise InvalidArgumentError(f"--backend takes local or ray, got {backend!r}")
    if isinstance(workers, bool) or not isinstance(workers, int):
        raise InvalidTypeError(f"workers must be an int, got {workers!r}")
    if workers < 1:
        raise InvalidArgumentError(f"--workers must be at least 1, got {workers}")
    if address is not None and backend != "ray":
        raise InvalidArgumentError("--address is the Ray cluster's: use it with --backend ray")
    if not specs:
        raise InvalidArgumentError("nothing to sweep: no runs planned")
    if run_timeout is not None and not _is_positive_seconds(run_timeout):
        raise InvalidArgumentError(
            f"--run-timeout must be a positive number of wall seconds, got {run_timeout!r}"
        )
    specs = [_absolute(spec) for spec in specs]
    cls = load_scenario(specs[0].scenario)
    engines = list(dict.fromkeys(spec.engine for spec in specs))
    if len(engines) > 1:
        raise InvalidArgumentError(
            f"a sweep runs on one engine; these runs name {' and '.join(map(str, engines))}: "
            "sweep each engine on its own"
        )
    if address is None:  # the runs use this machine's packages: its engine must be installed
        require_engine(cls, engines[0])
    else:  # a Ray cluster's own environment has the engine or not
        check_engine(cls, engines[0])
    name = str(cls.name)
    directory = None if out_dir is None else SweepDirectory(out_dir)
    rows: dict[int, SweepRow] = {}
    if directory is not None:
        directory.check()
        rows.update(directory.finished(specs))
    resumed = len(rows)
    given: OnRow = on_row or (lambda row: None)

    def row_done(row: SweepRow) -> None:
        if directory is not None:
            directory.append(row)
        given(row)

    idle: OnIdle = on_idle or (lambda: None)
    todo = [i for i in range(len(specs)) if i not in rows]
    interrupted = False
    wall0 = time.perf_counter()
    try:
        if not todo:
            pass
        elif backend == "local":
            _run_local(specs, todo, workers, run_timeout, rows, row_done, idle)
        else:
            _run_ray(specs, todo, workers, run_timeout, address, rows, row_done, idle)
    except KeyboardInterrupt:
        interrupted = True
    ordered = [rows[i] for i in sorted(rows)]
    swept = tuple(
        key
        for key in specs[0].params
        if len({_params_key({key: s.params[key]}) for s in specs}) > 1
    )
    return SweepResult(
        specs[0].scenario,
        name,
        len(specs),
        ordered,
        interrupted,
        time.perf_counter() - wall0,
        resumed=resumed,
        swept=swept,
        engine=engines[0],
    )


def _absolute(spec: RunSpec) -> RunSpec:
    """Scenario files by absolute path, so workers in another directory find them."""
    if not is_file_reference(spec.scenario):
        return spec
    path, class_name = split_file_reference(spec.scenario)
    resolved = str(Path(path).resolve()) + (f":{class_name}" if class_name else "")
    return dataclasses.replace(spec, scenario=resolved)
