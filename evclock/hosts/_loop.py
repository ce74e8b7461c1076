"""The simulation event loop: a real asyncio loop whose ``time()`` is simulation time.

The loop is one host of the simulation kernel (:class:`~evclock.kernel._core.SimCore`, where the
advancement rule lives). One iteration:

1. If nothing is runnable, ask the kernel to advance (``SimCore.advance``) and do what it
   answers: wait for outside work, wait as pacing asks (serving I/O), wait for I/O, or raise
   :class:`DeadlockError`. Without pacing, I/O or outside work, a shorter path moves time
   straight to the next deadline.
2. Poll real I/O without blocking; what arrives is handled at the current sim time.
3. Take the kernel's entries due now, run the callbacks that were ready, then fire the due
   entries - in exactly the order stock asyncio would run them.

``_run_once`` is overridden rather than merely the selector because asyncio's own heap
orders timers by float ``when`` only, which is neither FIFO on ties nor exact.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import contextvars
import functools
import heapq
import math
import operator
import select
import selectors
import threading
import time
from asyncio import events
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, TypeVar, TypeVarTuple, Unpack

from evclock._cpython import (
    drop_caller_frame,
    fd_to_key,
    log_slow_callback,
    running_loop,
    thread_limbo,
    thread_registry,
)
from evclock._errors import (
    DeadlockError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
    NotRunningError,
    StallError,
)
from evclock.hosts._tasks import describe_tasks
from evclock.kernel._core import DEADLOCK, HELD, MOVED, PACING, WAIT_IO, SimCore
from evclock.kernel._pacing import DEFAULT_MAX_LAG, PacingControls
from evclock.kernel._source import TimeSource
from evclock.kernel._virtual import source_or_virtual
from evclock.outside._threads import (
    EVENT_LOOP_WAITS,
    check_thread_inference,
    could_call_back,
    only_internal_threads,
)
from evclock.outside._work import EXACT, OutsideWork
from evclock.time._time import MAX_TIME_NS, real_number

if TYPE_CHECKING:
    from evclock.kernel._clock import SimClock

_T = TypeVar("_T")
_Ts = TypeVarTuple("_Ts")

_Future = asyncio.Future
_running_loop = running_loop
_read_debug = operator.attrgetter("_debug")
# Read on every advance: threading.active_count() would take a lock each time.
_thread_registry = thread_registry
_thread_limbo = thread_limbo

#: Default wall-time limit for sim time being held by outside work or an I/O wait.
DEFAULT_STALL_TIMEOUT = 60.0
#: While a thread (not an executor job) holds time, re-check it this often (wall seconds).
_THREAD_POLL = 0.001
#: Wall seconds between the two looks that confirm a deadlock (see _could_wake).
_DEADLOCK_CONFIRM = 0.02
#: While an external source waits for the outside, ask it again this often (wall seconds)
#: even if no I/O arrives, so that it can check its own liveness deadline.
_EXTERNAL_POLL = 0.05
_EXTERNAL_POLL_MS = round(_EXTERNAL_POLL * 1000)
#: Seconds beyond which a float time cannot be sim time (2**63 - 1 ns): such a timer never fires.
_MAX_TIME_S = MAX_TIME_NS / 1e9


def check_stall_timeout(value: object) -> float | None:
    if value is None:
        return None
    seconds = real_number(value)
    if seconds is None:
        raise InvalidTypeError(
            f"stall_timeout must be seconds (a number) or None, got {type(value).__name__}"
        )
    if math.isnan(seconds) or seconds <= 0:
        raise InvalidArgumentError(
            f"stall_timeout must be a positive number of wall seconds or None, got {value!r}"
        )
    return seconds


_copy_context = contextvars.copy_context
_round_float = float.__round__
_heappush = heapq.heappush


class _SimTimer(events.TimerHandle):
    """asyncio's ``TimerHandle`` (same class for every check, same private fields), built
    and cancelled in one frame each instead of two: every ``asyncio.sleep`` and every
    ``asyncio.timeout`` creates and cancels one (measured: benchmarks/instructions.py).

    The fields are asyncio's private ``Handle``/``TimerHandle`` slots; in debug mode the
    stock constructor runs (it records the creation traceback).
    """

    __slots__ = ()

    def __init__(
        self,
        when: float,
        callback: Callable[..., object],
        args: tuple[Any, ...],
        loop: SimEventLoop,
        context: contextvars.Context | None = None,
    ) -> None:
        if loop._debug:
            super().__init__(when, callback, args, loop, context)
            return
        self._context = context if context is not None else contextvars.copy_context()
        self._loop = loop
        self._callback = callback
        self._args = args
        self._cancelled = False
        self._repr = None
        self._source_traceback = None
        self._when = when
        self._scheduled = False

    def cancel(self) -> None:
        if self._cancelled:
            return
        if self._scheduled:  # still in the kernel's heap: counted there, to purge it
            self._loop._core.cancelled_timers += 1  # SimCore.timer_cancelled, inlined
        self._cancelled = True
        if self._loop._debug:
            self._repr = repr(self)  # type: ignore[assignment]  # as Handle.cancel (to log the callback afterwards)
        self._callback = None  # type: ignore[assignment]
        self._args = None  # type: ignore[assignment]


_new_timer = object.__new__  # a _SimTimer whose slots call_later() fills


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
        _stopping: bool
        _closed: bool
        _selector: selectors.BaseSelector
        _thread_id: int | None
        _current_handle: asyncio.Handle | None
        _debug: bool

        def _check_thread(self) -> None: ...
        def _write_to_self(self) -> None: ...

        def _process_events(self, event_list: list[Any]) -> None: ...
        def _check_callback(self, callback: object, method: str) -> None: ...

    # A loop whose __init__ failed before asyncio's ran (a bad argument) counts as closed, so
    # that its __del__ has nothing to complain about; asyncio's __init__ sets it to False.
    _closed = True

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
        source = source_or_virtual(source)
        # Validate everything before the selector (a resource) exists.
        self._stall_timeout = check_stall_timeout(stall_timeout)
        if watch_threads:
            check_thread_inference()
        self._core = core = SimCore(
            source, self, rtf=rtf, strict=strict, max_lag=max_lag, wall=wall
        )
        core.future_factory = self._refuse_wait
        source.attach(core)  # may refuse (a source drives one host): before the selector too
        super().__init__(selector)  # (calls set_debug: get_debug is set there)
        self._source = source
        core.future_loop = self  # waits are possible from now until close()
        # Registered file descriptors, read on every iteration: the selector's own dict when
        # it exposes one (all stdlib selectors do), else its public mapping view. The
        # self-pipe is always registered, so "real I/O" means more than one entry.
        self._io_map: Any = fd_to_key(self._selector)
        # OUTSIDE HOOK: epoll does not run a tty's pending input work (_hand_over_tty_input).
        self._epoll = isinstance(self._selector, getattr(selectors, "EpollSelector", ()))
        # asyncio private: BaseSelectorEventLoop._ssock, the self-pipe's read end (a socket,
        # never a terminal: _hand_over_tty_input need not poll it).
        self._self_pipe_fd: int = self._ssock.fileno()  # type: ignore[attr-defined]
        # _hand_over_tty_input's poll object (None: nothing to poll) and the registered fds
        # it was built for (None: rebuild): rebuilt only when those change.
        self._tty_poller: Any = None
        self._tty_built_for: set[Any] | None = None  # compared whole, never iterated
        if paused:
            core.pacer.pause()
        self._held_since: float | None = None
        # OUTSIDE HOOK: registered fds that deliver nothing by themselves: the self-pipe,
        # until a signal handler makes it carry signals (then it must be polled too).
        self._quiet_fds = 1
        # OUTSIDE HOOK: what holds sim time and what can wake the loop (evclock/_outside.py).
        self._outside = OutsideWork(
            lambda: self._thread_id,
            lambda: len(self._io_map) > 1,
            lambda: getattr(self, "_signal_handlers", None) or {},
            self._unaccounted_io,
            self._write_to_self,
            watch_threads=bool(watch_threads),
            sim_now=lambda: self._core.now_ns,
        )
        #: What held sim time at the last _held_horizon() (EXACT or INFERRED): how to wait.
        self._holder: str | None = None
        # _held_horizon() found nothing outside but an external source's own connection or
        # I/O whose owners account for it: _before_moving(), asked next, need not poll.
        self._outside_silent = False
        # EXTERNAL-SOURCE HOOK: fds whose traffic their owner accounts for exactly (the
        # clock server's participant connections): not inferred as work in flight.
        self._accounted_fds: set[int] = set()  # membership only, never iterated
        # I/O was polled after callbacks last ran: what that poll made ready is what
        # asyncio's per-iteration select would have, so running those callbacks needs no
        # other zero-timeout poll first (a move of time always polls: _before_moving).
        self._io_fresh = False
        # A callback came from another thread (call_soon_threadsafe) since the last advance.
        self._woken_from_outside = False
        # EXTERNAL-SOURCE HOOK: whether the source is external (it may name its fd:
        # TimeSource.io_fd).
        self._source_external = source.external
        # _wait_for_source's poll object: the source's fd and the self-pipe (built once).
        self._source_poller: Any = None
        self._source_poller_fd: int | None = None
        self._sim_clock: SimClock | None = None

    def set_debug(self, enabled: bool) -> None:
        """Turn asyncio's debug mode on or off (as asyncio's ``set_debug``)."""
        super().set_debug(enabled)
        self._answer_debug()

    def _answer_debug(self) -> None:
        # asyncio's Future and Handle constructors ask loop.get_debug() on every wait and
        # every callback: answered from C, without a Python frame - by bool() (False) while
        # debug mode is off, the common case (one call, no attribute lookup: measured with
        # benchmarks/wallgap.py), else by reading _debug. set_debug() is what sets _debug.
        if self._debug is False:
            self.get_debug = bool  # type: ignore[method-assign]
        else:
            self.get_debug = functools.partial(_read_debug, self)  # type: ignore[method-assign]

    def create_future(self) -> asyncio.Future[Any]:
        """A future on this loop (made without the ``loop=`` keyword when it runs here)."""
        # asyncio.sleep, wait_for, ...: a future on this loop, as BaseEventLoop's, made
        # without the loop= keyword (a dict on every call) when this loop runs here.
        if _running_loop() is self:
            return _Future()
        return _Future(loop=self)

    # ----------------------------------------------------------------- time

    def time(self) -> float:
        """Sim time in float seconds (derived from the exact integer nanoseconds)."""
        return self._core.now_ns / 1_000_000_000

    @property
    def now_ns(self) -> int:
        """Sim time in integer nanoseconds."""
        return self._core.now_ns

    @property
    def source(self) -> TimeSource:
        """The time source that drives this loop."""
        return self._source

    @property
    def clock(self) -> SimClock:
        """The sim clock of this loop (what :func:`evclock.clock` returns on it)."""
        clock = self._sim_clock
        if clock is None:
            from evclock.kernel._clock import SimClock

            clock = self._sim_clock = SimClock(self._core, self)
        return clock

    # ------------------------------------------------------------ scheduling

    def call_soon_threadsafe(
        self,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.Handle:
        """asyncio's, and the loop polls its I/O before the callback runs (see _run_once)."""
        handle = super().call_soon_threadsafe(callback, *args, context=context)
        self._woken_from_outside = True  # after it is queued: at worst one poll too many
        if self._debug:
            drop_caller_frame(handle)  # its source traceback ends at the caller, as asyncio's
        return handle

    def call_later(
        self,
        delay: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        """Schedule ``callback(*args)`` ``delay`` seconds of sim time from now (asyncio's
        contract, in exact integer nanoseconds; FIFO among callbacks due at one instant)."""
        # Hot path (every asyncio.sleep and timeout): one frame, no call_at hop (measured
        # with benchmarks/instructions.py).
        core = self._core
        try:
            # (a float's own __round__: round() looks it up on the type on every call)
            when_ns = core.now_ns + (
                _round_float(delay * 1e9) if type(delay) is float else round(delay * 1e9)
            )
        except (TypeError, ValueError, OverflowError):  # None, NaN, infinite, not a number
            if delay is None:
                raise InvalidTypeError("delay must not be None") from None
            return self.call_at(self.time() + delay, callback, *args, context=context)
        if self._closed:
            self._check_closed()
        if self._debug:
            timer = _SimTimer(when_ns / 1_000_000_000, callback, args, self, context)
            self._check_debug(timer, callback, "call_later")
            core.call_at(when_ns, timer)
            return timer
        # _SimTimer.__init__ and SimCore.call_at, inlined (two frames fewer on every
        # asyncio.sleep and timeout): asyncio's private Handle/TimerHandle slots, as there.
        timer = _new_timer(_SimTimer)
        timer._context = context if context is not None else _copy_context()
        timer._loop = self
        timer._callback = callback
        timer._args = args
        timer._cancelled = False
        timer._repr = None
        timer._source_traceback = None
        timer._when = when_ns / 1_000_000_000
        if when_ns > MAX_TIME_NS:
            timer._scheduled = False  # beyond sim time's range: never (as SimCore.call_at)
        else:
            timer._scheduled = True
            if core.at.setdefault(when_ns, timer) is timer:  # SimCore.schedule, inlined
                _heappush(core.heap, when_ns)
            else:
                core.schedule(when_ns, timer)
        return timer

    def call_at(
        self,
        when: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        """Schedule ``callback(*args)`` at sim time ``when`` (seconds, the loop's ``time()``);
        a time beyond sim time's range never fires, as an unbounded timer on stock asyncio."""
        if when is None:
            raise InvalidTypeError("when cannot be None")
        if when != when or when == -math.inf:
            raise InvalidArgumentError(f"call_at() needs a finite time, got {when!r}")
        if self._closed:
            self._check_closed()
        if self._debug:
            timer = _SimTimer(when, callback, args, self, context)
            self._check_debug(timer, callback, "call_at")
            if when <= _MAX_TIME_S:
                self._core.call_at(round(when * 1e9), timer)
            return timer
        # Hot path (every asyncio.timeout and wait_for): _SimTimer.__init__ and
        # SimCore.call_at inlined, as in call_later.
        timer = _new_timer(_SimTimer)
        timer._context = context if context is not None else _copy_context()
        timer._loop = self
        timer._callback = callback
        timer._args = args
        timer._cancelled = False
        timer._repr = None
        timer._source_traceback = None
        timer._when = when
        if when <= _MAX_TIME_S and (when_ns := round(when * 1e9)) <= MAX_TIME_NS:
            timer._scheduled = True
            core = self._core
            if core.at.setdefault(when_ns, timer) is timer:  # SimCore.schedule, inlined
                _heappush(core.heap, when_ns)
            else:
                core.schedule(when_ns, timer)
        else:
            # "never" (anyio's sleep_forever, an unbounded CancelScope, a huge delay): beyond
            # sim time's range, as on stock asyncio a timer that never fires nor moves time.
            timer._scheduled = False
        return timer

    def call_at_ns(
        self,
        when_ns: int,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        """:meth:`call_at` at an exact sim time in integer nanoseconds (no float round
        trip): for evclock's own timers that must land on an exact instant."""
        if self._closed:
            self._check_closed()
        timer = _SimTimer(when_ns / 1_000_000_000, callback, args, self, context)
        if self._debug:
            self._check_debug(timer, callback, "call_at")
        self._core.call_at(when_ns, timer)
        return timer

    def _check_debug(self, timer: Any, callback: object, method: str) -> None:
        self._check_thread()
        self._check_callback(callback, method)
        if timer._source_traceback:
            del timer._source_traceback[-2:]  # debug: the traceback ends in the caller

    def _timer_handle_cancelled(self, handle: asyncio.TimerHandle) -> None:
        # asyncio private hook: TimerHandle.cancel() reports a cancellation here (also of a
        # timer that already fired: asyncio.sleep cancels its handle in a finally); the
        # kernel counts the ones still in its heap, to purge them. (_SimTimer.cancel does
        # the same in its own frame.)
        if handle._scheduled:  # type: ignore[attr-defined]
            self._core.timer_cancelled()

    def _refuse_wait(self) -> asyncio.Future[None]:
        self._check_closed()
        raise AssertionError("unreachable: the loop is closed")

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
        core = self._core
        wake_next = core.wake_next
        while True:
            if ready or self._stopping:
                # One poll between runs of callbacks, as asyncio's select: here when
                # callbacks are ready, else in the rule (_before_moving, before time moves, or a
                # wait).
                if (
                    len(io_map) > self._quiet_fds  # OUTSIDE HOOK: real I/O or signals
                    and not self._io_fresh
                    and not (self._source_external and self._source_alone())
                ):
                    self._poll_io(0)  # what arrives is handled at the current sim time
            else:
                # The kernel's short path (rule step 0) when it allows one (no pacing, not an
                # external source) and, as this loop reports, nothing outside can matter (no
                # I/O, no outside work, no other thread); otherwise the full rule.
                if (
                    core.short_path
                    and len(io_map) <= self._quiet_fds
                    and not self._outside.active  # OUTSIDE HOOK: nothing outside at all
                    and (
                        (not _thread_limbo and len(_thread_registry) <= 1)
                        or only_internal_threads()
                    )
                ):
                    if self._held_since is not None:
                        self._held_since = None  # nothing holds time any more
                    if wake_next(ready):
                        continue
                self._advance()
                if self._woken_from_outside:
                    self._woken_from_outside = False
                    if (
                        ready
                        and not self._io_fresh
                        and len(io_map) > self._quiet_fds
                        and not (self._source_external and self._source_alone())
                    ):
                        # Callbacks another thread queued while time moved come after a
                        # poll too: when _before_moving skips its poll (I/O whose owners
                        # account for it) that is the poll the owners rely on - while physics
                        # runs flat out, a clock server reads and writes in its keepalives'.
                        self._poll_io(0)
            # Entries due now are taken before anything runs, so whatever the callbacks
            # below schedule for the same instant waits for the next iteration, as in asyncio.
            due = core.take_due()
            if ready:
                self._io_fresh = False
                debug = self._debug
                for _ in range(len(ready)):
                    handle = ready.popleft()
                    if handle._cancelled:
                        continue
                    if debug:
                        self._run_handle_debug(handle)
                    else:
                        handle._run()
            if due is not None:
                core.fire(due, ready)
            # Keep going without returning to run_forever() while tasks sleep in turn.
            if ready or self._stopping:
                return

    def _run_handle_debug(self, handle: asyncio.Handle) -> None:
        try:
            self._current_handle = handle
            t0 = time.monotonic()
            handle._run()
            dt = time.monotonic() - t0
            if dt >= self.slow_callback_duration:
                log_slow_callback(handle, dt)  # asyncio's own logger and message
        finally:
            self._current_handle = None
            # Drop the handle with this frame, as asyncio's _run_once does ("handle = None"):
            # a callback's exception traceback can keep the finished frame alive, and the
            # frame would keep the handle, its task and the exception in a cycle (a failed
            # task's "exception was never retrieved" then waits for the cyclic GC).
            del handle

    def _advance(self) -> None:
        """Nothing is runnable now: apply the kernel's rule and wait as it answers."""
        outcome = self._core.advance()
        if outcome == HELD:
            self._wait_for_outside_work()
            return
        self._held_since = None if outcome <= MOVED else self._held_since
        if outcome <= MOVED:
            return
        if outcome == PACING:
            self._wait_pacing(self._core.pacing_delay)
        elif outcome == WAIT_IO:
            self._wait_for_io()
        elif outcome == DEADLOCK:
            raise DeadlockError(
                "deadlock: every task is waiting and nothing can wake one "
                f"(no timer is scheduled, {self._source.describe()} cannot advance on its "
                "own, no I/O or signal handler is registered, no child process runs and no "
                "other thread is working or waiting for I/O). Waiting tasks:\n"
                + "\n".join(f"  {line}" for line in self._describe_waiting_tasks()),
                self._describe_waiting_tasks(),
            )
        else:  # WAIT_SOURCE: an external source waits for its messages (through the loop)
            self._wait_source()

    def _wait_source(self) -> None:
        """EXTERNAL-SOURCE HOOK: wait for an external source's news (serving all I/O).

        The source's reader runs when its fd is readable; then the kernel is asked again
        at once (this wait was the poll). No zero-timeout poll comes first whenever the
        only registered I/O is the source's own fd (``TimeSource.io_fd``), which the
        source reads when asked.
        """
        self._poll_io(_EXTERNAL_POLL)

    def _source_alone(self) -> bool:
        """EXTERNAL-SOURCE HOOK: the only thing outside the loop is an external source's
        own connection (its ``io_fd`` is the one registered fd besides the quiet self-pipe;
        no outside work, no other thread). The source reads that fd itself when the kernel
        asks it to advance and accounts for what is in flight on it, so the loop neither
        polls it beforehand nor infers held time from its unread bytes."""
        fd = self._source.io_fd
        return (
            fd is not None
            and len(self._io_map) == self._quiet_fds + 1
            and fd in self._io_map
            and not self._outside.active
            and only_internal_threads()
        )

    def _outside_quiet(self) -> bool:
        """OUTSIDE HOOK: nothing outside the loop holds sim time or could matter before it
        moves but I/O whose owners account for it exactly (``_account_fd``: a clock
        server's listener and connections; it holds sim time itself while a participant
        works): no other fd, no signal handler, no outside work, no other thread. Then
        nothing is in flight (the survey of :meth:`_held_horizon` would find nothing) and
        no poll need come before time moves (:meth:`_before_moving`): the owners read their
        fds between callbacks, and hold time while what they read matters."""
        io_map = self._io_map
        accounted = self._accounted_fds
        return (
            not self._outside.active
            and len(io_map) == self._quiet_fds + len(accounted)
            and accounted <= io_map.keys()
            and only_internal_threads()
        )

    def _wait_for_source(self) -> bool:
        """EXTERNAL-SOURCE HOOK: the loop's wait for its external source, taken by the source
        inside :meth:`~evclock.kernel.TimeSource.advance` so that the news it waits for (a
        clock server's grant) is read and used in the same call.

        Only when the source is alone (:meth:`_source_alone`: nothing else outside the loop
        could wake a task, so the loop itself would wait for exactly this fd next): block
        until the source's fd is readable or the loop's self-pipe is (a signal, a
        ``call_soon_threadsafe``), at most as long as the loop's own wait for the source
        (50 ms: the source then checks its liveness deadline, as after that wait).

        :returns: True when the source's fd is readable (read it now); False when the source
            is not alone, the wait timed out, or something woke the loop (the source then
            returns "no news" and the loop waits and serves I/O as usual).
        """
        if not self._source_alone():
            return False
        fd = self._source.io_fd
        assert fd is not None  # _source_alone: the source named its fd
        poller = self._source_poller
        if poller is None or self._source_poller_fd != fd:
            poller = self._source_poller = select.poll()
            poller.register(fd, select.POLLIN)
            poller.register(self._self_pipe_fd, select.POLLIN)
            self._source_poller_fd = fd
        events = poller.poll(_EXTERNAL_POLL_MS)
        for ready_fd, _ in events:
            if ready_fd == self._self_pipe_fd:
                return False  # the loop was woken: it reads the self-pipe and decides
        return bool(events)  # the source's fd: the only other one polled

    def _unaccounted_io(self) -> Any:
        """EXTERNAL-SOURCE HOOK: the registered I/O whose unread bytes may be inferred as
        work in flight (all of it but the fds their owner accounts for exactly)."""
        accounted = self._accounted_fds
        if not accounted:
            return self._io_map.values()
        return [key for key in self._io_map.values() if key.fd not in accounted]

    def _account_fd(self, fd: int, accounted: bool) -> None:
        """Declare that ``fd``'s owner accounts for its traffic exactly (``accounted``), or
        no longer does: the owner holds sim time itself while that traffic matters (the
        clock server's connections), so the loop infers nothing from the fd's unread bytes.
        """
        if accounted:
            self._accounted_fds.add(fd)
        else:
            self._accounted_fds.discard(fd)
        self._tty_built_for = None  # _hand_over_tty_input polls a different set now

    # ------------------------------------------------ what the kernel asks the loop

    def _anything_runnable(self) -> bool:
        """Whether a callback is ready to run (the kernel does not advance then)."""
        return bool(self._ready)

    def _held_horizon(self, paused: bool) -> int | None:
        """What work outside the loop holds of sim time (holds, executor jobs, awaited
        child processes, bytes in flight, busy threads: :mod:`evclock.outside`): None,
        nothing; else how far sim time may still move (threads held only in timed waits of
        known length: up to the first of their ends; 0 otherwise). The kernel decides."""
        if (self._source_external and self._source_alone()) or self._outside_quiet():
            self._holder = None  # nothing outside but the source, or accounted I/O
            self._outside_silent = True  # for _before_moving, which the kernel asks next
            return None
        self._outside_silent = False
        outside = self._outside
        holder = self._holder = outside.holder(timed_waits_hold=not paused)
        if holder is None:
            return None
        horizon = outside.horizon_ns
        return 0 if horizon is None else horizon

    def _before_moving(self) -> None:
        """Sim time may move: bytes that arrived since the last poll (a peer thread's reply,
        just delivered while the thread went back to waiting; a signal's byte on the
        self-pipe as an alarm hold ends) are taken in first; the kernel finds their callbacks
        ready and does not advance. So this polls even when no callback ran since the last
        poll. Not when :meth:`_held_horizon`, asked just before in the same advance, found
        nothing outside but the source's connection or I/O whose owners account for it."""
        if not self._outside_silent and len(self._io_map) > self._quiet_fds:
            if self._epoll:
                self._hand_over_tty_input()
            self._poll_io(0)

    def _hand_over_tty_input(self) -> None:
        """Bytes written to a terminal the loop reads (a pty) reach its read queue through
        the kernel's tty work queue, a moment after the write; epoll does not see them
        until that work has run, but ``poll()`` on the descriptor runs it at once (Linux's
        line discipline flushes pending input when polled). So the registered descriptors
        are polled once before time moves: exact, and what was written is read now.

        Only descriptors that can be a terminal are polled: not the self-pipe, nor the
        sockets whose owner accounts for their traffic exactly (``_account_fd``: a clock
        server's connections and listener); with none left, no system call at all.

        This runs before every advance with I/O registered, so the poll object is kept and
        rebuilt only when the registered descriptors (or the accounted ones) change: poll()
        registers fd numbers, so a reused number polls whatever it now is, as the selector
        does. An unchanged advance makes one system call and allocates nothing."""
        registered = self._io_map.keys()
        if registered != self._tty_built_for:
            accounted, self_pipe = self._accounted_fds, self._self_pipe_fd
            fds = [fd for fd in registered if fd != self_pipe and fd not in accounted]
            poller: Any = None
            if fds:
                poller = select.poll()
                for fd in fds:
                    poller.register(fd, select.POLLIN)
            self._tty_poller, self._tty_built_for = poller, set(registered)
        if self._tty_poller is not None:
            self._tty_poller.poll(0)

    def _could_wake(self) -> bool:
        """Could anything outside wake a task with nothing scheduled? (I/O, signal
        handlers, children, executor jobs, holds, threads: evclock/_outside.py)

        Asked twice, a moment apart, before answering no: a thread seen parked may just
        have been woken by one that has parked since (a hand-off chain).
        """
        outside = self._outside  # OUTSIDE HOOK
        return outside.can_wake() or self._poll_io(_DEADLOCK_CONFIRM) or outside.can_wake()

    def _would_deadlock(self) -> bool:
        """Whether, right now, nothing could ever wake a task: nothing is ready, nothing
        outside the loop is in flight, no I/O or signal handler is registered, nothing is
        scheduled and the source cannot move on its own. A quick test without waiting (the
        pytest plugin's guard asks it); the loop itself confirms a deadlock before raising
        :class:`DeadlockError`."""
        if self._ready or self._outside.active or len(self._io_map) > 1:
            return False
        return not self._source.free_running and not self._core.has_pending()

    def _interrupt_wait(self) -> None:
        """Nothing to do: the loop's waits are I/O waits, and whatever calls this runs in
        the loop (so the wait is over) or comes through the self-pipe (which ends it)."""

    def _serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` are on this sim time (only this loop's)."""
        return loop is self

    def _is_closed(self) -> bool:
        """Whether the loop is closed (asyncio's :meth:`is_closed`)."""
        return self._closed

    def _call_exception_handler(self, context: dict[str, Any]) -> None:
        """asyncio's :meth:`call_exception_handler`."""
        self.call_exception_handler(context)

    def _poll_io(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` wall seconds for I/O; True if something became ready."""
        event_list = self._selector.select(timeout)
        self._io_fresh = True
        if event_list:
            self._process_events(event_list)
        return bool(self._ready)

    def _wait_pacing(self, delay: float | None) -> None:
        """Wait as pacing asks, serving I/O: ``delay`` wall seconds, None until a control
        changes (paused with no step left).

        Paused, the loop waits for as long as anything could still resume it (a resume may
        come from a task woken by any of them): registered I/O, a signal handler, a child
        process, executor jobs or holds in flight, or any other live thread (an operator
        thread idle in its own event wait counts). Unbounded, as a pause is: it ends with a
        control. With none of these it is a deadlock.
        """
        if delay is None and not self._could_resume():
            raise DeadlockError(
                "the loop is paused and nothing could ever resume it: no I/O or signal "
                "handler is registered, no child process runs and no other thread runs; "
                "call resume() or step() from a task before pausing, or serve a control "
                "channel (a socket, a signal handler) that can",
                self._describe_waiting_tasks(),
            )
        self._poll_io(delay)

    def _could_resume(self) -> bool:
        # OUTSIDE HOOK: the outside model's wake sources (I/O, signal handlers, children,
        # jobs, holds), and any other thread at all: an idle GUI thread may call resume().
        if len(self._io_map) > 1 or could_call_back(self._thread_id):
            return True
        return self._outside.can_wake()

    def _held_for(self) -> float:
        now = time.monotonic()
        if self._held_since is None:
            self._held_since = now
        return now - self._held_since

    def _wait_for_outside_work(self) -> None:
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
        timeout = 0.05 if self._holder == EXACT else _THREAD_POLL
        if limit is not None:
            timeout = min(timeout, max(limit - held, 0.0))
        self._poll_io(timeout)

    def _wait_for_io(self) -> None:
        if self._ready:
            return  # _could_wake() polled, and something arrived
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
        """Run ``func(*args)`` in ``executor`` (the default one for None); sim time is held
        while the job is queued or runs, and until its result reaches the loop."""
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
        """As asyncio's; the loop polls its self-pipe from now on, as signals arrive there."""
        super().add_signal_handler(sig, callback, *args)
        self._quiet_fds = 0  # signals arrive through the self-pipe: poll it

    def remove_signal_handler(self, sig: int) -> bool:
        """As asyncio's; returns whether a handler was removed."""
        removed: bool = super().remove_signal_handler(sig)
        self._quiet_fds = 0 if self._signal_handlers else 1  # type: ignore[attr-defined]
        return removed

    async def shutdown_default_executor(self, *args: Any, **kwargs: Any) -> None:
        """As asyncio's, holding sim time meanwhile (3.12+ wraps it in a timeout that must
        not fire in sim time)."""
        # Hold sim time: 3.12+ wraps this in a 300 s timeout that must not fire in sim time.
        with self.hold_time():
            await super().shutdown_default_executor(*args, **kwargs)

    def _add_hold(self) -> None:
        """Hold sim time until a matching :meth:`_release_hold` (thread-safe; counted, so
        holds nest). :meth:`hold_time` is the block form; the clock server holds this way
        while a participant's answer is in flight."""
        self._outside.add_hold()

    def _release_hold(self, _fut: object = None) -> None:
        """Release one :meth:`_add_hold` (thread-safe). It takes an ignored argument so that
        it can be a future's done-callback."""
        self._outside.release_hold()

    def _restart_stall_bound(self) -> None:
        """Start the ``stall_timeout`` bound again: the hold in force is bounded by its
        owner, not by the loop. A holder with a timeout of its own (the clock server
        waiting for participants under its join, step and ``pause`` policies) calls this
        while that is so; its own timeout then ends the wait, with its own error, however
        long it is. Call it on the loop's thread."""
        self._held_since = None

    @contextlib.contextmanager
    def hold_time(self) -> Iterator[None]:
        """Keep sim time from moving while the block runs (thread-safe).

        Use it around work that will call the loop back from outside, when evclock cannot
        see it by itself (a C library's thread, another process)::

            with loop.hold_time():
                await wait_for_reply_from_subprocess()
        """
        self._add_hold()
        try:
            yield
        finally:
            self._release_hold()

    def _pacing_changed(self) -> None:
        self._core.pacing_changed()

    # OUTSIDE HOOK: a control called from another thread (a GUI, an operator) changes the
    # pacer there and hands the loop its reaction, which wakes a pacing or pause wait
    # (docs/architecture.md, "Pacing"; the mechanism is PacingControls', shared with
    # SimDriver). Until that callback ran, the loop does not advance: it runs what is ready
    # first.

    def _on_host_thread(self) -> bool:
        return self._thread_id is None or threading.get_ident() == self._thread_id

    def _call_on_host(self, what: str, reaction: Callable[[], None]) -> None:
        self.call_soon_threadsafe(reaction)

    def _stepping_until(self, when_ns: int) -> None:
        self._core.stop_at(when_ns)  # virtual time stops exactly there
        self._core.pacing_changed()

    def _require_running(self, what: str) -> None:
        self._check_closed()
        if not self.is_running():
            raise NotRunningError(
                f"{what} needs a running loop; call it from a task on the loop (or through "
                "loop.call_soon_threadsafe), or create the loop with paused=True to start paused"
            )

    # ------------------------------------------------------------- closing

    def close(self) -> None:
        """Close the loop (as asyncio's) and its time source; later sim-time waits raise
        :class:`LoopClosedError`."""
        if self.is_closed():
            return
        self._core.future_loop = None  # waits now go to future_factory, which refuses them
        try:
            super().close()
        finally:
            self._source.close()


# OUTSIDE HOOK: a thread blocked in this loop's selector is an event loop, not busy work.
EVENT_LOOP_WAITS.add(SimEventLoop._poll_io.__code__)
