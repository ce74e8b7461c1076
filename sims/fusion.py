"""Husky locating a landmark by fusing 50 Hz odometry with a 15 Hz camera that lags 80 ms.

Sensors, each publishing ROS-style messages (``header.stamp`` as ``sec``/``nanosec``):

* ``odometry`` (50 Hz): the base pose (position and unit quaternion), stamped when measured;
* ``camera`` (15 Hz): the landmark's position in the robot frame, stamped at capture and
  delivered :attr:`LandmarkFusion.camera_latency` later (exposure, transfer, detection).

The fusion controller pairs each detection with odometry through
``evclock.data.ApproximateTimeSynchronizer`` (ROS's ApproximateTime policy) and places the landmark
in the world three ways: with the pose of the paired odometry message, with the pose
interpolated at the detection's own stamp from ``evclock.data.TimeBuffer`` s (linear for the
position, slerp for the orientation) - the right way - and with the latest pose when the
detection arrives, the classic mistake of ignoring stamps. ``evclock.data.StampDiagnostics``
watches the stamps' ages. The mission drives an arc past the landmark; it succeeds when the
interpolated estimates are within :attr:`LandmarkFusion.required_accuracy` of the truth and
beat both other ways.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Coroutine
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

import evclock

from ._base import ClockLike, Metric, Scenario, TimeLike, pybullet
from .husky import LEFT_WHEELS, RIGHT_WHEELS, TRACK, WHEEL_RADIUS

# PyBullet only, imported when used (not with this module): see husky.py.


@dataclass(frozen=True)
class Header:
    """``std_msgs/Header``: the stamp in the ``builtin_interfaces/Time`` layout."""

    stamp: evclock.TimeMsg
    frame_id: str


@dataclass(frozen=True)
class Odometry:
    """The robot's pose at ``header.stamp``."""

    header: Header
    position: np.ndarray
    orientation: np.ndarray
    """Unit quaternion (x, y, z, w)."""


@dataclass(frozen=True)
class Detection:
    """The landmark's position in the robot frame at ``header.stamp`` (capture time)."""

    header: Header
    landmark: np.ndarray


class _StampClockView:
    """A sim-time :class:`evclock.data.StampClock` over a non-evclock :class:`ClockLike`."""

    clock_type = evclock.SIM

    def __init__(self, clock: ClockLike) -> None:
        self._clock = clock

    def now(self) -> evclock.Time:
        return evclock.Time(0, self._clock.now().nanoseconds)


def _stamp_clock(clock: ClockLike) -> evclock.data.StampClock:
    """The clock itself when it is evclock's; a sim-time view of a stand-in clock otherwise."""
    return clock if isinstance(clock, evclock.Clock) else _StampClockView(clock)


def _matrix(quaternion: np.ndarray) -> np.ndarray:
    """The rotation matrix of the unit ``quaternion`` (x, y, z, w)."""
    return np.array(pybullet().getMatrixFromQuaternion(quaternion.tolist())).reshape(3, 3)


class LandmarkFusion(Scenario):
    """Husky on an arc locating a pillar from lagging camera detections and odometry."""

    name = "fusion"
    description = "Husky fusing 50 Hz odometry and a 15 Hz camera lagging 80 ms (stamps, sync)"
    default_until = 10.0

    odometry_hz = 50.0
    camera_hz = 15.0
    drive_hz = 50.0
    camera_latency = 0.08
    """Seconds between capture (the stamp) and delivery of a detection."""
    drive_time = 6.0
    """Seconds of driving; the mission ends then."""
    speed = 1.0
    """m/s."""
    wheel_force = 50.0
    required_accuracy = 0.005
    """Metres: worst error allowed for the landmark estimated at the detections' stamps."""
    min_detections = 60
    stale_after = 0.15
    """Seconds: detections older than this when used are reported stale."""

    def __init__(self, client: int, seed: int = 0) -> None:
        """Load the plane, the Husky at the origin and a pillar beside a seeded arc."""
        super().__init__(client, seed)
        self.load_urdf("plane.urdf")
        self.robot = self.load_urdf("husky/husky.urdf", robot=True)
        self.turn_rate = float(self.rng.uniform(0.25, 0.45))
        """rad/s: the arc's curvature (seeded)."""
        radius = self.speed / self.turn_rate
        angle = float(self.rng.uniform(1.0, 1.6))
        inside = radius - float(self.rng.uniform(1.0, 2.0))
        self.landmark = np.array([inside * math.sin(angle), radius - inside * math.cos(angle), 0.5])
        p = pybullet()
        shape = p.createCollisionShape(
            p.GEOM_CYLINDER, radius=0.1, height=1.0, physicsClientId=client
        )
        p.createMultiBody(
            baseMass=0.0,
            baseCollisionShapeIndex=shape,
            basePosition=self.landmark.tolist(),
            physicsClientId=client,
        )
        self.errors: dict[str, list[float]] = {"interpolated": [], "paired": [], "latest": []}
        """Landmark position errors (metres) per way of fusing, one per detection."""
        self.latest_pose: tuple[np.ndarray, np.ndarray] | None = None
        self.stamps: evclock.data.StampDiagnostics | None = None
        self._clock_type = evclock.SIM
        """The domain of the stamps: the clock's (STEADY when run on wall time)."""

    # -- sensors ---------------------------------------------------------------------------

    def _pose(self) -> tuple[np.ndarray, np.ndarray]:
        position, orientation = pybullet().getBasePositionAndOrientation(
            self.robot, physicsClientId=self.client
        )
        return np.array(position), np.array(orientation)

    def _stamp(self, when: TimeLike) -> evclock.Time:
        return evclock.Time(0, when.nanoseconds, self._clock_type)

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        stamp_clock = _stamp_clock(clock)
        self._clock_type = stamp_clock.clock_type
        self.stamps = evclock.data.StampDiagnostics(
            "fusion", clock=stamp_clock, stale_after=self.stale_after, max_queue=5
        )
        sync = evclock.data.ApproximateTimeSynchronizer(
            ["odometry", "camera"],
            queue_size=20,
            clock=stamp_clock,
            diagnostics=self.stamps,
            name="fusion sync",
        )
        positions = evclock.data.TimeBuffer(200, name="odometry positions")
        orientations = evclock.data.TimeBuffer(200, interpolation="slerp", name="odometry attitude")
        in_flight: asyncio.Queue[tuple[int, Detection]] = asyncio.Queue()
        return {
            "odometry": self._odometry(clock, sync, positions, orientations),
            "camera": self._camera(clock, in_flight),
            "camera link": self._deliver(clock, in_flight, sync),
            "fusion": self._fuse(sync, positions, orientations),
        }

    async def _odometry(
        self,
        clock: ClockLike,
        sync: evclock.data.ApproximateTimeSynchronizer,
        positions: evclock.data.TimeBuffer,
        orientations: evclock.data.TimeBuffer,
    ) -> None:
        async for tick in clock.rate(self.odometry_hz, name="odometry"):
            position, orientation = self._pose()
            stamp = self._stamp(tick.actual)
            header = Header(stamp.to_msg(), "odom")
            positions.add(stamp, position)
            orientations.add(stamp, orientation / np.linalg.norm(orientation))
            self.latest_pose = (position, orientation)
            sync.add("odometry", Odometry(header, position, orientation))

    async def _camera(
        self, clock: ClockLike, in_flight: asyncio.Queue[tuple[int, Detection]]
    ) -> None:
        latency_ns = round(self.camera_latency * 1e9)
        async for tick in clock.rate(self.camera_hz, name="camera"):
            position, orientation = self._pose()
            relative = _matrix(orientation).T @ (self.landmark - position)
            stamp = self._stamp(tick.actual)
            detection = Detection(Header(stamp.to_msg(), "camera"), relative)
            in_flight.put_nowait((tick.actual.nanoseconds + latency_ns, detection))

    async def _deliver(
        self,
        clock: ClockLike,
        in_flight: asyncio.Queue[tuple[int, Detection]],
        sync: evclock.data.ApproximateTimeSynchronizer,
    ) -> None:
        while True:
            due_ns, detection = await in_flight.get()
            wait_ns = due_ns - clock.now().nanoseconds
            if wait_ns > 0:
                await clock.sleep(wait_ns / 1e9)
            sync.add("camera", detection)

    async def _fuse(
        self,
        sync: evclock.data.ApproximateTimeSynchronizer,
        positions: evclock.data.TimeBuffer,
        orientations: evclock.data.TimeBuffer,
    ) -> None:
        async for group in sync:
            odometry, detection = cast(tuple[Odometry, Detection], group)
            stamp = evclock.Time.from_msg(detection.header.stamp, sync.clock.clock_type)
            at_stamp = (positions.at(stamp), orientations.at(stamp))
            paired = (odometry.position, odometry.orientation)
            assert self.latest_pose is not None
            for way, (position, orientation) in (
                ("interpolated", at_stamp),
                ("paired", paired),
                ("latest", self.latest_pose),
            ):
                estimate = position + _matrix(orientation) @ detection.landmark
                self.errors[way].append(float(np.linalg.norm(estimate - self.landmark)))

    # -- mission -----------------------------------------------------------------------------

    async def _mission(self, clock: ClockLike) -> None:
        start = clock.now().seconds
        async for tick in clock.rate(self.drive_hz, name="drive"):
            if tick.actual.seconds - start >= self.drive_time:
                self._command_wheels(0.0, 0.0)
                return
            self._command_wheels(self.speed, self.turn_rate)

    def _command_wheels(self, speed: float, turn: float) -> None:
        left = (speed - turn * TRACK / 2.0) / WHEEL_RADIUS
        right = (speed + turn * TRACK / 2.0) / WHEEL_RADIUS
        p = pybullet()
        p.setJointMotorControlArray(
            self.robot,
            [*LEFT_WHEELS, *RIGHT_WHEELS],
            p.VELOCITY_CONTROL,
            targetVelocities=[left, left, right, right],
            forces=[self.wheel_force] * 4,
            physicsClientId=self.client,
        )

    def _worst(self, way: str) -> float:
        return max(self.errors[way], default=math.inf)

    def success(self) -> bool:
        """Enough detections fused, accurately at their stamps, better than the other ways."""
        return (
            self.finished_at is not None
            and len(self.errors["interpolated"]) >= self.min_detections
            and self._worst("interpolated") <= self.required_accuracy
            and self._worst("interpolated") < self._worst("paired") < self._worst("latest")
        )

    def _metrics(self) -> dict[str, Metric]:
        return {
            "detections_fused": len(self.errors["interpolated"]),
            "worst_error_at_stamp_m": self._worst("interpolated"),
            "worst_error_paired_odometry_m": self._worst("paired"),
            "worst_error_latest_pose_m": self._worst("latest"),
        }
