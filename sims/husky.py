"""Husky following seeded waypoints, then stopping short of an obstacle seen by a ray-cast lidar.

Two concurrent controllers:

* ``lidar`` (20 Hz): a horizontal fan of rays (``rayTestBatch``) from the front of the chassis;
  publishes the nearest range.
* ``drive`` (50 Hz, the mission): go-to-point steering through the waypoints, then straight at the
  obstacle box placed beyond the last one; slows down as the lidar range shrinks and halts once it
  drops below :attr:`HuskyPatrol.stop_range`.  Every tick it also checks robot/obstacle contacts.
"""

from __future__ import annotations

import math
from collections.abc import Coroutine
from typing import Any

import numpy as np

from ._base import ClockLike, Metric, Scenario, pybullet, wrap_angle

# PyBullet only, imported when a world is built (not with this module): `evclock list` and
# `evclock run husky --engine mujoco` name the scenario's engine without PyBullet installed.

LEFT_WHEELS = (2, 4)
"""``front_left_wheel``, ``rear_left_wheel`` (joints 0, 1, 6-9 are fixed)."""
RIGHT_WHEELS = (3, 5)
"""``front_right_wheel``, ``rear_right_wheel``."""
WHEEL_RADIUS = 0.17775
"""Metres, the URDF collision cylinder."""
TRACK = 0.5708
"""Metres between left and right wheel centres."""

BASE_WAYPOINTS = ((2.0, 0.0), (4.0, 1.5), (6.0, 1.5))
"""Nominal route (metres, world x/y); each run jitters every waypoint."""

OBSTACLE_HALF_EXTENTS = (0.2, 0.5, 0.3)
"""Metres: a static box, 1 m wide and 0.6 m tall, standing on the ground."""


class HuskyPatrol(Scenario):
    """Husky on a plane: follow waypoints, then stop before an obstacle without touching it."""

    name = "husky"
    description = "Husky following waypoints at 50 Hz, 20 Hz lidar stopping it before an obstacle"
    default_until = 20.0

    drive_hz = 50.0
    lidar_hz = 20.0
    cruise_speed = 0.8
    """m/s."""
    max_turn_rate = 1.0
    """rad/s."""
    heading_gain = 2.0
    """Turn rate per radian of heading error."""
    wheel_force = 50.0
    """N m: wheel velocity-motor force limit."""
    waypoint_tolerance = 0.3
    """Metres."""
    waypoint_jitter = 0.3
    """Metres: seeded uniform jitter on each waypoint coordinate."""

    lidar_offset = 0.52
    """Metres ahead of the base origin: just outside the chassis collision box (0.504 m)."""
    lidar_height = 0.3
    """Metres above the ground."""
    lidar_max_range = 5.0
    lidar_rays = 15
    lidar_half_fov = math.radians(30.0)
    slow_range = 1.5
    """Metres: below this lidar range the speed limit falls linearly..."""
    stop_range = 0.6
    """...reaching zero here, where the drive halts for good."""
    creep_speed = 0.15
    """m/s: lowest speed limit inside the slow-down zone, so the robot does reach stop_range."""
    still_speed = 0.02
    """m/s: below this planar speed the robot counts as stopped."""
    still_time = 0.5
    """Seconds the robot must stay stopped (after halting) for the mission to end."""
    required_clearance = 0.3
    """Metres: required final gap between robot and obstacle."""

    def __init__(self, client: int, seed: int = 0) -> None:
        """Load the plane, the Husky at the origin facing +x, seeded waypoints and the obstacle."""
        super().__init__(client, seed)
        self.load_urdf("plane.urdf")
        self.robot = self.load_urdf("husky/husky.urdf", robot=True)
        jitter = self.rng.uniform(-self.waypoint_jitter, self.waypoint_jitter, size=(3, 2))
        self.waypoints = [np.array(w) + d for w, d in zip(BASE_WAYPOINTS, jitter, strict=True)]
        heading = self.waypoints[-1] - self.waypoints[-2]
        ahead = 2.5 + float(self.rng.uniform(0.0, 0.5))
        self.obstacle_xy = self.waypoints[-1] + ahead * heading / np.linalg.norm(heading)
        p = pybullet()
        shape = p.createCollisionShape(
            p.GEOM_BOX, halfExtents=OBSTACLE_HALF_EXTENTS, physicsClientId=client
        )
        self.obstacle = p.createMultiBody(
            baseMass=0.0,
            baseCollisionShapeIndex=shape,
            basePosition=[*self.obstacle_xy, OBSTACLE_HALF_EXTENTS[2]],
            baseOrientation=p.getQuaternionFromEuler(
                [0.0, 0.0, math.atan2(heading[1], heading[0])]
            ),
            physicsClientId=client,
        )
        self.min_range = self.lidar_max_range
        """Nearest lidar return (metres), published by the lidar loop."""
        self.waypoints_reached = 0
        self.halted = False
        self.collided = False
        self.clearance = math.inf
        """Smallest robot/obstacle distance seen by the drive loop (metres)."""

    def _pose(self) -> tuple[np.ndarray, float]:
        """Base x/y position and yaw."""
        position, orientation = self.pb.getBasePositionAndOrientation(
            self.robot, physicsClientId=self.client
        )
        yaw = self.pb.getEulerFromQuaternion(orientation)[2]
        return np.array(position[:2]), yaw

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        return {"lidar": self._lidar(clock)}

    async def _lidar(self, clock: ClockLike) -> None:
        """Cast the ray fan every tick and publish the nearest hit."""
        offsets = np.linspace(-self.lidar_half_fov, self.lidar_half_fov, self.lidar_rays)
        async for _tick in clock.rate(self.lidar_hz, name="lidar"):
            xy, yaw = self._pose()
            front = xy + self.lidar_offset * np.array([math.cos(yaw), math.sin(yaw)])
            origin = [float(front[0]), float(front[1]), self.lidar_height]
            ends = [
                [
                    origin[0] + self.lidar_max_range * math.cos(yaw + offset),
                    origin[1] + self.lidar_max_range * math.sin(yaw + offset),
                    self.lidar_height,
                ]
                for offset in offsets
            ]
            hits = self.pb.rayTestBatch([origin] * len(ends), ends, physicsClientId=self.client)
            self.min_range = min(hit[2] for hit in hits) * self.lidar_max_range

    async def _mission(self, clock: ClockLike) -> None:
        """Drive the route; return once halted in front of the obstacle and stopped."""
        still_since: float | None = None
        async for tick in clock.rate(self.drive_hz, name="drive"):
            self._check_obstacle()
            if self.halted or self.min_range < self.stop_range:
                self.halted = True
                self._command_wheels(0.0, 0.0)
                linear, _ = self.pb.getBaseVelocity(self.robot, physicsClientId=self.client)
                if math.hypot(linear[0], linear[1]) > self.still_speed:
                    still_since = None
                elif still_since is None:
                    still_since = tick.actual.seconds
                elif tick.actual.seconds - still_since >= self.still_time:
                    return
                continue
            self._steer()

    def _check_obstacle(self) -> None:
        """Record any robot/obstacle contact and the current gap between them."""
        cid = self.client
        if self.pb.getContactPoints(bodyA=self.robot, bodyB=self.obstacle, physicsClientId=cid):
            self.collided = True
        closest = self.pb.getClosestPoints(
            self.robot, self.obstacle, distance=self.lidar_max_range, physicsClientId=cid
        )
        self.clearance = min([self.clearance, *(point[8] for point in closest)])

    def _steer(self) -> None:
        """Go-to-point toward the current waypoint (or the obstacle once all are reached)."""
        xy, yaw = self._pose()
        if self.waypoints_reached < len(self.waypoints):
            goal = self.waypoints[self.waypoints_reached]
            if np.linalg.norm(goal - xy) < self.waypoint_tolerance:
                self.waypoints_reached += 1
                return
        else:
            goal = self.obstacle_xy
        delta = goal - xy
        error = wrap_angle(math.atan2(delta[1], delta[0]) - yaw)
        turn = float(np.clip(self.heading_gain * error, -self.max_turn_rate, self.max_turn_rate))
        speed_limit = self.cruise_speed * (self.min_range - self.stop_range)
        speed_limit /= self.slow_range - self.stop_range
        speed_limit = min(self.cruise_speed, max(self.creep_speed, speed_limit))
        self._command_wheels(speed_limit * max(0.0, math.cos(error)), turn)

    def _command_wheels(self, speed: float, turn: float) -> None:
        """Differential-drive command: forward ``speed`` (m/s) and ``turn`` rate (rad/s)."""
        left = (speed - turn * TRACK / 2.0) / WHEEL_RADIUS
        right = (speed + turn * TRACK / 2.0) / WHEEL_RADIUS
        self.pb.setJointMotorControlArray(
            self.robot,
            [*LEFT_WHEELS, *RIGHT_WHEELS],
            pybullet().VELOCITY_CONTROL,
            targetVelocities=[left, left, right, right],
            forces=[self.wheel_force] * 4,
            physicsClientId=self.client,
        )

    def success(self) -> bool:
        """All waypoints reached, then halted with clearance and without ever touching the box."""
        return (
            self.waypoints_reached == len(self.waypoints)
            and self.finished_at is not None
            and self.clearance > self.required_clearance
            and not self.collided
        )

    def _metrics(self) -> dict[str, Metric]:
        return {
            "waypoints": len(self.waypoints),
            "waypoints_reached": self.waypoints_reached,
            "clearance_m": self.clearance,
            "collided": self.collided,
        }
