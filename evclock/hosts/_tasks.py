"""Where asyncio tasks are, told for error messages: each task's await chain and what it waits on.

One implementation for the loop's own reports (:class:`DeadlockError`, :class:`StallError`) and
for the pytest plugin's (which hides its own frames and labels the test's task).
"""

from __future__ import annotations

import asyncio
from collections.abc import Collection, Mapping
from types import FrameType
from typing import Any

from evclock._cpython import UNKNOWN, task_waiter


def coroutine_frames(coro: object) -> list[FrameType]:
    """The frames of a suspended coroutine's await chain, outermost first.

    The chain is followed through ``cr_await`` / ``gi_yieldfrom`` for as long as it leads to
    another coroutine or generator; it ends at what the innermost one waits on (a future).
    """
    frames: list[FrameType] = []
    while coro is not None:
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is not None:
            frames.append(frame)
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
        if not (hasattr(coro, "cr_frame") or hasattr(coro, "gi_frame")):
            break
    return frames


def describe_task(
    task: asyncio.Task[Any], *, label: str | None = None, hidden: Collection[str] = ()
) -> str:
    """``name: outer() at file:line -> ... -> inner() at file:line, waiting on <future>``.

    ``label`` is shown after the name (``Task-3 (the test): ...``); the frames of functions
    named in ``hidden`` (machinery between the task and the code of interest) are left out.
    Without frames to show, the task is ``running`` or shown as its coroutine's repr.
    """
    coro: Any = task.get_coro()
    where = " -> ".join(
        f"{frame.f_code.co_qualname.rpartition('<locals>.')[2]}() at "
        f"{frame.f_code.co_filename}:{frame.f_lineno}"
        for frame in coroutine_frames(coro)
        if frame.f_code.co_name not in hidden
    )
    if not where:
        where = "running" if getattr(coro, "cr_running", False) else repr(coro)
    waiter = task_waiter(task)
    known = waiter is not None and waiter is not UNKNOWN
    waits_on = f", waiting on {_short(waiter)}" if known else ""
    name = task.get_name() if label is None else f"{task.get_name()} ({label})"
    return f"{name}: {where}{waits_on}"


def describe_tasks(
    loop: asyncio.AbstractEventLoop,
    *,
    labels: Mapping[asyncio.Task[Any], str] | None = None,
    hidden: Collection[str] = (),
) -> tuple[str, ...]:
    """One :func:`describe_task` line per pending task of ``loop``, in order of task name;
    ``labels`` gives some tasks a label."""
    tasks = sorted((t for t in asyncio.all_tasks(loop) if not t.done()), key=lambda t: t.get_name())
    labels = labels or {}
    return tuple(describe_task(t, label=labels.get(t), hidden=hidden) for t in tasks)


def _short(obj: object) -> str:
    text = repr(obj)
    return text if len(text) <= 120 else text[:117] + "..."
