"""Sweeps: one scenario over many seeds and parameter values, each run in its own process.

:func:`plan` lists the runs (every parameter combination x every seed, in a fixed order);
:func:`sweep` executes them on a backend and returns a :class:`SweepResult` whose rows keep
that order whatever order the runs finish in:

- ``local``: a fresh process per run (forked from a ``forkserver`` that has imported the
  physics engine once), at most ``workers`` at a time;
- ``ray``: one Ray task per run, on a worker process that exits after it (``max_calls=1``),
  on the cluster at ``address`` or on a local Ray started for the sweep and stopped after it.

Every run is :func:`evclock.tools._runs.run_scenario` with its own physics client, so the row of
seed ``k`` equals ``evclock run SCENARIO --seed k`` bit for bit. A scenario exception or a
crashed worker is a failed row with the error; Ctrl-C (``KeyboardInterrupt``) stops the
running workers and returns the rows that finished, marked ``interrupted``.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
import multiprocessing
import multiprocessing.connection
import shlex
import signal
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from evclock._errors import InvalidArgumentError, InvalidTypeError, MissingExtraError
from evclock.tools._scenarios import (
    ParamValue,
    is_file_reference,
    load_scenario,
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
    """

    scenario: str
    seed: int
    params: dict[str, ParamValue]
    until: float | None = None

    def command(self) -> str:
        """The ``evclock run`` command line that reproduces this run."""
        words = ["evclock", "run", self.scenario, "--seed", str(self.seed)]
        for name, value in self.params.items():
            words += ["--param", f"{name}={_format_param(value)}"]
        if self.until is not None:
            words += ["--until", f"{self.until!r}"]
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


@dataclasses.dataclass
class SweepResult:
    """Every finished row, in plan order, and whether the sweep was interrupted.

    :ivar scenario: the scenario as given (a name, a file, ``module:Class``).
    :ivar name: the scenario class's ``name``.
    :ivar planned: how many runs were planned.
    :ivar rows: a :class:`SweepRow` per finished run, in plan order.
    :ivar interrupted: whether the sweep was stopped (Ctrl-C) before every run finished.
    :ivar wall_time_s: wall seconds the sweep took.
    """

    scenario: str
    """The scenario as given (a name, a file, module:Class)."""
    name: str
    """The scenario class's ``name``."""
    planned: int
    rows: list[SweepRow]
    interrupted: bool
    wall_time_s: float

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
            "planned": self.planned,
            "done": done,
            "success_rate": counts["success"] / done if done else None,
            "status_counts": {status: counts[status] for status in sorted(counts)},
            "quantiles": {key: quantiles(values) for key, values in fields.items()},
            "interrupted": self.interrupted,
            "wall_time_s": self.wall_time_s,
        }

    def to_json(self) -> dict[str, Any]:
        """Plain JSON data: the summary and every row."""
        return {
            "scenario": self.scenario,
            "name": self.name,
            "summary": self.summary(),
            "rows": [row.to_json() for row in self.rows],
        }


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


def parse_seeds(text: str) -> list[int]:
    """``"0:1000"`` (start inclusive, stop exclusive), ``"3"`` or ``"1,5,9"``."""
    try:
        if ":" in text:
            start_text, _, stop_text = text.partition(":")
            start, stop = int(start_text), int(stop_text)
            if stop <= start:
                raise InvalidArgumentError(text)  # reported below, with the expected forms
            return list(range(start, stop))
        seeds = [int(part) for part in text.split(",")]
    except ValueError:
        raise InvalidArgumentError(
            f"--seeds takes START:STOP (STOP excluded, STOP > START), N or N1,N2,..., got {text!r}"
        ) from None
    if len(set(seeds)) != len(seeds):
        raise InvalidArgumentError(f"--seeds lists a seed twice: {text!r}")
    return seeds


def plan(
    scenario: str,
    seeds: Sequence[int],
    params: dict[str, list[ParamValue]] | None = None,
    until: float | None = None,
) -> list[RunSpec]:
    """Every combination of parameter values (in the order given) times every seed.

    :param scenario: the scenario (a name, a file, or ``module:Class``).
    :param seeds: the seeds each combination runs with.
    :param params: the values to try, by parameter name (None: the defaults only).
    :param until: sim seconds each run lasts at most (None: the scenario's default).
    :returns: one :class:`RunSpec` per combination and seed.
    :raises InvalidArgumentError: ``seeds`` is empty.

    Example::

        specs = plan("kuka", seeds=range(10), params={"gain": [0.5, 1.0]})  # 20 runs
    """
    if not seeds:
        raise InvalidArgumentError("a sweep needs at least one seed")
    params = params or {}
    names = list(params)
    specs = []
    for combination in itertools.product(*(params[name] for name in names)):
        values = dict(zip(names, combination, strict=True))
        specs += [RunSpec(scenario, seed, values, until) for seed in seeds]
    return specs


def execute(spec: RunSpec) -> dict[str, Any]:
    """Run ``spec`` in this process: ``{"report": ...}`` or ``{"error": ...}``."""
    from evclock.tools._runs import run_scenario

    try:
        report = run_scenario(spec.scenario, seed=spec.seed, params=spec.params, until=spec.until)
    except Exception as exc:
        lines = traceback.format_exception_only(exc)
        return {"error": "".join(lines).strip(), "traceback": traceback.format_exc()}
    return {"report": report.to_json()}


def _row(spec: RunSpec, outcome: dict[str, Any]) -> SweepRow:
    if "error" in outcome:
        return SweepRow(spec, "error", error=str(outcome["error"]))
    report: dict[str, Any] = outcome["report"]
    return SweepRow(spec, str(report["verdict"]), report=report)


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
    workers: int,
    run_timeout: float | None,
    rows: dict[int, SweepRow],
    on_row: OnRow,
    on_idle: OnIdle,
) -> None:
    context = multiprocessing.get_context("forkserver")
    preload = ["evclock.tools._runs", "evclock.tools._sweep", "pybullet"]
    if not is_file_reference(specs[0].scenario):
        # The scenario's module is importable by name: import it once, in the server every
        # worker is forked from.
        preload.append(load_scenario(specs[0].scenario).__module__)
    context.set_forkserver_preload(preload)
    pending = collections.deque(enumerate(specs))
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
    pending = collections.deque(enumerate(specs))
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
    :returns: the :class:`SweepResult` (a Ctrl-C returns the rows finished so far).
    :raises InvalidArgumentError: an unknown ``backend``, ``workers`` below 1, ``address``
        without Ray, no ``specs``, a bad ``run_timeout``, or an unknown scenario.
    :raises InvalidTypeError: ``workers`` is not an int.
    :raises ScenarioError: the scenario cannot be imported.
    :raises MissingExtraError: ``backend="ray"`` without Ray (``pip install 'evclock[ray]'``).

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
    if run_timeout is not None and (
        isinstance(run_timeout, bool)
        or not isinstance(run_timeout, int | float)
        or not math.isfinite(run_timeout)
        or run_timeout <= 0
    ):
        raise InvalidArgumentError(
            f"--run-timeout must be a positive number of wall seconds, got {run_timeout!r}"
        )
    specs = [_absolute(spec) for spec in specs]
    name = str(load_scenario(specs[0].scenario).name)
    row_done: OnRow = on_row or (lambda row: None)
    idle: OnIdle = on_idle or (lambda: None)
    rows: dict[int, SweepRow] = {}
    interrupted = False
    wall0 = time.perf_counter()
    try:
        if backend == "local":
            _run_local(specs, workers, run_timeout, rows, row_done, idle)
        else:
            _run_ray(specs, workers, run_timeout, address, rows, row_done, idle)
    except KeyboardInterrupt:
        interrupted = True
    ordered = [rows[i] for i in sorted(rows)]
    return SweepResult(
        specs[0].scenario, name, len(specs), ordered, interrupted, time.perf_counter() - wall0
    )


def _absolute(spec: RunSpec) -> RunSpec:
    """Scenario files by absolute path, so workers in another directory find them."""
    if not is_file_reference(spec.scenario):
        return spec
    path, class_name = split_file_reference(spec.scenario)
    resolved = str(Path(path).resolve()) + (f":{class_name}" if class_name else "")
    return dataclasses.replace(spec, scenario=resolved)
