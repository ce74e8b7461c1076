"""The kernel's advancement rule on its own, with a scripted host (no event loop runs)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

import pytest

from evclock import PacingError
from evclock.kernel._core import DEADLOCK, DUE, HELD, MOVED, PACING, WAIT_IO, WAIT_SOURCE, SimCore
from evclock.sources import Gate, TimeSource, VirtualTimeSource


class ScriptedHost:
    """Answers the kernel's questions as the test says."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.runnable = False
        self.held = False
        self.wakeable = False
        self.interrupted = 0

    def _anything_runnable(self) -> bool:
        return self.runnable

    def _held_horizon(self, paused: bool) -> int | None:
        return 0 if self.held else None

    def _before_moving(self) -> None:
        pass

    def _could_wake(self) -> bool:
        return self.wakeable

    def _interrupt_wait(self) -> None:
        self.interrupted += 1

    def _serves(self, loop: asyncio.AbstractEventLoop) -> bool:
        return loop is self.loop

    def _is_closed(self) -> bool:
        return False

    def _call_exception_handler(self, context: dict[str, Any]) -> None:
        raise AssertionError(context)

    @property
    def clock(self) -> Any:
        raise AssertionError("not used")


@pytest.fixture
def loop() -> Iterator[asyncio.AbstractEventLoop]:
    loop = asyncio.new_event_loop()
    yield loop
    loop.close()


def make(
    loop: asyncio.AbstractEventLoop, source: TimeSource | None = None, **pacing: Any
) -> tuple[SimCore, ScriptedHost]:
    host = ScriptedHost(loop)
    core = SimCore(source or VirtualTimeSource(), host, **pacing)
    core.future_factory = loop.create_future
    return core, host


def test_the_rule_in_order(loop: asyncio.AbstractEventLoop) -> None:
    core, host = make(loop)
    assert core.advance() == DEADLOCK  # nothing scheduled, nothing could wake us
    host.wakeable = True
    assert core.advance() == WAIT_IO
    core.stop_at(5)
    host.held = True
    assert core.advance() == HELD  # outside work holds time: it does not move
    assert core.now_ns == 0
    host.held = False
    host.runnable = True
    assert core.advance() == DUE  # something runnable: run it first
    host.runnable = False
    assert core.advance() == MOVED
    assert core.now_ns == 5
    assert core.take_due() is not None  # the stop mark, due now
    core.stop_at(5)
    assert core.advance() == DUE


def test_a_pause_outranks_a_hold_and_a_step_asks_whether_paused(
    loop: asyncio.AbstractEventLoop,
) -> None:
    seen: list[bool] = []
    core, host = make(loop)
    host.held = True
    host._held_horizon = lambda paused: seen.append(paused) or (0 if host.held else None)  # type: ignore[method-assign]
    core.stop_at(5)
    core.pacer.pause()
    assert core.advance() == PACING  # paused, no step left: wait for a control, unbounded
    assert core.pacing_delay is None
    assert seen == []  # not even asked: nothing can move before a control
    core.pacer.step(1)
    assert core.advance() == HELD  # a step still waits for what holds time...
    assert seen == [True]  # ...told that the host is paused (timed thread waits do not hold)
    host.held = False
    assert core.advance() == MOVED
    assert core.now_ns == 5
    assert seen == [True, True]


def test_pacing_answers_with_a_wall_delay_instead_of_blocking(
    loop: asyncio.AbstractEventLoop,
) -> None:
    wall = [100.0]
    core, _ = make(loop, rtf=1.0, wall=lambda: wall[0])
    core.stop_at(2_000_000_000)
    assert core.advance() == PACING
    assert core.pacing_delay == 2.0  # two sim seconds at rtf=1
    wall[0] += 2.0
    assert core.advance() == MOVED
    assert core.now_ns == 2_000_000_000


def test_paused_waits_until_a_control_changes(loop: asyncio.AbstractEventLoop) -> None:
    core, _ = make(loop)
    core.pacer.pause()
    core.stop_at(10)
    assert core.advance() == PACING
    assert core.pacing_delay is None
    core.pacer.step(1)
    assert core.advance() == MOVED
    assert core.now_ns == 10
    core.pacer.resume()
    with pytest.raises(PacingError):
        core.pacer.step(1)


class Outside(TimeSource):
    external = True
    free_running = True

    def __init__(self) -> None:
        self._now = 0
        self.newest = 0

    @property
    def now_ns(self) -> int:
        return self._now

    def advance(self, target_ns: int | None, gate: Gate) -> int:
        newest = self.newest if target_ns is None else min(self.newest, target_ns)
        self._now = max(self._now, newest)
        return self._now


def test_an_external_source_without_news_waits_for_it(loop: asyncio.AbstractEventLoop) -> None:
    source = Outside()
    core, host = make(loop, source)
    assert core.advance() == WAIT_SOURCE  # idle is not a deadlock
    source.newest = 7
    assert core.advance() == MOVED  # time follows the outside even with nothing scheduled
    core.stop_at(9)
    source.newest = 20
    assert core.advance() == MOVED
    assert core.now_ns == 9  # never past a local deadline
    core.time_arrived()
    assert host.interrupted == 1


def test_a_wait_before_the_hosts_wait_interrupts_it(loop: asyncio.AbstractEventLoop) -> None:
    core, host = make(loop)
    core.notify_before = 100
    core.wait_settled(200)
    assert host.interrupted == 0
    core.stop_at(50)
    assert host.interrupted == 1
