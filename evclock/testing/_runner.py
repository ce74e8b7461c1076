"""evclock's own runner, for the opted-in ``async def`` tests no other plugin runs: one loop per
test, on which its async fixtures (made sync here) run too."""

from __future__ import annotations

import asyncio
import contextvars
import functools
import inspect
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, Final, TypeVar

import pytest

from evclock._errors import PluginUsageError

_T = TypeVar("_T")

#: The (private) fixture that gives a test evclock's runner.
RUNNER_FIXTURE: Final = "_evclock_runner"
_PYBULLET_FIXTURE: Final = "evclock_pybullet"


class Runner:
    """evclock's own runner for a test: one loop and one context for the test and its async
    fixtures (context variables set by a fixture are seen by the test)."""

    def __init__(self, factory: Callable[[], asyncio.AbstractEventLoop]) -> None:
        self._runner = asyncio.Runner(loop_factory=factory)
        self.loop = self._runner.get_loop()
        self._context = contextvars.copy_context()

    def run(self, coro: Coroutine[Any, Any, _T]) -> _T:
        return self._runner.run(coro, context=self._context)

    def close(self) -> None:
        self._runner.close()


def ensure_pybullet_first(request: pytest.FixtureRequest) -> None:
    """The PyBullet world must exist before the loop that steps it."""
    if _PYBULLET_FIXTURE in request.fixturenames and request.fixturename != _PYBULLET_FIXTURE:
        request.getfixturevalue(_PYBULLET_FIXTURE)


def wrap_async_fixture(
    func: Callable[..., Any], request: pytest.FixtureRequest
) -> Callable[..., Any]:
    """Make an async fixture a sync one that runs on the test's evclock runner."""
    instance = request.instance
    if instance is not None and inspect.ismethod(func) and type(func.__self__) is type(instance):
        func = func.__func__.__get__(instance)

    def runner() -> Runner:
        value: Runner = request.getfixturevalue(RUNNER_FIXTURE)
        return value

    if inspect.isasyncgenfunction(func):

        @functools.wraps(func, updated=())
        def evclock_asyncgen_fixture(**kwargs: Any) -> Iterator[Any]:
            run = runner().run
            agen = func(**kwargs)
            value = run(agen.__anext__())
            yield value
            run(_finish_asyncgen(agen, request.fixturename))

        return evclock_asyncgen_fixture

    @functools.wraps(func, updated=())
    def evclock_async_fixture(**kwargs: Any) -> Any:
        return runner().run(func(**kwargs))

    return evclock_async_fixture


async def _finish_asyncgen(agen: Any, name: str | None) -> None:
    try:
        await agen.__anext__()
    except StopAsyncIteration:
        return
    await agen.aclose()
    raise PluginUsageError(
        f"async generator fixture {name!r} yielded more than once; an async fixture yields "
        "exactly one value"
    )
