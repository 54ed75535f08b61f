"""Scores of a reconstruction against the phantom's ground truth (the metrics of ARCHITECTURE.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..splines import resample_by_arclength

__all__ = ["compare_with_truth"]


def compare_with_truth(rec: Any, case: Any, within_mm: float = 1.0, step_mm: float = 0.5) -> dict[str, Any]:
    """3D centreline error and coverage of a :class:`vesselcad.pipeline.Reconstruction`.

    The truth is run A's tree at the chosen frame of run A (its cardiac and
    respiratory phase). Error: distance of every reconstructed sample (every
    ``step_mm``) to the nearest true centreline; coverage: share of the true
    tree's length (all vessels, visible or not) within ``within_mm`` of the
    reconstruction.

    Returns
    -------
    dict
        ``mean_mm``, ``p95_mm``, ``max_mm``, ``coverage``, ``truth_length_mm``,
        ``phase_difference`` (true cardiac and respiratory difference of the pair,
        in cycles), ``ostium_mm`` (distance of the matched roots of the two views,
        triangulated, from the true ostium; NaN when the roots were not paired).
    """
    fa, fb = rec.phase.frame_a, rec.phase.frame_b
    truth = case.run_a.trees[fa]
    tpts = np.vstack([resample_by_arclength(np.asarray(b["points"], float), step_mm)
                      for b in truth["branches"]])
    d = np.abs(case.run_a.phases[fa] - case.run_b.phases[fb]) % 1.0
    d = np.minimum(d, 1.0 - d)
    out: dict[str, Any] = {"truth_length_mm": round(float(step_mm * (len(tpts) - len(truth["branches"]))), 2),
                           "phase_difference": {"cardiac": round(float(d[0]), 4),
                                                "respiratory": round(float(d[1]), 4)}}
    # The ostium: the matched root landmarks of the two views, triangulated.
    roots = tuple(rec.match.roots)
    root = next((m for m in rec.match.landmark_pairs if (m.a, m.b) == roots), None)
    ostium = np.asarray(truth["branches"][0]["points"][0], float)
    out["ostium_mm"] = (float("nan") if root is None
                        else round(float(np.linalg.norm(np.asarray(root.point_mm) - ostium)), 4))
    ok = [b for b in rec.branches if b.ok]
    if not ok:
        return {**out, "mean_mm": float("nan"), "p95_mm": float("nan"), "max_mm": float("nan"),
                "coverage": 0.0}
    pts = np.vstack([b.points_mm for b in ok])
    err, _ = cKDTree(tpts).query(pts)
    cov, _ = cKDTree(pts).query(tpts)
    return {**out, "mean_mm": round(float(err.mean()), 4), "p95_mm": round(float(np.percentile(err, 95)), 4),
            "max_mm": round(float(err.max()), 4), "coverage": round(float(np.mean(cov <= within_mm)), 4)}
