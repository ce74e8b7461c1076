"""What the plugin knows: one :class:`Session` per pytest run, which also makes the loops the
tests run on, and one :class:`ItemState` per opted-in test."""

from __future__ import annotations

import asyncio
import weakref
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

import pytest

from .._clock import WallClock, attach_clock
from .._loop import SimEventLoop
from ..sources import TimeSource, VirtualTimeSource
from ._options import Options, config_options
from ._selection import EVCLOCK_LOOP_FACTORY_NAME, Kind, asyncio_selection, is_async, wants_evclock

if TYPE_CHECKING:
    from ._budget import Budget
    from ._guard import CallGuard


class ItemState:
    """What evclock knows about one opted-in test."""

    def __init__(self, item: pytest.Function, options: Options, kind: Kind) -> None:
        self.item = item
        self.options = options
        self.kind = kind
        self.is_async = is_async(item)
        self.loops: list[asyncio.AbstractEventLoop] = []
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
        #: Every loop evclock's factory made (the budgets look for the one running).
        self.loops: weakref.WeakSet[asyncio.AbstractEventLoop] = weakref.WeakSet()
        # One stable object: pytest-asyncio parametrizes with it and anyio receives it.
        self.loop_factory: Callable[[], asyncio.AbstractEventLoop] = self._new_loop

    def _new_loop(self) -> asyncio.AbstractEventLoop:
        """Create the loop of the test being run, with its marker's options."""
        item = self.current_item
        state = state_of(item) if item is not None else None
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
        self.loops.add(loop)
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


SESSION = pytest.StashKey[Session]()


def session_of(config: pytest.Config) -> Session:
    return config.stash[SESSION]
