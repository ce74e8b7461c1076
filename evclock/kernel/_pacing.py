"""Pacing: how much wall time each advance of sim time takes; pause, resume and step."""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from evclock._errors import (
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    LagError,
    PacingError,
)
from evclock.time._time import SIM, Time, new_time, real_number, whole_number

if TYPE_CHECKING:
    from evclock.kernel._core import SimCore

#: How far behind its schedule a paced run may fall before it re-anchors instead of
#: bursting to catch up (seconds of wall time).
DEFAULT_MAX_LAG = 0.1


def check_rtf(rtf: object) -> float | None:
    """Validate a real-time factor: None (as fast as possible) or a positive finite number."""
    if rtf is None:
        return None
    value = real_number(rtf)
    if value is None:
        raise InvalidTypeError(
            f"rtf must be None (as fast as possible) or a positive number, got {type(rtf).__name__}"
        )
    if not math.isfinite(value) or value <= 0:
        raise InvalidArgumentError(
            f"rtf must be a positive finite real-time factor (1.0 = real time), got {rtf!r}; "
            "use rtf=None to run as fast as possible"
        )
    return value


def check_max_lag(max_lag: object) -> float:
    """Validate a lag bound: a positive finite number of wall seconds."""
    value = real_number(max_lag)
    if value is None:
        raise InvalidTypeError(f"max_lag must be a number of seconds, got {type(max_lag).__name__}")
    if not math.isfinite(value) or value <= 0:
        raise InvalidArgumentError(f"max_lag must be a positive number of seconds, got {max_lag!r}")
    return value


class RtfMeter:
    """Measures the achieved real-time factor: sim seconds per wall second.

    It takes its first sample when created (with the host), so a reading is defined as soon
    as any wall time has passed.
    """

    def __init__(
        self, sim_ns: int, window: float = 2.0, wall: Callable[[], float] = time.perf_counter
    ) -> None:
        self._wall = wall
        self._window = window
        self._samples: collections.deque[tuple[float, int]] = collections.deque()
        self.sample(sim_ns)

    def sample(self, sim_ns: int) -> None:
        """Record the pair (now, ``sim_ns``)."""
        now = self._wall()
        self._samples.append((now, sim_ns))
        while len(self._samples) > 2 and now - self._samples[0][0] > self._window:
            self._samples.popleft()

    def recent(self) -> float | None:
        """Achieved factor over the last window; None while no wall time has passed."""
        (w0, s0), (w1, s1) = self._samples[0], self._samples[-1]
        return (s1 - s0) / 1e9 / (w1 - w0) if w1 > w0 else None


class Pacer:
    """Decides, before each increment of sim time, whether it may happen now.

    It never blocks: :meth:`allow` answers yes, or no with :attr:`delay`, the wall seconds the
    host should wait (serving I/O) before asking again - None meaning "until a control
    changes" (paused with no step left). ``now_ns()`` reads sim time.

    Thread-safe: controls may come from any thread while the host thread asks :meth:`allow`
    (each method runs under :attr:`lock`, so a step is never lost nor taken twice).
    """

    def __init__(
        self,
        now_ns: Callable[[], int],
        *,
        rtf: float | None = None,
        strict: bool = False,
        max_lag: float = DEFAULT_MAX_LAG,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self._now_ns = now_ns
        self._wall = wall
        self._rtf = check_rtf(rtf)
        self.strict = bool(strict)
        self.max_lag = check_max_lag(max_lag)
        self._anchor: tuple[float, int] | None = None
        #: Held by every control and by :meth:`allow` (controls may come from any thread).
        self.lock = threading.Lock()
        self.paused = False
        self._step_budget = 0
        self._run_until_ns: int | None = None
        #: A step_until() from another thread whose stop mark the host has not placed yet:
        #: time may not move until it has (else it could pass the target).
        self._mark_pending = False
        self.meter = RtfMeter(now_ns(), wall=wall)
        #: True when advances need no pacing at all (the hot path skips the pacer).
        self.unpaced = True
        #: True when the last :meth:`allow` said no; :attr:`delay` says how long to wait.
        self.refused = False
        self.delay: float | None = None
        self._update_unpaced()

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
        rtf = check_rtf(value)
        with self.lock:
            self._rtf = rtf
            self._anchor = None
            self._update_unpaced()

    def _update_unpaced(self) -> None:
        self.unpaced = self._rtf is None and not self.paused

    def reanchor(self) -> None:
        """Forget the pacing schedule (after a jump or an rtf change): pace from now on."""
        with self.lock:
            self._anchor = None

    def pause(self) -> None:
        self._set_paused(True)

    def resume(self) -> None:
        self._set_paused(False)

    def _set_paused(self, paused: bool) -> None:
        """Pause or resume; either ends the steps and the ``step_until()`` under way, and a
        resumed run is paced from now."""
        with self.lock:
            self.paused = paused
            self._step_budget = 0
            self._run_until_ns = None
            self._mark_pending = False
            if not paused:
                self._anchor = None
            self._update_unpaced()

    def step(self, count: int) -> None:
        with self.lock:
            if not self.paused:
                raise PacingError(self._not_paused("step()"))
            self._step_budget += count
            self._anchor = None  # pace the steps from the request, not from before the pause

    def run_until(self, sim_ns: int, *, mark_pending: bool = False) -> None:
        """Advance until ``sim_ns`` while paused. ``mark_pending``: the host places the stop
        mark later, on its own thread (the call came from another one); until
        :meth:`mark_placed`, time does not move."""
        with self.lock:
            if not self.paused:
                raise PacingError(self._not_paused("step_until()"))
            self._run_until_ns = sim_ns
            self._mark_pending = mark_pending
            self._anchor = None

    def mark_placed(self, sim_ns: int) -> None:
        """The host placed the stop mark of ``run_until(sim_ns, mark_pending=True)``."""
        with self.lock:
            if self._run_until_ns == sim_ns:
                self._mark_pending = False

    def _not_paused(self, what: str) -> str:
        mode = "as fast as possible" if self._rtf is None else f"at rtf={self._rtf:g}"
        return (
            f"{what} needs a paused loop, but it is running {mode}; call pause() first, then step"
        )

    def waits_for_control(self) -> bool:
        """Paused with no step left and no ``step_until`` target ahead: sim time can move
        only after a control (a step, a resume) changes this."""
        with self.lock:
            return self.paused and self._step_budget <= 0 and not self._running_until()

    def _running_until(self) -> bool:
        """A placed ``step_until`` target lies ahead (with the lock held)."""
        until = self._run_until_ns
        return until is not None and not self._mark_pending and self._now_ns() < until

    def allow(self, next_ns: int) -> bool:
        """May sim time move to ``next_ns`` now? If not, :attr:`delay` says how long to wait."""
        with self.lock:
            return self._allow(next_ns)

    def _allow(self, next_ns: int) -> bool:
        stepping = False
        if self.paused:
            if self._step_budget > 0:
                stepping = True  # spent only once the pacing delay below is over
            elif not self._running_until():
                return self._refuse(None)
        if self._rtf is not None:
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
            if due > wall:
                return self._refuse(due - wall)
        if stepping:
            self._step_budget -= 1
        self.refused = False
        return True

    def _refuse(self, delay: float | None) -> bool:
        self.refused = True
        self.delay = delay
        return False


class PacingControls:
    """The pacing API shared by :class:`~evclock.SimEventLoop` and :class:`~evclock.SimDriver`:
    ``rtf``, ``paused``, ``achieved_rtf()``, ``pause()``, ``resume()``, ``step()`` and
    ``step_until()``. The host provides ``_core`` (its :class:`~evclock.kernel._core.SimCore`) and
    ``_require_running()``, and reacts to changes in ``_pacing_changed()``.

    **Thread-safe, one mechanism for both hosts.** A control may be called from any thread
    (a GUI, an operator). It validates and changes the pacer at once in the calling thread
    (under the pacer's lock), so a control that does not apply raises there, and two
    controls from one thread apply in order. The host's reaction (``_pacing_changed``,
    ``_stepping_until``), which touches the host's own state, runs on the host's thread:
    directly when called there, else handed over with ``_call_on_host`` (the host's
    ``call_soon_threadsafe``), which also wakes a host blocked in a pacing or pause wait.
    A ``step_until`` from another thread lets no time pass until the host has placed its
    stop mark, so time still stops exactly at the target.
    """

    _core: SimCore

    def _require_running(self, what: str) -> None:
        raise NotImplementedError

    def _on_host_thread(self) -> bool:
        """Whether the caller runs on the host's thread (the loop's)."""
        raise NotImplementedError

    def _call_on_host(self, what: str, reaction: Callable[[], None]) -> None:
        """Run ``reaction`` soon on the host's thread and wake the host (thread-safe);
        ``what`` names the control for error messages."""
        raise NotImplementedError

    def _pacing_changed(self) -> None:
        """Called on the host's thread after every change of rtf, pause state or step budget."""

    def _stepping_until(self, when_ns: int) -> None:
        """Called on the host's thread after ``step_until(when)``: place the stop mark."""
        self._pacing_changed()

    def _step_until_ended(self) -> None:
        """After pause() or resume(), on the host's thread: they end a ``step_until``, so
        its stop mark goes too (unless a newer step_until, from another thread, is on its
        way: it drops the old marks when it places its own)."""
        core = self._core
        if core.pacer.run_until_ns is None:
            core.drop_stops()
        self._pacing_changed()

    def _react(self, what: str, reaction: Callable[[], None]) -> None:
        if self._on_host_thread():
            reaction()
        else:
            self._call_on_host(what, reaction)

    @property
    def rtf(self) -> float | None:
        """Requested real-time factor (None: as fast as possible). Settable while running,
        from any thread."""
        return self._core.pacer.rtf

    @rtf.setter
    def rtf(self, value: float | None) -> None:
        self._core.pacer.rtf = value
        self._react("rtf", self._pacing_changed)

    @property
    def paused(self) -> bool:
        """Whether sim time is paused (work due at the current time still runs)."""
        return self._core.pacer.paused

    def achieved_rtf(self) -> float | None:
        """Real-time factor achieved over the last couple of wall seconds.

        Measured from the previous calls of the last two wall seconds, or from the creation
        of the loop (driver) on the first call; None only if no wall time has passed since.
        Each call records a sample: poll it periodically (a progress bar, a dashboard).
        """
        pacer = self._core.pacer
        with pacer.lock:
            pacer.meter.sample(self._core.now_ns)
            return pacer.meter.recent()

    def pause(self) -> None:
        """Stop sim time from advancing; I/O keeps being served. Thread-safe."""
        self._require_running("pause()")
        self._core.pacer.pause()
        self._react("pause()", self._step_until_ended)

    def resume(self) -> None:
        """Let sim time advance again at the requested rtf. Thread-safe."""
        self._require_running("resume()")
        self._core.pacer.resume()
        self._react("resume()", self._step_until_ended)

    def step(self, count: int = 1) -> None:
        """While paused, let sim time advance ``count`` increments (physics steps, or jumps to
        the next deadline on virtual time), then stay paused. Thread-safe."""
        self._require_running("step()")
        steps = whole_number(count)
        if steps is None:
            raise InvalidTypeError(f"step() count must be an int, got {type(count).__name__}")
        if steps < 1:
            raise InvalidArgumentError(f"step() count must be >= 1, got {count}")
        self._core.pacer.step(steps)
        self._react("step()", self._pacing_changed)

    def step_until(self, when: Time) -> None:
        """While paused, let sim time advance until it reaches ``when``, then stay paused.

        Virtual time stops exactly at ``when``; physics at the first step boundary at or
        after it. Thread-safe.
        """
        self._require_running("step_until()")
        if not isinstance(when, Time):
            raise InvalidTypeError(f"step_until() needs a Time, got {type(when).__name__}")
        if when.clock_type is not SIM:
            raise ClockMismatchError(
                f"step_until() needs a sim time, got a {when.clock_type.value} time"
            )
        if when.nanoseconds <= self._core.now_ns:
            raise InvalidArgumentError(
                f"step_until() target {when} is not after the current sim time "
                f"{new_time(self._core.now_ns, SIM)}"
            )
        when_ns = when.nanoseconds
        pacer = self._core.pacer
        on_host = self._on_host_thread()
        pacer.run_until(when_ns, mark_pending=not on_host)
        if on_host:
            self._core.drop_stops()  # a step_until still on its way ends here
            self._stepping_until(when_ns)
            return

        def place_mark() -> None:
            self._core.drop_stops()
            if pacer.run_until_ns == when_ns:  # else ended (or replaced) on its way here
                self._stepping_until(when_ns)
                pacer.mark_placed(when_ns)

        self._call_on_host("step_until()", place_mark)
