"""A one-minute patrol, tested in virtual time: 60 s of controller time in milliseconds.

``@pytest.mark.evclock`` runs each test on evclock's simulation loop: ``asyncio.sleep``,
``asyncio.timeout``, rate loops and ``evclock.clock()`` all follow sim time, which jumps straight
to the next deadline whenever every task waits. The assertions are about sim time and
behaviour - exact, and the same on every run. (How fast this runs on the wall clock is a
benchmark's business, not a test's.)

Run it with ``pytest examples/test_controller_in_virtual_time.py``.
"""

from __future__ import annotations

import asyncio

import pytest
from patrol_controller import Base, Patrol, obstacle

import evclock

# A bug that keeps the patrol going forever fails after 2 simulated minutes, not a CI timeout.
pytestmark = pytest.mark.evclock(sim_timeout=120)


async def test_a_clear_patrol_visits_a_waypoint_every_ten_seconds(
    evclock_clock: evclock.Clock,
) -> None:
    base = Base()
    log = await Patrol(base).run(60.0)

    assert evclock_clock.now() == evclock.Time(seconds=60, clock_type=evclock.SIM)
    # 4 m legs at 0.5 m/s take 8 s, then the base dwells 2 s.
    assert log.arrivals == [
        ("B", 8.0),
        ("C", 18.0),
        ("D", 28.0),
        ("A", 38.0),
        ("B", 48.0),
        ("C", 58.0),
    ]
    assert log.timeouts == []
    assert (base.x, base.y) == pytest.approx((4.0, 4.0))  # dwelling at C when time is up
    assert base.odometer == pytest.approx(6 * 4.0)
    assert log.missed == 0  # in sim time the 20 Hz loop never misses a period


async def test_a_blocked_leg_times_out_and_the_patrol_goes_on(
    evclock_clock: evclock.Clock,
) -> None:
    base = Base()
    async with asyncio.TaskGroup() as tasks:
        # An obstacle stops the base from 12 s to 19 s, during the leg from B to C (10-22 s).
        tasks.create_task(obstacle(base, appears=12.0, clears=19.0))
        log = await Patrol(base).run(60.0)

    assert evclock_clock.now().seconds == 60.0
    assert log.timeouts == [("C", 22.0)]  # the leg started at 10 s: a 12 s timeout
    # From where it stood at 22 s, D is 4.28 m away: 172 ticks of 50 ms.
    assert log.arrivals == [("B", 8.0), ("D", 30.6), ("A", 40.6), ("B", 50.6)]
    assert base.stopped is False
    assert log.missed == 0


async def test_the_rate_loop_ticks_on_exact_deadlines(evclock_clock: evclock.Clock) -> None:
    base = Base()
    patrol = Patrol(base, (("far", 100.0, 0.0),), leg_timeout=12.0)
    log = await patrol.run(15.0)

    assert log.timeouts == [("far", 12.0)]
    # One tick every 50 ms: 240 in the first leg (0 to 11.95 s), 60 in the second (12 to
    # 14.95 s); the timeouts cancel the ticks due at 12 s and 15 s.
    assert log.ticks == 300
    # The base moves 2.5 cm between two ticks of a leg: 239 + 59 such steps.
    assert base.odometer == pytest.approx(298 * 0.025)
    assert evclock_clock.now().nanoseconds == 15_000_000_000
