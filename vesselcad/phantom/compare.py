"""Scores of a reconstruction against the phantom's ground truth (the metrics of ARCHITECTURE.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage

from ..errors import ArgumentError
from ..metrics import distance_to_polyline
from ..splines import resample_by_arclength

__all__ = ["compare_with_truth"]


def compare_with_truth(rec: Any, case: Any, within_mm: float = 1.0, step_mm: float = 0.5) -> dict[str, Any]:
    """3D centreline error and coverage of a :class:`vesselcad.pipeline.Reconstruction`.

    The truth is run A's tree at the chosen frame of run A (its cardiac and
    respiratory phase). Error: distance of every reconstructed sample (every
    ``step_mm``) to the nearest true centreline; coverage: share of the true
    tree's length (all vessels, visible or not) within ``within_mm`` of the
    reconstruction. Both are exact distances to the other side's polylines
    (ARCHITECTURE.md: "to the ground-truth curve"), not to its samples: a point
    on the curve between two samples ``step_mm`` apart would otherwise count up
    to ``step_mm / 2`` off (a quarter of that on average).

    Returns
    -------
    dict
        ``mean_mm``, ``p95_mm``, ``max_mm``, ``coverage``, ``truth_length_mm``,
        ``phase_difference`` (true cardiac and respiratory difference of the pair,
        in cycles), ``ostium_mm`` (distance of the matched roots of the two views,
        triangulated, from the true ostium; NaN when the roots were not paired),
        ``visible`` (share of the true tree's length that the label masks of both
        chosen frames show: the coverage any reconstruction from them can reach).
    """
    fa, fb = rec.phase.frame_a, rec.phase.frame_b
    truth = case.run_a.trees[fa]
    tpts = np.vstack([resample_by_arclength(np.asarray(b["points"], float), step_mm)
                      for b in truth["branches"]])
    d = np.abs(case.run_a.phases[fa] - case.run_b.phases[fb]) % 1.0
    d = np.minimum(d, 1.0 - d)
    out: dict[str, Any] = {"truth_length_mm": round(float(step_mm * (len(tpts) - len(truth["branches"]))), 2),
                           "phase_difference": {"cardiac": round(float(d[0]), 4),
                                                "respiratory": round(float(d[1]), 4)},
                           "visible": round(visible_share(case, fa, fb), 4)}
    # The ostium: the matched root landmarks of the two views, triangulated.
    root = rec.match.root_pair
    ostium = np.asarray(truth["branches"][0]["points"][0], float)
    out["ostium_mm"] = (float("nan") if root is None
                        else round(float(np.linalg.norm(np.asarray(root.point_mm) - ostium)), 4))
    ok = [b for b in rec.branches if b.ok]
    if not ok:
        return {**out, "mean_mm": float("nan"), "p95_mm": float("nan"), "max_mm": float("nan"),
                "coverage": 0.0}
    pts = np.vstack([b.points_mm for b in ok])
    err = np.min([distance_to_polyline(pts, np.asarray(b["points"], float))
                  for b in truth["branches"] if len(b["points"])], axis=0)
    cov = np.min([distance_to_polyline(tpts, b.points_mm) for b in ok], axis=0)
    return {**out, "mean_mm": round(float(err.mean()), 4), "p95_mm": round(float(np.percentile(err, 95)), 4),
            "max_mm": round(float(err.max()), 4), "coverage": round(float(np.mean(cov <= within_mm)), 4)}


def visible_share(case: Any, frame_a: int, frame_b: int, max_gap_px: float = 1.5) -> float:
    """Share of run A's true tree at ``frame_a`` (by length) that both chosen frames show.

    A true centreline point counts as shown in a view when its projection lies
    inside the image within ``max_gap_px`` of that frame's vessel label; in
    run B the same point of the tree is taken at ``frame_b`` (the vessels move
    between the frames). No reconstruction from these two frames can cover
    more of the tree.
    """
    from .case import LABELS

    for name, fr, run in (("frame_a", frame_a, case.run_a), ("frame_b", frame_b, case.run_b)):
        n = len(run.labels)
        if isinstance(fr, bool) or not isinstance(fr, int | np.integer) or not 0 <= fr < n:
            raise ArgumentError(f"visible_share: {name} must be a frame index 0..{n - 1}, got {fr!r}")
    if not (isinstance(max_gap_px, int | float) and np.isfinite(max_gap_px) and max_gap_px >= 0):
        raise ArgumentError(f"visible_share: max_gap_px must be a number >= 0, got {max_gap_px!r}")
    shown = []
    for run, fr in ((case.run_a, frame_a), (case.run_b, frame_b)):
        v = run.view
        gap = ndimage.distance_transform_edt(run.labels[fr] != LABELS["vessel"])
        per = []
        for b in run.trees[fr]["branches"]:
            q = v.project(np.asarray(b["points"], float))
            inside = (q[:, 0] >= 0) & (q[:, 0] <= v.cols - 1) & (q[:, 1] >= 0) & (q[:, 1] <= v.rows - 1)
            ij = np.clip(np.round(q).astype(int), 0, [v.cols - 1, v.rows - 1])
            per.append(inside & (gap[ij[:, 1], ij[:, 0]] <= max_gap_px))
        shown.append(per)
    total = both = 0.0
    for k, b in enumerate(case.run_a.trees[frame_a]["branches"]):
        p = np.asarray(b["points"], float)
        if len(p) < 2 or len(shown[1][k]) != len(p):
            continue
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        ok = shown[0][k] & shown[1][k]
        total += float(seg.sum())
        both += float(seg[ok[:-1] & ok[1:]].sum())
    return both / total if total > 0 else 0.0
