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


#: ``python -c`` code that runs ``argv[1]``, then the file ``argv[2]`` as ``__main__`` with
#: the arguments after it.
_RUN_AFTER = (
    "import runpy, sys; exec(sys.argv[1]); sys.argv = sys.argv[2:]; "
    "runpy.run_path(sys.argv[0], run_name='__main__')"
)


def run_example(
    name: str, *args: str, before: str = "", **env: str
) -> subprocess.CompletedProcess[str]:
    """Run ``examples/<name> <args>``; the finished process (fails on a non-zero exit).

    ``before``: Python code the process runs first (a test's switch, set before the example
    imports anything); the example then runs as its file would.
    """
    environ = {k: v for k, v in os.environ.items() if k != "EVCLOCK_USE_SIM_TIME"}
    environ.update(env)
    script = [str(EXAMPLES / name), *args]
    proc = subprocess.run(
        [sys.executable, *(("-c", _RUN_AFTER, before) if before else ()), *script],
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
