"""The Starlette app: the dashboard page, its static files and the JSON API.

========================  ==========================================================
``GET  /``                the dashboard page
``GET  /api/state``       sim time, physics steps, pause state, requested and achieved
                          real-time factor, the driver's lockstep overruns, per-loop
                          statistics, episodes
``GET  /api/history``     the sampled history the plots show, as columns
``GET  /api/scene.jpg``   the live view of the world (JPEG), with headers ``X-Frame``,
                          ``X-Sim-Time-Ns``, ``X-Physics-Steps``, ``X-Episode``
``POST /api/pause``       pause sim time; answers with the state
``POST /api/resume``      resume; answers with the state
``POST /api/step``        ``{"count": n}`` (default 1): while paused, advance exactly n
                          physics steps; answers once they are done, with the state and
                          ``"step": {"count", "time_ns"}``; 409 if a pause interrupted
                          them, 504 if they took over ``step_timeout`` wall seconds (the
                          rest are cancelled either way: nothing steps on in the background)
``POST /api/rtf``         ``{"rtf": k}`` (a positive number, or null: as fast as
                          possible); answers with the state
========================  ==========================================================

Errors are JSON ``{"error": message, "type": name}``: evclock's own errors (stepping while
running, ``rtf <= 0``, a count that is not a positive int) and malformed bodies answer 400;
a step that did not complete answers ``"type": "StepNotCompleted"`` with ``"step": {"count",
"taken", "reason"}``.

The page is served with the current state embedded, so it shows the simulation at once,
before its first poll.
"""

from __future__ import annotations

import contextlib
import html
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

import evclock

from .config import DashboardConfig
from .sim import SimService, StepNotCompleted

STATIC = Path(__file__).resolve().parent / "static"
PAGE = STATIC / "index.html"
"""The page template: ``{{ scenario }}`` (HTML text) and ``{{ state_json }}`` are filled in."""
_NO_CACHE = {"Cache-Control": "no-store"}


def _service(request: Request) -> SimService:
    service: SimService = request.app.state.sim
    return service


async def _json_object(request: Request) -> dict[str, Any]:
    """The request body as a JSON object; an empty body is ``{}``; 400 otherwise."""
    raw = await request.body()
    if not raw.strip():
        return {}
    try:
        body = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise HTTPException(400, f"the request body is not valid JSON: {exc}") from None
    if not isinstance(body, dict):
        raise HTTPException(400, f"the request body must be a JSON object, got {body!r}")
    return body


def _state_response(service: SimService, **extra: Any) -> JSONResponse:
    return JSONResponse({**service.state(), **extra}, headers=_NO_CACHE)


def _embed_json(value: Any) -> str:
    """``value`` as JSON that is safe inside an HTML ``<script>`` element."""
    text = json.dumps(value, allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


async def index(request: Request) -> Response:
    """The dashboard page, with the current state embedded (no "connecting..." wait)."""
    state = _service(request).state()
    page = PAGE.read_text(encoding="utf-8")
    page = page.replace("{{ scenario }}", html.escape(_scenario_line(state)))
    page = page.replace("{{ state_json }}", _embed_json(state))
    return HTMLResponse(page, headers=_NO_CACHE)


def _scenario_line(state: dict[str, Any]) -> str:
    scenario = state["scenario"]
    return f"{scenario['name']}: {scenario['description']}"


async def get_state(request: Request) -> Response:
    """``GET /api/state``."""
    return _state_response(_service(request))


async def get_history(request: Request) -> Response:
    """``GET /api/history``."""
    return JSONResponse(_service(request).history(), headers=_NO_CACHE)


async def get_scene(request: Request) -> Response:
    """``GET /api/scene.jpg``: the latest frame of the scene view."""
    frame = await _service(request).scene.frame()
    headers = {
        **_NO_CACHE,
        "X-Frame": str(frame.number),
        "X-Sim-Time-Ns": str(frame.sim_time_ns),
        "X-Physics-Steps": str(frame.physics_steps),
        "X-Episode": str(frame.episode),
    }
    return Response(frame.jpeg, media_type="image/jpeg", headers=headers)


async def post_pause(request: Request) -> Response:
    """``POST /api/pause``."""
    service = _service(request)
    service.pause()
    return _state_response(service)


async def post_resume(request: Request) -> Response:
    """``POST /api/resume``."""
    service = _service(request)
    service.resume()
    return _state_response(service)


async def post_step(request: Request) -> Response:
    """``POST /api/step`` with ``{"count": n}``."""
    service = _service(request)
    body = await _json_object(request)
    result = await service.step(body.get("count", 1))
    return _state_response(service, step={"count": result.count, "time_ns": result.time_ns})


async def post_rtf(request: Request) -> Response:
    """``POST /api/rtf`` with ``{"rtf": k}`` (null: as fast as possible)."""
    service = _service(request)
    body = await _json_object(request)
    if "rtf" not in body:
        raise HTTPException(400, 'the request body must be {"rtf": <positive number or null>}')
    service.set_rtf(body["rtf"])
    return _state_response(service)


def _error(status: int, message: str, kind: str) -> JSONResponse:
    return JSONResponse({"error": message, "type": kind}, status_code=status)


async def _evclock_error(request: Request, exc: Exception) -> Response:
    return _error(400, str(exc), type(exc).__name__)


async def _step_not_completed(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StepNotCompleted)
    status = 409 if exc.reason == "interrupted" else 504
    step = {"count": exc.count, "taken": exc.taken, "reason": exc.reason}
    body = {"error": str(exc), "type": "StepNotCompleted", "step": step}
    return JSONResponse(body, status_code=status, headers=_NO_CACHE)


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, HTTPException)
    return _error(exc.status_code, exc.detail, "HTTPException")


def create_app(config: DashboardConfig | None = None) -> Starlette:
    """The dashboard app; its lifespan starts the simulation on the loop that serves it."""
    config = config if config is not None else DashboardConfig()

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        async with SimService(config) as service:
            app.state.sim = service
            yield

    routes = [
        Route("/", index),
        Route("/api/state", get_state),
        Route("/api/history", get_history),
        Route("/api/scene.jpg", get_scene),
        Route("/api/pause", post_pause, methods=["POST"]),
        Route("/api/resume", post_resume, methods=["POST"]),
        Route("/api/step", post_step, methods=["POST"]),
        Route("/api/rtf", post_rtf, methods=["POST"]),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    handlers = {
        evclock.EvClockError: _evclock_error,
        StepNotCompleted: _step_not_completed,
        HTTPException: _http_error,
    }
    return Starlette(routes=routes, lifespan=lifespan, exception_handlers=handlers)
