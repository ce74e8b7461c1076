"""Tests of stamped data and the synchronisers' front end, on evclock clocks."""

from __future__ import annotations

import asyncio
import logging
import re
from dataclasses import dataclass
from types import SimpleNamespace

import pytest

import evclock
from evclock import (
    SIM,
    STEADY,
    ClockMismatchError,
    Duration,
    InvalidArgumentError,
    InvalidTypeError,
    Time,
    TimeMsg,
    WallClock,
)
from evclock.data import (
    ApproximateTimeSynchronizer,
    StampDiagnostics,
    Stamped,
    TimeSynchronizer,
    stamp_of,
)


@dataclass
class Header:
    stamp: TimeMsg
    frame_id: str = ""


@dataclass
class RosMsg:
    """A ROS-style message: the stamp in header.stamp as sec/nanosec."""

    header: Header
    data: str


def ros(seconds: float, data: str = "") -> RosMsg:
    return RosMsg(Header(Time(seconds).to_msg()), data)


# -- stamp_of --------------------------------------------------------------------------------


def test_stamp_of_reads_ros_headers_stamp_attributes_and_keys() -> None:
    assert stamp_of(ros(10.02), SIM) == Time(10.02)
    assert stamp_of(ros(10.02), STEADY) == Time(10.02, clock_type=STEADY)  # read in the domain
    assert stamp_of(Stamped(Time(3), "x"), SIM) == Time(3)
    assert stamp_of(SimpleNamespace(stamp=TimeMsg(1, 5)), SIM) == Time(0, 1_000_000_005)
    header_time = SimpleNamespace(header=SimpleNamespace(stamp=Time(2)))
    assert stamp_of(header_time, SIM) == Time(2)
    assert stamp_of({"t": 4.5}, SIM, key=lambda m: Time(m["t"])) == Time(4.5)
    assert stamp_of((7, "x"), SIM, key=lambda m: TimeMsg(m[0], 0)) == Time(7)


def test_stamp_of_rejects_a_stamp_of_another_clock_domain() -> None:
    wall = Time(1_700_000_000, clock_type=evclock.SYSTEM)
    with pytest.raises(
        ClockMismatchError,
        match=r"message\.stamp is a system time but this "
        r"consumer runs on sim time: sim and wall stamps are mixed up",
    ):
        stamp_of(Stamped(wall, 1), SIM)
    with pytest.raises(ClockMismatchError, match=r"header\.stamp is a sim time"):
        stamp_of(SimpleNamespace(header=SimpleNamespace(stamp=Time(1))), STEADY)


def test_stamp_of_explains_what_it_cannot_read() -> None:
    with pytest.raises(
        InvalidTypeError,
        match=re.escape(
            "cannot read a time stamp from a str: give it a 'stamp' (evclock.Time), a ROS "
            "'header.stamp' (sec/nanosec), wrap it in evclock.data.Stamped(stamp, value), or pass "
            "key=lambda msg: <its Time>"
        ),
    ):
        stamp_of("hello", SIM)
    with pytest.raises(
        InvalidTypeError, match=r"message\.stamp must be an evclock\.Time or have sec and nanosec"
    ):
        stamp_of(SimpleNamespace(stamp=1.5), SIM)
    with pytest.raises(
        InvalidTypeError, match=r"Stamped\.stamp must be an evclock\.Time, got float"
    ):
        Stamped(1.5, "x")  # type: ignore[arg-type]


# -- synchronisers on the simulation loop ------------------------------------------------------


def test_approximate_sync_groups_camera_imu_lidar_with_async_for() -> None:
    async def main() -> list[tuple[float, ...]]:
        sync = ApproximateTimeSynchronizer(["camera", "imu", "lidar"], queue_size=20)
        clock = evclock.clock()

        async def publish(stream: str, period: float, offset: float, count: int) -> None:
            for k in range(count):
                await clock.sleep_until(Time(offset + k * period))
                sync.add(stream, ros(offset + k * period, stream))

        producers = [
            asyncio.create_task(publish("camera", 0.1, 10.00, 5)),
            asyncio.create_task(publish("imu", 0.01, 10.00, 50)),
            asyncio.create_task(publish("lidar", 0.1, 10.05, 5)),
        ]
        groups = []

        async def consume() -> None:
            async for camera, imu, lidar in sync:
                groups.append(
                    tuple(
                        m.header.stamp.sec + m.header.stamp.nanosec / 1e9
                        for m in (camera, imu, lidar)
                    )
                )

        consumer = asyncio.create_task(consume())
        await asyncio.gather(*producers)
        sync.close()
        await consumer
        return groups

    groups = evclock.run(main())
    # Each camera frame (10.0, 10.1, ...) pairs with the lidar scan 50 ms later and the IMU
    # sample in between that makes the spread smallest: spread 50 ms each.
    assert len(groups) == 4
    for camera, imu, lidar in groups:
        assert lidar - camera == pytest.approx(0.05)
        assert camera <= imu <= lidar


def test_callback_mode_and_exact_sync() -> None:
    received = []
    sync = TimeSynchronizer(
        2, clock=WallClock(STEADY), callback=lambda a, b: received.append((a, b))
    )
    a1, b1 = Stamped(Time(1, clock_type=STEADY), "a"), Stamped(Time(1, clock_type=STEADY), "b")
    sync.add(0, a1)
    assert received == []
    sync.input(1)(b1)
    assert received == [(a1, b1)]
    assert sync.stats()["groups"] == 1
    with pytest.raises(InvalidArgumentError, match="delivers its groups to its callback"):
        sync.__aiter__()


def test_a_wall_stamp_on_sim_time_raises() -> None:
    async def main() -> None:
        sync = ApproximateTimeSynchronizer(2)
        sync.add(0, Stamped(evclock.clock().now(), 1))
        sync.add(1, Stamped(Time(1_700_000_000, clock_type=evclock.SYSTEM), 2))

    with pytest.raises(ClockMismatchError, match="system time but this consumer runs on sim"):
        evclock.run(main())


def test_slop_mode_behaves_like_ros_python() -> None:
    out = []
    sync = ApproximateTimeSynchronizer(
        2, queue_size=5, slop=0.1, clock=WallClock(STEADY), callback=lambda a, b: out.append((a, b))
    )
    assert sync.slop == Duration(0.1)
    t = lambda s: Stamped(Time(s, clock_type=STEADY), s)  # noqa: E731
    sync.add(0, t(1.0))
    sync.add(1, t(1.2))  # 0.2 apart: beyond the slop
    assert out == []
    sync.add(1, t(1.05))
    assert [(a.value, b.value) for a, b in out] == [(1.0, 1.05)]


def test_consumer_falling_behind_drops_oldest_groups_and_warns() -> None:
    warnings: list[evclock.data.StampWarning] = []

    async def main() -> None:
        diag = StampDiagnostics("fusion", max_queue=3, on_warning=warnings.append)
        sync = TimeSynchronizer(["a", "b"], max_pending=5, diagnostics=diag)
        for k in range(8):
            await asyncio.sleep(0.1)
            now = evclock.clock().now()
            sync.add("a", Stamped(now, k))
            sync.add("b", Stamped(now, k))
        assert sync.pending_groups == 5
        assert sync.groups_dropped == 3
        first = await sync.__anext__()
        assert first[0].value == 3  # the three oldest were dropped
        assert diag.as_dict()["queues"]["TimeSynchronizer"] == {
            "depth": 4,
            "max_depth": 5,
            "behind": 6,  # observations above max_queue: depths 4, 5, 5, 5, 5, then 4
        }

    evclock.run(main())
    assert [w.kind for w in warnings] == ["behind"]
    assert warnings[0].message == (
        "consumer 'TimeSynchronizer' is falling behind: 4 items queued (max_queue 3); it "
        "processes more slowly than data arrives"
    )


def test_out_of_order_messages_are_counted_and_logged_once(caplog) -> None:
    sync = ApproximateTimeSynchronizer(2, clock=WallClock(STEADY), callback=lambda *m: None)
    caplog.set_level(logging.WARNING, logger="evclock.sync")
    for s in (2.0, 1.0, 0.5):
        sync.add(0, Stamped(Time(s, clock_type=STEADY), s))
    assert sync.stats()["streams"]["0"]["out_of_order"] == 2
    assert [r.getMessage() for r in caplog.records] == [
        "ApproximateTimeSynchronizer: a message on stream '0' arrived out of stamp order; the "
        "match may be suboptimal (counted in stats())"
    ]


def test_close_ends_iteration_after_the_queued_groups() -> None:
    async def main() -> list[int]:
        sync = TimeSynchronizer(2)
        now = evclock.clock().now()
        sync.add(0, Stamped(now, 1))
        sync.add(1, Stamped(now, 2))
        sync.close()
        with pytest.raises(InvalidArgumentError, match="is closed; no more messages"):
            sync.add(0, Stamped(now, 3))
        return [a.value async for a, _ in sync]

    assert evclock.run(main()) == [1]


def test_two_consumers_on_one_synchroniser_is_an_error() -> None:
    async def main() -> None:
        sync = TimeSynchronizer(2)
        first = asyncio.create_task(sync.__anext__())
        await asyncio.sleep(0)
        with pytest.raises(InvalidArgumentError, match="already being iterated by another task"):
            await sync.__anext__()
        sync.close()
        with pytest.raises(StopAsyncIteration):
            await first

    evclock.run(main())


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"streams": 1}, InvalidArgumentError, "needs at least 2 streams, got 1"),
        ({"streams": ["a", "a"]}, InvalidArgumentError, "stream names must be distinct"),
        ({"streams": "ab"}, InvalidTypeError, "streams must be a number of streams or a seq"),
        ({"streams": 2, "queue_size": 0}, InvalidArgumentError, "queue_size must be a positive"),
        ({"streams": 2, "max_pending": 0}, InvalidArgumentError, "max_pending must be a posit"),
        ({"streams": 2, "slop": 0}, InvalidArgumentError, "slop must be positive"),
        ({"streams": 2, "slop": -1.0}, InvalidArgumentError, "slop must not be negative"),
        ({"streams": 2, "slop": float("nan")}, InvalidArgumentError, "slop must be a number"),
        (
            {"streams": 2, "slop": 0.1, "max_interval": 1},
            InvalidArgumentError,
            "slop selects ROS Python's matching, which has no max_interval",
        ),
        ({"streams": 2, "age_penalty": -0.5}, InvalidArgumentError, "age_penalty must be a fin"),
        ({"streams": 2, "age_penalty": "1"}, InvalidTypeError, "age_penalty must be a number"),
        (
            {"streams": 2, "lower_bounds": [0.1]},
            InvalidArgumentError,
            r"lower_bounds needs one bound per stream \(2\), got 1",
        ),
        ({"streams": 2, "clock": "sim"}, InvalidTypeError, "or have a clock_type"),
        ({"streams": 2, "callback": 3}, InvalidTypeError, "callback must be callable"),
    ],
)
def test_bad_arguments_are_explained(kwargs, error, message) -> None:
    with pytest.raises(error, match=message):
        ApproximateTimeSynchronizer(**kwargs)


def test_async_callbacks_and_bad_streams_are_rejected() -> None:
    async def callback(a: object, b: object) -> None: ...

    with pytest.raises(InvalidTypeError, match="callback must be a plain function"):
        TimeSynchronizer(2, callback=callback)
    sync = TimeSynchronizer(["cam", "imu"], clock=WallClock(STEADY))
    with pytest.raises(
        InvalidArgumentError,
        match=r"unknown stream 'lidar'; this synchroniser "
        r"has \['cam', 'imu'\]",
    ):
        sync.add("lidar", Stamped(Time(0, clock_type=STEADY), 0))
    with pytest.raises(InvalidArgumentError, match=r"stream index 2 out of range"):
        sync.input(2)


def test_a_stream_that_never_matches_keeps_memory_bounded_and_counts_drops() -> None:
    for sync in (
        ApproximateTimeSynchronizer(["camera", "imu"], queue_size=8, clock=WallClock(STEADY)),
        ApproximateTimeSynchronizer(
            ["camera", "imu"], queue_size=8, slop=0.01, clock=WallClock(STEADY)
        ),
        TimeSynchronizer(["camera", "imu"], queue_size=8, clock=WallClock(STEADY)),
    ):
        for k in range(10_000):
            sync.add("camera", Stamped(Time(0, k * 1_000_000, STEADY), k))
            assert sync.stats()["held"] <= 8
        assert sync.dropped == {"camera": 9_992, "imu": 0}
        assert sync.stats()["streams"]["camera"]["received"] == 10_000
