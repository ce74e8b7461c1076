"""Stamp diagnostics: how old messages are when they are used, and consumers falling behind.

A :class:`StampDiagnostics` is told about each message (``observe(stream, stamp)``) and about
the depth of consumers' queues (``observe_queue(consumer, depth)``). It keeps per-stream age
statistics (age = the clock's now minus the stamp) and raises a :class:`StampWarning` through
its ``on_warning`` hook (default: the ``evclock.stamps`` logger) when

* a stamp is older than ``stale_after`` (``"stale"``: a frozen driver, a stuck pipeline);
* a stamp is ahead of the clock by more than ``future_tolerance`` (``"future"``: a sensor
  stamping with another clock - a wall stamp on sim time is ~1.7e9 s in the future);
* a consumer's queue holds more than ``max_queue`` items (``"behind"``: it cannot keep up).

Each condition warns once when it starts and again only after it has cleared, so a stuck
stream does not flood the log; every occurrence is counted. Diagnostics used on a running
loop are listed by :func:`diagnostics_report` (the latest one of each name, while it is
alive), which ``evclock run`` shows in its report.
"""

from __future__ import annotations

import asyncio
import logging
import math
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.data._stamped import StampClock, check_stamp_clock
from evclock.hosts._current import clock as running_clock
from evclock.time._time import Duration, Time, new_duration, to_nonnegative_nanoseconds

__all__ = [
    "StampDiagnostics",
    "StampWarning",
    "StreamAgeStats",
    "diagnostics_report",
]

_logger = logging.getLogger("evclock.stamps")

WarningKind = Literal["stale", "future", "behind"]

# Loop -> name -> diagnostics, all weak: a diagnostics object holds its clock, which holds
# the loop, so strong values would keep every loop that ever used one alive.
_registry: weakref.WeakKeyDictionary[
    asyncio.AbstractEventLoop, weakref.WeakValueDictionary[str, StampDiagnostics]
] = weakref.WeakKeyDictionary()


@dataclass(frozen=True, slots=True)
class StampWarning:
    """One diagnostic event: what happened, on which stream or consumer, and when.

    :ivar kind: ``"stale"``, ``"future"`` or ``"behind"`` (see :class:`StampDiagnostics`).
    :ivar stream: the stream (or consumer, for ``"behind"``) concerned.
    :ivar at: the clock's time when it was detected.
    :ivar message: a human-readable explanation with a hint.
    """

    kind: WarningKind
    """``"stale"``, ``"future"`` or ``"behind"`` (see :class:`StampDiagnostics`)."""
    stream: str
    """The stream (or consumer, for ``"behind"``) concerned."""
    at: Time
    """The clock's time when it was detected."""
    message: str
    """A human-readable explanation with a hint."""


@dataclass(slots=True)
class StreamAgeStats:
    """Age statistics of one stream's messages (age = clock now - stamp, at observation).

    :ivar count: messages observed.
    :ivar stale: messages older than ``stale_after``.
    :ivar future: messages stamped ahead of the clock by more than ``future_tolerance``.
    :ivar sum_ns: the sum of their ages, in nanoseconds (see :meth:`mean`).
    :ivar min_ns: the smallest age seen, in nanoseconds.
    :ivar max_ns: the largest age seen, in nanoseconds.
    :ivar last_stamp: the stamp of the latest message, or None before the first.
    """

    count: int = 0
    stale: int = 0
    """Messages older than ``stale_after``."""
    future: int = 0
    """Messages stamped ahead of the clock by more than ``future_tolerance``."""
    sum_ns: int = 0
    min_ns: int = 0
    max_ns: int = 0
    last_stamp: Time | None = None

    def mean(self) -> Duration:
        """Mean age (zero before the first message)."""
        return new_duration(self.sum_ns // self.count if self.count else 0)


class StampDiagnostics:
    """Per-stream message age statistics and warnings for stale, future and backed-up data.

    Args:
        name: how ``evclock run`` labels these diagnostics (the latest of each name is shown).
        clock: the clock ages are measured on; default ``evclock.clock()`` of the running loop
            at the first observation.
        stale_after: seconds or a :class:`Duration`: older stamps warn ``"stale"``
            (None: never).
        future_tolerance: seconds or a :class:`Duration` a stamp may be ahead of the clock
            before it warns ``"future"`` (default 0: a stamp can not be in the future of the
            clock that stamped it).
        max_queue: a consumer queue deeper than this warns ``"behind"`` (None: never).
        on_warning: called with each :class:`StampWarning` when a condition starts (default:
            log it as a warning on the ``evclock.stamps`` logger).
        window: how many recent ages per stream the percentiles are computed over.
    """

    def __init__(
        self,
        name: str = "stamps",
        *,
        clock: StampClock | None = None,
        stale_after: float | Duration | None = None,
        future_tolerance: float | Duration = 0,
        max_queue: int | None = None,
        on_warning: Callable[[StampWarning], object] | None = None,
        window: int = 1000,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise InvalidArgumentError(f"name must be a non-empty string, got {name!r}")
        if clock is not None:
            check_stamp_clock(clock)
        self.name = name
        self._clock = clock
        self._stale_ns = (
            None if stale_after is None else to_nonnegative_nanoseconds(stale_after, "stale_after")
        )
        self._future_ns = to_nonnegative_nanoseconds(future_tolerance, "future_tolerance")
        if max_queue is not None and (
            type(max_queue) is not int or max_queue < 1  # bool is not accepted either
        ):
            raise InvalidArgumentError(
                f"max_queue must be a positive int or None, got {max_queue!r}"
            )
        if type(window) is not int or window < 1:
            raise InvalidArgumentError(f"window must be a positive int, got {window!r}")
        if on_warning is not None and not callable(on_warning):
            raise InvalidTypeError(f"on_warning must be callable, got {type(on_warning).__name__}")
        self._max_queue = max_queue
        self._on_warning = on_warning
        self._window = window
        self._streams: dict[str, StreamAgeStats] = {}
        self._recent: dict[str, deque[int]] = {}
        self._queues: dict[str, list[int]] = {}  # consumer -> [depth, max depth, behind count]
        self._active: set[tuple[WarningKind, str]] = set()
        self.warnings: list[StampWarning] = []
        """Every warning raised so far, oldest first (at most 1000 kept)."""
        self._registered = False

    # -- clock and registry --

    def _now(self) -> Time:
        if self._clock is None:
            self._clock = running_clock()
        if not self._registered:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                loop = None
            if loop is not None:
                _registry.setdefault(loop, weakref.WeakValueDictionary())[self.name] = self
                self._registered = True
        return self._clock.now()

    @property
    def clock(self) -> StampClock | None:
        """The clock ages are measured on (None until the first observation if not given)."""
        return self._clock

    # -- observations --

    def observe(self, stream: str, stamp: Time) -> Duration:
        """Record a message of ``stream`` stamped ``stamp``; return its age (now - stamp).

        Raises:
            ClockMismatchError: ``stamp`` is of another clock domain than the clock.
        """
        if type(stamp) is not Time:
            raise InvalidTypeError(f"stamp must be an evclock.Time, got {type(stamp).__name__}")
        now = self._now()
        age = now - stamp  # ClockMismatchError for a stamp of another domain
        age_ns = age.nanoseconds
        stats = self._streams.get(stream)
        if stats is None:
            stats = self._streams[stream] = StreamAgeStats(min_ns=age_ns, max_ns=age_ns)
            self._recent[stream] = deque(maxlen=self._window)
        stats.count += 1
        stats.sum_ns += age_ns
        stats.min_ns = min(stats.min_ns, age_ns)
        stats.max_ns = max(stats.max_ns, age_ns)
        stats.last_stamp = stamp
        self._recent[stream].append(age_ns)
        stale = self._stale_ns is not None and age_ns > self._stale_ns
        future = -age_ns > self._future_ns
        stats.stale += stale
        stats.future += future
        self._condition(
            "stale",
            stream,
            stale,
            now,
            lambda: (
                f"stream {stream!r}: stamp {stamp} is {age.seconds:.6g} s old at {now} "
                f"(stale_after {self._stale_ns and self._stale_ns / 1e9:g} s): the producer may be "
                "stuck, or its stamps are taken long before publishing"
            ),
        )
        self._condition(
            "future",
            stream,
            future,
            now,
            lambda: (
                f"stream {stream!r}: stamp {stamp} is {-age.seconds:.6g} s ahead of the "
                f"clock ({now}): the producer stamps with another clock (a wall-clock stamp on "
                "sim time?); stamp with evclock.clock().now()"
            ),
        )
        return age

    def observe_queue(self, consumer: str, depth: int) -> None:
        """Record that ``consumer``'s queue now holds ``depth`` items."""
        if type(depth) is not int or depth < 0:
            raise InvalidArgumentError(f"depth must be a non-negative int, got {depth!r}")
        record = self._queues.setdefault(consumer, [0, 0, 0])
        record[0] = depth
        record[1] = max(record[1], depth)
        behind = self._max_queue is not None and depth > self._max_queue
        record[2] += behind
        if behind or ("behind", consumer) in self._active:
            self._condition(
                "behind",
                consumer,
                behind,
                self._now(),
                lambda: (
                    f"consumer {consumer!r} is falling behind: {depth} items queued "
                    f"(max_queue {self._max_queue}); it processes more slowly than data arrives"
                ),
            )

    def _condition(
        self, kind: WarningKind, stream: str, active: bool, now: Time, text: Callable[[], str]
    ) -> None:
        key = (kind, stream)
        if not active:
            self._active.discard(key)
            return
        if key in self._active:
            return
        self._active.add(key)
        warning = StampWarning(kind, stream, now, text())
        if len(self.warnings) < 1000:
            self.warnings.append(warning)
        if self._on_warning is None:
            _logger.warning("%s", warning.message)
        else:
            self._on_warning(warning)

    # -- results --

    def streams(self) -> dict[str, StreamAgeStats]:
        """Age statistics by stream, in the order the streams were first seen."""
        return dict(self._streams)

    def percentile(self, stream: str, q: float) -> Duration:
        """The ``q``-th percentile (0-100) of the stream's recent ages (last ``window``)."""
        recent = self._recent.get(stream)
        if recent is None:
            raise InvalidArgumentError(
                f"no message observed on stream {stream!r}; known: {list(self._streams)}"
            )
        if not (isinstance(q, int | float) and 0 <= q <= 100):
            raise InvalidArgumentError(f"q must be a number in [0, 100], got {q!r}")
        ordered = sorted(recent)
        return new_duration(ordered[math.ceil(q / 100 * (len(ordered) - 1))])

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers (seconds) for reports and JSON.

        ``queues`` gives per consumer the current and maximum depth and ``behind``, how many
        observations found it above ``max_queue``.
        """
        streams = {
            name: {
                "messages": s.count,
                "mean_age_s": s.mean().seconds,
                "p99_age_s": self.percentile(name, 99).seconds,
                "min_age_s": s.min_ns / 1e9,
                "max_age_s": s.max_ns / 1e9,
                "stale": s.stale,
                "future": s.future,
            }
            for name, s in self._streams.items()
        }
        queues = {
            name: {"depth": depth, "max_depth": peak, "behind": behind}
            for name, (depth, peak, behind) in self._queues.items()
        }
        return {
            "name": self.name,
            "streams": streams,
            "queues": queues,
            "warnings": [f"{w.kind}: {w.message}" for w in self.warnings],
        }


def diagnostics_report(loop: asyncio.AbstractEventLoop | None = None) -> list[dict[str, Any]]:
    """``as_dict()`` of every :class:`StampDiagnostics` used on ``loop`` (default: running).

    The latest diagnostics of each name still alive, in the order the names first appeared.

    :returns: one ``as_dict()`` per diagnostics, in that order.
    """
    if loop is None:
        loop = asyncio.get_running_loop()
    named = _registry.get(loop)
    return [] if named is None else [diag.as_dict() for diag in named.values()]


def render_diagnostics_report(reports: list[dict[str, Any]], console: Any) -> None:
    """Print stamp diagnostics as ``rich`` tables (used by ``evclock run``); nothing if none."""
    from rich.markup import escape  # names and warnings are text, never markup
    from rich.table import Table

    for report in reports:
        table = Table(title=escape(f"{report['name']}: stamp ages"))
        for column in ("stream", "msgs", "mean age ms", "p99 age ms", "max age ms", "stale"):
            table.add_column(column, justify="left" if column == "stream" else "right")
        table.add_column("future", justify="right")
        for stream, s in report["streams"].items():
            table.add_row(
                escape(stream),
                str(s["messages"]),
                _ms(s["mean_age_s"]),
                _ms(s["p99_age_s"]),
                _ms(s["max_age_s"]),
                str(s["stale"]),
                str(s["future"]),
            )
        console.print(table)
        if report["queues"]:
            queues = Table(title=escape(f"{report['name']}: consumer queues"))
            for column in ("consumer", "depth", "max depth", "above max_queue"):
                queues.add_column(column, justify="left" if column == "consumer" else "right")
            for consumer, q in report["queues"].items():
                queues.add_row(
                    escape(consumer), str(q["depth"]), str(q["max_depth"]), str(q["behind"])
                )
            console.print(queues)
        for line in report["warnings"]:
            console.print(f"[yellow]warning[/yellow] {escape(line)}")


def _ms(seconds: float) -> str:
    return "-" if not math.isfinite(seconds) else f"{seconds * 1e3:.3f}"
