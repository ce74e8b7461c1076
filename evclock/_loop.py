"""The simulation event loop: a real asyncio loop whose ``time()`` is simulation time.

How one iteration works (DESIGN section 4):

1. Run everything ready at the current sim time ``t``.
2. Poll real I/O without blocking; what arrives is handled at ``t``.
3. If work outside the loop is in flight (executor jobs, explicit holds, busy threads),
   wait for it in wall time without moving sim time.
4. Otherwise advance: the time source jumps (virtual time) or steps the physics toward the
   next deadline, paced as requested; I/O is served while pacing waits.
5. If nothing can ever happen - a deadlock - raise :class:`DeadlockError` naming the tasks.

Scheduling is ours: one heap of ``(when_ns, seq, kind, obj)`` entries in integer
nanoseconds, where ``seq`` makes timers due at the same time fire in the order they were
scheduled. ``kind`` 0 is a sleep future resolved in place (``clock.sleep``); kind 1 a
``TimerHandle`` (``call_at``, ``call_later``, ``asyncio.sleep``, timeouts). This is why
``_run_once`` is overridden rather than merely the selector: asyncio's own heap orders
timers by float ``when`` only, which is neither FIFO on ties nor exact.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import contextvars
import heapq
import itertools
import math
import selectors
import threading
import time
from asyncio import base_events, events, futures
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, TypeVar, TypeVarTuple, Unpack

from ._errors import (
    DeadlockError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
    NotRunningError,
    StallError,
)
from ._jumps import JumpHandle, TimeJump
from ._outside import EXACT, OutsideWork
from ._pacing import DEFAULT_MAX_LAG, Pacer, PacingControls, check_max_lag, check_rtf
from ._tasks import describe_tasks
from ._threads import EVENT_LOOP_WAITS, check_thread_inference, could_call_back, internal_count
from ._time import SIM, Time
from .sources import TimeSource, VirtualTimeSource

if TYPE_CHECKING:
    from ._clock import SimClock

_T = TypeVar("_T")
_Ts = TypeVarTuple("_Ts")

_SET_RESULT_UNLESS_CANCELLED = futures._set_result_unless_cancelled  # type: ignore[attr-defined]
_SLEEP, _HANDLE = 0, 1
# Read on every advance: threading.active_count() would take a lock each time.
_thread_registry: dict[int, threading.Thread] = threading._active  # type: ignore[attr-defined]
_thread_limbo: dict[threading.Thread, threading.Thread] = threading._limbo  # type: ignore[attr-defined]

#: Default wall-time limit for sim time being held by outside work or an I/O wait.
DEFAULT_STALL_TIMEOUT = 60.0
#: Wall seconds between the two looks that confirm a deadlock (see _wait_for_io_or_deadlock).
_DEADLOCK_CONFIRM = 0.02
#: While a thread (not an executor job) holds time, re-check it this often (wall seconds).
_THREAD_POLL = 0.001


def _check_stall_timeout(value: object) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidTypeError(
            f"stall_timeout must be seconds (a number) or None, got {type(value).__name__}"
        )
    if math.isnan(value) or value <= 0:
        raise InvalidArgumentError(
            f"stall_timeout must be a positive number of wall seconds or None, got {value!r}"
        )
    return float(value)


class SimEventLoop(PacingControls, asyncio.SelectorEventLoop):
    """An asyncio event loop whose clock is simulation time.

    ``asyncio.sleep``, ``asyncio.timeout``, ``wait_for``, ``call_later``/``call_at`` and
    anyio's time functions all follow sim time on it. Time only moves when every task waits
    (lockstep), exactly to the next deadline (virtual time) or in physics steps.

    Create it directly, through ``asyncio.Runner(loop_factory=evclock.loop_factory(...))``
    or with :func:`evclock.run`.

    :param source: what owns sim time; default a :class:`VirtualTimeSource` starting at 0.
    :param rtf: real-time factor: None = as fast as possible, 1.0 = real time, k = k x.
    :param strict: raise :class:`LagError` when lagging more than ``max_lag`` behind ``rtf``.
    :param max_lag: wall seconds a paced run may fall behind before re-anchoring (or raising).
    :param stall_timeout: wall seconds sim time may be held by outside work (threads,
        executor jobs) or by waiting for I/O before :class:`StallError`; None waits forever.
    :param paused: start paused (see :meth:`resume` and :meth:`step`).
    :param watch_threads: hold sim time while other non-daemon threads are busy (default).
    :param selector: the selector serving I/O (default: the platform's best). It may also
        be passed as the first positional argument, as to ``asyncio.SelectorEventLoop``.
    :param wall: the wall clock pacing reads, in seconds (default ``time.perf_counter``);
        tests inject a fake one.
    """

    if TYPE_CHECKING:
        # asyncio internals this loop works with (they have no public equivalent).
        _ready: collections.deque[asyncio.Handle]
        _scheduled: list[Any]
        _stopping: bool
        _closed: bool
        _timer_cancelled_count: int
        _selector: selectors.BaseSelector
        _thread_id: int | None
        _current_handle: asyncio.Handle | None
        _debug: bool

        def _check_thread(self) -> None: ...
        def _write_to_self(self) -> None: ...

        def _process_events(self, event_list: list[Any]) -> None: ...
        def _check_callback(self, callback: object, method: str) -> None: ...

    def __init__(
        self,
        source: TimeSource | None = None,
        *,
        rtf: float | None = None,
        strict: bool = False,
        max_lag: float = DEFAULT_MAX_LAG,
        stall_timeout: float | None = DEFAULT_STALL_TIMEOUT,
        paused: bool = False,
        watch_threads: bool = True,
        selector: Any = None,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        if isinstance(source, selectors.BaseSelector) and selector is None:
            # OUTSIDE HOOK: SimEventLoop(selector), like SelectorEventLoop(selector).
            source, selector = None, source
        if source is None:
            source = VirtualTimeSource()
        elif not isinstance(source, TimeSource):
            raise InvalidTypeError(
                f"source must be a TimeSource (e.g. VirtualTimeSource(), PyBulletTimeSource(...)), "
                f"got {type(source).__name__}"
            )
        # Validate everything before the selector (a resource) exists; until then the loop
        # counts as closed, so a rejected loop's __del__ has nothing to complain about.
        self._closed = True
        self._stall_timeout = _check_stall_timeout(stall_timeout)
        check_rtf(rtf)
        check_max_lag(max_lag)
        if watch_threads:
            check_thread_inference()
        self._now_ns: int = source.now_ns
        source.attach(self)  # may refuse (a source drives one loop): before the selector too
        super().__init__(selector)
        self._source = source
        self._seq = itertools.count().__next__
        # Registered file descriptors, read on every iteration: the selector's own dict when
        # it exposes one (all stdlib selectors do), else its public mapping view. The
        # self-pipe is always registered, so "real I/O" means more than one entry.
        self._io_map: Any = getattr(self._selector, "_fd_to_key", None) or self._selector.get_map()
        self._pacer = Pacer(
            self._wait_io, self._get_now_ns, rtf=rtf, strict=strict, max_lag=max_lag, wall=wall
        )
        if paused:
            self._pacer.pause()
        self._advance_directly = self._jump_when_idle = False
        self._update_fast_path()
        self._held_since: float | None = None
        # OUTSIDE HOOK: registered fds that deliver nothing by themselves: the self-pipe,
        # until a signal handler makes it carry signals (then it must be polled too).
        self._quiet_fds = 1
        # OUTSIDE HOOK: what holds sim time and what can wake the loop (evclock/_outside.py).
        self._outside = OutsideWork(
            lambda: self._thread_id,
            lambda: len(self._io_map) > 1,
            lambda: getattr(self, "_signal_handlers", None) or {},
            lambda: self._io_map.values(),
            self._write_to_self,
            watch_threads=bool(watch_threads),
        )
        self._jump_handlers: list[JumpHandle] = []
        self._sim_clock: SimClock | None = None

    # ----------------------------------------------------------------- time

    def time(self) -> float:
        """Sim time in float seconds (derived from the exact integer nanoseconds)."""
        return self._now_ns / 1_000_000_000

    def _get_now_ns(self) -> int:
        return self._now_ns

    @property
    def now_ns(self) -> int:
        """Sim time in integer nanoseconds."""
        return self._now_ns

    def _runs_on(self, loop: asyncio.AbstractEventLoop) -> bool:
        return loop is self

    @property
    def source(self) -> TimeSource:
        """The time source that drives this loop."""
        return self._source

    @property
    def clock(self) -> SimClock:
        """The sim clock of this loop (what :func:`evclock.clock` returns on it)."""
        clock = self._sim_clock
        if clock is None:
            from ._clock import SimClock

            clock = self._sim_clock = SimClock(self)
        return clock

    # ------------------------------------------------------------ scheduling

    def call_later(
        self,
        delay: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        if delay is None:
            raise TypeError("delay must not be None")
        if not -math.inf < delay < math.inf:
            return self.call_at(self.time() + delay, callback, *args, context=context)
        when_ns = self._now_ns + round(delay * 1e9)
        timer = self._call_at_ns(when_ns, when_ns / 1_000_000_000, callback, args, context)
        if timer._source_traceback:  # type: ignore[attr-defined]
            del timer._source_traceback[-1]  # type: ignore[attr-defined]  # debug: our frame
        return timer

    def call_at(
        self,
        when: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        if when is None:
            raise TypeError("when cannot be None")
        if when == math.inf:
            # "Never" (anyio's sleep_forever, an unbounded CancelScope): a handle that is
            # never scheduled, so it can neither fire nor move time.
            self._check_closed()
            return events.TimerHandle(when, callback, args, self, context)
        if when != when or when == -math.inf:
            raise InvalidArgumentError(f"call_at() needs a finite time, got {when!r}")
        return self._call_at_ns(round(when * 1e9), when, callback, args, context)

    def _call_at_ns(
        self,
        when_ns: int,
        when: float,
        callback: Callable[..., object],
        args: tuple[Any, ...],
        context: Any,
    ) -> asyncio.TimerHandle:
        self._check_closed()
        if self._debug:
            self._check_thread()
            self._check_callback(callback, "call_at")
        timer: Any = events.TimerHandle(when, callback, args, self, context)
        if timer._source_traceback:
            del timer._source_traceback[-1]
        heapq.heappush(self._scheduled, (when_ns, self._seq(), _HANDLE, timer))
        timer._scheduled = True
        handle: asyncio.TimerHandle = timer
        return handle

    def _check_closed(self) -> None:
        if self._closed:
            raise LoopClosedError(
                "this SimEventLoop is closed; create a new loop (evclock.run() and "
                "asyncio.Runner(loop_factory=evclock.loop_factory()) create one per run)"
            )

    # ------------------------------------------------------------ the engine

    def _run_once(self) -> None:
        ready = self._ready
        io_map = self._io_map
        sched = self._scheduled  # mutated in place only, so this reference stays valid
        heappop = heapq.heappop
        while True:
            if not ready and not self._stopping:
                # Fast path when nothing else can matter (no pacing, no I/O, no outside work,
                # no other thread): straight to a live head entry - a pure jump on virtual
                # time, steps on a stepping source. Otherwise the full rule in _idle().
                if (
                    self._advance_directly
                    and sched
                    and len(io_map) <= self._quiet_fds
                    and not self._outside.active  # OUTSIDE HOOK: nothing outside at all
                    and (
                        len(_thread_registry) + len(_thread_limbo) <= 1
                        or len(_thread_registry) + len(_thread_limbo) <= 1 + internal_count()
                    )
                ):
                    when, _, kind, obj = sched[0]
                    if obj.done() if kind == _SLEEP else obj._cancelled:
                        self._idle()
                    elif when > self._now_ns:
                        self._held_since = None
                        self._now_ns = (
                            when if self._jump_when_idle else self._source.advance(when, None)
                        )
                else:
                    self._idle()
            elif len(io_map) > self._quiet_fds:
                self._poll_io(0)
            # Entries due now are taken before anything runs, so whatever the callbacks
            # below schedule for the same instant waits for the next iteration, as in asyncio.
            now = self._now_ns
            single = batch = None
            if sched and sched[0][0] <= now:
                single = heappop(sched)
                if sched and sched[0][0] <= now:
                    batch = [single]
                    single = None
                    while sched and sched[0][0] <= now:
                        batch.append(heappop(sched))
            if ready:
                debug = self._debug
                for _ in range(len(ready)):
                    handle = ready.popleft()
                    if handle._cancelled:
                        continue
                    if debug:
                        self._run_handle_debug(handle)
                    else:
                        handle._run()
            if single is not None:
                # One entry due alone - the common case - without building a batch.
                if single[2] == _SLEEP:
                    if not single[3].done():
                        self._wake(single[3], None)
                else:
                    self._fire([single])
            elif batch is not None:
                self._fire(batch)
            # Keep going without returning to run_forever() only in the plain case of
            # tasks sleeping in turn (the common case in simulation, and the hot path).
            if ready or self._stopping or not sched:
                return

    def _run_handle_debug(self, handle: asyncio.Handle) -> None:
        try:
            self._current_handle = handle
            t0 = time.monotonic()
            handle._run()
            dt = time.monotonic() - t0
            if dt >= self.slow_callback_duration:
                # asyncio's own logger and message (wall seconds), as tools filter on both.
                base_events.logger.warning(  # type: ignore[attr-defined]
                    "Executing %s took %.3f seconds",
                    base_events._format_handle(handle),  # type: ignore[attr-defined]
                    dt,
                )
        finally:
            self._current_handle = None

    def _fire(self, batch: list[tuple[int, int, int, Any]]) -> None:
        """Fire due entries in (when, seq) order.

        A sleeping task is resumed in place: its future is resolved and its wake-up callback
        run right here, instead of through a ``call_soon`` hop. The order is exactly the one
        asyncio would produce (every due entry after the callbacks that were already ready,
        each in scheduling order); it just skips allocating and queueing a Handle per wakeup.
        """
        debug = self._debug
        for _, _, kind, obj in batch:
            if kind == _SLEEP:
                if obj.done():
                    continue
                fut, result = obj, None
            else:
                obj._scheduled = False
                if obj._cancelled:
                    self._timer_cancelled_count -= 1
                    continue
                if obj._callback is not _SET_RESULT_UNLESS_CANCELLED:
                    if debug:
                        self._run_handle_debug(obj)
                    else:
                        obj._run()
                    continue
                fut, result = obj._args  # asyncio.sleep(): resolve its future the same way
                if fut.done():
                    continue
            self._wake(fut, result)

    def _wake(self, fut: asyncio.Future[Any], result: object) -> None:
        """Resolve a sleep's future and run its waiters' wake-ups in place (no Handle hop)."""
        callbacks = fut._callbacks
        if not callbacks:
            fut.set_result(result)
            return
        if len(callbacks) == 1:  # the sleeping task's own wake-up: the usual case
            callback, ctx = callbacks[0]
            fut.remove_done_callback(callback)
            fut.set_result(result)
            try:
                ctx.run(callback, fut)
            except (SystemExit, KeyboardInterrupt):
                raise
            except BaseException as exc:
                self._report_wakeup_error(exc)
            return
        for callback, _ctx in callbacks:
            fut.remove_done_callback(callback)
        fut.set_result(result)
        for callback, ctx in callbacks:
            try:
                ctx.run(callback, fut)
            except (SystemExit, KeyboardInterrupt):
                raise
            except BaseException as exc:
                self._report_wakeup_error(exc)

    def _report_wakeup_error(self, exc: BaseException) -> None:
        self.call_exception_handler(
            {"message": "Exception in the wake-up callback of a sim-time sleep", "exception": exc}
        )

    def _drop_cancelled_head(self) -> None:
        sched = self._scheduled
        while sched:
            _, _, kind, obj = sched[0]
            if kind == _SLEEP:
                if not obj.done():
                    break
            elif obj._cancelled:
                obj._scheduled = False
                self._timer_cancelled_count -= 1
            else:
                break
            heapq.heappop(sched)
        if self._timer_cancelled_count > 64 and self._timer_cancelled_count * 2 > len(sched):
            self._purge_cancelled()

    def _purge_cancelled(self) -> None:
        keep = []
        for entry in self._scheduled:
            obj = entry[3]
            if entry[2] == _SLEEP:
                if not obj.done():
                    keep.append(entry)
            elif obj._cancelled:
                obj._scheduled = False
            else:
                keep.append(entry)
        heapq.heapify(keep)
        self._scheduled[:] = keep
        self._timer_cancelled_count = 0

    def _idle(self) -> None:
        """Nothing is runnable at the current time: serve I/O, wait for outside work, or advance."""
        sched = self._scheduled
        if sched:
            _, _, kind, obj = sched[0]
            if (
                obj.done() if kind == _SLEEP else obj._cancelled
            ) or self._timer_cancelled_count > 64:
                self._drop_cancelled_head()
            if sched and sched[0][0] <= self._now_ns:
                return
        if len(self._io_map) > self._quiet_fds and self._poll_io(0):
            return
        holder = self._outside.holder()  # OUTSIDE HOOK: is sim time held (and how far not)?
        if holder is not None:
            horizon = self._outside.horizon_ns
            if horizon is None or not sched or sched[0][0] - self._now_ns > horizon:
                self._wait_for_outside_work(holder)
                return
        if self._ready:
            return  # a thread handed work over while we looked
        target = sched[0][0] if sched else None
        if target is None and not self._source.free_running:
            self._wait_for_io_or_deadlock()
            return
        self._held_since = None
        pacer = self._pacer
        if self._jump_when_idle and target is not None:
            self._now_ns = max(target, self._now_ns)
        else:
            self._now_ns = self._source.advance(target, None if pacer.idle else pacer.allow)

    def _poll_io(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` wall seconds for I/O; True if something became ready."""
        event_list = self._selector.select(timeout)
        if event_list:
            self._process_events(event_list)
        return bool(self._ready)

    def _wait_io(self, timeout: float | None) -> bool:
        """Pacing/pause wait: block up to ``timeout`` serving I/O; True if work is ready."""
        if timeout is None and len(self._io_map) <= 1 and not could_call_back(self._thread_id):
            raise DeadlockError(
                "the loop is paused and nothing could ever resume it: no I/O is "
                "registered and no other thread runs; call resume() or step() from a "
                "task before pausing, or serve a control channel (socket) that can",
                self._describe_waiting_tasks(),
            )
        return self._poll_io(timeout)

    def _held_for(self) -> float:
        now = time.monotonic()
        if self._held_since is None:
            self._held_since = now
        return now - self._held_since

    def _wait_for_outside_work(self, holder: str) -> None:
        held = self._held_for()
        limit = self._stall_timeout
        if limit is not None and held > limit:
            raise StallError(
                f"sim time has been held for {held:.1f} s of wall time waiting for work "
                "outside the loop, which holds it:\n"
                + self._outside.describe()
                + "\nmake that work finish (a thread that polls with a timeout holds sim time "
                "while it runs: give it no timeout, or stop it), or raise stall_timeout "
                "(None waits forever)"
            )
        # Exact holders call back through the self-pipe when they end; threads are polled.
        timeout = 0.05 if holder == EXACT else _THREAD_POLL
        if limit is not None:
            timeout = min(timeout, max(limit - held, 0.0))
        self._poll_io(timeout)

    def _wait_for_io_or_deadlock(self) -> None:
        # OUTSIDE HOOK: could anything wake us? Asked twice, a moment apart: a thread seen
        # parked may just have been woken by one that has parked since (a hand-off chain).
        if not self._outside.can_wake() and not (
            self._poll_io(_DEADLOCK_CONFIRM) or self._outside.can_wake()
        ):
            raise DeadlockError(
                "deadlock: every task is waiting and nothing can wake one "
                f"(no timer is scheduled, {self._source.describe()} cannot advance on its "
                "own, no I/O or signal handler is registered, no child process runs and no "
                "other thread is working or waiting for I/O). Waiting tasks:\n"
                + "\n".join(f"  {line}" for line in self._describe_waiting_tasks()),
                self._describe_waiting_tasks(),
            )
        held = self._held_for()
        limit = self._stall_timeout
        if limit is not None and held > limit:
            raise StallError(
                f"no sim-time event is scheduled and the loop waited {held:.1f} s of wall "
                "time for I/O that never came; pass stall_timeout=None to wait for I/O "
                "forever. Waiting tasks:\n"
                + "\n".join(f"  {line}" for line in self._describe_waiting_tasks())
            )
        if self._poll_io(None if limit is None else max(limit - held, 0.0) + 1e-3):
            self._held_since = None  # I/O came: the wait is over, the bound starts again

    def _describe_waiting_tasks(self) -> tuple[str, ...]:
        return describe_tasks(self)

    # --------------------------------------------------- work outside the loop

    # OUTSIDE HOOKS: executor jobs, subprocesses and holds are counted in evclock/_outside.py.

    def run_in_executor(  # type: ignore[override]
        self, executor: concurrent.futures.Executor | None, func: Callable[..., _T], *args: Any
    ) -> asyncio.Future[_T]:
        self._check_closed()
        if self._debug:
            self._check_callback(func, "run_in_executor")  # on func, not on our wrapper
        token, job = self._outside.job(func, executor)
        try:
            fut: asyncio.Future[_T] = super().run_in_executor(executor, job, *args)
        except BaseException:
            self._outside.job_done(token)
            raise
        fut.add_done_callback(lambda _: self._outside.job_done(token))
        return fut

    async def _make_subprocess_transport(self, *args: Any, **kwargs: Any) -> Any:
        # asyncio internal (the one place every subprocess_exec/subprocess_shell and
        # create_subprocess_* goes through): the child is counted once it is connected.
        transport = await super()._make_subprocess_transport(*args, **kwargs)  # type: ignore[misc]
        self._outside.add_child(transport)
        return transport

    def add_signal_handler(
        self, sig: int, callback: Callable[[Unpack[_Ts]], object], *args: *_Ts
    ) -> None:
        super().add_signal_handler(sig, callback, *args)
        self._quiet_fds = 0  # signals arrive through the self-pipe: poll it

    def remove_signal_handler(self, sig: int) -> bool:
        removed: bool = super().remove_signal_handler(sig)
        self._quiet_fds = 0 if self._signal_handlers else 1  # type: ignore[attr-defined]
        return removed

    async def shutdown_default_executor(self, *args: Any, **kwargs: Any) -> None:
        # Hold sim time: 3.12+ wraps this in a 300 s timeout that must not fire in sim time.
        with self.hold_time():
            await super().shutdown_default_executor(*args, **kwargs)

    @property
    def _holds(self) -> int:
        """How many exactly-counted things outside the loop are in flight."""
        return self._outside.active

    @contextlib.contextmanager
    def hold_time(self) -> Iterator[None]:
        """Keep sim time from moving while the block runs (thread-safe).

        Use it around work that will call the loop back from outside, when evclock cannot
        see it by itself (a C library's thread, another process)::

            with loop.hold_time():
                await wait_for_reply_from_subprocess()
        """
        self._outside.add_hold()
        try:
            yield
        finally:
            self._outside.release_hold()

    def _update_fast_path(self) -> None:
        # Without pacing the loop may advance straight to the next deadline; a
        # discrete-event source is then advanced by the loop itself: a jump.
        self._advance_directly = self._pacer.idle
        self._jump_when_idle = self._source.discrete_event and self._pacer.idle

    # ------------------------------------------------------------ pacing API

    def _pacing_changed(self) -> None:
        self._update_fast_path()
        # OUTSIDE HOOK: a control called from another thread (a GUI, an operator) wakes
        # the loop, which may be blocked in a pacing or pause wait (DESIGN 5).
        if self._thread_id is not None and threading.get_ident() != self._thread_id:
            self._write_to_self()

    def _require_running(self, what: str) -> None:
        self._check_closed()
        if not self.is_running():
            raise NotRunningError(
                f"{what} needs a running loop; call it from a task on the loop (or through "
                "loop.call_soon_threadsafe), or create the loop with paused=True to start paused"
            )

    # ------------------------------------------------------------- jumps

    def _jump_time(self, before_ns: int, after_ns: int, assign: Callable[[int], None]) -> TimeJump:
        """Move sim time discontinuously (a reset or a restored snapshot).

        Pre-jump handlers run, the source takes the new time, every pending ``clock.sleep``
        is woken with :class:`ClockJumped`, other timers keep their remaining delay, then
        post-jump handlers run.
        """
        from ._errors import ClockJumped

        jump = TimeJump(Time._from_ns(before_ns, SIM), Time._from_ns(after_ns, SIM))
        handlers = [h for h in list(self._jump_handlers) if h.threshold.matches(jump)]
        for handler in handlers:
            if handler.pre is not None:
                handler.pre(jump)
        assign(after_ns)
        self._now_ns = after_ns
        delta = after_ns - before_ns
        kept = []
        for when_ns, seq, kind, obj in self._scheduled:
            if kind == _SLEEP:
                if not obj.done():
                    obj.set_exception(ClockJumped(jump))
            elif not obj._cancelled:
                shifted = max(when_ns + delta, after_ns)
                obj._when = shifted / 1_000_000_000
                kept.append((shifted, seq, kind, obj))
            else:
                obj._scheduled = False
        heapq.heapify(kept)
        self._scheduled[:] = kept
        self._timer_cancelled_count = 0
        self._pacer.reanchor()
        for handler in handlers:
            if handler.post is not None:
                handler.post(jump)
        return jump

    # ------------------------------------------------------------- closing

    def close(self) -> None:
        if self.is_closed():
            return
        try:
            super().close()
        finally:
            self._source.close()


# OUTSIDE HOOK: a thread blocked in this loop's selector is an event loop, not busy work.
EVENT_LOOP_WAITS.add(SimEventLoop._poll_io.__code__)
