"""Is any thread outside the loop still working on something that may call the loop back?

Sim time must not move while another thread is busy: a 50 ms job in a thread must finish
before a 5 s sim-time timeout can expire. Executor jobs and explicit holds are counted
exactly by the loop; this module covers the rest (plain ``threading.Thread`` producers,
anyio worker threads) by looking at what each thread is doing right now:

* a thread *parked* on a ``threading.Condition`` (``Event.wait``, ``Queue.get``,
  ``Semaphore.acquire`` ...) that nobody has notified can only be woken by another thread,
  so it is idle; once notified (its waiter lock released) it counts as busy again;
* an idle ``concurrent.futures`` worker (blocked on an empty work queue) is idle;
* a thread blocked in ``Thread.join`` waits for another thread, which is judged on its own;
* daemon threads are ignored here (background services by convention): they never hold
  sim time, though they may still call the loop back (resume a paused loop);
* anything else - computing, sleeping, blocked on a socket - is busy.

Inspection happens under the GIL on a snapshot of every thread's innermost frame, and the
caller checks its ready queue *after* this returns: a thread that handed a result to the
loop before parking has already appended it there, so no hand-off is missed.
"""

from __future__ import annotations

import concurrent.futures.thread as _cf_thread
import sys
import threading
import weakref
from types import CodeType, FrameType

_CONDITION_WAIT: CodeType = threading.Condition.wait.__code__
_POOL_WORKER: CodeType = _cf_thread._worker.__code__
_JOIN_CODES: frozenset[CodeType] = frozenset(
    code
    for code in (
        threading.Thread.join.__code__,
        getattr(threading.Thread, "_wait_for_tstate_lock", threading.Thread.join).__code__,
    )
)


def _is_parked(frame: FrameType) -> bool:
    code = frame.f_code
    if code is _CONDITION_WAIT:
        waiter = frame.f_locals.get("waiter")
        # Not yet allocated/queued, or already notified (released): about to run.
        return waiter is not None and waiter.locked()
    if code is _POOL_WORKER:
        work_queue = frame.f_locals.get("work_queue")
        return work_queue is not None and work_queue.empty()
    return code in _JOIN_CODES


def busy_threads(loop_thread_id: int | None) -> list[threading.Thread]:
    """Non-daemon threads other than the loop's that are doing something right now."""
    if threading.active_count() <= 1:
        return []
    frames = sys._current_frames()
    busy = []
    for thread in threading.enumerate():
        ident = thread.ident
        if ident is None or ident == loop_thread_id or thread.daemon:
            continue
        frame = frames.get(ident)
        if frame is None or not _is_parked(frame):
            busy.append(thread)
    return busy


#: evclock's own helper threads (the pytest plugin's watchdog): they never call the loop back.
_internal: weakref.WeakSet[threading.Thread] = weakref.WeakSet()


def mark_internal(thread: threading.Thread) -> None:
    """Declare ``thread`` one of evclock's helpers: it can neither hold nor resume sim time."""
    _internal.add(thread)


def could_call_back(loop_thread_id: int | None) -> bool:
    """Whether any other live thread (daemon or not, evclock's helpers aside) might still call
    the loop back, e.g. resume it while it is paused."""
    return any(
        t.ident != loop_thread_id and t not in _internal and t.is_alive()
        for t in threading.enumerate()
    )
