"""Resetting a PyBullet world mid-run: time jumps back, and nothing is left hanging.

Run it with ``python examples/reset_and_jumps.py``. A ball is dropped and a 10 Hz monitor
watches it; a supervisor saves the state at 0.5 s, lets the run go on to 1.5 s, then restores
the snapshot. Sim time jumps back to 0.5 s: the jump handlers run, a task in the middle of a
``clock.sleep`` is woken with ``evclock.ClockJumpedError`` (it recomputes its deadline), and the
rate loop re-anchors on the restored time. A ROS ``Rate.sleep`` would hang here.
"""

from __future__ import annotations

import asyncio

import pybullet as p

import evclock


def drop_ball(client: int) -> int:
    """A plane and a 10 cm ball 2 m above it; returns the ball's body id."""
    p.setGravity(0, 0, -9.81, physicsClientId=client)
    plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client)
    p.createMultiBody(0, plane, physicsClientId=client)
    ball = p.createCollisionShape(p.GEOM_SPHERE, radius=0.1, physicsClientId=client)
    return int(p.createMultiBody(1.0, ball, basePosition=[0, 0, 2], physicsClientId=client))


async def main() -> list[str]:
    clock = evclock.clock()
    source = asyncio.get_running_loop().source  # type: ignore[attr-defined]
    ball = drop_ball(source.client)
    log: list[str] = []

    def height() -> float:
        return float(p.getBasePositionAndOrientation(ball, physicsClientId=source.client)[0][2])

    clock.on_jump(
        pre=lambda jump: log.append(f"jump handler (pre):  leaving {jump.before}"),
        post=lambda jump: log.append(f"jump handler (post): now {jump.after}, delta {jump.delta}"),
    )

    async def monitor() -> None:
        async for tick in clock.rate(10, name="monitor"):
            if tick.index % 5 == 0:
                log.append(f"monitor tick {tick.index} at {tick.actual}: z = {height():.3f} m")

    async def slow_task() -> None:
        while True:
            try:
                await clock.sleep(0.8)
                log.append(f"slow task finished its sleep at {clock.now()}")
                return
            except evclock.ClockJumpedError as jumped:
                log.append(f"slow task woken by the jump ({jump_size(jumped)}); sleeping again")

    def jump_size(exc: evclock.ClockJumpedError) -> str:
        return f"delta {exc.jump.delta}"

    watcher = asyncio.create_task(monitor())
    await clock.sleep(0.5)
    snapshot = source.save_state()
    log.append(f"saved state at {clock.now()}, z = {height():.3f} m")
    await clock.sleep(0.9)
    sleeper = asyncio.create_task(slow_task())
    await clock.sleep(0.1)
    log.append(f"restoring at {clock.now()}, z = {height():.3f} m")
    source.restore_state(snapshot)
    log.append(f"restored: {clock.now()}, z = {height():.3f} m")
    await sleeper
    await clock.sleep(0.3)
    watcher.cancel()
    return log


if __name__ == "__main__":
    source = evclock.sources.PyBulletTimeSource.connect()
    for line in evclock.run(main(), source=source):
        print(line)
