"""Reading evclock recordings back: what they hold (``trace info``), their messages and fields
(``trace echo``, field plots), and the first divergence of two of them (``trace diff``).

Two runs of the same program and seed write the same messages on every deterministic channel
(everything except the wall-time channel ``/evclock/clock``), in the same order, with the same
sim-time stamps, bit for bit. :func:`first_divergence` walks both recordings in step and names
the first message that differs: when, on which channel, and which field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from evclock._errors import MissingExtraError, TraceError
from evclock.tools._record import FORMAT_VERSION, PROFILE


@dataclasses.dataclass(frozen=True)
class TraceMessage:
    """One recorded message: channel, sim-time stamp (ns) and decoded JSON content.

    :ivar topic: the channel it was recorded on.
    :ivar time_ns: its sim-time stamp, in integer nanoseconds.
    :ivar data: its content, decoded from JSON.
    :ivar deterministic: whether its channel is reproducible run to run (compared by
        ``evclock diff``).
    """

    topic: str
    time_ns: int
    data: Any
    deterministic: bool


@dataclasses.dataclass
class Trace:
    """A recording read back: its run metadata and messages in the order they were written.

    Made by :func:`read_trace`.

    :ivar path: the MCAP file it was read from.
    :ivar metadata: the recording's metadata records, by name (decoded JSON values).
    :ivar messages: every message, in the order it was written.
    :ivar schemas: each channel's schema name, by topic.
    """

    path: Path
    metadata: dict[str, dict[str, Any]]
    messages: list[TraceMessage]
    schemas: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def format_version(self) -> int:
        """The recording format version (1: written before evclock named its versions)."""
        return int(self.metadata.get("evclock.format", {}).get("version", 1))

    @property
    def timeline(self) -> str:
        """``"sim"`` (the stamps are sim time) or ``"wall"`` (a ``--wall`` run)."""
        return str(self.metadata.get("evclock.run", {}).get("time", "sim"))

    def topic(self, name: str) -> list[TraceMessage]:
        """The messages of channel ``name``.

        :param name: a channel's topic.
        :returns: its messages, in the order they were written.
        """
        return [m for m in self.messages if m.topic == name]

    @property
    def topics(self) -> list[str]:
        """Every channel, in order of first message."""
        return list(dict.fromkeys(m.topic for m in self.messages))


@dataclasses.dataclass(frozen=True)
class Divergence:
    """Where two recordings first differ.

    :ivar index: position among the deterministic messages.
    :ivar time_s: the sim time of the first difference in seconds, or None.
    :ivar topic: the channel that differs, or None when the channels themselves differ.
    :ivar detail: what differs, for people.
    """

    index: int
    """Position among the deterministic messages."""
    time_s: float | None
    topic: str | None
    detail: str

    def describe(self) -> str:
        """One line for people."""
        words = ["first divergence"]
        if self.time_s is not None:
            words.append(f"at sim time {self.time_s:.6f} s")
        if self.topic is not None:
            words.append(f"on {self.topic}")
        return " ".join(words) + f" (message {self.index}): {self.detail}"


def read_trace(path: Path) -> Trace:
    """Read an evclock MCAP recording (:class:`TraceError` if it is not one).

    :param path: the ``.mcap`` file written by ``evclock run ... --record``.
    :returns: the :class:`Trace`: its metadata and messages.
    :raises TraceError: no file at ``path``, or it is not a readable evclock recording.
    :raises MissingExtraError: the mcap package is missing (``pip install 'evclock[record]'``).

    Example::

        trace = read_trace(Path("run.mcap"))
        print(trace.topics)
    """
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
    except ImportError:
        raise MissingExtraError(
            "reading recordings needs the mcap package: pip install 'evclock[record]'"
        ) from None
    if not path.is_file():
        raise TraceError(f"no recording at {str(path)!r}")
    try:
        with path.open("rb") as stream:
            reader = make_reader(stream)
            header = reader.get_header()
            if header.profile != PROFILE:
                raise TraceError(
                    f"{str(path)!r} is an MCAP file but not an evclock recording "
                    f"(profile {header.profile!r}); record one with evclock run ... --record"
                )
            metadata = {
                record.name: {k: json.loads(v) for k, v in record.metadata.items()}
                for record in reader.iter_metadata()
            }
            _check_version(path, metadata)
            schemas: dict[str, str] = {}
            messages = []
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                schemas.setdefault(channel.topic, schema.name if schema else "")
                messages.append(
                    TraceMessage(
                        channel.topic,
                        message.log_time,
                        json.loads(message.data),
                        channel.metadata.get("deterministic") == "true",
                    )
                )
    except TraceError:
        raise
    except (McapError, ValueError, EOFError, OSError, KeyError, IndexError) as exc:
        raise TraceError(_unreadable(path, exc)) from None
    except Exception as exc:  # a decompressor's or a record parser's own error type
        raise TraceError(_unreadable(path, exc)) from None
    return Trace(path, metadata, messages, schemas)


def _unreadable(path: Path, exc: BaseException) -> str:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return (
        f"cannot read {str(path)!r} as an MCAP recording: {detail} (truncated or corrupt? "
        "a run that was killed leaves an unfinished file)"
    )


def _check_version(path: Path, metadata: dict[str, dict[str, Any]]) -> None:
    version = metadata.get("evclock.format", {}).get("version", 1)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        made_by = metadata.get("evclock.run", {}).get("evclock_version", "a newer evclock")
        raise TraceError(
            f"{str(path)!r} is an evclock recording of format version {version} (made by "
            f"evclock {made_by}); this evclock reads versions 1 to {FORMAT_VERSION}: upgrade "
            "evclock (pip install -U evclock)"
        )


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


def _field_difference(a: Any, b: Any, path: str = "") -> str:
    """The first differing field of two decoded messages, as ``path: a != b``."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in list(dict.fromkeys([*a, *b])):
            if key not in a or key not in b:
                return f"{path}{key}: only in {'b' if key not in a else 'a'}"
            if not _same(a[key], b[key]):
                return _field_difference(a[key], b[key], f"{path}{key}.")
    if isinstance(a, list) and isinstance(b, list):
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            if not _same(x, y):
                return _field_difference(x, y, f"{path.rstrip('.')}[{i}].")
        return f"{path.rstrip('.')}: {len(a)} items != {len(b)} items"
    return f"{path.rstrip('.')}: {a!r} != {b!r}"


def first_divergence(a: Trace, b: Trace) -> Divergence | None:
    """The first deterministic message that differs between ``a`` and ``b``, or None.

    :param a: a recording (see :func:`read_trace`).
    :param b: the recording to compare it with.
    :returns: where they first differ, or None when their deterministic messages agree.
    """
    left = [m for m in a.messages if m.deterministic]
    right = [m for m in b.messages if m.deterministic]
    for index, (x, y) in enumerate(zip(left, right, strict=False)):
        if x.topic != y.topic or x.time_ns != y.time_ns:
            return Divergence(
                index,
                min(x.time_ns, y.time_ns) / 1e9,
                None,
                f"a has {x.topic} at {x.time_ns / 1e9:.6f} s, "
                f"b has {y.topic} at {y.time_ns / 1e9:.6f} s",
            )
        if not _same(x.data, y.data):
            return Divergence(index, x.time_ns / 1e9, x.topic, _field_difference(x.data, y.data))
    if len(left) != len(right):
        shorter, longer = ("a", right) if len(left) < len(right) else ("b", left)
        nxt = longer[min(len(left), len(right))]
        return Divergence(
            min(len(left), len(right)),
            nxt.time_ns / 1e9,
            nxt.topic,
            f"{shorter} ends here; the other goes on",
        )
    return None


_PATH_PART = re.compile(r"\.?([^.\[\]]+)|\[([^\]]*)\]")


def parse_field_path(path: str) -> list[str | int]:
    """``a.b[2].c`` -> ``["a", "b", 2, "c"]``; ``joints[elbow]`` selects the item of a list
    whose ``name`` is ``elbow``.

    :param path: a field path (dots between names, ``[index]`` or ``[name]`` for lists).
    :returns: the path's parts.
    :raises TraceError: the path is empty or malformed.
    """
    parts: list[str | int] = []
    position = 0
    text = path.strip()
    while position < len(text):
        match = _PATH_PART.match(text, position)
        if match is None or match.end() == position:
            break
        name, index = match.groups()
        if name is not None:
            parts.append(name)
        elif index is not None and index.strip():
            item = index.strip()
            parts.append(int(item) if re.fullmatch(r"-?\d+", item) else item)
        else:
            break
        position = match.end()
    if not parts or position != len(text):
        raise TraceError(
            f"bad field path {path!r}: write names with dots, list items as [index] or "
            "[name] (e.g. joints[lbr_iiwa_joint_1].position)"
        )
    return parts


_MISSING = object()


def field_value(data: Any, parts: list[str | int]) -> Any:
    """The value at ``parts`` (see :func:`parse_field_path`) in a decoded message, or a
    sentinel when it has no such field (test with :func:`has_value`).

    :param data: a decoded message.
    :param parts: the path's parts.
    :returns: the value.
    """
    value = data
    for part in parts:
        if isinstance(part, int) and isinstance(value, list):
            if not -len(value) <= part < len(value):
                return _MISSING
            value = value[part]
        elif isinstance(value, list):
            named = [x for x in value if isinstance(x, dict) and x.get("name") == part]
            if not named:
                return _MISSING
            value = named[0]
        elif isinstance(value, dict) and str(part) in value:
            value = value[str(part)]
        else:
            return _MISSING
    return value


def missing_field(data: Any, parts: list[str | int]) -> str:
    """Why decoded message ``data`` has no field at ``parts``: where the path stops, and what
    exists there (the fields of an object, the items of a list).

    :param data: a decoded message.
    :param parts: the path's parts (see :func:`parse_field_path`).
    :returns: a clause for an error message.
    """
    value = data
    where = "the message"
    walked = ""
    for part in parts:
        if isinstance(value, list):
            names = [x["name"] for x in value if isinstance(x, dict) and "name" in x]
            if isinstance(part, int):
                if -len(value) <= part < len(value):
                    value, walked = value[part], f"{walked}[{part}]"
                    where = walked
                    continue
                return f"{where} has {len(value)} items ([0] to [{len(value) - 1}]), no [{part}]"
            named = [x for x in value if isinstance(x, dict) and x.get("name") == part]
            if named:
                value, walked = named[0], f"{walked}[{part}]"
                where = walked
                continue
            items = ", ".join(f"[{name}]" for name in names) or f"[0] to [{len(value) - 1}]"
            return f"{where} has no item [{part}]; its items: {items}"
        if isinstance(value, dict) and str(part) in value:
            value = value[str(part)]
            walked = f"{walked}.{part}" if walked else str(part)
            where = walked
            continue
        if isinstance(value, dict):
            return f"{where} has no field {part!r}; its fields: {', '.join(value) or 'none'}"
        return f"{where} is {_short(value, 60)}, which has no field {part!r}"
    return f"{where} exists"  # (not reached for a path field_value did not find)


def has_value(value: Any) -> bool:
    """Whether :func:`field_value` found a field.

    :param value: what :func:`field_value` returned.
    :returns: False for the missing-field sentinel.
    """
    return value is not _MISSING


def split_series(trace: Trace, series: str) -> tuple[str, str]:
    """``/topic.field.path`` -> (topic, field path): the longest recorded topic the text
    starts with, followed by ``.`` or ``[``.

    :param trace: the recording the topic is in.
    :param series: what the user wrote.
    :returns: the topic and the field path.
    :raises TraceError: no recorded topic starts the text, or no field follows it.
    """
    for topic in sorted(trace.topics, key=len, reverse=True):
        rest = series[len(topic) :]
        if series.startswith(topic) and rest[:1] in (".", "["):
            return topic, rest.removeprefix(".")
        if series == topic:
            raise TraceError(
                f"{series!r} names a topic but no field: write {topic}.FIELD "
                f"(fields: {', '.join(_fields(trace, topic)) or 'none'})"
            )
    raise TraceError(
        f"no topic of {str(trace.path)!r} starts {series!r}; its topics: "
        f"{', '.join(trace.topics) or 'none'} (write TOPIC.field, e.g. /evclock/clock.achieved_rtf)"
    )


def _fields(trace: Trace, topic: str) -> list[str]:
    messages = trace.topic(topic)
    return list(messages[0].data) if messages and isinstance(messages[0].data, dict) else []


def series_values(trace: Trace, series: str) -> tuple[list[float], list[float]]:
    """The numeric values of ``TOPIC.field`` over time (seconds).

    :param trace: a recording.
    :param series: ``TOPIC.field.path`` (see :func:`split_series`, :func:`parse_field_path`).
    :returns: the times (seconds of the recording's timeline) and the values; booleans
        count as 0 and 1, null as NaN.
    :raises TraceError: the topic or field is not in the recording, or the field is not a
        number.
    """
    topic, path = split_series(trace, series)
    parts = parse_field_path(path)
    times: list[float] = []
    values: list[float] = []
    for message in trace.topic(topic):
        value = field_value(message.data, parts)
        if not has_value(value):
            continue
        if value is None:
            value = math.nan
        if not isinstance(value, int | float):
            raise TraceError(
                f"{series} is not a number (at {message.time_ns / 1e9:.6f} s it is "
                f"{_short(value)}): plot a numeric field"
            )
        times.append(message.time_ns / 1e9)
        values.append(float(value))
    if not times:
        messages = trace.topic(topic)
        why = missing_field(messages[0].data, parts) if messages else "it has no message"
        raise TraceError(f"no message of {topic} has the field {path!r}: {why}")
    return times, values


def _short(value: Any, limit: int = 120) -> str:
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 20] + f"... ({len(text)} chars)"


def _abbreviated(value: Any) -> Any:
    """Long strings (embedded meshes) shown by their length, not their bytes."""
    if isinstance(value, str) and len(value) > 200:
        return f"<{len(value)} chars>"
    if isinstance(value, list):
        return [_abbreviated(x) for x in value]
    if isinstance(value, dict):
        return {k: _abbreviated(v) for k, v in value.items()}
    return value


def echo_lines(
    trace: Trace,
    topic: str,
    field: str | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
) -> Iterator[str]:
    """``trace echo``: one line per message of ``topic``: its time in seconds and its JSON
    content (or the value at ``field``), between ``start_s`` and ``end_s`` inclusive.

    :param trace: a recording.
    :param topic: one of its topics.
    :param field: a field path (see :func:`parse_field_path`), or None for the whole message.
    :param start_s: the first time to show (seconds), or None.
    :param end_s: the last time to show (seconds), or None.
    :returns: the lines, lazily.
    :raises TraceError: ``topic`` is not recorded, or ``field`` is malformed or in none of
        its messages (the message says what exists where the path stops).
    """
    if topic not in trace.topics:
        raise TraceError(
            f"no topic {topic!r} in {str(trace.path)!r}; its topics: "
            f"{', '.join(trace.topics) or 'none'}"
        )
    parts = parse_field_path(field) if field is not None else None
    messages = trace.topic(topic)
    if (
        parts is not None
        and messages
        and not any(has_value(field_value(m.data, parts)) for m in messages)
    ):
        raise TraceError(
            f"no message of {topic} has the field {field!r}: "
            f"{missing_field(messages[0].data, parts)}"
        )
    for message in messages:
        seconds = message.time_ns / 1e9
        if (start_s is not None and seconds < start_s) or (end_s is not None and seconds > end_s):
            continue
        value = message.data if parts is None else field_value(message.data, parts)
        shown = json.dumps(_abbreviated(value)) if has_value(value) else "(no such field)"
        yield f"{message.time_ns // 1_000_000_000}.{message.time_ns % 1_000_000_000:09d} {shown}"


def info_lines(trace: Trace) -> list[str]:
    """``trace info``: what a recording holds: the run (scenario, seed, parameters, evclock
    version, outcome), its duration and each topic with its schema and message count.

    :param trace: a recording.
    :returns: the lines to print.
    """
    run = trace.metadata.get("evclock.run", {})
    outcome = trace.metadata.get("evclock.outcome", {})
    lines = [f"recording: {trace.path} (evclock recording format {trace.format_version})"]
    if run:
        params = ", ".join(f"{k}={v}" for k, v in run.get("params", {}).items()) or "none"
        lines.append(f"scenario:  {run.get('scenario', '?')} ({run.get('class', '?')})")
        lines.append(f"seed:      {run.get('seed', '?')}")
        lines.append(f"params:    {params}")
        lines.append(f"evclock:   {run.get('evclock_version', 'unknown (format 1)')}")
    if outcome:
        lines.append(f"outcome:   {outcome.get('verdict', '?')}")
    stamps = [m.time_ns for m in trace.messages]
    clock = "wall" if trace.timeline == "wall" else "sim"
    if stamps:
        first, last = min(stamps), max(stamps)
        lines.append(
            f"duration:  {(last - first) / 1e9:.6f} s of {clock} time "
            f"({first / 1e9:.6f} s to {last / 1e9:.6f} s)"
        )
    else:
        lines.append("duration:  no message")
    lines.append(f"messages:  {len(trace.messages)}")
    counts: dict[str, int] = {}
    for message in trace.messages:
        counts[message.topic] = counts.get(message.topic, 0) + 1
    width = max((len(t) for t in counts), default=5)
    schema_width = max((len(trace.schemas.get(t, "")) for t in counts), default=6)
    lines.append(f"{'topic':<{width}}  {'schema':<{schema_width}}  messages")
    for topic in sorted(counts):
        lines.append(
            f"{topic:<{width}}  {trace.schemas.get(topic, ''):<{schema_width}}  {counts[topic]}"
        )
    return lines
