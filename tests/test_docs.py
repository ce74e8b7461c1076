"""The documentation covers what it must: every public name (with a docstring) in the API
reference, every page in the nav, every command-line option on the command's page, and a
README short enough to read. The code blocks themselves run in tests/test_readme.py; the
site's own build (``mkdocs build --strict``, a CI step) checks links and anchors."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from _examples import load_module

import evclock

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"


def _coverage() -> ModuleType:
    """docs/_hooks/api_coverage.py, the check the strict build runs as a MkDocs hook."""
    return load_module(DOCS / "_hooks" / "api_coverage.py")


def test_every_public_name_has_a_docstring_and_is_in_the_api_reference() -> None:
    assert _coverage().problems(DOCS) == []


def test_the_public_modules_are_those_with_an_all() -> None:
    coverage = _coverage()
    public = {"evclock", *(f"evclock.{name}" for name in ("time", "sources", "remote", "ros2"))}
    public |= {"evclock.data", "evclock.tools", "evclock.gym", "evclock.testing.plugin"}
    assert set(coverage.PUBLIC_MODULES) == public
    assert set(evclock.__all__) == set(coverage.public_names()["evclock"])


def test_the_check_finds_a_name_missing_from_the_api_pages(tmp_path: Path) -> None:
    shutil.copytree(DOCS / "api", tmp_path / "api")
    page = tmp_path / "api" / "data.md"
    page.write_text(page.read_text().replace("::: evclock.data.stamp_of\n", ""))
    (tmp_path / "api" / "extra.md").write_text("::: evclock.data._buffer.TimeBuffer\n")
    problems = _coverage().problems(tmp_path)
    assert any("evclock.data.stamp_of is missing from the API reference" in p for p in problems)
    assert any("'::: evclock.data._buffer.TimeBuffer' is not a public name" in p for p in problems)


def test_the_check_reads_docstrings_as_griffe_does() -> None:
    coverage = _coverage()
    assert coverage.docstring_of("evclock", "run")[1]  # a function, through two imports
    where, doc = coverage.docstring_of("evclock.ros2", "CLOCK_TYPE")  # an attribute docstring
    assert where == "evclock.ros2._wire"
    assert doc == "The ROS 2 type of ``/clock`` messages."
    assert coverage.docstring_of("evclock", "__version__")[1]  # declared under TYPE_CHECKING


def test_the_readme_is_at_most_200_lines() -> None:
    assert len(README.read_text().splitlines()) <= 200


def test_every_page_is_in_the_nav_and_every_nav_entry_exists() -> None:
    nav = re.findall(r"^\s*- (?:[^:\n]+: )?(\S+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), re.M)
    pages = {
        str(path.relative_to(DOCS)) for path in DOCS.rglob("*.md") if "_hooks" not in path.parts
    }
    assert len(nav) == len(set(nav))
    assert set(nav) == pages


def test_the_readme_links_exist() -> None:
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README.read_text()):
        if not target.startswith(("http://", "https://")):
            assert (ROOT / target).exists(), target


def test_architecture_references_in_the_code_name_existing_sections() -> None:
    headings = set(re.findall(r"^#+ (.+)$", (DOCS / "architecture.md").read_text(), re.M))
    source = Path(evclock.__file__).resolve().parent
    cited = {
        section
        for path in source.rglob("*.py")
        for section in re.findall(r'docs/architecture\.md, "([^"]+)"', path.read_text())
    }
    assert cited  # the code cites it
    assert cited <= headings


# ----------------------------------------------------------------------------- the command


def _commands() -> dict[str, Any]:
    import typer

    from evclock.tools._cli import app

    found: dict[str, Any] = {}

    def walk(command: Any, path: str) -> None:
        if hasattr(command, "commands"):
            for name, sub in command.commands.items():
                walk(sub, f"{path} {name}")
        else:
            found[path] = command

    walk(typer.main.get_command(app), "evclock")
    return found


def _section(text: str, heading: str) -> str:
    start = text.index(heading)
    following = text.find("\n## ", start + len(heading))
    return text[start : following if following != -1 else None]


@pytest.mark.parametrize("path", sorted(_commands()))
def test_the_command_page_lists_every_option_of_the_help(path: str) -> None:
    command = _commands()[path]
    text = _section((DOCS / "cli.md").read_text(), f"## `{path}`")
    options = {opt for param in command.params for opt in (*param.opts, *param.secondary_opts)}
    long_options = {opt for opt in options if opt.startswith("--")}
    for option in long_options:
        assert re.search(rf"`[^`]*{re.escape(option)}(?![\w-])", text), f"{path}: {option}"
    table = [line for line in text.splitlines() if line.startswith("| `-")]
    for line in table:
        for option in re.findall(r"(?<![\w-])(--?[a-z][\w-]*)", line.split("|")[1]):
            assert option in options, f"{path}: the page lists {option}, which the help does not"
    if long_options - {"--help"}:
        assert table, f"{path}: no options table"


def _extras_table(page: Path) -> dict[str, str]:
    """The extras table under a page's "## Extras" heading: extra -> what it installs."""
    text = page.read_text(encoding="utf-8").split("## Extras", 1)[1]
    rows = re.findall(r"^\| `([\w-]+)` \| ([^|]+) \|", text.split("\n## ", 1)[0], re.M)
    return {extra: installs.strip() for extra, installs in rows}


def test_the_extras_tables_of_the_readme_and_getting_started_agree_with_pyproject() -> None:
    import tomllib

    with (ROOT / "pyproject.toml").open("rb") as f:
        extras = list(tomllib.load(f)["project"]["optional-dependencies"])
    readme = _extras_table(README)
    getting_started = _extras_table(DOCS / "guides" / "getting-started.md")
    assert sorted(readme) == sorted(extras)
    assert readme == getting_started


def _pages() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def test_no_page_says_an_option_mujoco_runs_with_is_pybullet_s_alone() -> None:
    """The engines table says which options MuJoCo runs lack (its "no" rows); a page that
    calls options PyBullet's alone names only those (``--record`` on split runs was said to
    stay PyBullet's after MuJoCo recorded them)."""
    table = _section((DOCS / "guides" / "engines.md").read_text(), "| | PyBullet (default)")
    rows = [line.split("|") for line in table.splitlines() if line.startswith("| ")]
    pybullet_only = {
        option
        for row in rows
        if len(row) > 3 and row[3].strip().startswith("no")
        for option in re.findall(r"--[a-z][\w-]*", row[1])
    }
    assert pybullet_only == {"--gui"}
    claim = re.compile(r"(stays?|remains?) PyBullet's|PyBullet[- ]only|only on PyBullet")
    wrong = []
    for page in _pages():
        if page.name == "changelog.md":
            continue
        for clause in re.split(r"[;.:]\s|\n\n|\n\|", page.read_text(encoding="utf-8")):
            if claim.search(clause):
                options = set(re.findall(r"`(--[a-z][\w-]*)", clause))
                if options - pybullet_only:
                    wrong.append(f"{page.relative_to(ROOT)}: {' '.join(clause.split())}")
    assert not wrong, wrong
