"""Pacing: real time, k x real time, as fast as possible, and an operator pausing and stepping.

Run it with ``python examples/pacing.py``. A 10 Hz controller runs on virtual time:

1. at ``rtf=2`` (twice real time) for one simulated second;
2. as fast as possible (``loop.rtf = None``) for a simulated minute;
3. paused, while an operator thread - a stand-in for a GUI or a dashboard - steps the
   simulation three times (each step: one jump to the next deadline) and then resumes it.
   The controls are called directly from that thread: they are thread-safe and wake the
   loop. The operator waits for each step on a ``concurrent.futures.Future``: such a wait
   never holds sim time, whatever its timeout (a bare ``Event.wait(timeout)`` would: it
   may be a delay, see docs/guides/outside.md).

Sim times are exact and the same on every run; the wall-time figures depend on the machine.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time

import evclock


async def main() -> None:
    loop = asyncio.get_running_loop()
    assert isinstance(loop, evclock.SimEventLoop)
    clock = evclock.clock()
    next_tick: list[concurrent.futures.Future[evclock.Time]] = []

    async def controller() -> None:
        async for _tick in clock.rate(10, name="controller"):
            while next_tick:
                next_tick.pop().set_result(clock.now())

    task = asyncio.create_task(controller())

    started = time.perf_counter()
    await clock.sleep(1.0)
    print(f"rtf=2: 1 s of sim time took {time.perf_counter() - started:.2f} s of wall time")

    loop.rtf = None
    started = time.perf_counter()
    await clock.sleep(60.0)
    print(f"rtf=max: 60 s of sim time took {time.perf_counter() - started:.3f} s of wall time")

    def operator() -> None:
        for _ in range(3):
            ticked: concurrent.futures.Future[evclock.Time] = concurrent.futures.Future()
            next_tick.append(ticked)
            loop.step()
            print(f"  stepped: sim time {ticked.result(timeout=5)}")
        loop.resume()

    loop.pause()
    print(f"paused at {clock.now()}; the operator steps three times, then resumes")
    await asyncio.sleep(0)  # let the controller's tick due now run before the operator starts
    threading.Thread(target=operator, daemon=True).start()
    await clock.sleep(0.5)
    print(f"resumed; the controller's half second ended at {clock.now()}")
    task.cancel()
    (rate,) = clock.rates
    print(f"controller: {rate.stats.ticks} ticks, {rate.stats.missed} missed")


if __name__ == "__main__":
    evclock.run(main(), rtf=2.0)
