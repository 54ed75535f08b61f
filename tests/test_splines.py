"""2D branch splines (vesselcad.splines.fit_curve_2d)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vesselcad.splines import arc_length, fit_curve_2d

DATA = Path(__file__).parent / "data"


def test_pixel_staircase_fit_stays_on_the_points():
    # A skeleton piece (45 degree staircase ending in a vertical run) whose noise estimate is tiny:
    # FITPACK's near-interpolating fit oscillated to 1e5 px between its last knots without an error flag.
    pts = np.loadtxt(DATA / "staircase_branch_px.csv", delimiter=",")
    spline, _ = fit_curve_2d(pts)
    u = np.linspace(spline.t[3], spline.t[-4], 2000)
    v = spline(u)
    assert np.all(np.isfinite(v))
    # Every curve point lies within 2 px of the polyline, and the curve is about as long as it.
    seg_a, seg_b = pts[:-1], pts[1:]
    ab = seg_b - seg_a
    t = np.clip(np.einsum("mij,ij->mi", v[:, None] - seg_a[None], ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
    d = np.linalg.norm(v[:, None] - seg_a[None] - t[..., None] * ab[None], axis=-1).min(axis=1)
    assert d.max() < 2.0
    assert abs(arc_length(v)[-1] - arc_length(pts)[-1]) < 0.05 * arc_length(pts)[-1]


def test_straight_line_fit_is_the_line():
    x = np.linspace(10.0, 90.0, 81)
    pts = np.column_stack([x, 0.5 * x + 3.0])
    spline, _ = fit_curve_2d(pts)
    v = spline(np.linspace(spline.t[3], spline.t[-4], 500))
    assert np.abs(v[:, 1] - (0.5 * v[:, 0] + 3.0)).max() < 1e-6
    assert np.allclose(v[[0, -1]], pts[[0, -1]], atol=0.05)  # a smoothing fit, ends within noise
