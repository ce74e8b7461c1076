"""Zenoh sessions for ROS 2 interop: the optional dependencies and the session configuration.

``import evclock`` never imports Zenoh: the ``ros2`` extra's modules are imported here, on
first use, and a missing one raises :class:`~evclock.MissingExtraError` naming the extra.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Sequence
from typing import Any, Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, MissingExtraError

DEFAULT_CONNECT: Final = ("tcp/127.0.0.1:7447",)
"""Where rmw_zenoh's router listens by default (``ros2 run rmw_zenoh_cpp rmw_zenohd``), on
loopback: a ROS 2 graph on this machine is reached through it."""
DEFAULT_LISTEN: Final = ("tcp/127.0.0.1:0",)
"""Where evclock's session accepts direct peer connections (rmw_zenoh peers connect to each
other after the router introduced them); port 0 = any free port."""
#: How often a peer retries an endpoint that is not up yet (wall ms): first, then at most.
_RETRY_INIT_MS: Final = 100
_RETRY_MAX_MS: Final = 1000


def require(module: str) -> Any:
    """Import one of the ``ros2`` extra's modules, or say how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"evclock's ROS 2 support needs the 'ros2' extra (module {module!r} is missing): "
            "pip install 'evclock[ros2]'"
        ) from exc


def check_endpoints(endpoints: object, what: str) -> tuple[str, ...]:
    """Zenoh endpoints such as ``tcp/127.0.0.1:7447`` or ``unixsock-stream/path``."""
    if isinstance(endpoints, str):
        endpoints = (endpoints,)
    if not isinstance(endpoints, Sequence):
        raise InvalidTypeError(
            f"{what} takes a sequence of Zenoh endpoints (e.g. ['tcp/127.0.0.1:7447']), "
            f"got {type(endpoints).__name__}"
        )
    result = []
    for endpoint in endpoints:
        if not isinstance(endpoint, str) or "/" not in endpoint:
            raise InvalidArgumentError(
                f"{what}: {endpoint!r} is not a Zenoh endpoint; write <protocol>/<address>, "
                "e.g. tcp/127.0.0.1:7447 or unixsock-stream/tmp/clock.sock"
            )
        result.append(endpoint)
    return tuple(result)


def session_config(connect: Sequence[str], listen: Sequence[str]) -> dict[str, Any]:
    """A peer-mode session as rmw_zenoh configures its nodes, without multicast scouting:
    peers are found through ``connect`` endpoints (a router, or another peer) and gossip."""
    return {
        "mode": "peer",
        "connect": {
            "endpoints": list(connect),
            "retry": {"period_init_ms": _RETRY_INIT_MS, "period_max_ms": _RETRY_MAX_MS},
        },
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}},
    }


def open_session(connect: Sequence[str], listen: Sequence[str]) -> Any:
    """Open a Zenoh session (``zenoh.Session``) with :func:`session_config`."""
    zenoh = require("zenoh")
    config = zenoh.Config.from_json5(json.dumps(session_config(connect, listen)))
    return zenoh.open(config)
