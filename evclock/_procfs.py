"""What the Linux kernel says a thread is doing: the one module that reads ``/proc``.

For each thread of this process (``/proc/self/task/<tid>/``) and of a child process, the
scheduler state (``stat``: runnable or not), how often it got a CPU (``schedstat``) and the
system call it is blocked in with its arguments (``syscall``); for timed sleeps, futex
waits and waits on file descriptors, the timeout those arguments give or point to (read
from ``/proc/<pid>/mem``). The thread-state inference of :mod:`evclock.outside._threads`
turns these into "holds sim time or not".

Everything here answers None (unknown) rather than guess when ``/proc`` cannot be read, on
other platforms and architectures (x86_64 and aarch64 system call tables are known).
Verified on Linux x86_64 in CI; aarch64 by its system call table (tests/outside).
"""

from __future__ import annotations

import enum
import os
import socket
import stat
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import TypeVar


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
    #: Blocked on file descriptors with no timeout (``recv``, ``accept``, ``read``, a
    #: ``select``/``poll`` with none): waiting for the world outside, often the loop's own
    #: sockets, with no end of its own. It does not hold sim time, but it may wake the loop.
    WAITING_IO = "waiting for I/O"
    #: Waiting for a child process it started to exit (``waitpid``/``wait4``/``waitid``:
    #: ``subprocess.run``, ``Popen.wait``): the child is working for it. Holds sim time, as
    #: the thread's own work would.
    WAITING_CHILD = "waiting for a child process"
    #: A simulation loop waiting in its selector: it follows its own time.
    EVENT_LOOP = "an event loop waiting"


# ----------------------------------------------------------- the kernel's view (Linux)

# System calls a blocked thread can sit in, by number, per architecture: (kind, timeout
# argument). Kinds: "ms" an int of milliseconds (negative = none), "ptr" a pointer to a
# timespec (a timeval for select; 0 = none), FUTEX the futex rules, SLEEP a timed sleep,
# PAUSE no timeout at all, CHILD a wait for a child process. Any other system call (read,
# recv, accept, ...) is I/O with no timeout of its own.
_Rule = tuple[str, int]
FUTEX: _Rule = ("futex", 3)
SLEEP: _Rule = ("sleep", 0)
PAUSE: _Rule = ("pause", 0)
CHILD: _Rule = ("child", 0)
_X86_64: dict[int, _Rule] = {
    7: ("ms", 2),  # poll
    23: ("ptr", 4),  # select
    34: PAUSE,  # pause
    35: SLEEP,  # nanosleep
    61: CHILD,  # wait4
    128: ("ptr", 2),  # rt_sigtimedwait
    202: FUTEX,
    230: SLEEP,  # clock_nanosleep
    232: ("ms", 3),  # epoll_wait
    247: CHILD,  # waitid
    270: ("ptr", 4),  # pselect6
    271: ("ptr", 2),  # ppoll
    281: ("ms", 3),  # epoll_pwait
    441: ("ptr", 3),  # epoll_pwait2
    449: ("ptr", 3),  # futex_waitv
}
_AARCH64: dict[int, _Rule] = {
    22: ("ms", 3),  # epoll_pwait
    72: ("ptr", 4),  # pselect6
    73: ("ptr", 2),  # ppoll
    95: CHILD,  # waitid
    98: FUTEX,
    101: SLEEP,  # nanosleep
    115: SLEEP,  # clock_nanosleep
    137: ("ptr", 2),  # rt_sigtimedwait
    260: CHILD,  # wait4
    441: ("ptr", 3),  # epoll_pwait2
    449: ("ptr", 3),  # futex_waitv
}
_SYSCALLS: dict[int, _Rule] | None = {"x86_64": _X86_64, "aarch64": _AARCH64}.get(
    os.uname().machine
)
_FUTEX_CMD_MASK = 0x7F  # without FUTEX_PRIVATE_FLAG (128) and FUTEX_CLOCK_REALTIME (256)
_FUTEX_WAITS = frozenset({0, 6, 9, 11, 13})  # WAIT, LOCK_PI, WAIT_BITSET, WAIT_REQUEUE_PI, LOCK_PI2


def state_from_syscall(text: str) -> ThreadState:
    """Classify one ``/proc/.../syscall`` line: "running", or "nr arg0 .. arg5 sp pc".

    A wait with a timeout ends by itself and is timed work, whatever it waits on: a timed
    sleep, a futex wait with a timeout, and a ``select``/``poll``/``epoll`` wait on file
    descriptors with a timeout (a socket with ``settimeout``) are TIMED. A wait on
    descriptors with no timeout is WAITING_IO; a wait for a child process is WAITING_CHILD.
    A stock asyncio loop in a thread is no exception: its selector's timeout is its next
    timer (a simulation loop waiting on its own time is told apart by its frames, in
    :mod:`evclock.outside._threads`).
    """
    fields = text.split()
    if not fields or fields[0] == "running" or fields[0] == "-1":
        return ThreadState.RUNNING  # "-1": blocked outside a system call (a page fault)
    assert _SYSCALLS is not None
    args = [int(value, 16) for value in fields[1:7]]
    rule = _SYSCALLS.get(int(fields[0]))
    if rule is None:
        return ThreadState.WAITING_IO  # read, recv, accept, ...: no timeout of its own
    if rule is CHILD:
        return ThreadState.WAITING_CHILD
    if rule is PAUSE:
        return ThreadState.PARKED  # pause(): only a signal ends it
    if rule is SLEEP:
        return ThreadState.TIMED
    kind, timeout_arg = rule
    if rule is FUTEX:
        command = args[1] & _FUTEX_CMD_MASK
        if command not in _FUTEX_WAITS:
            return ThreadState.RUNNING  # a wake or requeue: over in an instant
        return ThreadState.TIMED if args[timeout_arg] else ThreadState.PARKED
    value = args[timeout_arg]
    # "ms": a negative int means no timeout; "ptr": a null pointer does.
    timed = value & 0x80000000 == 0 if kind == "ms" else value != 0
    return ThreadState.TIMED if timed else ThreadState.WAITING_IO


class KernelView:
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
    probe = KernelView()
    text = probe.read(threading.get_native_id())  # this thread: running
    probe.forget_except(set())
    return text == "running"


#: The kernel's view of this process's threads, or None where ``/proc`` cannot tell.
kernel_view: KernelView | None = KernelView() if _kernel_view_works() else None


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


def _read_timeout(mem_fd: int, address: int, timeval: bool) -> float | None:
    """The ``struct timespec`` (or ``struct timeval``, ``timeval``) at ``address`` in the
    process whose ``mem`` file is ``mem_fd``, in seconds (``/proc/<pid>/mem`` answers EIO
    rather than crash when the memory is gone)."""
    try:
        raw = os.pread(mem_fd, 16, address)
    except (OSError, OverflowError):
        return None
    if len(raw) != 16:
        return None
    seconds = int.from_bytes(raw[:8], sys.byteorder, signed=True)
    fraction = int.from_bytes(raw[8:], sys.byteorder, signed=True)
    per_second = 1_000_000 if timeval else 1_000_000_000
    if seconds < 0 or not 0 <= fraction < per_second:
        return None  # not a timeout (the thread left the call meanwhile)
    return seconds + fraction / per_second


#: Per architecture: the timed waits on file descriptors whose timeout is a length, by system
#: call number -> (argument, unit): "ms" an int of milliseconds, "timespec"/"timeval" a
#: pointer to one (select's timeval is only written back when the call returns).
_FD_WAIT_TIMEOUTS: dict[int, tuple[int, str]] = (
    {
        7: (2, "ms"),  # poll
        23: (4, "timeval"),  # select
        232: (3, "ms"),  # epoll_wait
        270: (4, "timespec"),  # pselect6
        271: (2, "timespec"),  # ppoll
        281: (3, "ms"),  # epoll_pwait
        441: (3, "timespec"),  # epoll_pwait2
    }
    if _SYSCALLS is _X86_64
    else {22: (3, "ms"), 72: (4, "timespec"), 73: (2, "timespec"), 441: (3, "timespec")}
)


def _timed_call(text: str) -> tuple[str, int, bool, int] | None:
    """For a ``syscall`` line of a timed sleep, futex wait or wait on file descriptors:
    (the unit of its timeout - "ms" for a value, "timespec"/"timeval" for a pointer -, that
    value or address, whether it is an absolute deadline, the clock id); None for anything
    else, or a wait without a timeout."""
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
        return "timespec", args[pointer_arg], absolute, clock
    if number == _FUTEX_NR:
        command = args[1] & _FUTEX_CMD_MASK
        if command not in (_FUTEX_WAIT, _FUTEX_WAIT_BITSET) or not args[3]:
            return None
        absolute = command == _FUTEX_WAIT_BITSET  # WAIT's timeout is a length
        if absolute and args[1] & _FUTEX_CLOCK_REALTIME:
            clock = time.CLOCK_REALTIME
        return "timespec", args[3], absolute, clock
    if number in _FD_WAIT_TIMEOUTS:
        arg, unit = _FD_WAIT_TIMEOUTS[number]
        value = args[arg]
        if unit == "ms":
            value &= 0xFFFFFFFF  # an int: negative means no timeout
            if value & 0x80000000:
                return None
        elif not value:
            return None
        return unit, value, False, clock
    return None


def _timed_deadline(
    waits: dict[_K, tuple[str, float]],
    key: _K,
    text: str,
    mem_fd: int,
    reread: Callable[[], str | None],
) -> float | None:
    """The monotonic deadline of the timed call ``text`` (see :func:`_timed_call`), read
    from its arguments (and the timeout they point to) and confirmed by reading the call
    again (unchanged: the deadline belongs to it); ``waits[key]`` keeps it per call, so that
    it stays one value."""
    call = _timed_call(text)
    if call is None:
        return None
    unit, where, absolute, clock = call
    value = where / 1000 if unit == "ms" else _read_timeout(mem_fd, where, unit == "timeval")
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


def thread_wait_deadline(thread: threading.Thread) -> float | None:
    """When ``thread``'s timed system call ends by itself, in ``time.monotonic()`` seconds:
    ``time.sleep`` (``clock_nanosleep`` with an absolute deadline), ``nanosleep``, futex
    waits with a timeout (``Lock.acquire(timeout=...)``, a C library's timed wait) and waits
    on file descriptors with a timeout (``select``, ``poll``, a socket with a timeout).
    None when unknown."""
    native_id = thread.native_id
    kernel = kernel_view
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
    if kernel_view is None:
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
            state = state_from_syscall(text)
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
#: two arguments), "select" (nfds, then the read, write and except fd_set pointers) or "fd"
#: (the descriptor is the first argument).
_FD_WAITS: dict[int, str] = (
    {7: "poll", 271: "poll", 23: "select", 270: "select", 0: "fd", 19: "fd", 45: "fd", 47: "fd"}
    if _SYSCALLS is _X86_64
    else {73: "poll", 72: "select", 63: "fd", 65: "fd", 207: "fd", 212: "fd"}
)
_MAX_POLL_FDS = 64
_MAX_SELECT_FDS = 1024  # FD_SETSIZE


def waited_fds(thread: threading.Thread) -> list[int]:
    """The descriptors ``thread`` is blocked on, if it waits in ``poll``/``ppoll`` (how a
    socket with a timeout waits), ``select``/``pselect6`` or in a ``read``/``recv`` on one
    descriptor: from its system call's arguments (and the pollfd array or fd_sets they point
    to). Empty when unknown."""
    native_id = thread.native_id
    kernel = kernel_view
    if kernel is None or native_id is None:
        return []
    text = kernel.read(native_id)
    fields = text.split() if text is not None else []
    if len(fields) < 7 or fields[0] in ("running", "-1"):
        return []
    kind = _FD_WAITS.get(int(fields[0]))
    args = [int(value, 16) for value in fields[1:5]]
    if kind == "fd":
        return [args[0]] if args[0] < 2**31 else []
    mem_fd = _own_mem()
    if kind == "select":
        return _selected_fds(args, mem_fd, lambda: kernel.read(native_id) == text)
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


def _selected_fds(args: list[int], mem_fd: int | None, unchanged: Callable[[], bool]) -> list[int]:
    """The descriptors of a ``select``/``pselect6`` call: the bits set in its three fd_sets."""
    nfds = args[0]
    if mem_fd is None or not 0 < nfds <= _MAX_SELECT_FDS:
        return []
    size = (nfds + 63) // 64 * 8  # an fd_set is an array of longs
    fds: set[int] = set()
    for pointer in args[1:4]:
        if not pointer:
            continue
        try:
            raw = os.pread(mem_fd, size, pointer)
        except (OSError, OverflowError):
            return []
        if len(raw) != size:
            return []
        bits = int.from_bytes(raw, "little")  # Linux: bit i of the set is fd i
        fds.update(fd for fd in range(nfds) if bits >> fd & 1)
    if not unchanged():
        return []
    return sorted(fds)


def far_end(fd: int) -> tuple[str, object] | None:
    """Who is at the other end of ``fd``, as :func:`near_end` names it from that end: a
    pipe's inode (both ends share it), a connected Unix socket's peer inode (the kernel's
    ``sock_diag``), a connected IP socket's peer address. None when it is none of these or
    cannot be told."""
    return _end(fd, far=True)


def near_end(fd: int) -> tuple[str, object] | None:
    """``fd``'s own end, named as :func:`far_end` names it from the other end."""
    return _end(fd, far=False)


def _end(fd: int, *, far: bool) -> tuple[str, object] | None:
    try:
        st = os.fstat(fd)
    except OSError:
        return None
    if stat.S_ISFIFO(st.st_mode):
        return ("pipe", st.st_ino)
    if not stat.S_ISSOCK(st.st_mode):
        return None
    try:
        with socket.socket(fileno=os.dup(fd)) as sock:
            if sock.family == socket.AF_UNIX:
                inode = _unix_peer_inode(st.st_ino) if far else st.st_ino
                return None if inode is None else ("unix", inode)
            if sock.family in (socket.AF_INET, socket.AF_INET6):
                return ("ip", sock.getpeername() if far else sock.getsockname())
    except OSError:
        return None
    return None


_NETLINK_SOCK_DIAG = 4
_SOCK_DIAG_BY_FAMILY = 20
_UDIAG_SHOW_PEER = 4
_UNIX_DIAG_PEER = 2


def _unix_peer_inode(inode: int) -> int | None:
    """The inode of the Unix socket connected to the one of ``inode`` (Linux ``sock_diag``:
    what ``ss -x`` shows as the peer), or None."""
    if not hasattr(socket, "AF_NETLINK"):
        return None
    try:
        with socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, _NETLINK_SOCK_DIAG) as nl:
            # struct unix_diag_req: family, protocol, pad, states, ino, show, cookie[2]
            request = struct.pack(
                "=BBHIIIII", socket.AF_UNIX, 0, 0, 0xFFFFFFFF, inode, _UDIAG_SHOW_PEER,
                0xFFFFFFFF, 0xFFFFFFFF,
            )  # fmt: skip
            header = struct.pack("=IHHII", 16 + len(request), _SOCK_DIAG_BY_FAMILY, 1, 1, 0)
            nl.sendto(header + request, (0, 0))
            data = nl.recv(8192)
    except OSError:
        return None
    if len(data) < 32:
        return None
    length, kind = struct.unpack_from("=IH", data)
    if kind != _SOCK_DIAG_BY_FAMILY:
        return None  # an error reply: no such socket
    offset = 32  # nlmsghdr (16) + struct unix_diag_msg (16), then attributes
    while offset + 4 <= min(length, len(data)):
        size, attribute = struct.unpack_from("=HH", data, offset)
        if size < 4:
            return None
        if attribute == _UNIX_DIAG_PEER and offset + 8 <= len(data):
            return int(struct.unpack_from("=I", data, offset + 4)[0])
        offset += (size + 3) & ~3
    return None


def forget_threads(alive: set[int]) -> None:
    """Threads other than ``alive`` (idents) ended: drop what was kept about their waits."""
    for ident in [i for i in _kernel_waits if i not in alive]:
        del _kernel_waits[ident]
