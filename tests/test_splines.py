"""Splines (vesselcad.splines) and pipe frames, against analytic curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vesselcad.errors import ArgumentError
from vesselcad.splines import PIXEL_NOISE_PX, arc_length, fit_curve_2d, fit_pspline, resample_by_arclength

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


def _rasterized_arc() -> tuple[np.ndarray, float, np.ndarray]:
    """An arc of radius 80 px rounded to pixel centres and resampled along them (as a skeleton piece)."""
    th = np.linspace(0.2, 1.6, 4000)
    pix = np.round(np.stack([200 + 80 * np.cos(th), 200 + 80 * np.sin(th)], axis=1))
    pix = pix[np.r_[True, np.any(np.diff(pix, axis=0) != 0, axis=1)]]
    return resample_by_arclength(pix, 0.9), 80.0, np.array([200.0, 200.0])


def test_pixel_quantization_floor_smooths_the_staircase_onto_the_curve():
    pts, radius, centre = _rasterized_arc()
    raw = np.linalg.norm(pts - centre, axis=1) - radius
    assert 0.2 < np.sqrt(np.mean(raw**2)) < 0.35  # the pixels' own error: about 1/sqrt(12) px
    off = {}
    for floor in (0.01, PIXEL_NOISE_PX):
        spline, sigma = fit_curve_2d(pts, min_noise_px=floor)
        u = np.linspace(spline.t[3], spline.t[-4], 3000)[100:-100]  # the ends rest on their end pixels
        off[floor] = np.linalg.norm(spline(u) - centre, axis=1) - radius
        assert sigma >= floor
    # The estimate alone (fourth differences) sees little of the steps and the fit follows them;
    # floored at the quantization's 1/sqrt(12) px it lies on the true arc within a fifth of that.
    assert np.sqrt(np.mean(off[0.01] ** 2)) > 0.1
    assert np.sqrt(np.mean(off[PIXEL_NOISE_PX] ** 2)) < 0.06
    assert np.abs(off[PIXEL_NOISE_PX]).max() < 0.2
    # A given noise is used as given, the floor only bounds the estimate.
    assert fit_curve_2d(pts, noise_px=0.05, min_noise_px=PIXEL_NOISE_PX)[1] == pytest.approx(0.05)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), "x", None])
def test_bad_noise_floor_is_rejected(bad):
    with pytest.raises(ArgumentError, match="min_noise_px"):
        fit_curve_2d(np.array([[0.0, 0.0], [5.0, 1.0], [10.0, 3.0], [15.0, 6.0], [20.0, 10.0]]),
                     min_noise_px=bad)


def test_straight_line_fit_is_the_line():
    x = np.linspace(10.0, 90.0, 81)
    pts = np.column_stack([x, 0.5 * x + 3.0])
    spline, _ = fit_curve_2d(pts)
    v = spline(np.linspace(spline.t[3], spline.t[-4], 500))
    assert np.abs(v[:, 1] - (0.5 * v[:, 0] + 3.0)).max() < 1e-6
    assert np.allclose(v[[0, -1]], pts[[0, -1]], atol=0.05)  # a smoothing fit, ends within noise


def _dense_pspline(x, y, knot_step, lam, domain):
    """The P-spline's penalized least squares written out densely (numpy's lstsq)."""
    from scipy.interpolate import BSpline

    a, b = domain
    n_int = max(int(np.ceil((b - a) / knot_step)) - 1, 0)
    t = np.r_[[a] * 4, np.linspace(a, b, n_int + 2)[1:-1], [b] * 4]
    n_c = len(t) - 4
    basis = BSpline.design_matrix(x, t, 3).toarray()
    diff2 = np.diff(np.eye(n_c), 2, axis=0)
    rows = [basis, np.sqrt(lam * len(x) / n_c) * diff2, 1e-6 * np.eye(n_c)]
    c = np.linalg.lstsq(np.vstack(rows), np.vstack([y, np.zeros((len(rows[1]) + n_c, y.shape[1]))]),
                        rcond=None)[0]
    return BSpline(t, c, 3)


def test_pspline_reproduces_a_cubic_without_penalty():
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.0, 40.0, 300))
    cubic = np.stack([0.002 * x**3 - 0.1 * x**2 + x - 4.0, 2.0 - 0.5 * x], axis=1)
    spl = fit_pspline(x, cubic, knot_step=2.5, lam=0.0, domain=(0.0, 40.0))
    u = np.linspace(0.0, 40.0, 500)
    truth = np.stack([0.002 * u**3 - 0.1 * u**2 + u - 4.0, 2.0 - 0.5 * u], axis=1)
    assert np.abs(spl(u) - truth).max() < 1e-8


@pytest.mark.parametrize("lam", [1e-6, 1e-3, 1.0])
def test_pspline_is_the_penalized_least_squares_fit(lam):
    rng = np.random.default_rng(5)
    # noisy samples with a 20 mm stretch without data: the penalty carries the fit across
    x = np.r_[np.sort(rng.uniform(0.0, 10.0, 80)), np.sort(rng.uniform(30.0, 40.0, 80))]
    y = np.stack([np.sin(x / 6.0), 0.1 * x], axis=1) + rng.normal(scale=0.05, size=(len(x), 2))
    spl = fit_pspline(x, y, knot_step=1.5, lam=lam, domain=(0.0, 40.0))
    ref = _dense_pspline(x, y, 1.5, lam, (0.0, 40.0))
    u = np.linspace(0.0, 40.0, 401)
    assert np.abs(spl(u) - ref(u)).max() < 1e-6 * max(1.0, np.abs(ref(u)).max())
    one = fit_pspline(x, y[:, 0], knot_step=1.5, lam=lam, domain=(0.0, 40.0))  # 1-D values
    assert one.c.shape == (spl.c.shape[0], 1)
    assert np.allclose(one(u)[:, 0], spl(u)[:, 0])
    with pytest.raises(ArgumentError):
        fit_pspline(np.ones(5), np.ones((5, 2)), knot_step=1.0, lam=0.0)


def test_rotation_minimizing_normals_turn_against_the_torsion_of_a_helix():
    from vesselcad.kernel.pipes import rotation_minimizing_normals

    a, c = 6.0, 2.0  # helix radius and pitch / 2 pi (mm)
    speed = np.hypot(a, c)
    s = np.linspace(0.0, 80.0, 3201)  # arc length
    phi = s / speed
    pts = np.stack([a * np.cos(phi), a * np.sin(phi), c * phi], axis=1)
    tan = np.stack([-a * np.sin(phi), a * np.cos(phi), np.full_like(phi, c)], axis=1) / speed
    frenet_n = np.stack([-np.cos(phi), -np.sin(phi), np.zeros_like(phi)], axis=1)
    frenet_b = np.cross(tan, frenet_n)
    nrm = rotation_minimizing_normals(pts, tan)
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0)
    assert np.abs(np.einsum("ij,ij->i", nrm, tan)).max() < 1e-12
    # a rotation-minimizing frame turns relative to Frenet's at minus the torsion
    angle = np.unwrap(np.arctan2(np.einsum("ij,ij->i", nrm, frenet_b), np.einsum("ij,ij->i", nrm, frenet_n)))
    torsion = c / speed**2
    slope = np.polyfit(s, angle, 1)[0]
    assert slope == pytest.approx(-torsion, rel=1e-4)
    assert np.abs(angle - (angle[0] - torsion * s)).max() < 1e-4


def test_rotation_minimizing_normals_keep_the_frame_over_a_repeated_point():
    from vesselcad.kernel.pipes import rotation_minimizing_normals

    # a planar arc: the frame's normal starts in the plane (radial) and turns with the
    # tangent, a repeated sample or not
    phi = np.linspace(0.0, 2.0, 200)
    pts = np.stack([10 * np.cos(phi), 10 * np.sin(phi), np.zeros_like(phi)], axis=1)
    tan = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=1)
    pts = np.insert(pts, 100, pts[99], axis=0)
    tan = np.insert(tan, 100, tan[99], axis=0)
    nrm = rotation_minimizing_normals(pts, tan)
    radial = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    assert np.abs(nrm - np.insert(radial, 100, radial[99], axis=0)).max() < 1e-9
    one = rotation_minimizing_normals(pts[:1], tan[:1])
    assert one.shape == (1, 3) and abs(one[0] @ tan[0]) < 1e-12
