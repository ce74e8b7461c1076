"""Running an example as its docstring says (``python examples/NAME ARGS...``), for the tests
that check what it prints, and importing a file that is not on ``sys.path`` (an example, a docs
hook) for the tests that call its functions.

One place for how: this interpreter, from the repository root, without
``EVCLOCK_USE_SIM_TIME`` in the environment unless the test sets it, output captured, and a
wall-time bound that guards against hangs on a loaded machine (not a timing check).
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
TIMEOUT = 300  # wall seconds


def run_example(name: str, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run ``examples/<name> <args>``; the finished process (fails on a non-zero exit)."""
    environ = {k: v for k, v in os.environ.items() if k != "EVCLOCK_USE_SIM_TIME"}
    environ.update(env)
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        cwd=ROOT,
        env=environ,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    assert proc.returncode == 0, f"{name} exited {proc.returncode}:\n{proc.stdout}{proc.stderr}"
    return proc


def output_lines(proc: subprocess.CompletedProcess[str]) -> list[str]:
    """The example's stdout lines, without the build banner PyBullet prints on start-up."""
    return [line for line in proc.stdout.splitlines() if not line.startswith("pybullet build")]


def load_module(path: Path) -> ModuleType:
    """Import the file at ``path`` as a module named after it, without touching ``sys.path``."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
