"""One scenario run: set up the world, run the controllers, report (``evclock run``).

On sim time the physics is stepped from evclock's loop while the scenario's controllers run as
tasks; ``wall=True`` runs the same controllers on wall time while a "world" task steps the
physics in real time, the stand-in for real hardware. :func:`run_scenario` returns a
:class:`RunReport`; a sweep runs the same function in each worker process, so a sweep row
equals the single run of the same seed and parameters.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import dataclasses
import math
import os
import re
import sys
import sysconfig
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any

from evclock._errors import EvClockError, InvalidArgumentError, InvalidTypeError
from evclock.data._diagnostics import diagnostics_report
from evclock.hosts._current import clock
from evclock.hosts._loop import SimEventLoop
from evclock.hosts._runner import run as evclock_run
from evclock.kernel._clock import Clock
from evclock.kernel._pacing import check_rtf
from evclock.kernel._rate import _period_fraction
from evclock.tools._scenarios import (
    ParamValue,
    configure,
    load_scenario,
    open_engine,
    require_engine,
)

if TYPE_CHECKING:
    from rich.progress import Progress

    from evclock.ros2._cli import Ros2ClockOptions
    from evclock.ros2._publisher import Ros2ClockPublisher
    from evclock.tools._record import Recorder

PHYSICS_HZ = 240
_PROGRESS_PERIOD = 0.05  # sim seconds between progress refreshes


@dataclasses.dataclass
class LoopReport:
    """One rate loop's figures at the end of a run.

    :ivar name: the loop's name.
    :ivar hz: its frequency, in hertz.
    :ivar stats: its :class:`~evclock.LoopStats` figures (ticks, misses, lateness...).
    :ivar on_physics_steps: whether its deadlines fall on physics steps (None: no physics
        step is known).
    """

    name: str
    hz: float
    stats: dict[str, float | int]
    on_physics_steps: bool | None = None
    """Whether every deadline of the loop falls on a physics step (its period is a whole
    number of steps); when not, a tick runs at the first step at or after its deadline, up
    to one step late by quantisation alone. None where no physics step is known: a wall-time
    run, and the controllers of a split run whose server does not serve its physics step
    (evclock 0.2's did not); known on both sides of a split run otherwise."""


@dataclasses.dataclass
class RunReport:
    """What a scenario run produced: success, timing, per-loop statistics, final state.

    ``finished`` is False when the run was cut short by its ``until`` limit before the
    mission ended (then the mission was neither accomplished nor failed).

    :ivar scenario: the scenario's name.
    :ivar seed: the seed of the run.
    :ivar mode: ``"sim"`` or ``"wall"`` time.
    :ivar success: whether the scenario accomplished its mission.
    :ivar finished: whether the mission ended before the ``until`` limit.
    :ivar sim_time_s: sim seconds run.
    :ivar wall_time_s: wall seconds the run took.
    :ivar achieved_rtf: sim time over wall time, or None when not measurable.
    :ivar summary: the scenario's own figures.
    :ivar loops: a :class:`LoopReport` per rate loop.
    :ivar final_state: the scenario's final state vector.
    :ivar params: the scenario parameters set for the run.
    :ivar until_s: the sim-time limit of the run, in seconds.
    :ivar setup_output: what the physics engine printed while the world was set up.
    :ivar stamps: stamp diagnostics the scenario used, if any.
    :ivar evclock_version: the evclock version that made the run.
    :ivar error: the exception the scenario or a controller raised, on one line
        (``RuntimeError: boom``; the root cause, not an ``ExceptionGroup``), or None.
    :ivar error_where: where it was raised (phase, function, file and line), or None.
    :ivar traceback: the exception's full traceback, or None.
    :ivar interrupted: whether the run was stopped by Ctrl-C (the report is partial).
    :ivar engine: the physics engine that ran the world (``pybullet`` or ``mujoco``).
    :ivar physics_step_s: the physics time step in seconds, or None (wall time).
    """

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
    params: dict[str, ParamValue] = dataclasses.field(default_factory=dict)
    until_s: float = math.nan
    setup_output: list[str] = dataclasses.field(default_factory=list)
    """What the physics engine printed while the world was set up (deduplicated, counted)."""
    stamps: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    """Stamp diagnostics the scenario used (see evclock.data._diagnostics), if any."""
    evclock_version: str = dataclasses.field(default_factory=lambda: _installed_version())
    """The evclock that made the run (its distribution's version)."""
    error: str | None = None
    """The exception that ended the run (set-up or controllers), on one line, or None."""
    error_where: str | None = None
    """Where that exception was raised: phase, function, file and line."""
    traceback: str | None = None
    """The full traceback of that exception."""
    interrupted: bool = False
    """Whether the run was stopped by Ctrl-C before it ended (the figures are partial)."""
    engine: str = "pybullet"
    """The physics engine that ran the world: ``pybullet`` or ``mujoco``."""
    physics_step_s: float | None = None
    """The physics time step in seconds (None on wall time): the quantum sim time moves by."""

    @property
    def verdict(self) -> str:
        """``success``, ``failed``, ``cut short``, ``error`` (the scenario or a controller
        raised) or ``interrupted`` (Ctrl-C)."""
        if self.error is not None:
            return "error"
        if self.interrupted:
            return "interrupted"
        if not self.finished:
            return "cut short"
        return "success" if self.success else "failed"

    def to_json(self) -> dict[str, Any]:
        """Plain JSON data (non-finite floats become null)."""
        data = dataclasses.asdict(self)
        data["summary"] = {k: _jsonable(v) for k, v in self.summary.items()}
        data["until_s"] = _jsonable(self.until_s)
        data["verdict"] = self.verdict
        return data


def _installed_version() -> str:
    from importlib.metadata import version

    return version("evclock")


def _jsonable(value: object) -> object:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def root_exception(exc: BaseException) -> BaseException:
    """The first leaf of ``exc`` when it is an exception group (a TaskGroup's), else ``exc``."""
    while isinstance(exc, BaseExceptionGroup) and exc.exceptions:
        exc = exc.exceptions[0]
    return exc


def describe_exception(exc: BaseException) -> str:
    """``Type: first line of the message`` of the root of ``exc`` (see :func:`root_exception`)."""
    root = root_exception(exc)
    lines = str(root).strip().splitlines()
    return f"{type(root).__name__}: {lines[0]}" if lines else type(root).__name__


def _library_file(filename: str) -> bool:
    stdlib = sysconfig.get_paths()["stdlib"]
    return filename.startswith(stdlib) or any(
        part in filename for part in ("site-packages", "dist-packages", "<frozen")
    )


def exception_origin(exc: BaseException) -> str:
    """``function (file:line)`` of the innermost frame of the root of ``exc`` in the user's
    code (not the standard library nor an installed package), else of the innermost frame."""
    frames = [
        (frame.f_code, line) for frame, line in traceback.walk_tb(root_exception(exc).__traceback__)
    ]
    if not frames:
        return "an unknown place"
    own = [(code, line) for code, line in frames if not _library_file(code.co_filename)]
    code, line = (own or frames)[-1]
    return f"{code.co_qualname} ({code.co_filename}:{line})"


def _traceback_text(exc: BaseException) -> str:
    return "".join(traceback.format_exception(exc))


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


def check_display_for_gui() -> None:
    """PyBullet's GUI on Linux needs an X display: fail clearly instead of with an X error."""
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        raise InvalidArgumentError(
            "--gui needs a display, but DISPLAY is not set (no X server here): run without "
            "--gui, or under a virtual display: xvfb-run evclock run ... --gui"
        )


_BULLET_MESSAGE = re.compile(r"b3(?:Warning|Error|Printf)\[[^\]]*\]:\s*")


@contextlib.contextmanager
def captured_native_stdout(lines: list[str]) -> Iterator[None]:
    """Collect what native code prints on file descriptor 1 into ``lines``, so the engine's
    set-up chatter (Bullet's ``b3Warning[file,line]: message``) does not tear through the
    progress bar. Each distinct message appears once, prefixed by its count when repeated,
    in order of first appearance. Python's own prints are flushed first and not captured."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    libc.fflush(None)
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            libc.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode(errors="replace")
    messages = (" ".join(m.split()) for m in _BULLET_MESSAGE.split(text))
    counts = collections.Counter(m for m in messages if m)
    lines.extend(f"{n}x {message}" if n > 1 else message for message, n in counts.items())


@contextlib.contextmanager
def silenced_native_stderr() -> Iterator[None]:
    """Send what native code writes on file descriptor 2 to /dev/null meanwhile (Python's own
    ``sys.stderr`` is flushed first)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(os.devnull, "wb") as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def import_pybullet_quietly() -> None:
    """Import PyBullet, if it is installed, without its ``pybullet build time: ...`` banner
    (a library's banner is no business of the user's terminal)."""
    import importlib.util

    if "pybullet" in sys.modules or importlib.util.find_spec("pybullet") is None:
        return
    with silenced_native_stderr():
        import pybullet  # noqa: F401


def _loop_reports(clk: Clock, step_ns: Fraction | None = None) -> list[LoopReport]:
    """A report per rate loop of ``clk``; with the physics step ``step_ns``, whether each
    loop's deadlines fall on physics steps."""
    return [
        loop_report(rate.name, float(rate.hz), rate.stats.as_dict(), step_ns) for rate in clk.rates
    ]


def loop_report(
    name: str, hz: float, stats: dict[str, float | int], step_ns: Fraction | None
) -> LoopReport:
    """The report of one rate loop; with the physics step ``step_ns``, whether its deadlines
    fall on physics steps (its exact period a whole number of steps)."""
    on_steps = None if step_ns is None else (_period_fraction(hz) / step_ns).denominator == 1
    return LoopReport(name, hz, stats, on_steps)


def scenario_class(scenario: str | type[Any], params: dict[str, ParamValue]) -> type[Any]:
    """The class ``scenario`` names (see :func:`load_scenario`) with ``params`` applied."""
    cls = load_scenario(scenario) if isinstance(scenario, str) else scenario
    return configure(cls, params)


def run_scenario(
    scenario: str | type[Any],
    *,
    until: float | None = None,
    rtf: float | None = None,
    seed: int = 0,
    params: dict[str, ParamValue] | None = None,
    gui: bool = False,
    wall: bool = False,
    record: Path | None = None,
    progress: Progress | None = None,
    ros2_clock: Ros2ClockOptions | None = None,
    engine: str = "pybullet",
) -> RunReport:
    """Run ``scenario`` (a name, ``module:Class``, a file, or a class) once and report.

    On sim time unless ``wall`` (see the module docstring), on either engine; ``record``
    writes an MCAP recording (see :mod:`evclock.tools._record`); ``progress`` (a rich
    Progress, refreshed by the run itself) shows sim time and the achieved real-time factor;
    ``ros2_clock`` publishes sim time as ROS 2 ``/clock`` meanwhile (see :mod:`evclock.ros2`).

    :param scenario: a registered name, ``module:Class``, a file, or a scenario class.
    :param until: sim seconds to run at most (default: the scenario's ``default_until``).
    :param rtf: real-time factor on sim time (None: as fast as possible).
    :param seed: the seed the scenario is set up with.
    :param params: scenario parameters to set (see :func:`load_scenario`'s classes).
    :param gui: show PyBullet's GUI (needs a display; MuJoCo runs have none).
    :param wall: run on wall time instead of sim time.
    :param record: an MCAP file to record the run to.
    :param progress: a rich Progress to show the run on.
    :param ros2_clock: publish sim time as ROS 2 ``/clock`` with these options.
    :param engine: the physics engine, ``"pybullet"`` (default) or ``"mujoco"`` (see
        :func:`~evclock.tools._scenarios.open_engine`).
    :returns: the :class:`RunReport` of the run.
    :raises InvalidTypeError: ``seed`` is not an int, or a parameter has the wrong type.
    :raises InvalidArgumentError: a non-positive ``until``, an unknown scenario or
        parameter, ``gui`` without a display or on MuJoCo, or ``ros2_clock`` with ``wall``.
    :raises ScenarioError: the scenario cannot be imported.
    :raises MissingExtraError: ``record`` or ``ros2_clock`` without their extra installed.

    Example::

        report = run_scenario("kuka", seed=3, until=5.0)
        print(report.verdict, report.achieved_rtf)
    """
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InvalidTypeError(f"seed must be an int, got {seed!r}")
    params = dict(params or {})
    cls = scenario_class(scenario, params)
    require_engine(cls, engine)
    if engine == "mujoco" and gui:  # before the display check: no display would do
        raise InvalidArgumentError(
            "--gui opens PyBullet's GUI, which MuJoCo runs do not have: drop --gui"
        )
    limit = cls.default_until if until is None else until
    if isinstance(limit, bool) or not (
        isinstance(limit, int | float) and math.isfinite(limit) and limit > 0
    ):
        raise InvalidArgumentError(f"--until must be a positive number of seconds, got {until!r}")
    if gui:
        check_display_for_gui()
    if wall:
        if ros2_clock is not None:
            raise InvalidArgumentError("--ros2-clock publishes sim time: drop --wall")
        report = _run_on_wall_time(cls, float(limit), seed, gui, progress, record, params, engine)
    else:
        report = _run_on_sim_time(
            cls, float(limit), rtf, seed, params, gui, record, progress, ros2_clock, engine
        )
    report.params = params
    return report


def step_hooks_of(scenario: Any) -> tuple[Any, Any]:
    """The scenario's ``before_step`` and ``after_step`` methods where its class overrides
    :class:`evclock_sims.Scenario`'s (which do nothing), else None for each: a scenario
    without hooks keeps the fast stepping loop."""
    try:
        from evclock_sims import Scenario
    except ImportError:  # a scenario class that does not derive from evclock_sims.Scenario
        return None, None
    found = []
    for name in ("before_step", "after_step"):
        method = getattr(type(scenario), name, None)
        overridden = method is not None and method is not getattr(Scenario, name, None)
        found.append(getattr(scenario, name) if overridden else None)
    return found[0], found[1]


def install_step_hooks(scenario: Any, source: Any) -> list[Any]:
    """Register the scenario's per-physics-step hooks (see :func:`step_hooks_of`) on the
    stepping ``source``: ``before_step`` before every physics step, ``after_step`` after.
    Returns the registered :class:`~evclock.sources.StepHook` handles (``remove()`` each)."""
    before, after = step_hooks_of(scenario)
    hooks = []
    if before is not None:
        hooks.append(source.add_step_hook(before, "before"))
    if after is not None:
        hooks.append(source.add_step_hook(after, "after"))
    return hooks


def _set_up(cls: type[Any], client: int, seed: int, output: list[str]) -> Any:
    with captured_native_stdout(output):
        return cls(client, seed)


def _error_report(
    cls: type[Any], seed: int, mode: str, limit: float, output: list[str], exc: BaseException
) -> RunReport:
    """The report of a run whose scenario raised while setting up its world."""
    return RunReport(
        scenario=cls.name,
        seed=seed,
        mode=mode,
        success=False,
        finished=False,
        sim_time_s=0.0,
        wall_time_s=0.0,
        achieved_rtf=None,
        summary={},
        loops=[],
        final_state=[],
        until_s=limit,
        setup_output=output,
        error=describe_exception(exc),
        error_where=f"setting up the world, in {exception_origin(exc)}",
        traceback=_traceback_text(exc),
    )


class _Outcome:
    """How the controllers' run ended: finished, cut short, raised, or interrupted."""

    def __init__(self) -> None:
        self.finished = True
        self.interrupted = False
        self.error: BaseException | None = None

    async def run(self, scenario: Any, clk: Clock, limit: float) -> None:
        """Run ``scenario`` for at most ``limit`` seconds, recording how it ended."""
        timeout = asyncio.timeout(limit)
        try:
            async with timeout:
                await scenario.run(clk)
        except TimeoutError as exc:
            if timeout.expired():
                self.finished = False
            else:
                self.error = exc
        except asyncio.CancelledError:
            # Ctrl-C: asyncio.Runner cancels the main task; the report says what ran so far.
            self.interrupted = True
        except Exception as exc:
            self.error = exc

    def apply(self, report: RunReport) -> RunReport:
        """Put the error or the interruption into ``report``."""
        report.interrupted = self.interrupted
        if self.error is not None:
            report.error = describe_exception(self.error)
            report.error_where = f"running the controllers, in {exception_origin(self.error)}"
            report.traceback = _traceback_text(self.error)
        return report


def _finish_progress(progress: Progress | None, task_id: Any, sim_s: float, cut: bool) -> None:
    """Leave the bar full: a mission that ended early completes it at its end time."""
    if progress is None:
        return
    if cut:
        progress.update(task_id, completed=sim_s)
    else:
        progress.update(task_id, total=sim_s, completed=sim_s)
    progress.refresh()


def _run_on_sim_time(
    cls: type[Any],
    limit: float,
    rtf: float | None,
    seed: int,
    params: dict[str, ParamValue],
    gui: bool,
    record: Path | None,
    progress: Progress | None,
    ros2_clock: Ros2ClockOptions | None = None,
    engine: str = "pybullet",
) -> RunReport:
    from evclock.ros2._cli import publishing
    from evclock.tools._ros2_state import publishing_robot_state

    output: list[str] = []
    recorder: Recorder | None = None
    opened, world = open_engine(cls, engine, gui=gui)
    source: Any = opened  # PyBullet's or MuJoCo's: a stepping source either way
    try:
        scenario = _set_up(cls, world, seed, output)
        if source is None:  # MuJoCo: the model exists once the scenario has built it
            source = world.time_source()
    except Exception as exc:
        if source is not None:
            source.close()
        return _error_report(cls, seed, "sim", limit, output, exc)
    except BaseException:
        if source is not None:
            source.close()
        raise
    install_step_hooks(scenario, source)
    try:
        from evclock.tools._record import open_recorder, world_of  # --record, --foxglove

        recorder = open_recorder(record, cls, seed, params, limit, world=world_of(source))
    except BaseException:
        source.close()
        raise
    task_id = progress.add_task(cls.name, total=limit, rtf="-") if progress else None

    async def show_progress(loop: SimEventLoop) -> None:
        assert progress is not None
        while True:
            achieved = loop.achieved_rtf()
            progress.update(
                task_id,  # type: ignore[arg-type]
                completed=min(loop.time(), limit),
                rtf="-" if achieved is None else f"{achieved:.2f}",
            )
            progress.refresh()
            await asyncio.sleep(_PROGRESS_PERIOD)

    async def main(clock_publisher: Ros2ClockPublisher | None) -> RunReport:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        wait = None if ros2_clock is None else ros2_clock.wait_for_subscribers
        if clock_publisher is not None and ros2_clock is not None and wait is not None:
            await clock_publisher.wait_for_subscribers(wait, timeout=ros2_clock.wait_timeout)
        clk = clock()
        if recorder is not None:
            recorder.attach(source, clk, scenario.state_vector)
        shower = asyncio.create_task(show_progress(loop)) if progress else None
        wall0 = time.perf_counter()
        loop.achieved_rtf()
        outcome = _Outcome()
        try:
            await outcome.run(scenario, clk, limit)
        finally:
            if shower is not None:
                shower.cancel()
        finished = outcome.finished and outcome.error is None and not outcome.interrupted
        wall_s = time.perf_counter() - wall0
        sim_s = loop.time()
        if recorder is not None:
            recorder.observe()
        _finish_progress(progress, task_id, sim_s, not finished)
        achieved = sim_s / wall_s if wall_s > 0 else None
        return outcome.apply(
            RunReport(
                scenario=cls.name,
                seed=seed,
                mode="sim",
                engine=engine,
                success=outcome.error is None and scenario.success(),
                finished=finished,
                sim_time_s=sim_s,
                wall_time_s=wall_s,
                achieved_rtf=achieved,
                summary=scenario.summary(),
                loops=_loop_reports(clk, source.time_step_ns),
                final_state=scenario.state_vector(),
                stamps=diagnostics_report(),
                until_s=limit,
                setup_output=output,
                physics_step_s=source.time_step,
            )
        )

    report: RunReport | None = None
    try:
        with (
            publishing(source, ros2_clock) as clock_publisher,
            publishing_robot_state(source, ros2_clock, getattr(scenario, "robot_urdf", None)),
        ):
            report = evclock_run(main(clock_publisher), source=source, rtf=rtf)
    finally:
        if recorder is not None:
            recorder.close(None if report is None else _outcome(report))
    assert report is not None
    return report


def _outcome(report: RunReport) -> dict[str, Any]:
    data = report.to_json()
    return {key: data[key] for key in ("verdict", "success", "sim_time_s", "summary")}


def _run_on_wall_time(
    cls: type[Any],
    limit: float,
    seed: int,
    gui: bool,
    progress: Progress | None,
    record: Path | None = None,
    params: dict[str, ParamValue] | None = None,
    engine: str = "pybullet",
) -> RunReport:
    from evclock.tools._record import open_recorder  # --record/--foxglove on wall time

    engine_world, step, close = _wall_time_engine(cls, engine, gui)
    output: list[str] = []
    try:
        try:
            scenario = _set_up(cls, engine_world, seed, output)
        except Exception as exc:
            return _error_report(cls, seed, "wall", limit, output, exc)
        task_id = progress.add_task(cls.name, total=limit, rtf="1 (wall)") if progress else None
        recorder = open_recorder(
            record, cls, seed, params or {}, limit, mode="wall", world=engine_world
        )
        refresh_every = round(PHYSICS_HZ * _PROGRESS_PERIOD)

        before, after = step_hooks_of(scenario)

        async def world() -> None:
            # The stand-in for real hardware: physics advances with the wall clock.
            async for tick in clock().rate(PHYSICS_HZ, name="world (physics)"):
                if before is not None:
                    before()
                step()
                if after is not None:
                    after()
                if recorder is not None:
                    recorder.observe()
                if progress is not None and tick.index % refresh_every == 0:
                    elapsed = time.perf_counter() - wall0
                    progress.update(task_id, completed=min(elapsed, limit))  # type: ignore[arg-type]
                    progress.refresh()

        async def main() -> RunReport:
            clk = clock()
            if recorder is not None:
                recorder.attach(None, clk, scenario.state_vector)
            start = clk.now().seconds
            physics = asyncio.create_task(world())
            outcome = _Outcome()
            try:
                await outcome.run(scenario, clk, limit)
            finally:
                physics.cancel()
            finished = outcome.finished and outcome.error is None and not outcome.interrupted
            wall_s = time.perf_counter() - wall0
            _finish_progress(progress, task_id, wall_s, not finished)
            summary = scenario.summary()
            if scenario.finished_at is not None:
                summary["mission_time_s"] = scenario.finished_at - start
            return outcome.apply(
                RunReport(
                    scenario=cls.name,
                    seed=seed,
                    mode="wall",
                    engine=engine,
                    success=outcome.error is None and scenario.success(),
                    finished=finished,
                    sim_time_s=wall_s,
                    wall_time_s=wall_s,
                    achieved_rtf=1.0,
                    summary=summary,
                    loops=_loop_reports(clk),
                    final_state=scenario.state_vector(),
                    stamps=diagnostics_report(),
                    until_s=limit,
                    setup_output=output,
                )
            )

        wall0 = time.perf_counter()
        report: RunReport | None = None
        try:
            report = evclock_run(main(), use_sim_time=False)
        finally:
            if recorder is not None:
                recorder.close(None if report is None else _outcome(report))
        return report
    finally:
        close()


def _wall_time_engine(
    cls: type[Any], engine: str, gui: bool
) -> tuple[Any, Callable[[], None], Callable[[], None]]:
    """The world a wall-time run builds scenario class ``cls`` in on ``engine``, one physics
    step of it, and how to close it: the physics stands in for real hardware, stepped by a
    wall-clock rate loop (no time source).

    :returns: ``(world, step, close)``: a PyBullet client id, or an
        ``evclock_sims.MuJoCoWorld`` (stepped once the scenario has built its model).
    """
    if engine == "mujoco":
        _, world = open_engine(cls, engine, gui=gui)

        def mj_step() -> None:
            world.mj.mj_step(world.model, world.data)

        return world, mj_step, lambda: None
    import pybullet as p

    cid = p.connect(p.GUI if gui else p.DIRECT)

    def pybullet_step() -> None:
        p.stepSimulation(physicsClientId=cid)

    return cid, pybullet_step, lambda: p.disconnect(cid)
