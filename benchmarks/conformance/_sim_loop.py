"""Make every new asyncio event loop in this process a ``SimEventLoop``.

Imported by the conformance children when ``EVCLOCK_CONFORMANCE_LOOP=sim``. It replaces the
loop class asyncio hands out, so that the suites run unmodified:

* ``asyncio.new_event_loop()``, ``asyncio.run()`` and ``asyncio.Runner()`` go through the
  default event-loop policy, whose loop factory becomes ``SimEventLoop``;
* tests that build ``asyncio.SelectorEventLoop(selector)`` directly get a ``SimEventLoop``
  on that selector (it takes a selector as its first positional argument for this reason);
  so do those that pass ``asyncio.EventLoop`` (3.13) as a loop factory.

The policy class attribute is patched rather than a policy installed, because test_asyncio
resets the policy (``set_event_loop_policy(None)``) after almost every test.
"""

from __future__ import annotations

import asyncio
import os
import signal
import sys

import evclock

LOOP_ENV = "EVCLOCK_CONFORMANCE_LOOP"


def install_if_requested() -> str:
    """Install ``SimEventLoop`` when the environment asks for it; return the loop's name."""
    # A runner started in the background (``cmd &``) hands its children SIGINT ignored;
    # test_asyncio's interrupt tests need Python's own handler, on either loop.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    which = os.environ.get(LOOP_ENV, "default")
    if which == "sim":
        asyncio.SelectorEventLoop = evclock.SimEventLoop  # type: ignore[misc]
        if sys.platform != "win32":
            import asyncio.unix_events as unix_events

            unix_events.SelectorEventLoop = evclock.SimEventLoop  # type: ignore[misc]
            if hasattr(unix_events, "EventLoop"):  # 3.13: the platform's default loop class
                unix_events.EventLoop = evclock.SimEventLoop
        if hasattr(asyncio, "EventLoop"):  # 3.13: asyncio.EventLoop, e.g. as a loop_factory
            asyncio.EventLoop = evclock.SimEventLoop
            unix_events._UnixDefaultEventLoopPolicy._loop_factory = evclock.SimEventLoop  # type: ignore[attr-defined]
    elif which != "default":
        raise SystemExit(f"{LOOP_ENV} must be 'default' or 'sim', got {which!r}")
    return which
