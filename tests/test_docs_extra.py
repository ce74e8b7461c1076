"""The ``docs`` extra installs everything the docs build imports: ``pip install -e ".[docs]"``
then ``mkdocs build --strict`` works in a fresh environment.

The build's hooks (``docs/_hooks/``, listed in mkdocs.yml) are loaded in a fresh interpreter and
run what imports at build time (the API check imports every public module, the pytest plugin
among them); every installed distribution that brought one of the modules imported is then
checked to be among the requirements of ``evclock[docs]``, followed transitively.
"""

from __future__ import annotations

import importlib.metadata
import json
import re
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parent.parent
HOOKS = sorted((ROOT / "docs" / "_hooks").glob("*.py"))


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements(requirements: list[str], extras: set[str]) -> list[Requirement]:
    """The requirements among ``requirements`` that apply with ``extras`` on this Python."""
    found = []
    for text in requirements:
        requirement = Requirement(text)
        marker = requirement.marker
        if marker is None or any(marker.evaluate({"extra": e}) for e in extras or {""}):
            found.append(requirement)
    return found


def docs_extra_closure() -> set[str]:
    """Every distribution ``pip install evclock[docs]`` installs, by normalised name: the
    extra as pyproject.toml declares it, then the installed distributions' own requirements."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    wanted: list[tuple[str, set[str]]] = [("evclock", {"docs"})]
    seen: set[tuple[str, frozenset[str]]] = set()
    closure: set[str] = set()
    while wanted:
        name, chosen = wanted.pop()
        key = (_normal(name), frozenset(chosen))
        if key in seen:
            continue
        seen.add(key)
        closure.add(key[0])
        if key[0] == "evclock":  # the source tree's own declaration, not an installed copy's
            texts = list(project["dependencies"])
            for extra in chosen:
                texts += extras[extra]
            requirements = _requirements(texts, set())
        else:
            try:
                texts = importlib.metadata.requires(name) or []
            except importlib.metadata.PackageNotFoundError:
                continue  # not installed here: what it imports is not imported either
            requirements = _requirements(texts, chosen)
        wanted += [(requirement.name, set(requirement.extras)) for requirement in requirements]
    return closure


_IMPORTED_BY_THE_HOOKS = textwrap.dedent(
    """
    import importlib.util, json, sys
    before = set(sys.modules)
    for path in sys.argv[1:]:
        spec = importlib.util.spec_from_file_location(path.rsplit("/", 1)[-1][:-3], path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        if hasattr(module, "public_names"):
            module.public_names()  # what the build's API check imports
    print(json.dumps(sorted({name.partition(".")[0] for name in set(sys.modules) - before})))
    """
)


def test_the_docs_extra_installs_what_the_docs_hooks_import() -> None:
    assert HOOKS, "docs/_hooks/ has no hook"
    result = subprocess.run(
        [sys.executable, "-c", _IMPORTED_BY_THE_HOOKS, *map(str, HOOKS)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    imported = json.loads(result.stdout)
    providers = importlib.metadata.packages_distributions()
    needed = {
        _normal(dist)
        for module in imported
        if module not in sys.stdlib_module_names and module not in ("evclock", "evclock_sims")
        for dist in providers.get(module, [])
    }
    assert "pytest" in needed  # the API check imports the pytest plugin
    missing = sorted(needed - docs_extra_closure())
    assert missing == [], (
        f"the docs build imports {missing}, which pip install 'evclock[docs]' does not install: "
        "add them to the docs extra in pyproject.toml"
    )
