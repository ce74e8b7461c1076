"""Pacing, pause and step, per physics step with PyBulletTimeSource (docs/architecture.md,
"Pacing").

No test measures wall time. The loop takes a fake wall clock (``wall=``) and a selector
whose ``select(timeout)`` lets ``timeout`` seconds of that fake clock pass instead of
waiting, and records each pacing wait. A blocking ``select(None)`` - the paused loop waiting
for a command - can be reported to the test instead of blocking (``on_block``).
"""

from __future__ import annotations

import asyncio
import re
import selectors
import socket
from collections.abc import Awaitable, Callable
from fractions import Fraction
from typing import Any

import pytest

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")

import evclock
from evclock import SIM, DeadlockError, LagError, NotRunningError, PacingError, SimEventLoop, Time
from evclock.sources import PyBulletTimeSource, VirtualTimeSource

NS = 1_000_000_000
DT = 1 / 240
STEP_NS = Fraction(NS, 240)


def raises_exactly(error: type[BaseException], message: str) -> Any:
    return pytest.raises(error, match="^" + re.escape(message) + "$")


def step_time(index: int) -> int:
    return index * STEP_NS.numerator // STEP_NS.denominator


class FakeWall:
    """A wall clock that only moves when told to."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class FakeWallSelector(selectors.DefaultSelector):
    """``select(t)`` moves the fake wall clock by ``t`` and polls real I/O without blocking."""

    def __init__(self, wall: FakeWall) -> None:
        super().__init__()
        self.wall = wall
        self.waits: list[float] = []
        self.on_block: Callable[[], None] | None = None
        self.blocks = 0

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None:
            self.blocks += 1
            callback, self.on_block = self.on_block, None
            if callback is not None:
                callback()
                return list(super().select(0))
            return list(super().select(None))  # really wait for I/O (loopback, in tests)
        if timeout > 0:
            self.waits.append(timeout)
            self.wall.now += timeout
        return list(super().select(0))


class Harness:
    """A SimEventLoop on a PyBullet source with a fake wall clock."""

    def __init__(self, client: int, **loop_kwargs: Any) -> None:
        self.wall = FakeWall()
        self.selector = FakeWallSelector(self.wall)
        self.source = PyBulletTimeSource(client)
        self.loop_kwargs = loop_kwargs

    def run(self, main: Callable[[], Awaitable[Any]]) -> Any:
        def factory() -> SimEventLoop:
            return SimEventLoop(
                self.source, wall=self.wall, selector=self.selector, **self.loop_kwargs
            )

        async def wrapper() -> Any:
            return await main()

        with asyncio.Runner(loop_factory=factory) as runner:
            return runner.run(wrapper())

    def blocked(self) -> asyncio.Future[int]:
        """A future resolved with the step index when the paused loop next blocks."""
        future: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self.selector.on_block = lambda: future.set_result(self.source.step_index)
        return future


def control_channel() -> tuple[SimEventLoop, Callable[[], None]]:
    """Register a socket on the running sim loop, as a real control channel would: a paused
    loop may then wait. The loop, and how to close the channel."""
    loop = asyncio.get_running_loop()
    assert isinstance(loop, SimEventLoop)
    ours, theirs = socket.socketpair()
    loop.add_reader(ours, lambda: None)

    def close() -> None:
        loop.remove_reader(ours)
        ours.close()
        theirs.close()

    return loop, close


# ----------------------------------------------------------------------------- rtf


def test_as_fast_as_possible_never_waits(client: int) -> None:
    h = Harness(client)

    async def main() -> None:
        await evclock.clock().sleep(1.0)

    h.run(main)
    assert h.source.step_index == 240
    assert h.selector.waits == []
    assert h.wall.now == 1000.0


@pytest.mark.parametrize("rtf", [1.0, 4.0, 0.5])
def test_rtf_paces_every_physics_step(client: int, rtf: float) -> None:
    h = Harness(client, rtf=rtf)

    async def main() -> None:
        await evclock.clock().sleep(1.0)

    h.run(main)
    assert h.source.step_index == 240
    # one wait before each step: its share of wall time (the first step anchors the pace)
    assert len(h.selector.waits) == 240
    # (each within a few ns: step times are whole nanoseconds, 4166666 or 4166667 apart)
    assert h.selector.waits == [pytest.approx(DT / rtf, abs=3e-9)] * 240
    assert h.wall.now - 1000.0 == pytest.approx(1.0 / rtf, abs=1e-9)


def test_rtf_change_while_running(client: int) -> None:
    h = Harness(client, rtf=1.0)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        await evclock.clock().sleep(0.5)
        loop.rtf = 2.0
        await evclock.clock().sleep(0.5)
        loop.rtf = None
        await evclock.clock().sleep(0.5)

    h.run(main)
    assert h.source.step_index == 360
    assert len(h.selector.waits) == 240
    assert h.wall.now - 1000.0 == pytest.approx(0.5 + 0.25, abs=1e-9)


def test_pacing_with_a_far_deadline_stays_per_step(client: int) -> None:
    """One advance toward a far deadline is still paced step by step."""
    h = Harness(client, rtf=1.0)

    async def main() -> None:
        await evclock.clock().sleep(10.0)

    h.run(main)
    assert h.source.step_index == 2400
    assert len(h.selector.waits) == 2400
    assert h.wall.now - 1000.0 == pytest.approx(10.0, abs=1e-6)


def test_achieved_rtf(client: int) -> None:
    h = Harness(client, rtf=2.0)

    async def main() -> float | None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        assert loop.achieved_rtf() is None  # one sample only
        await evclock.clock().sleep(1.0)
        return loop.achieved_rtf()

    assert h.run(main) == pytest.approx(2.0, rel=1e-6)


def _slow_step(h: Harness, at_step: int, seconds: float) -> None:
    """Make the physics step ``at_step`` take ``seconds`` of (fake) wall time."""

    def hook() -> None:
        if h.source.step_index == at_step:
            h.wall.now += seconds

    h.source.add_step_hook(hook)


def test_lag_beyond_the_bound_re_anchors_instead_of_bursting(client: int) -> None:
    h = Harness(client, rtf=1.0)
    _slow_step(h, 10, 0.5)
    h.run(lambda: evclock.clock().sleep(1.0))
    # The late step goes at once, then the pace resumes from there: the lost 0.5 s is not
    # caught up in a burst, so the waits still add up to the whole second of sim time.
    assert sum(h.selector.waits) == pytest.approx(1.0, abs=1e-9)
    assert min(h.selector.waits[10:]) == pytest.approx(DT, abs=3e-9)
    assert h.wall.now - 1000.0 == pytest.approx(1.5, abs=1e-9)


def test_lag_within_the_bound_is_caught_up(client: int) -> None:
    h = Harness(client, rtf=1.0, max_lag=0.1)
    _slow_step(h, 10, 0.05)
    h.run(lambda: evclock.clock().sleep(1.0))
    assert sum(h.selector.waits) == pytest.approx(0.95, abs=1e-9)
    assert h.wall.now - 1000.0 == pytest.approx(1.0, abs=1e-9)


def test_strict_pacing_raises_lag_error(client: int) -> None:
    h = Harness(client, rtf=1.0, strict=True)
    _slow_step(h, 10, 0.5)
    with raises_exactly(
        LagError,
        "the simulation lags 0.496 s of wall time behind rtf=1 (strict limit 0.1 s); lower "
        "the rtf, lighten the controllers or pass strict=False to let it run as fast as it can",
    ):
        h.run(lambda: evclock.clock().sleep(1.0))
    assert h.source.step_index == 10


def test_strict_pacing_keeps_up_when_the_physics_does(client: int) -> None:
    h = Harness(client, rtf=1.0, strict=True, max_lag=0.1)
    _slow_step(h, 10, 0.09)
    h.run(lambda: evclock.clock().sleep(1.0))
    assert h.source.step_index == 240


def test_pacing_virtual_time_waits_once_per_jump() -> None:
    wall = FakeWall()
    selector = FakeWallSelector(wall)

    async def main() -> None:
        await evclock.clock().sleep(2.0)
        await evclock.clock().sleep(1.0)

    loop_factory = lambda: SimEventLoop(  # noqa: E731
        VirtualTimeSource(), rtf=1.0, wall=wall, selector=selector
    )
    with asyncio.Runner(loop_factory=loop_factory) as runner:
        runner.run(main())
    assert selector.waits == [pytest.approx(2.0), pytest.approx(1.0)]


# --------------------------------------------------------------------- pause and step


def test_pause_step_and_resume(client: int) -> None:
    h = Harness(client)

    async def main() -> None:
        loop, close = control_channel()
        clock = evclock.clock()
        # a far deadline: each advance aims at it, the pacer must stop it step by step
        background = asyncio.ensure_future(clock.sleep(100.0))
        await clock.sleep(0.5)
        loop.pause()
        assert loop.paused
        blocked = h.blocked()
        assert await blocked == 120  # paused: not one step more
        assert clock.now_ns() == NS // 2

        loop.step(5)
        assert await h.blocked() == 125
        loop.step()
        assert await h.blocked() == 126
        assert clock.now_ns() == step_time(126)

        target = Time(0.6, clock_type=SIM)  # between steps 143 (0.5958 s) and 144 (0.6 s)
        loop.step_until(target)
        assert await h.blocked() == 144
        target = Time(0.61, clock_type=SIM)  # quantised up: step 147 (0.6125 s)
        loop.step_until(target)
        assert await h.blocked() == 147
        assert loop.paused

        loop.resume()
        assert not loop.paused
        await clock.sleep(1.0)
        assert h.source.step_index == 147 + 240
        background.cancel()
        close()

    h.run(main)
    assert h.selector.waits == []  # rtf=None: stepping is never paced


def test_step_counts_physics_steps_with_pacing(client: int) -> None:
    h = Harness(client, rtf=1.0)

    async def main() -> None:
        loop, close = control_channel()
        loop.pause()
        assert await h.blocked() == 0
        loop.step(24)
        assert await h.blocked() == 24
        close()

    h.run(main)
    # stepping while paused still follows the requested pace
    assert len(h.selector.waits) == 24
    assert sum(h.selector.waits) == pytest.approx(0.1, abs=1e-9)


def test_resume_does_not_burst_to_catch_up_the_pause(client: int) -> None:
    h = Harness(client, rtf=1.0)

    async def main() -> None:
        loop, close = control_channel()
        clock = evclock.clock()
        await clock.sleep(0.5)
        loop.pause()

        def long_pause_then_resume() -> None:
            h.wall.now += 30.0  # half a minute of wall time spent paused
            loop.resume()

        h.selector.on_block = long_pause_then_resume
        await clock.sleep(0.5)
        close()

    h.run(main)
    assert len(h.selector.waits) == 240
    assert sum(h.selector.waits) == pytest.approx(1.0, abs=1e-9)


def test_starting_paused_and_stepping_from_a_task(client: int) -> None:
    h = Harness(client, paused=True)

    async def main() -> None:
        loop, close = control_channel()
        assert loop.paused
        loop.step(3)
        # a task can wait for its steps with wait_until (stepping stops when it resolves)
        await h.source.wait_until(lambda: h.source.step_index >= 3)
        assert h.source.step_index == 3
        assert await h.blocked() == 3
        close()

    h.run(main)


def test_paused_with_nothing_to_resume_it_is_a_deadlock(client: int) -> None:
    h = Harness(client)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        loop.pause()
        await evclock.clock().sleep(1.0)

    with pytest.raises(DeadlockError, match=r"^the loop is paused and nothing could ever resume"):
        h.run(main)
    assert h.source.step_index == 0


def test_network_io_is_served_while_paused(client: int) -> None:
    """A TCP echo over loopback answers while sim time stands still; a command resumes."""
    h = Harness(client)

    async def main() -> tuple[int, int]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        clock = evclock.clock()

        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            while line := await reader.readline():
                if line == b"resume\n":
                    loop.resume()
                    writer.write(b"resumed\n")
                else:
                    writer.write(b"echo " + line)
                await writer.drain()
            writer.close()
            await writer.wait_closed()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        await clock.sleep(0.25)
        loop.pause()
        paused_at = (clock.now_ns(), h.source.step_index)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        for k in range(5):
            writer.write(f"hello {k}\n".encode())
            await writer.drain()
            assert await reader.readline() == f"echo hello {k}\n".encode()
        assert (clock.now_ns(), h.source.step_index) == paused_at
        writer.write(b"resume\n")
        await writer.drain()
        assert await reader.readline() == b"resumed\n"
        assert not loop.paused
        await clock.sleep(0.25)
        writer.close()
        await writer.wait_closed()
        server.close()
        await server.wait_closed()
        return clock.now_ns(), h.source.step_index

    assert h.run(main) == (NS // 2, 120)


# ------------------------------------------------------------------------- misuse


def test_pause_before_the_loop_runs_is_refused(client: int) -> None:
    loop = SimEventLoop(PyBulletTimeSource(client))
    try:
        for call, name in [
            (loop.pause, "pause()"),
            (loop.resume, "resume()"),
            (loop.step, "step()"),
            (lambda: loop.step_until(Time(1, clock_type=SIM)), "step_until()"),
        ]:
            with raises_exactly(
                NotRunningError,
                f"{name} needs a running loop; call it from a task on the loop (or through "
                "loop.call_soon_threadsafe), or create the loop with paused=True to start paused",
            ):
                call()
    finally:
        loop.close()


@pytest.mark.parametrize(("rtf", "mode"), [(None, "as fast as possible"), (2.0, "at rtf=2")])
def test_stepping_a_running_loop_is_refused(client: int, rtf: float | None, mode: str) -> None:
    h = Harness(client, rtf=rtf)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        with raises_exactly(
            PacingError,
            f"step() needs a paused loop, but it is running {mode}; call pause() first, then step",
        ):
            loop.step(3)
        with raises_exactly(
            PacingError,
            f"step_until() needs a paused loop, but it is running {mode}; call pause() "
            "first, then step",
        ):
            loop.step_until(Time(1, clock_type=SIM))
        await evclock.clock().sleep(0.1)

    h.run(main)
    assert h.source.step_index == 24


def test_step_argument_errors(client: int) -> None:
    h = Harness(client, paused=True)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, SimEventLoop)
        with raises_exactly(evclock.InvalidArgumentError, "step() count must be >= 1, got 0"):
            loop.step(0)
        with raises_exactly(evclock.InvalidTypeError, "step() count must be an int, got float"):
            loop.step(1.5)  # type: ignore[arg-type]
        with raises_exactly(
            evclock.InvalidArgumentError,
            "step_until() target 0.000000000 s (sim) is not after the current sim time "
            "0.000000000 s (sim)",
        ):
            loop.step_until(Time(0, clock_type=SIM))

    h.run(main)
