"""The world outside the loop: what holds sim time, and what can wake the loop.

The rule is stated in docs/architecture.md, "Work outside the loop".

One :class:`OutsideWork` per :class:`~evclock.SimEventLoop` answers the two questions the
loop asks whenever nothing is runnable at the current sim time:

**Is sim time held?** (:meth:`OutsideWork.holder`) Counted exactly where evclock can:

* explicit holds (``loop.hold_time()``), and an armed wall-clock ``SIGALRM`` timer
  (``signal.setitimer``) whose signal the loop handles (``add_signal_handler``);
* executor jobs (``run_in_executor``, ``asyncio.to_thread``) from submission until their
  result is back on the loop, except while the job's thread is *parked* - blocked without
  timeout on a lock, condition or queue, which only another thread can end (a job waiting
  for ``run_coroutine_threadsafe(...).result()`` waits for the loop: time must move);
* child processes the loop started, while they run and a task waits on them: on their exit
  (``Process.wait()``, ``communicate()``, anyio's ``Process.wait()``) or on their output (a
  read on their stdout or stderr); after the exit, a read (or asyncio's ``wait()``, which
  also waits for the pipes) while a grandchild keeps their pipes open. A child started
  with a protocol of your own holds while it runs (evclock cannot see what is awaited).
  A child nobody waits on does not hold: a long-running helper
  process lets the simulation run; its output and its exit still wake the loop.

Inferred: socket bytes the loop wrote that the kernel is still delivering (Linux; they
hold while their count moves, up to ``IN_FLIGHT_PATIENCE`` when it does not). And every
other thread, daemon or not (unless ``watch_threads=False``), from what
the kernel says it is doing (see :mod:`evclock.outside._threads`): running or sleeping with a
timeout holds; parked, blocked on I/O without timeout, or an event loop waiting does not.

**Could anything wake the loop?** (:meth:`OutsideWork.can_wake`) Registered I/O, signal
handlers, children still running, executor jobs and holds in flight, and threads that run,
sleep with a timeout, wait on I/O or are event loops. Otherwise waiting is a deadlock.

Every hold is bounded by ``stall_timeout``: the :class:`~evclock.StallError` names what
holds - each thread with its state and innermost frames.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import itertools
import selectors
import signal
import sys
import threading
import time
from asyncio import subprocess as aio_subprocess
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

from evclock._cpython import (
    event_waiters,
    stream_reader_waiter,
    subprocess_exit_waiters,
    subprocess_exited,
    subprocess_finished,
    thread_registry,
)
from evclock._procfs import (
    ThreadState,
    child_wait_deadline,
    far_end,
    forget_child,
    near_end,
    waited_fds,
)
from evclock.outside._threads import (
    HOLDING_STATES,
    WAKING_STATES,
    describe_thread,
    survey,
    thread_state,
    wait_deadline,
)

_T = TypeVar("_T")

#: How the loop should wait while time is held: exact holders call it back through its
#: self-pipe when they end; inferred ones (plain threads) must be polled.
EXACT, INFERRED = "exact", "inferred"

_QUEUED, _RESULT_IN_FLIGHT = -1, -2
#: Wall seconds unsent TCP bytes may stay unchanged and still count as in flight.
IN_FLIGHT_PATIENCE = 0.2

try:  # Linux: the unsent/unacknowledged bytes of a TCP socket
    import fcntl
    import struct
    import termios

    _TIOCOUTQ: int | None = termios.TIOCOUTQ if sys.platform.startswith("linux") else None
except ImportError:  # pragma: no cover - Windows
    _TIOCOUTQ = None


def _queued(fd: int, request: int) -> int:
    """A socket's queued byte count (``ioctl``); 0 for anything else (ENOTTY)."""
    try:
        return int(struct.unpack("i", fcntl.ioctl(fd, request, b"\0\0\0\0"))[0])
    except OSError:
        return 0


class OutsideWork:
    """Everything outside one loop that may hold its sim time or wake it."""

    def __init__(
        self,
        loop_thread_id: Callable[[], int | None],
        io_registered: Callable[[], bool],
        signal_handlers: Callable[[], Mapping[int, object]],
        registered: Callable[[], Iterable[selectors.SelectorKey]],
        wake_loop: Callable[[], None],
        *,
        watch_threads: bool,
        sim_now: Callable[[], int] = lambda: 0,
    ) -> None:
        self._loop_thread_id = loop_thread_id
        self._io_registered = io_registered
        self._signal_handlers = signal_handlers
        self._registered = registered
        self._in_flight: dict[int, int] = {}  # fd -> bytes the kernel has not delivered
        self._in_flight_since = 0.0
        self.horizon_ns: int | None = None
        self._wake_loop = wake_loop
        self._sim_now = sim_now
        #: Timed waits seen (of threads and children): which wait -> (its monotonic
        #: deadline, the sim time it ends at).
        self._pins: dict[object, tuple[float, int]] = {}
        self.watch_threads = watch_threads
        self._lock = threading.Lock()
        self._holds = 0
        # Executor jobs in flight: token -> (what, thread ident | _QUEUED | _RESULT_IN_FLIGHT).
        self._jobs: dict[int, tuple[str, int]] = {}
        self._tokens = itertools.count()
        self._children: list[asyncio.SubprocessTransport] = []
        #: How many exactly-counted things are in flight (holds, jobs, children): a plain
        #: attribute, read on the loop's hot path.
        self.active = 0

    # ----------------------------------------------------------- bookkeeping

    def add_hold(self) -> None:
        with self._lock:
            self._holds += 1
            self.active += 1

    def release_hold(self) -> None:
        with self._lock:
            self._holds -= 1
            self.active -= 1
        if threading.get_ident() != self._loop_thread_id():
            self._wake_loop()  # released from another thread: re-decide now, not at next poll

    def job(self, func: Callable[..., _T], executor: object) -> tuple[int, Callable[..., _T]]:
        """Register an executor job; return its token and the callable to submit instead.

        Thread-pool jobs are wrapped to record which thread runs them (the callable keeps
        its result and exceptions); a job for another executor (a process pool: the
        callable must stay picklable) is submitted unchanged and holds until it is done.
        """
        token = next(self._tokens)
        what = getattr(func, "__qualname__", None) or repr(func)
        with self._lock:
            self._jobs[token] = (what, _QUEUED)
            self.active += 1
        if executor is not None and not isinstance(executor, concurrent.futures.ThreadPoolExecutor):
            return token, func

        def run_job(*args: Any) -> _T:
            with self._lock:
                self._jobs[token] = (what, threading.get_ident())
            try:
                return func(*args)
            finally:
                with self._lock:
                    if token in self._jobs:
                        self._jobs[token] = (what, _RESULT_IN_FLIGHT)

        return token, run_job

    def job_done(self, token: int) -> None:
        """The job's result reached the loop (its asyncio future is done)."""
        with self._lock:
            if self._jobs.pop(token, None) is not None:
                self.active -= 1

    def add_child(self, transport: asyncio.SubprocessTransport) -> None:
        """A child process the loop started (its transport, once connected)."""
        with self._lock:
            self._children.append(transport)
            self.active += 1

    # ------------------------------------------------------------- questions

    def holder(self, *, timed_waits_hold: bool = True) -> str | None:
        """Whether sim time is held now: EXACT, INFERRED, or None.

        ``timed_waits_hold=False`` (the loop is paused: sim time moves only by steps, so a
        thread's wall-time timeout is no event on it): threads in timed waits do not hold.

        When held only by threads in timed waits of known length (``Event.wait(3)``,
        ``time.sleep(1)``), :attr:`horizon_ns` says how far sim time may still move: as on
        stock asyncio, where loop timers and thread timeouts race on one clock, what is due
        before the first of those waits ends happens first. Each such wait is an event on
        sim time, placed when it is first seen at sim ``now`` + its remaining wall length
        (sim time has not moved since the thread entered it: a running thread holds it),
        and kept there: sim time may advance up to it, then holds until the thread acts.
        Otherwise it is None: sim time stands still.
        """
        self.horizon_ns = None
        if self._holds or self._alarm_pending():
            return EXACT
        threads: list[tuple[threading.Thread, ThreadState]] | None = None
        if self._jobs:
            for _, where in list(self._jobs.values()):
                if where < 0:
                    return EXACT  # queued, or its result is on its way to the loop
                if threads is None:
                    threads = survey(self._loop_thread_id())
                if self._job_thread_holds(where, threads):
                    return EXACT
        timed: list[tuple[object, float]] = []  # (which wait, its monotonic deadline)
        if self._children and self._children_hold(timed):
            return EXACT
        if _TIOCOUTQ is not None:
            if self.watch_threads and threads is None:
                threads = survey(self._loop_thread_id())
            if self._bytes_in_flight(threads or ()):
                return INFERRED
        holder = EXACT  # children's timed waits end in output or an exit: both wake us
        if self.watch_threads:
            if threads is None:
                threads = survey(self._loop_thread_id())
            jobs = self._job_threads()
            for thread, state in threads:
                if state not in HOLDING_STATES or thread.ident in jobs:
                    continue
                if state is ThreadState.TIMED and (
                    not timed_waits_hold or self._waits_for_the_loop(thread)
                ):
                    continue
                deadline = wait_deadline(thread) if state is ThreadState.TIMED else None
                if deadline is None:
                    self._pins = {}
                    return INFERRED  # running, or a timed wait of unknown length
                timed.append((thread.ident or 0, deadline))
                holder = INFERRED
        if not timed:
            self._pins = {}
            return None
        now_ns = self._sim_now()
        mono = time.monotonic()
        pins = {}
        for key, deadline in timed:
            pin = self._pins.get(key)
            if pin is None or pin[0] != deadline:
                # First seen: the wait ends at sim now + its remaining wall length.
                pin = (deadline, now_ns + round(max(deadline - mono, 0.0) * 1e9))
            pins[key] = pin
        self._pins = pins
        self.horizon_ns = max(min(pin[1] for pin in pins.values()) - now_ns, 0)
        return holder

    def can_wake(self) -> bool:
        """Whether anything outside the loop could still make a task runnable."""
        if self._io_registered() or bool(self._signal_handlers()) or self.active:
            return True
        if self.watch_threads:
            return any(state in WAKING_STATES for _, state in survey(self._loop_thread_id()))
        return False

    def describe(self) -> str:
        """What holds sim time right now, one item per line (for StallError)."""
        lines = []
        if self._holds:
            lines.append(f"  {self._holds} explicit hold(s) (loop.hold_time())")
        threads = survey(self._loop_thread_id())
        by_ident = {t.ident: (t, s) for t, s in threads}
        for what, where in list(self._jobs.values()):
            if where == _QUEUED:
                lines.append(f"  executor job {what}: queued, waiting for a worker thread")
            elif where == _RESULT_IN_FLIGHT:
                lines.append(f"  executor job {what}: finished, result on its way")
            elif where in by_ident:
                thread, state = by_ident[where]
                if state is not ThreadState.PARKED:
                    lines.append(f"  executor job {what} in {describe_thread(thread, state)}")
        for child in list(self._children):
            if self._child_holds(child):
                lines.append(f"  child process {child.get_pid()}: a task waits on it")
        if self.watch_threads:
            jobs = self._job_threads()
            for thread, state in threads:
                if state in HOLDING_STATES and thread.ident not in jobs:
                    lines.append("  " + describe_thread(thread, state))
        return "\n".join(lines) or "  nothing any more (it just ended)"

    # ------------------------------------------------------------- internals

    def _bytes_in_flight(self, threads: Iterable[tuple[threading.Thread, ThreadState]]) -> bool:
        """Bytes on their way through the kernel, which on loopback arrive within
        milliseconds, hold sim time while their count moves:

        * bytes the loop wrote to a socket that the kernel has not delivered yet (an
          in-process TLS peer's close_notify);
        * bytes a thread blocked on a socket (``poll``, ``recv``) wrote to it that have
          not arrived yet: Nagle's algorithm keeps a small record (a TLS peer's reply)
          until the loop's side acknowledges the previous one, up to a delayed-ACK period,
          while the thread already waits for the answer; and sent bytes wait for their
          acknowledgement (counted until then, which bounds the same way).

        Bytes that stay put for ``IN_FLIGHT_PATIENCE`` are not in flight: the peer is not
        reading (its window is full), which is the peer's business, not the kernel's."""
        assert _TIOCOUTQ is not None
        pending = {}
        for key in list(self._registered()):
            # Transports register bare fds: ask every one; what is not a socket says so
            # (ENOTTY). A Unix socket counts its peer's unread bytes: bounded the same way.
            unsent = _queued(key.fd, _TIOCOUTQ)
            if unsent:
                pending[key.fd] = unsent
        for thread, state in threads:
            if state is ThreadState.WAITING_IO or state is ThreadState.TIMED:
                for fd in waited_fds(thread):
                    unsent = _queued(fd, _TIOCOUTQ)
                    if unsent:
                        pending[-1 - fd] = unsent  # apart from the loop's own descriptors
        now = time.monotonic()
        if pending != self._in_flight:
            self._in_flight = pending
            self._in_flight_since = now
        return bool(pending) and now - self._in_flight_since < IN_FLIGHT_PATIENCE

    def _waits_for_the_loop(self, thread: threading.Thread) -> bool:
        """Whether ``thread``'s timed wait is on a descriptor whose other end the loop
        serves (a pipe, a Unix or IP socket registered in its selector): it waits for the
        loop - an in-process peer on a socket with a timeout - which is no timed work of
        its own: only the loop can end it early, so it does not hold sim time. Exact: the
        ends are matched by the kernel's identities (pipe inode, peer inode, address)."""
        fds = waited_fds(thread)
        if not fds:
            return False
        loop_ends = [end for key in list(self._registered()) if (end := near_end(key.fd))]
        return bool(loop_ends) and any(far_end(fd) in loop_ends for fd in fds)

    def _alarm_pending(self) -> bool:
        """A wall-clock SIGALRM is armed (``signal.setitimer``/``alarm``) and the loop
        handles it: a wall-time event is on its way, like a thread's timed sleep."""
        sigalrm = getattr(signal, "SIGALRM", None)
        return (
            sigalrm is not None
            and sigalrm in self._signal_handlers()
            and signal.getitimer(signal.ITIMER_REAL)[0] > 0
        )

    def _job_threads(self) -> set[int]:
        return {where for _, where in list(self._jobs.values()) if where >= 0}

    def _job_thread_holds(
        self, ident: int, threads: list[tuple[threading.Thread, ThreadState]]
    ) -> bool:
        for thread, state in threads:
            if thread.ident == ident:
                return state is not ThreadState.PARKED
        # Not surveyed (the loop's own thread, when it runs its own executor job inline):
        # judge it directly.
        current = thread_registry.get(ident)
        if current is None:
            return True
        return thread_state(current, None) is not ThreadState.PARKED

    def _children_hold(self, timed: list[tuple[object, float]]) -> bool:
        """Whether a child holds sim time outright; a child a task waits on that is asleep
        in a timed wait whose end the kernel shows (``time.sleep`` in a worker process)
        is added to ``timed`` instead: like a thread's, that wait is an event in sim time."""
        holds = False
        kept = []
        for child in self._children:
            if _child_finished(child):
                pid = child.get_pid()
                if pid is not None:
                    forget_child(pid)
                continue
            kept.append(child)
            if holds or not self._child_holds(child):
                continue
            pid = child.get_pid()
            wait = (
                child_wait_deadline(pid) if pid is not None and not _child_exited(child) else None
            )
            if wait is None:
                holds = True
            else:
                timed.append(wait)
        with self._lock:
            self.active -= len(self._children) - len(kept)
            self._children[:] = kept
        return holds

    @staticmethod
    def _child_holds(child: asyncio.SubprocessTransport) -> bool:
        """A task waits on the child: on its exit while it runs, or on its output while
        that is open - also after the child exited, when a grandchild that inherited the
        pipe still holds it (it will write or close)."""
        if _child_finished(child):
            return False
        # asyncio internals (no public equivalent): the futures of Process.wait() callers.
        # asyncio resolves them once the child exited *and* its pipes closed: they hold
        # after the exit too while a grandchild keeps a pipe open.
        if any(not w.done() for w in subprocess_exit_waiters(child)):
            return True
        exited = _child_exited(child)
        protocol = child.get_protocol()
        if not exited:
            if not isinstance(protocol, aio_subprocess.SubprocessStreamProtocol):
                return True  # a protocol of the user's: what it awaits is invisible
            # anyio's subclass (_ProcessStreamProtocol) signals the exit with an
            # asyncio.Event ``exited`` that its Process.wait() awaits: Event._waiters
            # holds the futures of the tasks waiting on it (asyncio internal).
            exit_event = getattr(protocol, "exited", None)
            if isinstance(exit_event, asyncio.Event) and any(
                not w.done() for w in event_waiters(exit_event)
            ):
                return True
        elif not isinstance(protocol, aio_subprocess.SubprocessStreamProtocol):
            return False
        for reader in (protocol.stdout, protocol.stderr):
            # StreamReader._waiter: the future of a pending read (asyncio internal).
            waiter = stream_reader_waiter(reader) if reader is not None else None
            if waiter is not None and not waiter.done():
                return True
        return False


_child_exited = subprocess_exited


def _child_finished(child: asyncio.SubprocessTransport) -> bool:
    # Exited with every pipe closed; a closed transport (killed or given up) counts too.
    if subprocess_finished(child):
        return True
    return child.is_closing() and _child_exited(child)
