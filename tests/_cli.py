"""Running the ``evclock`` command as a user does (``python -m evclock ARGS...``), for the
tests that check its exit status and output.

One place for how: this interpreter, output captured as text, the exit status left to the
test, and a wall-time bound that guards against hangs on a loaded machine (not a timing
check).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path

#: Wall seconds, below the suite's per-test pytest-timeout (300 s), so that a hang fails its
#: test with the child's output instead of ending the whole session.
TIMEOUT = 240


def run_evclock(
    *args: str, cwd: Path | None = None, env: Mapping[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``evclock <args>`` in ``cwd`` (default: this one) with ``env`` (default: this
    process's environment); the finished process, whatever its exit status."""
    return subprocess.run(
        [sys.executable, "-m", "evclock", *args],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        cwd=cwd,
        env=env,
        check=False,
    )


def run_command(
    command: list[str], *args: str, cwd: Path | None = None, columns: int = 200
) -> subprocess.CompletedProcess[str]:
    """Run ``command`` (an ``evclock`` command line, such as one with an engine hidden) with
    ``args`` in ``cwd``, as on a terminal ``columns`` wide without colours; the finished
    process, whatever its exit status."""
    return subprocess.run(
        [*command, *args],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
        cwd=cwd,
        env={**os.environ, "COLUMNS": str(columns), "NO_COLOR": "1"},
    )


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (a wrapped line's breaks too) as one space."""
    return " ".join(text.split())


def interrupt_when(
    marker: Path, proc: subprocess.Popen[str], cleanup: Callable[[], None] = lambda: None
) -> tuple[str, str]:
    """Press Ctrl-C (SIGINT) on ``proc`` once ``marker`` exists (waiting at most half of
    :data:`TIMEOUT`); its stdout and stderr once it exited. A process still running on the way
    out is killed, then ``cleanup`` runs (to end what it started)."""
    try:
        deadline = time.monotonic() + TIMEOUT / 2
        while not marker.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert marker.exists(), proc.communicate(timeout=10)
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=TIMEOUT / 4)
    finally:
        if proc.poll() is None:
            proc.kill()
            cleanup()
            proc.communicate(timeout=10)
