"""``evclock run SIM --ros2-clock``: the command-line options and the publishing they start.

``evclock/_cli.py`` declares these options with the types below and wraps the simulation run
in :func:`publishing`; everything ROS 2 specific stays here.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import TYPE_CHECKING, Annotated, Any

import typer

from evclock._errors import InvalidArgumentError
from evclock.ros2._publisher import (
    Ros2ClockPublisher,
    check_subscriber_count,
    check_wait_timeout,
)
from evclock.ros2._rmw import (
    ENV_RMW_IMPLEMENTATION,
    MIDDLEWARES,
    Middleware,
    resolve_middleware,
)
from evclock.ros2._session import DEFAULT_CONNECT, DEFAULT_LISTEN, check_endpoints
from evclock.ros2._wire import (
    DEFAULT_WIRE_FORMAT as DEFAULT_WIRE_FORMAT,  # the --ros2-wire-format default
)
from evclock.ros2._wire import (
    ENV_ROS_DOMAIN_ID,
    WIRE_FORMATS,
    check_frame_prefix,
    clock_key_expr,
    resolve_domain_id,
    wire_format,
)

DEFAULT_WAIT_TIMEOUT = 60.0
"""Wall seconds ``--ros2-wait-for-subscribers`` waits at most (``--ros2-wait-timeout``)."""

if TYPE_CHECKING:
    from evclock.sources import SteppingTimeSource

Ros2ClockFlag = Annotated[
    bool,
    typer.Option(
        "--ros2-clock",
        help="Publish sim time as ROS 2 /clock over DDS or Zenoh (see --rmw; ros2 extra).",
    ),
]
Ros2Flag = Annotated[
    bool,
    typer.Option(
        "--ros2",
        help="Publish /clock, /joint_states, /tf and /tf_static on sim time over DDS (ros2 extra).",
    ),
]
Rmw = Annotated[
    str | None,
    typer.Option(
        "--rmw",
        help=f"ROS 2 middleware: {' or '.join(MIDDLEWARES)} (default: from "
        f"${ENV_RMW_IMPLEMENTATION}, else dds).",
    ),
]
RosDomainId = Annotated[
    int | None,
    typer.Option("--ros-domain-id", help=f"ROS domain id (default: ${ENV_ROS_DOMAIN_ID}, else 0)."),
]
Ros2ClockDecimation = Annotated[
    int,
    typer.Option(
        "--ros2-clock-decimation", help="Publish /clock every K physics steps (1 = every step)."
    ),
]
Ros2WireFormat = Annotated[
    str,
    typer.Option(
        "--ros2-wire-format",
        help=f"rmw_zenoh wire variant: {', '.join(WIRE_FORMATS)} (default {DEFAULT_WIRE_FORMAT}).",
    ),
]
Ros2Connect = Annotated[
    list[str] | None,
    typer.Option(
        "--ros2-connect",
        help=f"Zenoh endpoint to connect to, repeatable (default {DEFAULT_CONNECT[0]}: "
        "rmw_zenoh's router).",
    ),
]
Ros2Listen = Annotated[
    list[str] | None,
    typer.Option(
        "--ros2-listen",
        help=f"Zenoh endpoint accepting peers, repeatable (default {DEFAULT_LISTEN[0]}).",
    ),
]
Ros2FramePrefix = Annotated[
    str,
    typer.Option(
        "--ros2-frame-prefix",
        help="With --ros2: prepended to every TF frame (the URDF's link names), as "
        "robot_state_publisher's frame_prefix, e.g. robot1/ (world is never prefixed).",
    ),
]
Ros2WaitForSubscribers = Annotated[
    int | None,
    typer.Option(
        "--ros2-wait-for-subscribers",
        help="Hold sim time at its start, publishing it as /clock, until N /clock "
        "subscriptions matched (DDS).",
    ),
]
Ros2WaitTimeout = Annotated[
    float,
    typer.Option(
        "--ros2-wait-timeout",
        help="Wall seconds --ros2-wait-for-subscribers waits at most before failing.",
    ),
]


@dataclasses.dataclass(frozen=True)
class Ros2ClockOptions:
    """What ``--ros2-clock`` and its companions asked for, validated."""

    domain_id: int
    decimation: int
    wire_format: str
    connect: tuple[str, ...] | None
    listen: tuple[str, ...] | None
    middleware: Middleware = "dds"
    robot_state: bool = False
    frame_prefix: str = ""
    wait_for_subscribers: int | None = None
    wait_timeout: float = DEFAULT_WAIT_TIMEOUT

    @property
    def key_expr(self) -> str:
        return clock_key_expr(self.domain_id, "/clock", wire_format(self.wire_format))

    @property
    def extras(self) -> tuple[str, ...]:
        """The modules the chosen middleware needs (checked before any run)."""
        if self.middleware == "dds":
            return ("cyclonedds", "rosbags")
        return ("zenoh", "xxhash")

    def describe(self) -> str:
        every = "every step" if self.decimation == 1 else f"every {self.decimation} steps"
        if self.middleware == "dds":
            topics = ("/clock", "/joint_states", "/tf") if self.robot_state else ("/clock",)
            return (
                f"publishing {', '.join(topics)} {every} over DDS "
                f"({', '.join('rt' + topic for topic in topics)}) in domain {self.domain_id} "
                f"({self.wire_format} wire format)"
            )
        connect = self.connect or ()
        listen = self.listen or ()
        return (
            f"publishing /clock {every} on {self.key_expr} ({self.wire_format} wire format), "
            f"connecting to {', '.join(connect) or 'nothing'}, listening on "
            f"{', '.join(listen) or 'nothing'}"
        )


def options_from_cli(
    enabled: bool,
    domain_id: int | None,
    decimation: int,
    wire: str,
    connect: list[str] | None,
    listen: list[str] | None,
    rmw: str | None = None,
    robot_state: bool = False,
    frame_prefix: str = "",
    wait_for_subscribers: int | None = None,
    wait_timeout: float = DEFAULT_WAIT_TIMEOUT,
) -> Ros2ClockOptions | None:
    """Validate the options; None when ``--ros2-clock`` and ``--ros2`` are off (then the others
    are errors). ``--ros2`` is ``--ros2-clock`` and the robot state."""
    if frame_prefix and not robot_state:
        raise InvalidArgumentError(
            "--ros2-frame-prefix names the robot's TF frames: only with --ros2"
        )
    if wait_timeout != DEFAULT_WAIT_TIMEOUT and wait_for_subscribers is None:
        raise InvalidArgumentError("--ros2-wait-timeout: only with --ros2-wait-for-subscribers")
    enabled = enabled or robot_state
    if not enabled:
        given = [
            name
            for name, value, default in (
                ("--ros-domain-id", domain_id, None),
                ("--ros2-clock-decimation", decimation, 1),
                ("--ros2-wire-format", wire, DEFAULT_WIRE_FORMAT),
                ("--ros2-connect", connect, None),
                ("--ros2-listen", listen, None),
                ("--rmw", rmw, None),
                ("--ros2-wait-for-subscribers", wait_for_subscribers, None),
            )
            if value != default
        ]
        if given:
            raise InvalidArgumentError(f"{', '.join(given)}: only with --ros2-clock or --ros2")
        return None
    if decimation < 1:
        raise InvalidArgumentError(
            f"--ros2-clock-decimation must be >= 1 (1 = every step), got {decimation}"
        )
    if wait_for_subscribers is not None:
        check_subscriber_count(wait_for_subscribers, "--ros2-wait-for-subscribers")
        check_wait_timeout(wait_timeout, "--ros2-wait-timeout")
    middleware = resolve_middleware(rmw)
    if wait_for_subscribers is not None and middleware != "dds":
        raise InvalidArgumentError(
            "--ros2-wait-for-subscribers counts DDS readers of /clock; the middleware is "
            "Zenoh: drop it, or --rmw dds"
        )
    if middleware == "dds":
        if connect is not None or listen is not None:
            raise InvalidArgumentError(
                "--ros2-connect and --ros2-listen name Zenoh endpoints, but the middleware is "
                "DDS; add --rmw zenoh, or configure DDS discovery with CYCLONEDDS_URI"
            )
        return Ros2ClockOptions(
            domain_id=resolve_domain_id(domain_id),
            decimation=decimation,
            wire_format=wire_format(wire).name,
            connect=None,
            listen=None,
            middleware="dds",
            robot_state=robot_state,
            frame_prefix=check_frame_prefix(frame_prefix),
            wait_for_subscribers=wait_for_subscribers,
            wait_timeout=wait_timeout,
        )
    return Ros2ClockOptions(
        domain_id=resolve_domain_id(domain_id),
        decimation=decimation,
        wire_format=wire_format(wire).name,
        connect=check_endpoints(DEFAULT_CONNECT if connect is None else connect, "--ros2-connect"),
        listen=check_endpoints(DEFAULT_LISTEN if listen is None else listen, "--ros2-listen"),
        middleware="zenoh",
        robot_state=robot_state,
    )


@contextlib.contextmanager
def publishing(
    source: SteppingTimeSource[Any], options: Ros2ClockOptions | None
) -> Iterator[Ros2ClockPublisher | None]:
    """Publish ``source``'s time as /clock while the block runs (nothing when ``options`` is
    None)."""
    if options is None:
        yield None
        return
    with Ros2ClockPublisher(
        domain_id=options.domain_id,
        wire_format=options.wire_format,
        rmw=options.middleware,
        connect=options.connect,
        listen=options.listen,
    ) as publisher:
        hook = publisher.attach(source, decimation=options.decimation)
        try:
            yield publisher
        finally:
            hook.remove()
