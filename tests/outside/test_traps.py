"""The correctness traps of a virtual-time loop, one test each (issue: core, section 6)."""

from __future__ import annotations

import asyncio
import random
import socket
import threading
import time
import warnings

import anyio
import anyio.to_thread
import pytest

import evclock
from evclock.outside import _threads

# --------------------------------------------------------------------------- FIFO ties


def test_call_at_ties_fire_in_scheduling_order() -> None:
    async def main() -> list[int]:
        loop = asyncio.get_running_loop()
        order: list[int] = []
        done = loop.create_future()
        for i in range(50):
            loop.call_at(1.0, order.append, i)
        loop.call_at(1.0, done.set_result, None)
        await done
        return order

    assert evclock.run(main()) == list(range(50))


@pytest.mark.parametrize("kind", ["asyncio", "clock", "mixed"])
def test_sleepers_due_at_the_same_time_wake_in_scheduling_order(kind: str) -> None:
    async def sleeper(i: int, order: list[int]) -> None:
        use_clock = kind == "clock" or (kind == "mixed" and i % 2)
        if use_clock:
            await evclock.clock().sleep(0.5)
        else:
            await asyncio.sleep(0.5)
        order.append(i)

    async def main() -> list[int]:
        order: list[int] = []
        tasks = []
        for i in range(40):
            tasks.append(asyncio.create_task(sleeper(i, order)))
            await asyncio.sleep(0)  # each task schedules its sleep in turn
        await asyncio.gather(*tasks)
        return order

    assert evclock.run(main()) == list(range(40))


def _seeded_program(seed: int) -> list[tuple[int, str, int]]:
    async def worker(name: str, rng: random.Random, trace: list[tuple[int, str, int]]) -> None:
        clock = evclock.clock()
        for step in range(50):
            choice = rng.random()
            if choice < 0.4:
                await clock.sleep(rng.randint(0, 5) / 1000)
            elif choice < 0.8:
                await asyncio.sleep(rng.randint(0, 5) / 1000)
            else:
                await asyncio.sleep(0)
            trace.append((clock.now_ns(), name, step))

    async def main() -> list[tuple[int, str, int]]:
        trace: list[tuple[int, str, int]] = []
        rng = random.Random(seed)
        async with asyncio.TaskGroup() as tg:
            for i in range(20):
                tg.create_task(worker(f"w{i}", random.Random(rng.random()), trace))
        return trace

    return evclock.run(main())


def test_a_seeded_program_records_the_same_trace_twice() -> None:
    first, second = _seeded_program(7), _seeded_program(7)
    assert first == second
    assert len(first) == 20 * 50
    assert first != _seeded_program(8)


# ------------------------------------------------------------ work outside the loop


def test_timeout_around_a_50ms_thread_job_does_not_expire() -> None:
    async def main() -> tuple[str, float]:
        async with asyncio.timeout(5):
            result = await asyncio.to_thread(lambda: (time.sleep(0.05), "done")[1])
        return result, asyncio.get_running_loop().time()

    assert evclock.run(main()) == ("done", 0.0)


def test_run_in_executor_holds_sim_time() -> None:
    async def main() -> tuple[int, float]:
        loop = asyncio.get_running_loop()
        ticker_ran: list[float] = []

        async def ticker() -> None:
            while True:
                await asyncio.sleep(0.001)
                ticker_ran.append(loop.time())

        task = asyncio.create_task(ticker())
        await loop.run_in_executor(None, time.sleep, 0.05)
        task.cancel()
        return len(ticker_ran), loop.time()

    # Sim time stood still while the executor job ran: the 1 ms ticker never fired.
    assert evclock.run(main()) == (0, 0.0)


def test_anyio_to_thread_holds_sim_time() -> None:
    async def main() -> tuple[str, float]:
        with anyio.fail_after(1):
            result = await anyio.to_thread.run_sync(lambda: (time.sleep(0.05), "ok")[1])
        return result, anyio.current_time()

    assert evclock.run(main()) == ("ok", 0.0)


def test_thread_calling_call_soon_threadsafe_holds_sim_time() -> None:
    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[str] = loop.create_future()

        def producer() -> None:
            time.sleep(0.05)
            loop.call_soon_threadsafe(fut.set_result, "from thread")

        thread = threading.Thread(target=producer)
        thread.start()
        async with asyncio.timeout(5):
            value = await fut
        thread.join()
        return value, loop.time()

    assert evclock.run(main()) == ("from thread", 0.0)


def test_hold_time_blocks_advance_until_released() -> None:
    async def main() -> tuple[float, float]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        fut: asyncio.Future[float] = loop.create_future()

        def later() -> None:
            time.sleep(0.02)
            loop.call_soon_threadsafe(fut.set_result, loop.time())

        with loop.hold_time():
            threading.Thread(target=later, daemon=True).start()  # daemon: not watched
            async with asyncio.timeout(1):
                seen = await fut
        return seen, loop.time()

    assert evclock.run(main()) == (0.0, 0.0)


# ------------------------------------------------------------------- deadlock


def test_deadlock_raises_naming_the_waiting_tasks() -> None:
    async def stuck_forever(event: asyncio.Event) -> None:
        await event.wait()

    async def main() -> None:
        event = asyncio.Event()
        task = asyncio.create_task(stuck_forever(event), name="waiter")
        await evclock.clock().sleep(1)
        await task

    started = time.monotonic()
    with pytest.raises(evclock.DeadlockError) as info:
        evclock.run(main())
    assert time.monotonic() - started < 30  # bounded: it did not hang
    message = str(info.value)
    assert message.startswith("deadlock: every task is waiting and nothing can wake one")
    assert "waiter: stuck_forever() at" in message
    assert "Task-" in message
    assert any(line.startswith("waiter: stuck_forever()") for line in info.value.tasks)


# ------------------------------------------------------------------- shutdown


def test_shutdown_does_not_jump_time_and_leaves_no_warnings() -> None:
    end: list[float] = []

    async def main() -> None:
        await asyncio.to_thread(time.sleep, 0.01)
        loop = asyncio.get_running_loop()
        end.append(loop.time())

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with asyncio.Runner(loop_factory=evclock.loop_factory()) as runner:
            runner.run(main())
            loop = runner.get_loop()
        # After the runner closed (which shut the default executor down), time is unchanged.
        assert loop.time() == end[0] == 0.0


# ------------------------------------------------------------------ real sockets


def test_tcp_echo_over_loopback_on_the_sim_loop() -> None:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        data = await reader.readline()
        await evclock.clock().sleep(0.25)  # the server "thinks" for 250 ms of sim time
        writer.write(data.upper())
        await writer.drain()
        writer.close()
        await writer.wait_closed()

    async def main() -> tuple[bytes, float]:
        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        async with server:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"hello sim\n")
            await writer.drain()
            async with asyncio.timeout(10):
                reply = await reader.readline()
            writer.close()
            await writer.wait_closed()
        return reply, asyncio.get_running_loop().time()

    assert evclock.run(main()) == (b"HELLO SIM\n", 0.25)


def test_raw_socket_pair_reader_callback() -> None:
    async def main() -> bytes:
        loop = asyncio.get_running_loop()
        a, b = socket.socketpair()
        a.setblocking(False)
        b.setblocking(False)
        got: asyncio.Future[bytes] = loop.create_future()
        loop.add_reader(b, lambda: got.set_result(b.recv(100)))
        loop.call_later(3, a.send, b"ping")
        try:
            return await got
        finally:
            loop.remove_reader(b)
            a.close()
            b.close()

    assert evclock.run(main()) == b"ping"


def test_daemon_threads_do_not_hold_time_but_may_resume_a_paused_loop() -> None:
    async def main() -> tuple[float, float]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        stop = threading.Event()
        idle = threading.Thread(target=stop.wait, daemon=True)  # a background service
        idle.start()
        await asyncio.sleep(5)  # the idle daemon does not hold time
        advanced_to = loop.time()

        def operator() -> None:  # a daemon control thread, like a GUI or a web server
            time.sleep(0.02)
            loop.call_soon_threadsafe(loop.resume)

        loop.pause()
        threading.Thread(target=operator, daemon=True).start()
        await asyncio.sleep(1)  # paused: only the operator can let this finish
        stop.set()
        idle.join()
        return advanced_to, loop.time()

    assert evclock.run(main()) == (5.0, 6.0)


def test_evclock_helper_threads_do_not_hide_a_paused_deadlock() -> None:
    stop = threading.Event()
    helper = threading.Thread(target=stop.wait, daemon=True)
    _threads.mark_internal(helper)  # like the pytest plugin's watchdog
    helper.start()
    try:

        async def paused_forever() -> None:
            loop = asyncio.get_running_loop()
            assert isinstance(loop, evclock.SimEventLoop)
            loop.pause()
            await asyncio.sleep(1)

        with pytest.raises(evclock.DeadlockError, match="the loop is paused and nothing could"):
            evclock.run(paused_forever())
    finally:
        stop.set()
        helper.join()
