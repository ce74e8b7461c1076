"""pytest plugin for running anyio's own test suite in the conformance runner.

Loaded with ``-p _anyio_plugin`` (its folder on ``PYTHONPATH``). It

* installs ``SimEventLoop`` when ``EVCLOCK_CONFORMANCE_LOOP=sim`` (see ``_sim_loop``);
* keeps only the plain asyncio backend (anyio also parametrises its tests with trio, uvloop
  and an eager-task factory: none of those run on the loop under test), minus the tests
  named in the file ``EVCLOCK_CONFORMANCE_SKIP`` points to (already run by a previous
  process that died); when ``EVCLOCK_CONFORMANCE_ONLY`` names a file, only the tests it
  lists run (the runner's re-run of a test that failed only on ``SimEventLoop``);
* writes each test's start and outcome to the JSON-lines file named by
  ``EVCLOCK_CONFORMANCE_OUT``, in the same format as ``_asyncio_child``.
"""

from __future__ import annotations

import json
import os
from typing import IO, Any

import pytest
from _sim_loop import install_if_requested

install_if_requested()

_out: IO[str] | None = None


def _write(nodeid: str, **fields: Any) -> None:
    global _out
    if _out is None:
        _out = open(os.environ["EVCLOCK_CONFORMANCE_OUT"], "w", encoding="utf-8")  # noqa: SIM115
    _out.write(json.dumps({"test": nodeid, **fields}) + "\n")
    _out.flush()


def _backend_id(item: pytest.Item) -> str | None:
    callspec = getattr(item, "callspec", None)
    if callspec is None or "anyio_backend" not in callspec.params:
        return None
    param = callspec.params["anyio_backend"]
    if isinstance(param, tuple):
        name, options = param
        return "asyncio" if name == "asyncio" and not options.get("loop_factory") else "other"
    return str(param)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    with open(os.environ.get("EVCLOCK_CONFORMANCE_SKIP", os.devnull), encoding="utf-8") as f:
        already_run = {line.strip() for line in f if line.strip()}
    only_file = os.environ.get("EVCLOCK_CONFORMANCE_ONLY")
    only: set[str] | None = None
    if only_file:
        with open(only_file, encoding="utf-8") as f:
            only = {line.strip() for line in f if line.strip()}
    keep, drop = [], []
    for item in items:
        backend = _backend_id(item)
        wanted = backend in (None, "asyncio") and item.nodeid not in already_run
        wanted = wanted and (only is None or item.nodeid in only)
        (keep if wanted else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
    items[:] = keep


def pytest_runtest_logstart(nodeid: str, location: object) -> None:
    _write(nodeid, event="start")


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    # One record per phase that decides something (the runner keeps the worst per test):
    # a failure in any phase, a skip in setup or call, a pass only in call.
    if report.failed:
        _write(
            report.nodeid, outcome="fail", detail=f"{report.when}: {report.longreprtext}"[-4000:]
        )
    elif report.skipped:
        if hasattr(report, "wasxfail"):
            _write(report.nodeid, outcome="pass", detail="expected failure")
        else:
            _write(report.nodeid, outcome="skip", detail=str(report.longrepr)[-500:])
    elif report.when == "call":
        _write(report.nodeid, outcome="pass")
