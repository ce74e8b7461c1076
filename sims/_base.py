"""Shared scaffolding for the scenarios: the clock interface and the Scenario base class.

A scenario loads its world into an already-connected PyBullet client - or, for the scenarios
that also run on MuJoCo (``engines`` names ``"mujoco"``), into a
:class:`~evclock_sims._mujoco.MuJoCoWorld` - and runs its controllers as asyncio coroutines
against a :class:`ClockLike`.  Controllers never step the physics: whoever owns the clock steps
it once per 1/240 s of simulated time, and controllers only read state and write motor commands
between steps.  Only the engine-facing code of a scenario differs between engines; its
controllers are the same.
"""

from __future__ import annotations

import abc
import asyncio
import math
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from evclock._errors import AgentProtocolError
from evclock._extras import import_extra

from ._mujoco import MuJoCoWorld

ENGINES = ("pybullet", "mujoco")
"""The physics engines a scenario can run on; PyBullet is the default."""


def pybullet() -> Any:
    """The ``pybullet`` module; a missing PyBullet fails naming the extra that installs it."""
    return import_extra("pybullet", "pybullet", needed_by="evclock_sims (the bundled scenarios)")


def __getattr__(name: str) -> Any:
    # ``p`` and ``pybullet_data`` were module attributes (imported eagerly) before the
    # scenarios ran on MuJoCo too: now they are imported on first use.
    if name == "p":
        return pybullet()
    if name == "pybullet_data":
        return import_extra("pybullet_data", "pybullet", needed_by="evclock_sims")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


PHYSICS_HZ = 240
"""Physics rate of every scenario: one ``stepSimulation`` per 1/240 s of simulated time."""

GRAVITY = -9.81

Metric = float | int | bool | str


class TimeLike(Protocol):
    """A point in simulated time."""

    @property
    def seconds(self) -> float:
        """The time in seconds."""
        ...

    @property
    def nanoseconds(self) -> int:
        """The time in integer nanoseconds (exact)."""
        ...


class TickLike(Protocol):
    """One iteration of a drift-free rate loop."""

    @property
    def expected(self) -> TimeLike:
        """When this tick was due."""
        ...

    @property
    def actual(self) -> TimeLike:
        """When this tick actually ran."""
        ...

    @property
    def missed(self) -> int:
        """How many ticks were skipped because the loop ran late."""
        ...

    @property
    def index(self) -> int:
        """The tick number, counting from 0 at the first tick (skipped ticks count too)."""
        ...


class ClockLike(Protocol):
    """The clock interface scenario controllers use (satisfied by ``evclock.clock()``)."""

    def now(self) -> TimeLike:
        """The current simulated time."""
        ...

    def sleep(self, seconds: float) -> Awaitable[None]:
        """Suspend the caller for ``seconds`` of simulated time."""
        ...

    def rate(self, hz: float, *, name: str) -> AsyncIterator[TickLike]:
        """Yield a tick every ``1/hz`` simulated seconds, forever, without drift."""
        ...


def data_path(relative: str) -> str:
    """The absolute path of a file shipped in ``pybullet_data``."""
    data = import_extra("pybullet_data", "pybullet", needed_by="evclock_sims")
    return str(Path(data.getDataPath()) / relative)


def wrap_angle(angle: float) -> float:
    """``angle`` wrapped into [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class Scenario(abc.ABC):
    """A physics world plus an asyncio controller stack that drives it toward a mission.

    Subclasses call ``super().__init__`` first (which prepares the client and the seeded random
    generator ``self.rng``), then load their bodies.  ``world`` is a connected PyBullet client
    id, or a :class:`~evclock_sims._mujoco.MuJoCoWorld` for a scenario whose :attr:`engines`
    include ``"mujoco"``; :attr:`engine` says which.  :meth:`run` starts the subclass's
    :meth:`_services` (background rate loops) and its :meth:`_mission` concurrently in one
    ``asyncio.TaskGroup``; when the mission returns, the services are cancelled and ``run``
    returns.  The mission decides success; :meth:`success` and :meth:`summary` report it.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    default_until: ClassVar[float]
    """Simulated seconds the scenario needs to finish its mission (with margin)."""
    engines: ClassVar[tuple[str, ...]] = ("pybullet",)
    """The physics engines the scenario can run on (see :data:`ENGINES`)."""
    agent_controller: ClassVar[str | None] = None
    """The background controller (a label of :meth:`_services`) a learning agent may replace
    (see :mod:`evclock.gym`), for a scenario that implements the agent protocol; None for one
    that does not."""

    def __init__(self, world: int | MuJoCoWorld, seed: int = 0) -> None:
        """Prepare the world - a connected PyBullet client id (gravity, 1/240 s steps) or an
        empty :class:`MuJoCoWorld` - and the RNG."""
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.finished_at: float | None = None
        """Simulated seconds at which the mission ended, or None while it has not."""
        self.replaced: dict[str, Any] = {}
        """Controllers replaced for the next :meth:`run`: label -> a function of the clock
        returning the coroutine that runs instead (see :meth:`replace_controller`)."""
        self.world: MuJoCoWorld | None = None
        """The MuJoCo world, on MuJoCo (None on PyBullet)."""
        self._robot_urdf: Path | None = None
        self.pb: Any = None
        """The PyBullet API the controllers call: the ``pybullet`` module, or a stand-in that
        forwards the calls to the simulation process when the controllers run in another one
        (``evclock control``). World building and :meth:`state_vector` always use ``p``.
        None on MuJoCo."""
        if isinstance(world, MuJoCoWorld):
            if "mujoco" not in self.engines:
                raise TypeError(
                    f"scenario {self.name!r} runs on {', '.join(self.engines)} only, not on "
                    "MuJoCo: run it with --engine pybullet"
                )
            self.engine = "mujoco"
            self.client: Any = None
            self.world = world
            return
        if isinstance(world, bool) or not isinstance(world, int):
            raise TypeError(
                "a scenario is built in a connected PyBullet client (an int id) or a "
                f"MuJoCoWorld, got {type(world).__name__}"
            )
        p = pybullet()
        self.engine = "pybullet"
        """The engine the scenario runs on: ``"pybullet"`` or ``"mujoco"``."""
        self.client = world
        """The PyBullet client id (None on MuJoCo)."""
        self.pb = p
        p.setGravity(0.0, 0.0, GRAVITY, physicsClientId=world)
        p.setTimeStep(1.0 / PHYSICS_HZ, physicsClientId=world)

    def load_urdf(self, relative: str, *, robot: bool = False, **kwargs: Any) -> int:
        """Load a ``pybullet_data`` URDF into this scenario's PyBullet client; its body id.
        ``robot=True`` names it the scenario's robot (:attr:`robot_urdf`)."""
        path = data_path(relative)
        body: int = pybullet().loadURDF(path, physicsClientId=self.client, **kwargs)
        if robot:
            self._robot_urdf = Path(path)
        return body

    @property
    def robot_urdf(self) -> Path | None:
        """The URDF file of the scenario's robot (what ``evclock run --ros2`` publishes on
        ``/robot_description``): on MuJoCo the world's, on PyBullet the one loaded with
        ``load_urdf(..., robot=True)``; None when the scenario names none."""
        if self.world is not None:
            return self.world.urdf
        return self._robot_urdf

    def before_step(self) -> None:
        """Called before every physics step, when a subclass overrides it (``evclock run``
        registers it as a step hook of the time source; in ``--wall`` mode the world task
        calls it).  The place for what must be repeated every step - PyBullet clears the
        forces of ``applyExternalForce`` after each step - applied through the world
        (``p``), not ``self.pb``.  The clock reads the time of the step about to be taken."""
        return None  # nothing by default (and no hook registered)

    def after_step(self) -> None:
        """Called after every physics step, when a subclass overrides it (see
        :meth:`before_step`); the clock reads the time of the step just taken."""
        return None  # nothing by default (and no hook registered)

    def replace_controller(
        self, label: str, controller: Callable[[ClockLike], Coroutine[Any, Any, None]]
    ) -> None:
        """Run ``controller(clock)`` instead of the background controller ``label`` (a label
        of :meth:`_services`) in :meth:`run`: how a learning agent or a trained policy takes
        that controller's place (see :mod:`evclock.gym`).

        :raises AgentProtocolError: the scenario has no background controller ``label`` (the
            check runs in :meth:`run`, where the controllers are made).
        """
        self.replaced[label] = controller

    def _controllers(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        """The background controllers of a run, with the replaced ones swapped in."""
        services = self._services(clock)
        unknown = [label for label in self.replaced if label not in services]
        if unknown:
            for coro in services.values():
                coro.close()  # never started: closed, so none warns it was never awaited
            raise AgentProtocolError(
                f"scenario {self.name!r} has no background controller "
                f"{', '.join(map(repr, unknown))} to replace; its controllers: "
                f"{', '.join(services) or 'none'}"
            )
        for label, controller in self.replaced.items():
            services[label].close()
            services[label] = controller(clock)
        return services

    async def run(self, clock: ClockLike) -> None:
        """Run the controller stack until the mission is over (success or failure)."""
        policy = getattr(self, "policy", "")
        if policy and self.agent_controller is not None:
            # A trained policy as the agent's controller (evclock run --param policy=...).
            from evclock.gym import PolicyController

            if self.agent_controller not in self.replaced:
                self.replace_controller(self.agent_controller, PolicyController(policy, self))
        async with asyncio.TaskGroup() as group:
            services = [
                group.create_task(coro, name=f"{self.name}.{label}")
                for label, coro in self._controllers(clock).items()
            ]
            await group.create_task(self._mission(clock), name=f"{self.name}.mission")
            self.finished_at = clock.now().seconds
            for task in services:
                task.cancel()

    @abc.abstractmethod
    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        """Background controllers (label -> coroutine) that run until the mission ends."""

    @abc.abstractmethod
    async def _mission(self, clock: ClockLike) -> None:
        """The controller that decides when the scenario is over; returns when it is."""

    @abc.abstractmethod
    def success(self) -> bool:
        """Whether the mission was accomplished."""

    @abc.abstractmethod
    def _metrics(self) -> dict[str, Metric]:
        """Scenario-specific metrics for :meth:`summary`."""

    def summary(self) -> dict[str, Metric]:
        """Metrics for a report; ``mission_time_s`` is NaN while the mission has not ended."""
        return {
            "scenario": self.name,
            "seed": self.seed,
            "success": self.success(),
            "mission_time_s": math.nan if self.finished_at is None else self.finished_at,
            **self._metrics(),
        }

    def state_vector(self) -> list[float]:
        """The full physical state of every body, for bit-exact determinism comparisons.

        On PyBullet, per body (in body-id order): base position, orientation quaternion, linear
        and angular velocity, then every joint's position and velocity.  On MuJoCo: every joint
        position, then every velocity, then actuator activations.
        """
        if self.world is not None:
            return self.world.state_vector()
        p = pybullet()
        state: list[float] = []
        cid = self.client
        for i in range(p.getNumBodies(physicsClientId=cid)):
            body = p.getBodyUniqueId(i, physicsClientId=cid)
            position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            linear, angular = p.getBaseVelocity(body, physicsClientId=cid)
            state += [*position, *orientation, *linear, *angular]
            for joint in range(p.getNumJoints(body, physicsClientId=cid)):
                state += p.getJointState(body, joint, physicsClientId=cid)[:2]
        return state
