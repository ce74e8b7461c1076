"""A simulation that serves its sim time; its controller runs in another process.

The plant is a point whose velocity is the last command received (``x' = u``), integrated
at 1 kHz on this process's sim time. It serves that time (``evclock.remote.serve``), answers
``position`` queries and applies ``command`` messages at the sim time the controller sent
them, before the plant integrates any further (lockstep). Run::

    python examples/remote_sim.py unix:///tmp/plant.sock
    EVCLOCK_CLOCK=unix:///tmp/plant.sock python examples/remote_controller.py   # elsewhere

Both print the same sim times, and every run prints the same numbers.
"""

from __future__ import annotations

import asyncio
import sys

import evclock

PLANT_HZ = 1000


async def main(address: str) -> None:
    clock = evclock.clock()
    state = {"x": 0.0, "u": 0.0}

    def apply(message: evclock.remote.Message) -> None:
        state["u"] = float(message.data)

    async def plant() -> None:
        async for _tick in clock.rate(PLANT_HZ, name="plant"):
            state["x"] += state["u"] / PLANT_HZ

    async with evclock.remote.serve(address) as server:
        server.provide("position", lambda _request: repr(state["x"]).encode())
        server.subscribe("command", apply)
        print(f"serving sim time at {server.address}", flush=True)
        await server.wait_for_participants("controller")
        integrator = asyncio.create_task(plant())
        await server.wait_until_left()
        integrator.cancel()
    print(f"[t={clock.now().seconds:.3f} s] the controller left; x = {state['x']:.9f}")


if __name__ == "__main__":
    evclock.run(main(sys.argv[1] if len(sys.argv) > 1 else "unix:///tmp/evclock-plant.sock"))
