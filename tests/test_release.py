"""The version is one and the same everywhere a release names it: the installed package
(``evclock.__version__``), ``pyproject.toml``, the newest released section of CHANGELOG.md
(``## [X.Y.Z]``, dated ``## [X.Y.Z] - YYYY-MM-DD`` when it is released, below an optional
``## [Unreleased]``), the docstring of ``__version__`` and the upgrade page, which starts from
the release before it."""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import re
import tomllib
from pathlib import Path

import evclock

ROOT = Path(os.environ.get("EVCLOCK_SOURCE_TREE") or Path(__file__).resolve().parent.parent)
HEADING = re.compile(r"^## \[(?P<name>[^\]]+)\](?: - (?P<date>\S+))?[ \t]*$", re.M)


def version() -> str:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return str(tomllib.load(f)["project"]["version"])


def released() -> list[tuple[str, str | None]]:
    """The changelog's released sections, newest first: (version, date or None)."""
    headings = [(m["name"], m["date"]) for m in HEADING.finditer(_changelog())]
    if headings and headings[0][0] == "Unreleased":
        assert headings[0][1] is None, "the [Unreleased] section has no date"
        headings = headings[1:]
    return headings


def _changelog() -> str:
    return (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")


def _key(name: str) -> tuple[int, ...]:
    assert re.fullmatch(r"\d+\.\d+\.\d+", name), f"CHANGELOG.md: [{name}] is not X.Y.Z"
    return tuple(int(part) for part in name.split("."))


def test_the_installed_package_is_the_version_of_pyproject() -> None:
    assert evclock.__version__ == importlib.metadata.version("evclock") == version(), (
        "the installed evclock's metadata is not pyproject.toml's version: reinstall it "
        '(pip install -e ".[test]")'
    )


def test_the_newest_released_section_of_the_changelog_is_this_version() -> None:
    sections = released()
    assert sections[0][0] == version(), (
        f"pyproject.toml says {version()}, the changelog's newest section is [{sections[0][0]}]"
    )
    keys = [_key(name) for name, _ in sections]
    assert keys == sorted(set(keys), reverse=True), "the sections go newest first, once each"
    for name, date in sections:
        if date is not None:  # a release's date, as Keep a Changelog writes it
            assert datetime.date.fromisoformat(date).isoformat() == date, f"[{name}] - {date}"


def test_the_docs_name_this_version_and_the_upgrade_from_the_one_before() -> None:
    init = (ROOT / "evclock" / "__init__.py").read_text(encoding="utf-8")
    assert f'The installed version of evclock (``"{version()}"``)' in init
    previous = released()[1][0]
    upgrading = (ROOT / "docs" / "upgrading.md").read_text(encoding="utf-8")
    assert upgrading.startswith(f"# Upgrading from {previous}\n")
    assert f"to {version()}" in upgrading.split("\n## ")[0]
