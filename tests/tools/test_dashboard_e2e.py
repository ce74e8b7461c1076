"""The live dashboard end to end: the real page in headless Chromium, driven by Playwright.

Uses Debian's Chromium at /usr/bin/chromium (``.ci/run`` installs it; Playwright's own
browser download is never used). The dashboard is served in-process by uvicorn on a free
port, running the KUKA scenario in repeating episodes. Every wait is bounded and polls the
page; nothing is asserted about wall time.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from fractions import Fraction

import pytest

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")
# The dashboard extra, and Playwright (the test extra) to drive the page: skipped without them.
pytest.importorskip("starlette", reason="needs evclock[dashboard] (starlette)")
pytest.importorskip("uvicorn", reason="needs evclock[dashboard] (uvicorn)")
pytest.importorskip("PIL", reason="needs evclock[dashboard] (Pillow)")
pytest.importorskip("playwright", reason="needs playwright (evclock[test])")

from _chromium import CHROMIUM, CHROMIUM_FLAGS
from playwright.sync_api import Page, expect, sync_playwright

from examples.dashboard import BackgroundServer, DashboardConfig, create_app

TIMEOUT_MS = 30_000
"""Bound of every wait on the page (a hang guard, not a performance check)."""
STEP_NS = Fraction(10**9, 240)

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="end-to-end dashboard test needs Debian's chromium at /usr/bin/chromium "
    "(apt-get install chromium; .ci/run installs it)",
)


def sim_time_text(steps: int) -> str:
    """How the page shows the sim time after ``steps`` physics steps from 0."""
    return f"{int(steps * STEP_NS) / 1e9:.6f} s"


@pytest.fixture
def server() -> Iterator[BackgroundServer]:
    """The dashboard, running kuka in repeating episodes at rtf 1, on a free port."""
    app = create_app(DashboardConfig(scenario="kuka", rtf=1.0))
    with BackgroundServer(app) as running:
        yield running


@pytest.fixture
def page(server: BackgroundServer) -> Iterator[Page]:
    """A fresh headless Chromium page showing the dashboard."""
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS
        )
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 1100})
            page.set_default_timeout(TIMEOUT_MS)
            expect.set_options(timeout=TIMEOUT_MS)  # expect() has its own 5 s default
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.goto(server.url + "/")
            yield page
            assert errors == [], f"JavaScript errors on the page: {errors}"
        finally:
            browser.close()


def physics_steps(page: Page) -> int:
    return int(page.locator("#physics-steps").inner_text())


def renders(page: Page) -> int:
    return int(page.locator("body").get_attribute("data-renders") or 0)


def wait_for_steps_above(page: Page, steps: int) -> None:
    """Wait until the page shows more than ``steps`` physics steps."""
    page.wait_for_function(
        f"() => Number(document.getElementById('physics-steps').textContent) > {steps}"
    )


def wait_for_renders(page: Page, count: int) -> None:
    """Wait until the page has rendered ``count`` more states from the API."""
    target = renders(page) + count
    page.wait_for_function(f"() => Number(document.body.dataset.renders) >= {target}")


def scene_frame(page: Page) -> int:
    return int(page.locator("#scene").get_attribute("data-frame") or 0)


def wait_for_scene_frame_above(page: Page, frame: int) -> None:
    page.wait_for_function(
        f"() => Number(document.getElementById('scene').dataset.frame) > {frame}"
    )


def test_dashboard_controls_sim_time_end_to_end(page: Page) -> None:
    # The page arrives with the state: shown before any poll has answered.
    expect(page.locator("#scenario")).to_have_text(re.compile(r"^kuka: KUKA iiwa"))
    assert renders(page) >= 1

    # Several episodes, as fast as possible: the loops and their plot stay.
    page.click(".rtf-preset[data-rtf='max']")
    expect(page.locator("#requested-rtf")).to_have_text("max")
    page.wait_for_function(
        "() => /^#([3-9]|\\d\\d+) /.test(document.getElementById('episode').textContent)"
    )
    expect(page.locator("#loops tbody tr")).to_have_count(2)
    expect(page.locator("#loops tbody tr[data-loop='joint_control']")).to_be_visible()
    expect(page.locator("#loops tbody tr[data-loop='planner']")).to_be_visible()
    assert page.locator("#episodes tbody tr").count() >= 2
    expect(page.locator("#episodes tbody tr").last).to_contain_text("success")
    samples = int(page.locator("#lateness-plot").get_attribute("data-samples") or 0)
    page.wait_for_function(
        f"() => Number(document.getElementById('lateness-plot').dataset.samples) > {samples}"
    )
    expect(page.locator("#lateness-plot .u-legend")).to_contain_text("joint_control")
    expect(page.locator("#lateness-plot .u-legend")).to_contain_text("planner")

    # The scene view changes as the robot moves (within a few frames: the arm may rest
    # a moment at a target).
    wait_for_scene_frame_above(page, 0)
    before = page.locator("#scene").screenshot()
    for _ in range(10):
        wait_for_scene_frame_above(page, scene_frame(page))
        if page.locator("#scene").screenshot() != before:
            break
    else:
        pytest.fail("the scene view showed the same image for 10 frames while running")

    # Back to real time. Running: sim time advances on the page.
    page.click(".rtf-preset[data-rtf='1']")
    expect(page.locator("#requested-rtf")).to_have_text("1.000\u00d7")
    expect(page.locator("#run-state")).to_have_text("running")
    wait_for_steps_above(page, physics_steps(page) + 10)
    expect(page.locator("#loops tbody tr")).to_have_count(2)
    expect(page.locator("#loops tbody tr[data-loop='joint_control']")).to_be_visible()

    # The plots are drawn over sim time and take new samples.
    for plot in ("#rtf-plot", "#lateness-plot"):
        expect(page.locator(f"{plot} canvas")).to_have_count(1)
        expect(page.locator(f"{plot} .u-legend .u-series").first).to_contain_text("sim time (s)")
    samples = int(page.locator("#rtf-plot").get_attribute("data-samples") or 0)
    page.wait_for_function(
        f"() => Number(document.getElementById('rtf-plot').dataset.samples) > {samples}"
    )

    # Pause: sim time stops, over several fresh renders of the state.
    page.click("#pause")
    expect(page.locator("#run-state")).to_have_text("paused")
    expect(page.locator("#step")).to_be_enabled()
    paused_at = physics_steps(page)
    wait_for_renders(page, 3)
    assert physics_steps(page) == paused_at
    expect(page.locator("#achieved-rtf")).to_have_text("-")  # no real-time factor paused

    # Paused, the scene shows the paused world and renders no new frame.
    page.wait_for_function(
        f"() => document.getElementById('scene').dataset.steps === '{paused_at}'"
    )
    paused_frame = scene_frame(page)
    wait_for_renders(page, 3)
    assert scene_frame(page) == paused_frame

    # Step: exactly one physics step, then three.
    page.click("#step")
    expect(page.locator("#physics-steps")).to_have_text(str(paused_at + 1))
    expect(page.locator("#sim-time")).to_have_text(sim_time_text(paused_at + 1))
    page.fill("#step-count", "3")
    page.click("#step")
    expect(page.locator("#physics-steps")).to_have_text(str(paused_at + 4))
    wait_for_renders(page, 2)
    assert physics_steps(page) == paused_at + 4
    page.wait_for_function(
        f"() => document.getElementById('scene').dataset.steps === '{paused_at + 4}'"
    )
    assert scene_frame(page) > paused_frame  # a new frame for the stepped world

    # A long step shows its progress, and Pause stops it there.
    page.fill("#step-count", "100000")
    page.click("#step")
    expect(page.locator("#run-state")).to_have_text(re.compile(r"^stepping [1-9]\d*/100000$"))
    expect(page.locator("#pause")).to_be_enabled()
    page.click("#pause")
    expect(page.locator("#run-state")).to_have_text("paused")
    expect(page.locator("#step")).to_be_enabled()
    expect(page.locator("#error")).to_be_hidden()
    stopped_at = physics_steps(page)
    assert stopped_at > paused_at + 4
    wait_for_renders(page, 3)
    assert physics_steps(page) == stopped_at

    # Change the real-time factor; a bad one shows evclock's message.
    page.fill("#rtf-input", "2")
    page.click("#rtf-set")
    expect(page.locator("#requested-rtf")).to_have_text("2.000\u00d7")
    page.fill("#rtf-input", "0")
    page.click("#rtf-set")
    expect(page.locator("#error")).to_be_visible()
    expect(page.locator("#error")).to_contain_text("rtf must be a positive")
    expect(page.locator("#requested-rtf")).to_have_text("2.000\u00d7")

    # Resume: sim time advances again.
    page.click("#resume")
    expect(page.locator("#run-state")).to_have_text("running")
    expect(page.locator("#error")).to_be_hidden()
    expect(page.locator("#step")).to_be_disabled()
    wait_for_steps_above(page, stopped_at + 10)
