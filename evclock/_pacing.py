"""Pacing: how much wall time each advance of sim time takes; pause, resume and step."""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable

from ._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    LagError,
    PacingError,
)
from ._time import SIM, Time

#: How far behind its schedule a paced run may fall before it re-anchors instead of
#: bursting to catch up (seconds of wall time).
DEFAULT_MAX_LAG = 0.1


def check_rtf(rtf: object) -> float | None:
    """Validate a real-time factor: None (as fast as possible) or a positive finite number."""
    if rtf is None:
        return None
    if isinstance(rtf, bool) or not isinstance(rtf, int | float):
        raise InvalidTypeError(
            f"rtf must be None (as fast as possible) or a positive number, got {type(rtf).__name__}"
        )
    value = float(rtf)
    if not math.isfinite(value) or value <= 0:
        raise InvalidArgumentError(
            f"rtf must be a positive finite real-time factor (1.0 = real time), got {rtf!r}; "
            "use rtf=None to run as fast as possible"
        )
    return value


def check_max_lag(max_lag: object) -> float:
    """Validate a lag bound: a positive finite number of wall seconds."""
    if isinstance(max_lag, bool) or not isinstance(max_lag, int | float):
        raise InvalidTypeError(f"max_lag must be a number of seconds, got {type(max_lag).__name__}")
    if not math.isfinite(max_lag) or max_lag <= 0:
        raise InvalidArgumentError(f"max_lag must be a positive number of seconds, got {max_lag!r}")
    return float(max_lag)


class RtfMeter:
    """Measures the achieved real-time factor: sim seconds per wall second."""

    def __init__(self, window: float = 2.0, wall: Callable[[], float] = time.perf_counter) -> None:
        self._wall = wall
        self._window = window
        self._samples: collections.deque[tuple[float, int]] = collections.deque()
        self._first: tuple[float, int] | None = None

    def sample(self, sim_ns: int) -> None:
        """Record the pair (now, ``sim_ns``)."""
        now = self._wall()
        if self._first is None:
            self._first = (now, sim_ns)
        self._samples.append((now, sim_ns))
        while len(self._samples) > 2 and now - self._samples[0][0] > self._window:
            self._samples.popleft()

    def recent(self) -> float | None:
        """Achieved factor over the last window, or None before two samples."""
        if len(self._samples) < 2:
            return None
        (w0, s0), (w1, s1) = self._samples[0], self._samples[-1]
        return (s1 - s0) / 1e9 / (w1 - w0) if w1 > w0 else None

    def overall(self) -> float | None:
        """Achieved factor since the first sample."""
        if self._first is None or not self._samples:
            return None
        (w0, s0), (w1, s1) = self._first, self._samples[-1]
        return (s1 - s0) / 1e9 / (w1 - w0) if w1 > w0 else None


class Pacer:
    """Decides, before each increment of sim time, whether and when it may happen.

    The loop gives it two callables: ``wait(timeout)`` blocks up to ``timeout`` wall seconds
    while serving I/O and returns True if something became runnable at the current sim time
    (then the advance is abandoned, to be retried after that work ran); ``now_ns()`` reads
    sim time.
    """

    def __init__(
        self,
        wait: Callable[[float | None], bool],
        now_ns: Callable[[], int],
        *,
        rtf: float | None = None,
        strict: bool = False,
        max_lag: float = DEFAULT_MAX_LAG,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        if not (isinstance(max_lag, int | float) and math.isfinite(max_lag) and max_lag > 0):
            raise InvalidArgumentError(
                f"max_lag must be a positive number of seconds, got {max_lag!r}"
            )
        self._wait = wait
        self._now_ns = now_ns
        self._wall = wall
        self._rtf = check_rtf(rtf)
        self.strict = bool(strict)
        self.max_lag = check_max_lag(max_lag)
        self._anchor: tuple[float, int] | None = None
        self.paused = False
        self._step_budget = 0
        self._run_until_ns: int | None = None
        self.meter = RtfMeter(wall=wall)
        self.idle = True
        self._update_idle()

    @property
    def run_until_ns(self) -> int | None:
        """The target of a pending ``step_until()``, if any."""
        return self._run_until_ns

    @property
    def rtf(self) -> float | None:
        """Requested real-time factor; None means as fast as possible."""
        return self._rtf

    @rtf.setter
    def rtf(self, value: float | None) -> None:
        self._rtf = check_rtf(value)
        self._anchor = None
        self._update_idle()

    def _update_idle(self) -> None:
        #: True when advances need no pacing at all (the hot path skips the pacer).
        self.idle = self._rtf is None and not self.paused

    def reanchor(self) -> None:
        """Forget the pacing schedule (after a jump or an rtf change): pace from now on."""
        self._anchor = None

    def pause(self) -> None:
        self.paused = True
        self._step_budget = 0
        self._run_until_ns = None
        self._update_idle()

    def resume(self) -> None:
        self.paused = False
        self._step_budget = 0
        self._run_until_ns = None
        self._anchor = None
        self._update_idle()

    def step(self, count: int) -> None:
        if not self.paused:
            raise PacingError(self._not_paused("step()"))
        self._step_budget += count
        self._anchor = None  # pace the steps from the request, not from before the pause

    def run_until(self, sim_ns: int) -> None:
        if not self.paused:
            raise PacingError(self._not_paused("step_until()"))
        self._run_until_ns = sim_ns
        self._anchor = None

    def _not_paused(self, what: str) -> str:
        mode = "as fast as possible" if self._rtf is None else f"at rtf={self._rtf:g}"
        return (
            f"{what} needs a paused loop, but it is running {mode}; call pause() first, then step"
        )

    def allow(self, next_ns: int) -> bool:
        """May sim time move to ``next_ns`` now? Waits (serving I/O) as pacing requires.

        A control changed while waiting (pause, rtf, step - possibly from another thread,
        which wakes the wait) makes it decide again from the new settings.
        """
        while True:
            stepping = False
            while self.paused:
                if self._step_budget > 0:
                    stepping = True  # spent only once the pacing wait below is over
                    break
                if self._run_until_ns is not None and self._now_ns() < self._run_until_ns:
                    break
                if self._wait(None):
                    return False
            if self._rtf is not None:
                outcome = self._wait_for_pace(next_ns)
                if outcome == "work":
                    return False
                if outcome == "changed":
                    continue
            if stepping:
                self._step_budget -= 1
            return True

    def _controls(self) -> tuple[object, ...]:
        return (self._rtf, self.paused, self._step_budget, self._run_until_ns)

    def _wait_for_pace(self, next_ns: int) -> str:
        """Wait until ``next_ns`` is due at the requested rtf: "due", "work" (something
        became runnable first) or "changed" (a control changed meanwhile)."""
        assert self._rtf is not None
        wall = self._wall()
        if self._anchor is None:
            self._anchor = (wall, self._now_ns())
        wall0, sim0 = self._anchor
        due = wall0 + (next_ns - sim0) / 1e9 / self._rtf
        lag = wall - due
        if lag > self.max_lag:
            if self.strict:
                raise LagError(
                    f"the simulation lags {lag:.3f} s of wall time behind rtf={self._rtf:g} "
                    f"(strict limit {self.max_lag:g} s); lower the rtf, lighten the "
                    "controllers or pass strict=False to let it run as fast as it can"
                )
            # Re-anchor on now: never burst to catch up on lost time.
            now_ns = self._now_ns()
            self._anchor = (wall, now_ns)
            due = wall + (next_ns - now_ns) / 1e9 / self._rtf
        controls = self._controls()
        while (delay := due - self._wall()) > 0:
            if self._wait(delay):
                return "work"
            if self._controls() != controls:
                return "changed"
        return "due"


class PacingControls:
    """The pacing API shared by :class:`~evclock.SimEventLoop` and :class:`~evclock.SimDriver`:
    ``rtf``, ``paused``, ``achieved_rtf()``, ``pause()``, ``resume()``, ``step()`` and
    ``step_until()``. The host provides ``_pacer``, ``_now_ns``, ``_require_running()`` and
    reacts to changes in ``_pacing_changed()``."""

    _pacer: Pacer
    _now_ns: int

    def _require_running(self, what: str) -> None:
        raise NotImplementedError

    def _pacing_changed(self) -> None:
        """Called after every change of rtf, pause state or step budget."""

    def _stepping_until(self, when_ns: int) -> None:
        """Called after ``step_until(when)``; by default a plain pacing change."""
        self._pacing_changed()

    @property
    def rtf(self) -> float | None:
        """Requested real-time factor (None: as fast as possible). Settable while running."""
        return self._pacer.rtf

    @rtf.setter
    def rtf(self, value: float | None) -> None:
        self._pacer.rtf = value
        self._pacing_changed()

    @property
    def paused(self) -> bool:
        """Whether sim time is paused (work due at the current time still runs)."""
        return self._pacer.paused

    def achieved_rtf(self) -> float | None:
        """Real-time factor achieved over the last couple of wall seconds (None: not yet known).

        Each call records a sample: poll it periodically (a progress bar, a dashboard).
        """
        self._pacer.meter.sample(self._now_ns)
        return self._pacer.meter.recent()

    def pause(self) -> None:
        """Stop sim time from advancing; I/O keeps being served. Call from the loop's thread."""
        self._require_running("pause()")
        self._pacer.pause()
        self._pacing_changed()

    def resume(self) -> None:
        """Let sim time advance again at the requested rtf."""
        self._require_running("resume()")
        self._pacer.resume()
        self._pacing_changed()

    def step(self, count: int = 1) -> None:
        """While paused, let sim time advance ``count`` increments (physics steps, or jumps to
        the next deadline on virtual time), then stay paused."""
        self._require_running("step()")
        if isinstance(count, bool) or not isinstance(count, int):
            raise InvalidTypeError(f"step() count must be an int, got {type(count).__name__}")
        if count < 1:
            raise InvalidArgumentError(f"step() count must be >= 1, got {count}")
        self._pacer.step(count)
        self._pacing_changed()

    def step_until(self, when: Time) -> None:
        """While paused, let sim time advance until it reaches ``when``, then stay paused.

        Virtual time stops exactly at ``when``; physics at the first step boundary at or
        after it.
        """
        self._require_running("step_until()")
        if not isinstance(when, Time):
            raise InvalidTypeError(f"step_until() needs a Time, got {type(when).__name__}")
        if when.clock_type is not SIM:
            raise ClockMismatchError(
                f"step_until() needs a sim time, got a {when.clock_type.value} time"
            )
        if when.nanoseconds <= self._now_ns:
            raise InvalidArgumentError(
                f"step_until() target {when} is not after the current sim time "
                f"{Time._from_ns(self._now_ns, SIM)}"
            )
        self._pacer.run_until(when.nanoseconds)
        self._stepping_until(when.nanoseconds)
