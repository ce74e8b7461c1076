"""PyBullet as the owner of simulation time: a thin adapter over :class:`SteppingTimeSource`.

PyBullet keeps no time counter, so evclock counts the steps and derives the time exactly
from integers (docs/architecture.md, "Time and the step clock"; the step clock, hooks, waits
and snapshots-as-jumps live in ``_stepping.py``). ``pybullet`` is imported lazily, when the
first source is created: ``import evclock`` alone does not load it (nor numpy, nor its banner
on stderr).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from fractions import Fraction
from typing import TYPE_CHECKING, Any

from evclock._errors import InvalidArgumentError, InvalidTypeError, PhysicsError
from evclock._extras import import_extra
from evclock.sources._stepping import SteppingTimeSource, format_seconds
from evclock.time._time import SIM, Duration, Time, new_time, to_sim_time_ns

if TYPE_CHECKING:
    from evclock.kernel._jumps import TimeJump

_NS_PER_S = 1_000_000_000


def _pybullet() -> Any:
    return import_extra("pybullet", "pybullet", needed_by="PyBulletTimeSource")


class PyBulletTimeSource(SteppingTimeSource[tuple[int, ...]]):
    """Sim time driven by one or more PyBullet physics clients, in whole physics steps.

    ``PyBulletTimeSource(client, ...)`` steps already-connected clients (ids returned by
    ``p.connect``); :meth:`connect` creates a DIRECT (or GUI) client and owns it. Run a
    program on it with ``evclock.run(main(), source=source)``. Every advance of sim time
    calls ``p.stepSimulation`` on each client, in the order given, one step at a time.

    **Time.** Sim time is ``start_ns + floor(steps x dt_ns)``, where ``dt_ns`` is the time step
    as an exact fraction of nanoseconds (see :func:`exact_time_step`: ``1/240`` s is exactly
    ``12500000/3`` ns) and ``steps`` an integer: 24 simulated hours never drift by a
    nanosecond. A change of time step re-bases the count at the current step boundary.

    **Time step.** ``dt`` is read from the engine (``fixedTimeStep``); every client must have
    the same. ``numSubSteps`` does not change it: one ``stepSimulation`` always advances
    ``fixedTimeStep`` seconds, split into sub-steps inside the engine (checked by the tests).
    Change it with :meth:`set_time_step`. With ``watch_time_step=True`` (default), a change
    made directly with ``p.setTimeStep``/``p.setPhysicsEngineParameter(fixedTimeStep=...)``
    is detected too: the time step is re-read before each advance of the loop (one
    ``getPhysicsEngineParameters`` call per client), so a change made from a task
    takes effect from the next step. ``watch_time_step=False`` saves that call; then change
    the time step only through :meth:`set_time_step` (always required from inside a step hook).

    **Quantisation.** Sleeps are quantised *up* to step boundaries: a task sleeping until
    ``t`` wakes at the end of the first step whose time is ``>= t`` (with ``dt = 1/240`` s, a
    ``sleep(0.001)`` lasts one step, 4.1666 ms). Rates whose period is a whole number of steps
    (20 Hz, 60 Hz, 240 Hz at ``dt = 1/240``) tick exactly on their deadlines. A float
    duration of whole steps may round one nanosecond past a step (``1/240`` s is 4166667 ns,
    one step 4166666.67 ns) and then lasts one step more: wait whole steps with
    :meth:`sleep_steps`.

    **Free running.** With nothing scheduled, physics keeps stepping (``free_running``): a
    task may wait on a step hook or :meth:`wait_until`.

    :param clients: PyBullet physics client ids (``p.connect`` return values), at least one.
    :param start_ns: sim time of the current state, in integer nanoseconds (default 0).
    :param watch_time_step: detect time-step changes made directly through pybullet.
    """

    def __init__(self, *clients: int, start_ns: int = 0, watch_time_step: bool = True) -> None:
        if not clients:
            raise InvalidArgumentError(
                "PyBulletTimeSource needs at least one connected PyBullet client id, e.g. "
                "PyBulletTimeSource(p.connect(p.DIRECT)), or use PyBulletTimeSource.connect()"
            )
        for cid in clients:
            if isinstance(cid, bool) or not isinstance(cid, int):
                raise InvalidTypeError(
                    "PyBullet clients are int ids returned by p.connect(), "
                    f"got {type(cid).__name__}"
                )
        if len(set(clients)) != len(clients):
            raise InvalidArgumentError(
                f"PyBullet client ids must be distinct, got {clients!r}: a client listed twice "
                "would be stepped twice per step"
            )
        if type(start_ns) is not int:
            raise InvalidTypeError(
                f"start_ns must be an int number of nanoseconds, got {type(start_ns).__name__}"
            )
        if start_ns < 0:
            raise InvalidArgumentError(f"start_ns must not be negative, got {start_ns}")
        pb = _pybullet()
        self._p: Any = pb
        self._step: Callable[[int], object] = pb.stepSimulation
        self._clients: tuple[int, ...] = tuple(clients)
        self._owns_clients = False
        self._watch = bool(watch_time_step)
        for cid in clients:
            if not pb.isConnected(cid):
                raise PhysicsError(
                    f"PyBullet physics client {cid} is not connected; pass the id returned by "
                    "p.connect(p.DIRECT) (or p.GUI) while it is connected, or let "
                    "PyBulletTimeSource.connect() create one"
                )
            params = pb.getPhysicsEngineParameters(physicsClientId=cid)
            if params.get("useRealTimeSimulation"):
                raise PhysicsError(
                    f"PyBullet physics client {cid} has real-time simulation on (the server "
                    "steps itself on the wall clock); call "
                    f"p.setRealTimeSimulation(0, physicsClientId={cid}): evclock steps it"
                )
        self._closed = False
        super().__init__(self._read_time_step(), start_ns=start_ns)

    @classmethod
    def connect(
        cls,
        gui: bool = False,
        *,
        time_step: float | Fraction | Duration | None = None,
        options: str = "",
        start_ns: int = 0,
        watch_time_step: bool = True,
    ) -> PyBulletTimeSource:
        """Connect a new PyBullet client (DIRECT, or GUI with ``gui=True``) and drive it.

        The source owns this client: it is disconnected when the loop closes (or on
        :meth:`close`). ``time_step`` sets the engine's time step (default: PyBullet's 1/240 s);
        ``options`` is passed to ``p.connect``. Read the client id from :attr:`client`.
        Note that PyBullet ends the process if a GUI cannot open (no display).
        """
        pb = _pybullet()
        mode = pb.GUI if gui else pb.DIRECT
        cid = pb.connect(mode, options=options) if options else pb.connect(mode)
        if cid < 0:
            raise PhysicsError(
                f"could not connect to PyBullet in {'GUI' if gui else 'DIRECT'} mode "
                "(p.connect returned -1); a GUI needs a display, and only one GUI client may "
                "exist per process"
            )
        try:
            source = cls(cid, start_ns=start_ns, watch_time_step=watch_time_step)
            if time_step is not None:
                source.set_time_step(time_step)
        except BaseException:
            pb.disconnect(cid)
            raise
        source._owns_clients = True
        return source

    # ------------------------------------------------------------ the engine

    @property
    def clients(self) -> tuple[int, ...]:
        """The PyBullet client ids this source steps, in stepping order."""
        return self._clients

    @property
    def client(self) -> int:
        """The first (usually the only) client id."""
        return self._clients[0]

    def _step_engine(self, count: int) -> None:
        step = self._step
        clients = self._clients
        try:
            if len(clients) == 1:
                cid = clients[0]
                for _ in itertools.repeat(None, count):
                    step(cid)
            else:
                for _ in itertools.repeat(None, count):
                    for cid in clients:
                        step(cid)
        except self._p.error as exc:
            raise self._failure(exc, "stepSimulation") from exc

    def _set_engine_time_step(self, dt: float) -> float:
        pb = self._p
        for cid in self._clients:
            try:
                pb.setTimeStep(dt, physicsClientId=cid)
            except pb.error as exc:
                raise self._failure(exc, "setTimeStep") from exc
        return self._read_time_step()

    def _before_advance(self) -> None:
        if self._watch:
            self._check_time_step()

    def _read_time_step(self) -> float:
        """Read the shared time step from every client (validated)."""
        pb = self._p
        first: float | None = None
        for cid in self._clients:
            try:
                dt = pb.getPhysicsEngineParameters(physicsClientId=cid)["fixedTimeStep"]
            except pb.error as exc:
                raise self._failure(exc, "getPhysicsEngineParameters") from exc
            if not (isinstance(dt, float) and math.isfinite(dt) and dt > 0):
                raise PhysicsError(
                    f"PyBullet physics client {cid} has fixedTimeStep={dt!r}, which is not a "
                    "positive finite number of seconds; set one with "
                    f"p.setTimeStep(1/240, physicsClientId={cid}) or source.set_time_step(1/240)"
                )
            if first is None:
                first = dt
            elif dt != first:
                raise PhysicsError(
                    "PyBullet clients stepped together must share one time step, but client "
                    f"{self._clients[0]} has fixedTimeStep={first!r} and client {cid} has "
                    f"{dt!r}; give them the same with source.set_time_step(dt) (or "
                    "p.setTimeStep(dt, physicsClientId=...) on each)"
                )
        assert first is not None
        return first

    def _check_time_step(self) -> None:
        """The watch: pick up a time step changed directly through pybullet."""
        pb = self._p
        read = pb.getPhysicsEngineParameters
        dt = self._dt
        for cid in self._clients:
            try:
                changed = read(physicsClientId=cid)["fixedTimeStep"] != dt
            except pb.error as exc:
                raise self._failure(exc, "getPhysicsEngineParameters") from exc
            if changed:
                self._use_time_step(self._read_time_step())
                return

    def _sync_time_step(self) -> None:
        """Snapshots and resets do not hold the time step: go on with the engine's."""
        dt = self._read_time_step()
        if dt != self._dt:
            self._use_time_step(dt)

    def _failure(self, exc: BaseException, call: str) -> PhysicsError:
        pb = self._p
        for cid in self._clients:
            if not pb.isConnected(cid):
                return PhysicsError(
                    f"PyBullet physics client {cid} was disconnected while evclock was "
                    "stepping it (p.disconnect() was called, or its server or GUI window went "
                    "away); keep every client of a PyBulletTimeSource connected until the loop "
                    "closes"
                )
        return PhysicsError(f"PyBullet {call} failed on client(s) {self._clients}: {exc}")

    # ------------------------------------------------------ resets and states

    def reset_simulation(self, start: float | Duration | Time = 0) -> TimeJump | None:
        """``p.resetSimulation`` on every client, and move sim time to ``start`` (default 0).

        The world is emptied (bodies, constraints, gravity; PyBullet keeps the time step).
        Moving time is a jump (docs/architecture.md, "Time jumps"): jump handlers run, pending
        ``clock.sleep`` calls and :meth:`wait_until` waits raise :class:`ClockJumpedError`, rates
        and timers re-anchor. Returns the jump, or None when time did not move.
        """
        self._check_not_advancing("reset_simulation()")
        new_ns = to_sim_time_ns(start, "reset_simulation() start")
        pb = self._p
        for cid in self._clients:
            try:
                pb.resetSimulation(physicsClientId=cid)
            except pb.error as exc:
                raise self._failure(exc, "resetSimulation") from exc
        jump = self._move_time(new_ns, 0)
        self._sync_time_step()
        return jump

    def _save_engine_state(self) -> tuple[int, ...]:
        pb = self._p
        ids: list[int] = []
        for cid in self._clients:
            try:
                ids.append(pb.saveState(physicsClientId=cid))
            except pb.error as exc:
                raise self._failure(exc, "saveState") from exc
        return tuple(ids)

    def _restore_engine_state(self, state: tuple[int, ...], state_id: int) -> None:
        pb = self._p
        for cid, bullet_id in zip(self._clients, state, strict=True):
            try:
                pb.restoreState(stateId=bullet_id, physicsClientId=cid)
            except pb.error as exc:
                if not pb.isConnected(cid):
                    raise self._failure(exc, "restoreState") from exc
                raise PhysicsError(
                    f"PyBullet could not restore state {state_id} on client {cid}: a "
                    "snapshot only restores into the world it was taken from (same bodies, and "
                    "not after reset_simulation())"
                ) from exc

    def _remove_engine_state(self, state: tuple[int, ...]) -> None:
        pb = self._p
        for cid, bullet_id in zip(self._clients, state, strict=True):
            if pb.isConnected(cid):
                pb.removeState(bullet_id, physicsClientId=cid)

    def save_state(self) -> int:
        """Snapshot every client (``p.saveState``) with the current sim time; return its id.

        :meth:`restore_state` brings the physics and the clock back to it. Snapshots live in
        memory until :meth:`remove_state` (PyBullet drops them on reset).
        """
        return super().save_state()

    def restore_state(self, state_id: int) -> TimeJump | None:
        """Restore a :meth:`save_state` snapshot (``p.restoreState``) and its sim time.

        Time moves back (or forward) to the saved time as a jump, like
        :meth:`reset_simulation`; returns the jump, or None when the saved time is the
        current one (then no wait is interrupted). The time step is not part of a snapshot:
        the current one goes on.
        """
        jump = super().restore_state(state_id)
        self._sync_time_step()
        return jump

    # --------------------------------------------------------------- the rest

    def describe(self) -> str:
        """The source for messages: its time step and PyBullet client ids."""
        clients = ", ".join(str(c) for c in self._clients)
        plural = "s" if len(self._clients) > 1 else ""
        dt = format_seconds(Fraction(self._num, self._den) / _NS_PER_S)
        return f"PyBullet physics (client{plural} {clients}, dt={dt} s)"

    def close(self) -> None:
        """Disconnect the clients this source created (:meth:`connect`); others stay as they are."""
        if self._closed:
            return
        self._closed = True
        if self._owns_clients:
            pb = self._p
            for cid in self._clients:
                if pb.isConnected(cid):
                    pb.disconnect(cid)

    def __repr__(self) -> str:
        return f"<PyBulletTimeSource {self.describe()} now={new_time(self._now, SIM)}>"
