"""The hosts' public face: what a user calls on a SimEventLoop and a SimDriver, and nothing of
the kernel-host protocol (the kernel's questions and the loop's hooks for the clock server,
external sources and the pytest plugin are private names, as asyncio's own loop hooks)."""

from __future__ import annotations

import asyncio
import inspect
import re
from pathlib import Path

import pytest

import evclock
from evclock.kernel._core import CoreHost

API_PAGE = Path(__file__).resolve().parents[2] / "docs" / "api" / "evclock.md"

PACING = {"rtf", "paused", "achieved_rtf", "pause", "resume", "step", "step_until"}
#: SimEventLoop's public names beyond asyncio's own loop classes.
LOOP_SURFACE = PACING | {"clock", "source", "now_ns", "call_at_ns", "hold_time"}
DRIVER_SURFACE = PACING | {
    "clock",
    "source",
    "loop",
    "now",
    "now_ns",
    "running",
    "lockstep_overruns",
    "start",
    "stop",
    "run_until",
    "hold_time",
}
ASYNCIO_LOOPS = (asyncio.AbstractEventLoop, asyncio.BaseEventLoop, asyncio.SelectorEventLoop)


def public(cls: type, beyond: tuple[type, ...] = ()) -> set[str]:
    inherited = {name for base in beyond for name in dir(base)}
    return {n for n in dir(cls) if not n.startswith("_") and n not in inherited}


def test_the_loop_shows_only_what_a_user_calls_beyond_asyncio() -> None:
    assert public(evclock.SimEventLoop, ASYNCIO_LOOPS) == LOOP_SURFACE


def test_the_driver_shows_only_what_a_user_calls() -> None:
    assert public(evclock.SimDriver) == DRIVER_SURFACE


@pytest.mark.parametrize("host", [evclock.SimEventLoop, evclock.SimDriver])
def test_each_host_answers_the_kernel_through_private_names(host: type) -> None:
    # The protocol's questions (all but the clock, which users read too) are private, and
    # each host implements every one of them.
    protocol = {n for n, v in vars(CoreHost).items() if inspect.isfunction(v)}
    assert protocol >= {"_anything_runnable", "_held_horizon", "_could_wake", "_serves"}
    assert all(n.startswith("_") for n in protocol)
    assert all(callable(getattr(host, n, None)) for n in protocol), protocol


@pytest.mark.parametrize(
    ("name", "surface"),
    [("SimEventLoop", LOOP_SURFACE), ("SimDriver", DRIVER_SURFACE)],
)
def test_the_api_reference_lists_exactly_the_surface(name: str, surface: set[str]) -> None:
    # docs/api/evclock.md names the members mkdocstrings renders for each host.
    pattern = rf"^::: evclock\.{name}\n    options:\n      members: \[([^\]]*)\]"
    block = re.search(pattern, API_PAGE.read_text(), re.M)
    assert block is not None, f"docs/api/evclock.md has no members list for {name}"
    assert {m.strip() for m in block.group(1).split(",")} == surface
