"""The simulation behind the dashboard: a PyBullet scenario on a :class:`evclock.SimDriver`.

:class:`SimService` owns a PyBullet client, a :class:`evclock.sources.PyBulletTimeSource`
stepping it and a driver that paces the source on the *server's* event loop. The scenario's
controllers are ordinary tasks on that loop and wait on ``driver.clock`` (sim time), while the HTTP
handlers and the history sampler, on the same loop, use plain asyncio (wall time).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from types import TracebackType
from typing import Any, Literal, cast

import pybullet as p

from evclock import Rate, SimDriver
from evclock.sources import PyBulletTimeSource
from evclock_sims import Scenario, get_scenario

from .config import DashboardConfig
from .scene import SceneView, WorldPose, camera_for, read_world_pose

log = logging.getLogger(__name__)

_EPISODES_KEPT = 20


def finite(value: Any) -> Any:
    """``value`` with NaN and infinities replaced by None (JSON has no such numbers)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclasses.dataclass(slots=True)
class Episode:
    """One run of the scenario's mission, from its world's load to the mission's end."""

    number: int
    seed: int
    scenario: Scenario
    started_at: float
    """Sim seconds at the start."""
    earlier_rates: tuple[Rate, ...]
    """The clock's rate loops when the episode started: the episode's own are the others."""
    ended_at: float | None = None
    outcome: str = "running"
    """``running``, ``success``, ``failure``, ``timeout`` or ``error``."""
    error: str | None = None

    def as_dict(self, now: float) -> dict[str, Any]:
        """The episode for JSON (``now``: current sim seconds, for the running duration)."""
        summary = {key: finite(value) for key, value in self.scenario.summary().items()}
        end = self.ended_at if self.ended_at is not None else now
        return {
            "number": self.number,
            "seed": self.seed,
            "outcome": self.outcome,
            "started_at_s": self.started_at,
            "ended_at_s": self.ended_at,
            "duration_s": end - self.started_at,
            "error": self.error,
            "summary": summary,
        }


@dataclasses.dataclass(frozen=True, slots=True)
class Sample:
    """One point of the plotted history."""

    wall: float
    """Unix time, seconds."""
    sim: float
    achieved_rtf: float | None
    requested_rtf: float | None
    lateness_ms: dict[str, float | None]
    """Mean lateness of each loop's ticks since the previous sample (None: no tick)."""


@dataclasses.dataclass(slots=True)
class LoopTotals:
    """A loop's figures over the whole run, across episode resets (each episode's world has
    new rate loops of the same names: their statistics are added here when it ends)."""

    episodes: int = 0
    ticks: int = 0
    missed: int = 0
    total_lateness_ns: int = 0
    max_lateness_ns: int = 0

    def add(self, rate: Rate) -> None:
        """Add an ended episode's loop."""
        stats = rate.stats
        self.episodes += 1
        self.ticks += stats.ticks
        self.missed += stats.missed
        self.total_lateness_ns += stats.total_lateness_ns
        self.max_lateness_ns = max(self.max_lateness_ns, stats.max_lateness_ns)

    def with_current(self, rate: Rate | None) -> dict[str, Any]:
        """These totals plus the running episode's ``rate``, for JSON."""
        now = LoopTotals(*dataclasses.astuple(self))
        if rate is not None:
            now.add(rate)
        mean = now.total_lateness_ns / now.ticks / 1e9 if now.ticks else 0.0
        return {
            "episodes": now.episodes,
            "ticks": now.ticks,
            "missed": now.missed,
            "mean_lateness_s": mean,
            "max_lateness_s": now.max_lateness_ns / 1e9,
        }


@dataclasses.dataclass(frozen=True, slots=True)
class StepResult:
    """What ``POST /api/step`` reports besides the state."""

    count: int
    time_ns: int
    """Sim time once the steps were taken."""


class StepNotCompleted(Exception):
    """A ``step()`` that ended before its steps were all taken; nothing keeps stepping.

    ``reason`` is ``"interrupted"`` (a pause or a resume meanwhile, which ends the remaining
    steps) or ``"timeout"`` (still under way after ``config.step_timeout`` wall seconds: the
    rest were cancelled).
    """

    def __init__(
        self, reason: Literal["interrupted", "timeout"], count: int, taken: int, message: str
    ) -> None:
        super().__init__(message)
        self.reason = reason
        self.count = count
        self.taken = taken


@dataclasses.dataclass(slots=True)
class _Stepping:
    """A ``step()`` under way: its request, progress and how it may end early."""

    count: int
    first: int
    """``physics_steps`` when it started."""
    done: asyncio.Event
    interrupted: asyncio.Event
    interrupted_by: Literal["pause", "resume", ""] = ""
    """The control that interrupted it, if any."""

    def interrupt(self, control: Literal["pause", "resume"]) -> None:
        self.interrupted_by = control
        self.interrupted.set()


class SimService:
    """A scenario running in episodes on a sim-time driver, with controls and statistics.

    Use as an async context manager on the loop that serves the app::

        async with SimService(DashboardConfig(scenario="kuka")) as sim:
            sim.state(); sim.pause(); await sim.step(3); sim.set_rtf(2.0); sim.resume()

    Control errors are evclock's own (:class:`evclock.EvClockError` and subclasses, e.g.
    stepping while running, a non-positive rtf), with evclock's messages.
    """

    def __init__(self, config: DashboardConfig) -> None:
        self.config = config
        self._scenario_cls = get_scenario(config.scenario)
        self._stack = contextlib.AsyncExitStack()
        self._client = -1
        self._source: PyBulletTimeSource | None = None
        self._driver: SimDriver | None = None
        self._episode: Episode | None = None
        self._finished: collections.deque[Episode] = collections.deque(maxlen=_EPISODES_KEPT)
        self._history: collections.deque[Sample] = collections.deque(maxlen=config.history_size)
        #: Every loop ever sampled, in first-seen order: the plot's series outlive the samples
        #: and the episodes that had them (a series never disappears between two polls).
        self._series: dict[str, None] = {}
        self._last_counts: dict[Rate, tuple[int, int]] = {}
        #: The loops of episodes that ended since the last sample: their last ticks (or, for a
        #: short episode, all of them) still go into the next sample, under their names.
        self._ended_rates: list[Rate] = []
        #: Each loop's figures over the episodes that ended (by name, first-seen order).
        self._totals: dict[str, LoopTotals] = {}
        self._achieved_rtf: float | None = None
        self._steps_before_reset = 0
        self._step_lock = asyncio.Lock()
        self._stepping: _Stepping | None = None
        self.scene = SceneView(
            self._scene_progress,
            self._read_world_pose,
            lambda: self.driver.now_ns,
            camera_for(config.scenario),
            fps=config.scene_fps,
            size=config.scene_size,
        )
        """The live view of the world (rendered in a worker process on demand)."""

    # ---------------------------------------------------------------- lifecycle

    async def __aenter__(self) -> SimService:
        try:
            await self._start()
        except BaseException:
            await self._stack.aclose()
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self._stack.aclose()

    async def _start(self) -> None:
        client = p.connect(p.DIRECT)
        if client < 0:
            raise RuntimeError("could not connect a PyBullet DIRECT client")
        self._client = client
        self._stack.callback(self._disconnect)
        self._stack.callback(self.scene.close)
        scenario = self._scenario_cls(client, self.config.seed)  # sets the 1/240 s time step
        self._source = source = PyBulletTimeSource(client)
        driver = SimDriver(source, rtf=self.config.rtf, paused=self.config.paused)
        self._driver = await self._stack.enter_async_context(driver)
        self._episode = self._new_episode(1, self.config.seed, scenario)
        self._take_sample()
        tasks = [
            asyncio.create_task(self._run_episodes(), name="dashboard.episodes"),
            asyncio.create_task(self._sample_forever(), name="dashboard.sampler"),
        ]
        self._stack.push_async_callback(_cancel_all, tasks)

    def _disconnect(self) -> None:
        if p.isConnected(self._client):
            p.disconnect(self._client)

    @property
    def driver(self) -> SimDriver:
        """The running driver (after entering the service)."""
        if self._driver is None:
            raise RuntimeError("the simulation is not running: enter the SimService first")
        return self._driver

    @property
    def source(self) -> PyBulletTimeSource:
        """The PyBullet time source the driver steps."""
        if self._source is None:
            raise RuntimeError("the simulation is not running: enter the SimService first")
        return self._source

    @property
    def physics_steps(self) -> int:
        """Physics steps taken since the start (counted across episode resets)."""
        return self._steps_before_reset + self.source.step_index

    # ----------------------------------------------------------------- episodes

    def _new_episode(self, number: int, seed: int, scenario: Scenario) -> Episode:
        clock = self.driver.clock
        return Episode(number, seed, scenario, clock.now().seconds, clock.rates)

    async def _run_episodes(self) -> None:
        try:
            await self._episodes_loop()
        except Exception:
            log.exception("the episode runner stopped")
            raise

    async def _episodes_loop(self) -> None:
        clock = self.driver.clock
        while True:
            episode = self._episode
            assert episode is not None
            await self._run_mission(episode)
            self._finished.append(episode)
            log.info("episode %d (seed %d): %s", episode.number, episode.seed, episode.outcome)
            if not self.config.repeat:
                return  # the physics keeps stepping; the controllers are done
            await clock.sleep(self.config.episode_gap)
            # Reset the world at the current time (no time jump), then load the next one.
            ended = self.current_rates()  # before the next ones replace them
            self._ended_rates.extend(ended)
            for rate in ended:
                self._totals.setdefault(rate.name, LoopTotals()).add(rate)
            self._steps_before_reset += self.source.step_index
            self.source.reset_simulation(start=clock.now())
            seed = episode.seed + 1
            scenario = self._scenario_cls(self._client, seed)
            self._episode = self._new_episode(episode.number + 1, seed, scenario)

    async def _run_mission(self, episode: Episode) -> None:
        clock = self.driver.clock
        limit = self.config.episode_limit * episode.scenario.default_until
        mission = asyncio.create_task(episode.scenario.run(clock), name="dashboard.mission")
        deadline = asyncio.ensure_future(clock.sleep(limit))
        try:
            await asyncio.wait({mission, deadline}, return_when=asyncio.FIRST_COMPLETED)
            episode.ended_at = clock.now().seconds
        finally:
            await _cancel_all([mission, deadline])
        if not mission.done() or mission.cancelled():
            episode.outcome = "timeout"
        elif (error := mission.exception()) is not None:
            episode.outcome, episode.error = "error", f"{type(error).__name__}: {error}"
            log.error("episode %d failed", episode.number, exc_info=error)
        else:
            episode.outcome = "success" if episode.scenario.success() else "failure"

    def current_rates(self) -> tuple[Rate, ...]:
        """The rate loops of the current episode, in creation order.

        ``clock.rates`` keeps the latest loop of each name, so the next episode's loops
        replace this one's: they are the loops that were not there when it started.
        """
        rates = self.driver.clock.rates
        if self._episode is None:
            return rates
        earlier = self._episode.earlier_rates
        return tuple(rate for rate in rates if not any(rate is old for old in earlier))

    @property
    def episode(self) -> Episode | None:
        """The episode running now (or, with ``repeat=False``, the one that ran)."""
        return self._episode

    def _scene_progress(self) -> tuple[int, int]:
        episode = self._episode
        assert episode is not None
        return self.physics_steps, episode.number

    def _read_world_pose(self) -> WorldPose:
        episode = self._episode
        assert episode is not None
        return read_world_pose(self._client, episode.scenario, episode.number)

    # ------------------------------------------------------------------ history

    async def _sample_forever(self) -> None:
        while True:
            # Plain asyncio on the server's loop: wall time, whatever sim time does.
            await asyncio.sleep(self.config.sample_period)
            self._take_sample()

    def _take_sample(self) -> None:
        driver = self.driver
        self._achieved_rtf = driver.achieved_rtf()
        counts: dict[Rate, tuple[int, int]] = {}
        new: dict[str, tuple[int, int]] = {}  # name: ticks, lateness ns since the last sample
        ended, self._ended_rates = self._ended_rates, []
        current = self.current_rates()
        for rate in (*ended, *current):
            stats = rate.stats
            ticks, total = stats.ticks, stats.total_lateness_ns
            before_ticks, before_total = self._last_counts.get(rate, (0, 0))
            new_ticks, new_total = new.get(rate.name, (0, 0))
            new[rate.name] = (new_ticks + ticks - before_ticks, new_total + total - before_total)
            counts[rate] = (ticks, total)
        self._last_counts = {rate: counts[rate] for rate in current}  # the ended ones are done
        lateness = {name: ns / n / 1e6 if n else None for name, (n, ns) in new.items()}
        # Paused, sim time stands still: there is no real-time factor to show (the driver's
        # measure would decay towards 0 over its window), only "paused".
        achieved = None if driver.paused else self._achieved_rtf
        sample = Sample(time.time(), driver.now().seconds, achieved, driver.rtf, lateness)
        self._history.append(sample)
        self._series.update(dict.fromkeys(lateness))

    def history(self) -> dict[str, Any]:
        """The sampled history as columns (uPlot's layout): one list per series."""
        samples = list(self._history)
        names = list(self._series)
        return {
            "wall_s": [s.wall for s in samples],
            "sim_time_s": [s.sim for s in samples],
            "achieved_rtf": [s.achieved_rtf for s in samples],
            "requested_rtf": [s.requested_rtf for s in samples],
            "lateness_ms": {name: [s.lateness_ms.get(name) for s in samples] for name in names},
        }

    # --------------------------------------------------------------------- state

    def state(self) -> dict[str, Any]:
        """Everything the dashboard shows, as JSON-ready plain data."""
        driver, source = self.driver, self.source
        now = driver.now()
        episode = self._episode
        return {
            "scenario": {
                "name": self._scenario_cls.name,
                "description": self._scenario_cls.description,
                "repeat": self.config.repeat,
            },
            "sim_time_s": now.seconds,
            "sim_time_ns": now.nanoseconds,
            "physics_steps": self.physics_steps,
            "time_step_s": source.time_step,
            "paused": driver.paused,
            "stepping": self._stepping_info(),
            "rtf": driver.rtf,
            "achieved_rtf": None if driver.paused else finite(self._achieved_rtf),
            "lockstep_overruns": driver.lockstep_overruns,
            "loops": self._loops_info(),
            "episode": episode.as_dict(now.seconds) if episode is not None else None,
            "finished_episodes": [e.as_dict(now.seconds) for e in reversed(self._finished)],
        }

    def _loops_info(self) -> list[dict[str, Any]]:
        """The running episode's loops: their own figures, and under ``run`` their figures
        over the whole run, every episode's loop of the same name included."""
        return [
            {
                **_rate_info(rate),
                "run": self._totals.get(rate.name, LoopTotals()).with_current(rate),
            }
            for rate in self.current_rates()
        ]

    # ------------------------------------------------------------------ controls

    def pause(self) -> None:
        """Stop sim time (the HTTP server keeps serving); cancels a step under way."""
        self.driver.pause()
        if self._stepping is not None:
            self._stepping.interrupt("pause")

    def resume(self) -> None:
        """Let sim time advance again at the requested rtf; ends a step under way."""
        self.driver.resume()
        if self._stepping is not None:
            self._stepping.interrupt("resume")

    def set_rtf(self, rtf: object) -> None:
        """Change the requested real-time factor (None: as fast as possible).

        ``rtf`` is passed to evclock unchecked: evclock validates it and raises its errors.
        """
        self.driver.rtf = rtf  # type: ignore[assignment]

    async def step(self, count: object = 1) -> StepResult:
        """While paused, advance exactly ``count`` physics steps; return once they are taken.

        Returns after the work due at the final time has run (the controllers' ticks there),
        so the state read next shows it. Steps are paced at the requested rtf and counted
        across episode resets. Raises :class:`StepNotCompleted` if a :meth:`pause` cancels
        the remaining steps or a :meth:`resume` ends them (sim time then runs freely), or if
        they are not all taken within ``config.step_timeout`` wall seconds (the rest are then
        cancelled: nothing goes on stepping). Concurrent calls take their turns. ``count``
        is passed to evclock unchecked (it raises for a bad count or when running).
        """
        async with self._step_lock:
            driver = self.driver
            driver.step(count)  # type: ignore[arg-type]
            steps = cast(int, count)  # evclock accepted it: an int >= 1
            stepping = _Stepping(steps, self.physics_steps, asyncio.Event(), asyncio.Event())
            hook = self.source.add_step_hook(lambda: self._count_step(stepping))
            self._stepping = stepping
            try:
                ended = await _first_of(
                    stepping.done, stepping.interrupted, timeout=self.config.step_timeout
                )
            finally:
                hook.remove()
                self._stepping = None
            taken = self.physics_steps - stepping.first
            if ended is stepping.done:
                await driver.clock.sleep(0)  # after the ticks due at this time
                return StepResult(steps, driver.now_ns)
            if ended is stepping.interrupted:
                raise StepNotCompleted(
                    "interrupted",
                    steps,
                    taken,
                    f"the step was interrupted by a {stepping.interrupted_by} after {taken} of "
                    f"{steps} physics steps; "
                    + (
                        "the remaining ones were cancelled"
                        if stepping.interrupted_by == "pause"
                        else "sim time now runs freely"
                    ),
                )
            driver.pause()  # cancels the remaining steps
            rtf = "as fast as possible" if driver.rtf is None else f"rtf={driver.rtf:g}"
            raise StepNotCompleted(
                "timeout",
                steps,
                taken,
                f"only {taken} of {steps} physics steps were taken in "
                f"{self.config.step_timeout:g} s of wall time at {rtf}; the remaining ones "
                "were cancelled; step fewer at a time, raise the rtf, or raise step_timeout",
            )

    def _count_step(self, stepping: _Stepping) -> None:
        """A step hook: mark the step request done at its last physics step."""
        if self.physics_steps - stepping.first >= stepping.count:
            stepping.done.set()

    def _stepping_info(self) -> dict[str, int] | None:
        stepping = self._stepping
        if stepping is None:
            return None
        return {"count": stepping.count, "taken": self.physics_steps - stepping.first}


async def _first_of(*events: asyncio.Event, timeout: float) -> asyncio.Event | None:
    """The first of ``events`` to be set (checked in order), or None after ``timeout`` wall s."""
    waits = [asyncio.ensure_future(event.wait()) for event in events]
    try:
        await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        await _cancel_all(waits)
    return next((event for event in events if event.is_set()), None)


def _rate_info(rate: Rate) -> dict[str, Any]:
    stats = rate.stats
    return {
        "name": rate.name,
        "hz": rate.hz,
        "policy": rate.policy,
        **stats.as_dict(),
        "p50_lateness_s": stats.percentile(50).seconds,
    }


async def _cancel_all(tasks: Sequence[asyncio.Future[Any]]) -> None:
    """Cancel ``tasks`` and wait until they are done (their errors are theirs to report)."""
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
