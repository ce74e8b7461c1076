"""The API reference covers every public name, and every public name has a docstring.

Used twice: as a MkDocs hook (``hooks:`` in mkdocs.yml), where each finding is a warning and
so fails ``mkdocs build --strict``; and by ``tests/test_docs.py``. Standard library only: the
test suite also runs where the ``docs`` extra is not installed.

A public name is one listed in the ``__all__`` of a public module (:data:`PUBLIC_MODULES`).
Docstrings are read from the source the way mkdocstrings (griffe) reads them: the docstring
of a class or function, or the string literal right below an assignment (a ``#:`` comment is
not one). The API pages name what they document with ``::: evclock.NAME`` lines; a name
exported by two public modules (``evclock.SIM`` and ``evclock.time.SIM``) is covered by
either path.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import logging
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: The modules whose ``__all__`` is public API, in the order of the API pages.
PUBLIC_MODULES = (
    "evclock",
    "evclock.time",
    "evclock.sources",
    "evclock.remote",
    "evclock.ros2",
    "evclock.data",
    "evclock.tools",
    "evclock.gym",
    "evclock.testing.plugin",
)

#: The bundled scenarios' package (installed with evclock, not under it): its API page
#: documents what a scenario author uses; each ``::: evclock_sims.NAME`` must be in its
#: ``__all__`` and, where defined in its source, have a docstring.
SCENARIO_PACKAGE = "evclock_sims"

DIRECTIVE = re.compile(r"^:::[ \t]+([\w.]+)[ \t]*$", re.M)


def public_names() -> dict[str, list[str]]:
    """Every public module's ``__all__``, by module."""
    return {name: list(importlib.import_module(name).__all__) for name in PUBLIC_MODULES}


def _statements(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """The statements of a module body, including those under ``if`` (TYPE_CHECKING) and ``try``."""
    for node in body:
        yield node
        if isinstance(node, ast.If):
            yield from _statements(node.body)
            yield from _statements(node.orelse)
        elif isinstance(node, ast.Try):
            yield from _statements(node.body)


def _assigned(node: ast.stmt) -> list[str]:
    if isinstance(node, ast.Assign):
        return [target.id for target in node.targets if isinstance(target, ast.Name)]
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


def _imported_from(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module if is_package else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        base = base.rpartition(".")[0]
    return f"{base}.{node.module}" if node.module else base


def docstring_of(module: str, name: str) -> tuple[str, str | None]:
    """Where ``module.name`` is defined (following imports) and its docstring (None: none)."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return module, None
    path = Path(spec.origin)
    statements = list(_statements(ast.parse(path.read_text(encoding="utf-8")).body))
    for index, node in enumerate(statements):
        if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            if node.name == name:
                return module, ast.get_docstring(node)
        elif name in _assigned(node):
            after = statements[index + 1] if index + 1 < len(statements) else None
            if (
                isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                return module, after.value.value
        elif isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if (alias.asname or alias.name) == name:
                    source = _imported_from(module, path.name == "__init__.py", node)
                    return docstring_of(source, alias.name)
    return module, None


def documented_paths(api_dir: Path) -> dict[str, str]:
    """Every ``::: path`` of the API pages, with the page that holds it."""
    found: dict[str, str] = {}
    for page in sorted(api_dir.glob("*.md")):
        for path in DIRECTIVE.findall(page.read_text(encoding="utf-8")):
            found.setdefault(path, page.name)
    return found


def problems(docs_dir: Path) -> list[str]:
    """What is wrong with the API reference under ``docs_dir``; empty when nothing is."""
    names = public_names()
    modules = {module: importlib.import_module(module) for module in names}
    documented = documented_paths(docs_dir / "api")
    found: list[str] = []
    public_paths: set[str] = set()
    for module, exported in names.items():
        for name in exported:
            public_paths.add(f"{module}.{name}")
    for module, exported in names.items():
        for name in exported:
            where, doc = docstring_of(module, name)
            if not (doc and doc.strip()):
                found.append(f"{module}.{name} has no docstring (it is defined in {where})")
            value: Any = getattr(modules[module], name)
            paths = [f"{module}.{name}"] + [
                f"{other}.{name}"
                for other, other_names in names.items()
                if other != module
                and name in other_names
                and getattr(modules[other], name) is value
            ]
            if not any(path in documented for path in paths):
                found.append(
                    f"{module}.{name} is missing from the API reference: add "
                    f"'::: {module}.{name}' to a page of docs/api/"
                )
    scenario_names = set(importlib.import_module(SCENARIO_PACKAGE).__all__)
    for path, page in documented.items():
        package, _, name = path.rpartition(".")
        if package == SCENARIO_PACKAGE and name in scenario_names:
            where, doc = docstring_of(package, name)
            if not (doc and doc.strip()):
                found.append(f"{path} has no docstring (it is defined in {where})")
            continue
        if path not in public_paths:
            found.append(f"docs/api/{page}: '::: {path}' is not a public name of evclock")
    return found


log = logging.getLogger("mkdocs.hooks.api_coverage")


def on_pre_build(config: Any) -> None:
    """MkDocs hook: each problem is a warning, which ``--strict`` turns into a failure."""
    for problem in problems(Path(config["docs_dir"])):
        log.warning("API reference: %s", problem)
