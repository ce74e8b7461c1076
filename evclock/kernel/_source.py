"""The interface between the simulation loop and whatever owns simulation time."""

from __future__ import annotations

import abc
import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from evclock.kernel._clock import SimClock
    from evclock.kernel._jumps import TimeJump

Gate = Callable[[int], bool] | None
"""``gate(next_ns)`` is asked before each increment of time when pacing is active (None
otherwise: advance freely); False means "not now": the loop has something to run at the
current time (I/O arrived, a thread called back), so the source must stop and return."""


class SourceHost(Protocol):
    """What a time source may use of the simulation kernel that drives it (the
    :class:`~evclock.kernel._core.SimCore` of a :class:`~evclock.SimEventLoop` or of a
    :class:`~evclock.SimDriver`). The source owns time: the kernel only ever asks it to
    advance and uses what it returns, or learns of a jump through :meth:`jump`."""

    @property
    def now_ns(self) -> int:
        """Sim time as the kernel last took it from the source."""
        ...

    @property
    def clock(self) -> SimClock:
        """The sim clock tasks on this host read."""
        ...

    def stepped_to(self, now_ns: int) -> None:
        """Publish an intermediate time during a multi-increment advance (before hooks run
        and before the next gate call): hooks, predicates and pacing read the clock."""
        ...

    def time_arrived(self) -> None:
        """An ``external`` source received news from outside (call it from its reader
        callback): the host asks it to advance again at once."""
        ...

    def work_ready(self) -> bool:
        """True once a task became runnable: a stepping source stops stepping then."""
        ...

    def jump(self, before_ns: int, after_ns: int, assign: Callable[[int], None]) -> TimeJump:
        """Move time discontinuously; ``assign(after_ns)`` is called to set the source's time."""
        ...

    def serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` are on this host's sim time."""
        ...

    def is_closed(self) -> bool:
        """Whether the host (loop or driver) is closed."""
        ...

    def call_exception_handler(self, context: dict[str, Any]) -> None:
        """Report an error the source caught (a step hook that raised), as asyncio does."""
        ...


class TimeSource(abc.ABC):
    """Owns simulation time for one host (a :class:`~evclock.SimEventLoop` or a
    :class:`~evclock.SimDriver`).

    The host's kernel asks the source to advance only when every task waits, and takes the
    time it returns. A source either jumps (discrete-event: :class:`VirtualTimeSource`),
    moves in whole steps of an engine (:class:`SteppingTimeSource`, e.g.
    :class:`~evclock.sources.PyBulletTimeSource`) or follows time from outside (``external``).
    """

    #: True when time can move with nothing scheduled (physics keeps stepping, an outside
    #: clock goes on); False when an idle program with nothing scheduled is a deadlock.
    free_running: bool = False

    #: True when time comes from outside the process (another simulation, a ROS 2 /clock):
    #: :meth:`advance` does not wait on its own (but see :attr:`io_fd`) and may return the
    #: time unchanged ("no news yet"); the
    #: host then waits for I/O - the source's messages arrive through the loop (a reader
    #: registered with ``loop.add_reader``, or ``loop.call_soon_threadsafe`` from a foreign
    #: thread), which then calls ``host.time_arrived()`` - and asks again (also every 50 ms
    #: of wall time, so that the source can check its own deadline). Liveness is the
    #: source's job: it raises an
    #: :class:`~evclock.EvClockError` from ``advance`` (or its reader callback) when the
    #: outside is lost. An external source is ``free_running``: idle is not a deadlock.
    external: bool = False

    #: An ``external`` source whose news arrives on one file descriptor it registered
    #: with ``loop.add_reader`` may name it here (or set it in :meth:`attach`). When that
    #: fd is the only I/O and nothing else runs outside the loop, the loop asks the
    #: source directly instead of polling first, and does not count the fd's unread bytes
    #: as work in flight: the source reads the fd itself in :meth:`advance` if it needs
    #: to, and answers for what travels on it. It may then also take the loop's own wait
    #: for that fd inside :meth:`advance` (``SimEventLoop._wait_for_source()``: bounded,
    #: and ended by anything that wakes the loop), and use what it reads at once: the
    #: clock server's participant waits for its grant this way.
    io_fd: int | None = None

    _host: SourceHost | None = None

    def attach(self, loop: SourceHost) -> None:
        """Called once by the loop (or driver) that this source will drive."""
        if self._host is not None and self._host is not loop:
            from evclock._errors import SourceInUseError

            raise SourceInUseError(
                f"{type(self).__name__} is already attached to another loop; "
                "create one time source per loop"
            )
        self._host = loop

    @property
    def host(self) -> SourceHost | None:
        """The kernel this source is attached to (None: not attached)."""
        return self._host

    def detach(self) -> None:
        """Called by a host that stops driving this source (a stopped SimDriver); the
        source keeps its time and may be attached to a new host."""
        self._host = None

    @property
    @abc.abstractmethod
    def now_ns(self) -> int:
        """Current simulation time in integer nanoseconds."""

    @abc.abstractmethod
    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Move time toward ``target_ns`` (None: free-run one increment) and return the new time.

        Before every increment to a time ``t`` call ``gate(t)`` (unless ``gate`` is None); if
        it returns False, stop without moving. Stop as well once a task became ready
        (``host.work_ready()``: a step hook woke one). A source that moves in several
        increments within one call publishes each new time (``host.stepped_to(t)``) before
        the next ``gate`` call or hook: pacing, ``step_until`` and the clock read it.

        The returned time may be before ``target_ns`` (the gate said no, or a step hook woke
        a task) or after it (steps quantise time up to a step boundary). An ``external``
        source returns at most ``target_ns``, and may return the time unchanged.
        """

    def describe(self) -> str:
        """A short human description, for error messages."""
        return type(self).__name__

    def close(self) -> None:  # noqa: B027 - optional hook, most sources hold nothing
        """Release resources; called when the loop closes."""
