"""The docs' diagrams in a real browser: the site built (``mkdocs build --strict``) and served
on localhost, each page with a diagram opened in headless Chromium at a desktop and a phone
width. Every ``mermaid`` block must become Mermaid's SVG holding every label of its source,
drawn by the site's own copy of Mermaid (docs/_hooks/mermaid.py: no request leaves localhost),
and nothing may be wider than the page or the content column.

Uses Debian's Chromium at /usr/bin/chromium with the launch options of
tests/tools/test_dashboard_e2e.py (``.ci/run`` installs it; Playwright's own browser download
is never used). Every wait is bounded; nothing is asserted about wall time.
"""

from __future__ import annotations

import functools
import html
import http.server
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from _chromium import CHROMIUM, CHROMIUM_FLAGS
from _examples import load_module

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
HOOK = DOCS / "_hooks" / "mermaid.py"
MERMAID_BLOCK = re.compile(r"^```mermaid\n(.*?)^```", re.M | re.S)
#: Each docs page with diagrams (its path in the built site) and the sources of its diagrams.
DIAGRAMS = {
    page.relative_to(DOCS).with_suffix(".html").as_posix(): MERMAID_BLOCK.findall(page.read_text())
    for page in sorted(DOCS.rglob("*.md"))
    if "_hooks" not in page.parts and MERMAID_BLOCK.search(page.read_text())
}
VIEWPORTS = {"desktop": (1280, 900), "phone": (390, 844)}
#: At the desktop width a diagram is drawn at this fraction of its natural size or more, so
#: that its text stays as legible as the page's (Mermaid scales a wider one down to fit).
LEGIBLE_SCALE = 0.85
TIMEOUT_MS = 30_000
"""Bound of every wait on a page (a hang guard, not a performance check)."""

# Material draws each diagram into a closed shadow root; the test opens them to read the SVG.
OPEN_SHADOW_ROOTS = """
const attach = Element.prototype.attachShadow;
Element.prototype.attachShadow = function (init) {
    return attach.call(this, { ...init, mode: "open" });
};
"""
MEASURE = """
() => {
    const column = document.querySelector(".md-content__inner").getBoundingClientRect();
    return {
        scrollWidth: document.documentElement.scrollWidth,
        clientWidth: document.documentElement.clientWidth,
        column: [column.left, column.right],
        diagrams: [...document.querySelectorAll("div.mermaid")].map((div) => {
            const svg = div.shadowRoot && div.shadowRoot.querySelector("svg");
            if (!svg) return null;
            const box = svg.getBoundingClientRect();
            return {
                left: box.left, right: box.right, width: box.width, height: box.height,
                natural: svg.viewBox.baseVal.width, text: svg.textContent,
            };
        }),
    };
}
"""


def labels(source: str) -> list[str]:
    """The text of each quoted node and edge label of a Mermaid flowchart, as shown."""
    body = re.sub(r"\A---\n.*?^---\n", "", source, flags=re.M | re.S)  # not the front matter
    found = re.findall(r'"([^"]+)"', body)
    return [html.unescape(re.sub(r"<[^>]+>", " ", t).replace("#quot;", '"')) for t in found]


def squeezed(text: str) -> str:
    return "".join(text.split())


def test_the_docs_have_diagrams_and_no_ascii_art_left() -> None:
    assert {"architecture.html", "guides/simulation-loop.html"} <= DIAGRAMS.keys()
    assert all(labels(source) for sources in DIAGRAMS.values() for source in sources)
    # boxes and arrows drawn with characters, or a block marked as a diagram in plain text
    ascii_art = re.compile(
        r"^\s*\+-{3,}\+|-{3,}>|<-{3,}|<!-- test: skip: a diagram[^\n]*-->\n```(?!mermaid\n)", re.M
    )
    pages = [ROOT / "README.md", *DOCS.rglob("*.md")]
    drawn = [p.name for p in pages if ascii_art.search(MERMAID_BLOCK.sub("", p.read_text()))]
    assert drawn == [], "ASCII diagrams overflow the site's content column: draw them in Mermaid"


def test_without_npm_nor_a_cached_copy_the_build_says_how_to_provide_mermaid(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mkdocs.exceptions import PluginError

    hook = load_module(HOOK)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("PATH", str(tmp_path))  # no npm on it
    with pytest.raises(PluginError) as info:
        hook.script()
    assert str(info.value) == (
        "the docs' diagrams need Mermaid's script, which the site serves itself; npm is not "
        "installed to fetch it: install npm (Debian: apt-get install npm), or put "
        f"dist/mermaid.min.js of the npm package mermaid@{hook.VERSION} (SHA-256 {hook.SHA256}) "
        f"at {tmp_path / 'evclock' / f'mermaid-{hook.VERSION}.min.js'}"
    )


def test_a_cached_copy_that_is_not_the_pinned_one_is_not_served(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mkdocs.exceptions import PluginError

    hook = load_module(HOOK)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("PATH", str(tmp_path))
    cached = hook.cached_script()
    cached.parent.mkdir(parents=True)
    cached.write_text("window.mermaid = 'not mermaid';")
    with pytest.raises(PluginError, match="npm is not installed to fetch it"):
        hook.script()  # refetched, not served


# ------------------------------------------------------------------------- in the browser


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:
        pass


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The site, built from this checkout and served on a free localhost port: its URL."""
    out = tmp_path_factory.mktemp("site")
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert build.returncode == 0, build.stderr[-4000:]
    handler = functools.partial(_QuietHandler, directory=str(out))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not CHROMIUM.exists():
        pytest.skip(
            "the diagrams' browser test needs Debian's chromium at /usr/bin/chromium "
            "(apt-get install chromium; .ci/run installs it)"
        )
    pytest.importorskip("playwright", reason="needs playwright (evclock[test])")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS
        )
        try:
            yield launched
        finally:
            launched.close()


@pytest.mark.parametrize("viewport", sorted(VIEWPORTS))
@pytest.mark.parametrize("path", sorted(DIAGRAMS))
def test_every_diagram_renders_and_fits_the_content_column(
    browser: Any, site: str, path: str, viewport: str
) -> None:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    width, height = VIEWPORTS[viewport]
    sources = DIAGRAMS[path]
    page = browser.new_page(viewport={"width": width, "height": height})
    try:
        page.set_default_timeout(TIMEOUT_MS)
        page.add_init_script(OPEN_SHADOW_ROOTS)
        requested: list[str] = []
        errors: list[str] = []
        page.on("request", lambda request: requested.append(request.url))
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(site + path)
        # Material replaces each <pre class="mermaid"> by a <div class="mermaid"> holding the
        # SVG once Mermaid drew it; a diagram Mermaid cannot draw stays a <pre>.
        try:
            page.wait_for_function(
                "n => document.querySelectorAll('div.mermaid').length === n"
                " && !document.querySelector('pre.mermaid')",
                arg=len(sources),
            )
        except PlaywrightTimeout:
            pytest.fail(f"{path}: not every diagram was drawn; JavaScript errors: {errors}")
        seen = page.evaluate(MEASURE)
    finally:
        page.close()
    assert errors == [], f"JavaScript errors on {path}: {errors}"
    assert [url for url in requested if not url.startswith(site)] == []  # no CDN
    assert seen["scrollWidth"] <= seen["clientWidth"], f"{path} scrolls sideways at {width} px"
    left, right = seen["column"]
    for source, drawn in zip(sources, seen["diagrams"], strict=True):
        assert drawn is not None, f"{path}: a diagram has no SVG"
        assert drawn["height"] > 0
        assert drawn["left"] >= left - 0.5, f"{path}: a diagram starts left of the column"
        assert drawn["right"] <= right + 0.5, f"{path}: a diagram ends right of the column"
        text = squeezed(drawn["text"])
        missing = [label for label in labels(source) if squeezed(label) not in text]
        assert missing == [], f"{path}: labels not drawn: {missing}"
        if viewport == "desktop":
            assert drawn["width"] >= LEGIBLE_SCALE * drawn["natural"], (
                f"{path}: a diagram {drawn['natural']:.0f} px wide is shrunk to "
                f"{drawn['width']:.0f} px to fit the column: draw it narrower"
            )
