""":class:`ScenarioEnv`: a scenario as a Gymnasium environment, the agent in place of one of
its controllers while everything else keeps running on sim time.

How a step runs. Each episode has its own world and its own :class:`~evclock.SimEventLoop`
(time source: the engine's physics). The scenario runs on that loop as ``evclock run`` runs
it, except that its agent controller is replaced by a rate loop at the same rate and with the
same name which, at each tick, observes and stops the loop. ``step(action)`` applies the
action (at the sim time of the last observation: it takes effect at the next physics step, as
the replaced controller's command would), then runs the loop (``run_forever``) until the next
tick has observed: exactly one period of physics, other controllers and timers. The loop
stops at the end of that iteration, without moving time any further.

``reset()`` builds a new world and loop (with the episode's seed) rather than jumping the old
one's sim time backwards: a fresh world is exactly the state ``evclock run`` starts from (the
scenario draws everything from its seed while it is built), and takes milliseconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from pathlib import Path
from typing import Any, SupportsFloat

from evclock._errors import EnvStateError, InvalidArgumentError, InvalidTypeError
from evclock._extras import import_extra
from evclock.gym._protocol import check_action, check_protocol, check_rate
from evclock.hosts._loop import SimEventLoop
from evclock.tools._runs import install_step_hooks, root_exception, scenario_class
from evclock.tools._scenarios import ParamValue, open_world, require_engine

import_extra("gymnasium", "gym", needed_by="evclock.gym")  # the extra's error, if missing

import gymnasium  # noqa: E402

_ENDED = object()  # the observation of a period that ended with the scenario's run


class ScenarioEnv(gymnasium.Env[Any, Any]):
    """A scenario as a ``gymnasium.Env``: the agent replaces one of its controllers.

    ``step(action)`` applies the action where the replaced controller would, runs the
    simulation (physics, the other controllers, timers) for exactly one period of that
    controller on sim time, and returns what the agent observes then. ``reset(seed=...)``
    builds the world anew from the seed, at sim time 0.

    The episode is **terminated** when the scenario says its state is terminal
    (``terminated()``: the pole fell, every target was reached); **truncated** when
    ``max_episode_seconds`` of sim time have run, or the scenario's mission ended without a
    terminal state (the cart-pole held for its hold time). ``info`` holds ``sim_time``
    (seconds), ``seed`` (the episode's) and ``ticks`` (every rate loop's ticks so far, by
    name); the last step of an episode adds ``loops``, every rate loop's statistics
    (:meth:`evclock.LoopStats.as_dict`: ticks, misses, lateness).

    :param scenario: a registered name (``"cartpole"``), ``module:Class``, a file, or a
        scenario class implementing the agent protocol.
    :param controller: the controller the agent replaces (default: the scenario's
        ``agent_controller``).
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
        not the one it lets an agent replace.
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
        self._record = None if record is None else Path(record)
        self._episodes = 0
        self._source: Any = None
        self._loop: SimEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._recorder: Any = None
        self._observation: Any = _ENDED
        self._ended: str | None = "reset() was not called yet"
        self._closed = False
        self.scenario: Any = None
        """The scenario of the current episode (None before the first ``reset()``)."""
        # The spaces come from a scenario built once (the KUKA's bounds are its model's).
        source, probe = open_world(self._cls, 0 if seed is None else seed, engine=engine)
        try:
            self.hz = check_rate(probe)
            """The agent's rate: one step per ``1 / hz`` sim seconds."""
            self.observation_space = probe.observation_space()
            self.action_space = probe.action_space()
        finally:
            source.close()
        self._limit_ns = round(self.max_episode_seconds * 1e9)

    # ------------------------------------------------------------------ episodes

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start an episode in a new world: the observation at sim time 0, and ``info``.

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
        self._end_episode()
        self._start_episode(episode_seed)
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
        loop = self._loop
        assert loop is not None
        if observation is _ENDED:  # the mission ended between two ticks: observe its end
            observation = scenario.observe()
        # The mission ended (at this tick, or before): the run is over.
        ran_out = getattr(scenario, "finished_at", None) is not None or self._task_done()
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
            self._end_episode()
            self._closed = True
            self._ended = "the environment is closed"
        super().close()

    # ------------------------------------------------------------------ the loop

    def _start_episode(self, seed: int) -> None:
        source, scenario = open_world(self._cls, seed, engine=self.engine)
        install_step_hooks(scenario, source)
        self._source, self.scenario = source, scenario
        self._seed = seed
        loop = self._loop = SimEventLoop(source, watch_threads=False)
        clock = loop.clock
        scenario.replace_controller(self.controller, self._agent)
        if self._record is not None:
            from evclock.tools._record import open_recorder

            path = self._record.with_name(
                f"{self._record.stem}-{self._episodes}{self._record.suffix or '.mcap'}"
            )
            self._recorder = open_recorder(
                path, self._cls, seed, self._params, self.max_episode_seconds
            )
            self._recorder.attach(source, clock, scenario.state_vector)
        self._episodes += 1
        self._task = loop.create_task(scenario.run(clock), name=f"{self._cls.name}.run")
        self._task.add_done_callback(self._run_ended)
        self._ended = None

    async def _agent(self, clock: Any) -> None:
        """The agent's controller: at each tick, observe and stop the loop (``step()`` and
        ``reset()`` run it until then)."""
        scenario, loop = self.scenario, self._loop
        assert loop is not None
        async for _tick in clock.rate(self.hz, name=self.controller):
            self._observation = scenario.observe()
            loop.stop()  # at the end of this iteration: no time passes before it

    def _run_ended(self, task: asyncio.Task[None]) -> None:
        if self._loop is not None:
            self._loop.stop()

    def _run_period(self) -> Any:
        """Run the loop until the agent's next tick has observed (or the run ended)."""
        loop, task = self._loop, self._task
        assert loop is not None
        assert task is not None
        self._observation = _ENDED
        while self._observation is _ENDED and not task.done():
            loop.run_forever()
        if task.done():
            self._raise_if_failed(task)
        return self._observation

    def _task_done(self) -> bool:
        return self._task is not None and self._task.done()

    def _raise_if_failed(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            error = task.exception()
            assert error is not None
            self._ended = "a controller of the scenario raised: call reset()"
            raise root_exception(error)

    def _end_episode(self) -> None:
        loop, task = self._loop, self._task
        self._loop = self._task = None
        try:
            if loop is not None and task is not None:
                if not task.done():
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):  # cancelled here
                        loop.run_until_complete(task)
                loop.run_until_complete(loop.shutdown_asyncgens())
                loop.close()
        finally:
            if self._recorder is not None:
                recorder, self._recorder = self._recorder, None
                recorder.observe()
                recorder.close()
            if self._source is not None:
                source, self._source = self._source, None
                source.close()

    def _info(self, *, final: bool = False) -> dict[str, Any]:
        loop = self._loop
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
