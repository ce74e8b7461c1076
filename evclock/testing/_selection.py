"""Which tests evclock takes on (the marker, a loop fixture, pytest-asyncio's factory
selection) and which plugin runs each of them: pytest-asyncio, anyio or evclock itself."""

from __future__ import annotations

import inspect
import sys
from typing import Any, Final, Literal

import pytest

from evclock.testing._options import MARKER

EVCLOCK_LOOP_FACTORY_NAME: Final = "evclock"
"""The name under which evclock's loop factory is offered to pytest-asyncio:
``@pytest.mark.asyncio(loop_factories=["evclock"])``."""

#: Fixtures whose use opts a test in, like the marker (a module whose ``anyio_backend`` is
#: evclock's opts in all its anyio tests).
_LOOP_FIXTURES: Final = frozenset(
    {"evclock_loop", "evclock_clock", "evclock_pybullet", "evclock_anyio_backend"}
)

Kind = Literal["evclock", "asyncio", "anyio"]


def asyncio_selection(item: pytest.Item) -> tuple[str, ...] | None:
    """The factory names ``@pytest.mark.asyncio(loop_factories=...)`` selects, if any."""
    mark = item.get_closest_marker("asyncio")
    if mark is None:
        return None
    names = mark.kwargs.get("loop_factories")
    if names is None or isinstance(names, str):
        return None
    return tuple(str(name) for name in names)


def asyncio_loop_scope(item: pytest.Item) -> str:
    """The scope of the loop pytest-asyncio runs a test on, from its public configuration: the
    closest asyncio marker's ``loop_scope``, else ``asyncio_default_test_loop_scope``, else
    ``function``."""
    mark = item.get_closest_marker("asyncio")
    scope = mark.kwargs.get("loop_scope") or mark.kwargs.get("scope") if mark else None
    if scope is None:
        try:
            scope = item.config.getini("asyncio_default_test_loop_scope") or None
        except ValueError:  # pytest-asyncio is not installed
            scope = None
    return str(scope or "function")


def wants_evclock(item: pytest.Item) -> bool:
    """Whether a test opted in: the marker, a loop fixture, or pytest-asyncio's selection."""
    if not isinstance(item, pytest.Function):
        return False
    if item.get_closest_marker(MARKER) is not None:
        return True
    if not _LOOP_FIXTURES.isdisjoint(item.fixturenames):
        return True
    return EVCLOCK_LOOP_FACTORY_NAME in (asyncio_selection(item) or ())


def locate_test_function(item: pytest.Function) -> tuple[Any, str]:
    """Where the test's coroutine function lives: (holder, attribute name)."""
    obj = item.obj
    hypothesis = getattr(obj, "hypothesis", None)
    if hypothesis is not None and inspect.iscoroutinefunction(
        getattr(hypothesis, "inner_test", None)
    ):
        return hypothesis, "inner_test"
    return item, "obj"


def is_async(item: pytest.Function) -> bool:
    holder, name = locate_test_function(item)
    return inspect.iscoroutinefunction(getattr(holder, name))


def kind_of(item: pytest.Function) -> Kind:
    """Which plugin runs the test: pytest-asyncio, anyio, or evclock's own runner."""
    if "pytest_asyncio" in sys.modules:
        from pytest_asyncio import is_async_test

        if is_async_test(item):
            return "asyncio"
    if "anyio_backend" in item.fixturenames and is_async(item):
        return "anyio"
    return "evclock"
