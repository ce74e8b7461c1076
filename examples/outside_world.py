"""Work outside the loop on sim time: a child process, a thread, a signal, an in-process server.

Run it with ``python examples/outside_world.py``. Each part waits for something outside the
loop under a sim-time timeout, as a real program does on stock asyncio; the timeouts do not
fire, because outside work holds sim time while it runs (docs/guides/outside.md):

1. a child process that works 0.2 s of wall time, awaited with ``wait_for(..., 10)``;
2. a thread that waits 50 ms (``Event.wait(0.05)``) before handing over a result;
3. a signal sent by a child process to this one, waited for with ``add_signal_handler``;
4. a blocking echo server in a daemon thread, which holds no sim time while it waits in
   ``accept()`` (the controller sleeps 5 s of sim time meanwhile, instantly).

Sim times are exact and the same on every run.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import sys
import threading

import evclock


async def child_process() -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", "import time; time.sleep(0.2); print('computed')",
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, _ = await asyncio.wait_for(proc.communicate(), 10)
    print(f"child process said {out.decode().strip()!r} at {evclock.clock().now()}")


async def thread_with_a_timeout() -> None:
    loop = asyncio.get_running_loop()
    result: asyncio.Future[str] = loop.create_future()

    def worker() -> None:
        threading.Event().wait(0.05)  # a wall-time delay: it holds sim time
        loop.call_soon_threadsafe(result.set_result, "done")

    threading.Thread(target=worker).start()
    value = await asyncio.wait_for(result, 1)
    print(f"thread handed over {value!r} at {evclock.clock().now()}")


async def signal_from_a_child() -> None:
    loop = asyncio.get_running_loop()
    got: asyncio.Future[str] = loop.create_future()
    loop.add_signal_handler(signal.SIGUSR1, got.set_result, "SIGUSR1")
    try:
        kill = f"import os, time; time.sleep(0.1); os.kill({os.getpid()}, {signal.SIGUSR1:d})"
        proc = await asyncio.create_subprocess_exec(sys.executable, "-c", kill)
        print(f"received {await got} at {evclock.clock().now()}")
        await proc.wait()
    finally:
        loop.remove_signal_handler(signal.SIGUSR1)


async def server_in_a_daemon_thread() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.sendall(conn.recv(100).upper())

    threading.Thread(target=serve, daemon=True).start()
    await evclock.clock().sleep(5)  # the server waits in accept(): sim time runs
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"ping")
    reply = await asyncio.wait_for(reader.read(100), 1)
    writer.close()
    await writer.wait_closed()
    listener.close()
    print(f"server replied {reply.decode()!r} at {evclock.clock().now()}")


async def main() -> None:
    await child_process()
    await thread_with_a_timeout()
    await signal_from_a_child()
    await server_in_a_daemon_thread()


if __name__ == "__main__":
    evclock.run(main())
