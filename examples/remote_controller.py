"""A controller that joins a simulation in another process (see ``remote_sim.py``).

The launch decides the clock, as with ``use_sim_time``: ``EVCLOCK_CLOCK=unix:///tmp/plant.sock``
(or ``evclock.run(main(), clock=...)``) joins the served simulation in lockstep, with the
participant name from ``?name=`` (this example adds ``name=controller`` if missing). A
100 Hz proportional loop reads the plant's position and sends a command; the simulation
applies each command at the sim time of the tick that computed it.
"""

from __future__ import annotations

import os

import evclock

TARGET = 1.0
KP = 2.0
TICKS = 200


async def main() -> None:
    link = evclock.remote.participant()  # the connection to the simulation
    clock = evclock.clock()  # its sim time, exactly
    async for tick in clock.rate(100, name="control"):
        x = float(link.call("position"))
        link.publish("command", repr(KP * (TARGET - x)).encode())
        if tick.index % 50 == 0:
            print(f"[t={tick.actual.seconds:.3f} s] x = {x:.9f}")
        if tick.index == TICKS:
            break
    print(f"[t={clock.now().seconds:.3f} s] done after {TICKS} ticks")


if __name__ == "__main__":
    address = os.environ.get(evclock.ENV_CLOCK, "unix:///tmp/evclock-plant.sock")
    if "name=" not in address:
        address += ("&" if "?" in address else "?") + "name=controller"
    evclock.run(main(), clock=address)
