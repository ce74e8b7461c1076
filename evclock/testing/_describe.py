"""Where a test is, told for its failure report: its loop's tasks (the test's own labelled)
and a traceback through the lines where a coroutine waits - leaving out the machinery of
pytest, asyncio, anyio and evclock itself."""

from __future__ import annotations

import asyncio
import os
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any, Final

from evclock._errors import DeadlockError
from evclock.hosts._tasks import coroutine_frames
from evclock.hosts._tasks import describe_tasks as _describe_loop_tasks

if TYPE_CHECKING:
    from evclock.testing._guard import CallGuard

#: Frames of the machinery between a task and the test (the guard's ``evclock_test`` and
#: ``_run_guarded``, anyio's test runner).
_MACHINERY_CODE_NAMES: Final = frozenset(
    {"evclock_test", "_run_guarded", "_run_tests_and_fixtures"}
)

#: The evclock package (this plugin included).
_PACKAGE_DIR: Final = (
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))).replace("\\", "/") + "/"
)
_MACHINERY_PATHS: Final = ("/_pytest/", "/pluggy/", "/asyncio/", "/anyio/", _PACKAGE_DIR)


def describe_tasks(
    loop: asyncio.AbstractEventLoop, test_task: asyncio.Task[Any] | None
) -> tuple[str, ...]:
    """``Task-3 (the test): test_x() at f.py:12 -> helper() at g.py:4, waiting on <...>``, one
    line per pending task of ``loop``."""
    labels = {test_task: "the test"} if test_task is not None else None
    return _describe_loop_tasks(loop, labels=labels, hidden=_MACHINERY_CODE_NAMES)


def _suspended_traceback(coro: object) -> TracebackType | None:
    """A traceback through the lines where a suspended coroutine chain waits (for reports)."""
    tb: TracebackType | None = None
    for frame in reversed(coroutine_frames(coro)):
        if frame.f_code.co_name not in _MACHINERY_CODE_NAMES and _is_user_code(frame):
            tb = TracebackType(tb, frame, frame.f_lasti, frame.f_lineno)
    return tb


def explain_deadlock(exc: DeadlockError, call: CallGuard) -> DeadlockError:
    """The loop's DeadlockError, retold from the test's side: each task's whole await chain
    (the test's own line included) and a traceback that points at where the test waits."""
    if call.loop.is_closed() or getattr(call.coro, "cr_frame", None) is None:
        return exc
    tasks = describe_tasks(call.loop, call.task)
    head = str(exc).split("\n", 1)[0]
    better = DeadlockError(head + "\n" + "\n".join(f"  {line}" for line in tasks), tasks)
    return better.with_traceback(_suspended_traceback(call.coro))


def _is_machinery(path: str) -> bool:
    """Whether code at ``path`` belongs to pytest, asyncio, anyio or evclock itself."""
    path = path.replace("\\", "/")
    return any(part in path for part in _MACHINERY_PATHS)


def _is_user_code(frame: FrameType) -> bool:
    return not _is_machinery(frame.f_code.co_filename)
