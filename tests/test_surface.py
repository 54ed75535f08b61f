"""The robust quadric through a tree's 3D points (vesselcad.surface), against analytic ellipsoids."""

from __future__ import annotations

import numpy as np
import pytest

import vesselcad as vc
from vesselcad.surface import fit_quadric_surface, semi_axes

AXES = np.array([55.0, 42.0, 40.0])


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


def _ellipsoid_points(rng, n, theta_max=np.pi):
    """Points of the ellipsoid AXES (rotated, moved) whose polar angle is below theta_max."""
    th = np.arccos(rng.uniform(np.cos(theta_max), 1.0, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    u = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return u * AXES


def _normal(p):
    g = p / AXES**2
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def test_recovers_a_partly_seen_ellipsoid_despite_outliers():
    # A cap of an ellipsoid (the third of the heart one coronary tree covers), a quarter of the
    # points moved 5-15 mm along the normal (wrong pairs at the wrong depth), the whole turned and
    # moved: the fit must put the cap's points on it, flag the moved ones and measure their offset.
    rng = np.random.default_rng(3)
    R, t = _rotation(rng), np.array([10.0, -250.0, 40.0])
    p = _ellipsoid_points(rng, 800, theta_max=1.1)
    h = np.zeros(len(p))
    bad = rng.random(len(p)) < 0.25
    h[bad] = rng.uniform(5, 15, bad.sum()) * rng.choice([-1, 1], bad.sum())
    q = p + h[:, None] * _normal(p)
    s = fit_quadric_surface(q @ R.T + t)
    assert s is not None
    d = s.distance(q @ R.T + t)
    assert np.max(d[~bad]) < 0.01
    assert s.sigma_mm < 0.01
    assert s.inliers == pytest.approx(np.mean(~bad), abs=0.01)
    # First-order distance: within h^2 / R (R >= 29 mm, the smallest curvature radius here).
    assert np.all(np.abs(d[bad] - np.abs(h[bad])) < h[bad] ** 2 / 29.0 + 0.01)


def test_noisy_points_give_their_noise_as_spread():
    rng = np.random.default_rng(4)
    p = _ellipsoid_points(rng, 3000)
    q = p + rng.normal(0, 0.5, len(p))[:, None] * _normal(p)
    s = fit_quadric_surface(q)
    # |N(0, 0.5)| has median 0.337 mm, and 1.4826 times that is 0.5 mm.
    assert s.sigma_mm == pytest.approx(0.5, rel=0.1)
    assert s.distance(np.array([[0.0, 0.0, 40.0]]))[0] < 0.1


def test_too_few_or_degenerate_points_give_none():
    rng = np.random.default_rng(5)
    assert fit_quadric_surface(_ellipsoid_points(rng, 40)) is None
    line = np.outer(np.linspace(0, 50, 200), [1.0, 2.0, 0.5])
    assert fit_quadric_surface(line) is None
    with_nan = _ellipsoid_points(rng, 100)
    with_nan[:50] = np.nan
    assert fit_quadric_surface(with_nan) is None  # 50 finite points, fewer than 60


def test_bad_input_is_rejected():
    with pytest.raises(vc.ArgumentError, match="points"):
        fit_quadric_surface(np.zeros((10, 2)))
    with pytest.raises(vc.ArgumentError, match="min_points"):
        fit_quadric_surface(np.zeros((100, 3)), min_points=3)
    s = fit_quadric_surface(_ellipsoid_points(np.random.default_rng(6), 200))
    with pytest.raises(vc.ArgumentError, match="points"):
        s.distance(np.zeros((4, 2)))
    with pytest.raises(vc.ArgumentError, match="q"):
        semi_axes(np.zeros(6), 1.0)
    with pytest.raises(vc.ArgumentError, match="scale"):
        semi_axes(s.coefficients, 0.0)


def test_semi_axes_of_the_fit_are_the_ellipsoids():
    rng = np.random.default_rng(7)
    R = _rotation(rng)
    s = fit_quadric_surface(_ellipsoid_points(rng, 500, theta_max=1.5) @ R.T + 30.0)
    np.testing.assert_allclose(semi_axes(s.coefficients, s.scale), np.sort(AXES), rtol=1e-6)


def test_a_flat_patch_is_no_heart():
    # Points on a plane are fitted only by ellipsoids far larger than a heart (or none at all).
    rng = np.random.default_rng(8)
    p = np.c_[rng.uniform(-40, 40, (300, 2)), rng.normal(0, 0.2, 300)]
    assert fit_quadric_surface(p) is None


def test_rays_meet_a_sphere_where_geometry_says():
    from vesselcad.surface import QuadricSurface

    # sphere of radius 50 mm about (10, 0, 0): u = (x - c) / 25, q = (25/50)^2 |u|^2 = 1
    s = QuadricSurface(coefficients=np.array([0.25, 0.25, 0.25, 0, 0, 0, 0, 0, 0], float),
                       centre=np.array([10.0, 0.0, 0.0]), scale=25.0, sigma_mm=0.1, inliers=1.0)
    origins = np.array([[10.0, 0.0, -200.0], [10.0, 30.0, -200.0], [10.0, 80.0, -200.0]])
    dirs = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t = s.intersect_rays(origins, dirs, near=np.array([0.0, 1000.0, 150.0]))
    # first ray (direction of length 2): crossings at z = -50, +50, nearest t = 0 is z = -50: t = 75
    assert t[0] == pytest.approx(75.0)
    # second: |y| = 30, crossings at z = +-40; nearest t = 1000 is z = +40: t = 240
    assert t[1] == pytest.approx(240.0)
    assert np.isnan(t[2])  # |y| = 80 > 50: misses
    with pytest.raises(vc.ArgumentError, match="origins, directions, near"):
        s.intersect_rays(origins, dirs[:2], near=np.zeros(3))
