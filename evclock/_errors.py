"""The evclock exception hierarchy: every error evclock raises derives from EvClockError.

Errors that are also a classic Python category (a bad value, a wrong type, a misuse at run
time) derive from the matching built-in too, so ``except ValueError`` keeps working.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from evclock.kernel._jumps import TimeJump


class EvClockError(Exception):
    """Base class of every error raised by evclock."""


class InvalidArgumentError(EvClockError, ValueError):
    """A value is out of range: a negative, NaN or infinite duration, a zero rate, overflow."""


class InvalidTypeError(EvClockError, TypeError):
    """A value has the wrong type (for example a string where seconds were expected)."""


class ClockMismatchError(EvClockError, TypeError):
    """Times of different clock domains (SIM, SYSTEM, STEADY) were combined or compared."""


class NoSimulationError(EvClockError, RuntimeError):
    """Simulation time was asked for, but no simulation loop or driver is running."""


class LoopClosedError(EvClockError, RuntimeError):
    """The simulation loop was used after it was closed."""


class NotRunningError(EvClockError, RuntimeError):
    """An operation that needs a running loop (pause, step, ...) was called on an idle one."""


class DeadlockError(EvClockError, RuntimeError):
    """Every task waits and nothing can ever wake one: no timer, no physics, no I/O, no thread.

    ``tasks`` lists the waiting tasks' descriptions.
    """

    def __init__(self, message: str, tasks: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.tasks = tasks


class StallError(EvClockError, RuntimeError):
    """Work outside the loop (a thread, an executor job, I/O) held sim time for too long."""


class PacingError(EvClockError, RuntimeError):
    """Misuse of pacing controls, or (strict mode) the simulation lagged behind real time."""


class LagError(PacingError):
    """Strict pacing: the simulation fell behind the requested real-time factor by too much."""


class ClockJumpedError(EvClockError):
    """Raised in a task sleeping on sim time when the clock jumps (reset, restore).

    ``jump`` describes the jump: its ``delta`` and the times before and after.
    """

    def __init__(self, jump: TimeJump) -> None:
        super().__init__(
            f"sim time jumped from {jump.before} to {jump.after} while sleeping; "
            "the sleep was cancelled: re-compute the deadline from clock.now()"
        )
        self.jump = jump


class SimDriverError(EvClockError, RuntimeError):
    """A :class:`~evclock.SimDriver` was started twice, or on a loop that has a sim clock."""


class PhysicsError(EvClockError, RuntimeError):
    """The physics engine cannot be used: a disconnected client, a bad time step."""


class SimTimeLimitError(EvClockError, TimeoutError):
    """A run, a test or a wait exceeded its sim-time limit: ``run(until=...)``, a test's
    ``sim_timeout``, ``SteppingTimeSource.wait_until(timeout=...)``."""


class TimeLookupError(EvClockError, LookupError):
    """A time-indexed lookup found nothing: an empty buffer, no sample stamped exactly t."""


class ExtrapolationError(TimeLookupError):
    """A buffer lookup lies further outside the kept samples than ``max_extrapolation``."""


class SourceInUseError(EvClockError, RuntimeError):
    """A time source that already drives one loop (or SimDriver) was given to another; create
    one time source per loop."""


class PluginOptionError(EvClockError, ValueError):
    """An option of evclock's pytest plugin is invalid: an argument of
    ``@pytest.mark.evclock(...)``, an ``--evclock-*`` command-line option or an ``evclock_*``
    ini value."""


class PluginUsageError(EvClockError, RuntimeError):
    """evclock's pytest plugin cannot run a test as it is set up: an evclock fixture requested
    outside an evclock test, a test on a loop that is not evclock's (another loop factory, a
    plain anyio backend), ``evclock_pybullet`` on a shared or already created loop, an async
    generator fixture that yields twice."""


class ScenarioError(EvClockError, RuntimeError):
    """A scenario cannot be found or loaded: an import failure, a name registered twice."""


class AgentProtocolError(ScenarioError):
    """A scenario cannot host a learning agent: it lacks a method of the agent protocol
    (``observation_space``, ``action_space``, ``observe``, ``act``, ``reward``,
    ``terminated``), or names no controller the agent can replace (see ``evclock.gym``)."""


class ActionError(EvClockError, ValueError):
    """An action handed to an environment or returned by a policy is not in the action
    space: wrong type, shape or dtype, NaN, or outside the bounds (never clipped)."""


class EnvStateError(EvClockError, RuntimeError):
    """A Gymnasium environment is used out of order: ``step()`` before ``reset()``, after
    the episode ended, or after ``close()``."""


class MissingExtraError(EvClockError, ImportError):
    """An optional dependency is not installed; the message names the extra that installs it
    (``pip install 'evclock[pybullet]'``)."""

    extra: str | None = None
    """The extra that installs the missing module (``"pybullet"``), when known."""


class TraceError(EvClockError, ValueError):
    """A recorded trace (MCAP file) cannot be read, or is not an evclock recording."""


class RemoteClockError(EvClockError, RuntimeError):
    """Base class of the errors of sim time across processes (clock servers, participants)."""


class ClockLostError(RemoteClockError):
    """A joined process lost its clock: the clock server closed, died or stayed silent too long,
    or a followed ROS 2 ``/clock`` went silent."""


class JoinRefusedError(RemoteClockError):
    """Joining a clock server failed its checks, on either side: the server refused this
    process (name taken, protocol version, token, another user), or this process refused the
    server (a server running as another user, one that could not prove it knows the token,
    or one that answered a participant with a token without proving itself first)."""


class WeakTokenError(InvalidArgumentError):
    """A clock token too weak to be safe (below 128 bits): refused by the clock server and by
    participants. The server proves it knows the token to anyone who connects, so a short
    token could be guessed offline from one recorded proof."""


class ParticipantLostError(RemoteClockError):
    """A participant the simulation depends on died, stopped answering, never joined, or left
    without handing over what it owed (the scenario controllers' report).

    ``name`` is the participant's name, as it joined (bare, not quoted); for participants that
    never joined, the first missing one's (empty when a number of participants is short).
    """

    def __init__(self, message: str, name: str) -> None:
        super().__init__(message)
        self.name = name


class ProtocolError(RemoteClockError):
    """Bytes on a clock connection that are not evclock's clock protocol."""


class RemoteCallError(RemoteClockError):
    """A service call to the simulation process failed there (the message says why)."""


class Ros2MessageError(EvClockError, ValueError):
    """A ROS 2 ``/clock`` sample evclock cannot read: bad CDR, invalid time, unknown type hash."""


class Ros2SubscribersError(EvClockError, TimeoutError):
    """A ROS 2 publisher waited for its subscribers (``--ros2-wait-for-subscribers``) longer
    than its timeout; the message says how many matched and how many were awaited."""


class WrongThreadError(NotRunningError):
    """A method that runs only on a loop's (or driver's) own thread was called from another;
    the message names the thread-safe way to get it done (``run_coroutine_threadsafe``)."""
