"""The public surface: a small top-level namespace, the rest in subpackages imported on first
use, and a clear error for every name that moved in 0.2.0."""

from __future__ import annotations

import subprocess
import sys

import pytest

import evclock

LAZY = ("sources", "remote", "ros2", "data", "tools", "testing", "gym")


def test_import_evclock_loads_no_subpackage_of_the_upper_layers_nor_heavy_dependencies() -> None:
    code = (
        "import sys, evclock\n"
        f"names = {[f'evclock.{name}' for name in LAZY]!r} + "
        "['numpy', 'pybullet', 'gymnasium', 'typer', 'rich', 'fractions', 'ctypes', "
        "'importlib.metadata']\n"
        "print(sorted(name for name in names if name in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout == "[]\n"


def test_the_top_level_holds_what_a_controller_author_needs() -> None:
    assert 40 <= len(evclock.__all__) <= 50
    for name in evclock.__all__:
        assert getattr(evclock, name) is not None, name
    for name in ("run", "clock", "Time", "Duration", "Rate", "Timer", "SimEventLoop"):
        assert name in evclock.__all__


@pytest.mark.parametrize("name", LAZY)
def test_each_subpackage_is_an_attribute_imported_on_first_use(name: str) -> None:
    module = getattr(evclock, name)
    assert module.__name__ == f"evclock.{name}"


@pytest.mark.parametrize(
    ("name", "home"),
    [
        ("PyBulletTimeSource", "sources"),
        ("ClockServer", "remote"),
        ("Ros2ClockPublisher", "ros2"),
        ("ApproximateTimeSynchronizer", "data"),
        ("run_scenario", "tools"),
    ],
)
def test_a_moved_name_says_where_it_lives_now(name: str, home: str) -> None:
    with pytest.raises(AttributeError) as info:
        getattr(evclock, name)
    assert str(info.value) == (
        f"evclock.{name} moved to evclock.{home}.{name} in evclock 0.2.0: "
        f"use `from evclock.{home} import {name}` (see CHANGELOG.md)"
    )
    assert getattr(getattr(evclock, home), name) is not None


def test_a_renamed_error_says_its_new_name() -> None:
    with pytest.raises(AttributeError) as info:
        evclock.ClockJumped  # type: ignore[attr-defined]  # noqa: B018
    assert str(info.value) == (
        "evclock.ClockJumped was renamed evclock.ClockJumpedError in evclock 0.2.0 "
        "(see CHANGELOG.md)"
    )


def test_every_moved_name_is_public_in_its_new_home() -> None:
    for name, home in evclock._MOVED.items():  # type: ignore[attr-defined]
        module = getattr(evclock, home)
        assert name in module.__all__, f"{name} is not in evclock.{home}.__all__"


def test_an_unknown_name_is_a_plain_attribute_error() -> None:
    with pytest.raises(AttributeError, match="module 'evclock' has no attribute 'nope'"):
        evclock.nope  # type: ignore[attr-defined]  # noqa: B018
