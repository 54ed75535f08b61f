"""Open a page in a real headless Chromium (system package) with the network off, as a person would.

Used by tests/test_report_browser.py and docs/make_figures.py (the report screenshot).
Needs the ``playwright`` Python package (dev extra; its bundled browsers are not used)
and Chromium from the system packages (``apt-get install chromium``).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

# As root in a container, without GPU; background networking off because the machine has no
# network and Chromium's own connections would otherwise be refused, noisily. SwiftShader is
# Chromium's software GL, which WebGL needs without a GPU.
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]


def chromium_path() -> str | None:
    """The system Chromium, or None."""
    for name in (os.environ.get("VESSELCAD_CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and (p := shutil.which(name)):
            return p
    return None


@dataclass
class PageVisit:
    console: list[tuple[str, str]] = field(default_factory=list)   # (type, text), errors as "pageerror"
    requests: list[str] = field(default_factory=list)              # every URL the page asked for
    failed: list[str] = field(default_factory=list)                # requests that failed
    images: list[dict] = field(default_factory=list)               # id, complete, naturalWidth/Height
    rendered: bool = False                                         # #view3d[data-rendered=true] appeared
    status: str = ""                                               # text of #view3d-status

    @property
    def errors(self) -> list[str]:
        return [f"{t}: {m}" for t, m in self.console if t in ("error", "pageerror")]


def visit_report(html: Path, canvas_png: Path | None = None, page_png: Path | None = None,
                 timeout_ms: int = 20000) -> PageVisit:
    """Load report.html from disk offline, wait for the 3D view, collect what went wrong."""
    from playwright.sync_api import TimeoutError as PwTimeout
    from playwright.sync_api import sync_playwright

    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError("no Chromium on PATH (apt-get install chromium)")
    visit = PageVisit()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_ARGS)
        try:
            ctx = browser.new_context(offline=True, viewport={"width": 1300, "height": 900})
            page = ctx.new_page()
            page.on("console", lambda m: visit.console.append((m.type, m.text)))
            page.on("pageerror", lambda e: visit.console.append(("pageerror", str(e))))
            page.on("request", lambda r: visit.requests.append(r.url))
            page.on("requestfailed", lambda r: visit.failed.append(r.url))
            page.goto(Path(html).resolve().as_uri(), wait_until="load")
            try:
                page.wait_for_selector("#view3d[data-rendered='true']", timeout=timeout_ms)
                visit.rendered = True
            except PwTimeout:
                visit.rendered = False
            visit.status = page.inner_text("#view3d-status") if page.query_selector("#view3d-status") else ""
            visit.images = page.evaluate(
                "[...document.images].map(i => ({id: i.id, complete: i.complete, "
                "width: i.naturalWidth, height: i.naturalHeight}))")
            if canvas_png is not None and page.query_selector("#view3d"):
                page.locator("#view3d").screenshot(path=str(canvas_png))
            if page_png is not None:
                page.screenshot(path=str(page_png), full_page=True)
        finally:
            browser.close()
    return visit
