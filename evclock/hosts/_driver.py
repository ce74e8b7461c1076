"""Sim time on an event loop evclock does not own: a driver task steps and paces the simulation.

:class:`SimEventLoop` *is* the loop, so it sees everything and advances sim time only when
every task waits. An application whose loop is not ours (plain asyncio, uvloop, an ASGI
server, a notebook kernel that is already running) uses :class:`SimDriver` instead: one task
on that loop that owns sim time. evclock's own waits (``clock.sleep``, ``sleep_until``,
rates, timers) follow the driver's sim time; the loop's own timers - plain
``asyncio.sleep``, ``asyncio.timeout``, ``call_later`` - stay on wall time.

The driver repeats one cycle:

1. wake every ``clock.sleep`` due at the current sim time ``t`` (FIFO among equal deadlines);
2. *settle*: yield to the loop until the woken work is done at ``t`` (see below);
3. wake the ``run_until()`` callers due at ``t`` and settle again;
4. advance: jump to the next deadline (virtual time) or take physics steps (PyBullet),
   paced by :class:`~evclock.kernel._pacing.Pacer`; a pacing wait is an ``asyncio`` wait on the
   host loop, so I/O keeps flowing.

The driver is a host of the simulation kernel (:class:`~evclock.kernel._core.SimCore`), like
:class:`SimEventLoop`: the kernel holds the deadlines, the source, pacing and jumps, and
decides each advance; the driver supplies how to wait (``asyncio`` waits on the host loop)
and whether anything else is runnable.

Settling is how lockstep is approximated on a loop we cannot drive. On loops built on
``asyncio.BaseEventLoop`` the driver reads the loop's ready queue: it is settled when nothing
but itself is runnable (exact). On other loops (uvloop) it inspects the tasks instead: settled
when every other task is done or suspended on a future that is still pending, three checks in
a row (a chain of up to two plain callbacks - ``gather``, ``wait_for`` - is not visible in
tasks, so quiet must last). Either way at most ``max_settle_yields`` yields are spent; then
time advances anyway (counted in :attr:`SimDriver.lockstep_overruns`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import threading
import time
from collections.abc import Callable, Generator, Iterator
from types import TracebackType
from typing import Any, Final

from evclock._cpython import (
    UNKNOWN,
    loop_ready_queue,
    loop_thread_id,
    running_loop,
    task_waiter,
)
from evclock._errors import (
    ClockJumpedError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
    NotRunningError,
    SimDriverError,
    WrongThreadError,
)
from evclock.hosts._current import attach_clock, attached_clock, detach_clock
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._clock import Clock, SimClock
from evclock.kernel._core import DUE, HELD, MOVED, PACING, WAIT_SOURCE, Settling, SimCore
from evclock.kernel._pacing import DEFAULT_MAX_LAG, PacingControls
from evclock.kernel._source import TimeSource
from evclock.kernel._virtual import source_or_virtual
from evclock.time._time import MAX_TIME_NS, SIM, Duration, Time, new_time, to_sim_time_ns

#: Default bound of loop iterations the driver yields, after waking the tasks due at one sim
#: time, for that work to settle before it advances sim time anyway.
DEFAULT_MAX_SETTLE_YIELDS: Final = 100
#: Consecutive quiet checks needed when the loop's ready queue cannot be read (uvloop).
_QUIET_CHECKS_BY_TASKS: Final = 3
_NEW, _RUNNING, _STOPPED = "new", "running", "stopped"
#: ``notify_before`` while the driver waits for nothing in particular: any new deadline counts.
_ANY_DEADLINE: Final = MAX_TIME_NS + 1
#: While an external source waits for the outside, ask it again this often (wall seconds).
_EXTERNAL_POLL: Final = 0.05


class SimDriverClock(SimClock):
    """The sim clock of a :class:`SimDriver`: what :func:`evclock.clock` and
    :func:`evclock.sim_clock` return on the loop the driver runs on.

    A :class:`SimClock` whose waits must be awaited on the driver's loop while it runs.
    """

    def __init__(self, driver: SimDriver) -> None:
        super().__init__(driver._core, driver)
        self._driver = driver

    @property
    def driver(self) -> SimDriver:
        """The driver that owns this clock (pause, step, rtf)."""
        return self._driver

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the driver runs (or ran) on."""
        loop = self._driver.loop
        if loop is None:
            raise NotRunningError(
                "this SimDriver has not started yet, so its clock has no event loop; start it "
                "first (async with evclock.SimDriver() as sim: ...)"
            )
        return loop

    def __repr__(self) -> str:
        return f"<SimDriverClock now={self.now()} source={self._driver.source.describe()}>"


class _WakeProbe:
    """True once a task became runnable during an advance (for loops without a ready queue).

    Sources check ``loop._ready`` between physics steps so that a step hook waking a task
    stops the advance. Without a readable ready queue, the probe snapshots the futures the
    other tasks wait on (at its first check) and reports when one of them is done.
    """

    __slots__ = ("_driver", "_futures")

    def __init__(self, driver: SimDriver) -> None:
        self._driver = driver
        self._futures: list[asyncio.Future[Any]] | None = None

    def arm(self) -> None:
        self._futures = None

    def __bool__(self) -> bool:
        futures = self._futures
        if futures is None:
            futures = self._futures = []
            loop = self._driver._loop
            assert loop is not None
            me = asyncio.current_task(loop)
            for task in asyncio.all_tasks(loop):
                if task is me:
                    continue
                waiter = task_waiter(task)
                if waiter is None:
                    return True
                if waiter is not UNKNOWN:
                    futures.append(waiter)
        return any(f.done() for f in futures)


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class SimDriver(PacingControls):
    """Drives simulation time from a task on an event loop evclock does not own.

    For applications whose loop is not a :class:`SimEventLoop` - plain asyncio, uvloop, an
    ASGI server's loop, a notebook kernel's loop that is already running::

        async with evclock.SimDriver(rtf=None) as sim:
            task = asyncio.create_task(controller())   # evclock.clock() is sim.clock here
            await sim.run_until(5.0)

    **What follows sim time.** ``sim.clock`` - also what :func:`evclock.clock` and
    :func:`evclock.sim_clock` return on this loop while the driver runs - and everything built
    on it: ``clock.sleep``, ``sleep_until``, ``clock.rate``, ``clock.timer``. **What does not:**
    the loop's own timers - plain ``asyncio.sleep``, ``asyncio.timeout``, ``wait_for``,
    ``call_later`` and anyio's sleeps - stay on *wall* time (evclock does not own this loop's
    clock). With ``rtf=None`` a plain ``await asyncio.sleep(0.05)`` lets as much sim time
    pass as the driver can compute in 50 ms; use ``clock.sleep`` in controllers.

    **How it advances.** A cycle: wake the ``clock.sleep`` waits due at the current sim time
    ``t`` (in deadline order, FIFO among equal deadlines), let the woken work settle, then
    advance. Virtual time jumps exactly to the next deadline; a PyBullet source steps the
    physics in whole steps toward it (sleeps quantise up to step boundaries) and keeps
    stepping, one step per cycle, when nothing is scheduled. Virtual time with nothing
    scheduled stands still - no deadlock error, since I/O may still come - until a task
    sleeps on sim time. Pacing uses the same :class:`~evclock.kernel._pacing.Pacer` as
    :class:`SimEventLoop` (``rtf``, ``max_lag``, ``strict``; ``wall`` is the clock it reads);
    its waits are ``asyncio`` waits on the host loop, so I/O keeps flowing, and a sleep
    registered meanwhile for an earlier time cuts the wait short. Each cycle yields to the
    loop at least once, also with ``rtf=None``, so the application stays responsive.

    **Lockstep, approximated.** After waking the tasks due at ``t`` the driver yields
    (``await asyncio.sleep(0)``) until that work settled, re-firing sleeps due at ``t``
    (``clock.sleep(0)``) as it goes: on loops derived from ``asyncio.BaseEventLoop`` until the
    loop's ready queue is empty - nothing but the driver is runnable, which includes tasks
    the woken ones created, queues and events they set, and callbacks; on other loops
    (uvloop) until, three checks in a row, every other task is done or suspended on a still
    pending future. Work that waits on something outside (I/O, wall-time sleeps, threads)
    counts as settled: sim time does not wait for it - wrap such work in
    :meth:`hold_time` to make it. After ``max_settle_yields`` yields time advances anyway
    (a task spinning on ``asyncio.sleep(0)`` would otherwise stop the simulation); each such
    advance is counted in :attr:`lockstep_overruns`. Unrelated busy work on the loop (a
    server handling requests) delays advances the same way.

    **Jumps.** A source that jumps (``VirtualTimeSource.set_time``, a PyBullet reset or
    restored state) runs the jump handlers, wakes every pending ``clock.sleep`` with
    :class:`ClockJumpedError` and re-anchors rates, timers and pacing, as on a SimEventLoop.

    **run_until.** ``await sim.run_until(t)`` returns once sim time reached ``t`` *and* the
    work due at ``t`` has settled, so the caller sees the state at ``t``; the driver goes
    on afterwards. On a paused driver it advances to ``t`` (exactly on virtual time) and
    stays paused: ``SimDriver(paused=True)`` plus ``run_until`` is the notebook workflow.

    **Life cycle.** A driver runs once: ``async with`` (or :meth:`start`, or the first
    :meth:`run_until`) attaches the source and the clock to the running loop; :meth:`stop`
    (or leaving the ``async with``) ends the driver task, cancels the sim-time waits still
    pending and those started while it stops (their tasks get ``CancelledError``;
    :meth:`run_until` raises :class:`LoopClosedError`), lets those tasks finish, and
    restores the loop's previous clock; later waits on the clock raise
    :class:`LoopClosedError`. The source is detached, not closed: a new
    ``SimDriver(source)`` can go on from the same time (close a PyBullet source you connected
    yourself). If the driver fails (a :class:`LagError` in strict mode, a
    :class:`PhysicsError`), pending waits and :meth:`run_until` raise that error and
    :meth:`stop` re-raises it unless :meth:`run_until` already did.

    **Threads.** The controls (:meth:`pause`, :meth:`resume`, :meth:`step`,
    :meth:`step_until`, ``rtf``, :meth:`achieved_rtf`) and :meth:`hold_time` are
    thread-safe: a GUI or operator thread calls them directly and the driver wakes at once.
    Waits (:meth:`run_until`, ``clock.sleep``) and :meth:`stop` are awaited on the driver's
    loop; from another thread they raise :class:`WrongThreadError` - hand them to the loop
    with ``asyncio.run_coroutine_threadsafe(sim.run_until(t), sim.loop)``.

    :param source: what owns sim time; default a :class:`VirtualTimeSource` starting at 0.
    :param rtf: real-time factor: None = as fast as possible, 1.0 = real time, k = k x.
    :param max_lag: wall seconds a paced run may fall behind before re-anchoring (or raising).
    :param strict: raise :class:`LagError` when lagging more than ``max_lag`` behind ``rtf``.
    :param paused: start paused (see :meth:`resume`, :meth:`step`, :meth:`run_until`).
    :param max_settle_yields: bound of loop iterations spent letting the work of one sim time
        settle before advancing anyway.
    :param wall: the wall clock pacing reads, in seconds (default ``time.perf_counter``).
    """

    def __init__(
        self,
        source: TimeSource | None = None,
        *,
        rtf: float | None = 1.0,
        max_lag: float = DEFAULT_MAX_LAG,
        strict: bool = False,
        paused: bool = False,
        max_settle_yields: int = DEFAULT_MAX_SETTLE_YIELDS,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        source = source_or_virtual(source)
        if isinstance(max_settle_yields, bool) or not isinstance(max_settle_yields, int):
            raise InvalidTypeError(
                f"max_settle_yields must be an int, got {type(max_settle_yields).__name__}"
            )
        if max_settle_yields < 1:
            raise InvalidArgumentError(f"max_settle_yields must be >= 1, got {max_settle_yields}")
        if not callable(wall):
            raise InvalidTypeError(
                f"wall must be a callable returning seconds, got {type(wall).__name__}"
            )
        self._source = source
        self._core = SimCore(source, self, rtf=rtf, strict=strict, max_lag=max_lag, wall=wall)
        self._core.future_factory = self._new_future
        if paused:
            self._core.pacer.pause()
        self._max_settle_yields = max_settle_yields
        self._clock = SimDriverClock(self)
        self._state = _NEW
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._wakeup: asyncio.Future[None] | None = None
        self._ready_queue: collections.deque[Any] | None = None
        self._settling = Settling(1, max_settle_yields)
        self._probe = _WakeProbe(self)
        self._overran = False
        self._holds = 0
        self._holds_lock = threading.Lock()
        self._draining = False
        self._step_until_ns: int | None = None
        self._previous_clock: Clock | None = None
        self._error: Exception | None = None
        self._error_reported = False
        self._lockstep_overruns = 0
        self._step_waiters: list[asyncio.Future[None]] = []

    # ------------------------------------------------------------ properties

    @property
    def clock(self) -> SimDriverClock:
        """The sim clock (what :func:`evclock.clock` returns on the driver's loop)."""
        return self._clock

    @property
    def source(self) -> TimeSource:
        """The time source this driver advances."""
        return self._source

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        """The event loop the driver runs (or ran) on; None before it started."""
        return self._loop

    @property
    def now_ns(self) -> int:
        """Sim time in integer nanoseconds."""
        return self._core.now_ns

    def now(self) -> Time:
        """Current sim time."""
        return new_time(self._core.now_ns, SIM)

    @property
    def running(self) -> bool:
        """True between start and stop."""
        return self._state is _RUNNING

    @property
    def lockstep_overruns(self) -> int:
        """How many times sim time advanced before the work of the previous sim time had
        settled (``max_settle_yields`` reached); 0 means every advance was in lockstep."""
        return self._lockstep_overruns

    def __repr__(self) -> str:
        pacer = self._core.pacer
        rtf = "None" if pacer.rtf is None else f"{pacer.rtf:g}"
        paused = " paused" if pacer.paused else ""
        return (
            f"<SimDriver {self._state}{paused} now={self.now()} rtf={rtf} "
            f"source={self._source.describe()}>"
        )

    # ------------------------------------------------------------ life cycle

    async def __aenter__(self) -> SimDriver:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    def start(self) -> asyncio.Task[None]:
        """Start the driver task on the running loop and attach the clock to that loop."""
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            raise NotRunningError(
                "SimDriver.start() needs a running event loop; call it from a coroutine "
                "(async with evclock.SimDriver() as sim: ...)"
            ) from None
        if self._state is _RUNNING:
            raise SimDriverError(
                "this SimDriver is already running; a driver is started once (by async with, "
                "start() or run_until())"
            )
        if self._state is _STOPPED:
            raise LoopClosedError(self._stopped_message())
        if isinstance(loop, SimEventLoop):
            raise SimDriverError(
                "SimDriver drives sim time on loops evclock does not own, but this loop is a "
                "SimEventLoop, whose time already is sim time; use evclock.clock() and the "
                "loop's pause(), step() and rtf instead"
            )
        previous = attached_clock(loop)
        if isinstance(previous, SimDriverClock):
            raise SimDriverError(
                "another SimDriver is already running on this event loop; stop it first "
                "(one sim clock per loop)"
            )
        source = self._source
        source.attach(self._core)  # the driver's kernel is the source's host
        self._core.now_ns = source.now_ns  # the source may have moved since (a former driver)
        self._loop = loop
        self._ready_queue = loop_ready_queue(loop)
        # Exact where the ready queue is visible; by tasks, quiet must last (see the module).
        needed = 1 if self._ready_queue is not None else _QUIET_CHECKS_BY_TASKS
        self._settling = Settling(needed, self._max_settle_yields)
        self._previous_clock = previous
        attach_clock(loop, self._clock)
        self._state = _RUNNING
        self._task = task = loop.create_task(self._run(), name="evclock-sim-driver")
        task.add_done_callback(self._on_task_done)
        return task

    def _on_task_done(self, task: asyncio.Task[None]) -> None:
        # A task cancelled before its first step never ran _run's cleanup: do it here.
        if self._state is _RUNNING:
            self._shutdown(None if task.cancelled() else task.exception())

    async def stop(self) -> None:
        """Stop the driver: end its task, cancel pending sim-time waits, restore the loop's clock.

        Returns once the tasks whose waits were cancelled have finished (within
        ``max_settle_yields`` loop iterations). Idempotent; re-raises the error the driver
        failed with, unless :meth:`run_until` already raised it.
        """
        if self._state is _NEW:
            self._state = _STOPPED
            return
        self._check_loop_thread("stop()")
        task = self._task
        assert task is not None
        if not task.done():
            self._stopping = True
            self._draining = True  # waits started while stopping are cancelled at once
            self._wake_driver()
            try:
                await asyncio.wait((task,))
                await self._settle(stop_early=False)
            finally:
                self._draining = False
        if not task.cancelled():
            task.exception()  # retrieved here: the error is handled below
        error = self._error
        if error is not None and not self._error_reported:
            self._error_reported = True
            raise error

    async def run_until(self, when: float | Time) -> None:
        """Wait until sim time reaches ``when`` (seconds or a sim :class:`Time`); start if needed.

        Returns once the work due at ``when`` has settled too (the controllers' ticks at
        ``when`` have run), so the caller sees the state at ``when``. Other tasks keep
        running meanwhile, and the driver keeps going afterwards unless paused. If the driver
        is paused, it advances to ``when`` - exactly on virtual time, to the first step
        boundary at or after it with physics - and stays paused there: the notebook
        workflow, ``sim = SimDriver(paused=True)`` then ``await sim.run_until(5.0)``. A
        backward jump meanwhile does not end the wait: it goes on until time reaches
        ``when`` again.
        """
        when_ns = self._target_ns(when)
        self._check_loop_thread("run_until(t)")
        if self._state is _STOPPED:
            raise LoopClosedError(self._stopped_message())
        if self._state is _NEW:
            self.start()
        core = self._core
        while core.now_ns < when_ns:
            if core.pacer.paused:
                self._extend_step_until(when_ns)
            self._check_can_wait()
            fut = core.wait_settled(when_ns)
            try:
                await fut
            except ClockJumpedError:
                continue
            except Exception as exc:
                if exc is self._error:
                    self._error_reported = True
                raise

    @staticmethod
    def _target_ns(when: object) -> int:
        if isinstance(when, Duration):
            raise InvalidTypeError(
                "run_until() needs a sim Time or seconds since the sim epoch, got Duration; "
                "to run for a duration use run_until(sim.now() + duration)"
            )
        return to_sim_time_ns(when, "run_until() time")

    def _check_loop_thread(self, what: str) -> None:
        """Refuse to await ``what`` anywhere but on the driver's running loop."""
        loop = self._loop
        if self._state is not _RUNNING or loop is None:
            return
        if running_loop() is not loop:
            raise WrongThreadError(
                f"SimDriver.{what} must be awaited on the event loop the driver runs on, "
                "but it was called from another thread (or loop); hand it to the driver's "
                f"loop with asyncio.run_coroutine_threadsafe(sim.{what}"
                ", sim.loop).result(timeout), or call the thread-safe controls (pause(), "
                "resume(), step(), step_until(), rtf) directly"
            )

    def _stopped_message(self) -> str:
        message = (
            "this SimDriver is stopped and cannot be used again; create a new SimDriver "
            "(it can take over the same time source)"
        )
        if self._error is not None:
            message += f"; it stopped because of {type(self._error).__name__}: {self._error}"
        return message

    # ------------------------------------------------------------ controls

    def _require_running(self, what: str) -> None:
        if self._state is _RUNNING:
            return
        if self._state is _STOPPED:
            raise LoopClosedError(self._stopped_message())
        raise NotRunningError(
            f"{what} needs a running SimDriver; start it first (async with "
            "evclock.SimDriver() as sim: ..., or sim.start()), or create it with paused=True "
            "to start paused"
        )

    def step(self, count: int = 1) -> Steps:  # type: ignore[override]  # None -> awaitable
        """While paused, let sim time advance ``count`` increments (physics steps, or jumps to
        the next deadline on virtual time), then stay paused. Thread-safe.

        Returns a :class:`Steps`: ``await sim.step(5)`` (on the driver's loop) returns once
        the five steps are taken and the work they woke has settled, so the caller sees the
        state after them; not awaiting it just requests the steps, as before.

        :param count: how many increments (at least 1).
        :returns: an awaitable that is done when the steps are taken.
        :raises InvalidTypeError: ``count`` is not an int.
        :raises InvalidArgumentError: ``count`` is below 1.
        :raises PacingError: the driver is not paused.
        """
        super().step(count)
        return Steps(self)

    async def _steps_taken(self) -> None:
        self._check_loop_thread("await step(n)")
        if self._state is _STOPPED:
            raise LoopClosedError(self._stopped_message())
        pacer = self._core.pacer
        if not pacer.paused or pacer.waits_for_control():
            return  # already taken (or resumed meanwhile: the steps are moot)
        fut = self._new_future()
        self._step_waiters.append(fut)
        await fut

    def _steps_settled(self) -> None:
        """Resolve the ``await step(n)`` waits once the steps are taken (after a settle)."""
        pacer = self._core.pacer
        if pacer.paused and not pacer.waits_for_control():
            return
        waiters, self._step_waiters = self._step_waiters, []
        for fut in waiters:
            _resolve(fut)

    def _on_host_thread(self) -> bool:
        loop = self._loop
        thread_id = loop_thread_id(loop)
        if thread_id is not UNKNOWN:
            return thread_id is None or thread_id == threading.get_ident()
        # Loops that do not say which thread runs them (uvloop): the caller is on the
        # driver's loop exactly when that loop is running in the caller's thread.
        return running_loop() is loop

    def _call_on_host(self, what: str, reaction: Callable[[], None]) -> None:
        # The same mechanism as SimEventLoop's: the pacer changed in the calling thread;
        # the driver's reaction (waking its wait) runs on the loop's thread.
        loop = self._loop
        assert loop is not None
        try:
            loop.call_soon_threadsafe(reaction)
        except RuntimeError:  # the loop closed meanwhile
            raise LoopClosedError(
                f"SimDriver.{what} was called from another thread after the driver's event "
                "loop closed; there is nothing left to control"
            ) from None

    def _pacing_changed(self) -> None:
        if self._core.pacer.run_until_ns is None:
            self._step_until_ns = None  # pause() and resume() end a step_until()
        self._wake_driver()

    def _stepping_until(self, when_ns: int) -> None:
        self._step_until_ns = when_ns
        self._core.stop_at(when_ns)  # stop exactly there
        self._wake_driver()

    def _extend_step_until(self, when_ns: int) -> None:
        if self._step_until_ns is None or self._step_until_ns < when_ns:
            pacer = self._core.pacer
            pacer.run_until(when_ns)
            self._step_until_ns = when_ns
            pacer.reanchor()
            self._wake_driver()

    @contextlib.contextmanager
    def hold_time(self) -> Iterator[None]:
        """Keep sim time from advancing while the block runs (thread-safe).

        The driver cannot see work outside the loop (threads, executor jobs, a reply from
        another process): wrap it to keep it in lockstep, e.g.
        ``with sim.hold_time(): data = await asyncio.to_thread(read_sensor)``, or use it
        in the thread doing that work.
        """
        with self._holds_lock:
            self._holds += 1
        try:
            yield
        finally:
            with self._holds_lock:
                self._holds -= 1
                last = not self._holds
            if last:
                if self._on_host_thread():
                    self._wake_driver()
                elif self._state is _RUNNING:
                    with contextlib.suppress(LoopClosedError):  # closed: nothing to wake
                        self._call_on_host("hold_time()", self._wake_driver)

    # ------------------------------------------------ what the kernel asks the driver

    def _new_future(self) -> asyncio.Future[None]:
        """A future for a sim-time wait (every wait on this driver's clock starts here)."""
        loop = self._loop
        if self._state is not _RUNNING or running_loop() is not loop:
            return self._wait_refused()
        assert loop is not None
        return loop.create_future()

    def _anything_runnable(self) -> bool:
        """Whether a task became runnable (a stepping source stops stepping then). False
        after a lockstep overrun: time advances anyway."""
        if self._overran:
            return False
        ready = self._ready_queue
        return bool(ready) if ready is not None else bool(self._probe)

    def _held_horizon(self, paused: bool) -> int | None:
        """0 while :meth:`hold_time` holds sim time, else None (the driver sees no threads:
        ``paused`` changes nothing here)."""
        return 0 if self._holds > 0 else None

    def _before_moving(self) -> None:
        """Nothing to take in: the host loop serves its own I/O while the driver yields."""

    def _could_wake(self) -> bool:
        """Always: the host loop may serve I/O the driver cannot see, so idle is no deadlock."""
        return True

    def _interrupt_wait(self) -> None:
        """End the driver's current wait (an earlier deadline, a jump, news from outside)."""
        self._wake_driver()

    def _serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` may wait on this driver's sim time (for sources)."""
        return self._state is _RUNNING and loop is self._loop

    def _is_closed(self) -> bool:
        """True once stopped (a source then moves its time without a jump)."""
        return self._state is _STOPPED

    def _call_exception_handler(self, context: dict[str, Any]) -> None:
        """Report an error from a source (a failing step hook) to the host loop."""
        loop = self._loop
        assert loop is not None
        loop.call_exception_handler(context)

    def _wait_refused(self) -> asyncio.Future[None]:
        loop = self._loop
        if self._draining and loop is not None and running_loop() is loop:
            fut: asyncio.Future[None] = loop.create_future()
            fut.cancel()
            return fut
        self._check_can_wait()
        raise AssertionError("unreachable")

    def _check_can_wait(self) -> None:
        if self._state is _RUNNING and running_loop() is self._loop:
            return
        if self._state is _STOPPED:
            raise LoopClosedError(self._stopped_message())
        if self._state is _NEW:
            raise NotRunningError(
                "this SimDriver is not running: start it (async with evclock.SimDriver() as "
                "sim: ..., or sim.start()) before waiting on its clock"
            )
        raise NotRunningError(
            "this SimDriver's clock can only be waited on from the event loop the driver "
            "runs on (in its thread)"
        )

    def _wake_driver(self) -> None:
        """End the driver's current wait (a control changed, stop(), an earlier deadline)."""
        fut = self._wakeup
        if fut is not None and not fut.done():
            fut.set_result(None)

    async def _wait(self, timeout: float | None, notify_before: int) -> None:
        """Wait up to ``timeout`` wall seconds (None: no limit) or until woken: a control
        changed, stop() was called, or a deadline before ``notify_before`` was scheduled."""
        loop = self._loop
        assert loop is not None
        fut: asyncio.Future[None] = loop.create_future()
        self._wakeup = fut
        core = self._core
        core.notify_before = notify_before
        handle = None if timeout is None else loop.call_later(timeout, _resolve, fut)
        try:
            await fut
        finally:
            self._wakeup = None
            core.notify_before = -1
            if handle is not None:
                handle.cancel()

    # ------------------------------------------------------------ the engine

    def _quiescent(self) -> bool:
        """Nothing but the current task can run now (as far as this loop lets us see)."""
        ready = self._ready_queue
        if ready is not None:
            return not ready
        loop = self._loop
        assert loop is not None
        me = asyncio.current_task(loop)
        for task in asyncio.all_tasks(loop):
            if task is me:
                continue
            waiter = task_waiter(task)
            if waiter is None or (waiter is not UNKNOWN and waiter.done()):
                return False
        return True

    async def _settle(self, *, stop_early: bool) -> None:
        """Yield until the work woken at the current sim time is done, as the kernel's
        :class:`~evclock.kernel._core.Settling` rule says (bounded)."""
        settling = self._settling
        settling.start()
        self._overran = False
        core = self._core
        while True:
            await asyncio.sleep(0)
            if stop_early and self._stopping:
                return
            # clock.sleep(0) and sleep_until(now) wake like a yield
            woke = core.due_now() and core.wake_due()
            if settling.observe(woke, not woke and self._quiescent()):
                break
        if settling.overran and stop_early:
            self._overran = True
            self._lockstep_overruns += 1

    async def _run(self) -> None:
        core = self._core
        error: BaseException | None = None
        try:
            while True:
                core.wake_due()
                await self._settle(stop_early=True)
                if self._stopping:
                    return
                if self._step_waiters:
                    self._steps_settled()
                if core.settled_due_now() and core.wake_settled():
                    continue
                self._probe.arm()
                outcome = core.advance()
                if outcome in (DUE, MOVED):
                    continue
                if outcome == HELD:
                    # Time is held; waits due now (clock.sleep(0)) still wake.
                    await self._wait(None, core.now_ns + 1)
                elif outcome == PACING:
                    target = core.next_deadline()
                    await self._wait(core.pacing_delay, _ANY_DEADLINE if target is None else target)
                elif outcome == WAIT_SOURCE:
                    await self._wait(_EXTERNAL_POLL, _ANY_DEADLINE)
                else:  # nothing scheduled and time cannot move on its own: wait for a wait
                    await self._wait(None, _ANY_DEADLINE)
                    core.pacer.reanchor()  # standing still with nothing scheduled is not lag
        except BaseException as exc:
            error = exc
            raise
        finally:
            self._shutdown(error)

    def _shutdown(self, error: BaseException | None) -> None:
        self._state = _STOPPED
        self._stopping = True
        failure = error if isinstance(error, Exception) else None
        self._error = failure
        waiters, self._step_waiters = self._step_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_exception(
                    failure
                    or LoopClosedError("the SimDriver was stopped before the steps were taken")
                )
        self._core.end_waits(
            failure,
            lambda: LoopClosedError(
                "the SimDriver was stopped before sim time reached the run_until() target"
            ),
        )
        source = self._source
        if source.host is self._core:
            source.detach()  # the source keeps its time for a next host
        loop = self._loop
        assert loop is not None
        if attached_clock(loop) is self._clock:
            if self._previous_clock is not None:
                attach_clock(loop, self._previous_clock)
            else:
                detach_clock(loop)


class Steps:
    """What :meth:`SimDriver.step` returns: awaiting it (on the driver's loop) waits until
    the requested steps are taken and the work they woke has settled.

    :param driver: the driver the steps were requested from.
    """

    __slots__ = ("_driver",)

    def __init__(self, driver: SimDriver) -> None:
        self._driver = driver

    def __await__(self) -> Generator[Any, None, None]:
        return self._driver._steps_taken().__await__()

    def __repr__(self) -> str:
        return f"<Steps of {self._driver!r}>"
