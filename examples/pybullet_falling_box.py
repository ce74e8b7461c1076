"""A box falls onto a plane; a 20 Hz controller samples its height on simulation time.

Run it with ``python examples/pybullet_falling_box.py``. PyBullet owns the physics and
evclock owns time: sim time advances in whole physics steps (1/240 s), and the controller's
``clock.rate(20)`` ticks every 12 steps, exactly, whatever the speed of the machine.
The controller code would run unchanged on the wall clock of a real robot.
"""

from __future__ import annotations

import pybullet as p

import evclock
from evclock.sources import PyBulletTimeSource

RATE_HZ = 20
DURATION_S = 2.0
BOX_HALF_SIZE = 0.1
DROP_HEIGHT = 1.0


def build_world(client: int) -> int:
    """A static plane and a 1 kg box 1 m above it; returns the box's body id."""
    p.setGravity(0, 0, -9.81, physicsClientId=client)
    plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client)
    p.createMultiBody(0, plane, physicsClientId=client)
    box = p.createCollisionShape(
        p.GEOM_BOX, halfExtents=[BOX_HALF_SIZE] * 3, physicsClientId=client
    )
    return int(
        p.createMultiBody(1.0, box, basePosition=[0, 0, DROP_HEIGHT], physicsClientId=client)
    )


async def controller(client: int, box: int) -> list[tuple[float, float]]:
    """Sample the box height at 20 Hz for two seconds; return ``(sim time, height)`` pairs."""
    clock = evclock.clock()
    samples: list[tuple[float, float]] = []
    async for tick in clock.rate(RATE_HZ):
        height = p.getBasePositionAndOrientation(box, physicsClientId=client)[0][2]
        samples.append((tick.actual.seconds, height))
        print(f"t={tick.actual.seconds:.3f} s  height={height:.4f} m")
        if tick.actual.seconds >= DURATION_S:
            break
    return samples


def main() -> list[tuple[float, float]]:
    """Build the world, run the controller on sim time, and return its samples."""
    source = PyBulletTimeSource.connect()  # a DIRECT client, disconnected at the end
    box = build_world(source.client)
    samples = evclock.run(controller(source.client, box), source=source)
    print(f"done: {len(samples)} samples, {source.step_index} physics steps")
    return samples


if __name__ == "__main__":
    main()
