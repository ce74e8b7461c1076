""":class:`ScenarioEnv`: a scenario as a Gymnasium environment, the agent in place of one of
its controllers while everything else keeps running on sim time.

How a step runs. The environment owns one world (the engine's physics: a compiled MuJoCo
model, a PyBullet client) and one :class:`~evclock.SimEventLoop` on it, kept across episodes.
The scenario runs on that loop as ``evclock run`` runs it, except that its agent controller is
replaced by a rate loop at the same rate and with the same name which, at each tick, observes
and stops the loop. ``step(action)`` applies the action (at the sim time of the last
observation: it takes effect at the next physics step, as the replaced controller's command
would), then runs the loop until the next tick has observed: exactly one period of physics,
other controllers and timers. The loop stops at the end of that iteration, without moving time
any further.

How a reset runs: in place, to exactly the state of a new environment (:class:`_Episodes`).
The old episode's tasks are cancelled and run to their end; the source resets the engine and
moves sim time back to 0 (a jump nobody waits through: no task is left); the rate loops and
timers of the old episode are forgotten; the scenario is built again with the episode's seed
into the same world. On MuJoCo the model is not compiled again (``mj_resetData`` gives the
state of a new ``MjData``); on PyBullet the world is emptied (``resetSimulation``) and the
scenario loads its bodies again (PyBullet's ``restoreState`` brings back positions and
velocities but not motor settings nor every solver cache, so it is not used). A loop left in an
unknown state (an error raised by the physics or a step hook, not by a controller) is closed and
built anew at the next reset.
"""

from __future__ import annotations

import asyncio
import math
import weakref
from pathlib import Path
from typing import Any, SupportsFloat

from evclock._errors import EnvStateError, InvalidArgumentError, InvalidTypeError
from evclock._extras import import_extra
from evclock.gym._protocol import check_action, check_protocol, check_rate
from evclock.hosts._loop import SimEventLoop
from evclock.tools._runs import (
    import_pybullet_quietly,
    install_step_hooks,
    root_exception,
    scenario_class,
)
from evclock.tools._scenarios import ParamValue, open_world, require_engine

import_extra("gymnasium", "gym", needed_by="evclock.gym")  # the extra's error, if missing

import gymnasium  # noqa: E402

_ENDED = object()  # the observation of a period that ended with the scenario's run


def _finish(loop: SimEventLoop, task: asyncio.Task[None]) -> None:
    """Cancel ``task`` and any other task left on ``loop``, and run them to their end (at the
    current sim time: cancelled tasks end without waiting)."""
    pending = {task, *asyncio.all_tasks(loop)}
    for other in pending:
        other.cancel()
    waiter = loop.create_task(asyncio.wait(pending))
    waiter.add_done_callback(lambda _: loop.stop())
    while not waiter.done():  # the run's own done callback stops the loop too
        loop.run_forever()
    for other in pending:  # retrieved: nothing logs "exception never retrieved"
        if not other.cancelled():
            other.exception()


class _Episodes:
    """The world, the loop and the scenario of an environment's episodes, kept across resets.

    Separate from :class:`ScenarioEnv` so that nothing the loop runs refers to the environment:
    an environment dropped without ``close()`` is freed at once, and its finalizer closes this
    (cancelling the episode's tasks and running them to their end) before anything warns.
    """

    def __init__(self, cls: type[Any], engine: str, label: str, seed: int) -> None:
        self.cls, self.engine, self.label = cls, engine, label
        self.source: Any = None
        self.scenario: Any = None
        self.loop: SimEventLoop | None = None
        self.task: asyncio.Task[None] | None = None
        self.observation: Any = _ENDED
        self.hz = 0.0
        self._hooks: list[Any] = []
        self._open(seed)

    def _open(self, seed: int) -> None:
        """Build the world and the loop anew, the scenario in it with ``seed``."""
        self.source, self.scenario = open_world(self.cls, seed, engine=self.engine)
        self.scenario.agent_controller = self.label  # the spaces and the rate are its
        try:
            self.hz = check_rate(self.scenario)
            self.loop = SimEventLoop(self.source, watch_threads=False)
        except BaseException:
            self.source.close()
            raise

    def start(self, seed: int) -> Any:
        """End the running episode, reset the world in place and start the scenario with
        ``seed``; returns the scenario (not running yet: :meth:`run_period` runs it)."""
        self.stop()
        loop = self.loop
        if loop is None or loop.is_closed():
            self._open(seed)
        else:
            self.source.reset_simulation()  # time back to 0: no task is left to hear the jump
            world = self.scenario.world
            if world is not None:
                world.clear()  # MuJoCo: the same model, the data of a new MjData
            else:
                world = self.source.client
            loop.clock._forget_loops()
            self.scenario = self.cls(world, seed)
            self.scenario.agent_controller = self.label
        loop = self.loop
        assert loop is not None
        scenario = self.scenario
        self._hooks = install_step_hooks(scenario, self.source)
        scenario.replace_controller(self.label, self._agent)
        return scenario

    def run(self) -> None:
        """Start the scenario's run on the loop (after :meth:`start` and any recorder)."""
        loop = self.loop
        assert loop is not None
        self.task = loop.create_task(self.scenario.run(loop.clock), name=f"{self.cls.name}.run")
        self.task.add_done_callback(self._run_ended)

    async def _agent(self, clock: Any) -> None:
        """The agent's controller: at each tick, observe and stop the loop (``step()`` and
        ``reset()`` run it until then)."""
        scenario, loop = self.scenario, self.loop
        assert loop is not None
        async for _tick in clock.rate(self.hz, name=self.label):
            self.observation = scenario.observe()
            loop.stop()  # at the end of this iteration: no time passes before it

    def _run_ended(self, task: asyncio.Task[None]) -> None:
        if self.loop is not None:
            self.loop.stop()

    def run_period(self) -> Any:
        """Run the loop until the agent's next tick has observed (or the run ended); the
        observation, or ``_ENDED``."""
        loop, task = self.loop, self.task
        assert loop is not None
        assert task is not None
        self.observation = _ENDED
        try:
            while self.observation is _ENDED and not task.done():
                loop.run_forever()
        except BaseException:
            self.close_loop()  # raised by the physics or a hook, not a task: start afresh
            raise
        return self.observation

    def stop(self) -> None:
        """Cancel the episode's tasks and run them to their end (nothing left pending)."""
        task, self.task = self.task, None
        loop = self.loop
        for hook in self._hooks:
            hook.remove()
        self._hooks = []
        if task is None or loop is None or loop.is_closed():
            return
        try:
            _finish(loop, task)
        except BaseException:
            self.close_loop()
            raise

    def close_loop(self) -> None:
        """Close the loop and the source (the next :meth:`start` builds them anew)."""
        loop, self.loop = self.loop, None
        task, self.task = self.task, None
        try:
            if loop is not None and not loop.is_closed():
                if task is not None:
                    _finish(loop, task)
                loop.run_until_complete(loop.shutdown_asyncgens())
                loop.close()
        finally:
            if self.source is not None:
                self.source.close()

    def close(self) -> None:
        """End the episode and free the world (the finalizer of a dropped environment)."""
        try:
            self.stop()
        finally:
            self.close_loop()


class ScenarioEnv(gymnasium.Env[Any, Any]):
    """A scenario as a ``gymnasium.Env``: the agent replaces one of its controllers.

    ``step(action)`` applies the action where the replaced controller would, runs the
    simulation (physics, the other controllers, timers) for exactly one period of that
    controller on sim time, and returns what the agent observes then. ``reset(seed=...)``
    resets the world in place to sim time 0 and builds the scenario again with the seed: the
    episode is bit for bit the one a new environment (or ``evclock run`` with the same
    controller) gives with that seed, whatever ran before; only what no seed changes is kept
    (the compiled MuJoCo model, the event loop, the cart-pole's LQR gain).

    The episode is **terminated** when the scenario says its state is terminal
    (``terminated()``: the pole fell, every target was reached); **truncated** when
    ``max_episode_seconds`` of sim time have run, or the scenario's mission ended without a
    terminal state (the cart-pole held for its hold time). ``info`` holds ``sim_time``
    (seconds), ``seed`` (the episode's) and ``ticks`` (every rate loop's ticks so far, by
    name); the last step of an episode adds ``loops``, every rate loop's statistics
    (:meth:`evclock.LoopStats.as_dict`: ticks, misses, lateness).

    An environment dropped without :meth:`close` (or still open when the interpreter exits)
    is closed then: its episode's tasks are cancelled and run to their end, quietly.

    :param scenario: a registered name (``"cartpole"``), ``module:Class``, a file, or a
        scenario class implementing the agent protocol.
    :param controller: the controller the agent replaces: one of the scenario's
        ``agent_controllers`` (the KUKA's ``"joint_control"``, 100 Hz joint targets, or
        ``"planner"``, 10 Hz goals for the joint controller), each with its own rate,
        observation and action spaces (default: the scenario's ``agent_controller``).
    :param engine: ``"mujoco"`` (default: Gymnasium's reference engine, on every Python) or
        ``"pybullet"``.
    :param seed: the seed of the first episode when ``reset()`` is given none.
    :param params: scenario parameters (see :func:`evclock.tools.parameters`).
    :param max_episode_seconds: sim seconds per episode at most (default: the scenario's
        ``default_until``).
    :param record: record every episode to MCAP: episode ``k`` to ``STEM-k.mcap`` next to
        ``record`` (``runs/cartpole.mcap`` -> ``runs/cartpole-0.mcap``, ...).
    :param render_mode: only None (watch episodes in Foxglove through ``record``).
    :raises AgentProtocolError: the scenario lacks the agent protocol, or ``controller`` is
        not one it lets an agent replace (the message names those).
    :raises InvalidArgumentError: an unknown engine or parameter, a bad time limit.
    :raises MissingExtraError: the engine is not installed (the message names its extra).
    """

    metadata = {"render_modes": []}  # noqa: RUF012  (Gymnasium's own attribute)

    def __init__(
        self,
        scenario: str | type[Any],
        controller: str | None = None,
        *,
        engine: str = "mujoco",
        seed: int | None = None,
        params: dict[str, ParamValue] | None = None,
        max_episode_seconds: float | None = None,
        record: str | Path | None = None,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None:
            raise InvalidArgumentError(
                f"ScenarioEnv renders nothing itself (render_mode={render_mode!r}): record "
                "episodes with record=PATH and watch them in Foxglove"
            )
        self.render_mode = None
        self._params = dict(params or {})
        self._cls = scenario_class(scenario, self._params)
        require_engine(self._cls, engine)  # the engine is installed, or the extra is named
        if engine == "pybullet":
            import_pybullet_quietly()  # as the command line: no banner on the user's stderr
        self.controller = check_protocol(self._cls, controller)
        """The label of the controller the agent replaces."""
        self.engine = engine
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise InvalidTypeError(f"seed must be an int or None, got {seed!r}")
        self._next_seed = seed
        limit = self._cls.default_until if max_episode_seconds is None else max_episode_seconds
        if isinstance(limit, bool) or not (
            isinstance(limit, int | float) and math.isfinite(limit) and limit > 0
        ):
            raise InvalidArgumentError(
                f"max_episode_seconds must be a positive number of sim seconds, got {limit!r}"
            )
        self.max_episode_seconds = float(limit)
        self._limit_ns = round(self.max_episode_seconds * 1e9)
        self._record = None if record is None else Path(record)
        self._episodes_run = 0
        self._recorder: Any = None
        self._ended: str | None = "reset() was not called yet"
        self._closed = False
        self._seed = 0
        # The world, built once: the spaces come from its scenario (the KUKA's bounds are its
        # model's), and every episode resets it in place.
        episodes = self._episodes = _Episodes(
            self._cls, engine, self.controller, 0 if seed is None else seed
        )
        self._finalizer = weakref.finalize(self, episodes.close)
        probe = episodes.scenario
        self.hz = episodes.hz
        """The agent's rate: one step per ``1 / hz`` sim seconds."""
        self.observation_space = probe.observation_space()
        self.action_space = probe.action_space()
        self.scenario: Any = None
        """The scenario of the current episode (None before the first ``reset()``)."""

    # ------------------------------------------------------------------ episodes

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start an episode: reset the world in place, build the scenario with the seed, and
        return the observation at sim time 0 and ``info``.

        :param seed: the episode's seed (default: the constructor's for the first episode,
            then the next draw of the environment's generator).
        :param options: no options are supported: None or empty.
        """
        if self._closed:
            raise EnvStateError("reset() on a closed environment: make a new one")
        if options:
            raise InvalidArgumentError(
                f"ScenarioEnv.reset() takes no options, got {sorted(options)!r}"
            )
        if seed is None and self._next_seed is not None:
            seed = self._next_seed
        self._next_seed = None
        super().reset(seed=seed)
        episode_seed = seed if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        self._ended = "the last reset() failed: call reset()"
        self._close_recorder()
        episodes = self._episodes
        self.scenario = episodes.start(episode_seed)
        self._seed = episode_seed
        if self._record is not None:
            self._open_recorder(episode_seed)
        self._episodes_run += 1
        episodes.run()
        self._ended = None
        observation = self._run_period()
        if observation is _ENDED:
            raise EnvStateError(f"scenario {self._cls.name!r} ended before its agent's first tick")
        return observation, self._info()

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply ``action``, run one period of the agent's controller, and return
        ``(observation, reward, terminated, truncated, info)``.

        :raises ActionError: ``action`` is not in the action space (never clipped).
        :raises EnvStateError: no episode runs (before ``reset()``, after it ended, after
            ``close()``).
        """
        if self._ended is not None:
            raise EnvStateError(f"step() needs a running episode, but {self._ended}")
        checked = check_action(self.action_space, action, who="step()")
        scenario = self.scenario
        scenario.act(checked)
        observation = self._run_period()
        if observation is _ENDED:  # the mission ended between two ticks: observe its end
            observation = scenario.observe()
        episodes = self._episodes
        loop = episodes.loop
        assert loop is not None
        task = episodes.task
        # The mission ended (at this tick, or before): the run is over.
        ran_out = getattr(scenario, "finished_at", None) is not None or (
            task is not None and task.done()
        )
        terminated = bool(scenario.terminated())
        truncated = not terminated and (ran_out or loop.now_ns >= self._limit_ns)
        reward = float(scenario.reward())
        if terminated or truncated:
            why = "terminated" if terminated else "truncated"
            self._ended = f"the episode ended ({why}) at sim time {loop.time():g} s: call reset()"
        info = self._info(final=terminated or truncated)
        return observation, reward, terminated, truncated, info

    def close(self) -> None:
        """End the episode and free its world; the environment cannot be used afterwards."""
        if not self._closed:
            self._closed = True
            self._ended = "the environment is closed"
            try:
                self._close_recorder()
            finally:
                self._finalizer()
        super().close()

    # ------------------------------------------------------------------ the loop

    def _open_recorder(self, seed: int) -> None:
        from evclock.tools._record import open_recorder

        assert self._record is not None
        episodes = self._episodes
        assert episodes.loop is not None
        path = self._record.with_name(
            f"{self._record.stem}-{self._episodes_run}{self._record.suffix or '.mcap'}"
        )
        self._recorder = open_recorder(
            path, self._cls, seed, self._params, self.max_episode_seconds
        )
        self._recorder.attach(episodes.source, episodes.loop.clock, self.scenario.state_vector)

    def _close_recorder(self) -> None:
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            recorder.observe()
            recorder.close()

    def _run_period(self) -> Any:
        """Run the loop until the agent's next tick has observed (or the run ended)."""
        episodes = self._episodes
        try:
            observation = episodes.run_period()
        except BaseException:
            self._ended = "the simulation raised: call reset()"
            raise
        task = episodes.task
        assert task is not None
        if task.done() and not task.cancelled() and task.exception() is not None:
            error = task.exception()
            assert error is not None
            self._ended = "a controller of the scenario raised: call reset()"
            raise root_exception(error)
        return observation

    def _info(self, *, final: bool = False) -> dict[str, Any]:
        loop = self._episodes.loop
        assert loop is not None
        rates = loop.clock.rates
        info: dict[str, Any] = {
            "sim_time": loop.time(),
            "seed": self._seed,
            "ticks": {rate.name: rate.stats.ticks for rate in rates},
        }
        if final:  # the full statistics sort recent latenesses: once per episode
            info["loops"] = {rate.name: rate.stats.as_dict() for rate in rates}
        return info
