"""Filters and the new synchronisers' front ends: Cache, TimeSequencer, chaining, drop
reasons, and the reset on a backward time jump (a real PyBullet restore and reset).

Cache and TimeSequencer are also checked against the reference models of ROS's C++ filters
in ``ros_reference.py`` (models written from the ROS sources, not the ROS binaries).
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from _examples import run_example
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ros_reference import RosCache, RosTimeSequencer

import evclock
from evclock import SIM, ClockMismatchError, InvalidArgumentError, InvalidTypeError, Time
from evclock.data import (
    DROP_REASONS,
    ApproximateEpsilonTimeSynchronizer,
    ApproximateTimeSynchronizer,
    Cache,
    Chain,
    LatestTimeSynchronizer,
    PassThrough,
    Stamped,
    TimeSequencer,
    TimeSynchronizer,
)

CASES = settings(max_examples=1_000, deadline=None, suppress_health_check=[HealthCheck.too_slow])


class ManualClock:
    """A sim-domain clock whose time the test sets (no timers: dispatch is called by hand)."""

    clock_type = SIM

    def __init__(self) -> None:
        self.ns = 0

    def now(self) -> Time:
        return Time(nanoseconds=self.ns)


def msg(ns: int, value: object) -> Stamped[object]:
    return Stamped(Time(nanoseconds=ns), value)


# -- Cache ------------------------------------------------------------------------------------

ops = st.lists(
    st.one_of(
        st.tuples(st.just("add"), st.integers(0, 20)),
        st.tuples(st.just("interval"), st.integers(0, 22), st.integers(0, 22)),
        st.tuples(st.just("surrounding"), st.integers(0, 22), st.integers(0, 22)),
        st.tuples(st.just("before"), st.integers(0, 22)),
        st.tuples(st.just("after"), st.integers(0, 22)),
    ),
    max_size=40,
)


@CASES
@given(size=st.integers(1, 6), operations=ops)
def test_cache_agrees_with_the_ros_cpp_cache_model(size: int, operations: list[Any]) -> None:
    cache = Cache(cache_size=size, clock=ManualClock())
    ref = RosCache(size)
    for k, op in enumerate(operations):
        if op[0] == "add":
            cache.add(msg(op[1], k))
            ref.add(op[1], msg(op[1], k))
        elif op[0] in ("interval", "surrounding"):
            lo, hi = sorted(op[1:])
            mine = getattr(cache, op[0])(Time(nanoseconds=lo), Time(nanoseconds=hi))
            assert mine == getattr(ref, op[0])(lo, hi)
        else:
            assert getattr(cache, op[0])(Time(nanoseconds=op[1])) == getattr(ref, op[0])(op[1])
        assert len(cache) == len(ref.cache) <= size
        stamps = [stamp for stamp, _ in ref.cache]
        assert cache.oldest_time == (Time(nanoseconds=stamps[0]) if stamps else None)
        assert cache.newest_time == (Time(nanoseconds=stamps[-1]) if stamps else None)


def test_cache_queries_by_hand() -> None:
    cache = Cache(cache_size=3, clock=ManualClock())
    for t, v in ((1.0, "a"), (3.0, "c"), (2.0, "b"), (2.0, "b2")):  # out of order, a tie
        cache.add(Stamped(Time(t), v))
    assert [m.value for m in cache.interval(2.0, 3.0)] == ["b", "b2", "c"]  # "a" evicted
    assert cache.evicted == 1
    assert cache.before(Time(2.0)) is None
    assert cache.after(Time(2.0)).value == "c"
    assert cache.oldest.value == "b"
    assert cache.newest.value == "c"
    assert [m.value for m in cache.surrounding(2.5, 2.6)] == ["b2", "c"]
    with pytest.raises(ClockMismatchError, match="is a steady time but Cache holds sim stamps"):
        cache.before(Time(1.0, clock_type=evclock.STEADY))
    with pytest.raises(InvalidArgumentError, match="cache_size must be a positive int, got 0"):
        Cache(cache_size=0)


# -- TimeSequencer -------------------------------------------------------------------------


@CASES
@given(
    delay=st.integers(0, 5),
    queue_size=st.integers(0, 4),
    steps=st.lists(
        st.tuples(st.integers(0, 3), st.lists(st.integers(0, 30), max_size=4)), max_size=15
    ),
)
def test_time_sequencer_agrees_with_the_ros_model(delay, queue_size, steps) -> None:
    clock = ManualClock()
    released: list[Any] = []
    seq = TimeSequencer(delay=delay, update_rate=1, queue_size=queue_size, clock=clock)
    seq.register_callback(released.append)
    ref = RosTimeSequencer(delay * 10**9, queue_size)
    expected: list[Any] = []
    k = 0
    for advance, stamps in steps:
        for s in stamps:
            m = msg(s * 10**9, k)
            k += 1
            seq.add(m)
            ref.add(s * 10**9, m)
        clock.ns += advance * 10**9
        seq.dispatch()
        expected += ref.dispatch(clock.ns)
        assert released == expected


def test_time_sequencer_releases_in_stamp_order_after_the_delay_in_sim_time() -> None:
    async def main() -> list[tuple[float, str]]:
        clock = evclock.clock()
        out: list[tuple[float, str]] = []
        dropped: list[tuple[str, str]] = []
        seq = TimeSequencer(
            delay=0.5,
            update_rate=0.1,
            queue_size=10,
            on_drop=lambda m, why: dropped.append((m.value, why)),
        )
        seq.register_callback(lambda m: out.append((clock.now().seconds, m.value)))
        for t, v in ((0.3, "c"), (0.1, "a"), (0.2, "b")):  # arrive out of order at t=0
            seq.add(Stamped(Time(t), v))
        await clock.sleep(1.0)
        seq.add(Stamped(Time(0.05), "late"))  # older than what was released: dropped
        seq.close()
        assert dropped == [("late", "late")]
        return out

    # Released at the first check (every 0.1 s of sim time) at or after stamp + 0.5 s.
    assert evclock.run(main()) == [(0.6, "a"), (0.7, "b"), (0.8, "c")]


# -- chaining and the new synchronisers on sim time ---------------------------------------


def test_subscriber_cache_synchroniser_pipeline() -> None:
    async def main() -> tuple[list[tuple[str, str]], list[str]]:
        clock = evclock.clock()
        camera, lidar = PassThrough(), PassThrough()
        camera_cache = Cache(camera, cache_size=50)
        chain = Chain(PassThrough(), PassThrough())  # two filters in a row: a no-op chain
        chain.connect_input(lidar)
        groups: list[tuple[str, str]] = []
        sync = ApproximateEpsilonTimeSynchronizer(
            ["camera", "lidar"],
            10,
            epsilon=0.02,
            callback=lambda c, li: groups.append((c.value, li.value)),
        )
        sync.connect_input(camera_cache, chain)
        for k in range(5):
            await clock.sleep_until(Time(k * 0.1))
            camera.add(Stamped(clock.now(), f"c{k}"))
            lidar.add(Stamped(clock.now() + evclock.Duration(0.01), f"l{k}"))
        return groups, [m.value for m in camera_cache.interval(0.1, 0.3)]

    groups, cached = evclock.run(main())
    assert groups == [(f"c{k}", f"l{k}") for k in range(5)]
    assert cached == ["c1", "c2", "c3"]


def test_latest_time_synchroniser_holds_the_slow_stream_on_sim_time() -> None:
    async def main() -> list[tuple[str, str]]:
        clock = evclock.clock()
        sync = LatestTimeSynchronizer(["imu", "camera"])

        async def imu() -> None:
            async for tick in clock.rate(100):
                sync.add("imu", f"imu{tick.index}")
                if tick.index == 10:
                    return

        async def camera() -> None:
            async for tick in clock.rate(25):
                sync.add("camera", f"cam{tick.index}")
                if tick.index == 2:
                    return

        await asyncio.gather(imu(), camera())
        sync.close()
        return [group async for group in sync]

    groups = evclock.run(main())
    # From the 2nd IMU sample on, one group per IMU sample, the camera held between frames.
    assert [g[0] for g in groups] == [f"imu{k}" for k in range(1, 11)]
    assert [g[1] for g in groups] == ["cam0"] * 3 + ["cam1"] * 4 + ["cam2"] * 3


def test_drop_callbacks_name_the_reason() -> None:
    drops: list[tuple[str, object, str]] = []
    clock = ManualClock()
    sync = ApproximateTimeSynchronizer(
        ["a", "b"], queue_size=2, clock=clock, on_drop=lambda *d: drops.append(d)
    )
    for k in range(4):
        sync.add("a", msg(k * 10**9, f"a{k}"))  # b never comes: the queue bound drops a0, a1
    assert drops == [("a", drops[0][1], "queue_full"), ("a", drops[1][1], "queue_full")]
    assert [d[1].value for d in drops] == ["a0", "a1"]
    exact = TimeSynchronizer(["a", "b"], clock=clock, on_drop=lambda *d: drops.append(d))
    exact.add("a", msg(1, "x"))
    exact.add("a", msg(1, "y"))
    assert drops[-1][1].value == "x"
    assert drops[-1][2] == "replaced"
    assert set(DROP_REASONS) >= {reason for _, _, reason in drops}
    with pytest.raises(InvalidTypeError, match="on_drop must be callable, got int"):
        TimeSynchronizer(2, on_drop=3)  # type: ignore[arg-type]


def test_slop_from_float_seconds_is_truncated_like_rclpy() -> None:
    sync = ApproximateTimeSynchronizer(2, 5, slop=1.001, clock=ManualClock())
    assert sync.slop is not None
    assert sync.slop.nanoseconds == 1_000_999_999
    ros1 = ApproximateTimeSynchronizer(2, 5, slop=2.3, seconds_convention="ros1")
    assert ros1.slop is not None
    assert ros1.slop.nanoseconds == 2_299_999_999
    with pytest.raises(InvalidArgumentError, match="long_double_bits must be 64"):
        ApproximateTimeSynchronizer(2, long_double_bits=80)
    with pytest.raises(InvalidArgumentError, match="seconds_convention must be 'ros2'"):
        ApproximateTimeSynchronizer(2, seconds_convention="ros3")  # type: ignore[arg-type]


# -- reset on a backward jump: a real PyBullet restore and reset -----------------------------


def test_a_pybullet_restore_and_reset_clear_synchronisers_caches_and_sequencers() -> None:
    pytest.importorskip("pybullet")

    async def main() -> dict[str, Any]:
        clock = evclock.clock()
        source = asyncio.get_running_loop().source  # type: ignore[attr-defined]
        drops: list[tuple[str, str]] = []
        groups: list[tuple[float, float]] = []
        sync = ApproximateTimeSynchronizer(
            ["a", "b"],
            10,
            age_penalty=0.1,
            on_drop=lambda s, m, why: drops.append((m.value, why)),
            callback=lambda a, b: groups.append((a.stamp.seconds, b.stamp.seconds)),
        )
        cache = Cache(cache_size=100)
        released: list[str] = []
        seq = TimeSequencer(delay=0.2, update_rate=0.05)
        seq.register_callback(lambda m: released.append(m.value))
        await clock.sleep(0.5)
        snapshot = source.save_state()
        await clock.sleep(0.5)  # t = 1.0
        sync.add("a", Stamped(clock.now(), "a@1.0"))  # waits for b: held
        cache.add(Stamped(clock.now(), "c@1.0"))
        seq.add(Stamped(clock.now(), "s@1.0"))
        source.restore_state(snapshot)  # back to 0.5 s: a real backward jump
        after_restore = (clock.now().seconds, sync.resets, len(cache), len(seq), list(drops))
        # After the jump, matching works again from the restored time.
        sync.add("a", Stamped(clock.now(), "a@0.5"))
        sync.add("b", Stamped(clock.now(), "b@0.5"))
        seq.add(Stamped(clock.now(), "s@0.5"))  # not "late": the last release was forgotten
        await clock.sleep(0.3)
        source.reset_simulation()  # resetSimulation: back to 0
        after_reset = (clock.now().seconds, sync.resets, cache.resets, seq.resets)
        seq.close()
        sync.close()
        return {
            "after_restore": after_restore,
            "after_reset": after_reset,
            "groups": groups,
            "released": released,
        }

    source = evclock.sources.PyBulletTimeSource.connect()
    result = evclock.run(main(), source=source)
    assert result["after_restore"] == (0.5, 1, 0, 0, [("a@1.0", "reset")])
    assert result["groups"] == [(0.5, 0.5)]
    assert result["released"] == ["s@0.5"]
    assert result["after_reset"] == (0.0, 2, 2, 2)


def test_reset_on_jump_can_be_turned_off() -> None:
    pytest.importorskip("pybullet")

    async def main() -> int:
        clock = evclock.clock()
        source = asyncio.get_running_loop().source  # type: ignore[attr-defined]
        sync = TimeSynchronizer(2, reset_on_jump=False)
        await clock.sleep(0.1)
        sync.add(0, Stamped(clock.now(), "kept"))
        source.reset_simulation()
        return sync.stats()["held"]

    source = evclock.sources.PyBulletTimeSource.connect()
    assert evclock.run(main(), source=source) == 1


# -- the example ------------------------------------------------------------------------------


def test_the_fusion_pipeline_example_runs_as_documented() -> None:
    pytest.importorskip("pybullet")
    proc = run_example("fusion_pipeline.py")
    assert proc.stdout.splitlines() == [
        "fusion pipeline seed 0: success",
        "detections fused: 89",
        "worst error at the detection stamp (cache + interpolation): 1.9 mm",
        "worst error with the paired odometry message: 7.2 mm",
        "worst error with the latest pose: 82.4 mm",
        "odometry cached: 200 (oldest 2.020833333 s (sim))",
        "dropped, odometry: not_selected: 205",
    ]
