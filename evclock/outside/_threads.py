"""What is each thread outside the loop doing right now?

The rule is stated in docs/architecture.md, "Work outside the loop".

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

import threading
import time
import traceback
import weakref
from types import CodeType, FrameType

from evclock._cpython import (
    ASYNCIO_CHILD_WATCHER_THREAD_PREFIX,
    CONDITION_WAIT,
    FUTURE_WAIT_CODES,
    JOIN_CODES,
    POOL_WORKER,
    POPEN_EXECUTE_CHILD,
    condition_wait_locals,
    current_frames,
    gil_enabled,
    pool_worker_queue,
    thread_limbo,
    thread_registry,
)
from evclock._errors import InvalidArgumentError
from evclock._procfs import (
    ThreadState,
    forget_threads,
    kernel_view,
    state_from_syscall,
    thread_wait_deadline,
)

#: States in which a thread keeps sim time from moving.
HOLDING_STATES = frozenset({ThreadState.RUNNING, ThreadState.TIMED, ThreadState.WAITING_CHILD})
#: States in which a thread may still wake the loop.
WAKING_STATES = frozenset(
    {
        ThreadState.RUNNING,
        ThreadState.TIMED,
        ThreadState.WAITING_IO,
        ThreadState.WAITING_CHILD,
        ThreadState.EVENT_LOOP,
    }
)

# ---------------------------------------------------------------- frames (all platforms)

#: Code objects of event-loop iterations that block in a selector (evclock adds its own).
#: Code objects where a simulation loop waits in its selector (the loop module adds its
#: own): such a thread waits for its own time to come, it never holds another loop's. A
#: stock asyncio loop in a thread (anyio's blocking portal) is judged by the kernel like
#: any thread: waiting for its next timer holds, waiting for I/O only does not.
EVENT_LOOP_WAITS: set[CodeType] = set()
#: Waits for another thread or a loop, which is judged on its own: ``Thread.join`` and
#: ``concurrent.futures.Future.result`` (what ``run_coroutine_threadsafe`` and anyio's
#: ``from_thread`` block on). Their timeout is a safety bound, not work: parked either way.
_WAITS_ON_OTHERS: frozenset[CodeType] = JOIN_CODES | FUTURE_WAIT_CODES
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
        frame = frame.f_back
    return None


def _state_from_frames(frame: FrameType) -> ThreadState:
    # Condition.wait calls nothing but lock methods: whatever frames sit inside it are
    # wrappers around acquiring (blockbuster, tracers), so it is searched a few frames out.
    inner: FrameType | None = frame
    for _ in range(_FRAME_DEPTH):
        if inner is None:
            break
        if inner.f_code is CONDITION_WAIT:
            timeout, waiter = condition_wait_locals(inner)
            if timeout is not None:
                return ThreadState.TIMED
            # Not yet queued, or already notified (released): about to run.
            parked = waiter is not None and waiter.locked()
            return ThreadState.PARKED if parked else ThreadState.RUNNING
        inner = inner.f_back
    code = frame.f_code
    if code is POOL_WORKER:  # innermost: blocked on its work queue, not running a job
        work_queue = pool_worker_queue(frame)
        idle = work_queue is not None and work_queue.empty()
        return ThreadState.PARKED if idle else ThreadState.RUNNING
    return ThreadState.RUNNING


def check_thread_inference() -> None:
    """Refuse to guess from frames on an interpreter running without the GIL.

    Frame inspection reads other threads' frames, which is only consistent under the GIL;
    the kernel view does not need it.
    """
    if kernel_view is None and not gil_enabled():
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
    if frame is not None and frame.f_code is POPEN_EXECUTE_CHILD:
        return ThreadState.WAITING_CHILD  # starting a child: blocked until it has exec'd
    native_id = thread.native_id
    text = (
        kernel_view.read(native_id, remember=True)
        if kernel_view is not None and native_id is not None
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
        state = state_from_syscall(text)
        if state is ThreadState.WAITING_CHILD and thread.name.startswith(
            ASYNCIO_CHILD_WATCHER_THREAD_PREFIX
        ):
            # asyncio's own watcher of a child of the loop's subprocess transport: the loop
            # accounts for that child itself (an awaited child holds, an idle server not).
            return ThreadState.WAITING_IO
        return state
    if frame is None:
        return ThreadState.RUNNING  # starting or finishing
    return _state_from_frames(frame)


#: evclock's own helper threads (the pytest plugin's watchdog, the clock server's): they
#: never call the loop back. Weak references in a plain list: read on every advance of a
#: loop beside one (a WeakSet's iteration costs a dozen Python calls), pruned as they die.
_internal: list[weakref.ref[threading.Thread]] = []


def mark_internal(thread: threading.Thread) -> None:
    """Declare ``thread`` one of evclock's helpers: it can neither hold nor resume sim time."""
    _internal[:] = [ref for ref in _internal if ref() is not None]
    _internal.append(weakref.ref(thread))


def _is_internal(thread: threading.Thread) -> bool:
    return any(ref() is thread for ref in _internal)


def internal_count() -> int:
    """How many of evclock's helper threads are running (in the interpreter's registry of
    running threads, as :func:`only_internal_threads` counts them)."""
    registry = thread_registry
    count = 0
    for ref in _internal:
        thread = ref()
        if thread is not None and registry.get(thread.ident) is thread:  # type: ignore[arg-type]
            count += 1
    return count


def only_internal_threads() -> bool:
    """No thread runs (or is starting) but the calling one and evclock's own helpers."""
    others = len(thread_registry) + len(thread_limbo) - 1
    return others <= 0 or others <= internal_count()


def other_threads(loop_thread_id: int | None) -> list[threading.Thread]:
    """Live threads other than the loop's and evclock's helpers, in start order."""
    return [
        t
        for t in threading.enumerate()
        if t.ident is not None and t.ident != loop_thread_id and not _is_internal(t)
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
    exactly: :meth:`evclock._procfs.KernelView.unchanged`); only the others are read again.
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
            and kernel_view is not None
            and thread.native_id is not None
            and kernel_view.unchanged(thread.native_id)
        ):
            _unchanged.add(ident)
            result.append(known)
            continue
        if frames is None:
            frames = current_frames()
        _deadline_read.pop(ident, None)
        known = _surveyed[ident] = (thread, thread_state(thread, frames.get(ident)))
        result.append(known)
    if len(_surveyed) > len(threads):  # some thread ended: forget it
        alive = {t.ident for t in threads}
        for table in (_surveyed, _deadline_read, _timed_waits):
            for ident in [i for i in table if i not in alive]:
                del table[ident]
        forget_threads({i for i in alive if i is not None})
        if kernel_view is not None:
            kernel_view.forget_except({t.native_id for t in threads if t.native_id is not None})
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
    frame: FrameType | None = current_frames().get(ident)
    for _ in range(_FRAME_DEPTH):
        if frame is None:
            break
        if frame.f_code is CONDITION_WAIT:
            timeout, waiter = condition_wait_locals(frame)
            if not isinstance(timeout, int | float) or waiter is None:
                return None
            seen = _timed_waits.get(ident)
            if seen is None or seen[0] is not waiter:
                seen = _timed_waits[ident] = (waiter, time.monotonic() + max(timeout, 0))
            return seen[1]
        frame = frame.f_back
    _timed_waits.pop(ident, None)
    return thread_wait_deadline(thread)


def describe_thread(thread: threading.Thread, state: ThreadState) -> str:
    """A thread's name, state and innermost frames, for error messages."""
    frame = current_frames().get(thread.ident or 0)
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
