"""Stamped sensor data on sim time: synchronise, interpolate, and catch the classic mistakes.

A camera (10 Hz, delivered 30 ms after capture), an IMU (100 Hz) and a lidar (10 Hz, 50 ms
after the camera) publish ROS-style messages (``header.stamp`` with ``sec``/``nanosec``).
An ``ApproximateTimeSynchronizer`` groups them by stamp, a ``TimeBuffer`` gives the IMU's
heading at each camera stamp (slerp), and ``StampDiagnostics`` reports ages, a stale camera
and a wall-clock stamp. Runs in milliseconds of wall time on virtual time.

    python examples/sensor_fusion.py
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import evclock
from evclock import Time, TimeMsg


@dataclass(frozen=True)
class Header:
    stamp: TimeMsg


@dataclass(frozen=True)
class Msg:
    header: Header
    data: object


def stamped(t: Time, data: object) -> Msg:
    return Msg(Header(t.to_msg()), data)


def heading(yaw: float) -> list[float]:
    """A unit quaternion (x, y, z, w) for a rotation of ``yaw`` about z."""
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]


async def main() -> None:
    clock = evclock.clock()
    await clock.sleep(10.0)  # start at t = 10 s, like the camera at 10.00 s
    diag = evclock.data.StampDiagnostics(
        "perception",
        stale_after=0.1,
        on_warning=lambda w: print(f"  warning: {w.kind} stamp on {w.stream!r} at {w.at}"),
    )
    sync = evclock.data.ApproximateTimeSynchronizer(
        ["camera", "imu", "lidar"], queue_size=30, diagnostics=diag
    )
    attitude = evclock.data.TimeBuffer(100, interpolation="slerp", name="imu attitude")

    async def imu() -> None:
        async for tick in clock.rate(100, name="imu"):
            yaw = 0.5 * (tick.actual - Time(10)).seconds  # turning at 0.5 rad/s
            attitude.add(tick.actual, heading(yaw))
            sync.add("imu", stamped(tick.actual, yaw))

    async def camera() -> None:
        frame = 0
        async for tick in clock.rate(10, name="camera"):
            capture = tick.actual
            # The driver freezes for 200 ms at frame 5: delivered late, hence stale.
            await clock.sleep(0.23 if frame == 5 else 0.03)
            sync.add("camera", stamped(capture, f"frame {frame}"))
            frame += 1

    async def lidar() -> None:
        await clock.sleep(0.05)
        async for tick in clock.rate(10, name="lidar"):
            sync.add("lidar", stamped(tick.actual, "scan"))

    producers = [asyncio.create_task(f()) for f in (imu, camera, lidar)]
    async for cam, gyro, scan in sync:
        stamps = [Time.from_msg(m.header.stamp) for m in (cam, gyro, scan)]
        spread = max(stamps) - min(stamps)
        q = attitude.at(stamps[0])
        yaw = 2 * math.atan2(q[2], q[3])
        print(
            f"[{clock.now()}] {cam.data}: camera {stamps[0].seconds:.2f} imu "
            f"{stamps[1].seconds:.2f} lidar {stamps[2].seconds:.2f}, spread "
            f"{spread.seconds * 1e3:.0f} ms, yaw {yaw:.3f}"
        )
        if cam.data == "frame 7":
            break
    for task in producers:
        task.cancel()

    camera_stats = diag.streams()["camera"]
    print(
        f"camera: {camera_stats.count} frames, mean age {camera_stats.mean().seconds * 1e3:.0f}"
        f" ms, max {camera_stats.max_ns / 1e6:.0f} ms, {camera_stats.stale} stale"
    )
    print(f"dropped: {sync.dropped}")

    # A message stamped with the wall clock on sim time (time.time() instead of clock.now()).
    wall = Time(1_700_000_000.0, clock_type=evclock.SYSTEM)
    try:
        sync.add("camera", evclock.data.Stamped(wall, "frame from a wall-clock driver"))
    except evclock.ClockMismatchError as error:
        print(f"ClockMismatchError: {str(error).split(':')[0]}")
    # As a ROS stamp (no domain), it is read as sim time: far in the future, hence flagged.
    sync.add("camera", stamped(Time(1_700_000_000.0), "frame"))
    print(f"future stamps flagged: {diag.streams()['camera'].future}")
    print(f"done at {clock.now()}, dropped: {sync.dropped}")


if __name__ == "__main__":
    evclock.run(main())
