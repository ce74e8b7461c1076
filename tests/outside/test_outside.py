"""The world outside the loop: subprocesses, signals, threads and I/O
(docs/guides/outside.md). Each case behaves as on stock asyncio - same results, no false
timeout, no false deadlock, no hang - only on sim time. Every wait here is bounded."""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import os
import pathlib
import queue
import select
import signal
import socket
import ssl
import subprocess
import sys
import threading
import time

import anyio
import anyio.from_thread
import anyio.to_process
import pytest
from _examples import run_example

import evclock

PY = sys.executable


def sim_time() -> float:
    return asyncio.get_running_loop().time()


# ------------------------------------------------------------------ subprocesses


def test_waiting_for_a_child_holds_sim_time() -> None:
    async def main() -> tuple[int, float]:
        proc = await asyncio.create_subprocess_exec("sleep", "0.3")
        code = await proc.wait()
        return code, sim_time()

    assert evclock.run(main()) == (0, 0.0)


def test_communicate_under_wait_for_does_not_time_out_in_sim_time() -> None:
    async def main() -> tuple[bytes, float]:
        proc = await asyncio.create_subprocess_exec(
            PY, "-c", "import time; time.sleep(0.2); print('hi')", stdout=asyncio.subprocess.PIPE
        )
        out, _ = await asyncio.wait_for(proc.communicate(), 10)
        return out, sim_time()

    assert evclock.run(main()) == (b"hi\n", 0.0)


def test_reading_a_childs_output_holds_sim_time_until_it_speaks() -> None:
    async def main() -> tuple[bytes, float]:
        proc = await asyncio.create_subprocess_exec(
            PY, "-c", "import time; time.sleep(0.2); print('ready', flush=True); input()",
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stdout is not None
        assert proc.stdin is not None
        async with asyncio.timeout(5):
            line = await proc.stdout.readline()
        proc.stdin.close()
        await proc.wait()
        return line, sim_time()

    assert evclock.run(main()) == (b"ready\n", 0.0)


def test_a_child_nobody_waits_on_lets_sim_time_run() -> None:
    async def main() -> tuple[float, int]:
        proc = await asyncio.create_subprocess_exec("sleep", "30")
        await asyncio.sleep(100)  # nobody awaits the child: the simulation goes on
        at = sim_time()
        proc.kill()
        return at, await proc.wait()

    started = time.monotonic()
    assert evclock.run(main()) == (100.0, -signal.SIGKILL)
    assert time.monotonic() - started < 20  # did not wait for the child's 30 s


def test_anyio_run_process_and_to_process() -> None:
    async def main() -> tuple[bytes, int, float]:
        result = await anyio.run_process([PY, "-c", "print('out')"])
        value = await anyio.to_process.run_sync(abs, -7)
        return result.stdout, value, anyio.current_time()

    assert evclock.run(main()) == (b"out\n", 7, 0.0)


def test_anyio_close_of_a_child_blocked_on_a_full_stdout_pipe() -> None:
    """anyio's Process.aclose() closes the pipes (the child gets EPIPE) and waits on its
    protocol's ``exited`` event: that wait holds sim time while the child runs."""

    async def main() -> tuple[int | None, float]:
        process = await anyio.open_process([PY, "-c", "import sys; sys.stdout.write('x' * 2**20)"])
        with anyio.fail_after(5):
            await process.aclose()
        return process.returncode, sim_time()

    code, at = evclock.run(main())
    assert code not in (0, None)  # it died of the closed pipe
    assert at == 0.0


GRANDCHILD = (
    "import subprocess, sys; subprocess.Popen([sys.executable, '-c', "
    "'import select, sys; select.select([sys.stdin], [], [], 10)'])"
)


def test_output_held_open_by_a_grandchild_holds_sim_time_after_the_child_exited() -> None:
    """The child exits at once; its child (inheriting stdin and stdout) lives until stdin
    closes. asyncio's wait() returns once the child exited and its pipes closed: it holds
    sim time until then, also after the child's exit, so no 5 s timeout fires."""

    async def main() -> tuple[int, bytes, float]:
        proc = await asyncio.create_subprocess_exec(
            PY, "-c", GRANDCHILD,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stdin is not None
        assert proc.stdout is not None
        await asyncio.sleep(0)
        proc.stdin.close()  # the grandchild sees EOF, exits, and so closes stdout
        code = await asyncio.wait_for(proc.wait(), 5)
        rest = await asyncio.wait_for(proc.stdout.read(), 3)
        return code, rest, sim_time()

    assert evclock.run(main()) == (0, b"", 0.0)


def test_anyio_wait_returns_on_exit_while_a_grandchild_keeps_stdout_open() -> None:
    async def main() -> tuple[int, float]:
        process = await anyio.open_process([PY, "-c", GRANDCHILD])
        assert process.stdin is not None
        assert process.stdout is not None
        async with process.stdin:
            with anyio.fail_after(5):
                code = await process.wait()
        with anyio.fail_after(3, shield=True):
            async for _ in process.stdout:
                pass
        await process.aclose()
        return code, sim_time()

    assert evclock.run(main()) == (0, 0.0)


def test_a_child_asleep_in_a_timed_wait_is_an_event_in_sim_time() -> None:
    """anyio's to_process test_cancel_during: the worker process sleeps 5 s (time.sleep,
    whose end the kernel shows) while a task waits on its reply; a 0.1 s sim sleep ends
    first, as on stock asyncio, and cancelling the call kills the worker."""

    async def main() -> tuple[float, float, bool]:
        first_pid = await anyio.to_process.run_sync(os.getpid)
        async with anyio.create_task_group() as tg:
            tg.start_soon(
                functools.partial(anyio.to_process.run_sync, cancellable=True), time.sleep, 5
            )
            await asyncio.sleep(0.1)  # ends while the worker still sleeps
            slept_until = sim_time()
            tg.cancel_scope.cancel()
        cancelled_at = sim_time()
        second_pid = await anyio.to_process.run_sync(os.getpid)
        return slept_until, cancelled_at, second_pid != first_pid

    assert evclock.run(main()) == (0.1, 0.1, True)


# ------------------------------------------------------------------------ signals


def test_a_program_waiting_for_sigterm_gets_it() -> None:
    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        got: asyncio.Future[str] = loop.create_future()
        loop.add_signal_handler(signal.SIGTERM, got.set_result, "SIGTERM")
        try:
            threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGTERM)).start()
            return await got, sim_time()
        finally:
            loop.remove_signal_handler(signal.SIGTERM)

    assert evclock.run(main()) == ("SIGTERM", 0.0)


def test_a_signal_from_a_child_process_wakes_the_loop() -> None:
    async def main() -> str:
        loop = asyncio.get_running_loop()
        got: asyncio.Future[str] = loop.create_future()
        loop.add_signal_handler(signal.SIGUSR1, got.set_result, "SIGUSR1")
        try:
            code = f"import os, time; time.sleep(0.1); os.kill({os.getpid()}, {signal.SIGUSR1:d})"
            proc = await asyncio.create_subprocess_exec(PY, "-c", code)
            value = await got
            await proc.wait()
            return value
        finally:
            loop.remove_signal_handler(signal.SIGUSR1)

    assert evclock.run(main()) == "SIGUSR1"


# ------------------------------------------------------------------------ threads


def _timed_work_in_a_thread(wait: str) -> None:
    """One kind of timed thread work, about 50 ms of wall time (docs/guides/outside.md)."""
    if wait == "event":
        threading.Event().wait(0.05)
    elif wait == "queue":
        with pytest.raises(queue.Empty):
            queue.Queue().get(timeout=0.05)
    elif wait in ("select", "poll", "socket_timeout"):
        a, b = socket.socketpair()
        with a, b:
            if wait == "select":
                assert select.select([a], [], [], 0.05) == ([], [], [])
            elif wait == "poll":
                poller = select.poll()
                poller.register(a, select.POLLIN)
                assert poller.poll(50) == []
            else:
                a.settimeout(0.05)
                with pytest.raises(TimeoutError):
                    a.recv(1)
    elif wait == "subprocess_run":
        subprocess.run(["sleep", "0.05"], check=True, timeout=30)
    else:
        assert wait == "popen_wait"
        with subprocess.Popen(["sleep", "0.05"]) as child:
            assert child.wait(timeout=30) == 0


@pytest.mark.parametrize(
    "wait",
    ["timer", "event", "queue", "select", "poll", "socket_timeout", "subprocess_run", "popen_wait"],
)
def test_a_thread_that_waits_with_a_timeout_holds_sim_time(wait: str) -> None:
    """Timed work in a plain thread holds sim time: a timed select/poll on a pipe or socket
    and a wait for a child process the thread started, as a timed sleep or event wait does
    (no false timeout: the wait_for's 1 s of sim time does not pass meanwhile)."""

    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[str] = loop.create_future()

        def deliver() -> None:
            loop.call_soon_threadsafe(fut.set_result, wait)

        def worker() -> None:
            _timed_work_in_a_thread(wait)
            deliver()

        if wait == "timer":
            threading.Timer(0.05, deliver).start()
        else:
            threading.Thread(target=worker).start()
        return await asyncio.wait_for(fut, 1), sim_time()

    assert evclock.run(main()) == (wait, 0.0)


@pytest.mark.parametrize("channel", ["socketpair", "tcp"])
def test_a_timed_wait_on_what_the_loop_serves_waits_for_the_loop(channel: str) -> None:
    """A peer thread waiting with a timeout on a socket whose other end the loop reads (an
    in-process server, a socket with a 20 s safety timeout) waits for the loop, not for its
    timeout: it does not hold sim time, so a 1 s sim sleep ends without waiting for the
    peer's 20 s (held, the peer would time out and get nothing), and the peer then gets the
    loop's answer."""

    async def main() -> tuple[float, bytes]:
        loop = asyncio.get_running_loop()
        if channel == "socketpair":
            ours, theirs = socket.socketpair()
        else:
            server = socket.create_server(("127.0.0.1", 0))
            theirs = socket.create_connection(server.getsockname())
            ours, _ = server.accept()
            server.close()
        theirs.settimeout(20)
        got: list[bytes] = []
        thread = threading.Thread(target=lambda: got.append(theirs.recv(1)))
        loop.add_reader(ours, lambda: None)  # the loop serves its end
        thread.start()
        await asyncio.sleep(1)  # the peer's timed wait is no reason to hold this
        loop.remove_reader(ours)
        ours.sendall(b"!")
        await asyncio.to_thread(thread.join, 30)
        ours.close()
        theirs.close()
        return sim_time(), got[0]

    assert evclock.run(main()) == (1.0, b"!")


def test_a_long_timed_wait_lets_earlier_sim_timers_fire_first() -> None:
    """As on stock asyncio, where loop timers and thread timeouts race on one clock: a
    thread's 3 s safety timeout does not keep a 0.1 s sleep from ending first."""

    async def main() -> tuple[list[bool], float]:
        event = threading.Event()
        woke: list[bool] = []
        thread = threading.Thread(target=lambda: woke.append(event.wait(3)))
        thread.start()
        await asyncio.sleep(0.1)  # ends before the thread's wait would time out
        at = sim_time()
        event.set()
        await asyncio.to_thread(thread.join, 10)
        return woke, at

    assert evclock.run(main()) == ([True], 0.1)


@pytest.mark.parametrize("wait", ["event", "time_sleep", "lock_timeout", "select", "poll"])
def test_a_timed_wait_is_an_event_in_sim_time_that_earlier_timers_cannot_pass(wait: str) -> None:
    """A thread's timed wait of remaining wall length L, first seen at sim time t, ends at
    sim t + L: a series of earlier sim timers runs up to it, never past it (sim time then
    holds until the thread acts). Event.wait is timed from its frame; time.sleep and
    Lock.acquire(timeout=...), select and poll from the deadline the kernel shows (Linux)."""

    async def main() -> tuple[float, int]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[float] = loop.create_future()
        ticks = 0

        def worker() -> None:
            if wait == "event":
                threading.Event().wait(1)
            elif wait == "time_sleep":
                time.sleep(1)
            elif wait == "select":
                a, b = socket.socketpair()
                with a, b:
                    select.select([a], [], [], 1)
            elif wait == "poll":
                a, b = socket.socketpair()
                with a, b:
                    poller = select.poll()
                    poller.register(a, select.POLLIN)
                    poller.poll(1000)
            else:
                lock = threading.Lock()
                lock.acquire()
                lock.acquire(timeout=1)
            loop.call_soon_threadsafe(lambda: fut.set_result(loop.time()))

        async def ticker() -> None:
            nonlocal ticks
            while True:
                await asyncio.sleep(0.1)
                ticks += 1

        thread = threading.Thread(target=worker)
        thread.start()
        task = asyncio.create_task(ticker())
        delivered_at = await asyncio.wait_for(fut, 30)
        task.cancel()
        await asyncio.to_thread(thread.join, 10)
        return delivered_at, ticks

    delivered_at, ticks = evclock.run(main())
    if wait == "event":  # timed from when it is first seen: exactly 1 s of sim time
        assert (delivered_at, ticks) == (0.9, 9)
    else:  # from the kernel's deadline: what was left of 1 s when first seen
        assert 0.5 <= delivered_at <= 0.9
        assert ticks == round(delivered_at * 10)


def test_a_peer_thread_in_time_sleep_lets_a_short_sim_timeout_fire_first() -> None:
    """anyio's test_receive_timeout: the peer sleeps 1 s before closing; a 0.1 s timeout on
    the read fires first, as on stock asyncio; the close then arrives while time holds."""

    async def main() -> tuple[float, bytes, float]:
        server = socket.create_server(("127.0.0.1", 0))

        def serve() -> None:
            conn, _ = server.accept()
            time.sleep(1)
            conn.close()

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        reader, writer = await asyncio.open_connection(*server.getsockname()[:2])
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(reader.read(1), 0.1)
        timed_out_at = sim_time()
        rest = await asyncio.wait_for(reader.read(1), 5)  # EOF once the thread closes
        writer.close()
        await asyncio.to_thread(thread.join, 10)
        server.close()
        return timed_out_at, rest, sim_time()

    assert evclock.run(main()) == (0.1, b"", 0.1)


def _self_signed(tmp_path: pathlib.Path) -> tuple[str, str]:
    cert, key = str(tmp_path / "cert.pem"), str(tmp_path / "key.pem")
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", key,
         "-out", cert, "-days", "1", "-subj", "/CN=localhost"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    return cert, key


def test_a_tls_peer_thread_on_a_blocking_socket_gives_no_false_timeout(
    tmp_path: pathlib.Path,
) -> None:
    """test_ssl's threaded TLS server: its small records (session tickets, then b"O")
    can wait in its socket for the loop's ACK (Nagle) while the thread already blocks in
    recv; those unsent bytes are in flight, so no 30 s timeout fires in sim time."""
    cert, key = _self_signed(tmp_path)
    server_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server_ctx.load_cert_chain(cert, key)
    client_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    client_ctx.load_verify_locations(cert)
    hello = b"1" * 1000

    async def main() -> list[object]:
        server = socket.create_server(("127.0.0.1", 0))
        got: list[object] = []

        def serve() -> None:
            conn, _ = server.accept()
            conn.settimeout(20)  # a safety bound: it waits in poll(), like test_ssl's
            tls = server_ctx.wrap_socket(conn, server_side=True)
            tls.sendall(b"O")
            data = b""
            while len(data) < len(hello):
                data += tls.recv(len(hello) - len(data))
            got.append(len(data))
            tls.unwrap()
            tls.close()

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        loop = asyncio.get_running_loop()
        port = server.getsockname()[1]
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection("127.0.0.1", port, ssl=client_ctx, server_hostname="localhost"),
            30,
        )
        got.append(await asyncio.wait_for(reader.readexactly(1), 30))
        writer.write(hello)
        got.append(await asyncio.wait_for(reader.read(), 30))  # the peer's close_notify
        writer.close()
        await asyncio.to_thread(thread.join, 20)
        server.close()
        return [*got, loop.time()]

    assert evclock.run(main()) == [b"O", 1000, b"", 0.0]


@pytest.mark.parametrize("blocker", ["lock", "simple_queue"])
def test_a_thread_blocked_on_what_only_the_loop_releases_does_not_hold(blocker: str) -> None:
    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        lock = threading.Lock()
        lock.acquire()
        handoff: queue.SimpleQueue[str] = queue.SimpleQueue()
        fut: asyncio.Future[str] = loop.create_future()

        def worker() -> None:
            if blocker == "lock":
                lock.acquire()
                value = "unlocked"
            else:
                value = handoff.get()
            loop.call_soon_threadsafe(fut.set_result, value)

        thread = threading.Thread(target=worker)
        thread.start()
        await asyncio.sleep(1)  # the blocked thread holds no sim time
        lock.release()
        handoff.put("queued")
        value = await asyncio.wait_for(fut, 5)
        thread.join(5)
        return value, sim_time()

    expected = "unlocked" if blocker == "lock" else "queued"
    assert evclock.run(main()) == (expected, 1.0)


def test_an_executor_job_waiting_for_the_loop_does_not_hold() -> None:
    async def main() -> tuple[float, float]:
        loop = asyncio.get_running_loop()

        def job() -> float:
            inner = asyncio.run_coroutine_threadsafe(asyncio.sleep(2, result=loop.time()), loop)
            return inner.result()  # no timeout: bounded by the loop's stall_timeout below

        started_at = await loop.run_in_executor(None, job)
        return started_at, sim_time()

    assert evclock.run(main(), stall_timeout=10) == (0.0, 2.0)


def test_two_sim_loops_in_two_threads_do_not_stall_each_other() -> None:
    results: dict[str, float] = {}

    def run(name: str) -> None:
        async def main() -> float:
            for _ in range(50):
                await asyncio.sleep(0.1)
            return sim_time()

        results[name] = evclock.run(main(), stall_timeout=10)

    threads = [threading.Thread(target=run, args=(name,)) for name in ("a", "b")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert results == {"a": pytest.approx(5.0), "b": pytest.approx(5.0)}


def test_a_blocking_server_in_a_daemon_thread_is_a_peer() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def serve() -> None:  # blocking sockets, a daemon thread: an in-process test server
        conn, _ = listener.accept()
        with conn:
            data = conn.recv(100)
            time.sleep(0.05)  # "thinks" in wall time before answering
            conn.sendall(data.upper())

    threading.Thread(target=serve, daemon=True).start()

    async def main() -> tuple[bytes, float]:
        await asyncio.sleep(3)  # the server, waiting in accept(), holds no sim time
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"ping")
        reply = await asyncio.wait_for(reader.read(100), 1)
        writer.close()
        await writer.wait_closed()
        return reply, sim_time()

    try:
        assert evclock.run(main()) == (b"PING", 3.0)
    finally:
        listener.close()


def test_anyio_blocking_portal_in_a_daemon_thread() -> None:
    with anyio.from_thread.start_blocking_portal() as portal:

        async def main() -> tuple[int, float]:
            loop = asyncio.get_running_loop()
            value = await loop.run_in_executor(None, portal.call, abs, -3)
            fut: asyncio.Future[int] = loop.create_future()
            portal.start_task_soon(_deliver, loop, fut)
            return value + await asyncio.wait_for(fut, 1), sim_time()

        assert evclock.run(main()) == (7, 0.0)


async def _deliver(loop: asyncio.AbstractEventLoop, fut: asyncio.Future[int]) -> None:
    await anyio.sleep(0.05)  # wall time, on the portal's own loop
    loop.call_soon_threadsafe(fut.set_result, 4)


# ------------------------------------------------------------- bounds and errors


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux's tty work queue")
@pytest.mark.parametrize("reader", ["master", "raw slave"])
def test_bytes_written_to_a_pty_are_read_before_sim_time_moves(reader: str) -> None:
    # A pty hands written bytes to the other end through the kernel's tty work queue, a
    # moment later, and epoll does not see them until that work has run: a loop that only
    # asked epoll would jump to the 1 s timeout. Each of many writes is read at once.
    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        # Other I/O first, and time moving with it registered: the pty registered later is
        # handed over too (what the loop polls follows what is registered).
        other, peer = socket.socketpair()
        loop.add_reader(other, lambda: None)
        await asyncio.sleep(0.001)
        master, slave = os.openpty()
        if reader == "master":
            read_fd, write_fd = master, slave
        else:
            import tty

            tty.setraw(slave)  # no line buffering: every byte is input at once
            read_fd, write_fd = slave, master
        got: asyncio.Queue[bytes] = asyncio.Queue()

        class Reader(asyncio.Protocol):
            def data_received(self, data: bytes) -> None:
                got.put_nowait(data)

        transport, _ = await loop.connect_read_pipe(Reader, os.fdopen(read_fd, "rb", 0))
        waited = []
        try:
            for _ in range(100):
                os.write(write_fd, b"x")
                start = loop.time()
                assert await asyncio.wait_for(got.get(), 1.0) == b"x"
                waited.append(loop.time() - start)
        finally:
            transport.close()
            os.close(write_fd)
            loop.remove_reader(other)
            other.close()
            peer.close()
        return waited

    assert evclock.run(main()) == [0.0] * 100


def test_stall_timeout_bounds_waiting_for_io_that_never_comes() -> None:
    a, b = socket.socketpair()

    async def main() -> None:
        reader, writer = await asyncio.open_connection(sock=a)
        try:
            await reader.read(1)  # the peer never speaks
        finally:
            writer.close()  # run when the runner cancels this task after the StallError

    started = time.monotonic()
    try:
        with pytest.raises(evclock.StallError, match=r"waited .* s of wall time for I/O"):
            evclock.run(main(), stall_timeout=0.3)
    finally:
        b.close()
    assert time.monotonic() - started < 20


def test_a_thread_polling_forever_is_a_stall_naming_it_and_its_stack() -> None:
    stop = threading.Event()

    def poller() -> None:
        while not stop.wait(0.01):
            pass

    thread = threading.Thread(target=poller, name="poller")
    thread.start()

    async def main() -> None:
        await asyncio.sleep(1)

    try:
        with pytest.raises(evclock.StallError) as info:
            evclock.run(main(), stall_timeout=0.3)
    finally:
        stop.set()
        thread.join(5)
    message = str(info.value)
    assert "waiting for work outside the loop, which holds it:" in message
    assert "thread 'poller' (" in message  # waiting with a timeout, or awake between two
    assert "in poller" in message  # its stack


def test_an_idle_worker_thread_does_not_hide_a_deadlock() -> None:
    async def main() -> None:
        await asyncio.to_thread(time.sleep, 0.01)  # leaves an idle pool worker alive
        await asyncio.get_running_loop().create_future()  # nothing can ever resolve it

    with pytest.raises(evclock.DeadlockError, match="nothing can wake one"):
        evclock.run(main())


def test_selector_as_first_positional_argument() -> None:
    import selectors

    selector = selectors.DefaultSelector()
    loop = evclock.SimEventLoop(selector)
    try:
        assert loop._selector is selector

        async def main() -> float:
            await asyncio.sleep(2)
            return sim_time()

        assert loop.run_until_complete(main()) == 2.0
    finally:
        loop.close()


def test_a_paused_loop_whose_only_waker_is_a_signal_handler_waits_for_the_signal() -> None:
    # No thread, no socket: only SIGUSR1 (sent by a process the loop does not know) can
    # resume the loop, through its handler. Paused with that handler, the loop waits.
    async def main() -> tuple[float, bool, list[str]]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        got: list[str] = []

        def on_signal() -> None:
            got.append("SIGUSR1")
            loop.resume()

        loop.add_signal_handler(signal.SIGUSR1, on_signal)
        kill = f"os.kill({os.getpid()}, {int(signal.SIGUSR1)})"
        sender = subprocess.Popen([PY, "-c", f"import os, time; time.sleep(0.3); {kill}"])
        try:
            loop.pause()
            await asyncio.sleep(2)
        finally:
            sender.wait(10)
            loop.remove_signal_handler(signal.SIGUSR1)
        return loop.time(), loop.paused, got

    assert evclock.run(main()) == (2.0, False, ["SIGUSR1"])


def test_a_paused_loop_nothing_can_resume_is_a_deadlock() -> None:
    async def main() -> None:
        asyncio.get_running_loop().pause()  # type: ignore[attr-defined]
        await asyncio.sleep(1)

    with pytest.raises(evclock.DeadlockError) as info:
        evclock.run(main())
    assert str(info.value).startswith(
        "the loop is paused and nothing could ever resume it: no I/O or signal handler is "
        "registered, no child process runs and no other thread runs; call resume() or step() "
        "from a task before pausing, or serve a control channel (a socket, a signal handler) "
        "that can"
    )


# ------------------------------------------------------ controls from another thread


class Done:
    """Set by the loop when a test's scenario is over. Waiting on it is waiting on a
    concurrent future, which never holds sim time whatever its timeout (an
    ``Event.wait(10)`` would hold it for those 10 s: it may be a delay)."""

    def __init__(self) -> None:
        self._future: concurrent.futures.Future[None] = concurrent.futures.Future()

    def set(self) -> None:
        if not self._future.done():
            self._future.set_result(None)

    def wait(self, timeout: float) -> bool:
        try:
            self._future.result(timeout)
        except concurrent.futures.TimeoutError:
            return False
        return True


def _operate(loop: evclock.SimEventLoop, action: object, done: Done) -> None:
    """Call a control directly from this (operator) thread once the loop waits; if the loop
    has not finished 10 s later, unblock it through call_soon_threadsafe so that the test
    fails on its assertion instead of hanging."""
    time.sleep(0.05)
    action()  # type: ignore[operator]
    if not done.wait(10):
        loop.call_soon_threadsafe(loop.stop)


def test_step_and_resume_called_from_another_thread_wake_a_paused_loop() -> None:
    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        done = Done()
        seen = []
        loop.pause()
        threading.Thread(target=_operate, args=(loop, loop.step, done), daemon=True).start()
        await asyncio.sleep(3)  # one step: a jump to this deadline
        seen.append(loop.time())
        threading.Thread(target=_operate, args=(loop, loop.resume, done), daemon=True).start()
        await asyncio.sleep(4)
        seen.append(loop.time())
        done.set()
        return seen

    assert evclock.run(main()) == [3.0, 7.0]


def test_step_until_called_from_another_thread() -> None:
    async def main() -> float:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        done = Done()
        loop.pause()
        target = evclock.Time(2.5)

        def step_until() -> None:
            loop.step_until(target)

        threading.Thread(target=_operate, args=(loop, step_until, done), daemon=True).start()
        while loop.time() < 2.5:
            await asyncio.sleep(0.5)
        done.set()
        return loop.time()

    assert evclock.run(main()) == 2.5


def test_rtf_set_from_another_thread_ends_a_long_pacing_wait() -> None:
    async def main() -> float:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        done = Done()

        def full_speed() -> None:
            loop.rtf = None

        threading.Thread(target=_operate, args=(loop, full_speed, done), daemon=True).start()
        await asyncio.sleep(3600)  # at rtf=0.001 this would take 3.6 million wall seconds
        done.set()
        return loop.time()

    started = time.monotonic()
    assert evclock.run(main(), rtf=0.001) == 3600.0
    assert time.monotonic() - started < 30


def test_a_control_that_does_not_apply_raises_in_the_calling_thread() -> None:
    async def main() -> str:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, evclock.SimEventLoop)
        errors: list[BaseException] = []

        def operator() -> None:
            try:
                loop.step()  # the loop is not paused
            except evclock.PacingError as exc:
                errors.append(exc)

        thread = threading.Thread(target=operator)
        thread.start()
        await asyncio.to_thread(thread.join, 10)
        return str(errors[0])

    assert evclock.run(main()) == (
        "step() needs a paused loop, but it is running as fast as possible; "
        "call pause() first, then step"
    )


# ------------------------------------------- SimDriver's controls from another thread


def _in_thread(action: object) -> concurrent.futures.Future[object]:
    """Run ``action`` in a new (operator) thread after a moment; its result or error."""
    result: concurrent.futures.Future[object] = concurrent.futures.Future()

    def operator() -> None:
        time.sleep(0.05)  # let the driver reach its wait first
        try:
            result.set_result(action())  # type: ignore[operator]
        except BaseException as exc:
            result.set_exception(exc)

    threading.Thread(target=operator, daemon=True).start()
    return result


async def _outcome(result: concurrent.futures.Future[object]) -> object:
    return await asyncio.wait_for(asyncio.wrap_future(result), 10)


def test_driver_step_resume_and_rtf_from_another_thread_wake_it() -> None:
    # A plain asyncio loop sleeps in epoll while the paused driver waits: only the control's
    # hand-over (call_soon_threadsafe) can wake it. wait_for is wall time here (a bound).
    async def main() -> list[object]:
        seen: list[object] = []
        async with evclock.SimDriver(rtf=None, paused=True) as sim:
            op = _in_thread(sim.step)
            await asyncio.wait_for(sim.clock.sleep(3), 10)  # one step: a jump to 3 s
            # step() returns an awaitable of the steps (awaited on the driver's loop only)
            seen += [sim.now_ns, type(await _outcome(op)).__name__, sim.paused]
            op = _in_thread(sim.resume)
            await asyncio.wait_for(sim.clock.sleep(4), 10)
            seen += [sim.now_ns, sim.paused]

            def slow() -> None:
                sim.rtf = 0.001  # from the operator thread: a very long pacing wait

            await _outcome(_in_thread(slow))

            def full_speed() -> None:
                sim.rtf = None

            op = _in_thread(full_speed)
            await asyncio.wait_for(sim.clock.sleep(3600), 10)  # 3.6e6 wall s at rtf=0.001
            seen += [sim.now_ns, sim.rtf]
            await _outcome(op)
        return seen

    assert asyncio.run(main()) == [3 * 10**9, "Steps", True, 7 * 10**9, False, 3607 * 10**9, None]


def test_driver_pause_and_step_until_from_another_thread_stop_exactly() -> None:
    async def main() -> list[object]:
        seen: list[object] = []
        async with evclock.SimDriver(rtf=None) as sim:
            ticks: list[int] = []

            async def controller() -> None:
                async for tick in sim.clock.rate(10):
                    ticks.append(tick.index)

            task = asyncio.create_task(controller())
            await asyncio.wait_for(sim.run_until(1.0), 10)
            await _outcome(_in_thread(sim.pause))
            paused_at = sim.now_ns
            for _ in range(50):  # paused: time stands still
                await asyncio.sleep(0.001)
            seen += [sim.paused, sim.now_ns == paused_at]
            target = evclock.Time(seconds=paused_at / 1e9 + 2.55)
            await _outcome(_in_thread(lambda: sim.step_until(target)))
            while sim.now_ns < target.nanoseconds:
                await asyncio.wait_for(sim.clock.sleep(0.05), 10)
            for _ in range(50):
                await asyncio.sleep(0.001)
            seen += [sim.now_ns - paused_at, sim.paused]
            task.cancel()
        return seen

    assert asyncio.run(main()) == [True, True, 2_550_000_000, True]


def test_driver_control_that_does_not_apply_raises_in_the_calling_thread() -> None:
    async def main() -> str:
        async with evclock.SimDriver(rtf=None) as sim:
            with pytest.raises(evclock.PacingError) as info:
                await _outcome(_in_thread(sim.step))  # not paused
            return str(info.value)

    assert asyncio.run(main()) == (
        "step() needs a paused loop, but it is running as fast as possible; "
        "call pause() first, then step"
    )


def test_driver_hold_time_from_another_thread_holds_and_wakes_it() -> None:
    async def main() -> list[object]:
        async with evclock.SimDriver(rtf=None) as sim:
            entered = threading.Event()
            leave = threading.Event()

            def worker() -> None:
                with sim.hold_time():
                    entered.set()
                    leave.wait(10)

            thread = threading.Thread(target=worker)
            thread.start()
            assert await asyncio.to_thread(entered.wait, 10)
            before = sim.now_ns
            sleeper = asyncio.ensure_future(sim.clock.sleep(5))
            for _ in range(50):
                await asyncio.sleep(0.001)
            held = [sim.now_ns == before, sleeper.done()]
            leave.set()
            await asyncio.wait_for(sleeper, 10)
            await asyncio.to_thread(thread.join, 10)
            return [*held, sim.now_ns - before]

    assert asyncio.run(main()) == [True, False, 5 * 10**9]


def test_driver_waits_from_another_thread_raise_wrong_thread_error() -> None:
    async def main() -> list[str]:
        async with evclock.SimDriver(rtf=None) as sim:

            def elsewhere() -> list[str]:
                messages = []
                for coro in (sim.run_until(1.0), sim.stop()):
                    with pytest.raises(evclock.WrongThreadError) as info:
                        asyncio.run(coro)
                    messages.append(str(info.value))
                return messages

            messages = await asyncio.to_thread(elsewhere)
        return messages

    assert asyncio.run(main()) == [
        "SimDriver.run_until(t) must be awaited on the event loop the driver runs on, but it "
        "was called from another thread (or loop); hand it to the driver's loop with "
        "asyncio.run_coroutine_threadsafe(sim.run_until(t), sim.loop).result(timeout), or "
        "call the thread-safe controls (pause(), resume(), step(), step_until(), rtf) directly",
        "SimDriver.stop() must be awaited on the event loop the driver runs on, but it was "
        "called from another thread (or loop); hand it to the driver's loop with "
        "asyncio.run_coroutine_threadsafe(sim.stop(), sim.loop).result(timeout), or call "
        "the thread-safe controls (pause(), resume(), step(), step_until(), rtf) directly",
    ]
    assert issubclass(evclock.WrongThreadError, evclock.NotRunningError)


def test_outside_world_example_prints_exact_sim_times() -> None:
    proc = run_example("outside_world.py")
    assert proc.stdout.splitlines() == [
        "child process said 'computed' at 0.000000000 s (sim)",
        "thread handed over 'done' at 0.000000000 s (sim)",
        "received SIGUSR1 at 0.000000000 s (sim)",
        "server replied 'PING' at 5.000000000 s (sim)",
    ]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="needs Linux scheduling classes")
def test_a_parked_thread_the_loop_wakes_holds_time_after_many_unchanged_surveys() -> None:
    # The thread stays parked for many steps (its state is reused, as it has not run since),
    # then the loop itself wakes it. Pinned to the loop's CPU at idle priority, the woken
    # thread cannot run before the loop looks again: runnable but not yet run, it must
    # already hold sim time until it answers.
    cpu = min(os.sched_getaffinity(0))
    affinity = os.sched_getaffinity(0)

    async def main() -> tuple[str, int]:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        wake: queue.Queue[int] = queue.Queue()
        answer: asyncio.Future[str] = loop.create_future()

        def worker() -> None:
            os.sched_setaffinity(0, {cpu})
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            wake.get(timeout=60)
            busy_until = time.monotonic() + 0.05
            while time.monotonic() < busy_until:
                pass
            loop.call_soon_threadsafe(answer.set_result, "done")

        thread = threading.Thread(target=worker, daemon=True)
        thread.start()
        for _ in range(200):
            await clock.sleep(0.001)
        wake.put(1)
        result = await asyncio.wait_for(answer, 0.01)
        thread.join(60)
        return result, clock.now_ns()

    os.sched_setaffinity(0, {cpu})
    try:
        result, now_ns = evclock.run(main())
    finally:
        os.sched_setaffinity(0, affinity)
    assert result == "done"
    assert now_ns == 200 * 1_000_000
