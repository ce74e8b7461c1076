"""Precise wall-time waits for :class:`evclock.WallClock`.

The stock asyncio loop cannot wake a task at a precise wall time: the epoll selector takes
its timeout in whole milliseconds, rounded up, so ``asyncio.sleep(0.0004)`` sleeps about
1 ms, and the kernel adds its timer slack (50 us by default) on top. uvloop's timers are in
milliseconds too. A 1 kHz control loop built on those waits is late by half a period on
average.

A precise wait here has three phases:

1. **coarse**: a long wait first sleeps on the loop's own timer until a few milliseconds
   before the deadline (cheap, cancellable, keeps the precise timer's queue short);
2. **timer**: on Linux, a ``timerfd`` armed at the absolute deadline (minus ``spin_margin``)
   is watched with ``loop.add_reader``, so the loop's ``epoll_wait`` is woken by the kernel
   exactly then: timerfd expirations are high-resolution timers with no slack, and no
   millisecond rounding is involved. One timerfd per loop and clock serves every sleeper
   (a heap of deadlines; the fd is armed at the earliest). Where there is no timerfd
   (other systems, Python loops without ``add_reader`` such as the Windows proactor) this
   phase uses the loop's timer, with its granularity;
3. **spin** (optional): the last ``spin_margin`` nanoseconds are waited by yielding to the
   loop (``await asyncio.sleep(0)``) until the clock reads the deadline. Each yield runs
   every other ready callback and polls I/O, so other tasks are never starved; the cost is
   CPU time, about ``spin_margin`` per wait.

A precise wait never returns before the clock reads the deadline (it re-checks the clock
after every wake-up), and always yields to the loop at least once.

Timer slack: :func:`set_timer_slack` wraps Linux ``prctl(PR_SET_TIMERSLACK)`` (per
thread). timerfd expirations ignore it; :class:`TimerSlack` lowers it, opt-in
(``WallClock(timer_slack=...)``), only while precise waits are pending on the loop's
thread, for the fallback path (where the loop's millisecond rounding dominates anyway).
"""

from __future__ import annotations

import asyncio
import ctypes
import heapq
import itertools
import os
import sys
import threading
import weakref
from collections.abc import Callable
from typing import Final

from evclock._errors import InvalidArgumentError

#: Waits longer than this go through the loop's own timer first, up to this close.
COARSE_NS: Final = 5_000_000
#: Default spin margin of :class:`evclock.WallClock` (see its docstring for the figures).
DEFAULT_SPIN_MARGIN_NS: Final = 100_000  # WallClock(spin_margin=100e-6), its default

CLOCK_REALTIME: Final = 0
CLOCK_MONOTONIC: Final = 1
_TFD_TIMER_ABSTIME: Final = 1
_PR_SET_TIMERSLACK: Final = 29
_PR_GET_TIMERSLACK: Final = 30
# prctl is variadic and the kernel reads unsigned longs: pass full-width zeros.
_ZERO: Final = ctypes.c_ulong(0)

ClockRead = Callable[[], int]


# --------------------------------------------------------------------------------------
# timerfd through ctypes (``os.timerfd_create`` only exists from Python 3.13)


class _Timespec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class _Itimerspec(ctypes.Structure):
    _fields_ = (("it_interval", _Timespec), ("it_value", _Timespec))


def _load_libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.timerfd_create.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.timerfd_create.restype = ctypes.c_int
        libc.timerfd_settime.argtypes = (
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_Itimerspec),
            ctypes.POINTER(_Itimerspec),
        )
        libc.timerfd_settime.restype = ctypes.c_int
        libc.prctl.restype = ctypes.c_int
    except (OSError, AttributeError):
        return None
    return libc


_libc: ctypes.CDLL | None = _load_libc()


def _timerfd_create(clockid: int) -> int:
    """A non-blocking, close-on-exec timerfd on ``clockid``; OSError when unavailable."""
    if _libc is None:
        raise OSError("timerfd is not available on this platform")
    # TFD_NONBLOCK and TFD_CLOEXEC are defined as O_NONBLOCK and O_CLOEXEC.
    fd = int(_libc.timerfd_create(clockid, os.O_NONBLOCK | os.O_CLOEXEC))
    if fd < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"timerfd_create: {os.strerror(err)}")
    return fd


def _timerfd_arm(fd: int, spec: _Itimerspec, when_ns: int) -> None:
    """Arm ``fd`` to expire once at the absolute clock time ``when_ns`` (``spec`` is scratch)."""
    assert _libc is not None
    when_ns = max(when_ns, 1)  # an all-zero it_value would disarm the timer
    spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(when_ns, 1_000_000_000)
    if _libc.timerfd_settime(fd, _TFD_TIMER_ABSTIME, spec, None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"timerfd_settime: {os.strerror(err)}")


class _PreciseTimer:
    """One timerfd watched by one loop, serving every precise sleeper on one clock.

    The fd stays registered with the loop for the loop's life (an unarmed timerfd never
    becomes readable; registering once saves two ``epoll_ctl`` calls per wait) and is
    closed when the loop is garbage-collected. The timer holds no reference to the loop,
    so it does not keep it alive.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, clockid: int, read: ClockRead) -> None:
        self._read = read
        self._fd = _timerfd_create(clockid)
        self._spec = _Itimerspec()
        self._heap: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._armed: int | None = None
        try:
            loop.add_reader(self._fd, self._on_expired)
        except BaseException:
            os.close(self._fd)
            raise
        self._finalizer = weakref.finalize(loop, os.close, self._fd)

    def wait(self, loop: asyncio.AbstractEventLoop, when_ns: int) -> asyncio.Future[None]:
        """A future resolved once the clock reads at least ``when_ns``."""
        fut: asyncio.Future[None] = loop.create_future()
        heapq.heappush(self._heap, (when_ns, next(self._seq), fut))
        if self._armed is None or when_ns < self._armed:
            _timerfd_arm(self._fd, self._spec, when_ns)
            self._armed = when_ns
        return fut

    def _on_expired(self) -> None:
        try:
            os.read(self._fd, 8)
        except BlockingIOError:  # re-armed after it became readable: nothing due yet
            return
        self._armed = None
        heap = self._heap
        now = self._read()
        while heap and (heap[0][0] <= now or heap[0][2].done()):
            fut = heapq.heappop(heap)[2]
            if not fut.done():
                fut.set_result(None)
        if heap:
            self._armed = heap[0][0]
            _timerfd_arm(self._fd, self._spec, self._armed)


#: Per loop and clock id: the loop's precise timer, or None where it cannot have one.
_timers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[int, _PreciseTimer | None]] = (
    weakref.WeakKeyDictionary()
)


def precise_timer(
    loop: asyncio.AbstractEventLoop, clockid: int, read: ClockRead
) -> _PreciseTimer | None:
    """The timerfd-based timer of ``loop`` for ``clockid``; None where unavailable (no
    timerfd, or a loop without ``add_reader`` such as the Windows proactor)."""
    per_loop = _timers.get(loop)
    if per_loop is None:
        per_loop = _timers[loop] = {}
    try:
        return per_loop[clockid]
    except KeyError:
        pass
    timer: _PreciseTimer | None
    try:
        timer = _PreciseTimer(loop, clockid, read)
    except (OSError, NotImplementedError, AttributeError, ValueError):
        timer = None
    per_loop[clockid] = timer
    return timer


# --------------------------------------------------------------------------------------
# Timer slack (Linux prctl), opt-in


def get_timer_slack() -> int | None:
    """The calling thread's timer slack in nanoseconds; None where unavailable."""
    if _libc is None:
        return None
    try:
        value = int(_libc.prctl(_PR_GET_TIMERSLACK, _ZERO, _ZERO, _ZERO, _ZERO))
    except (OSError, AttributeError):
        return None
    return value if value >= 0 else None


def set_timer_slack(ns: int) -> int | None:
    """Set the calling thread's timer slack; returns the previous value, or None (and does
    nothing) where ``prctl(PR_SET_TIMERSLACK)`` is unavailable.

    ``ns`` must be positive: 0 would mean "the thread's default slack" to the kernel.
    """
    if ns <= 0:
        raise InvalidArgumentError(
            f"timer slack must be a positive number of nanoseconds, got {ns!r}"
        )
    previous = get_timer_slack()
    if previous is None or _libc is None:
        return None
    try:
        if _libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(ns), _ZERO, _ZERO, _ZERO) != 0:
            return None
    except (OSError, AttributeError):
        return None
    return previous


class TimerSlack:
    """Lowers a thread's timer slack only while precise waits are pending on it.

    The first pending wait on a thread saves the thread's slack and sets ``ns``; the last
    one to finish restores the saved value. A no-op where prctl is unavailable.
    """

    def __init__(self, ns: int) -> None:
        if isinstance(ns, bool) or not isinstance(ns, int) or ns <= 0:
            raise InvalidArgumentError(
                f"timer slack must be a positive number of nanoseconds, got {ns!r}"
            )
        self.ns = ns
        self._local = threading.local()

    def acquire(self) -> None:
        """Enter a precise wait on the calling thread."""
        depth: int = getattr(self._local, "depth", 0)
        if depth == 0:
            self._local.saved = set_timer_slack(self.ns)
        self._local.depth = depth + 1

    def release(self) -> None:
        """Leave a precise wait on the calling thread."""
        depth: int = self._local.depth - 1
        self._local.depth = depth
        if depth == 0:
            saved: int | None = self._local.saved
            self._local.saved = None
            if saved is not None:
                set_timer_slack(saved)


# --------------------------------------------------------------------------------------
# The wait itself


async def sleep_until_ns(
    when_ns: int,
    read: ClockRead,
    clockid: int,
    spin_margin_ns: int,
    slack: TimerSlack | None = None,
) -> None:
    """Wait until ``read()`` returns at least ``when_ns``, precisely (see the module doc).

    Always yields to the loop at least once, like ``asyncio.sleep(0)``.
    """
    loop = asyncio.get_running_loop()
    target = when_ns - spin_margin_ns
    remaining = target - read()
    yielded = False
    if remaining > COARSE_NS:
        await asyncio.sleep((remaining - COARSE_NS) / 1e9)
        remaining = target - read()
        yielded = True
    if remaining > 0:
        if slack is not None:
            slack.acquire()
        try:
            timer = precise_timer(loop, clockid, read)
            if timer is not None:
                await timer.wait(loop, target)
            else:
                await asyncio.sleep(remaining / 1e9)
            # Never trust one wake-up: the system clock can be stepped back meanwhile.
            while (remaining := target - read()) > 0:
                if timer is not None:
                    await timer.wait(loop, target)
                else:
                    await asyncio.sleep(remaining / 1e9)
        finally:
            if slack is not None:
                slack.release()
        yielded = True
    while read() < when_ns:
        await asyncio.sleep(0)
        yielded = True
    if not yielded:
        await asyncio.sleep(0)
