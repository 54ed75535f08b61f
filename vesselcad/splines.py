"""Cubic B-spline fits of centrelines: 2D branch curves in pixels, 3D curves in mm.

Pure numpy/scipy. The 2D fit smooths by the pixel noise it estimates from the
points themselves (fourth differences, which cancel the curve's own shape up to
cubic terms), so exact projections stay exact and skeleton pixels are smoothed.
The 3D fit is a penalized least-squares B-spline (P-spline) over a given
parameter, which also bridges gaps in the data smoothly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import interpolate, linalg, ndimage

from .errors import ArgumentError

__all__ = ["estimate_noise_px", "fit_curve_2d", "fit_pspline", "arc_length", "resample_by_arclength",
           "PIXEL_NOISE_PX"]

#: Floor of the estimated noise: below this a fit is as exact as the data need
#: (4 µm at the isocentre for 0.27 mm pixels) and the knot count stays small.
MIN_NOISE_PX = 0.01
#: Noise of points that are pixel centres of a skeleton (or were resampled along
#: one): the true centreline lies anywhere in the pixel, a uniform error of
#: standard deviation 1/sqrt(12) px per coordinate. The fourth differences see
#: far less on a pixel staircase (a straight run of pixels has none, the steps
#: are rare and regular), and a fit smoothed by that estimate follows the steps.
PIXEL_NOISE_PX = float(1.0 / np.sqrt(12.0))


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative chord length along ordered points, starting at 0, shape (n,)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample_by_arclength(points: np.ndarray, step: float) -> np.ndarray:
    """Ordered points resampled at (about) equal chord length ``step``."""
    s = arc_length(points)
    n = max(int(np.ceil(s[-1] / step)) + 1, 2)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, k]) for k in range(points.shape[1])], axis=1)


def estimate_noise_px(points: np.ndarray) -> float:
    """Per-coordinate noise sigma of densely sampled curve points.

    Uses the median absolute fourth difference of points resampled at 1-unit
    spacing: for white noise of sigma s the fourth difference has standard
    deviation ``sqrt(70) * s``, while a smooth curve contributes almost nothing.

    Parameters
    ----------
    points : numpy.ndarray, shape (n, d)

    Returns
    -------
    float
        The noise estimate, at least ``MIN_NOISE_PX``.
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) < 6:
        return MIN_NOISE_PX
    d4 = np.diff(pts, n=4, axis=0).ravel()
    mad = float(np.median(np.abs(d4 - np.median(d4))))
    return max(1.4826 * mad / np.sqrt(70.0), MIN_NOISE_PX)


def _dedupe(points: np.ndarray) -> np.ndarray:
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9])
    return points[keep]


def fit_curve_2d(points_px: Any, noise_px: float | None = None, name: str = "points_px",
                 min_noise_px: float = MIN_NOISE_PX) -> tuple[interpolate.BSpline, float]:
    """Fit a clamped cubic B-spline to an ordered 2D polyline.

    The curve is parametrized by chord length in pixels (parameter 0 at the
    first point) and smoothed so that the residual matches the pixel noise.

    Parameters
    ----------
    points_px : array_like, shape (n, 2)
        Ordered ``(col, row)`` points, ``n >= 2``.
    noise_px : float, optional
        Noise sigma per coordinate; estimated from the points when omitted.
    name : str
        Argument name used in error messages.
    min_noise_px : float
        Floor under the estimated noise (not under a given ``noise_px``):
        :data:`PIXEL_NOISE_PX` for skeleton pixels, whose quantization the
        estimate misses; the default keeps exact projections (nearly) exact.

    Returns
    -------
    spline : scipy.interpolate.BSpline
        Vector-valued spline, ``spline(u)`` has shape (..., 2).
    noise_px : float
        The noise sigma used.
    """
    if isinstance(points_px, interpolate.BSpline):
        spl = points_px
        if np.asarray(spl.c).ndim != 2 or np.asarray(spl.c).shape[1] != 2:
            raise ArgumentError(f"{name}: a BSpline must be vector-valued with 2 components")
        return spl, 0.0
    try:
        pts = np.asarray(points_px, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ArgumentError(f"{name}: expected an (n, 2) array of (col, row) pixels ({exc})") from None
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ArgumentError(f"{name}: expected an (n, 2) array of (col, row) pixels, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ArgumentError(f"{name}: contains non-finite values")
    pts = _dedupe(pts)
    if len(pts) < 2:
        raise ArgumentError(f"{name}: a branch needs at least 2 distinct points, got {len(pts)}")
    try:
        floor = float(min_noise_px)
    except (TypeError, ValueError):
        floor = float("nan")
    if not (np.isfinite(floor) and floor >= 0):
        raise ArgumentError(f"min_noise_px: expected a finite value >= 0, got {min_noise_px!r}")
    sigma = (max(estimate_noise_px(pts), floor) if noise_px is None
             else max(float(noise_px), MIN_NOISE_PX))
    # Parametrize by the chord length of a lightly smoothed copy, so that noisy
    # points do not inflate the parameter: it stays close to the arc length in px.
    smooth = ndimage.gaussian_filter1d(pts, sigma=min(2.0, len(pts) / 6.0), axis=0, mode="nearest")
    smooth[0], smooth[-1] = pts[0], pts[-1]
    u = arc_length(smooth)
    keep = np.concatenate([[True], np.diff(u) > 1e-9])
    pts, u = pts[keep], u[keep]
    if len(pts) < 2:
        raise ArgumentError(f"{name}: a branch needs at least 2 distinct points")
    if len(pts) < 4:
        # Too few points for a cubic: an exact cubic through a densified polyline.
        dense = resample_by_arclength(pts, max(u[-1] / 8.0, 1e-6))
        u = arc_length(dense)
        spl = interpolate.make_interp_spline(u, dense, k=3)
        return spl, sigma
    s = len(pts) * 2.0 * sigma**2
    # FITPACK can return (with no error flag) a nearly interpolating fit that
    # oscillates wildly between dense knots (seen on pixel staircases with a
    # tiny noise estimate): such a fit leaves the points' bounding box, and a
    # larger smoothing is tried instead.
    lo, hi = pts.min(axis=0) - (2.0 + 4.0 * sigma), pts.max(axis=0) + (2.0 + 4.0 * sigma)
    uu = np.linspace(u[0], u[-1], 4 * len(u))
    for _ in range(12):
        tck, _ = interpolate.splprep(pts.T, u=u, k=3, s=s, quiet=2)
        t, c, k = tck
        spl = interpolate.BSpline(np.asarray(t), np.stack(c, axis=1), k)
        v = spl(uu)
        if np.all(np.isfinite(v)) and np.all(v >= lo) and np.all(v <= hi):
            break
        s = max(2.0 * s, 0.01 * len(pts))
    return spl, sigma


def fit_pspline(param: np.ndarray, values: np.ndarray, knot_step: float, lam: float,
                domain: tuple[float, float] | None = None) -> interpolate.BSpline:
    """Penalized least-squares cubic B-spline (P-spline) of vector data.

    Parameters
    ----------
    param : numpy.ndarray, shape (n,)
        Parameter of each sample (need not be sorted or unique).
    values : numpy.ndarray, shape (n, d)
        Sample values.
    knot_step : float
        Spacing of the uniform interior knots, in parameter units.
    lam : float
        Weight of the squared second differences of the control points,
        relative to the data term (0 gives a plain least-squares fit; a small
        positive value keeps knot spans without data well defined).
    domain : (float, float), optional
        Parameter range of the spline; defaults to the data range.

    Returns
    -------
    scipy.interpolate.BSpline
    """
    x = np.asarray(param, dtype=float)
    y = np.asarray(values, dtype=float)
    a, b = (float(x.min()), float(x.max())) if domain is None else domain
    if b <= a:
        raise ArgumentError("fit_pspline: the parameter range is empty")
    n_int = max(int(np.ceil((b - a) / knot_step)) - 1, 0)
    inner = np.linspace(a, b, n_int + 2)[1:-1]
    k = 3
    t = np.concatenate([[a] * (k + 1), inner, [b] * (k + 1)])
    n_c = len(t) - k - 1
    y2 = y.reshape(len(x), -1)
    # The normal equations are banded (k super- and sub-diagonals): assemble the
    # bands from the design matrix's k + 1 entries per row and solve them banded
    # (2-3x faster than sparse matrices at the sizes the trees use).
    B = interpolate.BSpline.design_matrix(np.clip(x, a, b), t, k).tocsr()
    B.sort_indices()  # each row holds the k + 1 basis functions that do not vanish there
    col = B.indices.reshape(-1, k + 1)
    val = B.data.reshape(-1, k + 1)
    upper = np.zeros((k + 1, n_c))  # upper[o, i] = lhs[i, i + o]
    for o in range(k + 1):
        for q in range(k + 1 - o):
            upper[o] += np.bincount(col[:, q], val[:, q] * val[:, q + o], minlength=n_c)
    if n_c > 2 and lam > 0:
        d = np.array([1.0, -2.0, 1.0])
        rows = np.arange(n_c - 2)
        w = lam * max(len(x), 1) / n_c
        for o in range(3):
            for q in range(3 - o):
                upper[o] += w * d[q] * d[q + o] * np.bincount(rows + q, minlength=n_c)
    upper[0] += 1e-12
    ab = np.zeros((2 * k + 1, n_c))  # general banded form: ab[k + i - j, j] = lhs[i, j]
    for o in range(k + 1):
        ab[k - o, o:] = upper[o, : n_c - o]
        ab[k + o, : n_c - o] = upper[o, : n_c - o]
    rhs = np.stack([sum(np.bincount(col[:, q], val[:, q] * y2[:, j], minlength=n_c) for q in range(k + 1))
                    for j in range(y2.shape[1])], axis=1)
    c = linalg.solve_banded((k, k), ab, rhs, check_finite=False)
    return interpolate.BSpline(t, np.asarray(c).reshape(n_c, -1), k)

