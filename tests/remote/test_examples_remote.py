"""The remote example pair runs as documented: a served plant and a controller joining it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from _remote_helpers import ROOT, WAIT

EXAMPLES = ROOT / "examples"

CONTROLLER_OUTPUT = """\
[t=0.000 s] x = 0.000000000
[t=0.500 s] x = 0.635830320
[t=1.000 s] x = 0.867380444
[t=1.500 s] x = 0.951703979
[t=2.000 s] x = 0.982412053
[t=2.000 s] done after 200 ticks
"""


def test_remote_example_pair(tmp_path: Path) -> None:
    address = f"unix://{tmp_path / 'plant.sock'}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("EVCLOCK_")}
    sim = subprocess.Popen(
        [sys.executable, str(EXAMPLES / "remote_sim.py"), address],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    controller = subprocess.run(
        [sys.executable, str(EXAMPLES / "remote_controller.py")],
        cwd=ROOT,
        env={**env, "EVCLOCK_CLOCK": address},
        capture_output=True,
        text=True,
        timeout=WAIT,
        check=False,
    )
    sim_out, sim_err = sim.communicate(timeout=WAIT)
    assert controller.returncode == 0, controller.stderr
    assert sim.returncode == 0, sim_err
    assert controller.stdout == CONTROLLER_OUTPUT
    assert sim_out == (
        f"serving sim time at {address}\n[t=2.000 s] the controller left; x = 0.982412053\n"
    )
