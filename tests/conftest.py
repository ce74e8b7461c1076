"""Shared set-up of the test suite: the repository root on sys.path (for ``examples``), and
the PyBullet rule, Ctrl-C for child processes.

PyBullet publishes wheels for CPython 3.11 only, so the ``test`` extra installs it there and
nowhere else. Tests that need it are skipped where it is missing - whole modules through
``pytest.importorskip("pybullet")``, single tests through ``@pytest.mark.pybullet`` - and a
missing PyBullet on 3.11 is an error, so that the full suite can never skip them silently.

A failure is also written out when it happens, not only in the end-of-session summary: a hang
later in the session ends it at once (pytest-timeout's thread method dumps the stacks and
exits), and the failures before it would otherwise be lost with the summary.
"""

from __future__ import annotations

import importlib.util
import signal
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

HAVE_PYBULLET = importlib.util.find_spec("pybullet") is not None
_PYBULLET_WHEELS = sys.version_info < (3, 12)  # as the test extra's marker says
_SKIP_REASON = "PyBullet is not installed: pip install 'evclock[pybullet]'"


def pytest_configure(config: pytest.Config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # A suite started as a background job of a non-interactive shell inherits SIGINT
        # ignored, and so would every child it starts; the tests that press Ctrl-C on a child
        # (a sweep, the dashboard) need it delivered, as from a terminal.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if _PYBULLET_WHEELS and not HAVE_PYBULLET:
        raise pytest.UsageError(
            "PyBullet is missing, and on this Python the full suite needs it: "
            "pip install -e '.[test]' installs it"
        )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    if HAVE_PYBULLET:
        return
    skip = pytest.mark.skip(reason=_SKIP_REASON)
    for item in items:
        if item.get_closest_marker("pybullet") is not None:
            item.add_marker(skip)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if not report.failed:
        return
    terminal = _terminal
    if terminal is None:
        return
    terminal.write_line("")
    terminal.write_sep("!", f"FAILED ({report.when}) {report.nodeid}", red=True)
    terminal.write_line(report.longreprtext)
    terminal.write_sep("!", "end of failure (the summary repeats it)", red=True)


_terminal: pytest.TerminalReporter | None = None


@pytest.hookimpl(trylast=True)
def pytest_sessionstart(session: pytest.Session) -> None:
    global _terminal
    _terminal = session.config.pluginmanager.get_plugin("terminalreporter")
