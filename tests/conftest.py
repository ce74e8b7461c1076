"""Shared set-up of the test suite: the repository root on sys.path (for ``examples``), the
evclock under test, the PyBullet rule, Ctrl-C for child processes, DDS on loopback only.

The repository root is *appended* to sys.path, so an installed evclock is imported before
a package folder beside the tests. CI tests the installed wheel from a copy of the
repository without the package folders (so that no child process a test starts can import
them either), with ``EVCLOCK_TEST_INSTALLED=1``: the session then refuses to start if evclock
comes from an ``evclock/`` folder of the tree under test. The header line names the evclock
that runs.

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
import itertools
import os
import signal
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))
INSTALLED_ONLY = os.environ.get("EVCLOCK_TEST_INSTALLED") == "1"

#: PyBullet's ``client`` and ``client2`` fixtures, shared by the modules that drive it.
pytest_plugins = ["_pybullet_fixtures"]

HAVE_PYBULLET = importlib.util.find_spec("pybullet") is not None
_PYBULLET_WHEELS = sys.version_info < (3, 12)  # as the test extra's marker says
_SKIP_REASON = "PyBullet is not installed: pip install 'evclock[pybullet]'"
#: Cyclone DDS on the loopback interface only, multicast off, peers found by unicast on
#: 127.0.0.1: every DDS participant of the suite (and of the processes it starts, docs blocks
#: included) stays on the host. Cyclone DDS reads CYCLONEDDS_URI as a file URI or inline XML.
LOOPBACK_CYCLONEDDS = (
    '<CycloneDDS xmlns="https://cdds.io/config"><Domain id="any"><General><Interfaces>'
    '<NetworkInterface address="127.0.0.1"/></Interfaces><AllowMulticast>false'
    "</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers>"
    '<Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
)


_dds_domains = itertools.count()


@pytest.fixture
def loopback_dds(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> int:
    """A ROS domain of this test's own, on a loopback-only Cyclone DDS configuration
    (``CYCLONEDDS_URI`` names it; ``ROS_DOMAIN_ID`` holds the domain; DDS, ROS's default
    middleware, is chosen). Concurrent workers of one session get disjoint bands of domains,
    and concurrent sessions (on one machine) different offsets."""
    config = tmp_path / "cyclonedds.xml"
    config.write_text(LOOPBACK_CYCLONEDDS)
    monkeypatch.setenv("CYCLONEDDS_URI", config.as_uri())
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    session = os.getppid() if "PYTEST_XDIST_WORKER" in os.environ else os.getpid()
    band = index * 50 + next(_dds_domains) % 50
    domain = 20 + (session * 37 + band) % 210  # domains 20..229: Cyclone's ports fit
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    return domain


def pytest_configure(config: pytest.Config) -> None:
    os.environ["CYCLONEDDS_URI"] = LOOPBACK_CYCLONEDDS
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # A suite started as a background job of a non-interactive shell inherits SIGINT
        # ignored, and so would every child it starts; the tests that press Ctrl-C on a child
        # (a sweep, the dashboard) need it delivered, as from a terminal.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    import evclock

    location = Path(evclock.__file__).resolve()
    if INSTALLED_ONLY and location.is_relative_to(ROOT / "evclock"):
        raise pytest.UsageError(
            f"EVCLOCK_TEST_INSTALLED=1 but evclock is imported from the tree under test "
            f"({location}): install the wheel, and run the tests from a copy of the "
            "repository without evclock/ (as .ci/run does)"
        )
    if _PYBULLET_WHEELS and not HAVE_PYBULLET:
        raise pytest.UsageError(
            "PyBullet is missing, and on this Python the full suite needs it: "
            "pip install -e '.[test]' installs it"
        )


def pytest_report_header() -> str:
    import evclock

    return f"evclock {evclock.__version__} from {Path(evclock.__file__).resolve().parent}"


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
