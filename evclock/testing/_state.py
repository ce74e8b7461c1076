"""What the plugin knows: one :class:`Session` per pytest run, which also makes the loops the
tests run on, and one :class:`ItemState` per opted-in test."""

from __future__ import annotations

import asyncio
import itertools
import weakref
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import pytest

from evclock._errors import PluginUsageError
from evclock.hosts._current import attach_clock
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._clock import WallClock
from evclock.sources import TimeSource, VirtualTimeSource
from evclock.testing._options import Options, config_options
from evclock.testing._selection import (
    EVCLOCK_LOOP_FACTORY_NAME,
    Kind,
    asyncio_loop_scope,
    asyncio_selection,
    is_async,
    wants_evclock,
)

if TYPE_CHECKING:
    from evclock.testing._budget import Budget
    from evclock.testing._guard import CallGuard


class ItemState:
    """What evclock knows about one opted-in test."""

    def __init__(self, item: pytest.Function, options: Options, kind: Kind) -> None:
        self.item = item
        self.options = options
        self.kind = kind
        self.is_async = is_async(item)
        self.loops: list[asyncio.AbstractEventLoop] = []
        #: A loop made before pytest-asyncio asked for it (the evclock_loop fixture was set up
        #: first): evclock's factory hands this one out at pytest-asyncio's request.
        self.early_loop: asyncio.AbstractEventLoop | None = None
        self.pybullet_source: TimeSource | None = None
        self.source_adopted = False
        self.budget: Budget | None = None
        self.call: CallGuard | None = None
        # An explicit multi-factory selection may deliberately run variants on other loops.
        self.expect_sim = not options.wall and asyncio_selection(item) in (
            None,
            (EVCLOCK_LOOP_FACTORY_NAME,),
        )


ITEM_STATE = pytest.StashKey[ItemState]()


def state_of(item: pytest.Item) -> ItemState | None:
    return item.stash.get(ITEM_STATE, None)


class Session:
    """Plugin state for one pytest run (one ``Config``)."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.defaults = config_options(config)
        self.current_item: pytest.Item | None = None
        self.asyncio_hooked = False
        #: Every loop evclock's factory made, in order (the budgets look for the one running).
        self._loops: weakref.WeakValueDictionary[int, asyncio.AbstractEventLoop] = (
            weakref.WeakValueDictionary()
        )
        self._loop_numbers = itertools.count()
        #: pytest-asyncio's loops shared by several tests (loop_scope wider than function),
        #: by (scope, node id of the scope's node).
        self._shared_loops: dict[tuple[str, str], asyncio.AbstractEventLoop] = {}
        # One stable object: pytest-asyncio parametrizes with it and anyio receives it.
        self.loop_factory: Callable[[], asyncio.AbstractEventLoop] = self._new_loop

    def open_loops(self) -> list[asyncio.AbstractEventLoop]:
        """The loops evclock made that are not closed, oldest first."""
        return [loop for _, loop in sorted(self._loops.items()) if not loop.is_closed()]

    def _new_loop(self) -> asyncio.AbstractEventLoop:
        """The factory: the loop of the test being run, with its marker's options."""
        item = self.current_item
        state = state_of(item) if item is not None else None
        if state is not None and state.early_loop is not None:
            loop, state.early_loop = state.early_loop, None
        else:
            loop = self._make_loop(state)
        if state is not None and state.kind == "asyncio":
            key = _shared_key(state.item)
            if key[0] != "function":
                for old in [k for k, v in self._shared_loops.items() if v.is_closed()]:
                    del self._shared_loops[old]
                self._shared_loops[key] = loop
        return loop

    def asyncio_test_loop(self, state: ItemState) -> asyncio.AbstractEventLoop:
        """The loop pytest-asyncio runs ``state``'s test on, made now if it does not exist yet:
        evclock's factory will then hand this one out when pytest-asyncio asks for it."""
        if not _uses_evclock_factory(state.item, self.loop_factory):
            raise PluginUsageError(
                f"{state.item.nodeid}: this variant runs on another loop factory's loop; "
                "evclock's fixtures need evclock's (select only 'evclock' in loop_factories)"
            )
        if state.early_loop is not None:
            return state.early_loop
        if asyncio_loop_scope(state.item) == "function":
            if state.loops:
                return state.loops[-1]
        else:
            shared = self._shared_loops.get(_shared_key(state.item))
            if shared is not None and not shared.is_closed():
                return shared
        state.early_loop = self._make_loop(state)
        return state.early_loop

    def _make_loop(self, state: ItemState | None) -> asyncio.AbstractEventLoop:
        options = state.options if state is not None else self.defaults
        loop: asyncio.AbstractEventLoop
        if options.wall:
            loop = asyncio.new_event_loop()
            attach_clock(loop, WallClock())
        else:
            source: TimeSource
            if state is not None and state.pybullet_source is not None and not state.source_adopted:
                source = state.pybullet_source
                state.source_adopted = True
            else:
                source = VirtualTimeSource(options.start_ns)
            loop = SimEventLoop(source, rtf=options.rtf, stall_timeout=options.stall_timeout)
        if state is not None:
            state.loops.append(loop)
        self._loops[next(self._loop_numbers)] = loop
        return loop

    def asyncio_factories(
        self,
        item: pytest.Item,
        result: Mapping[str, Callable[[], asyncio.AbstractEventLoop]] | None,
    ) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
        """Answer ``pytest_asyncio_loop_factories`` for ``item`` given other plugins' answer."""
        if not wants_evclock(item):
            # Leave other tests alone: someone else's answer, else asyncio's default loop.
            return result if result is not None else {"asyncio": asyncio.new_event_loop}
        selected = asyncio_selection(item)
        if selected is None:
            return {EVCLOCK_LOOP_FACTORY_NAME: self.loop_factory}
        if EVCLOCK_LOOP_FACTORY_NAME not in selected:
            pytest.fail(
                f"{item.nodeid}: the test uses evclock but "
                f"@pytest.mark.asyncio(loop_factories={list(selected)!r}) does not select "
                f"{EVCLOCK_LOOP_FACTORY_NAME!r}; add it to the list",
                pytrace=False,
            )
        return {**(result or {}), EVCLOCK_LOOP_FACTORY_NAME: self.loop_factory}


def _shared_key(item: pytest.Function) -> tuple[str, str]:
    """Which pytest-asyncio loop a test shares: its loop scope and the node of that scope."""
    scope = asyncio_loop_scope(item)
    node_type: Any = {
        "function": pytest.Function,
        "class": pytest.Class,
        "module": pytest.Module,
        "package": pytest.Package,
        "session": pytest.Session,
    }[scope]
    node = item.getparent(node_type) or item.session
    return scope, node.nodeid


def _uses_evclock_factory(item: pytest.Function, factory: object) -> bool:
    """Whether pytest-asyncio runs this test (variant) with evclock's loop factory: true unless
    it is parametrized over factories with another one."""
    callspec = getattr(item, "callspec", None)
    if callspec is None or asyncio_selection(item) is None:
        return True
    return any(value is factory for value in callspec.params.values())


SESSION = pytest.StashKey[Session]()


def session_of(config: pytest.Config) -> Session:
    return config.stash[SESSION]
