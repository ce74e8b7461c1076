"""Run one module of CPython's ``test.test_asyncio`` and record each test's outcome.

Usage (the runner calls it; one subprocess per module)::

    EVCLOCK_CONFORMANCE_LOOP=sim python _asyncio_child.py test_events results.jsonl

Each line of the results file is a JSON object: ``{"test": id, "event": "start"}`` before a
test runs, then ``{"test": id, "outcome": "pass"|"fail"|"skip", "detail": ...}``. Lines are
flushed as they are written, so when the runner kills a module that hangs, the last "start"
without an outcome names the test that hung. Tests named in the file that
``EVCLOCK_CONFORMANCE_SKIP`` points to (one id a line: those a previous process already ran)
are left out; when ``EVCLOCK_CONFORMANCE_ONLY`` names a file, only the tests it lists run
(the runner's re-run of a test that failed only on ``SimEventLoop``).
"""

from __future__ import annotations

import faulthandler
import json
import os
import sys
import traceback
import unittest
from collections.abc import Iterator
from types import TracebackType
from typing import IO, Any

from _sim_loop import install_if_requested

_PREFIX = "test.test_asyncio."
#: Wall seconds one test may take (a passing test_asyncio test takes a few seconds).
PER_TEST_TIMEOUT = 30.0
_ExcInfo = tuple[type[BaseException], BaseException, TracebackType | None]


class RecordingResult(unittest.TestResult):
    """Writes every test's start and outcome to a JSON-lines file, as it happens."""

    def __init__(self, out: IO[str]) -> None:
        super().__init__()
        self._out = out

    def _write(self, test: unittest.TestCase, **fields: Any) -> None:
        self._out.write(json.dumps({"test": test.id().removeprefix(_PREFIX), **fields}) + "\n")
        self._out.flush()

    def startTest(self, test: unittest.TestCase) -> None:
        super().startTest(test)
        self._write(test, event="start")
        # A test that hangs ends this process (stacks on stderr); the runner goes on
        # with the rest of the module in a new one.
        faulthandler.dump_traceback_later(PER_TEST_TIMEOUT, exit=True)

    def stopTest(self, test: unittest.TestCase) -> None:
        faulthandler.cancel_dump_traceback_later()
        super().stopTest(test)

    def addSuccess(self, test: unittest.TestCase) -> None:
        super().addSuccess(test)
        self._write(test, outcome="pass")

    def addExpectedFailure(self, test: unittest.TestCase, err: _ExcInfo) -> None:
        super().addExpectedFailure(test, err)
        self._write(test, outcome="pass", detail="expected failure")

    def addSkip(self, test: unittest.TestCase, reason: str) -> None:
        super().addSkip(test, reason)
        self._write(test, outcome="skip", detail=reason)

    def addFailure(self, test: unittest.TestCase, err: _ExcInfo) -> None:
        super().addFailure(test, err)
        self._write(test, outcome="fail", detail=_format(err))

    def addError(self, test: unittest.TestCase, err: _ExcInfo) -> None:
        super().addError(test, err)
        self._write(test, outcome="fail", detail=_format(err))

    def addUnexpectedSuccess(self, test: unittest.TestCase) -> None:
        super().addUnexpectedSuccess(test)
        self._write(test, outcome="fail", detail="unexpected success")

    def addSubTest(
        self, test: unittest.TestCase, subtest: unittest.TestCase, err: _ExcInfo | None
    ) -> None:
        super().addSubTest(test, subtest, err)
        if err is not None:
            self._write(test, outcome="fail", detail=f"{subtest.id()}: {_format(err)}")


def _format(err: _ExcInfo) -> str:
    return "".join(traceback.format_exception(*err))[-4000:]


def _tests(suite: unittest.TestSuite) -> Iterator[unittest.TestCase]:
    for item in suite:
        if isinstance(item, unittest.TestSuite):
            yield from _tests(item)
        else:
            yield item


def main() -> None:
    module, out_path = sys.argv[1], sys.argv[2]
    install_if_requested()
    with open(os.environ.get("EVCLOCK_CONFORMANCE_SKIP", os.devnull), encoding="utf-8") as f:
        skip = {line.strip() for line in f if line.strip()}
    only: set[str] | None = None
    if os.environ.get("EVCLOCK_CONFORMANCE_ONLY"):
        with open(os.environ["EVCLOCK_CONFORMANCE_ONLY"], encoding="utf-8") as f:
            only = {line.strip() for line in f if line.strip()}
    loaded = unittest.defaultTestLoader.loadTestsFromName(_PREFIX + module)
    suite = unittest.TestSuite(
        t
        for t in _tests(loaded)
        if t.id().removeprefix(_PREFIX) not in skip
        and (only is None or t.id().removeprefix(_PREFIX) in only)
    )
    with open(out_path, "w", encoding="utf-8") as out:
        suite.run(RecordingResult(out))


if __name__ == "__main__":
    main()
