"""MuJoCo as the owner of simulation time: a thin adapter over :class:`SteppingTimeSource`.

MuJoCo keeps its own time (``MjData.time``), but as a float that accumulates rounding: evclock
never reads it. Sim time is the integer step count times the model's time step as an exact
fraction of nanoseconds (docs/architecture.md, "Time and the step clock"), exactly as for
PyBullet; the step clock, hooks, waits and snapshots-as-jumps live in ``_stepping.py``.
``mujoco`` is imported lazily, when the first source is created: ``import evclock`` alone does
not load it (nor numpy).
"""

from __future__ import annotations

import math
import os
from fractions import Fraction
from typing import TYPE_CHECKING, Any

from evclock._errors import InvalidArgumentError, InvalidTypeError, PhysicsError
from evclock._extras import import_extra
from evclock.sources._stepping import SteppingTimeSource, format_seconds
from evclock.time._time import SIM, Duration, Time, new_time, to_sim_time_ns

if TYPE_CHECKING:
    from evclock.kernel._jumps import TimeJump

_NS_PER_S = 1_000_000_000

#: MuJoCo's warnings that mean the state is no longer valid (NaN, inf or a huge value): each
#: is raised as a PhysicsError naming the step. (The others - contact or constraint buffers
#: full, a bad inertia - leave a valid state and are MuJoCo's to report.)
_BAD_STATE_WARNINGS = ("mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC", "mjWARN_BADCTRL")
_WHAT_WENT_BAD = {
    "mjWARN_BADQPOS": "a NaN, infinite or huge joint position (qpos) at DOF {}",
    "mjWARN_BADQVEL": "a NaN, infinite or huge joint velocity (qvel) at DOF {}",
    "mjWARN_BADQACC": "a NaN, infinite or huge acceleration (qacc) at DOF {}",
    "mjWARN_BADCTRL": "a NaN, infinite or huge control (ctrl) at actuator {}",
}


def _mujoco() -> Any:
    return import_extra("mujoco", "mujoco", needed_by="MuJoCoTimeSource")


class MuJoCoTimeSource(SteppingTimeSource[Any]):
    """Sim time driven by a MuJoCo model and its data, in whole ``mj_step`` steps.

    ``MuJoCoTimeSource(model, data)`` steps an ``MjModel`` and its ``MjData`` (created with
    ``MjData(model)`` when not given); :meth:`load` loads a model file (MJCF or URDF). Run a
    program on it with ``evclock.run(main(), source=source)``. A run of steps with nothing due
    in between is one ``mj_step(model, data, nstep)`` call; with step hooks or
    :meth:`wait_until` waiters, one step at a time.

    **Time.** Sim time is ``start_ns + floor(steps x dt_ns)``, where ``dt_ns`` is the model's
    ``opt.timestep`` as an exact fraction of nanoseconds (see :func:`exact_time_step`:
    ``1/240`` s is exactly ``12500000/3`` ns) and ``steps`` an integer: 24 simulated hours
    never drift by a nanosecond. ``data.time`` is MuJoCo's float sum of the steps and is never
    read.

    **Time step.** Change it with :meth:`set_time_step`. With ``watch_time_step=True``
    (default), a change made directly (``model.opt.timestep = ...``) is detected before each
    advance of the loop and time re-bases at the current step boundary, as for PyBullet.

    **Bad states.** MuJoCo warns (``mjWARN_BADQACC``, ``mjWARN_BADQPOS``, ``mjWARN_BADQVEL``,
    ``mjWARN_BADCTRL``) when the state becomes NaN, infinite or huge, and resets the data. The
    source checks the warning counters after each run of steps and raises
    :class:`~evclock.PhysicsError` naming the warning, the step and its sim time. The step is
    counted, never inferred from ``data.time`` (which each reset sets back to zero): a run of
    steps in which one failed is taken again from its start one step at a time, up to the
    first failing step, so a run with or without step hooks names the same step and leaves
    the same data. The source owns the counters of these four warnings: it zeroes them when
    it takes the data over, once it has reported one, and at each reset or restore (MuJoCo's
    counter reads 1 after every failure, so one left at 1 would hide the next).

    **Snapshots** (:meth:`save_state`, :meth:`restore_state`) are ``mj_getState`` /
    ``mj_setState`` of the full integration state, restored as time jumps with the same policy
    as PyBullet's; :meth:`reset_simulation` is ``mj_resetData`` (or a keyframe) and a jump.

    :param model: the ``mujoco.MjModel`` to step.
    :param data: its ``mujoco.MjData`` (default: a new ``MjData(model)``).
    :param time_step: set the model's time step first (float seconds, a ``Fraction`` or a
        :class:`Duration`); default: the model's own ``opt.timestep``.
    :param start_ns: sim time of the current state, in integer nanoseconds (default 0).
    :param watch_time_step: detect time-step changes made directly on the model.
    :raises MissingExtraError: MuJoCo is not installed (``pip install 'evclock[mujoco]'``).
    :raises InvalidTypeError: ``model`` or ``data`` is not a MuJoCo model or data.
    :raises InvalidArgumentError: ``data`` was not made for ``model`` (other sizes), or a bad
        ``start_ns``.
    :raises PhysicsError: the model has no valid time step (zero, negative or not finite).
    """

    def __init__(
        self,
        model: Any,
        data: Any = None,
        *,
        time_step: float | Fraction | Duration | None = None,
        start_ns: int = 0,
        watch_time_step: bool = True,
    ) -> None:
        mj = _mujoco()
        if not isinstance(model, mj.MjModel):
            raise InvalidTypeError(
                f"MuJoCoTimeSource needs a mujoco.MjModel, got {type(model).__name__}; load "
                "one with mujoco.MjModel.from_xml_path(path) or use MuJoCoTimeSource.load(path)"
            )
        if data is None:
            data = mj.MjData(model)
        elif not isinstance(data, mj.MjData):
            raise InvalidTypeError(
                f"MuJoCoTimeSource's data must be a mujoco.MjData, got {type(data).__name__}"
            )
        elif (data.qpos.size, data.qvel.size, data.act.size, data.ctrl.size) != (
            model.nq,
            model.nv,
            model.na,
            model.nu,
        ):
            raise InvalidArgumentError(
                "this MjData was not made for this MjModel (its qpos, qvel, act or ctrl sizes "
                "differ); pass mujoco.MjData(model) of the same model"
            )
        self._mj: Any = mj
        self._model: Any = model
        self._data: Any = data
        self._opt: Any = model.opt
        self._mj_step: Any = mj.mj_step
        self._watch = bool(watch_time_step)
        self._state_kind: int = int(mj.mjtState.mjSTATE_INTEGRATION)
        kinds = mj.mjtWarning
        self._warning_names = _BAD_STATE_WARNINGS
        self._warning_index = tuple(int(getattr(kinds, name)) for name in _BAD_STATE_WARNINGS)
        # A view of MuJoCo's warning counters: comparing its bytes after each run of steps
        # costs a fraction of a microsecond.
        self._warning_numbers: Any = data.warning.number
        self._warnings_seen = b""
        self._clear_bad_state_warnings()
        import numpy  # a dependency of mujoco's, loaded with it

        self._run_start: Any = numpy.empty(mj.mj_stateSize(model, self._state_kind))
        self._closed = False
        if time_step is not None:
            # Validate and set through the shared code path once the clock exists.
            super().__init__(1, start_ns=start_ns)
            self.set_time_step(time_step)
        else:
            super().__init__(self._read_time_step(), start_ns=start_ns)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        *,
        time_step: float | Fraction | Duration | None = None,
        start_ns: int = 0,
        watch_time_step: bool = True,
    ) -> MuJoCoTimeSource:
        """Load a model file (MJCF, or a URDF MuJoCo can read) and drive a new data for it.

        :param path: the model file.
        :param time_step: set the model's time step (default: the file's, MuJoCo's 0.002 s
            when it sets none).
        :param start_ns: sim time of the initial state, in integer nanoseconds.
        :param watch_time_step: detect time-step changes made directly on the model.
        :returns: the source; its :attr:`model` and :attr:`data` are the loaded ones.
        :raises PhysicsError: MuJoCo cannot load the file (the message gives MuJoCo's reason
            and the path), or the model has no valid time step.
        :raises InvalidTypeError: ``path`` is not a path.
        """
        if not isinstance(path, str | os.PathLike):
            raise InvalidTypeError(
                f"MuJoCoTimeSource.load() takes a file path, got {type(path).__name__}"
            )
        mj = _mujoco()
        text = os.fspath(path)
        try:
            model = mj.MjModel.from_xml_path(text)
        except ValueError as exc:
            reason = " ".join(str(exc).split())
            raise PhysicsError(
                f"MuJoCo could not load the model file {text!r}: {reason}; check that the "
                "file exists and is valid MJCF (or URDF), and the paths of its meshes"
            ) from exc
        return cls(model, time_step=time_step, start_ns=start_ns, watch_time_step=watch_time_step)

    # ------------------------------------------------------------ the engine

    @property
    def model(self) -> Any:
        """The ``mujoco.MjModel`` this source steps."""
        return self._model

    @property
    def data(self) -> Any:
        """The ``mujoco.MjData`` this source steps."""
        return self._data

    def _step_engine(self, count: int) -> None:
        if count > 1:
            # The state before a run of steps, to find which one failed if one does.
            self._mj.mj_getState(self._model, self._data, self._run_start, self._state_kind)
        self._mj_step(self._model, self._data, count)
        if self._warning_numbers.tobytes() != self._warnings_seen:
            self._check_warnings(count)

    def _check_warnings(self, count: int) -> None:
        """A warning counter changed during the last ``count`` steps: raise the error for a
        bad state (other warnings - contact buffer full, bad inertia - are MuJoCo's to report)."""
        import numpy  # loaded with mujoco

        numbers = self._warning_numbers
        seen = numpy.frombuffer(self._warnings_seen, dtype=numbers.dtype).copy()  # before
        if not self._bad_warning_changed(seen):
            self._warnings_seen = numbers.tobytes()
            return
        offset = 0 if count == 1 else self._replay_to_first_failure(seen, count)
        name = next(
            name
            for name, index in zip(self._warning_names, self._warning_index, strict=True)
            if numbers[index] != seen[index]
        )
        lastinfo = self._data.warning.lastinfo[self._warning_index[self._warning_names.index(name)]]
        self._clear_bad_state_warnings()
        detail = _WHAT_WENT_BAD[name].format(int(lastinfo))
        where = (
            f"in step {self._step_index + 1 + offset} (from sim time "
            f"{self._time_after(offset)} to {self._time_after(offset + 1)})"
        )
        if name == "mjWARN_BADCTRL":
            what = "MuJoCo zeroed the controls; check the controls set before that step"
        else:
            what = (
                "The simulation is unstable and MuJoCo reset its data; lower the time step, add "
                "joint damping or armature, or check the controls and forces applied before "
                "that step"
            )
        raise PhysicsError(f"MuJoCo reported {name} {where}: {detail}. {what}")

    def _clear_bad_state_warnings(self) -> None:
        """Zero MuJoCo's counters of the bad-state warnings, and take the counters as seen.

        MuJoCo resets the data at a bad state and then counts the warning, so its counter
        reads 1 after every failure: a counter that already reads 1 would not change at the
        next one. The source owns these counters from the start, after each failure it
        reports and after each reset or restore, so that every failure changes one.
        """
        numbers = self._warning_numbers
        for index in self._warning_index:
            numbers[index] = 0
        self._warnings_seen = numbers.tobytes()

    def _bad_warning_changed(self, seen: Any) -> bool:
        numbers = self._warning_numbers
        return any(numbers[index] != seen[index] for index in self._warning_index)

    def _replay_to_first_failure(self, seen: Any, count: int) -> int:
        """Which step of a run of ``count`` failed first (0-based), counted exactly: the run
        is taken again from its start state one ``mj_step`` at a time up to that step, which
        leaves the data as stepping one at a time would. (MuJoCo resets the data, ``time``
        included, at each failure, so the state after the run cannot tell.)"""
        mj, model, data = self._mj, self._model, self._data
        mj.mj_setState(model, data, self._run_start, self._state_kind)
        self._warning_numbers[:] = seen
        for offset in range(count):
            self._mj_step(model, data, 1)
            if self._bad_warning_changed(seen):
                return offset
        raise PhysicsError(  # MuJoCo's stepping is deterministic: never expected
            f"MuJoCo reported a bad state in a run of {count} steps, but not when the run was "
            "taken again one step at a time; report this to evclock with the model"
        )

    def _time_after(self, steps: int) -> str:
        """The sim time ``steps`` steps after the current one, for messages (``1.5 s``)."""
        ns = self._base_ns + (self._steps + steps) * self._num // self._den
        seconds, fraction = divmod(ns, _NS_PER_S)
        return f"{seconds}.{fraction:09d}".rstrip("0").rstrip(".") + " s"

    def _set_engine_time_step(self, dt: float) -> float:
        self._opt.timestep = dt
        return self._read_time_step()

    def _before_advance(self) -> None:
        if self._watch and self._opt.timestep != self._dt:
            self._use_time_step(self._read_time_step())

    def _read_time_step(self) -> float:
        dt = float(self._opt.timestep)
        if not (math.isfinite(dt) and dt > 0):
            raise PhysicsError(
                f"the MuJoCo model has opt.timestep={dt!r}, which is not a positive finite "
                'number of seconds; set one in the model (<option timestep="0.002"/>), with '
                "MuJoCoTimeSource(model, time_step=1/240) or source.set_time_step(1/240)"
            )
        return dt

    def _sync_time_step(self) -> None:
        """Resets and snapshots keep the model's time step: go on with the model's."""
        dt = self._read_time_step()
        if dt != self._dt:
            self._use_time_step(dt)

    # ------------------------------------------------------ resets and states

    def reset_simulation(
        self, start: float | Duration | Time = 0, *, keyframe: int | str | None = None
    ) -> TimeJump | None:
        """``mj_resetData`` (or ``mj_resetDataKeyframe``), then move sim time to ``start``.

        The data goes back to the model's defaults (or the keyframe's); the model, and so its
        time step, stays. Moving time is a jump (docs/architecture.md, "Time jumps"): jump
        handlers run, pending ``clock.sleep`` calls and :meth:`wait_until` waits raise
        :class:`~evclock.ClockJumpedError`, rates and timers re-anchor.

        :param start: the sim time of the reset state (seconds or a sim :class:`Time`).
        :param keyframe: reset to this keyframe of the model (index or name) instead.
        :returns: the jump, or None when time did not move.
        :raises PhysicsError: called from a step hook or predicate.
        :raises InvalidArgumentError: an unknown keyframe, or a bad ``start``.
        """
        self._check_not_advancing("reset_simulation()")
        new_ns = to_sim_time_ns(start, "reset_simulation() start")
        mj = self._mj
        model, data = self._model, self._data
        if keyframe is None:
            mj.mj_resetData(model, data)
        else:
            mj.mj_resetDataKeyframe(model, data, self._keyframe_index(keyframe))
        mj.mj_forward(model, data)
        self._clear_bad_state_warnings()
        jump = self._move_time(new_ns, 0)
        self._sync_time_step()
        return jump

    def _keyframe_index(self, keyframe: int | str) -> int:
        model = self._model
        if isinstance(keyframe, str):
            index = int(self._mj.mj_name2id(model, self._mj.mjtObj.mjOBJ_KEY, keyframe))
            if index < 0:
                raise InvalidArgumentError(f"the MuJoCo model has no keyframe named {keyframe!r}")
            return index
        if isinstance(keyframe, bool) or not isinstance(keyframe, int):
            raise InvalidTypeError(
                f"keyframe must be an index or a name, got {type(keyframe).__name__}"
            )
        if not 0 <= keyframe < model.nkey:
            raise InvalidArgumentError(
                f"keyframe index {keyframe} is out of range: the model has {model.nkey}"
            )
        return keyframe

    def _save_engine_state(self) -> Any:
        import numpy  # a dependency of mujoco's, loaded with it

        mj = self._mj
        size = mj.mj_stateSize(self._model, self._state_kind)
        state = numpy.empty(size)
        mj.mj_getState(self._model, self._data, state, self._state_kind)
        return state

    def _restore_engine_state(self, state: Any, state_id: int) -> None:
        mj = self._mj
        mj.mj_setState(self._model, self._data, state, self._state_kind)
        # Positions and velocities are back; recompute what derives from them (body poses,
        # sensors) so that controllers read the restored world before the next step.
        mj.mj_forward(self._model, self._data)
        self._clear_bad_state_warnings()

    def save_state(self) -> int:
        """Snapshot the data (``mj_getState`` of the full integration state) with the
        current sim time; return its id.

        :meth:`restore_state` brings the physics and the clock back to it; snapshots live in
        memory until :meth:`remove_state`.

        :returns: the snapshot's id.
        :raises PhysicsError: called from a step hook or predicate.
        """
        return super().save_state()

    def restore_state(self, state_id: int) -> TimeJump | None:
        """Restore a :meth:`save_state` snapshot (``mj_setState``, then ``mj_forward``) and
        its sim time.

        Time moves back (or forward) to the saved time as a jump, like
        :meth:`reset_simulation` and PyBullet's restore. The time step belongs to the model,
        not to a snapshot: the current one goes on.

        :param state_id: an id returned by :meth:`save_state`.
        :returns: the jump, or None when the saved time is the current one (then no wait is
            interrupted).
        :raises InvalidArgumentError: an unknown id.
        :raises PhysicsError: called from a step hook or predicate.
        """
        jump = super().restore_state(state_id)
        self._sync_time_step()
        return jump

    # --------------------------------------------------------------- the rest

    def describe(self) -> str:
        """The source for messages: its model's name and time step.

        :returns: e.g. ``MuJoCo physics (model 'lbr_iiwa', dt=1/240 s)``.
        """
        name = bytes(self._model.names).split(b"\0", 1)[0].decode(errors="replace") or "unnamed"
        dt = format_seconds(Fraction(self._num, self._den) / _NS_PER_S)
        return f"MuJoCo physics (model {name!r}, dt={dt} s)"

    def close(self) -> None:
        """Nothing to release: the model and data are garbage-collected with the source."""
        self._closed = True

    def __repr__(self) -> str:
        return f"<MuJoCoTimeSource {self.describe()} now={new_time(self._now, SIM)}>"
