"""Serve the app in-process: uvicorn on a background thread with its own event loop.

For tests, notebooks and scripts that need the dashboard running beside them::

    with BackgroundServer(create_app(DashboardConfig(paused=True))) as server:
        httpx.get(server.url + "/api/state")
"""

from __future__ import annotations

import threading
import time
from types import TracebackType
from typing import Literal

import uvicorn
from starlette.types import ASGIApp


class BackgroundServer:
    """uvicorn serving ``app`` on ``host:port`` (port 0: a free port) from a daemon thread.

    ``loop`` is uvicorn's event loop choice: ``"auto"`` (uvloop when installed, else
    asyncio), ``"asyncio"`` or ``"uvloop"``. :meth:`start` returns once the app's lifespan
    has started and the socket listens (or raises if the server failed to start); :meth:`stop`
    shuts it down gracefully.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        loop: Literal["auto", "asyncio", "uvloop"] = "auto",
        timeout: float = 30.0,
    ) -> None:
        config = uvicorn.Config(
            app, host=host, port=port, loop=loop, log_config=None, log_level="warning", ws="none"
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(
            target=self._server.run, name="dashboard-server", daemon=True
        )
        self._timeout = timeout

    def start(self) -> None:
        """Start serving; wait (at most ``timeout`` wall seconds) until the server is up."""
        self._thread.start()
        deadline = time.monotonic() + self._timeout
        while not self._server.started:
            if not self._thread.is_alive():
                raise RuntimeError("the dashboard server failed to start (see the log)")
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"the dashboard server did not start in {self._timeout} s")
            time.sleep(0.01)

    def stop(self) -> None:
        """Ask the server to exit and wait for it (the app's lifespan shuts down too)."""
        self._server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(self._timeout)

    @property
    def port(self) -> int:
        """The port the server listens on (the chosen one when created with port 0)."""
        sockets = self._server.servers[0].sockets
        port: int = sockets[0].getsockname()[1]
        return port

    @property
    def url(self) -> str:
        """``http://host:port``, without a trailing slash."""
        return f"http://{self._server.config.host}:{self.port}"

    def __enter__(self) -> BackgroundServer:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
