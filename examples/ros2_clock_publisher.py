"""A PyBullet simulation publishes its time as ROS 2 ``/clock`` over DDS or Zenoh.

Run it with ``python examples/ros2_clock_publisher.py``, then, in a ROS 2 shell (any DDS
middleware, ROS's default): ``ros2 topic echo /clock``. Every physics step (240 Hz of sim
time, paced at real time) is published; a ROS 2 node with ``use_sim_time:=true`` follows it.
With ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` it speaks rmw_zenoh's format instead, to rmw_zenoh's
router (``ros2 run rmw_zenoh_cpp rmw_zenohd``) or, with ``--listen``/``--connect``, to other
Zenoh endpoints, e.g. a Unix socket that ``examples/ros2_clock_follower.py`` connects to (what
the tests do, without ROS).
"""

from __future__ import annotations

import argparse

import pybullet as p

import evclock
from evclock.ros2 import DEFAULT_CONNECT, DEFAULT_LISTEN, Ros2ClockPublisher


def build_world(client: int) -> int:
    """A plane and a box falling on it: something for the physics to do."""
    p.setGravity(0, 0, -9.81, physicsClientId=client)
    plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client)
    p.createMultiBody(0, plane, physicsClientId=client)
    box = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.1] * 3, physicsClientId=client)
    return int(p.createMultiBody(1.0, box, basePosition=[0, 0, 1], physicsClientId=client))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--until", type=float, default=5.0, help="sim seconds to run")
    parser.add_argument("--rtf", type=float, default=1.0, help="real-time factor")
    parser.add_argument(
        "--connect", action="append", help=f"Zenoh only; default {DEFAULT_CONNECT[0]}"
    )
    parser.add_argument(
        "--listen", action="append", help=f"Zenoh only; default {DEFAULT_LISTEN[0]}"
    )
    args = parser.parse_args()

    source = evclock.sources.PyBulletTimeSource.connect()
    box = build_world(source.client)
    with Ros2ClockPublisher(connect=args.connect, listen=args.listen) as publisher:
        publisher.attach(source)  # publish now and after every physics step
        print(f"publishing {publisher.topic}: {publisher!r}", flush=True)

        async def watch() -> None:
            async for tick in evclock.clock().rate(1):  # a status line every sim second
                z = p.getBasePositionAndOrientation(box, physicsClientId=source.client)[0][2]
                print(f"t={tick.actual.seconds:.3f} s  box z={z:.3f} m", flush=True)
                if tick.actual.seconds >= args.until:
                    break

        evclock.run(watch(), source=source, rtf=args.rtf)
        print(f"published {publisher.sequence_number} /clock messages", flush=True)


if __name__ == "__main__":
    main()
