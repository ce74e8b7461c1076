"""Sim time across processes: serving, joining, lockstep, follow and the data channel.

The simulation runs in the test process (``evclock.run`` + ``evclock.remote.serve``); participants
are real interpreter processes joining over a real Unix socket (or loopback TCP).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import re
import socket
import stat
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from _remote_helpers import WAKE_TIMES, finish, read_line, serve_until_left, spawn

import evclock
from evclock.remote import _protocol as proto
from evclock.remote._address import parse_address

TICKER = """
import json, sys, evclock

async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    seen = [clock.now().nanoseconds]
    for i in range(int(sys.argv[1])):
        await clock.sleep(0.001)
        seen.append(clock.now().nanoseconds)
        link.publish("tick", str(i).encode())
    print(json.dumps(seen))

evclock.run(main())
"""

#: Clock tokens of 128 bits or more (22 URL-safe characters): a weaker one is refused.
TOKEN = "kB2n7T0qZx4LmP9sWv3YcR"
OTHER_TOKEN = "Qe5hVd8uNa1oJf6gXt0bUy"


def address(tmp_path: Path, name: str = "sim.sock") -> str:
    return f"unix://{tmp_path / name}"


def test_lockstep_participant_runs_on_server_time_and_data_is_handled_at_its_time(
    tmp_path: Path,
) -> None:
    url = address(tmp_path)
    proc = spawn(tmp_path, TICKER, "5", EVCLOCK_CLOCK=f"{url}?name=ticker")
    handled: list[tuple[int, int, str]] = []

    async def main() -> int:
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:

            def on_tick(message: evclock.remote.Message) -> None:
                now = clock.now().nanoseconds
                handled.append((message.time.nanoseconds, now, message.data.decode()))

            server.subscribe("tick", on_tick)
            await server.wait_for_participants("ticker")
            assert server.participants == ("ticker",)
            await server.wait_until_left()
            return evclock.clock().now().nanoseconds

    end = evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    assert json.loads(out) == [0, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 5_000_000]
    # Each message was handled by the simulation at the sim time it was sent, in order.
    assert handled == [((i + 1) * 1_000_000, (i + 1) * 1_000_000, str(i)) for i in range(5)]
    assert end == 5_000_000


def test_participants_due_at_the_same_time_are_granted_together_and_one_may_leave_early(
    tmp_path: Path,
) -> None:
    # a, b and c share every 1 ms deadline (one group per deadline on the server); c leaves
    # after 2 rounds while a and b are still due then; d's deadlines fall in between.
    url = address(tmp_path)
    rounds = {"a": "6", "b": "6", "c": "2"}
    procs = {
        n: spawn(tmp_path, TICKER, k, EVCLOCK_CLOCK=f"{url}?name={n}") for n, k in rounds.items()
    }
    procs["d"] = spawn(
        tmp_path, TICKER.replace("0.001", "0.0015"), "4", EVCLOCK_CLOCK=f"{url}?name=d"
    )
    handled: list[tuple[int, str, str]] = []

    async def main() -> int:
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:

            def on_tick(message: evclock.remote.Message) -> None:
                assert clock.now() == message.time  # handled at its sim time
                handled.append((message.time.nanoseconds, message.sender, message.data.decode()))

            server.subscribe("tick", on_tick)
            await server.wait_for_participants("a", "b", "c", "d")
            await server.wait_until_left()
            return clock.now().nanoseconds

    end = evclock.run(main())
    outs = {}
    for name, proc in procs.items():
        code, out, err = finish(proc)
        assert code == 0, err
        outs[name] = json.loads(out)
    start = outs["a"][0]  # the time all four had joined at (they join while time is held)
    assert all(seen[0] == start for seen in outs.values())
    for name, count in (("a", 6), ("b", 6), ("c", 2)):
        assert outs[name] == [start + i * 1_000_000 for i in range(count + 1)]
    assert outs["d"] == [start + i * 1_500_000 for i in range(5)]
    assert end == start + 6_000_000
    # Everything sent was handled, in time order; at a shared time in join order (one order
    # throughout: the order the processes happened to join in).
    times = [t_ns for t_ns, _, _ in handled]
    assert times == sorted(times)
    before: set[tuple[str, str]] = set()  # (x, y): x was handled before y at a shared time
    for t_ns in sorted(set(times)):
        senders = [sender for t, sender, _ in handled if t == t_ns]
        before.update(itertools.combinations(senders, 2))
    assert not any((y, x) in before for x, y in before)
    assert sorted(sender for _, sender, _ in handled) == sorted("a" * 6 + "b" * 6 + "cc" + "d" * 4)


def test_simulation_does_not_advance_while_a_participant_works(tmp_path: Path) -> None:
    url = address(tmp_path)
    slow = """
    import time, evclock
    async def main():
        clock = evclock.clock()
        for _ in range(3):
            await clock.sleep(0.010)
            time.sleep(0.05)  # 50 ms of wall-time work at this sim time
            evclock.remote.participant().publish("done", b"")
    evclock.run(main())
    """
    proc = spawn(tmp_path, slow, EVCLOCK_CLOCK=f"{url}?name=slow")
    seen: list[tuple[int, int]] = []

    async def main() -> None:
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            server.subscribe(
                "done", lambda m: seen.append((m.time.nanoseconds, clock.now().nanoseconds))
            )
            await server.wait_for_participants("slow")

            async def busy_sim() -> None:  # the simulation's own 1 kHz activity
                while True:
                    await clock.sleep(0.001)

            task = asyncio.create_task(busy_sim())
            await server.wait_until_left()
            task.cancel()

    evclock.run(main())
    code, _, err = finish(proc)
    assert code == 0, err
    assert seen == [(10_000_000, 10_000_000), (20_000_000, 20_000_000), (30_000_000, 30_000_000)]


class KeepaliveCount:
    """Counts a clock server's keepalives (every 0.2 s of wall time, one more callback
    each), which the poll-counting tests allow for."""

    def __init__(self) -> None:
        self.count = 0

    def watch(self, server: evclock.remote.ClockServer) -> None:
        keepalive = server._keepalive

        def counting_keepalive() -> None:
            self.count += 1
            keepalive()

        server._keepalive = counting_keepalive  # type: ignore[method-assign]


def test_a_lockstep_round_costs_the_server_no_zero_timeout_poll(tmp_path: Path) -> None:
    """Per round the server waits for the DONE (a blocking poll) and nothing more: its
    connections are accounted for (it holds sim time while a participant works), so no
    poll comes before time moves, nor before running what the DONE or the move made ready.
    Only zero-timeout polls are counted (how many blocking waits time out depends on the
    machine's speed), and the server's keepalives (every 0.2 s of wall time, one more
    callback each) are counted to be allowed for."""
    url = address(tmp_path)
    rounds = 200
    proc = spawn(tmp_path, TICKER, str(rounds), EVCLOCK_CLOCK=f"{url}?name=ticker")
    zero_polls = 0
    keepalives = KeepaliveCount()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("ticker")
            select = loop._selector.select  # type: ignore[attr-defined]

            def counting_select(timeout: float | None = None) -> object:
                nonlocal zero_polls
                zero_polls += timeout == 0
                return select(timeout)

            loop._selector.select = counting_select  # type: ignore[attr-defined]
            keepalives.watch(server)
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    assert len(json.loads(out)) == rounds + 1
    # A few around the join and the leave, at most two per keepalive (one callback between
    # two rounds); none per round (one per round before the round path, three before that).
    assert zero_polls <= 10 + 2 * keepalives.count, (zero_polls, keepalives.count)


COUNTING_TICKER = """
import asyncio, json, sys, evclock

async def main():
    loop = asyncio.get_running_loop()
    clock = evclock.clock()
    await clock.sleep(0.001)
    selects = 0
    select = loop._selector.select

    def counting_select(timeout=None):
        nonlocal selects
        selects += 1
        return select(timeout)

    loop._selector.select = counting_select
    for _ in range(int(sys.argv[1])):
        await clock.sleep(0.001)
    print(json.dumps({"selects": selects, "now": clock.now().nanoseconds}))

evclock.run(main())
"""


def test_a_lockstep_participant_waits_for_its_grant_inside_the_advance(tmp_path: Path) -> None:
    """A participant with nothing else outside its loop waits for the grant in the loop's
    request to advance (SimEventLoop._wait_for_source) and moves at once: its loop's selector
    is not polled per round (it was, once or twice, before). Only the server's keepalives
    (every 0.2 s of wall time, read through the loop) and the leave may poll it."""
    url = address(tmp_path)
    rounds = 300
    proc = spawn(tmp_path, COUNTING_TICKER, str(rounds), EVCLOCK_CLOCK=f"{url}?name=ticker")
    keepalives = KeepaliveCount()

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            keepalives.watch(server)
            await server.wait_for_participants("ticker")
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    seen = json.loads(out)
    assert seen["now"] == (rounds + 1) * 1_000_000
    assert seen["selects"] <= 5 + 2 * keepalives.count, (seen, keepalives.count)


WAITS_FOR_A_GRANT = """
import evclock

async def main():
    clock = evclock.clock()
    await clock.sleep(0.001)
    print("waiting", flush=True)
    await clock.sleep(0.001)  # the simulation holds its time before this deadline

evclock.run(main())
"""


def test_ctrl_c_ends_a_lockstep_participant_waiting_for_its_grant(tmp_path: Path) -> None:
    """The participant's wait for a grant inside its advance is ended by a signal, as the
    loop's own wait is: Ctrl-C (SIGINT) ends it while the simulation withholds the grant."""
    import signal
    import time

    url = address(tmp_path)
    proc = spawn(tmp_path, WAITS_FOR_A_GRANT, EVCLOCK_CLOCK=f"{url}?name=waiter")

    def interrupt_while_held() -> tuple[int | None, float]:
        assert read_line(proc) == "waiting\n"
        proc.send_signal(signal.SIGINT)
        start = time.monotonic()
        try:
            code = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            return None, time.monotonic() - start
        return code, time.monotonic() - start

    async def main() -> tuple[int | None, float]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url, on_fault="drop") as server:
            await server.wait_for_participants("waiter")
            await evclock.clock().sleep(0.0015)
            # An executor job holds sim time at 1.5 ms: the grant of 2 ms never comes.
            result = await loop.run_in_executor(None, interrupt_while_held)
            await server.wait_until_left()
            return result

    code, waited = evclock.run(main())
    _, err = proc.communicate(timeout=60)
    assert code is not None, f"the participant ignored SIGINT for {waited:.1f} s"
    assert code != 0
    assert "KeyboardInterrupt" in err, err


@pytest.mark.pybullet
def test_follower_sees_every_physics_step_and_never_holds_the_simulation(tmp_path: Path) -> None:
    from evclock.sources import PyBulletTimeSource

    url = address(tmp_path)
    proc = spawn(
        tmp_path, WAKE_TIMES, "3", "0.010", EVCLOCK_CLOCK=f"{url}?name=watcher&mode=follow"
    )
    source = PyBulletTimeSource.connect()

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("watcher")
            await server.wait_until_left()

    evclock.run(main(), source=source)
    code, out, err = finish(proc)
    assert code == 0, err
    times = json.loads(out)
    step = 1_000_000_000 / 240
    # On step boundaries (exact ns of whole steps), in order, each at least 10 ms after the last.
    assert all(abs(t / step - round(t / step)) < 1e-6 for t in times)
    assert times == sorted(times)
    assert times[0] >= 10_000_000
    assert all(b - a >= 10_000_000 for a, b in itertools.pairwise(times))


def test_a_participant_started_before_the_server_waits_for_it(tmp_path: Path) -> None:
    url = address(tmp_path)
    proc = spawn(tmp_path, TICKER, "2", EVCLOCK_CLOCK=f"{url}?name=early")
    # The participant is already retrying when the server comes up.

    serve_until_left(url, "early")
    code, out, err = finish(proc)
    assert code == 0, err
    assert json.loads(out) == [0, 1_000_000, 2_000_000]


def test_late_join_starts_at_the_current_sim_time(tmp_path: Path) -> None:
    url = address(tmp_path)

    async def main() -> None:
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            await clock.sleep(0.5)
            proc = spawn(tmp_path, TICKER, "1", EVCLOCK_CLOCK=f"{url}?name=late")
            await server.wait_for_participants("late")
            await server.wait_until_left()
        code, out, err = finish(proc)
        assert code == 0, err
        assert json.loads(out) == [500_000_000, 501_000_000]

    evclock.run(main())


def test_participants_exchange_data_at_the_same_sim_time(tmp_path: Path) -> None:
    url = address(tmp_path)
    listener = """
    import json, evclock
    async def main():
        clock = evclock.clock()
        link = evclock.remote.participant()
        got = []
        import asyncio
        done = asyncio.Event()
        def on_ping(message):
            now = clock.now().nanoseconds
            got.append([message.sender, message.time.nanoseconds, now, message.data.decode()])
            if len(got) == 3:
                done.set()
        link.subscribe("ping", on_ping)
        link.publish("ready", b"")
        await done.wait()
        print(json.dumps(got))
    evclock.run(main())
    """
    talker = """
    import evclock
    async def main():
        clock = evclock.clock()
        for i in range(3):
            await clock.sleep(0.25)
            evclock.remote.participant().publish("ping", f"#{i}".encode())
    evclock.run(main())
    """

    async def main() -> tuple[subprocess.Popen[str], subprocess.Popen[str]]:
        async with evclock.remote.serve(url) as server:
            ready = asyncio.Event()
            server.subscribe("ready", lambda _m: ready.set())
            first = spawn(tmp_path, listener, EVCLOCK_CLOCK=f"{url}?name=listener")
            await server.wait_for_participants("listener")
            await ready.wait()
            second = spawn(tmp_path, talker, EVCLOCK_CLOCK=f"{url}?name=talker")
            await server.wait_for_participants("talker")
            await server.wait_until_left()
        return first, second

    first, second = evclock.run(main())
    code, out, err = finish(first)
    assert code == 0, err
    assert finish(second)[0] == 0
    assert json.loads(out) == [
        ["talker", 250_000_000, 250_000_000, "#0"],
        ["talker", 500_000_000, 500_000_000, "#1"],
        ["talker", 750_000_000, 750_000_000, "#2"],
    ]


def test_calls_are_answered_and_their_errors_reported(tmp_path: Path) -> None:
    url = address(tmp_path)
    caller = """
    import evclock
    async def main():
        link = evclock.remote.participant()
        print(link.call("echo", b"abc").decode())
        for service in ("broken", "missing"):
            try:
                link.call(service)
            except evclock.remote.RemoteCallError as exc:
                print(exc)
    evclock.run(main())
    """
    proc = spawn(tmp_path, caller, EVCLOCK_CLOCK=f"{url}?name=caller")

    def broken(_data: bytes) -> bytes:
        raise ValueError("no such joint")

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            server.provide("echo", lambda data: data[::-1])
            server.provide("broken", broken)
            await server.wait_for_participants("caller")
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    assert out.splitlines() == [
        "cba",
        "call to 'broken' failed in the simulation: ValueError: no such joint",
        "call to 'missing' failed in the simulation: no service 'missing' (known: broken, echo)",
    ]


def test_unix_socket_is_owner_only_and_removed_afterwards(tmp_path: Path) -> None:
    path = tmp_path / "private.sock"

    async def main() -> int:
        async with evclock.remote.serve(f"unix://{path}"):
            return stat.S_IMODE(os.stat(path).st_mode)

    assert evclock.run(main()) == 0o600
    assert not path.exists()


def test_an_existing_socket_file_is_not_replaced(tmp_path: Path) -> None:
    path = tmp_path / "taken.sock"
    path.write_text("")

    async def main() -> None:
        async with evclock.remote.serve(f"unix://{path}"):
            pass

    with pytest.raises(evclock.InvalidArgumentError, match="already exists; another clock server"):
        evclock.run(main())


@pytest.mark.pybullet
def test_tcp_serves_on_loopback_and_checks_the_token(tmp_path: Path) -> None:
    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve("tcp://127.0.0.1:0", token=TOKEN) as server:
            assert server.address.startswith("tcp://127.0.0.1:")
            wrong = spawn(
                tmp_path, TICKER, "1", EVCLOCK_CLOCK=f"{server.address}?token={OTHER_TOKEN}"
            )
            # Served while we wait for the refused process to end (a wait in a worker thread).
            code, _, refused = await loop.run_in_executor(None, finish, wrong)
            assert code == 1
            right = spawn(
                tmp_path, TICKER, "1", EVCLOCK_CLOCK=f"{server.address}?token={TOKEN}&name=ok"
            )
            await server.wait_for_participants("ok")
            await server.wait_until_left()
        code, out, err = finish(right)
        assert code == 0, err
        return [refused.strip().splitlines()[-1], out, server.address]

    wrong, right, served = evclock.run(main())
    # The server could not prove it knows the other token: the participant sends it nothing.
    assert wrong == (
        f"evclock.remote.JoinRefusedError: the clock server at {served} could not "
        "prove it knows the token: it is not the simulation you meant (or the tokens "
        "differ); the token was not sent to it"
    )
    assert json.loads(right) == [0, 1_000_000]


def test_tcp_refuses_a_non_loopback_address_without_a_token() -> None:
    async def main() -> None:
        async with evclock.remote.serve("tcp://0.0.0.0:0"):
            pass

    with pytest.raises(evclock.InvalidArgumentError, match="needs a shared token"):
        evclock.run(main())

    async def with_token() -> None:
        async with evclock.remote.serve("tcp://0.0.0.0:0", token=TOKEN):
            pass

    with pytest.raises(evclock.InvalidArgumentError, match="not a loopback address"):
        evclock.run(with_token())


def test_serve_needs_a_sim_loop() -> None:
    async def main() -> None:
        async with evclock.remote.serve("unix:///tmp/never.sock"):
            pass

    with pytest.raises(evclock.InvalidTypeError, match="serves the sim time of a SimEventLoop"):
        evclock.run(main(), use_sim_time=False)


# ------------------------------------------------------------------ launch-time clock choice


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("http://x", "unsupported clock 'http://x': known schemes are unix://, tcp://"),
        ("unix://relative.sock", "unix:///absolute/path.sock (three slashes)"),
        ("unix:///tmp/s.sock?mode=fast", "mode must be 'lockstep' or 'follow'"),
        ("unix:///tmp/s.sock?color=red", "unknown option 'color' in clock address"),
        ("unix:///tmp/s.sock?timeout=-1", "timeout must be a positive number of seconds"),
        ("unix:///tmp/s.sock?timeout=0.1", "timeout must be at least 0.5 s (the server's keep"),
        ("tcp://127.0.0.1", "a tcp clock address is tcp://HOST:PORT"),
    ],
)
def test_bad_clock_addresses_are_refused(url: str, message: str) -> None:
    async def main() -> None:
        raise AssertionError("must not run")

    with pytest.raises(
        evclock.InvalidArgumentError, match=message.replace("(", r"\(").replace(")", r"\)")
    ):
        evclock.run(main(), clock=url)


def test_clock_conflicts_are_errors_not_guesses(monkeypatch: pytest.MonkeyPatch) -> None:
    async def main() -> None:
        raise AssertionError("must not run")

    with pytest.raises(evclock.InvalidArgumentError, match="which owns sim time; drop source="):
        evclock.run(main(), clock="unix:///tmp/x.sock", source=evclock.sources.VirtualTimeSource())
    with pytest.raises(evclock.InvalidArgumentError, match=r"pacing .* belongs to that simulation"):
        evclock.run(main(), clock="unix:///tmp/x.sock", rtf=1.0)
    with pytest.raises(evclock.InvalidArgumentError, match="use_sim_time resolved to False"):
        evclock.run(main(), clock="unix:///tmp/x.sock", use_sim_time=False)
    monkeypatch.setenv("EVCLOCK_CLOCK", "unix:///tmp/x.sock")
    with pytest.raises(
        evclock.InvalidArgumentError, match=re.escape("EVCLOCK_CLOCK='unix:///tmp/x.sock'")
    ):
        evclock.run(main(), source=evclock.sources.VirtualTimeSource())
    with pytest.raises(evclock.InvalidTypeError, match="clock must be a URL string"):
        evclock.run(main(), clock=3)  # type: ignore[arg-type]


def test_no_server_is_a_clock_lost_error_after_the_timeout(tmp_path: Path) -> None:
    async def main() -> None:
        raise AssertionError("must not run")

    with pytest.raises(
        evclock.ClockLostError, match=r"no clock server at unix://.* after waiting 0\.5 s"
    ):
        evclock.run(main(), clock=f"unix://{tmp_path / 'none.sock'}?timeout=0.5")


def test_a_registered_clock_scheme_provides_the_source(monkeypatch: pytest.MonkeyPatch) -> None:
    from evclock.hosts import _config

    monkeypatch.setattr(_config, "_CLOCK_SCHEMES", dict(_config._CLOCK_SCHEMES))
    made: list[str] = []

    def factory(url: str) -> evclock.sources.TimeSource:
        made.append(url)
        return evclock.sources.VirtualTimeSource(7_000_000_000)

    evclock.register_clock_scheme("fake", factory)

    async def main() -> float:
        await asyncio.sleep(1)
        return evclock.clock().now().seconds

    monkeypatch.setenv("EVCLOCK_CLOCK", "fake://anything")
    assert evclock.run(main()) == 8.0
    assert made == ["fake://anything"]
    with pytest.raises(evclock.InvalidArgumentError, match="a clock scheme is a lowercase word"):
        evclock.register_clock_scheme("Bad Scheme", factory)


def test_participant_outside_a_joined_program_is_an_error() -> None:
    async def main() -> None:
        evclock.remote.participant()

    with pytest.raises(evclock.NoSimulationError, match="did not join a clock server"):
        evclock.run(main())


# ------------------------------------------------------------------ framing


def test_frames_split_across_reads_are_reassembled() -> None:
    stream = proto.grant(5) + proto.done(5, 10) + proto.publish(5, "topic", b"\x00" * 1000)
    reader = proto.Reader()
    frames = []
    for i in range(0, len(stream), 7):
        frames += reader.feed(stream[i : i + 7])
    assert [kind for kind, _ in frames] == [proto.GRANT, proto.DONE, proto.PUBLISH]
    assert proto.parse_stamp(frames[0][1]) == 5
    assert proto.parse_done(frames[1][1]) == (5, 10)
    assert proto.parse_publish(frames[2][1]) == (5, "topic", b"\x00" * 1000)


def test_a_bad_frame_length_is_a_protocol_error() -> None:
    with pytest.raises(evclock.remote.ProtocolError, match="bad frame length"):
        proto.Reader().feed(b"GET / HTTP/1.1\r\n\r\n")


def test_address_options_are_parsed() -> None:
    parsed = parse_address("unix:///tmp/a.sock?mode=follow&name=cam&timeout=2.5&token=t")
    assert (parsed.path, parsed.mode, parsed.name, parsed.timeout, parsed.token) == (
        "/tmp/a.sock",
        "follow",
        "cam",
        2.5,
        "t",
    )
    assert str(parse_address("tcp://127.0.0.1:7411")) == "tcp://127.0.0.1:7411"


def test_a_long_wait_on_a_live_server_is_not_a_lost_clock(tmp_path: Path) -> None:
    url = address(tmp_path)
    # 1 s of patience, 3 s of wall time until its deadline: the server's keepalives (every
    # 0.2 s) count, with room for a loaded machine's stalls between them.
    proc = spawn(tmp_path, TICKER.replace("0.001", "3.0"), "1", EVCLOCK_CLOCK=f"{url}?timeout=1")

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants(count=1)
            await server.wait_until_left()

    evclock.run(main(), rtf=1.0)
    code, out, err = finish(proc)
    assert code == 0, err
    assert json.loads(out) == [0, 3_000_000_000]


def test_physics_calls_carry_plain_and_numpy_values_only() -> None:
    np = pytest.importorskip("numpy")
    from evclock.remote._physics import encode_call

    data = encode_call("resetBasePositionAndOrientation", (1, np.zeros(2)), {"physicsClientId": 0})
    assert json.loads(data) == ["resetBasePositionAndOrientation", [1, [0.0, 0.0]], {}]
    with pytest.raises(
        evclock.InvalidTypeError,
        match=r"^object cannot be sent to the simulation: pass numbers, strings, lists, "
        r"tuples, dicts or numpy arrays$",
    ):
        encode_call("resetBasePositionAndOrientation", (object(),), {})


def test_whole_frames_one_or_several_per_read() -> None:
    reader = proto.Reader()
    assert reader.feed(proto.grant(7)) == [(proto.GRANT, (7).to_bytes(8, "little"))]
    two = reader.feed(proto.done(7, 9) + proto.bye())
    assert [kind for kind, _ in two] == [proto.DONE, proto.BYE]
    with pytest.raises(evclock.remote.ProtocolError, match="bad frame length 0"):
        reader.feed(b"\x00\x00\x00\x00D")


def test_a_rounds_frames_unpack_whole_and_the_reader_says_when_it_holds_a_partial_one() -> None:
    # The hot path of a round takes a read that is exactly one GRANT / DONE in one unpack.
    assert len(proto.grant(7)) == proto.STAMP_SIZE
    assert proto.unpack_stamp(proto.grant(7)) == (proto.STAMP_SIZE - 4, proto.GRANT, 7)
    assert len(proto.done(7, 9)) == proto.DONE_SIZE
    assert proto.unpack_done(proto.done(7, proto.NO_DEADLINE)) == (
        proto.DONE_SIZE - 4,
        proto.DONE,
        7,
        proto.NO_DEADLINE,
    )
    # A frame cut across reads: the next read, even of a DONE's size, is not a frame start.
    reader = proto.Reader()
    assert reader.between_frames
    frame = proto.done(7, 9)
    assert reader.feed(frame[:5]) == []
    assert not reader.between_frames
    assert reader.feed(frame[5:]) == [(proto.DONE, frame[5:])]
    assert reader.between_frames


def test_the_simulation_publishes_to_a_waiting_lockstep_participant(tmp_path: Path) -> None:
    url = address(tmp_path)
    waiter = """
    import asyncio, json, evclock
    async def main():
        clock = evclock.clock()
        got = asyncio.Queue()
        evclock.remote.participant().subscribe("cmd", got.put_nowait)
        evclock.remote.participant().publish("subscribed", b"")
        message = await got.get()  # no deadline: only data wakes this participant
        print(json.dumps([message.sender, message.time.nanoseconds, clock.now().nanoseconds]))
    evclock.run(main())
    """
    proc = spawn(tmp_path, waiter, EVCLOCK_CLOCK=f"{url}?name=waiter")

    async def main() -> None:
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            subscribed = asyncio.Event()
            server.subscribe("subscribed", lambda _m: subscribed.set())
            await server.wait_for_participants("waiter")
            await subscribed.wait()
            await clock.sleep(0.3)
            server.publish("cmd", b"go")
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    assert json.loads(out) == ["simulation", 300_000_000, 300_000_000]


def test_a_busy_tcp_port_is_a_clear_error() -> None:
    async def main() -> None:
        async with (
            evclock.remote.serve("tcp://127.0.0.1:0", token=TOKEN) as first,
            evclock.remote.serve(first.address, token=TOKEN),
        ):
            pass

    with pytest.raises(evclock.InvalidArgumentError, match=r"cannot serve on tcp://127\.0\.0\.1:"):
        evclock.run(main())


def test_loop_factory_joins_a_clock_server(tmp_path: Path) -> None:
    url = address(tmp_path)
    server = spawn(
        tmp_path,
        """
        import sys, evclock
        async def main():
            async with evclock.remote.serve(sys.argv[1]) as server:
                await server.wait_for_participants("runner")
                await server.wait_until_left()
        evclock.run(main())
        """,
        url,
    )

    async def main() -> int:
        await asyncio.sleep(0.25)  # plain asyncio on the joined loop follows the server
        return evclock.clock().now().nanoseconds

    factory = evclock.loop_factory(clock=f"{url}?name=runner")
    with asyncio.Runner(loop_factory=factory) as runner:
        assert runner.run(main()) == 250_000_000
    assert finish(server)[0] == 0
    with pytest.raises(evclock.InvalidArgumentError, match="takes a source or a clock URL"):
        evclock.loop_factory(clock=url, source=evclock.sources.VirtualTimeSource)
    with pytest.raises(evclock.InvalidArgumentError, match="pacing"):
        evclock.loop_factory(clock=url, rtf=2.0)


def test_a_sim_driver_refuses_a_remote_clock_and_leaves_the_server_cleanly(
    tmp_path: Path,
) -> None:
    url = address(tmp_path)
    server = spawn(
        tmp_path,
        """
        import sys, evclock
        async def main():
            clock = evclock.clock()
            async with evclock.remote.serve(sys.argv[1]) as server:
                await server.wait_for_participants("driver")
                await server.wait_until_left()  # the refused one leaves cleanly
                print("left at", clock.now().nanoseconds, flush=True)
                await server.wait_for_participants("loop")
                await server.wait_until_left()
        evclock.run(main())
        """,
        url,
    )
    source = evclock.remote.RemoteClockSource(f"{url}?name=driver")
    driver = evclock.SimDriver(source=source)

    async def main() -> None:
        with pytest.raises(evclock.InvalidTypeError) as info:
            driver.start()
        message = str(info.value)
        assert "can only drive a SimEventLoop, not a SimDriver" in message
        assert "evclock.run(main(), clock=...)" in message
        assert "loop_factory(clock=...)" in message

    asyncio.run(main())

    async def joined() -> int:
        await evclock.clock().sleep(0.003)
        return evclock.clock().now().nanoseconds

    # The server went on: a SimEventLoop joins it under another name and runs on its time.
    assert evclock.run(joined(), clock=f"{url}?name=loop") == 3_000_000
    code, out, err = finish(server)
    assert code == 0, err
    assert out.splitlines() == ["left at 0"]


JUMPER = """
import json, evclock

async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    events = []
    link.subscribe(
        "news",
        lambda m: events.append(
            ["msg", m.data.decode(), m.time.nanoseconds, clock.now().nanoseconds]
        ),
    )
    clock.on_jump(
        post=lambda j: events.append(["jump", j.before.nanoseconds, j.after.nanoseconds]),
        threshold=evclock.JumpThreshold(min_forward=evclock.Duration(nanoseconds=1)),
    )
    ticks = 0
    while ticks < 6:
        try:
            await clock.sleep(0.001)
            events.append(["tick", clock.now().nanoseconds])
            ticks += 1
        except evclock.ClockJumpedError as exc:
            events.append(["woken", clock.now().nanoseconds, exc.jump.after.nanoseconds])
    print(json.dumps(events))

evclock.run(main())
"""


@pytest.mark.parametrize("to_ns", [1_000_000, 9_000_000], ids=["backward", "forward"])
def test_a_time_jump_reaches_lockstep_participants_in_order_with_data(
    tmp_path: Path, to_ns: int
) -> None:
    url = address(tmp_path)
    proc = spawn(tmp_path, JUMPER, EVCLOCK_CLOCK=f"{url}?name=p")
    seen: list[tuple[int, int]] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        clock.on_jump(
            post=lambda j: seen.append((j.before.nanoseconds, j.after.nanoseconds)),
            threshold=evclock.JumpThreshold(min_forward=evclock.Duration(nanoseconds=1)),
        )
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("p")
            await clock.sleep(0.0035)
            server.publish("news", b"before")
            await clock.sleep(0.001)  # 4.5 ms: the participant's tick at 4 ms is done
            loop.source.set_time(to_ns)  # a reset: the participant's clock jumps alike
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    assert seen == [(4_500_000, to_ns)]
    ms = 1_000_000
    assert json.loads(out) == [
        ["tick", 1 * ms],
        ["tick", 2 * ms],
        ["tick", 3 * ms],
        ["msg", "before", 3_500_000, 3_500_000],
        ["tick", 4 * ms],
        ["jump", 4_500_000, to_ns],  # the simulation's jump: its clock first reaches 4.5 ms
        ["woken", to_ns, to_ns],  # its pending sleep (due at 5 ms) raised ClockJumpedError
        ["tick", to_ns + 1 * ms],
        ["tick", to_ns + 2 * ms],  # six ticks in all: it leaves, the server ends
    ]


SNAPSHOT_PARTICIPANT = """
import json, evclock
async def main():
    clock = evclock.clock()
    events = []
    clock.on_jump(
        post=lambda j: events.append(["jump", j.before.nanoseconds, j.after.nanoseconds]),
        threshold=evclock.JumpThreshold(min_forward=evclock.Duration(nanoseconds=1)),
    )
    ticks = 0
    while ticks < 8:
        try:
            await clock.sleep(0.25)  # 60 physics steps at 240 Hz
            events.append(["tick", clock.now().nanoseconds])
            ticks += 1
        except evclock.ClockJumpedError:
            events.append(["woken", clock.now().nanoseconds])
    print(json.dumps(events))
evclock.run(main())
"""


@pytest.mark.pybullet
def test_a_restored_pybullet_snapshot_reaches_every_participant_as_one_jump(
    tmp_path: Path,
) -> None:
    # The simulation steps PyBullet, snapshots at 0.6 s and restores the snapshot at 1.1 s:
    # its clock jumps back 1.1 s -> 0.6 s. A lockstep participant and a follower see that
    # same jump; the lockstep one, whose 0.25 s sleeps are on physics steps, keeps exactly
    # the timeline an in-process task would (its sleep due at 1.25 s raises ClockJumpedError
    # at 0.6 s, then it ticks every 0.25 s from there).
    from evclock.sources import PyBulletTimeSource

    url = address(tmp_path)
    lockstep = spawn(tmp_path, SNAPSHOT_PARTICIPANT, EVCLOCK_CLOCK=f"{url}?name=lock")
    follower = spawn(tmp_path, SNAPSHOT_PARTICIPANT, EVCLOCK_CLOCK=f"{url}?name=fol&mode=follow")
    source = PyBulletTimeSource.connect()
    jumps: list[tuple[int, int]] = []

    async def main() -> None:
        clock = evclock.clock()
        clock.on_jump(post=lambda j: jumps.append((j.before.nanoseconds, j.after.nanoseconds)))
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("lock", "fol")
            await clock.sleep(0.6)
            snapshot = source.save_state()
            await clock.sleep(0.5)
            source.restore_state(snapshot)
            await server.wait_until_left()

    evclock.run(main(), source=source)
    ms = 1_000_000
    assert jumps == [(1100 * ms, 600 * ms)]
    code, out, err = finish(lockstep)
    assert code == 0, err
    assert json.loads(out) == [
        ["tick", 250 * ms],
        ["tick", 500 * ms],
        ["tick", 750 * ms],
        ["tick", 1000 * ms],
        ["jump", 1100 * ms, 600 * ms],
        ["woken", 600 * ms],
        ["tick", 850 * ms],
        ["tick", 1100 * ms],
        ["tick", 1350 * ms],
        ["tick", 1600 * ms],
    ]
    code, out, err = finish(follower)
    assert code == 0, err
    # A follower may fire a deadline at a later physics step than due (it never holds the
    # simulation), but it hears the same jump, in order, and wakes at its target.
    events = json.loads(out)
    kinds = [event[0] for event in events]
    assert kinds.count("jump") == 1
    at = kinds.index("jump")
    assert events[at] == ["jump", 1100 * ms, 600 * ms]
    assert all(kind == "tick" for kind in kinds[:at])
    assert events[at + 1] == ["woken", 600 * ms]
    assert all(t <= 1100 * ms for _, t in events[:at])


def test_a_jump_while_a_participant_works_supersedes_its_round(tmp_path: Path) -> None:
    # The simulation publishes (granting the subscribed participant 3.5 ms) and jumps back
    # in the same step: the participant handles the data, then jumps; a DONE it sent for
    # 3.5 ms before reading the JUMP is about a time that no longer exists and is ignored.
    url = address(tmp_path)
    proc = spawn(tmp_path, JUMPER, EVCLOCK_CLOCK=f"{url}?name=p")

    async def main() -> None:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("p")
            await clock.sleep(0.0035)
            server.publish("news", b"before")
            loop.source.set_time(0)
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    ms = 1_000_000
    # Whether or not it had applied the grant to 3.5 ms when it read the JUMP, it handles
    # the data at 3.5 ms and jumps from there, as the simulation did: the same events.
    assert json.loads(out) == [
        ["tick", ms],
        ["tick", 2 * ms],
        ["tick", 3 * ms],
        ["msg", "before", 3_500_000, 3_500_000],
        ["jump", 3_500_000, 0],
        ["woken", 0, 0],
        ["tick", ms],
        ["tick", 2 * ms],
        ["tick", 3 * ms],
    ]


def test_a_time_jump_reaches_a_follower(tmp_path: Path) -> None:
    # The follower tells the simulation when its own clock has reached 0.5 s, so it is at
    # the simulation's time when the jump comes (a follower behind it: the next test).
    url = address(tmp_path)
    proc = spawn(
        tmp_path,
        """
        import asyncio, json, evclock
        async def main():
            clock = evclock.clock()
            link = evclock.remote.participant()
            await clock.sleep(0.5)
            sleeping = asyncio.ensure_future(clock.sleep(3600))
            await asyncio.sleep(0)  # asleep before it says so (the jump may come with the reply)
            link.call("ready")  # a follower cannot publish; it may ask
            try:
                await sleeping
            except evclock.ClockJumpedError as exc:
                print(json.dumps([clock.now().nanoseconds, exc.jump.before.nanoseconds,
                                  exc.jump.after.nanoseconds]))
        evclock.run(main())
        """,
        EVCLOCK_CLOCK=f"{url}?name=f&mode=follow",
    )

    async def main() -> None:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            ready = asyncio.Event()
            server.provide("ready", lambda _: ready.set() or b"")
            await server.wait_for_participants("f")
            await clock.sleep(0.5)
            await ready.wait()
            loop.source.set_time(100_000_000)
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    woken_at, before, after = json.loads(out)
    assert woken_at == after == 100_000_000
    assert before == 500_000_000


class ScriptedServer:
    """A clock server that follows a script, byte for byte, on a real Unix socket: it makes
    certain orders of frames (several in one write) that a real server makes only by chance.
    Every read is bounded (10 s)."""

    def __init__(self, path: Path, script: Callable[[ScriptedServer], None]) -> None:
        self.received: list[tuple[int, bytes]] = []
        self._reader = proto.Reader()
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(path))
        self._listener.listen(1)
        self._listener.settimeout(10)
        self._script = script
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        conn, _ = self._listener.accept()
        with conn:
            conn.settimeout(10)
            self.conn = conn
            self.expect(proto.HELLO)
            self.send(proto.challenge(proto.new_nonce(), b""))  # a server without a token
            self.expect(proto.PROOF)
            self._script(self)
            # Parked in a read without timeout, as a server's reader is (a thread in a timed
            # read would hold the participant's sim time); finish() bounds the whole wait.
            conn.settimeout(None)
            while data := conn.recv(4096):  # until the participant leaves (BYE, EOF)
                self.received.extend(self._reader.feed(data))

    def expect(self, kind: int) -> bytes:
        """Read until a frame of ``kind`` arrives; its payload."""
        while True:
            for got, payload in self.received:
                if got == kind:
                    return payload
            data = self.conn.recv(4096)
            assert data, f"the participant closed before sending frame kind {kind}"
            self.received.extend(self._reader.feed(data))

    def send(self, data: bytes) -> None:
        self.conn.sendall(data)

    def finish(self) -> list[int]:
        """Wait for the participant to leave; the kinds of every frame it sent."""
        self._thread.join(15)
        self._listener.close()
        assert not self._thread.is_alive()
        return [kind for kind, _ in self.received]


def test_frames_that_come_with_the_welcome_are_not_lost(tmp_path: Path) -> None:
    # A server that jumps at once after a join sends WELCOME and JUMP together; the
    # participant's join reads both in one recv. The JUMP (0.5 s -> 0.1 s, the follower
    # still at 0) must be applied.
    path = tmp_path / "scripted.sock"
    server = ScriptedServer(
        path,
        lambda s: s.send(
            proto.welcome(0, proto.MAX_FRAME, b"{}") + proto.jump(1, 500_000_000, 100_000_000)
        ),
    )
    seen: list[int] = []

    async def main() -> None:
        try:
            await evclock.clock().sleep(3600)
        except evclock.ClockJumpedError as exc:
            seen[:] = [exc.jump.before.nanoseconds, exc.jump.after.nanoseconds]
            seen.append(evclock.clock().now().nanoseconds)

    try:
        evclock.run(main(), clock=f"unix://{path}?name=f&mode=follow&timeout=10")
    finally:
        kinds = server.finish()
    assert seen == [500_000_000, 100_000_000, 100_000_000]
    assert kinds[-1] == proto.BYE
    acked = [proto.parse_jumped(p) for kind, p in server.received if kind == proto.JUMPED]
    assert acked == [1]  # it acknowledged the jump


def test_a_lockstep_participant_does_its_granted_round_before_the_jump_after_it(
    tmp_path: Path,
) -> None:
    # The simulation grants 1 ms, and a task of its own jumps back to 0 at 1 ms: GRANT and
    # JUMP arrive in one read, before the participant applied the grant. It works at 1 ms
    # first (its tick there), then jumps from 1 ms, as the simulation did; the round at
    # 1 ms is superseded (no DONE for it), its sleep due at 2 ms raises ClockJumpedError.
    ms = 1_000_000

    def script(s: ScriptedServer) -> None:
        s.send(proto.welcome(0, proto.MAX_FRAME, b"{}"))
        assert proto.parse_done(s.expect(proto.DONE)) == (0, ms)  # at work at 0, due at 1 ms
        s.send(proto.grant(ms) + proto.jump(1, ms, 0))

    path = tmp_path / "scripted.sock"
    server = ScriptedServer(path, script)
    events: list[list[int | str]] = []

    async def main() -> None:
        clock = evclock.clock()
        clock.on_jump(
            post=lambda j: events.append(["jump", j.before.nanoseconds, j.after.nanoseconds]),
            threshold=evclock.JumpThreshold(min_forward=evclock.Duration(nanoseconds=1)),
        )
        await clock.sleep(0.001)
        events.append(["tick", clock.now().nanoseconds])
        try:
            await clock.sleep(0.001)
        except evclock.ClockJumpedError:
            events.append(["woken", clock.now().nanoseconds])

    try:
        evclock.run(main(), clock=f"unix://{path}?name=p&timeout=10")
    finally:
        kinds = server.finish()
    assert events == [["tick", ms], ["jump", ms, 0], ["woken", 0]]
    assert kinds[-1] == proto.BYE
    acked = [proto.parse_jumped(p) for kind, p in server.received if kind == proto.JUMPED]
    assert acked == [1]
    dones = [proto.parse_done(p) for kind, p in server.received if kind == proto.DONE]
    assert all(t == 0 for t, _ in dones)  # none for the superseded round at 1 ms


@pytest.mark.parametrize("lag", [0.0, 0.3], ids=["prompt", "lagging"])
def test_a_follower_behind_the_simulation_reaches_the_jump_time_then_jumps_back(
    tmp_path: Path, lag: float
) -> None:
    # The simulation reaches 0.5 s and jumps back to 0.1 s without waiting for the follower
    # (followers never hold it), which may still be at 0 when it reads the JUMP (the more
    # so when it is busy for `lag` wall seconds first): its clock first moves to 0.5 s, its
    # deadline at 0.3 s firing on the way, and then jumps back, so its long sleep raises
    # ClockJumpedError, as in-process. Same outcome whatever the timing.
    url = address(tmp_path)
    proc = spawn(
        tmp_path,
        f"""
        import json, time, evclock
        async def main():
            time.sleep({lag})  # busy: the simulation runs on
            clock = evclock.clock()
            seen = []
            clock.on_jump(
                post=lambda j: seen.append(["jump", j.before.nanoseconds, j.after.nanoseconds]),
                threshold=evclock.JumpThreshold(min_forward=evclock.Duration(nanoseconds=1)),
            )
            await clock.sleep(0.3)
            seen.append(["woken", clock.now().nanoseconds])
            try:
                await clock.sleep(3600)
            except evclock.ClockJumpedError as exc:
                seen.append(["jumped", clock.now().nanoseconds, exc.jump.before.nanoseconds,
                             exc.jump.after.nanoseconds])
            print(json.dumps(seen))
        evclock.run(main())
        """,
        EVCLOCK_CLOCK=f"{url}?name=f&mode=follow",
    )

    async def main() -> None:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("f")
            await clock.sleep(0.5)
            loop.source.set_time(100_000_000)
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    ms = 1_000_000
    assert json.loads(out) == [
        ["woken", 300 * ms],
        ["jump", 500 * ms, 100 * ms],
        ["jumped", 100 * ms, 500 * ms, 100 * ms],
    ]
