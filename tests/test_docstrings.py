"""Every public function and class documents its parameters, and every function what it returns.

Public names are those in ``__all__`` of the documented modules. Exception classes and enums
are left out (their signatures are inherited). A class counts as documented by its class
docstring plus its own ``__init__``'s (the API pages merge the two).
"""

from __future__ import annotations

import enum
import importlib
import inspect
import re
from collections.abc import Callable, Iterator
from typing import Any

import pytest

MODULES = [
    "evclock",
    "evclock.sources",
    "evclock.remote",
    "evclock.data",
    "evclock.tools",
    "evclock.ros2",
    "evclock.time",
    "evclock.gym",
]

RETURNS = re.compile(r":returns?:|\bReturns:|\breturns?\b", re.IGNORECASE)


def _public() -> Iterator[tuple[str, Any]]:
    seen: set[int] = set()
    for module_name in MODULES:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if id(obj) in seen:
                continue  # evclock.time re-exports evclock's names
            if inspect.isclass(obj):
                if issubclass(obj, BaseException | enum.Enum):
                    continue
            elif not inspect.isfunction(obj):
                continue  # constants, aliases
            seen.add(id(obj))
            yield f"{module_name}.{name}", obj


PUBLIC = dict(_public())
FUNCTIONS = {name: obj for name, obj in PUBLIC.items() if inspect.isfunction(obj)}


def _docstring(obj: Any) -> str:
    doc = inspect.getdoc(obj) or ""
    init = vars(obj).get("__init__") if inspect.isclass(obj) else None
    if init is not None and init.__doc__:
        doc += "\n" + inspect.cleandoc(init.__doc__)
    return doc


def _parameters(obj: Callable[..., Any]) -> list[str]:
    skipped = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    return [
        p.name
        for p in inspect.signature(obj).parameters.values()
        if p.name != "self" and p.kind not in skipped
    ]


def test_the_check_covers_the_public_api() -> None:
    assert {"evclock.run", "evclock.SimClock", "evclock.tools.sweep"} <= PUBLIC.keys()
    assert "evclock.ClockType" not in PUBLIC  # an Enum
    assert "evclock.EvClockError" not in PUBLIC  # an exception


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_every_parameter_is_documented(name: str) -> None:
    obj = PUBLIC[name]
    doc = _docstring(obj)
    missing = [p for p in _parameters(obj) if not re.search(rf"\b{re.escape(p)}\b", doc)]
    assert not missing, f"{name}: the docstring does not mention {', '.join(missing)}"


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_every_return_value_is_documented(name: str) -> None:
    function = FUNCTIONS[name]
    returns = inspect.signature(function).return_annotation
    if returns in (None, "None", inspect.Signature.empty):
        return
    assert RETURNS.search(_docstring(function)), (
        f"{name}: the docstring does not say what it returns"
    )
