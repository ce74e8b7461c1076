"""CPython's internals that evclock relies on: the one module that names them.

evclock is a faithful asyncio loop and watches the threads of its process, and both need a
few things CPython offers no public name for. Each is bound or read here, with why it is
needed, what breaks if CPython changes it, and where that would show. Everything here is
verified on CPython 3.11, 3.12 and 3.13, on every supported Python in CI: by evclock's own
suite and by the conformance runs (CPython's own ``test_asyncio`` and anyio's suite on
``SimEventLoop``, ``benchmarks/conformance/run.py``).

Two kinds of private names are used, and ``tests/test_internals.py`` checks both:

* **Module-level privates** (functions, registries, code objects of asyncio, threading and
  the interpreter) are bound in this module only; the rest of evclock imports the bindings.
* **Fields and methods of asyncio's objects** (a ``Future``'s callbacks, a ``TimerHandle``'s
  slots, the event loop's ready queue, the hooks ``SimEventLoop`` overrides) are used in
  place by the kernel and the loop, on paths that run once per wake-up, where a function
  call would cost more than the work. Each is declared in :data:`ASYNCIO_PRIVATES` with the
  modules that use it; the test fails on an undeclared one.

Reading ``/proc`` (what the Linux kernel says a thread is doing) is the job of
:mod:`evclock._procfs`.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import concurrent.futures.thread
import subprocess
import sys
import threading
from asyncio import base_events, futures
from collections.abc import Callable
from types import CodeType, FrameType
from typing import Any, Final

# ------------------------------------------------------------------------------- asyncio

#: ``asyncio._get_running_loop``: the running loop or None, read in C without raising.
#: Why: a future made with no ``loop=`` on the running loop is bound to it in C, and this is
#: the cheapest way to know that the running loop is the one at hand (every sleep asks).
#: If it went away: ``asyncio.get_running_loop`` (slower, raises when none).
running_loop: Callable[[], asyncio.AbstractEventLoop | None] = asyncio._get_running_loop

#: ``asyncio.futures._set_result_unless_cancelled``: what ``asyncio.sleep(delay)`` schedules
#: with ``call_later``. Why: the kernel recognises it to wake the sleeping task in place,
#: exactly as the timer would (the asyncio.sleep hot path). If it changed: asyncio.sleep
#: would take the general timer path (slower, same behaviour); the fan-out benchmark shows it.
SET_RESULT_UNLESS_CANCELLED: Final[Callable[..., None]] = futures._set_result_unless_cancelled  # type: ignore[attr-defined]


def log_slow_callback(handle: asyncio.Handle, seconds: float) -> None:
    """Debug mode's slow-callback warning, exactly as ``BaseEventLoop._run_once`` logs it:
    on asyncio's own logger (``asyncio.base_events.logger``) with its message and
    ``asyncio.base_events._format_handle``, so that tools filtering on either, and tests
    patching the logger (CPython's ``test_log_slow_callbacks``), see it. Both are looked up
    at call time for that reason. If they went away: log on ``logging.getLogger("asyncio")``
    with ``repr(handle)``."""
    base_events.logger.warning(  # type: ignore[attr-defined]
        "Executing %s took %.3f seconds",
        base_events._format_handle(handle),  # type: ignore[attr-defined]
        seconds,
    )


#: The name prefix of the threads asyncio's ``ThreadedChildWatcher`` starts, one per child
#: process, each blocked in ``waitpid`` until its child exits (``asyncio-waitpid-N``, in
#: Lib/asyncio/unix_events.py on 3.11, 3.12 and 3.13; 3.12+ use it only where pidfds are
#: unavailable). Why: such a thread waits for a child of the loop's own subprocess transport,
#: which the loop accounts for itself (awaited children hold sim time, idle servers do not);
#: a thread of the program waiting for its own child holds sim time. If the name changed:
#: those threads would hold sim time while any asyncio child runs (safe, but a long-lived
#: child would stall sim time), which tests/outside/test_outside.py shows.
ASYNCIO_CHILD_WATCHER_THREAD_PREFIX = "asyncio-waitpid-"


#: Fields and methods of asyncio's objects that evclock uses in place, and the modules
#: that do. A field's meaning is asyncio's (Lib/asyncio/events.py, futures.py, base_events.py,
#: selector_events.py, unix_events.py); ``SimEventLoop`` subclasses ``SelectorEventLoop``
#: and ``_SimTimer`` subclasses ``TimerHandle`` and sets their slots as their constructors do.
#: If one changed, CPython's test_asyncio on SimEventLoop fails in the conformance run.
ASYNCIO_PRIVATES: Final[dict[str, tuple[str, tuple[str, ...]]]] = {
    "_callbacks": (
        "Future: the done-callbacks (a list; the C future answers None when empty). The "
        "kernel wakes a lone waiting task in place from it",
        ("kernel/_core.py",),
    ),
    "_scheduled": (
        "TimerHandle: in the loop's heap. The kernel keeps it, as BaseEventLoop does, so "
        "that cancel() reports what to purge",
        ("kernel/_core.py", "hosts/_loop.py"),
    ),
    "_cancelled": ("Handle: cancelled", ("kernel/_core.py", "hosts/_loop.py")),
    "_callback": ("Handle: the callback", ("kernel/_core.py", "hosts/_loop.py")),
    "_args": ("Handle: the callback's arguments", ("kernel/_core.py", "hosts/_loop.py")),
    "_when": (
        "TimerHandle: when, in loop time; rewritten when sim time jumps",
        ("kernel/_core.py", "hosts/_loop.py"),
    ),
    "_context": ("Handle: the contextvars context", ("hosts/_loop.py",)),
    "_repr": ("Handle: the cached repr (debug mode)", ("hosts/_loop.py",)),
    "_source_traceback": ("Handle: the creation traceback (debug mode)", ("hosts/_loop.py",)),
    "_ready": (
        "BaseEventLoop: the deque of ready handles; the loop runs them as _run_once does",
        ("hosts/_loop.py",),
    ),
    "_selector": ("BaseSelectorEventLoop: the selector polled for I/O", ("hosts/_loop.py",)),
    "_ssock": ("BaseSelectorEventLoop: the self-pipe's read end", ("hosts/_loop.py",)),
    "_thread_id": ("BaseEventLoop: the thread running the loop", ("hosts/_loop.py",)),
    "_current_handle": ("BaseEventLoop: the handle running (debug mode)", ("hosts/_loop.py",)),
    "_debug": ("BaseEventLoop: debug mode (read in C through get_debug)", ("hosts/_loop.py",)),
    "_stopping": ("BaseEventLoop: stop() was called", ("hosts/_loop.py",)),
    "_closed": ("BaseEventLoop: closed", ("hosts/_loop.py",)),
    "_signal_handlers": ("_UnixSelectorEventLoop: the installed handlers", ("hosts/_loop.py",)),
    # Methods: hooks SimEventLoop overrides, and helpers it calls as BaseEventLoop does.
    "_run_once": (
        "BaseEventLoop: one iteration; SimEventLoop's own orders timers by exact (ns, FIFO)",
        ("hosts/_loop.py",),
    ),
    "_run": ("Handle: run the callback (with the context, reporting errors)", ("hosts/_loop.py",)),
    "_process_events": ("BaseSelectorEventLoop: dispatch selected events", ("hosts/_loop.py",)),
    "_write_to_self": ("BaseSelectorEventLoop: wake the selector", ("hosts/_loop.py",)),
    "_check_closed": ("BaseEventLoop: raise if closed", ("hosts/_loop.py",)),
    "_check_thread": ("BaseEventLoop: debug-mode thread check", ("hosts/_loop.py",)),
    "_check_callback": ("BaseEventLoop: debug-mode callback check", ("hosts/_loop.py",)),
    "_timer_handle_cancelled": (
        "BaseEventLoop: TimerHandle.cancel() reports here; the kernel counts what to purge",
        ("hosts/_loop.py",),
    ),
    "_make_subprocess_transport": (
        "the one place every asyncio subprocess is created: its child is counted as outside work",
        ("hosts/_loop.py",),
    ),
}


def fd_to_key(selector: Any) -> Any:
    """The selector's own ``fd -> key`` dict (``_BaseSelectorImpl._fd_to_key``), read on
    every loop iteration to know whether real I/O is registered; its public mapping view
    where a selector has no such dict (all stdlib selectors have it)."""
    return getattr(selector, "_fd_to_key", None) or selector.get_map()


#: Returned by the readers below when an object does not have the field (not asyncio's own
#: class: uvloop's loop, a task of another implementation).
UNKNOWN: Final[Any] = object()


def task_waiter(task: asyncio.Task[Any]) -> Any:
    """``Task._fut_waiter``: the future the task waits on (None: runnable or running);
    :data:`UNKNOWN` for a task class without the field. Used to tell what a task waits on
    in error messages, and by ``SimDriver`` to know whether a task can run."""
    return getattr(task, "_fut_waiter", UNKNOWN)


def drop_caller_frame(handle: asyncio.Handle) -> None:
    """Remove the last frame of ``Handle._source_traceback`` (kept in debug mode only).

    Why: asyncio's ``call_soon_threadsafe`` drops its own frames so that a handle's source
    traceback ends at its caller; ``SimEventLoop`` overrides it (to note a wake-up from
    another thread), so its own frame would be the last one left (CPython's
    ``test_handle_source_traceback`` checks the caller's). If the field went away, nothing
    is dropped and the traceback keeps one frame more."""
    source = getattr(handle, "_source_traceback", None)
    if source:
        del source[-1]


def loop_ready_queue(loop: asyncio.AbstractEventLoop) -> Any:
    """``BaseEventLoop._ready``: the deque of ready handles of a loop evclock does not own
    (``SimDriver`` checks it between physics steps); None for a loop without one (uvloop)."""
    ready = getattr(loop, "_ready", None)
    return ready if isinstance(ready, collections.deque) else None


def loop_thread_id(loop: asyncio.AbstractEventLoop | None) -> Any:
    """``BaseEventLoop._thread_id``: the thread running the loop (None: not running);
    :data:`UNKNOWN` for a loop that does not say (uvloop)."""
    return getattr(loop, "_thread_id", UNKNOWN)


def subprocess_exited(child: asyncio.SubprocessTransport) -> bool:
    """``BaseSubprocessTransport._returncode`` is set: the exit was reported to the loop."""
    return getattr(child, "_returncode", None) is not None


def subprocess_finished(child: asyncio.SubprocessTransport) -> bool:
    """``BaseSubprocessTransport._finished``: exited and every pipe closed."""
    return bool(getattr(child, "_finished", False))


def subprocess_exit_waiters(child: asyncio.SubprocessTransport) -> Any:
    """``BaseSubprocessTransport._exit_waiters``: the futures of ``Process.wait()`` callers,
    resolved once the child exited *and* its pipes closed (so they hold while a grandchild
    keeps a pipe open)."""
    return getattr(child, "_exit_waiters", None) or ()


def event_waiters(event: asyncio.Event) -> Any:
    """``asyncio.Event._waiters``: the futures of the tasks waiting on the event (anyio's
    process protocol signals a child's exit with one)."""
    return getattr(event, "_waiters", None) or ()


def stream_reader_waiter(reader: asyncio.StreamReader) -> Any:
    """``StreamReader._waiter``: the future of a pending read, or None."""
    return getattr(reader, "_waiter", None)


# ----------------------------------------------------------------------------- threading

#: ``threading._active`` and ``threading._limbo``: the registries of live and starting
#: threads. Why: the loop asks "is any other thread alive?" before every move of sim time;
#: ``threading.active_count()`` takes a lock each time. If they went away:
#: ``threading.active_count()`` (slower, same answer).
thread_registry: dict[int, threading.Thread] = threading._active  # type: ignore[attr-defined]
thread_limbo: dict[threading.Thread, threading.Thread] = threading._limbo  # type: ignore[attr-defined]

#: Code objects of the standard library's waits, recognised in a thread's innermost frames
#: (the thread-state inference of :mod:`evclock.outside._threads`). If one changed, the
#: inference would count that wait as running (sim time held: safe, but slower), which
#: tests/outside/test_outside.py shows.
CONDITION_WAIT: Final[CodeType] = threading.Condition.wait.__code__
#: An idle ``ThreadPoolExecutor`` worker, blocked on its work queue.
POOL_WORKER: Final[CodeType] = concurrent.futures.thread._worker.__code__
#: ``Thread.join`` and the private ``Thread._wait_for_tstate_lock`` it waits in (3.11-3.12;
#: 3.13 joins in C, so only ``join`` is found there).
JOIN_CODES: Final[frozenset[CodeType]] = frozenset(
    code
    for code in (
        threading.Thread.join.__code__,
        getattr(threading.Thread, "_wait_for_tstate_lock", threading.Thread.join).__code__,
    )
)
#: ``subprocess.Popen._execute_child``: a thread starting a child process blocks there in a
#: ``read`` of its error pipe until the child has exec'd (3.11, 3.12 and 3.13). Why: that
#: read is part of starting the child, work in progress, not a wait for the world outside.
#: If it changed: a thread starting a child would not hold sim time for those milliseconds
#: (a false timeout), which tests/outside/test_outside.py shows.
POPEN_EXECUTE_CHILD: Final[CodeType] = subprocess.Popen._execute_child.__code__  # type: ignore[attr-defined]
#: ``concurrent.futures.Future.result``/``exception``: what ``run_coroutine_threadsafe`` and
#: anyio's ``from_thread`` block on.
FUTURE_WAIT_CODES: Final[frozenset[CodeType]] = frozenset(
    {concurrent.futures.Future.result.__code__, concurrent.futures.Future.exception.__code__}
)


def condition_wait_locals(frame: FrameType) -> tuple[Any, Any]:
    """The ``timeout`` and ``waiter`` locals of a ``Condition.wait`` frame (the wait's
    timeout, and the lock the waiting thread blocks on: locked while it waits)."""
    local = frame.f_locals
    return local.get("timeout"), local.get("waiter")


def pool_worker_queue(frame: FrameType) -> Any:
    """The ``work_queue`` local of an idle ``ThreadPoolExecutor`` worker's frame."""
    return frame.f_locals.get("work_queue")


# --------------------------------------------------------------------------- interpreter

#: ``sys._current_frames``: every thread's innermost frame. Why: the thread-state inference
#: reads where other threads are (and names them in StallError messages). No public
#: equivalent; ``faulthandler`` only prints.
current_frames: Callable[[], dict[int, FrameType]] = sys._current_frames


def gil_enabled() -> bool:
    """Whether this interpreter runs with the GIL (``sys._is_gil_enabled``, 3.13+; always
    True before). Reading another thread's frames is only consistent under the GIL."""
    check: Callable[[], bool] = getattr(sys, "_is_gil_enabled", lambda: True)
    return check()
