"""The live dashboard example (``examples/dashboard``) at the API level.

The app runs in-process under uvicorn (``BackgroundServer``: a background thread with its
own event loop, on a free port) and the tests talk HTTP to it with httpx: the driver paces
the simulation on the server's loop between requests, as in production. The simulation
starts paused so that every check of sim time is exact. Every wait is for a condition and
bounded (``WAIT``): where time must move, the test polls the state; to check that something
does *not* move, it waits until the server has taken fresh history samples (so its loop has
kept running meanwhile) instead of sleeping. Nothing is asserted about wall time.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any

import pytest

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")
# The dashboard extra, and httpx (the test extra) to talk to the app: skipped without them.
pytest.importorskip("starlette", reason="needs evclock[dashboard] (starlette)")
pytest.importorskip("uvicorn", reason="needs evclock[dashboard] (uvicorn)")
pytest.importorskip("PIL", reason="needs evclock[dashboard] (Pillow)")
pytest.importorskip("httpx", reason="needs httpx (evclock[test])")

import httpx

import evclock
from examples.dashboard import BackgroundServer, DashboardConfig, create_app
from examples.dashboard.__main__ import build_parser, parse_rtf

STEP_NS = Fraction(10**9, 240)
"""One physics step of every scenario (1/240 s), exactly, in nanoseconds."""
WAIT = 30.0
"""Wall seconds a poll may take before the test fails (a hang guard, not a performance check)."""


def exact_time_ns(steps: int) -> int:
    """Sim time after ``steps`` physics steps from 0, as evclock keeps it."""
    return int(steps * STEP_NS)


@pytest.fixture
def make_client() -> Iterator[Callable[..., httpx.Client]]:
    """Serve the app (on uvicorn's ``loop``) with a DashboardConfig built from keyword arguments
    (paused by default); return an HTTP client for it."""
    with contextlib.ExitStack() as stack:

        def make(loop: str = "asyncio", **options: Any) -> httpx.Client:
            options.setdefault("paused", True)
            app = create_app(DashboardConfig(**options))
            server = stack.enter_context(BackgroundServer(app, loop=loop))  # type: ignore[arg-type]
            return stack.enter_context(httpx.Client(base_url=server.url, timeout=WAIT))

        yield make


@pytest.fixture
def client(make_client: Callable[..., httpx.Client]) -> httpx.Client:
    """The default app (kuka, rtf 1), started paused."""
    return make_client()


def state(client: httpx.Client) -> dict[str, Any]:
    response = client.get("/api/state")
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


def post(client: httpx.Client, path: str, body: object = None) -> httpx.Response:
    content = None if body is None else json.dumps(body)
    return client.post(path, content=content, headers={"Content-Type": "application/json"})


def post_ok(client: httpx.Client, path: str, body: object = None) -> dict[str, Any]:
    response = post(client, path, body)
    assert response.status_code == 200, response.text
    result: dict[str, Any] = response.json()
    return result


def wait_for(
    predicate: Callable[[dict[str, Any]], bool], client: httpx.Client, what: str
) -> dict[str, Any]:
    """Poll /api/state until ``predicate(state)`` holds (fails after WAIT wall seconds)."""
    deadline = time.monotonic() + WAIT
    while True:
        current = state(client)
        if predicate(current):
            return current
        assert time.monotonic() < deadline, f"timed out waiting for {what}; last state {current}"
        time.sleep(0.02)


def samples(client: httpx.Client) -> int:
    response = client.get("/api/history")
    assert response.status_code == 200, response.text
    return len(response.json()["wall_s"])


def let_the_server_run(client: httpx.Client, count: int = 2) -> None:
    """Wait until the server's sampler has taken ``count`` more samples (its loop kept running).

    Replaces a sleep before checking that something did *not* change. The history keeps
    ``history_size`` samples, so the fixture's configs keep it well above what a test fills.
    """
    target = samples(client) + count
    deadline = time.monotonic() + WAIT
    while samples(client) < target:
        assert time.monotonic() < deadline, f"the sampler did not take {count} more samples"
        time.sleep(0.02)


def assert_error(response: httpx.Response, kind: type[Exception], *fragments: str) -> str:
    """A 400 JSON error of evclock type ``kind`` whose message contains ``fragments``."""
    assert response.status_code == 400, response.text
    body = response.json()
    assert body["type"] == kind.__name__
    message: str = body["error"]
    for fragment in fragments:
        assert fragment in message
    return message


# ------------------------------------------------------------------------- state


def test_initial_state_is_paused_at_zero_with_the_scenario_loops(client: httpx.Client) -> None:
    current = wait_for(lambda s: len(s["loops"]) == 2, client, "the controllers' rate loops")
    assert current["paused"] is True
    assert current["sim_time_ns"] == 0
    assert current["physics_steps"] == 0
    assert current["rtf"] == 1.0
    assert current["time_step_s"] == 1 / 240
    assert current["lockstep_overruns"] == 0
    assert current["scenario"]["name"] == "kuka"
    names = {loop["name"]: loop for loop in current["loops"]}
    assert set(names) == {"joint_control", "planner"}
    assert names["joint_control"]["hz"] == 100
    assert names["planner"]["ticks"] == 1  # tick 0 comes at once, even paused
    assert {"ticks", "missed", "mean_lateness_s", "p99_lateness_s", "max_lateness_s"} <= set(
        names["planner"]
    )
    assert current["episode"]["number"] == 1
    assert current["episode"]["outcome"] == "running"
    assert current["finished_episodes"] == []


def test_paused_sim_time_does_not_advance(client: httpx.Client) -> None:
    first = state(client)
    let_the_server_run(client)  # the driver keeps running meanwhile; sim time must not move
    assert state(client)["sim_time_ns"] == first["sim_time_ns"] == 0
    assert state(client)["stepping"] is None


# ------------------------------------------------------------------------- step


def test_step_advances_exactly_the_requested_physics_steps(client: httpx.Client) -> None:
    result = post_ok(client, "/api/step", {"count": 5})
    assert result["step"] == {"count": 5, "time_ns": exact_time_ns(5)}
    assert result["stepping"] is None
    assert result["physics_steps"] == 5
    assert result["sim_time_ns"] == exact_time_ns(5)
    assert result["paused"] is True

    result = post_ok(client, "/api/step")  # default: one step
    assert result["physics_steps"] == 6
    assert result["sim_time_ns"] == exact_time_ns(6)
    let_the_server_run(client)
    assert state(client)["sim_time_ns"] == exact_time_ns(6)  # and stays paused


def test_stepping_runs_the_controllers_on_sim_time(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(rtf=None)  # steps are paced too: take them as fast as possible
    post_ok(client, "/api/step", {"count": 240})  # one simulated second
    loops = {loop["name"]: loop for loop in state(client)["loops"]}
    # 100 Hz and 10 Hz rates over [0, 1 s]: ticks at 0, 10 ms, ..., 1 s and 0, 0.1, ..., 1 s.
    assert loops["joint_control"]["ticks"] == 101
    assert loops["planner"]["ticks"] == 11
    assert loops["joint_control"]["missed"] == 0
    # Deadlines fall between 1/240 s physics steps: lateness is under one step.
    assert 0 < loops["joint_control"]["max_lateness_s"] < 1 / 240


def test_step_while_running_is_a_400_with_evclocks_message(client: httpx.Client) -> None:
    post_ok(client, "/api/resume")
    message = assert_error(post(client, "/api/step", {"count": 1}), evclock.PacingError)
    assert "pause" in message


@pytest.mark.parametrize(
    ("control", "value", "kind", "fragment"),
    [
        ("step", 0, evclock.InvalidArgumentError, "0"),
        ("step", -3, evclock.InvalidArgumentError, "-3"),
        ("step", "2", evclock.InvalidTypeError, "str"),
        ("step", 1.5, evclock.InvalidTypeError, "float"),
        ("step", True, evclock.InvalidTypeError, "bool"),
        ("rtf", 0, evclock.InvalidArgumentError, "positive"),
        ("rtf", -1.5, evclock.InvalidArgumentError, "-1.5"),
        ("rtf", "fast", evclock.InvalidTypeError, "str"),
        ("rtf", True, evclock.InvalidTypeError, "bool"),
    ],
)
def test_bad_step_counts_and_rtf_values_are_400s_and_change_nothing(
    client: httpx.Client, control: str, value: object, kind: type[Exception], fragment: str
) -> None:
    field = "count" if control == "step" else "rtf"
    assert_error(post(client, f"/api/{control}", {field: value}), kind, field, fragment)
    after = state(client)
    assert (after["physics_steps"], after["rtf"]) == (0, 1.0)


# ------------------------------------------------------------------ pause/resume


def test_resume_advances_and_pause_stops_sim_time(client: httpx.Client) -> None:
    resumed = post_ok(client, "/api/resume")
    assert resumed["paused"] is False
    wait_for(lambda s: s["physics_steps"] > 10, client, "sim time to advance after resume")

    paused = post_ok(client, "/api/pause")
    assert paused["paused"] is True
    frozen = paused["sim_time_ns"]
    let_the_server_run(client)
    later = state(client)
    assert later["sim_time_ns"] == frozen
    assert later["sim_time_ns"] == exact_time_ns(later["physics_steps"])

    stepped = post_ok(client, "/api/step", {"count": 3})
    assert stepped["physics_steps"] == later["physics_steps"] + 3


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
def test_pause_step_resume_on_each_event_loop(
    make_client: Callable[..., httpx.Client], loop: str
) -> None:
    """The driver settles differently on asyncio (ready queue) and uvloop (task inspection)."""
    if loop == "uvloop":
        pytest.importorskip("uvloop", reason="uvloop is not available on this platform")
    client = make_client(loop=loop)
    stepped = post_ok(client, "/api/step", {"count": 7})
    assert (stepped["physics_steps"], stepped["sim_time_ns"]) == (7, exact_time_ns(7))
    ticks = {rate["name"]: rate["ticks"] for rate in stepped["loops"]}
    assert ticks == {"joint_control": 3, "planner": 1}  # 7 steps = 29.2 ms: 0, 10, 20 ms; 0 ms
    post_ok(client, "/api/resume")
    wait_for(lambda s: s["physics_steps"] > 30, client, "sim time to advance")
    frozen = post_ok(client, "/api/pause")["sim_time_ns"]
    let_the_server_run(client)
    assert state(client)["sim_time_ns"] == frozen


# -------------------------------------------------------------------------- rtf


def test_rtf_can_be_changed_and_set_to_as_fast_as_possible(client: httpx.Client) -> None:
    assert post_ok(client, "/api/rtf", {"rtf": 2.5})["rtf"] == 2.5
    assert post_ok(client, "/api/rtf", {"rtf": 3})["rtf"] == 3.0
    assert post_ok(client, "/api/rtf", {"rtf": None})["rtf"] is None
    assert state(client)["rtf"] is None


def test_achieved_rtf_is_reported_while_running(make_client: Callable[..., httpx.Client]) -> None:
    client = make_client(paused=False, rtf=None)
    current = wait_for(
        lambda s: s["achieved_rtf"] is not None and s["achieved_rtf"] > 0,
        client,
        "an achieved real-time factor",
    )
    assert current["rtf"] is None


# ------------------------------------------------------------------ bad bodies


@pytest.mark.parametrize(
    ("path", "content", "fragment"),
    [
        ("/api/step", b"{not json", "not valid JSON"),
        ("/api/step", b"[1, 2]", "JSON object"),
        ("/api/rtf", b'"fast"', "JSON object"),
        ("/api/rtf", b"{}", '{"rtf"'),
    ],
)
def test_malformed_bodies_are_400s(
    client: httpx.Client, path: str, content: bytes, fragment: str
) -> None:
    response = client.post(path, content=content)
    assert response.status_code == 400, response.text
    assert fragment in response.json()["error"]


def test_controls_need_post(client: httpx.Client) -> None:
    assert client.get("/api/pause").status_code == 405


# ------------------------------------------------------------- history, page


def test_history_has_one_column_per_series(client: httpx.Client) -> None:
    post_ok(client, "/api/step", {"count": 24})
    stepped_s = exact_time_ns(24) / 1e9
    deadline = time.monotonic() + WAIT
    # Wait for a sample taken after the step (earlier ones show sim time 0).
    while (history := client.get("/api/history").json())["sim_time_s"][-1] != stepped_s:
        assert time.monotonic() < deadline, f"no sample after the step: {history}"
        time.sleep(0.02)
    columns = [history["wall_s"], history["sim_time_s"], history["achieved_rtf"]]
    columns += [history["requested_rtf"], *history["lateness_ms"].values()]
    assert len({len(column) for column in columns}) == 1
    assert set(history["lateness_ms"]) == {"joint_control", "planner"}
    assert history["wall_s"] == sorted(history["wall_s"])
    assert history["sim_time_s"][0] == 0.0


def test_page_and_vendored_assets_are_served(client: httpx.Client) -> None:
    page = client.get("/")
    assert page.status_code == 200
    assert 'id="sim-time"' in page.text
    assert 'id="rtf-plot"' in page.text
    assert 'id="scene"' in page.text
    for asset in ("dashboard.js", "dashboard.css", "vendor/uplot/uPlot.iife.min.js"):
        response = client.get(f"/static/{asset}")
        assert response.status_code == 200, asset
        assert "cdn" not in response.text.lower() or asset.startswith("vendor")
    assert "MIT" in client.get("/static/vendor/uplot/LICENSE").text


# ------------------------------------------------------------------- episodes


def test_a_finished_mission_starts_the_next_episode_without_a_time_jump(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(paused=False, rtf=None)
    # Running, not in the gap after it ended (the ended episode is still the current one
    # then, and already among the finished).
    current = wait_for(
        lambda s: s["episode"]["number"] >= 2 and s["episode"]["outcome"] == "running",
        client,
        "the second episode",
    )
    first = current["finished_episodes"][-1]
    assert first["number"] == 1
    assert first["seed"] == 0
    assert first["outcome"] == "success"
    assert 0 < first["summary"]["mission_time_s"] <= first["ended_at_s"]
    assert first["duration_s"] == first["ended_at_s"] - first["started_at_s"]
    episode = current["episode"]
    assert episode["seed"] == episode["number"] - 1
    previous = current["finished_episodes"][0]  # newest first
    assert previous["number"] == episode["number"] - 1
    assert episode["started_at_s"] >= previous["ended_at_s"] >= first["ended_at_s"]
    # Steps are counted across the world reset, and sim time never went back.
    assert current["sim_time_ns"] == exact_time_ns(current["physics_steps"])
    # The new episode's rate loops are listed (the clock replaced the earlier ones by name).
    later = wait_for(lambda s: s["episode"]["number"] >= 2 and s["loops"], client, "the loops")
    assert [loop["name"] for loop in later["loops"]] == ["joint_control", "planner"]


def test_once_keeps_stepping_the_physics_after_the_mission(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(paused=False, rtf=None, repeat=False)
    done = wait_for(lambda s: s["finished_episodes"], client, "the mission to end")
    wait_for(lambda s: s["sim_time_ns"] > done["sim_time_ns"], client, "physics after the mission")
    assert state(client)["episode"]["number"] == 1


def test_a_mission_over_its_sim_time_limit_is_a_timeout(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(paused=False, rtf=None, episode_limit=0.01)  # kuka: 0.1 s of sim time
    current = wait_for(lambda s: s["finished_episodes"], client, "the mission's time limit")
    first = current["finished_episodes"][-1]
    assert first["outcome"] == "timeout"
    assert first["duration_s"] == pytest.approx(0.1, abs=1 / 240)  # up to a step boundary


@pytest.mark.parametrize("scenario", ["husky", "cartpole"])
def test_other_scenarios(make_client: Callable[..., httpx.Client], scenario: str) -> None:
    client = make_client(scenario=scenario)
    result = post_ok(client, "/api/step", {"count": 12})
    assert result["scenario"]["name"] == scenario
    assert result["sim_time_ns"] == exact_time_ns(12)
    assert len(result["loops"]) >= 1


# ---------------------------------------------------------- config and command


def test_unknown_scenario_lists_the_valid_names() -> None:
    with pytest.raises(ValueError, match="valid names: kuka, husky, cartpole"):
        DashboardConfig(scenario="nope")


def test_command_line() -> None:
    args = build_parser().parse_args([])
    assert (args.scenario, args.port, args.rtf, args.paused, args.once) == (
        "kuka",
        8000,
        1.0,
        False,
        False,
    )
    args = build_parser().parse_args(["--scenario", "husky", "--rtf", "max", "--port", "0"])
    assert (args.scenario, args.rtf, args.port) == ("husky", None, 0)
    assert parse_rtf("2.5") == 2.5
    for bad in ("0", "-1", "nan", "fast"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_rtf(bad)


def test_background_server_serves_on_a_free_port() -> None:
    app = create_app(DashboardConfig(paused=True))
    with BackgroundServer(app) as server:
        assert server.port > 0
        response = httpx.post(server.url + "/api/step", json={"count": 2}, timeout=WAIT)
        assert response.status_code == 200
        assert response.json()["physics_steps"] == 2
        assert httpx.get(server.url + "/", timeout=WAIT).status_code == 200


# ------------------------------------------------- episodes: statistics survive


def _in_the_third_episode(
    make_client: Callable[..., httpx.Client],
) -> tuple[httpx.Client, dict[str, Any]]:
    """A client of a run at rtf=None, and its state once the third episode's loops tick."""
    client = make_client(paused=False, rtf=None)
    current = wait_for(
        lambda s: s["episode"]["number"] >= 3 and s["loops"] and s["loops"][0]["ticks"] > 1,
        client,
        "the third episode, with its loops ticking",
    )
    return client, current


def test_loop_statistics_and_lateness_survive_episode_resets(
    make_client: Callable[..., httpx.Client],
) -> None:
    client, current = _in_the_third_episode(make_client)
    episode = current["episode"]
    loops = {loop["name"]: loop for loop in current["loops"]}
    assert set(loops) == {"joint_control", "planner"}
    # The statistics are this episode's own: no more ticks than since it started (a tick at
    # the start, then one per period; the times are float seconds, hence the rounding).
    since_start_s = current["sim_time_s"] - episode["started_at_s"]
    assert 0 < loops["joint_control"]["ticks"] <= round(since_start_s * 100) + 1
    assert 0 < loops["planner"]["ticks"] <= round(since_start_s * 10) + 1
    # The lateness plot keeps its series and gets values from this episode too.
    deadline = time.monotonic() + WAIT
    while True:
        history = client.get("/api/history").json()
        # The series appears with the first sample of the loop's ticks (every 0.25 s of wall
        # time, and at rtf=None an episode is shorter): until then, keep polling.
        unsampled = [None] * len(history["sim_time_s"])
        series = history["lateness_ms"].get("joint_control", unsampled)
        recent = [
            late
            for sim, late in zip(history["sim_time_s"], series, strict=True)
            if sim > episode["started_at_s"] and late is not None
        ]
        if recent:
            break
        assert time.monotonic() < deadline, f"no lateness sample in episode 3: {history}"
        time.sleep(0.02)
    assert set(history["lateness_ms"]) == {"joint_control", "planner"}
    assert all(0 <= late < 1000 / 240 for late in recent)  # under one physics step, in ms


def test_each_loop_keeps_its_figures_over_the_whole_run(
    make_client: Callable[..., httpx.Client],
) -> None:
    _, current = _in_the_third_episode(make_client)
    number = current["episode"]["number"]
    ended = [e for e in current["finished_episodes"] if e["number"] < number]
    assert len(ended) == number - 1
    for loop in current["loops"]:
        run = loop["run"]
        assert run["episodes"] == number  # every episode had this loop, the running one too
        # The ended episodes' ticks are kept: one per period of each, start included (+-1:
        # the mission's last tick and the loop's at the same time run in either order).
        earlier = sum(math.floor(e["duration_s"] * loop["hz"]) + 1 for e in ended)
        assert abs(run["ticks"] - loop["ticks"] - earlier) <= len(ended)
        assert run["missed"] >= loop["missed"]
        assert run["max_lateness_s"] >= loop["max_lateness_s"]
        assert 0 <= run["mean_lateness_s"] <= run["max_lateness_s"]


def test_no_real_time_factor_while_paused(make_client: Callable[..., httpx.Client]) -> None:
    client = make_client(paused=False, rtf=None)
    wait_for(lambda s: s["achieved_rtf"] is not None, client, "an achieved real-time factor")
    assert post(client, "/api/pause", {}).status_code == 200
    let_the_server_run(client, 3)
    assert state(client)["achieved_rtf"] is None
    history = client.get("/api/history").json()
    # The samples taken since the pause (sim time no longer moves) have no rtf.
    paused_at = history["sim_time_s"][-1]
    paused = [
        rtf
        for sim, rtf in zip(history["sim_time_s"], history["achieved_rtf"], strict=True)
        if sim == paused_at
    ]
    assert len(paused) >= 2
    assert paused[1:] == [None] * (len(paused) - 1)


# -------------------------------------------- step: answers when done, or says why


def test_a_step_across_an_episode_reset_takes_exactly_its_steps(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(rtf=None)
    count = 240 * 12  # 12 simulated seconds: longer than a kuka mission plus the gap
    result = post_ok(client, "/api/step", {"count": count})
    assert result["step"]["count"] == count
    assert result["physics_steps"] == count
    assert result["episode"]["number"] >= 2
    assert result["finished_episodes"][-1]["outcome"] == "success"
    assert result["paused"] is True
    assert result["stepping"] is None
    let_the_server_run(client)
    assert state(client)["physics_steps"] == count


class StepInBackground:
    """``POST /api/step`` on its own thread and client (the test keeps polling meanwhile)."""

    def __init__(self, url: str, count: int) -> None:
        self.response: httpx.Response | None = None
        self._thread = threading.Thread(target=self._post, args=(url, count), daemon=True)
        self._thread.start()

    def _post(self, url: str, count: int) -> None:
        with httpx.Client(base_url=url, timeout=WAIT) as client:
            self.response = post(client, "/api/step", {"count": count})

    def result(self) -> httpx.Response:
        self._thread.join(WAIT)
        assert self.response is not None, "the step request did not answer"
        return self.response


def test_pause_interrupts_a_step_and_cancels_the_rest(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(rtf=1.0)
    count = 240 * 3600  # an hour of steps at rtf 1: under way for the whole test
    step = StepInBackground(str(client.base_url), count)
    under_way = wait_for(
        lambda s: s["stepping"] is not None and s["stepping"]["taken"] > 0,
        client,
        "the step to be under way",
    )
    assert under_way["stepping"]["count"] == count
    assert under_way["paused"] is True

    post_ok(client, "/api/pause")
    response = step.result()
    assert response.status_code == 409, response.text
    body = response.json()
    assert body["type"] == "StepNotCompleted"
    assert body["step"]["reason"] == "interrupted"
    assert body["step"]["count"] == count
    assert 0 < body["step"]["taken"] < count
    assert "interrupted by a pause" in body["error"]
    assert body["error"].endswith("physics steps; the remaining ones were cancelled")
    assert f"of {count} physics steps" in body["error"]
    # Nothing steps on in the background.
    stopped = state(client)
    assert stopped["stepping"] is None
    let_the_server_run(client)
    assert state(client)["physics_steps"] == stopped["physics_steps"]
    assert stopped["physics_steps"] == body["step"]["taken"]


def test_a_step_over_its_timeout_answers_504_and_cancels_the_rest(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(rtf=1.0, step_timeout=0.5)
    count = 240 * 3600  # an hour at rtf 1, against half a second of wall time
    response = post(client, "/api/step", {"count": count})
    assert response.status_code == 504, response.text
    body = response.json()
    assert body["type"] == "StepNotCompleted"
    assert body["step"]["reason"] == "timeout"
    assert 0 <= body["step"]["taken"] < count
    assert f"of {count} physics steps were taken in 0.5 s of wall time at rtf=1" in body["error"]
    assert "raise the rtf" in body["error"]
    stopped = state(client)
    assert stopped["paused"] is True
    assert stopped["stepping"] is None
    assert stopped["physics_steps"] == body["step"]["taken"]
    let_the_server_run(client)
    assert state(client)["physics_steps"] == stopped["physics_steps"]


# --------------------------------------------------------------------- scene


def scene(client: httpx.Client) -> httpx.Response:
    response = client.get("/api/scene.jpg")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/jpeg"
    assert response.content[:3] == b"\xff\xd8\xff"  # a JPEG
    return response


def test_scene_view_renders_frames_as_the_robot_moves(
    make_client: Callable[..., httpx.Client],
) -> None:
    client = make_client(rtf=None)
    first = scene(client)
    assert first.headers["X-Frame"] == "1"
    assert first.headers["X-Physics-Steps"] == "0"
    assert first.headers["X-Sim-Time-Ns"] == "0"
    assert first.headers["X-Episode"] == "1"

    # Paused: nothing moved, so no new frame whoever asks.
    let_the_server_run(client)
    assert scene(client).headers["X-Frame"] == "1"

    post_ok(client, "/api/step", {"count": 240})  # one second: the arm reaches out
    moved = scene(client)
    assert moved.headers["X-Frame"] == "2"
    assert moved.headers["X-Physics-Steps"] == "240"
    assert moved.headers["X-Sim-Time-Ns"] == str(exact_time_ns(240))
    assert moved.content != first.content


def test_scene_view_renders_at_most_scene_fps(make_client: Callable[..., httpx.Client]) -> None:
    client = make_client(rtf=None, scene_fps=0.001)  # one frame per 1000 wall seconds
    assert scene(client).headers["X-Frame"] == "1"
    post_ok(client, "/api/step", {"count": 24})
    again = scene(client)  # the world moved, but the next frame is not due yet
    assert again.headers["X-Frame"] == "1"
    assert again.headers["X-Physics-Steps"] == "0"


@pytest.mark.parametrize("scenario", ["husky", "cartpole"])
def test_scene_view_of_other_scenarios(
    make_client: Callable[..., httpx.Client], scenario: str
) -> None:
    client = make_client(scenario=scenario, rtf=None)
    post_ok(client, "/api/step", {"count": 48})
    assert scene(client).headers["X-Physics-Steps"] == "48"


def test_scene_view_follows_episode_resets(make_client: Callable[..., httpx.Client]) -> None:
    client = make_client(rtf=None)
    post_ok(client, "/api/step", {"count": 240 * 12})  # past the first mission and reset
    frame = scene(client)
    assert int(frame.headers["X-Episode"]) >= 2
    assert frame.headers["X-Physics-Steps"] == str(240 * 12)


# --------------------------------------------------------------- the page


def test_the_page_arrives_with_the_state_embedded(client: httpx.Client) -> None:
    post_ok(client, "/api/step", {"count": 3})
    page = client.get("/").text
    assert "connecting" not in page
    assert '<p id="scenario" class="muted">kuka: KUKA iiwa' in page
    match = re.search(r'<script id="initial-state" type="application/json">(.*?)</script>', page)
    assert match is not None
    embedded = json.loads(match.group(1))
    assert embedded["physics_steps"] == 3
    assert embedded["scenario"]["name"] == "kuka"
    assert "</" not in match.group(1)  # nothing in the JSON can close the script element


# ------------------------------------------------ from any working directory

DASHBOARD = Path(__file__).resolve().parents[2] / "examples" / "dashboard"


def test_the_dashboard_runs_from_any_working_directory(tmp_path: Path) -> None:
    """``python path/to/examples/dashboard`` from an unrelated folder serves, scene included."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    command = [sys.executable, str(DASHBOARD), "--port", "0", "--paused", "--loop", "asyncio"]
    lines: queue.Queue[str] = queue.Queue()
    with subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    ) as process:
        assert process.stderr is not None
        reader = threading.Thread(target=_read_lines, args=(process.stderr, lines))
        reader.start()
        try:
            url = _wait_for_url(process, lines)
            with httpx.Client(base_url=url, timeout=WAIT) as client:
                assert state(client)["scenario"]["name"] == "kuka"
                assert post_ok(client, "/api/step", {"count": 2})["physics_steps"] == 2
                assert scene(client).headers["X-Physics-Steps"] == "2"
        finally:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(WAIT)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(WAIT)
            reader.join(WAIT)  # ends at the end of the log, the process being gone
    assert process.returncode == 0


def _read_lines(stream: Iterable[str], lines: queue.Queue[str]) -> None:
    for line in stream:
        lines.put(line)


def _wait_for_url(process: subprocess.Popen[str], lines: queue.Queue[str]) -> str:
    """The URL uvicorn logs once it listens (at most WAIT wall seconds)."""
    deadline = time.monotonic() + WAIT
    log: list[str] = []
    while True:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"the server did not log its URL: {log}"
        assert process.poll() is None, f"the server exited: {log}"
        with contextlib.suppress(queue.Empty):
            log.append(lines.get(timeout=min(remaining, 1.0)))
            found = re.search(r"running on (http://127\.0\.0\.1:\d+)", log[-1])
            if found:
                return found.group(1)


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"scene_fps": 0}, "scene_fps must be positive"),
        ({"scene_size": (8, 8)}, "scene_size must be (width, height) within"),
    ],
)
def test_bad_scene_settings(options: dict[str, Any], fragment: str) -> None:
    with pytest.raises(ValueError, match=re.escape(fragment)):
        DashboardConfig(**options)


def test_resume_ends_a_step_under_way(make_client: Callable[..., httpx.Client]) -> None:
    client = make_client(rtf=1.0)
    count = 240 * 3600
    step = StepInBackground(str(client.base_url), count)
    wait_for(lambda s: s["stepping"] is not None, client, "the step to be under way")
    post_ok(client, "/api/resume")
    response = step.result()
    assert response.status_code == 409, response.text
    body = response.json()
    assert body["step"]["reason"] == "interrupted"
    assert "interrupted by a resume after" in body["error"]
    assert body["error"].endswith("physics steps; sim time now runs freely")
    current = state(client)
    assert current["paused"] is False  # the resume stands: sim time runs freely
    assert current["stepping"] is None


def test_without_pillow_the_error_names_the_extra() -> None:
    code = (
        "import sys; sys.modules['PIL'] = None\n"  # as if Pillow were not installed
        "import examples.dashboard\n"
    )
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=WAIT
    )
    assert result.returncode == 1
    assert "scene view encodes JPEG with Pillow" in result.stderr
    assert "pip install 'evclock[dashboard]'" in result.stderr
