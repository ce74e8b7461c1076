"""Optional dependencies: import one, or fail with an error naming the extra that installs it."""

from __future__ import annotations

import importlib
from types import ModuleType

from ._errors import MissingExtraError


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
        raise MissingExtraError(
            f"{needed_by} needs {module!r}, which is not installed; install it with: "
            f"pip install 'evclock[{extra}]'",
            name=module,
        ) from exc
