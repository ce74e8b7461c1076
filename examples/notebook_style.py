"""evclock on an event loop you cannot replace: the notebook (or ASGI server) case.

A Jupyter kernel already runs an asyncio loop, and so does uvicorn: ``evclock.run()``, which
creates a :class:`evclock.SimEventLoop`, is not an option there. :class:`evclock.SimDriver`
is: a task on the running loop that owns sim time, steps and paces it. Controllers keep
calling ``evclock.clock()`` and get the driver's sim clock - the same code as under
``evclock.run()`` and on the real robot.

Here ``asyncio.run(kernel())`` stands for the kernel's loop, and the body of ``kernel()`` is
what you would type into notebook cells (top-level ``await`` works there). ``evclock.run``
is never called. The script shows:

* ``SimDriver(rtf=None, paused=True)`` + ``await sim.run_until(t)``: advance as fast as
  possible to exactly ``t``, then stay paused - the notebook workflow, cell after cell;
* ``sim.step(n)`` while paused: ``n`` jumps to the next deadline;
* plain ``asyncio.sleep`` stays *wall* time: paused, sim time does not move during it;
  running with ``rtf=None``, sim time races on during it;
* leaving ``async with`` stops the driver, cancels the controllers' sim-time waits and gives
  the loop its wall clock back.

Run: ``python examples/notebook_style.py``
"""

from __future__ import annotations

import asyncio

import evclock

LOUD = [True]  # the controllers print only while the output is deterministic
GOAL = [1.0]  # the joint's current goal, set by the planner


def say(message: str) -> None:
    """Print ``message`` stamped with the sim time."""
    if LOUD[0]:
        print(f"[sim {evclock.clock().now().seconds:6.3f} s] {message}")


async def joint_controller() -> None:
    """A 50 Hz control loop driving a first-order plant toward the current goal."""
    clock = evclock.clock()  # the SimDriver's clock here; a wall clock on the robot
    position = 0.0
    async for tick in clock.rate(50, name="joint_control"):
        position += (GOAL[0] - position) * 0.05
        if tick.index % 100 == 0:
            say(f"joint_control tick {tick.index}: position {position:.4f}")


async def planner() -> None:
    """Every 1.5 s of sim time, pick a new goal."""
    clock = evclock.clock()
    for goal in (2.0, 0.5, 1.5):
        await clock.sleep(1.5)
        GOAL[0] = goal
        say(f"planner: new goal {goal}")


async def kernel() -> None:
    """The notebook session, on a loop evclock does not own."""
    loop = asyncio.get_running_loop()
    print(
        f"kernel loop: {type(loop).__name__}; a SimEventLoop: "
        f"{isinstance(loop, evclock.SimEventLoop)}"
    )

    # Cell 1: start the simulation, paused, and the controllers.
    async with evclock.SimDriver(rtf=None, paused=True) as sim:
        print(f"evclock.clock() is sim.clock: {evclock.clock() is sim.clock}")
        control = asyncio.create_task(joint_controller())
        plan = asyncio.create_task(planner())

        # Cell 2: run to 5 s of sim time, as fast as possible; it stays paused there.
        await sim.run_until(5.0)
        say(f"run_until(5.0) returned; paused: {sim.paused}")

        # Cell 3: three increments (on virtual time, jumps to the next deadline: the
        # 50 Hz ticks at 5.02, 5.04 and 5.06 s); this cell's own sleep ends on the third.
        sim.step(3)
        await evclock.clock().sleep(0.06)
        say(f"step(3) done; still paused: {sim.paused}")

        # Cell 4: plain asyncio.sleep is wall time. Paused, sim time stands still meanwhile.
        before = sim.now()
        await asyncio.sleep(0.02)
        say(f"plain asyncio.sleep(0.02) while paused: sim time moved: {sim.now() != before}")

        # Cell 5: resumed with rtf=None, sim time races on during a plain wall-time sleep.
        LOUD[0] = False
        sim.resume()
        for _ in range(250):  # one pass, unless the machine is badly overloaded
            await asyncio.sleep(0.02)
            if sim.now() > before:
                break
        moved = sim.now() > before
        print(f"plain asyncio.sleep(0.02) while running: sim time moved on: {moved}")
        print(f"every advance in lockstep: {sim.lockstep_overruns == 0}")

    # Leaving the block stopped the driver: sim-time waits were cancelled.
    print(
        f"planner finished: {plan.done() and not plan.cancelled()}; "
        f"controller cancelled: {control.cancelled()}"
    )
    print(f"evclock.clock() is now a {type(evclock.clock()).__name__}")


if __name__ == "__main__":
    asyncio.run(kernel())  # stands for the notebook kernel's own, already running loop
