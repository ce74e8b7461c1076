"""MuJoCo across processes: scenario controllers in one process, the ``MjData`` in another.

A MuJoCo scenario's controllers read and write the simulation's ``mujoco.MjData`` through
``world.data`` (``data.qpos[joints]``, ``data.ctrl[:] = targets``). In the controller process
of a split run that is a :class:`RemoteMjData`: a read of a field is a call answered by the
simulation at once, at the current sim time (the whole field); a write into a field is
published on the ordered data channel and applied when the lockstep round closes, before
physics advances - exactly where an in-process controller's write lands. The controller
process keeps its own copy of the model (built from the same description) for what it
computes itself: kinematics and dynamics on a scratch ``MjData``.

What is served (:data:`READS`, :data:`WRITES`), as JSON whose floats round-trip exactly, so a
split run computes bit for bit what an in-process run computes:

* a read, service :data:`SERVICE`: ``["qpos", "qvel"]`` (the names of one or more readable
  fields) is answered with ``[[...], [...]]``, each field's values as nested lists in the
  shape ``MjData`` gives it (``xpos``: one ``[x, y, z]`` per body);
* a write, topic :data:`TOPIC`: ``["ctrl", [0, 1], [0.5, -0.2]]`` (a writable field, flat
  row-major indices into it, one value per index) sets ``ctrl[0] = 0.5; ctrl[1] = -0.2``.

Every request is checked in the simulation process before it touches MuJoCo: field names
from the lists above only, indices that are integers within the field's size (the model's),
each at most once, as many values as indices, finite numbers only. A request that fails is
answered with an error to the participant that sent it (:class:`~evclock.RemoteCallError`
for a read, an ERROR frame for a write); the simulation goes on. A participant cannot load a
model, step, reset, or change the model or the state (positions, velocities) directly.
"""

from __future__ import annotations

import json
import math
from typing import Any, Final

import numpy as np

from evclock._errors import InvalidArgumentError, InvalidTypeError, ProtocolError
from evclock.remote._checks import (
    all_finite_numbers,
    decode_request,
    is_finite_number,
    is_int,
    shown,
    shown_name,
)

SERVICE: Final = "mujoco"  # reads: request/reply
TOPIC: Final = "mujoco"  # writes: ordered, applied at the end of the round

#: The ``MjData`` fields a controller in another process may read.
READS: Final = (
    "act",
    "actuator_force",
    "ctrl",
    "qacc",
    "qfrc_actuator",
    "qfrc_applied",
    "qfrc_bias",
    "qpos",
    "qvel",
    "sensordata",
    "xfrc_applied",
    "xpos",
    "xquat",
)
#: The ``MjData`` fields it may write: the actuators' controls and applied forces.
WRITES: Final = ("ctrl", "qfrc_applied", "xfrc_applied")


def _bad(field: object, reason: str) -> InvalidArgumentError:
    return InvalidArgumentError(f"mujoco.{field}: {reason}")


def _field_name(name: object, allowed: tuple[str, ...], kind: str) -> str:
    if not isinstance(name, str):
        raise InvalidArgumentError(f"a mujoco {kind} names a field by a string, got {shown(name)}")
    if name not in allowed:
        raise _unserved(name, kind)
    return name


def _unserved(name: str, kind: str) -> InvalidArgumentError:
    allowed, label = (READS, "readable") if kind == "read" else (WRITES, "writable")
    if kind == "write" and name in READS:
        reason = "is read-only to controllers in another process"
    else:
        reason = "is not served to controllers in another process"
    return InvalidArgumentError(
        f"mujoco.{shown_name(name)} {reason} ({label}: {', '.join(allowed)})"
    )


class MjDataService:
    """Serves a ``mujoco.MjData`` to remote controllers (install it on a ClockServer).

    Every request is validated before it touches MuJoCo (see the module docstring).

    :param data: the ``MjData`` the simulation steps.
    """

    def __init__(self, data: Any) -> None:
        self._data = data

    def install(self, server: Any) -> None:
        """Answer reads and apply writes on ``server`` (a
        :class:`~evclock.remote.ClockServer`)."""
        server.provide(SERVICE, self.answer)
        server.subscribe(TOPIC, self.apply)

    def answer(self, data: bytes) -> bytes:
        """Answer a read request (validated first).

        :param data: the request: the names of the fields to read, a JSON list.
        :returns: their values, a JSON list (one nested list per field, in request order).
        :raises InvalidArgumentError: a field is not served, or the list is empty or too long.
        :raises ProtocolError: the request is not JSON.
        """
        names = decode_request(data, "a mujoco request")
        if not isinstance(names, list) or not names:
            raise InvalidArgumentError(
                f"a mujoco read is a list of field names (readable: {', '.join(READS)})"
            )
        if len(names) > len(READS):
            raise InvalidArgumentError(
                f"a mujoco read names at most {len(READS)} fields, got {len(names)}"
            )
        fields = [_field_name(name, READS, "read") for name in names]
        values = [getattr(self._data, field).tolist() for field in fields]
        return json.dumps(values, allow_nan=True).encode()

    def apply(self, message: Any) -> None:
        """Apply a write (validated first; an invalid one raises and is not applied).

        :param message: the :class:`~evclock.remote.Message` carrying the write.
        :raises InvalidArgumentError: the field is not writable, or an index or a value is
            invalid.
        :raises ProtocolError: the request is not ``[field, indices, values]`` JSON.
        """
        request = decode_request(message.data, "a mujoco request")
        if not isinstance(request, list) or len(request) != 3:
            raise ProtocolError("a mujoco write is not [field, indices, values] JSON")
        name, indices, values = request
        field = _field_name(name, WRITES, "write")
        target = getattr(self._data, field)
        size = int(target.size)
        if not isinstance(indices, list) or not isinstance(values, list):
            raise _bad(field, "indices and values must be lists")
        if len(indices) > size:
            raise _bad(field, f"{len(indices)} indices for a field of {size} values")
        if len(values) != len(indices):
            raise _bad(field, f"{len(indices)} indices but {len(values)} values")
        seen: set[int] = set()
        for index in indices:
            if not is_int(index):
                raise _bad(field, f"an index must be an integer, got {shown(index)}")
            if not 0 <= index < size:
                raise _bad(
                    field,
                    f"index {shown(index)} is out of range: the model's {field} has {size} values "
                    f"(valid: 0 to {size - 1})",
                )
            if index in seen:
                raise _bad(field, f"index {index} is given twice")
            seen.add(index)
        if not all_finite_numbers(values):
            bad = next(value for value in values if not is_finite_number(value))
            raise _bad(field, f"values must be finite numbers, got {shown(bad)}")
        np.put(target, indices, values)  # in place, flat (row-major) indices


class RemoteField:
    """One served ``MjData`` field, seen from a controller process: index it to read
    (``data.qpos[joints]``: a fresh copy, read at the current sim time), assign into it to
    write (``data.ctrl[:] = targets``: applied when the round closes).

    :param owner: the :class:`RemoteMjData` it belongs to.
    :param name: the field's name.
    :param shape: the field's shape in the model.
    """

    def __init__(self, owner: RemoteMjData, name: str, shape: tuple[int, ...]) -> None:
        self._owner = owner
        self.name = name
        """The field's name (``"qpos"``...)."""
        self.shape = shape
        """The field's shape in the model."""

    @property
    def size(self) -> int:
        """How many values the field holds."""
        return int(math.prod(self.shape))

    def read(self) -> np.ndarray:
        """The whole field, read in the simulation at the current sim time (a copy)."""
        (array,) = self._owner.read(self.name)
        return array

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        array = self.read()
        return array if dtype is None else array.astype(dtype)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: Any) -> Any:
        return self.read()[key]

    def __setitem__(self, key: Any, value: Any) -> None:
        indices = np.arange(self.size).reshape(self.shape)[key]
        values = np.broadcast_to(np.asarray(value, dtype=np.float64), np.shape(indices))
        self._owner.write(self.name, np.ravel(indices).tolist(), np.ravel(values).tolist())

    def tolist(self) -> Any:
        """The field's values as (nested) Python lists."""
        return self.read().tolist()

    def copy(self) -> np.ndarray:
        """The field's values (a numpy array)."""
        return self.read()

    def __repr__(self) -> str:
        return f"<remote MjData field {self.name} {self.shape}>"


class RemoteMjData:
    """Stands in for a scenario's ``mujoco.MjData`` in a controller process
    (``world.data`` in ``evclock control``): its served fields (:data:`READS`) are
    :class:`RemoteField` objects that read from and write to the simulation's.

    :param participant: the process's :class:`~evclock.remote.RemoteClockSource` (see
        :func:`evclock.remote.participant`).
    :param local: an ``MjData`` of this process's copy of the model (it gives the fields'
        shapes; it is never read otherwise).
    """

    def __init__(self, participant: Any, local: Any) -> None:
        shapes = {name: tuple(getattr(local, name).shape) for name in READS}
        object.__setattr__(self, "_participant", participant)
        object.__setattr__(self, "_shapes", shapes)

    def __getattr__(self, name: str) -> Any:
        shapes: dict[str, tuple[int, ...]] = object.__getattribute__(self, "_shapes")
        if name in shapes:
            return RemoteField(self, name, shapes[name])
        raise AttributeError(
            f"MjData.{name} is not available to controllers in another process; they may "
            f"read {', '.join(READS)} and write {', '.join(WRITES)}"
        )

    def __setattr__(self, name: str, value: Any) -> None:
        raise InvalidArgumentError(
            f"MjData.{name} cannot be replaced from another process: assign into a writable "
            f"field instead (data.ctrl[:] = values; writable: {', '.join(WRITES)})"
        )

    def read(self, *names: str) -> list[np.ndarray]:
        """Read several fields in one call, at the current sim time.

        :param names: served field names (:data:`READS`).
        :returns: one array per name, in that order, shaped as in the model.
        :raises RemoteCallError: the simulation refused the request.
        :raises InvalidArgumentError: the simulation's field has another size than this
            process's model gives it (the two do not run the same model).
        """
        reply = json.loads(self._participant.call(SERVICE, json.dumps(list(names)).encode()))
        arrays = []
        for name, values in zip(names, reply, strict=True):
            array = np.array(values, dtype=np.float64)
            shape = self._shapes[name]
            if array.shape != shape:
                raise InvalidArgumentError(
                    f"the simulation's MjData.{name} has shape {array.shape}, this process's "
                    f"model gives it {shape}: the controllers and the simulation must build "
                    "the same model"
                )
            arrays.append(array)
        return arrays

    def write(self, name: str, indices: list[int], values: list[float]) -> None:
        """Set ``name``'s values at flat (row-major) ``indices`` to ``values`` when the
        lockstep round closes, before physics advances.

        :param name: a writable field (:data:`WRITES`).
        :param indices: flat indices into the field.
        :param values: one number per index.
        :raises InvalidArgumentError: the field is not writable.
        :raises InvalidTypeError: a value cannot be sent (not a number).
        """
        if name not in WRITES:
            raise _unserved(name, "write")
        try:
            request = json.dumps([name, indices, values])
        except TypeError as exc:
            raise InvalidTypeError(f"mujoco.{name}: values must be numbers ({exc})") from None
        self._participant.publish(TOPIC, request.encode())
