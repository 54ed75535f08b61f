"""Epipolar structure of a view pair: the common epipolar angle, conditioning, ordered correspondence.

Every epipolar plane contains both X-ray sources. The angle ``theta`` of that
plane about the baseline is therefore a coordinate that both views share: a
3D point, its pixel in view A and its pixel in view B all have the same
``theta``. Two 2D curves of one branch correspond where their ``theta`` agree.
Where a curve's tangent runs along its epipolar line, ``theta`` is stationary
and the correspondence (hence the depth) is ill-conditioned; the sine of that
angle is the conditioning used throughout.

Pure numpy; the geometric core (:mod:`vesselcad.centreline3d`) builds on it.
"""

from __future__ import annotations

import numpy as np
from scipy import interpolate

from . import _dp
from .errors import ArgumentError
from .geometry import CArmView, check_view

__all__ = ["EpipolarPair", "ordered_correspondence"]


class EpipolarPair:
    """Epipolar geometry of two views.

    Parameters
    ----------
    view_a, view_b : CArmView

    Raises
    ------
    ArgumentError
        If the two views have the same source position (no baseline).
    """

    def __init__(self, view_a: CArmView, view_b: CArmView) -> None:
        check_view(view_a, "view_a")
        check_view(view_b, "view_b")
        self.view_a, self.view_b = view_a, view_b
        sa, sb = view_a.source, view_b.source
        base = sb - sa
        length = float(np.linalg.norm(base))
        if length < 1e-3:
            raise ArgumentError(
                "view_a, view_b: identical source positions; two different C-arm angles are needed"
            )
        self.origin = sa
        self.axis = base / length
        # Reference direction: from the baseline toward the isocentre.
        to_iso = -sa - (-sa @ self.axis) * self.axis
        if np.linalg.norm(to_iso) < 1e-6:  # opposite views: any perpendicular will do
            to_iso = np.cross(self.axis, [0.0, 0.0, 1.0])
            if np.linalg.norm(to_iso) < 1e-6:
                to_iso = np.cross(self.axis, [1.0, 0.0, 0.0])
        self.m = to_iso / np.linalg.norm(to_iso)
        self.n = np.cross(self.axis, self.m)

    def theta(self, points_mm: np.ndarray) -> np.ndarray:
        """Epipolar angle (radians) of 3D points, shape (...)."""
        rel = np.asarray(points_mm, dtype=float) - self.origin
        return np.arctan2(rel @ self.n, rel @ self.m)

    def theta_px(self, view: CArmView, points_px: np.ndarray) -> np.ndarray:
        """Epipolar angle of pixels of ``view`` (one of the pair), shape (...)."""
        return self.theta(view.pixel_to_detector(points_px))

    def theta_per_px(self, view: CArmView, points_px: np.ndarray) -> float:
        """Median magnitude of the gradient of ``theta`` in pixel space along the points."""
        p = np.asarray(points_px, dtype=float)
        t0 = self.theta_px(view, p)
        gx = self.theta_px(view, p + [1.0, 0.0]) - t0
        gy = self.theta_px(view, p + [0.0, 1.0]) - t0
        return float(np.median(np.hypot(gx, gy)))

    def conditioning(self, view: CArmView, points_px: np.ndarray, tangents_px: np.ndarray) -> np.ndarray:
        """Sine of the angle between a curve's tangent and its epipolar line, shape (n,).

        Parameters
        ----------
        view : CArmView
            The view the curve lies in.
        points_px, tangents_px : numpy.ndarray, shape (n, 2)
            Curve points and tangent vectors (any length) in pixels.
        """
        dr, dc = view.pixel_spacing_mm
        t3 = (tangents_px[:, :1] * dc) * view.col_axis + (tangents_px[:, 1:2] * dr) * view.row_axis
        t3 /= np.maximum(np.linalg.norm(t3, axis=1, keepdims=True), 1e-300)
        x = view.pixel_to_detector(points_px)
        normal = np.cross(self.axis, x - self.origin)  # normal of the epipolar plane through x
        d = view.detector_direction
        normal -= (normal @ d)[:, None] * d  # its component in the detector plane
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return np.abs(np.einsum("ij,ij->i", t3, normal))


def ordered_correspondence(theta_a: np.ndarray, theta_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monotone alignment of two sequences of epipolar angles (dynamic time warping).

    Finds the path from ``(0, 0)`` to ``(n_a - 1, n_b - 1)`` with steps
    (1, 0), (0, 1), (1, 1) that minimizes the summed ``|theta_a[i] - theta_b[j]|``:
    the ordering constraint of epipolar matching, solved globally.

    Parameters
    ----------
    theta_a, theta_b : numpy.ndarray, shape (n_a,), (n_b,)

    Returns
    -------
    i, j : numpy.ndarray of int
        The path, from the start to the end of both curves.
    """
    ta = np.asarray(theta_a, dtype=float)
    tb = np.asarray(theta_b, dtype=float)
    na, nb = len(ta), len(tb)
    cost = np.abs(ta[:, None] - tb[None, :])
    D = np.empty((na, nb))
    D[0] = np.cumsum(cost[0])
    for i in range(1, na):
        # Diagonal or vertical step into each cell, then the horizontal chain in
        # closed form: D[i, j] = C_j + min_{k <= j} (A_k - C_k).
        prev = D[i - 1]
        best = prev.copy()
        best[1:] = np.minimum(prev[1:], prev[:-1])
        a = cost[i] + best
        c = np.cumsum(cost[i])
        D[i] = c + np.minimum.accumulate(a - c)
    return backtrack(D)


def backtrack(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monotone path of an accumulated-cost matrix from (0, 0) to its last cell.

    Walks back from the last cell, each time to the cheapest of the diagonal,
    upper and left neighbours (the first of equals), along the first row and
    column straight to (0, 0); compiled (:mod:`vesselcad._dp`).
    """
    if D.ndim != 2 or 0 in D.shape:
        raise ArgumentError(f"D: expected a non-empty 2D array, got shape {D.shape}")
    return _dp.backtrack(np.ascontiguousarray(D, dtype=float))


def sample_curve(spline: interpolate.BSpline, step_px: float, max_samples: int = 100000
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parameters, points and unit tangents of a 2D spline every ``step_px`` of parameter."""
    a, b = float(spline.t[spline.k]), float(spline.t[-spline.k - 1])
    n = int(np.clip(np.ceil((b - a) / step_px) + 1, 8, max_samples))
    u = np.linspace(a, b, n)
    pts = spline(u)
    tan = spline.derivative()(u)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-300)
    return u, pts, tan
