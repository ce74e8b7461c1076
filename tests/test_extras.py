"""Optional dependencies: ``import evclock`` loads none of them, and a missing one fails with an
error naming the extra that installs it. Each case runs in a fresh interpreter where the
package is made unimportable (``sys.modules[name] = None``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

import evclock
from evclock._extras import import_extra

#: Wall seconds a child interpreter may take (it only imports evclock).
_CHILD_TIMEOUT = 120


def python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=_CHILD_TIMEOUT,
        check=False,
    )


def test_import_evclock_loads_no_optional_or_heavy_dependency() -> None:
    result = python(
        """
        import sys
        import evclock
        heavy = ("pybullet", "numpy", "typer", "rich", "pytest", "anyio", "starlette", "uvicorn")
        print(sorted(name for name in heavy if name in sys.modules))
        """
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_missing_extra_names_the_extra() -> None:
    with pytest.raises(evclock.MissingExtraError) as info:
        import_extra("evclock_no_such_module", "pybullet", needed_by="this test")
    assert str(info.value) == (
        "this test needs 'evclock_no_such_module', which is not installed; install it with: "
        "pip install 'evclock[pybullet]'"
    )
    assert isinstance(info.value, ImportError)
    assert info.value.name == "evclock_no_such_module"


def test_a_broken_installation_is_not_reported_as_a_missing_extra() -> None:
    # The module exists but something it imports does not: that error propagates unchanged.
    result = python(
        """
        import sys, types
        from evclock._extras import import_extra
        sys.modules["broken_pkg"] = None
        module = types.ModuleType("outer_pkg")
        sys.modules.pop("outer_pkg", None)
        import importlib.abc, importlib.machinery
        class Finder(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name == "outer_pkg":
                    return importlib.machinery.ModuleSpec(name, Loader())
        class Loader(importlib.abc.Loader):
            def create_module(self, spec):
                return None
            def exec_module(self, module):
                import broken_pkg  # noqa: F401
        sys.meta_path.insert(0, Finder())
        try:
            import_extra("outer_pkg", "x", needed_by="test")
        except Exception as exc:
            print(type(exc).__name__, exc.name)
        """
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ModuleNotFoundError broken_pkg"


def test_pybullet_source_without_pybullet() -> None:
    result = python(
        """
        import sys
        sys.modules["pybullet"] = None
        import evclock
        try:
            evclock.PyBulletTimeSource.connect()
        except evclock.MissingExtraError as exc:
            print(exc)
        """
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == (
        "PyBulletTimeSource needs 'pybullet', which is not installed; install it with: "
        "pip install 'evclock[pybullet]'"
    )


def test_evclock_run_without_pybullet_exits_2_naming_the_extra() -> None:
    result = python(
        """
        import sys
        sys.modules["pybullet"] = None
        from evclock._cli import main
        sys.argv = ["evclock", "run", "kuka", "--quiet"]
        main()
        """
    )
    assert result.returncode == 2, result.stderr
    assert "error: the bundled scenarios (evclock_sims) needs 'pybullet', which is not " in (
        " ".join(result.stderr.split())
    )
    assert "pip install 'evclock[pybullet]'" in " ".join(result.stderr.split())
