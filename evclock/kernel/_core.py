"""The simulation kernel: one object owns sim time and the rule that advances it.

Every host of sim time - :class:`~evclock.SimEventLoop` (the loop *is* the simulation) and
:class:`~evclock.SimDriver` (a task on a loop evclock does not own) - keeps a :class:`SimCore`
and asks it one question when nothing is runnable: :meth:`SimCore.advance`. The answer is
one of the outcomes below; the host only supplies *how to wait* for each and answers the
kernel's questions about the world around it (:class:`CoreHost`).

The rule (docs/architecture.md, "The advancement rule"), in order:

0. the short path: no pacing, not an external source (:attr:`SimCore.short_path`) and, as
   the host reports, nothing outside (no I/O, outside work or other thread): straight to
   the next deadline and wake what is due there (:meth:`SimCore.wake_next`); it is steps
   1, 4 and 5 below for that case. Otherwise:

1. something due at the current time, or a task runnable         -> ``DUE``: run it
2. paused with no step left: a pause outranks every hold          -> ``PACING`` (no delay)
3. outside work holds sim time (executor jobs, holds, children, threads;
   while paused, not threads in timed waits), and the next
   deadline lies beyond what the hold lets move (a thread's timed
   wait of known length is an event ahead: earlier ones fire)     -> ``HELD``: wait for it
4. nothing scheduled and the source cannot move on its own:
   something outside could wake us (I/O, threads, peers)          -> ``WAIT_IO``
   nothing could                                                   -> ``DEADLOCK``
5. ask the source to advance toward the next deadline (gated by the pacer):
   time moved                                                      -> ``MOVED``
   the pacer said "not yet"                                        -> ``PACING`` (wait
   :attr:`SimCore.pacing_delay` wall seconds; None: until a control changes)
   an external source has no news from outside yet                 -> ``WAIT_SOURCE``

Scheduling is the kernel's too: one heap of distinct deadlines in integer nanoseconds and,
beside it, a dict from each deadline to what is due then: one entry, or a ``_Bucket`` of
several in scheduling order (FIFO). The heap compares plain ints, at a third of the cost
of comparing ``(when, seq, ...)`` tuples (measured: benchmarks/instructions.py). Nothing
outside this module reads an entry. Kinds: a sim-time sleep future (``clock.sleep``), an
asyncio ``TimerHandle`` (``call_at``, ``asyncio.sleep``, timeouts) and a stop mark (the
target of ``step_until``/``run_until``: time stops there exactly). A second heap holds
waits woken only once the work due at their time has settled (``SimDriver.run_until``).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import operator
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Final, Protocol

from evclock._cpython import SET_RESULT_UNLESS_CANCELLED, running_loop
from evclock._errors import ClockJumpedError, InvalidArgumentError
from evclock.kernel._jumps import JumpHandle, TimeJump
from evclock.kernel._pacing import DEFAULT_MAX_LAG, Pacer
from evclock.kernel._source import TimeSource
from evclock.kernel._virtual import VirtualTimeSource
from evclock.time._time import (
    MAX_TIME_NS,
    SIM,
    Duration,
    duration_ns,
    format_time_range_error,
    new_time,
    sleep_duration_ns,
)

if TYPE_CHECKING:
    from evclock.kernel._clock import SimClock

#: What :meth:`SimCore.advance` tells its host.
DUE: Final = 0  #: something is due or runnable at the current time: run it
MOVED: Final = 1  #: sim time moved
HELD: Final = 2  #: work outside the host holds sim time: wait for it in wall time
PACING: Final = 3  #: pacing: wait ``pacing_delay`` wall seconds (None: until a control changes)
WAIT_IO: Final = 4  #: nothing can move time on its own; something outside could wake us
WAIT_SOURCE: Final = 5  #: an external source is waiting for news from outside
DEADLOCK: Final = 6  #: nothing can ever wake a task

# Entries: a future resolved when due (clock.sleep), an asyncio TimerHandle (call_at,
# asyncio.sleep, timeouts) or _STOP, a point where time stops (step_until / run_until).
_STOP: Final = object()
_TimerHandle: type[Any] = asyncio.TimerHandle  # its private fields are read here


class _Bucket(list[Any]):
    """Several entries due at one deadline, in scheduling order."""

    __slots__ = ()


_Future = asyncio.Future
# A future created with no loop= on the running loop is bound to it, found in C.
_running_loop = running_loop
# asyncio.sleep() schedules this function through call_later(); the kernel recognises it to
# resolve the sleep's future exactly as the handle would.
_SET_RESULT_UNLESS_CANCELLED = SET_RESULT_UNLESS_CANCELLED
# The C future's methods, unbound, for futures of exactly that type: a call through them
# skips the method lookup on the instance, which CPython 3.11's specialising interpreter
# does not cache for a type whose instances may carry a __dict__ (LOAD_METHOD then takes
# the generic lookup on every call: instruction- and data-cache misses per wake-up,
# measured with benchmarks/wallgap.py). 3.12+ caches it; the unbound call is as cheap.
_future_set_result = _Future.set_result
_future_remove_done_callback = _Future.remove_done_callback
# round() looks __round__ up on the type on every call; the float's own method does not.
_round_float = float.__round__
_deadline = operator.itemgetter(0)
_duration_ns = duration_ns
_heappush = heapq.heappush
_heappop = heapq.heappop
#: Purge cancelled timers from the heap once they are this many and half of it.
_PURGE_AT: Final = 64


def clock_sleep(clock: SimClock, duration: float | Duration) -> asyncio.Future[None]:
    """Wait ``duration`` (seconds or a :class:`Duration`) of sim time: ``SimClock.sleep``.

    Every controller's hot path, so it lives here, in one frame: it converts the duration
    and pushes the wait on the kernel's heap. Negative, NaN and infinite durations raise
    :class:`InvalidArgumentError`, as does a wait beyond sim time's range.
    """
    if type(duration) is float and 0.0 <= duration < 1e9:
        ns = _round_float(duration * 1e9)
    elif type(duration) is not Duration or (ns := _duration_ns(duration)) < 0:
        ns = sleep_duration_ns(duration)
    core = clock.core
    when = core.now_ns + ns
    if when > MAX_TIME_NS:
        raise InvalidArgumentError(format_time_range_error("the wait", when))
    loop = core.future_loop
    if loop is not None and _running_loop() is loop:
        # on the running loop, found in C (a loop= keyword costs a dict on every call)
        fut: asyncio.Future[None] = _Future()
    else:
        fut = _Future(loop=loop) if loop is not None else core.future_factory()
    if core.at.setdefault(when, fut) is fut:
        _heappush(core.heap, when)
    else:
        core.schedule(when, fut)
    if when < core.notify_before:
        core.host._interrupt_wait()
    return fut


def clock_sleep_until(clock: SimClock, when_ns: int) -> asyncio.Future[None]:
    """Wait until sim time reaches ``when_ns`` (at least now): ``SimClock.sleep_until_ns``,
    the hot path of rates and timers."""
    core = clock.core
    now = core.now_ns
    if when_ns < now:
        when_ns = now
    elif when_ns > MAX_TIME_NS:
        raise InvalidArgumentError(format_time_range_error("the wait", when_ns))
    loop = core.future_loop
    if loop is not None and _running_loop() is loop:
        # on the running loop, found in C (a loop= keyword costs a dict on every call)
        fut: asyncio.Future[None] = _Future()
    else:
        fut = _Future(loop=loop) if loop is not None else core.future_factory()
    if core.at.setdefault(when_ns, fut) is fut:
        _heappush(core.heap, when_ns)
    else:
        core.schedule(when_ns, fut)
    if when_ns < core.notify_before:
        core.host._interrupt_wait()
    return fut


class CoreHost(Protocol):
    """What the kernel asks of the host it runs in (a SimEventLoop or a SimDriver).

    Private names, as asyncio's own loop hooks (``_timer_handle_cancelled``,
    ``_write_to_self``): the kernel calls them, a user never does, so they stay off the
    hosts' public face (tests/hosts/test_host_surface.py holds it to a list)."""

    def _anything_runnable(self) -> bool:
        """Is anything else runnable at the current time (a task, a callback)?"""
        ...

    def _held_horizon(self, paused: bool) -> int | None:
        """What work outside the host (executor jobs, holds, children, busy threads) holds
        of sim time: None, nothing; otherwise how many nanoseconds sim time may still move
        before the hold applies - 0 for none at all; a thread's timed wait of known length
        is an event ahead, which earlier deadlines may reach (the kernel decides).

        ``paused``: the host is paused (time moves only by steps), so sim time and wall
        time are decoupled and a thread's timed wait is no event on sim time: it does not
        hold. Running threads, executor jobs, children and explicit holds still do."""
        ...

    def _before_moving(self) -> None:
        """Sim time is about to move: take in what arrived from outside meanwhile (poll
        I/O), so that work it makes ready runs at the current time first."""
        ...

    def _could_wake(self) -> bool:
        """Could anything outside wake a task (registered I/O, signal handlers, threads,
        peers)? False with nothing scheduled is a deadlock."""
        ...

    def _interrupt_wait(self) -> None:
        """End the host's current wait now: a deadline before :attr:`SimCore.notify_before`
        was scheduled, time jumped, or an external source received news."""
        ...

    def _serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` wait on this host's sim time."""
        ...

    def _is_closed(self) -> bool:
        """True once the host closed (a source then moves its time without a jump)."""
        ...

    def _call_exception_handler(self, context: dict[str, Any]) -> None:
        """Report an error from a wake-up callback or a source to the host's loop."""
        ...

    @property
    def clock(self) -> SimClock: ...


class Settling:
    """The rule's step for a host that cannot see every task (:class:`~evclock.SimDriver`
    on a loop evclock does not own): before time moves, the work woken at the current time
    must settle. The host yields to its loop and reports what it saw after each yield
    (:meth:`observe`); settled after ``needed`` quiet looks in a row (a wait due now that
    was woken starts the count again, as a yield does); after ``limit`` looks time moves
    anyway, an overrun (:attr:`overran`).
    """

    __slots__ = ("limit", "looks", "needed", "overran", "quiet")

    def __init__(self, needed: int, limit: int) -> None:
        self.needed = needed
        self.limit = limit
        self.looks = 0
        self.quiet = 0
        #: Whether the last settling ran out of looks (time then moves anyway).
        self.overran = False

    def start(self) -> None:
        """New work was woken: settle it from the start."""
        self.looks = self.quiet = 0
        self.overran = False

    def observe(self, woke_due: bool, quiescent: bool) -> bool:
        """One look after a yield: ``woke_due``, waits due now were woken; ``quiescent``,
        nothing else looked runnable. True once time may move (settled, or out of looks)."""
        self.looks += 1
        if woke_due or not quiescent:
            self.quiet = 0
        else:
            self.quiet += 1
            if self.quiet >= self.needed:
                return True
        if self.looks >= self.limit:
            self.overran = True
            return True
        return False


class SimCore:
    """Sim time, its heap of deadlines, its source, pacing and jumps: the advancement rule.

    Time sources talk to the kernel through :class:`~evclock.sources.SourceHost`, which this
    class implements: :attr:`now_ns`, :meth:`stepped_to`, :meth:`work_ready`, :meth:`jump`,
    :meth:`serves`, :meth:`time_arrived`, :attr:`clock`, :meth:`is_closed` and
    :meth:`call_exception_handler`.
    """

    #: Whether kernels made from now on wake tasks in place (the default); False: through
    #: asyncio's own path. tests/kernel/test_wake_paths.py runs its corpus both ways.
    wake_in_place: bool = True

    def __init__(
        self,
        source: TimeSource,
        host: CoreHost,
        *,
        rtf: float | None = None,
        strict: bool = False,
        max_lag: float = DEFAULT_MAX_LAG,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        #: Sim time in integer nanoseconds: what the source last returned.
        self.now_ns: int = source.now_ns
        self.source = source
        self.host = host
        self.pacer = Pacer(self._read_now, rtf=rtf, strict=strict, max_lag=max_lag, wall=wall)
        #: After PACING: wall seconds to wait before asking again (None: until a control changes).
        self.pacing_delay: float | None = None
        #: The host is told (:meth:`CoreHost._interrupt_wait`) of deadlines before this.
        self.notify_before: int = -1
        self.jump_handlers: list[JumpHandle] = []
        #: The schedule (see the module): ``heap`` holds each distinct deadline once, ``at``
        #: maps it to what is due then (one entry, or a ``_Bucket`` of several in FIFO
        #: order). Hot paths outside this class (``clock_sleep``, ``SimEventLoop.call_later``)
        #: insert inline, as :meth:`schedule` does: ``if at.setdefault(when, e) is e:
        #: heappush(heap, when)``, else ``schedule(when, e)``. Nothing else writes them.
        self.heap: list[int] = []
        self.at: dict[int, Any] = {}
        self._settled: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = itertools.count().__next__
        #: Cancelled timers still in the heap (purged once they are many): a timer's cancel()
        #: counts itself here while it is scheduled (``SimEventLoop``'s timers, inline).
        self.cancelled_timers = 0
        #: Creates the future of a sim-time wait, raising if waits are impossible now or here
        #: (closed loop, stopped driver, wrong thread): set by the host.
        self.future_factory: Callable[[], asyncio.Future[None]]
        #: Or, faster, the loop a plain future is created on when waits are possible there
        #: with no further check (an open SimEventLoop); None: use ``future_factory``.
        self.future_loop: asyncio.AbstractEventLoop | None = None
        self._anything_runnable = host._anything_runnable
        # The default source moves exactly to any later target it is given: the hot path
        # (wake_next) moves it itself instead of calling its advance() (exact type only: a
        # subclass may override advance()).
        self._virtual = source if type(source) is VirtualTimeSource else None
        #: Whether wake-ups run in place (see :meth:`wake_next` and :meth:`fire`); False:
        #: every wake-up takes asyncio's own path (the future's callbacks scheduled with
        #: ``call_soon``, run from the ready queue) - for the tests that compare the two.
        self._in_place = self.wake_in_place
        if not self._in_place:
            self._virtual = None  # (the short path's in-place wake-up is taken only with it)
        #: Whether the short path (:meth:`wake_next`) may be taken, as far as the kernel
        #: knows: no pacing and no external source (the host adds what it sees outside).
        self.short_path = False
        self.pacing_changed()

    def _read_now(self) -> int:
        return self.now_ns

    # ------------------------------------------------------------ scheduling

    def call_at(self, when_ns: int, timer: Any) -> None:
        """Schedule an asyncio ``TimerHandle`` at ``when_ns`` (beyond the time range: never)."""
        if when_ns <= MAX_TIME_NS:
            if self.at.setdefault(when_ns, timer) is timer:
                heapq.heappush(self.heap, when_ns)
            else:
                self.schedule(when_ns, timer)
            timer._scheduled = True

    def schedule(self, when_ns: int, entry: Any) -> None:
        """Schedule ``entry`` at ``when_ns``, after what is due then already."""
        at = self.at
        present = at.setdefault(when_ns, entry)
        if present is entry:
            heapq.heappush(self.heap, when_ns)
        elif type(present) is _Bucket:
            present.append(entry)
        else:
            at[when_ns] = _Bucket((present, entry))

    def timer_cancelled(self) -> None:
        """A scheduled timer was cancelled (it stays in the heap until purged)."""
        self.cancelled_timers += 1

    def stop_at(self, when_ns: int) -> None:
        """Make time stop exactly at ``when_ns`` on its way (step_until, run_until)."""
        self.schedule(when_ns, _STOP)
        if when_ns < self.notify_before:
            self.host._interrupt_wait()

    def drop_stops(self) -> None:
        """Remove every stop mark still ahead: the ``step_until`` that placed it ended
        before its target (``pause()``, ``resume()``, a new ``step_until``), and a mark left
        behind would stop time where nothing is due - a step spent on no wake-up."""
        for entry in self.at.values():
            if entry is _STOP or (type(entry) is _Bucket and any(one is _STOP for one in entry)):
                break
        else:
            return
        self._rebuild([(when, entry) for when, entry in self._entries() if entry is not _STOP])

    def wait_settled(self, when_ns: int) -> asyncio.Future[None]:
        """A future resolved at ``when_ns`` once the work due then has settled
        (:meth:`wake_settled`); time stops there exactly."""
        fut = self.future_factory()
        heapq.heappush(self._settled, (when_ns, self._seq(), fut))
        if when_ns < self.notify_before:
            self.host._interrupt_wait()
        return fut

    def next_deadline(self) -> int | None:
        """The earliest live deadline, dropping cancelled entries at the head."""
        heap = self.heap
        at = self.at
        while heap and self._dead(at[heap[0]]):
            del at[heapq.heappop(heap)]
        if self.cancelled_timers > _PURGE_AT and self.cancelled_timers * 2 > len(heap):
            self._purge()
        settled = self._settled
        while settled and settled[0][2].done():
            heapq.heappop(settled)
        if heap:
            head = heap[0]
            return min(head, settled[0][0]) if settled else head
        return settled[0][0] if settled else None

    def has_pending(self) -> bool:
        """Whether any scheduled wait or timer can still fire (for deadlock detection)."""
        return self.next_deadline() is not None

    def _dead(self, entry: Any) -> bool:
        """Whether nothing in ``entry`` (at the heap's head) can fire any more; then it is
        dropped: a cancelled timer leaves the count of those to purge."""
        if type(entry) is _Bucket:
            for one in entry:
                if one is _STOP:
                    return False
                if isinstance(one, _TimerHandle):
                    if not one._cancelled:
                        return False
                elif not one.done():
                    return False
            for one in entry:
                if isinstance(one, _TimerHandle):
                    one._scheduled = False
                    self.cancelled_timers -= 1
            return True
        if entry is _STOP:
            return False
        if isinstance(entry, _TimerHandle):
            if not entry._cancelled:
                return False
            entry._scheduled = False
            self.cancelled_timers -= 1
            return True
        return bool(entry.done())

    def _entries(self) -> list[tuple[int, Any]]:
        """Every scheduled ``(when_ns, entry)``, in firing order."""
        at = self.at
        out: list[tuple[int, Any]] = []
        for when in sorted(self.heap):
            entry = at[when]
            if type(entry) is _Bucket:
                out.extend((when, one) for one in entry)
            else:
                out.append((when, entry))
        return out

    def _rebuild(self, entries: list[tuple[int, Any]]) -> None:
        """Schedule exactly ``entries`` (``(when_ns, entry)``, in firing order)."""
        self.heap.clear()
        self.at.clear()
        for when, entry in entries:
            self.schedule(when, entry)

    def _purge(self) -> None:
        keep = []
        for when, entry in self._entries():
            if isinstance(entry, _TimerHandle):
                if entry._cancelled:
                    entry._scheduled = False
                    continue
            elif entry is not _STOP and entry.done():
                continue
            keep.append((when, entry))
        self._rebuild(keep)
        self.cancelled_timers = 0

    # ------------------------------------------------------------- firing

    def take_due(self) -> list[Any] | None:
        """Pop every entry due at the current time (to :meth:`fire` after the ready
        callbacks, as asyncio does with its timers), or None."""
        heap = self.heap
        now = self.now_ns
        if not heap or heap[0] > now:
            return None
        return self._pop_due(now, [])

    def _pop_due(self, now: int, due: list[Any]) -> list[Any]:
        """Append the entries due at ``now`` to ``due``, in order."""
        heap = self.heap
        pop = self.at.pop
        while heap and heap[0] <= now:
            entry = pop(heapq.heappop(heap))
            if type(entry) is _Bucket:
                due.extend(entry)
            else:
                due.append(entry)
        return due

    def fire(self, due: list[Any], ready: Any) -> None:
        """Fire entries from :meth:`take_due`, in (when, seq) order, on a SimEventLoop.

        The order is exactly stock asyncio's: a timer callback runs here; a resolved sleep's
        wake-ups (its task's step) run after every entry of the batch, in order - queued
        at the end of the ready queue. When nothing was queued before the batch, and none
        of its plain callbacks queues anything, those wake-ups would be the very next
        callbacks to run, in that order: they run here, in place, with no ``Handle``
        (every future resolved first, so each step sees the others' futures done, as on
        stock asyncio).
        """
        in_place: list[tuple[Any, Any, asyncio.Future[Any]]] | None = (
            None if ready or not self._in_place else []
        )
        for obj in due:
            if obj is _STOP:
                continue
            if not isinstance(obj, _TimerHandle):
                if obj.done():
                    continue
                fut, result = obj, None
            else:
                obj._scheduled = False
                if obj._cancelled:
                    self.cancelled_timers -= 1
                    continue
                if obj._callback is not _SET_RESULT_UNLESS_CANCELLED or obj._args[0].done():
                    if in_place:
                        # A plain callback may queue work, which must come after the
                        # wake-ups collected so far: queue them as asyncio would have.
                        self._queue_wakeups(in_place, ready)
                    in_place = None
                    obj._run()
                    continue
                fut, result = obj._args
            if in_place is None:
                fut.set_result(result)
                continue
            # a copy (the pure-Python future returns its own list; a C one None when empty)
            callbacks = fut._callbacks
            if callbacks:
                for callback, ctx in list(callbacks):
                    fut.remove_done_callback(callback)
                    in_place.append((callback, ctx, fut))
            fut.set_result(result)
        if in_place:
            self._run_wakeups(in_place, ready)

    def _queue_wakeups(self, wakeups: list[tuple[Any, Any, Any]], ready: Any) -> None:
        """Queue collected wake-ups at the end of the ready queue, in order."""
        loop = self.host
        for callback, ctx, fut in wakeups:
            ready.append(asyncio.Handle(callback, (fut,), loop, ctx))  # type: ignore[arg-type]

    def _run_wakeups(self, wakeups: list[tuple[Any, Any, Any]], ready: Any) -> None:
        """Run collected wake-ups in place, in order (what would run next anyway); if one
        raises SystemExit or KeyboardInterrupt, the rest are queued first, as they were."""
        for i, (callback, ctx, fut) in enumerate(wakeups):
            try:
                ctx.run(callback, fut)
            except (SystemExit, KeyboardInterrupt):
                rest = wakeups[i + 1 :]
                loop = self.host
                for callback, ctx, fut in reversed(rest):
                    ready.appendleft(asyncio.Handle(callback, (fut,), loop, ctx))  # type: ignore[arg-type]
                raise
            except BaseException as exc:
                self._report_wakeup_error(exc)

    def _report_wakeup_error(self, exc: BaseException) -> None:
        self.host._call_exception_handler(
            {"message": "Exception in a wake-up callback of a sim-time wait", "exception": exc}
        )

    def wake_due(self) -> bool:
        """Resolve every sleep due now through its future (hosts on a foreign loop)."""
        heap = self.heap
        now = self.now_ns
        woke = False
        if heap and heap[0] <= now:
            for obj in self._pop_due(now, []):
                if obj is not _STOP and not isinstance(obj, _TimerHandle) and not obj.done():
                    obj.set_result(None)
                    woke = True
        return woke

    def wake_settled(self) -> bool:
        """Resolve the :meth:`wait_settled` waits due now."""
        settled = self._settled
        now = self.now_ns
        woke = False
        while settled and settled[0][0] <= now:
            fut = heapq.heappop(settled)[2]
            if not fut.done():
                fut.set_result(None)
                woke = True
        return woke

    def due_now(self) -> bool:
        """Whether an entry of the main heap is due at the current time."""
        heap = self.heap
        return bool(heap) and heap[0] <= self.now_ns

    def settled_due_now(self) -> bool:
        """Whether a :meth:`wait_settled` wait is due at the current time."""
        settled = self._settled
        return bool(settled) and settled[0][0] <= self.now_ns

    # ------------------------------------------------------------- the rule

    def pacing_changed(self) -> None:
        """A pacing control changed (rtf, pause, step, step_until): re-decide whether the
        short path may be taken. Without pacing the host may advance straight to the next
        deadline, unless the source waits for the outside (never the short path then)."""
        self.short_path = self.pacer.unpaced and not self.source.external

    def advance(self) -> int:
        """Nothing ran at the current time: decide and, if possible, move time (see module)."""
        target = self.next_deadline()
        if (target is not None and target <= self.now_ns) or self._anything_runnable():
            return DUE
        host = self.host
        pacer = self.pacer
        if pacer.paused and pacer.waits_for_control():
            # A pause outranks a hold: nothing moves until a control, however long, so
            # the host waits as paused (unbounded), not as held (bounded by stall_timeout).
            self.pacing_delay = None
            return PACING
        horizon = host._held_horizon(pacer.paused)
        if horizon is not None and (target is None or target - self.now_ns > horizon):
            return HELD  # (a hold with a horizon lets earlier deadlines fire first)
        host._before_moving()
        if self._anything_runnable():
            return DUE  # a thread handed work over (and ended) while the host looked
        source = self.source
        if target is None and not source.free_running:
            return WAIT_IO if host._could_wake() else DEADLOCK
        gate = None if pacer.unpaced else pacer.allow
        before = self.now_ns
        now = self.now_ns = source.advance(target, gate)
        if now != before:
            return MOVED
        if gate is not None and pacer.refused:
            self.pacing_delay = pacer.delay
            return PACING
        if source.external:
            return WAIT_SOURCE
        return DUE  # a step hook woke a task before time could move

    def wake_next(self, ready: Any) -> bool:
        """The short path (rule step 0), when the host checked that nothing else can matter
        (no pacing, no I/O, no outside work, nothing ready): advance straight to the next
        deadline and fire what is due there. False if nothing is scheduled (the host applies
        :meth:`advance`).

        Same order as :meth:`take_due` then :meth:`fire`; if the advance itself made work
        ready (a step hook), the host runs it first. The common case - one task waits alone
        at the next deadline, on a ``clock.sleep`` future or ``asyncio.sleep``'s timer - is
        woken here in place, with no ``Handle``: this is the one wake routine of the kernel.
        """
        heap = self.heap
        at = self.at
        virtual = self._virtual
        fut: Any = None
        # The common case first: one task waits alone at the next deadline (deadlines are
        # distinct), later than now, on the default source, on a clock.sleep future or on
        # asyncio.sleep's timer. A done future has no callbacks, a cancelled timer no
        # callback: both fail the unpacking below and take the general path.
        if virtual is not None and heap:
            when = heap[0]
            if when > self.now_ns:
                obj = at[when]
                if type(obj) is _Future:
                    fut, result = obj, None
                elif (
                    isinstance(obj, _TimerHandle) and obj._callback is _SET_RESULT_UNLESS_CANCELLED
                ):
                    fut, result = obj._args
                if fut is not None:
                    try:
                        # Exactly one done-callback (a task's wake-up): the future is
                        # pending, as a future drops its callbacks when it completes.
                        ((callback, ctx),) = fut._callbacks
                    except (TypeError, ValueError, AttributeError):
                        fut = None  # done, several waiters, none, not a future: below
                    else:
                        virtual.now_ns = self.now_ns = when
                        _heappop(heap)
                        del at[when]
                        if fut is not obj:
                            obj._scheduled = False
        if fut is None:
            # Every other case: timers, buckets, dead entries, stepping sources, entries
            # due now. Drop what can no longer fire at the head first.
            while heap:
                when = heap[0]
                obj = at[when]
                if type(obj) is _Future:
                    if not obj.done():
                        break
                elif isinstance(obj, _TimerHandle):
                    if not obj._cancelled:
                        break
                    obj._scheduled = False
                    self.cancelled_timers -= 1
                elif not self._dead(obj):
                    break
                _heappop(heap)
                del at[when]
            else:
                return False
            now = self.now_ns
            if when > now:
                if virtual is not None:
                    # VirtualTimeSource.advance(when, None), inlined: it moves exactly to
                    # any later target (the hot path's one call saved)
                    virtual.now_ns = self.now_ns = now = when
                else:
                    now = self.now_ns = self.source.advance(when, None)
                    if ready or not heap:
                        return True
                    when = heap[0]  # a step hook may have scheduled (or jumped) meanwhile
                    if when > now:
                        return True  # a stepping source returns in chunks on long advances
                    obj = at[when]
            _heappop(heap)
            del at[when]
            # Deadlines are distinct in the heap: ``obj`` is alone unless it was overdue.
            if type(obj) is not _Bucket and (not heap or heap[0] > now) and self._in_place:
                if type(obj) is _Future:
                    fut, result = obj, None
                elif isinstance(obj, _TimerHandle):
                    if obj._callback is _SET_RESULT_UNLESS_CANCELLED:
                        fut, result = obj._args  # asyncio.sleep's future
                elif obj is not _STOP:
                    fut, result = obj, None  # a future of another type (a foreign loop's)
                if fut is not None:
                    try:
                        ((callback, ctx),) = fut._callbacks  # one waiter, pending
                    except (TypeError, ValueError):
                        fut = None  # several waiters, none, or done: fire() below
                    else:
                        if fut is not obj:
                            obj._scheduled = False
            if fut is None:
                self.fire(self._pop_due(now, list(obj) if type(obj) is _Bucket else [obj]), ready)
                return True
        # The one wake-up done here, in place: resolve the future and run its one waiter's
        # step now, as the ready queue would have next (no Handle, no call_soon hop).
        if type(fut) is _Future:
            _future_remove_done_callback(fut, callback)
            _future_set_result(fut, result)
        else:
            fut.remove_done_callback(callback)
            fut.set_result(result)
        try:
            ctx.run(callback, fut)
        except (SystemExit, KeyboardInterrupt):
            raise
        except BaseException as exc:
            self._report_wakeup_error(exc)
        return True

    # ------------------------------------------------ what time sources use

    @property
    def clock(self) -> SimClock:
        """The sim clock tasks on this host read."""
        return self.host.clock

    def stepped_to(self, now_ns: int) -> None:
        """A source moving in several increments publishes each new time (before its hooks)."""
        self.now_ns = now_ns

    def time_arrived(self) -> None:
        """An external source received news from outside (call it from the reader callback):
        the host asks the source to advance again at once instead of at its next poll."""
        self.host._interrupt_wait()

    def work_ready(self) -> bool:
        """Whether a task became runnable (a stepping source stops stepping then)."""
        return self._anything_runnable()

    def serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` wait on this sim time."""
        return self.host._serves(loop)

    def is_closed(self) -> bool:
        """True once the host closed (a source then moves its time without a jump)."""
        return self.host._is_closed()

    def call_exception_handler(self, context: dict[str, Any]) -> None:
        """Report an error from a source (a failing step hook) to the host."""
        self.host._call_exception_handler(context)

    def jump(self, before_ns: int, after_ns: int, assign: Callable[[int], None]) -> TimeJump:
        """Move sim time discontinuously (a reset, a restored snapshot, ``set_time``).

        Pre-jump handlers run, ``assign(after_ns)`` gives the source its new time, every
        pending sim-time wait is woken with :class:`ClockJumpedError`, asyncio timers keep their
        remaining delay, stop marks ahead of the new time stay, pacing re-anchors, then
        post-jump handlers run.
        """
        jump = TimeJump(new_time(before_ns, SIM), new_time(after_ns, SIM))
        handlers = [h for h in list(self.jump_handlers) if h.threshold.matches(jump)]
        for handler in handlers:
            if handler.pre is not None:
                handler.pre(jump)
        assign(after_ns)
        self.now_ns = after_ns
        delta = after_ns - before_ns
        kept = []
        woken: list[asyncio.Future[None]] = []
        for when_ns, obj in self._entries():
            if obj is _STOP:
                if when_ns > after_ns:
                    kept.append((when_ns, obj))
            elif isinstance(obj, _TimerHandle):
                if obj._cancelled:
                    obj._scheduled = False
                    continue
                shifted = max(when_ns + delta, after_ns)
                obj._when = shifted / 1_000_000_000
                kept.append((shifted, obj))
            elif not obj.done():
                woken.append(obj)
        kept.sort(key=_deadline)  # stable: equal deadlines keep their order
        self._rebuild(kept)
        self.cancelled_timers = 0
        settled, self._settled = self._settled, []
        woken.extend(fut for _, _, fut in settled if not fut.done())
        for fut in woken:
            fut.set_exception(ClockJumpedError(jump))
        self.pacer.reanchor()
        self.host._interrupt_wait()
        for handler in handlers:
            if handler.post is not None:
                handler.post(jump)
        return jump

    # ------------------------------------------------------------- shutdown

    def end_waits(self, failure: Exception | None, settled_error: Callable[[], Exception]) -> None:
        """The host stops for good: pending waits raise ``failure`` (or are cancelled);
        :meth:`wait_settled` waits raise ``failure`` or ``settled_error()``."""
        entries = self._entries()
        self.heap, self.at = [], {}
        for _, obj in entries:
            if obj is _STOP or isinstance(obj, _TimerHandle) or obj.done():
                continue
            if failure is not None:
                obj.set_exception(failure)
            else:
                obj.cancel()
        settled, self._settled = self._settled, []
        for _, _, fut in settled:
            if not fut.done():
                fut.set_exception(failure or settled_error())
