"""Reading evclock recordings back, and the first divergence of two of them (``trace diff``).

Two runs of the same program and seed write the same messages on every deterministic channel
(everything except the wall-time channel ``/evclock/clock``), in the same order, with the same
sim-time stamps, bit for bit. :func:`first_divergence` walks both recordings in step and names
the first message that differs: when, on which channel, and which field.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from evclock._errors import MissingExtraError, TraceError
from evclock.tools._record import PROFILE


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
    """

    path: Path
    metadata: dict[str, dict[str, Any]]
    messages: list[TraceMessage]

    def topic(self, name: str) -> list[TraceMessage]:
        """The messages of channel ``name``."""
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
            messages = [
                TraceMessage(
                    channel.topic,
                    message.log_time,
                    json.loads(message.data),
                    channel.metadata.get("deterministic") == "true",
                )
                for _schema, channel, message in reader.iter_messages(log_time_order=False)
            ]
    except (McapError, ValueError, EOFError) as exc:
        if isinstance(exc, TraceError):
            raise
        raise TraceError(f"cannot read {str(path)!r} as an MCAP recording: {exc}") from None
    return Trace(path, metadata, messages)


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
