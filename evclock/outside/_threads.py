"""What is each thread outside the loop doing right now? (DESIGN section 11)

Sim time must not move while another thread is about to hand the loop something, and must
move while every other thread only waits for the loop. This module classifies a thread into
one of the :class:`ThreadState` values, from the most exact source available:

* **Linux** (``/proc/self/task/<tid>/syscall``): the kernel says whether the thread runs or
  sleeps in a system call, which one and (from its arguments) whether with a timeout. A
  futex wait without timeout is what every ``Lock.acquire()``, ``Condition.wait()``,
  ``Queue.get()``, ``SimpleQueue.get()``, ``Thread.join()`` and idle pool worker comes down
  to, whatever Python wrappers (blockbuster, debuggers) sit around it: only another thread
  of this process can end it. A thread woken by a ``notify()``, a released lock or arriving
  bytes is runnable in the kernel at once, before it gets a CPU: no race with its wake-up.
* **Elsewhere** (or when ``/proc`` cannot be read): the thread's Python frames, which
  recognise ``Condition.wait`` (with or without timeout), idle ``concurrent.futures``
  workers and ``Thread.join``; anything else counts as running.

Either way, some waits are recognised from the innermost Python frames first: a simulation
loop waiting in its selector (another ``evclock.run()`` in a thread) is a loop, not work;
``Thread.join`` and ``concurrent.futures.Future.result`` wait for another party, which is
judged on its own, so they are parked whatever their timeout.
"""

from __future__ import annotations

import concurrent.futures
import concurrent.futures.thread as _cf_thread
import enum
import os
import platform
import sys
import threading
import time
import traceback
import weakref
from asyncio import base_events
from collections.abc import Callable
from types import CodeType, FrameType
from typing import TypeVar

from evclock._errors import InvalidArgumentError


class ThreadState(enum.Enum):
    """What a thread outside the loop is doing, as far as sim time is concerned."""

    #: Executing (or runnable): it may hand the loop a result any moment. Holds sim time.
    RUNNING = "running"
    #: Sleeping with a wall-time timeout (``time.sleep``, ``Event.wait(0.05)``,
    #: ``Queue.get(timeout=...)``, ``threading.Timer``, a stock asyncio loop waiting for its
    #: next timer): it wakes by itself. Holds sim time.
    TIMED = "waiting with a timeout"
    #: Waiting without timeout for another thread of this process (a lock, a condition, a
    #: queue, a join): it neither holds sim time nor can wake the loop by itself.
    PARKED = "parked"
    #: Blocked on file descriptors or a child process (``recv``, ``accept``, ``read``,
    #: ``select``, ``waitpid``), with or without a timeout (on I/O a timeout is a safety
    #: bound): waiting for the world outside, often the loop's own sockets. It does not hold
    #: sim time, but it may wake the loop.
    WAITING_IO = "waiting for I/O"
    #: A simulation loop waiting in its selector: it follows its own time.
    EVENT_LOOP = "an event loop waiting"


#: States in which a thread keeps sim time from moving.
HOLDING_STATES = frozenset({ThreadState.RUNNING, ThreadState.TIMED})
#: States in which a thread may still wake the loop.
WAKING_STATES = frozenset(
    {ThreadState.RUNNING, ThreadState.TIMED, ThreadState.WAITING_IO, ThreadState.EVENT_LOOP}
)

# ---------------------------------------------------------------- frames (all platforms)

_CONDITION_WAIT: CodeType = threading.Condition.wait.__code__
_POOL_WORKER: CodeType = _cf_thread._worker.__code__
_JOIN_CODES: frozenset[CodeType] = frozenset(
    code
    for code in (
        threading.Thread.join.__code__,
        getattr(threading.Thread, "_wait_for_tstate_lock", threading.Thread.join).__code__,
    )
)
#: Code objects of event-loop iterations that block in a selector (evclock adds its own).
#: Code objects where a simulation loop waits in its selector (the loop module adds its
#: own): such a thread waits for its own time to come, it never holds another loop's. A
#: stock asyncio loop in a thread (anyio's blocking portal) is judged by the kernel like
#: any thread: waiting for its next timer holds, waiting for I/O only does not.
EVENT_LOOP_WAITS: set[CodeType] = set()
#: Waits for another thread or a loop, which is judged on its own: ``Thread.join`` and
#: ``concurrent.futures.Future.result`` (what ``run_coroutine_threadsafe`` and anyio's
#: ``from_thread`` block on). Their timeout is a safety bound, not work: parked either way.
_WAITS_ON_OTHERS: frozenset[CodeType] = _JOIN_CODES | {
    concurrent.futures.Future.result.__code__,
    concurrent.futures.Future.exception.__code__,
}
#: A stock asyncio loop's iteration: in a thread that waits in its selector, the timeout
#: is the loop's next timer, a real delay (anyio's blocking portal sleeping, say).
_ASYNCIO_RUN_ONCE: CodeType = base_events.BaseEventLoop._run_once.__code__  # type: ignore[attr-defined]
_ASYNCIO_LOOP = ThreadState.RUNNING  # marker returned by _waits_on_another_party
#: How many frames outward from the innermost one are searched for a known wait: wrappers
#: around lock acquisition (blockbuster, tracers) add a few.
_FRAME_DEPTH = 6


def _waits_on_another_party(frame: FrameType | None) -> ThreadState | None:
    """What the innermost frames say: EVENT_LOOP (a simulation loop waiting), PARKED (a
    wait that another party ends, whatever its timeout), RUNNING_LOOP (a stock asyncio
    loop: the kernel decides, its timeout being its next timer), or None."""
    for _ in range(_FRAME_DEPTH):
        if frame is None:
            return None
        code = frame.f_code
        if code in EVENT_LOOP_WAITS:
            return ThreadState.EVENT_LOOP
        if code in _WAITS_ON_OTHERS:
            return ThreadState.PARKED
        if code is _ASYNCIO_RUN_ONCE:
            return _ASYNCIO_LOOP
        frame = frame.f_back
    return None


def _state_from_frames(frame: FrameType) -> ThreadState:
    # Condition.wait calls nothing but lock methods: whatever frames sit inside it are
    # wrappers around acquiring (blockbuster, tracers), so it is searched a few frames out.
    inner: FrameType | None = frame
    for _ in range(_FRAME_DEPTH):
        if inner is None:
            break
        if inner.f_code is _CONDITION_WAIT:
            if inner.f_locals.get("timeout") is not None:
                return ThreadState.TIMED
            waiter = inner.f_locals.get("waiter")
            # Not yet queued, or already notified (released): about to run.
            parked = waiter is not None and waiter.locked()
            return ThreadState.PARKED if parked else ThreadState.RUNNING
        inner = inner.f_back
    code = frame.f_code
    if code is _POOL_WORKER:  # innermost: blocked on its work queue, not running a job
        work_queue = frame.f_locals.get("work_queue")
        idle = work_queue is not None and work_queue.empty()
        return ThreadState.PARKED if idle else ThreadState.RUNNING
    return ThreadState.RUNNING


# ----------------------------------------------------------- the kernel's view (Linux)

# System calls a blocked thread can sit in, by number, per architecture: (kind, timeout
# argument, file-descriptor count argument). Kinds: "ms" an int of milliseconds (negative =
# none), "ptr" a pointer (0 = none), FUTEX the futex rules, SLEEP a timed sleep, PAUSE no
# timeout at all. The fd count is -1 when the call always watches descriptors (epoll), None
# when it watches none. Any other system call (read, recv, accept, wait4, ...) is I/O.
_Rule = tuple[str, int, int | None]
FUTEX: _Rule = ("futex", 3, None)
SLEEP: _Rule = ("sleep", 0, None)
PAUSE: _Rule = ("pause", 0, None)
_X86_64: dict[int, _Rule] = {
    7: ("ms", 2, 1),  # poll
    23: ("ptr", 4, 0),  # select
    34: PAUSE,  # pause
    35: SLEEP,  # nanosleep
    128: ("ptr", 2, None),  # rt_sigtimedwait
    202: FUTEX,
    230: SLEEP,  # clock_nanosleep
    232: ("ms", 3, -1),  # epoll_wait
    270: ("ptr", 4, 0),  # pselect6
    271: ("ptr", 2, 1),  # ppoll
    281: ("ms", 3, -1),  # epoll_pwait
    441: ("ptr", 3, -1),  # epoll_pwait2
    449: ("ptr", 3, None),  # futex_waitv
}
_AARCH64: dict[int, _Rule] = {
    22: ("ms", 3, -1),  # epoll_pwait
    72: ("ptr", 4, 0),  # pselect6
    73: ("ptr", 2, 1),  # ppoll
    98: FUTEX,
    101: SLEEP,  # nanosleep
    115: SLEEP,  # clock_nanosleep
    137: ("ptr", 2, None),  # rt_sigtimedwait
    441: ("ptr", 3, -1),  # epoll_pwait2
    449: ("ptr", 3, None),  # futex_waitv
}
_SYSCALLS: dict[int, _Rule] | None = {"x86_64": _X86_64, "aarch64": _AARCH64}.get(
    platform.machine()
)
_FUTEX_CMD_MASK = 0x7F  # without FUTEX_PRIVATE_FLAG (128) and FUTEX_CLOCK_REALTIME (256)
_FUTEX_WAITS = frozenset({0, 6, 9, 11, 13})  # WAIT, LOCK_PI, WAIT_BITSET, WAIT_REQUEUE_PI, LOCK_PI2


def _state_from_syscall(text: str, event_loop: bool) -> ThreadState:
    """Classify one ``/proc/.../syscall`` line: "running", or "nr arg0 .. arg5 sp pc".

    A wait on file descriptors (select, poll, epoll, a socket with a timeout) is waiting for
    I/O whatever its timeout - a safety bound or a periodic check, not work - except in a
    thread running an asyncio loop (``event_loop``), whose timeout is its next timer.
    """
    fields = text.split()
    if not fields or fields[0] == "running" or fields[0] == "-1":
        return ThreadState.RUNNING  # "-1": blocked outside a system call (a page fault)
    assert _SYSCALLS is not None
    args = [int(value, 16) for value in fields[1:7]]
    rule = _SYSCALLS.get(int(fields[0]))
    if rule is None:
        return ThreadState.WAITING_IO  # read, recv, accept, wait4, ...: no timeout of its own
    if rule is PAUSE:
        return ThreadState.PARKED  # pause(): only a signal ends it
    if rule is SLEEP:
        return ThreadState.TIMED
    kind, timeout_arg, fds_arg = rule
    if rule is FUTEX:
        command = args[1] & _FUTEX_CMD_MASK
        if command not in _FUTEX_WAITS:
            return ThreadState.RUNNING  # a wake or requeue: over in an instant
        return ThreadState.TIMED if args[timeout_arg] else ThreadState.PARKED
    watches_fds = fds_arg is not None and (fds_arg < 0 or args[fds_arg] != 0)
    if watches_fds and not event_loop:
        return ThreadState.WAITING_IO
    value = args[timeout_arg]
    # "ms": a negative int means no timeout; "ptr": a null pointer does.
    timed = value & 0x80000000 == 0 if kind == "ms" else value != 0
    return ThreadState.TIMED if timed else ThreadState.WAITING_IO


class _KernelView:
    """Reads each thread's scheduler state and current system call from ``/proc``; three
    open files per thread, re-read with ``pread``.

    ``schedstat`` counts the times a thread got a CPU: a thread whose count has not moved
    since its system call was read, and that is not runnable now, is still in that system
    call, so what was concluded from it still holds (:meth:`unchanged`). That is exact, and
    it keeps a survey cheap when other threads just wait (one idle timer thread used to cost
    every step of the loop two file reads, a frame walk and a frame's locals).
    """

    def __init__(self) -> None:
        self._files: dict[int, tuple[int, int, int]] = {}
        self._runs: dict[int, bytes] = {}

    def _open(self, native_id: int) -> tuple[int, int, int]:
        files = self._files.get(native_id)
        if files is None:
            task = f"/proc/self/task/{native_id}"
            files = (
                os.open(f"{task}/syscall", os.O_RDONLY),
                os.open(f"{task}/stat", os.O_RDONLY),
                os.open(f"{task}/schedstat", os.O_RDONLY),
            )
            self._files[native_id] = files
        return files

    def read(self, native_id: int, *, remember: bool = False) -> str | None:
        """The thread's ``syscall`` line, or "running" when the scheduler has it runnable:
        a thread woken (a futex released, bytes arrived) but not yet on a CPU still shows
        the system call it is leaving. ``remember``: the reading a survey keeps, which
        :meth:`unchanged` compares with."""
        try:
            files = self._open(native_id)
            runs = os.pread(files[2], 128, 0)  # before the system call: see unchanged()
            syscall = os.pread(files[0], 256, 0).decode("ascii", "replace")
            stat = os.pread(files[1], 1024, 0).decode("ascii", "replace")
        except OSError:
            if remember:
                self._runs.pop(native_id, None)
            return None
        state = stat.rpartition(")")[2].split()[:1]
        if state == ["R"]:
            if remember:
                self._runs.pop(native_id, None)
            return "running"
        if remember:
            self._runs[native_id] = runs
        return syscall

    def unchanged(self, native_id: int) -> bool:
        """Whether the thread has not run since its system call was last read (and is not
        runnable now): then it is still blocked exactly as that reading said."""
        runs = self._runs.get(native_id)
        if runs is None:
            return False
        try:
            files = self._files[native_id]
            stat = os.pread(files[1], 1024, 0).decode("ascii", "replace")
            now = os.pread(files[2], 128, 0)
        except OSError:
            return False
        return now == runs and stat.rpartition(")")[2].split()[:1] != ["R"]

    def forget_except(self, alive: set[int]) -> None:
        for native_id in [n for n in self._files if n not in alive]:
            self._runs.pop(native_id, None)
            for fd in self._files.pop(native_id, ()):
                os.close(fd)


def _kernel_view_works() -> bool:
    if _SYSCALLS is None or not sys.platform.startswith("linux"):
        return False
    probe = _KernelView()
    text = probe.read(threading.get_native_id())  # this thread: running
    probe.forget_except(set())
    return text == "running"


_kernel: _KernelView | None = _KernelView() if _kernel_view_works() else None


def check_thread_inference() -> None:
    """Refuse to guess from frames on an interpreter running without the GIL.

    Frame inspection reads other threads' frames, which is only consistent under the GIL;
    the kernel view does not need it.
    """
    gil_enabled = getattr(sys, "_is_gil_enabled", lambda: True)()
    if _kernel is None and not gil_enabled:
        raise InvalidArgumentError(
            "watch_threads=True needs to see what other threads do: on this platform that "
            "means reading their Python frames, which needs the GIL, and this interpreter "
            "runs without it; run with PYTHON_GIL=1, or pass watch_threads=False (then only "
            "executor jobs, subprocesses and loop.hold_time() hold sim time)"
        )


def thread_state(thread: threading.Thread, frame: FrameType | None) -> ThreadState:
    """The state of ``thread``, whose innermost Python frame is ``frame`` (None: none yet)."""
    from_frames = _waits_on_another_party(frame)
    if from_frames is ThreadState.EVENT_LOOP:
        return from_frames
    native_id = thread.native_id
    text = (
        _kernel.read(native_id, remember=True)
        if _kernel is not None and native_id is not None
        else None
    )
    if from_frames is ThreadState.PARKED:
        # Waiting on another party - unless already woken (then it is about to deliver).
        if text is not None:
            return ThreadState.RUNNING if text == "running" else ThreadState.PARKED
        assert frame is not None
        woken = _state_from_frames(frame) is ThreadState.RUNNING
        return ThreadState.RUNNING if woken else ThreadState.PARKED
    if text is not None:
        return _state_from_syscall(text, event_loop=from_frames is _ASYNCIO_LOOP)
    if frame is None:
        return ThreadState.RUNNING  # starting or finishing
    return _state_from_frames(frame)


#: evclock's own helper threads (the pytest plugin's watchdog): they never call the loop back.
_internal: weakref.WeakSet[threading.Thread] = weakref.WeakSet()


def mark_internal(thread: threading.Thread) -> None:
    """Declare ``thread`` one of evclock's helpers: it can neither hold nor resume sim time."""
    _internal.add(thread)


def internal_count() -> int:
    """How many of evclock's helper threads are alive (they do not count as outside work)."""
    return sum(1 for thread in list(_internal) if thread.is_alive())


def other_threads(loop_thread_id: int | None) -> list[threading.Thread]:
    """Live threads other than the loop's and evclock's helpers, in start order."""
    return [
        t
        for t in threading.enumerate()
        if t.ident is not None and t.ident != loop_thread_id and t not in _internal
    ]


#: Per thread (ident): the thread and its state at the last survey that read it.
_surveyed: dict[int, tuple[threading.Thread, ThreadState]] = {}
#: Threads found unchanged (not run since their last reading) by the latest survey.
_unchanged: set[int] = set()
#: Per thread: the end of the timed wait found since its last reading (wait_deadline).
_deadline_read: dict[int, float] = {}


def survey(loop_thread_id: int | None) -> list[tuple[threading.Thread, ThreadState]]:
    """Every other thread with its current state.

    A thread that has not run since it was last read keeps its state (the kernel says so
    exactly: :meth:`_KernelView.unchanged`); only the others are read again.
    """
    threads = other_threads(loop_thread_id)
    # Two simulation loops in two threads survey at once: one at a time, as the tables
    # below (and the kernel view's open files) are shared.
    with _survey_lock:
        return _survey(threads)


_survey_lock = threading.Lock()


def _survey(threads: list[threading.Thread]) -> list[tuple[threading.Thread, ThreadState]]:
    _unchanged.clear()
    if not threads:
        return []
    result = []
    frames: dict[int, FrameType] | None = None
    for thread in threads:
        ident = thread.ident or 0
        known = _surveyed.get(ident)
        if (
            known is not None
            and known[0] is thread
            and _kernel is not None
            and thread.native_id is not None
            and _kernel.unchanged(thread.native_id)
        ):
            _unchanged.add(ident)
            result.append(known)
            continue
        if frames is None:
            frames = sys._current_frames()
        _deadline_read.pop(ident, None)
        known = _surveyed[ident] = (thread, thread_state(thread, frames.get(ident)))
        result.append(known)
    if len(_surveyed) > len(threads):  # some thread ended: forget it
        alive = {t.ident for t in threads}
        for table in (_surveyed, _deadline_read, _timed_waits, _kernel_waits):
            for ident in [i for i in table if i not in alive]:
                del table[ident]
        if _kernel is not None:
            _kernel.forget_except({t.native_id for t in threads if t.native_id is not None})
    return result


#: Per thread: the Condition.wait it is in (its waiter lock) and when that wait times out.
_timed_waits: dict[int, tuple[object, float]] = {}


def wait_deadline(thread: threading.Thread) -> float | None:
    """When ``thread``'s current timed wait ends by itself (``time.monotonic()`` seconds),
    if it is a ``Condition.wait(timeout)`` (``Event.wait``, ``Queue.get``, ``Timer``), or,
    on Linux, a timed system call whose deadline the kernel shows (``time.sleep``, a
    ``Lock.acquire(timeout=...)``, a C library's timed futex wait or sleep); None when
    unknown.

    The wait is timed from the first time it is seen, which is at or after its start: the
    deadline may be late, never early (time is held a little longer, never too little).
    """
    ident = thread.ident or 0
    with _survey_lock:
        if ident in _unchanged and ident in _deadline_read:
            return _deadline_read[ident]  # not run since: still in the same wait
    deadline = _wait_deadline(thread, ident)
    if deadline is not None:
        with _survey_lock:
            _deadline_read[ident] = deadline
    return deadline


def _wait_deadline(thread: threading.Thread, ident: int) -> float | None:
    frame: FrameType | None = sys._current_frames().get(ident)
    for _ in range(_FRAME_DEPTH):
        if frame is None:
            break
        if frame.f_code is _CONDITION_WAIT:
            timeout = frame.f_locals.get("timeout")
            waiter = frame.f_locals.get("waiter")
            if not isinstance(timeout, int | float) or waiter is None:
                return None
            seen = _timed_waits.get(ident)
            if seen is None or seen[0] is not waiter:
                seen = _timed_waits[ident] = (waiter, time.monotonic() + max(timeout, 0))
            return seen[1]
        frame = frame.f_back
    _timed_waits.pop(ident, None)
    return _kernel_wait_deadline(thread)


# ------------------------------------------- the length of a timed wait, from the kernel

#: Per architecture: system call number -> (clock id argument or None for nanosleep's
#: CLOCK_MONOTONIC-relative request, flags argument or None, timespec pointer argument).
_SLEEPS: dict[int, tuple[int | None, int | None, int]] = (
    {35: (None, None, 0), 230: (0, 1, 2)}  # nanosleep, clock_nanosleep
    if _SYSCALLS is _X86_64
    else {101: (None, None, 0), 115: (0, 1, 2)}
)
_FUTEX_NR = next((nr for nr, rule in (_SYSCALLS or {}).items() if rule is FUTEX), None)
_TIMER_ABSTIME = 1
_FUTEX_WAIT, _FUTEX_WAIT_BITSET, _FUTEX_CLOCK_REALTIME = 0, 9, 256
_mem_fd: int | None = None
_K = TypeVar("_K")
#: Per thread: its timed system call (the syscall line and its timespec) and that call's
#: deadline on the monotonic clock, computed when first seen.
_kernel_waits: dict[int, tuple[str, float]] = {}


def _read_timespec(mem_fd: int, address: int) -> float | None:
    """The ``struct timespec`` at ``address`` in the process whose ``mem`` file is
    ``mem_fd`` (``/proc/<pid>/mem`` answers EIO rather than crash when the memory is gone)."""
    try:
        raw = os.pread(mem_fd, 16, address)
    except (OSError, OverflowError):
        return None
    if len(raw) != 16:
        return None
    seconds = int.from_bytes(raw[:8], sys.byteorder, signed=True)
    nanos = int.from_bytes(raw[8:], sys.byteorder, signed=True)
    if seconds < 0 or not 0 <= nanos < 1_000_000_000:
        return None  # not a timespec (the thread left the call meanwhile)
    return seconds + nanos / 1e9


def _timed_call(text: str) -> tuple[int, bool, int] | None:
    """For a ``syscall`` line of a timed sleep or futex wait: (address of its timespec,
    whether that is an absolute deadline, the clock id); None for anything else."""
    fields = text.split()
    if len(fields) < 7 or fields[0] in ("running", "-1"):
        return None
    number = int(fields[0])
    args = [int(value, 16) for value in fields[1:7]]
    clock = time.CLOCK_MONOTONIC
    if number in _SLEEPS:
        clock_arg, flags_arg, pointer_arg = _SLEEPS[number]
        if clock_arg is not None:
            clock = args[clock_arg]
        absolute = flags_arg is not None and bool(args[flags_arg] & _TIMER_ABSTIME)
        return args[pointer_arg], absolute, clock
    if number == _FUTEX_NR:
        command = args[1] & _FUTEX_CMD_MASK
        if command not in (_FUTEX_WAIT, _FUTEX_WAIT_BITSET) or not args[3]:
            return None
        absolute = command == _FUTEX_WAIT_BITSET  # WAIT's timeout is a length
        if absolute and args[1] & _FUTEX_CLOCK_REALTIME:
            clock = time.CLOCK_REALTIME
        return args[3], absolute, clock
    return None


def _timed_deadline(
    waits: dict[_K, tuple[str, float]],
    key: _K,
    text: str,
    mem_fd: int,
    reread: Callable[[], str | None],
) -> float | None:
    """The monotonic deadline of the timed call ``text`` (see :func:`_timed_call`), read
    from its timespec and confirmed by reading the call again (unchanged: the deadline
    belongs to it); ``waits[key]`` keeps it per call, so that it stays one value."""
    call = _timed_call(text)
    if call is None:
        return None
    pointer, absolute, clock = call
    value = _read_timespec(mem_fd, pointer)
    if value is None or reread() != text:
        return None
    try:
        now = time.clock_gettime(clock)
    except OSError:
        return None
    mono = time.monotonic()
    identity = f"{text} {value!r}"
    seen = waits.get(key)
    if absolute:
        if seen is None or seen[0] != identity:  # converted to the monotonic clock once
            seen = (identity, mono + (value - now))
            waits[key] = seen
        return seen[1]
    # A length: timed from when the call is first seen (at or after its start), and again
    # from now once that end has passed (the same call site sleeping anew).
    if seen is None or seen[0] != identity or seen[1] < mono:
        seen = (identity, mono + value)
        waits[key] = seen
    return seen[1]


def _own_mem() -> int | None:
    global _mem_fd
    if _mem_fd is None:
        try:
            _mem_fd = os.open("/proc/self/mem", os.O_RDONLY)
        except OSError:
            return None
    return _mem_fd


def _kernel_wait_deadline(thread: threading.Thread) -> float | None:
    """When ``thread``'s timed system call ends by itself, in ``time.monotonic()`` seconds:
    ``time.sleep`` (``clock_nanosleep`` with an absolute deadline), ``nanosleep``, and
    futex waits with a timeout (``Lock.acquire(timeout=...)``, a C library's timed wait).
    None when unknown."""
    native_id = thread.native_id
    kernel = _kernel
    if kernel is None or native_id is None:
        return None
    text = kernel.read(native_id)
    mem_fd = _own_mem()
    if text is None or mem_fd is None:
        return None
    return _timed_deadline(
        _kernel_waits, thread.ident or 0, text, mem_fd, lambda: kernel.read(native_id)
    )


#: Per (child pid, thread id): its timed call and deadline, as ``_kernel_waits``.
_child_waits: dict[tuple[int, int], tuple[str, float]] = {}


def child_wait_deadline(pid: int) -> tuple[str, float] | None:
    """A child process that is asleep, every thread of it blocked, at least one in a timed
    wait whose end the kernel shows (``time.sleep`` in the child): (an identity of that
    wait, its monotonic deadline) for the earliest. None when any thread runs, or a timed
    wait's length cannot be read, or nothing is timed (Linux only; reading another
    process's memory needs ptrace rights over it, which a parent has by default)."""
    if _kernel is None:
        return None
    base = f"/proc/{pid}"
    try:
        tids = sorted(int(name) for name in os.listdir(f"{base}/task"))
        mem_fd = os.open(f"{base}/mem", os.O_RDONLY)
    except (OSError, ValueError):
        return None
    try:
        earliest: tuple[str, float] | None = None
        for tid in tids:

            def read(tid: int = tid) -> str | None:
                try:
                    with open(f"{base}/task/{tid}/stat", "rb") as stat:
                        state = stat.read().rpartition(b")")[2].split()[:1]
                    if state == [b"R"]:
                        return "running"
                    with open(f"{base}/task/{tid}/syscall", "rb") as syscall:
                        return syscall.read().decode("ascii", "replace")
                except OSError:
                    return None

            text = read()
            if text is None:
                return None
            state = _state_from_syscall(text, event_loop=False)
            if state is ThreadState.RUNNING:
                return None
            if state is not ThreadState.TIMED:
                continue  # parked, or blocked on I/O: not what ends the wait
            deadline = _timed_deadline(_child_waits, (pid, tid), text, mem_fd, read)
            if deadline is None:
                return None
            if earliest is None or deadline < earliest[1]:
                earliest = (f"{pid}:{tid}:{_child_waits[(pid, tid)][0]}", deadline)
        return earliest
    finally:
        os.close(mem_fd)


def forget_child(pid: int) -> None:
    """A child is gone: drop what was kept about its waits."""
    for key in [k for k in _child_waits if k[0] == pid]:
        del _child_waits[key]


# ------------------------------------------ which descriptors a thread waits on (Linux)

#: System calls that wait on descriptors: "poll" (a pollfd array and its length in the first
#: two arguments) or "fd" (the descriptor is the first argument).
_FD_WAITS: dict[int, str] = (
    {7: "poll", 271: "poll", 0: "fd", 19: "fd", 45: "fd", 47: "fd"}
    if _SYSCALLS is _X86_64
    else {73: "poll", 63: "fd", 65: "fd", 207: "fd", 212: "fd"}
)
_MAX_POLL_FDS = 64


def waited_fds(thread: threading.Thread) -> list[int]:
    """The descriptors ``thread`` is blocked on, if it waits in ``poll``/``ppoll`` (how a
    socket with a timeout waits) or in a ``read``/``recv`` on one descriptor: from its
    system call's arguments (and the pollfd array they point to). Empty when unknown."""
    native_id = thread.native_id
    kernel = _kernel
    if kernel is None or native_id is None:
        return []
    text = kernel.read(native_id)
    fields = text.split() if text is not None else []
    if len(fields) < 7 or fields[0] in ("running", "-1"):
        return []
    kind = _FD_WAITS.get(int(fields[0]))
    args = [int(value, 16) for value in fields[1:3]]
    if kind == "fd":
        return [args[0]] if args[0] < 2**31 else []
    mem_fd = _own_mem()
    if kind != "poll" or mem_fd is None or not 0 < args[1] <= _MAX_POLL_FDS:
        return []
    try:
        raw = os.pread(mem_fd, 8 * args[1], args[0])  # struct pollfd {int fd; short; short}
    except (OSError, OverflowError):
        return []
    if kernel.read(native_id) != text or len(raw) != 8 * args[1]:
        return []
    fds = [
        int.from_bytes(raw[i : i + 4], sys.byteorder, signed=True) for i in range(0, len(raw), 8)
    ]
    return [fd for fd in fds if fd >= 0]


def describe_thread(thread: threading.Thread, state: ThreadState) -> str:
    """A thread's name, state and innermost frames, for error messages."""
    frame = sys._current_frames().get(thread.ident or 0)
    kind = "daemon thread" if thread.daemon else "thread"
    head = f"{kind} {thread.name!r} ({state.value})"
    if frame is None:
        return head
    lines = "".join(traceback.format_stack(frame, limit=4)).splitlines()
    return head + ":\n" + "\n".join("    " + line for line in lines)


def could_call_back(loop_thread_id: int | None) -> bool:
    """Whether any other live thread (daemon or not, evclock's helpers aside) might still call
    the loop back, e.g. resume it while it is paused."""
    return any(t.is_alive() for t in other_threads(loop_thread_id))
