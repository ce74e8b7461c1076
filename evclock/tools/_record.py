"""Recording a run to an MCAP file (``evclock run ... --record run.mcap``).

Every channel carries JSON messages described by a JSON Schema (the encodings Foxglove
documents for MCAP), stamped with the sim time in nanoseconds (``log_time`` and
``publish_time``):

- ``/evclock/clock``: sim time, wall time since the start and the achieved real-time factor
  over the last window. Wall-time dependent, so ``trace diff`` skips it.
- ``/evclock/loop/<name>``: one message per tick of each rate loop: its lateness and the
  periods it missed.
- ``/evclock/state``: the scenario's full physical state vector, sampled periodically.
- ``/evclock/jump``: every time jump (reset, restored snapshot).
- any user channel a controller writes with :func:`evclock.tools.record`.

The recorder observes the run from a PyBullet step hook (run before each step, when all the
work at the current time is done), so it adds no task or timer to the program: a recorded run
has the same trajectory as an unrecorded one.
"""

from __future__ import annotations

import contextvars
import json
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from evclock._errors import InvalidArgumentError, InvalidTypeError, MissingExtraError

if TYPE_CHECKING:
    from evclock.kernel._clock import Clock
    from evclock.kernel._jumps import TimeJump
    from evclock.sources import PyBulletTimeSource

PROFILE = "evclock"
"""The MCAP profile of evclock recordings."""
WALL_TIME_TOPICS = frozenset({"/evclock/clock"})
"""Channels whose content depends on wall time: ``trace diff`` does not compare them."""
SAMPLE_PERIOD_S = 0.05
"""Sim seconds between two ``/evclock/clock`` and ``/evclock/state`` samples."""
_RESERVED_PREFIX = "/evclock/"

_CLOCK_SCHEMA = {
    "type": "object",
    "title": "evclock.Clock",
    "properties": {
        "sim_time_s": {"type": "number"},
        "wall_time_s": {"type": "number"},
        "achieved_rtf": {"type": ["number", "null"]},
    },
}
_TICK_SCHEMA = {
    "type": "object",
    "title": "evclock.Tick",
    "properties": {
        "loop": {"type": "string"},
        "lateness_s": {"type": "number"},
        "missed": {"type": "integer"},
    },
}
_STATE_SCHEMA = {
    "type": "object",
    "title": "evclock.State",
    "properties": {"state": {"type": "array", "items": {"type": "number"}}},
}
_JUMP_SCHEMA = {
    "type": "object",
    "title": "evclock.Jump",
    "properties": {
        "before_s": {"type": "number"},
        "after_s": {"type": "number"},
        "delta_s": {"type": "number"},
    },
}
_USER_SCHEMA = {"type": "object", "title": "evclock.UserMessage"}

_ACTIVE: contextvars.ContextVar[Recorder | None] = contextvars.ContextVar(
    "evclock_recorder", default=None
)


def mcap_writer_class() -> Any:
    """``mcap.writer.Writer``, or a clear error naming the extra to install."""
    try:
        from mcap.writer import Writer
    except ImportError:
        raise MissingExtraError(
            "recording needs the mcap package: pip install 'evclock[record]'"
        ) from None
    return Writer


def record(topic: str, message: Mapping[str, Any]) -> None:
    """Write ``message`` (JSON-serialisable) on channel ``topic`` of the current recording.

    Stamped with the current sim time. Outside a recorded run (``--record``) there is no
    recording and the call does nothing, so controllers can log unconditionally.
    """
    if not isinstance(topic, str) or not topic:
        raise InvalidTypeError(f"record() needs a topic name (a non-empty str), got {topic!r}")
    if topic.startswith(_RESERVED_PREFIX):
        raise InvalidArgumentError(
            f"topic {topic!r} is reserved for evclock's own channels; pick another name"
        )
    if not isinstance(message, Mapping):
        raise InvalidTypeError(
            f"record() needs a mapping (a JSON object) as message, got {type(message).__name__}"
        )
    recorder = _ACTIVE.get()
    if recorder is not None:
        recorder.write_user(topic, message)


class Recorder:
    """Writes one run's channels to an MCAP file; see the module docstring."""

    def __init__(self, path: Path, metadata: Mapping[str, Any]) -> None:
        writer_class = mcap_writer_class()
        self.path = path
        self._file: IO[bytes] = path.open("wb")
        self._writer = writer_class(self._file)
        self._writer.start(profile=PROFILE, library="evclock")
        self._writer.add_metadata("evclock.run", {k: json.dumps(v) for k, v in metadata.items()})
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence = 0
        self._clock: Clock | None = None
        self._state: Callable[[], list[float]] | None = None
        self._seen: dict[str, tuple[int, int]] = {}  # loop name -> (ticks, missed) recorded
        self._next_sample_ns = 0
        self._sample_ns = round(SAMPLE_PERIOD_S * 1e9)
        self._wall0 = time.perf_counter()
        self._last_sample = (0, self._wall0)
        self._closed = False

    def _channel(self, topic: str, schema: Mapping[str, Any]) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            title = str(schema["title"])
            schema_id = self._schemas.get(title)
            if schema_id is None:
                data = json.dumps(schema).encode()
                schema_id = self._writer.register_schema(title, "jsonschema", data)
                self._schemas[title] = schema_id
            deterministic = "false" if topic in WALL_TIME_TOPICS else "true"
            channel = self._writer.register_channel(
                topic, "json", schema_id, {"deterministic": deterministic}
            )
            self._channels[topic] = channel
        return channel

    def _write(self, topic: str, schema: Mapping[str, Any], time_ns: int, data: object) -> None:
        if self._closed:
            return
        channel = self._channel(topic, schema)
        payload = json.dumps(data, allow_nan=True).encode()
        self._writer.add_message(channel, time_ns, payload, time_ns, self._sequence)
        self._sequence += 1

    def write_user(self, topic: str, message: Mapping[str, Any]) -> None:
        """A user message at the current sim time (see :func:`record`)."""
        if self._clock is None:
            raise InvalidArgumentError("record() was called before the run started")
        try:
            data = dict(message)
            json.dumps(data)
        except (TypeError, ValueError) as exc:
            raise InvalidTypeError(
                f"record({topic!r}, ...) needs a JSON-serialisable message: {exc}"
            ) from None
        self._write(topic, _USER_SCHEMA, self._clock.now_ns(), data)

    def attach(
        self,
        source: PyBulletTimeSource,
        clk: Clock,
        state: Callable[[], list[float]],
    ) -> contextvars.Token[Recorder | None]:
        """Start observing: a step hook on ``source``, a jump handler on ``clk``.

        Call from the running program (the returned token resets :func:`record`'s target).
        """
        self._clock = clk
        self._state = state
        self._next_sample_ns = clk.now_ns()
        self._last_sample = (clk.now_ns(), time.perf_counter())
        source.add_step_hook(self.observe, when="before")
        clk.on_jump(post=self._jumped)
        return _ACTIVE.set(self)

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
        self._next_sample_ns = jump.after.nanoseconds

    def observe(self) -> None:
        """Record the ticks since the last call and, when due, a clock and state sample.

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
        if now >= self._next_sample_ns:
            self._next_sample_ns = now + self._sample_ns
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
            self._write("/evclock/state", _STATE_SCHEMA, now, {"state": self._state()})

    def close(self, outcome: Mapping[str, Any] | None = None) -> None:
        """Write the run's outcome as metadata (when given) and finish the file."""
        if self._closed:
            return
        try:
            if outcome is not None:
                self._writer.add_metadata(
                    "evclock.outcome", {k: json.dumps(v) for k, v in outcome.items()}
                )
            self._writer.finish()
        finally:
            self._closed = True
            self._file.close()
