"""Recording a run to an MCAP file (``evclock run ... --record run.mcap``), and the same
channels served live to Foxglove (``--foxglove``, see :mod:`evclock.tools._foxglove`).

Every channel carries JSON messages described by a JSON Schema (the encodings Foxglove
documents for MCAP), stamped with the sim time in integer nanoseconds (``log_time`` and
``publish_time``; wall time in ``--wall`` runs):

- ``/evclock/clock``: sim time, wall time since the start and the achieved real-time factor
  over the last window. Wall-time dependent, so ``trace diff`` skips it.
- ``/evclock/loop/<name>``: one message per tick of each rate loop: its lateness and the
  periods it missed.
- ``/evclock/state``: the world's full physical state by name (per body: base pose and
  velocities, each joint's position and velocity), sampled periodically.
- ``/evclock/joints`` (``foxglove.JointStates``), ``/evclock/transforms``
  (``foxglove.FrameTransforms``), ``/evclock/scene`` (``foxglove.SceneUpdate``, once: the
  robot's shapes and meshes; a viewer that subscribes later is sent it again, never the
  file) and ``/evclock/log`` (``foxglove.Log``: the controllers'
  :mod:`logging` records): what Foxglove's 3D, plot and log panels show.
- ``/evclock/jump``: every time jump (reset, restored snapshot).
- any user channel a controller writes with :func:`evclock.tools.record`, with a JSON Schema
  of its fields (from the dataclass or TypedDict the user writes, else from the first message).

The file's ``evclock.format`` metadata names its format version (:data:`FORMAT_VERSION`;
recordings without it are version 1, whose state is an unnamed array).

The recorder observes the run from a step hook of the physics engine's time source (run before
each step, when all the work at the current time is done), so it adds no task or timer to the
program: a recorded run has the same trajectory as an unrecorded one. It reads the world by
name on either engine: PyBullet's bodies, links and joints (:class:`~evclock.tools._foxglove.
World`) or a MuJoCo model's trees, bodies and joints
(:class:`~evclock.tools._world_mujoco.MuJoCoWorldReader`), in the same messages.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from evclock._errors import InvalidArgumentError, InvalidTypeError, MissingExtraError
from evclock.tools._foxglove import object_schema

if TYPE_CHECKING:
    from evclock.kernel._clock import Clock
    from evclock.kernel._jumps import TimeJump
    from evclock.sources._stepping import SteppingTimeSource
    from evclock.tools._foxglove import LiveView, World
    from evclock.tools._world_mujoco import MuJoCoWorldReader

PROFILE = "evclock"
"""The MCAP profile of evclock recordings."""
FORMAT_VERSION = 2
"""The recording format this evclock writes (and the newest it reads)."""
WALL_TIME_TOPICS = frozenset({"/evclock/clock"})
"""Channels whose content depends on wall time: ``trace diff`` does not compare them."""
SAMPLE_PERIOD_S = 0.05
"""Sim seconds between two samples of the clock, state, joints and transforms: samples are
due on a drift-free grid (``start + i x 0.05 s``, as a rate loop's deadlines), each taken at
the first physics step at or after its grid point."""
_RESERVED_PREFIX = "/evclock/"

_NUMBER = {"type": "number"}

_CLOCK_SCHEMA = object_schema(
    "evclock.Clock",
    {
        "sim_time_s": _NUMBER,
        "wall_time_s": _NUMBER,
        "achieved_rtf": {"type": ["number", "null"]},
    },
)
_TICK_SCHEMA = object_schema(
    "evclock.Tick",
    {"loop": {"type": "string"}, "lateness_s": _NUMBER, "missed": {"type": "integer"}},
)
_VECTOR_STATE_SCHEMA = object_schema(
    "evclock.State", {"state": {"type": "array", "items": _NUMBER}}
)
_JUMP_SCHEMA = object_schema(
    "evclock.Jump",
    {"before_s": _NUMBER, "after_s": _NUMBER, "delta_s": _NUMBER},
)

_ACTIVE: contextvars.ContextVar[Recorder | None] = contextvars.ContextVar(
    "evclock_recorder", default=None
)
_LIVE_ADDRESS: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "evclock_foxglove_address", default=None
)


def mcap_writer_class() -> Any:
    """``mcap.writer.Writer``, or a clear error naming the extra to install.

    :returns: the writer class.
    :raises MissingExtraError: the mcap package is not installed.
    """
    try:
        from mcap.writer import Writer
    except ImportError:
        raise MissingExtraError(
            "recording needs the mcap package: pip install 'evclock[record]'"
        ) from None
    return Writer


def record(topic: str, message: Any, *, message_type: type[Any] | None = None) -> None:
    """Write ``message`` on channel ``topic`` of the current recording (and live view).

    Stamped with the current sim time. Outside a recorded run (``--record``, ``--foxglove``)
    there is no recording and the call does nothing, so controllers can log unconditionally.
    The channel's JSON Schema names each field and its type: from the message's dataclass,
    from ``message_type`` (a dataclass or TypedDict), else inferred from the first message.

    :param topic: the channel's name (not under ``/evclock/``).
    :param message: a JSON-serialisable mapping, or a dataclass instance.
    :param message_type: the dataclass or TypedDict the messages of ``topic`` follow.
    :raises InvalidTypeError: ``topic`` is not a non-empty str, ``message`` is neither a
        mapping nor a dataclass instance, or it cannot be written as JSON.
    :raises InvalidArgumentError: ``topic`` is reserved for evclock's own channels.

    Example::

        @dataclasses.dataclass
        class Error:
            error_m: float

        evclock.tools.record("/arm/error", Error(0.01))
    """
    if not isinstance(topic, str) or not topic:
        raise InvalidTypeError(f"record() needs a topic name (a non-empty str), got {topic!r}")
    if topic.startswith(_RESERVED_PREFIX):
        raise InvalidArgumentError(
            f"topic {topic!r} is reserved for evclock's own channels; pick another name"
        )
    if dataclasses.is_dataclass(message) and not isinstance(message, type):
        message_type = message_type or type(message)
        message = dataclasses.asdict(message)
    if not isinstance(message, Mapping):
        raise InvalidTypeError(
            "record() needs a mapping (a JSON object) or a dataclass instance as message, "
            f"got {type(message).__name__}"
        )
    recorder = _ACTIVE.get()
    if recorder is not None:
        recorder.write_user(topic, message, message_type)


@contextlib.contextmanager
def live_view(address: str | None) -> Iterator[None]:
    """Serve the runs started inside this block live to Foxglove at ``address``
    (``HOST:PORT``; None: no live view). ``evclock run --foxglove`` uses it.

    :param address: where to serve, or None.
    :returns: a context manager.
    """
    token = _LIVE_ADDRESS.set(address)
    try:
        yield
    finally:
        _LIVE_ADDRESS.reset(token)


def run_metadata(
    cls: type[Any], seed: int, params: Mapping[str, Any], until_s: float
) -> dict[str, Any]:
    """The ``evclock.run`` metadata of a recording: scenario, class, seed, parameters, the
    sim-time limit and the evclock version.

    :param cls: the scenario class.
    :param seed: the run's seed.
    :param params: the parameters set.
    :param until_s: the sim-time limit.
    :returns: the metadata values (JSON-serialisable).
    """
    from importlib.metadata import version

    return {
        "scenario": cls.name,
        "seed": seed,
        "params": dict(params),
        "until_s": until_s,
        "class": cls.__qualname__,
        "evclock_version": version("evclock"),
    }


def open_recorder(
    path: Path | None,
    cls: type[Any],
    seed: int,
    params: Mapping[str, Any],
    until_s: float,
    *,
    mode: str = "sim",
    world: Any = None,
) -> Recorder | None:
    """The recorder of a run: to ``path`` and/or live (inside :func:`live_view`), or None.

    :param path: the MCAP file to write, or None.
    :param cls: the scenario class.
    :param seed: the run's seed.
    :param params: the parameters set.
    :param until_s: the sim-time limit.
    :param mode: ``"sim"`` or ``"wall"`` (the timeline of the recording).
    :param world: the world to read (see :meth:`Recorder.attach`), built already: its
        channels are served live from the start (a viewer connecting at any time is told
        of the scene, and sent it when it subscribes).
    :returns: a :class:`Recorder`, or None when there is nothing to record to.
    :raises MissingExtraError: the record extra is not installed.
    """
    address = _LIVE_ADDRESS.get()
    if path is None and address is None:
        return None
    metadata = {**run_metadata(cls, seed, params, until_s), "time": mode}
    reader = None if world is None else world_reader(world)
    live: LiveView | None = None
    if address is not None:
        from evclock.tools._foxglove import LiveView
        from evclock.tools._scenarios import parameters

        live = LiveView(
            address,
            f"evclock {cls.name}",
            {"seed": seed, **parameters(cls)},  # ``cls`` has ``params`` applied
            until_ns=round(until_s * 1e9) if mode == "sim" else None,
            channels={
                topic: (schema, _metadata(topic))
                for topic, schema in _known_channels(reader is not None).items()
            },
        )
        _announce(live)
    try:
        return Recorder(path, metadata, live=live, world=reader)
    except BaseException:
        if live is not None:
            live.close()
        raise


def _metadata(topic: str) -> dict[str, str]:
    return {"deterministic": "false" if topic in WALL_TIME_TOPICS else "true"}


def _known_channels(world: bool) -> dict[str, Mapping[str, Any]]:
    """The channels a run writes at its first sample whose schemas are known before it:
    the clock's and, with a world read by name, its joints, transforms and scene."""
    from evclock.tools._foxglove import (
        FRAME_TRANSFORMS_SCHEMA,
        JOINT_STATES_SCHEMA,
        SCENE_UPDATE_SCHEMA,
    )

    known: dict[str, Mapping[str, Any]] = {"/evclock/clock": _CLOCK_SCHEMA}
    if world:
        known["/evclock/joints"] = JOINT_STATES_SCHEMA
        known["/evclock/transforms"] = FRAME_TRANSFORMS_SCHEMA
        known["/evclock/scene"] = SCENE_UPDATE_SCHEMA
    return known


def _announce(live: LiveView) -> None:
    import sys

    print(
        f"foxglove: live view at {live.url} (open it in Foxglove: Open connection > "
        "Foxglove WebSocket)",
        file=sys.stderr,
        flush=True,
    )


@dataclasses.dataclass
class _Channel:
    schema: Mapping[str, Any]
    metadata: dict[str, str]
    id: int | None  # in the file


class Recorder:
    """Writes one run's channels to an MCAP file and/or a live view; see the module
    docstring.

    :param path: the MCAP file to write, or None (live view only).
    :param metadata: the ``evclock.run`` metadata (see :func:`run_metadata`).
    :param live: a :class:`~evclock.tools._foxglove.LiveView` to serve the channels on.
    :param world: the reader of the world, when known before :meth:`attach`.
    :raises MissingExtraError: the mcap package is not installed.
    """

    def __init__(
        self,
        path: Path | None,
        metadata: Mapping[str, Any],
        *,
        live: LiveView | None = None,
        world: World | MuJoCoWorldReader | None = None,
    ) -> None:
        self.path = path
        self._live = live
        self._file: IO[bytes] | None = None
        self._writer: Any = None
        if path is not None:
            writer_class = mcap_writer_class()
            self._file = path.open("wb")
            self._writer = writer_class(self._file)
            self._writer.start(profile=PROFILE, library="evclock")
            self._writer.add_metadata("evclock.format", {"version": str(FORMAT_VERSION)})
            self._writer.add_metadata(
                "evclock.run", {k: json.dumps(v) for k, v in metadata.items()}
            )
        self._channels: dict[str, _Channel] = {}
        self._schemas: dict[str, int] = {}  # schema JSON -> id in the file
        self._sequence = 0
        self._clock: Clock | None = None
        self._state: Callable[[], list[float]] | None = None
        self._world = world
        self._scene_sent = False
        self._log_handler: logging.Handler | None = None
        self._hooks: list[Any] = []  # the step hook and jump handler attach() registered
        self._seen: dict[str, tuple[int, int]] = {}  # loop name -> (ticks, missed) recorded
        from evclock.kernel._rate import DeadlineGrid

        self._samples = DeadlineGrid(round(SAMPLE_PERIOD_S * 1e9))
        self._wall0 = time.perf_counter()
        self._last_sample = (0, self._wall0)
        self._closed = False

    def _channel(self, topic: str, schema: Mapping[str, Any]) -> _Channel:
        channel = self._channels.get(topic)
        if channel is None:
            channel = _Channel(schema, _metadata(topic), None)
            if self._writer is not None:
                data = json.dumps(schema).encode()
                key = data.decode()
                schema_id = self._schemas.get(key)
                if schema_id is None:
                    schema_id = self._writer.register_schema(
                        str(schema["title"]), "jsonschema", data
                    )
                    self._schemas[key] = schema_id
                channel.id = self._writer.register_channel(
                    topic, "json", schema_id, channel.metadata
                )
            self._channels[topic] = channel
        return channel

    def _write(self, topic: str, schema: Mapping[str, Any], time_ns: int, data: object) -> None:
        if self._closed:
            return
        channel = self._channel(topic, schema)
        payload = json.dumps(data, allow_nan=True).encode()
        if channel.id is not None:
            self._writer.add_message(channel.id, time_ns, payload, time_ns, self._sequence)
        if self._live is not None:
            self._live.log(topic, channel.schema, channel.metadata, time_ns, payload)
        self._sequence += 1

    def write_user(
        self, topic: str, message: Mapping[str, Any], message_type: type[Any] | None = None
    ) -> None:
        """A user message at the current sim time (see :func:`record`).

        :param topic: the channel.
        :param message: the message (a JSON object).
        :param message_type: the dataclass or TypedDict it follows, if known.
        :raises InvalidArgumentError: called before the run started.
        :raises InvalidTypeError: the message cannot be written as JSON.
        """
        from evclock.tools._foxglove import schema_of_message, schema_of_type

        if self._clock is None:
            raise InvalidArgumentError("record() was called before the run started")
        try:
            data = dict(message)
            json.dumps(data)
        except (TypeError, ValueError) as exc:
            raise InvalidTypeError(
                f"record({topic!r}, ...) needs a JSON-serialisable message: {exc}"
            ) from None
        if topic not in self._channels:
            title = topic.strip("/").replace("/", ".") or "message"
            schema = (
                schema_of_type(message_type, title)
                if message_type is not None
                else schema_of_message(data, title)
            )
            self._channel(topic, schema)
        self._write(topic, self._channels[topic].schema, self._clock.now_ns(), data)

    def attach(
        self,
        source: SteppingTimeSource[Any] | None,
        clk: Clock,
        state: Callable[[], list[float]],
        *,
        world: Any = None,
    ) -> contextvars.Token[Recorder | None]:
        """Start observing: a step hook on ``source``, a jump handler on ``clk``, a
        :mod:`logging` handler for the controllers' logs.

        Call from the running program (the returned token resets :func:`record`'s target).
        Without a ``source`` (wall time), the caller calls :meth:`observe` after each
        physics step.

        :param source: the time source stepping the run (PyBullet's or MuJoCo's), or None.
        :param clk: the run's clock (its time stamps every message).
        :param state: the scenario's state vector (recorded when the world cannot be read
            by name).
        :param world: the world to read: a PyBullet client id, or anything with a MuJoCo
            ``model`` and ``data`` (default: the one given to :func:`open_recorder`, else the
            source's, see :func:`world_of`).
        :returns: the token of :func:`record`'s target.
        """
        from evclock.tools._foxglove import logging_handler

        self._clock = clk
        self._state = state
        if world is not None:
            self._world = world_reader(world)
        elif self._world is None and source is not None:
            self._world = world_reader(world_of(source))
        self._samples.start(clk.now_ns())
        self._last_sample = (clk.now_ns(), time.perf_counter())
        if source is not None:
            self._hooks.append(source.add_step_hook(self.observe, when="before"))
        self._hooks.append(clk.on_jump(post=self._jumped))
        if self._live is not None and source is not None:  # a sim-time run: it can pause
            import asyncio

            self._live.control(asyncio.get_running_loop())
        self._log_handler = logging_handler(self._logged)
        logging.getLogger().addHandler(self._log_handler)
        return _ACTIVE.set(self)

    def _logged(self, log: logging.LogRecord) -> None:
        from evclock.tools._foxglove import LOG_SCHEMA, log_message

        if self._clock is not None:
            now = self._clock.now_ns()
            self._write("/evclock/log", LOG_SCHEMA, now, log_message(log, now))

    def _jumped(self, jump: TimeJump) -> None:
        self._write(
            "/evclock/jump",
            _JUMP_SCHEMA,
            jump.after.nanoseconds,
            {
                "before_s": jump.before.seconds,
                "after_s": jump.after.seconds,
                "delta_s": jump.delta.seconds,
            },
        )
        self._samples.start(jump.after.nanoseconds)

    def observe(self) -> None:
        """Record the ticks since the last call and, when due, a sample of the clock, the
        state, the joints and the link poses.

        Runs before each physics step: every task has finished its work at the current time.
        """
        assert self._clock is not None
        assert self._state is not None
        now = self._clock.now_ns()
        for rate in self._clock.rates:
            stats = rate.stats
            ticks, missed = self._seen.get(rate.name, (0, 0))
            new = stats.ticks - ticks
            if new > 0:
                recent = list(stats.recent_lateness_ns)[-new:]
                extra_missed = stats.missed - missed
                for i, lateness in enumerate(recent):
                    self._write(
                        f"/evclock/loop/{rate.name}",
                        _TICK_SCHEMA,
                        now,
                        {
                            "loop": rate.name,
                            "lateness_s": lateness / 1e9,
                            "missed": extra_missed if i == 0 else 0,
                        },
                    )
                self._seen[rate.name] = (stats.ticks, stats.missed)
        samples = self._samples
        if now >= samples.next_ns:
            samples.serve(now)
            self._sample(now)

    def _sample(self, now: int) -> None:
        from evclock.tools._foxglove import (
            FRAME_TRANSFORMS_SCHEMA,
            JOINT_STATES_SCHEMA,
            SCENE_UPDATE_SCHEMA,
            schema_of_message,
        )

        assert self._state is not None
        wall = time.perf_counter()
        sim0, wall0 = self._last_sample
        rtf = (now - sim0) / 1e9 / (wall - wall0) if wall > wall0 and now > sim0 else None
        self._last_sample = (now, wall)
        self._write(
            "/evclock/clock",
            _CLOCK_SCHEMA,
            now,
            {
                "sim_time_s": now / 1e9,
                "wall_time_s": wall - self._wall0,
                "achieved_rtf": rtf if rtf is None or math.isfinite(rtf) else None,
            },
        )
        world = self._world
        if world is None:
            self._write("/evclock/state", _VECTOR_STATE_SCHEMA, now, {"state": self._state()})
        else:
            state = world.state()
            schema = (
                self._channels["/evclock/state"].schema
                if "/evclock/state" in self._channels
                else schema_of_message(state, "evclock.State")
            )
            self._write("/evclock/state", schema, now, state)
            self._write("/evclock/joints", JOINT_STATES_SCHEMA, now, world.joint_states(now))
            self._write("/evclock/transforms", FRAME_TRANSFORMS_SCHEMA, now, world.transforms(now))
            if not self._scene_sent:  # once: the live view sends it to later subscribers
                self._scene_sent = True
                self._write("/evclock/scene", SCENE_UPDATE_SCHEMA, now, world.scene(now))
        if self._live is not None:
            self._live.tick(now)

    def close(self, outcome: Mapping[str, Any] | None = None) -> None:
        """Write the run's outcome as metadata (when given) and finish the file.

        :param outcome: the run's verdict and summary, or None.
        """
        if self._closed:
            return
        try:
            for hook in self._hooks:  # a closed recorder observes nothing more
                hook.remove()
            self._hooks.clear()
            if self._log_handler is not None:
                logging.getLogger().removeHandler(self._log_handler)
            if self._writer is not None:
                if outcome is not None:
                    self._writer.add_metadata(
                        "evclock.outcome", {k: json.dumps(v) for k, v in outcome.items()}
                    )
                self._writer.finish()
        finally:
            self._closed = True
            if self._file is not None:
                self._file.close()
            if self._live is not None:
                self._live.close()


def foxglove_option(
    enabled: bool,
    address: str,
    rtf: float | None,
    *,
    serve: str | None = None,
) -> tuple[contextlib.AbstractContextManager[None], float | None]:
    """What ``evclock run --foxglove [--foxglove-addr ADDR]`` asks for, checked before the
    run: the block to run in (:func:`live_view`) and the pace (real time unless a
    real-time factor was given: a live view at full speed would be over before it is seen).

    :param enabled: whether ``--foxglove`` was given.
    :param address: ``--foxglove-addr`` (``HOST:PORT``).
    :param rtf: the requested real-time factor (None: as fast as possible).
    :param serve: ``--serve``'s address, if given (the simulation serves the live view).
    :returns: the context manager to run in, and the real-time factor to run at.
    :raises InvalidArgumentError: a malformed address.
    :raises MissingExtraError: foxglove-sdk is not installed (``evclock[record]``).
    """
    if not enabled:
        return contextlib.nullcontext(), rtf
    from evclock._extras import import_extra
    from evclock.tools._foxglove import parse_address

    del serve  # the simulation serves the live view, wherever the controllers run
    parse_address(address)
    import_extra("foxglove", "record", needed_by="evclock run --foxglove")
    return live_view(address), 1.0 if rtf is None else rtf


def world_of(source: Any) -> Any:
    """The world a stepping source steps: PyBullet's client id, or MuJoCo's source itself
    (it has the ``model`` and ``data``)."""
    return getattr(source, "client", source)


def world_reader(world: Any) -> World | MuJoCoWorldReader | None:
    """The reader of ``world``: a PyBullet client id, or an object with a MuJoCo ``model`` and
    ``data`` (a MuJoCo source, an ``evclock_sims.MuJoCoWorld``); None when it is neither (then
    the recorder records the scenario's state vector)."""
    if isinstance(world, int) and not isinstance(world, bool):
        from evclock._extras import import_extra
        from evclock.tools._foxglove import World

        pybullet = import_extra("pybullet", "pybullet", needed_by="reading a PyBullet world")
        return World(world, pybullet)
    model, data = getattr(world, "model", None), getattr(world, "data", None)
    if model is not None and data is not None:
        from evclock.tools._world_mujoco import MuJoCoWorldReader

        return MuJoCoWorldReader(model, data)
    return None
