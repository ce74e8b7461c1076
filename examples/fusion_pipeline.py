"""A message-filter pipeline on the fusion scenario: subscriber -> cache -> synchroniser,
then interpolation between the cached odometry messages around each detection's stamp.

The ``fusion`` scenario (a Husky on an arc, 50 Hz odometry, a 15 Hz camera whose detections
arrive 80 ms after capture) is run with its fusion controller rebuilt the ROS
``message_filters`` way:

* odometry goes into a ``PassThrough`` (the subscriber), then a ``Cache`` of its last 200
  messages (sorted by stamp);
* the cache and the camera's ``PassThrough`` feed an ``ApproximateTimeSynchronizer``
  (``connect_input``), whose drops are reported with their reason;
* for each (odometry, detection) group, the cache gives the two odometry messages around the
  detection's stamp (``surrounding``), interpolated linearly (position) and by slerp
  (attitude) to place the landmark seen by the camera.

Everything runs on PyBullet sim time, deterministically::

    python examples/fusion_pipeline.py
"""

from __future__ import annotations

from asyncio import Queue
from collections import Counter
from collections.abc import Coroutine
from typing import Any

import numpy as np

import evclock
from evclock.data import ApproximateTimeSynchronizer, Cache, PassThrough
from evclock_sims import ClockLike
from evclock_sims.fusion import Detection, Header, LandmarkFusion, Odometry, _stamp_clock


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x, y, z, w), along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)


def pose_at(cache: Cache, stamp: evclock.Time) -> tuple[np.ndarray, np.ndarray]:
    """The odometry pose at ``stamp``, interpolated between the cached messages around it."""
    around = cache.surrounding(stamp, stamp)
    before, after = around[0], around[-1]
    t0 = evclock.Time.from_msg(before.header.stamp, stamp.clock_type)
    t1 = evclock.Time.from_msg(after.header.stamp, stamp.clock_type)
    u = 0.0 if t1 == t0 else (stamp - t0) / (t1 - t0)
    position = before.position + u * (after.position - before.position)
    return position, slerp(before.orientation, after.orientation, u)


class _CameraLink:
    """What the scenario's camera link delivers to: here, the camera subscriber."""

    def __init__(self, subscriber: PassThrough) -> None:
        self._subscriber = subscriber

    def add(self, stream: str, message: object) -> None:
        self._subscriber.add(message)


class PipelineFusion(LandmarkFusion):
    """The fusion scenario with a subscriber -> cache -> synchroniser pipeline."""

    name = "fusion-pipeline"

    def _services(self, clock: ClockLike) -> dict[str, Coroutine[Any, Any, None]]:
        stamp_clock = _stamp_clock(clock)
        self._clock_type = stamp_clock.clock_type
        self.drops: Counter[str] = Counter()
        odometry, camera = PassThrough(), PassThrough()
        self.cache = Cache(odometry, cache_size=200, clock=stamp_clock, name="odometry cache")
        sync = ApproximateTimeSynchronizer(
            ["odometry", "camera"],
            queue_size=20,
            clock=stamp_clock,
            name="pipeline sync",
            on_drop=lambda stream, message, reason: self.drops.update([f"{stream}: {reason}"]),
        )
        sync.connect_input(self.cache, camera)
        in_flight: Queue[tuple[int, Detection]] = Queue()
        return {
            "odometry": self._publish_odometry(clock, odometry),
            "camera": self._camera(clock, in_flight),
            "camera link": self._deliver(clock, in_flight, _CameraLink(camera)),  # type: ignore[arg-type]
            "fusion": self._fuse_pipeline(sync),
        }

    async def _publish_odometry(self, clock: ClockLike, subscriber: PassThrough) -> None:
        async for tick in clock.rate(self.odometry_hz, name="odometry"):
            position, orientation = self._pose()
            stamp = self._stamp(tick.actual)
            self.latest_pose = (position, orientation)
            unit = orientation / np.linalg.norm(orientation)
            subscriber.add(Odometry(Header(stamp.to_msg(), "odom"), position, unit))

    async def _fuse_pipeline(self, sync: ApproximateTimeSynchronizer) -> None:
        async for group in sync:
            odometry, detection = group
            assert isinstance(odometry, Odometry)
            assert isinstance(detection, Detection)
            stamp = evclock.Time.from_msg(detection.header.stamp, sync.clock.clock_type)
            assert self.latest_pose is not None
            for way, (position, orientation) in (
                ("interpolated", pose_at(self.cache, stamp)),
                ("paired", (odometry.position, odometry.orientation)),
                ("latest", self.latest_pose),
            ):
                estimate = position + _rotation(orientation) @ detection.landmark
                self.errors[way].append(float(np.linalg.norm(estimate - self.landmark)))


def _rotation(q: np.ndarray) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


if __name__ == "__main__":
    scenario: list[PipelineFusion] = []

    class Recorded(PipelineFusion):
        def __init__(self, client: int, seed: int = 0) -> None:
            super().__init__(client, seed)
            scenario.append(self)

    report = evclock.tools.run_scenario(Recorded, seed=0)
    summary = report.summary
    print(f"fusion pipeline seed {report.seed}: {report.verdict}")
    print(f"detections fused: {summary['detections_fused']}")
    for way, key in (
        ("at the detection stamp (cache + interpolation)", "worst_error_at_stamp_m"),
        ("with the paired odometry message", "worst_error_paired_odometry_m"),
        ("with the latest pose", "worst_error_latest_pose_m"),
    ):
        print(f"worst error {way}: {1000 * float(summary[key]):.1f} mm")
    fusion = scenario[0]
    print(f"odometry cached: {len(fusion.cache)} (oldest {fusion.cache.oldest_time})")
    for reason, count in sorted(fusion.drops.items()):
        print(f"dropped, {reason}: {count}")
