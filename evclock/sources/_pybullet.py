"""PyBullet as the owner of simulation time: sim time moves in whole physics steps.

PyBullet keeps no time counter, so evclock counts the steps and derives the time exactly
from integers (DESIGN section 2). ``pybullet`` is imported lazily, when the first source is
created: ``import evclock`` alone does not load it (nor numpy, nor its banner on stderr).
"""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import Callable
from fractions import Fraction
from typing import TYPE_CHECKING, Any, Literal

from .._errors import (
    ClockJumped,
    InvalidArgumentError,
    InvalidTypeError,
    NotRunningError,
    PhysicsError,
)
from .._extras import import_extra
from .._time import SIM, Duration, Time, to_nanoseconds
from ._base import Gate, TimeSource

if TYPE_CHECKING:
    from .._jumps import TimeJump

_NS_PER_S = 1_000_000_000
#: Largest denominator tried when recovering the fraction a float time step was typed as.
_MAX_DENOMINATOR = 10**6
#: Upper bound of steps per ``advance()`` call on the fast path, so that a long sleep still
#: returns to the loop regularly (to poll I/O) instead of stepping for seconds on end.
_FAST_CHUNK = 1024
_STEP_HOOK_WHEN = ("before", "after")


def _pybullet() -> Any:
    return import_extra("pybullet", "pybullet", needed_by="PyBulletTimeSource")


def exact_time_step(dt: float) -> Fraction:
    """The exact value, in seconds, that evclock uses for a float time step ``dt``.

    A time step is usually typed as a simple fraction (``1/240``, ``0.001``) that a float
    cannot hold exactly. If a fraction with a denominator of at most 10**6 rounds to exactly
    the float ``dt``, that fraction is the time step (``1/240`` stays ``1/240``, so 240 steps
    are exactly one second); otherwise the float's exact binary value is used.
    """
    exact = Fraction(dt)
    simple = exact.limit_denominator(_MAX_DENOMINATOR)
    return simple if simple and float(simple) == dt else exact


def _format_seconds(value: Fraction) -> str:
    if value.denominator == 1:
        return str(value.numerator)
    if value.numerator == 1 and value.denominator <= _MAX_DENOMINATOR:
        return f"1/{value.denominator}"
    return f"{float(value):g}"


def _describe_callable(fn: object) -> str:
    name = getattr(fn, "__qualname__", None) or getattr(fn, "__name__", None)
    return str(name) if name else repr(fn)


class StepHook:
    """A function called around every physics step; see :meth:`PyBulletTimeSource.add_step_hook`.

    ``remove()`` unregisters it (idempotent). If the function raises, the error goes to the
    loop's exception handler, the hook is removed and :meth:`exception` returns the error.
    """

    __slots__ = ("_exception", "_fn", "_source", "active", "when")

    def __init__(
        self, source: PyBulletTimeSource, fn: Callable[[], object], when: Literal["before", "after"]
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
        return f"<StepHook {self.when} {_describe_callable(self._fn)} {state}>"


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


class _SavedState:
    __slots__ = ("bullet_ids", "step_index", "time_ns")

    def __init__(self, bullet_ids: tuple[int, ...], time_ns: int, step_index: int) -> None:
        self.bullet_ids = bullet_ids
        self.time_ns = time_ns
        self.step_index = step_index


class PyBulletTimeSource(TimeSource):
    """Sim time driven by one or more PyBullet physics clients, in whole physics steps.

    ``PyBulletTimeSource(client, ...)`` steps already-connected clients (ids returned by
    ``p.connect``); :meth:`connect` creates a DIRECT (or GUI) client and owns it. Run a
    program on it with ``evclock.run(main(), source=source)``. Every advance of sim time
    calls ``p.stepSimulation`` on each client, in the order given, one step at a time.

    **Time.** Sim time is ``start_ns + floor(steps x dt_ns)``, where ``dt_ns`` is the time step
    as an exact fraction of nanoseconds (see :func:`exact_time_step`: ``1/240`` s is exactly
    ``12500000/3`` ns) and ``steps`` an integer: 24 simulated hours never drift by a
    nanosecond. A change of time step re-bases the count at the current step boundary.

    **Time step.** ``dt`` is read from the engine (``fixedTimeStep``); every client must have
    the same. ``numSubSteps`` does not change it: one ``stepSimulation`` always advances
    ``fixedTimeStep`` seconds, split into sub-steps inside the engine (checked by the tests).
    Change it with :meth:`set_time_step`. With ``watch_time_step=True`` (default), a change
    made directly with ``p.setTimeStep``/``p.setPhysicsEngineParameter(fixedTimeStep=...)``
    is detected too: the time step is re-read before each advance of the loop (one
    ``getPhysicsEngineParameters`` call per client, about 2 us), so a change made from a task
    takes effect from the next step. ``watch_time_step=False`` saves that call; then change
    the time step only through :meth:`set_time_step` (always required from inside a step hook).

    **Quantisation.** Sleeps are quantised *up* to step boundaries: a task sleeping until
    ``t`` wakes at the end of the first step whose time is ``>= t`` (with ``dt = 1/240`` s, a
    ``sleep(0.001)`` lasts one step, 4.1666 ms). Rates whose period is a whole number of steps
    (20 Hz, 60 Hz, 240 Hz at ``dt = 1/240``) tick exactly on their deadlines. A float
    duration of whole steps may round one nanosecond past a step (``1/240`` s is 4166667 ns,
    one step 4166666.67 ns) and then lasts one step more: wait whole steps with
    :meth:`sleep_steps`.

    **Free running.** With nothing scheduled, physics keeps stepping (``free_running``): a
    task may wait on a step hook or :meth:`wait_until`.

    :param clients: PyBullet physics client ids (``p.connect`` return values), at least one.
    :param start_ns: sim time of the current state, in integer nanoseconds (default 0).
    :param watch_time_step: detect time-step changes made directly through pybullet.
    """

    free_running = True

    def __init__(self, *clients: int, start_ns: int = 0, watch_time_step: bool = True) -> None:
        if not clients:
            raise InvalidArgumentError(
                "PyBulletTimeSource needs at least one connected PyBullet client id, e.g. "
                "PyBulletTimeSource(p.connect(p.DIRECT)), or use PyBulletTimeSource.connect()"
            )
        for cid in clients:
            if isinstance(cid, bool) or not isinstance(cid, int):
                raise InvalidTypeError(
                    "PyBullet clients are int ids returned by p.connect(), "
                    f"got {type(cid).__name__}"
                )
        if len(set(clients)) != len(clients):
            raise InvalidArgumentError(
                f"PyBullet client ids must be distinct, got {clients!r}: a client listed twice "
                "would be stepped twice per step"
            )
        if type(start_ns) is not int:
            raise InvalidTypeError(
                f"start_ns must be an int number of nanoseconds, got {type(start_ns).__name__}"
            )
        if start_ns < 0:
            raise InvalidArgumentError(f"start_ns must not be negative, got {start_ns}")
        pb = _pybullet()
        self._p: Any = pb
        self._step: Callable[[int], object] = pb.stepSimulation
        self._clients: tuple[int, ...] = tuple(clients)
        self._owns_clients = False
        self._watch = bool(watch_time_step)
        for cid in clients:
            if not pb.isConnected(cid):
                raise PhysicsError(
                    f"PyBullet physics client {cid} is not connected; pass the id returned by "
                    "p.connect(p.DIRECT) (or p.GUI) while it is connected, or let "
                    "PyBulletTimeSource.connect() create one"
                )
            params = pb.getPhysicsEngineParameters(physicsClientId=cid)
            if params.get("useRealTimeSimulation"):
                raise PhysicsError(
                    f"PyBullet physics client {cid} has real-time simulation on (the server "
                    "steps itself on the wall clock); call "
                    f"p.setRealTimeSimulation(0, physicsClientId={cid}): evclock steps it"
                )
        # Time keeping: now = base + steps * num // den (num/den = dt in ns, exact).
        self._dt = 0.0
        self._num = 1
        self._den = 1
        self._base_ns = start_ns
        self._steps = 0
        self._now = start_ns
        self._step_index = 0
        self._use_engine_time_step(self._read_time_step())
        self._before: tuple[StepHook, ...] = ()
        self._after: tuple[StepHook, ...] = ()
        self._waiters: list[_Waiter] = []
        self._slow = False
        self._advancing = False
        self._states: dict[int, _SavedState] = {}
        self._state_ids = itertools.count(1)
        self._closed = False

    @classmethod
    def connect(
        cls,
        gui: bool = False,
        *,
        time_step: float | Fraction | Duration | None = None,
        options: str = "",
        start_ns: int = 0,
        watch_time_step: bool = True,
    ) -> PyBulletTimeSource:
        """Connect a new PyBullet client (DIRECT, or GUI with ``gui=True``) and drive it.

        The source owns this client: it is disconnected when the loop closes (or on
        :meth:`close`). ``time_step`` sets the engine's time step (default: PyBullet's 1/240 s);
        ``options`` is passed to ``p.connect``. Read the client id from :attr:`client`.
        Note that PyBullet ends the process if a GUI cannot open (no display).
        """
        pb = _pybullet()
        mode = pb.GUI if gui else pb.DIRECT
        cid = pb.connect(mode, options=options) if options else pb.connect(mode)
        if cid < 0:
            raise PhysicsError(
                f"could not connect to PyBullet in {'GUI' if gui else 'DIRECT'} mode "
                "(p.connect returned -1); a GUI needs a display, and only one GUI client may "
                "exist per process"
            )
        try:
            source = cls(cid, start_ns=start_ns, watch_time_step=watch_time_step)
            if time_step is not None:
                source.set_time_step(time_step)
        except BaseException:
            pb.disconnect(cid)
            raise
        source._owns_clients = True
        return source

    # ------------------------------------------------------------------ time

    @property
    def now_ns(self) -> int:
        return self._now

    @property
    def clients(self) -> tuple[int, ...]:
        """The PyBullet client ids this source steps, in stepping order."""
        return self._clients

    @property
    def client(self) -> int:
        """The first (usually the only) client id."""
        return self._clients[0]

    @property
    def time_step(self) -> float:
        """The engine's time step in seconds (``fixedTimeStep``), as a float."""
        return self._dt

    @property
    def time_step_ns(self) -> Fraction:
        """The exact time step used for time keeping, in nanoseconds (``12500000/3`` at 1/240 s)."""
        return Fraction(self._num, self._den)

    @property
    def step_index(self) -> int:
        """Physics steps taken since the start, or since the last :meth:`reset_simulation`.

        :meth:`restore_state` restores the index saved with the state.
        """
        return self._step_index

    def _read_time_step(self) -> float:
        """Read the shared time step from every client (validated)."""
        pb = self._p
        first: float | None = None
        for cid in self._clients:
            try:
                dt = pb.getPhysicsEngineParameters(physicsClientId=cid)["fixedTimeStep"]
            except pb.error as exc:
                raise self._failure(exc, "getPhysicsEngineParameters") from exc
            if not (isinstance(dt, float) and math.isfinite(dt) and dt > 0):
                raise PhysicsError(
                    f"PyBullet physics client {cid} has fixedTimeStep={dt!r}, which is not a "
                    "positive finite number of seconds; set one with "
                    f"p.setTimeStep(1/240, physicsClientId={cid}) or source.set_time_step(1/240)"
                )
            if first is None:
                first = dt
            elif dt != first:
                raise PhysicsError(
                    "PyBullet clients stepped together must share one time step, but client "
                    f"{self._clients[0]} has fixedTimeStep={first!r} and client {cid} has "
                    f"{dt!r}; give them the same with source.set_time_step(dt) (or "
                    "p.setTimeStep(dt, physicsClientId=...) on each)"
                )
        assert first is not None
        return first

    def _use_engine_time_step(self, dt: float, exact: Fraction | None = None) -> None:
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

    def _check_time_step(self) -> None:
        """The watch: pick up a time step changed directly through pybullet."""
        pb = self._p
        read = pb.getPhysicsEngineParameters
        dt = self._dt
        for cid in self._clients:
            try:
                changed = read(physicsClientId=cid)["fixedTimeStep"] != dt
            except pb.error as exc:
                raise self._failure(exc, "getPhysicsEngineParameters") from exc
            if changed:
                self._use_engine_time_step(self._read_time_step())
                return

    def set_time_step(self, dt: float | Fraction | Duration) -> None:
        """Change the physics time step of every client, from the next step on.

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
        pb = self._p
        value = float(exact)
        for cid in self._clients:
            try:
                pb.setTimeStep(value, physicsClientId=cid)
            except pb.error as exc:
                raise self._failure(exc, "setTimeStep") from exc
        read_back = self._read_time_step()
        self._use_engine_time_step(read_back, exact if read_back == value else None)

    # --------------------------------------------------------------- stepping

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        now = self._now
        if target_ns is not None and target_ns <= now:
            return now
        if self._watch:
            self._check_time_step()
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
        step = self._step
        clients = self._clients
        try:
            if len(clients) == 1:
                cid = clients[0]
                for _ in itertools.repeat(None, count):
                    step(cid)
            else:
                for _ in itertools.repeat(None, count):
                    for cid in clients:
                        step(cid)
        except self._p.error as exc:
            raise self._failure(exc, "stepSimulation") from exc
        self._steps += count
        self._step_index += count
        self._now = now = self._base_ns + self._steps * self._num // self._den
        return now

    def _advance_slow(self, target_ns: int | None, gate: Gate) -> int:
        """One step at a time: gate, before-hooks, step, after-hooks, waiters."""
        loop = self._loop
        ready: Any = loop._ready if loop is not None else ()
        step = self._step
        clients = self._clients
        self._advancing = True
        try:
            while True:
                if gate is not None and not gate(
                    self._base_ns + (self._steps + 1) * self._num // self._den
                ):
                    break
                if self._before:
                    self._run_hooks(self._before)
                try:
                    for cid in clients:
                        step(cid)
                except self._p.error as exc:
                    raise self._failure(exc, "stepSimulation") from exc
                self._steps += 1
                self._step_index += 1
                self._now = now = self._base_ns + self._steps * self._num // self._den
                if loop is not None:
                    # Hooks, predicates and the pacer read the loop's time during the advance.
                    loop._now_ns = now
                if self._after:
                    self._run_hooks(self._after)
                if self._waiters:
                    self._check_waiters(now)
                if ready or target_ns is None or now >= target_ns:
                    break
        finally:
            self._advancing = False
        return self._now

    def _failure(self, exc: BaseException, call: str) -> PhysicsError:
        pb = self._p
        for cid in self._clients:
            if not pb.isConnected(cid):
                return PhysicsError(
                    f"PyBullet physics client {cid} was disconnected while evclock was "
                    "stepping it (p.disconnect() was called, or its server or GUI window went "
                    "away); keep every client of a PyBulletTimeSource connected until the loop "
                    "closes"
                )
        return PhysicsError(f"PyBullet {call} failed on client(s) {self._clients}: {exc}")

    # ------------------------------------------------------------ step hooks

    def add_step_hook(
        self, fn: Callable[[], object], when: Literal["before", "after"] = "after"
    ) -> StepHook:
        """Call ``fn()`` before or after every physics step; returns a handle with ``remove()``.

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
                loop = self._loop
                if loop is None:
                    raise
                loop.call_exception_handler(
                    {
                        "message": f"evclock step hook {_describe_callable(hook._fn)} raised; "
                        "hook removed",
                        "exception": exc,
                    }
                )

    # ------------------------------------------------------------ waiting

    def time_of_step(self, count: int) -> Time:
        """The sim time ``count`` physics steps from now, at the current time step."""
        if isinstance(count, bool) or not isinstance(count, int):
            raise InvalidTypeError(f"step count must be an int, got {type(count).__name__}")
        if count < 0:
            raise InvalidArgumentError(f"step count must not be negative, got {count}")
        return Time._from_ns(self._base_ns + (self._steps + count) * self._num // self._den, SIM)

    async def sleep_steps(self, count: int) -> None:
        """Sleep exactly ``count`` physics steps (a sim-time sleep: a jump raises ClockJumped).

        Prefer it to ``clock.sleep(count * dt)`` when whole steps matter: a float ``dt`` such
        as 1/240 s rounds to a whole nanosecond *above* the exact step (4166667 ns vs
        4166666.67 ns), so ``sleep(1/240)`` may end one step later than intended.
        """
        when = self.time_of_step(count)
        loop = asyncio.get_running_loop()
        if self._loop is None or not self._loop._runs_on(loop):
            raise NotRunningError(self._wrong_loop("sleep_steps()"))
        if count < 1:
            raise InvalidArgumentError(f"sleep_steps() count must be >= 1, got {count}")
        await self._loop.clock.sleep_until(when)

    @staticmethod
    def _wrong_loop(what: str) -> str:
        return (
            f"{what} must be awaited in a task on the sim time this PyBulletTimeSource drives: "
            "the SimEventLoop of evclock.run(main(), source=source), or the loop of an "
            "evclock.SimDriver(source)"
        )

    async def wait_until(
        self, predicate: Callable[[], object], timeout: float | Duration | None = None
    ) -> Time:
        """Wait until ``predicate()`` is true; return the sim time at which it was.

        The predicate is evaluated now (returning at once if it holds), then after every
        physics step: the call resolves at the first step where it is true, e.g.
        ``await source.wait_until(lambda: bool(p.getContactPoints(gripper, cube)))``.
        ``timeout`` (sim seconds or a Duration) raises :class:`TimeoutError` at the first step
        at or after the deadline where the predicate is still false. If the predicate raises,
        the error is raised here. A clock jump (reset, restored state) raises
        :class:`ClockJumped`, like every pending sim-time wait.
        Costs nothing when no one waits.
        """
        if not callable(predicate):
            raise InvalidTypeError(
                f"wait_until() needs a callable predicate, got {type(predicate).__name__}"
            )
        deadline: int | None = None
        limit: Duration | None = None
        if timeout is not None:
            timeout_ns = to_nanoseconds(timeout, "wait_until() timeout")
            if timeout_ns < 0:
                raise InvalidArgumentError(
                    f"wait_until() timeout must not be negative, got {timeout!r}"
                )
            limit = Duration._from_ns(timeout_ns)
        loop = asyncio.get_running_loop()
        if self._loop is None or not self._loop._runs_on(loop):
            raise NotRunningError(self._wrong_loop("wait_until()"))
        if predicate():
            return Time._from_ns(self._now, SIM)
        if limit is not None:
            if limit.nanoseconds == 0:
                raise TimeoutError(self._timeout_message(predicate, limit))
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
            f"wait_until({_describe_callable(predicate)}) timed out: the predicate stayed "
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
                future.set_result(Time._from_ns(now, SIM))
            elif waiter.deadline_ns is not None and now >= waiter.deadline_ns:
                assert waiter.timeout is not None
                future.set_exception(
                    TimeoutError(self._timeout_message(waiter.predicate, waiter.timeout))
                )
            else:
                keep.append(waiter)
        self._waiters = keep
        self._update_slow()

    # ------------------------------------------------------ resets and states

    def _check_not_advancing(self, what: str) -> None:
        if self._advancing:
            raise PhysicsError(
                f"{what} cannot be called from a step hook or a wait_until() predicate: the "
                "physics is in the middle of advancing; call it from a task"
            )

    def reset_simulation(self, start: float | Duration | Time = 0) -> TimeJump | None:
        """``p.resetSimulation`` on every client, and move sim time to ``start`` (default 0).

        The world is emptied (bodies, constraints, gravity; PyBullet keeps the time step).
        Moving time is a jump (DESIGN section 7): jump handlers run, pending
        ``clock.sleep`` calls and :meth:`wait_until` waits raise :class:`ClockJumped`, rates
        and timers re-anchor. Returns the jump, or None when time did not move.
        """
        self._check_not_advancing("reset_simulation()")
        new_ns = self._time_arg(start, "reset_simulation() start")
        pb = self._p
        for cid in self._clients:
            try:
                pb.resetSimulation(physicsClientId=cid)
            except pb.error as exc:
                raise self._failure(exc, "resetSimulation") from exc
        return self._move_time(new_ns, 0)

    def save_state(self) -> int:
        """Snapshot every client (``p.saveState``) with the current sim time; return its id.

        :meth:`restore_state` brings the physics and the clock back to it. Snapshots live in
        memory until :meth:`remove_state` (PyBullet drops them on reset).
        """
        self._check_not_advancing("save_state()")
        pb = self._p
        ids: list[int] = []
        for cid in self._clients:
            try:
                ids.append(pb.saveState(physicsClientId=cid))
            except pb.error as exc:
                raise self._failure(exc, "saveState") from exc
        state_id = next(self._state_ids)
        self._states[state_id] = _SavedState(tuple(ids), self._now, self._step_index)
        return state_id

    def restore_state(self, state_id: int) -> TimeJump | None:
        """Restore a :meth:`save_state` snapshot (``p.restoreState``) and its sim time.

        Time moves back (or forward) to the saved time as a jump, like
        :meth:`reset_simulation`; returns the jump, or None when the saved time is the
        current one (then no wait is interrupted). The time step is not part of a snapshot:
        the current one goes on.
        """
        self._check_not_advancing("restore_state()")
        saved = self._saved(state_id)
        pb = self._p
        for cid, bullet_id in zip(self._clients, saved.bullet_ids, strict=True):
            try:
                pb.restoreState(stateId=bullet_id, physicsClientId=cid)
            except pb.error as exc:
                if not pb.isConnected(cid):
                    raise self._failure(exc, "restoreState") from exc
                raise PhysicsError(
                    f"PyBullet could not restore state {state_id} on client {cid}: a snapshot "
                    "only restores into the world it was taken from (same bodies, and not "
                    "after reset_simulation())"
                ) from exc
        return self._move_time(saved.time_ns, saved.step_index)

    def remove_state(self, state_id: int) -> None:
        """Free a snapshot (``p.removeState``); its id becomes unknown."""
        saved = self._saved(state_id)
        del self._states[state_id]
        pb = self._p
        for cid, bullet_id in zip(self._clients, saved.bullet_ids, strict=True):
            if pb.isConnected(cid):
                pb.removeState(bullet_id, physicsClientId=cid)

    def _saved(self, state_id: int) -> _SavedState:
        saved = self._states.get(state_id) if isinstance(state_id, int) else None
        if saved is None:
            raise InvalidArgumentError(
                f"unknown state id {state_id!r}: pass an id returned by save_state() of this "
                "source that was not removed"
            )
        return saved

    @staticmethod
    def _time_arg(value: object, what: str) -> int:
        if isinstance(value, Time):
            if value.clock_type is not SIM:
                raise InvalidArgumentError(
                    f"{what} must be a sim time, got a {value.clock_type.value} time"
                )
            return value.nanoseconds
        ns = to_nanoseconds(value, what)
        if ns < 0:
            raise InvalidArgumentError(f"{what} must not be negative, got {value!r}")
        return ns

    def _move_time(self, new_ns: int, step_index: int) -> TimeJump | None:
        def assign(ns: int) -> None:
            self._base_ns = self._now = ns
            self._steps = 0
            self._step_index = step_index

        loop = self._loop
        before = self._now
        jump: TimeJump | None = None
        if loop is None or loop.is_closed() or new_ns == before:
            assign(new_ns)
        else:
            jump = loop._jump_time(before, new_ns, assign)
            waiters, self._waiters = self._waiters, []
            self._update_slow()
            for waiter in waiters:
                if not waiter.future.done():
                    waiter.future.set_exception(ClockJumped(jump))
        # Snapshots do not hold the time step: go on with the engine's (re-read, to be safe).
        dt = self._read_time_step()
        if dt != self._dt:
            self._use_engine_time_step(dt)
        return jump

    # --------------------------------------------------------------- the rest

    def describe(self) -> str:
        clients = ", ".join(str(c) for c in self._clients)
        plural = "s" if len(self._clients) > 1 else ""
        dt = _format_seconds(Fraction(self._num, self._den) / _NS_PER_S)
        return f"PyBullet physics (client{plural} {clients}, dt={dt} s)"

    def close(self) -> None:
        """Disconnect the clients this source created (:meth:`connect`); others stay as they are."""
        if self._closed:
            return
        self._closed = True
        if self._owns_clients:
            pb = self._p
            for cid in self._clients:
                if pb.isConnected(cid):
                    pb.disconnect(cid)

    def __repr__(self) -> str:
        return f"<PyBulletTimeSource {self.describe()} now={Time._from_ns(self._now, SIM)}>"
