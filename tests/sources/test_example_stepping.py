"""The custom stepping source example runs and prints exact sim times."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_custom_stepping_source_example() -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "custom_stepping_source.py")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        "0.000000000 s (sim): x = +1.000",
        "0.200000000 s (sim): x = +0.921",
        "0.400000000 s (sim): x = +0.696",
        "0.600000000 s (sim): x = +0.361",
        "600 steps in 0.600000000 s (sim)",
        "the mass came back at 3.071000000 s (sim)",
        "a sleeper was woken by the jump: -1.000000000 s",
        "restored to 3.071000000 s (sim), x = +0.990",
    ]
