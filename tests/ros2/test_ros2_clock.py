"""Publishing and following ROS 2 /clock through real Zenoh sessions on a Unix socket.

The other side of each exchange is a plain Zenoh session of the test (no evclock code), so
what crosses the wire is what is asserted. Every wait is bounded by a wall deadline.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from _ros2_helpers import jumps_on_reset, repeating

import evclock
from evclock import (
    ClockLostError,
    ClockMismatchError,
    InvalidArgumentError,
    InvalidTypeError,
    LoopClosedError,
    Time,
)
from evclock.outside._threads import mark_internal
from evclock.ros2 import (
    CLOCK_TYPE_HASH,
    Ros2ClockPublisher,
    Ros2ClockSource,
    Ros2MessageError,
    encode_clock,
)

# The ros2 extra: where it is missing, every test that opens a session skips (``endpoint``).
with contextlib.suppress(ModuleNotFoundError):
    import zenoh
    from zenoh.ext import Int64, z_deserialize

WAIT = 10.0  # wall seconds: a guard against hangs, never a performance assertion
KEY = f"0/clock/rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}"
S = 1_000_000_000


@pytest.fixture(autouse=True)
def _zenoh_middleware(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests speak Zenoh: chosen as a ROS node chooses it (DDS is the default)."""
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_zenoh_cpp")


@pytest.fixture
def endpoint() -> Iterator[str]:
    pytest.importorskip("zenoh", reason="needs evclock[ros2] (eclipse-zenoh)")
    pytest.importorskip("xxhash", reason="needs evclock[ros2] (xxhash)")
    with tempfile.TemporaryDirectory(prefix="evros2") as folder:  # short: sun_path limit
        yield f"unixsock-stream/{folder}/zenoh.sock"


def raw_session(*, connect: list[str], listen: list[str]) -> Any:
    config = {
        "mode": "peer",
        "connect": {"endpoints": connect},
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}},
    }
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def next_sample(subscriber: Any, timeout: float) -> Any:
    """The next sample of a channel subscriber within ``timeout`` wall seconds, or None."""
    deadline = time.monotonic() + timeout
    while True:
        sample = subscriber.handler.try_recv()
        if sample is not None or time.monotonic() >= deadline:
            return sample
        time.sleep(0.001)


class Received:
    """A raw subscriber of the test, read through a channel: a Python callback would run on
    a non-daemon Zenoh thread, which the loop would count as busy work holding sim time."""

    def __init__(self, session: Any, key: str) -> None:
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))

    def poll(self, timeout: float) -> tuple[str, bytes, bytes | None] | None:
        sample = next_sample(self._sub, timeout)
        if sample is None:
            return None
        attachment = sample.attachment
        return (
            str(sample.key_expr),
            sample.payload.to_bytes(),
            None if attachment is None else attachment.to_bytes(),
        )

    def next(self) -> tuple[str, bytes, bytes | None]:
        sample = self.poll(WAIT)
        assert sample is not None, "no sample arrived"
        return sample

    def empty(self) -> bool:
        return self.poll(0) is None

    def routed_after(self, send: Callable[[], None]) -> None:
        """Send until one sample arrives (the subscription reached the sender), then drain."""
        deadline = time.monotonic() + WAIT
        while True:
            send()
            if self.poll(0.02) is not None:
                break
            assert time.monotonic() < deadline, "the subscription never reached the sender"
        while self.poll(0.05) is not None:
            pass

    def close(self) -> None:
        self._sub.undeclare()


def liveliness_keys(session: Any) -> list[str]:
    replies = session.liveliness().get("@ros2_lv/0/**", timeout=WAIT)
    return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)


class Withdrawals:
    """The liveliness tokens a session sees withdrawn.

    A withdrawal reaches the other sessions of the graph a moment after the withdrawing
    session's ``close()`` returns (Zenoh routes it asynchronously): a test waits for the
    DELETE samples themselves, with a bound, instead of querying at once."""

    def __init__(self, session: Any) -> None:
        self._sub = session.liveliness().declare_subscriber(
            "@ros2_lv/0/**", zenoh.handlers.FifoChannel(256)
        )

    def wait_for(self, keys: list[str]) -> None:
        pending = list(keys)
        deadline = time.monotonic() + WAIT
        try:
            while pending:
                sample = next_sample(self._sub, deadline - time.monotonic())
                assert sample is not None, f"tokens never withdrawn: {pending}"
                if sample.kind == zenoh.SampleKind.DELETE and str(sample.key_expr) in pending:
                    pending.remove(str(sample.key_expr))
        finally:
            self._sub.undeclare()


# ------------------------------------------------------------------------------- publisher


def test_publisher_sends_rmw_zenoh_samples_and_tokens(endpoint: str) -> None:
    stamps = iter(range(1_700_000_000_000_000_000, 1_800_000_000_000_000_000, 1000))
    pub = Ros2ClockPublisher(connect=[], listen=[endpoint], wall_clock_ns=lambda: next(stamps))
    peer = raw_session(connect=[endpoint], listen=[])
    try:
        with pub:
            received = Received(peer, "0/clock/**")
            received.routed_after(lambda: pub.publish(0))
            warmup = pub.sequence_number
            pub.publish(Time(1, 500))
            pub.publish(2 * S + 7)
            for expected_ns in (1 * S + 500, 2 * S + 7):
                key, payload, attachment = received.next()
                assert key == KEY == pub.key_expr
                sec, nanosec = divmod(expected_ns, S)
                cdr_header = b"\x00\x01\x00\x00"
                assert payload == cdr_header + sec.to_bytes(4, "little") + nanosec.to_bytes(
                    4, "little"
                )
                assert attachment is not None
                seq, stamp, gid = z_deserialize(
                    tuple[Int64, Int64, bytes], zenoh.ZBytes(attachment)
                )
                warmup += 1
                assert int(seq) == warmup
                assert 1_700_000_000_000_000_000 <= int(stamp) < 1_800_000_000_000_000_000
                assert gid == pub.gid
            tokens = liveliness_keys(peer)
            assert tokens == sorted(pub.liveliness_tokens)
            assert any("/NN/%/%/evclock_clock" in t for t in tokens)
            assert any(
                t.endswith(
                    f"/MP/%/%/evclock_clock/%clock/rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}/2:2:,1:,:,:,,"
                )
                for t in tokens
            )
            received.close()
            withdrawals = Withdrawals(peer)
        withdrawals.wait_for(tokens)  # closing withdrew the node and its publisher
        assert liveliness_keys(peer) == []
    finally:
        pub.close()
        peer.close()


@pytest.mark.pybullet
def test_publisher_follows_pybullet_steps_with_decimation(endpoint: str) -> None:
    source = evclock.sources.PyBulletTimeSource.connect()
    with Ros2ClockPublisher(connect=[], listen=[endpoint]) as pub:
        peer = raw_session(connect=[endpoint], listen=[])
        try:
            received = Received(peer, KEY)
            received.routed_after(lambda: pub.publish(0))
            hook = pub.attach(source, decimation=3)

            async def main() -> None:
                await source.sleep_steps(10)

            evclock.run(main(), source=source)
            hook.remove()
            times = [received.next() for _ in range(4)]
            from evclock.ros2 import decode_clock

            assert [decode_clock(p) for _, p, _ in times] == [
                0,
                3 * 12_500_000 // 3,
                6 * 12_500_000 // 3,
                9 * 12_500_000 // 3,
            ]
            assert received.empty()
            received.close()
        finally:
            peer.close()


@pytest.mark.pybullet
def test_publisher_rejects_bad_input(endpoint: str) -> None:
    pub = Ros2ClockPublisher(connect=[], listen=[endpoint])
    with pytest.raises(ClockMismatchError, match="/clock carries sim time, got a steady time"):
        pub.publish(Time(1, clock_type=evclock.STEADY))
    with pytest.raises(InvalidTypeError, match="publish\\(\\) takes a sim Time or int"):
        pub.publish(True)
    with pytest.raises(InvalidTypeError, match="attach\\(\\) takes a stepping source"):
        pub.attach(evclock.sources.VirtualTimeSource())  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="decimation must be >= 1"):
        pub.attach(evclock.sources.PyBulletTimeSource.connect(), decimation=0)
    pub.close()
    with pytest.raises(LoopClosedError, match="this Ros2ClockPublisher is closed"):
        pub.publish(0)
    with pytest.raises(InvalidArgumentError, match="is not a Zenoh endpoint"):
        Ros2ClockPublisher(connect=["127.0.0.1:7447"])


# -------------------------------------------------------------------------------- follower


class Feed:
    """The outside clock: a raw Zenoh publisher putting Clock samples on ``key``."""

    def __init__(self, session: Any, key: str = KEY) -> None:
        self._pub = session.declare_publisher(key)

    def __call__(self, time_ns: int) -> None:
        self._pub.put(encode_clock(time_ns))


def start_follower(endpoint: str, feed: Feed, first_ns: int, **options: Any) -> Ros2ClockSource:
    """Open a follower while the outside clock repeats ``first_ns`` (the follower waits for
    its first message during construction)."""
    options.setdefault("startup_timeout", WAIT)
    with repeating(feed, first_ns, WAIT):
        return Ros2ClockSource(connect=[endpoint], listen=[], **options)


@pytest.fixture
def outside(endpoint: str) -> Iterator[Any]:
    session = raw_session(connect=[], listen=[endpoint])
    yield session
    session.close()


def test_follower_timers_sleeps_and_timeouts_follow_clock(endpoint: str, outside: Any) -> None:
    feed = Feed(outside)
    source = start_follower(endpoint, feed, 1 * S)
    assert source.now_ns == 1 * S  # the program starts at the publisher's time

    async def main() -> list[int]:
        loop = asyncio.get_running_loop()
        clk = evclock.clock()
        assert clk.now() == Time(1)
        fired: list[int] = []
        timer = clk.timer(0.25, lambda: fired.append(clk.now().nanoseconds))
        feed(1_600_000_000)  # /clock moves on: local deadlines fire in turn, on its time
        await clk.sleep_until(Time(0, 1_600_000_000))
        assert fired == [1_250_000_000, 1_500_000_000]
        timer.cancel()

        feed(2 * S)
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.3):  # an asyncio timeout on the followed time
                await asyncio.Event().wait()
        assert clk.now() == Time(0, 1_900_000_000)

        # A sleep past the newest /clock waits; time follows /clock meanwhile, never past it.
        sleeper = asyncio.ensure_future(clk.sleep_until(Time(0, 2_900_000_000)))
        seen = asyncio.Event()

        def watch() -> None:  # another thread: once the loop has read 2.5 s, poke it
            deadline = time.monotonic() + WAIT
            while source.latest != Time(0, 2_500_000_000) and time.monotonic() < deadline:
                time.sleep(0.001)
            loop.call_soon_threadsafe(seen.set)

        feed(2_500_000_000)
        watcher = threading.Thread(target=watch, daemon=True)
        # It polls with a timeout, which holds sim time (docs/guides/outside.md);
        # it only observes the source: declare it one of the test's helpers.
        mark_internal(watcher)
        watcher.start()
        await seen.wait()
        watcher.join(WAIT)
        assert clk.now() == Time(0, 2_500_000_000)
        assert not sleeper.done()
        feed(3 * S)
        await sleeper
        assert clk.now() == Time(0, 2_900_000_000)  # woken at its deadline, not at 3 s
        return fired

    assert evclock.run(main(), source=source) == [1_250_000_000, 1_500_000_000]
    assert source.received >= 5


def test_follower_declares_itself_in_the_ros_graph(endpoint: str, outside: Any) -> None:
    source = start_follower(endpoint, Feed(outside), 0)
    try:
        tokens = liveliness_keys(outside)
        assert len(tokens) == 2
        assert any(t.endswith("/NN/%/%/evclock_follower") for t in tokens)
        assert any(
            f"/MS/%/%/evclock_follower/%clock/rosgraph_msgs::msg::dds_::Clock_/{CLOCK_TYPE_HASH}"
            in t
            for t in tokens
        )
        withdrawals = Withdrawals(outside)
    finally:
        source.close()
    withdrawals.wait_for(tokens)  # closing withdrew the node and its subscription
    assert liveliness_keys(outside) == []


def test_follower_accepts_humble_keys(endpoint: str, outside: Any) -> None:
    humble = Feed(outside, "0/clock/rosgraph_msgs::msg::dds_::Clock_/TypeHashNotSupported")
    source = start_follower(endpoint, humble, 4 * S)

    async def main() -> Time:
        humble(5 * S)
        await asyncio.sleep(1)
        return evclock.clock().now()

    assert evclock.run(main(), source=source) == Time(5)


def test_backward_clock_is_a_jump(endpoint: str, outside: Any) -> None:
    feed = Feed(outside)
    source = start_follower(endpoint, feed, 10 * S)
    (jump,) = evclock.run(jumps_on_reset(feed), source=source)
    assert (jump.before, jump.after) == (Time(10), Time(3))


def test_silent_publisher_is_reported(endpoint: str, outside: Any) -> None:
    source = start_follower(endpoint, Feed(outside), 1 * S, silence_timeout=0.3)

    async def main() -> None:
        await evclock.clock().sleep(1)

    with pytest.raises(
        ClockLostError, match=r"no /clock message for \d+\.\d s of wall time"
    ) as info:
        evclock.run(main(), source=source)
    assert "raise silence_timeout (now 0.3 s) or pass None" in str(info.value)


def test_no_clock_at_startup_waits_until_the_startup_timeout(endpoint: str) -> None:
    with pytest.raises(
        ClockLostError, match=r"no /clock message arrived within startup_timeout=0.3 s"
    ):
        Ros2ClockSource(connect=[endpoint], listen=[], startup_timeout=0.3)


def test_unknown_type_hash_ends_the_run(endpoint: str, outside: Any) -> None:
    source = start_follower(endpoint, Feed(outside), 1 * S)
    other = Feed(outside, "0/clock/rosgraph_msgs::msg::dds_::Clock_/RIHS01_00")

    async def main() -> None:
        other(2 * S)
        await evclock.clock().sleep(1)

    with pytest.raises(Ros2MessageError, match="type hash 'RIHS01_00'"):
        evclock.run(main(), source=source)


def test_follower_rejects_bad_options() -> None:
    with pytest.raises(InvalidArgumentError, match="silence_timeout must be a positive number"):
        Ros2ClockSource(silence_timeout=0)
    with pytest.raises(InvalidTypeError, match="startup_timeout must be wall seconds or None"):
        Ros2ClockSource(startup_timeout="5")  # type: ignore[arg-type]


def test_clock_url_in_the_environment_selects_the_follower(
    endpoint: str, outside: Any, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    feed = Feed(outside)
    monkeypatch.setenv(
        "EVCLOCK_CLOCK", f"ros2:///clock?connect={endpoint}&listen=&startup_timeout=10"
    )

    async def main() -> Time:
        return evclock.clock().now()

    with repeating(feed, 7 * S, WAIT):
        assert evclock.run(main()) == Time(7)


def test_publisher_run_publishes_a_virtual_time_loop_at_a_rate(endpoint: str) -> None:
    with Ros2ClockPublisher(connect=[], listen=[endpoint]) as pub:
        peer = raw_session(connect=[endpoint], listen=[])
        try:
            received = Received(peer, KEY)
            received.routed_after(lambda: pub.publish(0))

            async def main() -> None:
                task = asyncio.create_task(pub.run(10))
                await asyncio.sleep(0.35)
                task.cancel()

            evclock.run(main())
            from evclock.ros2 import decode_clock

            stamps = [decode_clock(received.next()[1]) for _ in range(4)]
            assert stamps == [0, 100_000_000, 200_000_000, 300_000_000]
            assert received.empty()
            received.close()
        finally:
            peer.close()


def test_follower_honours_pacing(endpoint: str, outside: Any) -> None:
    feed = Feed(outside)
    source = start_follower(endpoint, feed, 1 * S)

    async def main() -> Time:
        feed(3 * S)
        await evclock.clock().sleep(1)  # paced at 1000x: 1 ms of wall time
        return evclock.clock().now()

    assert evclock.run(main(), source=source, rtf=1000) == Time(2)


def test_sim_driver_refuses_an_external_source(endpoint: str, outside: Any) -> None:
    source = start_follower(endpoint, Feed(outside), 0)
    try:

        async def drive() -> None:
            async with evclock.SimDriver(source):
                pass

        with pytest.raises(evclock.SimDriverError, match="which SimDriver cannot host yet"):
            asyncio.run(drive())
    finally:
        source.close()


def test_waiting_for_the_first_clock_is_reported_while_it_lasts(
    endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level("WARNING", logger="evclock.ros2"), pytest.raises(ClockLostError):
        Ros2ClockSource(connect=[endpoint], listen=[], startup_timeout=0.5, silence_timeout=0.2)
    warnings = [r.getMessage() for r in caplog.records if r.name == "evclock.ros2"]
    assert warnings[:2] == [
        "still waiting for the first /clock message after 0.2 s (ROS 2 /clock (domain 0) "
        f"over Zenoh via {endpoint})",
        "still waiting for the first /clock message after 0.4 s (ROS 2 /clock (domain 0) "
        f"over Zenoh via {endpoint})",
    ]


def test_missing_zenoh_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", None)  # as if eclipse-zenoh were not installed
    with pytest.raises(evclock.MissingExtraError, match=r"module 'zenoh' is missing.*ros2\]'"):
        Ros2ClockSource()
    with pytest.raises(evclock.MissingExtraError, match=r"pip install 'evclock\[ros2\]'"):
        Ros2ClockPublisher()


def test_after_a_backward_jump_shifted_deadlines_still_fire_exactly(
    endpoint: str, outside: Any
) -> None:
    feed = Feed(outside)
    source = start_follower(endpoint, feed, 10 * S)

    async def main() -> list[Time]:
        clk = evclock.clock()
        fired: list[Time] = []
        asyncio.get_running_loop().call_later(0.5, lambda: fired.append(clk.now()))
        feed(3 * S)  # a reset, then the simulator runs on at once
        feed(4 * S)
        await asyncio.sleep(0.6)  # asyncio timers keep their remaining delay across a jump
        assert clk.now() == Time(0, 3_600_000_000)
        return fired

    assert evclock.run(main(), source=source) == [Time(0, 3_500_000_000)]
