"""Optional dependencies: ``import evclock`` loads none of them, and a missing one fails with an
error naming the extra that installs it. Each case runs in a fresh interpreter where the
package is made unimportable (``sys.modules[name] = None``)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _cli import one_line, run_command

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
            evclock.sources.PyBulletTimeSource.connect()
        except evclock.MissingExtraError as exc:
            print(exc)
        """
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == (
        "PyBulletTimeSource needs 'pybullet', which is not installed; install it with: "
        "pip install 'evclock[pybullet]'"
    )


#: Where PyBullet installs from a wheel, as the errors that suggest installing it say.
_WHEELS = (
    "(PyBullet has wheels for CPython 3.11 only; on another Python pip builds it from source, "
    "which needs a C++ compiler and about half an hour)"
)


def test_evclock_run_without_pybullet_exits_2_naming_the_extra() -> None:
    result = python(
        """
        import sys
        sys.modules["pybullet"] = None
        from evclock.tools._cli import main
        sys.argv = ["evclock", "run", "kuka", "--quiet"]
        main()
        """
    )
    assert result.returncode == 2, result.stderr
    message = " ".join(result.stderr.split())  # evclock's errors go to stderr
    # kuka also runs on MuJoCo: the error says so.
    assert message == (
        "error: scenario 'kuka' runs on PyBullet by default, which is not installed: pip "
        f"install 'evclock[pybullet]' {_WHEELS}; or run it on MuJoCo: --engine mujoco"
    )


# --- the `evclock` command without its extras: a one-line error (or, for `list`, a note), never
# a traceback. Each case hides the extra's module in a fresh interpreter.

#: A scenario that needs no extra (a duck-typed class: evclock_sims itself needs PyBullet).
_LIGHT = """
class Light:
    name = "light"
    description = "no physics [a test scenario]"
    default_until = 1.5
    async def run(self, clock): ...
    def success(self): return True
    def summary(self): return {}
    def state_vector(self): return []
"""

#: A scenario module that imports PyBullet itself before anything of evclock's.
_NEEDS_PYBULLET = """
import pybullet as p
from evclock_sims import Scenario

class Reach(Scenario):
    name = "reach"
    description = "imports pybullet first"
    default_until = 1.0
    def _services(self, clock): return {}
    async def _mission(self, clock): ...
    def success(self): return True
    def _metrics(self): return {}
"""


def cli(args: list[str], *, hide: tuple[str, ...], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``evclock ARGS`` in a fresh interpreter where the modules ``hide`` are not installed and
    ``cwd`` (holding the test's scenario modules and distributions) is on ``sys.path``."""
    code = f"""
        import sys
        for name in {list(hide)!r}:
            sys.modules[name] = None
        sys.path.insert(0, {str(cwd)!r})
        from evclock.tools._cli import main
        sys.argv = ["evclock", *{args!r}]
        main()
        """
    return run_command([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, columns=300)


def register(directory: Path, entry_points: dict[str, str]) -> None:
    """A distribution ``evclock-test-scenarios`` in ``directory`` registering ``entry_points``."""
    info = directory / "evclock_test_scenarios-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: evclock-test-scenarios\nVersion: 1.0\n"
    )
    lines = "".join(f"{name} = {target}\n" for name, target in entry_points.items())
    (info / "entry_points.txt").write_text(f"[evclock.scenarios]\n{lines}")


@pytest.fixture
def scenarios(tmp_path: Path) -> Path:
    (tmp_path / "light_scenario.py").write_text(_LIGHT)
    (tmp_path / "reach_scenario.py").write_text(_NEEDS_PYBULLET)
    return tmp_path


def test_evclock_list_without_pybullet_lists_every_scenario_and_names_the_extra(
    scenarios: Path,
) -> None:
    register(scenarios, {"light": "light_scenario:Light", "reach": "reach_scenario:Reach"})
    result = cli(["list"], hide=("pybullet",), cwd=scenarios)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    rows = {line.split()[1]: one_line(line) for line in result.stdout.splitlines() if "│" in line}
    # What can be loaded is listed in full, with its engines and those installed; the others
    # with what they need.
    assert rows["light"] == (
        "│ light │ 1.5 │ pybullet │ no │ no physics [a test scenario] │ evclock-test-scenarios │"
    )
    for name in ("fusion", "husky"):  # they load without PyBullet: their engine is named
        assert rows[name].startswith(f"│ {name} │ ")
        assert "│ pybullet │ no │" in rows[name]
    for name in ("cartpole", "kuka"):  # they run on MuJoCo too
        assert rows[name].startswith(f"│ {name} │ ")
        assert "│ pybullet, mujoco │ on mujoco │" in rows[name]
    assert rows["reach"] == (
        "│ reach │ - │ - │ - │ (needs evclock[pybullet]) │ evclock-test-scenarios │"
    )
    assert one_line(result.stderr) == (
        "note: fusion, husky, light cannot run here: PyBullet is not installed: pip install "
        f"'evclock[pybullet]' {_WHEELS} "
        "note: reach cannot run here: scenario 'reach' (evclock-test-scenarios) needs "
        "'pybullet', which is not installed; install it with: pip install 'evclock[pybullet]'"
    )


def test_evclock_list_reports_a_broken_registration_and_lists_the_others(
    scenarios: Path,
) -> None:
    (scenarios / "raising_scenario.py").write_text("raise RuntimeError('boom at import')\n")
    register(
        scenarios,
        {
            "light": "light_scenario:Light",
            "gone": "no_such_scenario_module:Gone",
            "raising": "raising_scenario:X",
        },
    )
    result = cli(["list"], hide=("pybullet",), cwd=scenarios)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    stdout = one_line(result.stdout)
    assert (
        "│ light │ 1.5 │ pybullet │ no │ no physics [a test scenario] │ evclock-test-scenarios │"
        in stdout
    )
    assert "│ gone │ - │ - │ - │ (broken: see the error below) │ evclock-test-scenarios │" in stdout
    assert "│ husky │ 20 │ pybullet │ no │ Husky following" in stdout
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert errors == [
        "error: scenario 'gone' (no_such_scenario_module:Gone) cannot be loaded: cannot import "
        "'no_such_scenario_module' for scenario 'gone' (evclock-test-scenarios): No module "
        "named 'no_such_scenario_module'; is the package installed (or on PYTHONPATH)?",
        "error: scenario 'raising' (raising_scenario:X) cannot be loaded: RuntimeError: boom "
        "at import",
    ]


_PYBULLET_ERROR = (
    "needs 'pybullet', which is not installed; install it with: pip install 'evclock[pybullet]'"
)
_BUNDLED = (
    "error: scenario '{name}' runs on PyBullet only, which is not installed: pip install "
    f"'evclock[pybullet]' {_WHEELS}"
)


@pytest.mark.parametrize(
    ("hide", "args", "error"),
    [
        (("pybullet",), ["run", "husky", "--quiet"], _BUNDLED.format(name="husky")),
        (
            ("pybullet",),
            ["run", "reach_scenario.py"],
            f"error: scenario file 'reach_scenario.py' {_PYBULLET_ERROR}",
        ),
        (
            ("pybullet",),
            ["run", "reach_scenario:Reach"],
            f"error: 'reach_scenario:Reach' {_PYBULLET_ERROR}",
        ),
        (
            ("pybullet",),
            ["sweep", "husky", "--seeds", "2", "--quiet"],
            _BUNDLED.format(name="husky"),
        ),
        (
            ("pybullet",),
            ["sweep", "reach_scenario.py:Reach", "--seeds", "2", "--quiet"],
            f"error: scenario file 'reach_scenario.py' {_PYBULLET_ERROR}",
        ),
        (
            ("pybullet",),
            ["control", "husky", "--clock", "unix:///nonexistent/sim.sock"],
            _BUNDLED.format(name="husky"),
        ),
        (
            ("pybullet",),
            ["control", "light_scenario:Light", "--clock", "unix:///nonexistent/sim.sock"],
            _BUNDLED.format(name="light"),
        ),
        (
            ("mcap",),
            ["run", "light_scenario.py:Light", "--record", "out.mcap"],
            "error: recording needs the mcap package: pip install 'evclock[record]'",
        ),
        (
            ("mcap",),
            ["trace", "diff", "a.mcap", "b.mcap"],
            "error: reading recordings needs the mcap package: pip install 'evclock[record]'",
        ),
        pytest.param(
            ("mcap",),
            ["plot", "a.mcap", "-o", "out.png"],
            "error: reading recordings needs the mcap package: pip install 'evclock[record]'",
            marks=pytest.mark.skipif(  # plot names a missing matplotlib first
                importlib.util.find_spec("matplotlib") is None,
                reason="needs evclock[plot] (matplotlib)",
            ),
        ),
        (
            ("matplotlib",),
            ["plot", "a.mcap", "-o", "out.png"],
            "error: plots need matplotlib: pip install 'evclock[plot]'",
        ),
        (
            ("matplotlib",),
            ["sweep", "light_scenario.py:Light", "--plot", "out.png"],
            "error: plots need matplotlib: pip install 'evclock[plot]'",
        ),
        (
            ("ray",),
            ["sweep", "light_scenario.py:Light", "--backend", "ray", "--quiet"],
            "error: the ray backend needs Ray: pip install 'evclock[ray]'",
        ),
        (
            ("cyclonedds",),
            ["run", "light_scenario.py:Light", "--ros2-clock", "--quiet"],
            "error: evclock's ROS 2 support needs the 'ros2' extra (module 'cyclonedds' is "
            "missing): pip install 'evclock[ros2]'",
        ),
        (
            ("zenoh",),
            ["run", "light_scenario.py:Light", "--ros2-clock", "--rmw", "zenoh", "--quiet"],
            "error: evclock's ROS 2 support needs the 'ros2' extra (module 'zenoh' is "
            "missing): pip install 'evclock[ros2]'",
        ),
    ],
)
def test_a_command_without_its_extra_prints_one_error_line_and_exits_2(
    scenarios: Path, hide: tuple[str, ...], args: list[str], error: str
) -> None:
    for name in ("a.mcap", "b.mcap"):
        (scenarios / name).write_bytes(b"")
    result = cli(args, hide=hide, cwd=scenarios)
    assert result.returncode == 2, result.stderr
    assert one_line(result.stderr).endswith(one_line(error)), result.stderr
    assert "Traceback" not in result.stderr
