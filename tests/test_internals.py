"""One home for CPython's internals: evclock/_cpython.py names every private of asyncio,
threading and the interpreter that evclock uses, and evclock/_procfs.py is the only reader
of ``/proc``. This scans evclock's source (with ``ast``) and fails on any other use.

What counts as a private of the standard library:
* a ``_name`` imported from, or read as an attribute of, a standard-library module;
* ``getattr(obj, "_name")`` where ``_name`` is a private of the asyncio and threading
  classes evclock works with;
* an attribute ``obj._name`` where ``_name`` is such a private and evclock defines no
  attribute of that name itself: it must be declared in ``_cpython.ASYNCIO_PRIVATES`` for
  the module that uses it.
"""

from __future__ import annotations

import ast
import asyncio
import asyncio.base_events
import asyncio.base_subprocess
import asyncio.events
import asyncio.futures
import asyncio.selector_events
import asyncio.streams
import asyncio.tasks
import asyncio.unix_events
import concurrent.futures
import concurrent.futures.thread
import inspect
import re
import selectors
import sys
import threading
from pathlib import Path

import evclock
from evclock import _cpython

PACKAGE = Path(evclock.__file__).resolve().parent
HOMES = {"_cpython.py", "_procfs.py"}
STDLIB = set(sys.stdlib_module_names)
CLASSES = (
    asyncio.base_events.BaseEventLoop,
    asyncio.selector_events.BaseSelectorEventLoop,
    asyncio.unix_events._UnixSelectorEventLoop,
    asyncio.events.Handle,
    asyncio.events.TimerHandle,
    asyncio.futures._PyFuture,  # type: ignore[attr-defined]
    asyncio.tasks._PyTask,  # type: ignore[attr-defined]
    asyncio.base_subprocess.BaseSubprocessTransport,
    asyncio.streams.StreamReader,
    asyncio.Event,
    threading.Thread,
    threading.Condition,
    concurrent.futures.thread.ThreadPoolExecutor,
    selectors.BaseSelector,
    selectors.EpollSelector,
)


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def stdlib_private_names() -> set[str]:
    """The private attributes and methods of the classes above (their own and their
    instances', as assigned in their source)."""
    names: set[str] = set()
    for cls in CLASSES:
        names |= {n for n in dir(cls) if _is_private(n)}
        names |= {n for n in getattr(cls, "__slots__", ()) if _is_private(n)}
        for klass in cls.__mro__:
            try:
                source = inspect.getsource(klass)
            except (OSError, TypeError):
                continue
            names |= set(re.findall(r"self\.(_[a-z]\w*)\s*=", source))
    return names


def modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def relative(path: Path) -> str:
    return path.relative_to(PACKAGE).as_posix()


def _asyncio_subclass(node: ast.ClassDef) -> bool:
    return any(
        re.search(r"asyncio|events\.|SelectorEventLoop|TimerHandle", ast.unparse(base))
        for base in node.bases
    )


def own_private_names() -> set[str]:
    """Private names evclock defines for its own objects (outside its asyncio subclasses)."""
    own: set[str] = set()
    for path in modules():
        tree = ast.parse(path.read_text())
        skip: set[ast.AST] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and _asyncio_subclass(node):
                skip |= set(ast.walk(node))
        for node in ast.walk(tree):
            if node in skip:
                continue
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                if _is_private(node.name):
                    own.add(node.name)
            elif (
                isinstance(node, ast.Attribute)
                and isinstance(node.ctx, ast.Store)
                and _is_private(node.attr)
            ):
                own.add(node.attr)
            elif isinstance(node, ast.Assign | ast.AnnAssign):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                own |= {t.id for t in targets if isinstance(t, ast.Name) and _is_private(t.id)}
    return own


def stdlib_module_names(tree: ast.Module) -> set[str]:
    """The names a module binds to standard-library modules (``import asyncio``,
    ``from asyncio import base_events``, ``import concurrent.futures as cf``)."""
    bound: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in STDLIB:
                    bound.add(alias.asname or alias.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] not in STDLIB:
                continue
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if full in sys.modules or full.split(".")[0] in ("asyncio", "concurrent"):
                    bound.add(alias.asname or alias.name)
    return bound


def violations() -> list[str]:
    private = stdlib_private_names()
    own = own_private_names()
    found = []
    for path in modules():
        name = relative(path)
        if name in HOMES:
            continue
        tree = ast.parse(path.read_text())
        stdlib_names = stdlib_module_names(tree)
        for node in ast.walk(tree):
            where = f"{name}:{getattr(node, 'lineno', '?')}"
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.split(".")[0] in STDLIB:
                    for alias in node.names:
                        if _is_private(alias.name):
                            found.append(f"{where}: from {node.module} import {alias.name}")
            elif isinstance(node, ast.Attribute) and _is_private(node.attr):
                base = node.value
                if isinstance(base, ast.Name) and base.id in stdlib_names:
                    found.append(f"{where}: {base.id}.{node.attr}")
                elif node.attr in private and node.attr not in own:
                    declared = _cpython.ASYNCIO_PRIVATES.get(node.attr)
                    if declared is None or name not in declared[1]:
                        found.append(f"{where}: .{node.attr} (not declared for this module)")
            elif (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "getattr"
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)
                and node.args[1].value in private
                and node.args[1].value not in own
            ):
                found.append(f"{where}: getattr(..., {node.args[1].value!r})")
    return found


def _without_docstrings(tree: ast.Module) -> None:
    """Drop docstrings (they may mention /proc), so only code is scanned."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            body[0].value.value = ""


def test_no_private_of_the_standard_library_outside_its_home() -> None:
    assert violations() == []


def test_proc_is_read_only_in_procfs() -> None:
    readers = []
    for path in modules():
        if relative(path) == "_procfs.py":
            continue
        tree = ast.parse(path.read_text())
        _without_docstrings(tree)
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and node.value.startswith("/proc")
            ):
                readers.append(f"{relative(path)}:{node.lineno}: {node.value!r}")
    assert readers == []


def test_every_declared_private_is_used_where_it_says() -> None:
    stale = []
    for attr, (why, users) in _cpython.ASYNCIO_PRIVATES.items():
        assert why, attr
        for user in users:
            text = (PACKAGE / user).read_text()
            if not re.search(rf"\.{re.escape(attr)}\b|\b{re.escape(attr)}\s*[=:(]", text):
                stale.append(f"{attr} in {user}")
    assert stale == []


def test_the_scan_finds_what_it_must(tmp_path: Path) -> None:
    """The scanner itself: a module using each kind of private is reported."""
    private = stdlib_private_names()
    assert {"_ready", "_callbacks", "_scheduled", "_fut_waiter"} <= private
    tree = ast.parse(
        "import asyncio, threading\n"
        "from asyncio import base_events\n"
        "x = asyncio._get_running_loop\n"
        "y = threading._active\n"
        "z = base_events._format_handle\n"
    )
    names = stdlib_module_names(tree)
    hits = [
        f"{n.value.id}.{n.attr}"
        for n in ast.walk(tree)
        if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in names
    ]
    assert hits == ["asyncio._get_running_loop", "threading._active", "base_events._format_handle"]
