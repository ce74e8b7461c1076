"""The ``evclock`` command with an engine hidden, for tests of what a run needs alone and of
what a machine without an engine is told."""

from __future__ import annotations

import sys


def cli_without(*modules: str) -> list[str]:
    """``evclock`` run by this interpreter with ``modules`` unimportable (as if not installed):
    append the command's arguments."""
    return [
        sys.executable,
        "-c",
        "import sys\n"
        f"for name in {list(modules)!r}:\n"
        "    sys.modules[name] = None\n"
        "from evclock.tools._cli import main\n"
        "main()",
    ]


#: ``evclock`` with ``pybullet`` and ``pybullet_data`` unimportable: a MuJoCo run (in-process,
#: split, recorded) must need neither.
CLI_WITHOUT_PYBULLET = cli_without("pybullet", "pybullet_data")

#: ``evclock`` with neither engine importable.
CLI_WITHOUT_ENGINES = cli_without("pybullet", "pybullet_data", "mujoco")
