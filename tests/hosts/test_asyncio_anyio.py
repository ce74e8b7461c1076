"""asyncio's and anyio's own time functions follow sim time on the simulation loop."""

from __future__ import annotations

import asyncio

import anyio
import pytest

import evclock


def now() -> float:
    return asyncio.get_running_loop().time()


def run(coro: object) -> object:
    return evclock.run(coro)  # type: ignore[arg-type]


def test_asyncio_sleep() -> None:
    async def main() -> float:
        await asyncio.sleep(3600)
        return now()

    assert run(main()) == 3600.0


def test_asyncio_timeout_expires_in_sim_time() -> None:
    async def main() -> tuple[bool, float]:
        expired = False
        try:
            async with asyncio.timeout(5):
                await asyncio.sleep(100)
        except TimeoutError:
            expired = True
        return expired, now()

    assert run(main()) == (True, 5.0)


def test_asyncio_timeout_that_does_not_expire_does_not_move_time() -> None:
    async def main() -> float:
        async with asyncio.timeout(5):
            await asyncio.sleep(1)
        await asyncio.sleep(0)
        return now()

    assert run(main()) == 1.0


def test_asyncio_wait_for() -> None:
    async def main() -> tuple[str, float]:
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asyncio.sleep(10), timeout=2)
        t = now()
        result = await asyncio.wait_for(asyncio.sleep(1, result="ok"), timeout=2)
        return result, now() - t

    assert run(main()) == ("ok", 1.0)


def test_call_later_and_call_at() -> None:
    async def main() -> list[tuple[str, float]]:
        loop = asyncio.get_running_loop()
        fired: list[tuple[str, float]] = []
        done = loop.create_future()
        loop.call_later(2, lambda: fired.append(("later", loop.time())))
        loop.call_at(7, lambda: (fired.append(("at", loop.time())), done.set_result(None)))
        await done
        return fired

    assert run(main()) == [("later", 2.0), ("at", 7.0)]


def test_anyio_sleep_fail_after_move_on_after() -> None:
    async def main() -> list[float]:
        out = []
        await anyio.sleep(2)
        out.append(anyio.current_time())
        with pytest.raises(TimeoutError):
            with anyio.fail_after(3):
                await anyio.sleep(10)
        out.append(anyio.current_time())
        with anyio.move_on_after(4) as scope:
            await anyio.sleep(10)
        assert scope.cancelled_caught
        out.append(anyio.current_time())
        return out

    assert run(main()) == [2.0, 5.0, 9.0]


def test_anyio_cancel_scope_deadline() -> None:
    async def main() -> tuple[bool, float]:
        with anyio.CancelScope(deadline=anyio.current_time() + 1.5) as scope:
            await anyio.sleep_forever()
        return scope.cancelled_caught, anyio.current_time()

    assert run(main()) == (True, 1.5)


def test_asyncio_task_group() -> None:
    async def worker(delay: float, out: list[float]) -> None:
        await asyncio.sleep(delay)
        out.append(now())

    async def main() -> tuple[list[float], float]:
        out: list[float] = []
        async with asyncio.TaskGroup() as tg:
            for d in (3, 1, 2):
                tg.create_task(worker(d, out))
        return out, now()

    assert run(main()) == ([1.0, 2.0, 3.0], 3.0)


def test_anyio_task_group() -> None:
    async def worker(delay: float, out: list[float]) -> None:
        await anyio.sleep(delay)
        out.append(anyio.current_time())

    async def main() -> tuple[list[float], float]:
        out: list[float] = []
        async with anyio.create_task_group() as tg:
            for d in (3, 1, 2):
                tg.start_soon(worker, d, out)
        return out, anyio.current_time()

    assert run(main()) == ([1.0, 2.0, 3.0], 3.0)


def test_anyio_run_with_loop_factory_backend_option() -> None:
    async def main() -> float:
        await anyio.sleep(42)
        return anyio.current_time()

    assert anyio.run(main, backend_options={"loop_factory": evclock.loop_factory()}) == 42.0
