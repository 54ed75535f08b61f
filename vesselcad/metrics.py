"""Error measures of reconstructed centrelines, exactly as ARCHITECTURE.md defines them.

- Reprojection error of a 3D centreline in one view: samples every 0.5 mm
  along the 3D curve, projected; 2D distance to the nearest point of that
  view's 2D centreline (the polyline, not just its vertices).
- 3D centreline error (phantom): distance from samples of the reconstructed
  curve to the ground-truth curve; coverage = share of the ground-truth length
  within 1 mm of the reconstruction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .errors import ArgumentError
from .geometry import CArmView, as_points
from .splines import resample_by_arclength

__all__ = ["ReprojectionError", "CentrelineError", "reprojection_error", "centreline_error",
           "distance_to_polyline"]


def _densify(poly: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points at most ``step`` apart along a polyline, and the segment each lies on."""
    seg = np.diff(poly, axis=0)
    n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / step).astype(int), 1)
    owner = np.repeat(np.arange(len(seg)), n)
    first = np.repeat(np.cumsum(n) - n, n)
    t = (np.arange(len(owner)) - first) / n[owner]
    dense = np.vstack([poly[owner] + t[:, None] * seg[owner], poly[-1:]])
    return dense, np.append(owner, len(seg) - 1)


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Exact distance from each point to an ordered polyline (any dimension), shape (n,).

    Candidate segments come from a k-d tree of the densified polyline, then the
    point-to-segment distance is computed exactly for each candidate.
    """
    pts = np.asarray(points, dtype=float)
    poly = np.asarray(polyline, dtype=float)
    if len(poly) == 1:
        return np.linalg.norm(pts - poly[0], axis=-1)
    seg_len = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    dense, owner = _densify(poly, max(float(np.median(seg_len)), 1e-9))
    _, idx = cKDTree(dense).query(pts, k=min(4, len(dense)))
    idx = np.atleast_2d(idx.T).T if idx.ndim == 1 else idx
    cand = np.concatenate([owner[idx] - 1, owner[idx], owner[idx] + 1], axis=1)
    cand = np.clip(cand, 0, len(poly) - 2)
    a, b = poly[cand], poly[cand + 1]
    ab = b - a
    t = np.clip(np.einsum("nkd,nkd->nk", pts[:, None] - a, ab) / np.maximum(
        np.einsum("nkd,nkd->nk", ab, ab), 1e-300), 0.0, 1.0)
    d = np.linalg.norm(pts[:, None] - (a + t[..., None] * ab), axis=-1)
    return d.min(axis=1)


@dataclass(frozen=True)
class ReprojectionError:
    """Reprojection error of a 3D centreline in one or two views.

    ``px``/``mm`` hold the per-sample distances (mm at the isocentre plane),
    concatenated over the views; the summary fields are over all of them.
    """

    px: np.ndarray
    mm: np.ndarray

    @property
    def mean_px(self) -> float:
        return float(self.px.mean())

    @property
    def sd_px(self) -> float:
        return float(self.px.std())

    @property
    def max_px(self) -> float:
        return float(self.px.max())

    @property
    def mean_mm(self) -> float:
        return float(self.mm.mean())

    @property
    def sd_mm(self) -> float:
        return float(self.mm.std())

    @property
    def max_mm(self) -> float:
        return float(self.mm.max())

    def to_dict(self) -> dict[str, float]:
        return {"mean_px": self.mean_px, "sd_px": self.sd_px, "max_px": self.max_px,
                "mean_mm": self.mean_mm, "sd_mm": self.sd_mm, "max_mm": self.max_mm}


def _samples(curve: Any, step_mm: float) -> np.ndarray:
    if hasattr(curve, "sample_every"):
        return curve.sample_every(step_mm)
    pts = as_points(curve, 3, "curve")
    if pts.ndim != 2 or len(pts) < 2:
        raise ArgumentError("curve: expected a Centreline3D or an (n, 3) polyline with n >= 2")
    return resample_by_arclength(pts, step_mm)


def reprojection_error(curve: Any, views: CArmView | list[CArmView],
                       centrelines_px: Any, step_mm: float = 0.5) -> ReprojectionError:
    """Reprojection error of a 3D centreline against 2D centrelines.

    Parameters
    ----------
    curve : Centreline3D or array_like, shape (n, 3)
        The 3D centreline (a polyline is resampled every ``step_mm``).
    views : CArmView or list of CArmView
        One view, or both views of the pair.
    centrelines_px : array_like (n, 2), or a list of them (one per view)
        Each view's 2D centreline as an ordered polyline in pixels.
    step_mm : float
        Sampling step along the 3D curve (0.5 mm by the contract).

    Returns
    -------
    ReprojectionError
        Distances in px and in mm at the isocentre, over all views.
    """
    if isinstance(views, CArmView):
        views, centrelines_px = [views], [centrelines_px]
    if len(views) != len(centrelines_px):
        raise ArgumentError("views, centrelines_px: expected one 2D centreline per view")
    pts = _samples(curve, step_mm)
    px, mm = [], []
    for view, line in zip(views, centrelines_px, strict=True):
        poly = as_points(line, 2, "centrelines_px")
        proj = view.project(pts)
        d = distance_to_polyline(proj, poly)
        px.append(d)
        mr, mc = view.mm_per_px
        mm.append(d * 0.5 * (mr + mc))
    return ReprojectionError(px=np.concatenate(px), mm=np.concatenate(mm))


@dataclass(frozen=True)
class CentrelineError:
    """3D error of a reconstructed centreline against the ground truth (mm)."""

    mean_mm: float
    max_mm: float
    p95_mm: float
    coverage: float
    distances_mm: np.ndarray

    def to_dict(self) -> dict[str, float]:
        return {"mean_mm": self.mean_mm, "max_mm": self.max_mm, "p95_mm": self.p95_mm,
                "coverage": self.coverage}


def centreline_error(curve: Any, truth_mm: Any, step_mm: float = 0.5, within_mm: float = 1.0
                     ) -> CentrelineError:
    """Distance of a reconstructed centreline to the true one, and the truth's coverage.

    Parameters
    ----------
    curve : Centreline3D or array_like, shape (n, 3)
    truth_mm : array_like, shape (m, 3)
        Ordered ground-truth polyline.
    step_mm : float
        Sampling step along both curves.
    within_mm : float
        A truth sample counts as covered if the reconstruction passes within this distance.
    """
    pts = _samples(curve, step_mm)
    truth = as_points(truth_mm, 3, "truth_mm")
    d = distance_to_polyline(pts, truth)
    tsamp = _samples(truth, step_mm)
    cov = distance_to_polyline(tsamp, pts) <= within_mm
    return CentrelineError(mean_mm=float(d.mean()), max_mm=float(d.max()),
                           p95_mm=float(np.percentile(d, 95)), coverage=float(cov.mean()),
                           distances_mm=d)
