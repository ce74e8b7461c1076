"""Which ROS 2 middleware evclock speaks: chosen as a ROS node chooses its rmw implementation.

A ROS 2 node reads ``RMW_IMPLEMENTATION`` and, when it is unset, loads the distribution's
default, Fast DDS (rmw_implementation's ``RMW_IMPLEMENTATION_DEFAULT``: ``rmw_fastrtps_cpp`` in
Humble, Jazzy and Kilted). evclock speaks two wire protocols: DDS (RTPS, through Cyclone DDS,
which every DDS rmw reaches on the wire) and Zenoh (rmw_zenoh's format). An explicit
``rmw="dds"|"zenoh"`` (``--rmw``, ``?rmw=``) wins over the environment.
"""

from __future__ import annotations

import os
from typing import Final, Literal

from evclock._errors import InvalidArgumentError, InvalidTypeError

Middleware = Literal["dds", "zenoh"]
ENV_RMW_IMPLEMENTATION: Final = "RMW_IMPLEMENTATION"
"""The environment variable a ROS 2 node reads its middleware from."""
MIDDLEWARES: Final[tuple[Middleware, ...]] = ("dds", "zenoh")
"""The middlewares evclock speaks (``rmw=``)."""
DEFAULT_MIDDLEWARE: Final[Middleware] = "dds"
"""The middleware when neither ``rmw=`` nor ``RMW_IMPLEMENTATION`` says: DDS, as ROS."""
RMW_IMPLEMENTATIONS: Final[dict[str, Middleware]] = {
    "rmw_fastrtps_cpp": "dds",
    "rmw_fastrtps_dynamic_cpp": "dds",
    "rmw_cyclonedds_cpp": "dds",
    "rmw_connextdds": "dds",
    "rmw_gurumdds_cpp": "dds",
    "rmw_zenoh_cpp": "zenoh",
}
"""The ``RMW_IMPLEMENTATION`` values evclock understands, and the wire protocol each speaks."""


def resolve_middleware(rmw: object = None) -> Middleware:
    """The middleware to speak: ``rmw`` if given, else from ``RMW_IMPLEMENTATION``, else DDS.

    :param rmw: ``"dds"``, ``"zenoh"`` or None (read the environment as ROS does).
    :returns: ``"dds"`` or ``"zenoh"``.
    :raises InvalidTypeError: ``rmw`` is neither a str nor None.
    :raises InvalidArgumentError: ``rmw`` or ``RMW_IMPLEMENTATION`` names an unknown middleware.
    """
    if rmw is not None:
        if not isinstance(rmw, str):
            raise InvalidTypeError(f"rmw must be 'dds' or 'zenoh', got {type(rmw).__name__}")
        if rmw not in MIDDLEWARES:
            raise InvalidArgumentError(
                f"unknown ROS 2 middleware {rmw[:80]!r}; choose one of: {', '.join(MIDDLEWARES)}"
            )
        return rmw  # type: ignore[return-value,unused-ignore]  # checked just above
    raw = os.environ.get(ENV_RMW_IMPLEMENTATION, "").strip()
    if not raw:
        return DEFAULT_MIDDLEWARE
    try:
        return RMW_IMPLEMENTATIONS[raw]
    except KeyError:
        raise InvalidArgumentError(
            f"{ENV_RMW_IMPLEMENTATION}={raw[:80]!r} is not a middleware evclock speaks; use one "
            f"of: {', '.join(RMW_IMPLEMENTATIONS)} (or pass rmw='dds'|'zenoh')"
        ) from None
