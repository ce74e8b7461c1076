"""The live dashboard end to end: the real page in headless Chromium, driven by Playwright.

Uses Debian's Chromium at /usr/bin/chromium (``.ci/run`` installs it; Playwright's own
browser download is never used). The dashboard is served in-process by uvicorn on a free
port, running the KUKA scenario in real time. Every wait is bounded and polls the page;
nothing is asserted about wall time.
"""

from __future__ import annotations

from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import pytest

# PyBullet has wheels for CPython 3.11 only: elsewhere these tests are skipped (conftest.py
# makes a missing PyBullet an error on 3.11).
pytest.importorskip("pybullet", reason="PyBullet is not installed: pip install 'evclock[pybullet]'")
from playwright.sync_api import Page, expect, sync_playwright

from examples.dashboard import BackgroundServer, DashboardConfig, create_app

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
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
    """The dashboard, running kuka at rtf 1, on a free port."""
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


def test_dashboard_controls_sim_time_end_to_end(page: Page) -> None:
    # Running: sim time advances on the page.
    expect(page.locator("#run-state")).to_have_text("running")
    wait_for_steps_above(page, physics_steps(page) + 10)
    expect(page.locator("#loops tbody tr")).to_have_count(2)
    expect(page.locator("#loops tbody tr[data-loop='joint_control']")).to_be_visible()

    # The plots are drawn and take new samples.
    for plot in ("#rtf-plot", "#lateness-plot"):
        expect(page.locator(f"{plot} canvas")).to_have_count(1)
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

    # Step: exactly one physics step, then three.
    page.click("#step")
    expect(page.locator("#physics-steps")).to_have_text(str(paused_at + 1))
    expect(page.locator("#sim-time")).to_have_text(sim_time_text(paused_at + 1))
    page.fill("#step-count", "3")
    page.click("#step")
    expect(page.locator("#physics-steps")).to_have_text(str(paused_at + 4))
    wait_for_renders(page, 2)
    assert physics_steps(page) == paused_at + 4

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
    wait_for_steps_above(page, paused_at + 4 + 10)
