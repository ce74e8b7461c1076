"""The distribution: a wheel built from this source tree holds every module and data file of
the package, so an installed evclock imports exactly what the checkout does.

The regression this guards: the wheel once left out ``evclock/_remote/`` (now
``evclock/remote/``), so a non-editable install could not ``import evclock`` and, through the
``pytest11`` entry point, broke every pytest run in that environment.

CI builds the wheel once and passes it in ``EVCLOCK_WHEEL``, and runs the suite from a copy
of the repository without the package folders, naming the source tree in
``EVCLOCK_SOURCE_TREE``; without them the test builds a wheel (PEP 517, through ``python -m
build``) from this checkout and compares it with this checkout.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(os.environ.get("EVCLOCK_SOURCE_TREE") or Path(__file__).resolve().parent.parent)
#: Each installed package and its folder in the source tree (pyproject.toml's package-dir).
PACKAGES = {"evclock": "evclock", "evclock_sims": "sims"}
# Files the package needs at run time besides its modules.
DATA_FILES = (
    "evclock/py.typed",
    "evclock/tools/foxglove_layout.json",  # the saved Foxglove layout (evclock trace layout)
    # The robot models of the MuJoCo scenarios, used where pybullet_data is absent.
    "evclock_sims/models/LICENSE.txt",
    "evclock_sims/models/cartpole.urdf",
    "evclock_sims/models/kuka_iiwa/model.urdf",
    *(f"evclock_sims/models/kuka_iiwa/meshes/link_{i}.stl" for i in range(8)),
)


def source_files() -> set[str]:
    """Every module and needed data file of the source tree, as wheel paths."""
    found: set[str] = set(DATA_FILES)
    for package, folder in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            found.add(f"{package}/{path.relative_to(ROOT / folder).as_posix()}")
    return found


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    given = os.environ.get("EVCLOCK_WHEEL")
    if given:
        return Path(given)
    pytest.importorskip("build", reason="the test extra installs `build`")
    # Built from a copy: setuptools writes evclock.egg-info into the tree it builds, and in
    # the checkout that would race with the tests that list the installed scenarios meanwhile.
    tree = tmp_path_factory.mktemp("tree")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, tree / name)
    for folder in PACKAGES.values():
        shutil.copytree(ROOT / folder, tree / folder, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("dist")
    subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(out), str(tree)],
        check=True,
        capture_output=True,
        timeout=600,
    )
    (built,) = out.glob("evclock-*.whl")
    return built


def test_the_source_tree_is_where_this_test_expects_it() -> None:
    # Guards the next test against comparing an empty listing with an empty wheel.
    assert "evclock/__init__.py" in source_files()
    assert "evclock/remote/__init__.py" in source_files()
    assert "evclock_sims/kuka.py" in source_files()


def test_the_wheel_holds_every_module_of_the_source_tree(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        in_wheel = set(archive.namelist())
    missing = sorted(source_files() - in_wheel)
    assert missing == [], f"the wheel {wheel.name} leaves out {missing}"


def test_the_wheel_declares_its_command_and_pytest_plugin(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        (entry_points,) = (n for n in archive.namelist() if n.endswith("entry_points.txt"))
        text = archive.read(entry_points).decode()
    assert "[console_scripts]\nevclock = evclock.tools._cli:main" in text
    assert "[pytest11]\nevclock = evclock.testing.plugin" in text
