"""The ``evclock`` command with PyBullet hidden, for tests of what MuJoCo runs need alone."""

from __future__ import annotations

import sys

#: ``evclock`` run by this interpreter with ``pybullet`` and ``pybullet_data`` unimportable: a
#: MuJoCo run (in-process, split, recorded) must need neither.
CLI_WITHOUT_PYBULLET = [
    sys.executable,
    "-c",
    "import sys\n"
    "sys.modules['pybullet'] = sys.modules['pybullet_data'] = None\n"
    "from evclock.tools._cli import main\n"
    "main()",
]
