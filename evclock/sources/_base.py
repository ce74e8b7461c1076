"""The interface between the simulation loop and whatever owns simulation time."""

from __future__ import annotations

import abc
import asyncio
from collections.abc import Callable, Sized
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from .._clock import SimClock
    from .._jumps import TimeJump

#: ``gate(next_ns)`` is asked before each increment of time when pacing is active (None
#: otherwise: advance freely); False means "not now": the loop has something to run at the
#: current time (I/O arrived, a thread called back), so the source must stop and return.
Gate = Callable[[int], bool] | None


class SourceHost(Protocol):
    """What a time source needs from whatever drives it: a :class:`~evclock.SimEventLoop`,
    or a :class:`~evclock.SimDriver` on a loop evclock does not own."""

    #: Sim time as the host publishes it; a source stepping several increments per advance
    #: writes each new time here before its hooks and the next gate call.
    _now_ns: int

    @property
    def now_ns(self) -> int: ...

    @property
    def clock(self) -> SimClock:
        """The sim clock tasks on this host read."""
        ...

    @property
    def _ready(self) -> Sized:
        """Non-empty (truthy) once a task became runnable: a stepping source stops then."""
        ...

    def _jump_time(
        self, before_ns: int, after_ns: int, assign: Callable[[int], None]
    ) -> TimeJump: ...

    def _runs_on(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether tasks of ``loop`` are on this host's sim time."""
        ...

    def is_closed(self) -> bool: ...

    def call_exception_handler(self, context: dict[str, Any]) -> None: ...


class TimeSource(abc.ABC):
    """Owns simulation time for one :class:`~evclock.SimEventLoop`.

    The loop asks the source to advance only when every task waits. A source either jumps
    (discrete-event: :class:`VirtualTimeSource`) or moves in whole steps of a physics engine
    (:class:`~evclock.PyBulletTimeSource`).
    """

    #: True when time can move with nothing scheduled (physics keeps stepping); False when an
    #: idle program with nothing scheduled is a deadlock.
    free_running: bool = False

    #: True when advancing is a pure jump to the target with no side effects (virtual time):
    #: the loop then moves time itself and reads it back through ``loop.now_ns``.
    discrete_event: bool = False

    # external-source contract: time comes from outside the process (a followed ROS 2
    # /clock). advance() never blocks and may return the time unchanged ("waiting for the
    # outside"); the host then waits for I/O instead of spinning or reporting a deadlock.
    external: bool = False

    _loop: SourceHost | None = None

    def attach(self, loop: SourceHost) -> None:
        """Called once by the loop (or driver) that this source will drive."""
        if self._loop is not None and self._loop is not loop:
            from .._errors import EvClockError

            raise EvClockError(
                f"{type(self).__name__} is already attached to another loop; "
                "create one time source per loop"
            )
        self._loop = loop

    def detach(self) -> None:
        """Called by a host that stops driving this source (a stopped SimDriver); the
        source keeps its time and may be attached to a new host."""
        self._loop = None

    @property
    @abc.abstractmethod
    def now_ns(self) -> int:
        """Current simulation time in integer nanoseconds."""

    @abc.abstractmethod
    def advance(self, target_ns: int | None, gate: Gate) -> int:
        """Move time toward ``target_ns`` (None: free-run one increment) and return the new time.

        Before every increment to a time ``t`` call ``gate(t)`` (unless ``gate`` is None); if
        it returns False, stop without moving. Stop as well once a task became ready (a
        step hook woke one). A source that moves in several increments within one call must
        publish each new time to the loop (``loop._now_ns = t``) before the next ``gate``
        call or hook: pacing, ``step_until`` and the clock read the loop's time.

        The returned time may be before ``target_ns`` (the gate said no, or a step hook woke
        a task) or after it (steps quantise time up to a step boundary).
        """

    def describe(self) -> str:
        """A short human description, for error messages."""
        return type(self).__name__

    def close(self) -> None:  # noqa: B027 - optional hook, most sources hold nothing
        """Release resources; called when the loop closes."""
