"""report.html as a person sees it: real headless Chromium, network off, no console errors,
overlays loaded, the 3D view drawn (its pixels show the vessel and the centrelines)."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
from browser import chromium_path, visit_report
from matplotlib.image import imread

from vesselcad.phantom import generate_case, write_case
from vesselcad.pipeline import reconstruct

_REQUIRED = os.environ.get("VESSELCAD_REQUIRE_BROWSER") == "1"  # .ci/run sets it: no silent skip in CI


def _need_browser() -> None:
    missing = []
    try:
        import playwright  # noqa: F401
    except ImportError:
        missing.append("the playwright package")
    if chromium_path() is None:
        missing.append("Chromium (apt-get install chromium)")
    if missing:
        if _REQUIRED:
            pytest.fail("browser test required but missing " + " and ".join(missing))
        pytest.skip("needs " + " and ".join(missing))


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    _need_browser()
    out = tmp_path_factory.mktemp("report")
    case = generate_case(3, "rca", 8, rows=256, cols=256)
    paths = write_case(case, out / "input")
    rec = reconstruct(paths["run_a"], paths["run_b"], labels=(case.run_a.labels, case.run_b.labels))
    assert rec.solid is not None and rec.ok_branches
    rec.write(out)
    return out


def test_report_renders_offline_without_errors(report_dir, tmp_path):
    canvas_png = tmp_path / "canvas.png"
    v = visit_report(report_dir / "report.html", canvas_png=canvas_png, page_png=tmp_path / "page.png")
    assert v.rendered, (v.status, v.console)
    assert v.errors == [] and v.failed == []
    # self-contained: the only thing loaded from anywhere is the page itself
    assert [u for u in v.requests if not u.startswith("data:")] == [(report_dir / "report.html").as_uri()]
    imgs = {i["id"]: i for i in v.images}
    for name in ("overlay", "phase"):
        png = imread(report_dir / f"{name}.png")
        assert imgs[name]["complete"] and (imgs[name]["height"], imgs[name]["width"]) == png.shape[:2]
    m = re.match(r"(\d+) vertices, (\d+) triangles", v.status)
    assert m and int(m.group(2)) > 100
    # The drawn canvas: the solid's shaded red and the blue centrelines on white.
    px = (imread(canvas_png)[..., :3] * 255).astype(int)
    r, g, b = px[..., 0], px[..., 1], px[..., 2]
    red = (r > 90) & (r > 2 * g) & (r > 2 * b)
    blue = (b > 150) & (b > 2 * r)
    assert red.mean() > 0.005, red.mean()
    assert blue.sum() > 20
    rows, cols = np.nonzero(red)
    # the model is framed: centred on the canvas, not cut off at its edges
    assert 0.2 < rows.mean() / px.shape[0] < 0.8 and 0.2 < cols.mean() / px.shape[1] < 0.8


def test_broken_report_is_caught(report_dir, tmp_path):
    # The check can fail: a page whose mesh data is damaged must show up as a page error.
    html = (report_dir / "report.html").read_text()
    bad = re.sub(r'(<script[^>]*id="mesh-vertices"[^>]*>)[^<]*', r"\1###", html, count=1)
    assert bad != html
    page = tmp_path / "report.html"
    page.write_text(bad)
    v = visit_report(page, timeout_ms=3000)
    assert not v.rendered and any("pageerror" in e for e in v.errors)
