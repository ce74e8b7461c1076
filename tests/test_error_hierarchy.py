"""One error hierarchy: every error evclock raises is an ``EvClockError`` named ``*Error``.

The classes are checked by import; the raise sites by reading evclock's source with ``ast``: no
site raises (or builds) the bare ``EvClockError`` or a plain builtin that users would want to
catch as an evclock error, except the few that asyncio's own contract asks for (allowlisted).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

import evclock
from evclock import _errors
from evclock.testing._budget import WallTimeBudgetError

PACKAGE = Path(evclock.__file__).parent

#: Every evclock error class: those of ``evclock._errors``, and the one defined elsewhere.
ERRORS: list[type[BaseException]] = [
    obj
    for obj in vars(_errors).values()
    if isinstance(obj, type) and issubclass(obj, BaseException) and obj.__module__ != "builtins"
]
#: Error classes defined outside ``evclock/_errors.py``, with the reason.
DEFINED_ELSEWHERE = {
    ("testing/_budget.py", "WallTimeBudgetError"): "the pytest plugin's own, next to its budget",
}
ALL_ERRORS = [*ERRORS, WallTimeBudgetError]

#: Builtins that no evclock code may raise plain: the matching EvClockError subclass instead.
PLAIN = frozenset(
    {"EvClockError", "ValueError", "RuntimeError", "TypeError", "KeyError", "LookupError"}
    | {"IndexError", "TimeoutError"}
)
#: (file under evclock/, enclosing function, exception) -> why the plain builtin stays.
ALLOWED: dict[tuple[str, str, str], str] = {}


def test_the_hierarchy_is_found() -> None:
    assert _errors.EvClockError in ERRORS
    assert len(ERRORS) > 20


@pytest.mark.parametrize("error", ALL_ERRORS, ids=lambda error: error.__name__)
def test_every_error_is_an_evclock_error_named_error_with_a_docstring(
    error: type[BaseException],
) -> None:
    assert issubclass(error, evclock.EvClockError)
    assert error.__name__.endswith("Error")
    assert error.__doc__ is not None
    assert error.__doc__.strip()


def test_the_errors_page_lists_every_error() -> None:
    page = Path(__file__).resolve().parents[1] / "docs" / "errors.md"
    if not page.exists():
        pytest.skip("no docs/ in this tree")
    rows = [line for line in page.read_text().splitlines() if line.startswith("| `")]
    listed = [row.split("`")[1] for row in rows]
    assert sorted(listed) == sorted(error.__name__ for error in ALL_ERRORS)


def _sources() -> Iterator[tuple[str, ast.Module]]:
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE).as_posix(), ast.parse(path.read_text(), str(path))


def _name_of(node: ast.expr) -> str | None:
    """``X`` for ``X``, ``X(...)``, ``module.X`` and ``module.X(...)``."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _plain_sites(tree: ast.Module) -> Iterator[tuple[str, str, int]]:
    """(enclosing function, exception, line) of each raise of a plain exception in ``tree``,
    and of each plain exception built without a raise (``future.set_exception(X(...))``)."""

    def visit(node: ast.AST, scope: str) -> Iterator[tuple[str, str, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                inner = f"{scope}.{child.name}" if scope else child.name
                yield from visit(child, inner)
                continue
            if isinstance(child, ast.Raise) and child.exc is not None:
                name = _name_of(child.exc)
                if name in PLAIN:
                    yield scope, name, child.lineno
                if isinstance(child.exc, ast.Call):  # its arguments may build one too
                    for arg in (*child.exc.args, *(k.value for k in child.exc.keywords)):
                        yield from visit(arg, scope)
                continue
            if (
                isinstance(child, ast.Call)
                and isinstance(child.func, ast.Name)
                and child.func.id in PLAIN
            ):
                yield scope, child.func.id, child.lineno
            yield from visit(child, scope)

    yield from visit(tree, "")


def test_no_bare_base_class_or_plain_builtin_is_raised() -> None:
    found: list[str] = []
    used: set[tuple[str, str, str]] = set()
    for path, tree in _sources():
        for scope, name, line in _plain_sites(tree):
            key = (path, scope, name)
            if key in ALLOWED:
                used.add(key)
            else:
                found.append(f"evclock/{path}:{line}: {name} in {scope or '<module>'}")
    assert not found, (
        "raise an EvClockError subclass (evclock/_errors.py) instead of:\n" + "\n".join(found)
    )
    assert not set(ALLOWED) - used, f"stale allowlist entries: {sorted(set(ALLOWED) - used)}"


def test_every_error_class_is_defined_in_the_errors_module() -> None:
    elsewhere = set()
    for path, tree in _sources():
        if path == "_errors.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and any(
                (_name_of(base) or "").endswith(("Error", "Exception")) for base in node.bases
            ):
                elsewhere.add((path, node.name))
    assert elsewhere == set(DEFINED_ELSEWHERE)


def test_the_scan_finds_what_it_must() -> None:
    tree = ast.parse(
        "def f():\n"
        "    raise ValueError('x')\n"
        "class C:\n"
        "    def g(self):\n"
        "        raise EvClockError\n"
        "    async def h(self, fut):\n"
        "        fut.set_exception(builtins_alias(TimeoutError('late')))\n"
        "        raise errors.RuntimeError('y') from None\n"
        "        raise InvalidArgumentError(str(KeyError('k')))\n"
        "raise InvalidTypeError('fine')\n"
    )
    assert list(_plain_sites(tree)) == [
        ("f", "ValueError", 2),
        ("C.g", "EvClockError", 5),
        ("C.h", "TimeoutError", 7),
        ("C.h", "RuntimeError", 8),
        ("C.h", "KeyError", 9),
    ]
