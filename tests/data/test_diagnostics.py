"""Tests of StampDiagnostics: ages, stale and future stamps, queue depth, the run report."""

from __future__ import annotations

import asyncio
import gc
import logging
import weakref

import pytest

import evclock
from evclock import ClockMismatchError, Duration, InvalidArgumentError, Time
from evclock.data import StampDiagnostics, StampWarning, diagnostics_report


def test_ages_stale_episodes_and_percentiles() -> None:
    seen: list[StampWarning] = []

    async def main() -> StampDiagnostics:
        diag = StampDiagnostics("perception", stale_after=0.2, on_warning=seen.append)
        clock = evclock.clock()
        await asyncio.sleep(1.0)
        for k in range(10):
            await asyncio.sleep(0.1)
            lag = 0.5 if k in (3, 4, 7) else 0.05  # a stuck driver twice
            age = diag.observe("camera", clock.now() - Duration(lag))
            assert age == Duration(lag)
        return diag

    diag = evclock.run(main())
    assert [(w.kind, w.stream, w.at) for w in seen] == [
        ("stale", "camera", Time(1.4)),
        ("stale", "camera", Time(1.8)),
    ]  # once per episode: k=3,4 is one, k=7 another
    assert seen[0].message == (
        "stream 'camera': stamp 0.900000000 s (sim) is 0.5 s old at 1.400000000 s (sim)"
        " (stale_after 0.2 s): the producer may be stuck, or its stamps are taken long before "
        "publishing"
    )
    stats = diag.streams()["camera"]
    assert (stats.count, stats.stale, stats.future) == (10, 3, 0)
    assert stats.mean() == Duration(0.185)
    assert diag.percentile("camera", 50) == Duration(0.05)
    assert diag.percentile("camera", 99) == Duration(0.5)
    row = diag.as_dict()["streams"]["camera"]
    assert (row["max_age_s"], row["min_age_s"], row["stale"]) == (0.5, 0.05, 3)


def test_a_wall_clock_ros_stamp_on_sim_time_is_flagged_as_future(caplog) -> None:
    caplog.set_level(logging.WARNING, logger="evclock.stamps")

    async def main() -> None:
        diag = StampDiagnostics()
        wall_msg_stamp = evclock.TimeMsg(sec=1_700_000_000, nanosec=0)  # time.time() on sim
        diag.observe(
            "lidar",
            evclock.data.stamp_of(type("Scan", (), {"stamp": wall_msg_stamp})(), evclock.SIM),
        )
        assert diag.streams()["lidar"].future == 1

    evclock.run(main())
    assert len(caplog.records) == 1
    assert "1.7e+09 s ahead of the clock" in caplog.records[0].getMessage()
    assert "a wall-clock stamp on sim time?" in caplog.records[0].getMessage()


def test_a_domain_mixup_in_observe_raises() -> None:
    async def main() -> None:
        StampDiagnostics().observe("x", Time(1, clock_type=evclock.SYSTEM))

    with pytest.raises(ClockMismatchError):
        evclock.run(main())


def test_report_lists_the_latest_diagnostics_of_each_name_on_the_loop() -> None:
    async def main() -> list[dict[str, object]]:
        alive = [StampDiagnostics(name) for name in ("a", "b", "a", "unused", "dropped")]
        for diag, stream in zip(alive, ("s", "s", "t", None, "s"), strict=True):
            if stream is not None:  # "unused" never observes anything: not listed
                diag.observe(stream, evclock.clock().now())
        del alive[4], diag  # gone: not listed either (the registry holds no strong reference)
        gc.collect()
        return diagnostics_report()

    report = evclock.run(main())
    assert [(r["name"], list(r["streams"])) for r in report] == [("a", ["t"]), ("b", ["s"])]


def test_diagnostics_do_not_keep_their_loop_alive() -> None:
    loops: list[weakref.ref[asyncio.AbstractEventLoop]] = []

    async def main() -> int:
        loops.append(weakref.ref(asyncio.get_running_loop()))
        diag = StampDiagnostics()  # registered for the loop's report
        diag.observe("s", evclock.clock().now())
        return diag.streams()["s"].count

    assert evclock.run(main()) == 1
    gc.collect()
    assert loops[0]() is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"name": ""}, "name must be a non-empty string"),
        ({"stale_after": -1.0}, "stale_after must not be negative"),
        ({"max_queue": 0}, "max_queue must be a positive int or None, got 0"),
        ({"window": 0}, "window must be a positive int, got 0"),
    ],
)
def test_bad_arguments(kwargs, message) -> None:
    with pytest.raises(InvalidArgumentError, match=message):
        StampDiagnostics(**kwargs)


def test_percentile_of_an_unknown_stream() -> None:
    with pytest.raises(InvalidArgumentError, match=r"no message observed on stream 'x'; known"):
        StampDiagnostics().percentile("x", 50)
