"""A source of sim time that moves in whole steps of an engine: exact step clock, step hooks,
predicate waits, and snapshots restored as time jumps.

:class:`SteppingTimeSource` holds everything that does not depend on the engine; an adapter
(:class:`~evclock.sources.PyBulletTimeSource`, or your own for MuJoCo or a custom fixed-step
integrator) implements a handful of methods: take ``count`` steps, read and set the engine's
time step, and - for snapshots - save, restore and free an engine state.
"""

from __future__ import annotations

import abc
import asyncio
import itertools
import math
from collections.abc import Callable
from fractions import Fraction
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

from evclock._errors import (
    ClockJumpedError,
    InvalidArgumentError,
    InvalidTypeError,
    NotRunningError,
    PhysicsError,
    SimTimeLimitError,
)
from evclock.kernel._source import Gate, TimeSource
from evclock.time._time import (
    MAX_TIME_NS,
    SIM,
    Duration,
    Time,
    format_time_range_error,
    new_duration,
    new_time,
    to_span_ns,
    whole_number,
)

if TYPE_CHECKING:
    from evclock.kernel._jumps import TimeJump

_NS_PER_S = 1_000_000_000
#: Largest denominator tried when recovering the fraction a float time step was typed as.
_MAX_DENOMINATOR = 10**6
#: Upper bound of steps per ``advance()`` call on the fast path, so that a long sleep still
#: returns to the loop regularly (to poll I/O) instead of stepping for seconds on end.
_FAST_CHUNK = 1024
_STEP_HOOK_WHEN = ("before", "after")
#: An engine's saved state (whatever the adapter returns from ``_save_engine_state``).
_State = TypeVar("_State")


def exact_time_step(dt: float) -> Fraction:
    """The exact value, in seconds, that evclock uses for a float time step ``dt``.

    A time step is usually typed as a simple fraction (``1/240``, ``0.001``) that a float
    cannot hold exactly. If a fraction with a denominator of at most 10**6 rounds to exactly
    the float ``dt``, that fraction is the time step (``1/240`` stays ``1/240``, so 240 steps
    are exactly one second); otherwise the float's exact binary value is used.

    :param dt: the time step, in seconds (a positive float).
    :returns: the time step in seconds, as an exact :class:`~fractions.Fraction`.
    """
    exact = Fraction(dt)
    simple = exact.limit_denominator(_MAX_DENOMINATOR)
    return simple if simple and float(simple) == dt else exact


def format_seconds(value: Fraction) -> str:
    """A time step for messages: ``1/240``, ``2``, or a float's ``%g``."""
    if value.denominator == 1:
        return str(value.numerator)
    if value.numerator == 1 and value.denominator <= _MAX_DENOMINATOR:
        return f"1/{value.denominator}"
    return f"{float(value):g}"


def describe_callable(fn: object) -> str:
    """A callable's qualified name, for messages."""
    name = getattr(fn, "__qualname__", None) or getattr(fn, "__name__", None)
    return str(name) if name else repr(fn)


class StepHook:
    """A function called around every step; see :meth:`SteppingTimeSource.add_step_hook`.

    ``remove()`` unregisters it (idempotent). If the function raises, the error goes to the
    loop's exception handler, the hook is removed and :meth:`exception` returns the error.

    :param source: the stepping source the hook is registered on.
    :param fn: called with no arguments around every step.
    :param when: ``"before"`` or ``"after"`` the step.
    """

    __slots__ = ("_exception", "_fn", "_source", "active", "when")

    def __init__(
        self,
        source: SteppingTimeSource[Any],
        fn: Callable[[], object],
        when: Literal["before", "after"],
    ) -> None:
        self._source = source
        self._fn = fn
        self.when = when
        #: False once removed (by :meth:`remove` or after the function raised).
        self.active = True
        self._exception: BaseException | None = None

    @property
    def function(self) -> Callable[[], object]:
        """The hooked function."""
        return self._fn

    def remove(self) -> None:
        """Stop calling the function (idempotent)."""
        if self.active:
            self.active = False
            self._source._remove_hook(self)

    def exception(self) -> BaseException | None:
        """The error that removed the hook, if its function raised."""
        return self._exception

    def __repr__(self) -> str:
        state = "active" if self.active else "removed"
        return f"<StepHook {self.when} {describe_callable(self._fn)} {state}>"


class _Waiter:
    __slots__ = ("deadline_ns", "future", "predicate", "timeout")

    def __init__(
        self,
        predicate: Callable[[], object],
        future: asyncio.Future[Time],
        deadline_ns: int | None,
        timeout: Duration | None,
    ) -> None:
        self.predicate = predicate
        self.future = future
        self.deadline_ns = deadline_ns
        self.timeout = timeout


class _SavedState(Generic[_State]):
    __slots__ = ("engine_state", "step_index", "time_ns")

    def __init__(self, engine_state: _State, time_ns: int, step_index: int) -> None:
        self.engine_state = engine_state
        self.time_ns = time_ns
        self.step_index = step_index


class SteppingTimeSource(TimeSource, Generic[_State]):
    """Sim time that moves in whole steps of an engine (physics, a fixed-step integrator).

    **Time.** Sim time is ``start_ns + floor(steps x dt_ns)``, where ``dt_ns`` is the time step
    as an exact fraction of nanoseconds (see :func:`exact_time_step`: ``1/240`` s is exactly
    ``12500000/3`` ns) and ``steps`` an integer: 24 simulated hours never drift by a
    nanosecond. A change of time step re-bases the count at the current step boundary.

    **Quantisation.** Sleeps are quantised *up* to step boundaries: a task sleeping until
    ``t`` wakes at the end of the first step whose time is ``>= t``. Wait whole steps with
    :meth:`sleep_steps`.

    **Free running.** With nothing scheduled, the engine keeps stepping (``free_running``): a
    task may wait on a step hook or :meth:`wait_until`.

    **Writing an adapter** (about a hundred lines; see ``PyBulletTimeSource``): call
    ``super().__init__(time_step, start_ns=...)`` and implement

    * ``_step_engine(count)``: take ``count`` steps (raise :class:`PhysicsError` on failure);
    * ``_set_engine_time_step(dt)``: set the engine's time step to ``dt`` float seconds and
      return the value it now uses (read back);
    * for snapshots, ``_save_engine_state()``, ``_restore_engine_state(state, state_id)`` and
      ``_remove_engine_state(state)`` (default: snapshots unsupported);
    * optionally ``_before_advance()`` (called before each advance: pick up a time step
      changed behind evclock's back) and :meth:`describe`.

    :param time_step: the engine's time step in float seconds, or exact as a ``Fraction``.
    :param start_ns: sim time of the current state, in integer nanoseconds (default 0).
    """

    free_running = True

    def __init__(self, time_step: float | Fraction, *, start_ns: int = 0) -> None:
        start = whole_number(start_ns)
        if start is None:
            raise InvalidTypeError(
                f"start_ns must be an int number of nanoseconds, got {type(start_ns).__name__}"
            )
        start_ns = start
        if start_ns < 0:
            raise InvalidArgumentError(f"start_ns must not be negative, got {start_ns}")
        if start_ns > MAX_TIME_NS:
            raise InvalidArgumentError(format_time_range_error("start_ns", start_ns))
        # Time keeping: now = base + steps * num // den (num/den = dt in ns, exact).
        self._dt = 0.0
        self._num = 1
        self._den = 1
        self._base_ns = start_ns
        self._steps = 0
        self._now = start_ns
        self._step_index = 0
        if isinstance(time_step, Fraction):
            self._use_time_step(float(time_step), time_step)
        else:
            self._use_time_step(time_step)
        self._before: tuple[StepHook, ...] = ()
        self._after: tuple[StepHook, ...] = ()
        self._waiters: list[_Waiter] = []
        self._slow = False
        self._advancing = False
        self._states: dict[int, _SavedState[_State]] = {}
        self._state_ids = itertools.count(1)

    # ------------------------------------------------------- the engine's part

    @abc.abstractmethod
    def _step_engine(self, count: int) -> None:
        """Take ``count`` (>= 1) steps of the engine."""

    @abc.abstractmethod
    def _set_engine_time_step(self, dt: float) -> float:
        """Set the engine's time step (float seconds); return the one it now uses."""

    def _before_advance(self) -> None:
        """Called before each advance (e.g. to pick up a time step changed directly)."""

    def _save_engine_state(self) -> _State:
        """Snapshot the engine; the returned value is given back to restore it."""
        raise PhysicsError(f"{type(self).__name__} does not support snapshots")

    def _restore_engine_state(self, state: _State, state_id: int) -> None:
        """Bring the engine back to snapshot ``state_id`` (from :meth:`_save_engine_state`)."""
        raise PhysicsError(f"{type(self).__name__} does not support snapshots")

    def _remove_engine_state(self, state: _State) -> None:
        """Free a snapshot (nothing to do by default)."""

    # ------------------------------------------------------------------ time

    @property
    def now_ns(self) -> int:
        """Current sim time in integer nanoseconds: the time of the last step taken."""
        return self._now

    @property
    def time_step(self) -> float:
        """The engine's time step in seconds, as a float."""
        return self._dt

    @property
    def time_step_ns(self) -> Fraction:
        """The exact time step used for time keeping, in nanoseconds (``12500000/3`` at 1/240 s)."""
        return Fraction(self._num, self._den)

    @property
    def step_index(self) -> int:
        """Steps taken since the start, or since the last reset; :meth:`restore_state`
        restores the index saved with the state."""
        return self._step_index

    def _use_time_step(self, dt: float, exact: Fraction | None = None) -> None:
        """Re-base at the current step boundary and continue with time step ``dt``."""
        dt_ns = (exact if exact is not None else exact_time_step(dt)) * _NS_PER_S
        if dt_ns < 1:
            raise PhysicsError(
                f"time step {dt!r} s is shorter than 1 ns; evclock counts time in integer "
                "nanoseconds, so each step must last at least 1 ns"
            )
        self._base_ns = self._now
        self._steps = 0
        self._dt = dt
        self._num = dt_ns.numerator
        self._den = dt_ns.denominator

    def set_time_step(self, dt: float | Fraction | Duration) -> None:
        """Change the time step, from the next step on.

        ``dt`` is seconds (a float, an int or an exact :class:`~fractions.Fraction`) or a
        :class:`Duration`. Time re-bases at the current step boundary; the time already
        elapsed is unchanged. Safe to call from a task or a step hook.
        """
        exact: Fraction
        if isinstance(dt, Duration):
            exact = Fraction(dt.nanoseconds, _NS_PER_S)
        elif isinstance(dt, Fraction):
            exact = dt
        elif isinstance(dt, bool) or not isinstance(dt, int | float):
            raise InvalidTypeError(
                "time step must be seconds (a float, an int or a Fraction) or a Duration, "
                f"got {type(dt).__name__}"
            )
        elif isinstance(dt, float) and not math.isfinite(dt):
            raise InvalidArgumentError(
                f"time step must be a positive finite number of seconds, got {dt!r}"
            )
        else:
            exact = exact_time_step(float(dt))
        if exact <= 0:
            raise InvalidArgumentError(
                f"time step must be a positive finite number of seconds, got {dt!r}"
            )
        value = float(exact)
        read_back = self._set_engine_time_step(value)
        self._use_time_step(read_back, exact if read_back == value else None)

    # --------------------------------------------------------------- stepping

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Step the engine in whole steps toward the first step boundary at or after
        ``target_ns`` (None: one step), asking ``gate`` before each step; return the new time,
        which may fall short of the target (the kernel then asks again)."""
        now = self._now
        if target_ns is not None and target_ns <= now:
            return now
        self._before_advance()
        if gate is not None or self._slow:
            return self._advance_slow(target_ns, gate)
        # Fast path: nothing to call between steps, so step in a tight loop.
        if target_ns is None:
            count = 1
        else:
            # The first step count k with floor(k * num / den) >= target - base.
            count = -((self._base_ns - target_ns) * self._den // self._num) - self._steps
            if count > _FAST_CHUNK:
                count = _FAST_CHUNK
        self._step_engine(count)
        self._steps += count
        self._step_index += count
        self._now = now = self._base_ns + self._steps * self._num // self._den
        return now

    def _advance_slow(self, target_ns: int | None, gate: Gate) -> int:
        """One step at a time: gate, before-hooks, step, after-hooks, waiters."""
        host = self._host
        self._advancing = True
        try:
            while True:
                if gate is not None and not gate(
                    self._base_ns + (self._steps + 1) * self._num // self._den
                ):
                    break
                if self._before:
                    self._run_hooks(self._before)
                self._step_engine(1)
                self._steps += 1
                self._step_index += 1
                self._now = now = self._base_ns + self._steps * self._num // self._den
                if host is not None:
                    # Hooks, predicates and the pacer read the clock during the advance.
                    host.stepped_to(now)
                if self._after:
                    self._run_hooks(self._after)
                if self._waiters:
                    self._check_waiters(now)
                if target_ns is None or now >= target_ns:
                    break
                if host is not None and host.work_ready():
                    break
        finally:
            self._advancing = False
        return self._now

    # ------------------------------------------------------------ step hooks

    def add_step_hook(
        self, fn: Callable[[], object], when: Literal["before", "after"] = "after"
    ) -> StepHook:
        """Call ``fn()`` before or after every step; returns a handle with ``remove()``.

        Hooks run in registration order, inside the advance of sim time: the loop's clock
        reads the time of the step about to be taken ("before") or just taken ("after").
        A hook may apply forces, record sensors, or wake a task (set an ``asyncio.Event``,
        resolve a future): then the loop stops stepping after that step and runs the task.
        Hooks turn the tight stepping loop into a per-step one; remove them when done.
        """
        if not callable(fn):
            raise InvalidTypeError(f"a step hook must be callable, got {type(fn).__name__}")
        if when not in _STEP_HOOK_WHEN:
            raise InvalidArgumentError(
                f"step hook 'when' must be 'before' or 'after', got {when!r}"
            )
        hook = StepHook(self, fn, when)
        if when == "before":
            self._before = (*self._before, hook)
        else:
            self._after = (*self._after, hook)
        self._update_slow()
        return hook

    def _remove_hook(self, hook: StepHook) -> None:
        self._before = tuple(h for h in self._before if h is not hook)
        self._after = tuple(h for h in self._after if h is not hook)
        self._update_slow()

    @property
    def step_hooks(self) -> tuple[StepHook, ...]:
        """The active step hooks: "before" ones first, each group in registration order."""
        return self._before + self._after

    def _update_slow(self) -> None:
        self._slow = bool(self._before or self._after or self._waiters)

    def _run_hooks(self, hooks: tuple[StepHook, ...]) -> None:
        for hook in hooks:
            if not hook.active:
                continue  # removed by an earlier hook of this step
            try:
                hook._fn()
            except Exception as exc:
                hook._exception = exc
                hook.remove()
                host = self._host
                if host is None:
                    raise
                host.call_exception_handler(
                    {
                        "message": f"evclock step hook {describe_callable(hook._fn)} raised; "
                        "hook removed",
                        "exception": exc,
                    }
                )

    # ------------------------------------------------------------ waiting

    def time_of_step(self, count: int) -> Time:
        """The sim time ``count`` steps from now, at the current time step."""
        steps = whole_number(count)
        if steps is None:
            raise InvalidTypeError(f"step count must be an int, got {type(count).__name__}")
        if steps < 0:
            raise InvalidArgumentError(f"step count must not be negative, got {count}")
        ns = self._base_ns + (self._steps + steps) * self._num // self._den
        if ns > MAX_TIME_NS:
            raise InvalidArgumentError(format_time_range_error(f"{count} steps", ns))
        return new_time(ns, SIM)

    async def sleep_steps(self, count: int) -> None:
        """Sleep exactly ``count`` steps (a sim-time sleep: a jump raises ClockJumpedError).

        Prefer it to ``clock.sleep(count * dt)`` when whole steps matter: a float ``dt`` such
        as 1/240 s rounds to a whole nanosecond *above* the exact step (4166667 ns vs
        4166666.67 ns), so ``sleep(1/240)`` may end one step later than intended.
        """
        when = self.time_of_step(count)
        loop = asyncio.get_running_loop()
        if self._host is None or not self._host.serves(loop):
            raise NotRunningError(self._wrong_loop("sleep_steps()"))
        if count < 1:
            raise InvalidArgumentError(f"sleep_steps() count must be >= 1, got {count}")
        await self._host.clock.sleep_until(when)

    @classmethod
    def _wrong_loop(cls, what: str) -> str:
        return (
            f"{what} must be awaited in a task on the sim time this {cls.__name__} drives: "
            "the SimEventLoop of evclock.run(main(), source=source), or the loop of an "
            "evclock.SimDriver(source)"
        )

    async def wait_until(
        self, predicate: Callable[[], object], timeout: float | Duration | None = None
    ) -> Time:
        """Wait until ``predicate()`` is true; return the sim time at which it was.

        The predicate is evaluated now (returning at once if it holds), then after every
        step: the call resolves at the first step where it is true, e.g.
        ``await source.wait_until(lambda: bool(p.getContactPoints(gripper, cube)))``.
        ``timeout`` (sim seconds or a Duration) raises :class:`~evclock.SimTimeLimitError` (a
        :class:`TimeoutError`) at the first step at or after the deadline where the predicate
        is still false. If the predicate raises,
        the error is raised here. A clock jump (reset, restored state) raises
        :class:`ClockJumpedError`, like every pending sim-time wait.
        Costs nothing when no one waits.
        """
        if not callable(predicate):
            raise InvalidTypeError(
                f"wait_until() needs a callable predicate, got {type(predicate).__name__}"
            )
        deadline: int | None = None
        limit: Duration | None = None
        if timeout is not None:
            limit = new_duration(to_span_ns(timeout, "wait_until() timeout"))
        loop = asyncio.get_running_loop()
        if self._host is None or not self._host.serves(loop):
            raise NotRunningError(self._wrong_loop("wait_until()"))
        if predicate():
            return new_time(self._now, SIM)
        if limit is not None:
            if limit.nanoseconds == 0:
                raise SimTimeLimitError(self._timeout_message(predicate, limit))
            deadline = self._now + limit.nanoseconds
        future: asyncio.Future[Time] = loop.create_future()
        waiter = _Waiter(predicate, future, deadline, limit)
        self._waiters.append(waiter)
        self._slow = True
        try:
            return await future
        finally:
            if waiter in self._waiters:
                self._waiters.remove(waiter)
                self._update_slow()

    @staticmethod
    def _timeout_message(predicate: object, limit: Duration) -> str:
        return (
            f"wait_until({describe_callable(predicate)}) timed out: the predicate stayed "
            f"false for {limit} of sim time"
        )

    def _check_waiters(self, now: int) -> None:
        keep: list[_Waiter] = []
        for waiter in self._waiters:
            future = waiter.future
            if future.done():
                continue
            try:
                holds = waiter.predicate()
            except Exception as exc:
                future.set_exception(exc)
                continue
            if holds:
                future.set_result(new_time(now, SIM))
            elif waiter.deadline_ns is not None and now >= waiter.deadline_ns:
                assert waiter.timeout is not None
                future.set_exception(
                    SimTimeLimitError(self._timeout_message(waiter.predicate, waiter.timeout))
                )
            else:
                keep.append(waiter)
        self._waiters = keep
        self._update_slow()

    # ------------------------------------------------------ snapshots and jumps

    def _check_not_advancing(self, what: str) -> None:
        if self._advancing:
            raise PhysicsError(
                f"{what} cannot be called from a step hook or a wait_until() predicate: the "
                "physics is in the middle of advancing; call it from a task"
            )

    def save_state(self) -> int:
        """Snapshot the engine with the current sim time; return its id.

        :meth:`restore_state` brings the engine and the clock back to it; :meth:`remove_state`
        frees it.
        """
        self._check_not_advancing("save_state()")
        engine_state = self._save_engine_state()
        state_id = next(self._state_ids)
        self._states[state_id] = _SavedState(engine_state, self._now, self._step_index)
        return state_id

    def restore_state(self, state_id: int) -> TimeJump | None:
        """Restore a :meth:`save_state` snapshot and its sim time.

        Time moves back (or forward) to the saved time as a jump: jump handlers run, pending
        sim-time waits raise :class:`ClockJumpedError`, rates and timers re-anchor. Returns the
        jump, or None when the saved time is the current one (then no wait is interrupted).
        The time step is not part of a snapshot: the current one goes on.
        """
        self._check_not_advancing("restore_state()")
        saved = self._saved(state_id)
        self._restore_engine_state(saved.engine_state, state_id)
        return self._move_time(saved.time_ns, saved.step_index)

    def remove_state(self, state_id: int) -> None:
        """Free a snapshot; its id becomes unknown."""
        saved = self._saved(state_id)
        del self._states[state_id]
        self._remove_engine_state(saved.engine_state)

    def _saved(self, state_id: int) -> _SavedState[_State]:
        saved = self._states.get(state_id) if isinstance(state_id, int) else None
        if saved is None:
            raise InvalidArgumentError(
                f"unknown state id {state_id!r}: pass an id returned by save_state() of this "
                "source that was not removed"
            )
        return saved

    def _move_time(self, new_ns: int, step_index: int) -> TimeJump | None:
        """Move the clock to ``new_ns`` (a reset or a restored snapshot): a jump if a host
        runs on this source and the time changes."""

        def assign(ns: int) -> None:
            self._base_ns = self._now = ns
            self._steps = 0
            self._step_index = step_index

        host = self._host
        before = self._now
        jump: TimeJump | None = None
        if host is None or host.is_closed() or new_ns == before:
            assign(new_ns)
        else:
            jump = host.jump(before, new_ns, assign)
            waiters, self._waiters = self._waiters, []
            self._update_slow()
            for waiter in waiters:
                if not waiter.future.done():
                    waiter.future.set_exception(ClockJumpedError(jump))
        return jump

    def describe(self) -> str:
        """The source for messages: its class and time step."""
        return f"{type(self).__name__} (dt={format_seconds(self.time_step_ns / _NS_PER_S)} s)"

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()} now={new_time(self._now, SIM)}>"
