"""Optional dependencies: import one, or fail with an error naming the extra that installs it."""

from __future__ import annotations

import importlib
from types import ModuleType

from evclock._errors import MissingExtraError

#: The extra that installs each optional top-level module evclock or its scenarios import.
EXTRA_OF_MODULE = {
    "pybullet": "pybullet",
    "pybullet_data": "pybullet",
    "mujoco": "mujoco",
    "starlette": "dashboard",
    "uvicorn": "dashboard",
    "PIL": "dashboard",
    "mcap": "record",
    "matplotlib": "plot",
    "ray": "ray",
    "zenoh": "ros2",
    "xxhash": "ros2",
    "cyclonedds": "ros2",
    "rosbags": "ros2",
    "gymnasium": "gym",
}


def missing_extra(module: str, extra: str, *, needed_by: str) -> MissingExtraError:
    """The error saying ``needed_by`` needs ``module``, which ``evclock[extra]`` installs."""
    error = MissingExtraError(
        f"{needed_by} needs {module!r}, which is not installed; install it with: "
        f"pip install 'evclock[{extra}]'",
        name=module,
    )
    error.extra = extra
    return error


def import_extra(module: str, extra: str, *, needed_by: str) -> ModuleType:
    """Import ``module``, which the ``evclock[extra]`` extra installs.

    :raises MissingExtraError: ``module`` is not installed; the message says what needed it and
        the command that installs it. Any other import failure (a broken installation) propagates
        unchanged.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module.partition(".")[0]:
            raise  # the package is there but something it imports is not: not ours to explain
        raise missing_extra(module, extra, needed_by=needed_by) from exc


def extra_for(exc: ModuleNotFoundError, *, needed_by: str) -> MissingExtraError | None:
    """``exc`` (raised while importing user code) as a :class:`MissingExtraError` when the
    missing module is one an evclock extra installs (``pybullet``), else ``None``."""
    top = (exc.name or "").partition(".")[0]
    extra = EXTRA_OF_MODULE.get(top)
    return None if extra is None else missing_extra(top, extra, needed_by=needed_by)
