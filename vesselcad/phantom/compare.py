"""Scores of a reconstruction against the phantom's ground truth (the metrics of ARCHITECTURE.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage

from ..errors import ArgumentError
from ..metrics import distance_to_polyline
from ..splines import resample_by_arclength

__all__ = ["compare_with_truth", "error_anatomy"]


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


def error_anatomy(rec: Any, case: Any, off_mm: float = 3.0, missed_mm: float = 5.0,
                  step_mm: float = 0.5) -> dict[str, float]:
    """Where a reconstruction's 3D error and its missing length lie, against the phantom's truth.

    The truth is that of :func:`compare_with_truth` (run A's tree at the chosen
    frame of run A). Two questions the mean error and the coverage do not
    answer:

    - how much of the error sits on branches that are *off* the truth, whose
      median distance to it exceeds ``off_mm`` (two different vessels paired,
      as a rule), and what the mean would be without them;
    - where the true length lies that no reconstructed branch comes within
      ``missed_mm`` of (not merely inaccurate but *missed*): each true
      branch's missed runs are counted as ``distal`` (running to the
      branch's end: a pair that stopped short), ``proximal`` (from its start),
      ``inside`` (neither end: a gap) or ``whole`` (the entire branch).

    Parameters
    ----------
    rec : Reconstruction
        Needs ``phase.frame_a`` and ``branches`` (``ok``, ``points_mm``).
    case : PhantomCase
    off_mm : float
        Median distance to the truth above which a branch counts as off.
    missed_mm : float
        Distance from every reconstructed branch above which a true sample counts as missed.
    step_mm : float
        Sampling step along both the reconstruction and the truth.

    Returns
    -------
    dict
        ``off_samples`` and ``off_error``: the off branches' share of the
        reconstructed samples and of their summed error; ``mean_mm_without_off``
        (NaN when every branch is off); ``missed``: share of the true length
        missed, and ``missed_distal``, ``missed_proximal``, ``missed_inside``,
        ``missed_whole``: its parts as shares of the whole true length. With no
        reconstructed branch, everything is missed (``missed_whole`` = 1).
    """
    for name, v in (("off_mm", off_mm), ("missed_mm", missed_mm), ("step_mm", step_mm)):
        if isinstance(v, bool) or not isinstance(v, int | float) or not (np.isfinite(v) and v > 0):
            raise ArgumentError(f"error_anatomy: {name} must be a number > 0, got {v!r}")
    truth = [np.asarray(b["points"], float) for b in case.run_a.trees[rec.phase.frame_a]["branches"]]
    truth = [t for t in truth if len(t) > 1]
    samples = [resample_by_arclength(t, step_mm) for t in truth]
    total = sum(len(s) for s in samples)
    ok = [b.points_mm for b in rec.branches if b.ok and b.points_mm is not None and len(b.points_mm) > 1]
    out = {"off_samples": 0.0, "off_error": 0.0, "mean_mm_without_off": float("nan")}
    if not ok:
        return {**out, "missed": 1.0, "missed_distal": 0.0, "missed_proximal": 0.0, "missed_inside": 0.0,
                "missed_whole": 1.0}
    # error of every reconstructed sample, per branch
    errs = [np.min([distance_to_polyline(resample_by_arclength(p, step_mm), t) for t in truth], axis=0)
            for p in ok]
    off = np.array([np.median(e) > off_mm for e in errs])
    n = np.array([len(e) for e in errs], float)
    s = np.array([e.sum() for e in errs])
    out["off_samples"] = round(float(n[off].sum() / n.sum()), 4)
    out["off_error"] = round(float(s[off].sum() / max(s.sum(), 1e-12)), 4)
    if (~off).any():
        out["mean_mm_without_off"] = round(float(s[~off].sum() / n[~off].sum()), 4)
    parts = {"distal": 0, "proximal": 0, "inside": 0, "whole": 0}
    for q in samples:
        far = np.min([distance_to_polyline(q, p) for p in ok], axis=0) > missed_mm
        if far.all():
            parts["whole"] += len(q)
            continue
        # runs of missed samples: starts and ends of the True stretches
        edge = np.diff(np.r_[0, far.astype(np.int8), 0])
        starts, ends = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
        for a, b in zip(starts, ends, strict=True):
            key = "proximal" if a == 0 else "distal" if b == len(q) else "inside"
            parts[key] += int(b - a)
    out.update({f"missed_{k}": round(v / total, 4) for k, v in parts.items()})
    out["missed"] = round(sum(parts.values()) / total, 4)
    return out


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
