"""The whole method on two runs: segmentation, phase, graphs, matching, 3D centrelines, tree, solid.

:func:`reconstruct` only chains the stages' public functions; each stage's
choices and numbers are kept on the returned :class:`Reconstruction` so that a
person (``report.html``) or a script (``report.json``) can see where a case
went wrong. One branch that cannot be reconstructed is reported with its
reason; the rest of the tree is still produced.

See docs/usage.md.
"""

from __future__ import annotations

import os
import time
import warnings as _warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .centreline2d import CentrelineGraph, centreline_graph
from .epipolar import EpipolarPair
from .errors import ArgumentError, VesselcadError, VesselcadWarning
from .geometry import CArmView
from .io import XARun, load_run
from .matching import BranchPair, GraphMatch, match_graphs
from .metrics import ReprojectionError, distance_to_polyline, reprojection_error
from .phase import DISAGREE_MM, OBJECTS, PREFER_FILL, PhaseMatch, match_phase
from .refine import Refinement, refine_geometry
from .segment import Segmenter
from .splines import resample_by_arclength
from .surface import semi_axes
from .tree import TreeBranch, VesselTree, _reattached

__all__ = ["BranchResult", "Reconstruction", "ReconstructionError", "reconstruct"]

#: Smallest radius written to the tree (mm): thinner vessels are below the resolution of the images.
MIN_RADIUS_MM = 0.3
#: Shortest 3D branch kept (mm).
MIN_LENGTH_MM = 1.0
#: A 3D branch whose reprojection onto its own 2D pieces is worse than this (mean px, or max px)
#: is not a consistent curve (a wrong match, or a span along the epipolar lines) and is left out.
MAX_REPROJECTION_MEAN_PX = 2.0
MAX_REPROJECTION_MAX_PX = 10.0
#: 3D points farther than this from the isocentre are outside the heart (the isocentre is set on
#: the heart; coronary trees span about +-60 mm around it) (mm).
MAX_RADIUS_FROM_ISOCENTRE_MM = 100.0
#: A 3D centreline's end is cut where it turns by more than HOOK_TURN_DEG degrees
#: between two 0.5 mm samples within HOOK_REACH_MM of it (``_without_hooks``).
HOOK_TURN_DEG = 60.0
HOOK_REACH_MM = 5.0
#: A branch without a parent whose start lies within this many pixels of another
#: branch's 2D piece in both views leaves that branch (see ``_link_parents``)...
JOIN_PX = 3.0
#: The point it leaves is the other branch's 3D point whose projections are nearest to
#: the start in both views, if within this many pixels (that branch's own depth can
#: be off near its ends).
JOIN_REPROJECTION_PX = 10.0
#: A linked branch whose 3D start lies outside its parent's lumen has it moved onto
#: the parent when it is at most this far (mm) from it (``_link_parents``).
MAX_JOIN_GAP_MM = 10.0
#: A moved start is brought back onto both images' vessels in this many rounds (0: not at all) ...
ON_VESSEL_ROUNDS = 3
#: ... of Gauss-Newton steps damped by this much (px² per mm²; the views give 20-50 where they
#: decide a direction, near 0 along the epipolar lines).
ON_VESSEL_DAMPING = 1.0
#: ... and ramped in over this length (mm) from the new start; not where a child would then
#: leave its parent's end at more than this angle (degrees from the parent's direction; its
#: first 2 mm) and more steeply than the shift alone made it.
ON_VESSEL_RAMP_MM = 2.0
ON_VESSEL_MAX_ANGLE_DEG = 120.0
#: A branch still without a parent whose 3D start lies at most ``MAX_JOIN_GAP_MM`` from another
#: branch is joined to it when, in both views, the skeleton runs from the start's projection to
#: that point's projection (each within ``JOIN_PX``) without a detour: along it no longer than
#: ``SKELETON_DETOUR`` times the straight line plus ``SKELETON_DETOUR_PX`` (``_joins_along_skeletons``).
#: None: not at all.
SKELETON_DETOUR: float | None = 1.3
SKELETON_DETOUR_PX = 5.0
#: Such a join reaches this far (mm) in 3D. A gap up to ``MAX_JOIN_GAP_MM`` closes by moving the
#: branch's start, as for the other links; a wider one is bridged: a new stretch of centreline
#: from where the parent's skeleton forks to the branch's start that follows the two skeleton
#: paths between them (``_bridge``), the branch's own points left where they are (a moved start
#: would bend up to half the branch). None: no bridges, joins up to ``MAX_JOIN_GAP_MM`` only.
#: docs/results.md (issue 13, 2026-12-05): 20 mm against 30 (worse 3D error) and moving instead.
MAX_BRIDGE_MM: float | None = 20.0
#: ... unless the bridge, brought onto the two paths, stays farther than this (px, mean) from
#: either: the paths are then not one vessel (one turns onto another vessel at a crossing),
#: and the branch stays apart.
BRIDGE_MAX_PX = 1.0
#: How the warning of a branch joined that way begins (the report's overlay marks its start).
JOINED_NOTE = "joined across"
#: Skeleton paths from the other branch to a branch's start that run, in both views, more than
#: this many pixels (their last ``JOIN_PX`` aside) within ``JOIN_PX`` of the branch's own 2D
#: piece walk back over the branch: the branch runs towards the other one, and joining its
#: start would fold the centreline back on itself (true labels rca 2104: a 14 mm bridge out
#: and the branch back along it, 0.05 mm apart). Such a branch is joined the other way
#: round, from its end, where paths from there qualify (its children keep their places on
#: it), else as before; None: not checked.
OWN_WALK_PX: float | None = 3.0 * JOIN_PX
#: ... and at least this share of the branch's 2D piece, in both views (a path that runs
#: over a few millimetres of the branch's start is a hook of its start, not a reversal).
OWN_WALK_SHARE = 0.5
#: A 3D branch whose points lie, by their median, farther from the heart's surface fitted by the
#: matching (``GraphMatch.surface``) than ``OFF_SURFACE_SIGMAS`` times that fit's spread, and at
#: least ``OFF_SURFACE_MIN_MM``, is left out (``reconstruct(off_surface_sigmas=...)``): a pairing of
#: two vessels that share a band of epipolar lines reprojects perfectly but lies inside or outside
#: the heart. Points within ``OFF_SURFACE_OSTIUM_MM`` of the ostium do not count (the proximal
#: vessel leaves the aorta, or the coronary sinus the right atrium, off that surface).
OFF_SURFACE_SIGMAS = 4.0
OFF_SURFACE_MIN_MM = 1.5
OFF_SURFACE_OSTIUM_MM = 25.0
#: Of a branch kept by that rule, the samples at either end of its 3D centreline that lie farther
#: from the surface than ``OFF_SURFACE_END_SIGMAS`` times the fit's spread (taken as at least
#: ``matching.SURFACE_SIGMA_MIN_MM``, as the matching does) are trimmed: a pair that starts or ends
#: on the wrong vessel (a one-ended pair run on past where its vessel ends in one view) leaves the
#: surface there, while its median stays on it. Points within ``OFF_SURFACE_OSTIUM_MM`` of the
#: ostium are never trimmed, nor a branch that would keep less than ``OFF_SURFACE_END_KEEP_MM``.
#: None: no trimming.
OFF_SURFACE_END_SIGMAS: float | None = 1.0
OFF_SURFACE_END_KEEP_MM = 2.0
#: Where a branch runs along the epipolar lines (its tangent within these angles, degrees, of
#: them in either view) two views barely fix its depth, and the depth along view A's rays is
#: taken from the heart's surface fitted by the matching instead: wholly below the first
#: angle, blended linearly up to the second (``_depth_from_surface``; docs/results.md, issue 13,
#: 2026-12-05: on 24 phantom cases, true labels, 1.316 -> 1.269 mm, coverage 43.6 -> 44.4 %) ...
SURFACE_DEPTH_DEG = (5.0, 10.0)
#: ... where the surface lies at most this far (mm) along the ray from the two views' point ...
SURFACE_DEPTH_MAX_MM = 5.0
#: ... and only from a surface the tree's own points follow to within this spread (mm; the
#: fit's ``sigma_mm``, 0.2-1.4 mm on the phantom): within 5 deg of the lines the views' depth
#: was 1.15 mm off (median), so a surface no closer than that to the vessels is no better.
SURFACE_DEPTH_MAX_SIGMA_MM = 1.5
#: ``reconstruct(tta=...)``: which frames are segmented with mirror test-time augmentation.
TTA_MODES = ("chosen", "all", "none")
#: Phase matching's weight of the vessels' epipolar consistency (mm per unit, ``match_phase``'s
#: ``vessel_weight``) when the labels come from the segmentation model: its catheter tips (the key
#: point) are 5 px or more off in most frames, so the vessels must count more than with true
#: labels (``match_phase``'s default of 10, used for labels given to ``reconstruct``); docs/phase.md.
MODEL_VESSEL_WEIGHT_MM = 30.0
#: ``reconstruct(frame_search=...)``: how many frames the model labels for the phase matching.
FRAME_SEARCH_MODES = ("all", "coarse")
#: The coarse-to-fine frame search (:class:`_FrameLabeller`) runs on runs of at least this many
#: frames at least ``COARSE_MIN_FPS`` frames per second; shorter or slower runs are labelled whole.
COARSE_MIN_FRAMES = 24
COARSE_MIN_FPS = 12.0
#: It first labels every ``COARSE_PROBE``-th frame, then every ``COARSE_STRIDE``-th frame within
#: ``COARSE_PROBE - 1`` frames of those whose vessel area is at least ``COARSE_KEEP`` of the
#: largest (the phase matching only chooses frames filled to 0.9 of the run's largest when it
#: can: ``match_phase``'s ``prefer_fill``), then the neighbours of the ``COARSE_TOP`` best pairs
#: and every frame within ``COARSE_REACH`` frames of the best one, until nothing is added.
#: A stride of 2 labelled 61 % instead of 76 % of the frames but chose another pair in 5 of 48
#: phantom cases (one of them 3.4 mm worse; docs/phase.md), so every frame near the filled
#: probes is labelled.
COARSE_PROBE = 4
COARSE_STRIDE = 1
COARSE_KEEP = 0.75
COARSE_TOP = 12
COARSE_REACH = 2
#: ``reconstruct(max_side=...)``: frames with more rows or columns than this are area averaged down
#: to it before anything else (``XARun.resampled``). The method's pixel parameters (skeleton
#: pruning, landmark and branch tolerances, the continuation's steps, the segmentation network's
#: training scales) are set for cine of 512 pixels a side at about 0.27 mm per pixel at the
#: isocentre. On 1024-pixel phantom runs of the same field, taken as they were, a case took
#: twice as long (the network at 768 px, every later stage on four times the pixels); with true
#: labels the trees lay farther from the truth (1.77 against 1.45 mm), with the model's they
#: fell outside what three noise draws of the 512-px runs gave, reduced they fell among them
#: (docs/results.md, 2026-12-06).
WORK_MAX_SIDE = 512


class ReconstructionError(VesselcadError, RuntimeError):
    """The runs cannot give a tree; the message says which stage stopped and why."""


@dataclass
class BranchResult:
    """One matched branch pair and what became of it.

    Attributes
    ----------
    id : int
        Branch id in the output tree (index in ``Reconstruction.branches``).
    pair : BranchPair
        The matched 2D pieces (view A, view B).
    points_mm, radius_mm : numpy.ndarray or None
        3D centreline samples every 0.5 mm and the radius there (None when it failed).
    reprojection : ReprojectionError or None
        Reprojection of the 3D centreline onto the pair's 2D pieces (both views).
    parent : int or None
        The branch it leaves from.
    status : str
        ``"ok"`` or the reason it is not in the tree.
    warnings : list of str
    """

    id: int
    pair: BranchPair
    points_mm: np.ndarray | None = None
    radius_mm: np.ndarray | None = None
    reprojection: ReprojectionError | None = None
    parent: int | None = None
    status: str = "ok"
    ill_conditioned: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self) -> dict[str, Any]:
        rp = self.reprojection
        return {
            "id": self.id, "graph_branches": [self.pair.a, self.pair.b], "parent": self.parent,
            "status": self.status,
            "length_mm": None if self.points_mm is None else round(_length(self.points_mm), 3),
            "reprojection_px": None if rp is None else {k: round(getattr(rp, f"{k}_px"), 4)
                                                        for k in ("mean", "sd", "max")},
            "reprojection_mm": None if rp is None else {k: round(getattr(rp, f"{k}_mm"), 4)
                                                        for k in ("mean", "sd", "max")},
            "match_error_px": round(self.pair.error_px, 4), "found_by": self.pair.found_by,
            "ill_conditioned": round(self.ill_conditioned, 4),
            "warnings": list(self.warnings),
        }


@dataclass
class Reconstruction:
    """Everything :func:`reconstruct` found, stage by stage.

    Attributes
    ----------
    tree : VesselTree or None
        The reconstructed centrelines with radii (LPS mm), None if no branch survived.
    solid : VesselSolid or None
        One fused OCCT solid of the tree (None if not asked for or if it failed; see warnings).
    phase : PhaseMatch
        The chosen frame pair and the phase error matrix.
    graphs : (CentrelineGraph, CentrelineGraph)
        2D centreline graphs of the chosen frames.
    match : GraphMatch
        Landmarks and branches paired across the views.
    branches : list of BranchResult
        One per branch pair, in tree-id order.
    views : (CArmView, CArmView)
        The geometry used for the tree (refined when ``refinement.applied``).
    header_views : (CArmView, CArmView)
        The geometry from the files (and overrides).
    refinement : Refinement or None
    frames : (numpy.ndarray, numpy.ndarray)
        The chosen frames (images).
    labels : (numpy.ndarray, numpy.ndarray)
        Segmentation labels of the chosen frames.
    errors : dict
        Reprojection error over all reconstructed branches (px and mm, both views).
    timings : dict of str to float
        Seconds per stage.
    warnings : list of str
    sources : (str, str)
        The runs' files (empty where the runs were given as arrays).
    segmentation : dict or None
        Where the labels came from: ``{"labels": "given"}``, or the model
        that made them (``model`` file name, its ``sha256``, ``layout``,
        ``tta``, ``frame_search``); report.json's ``segmentation``.
    """

    tree: VesselTree | None
    solid: Any
    phase: PhaseMatch
    graphs: tuple[CentrelineGraph, CentrelineGraph]
    match: GraphMatch
    branches: list[BranchResult]
    views: tuple[CArmView, CArmView]
    header_views: tuple[CArmView, CArmView]
    refinement: Refinement | None
    frames: tuple[np.ndarray, np.ndarray]
    labels: tuple[np.ndarray, np.ndarray]
    errors: dict[str, float]
    timings: dict[str, float]
    warnings: list[str] = field(default_factory=list)
    sources: tuple[str, str] = ("", "")
    segmentation: dict[str, Any] | None = None

    @property
    def ok_branches(self) -> list[BranchResult]:
        return [b for b in self.branches if b.ok]

    @property
    def solid_left_out(self) -> dict[int, str]:
        """The tree's branches the solid does not hold, with the reason (branch id -> why).

        The solid holds one tree; a branch of another tree, or one whose pipe or
        union failed, or that hangs from such a branch, is listed here with
        what :attr:`VesselSolid.failed` says of it (or of the merged vessel it
        is part of). A pipe that went into the union is held even where none of
        its surface is left (a short branch wholly inside other vessels). Empty
        when the solid holds every branch, and when there is no solid (see
        :attr:`solid_share`).
        """
        if self.solid is None or self.tree is None:
            return {}
        failed = self.solid.failed
        # every pipe that went into the union and was not given up: also one wholly inside other
        # vessels, of which no face is left (cs 2023, true labels: a 7 mm branch inside two others)
        held = set(self.solid.branch_ids)
        held |= {p.branch_id for p in self.solid.pipes if p.branch_id not in failed}
        out: dict[int, str] = {}
        placed: set[int] = set()
        specs = self.solid.specs or [{"id": b.id, "segments": (b.id,)} for b in self.tree]
        for spec in specs:
            members = spec.get("segments") or (spec["id"],)
            placed.update(members)
            if spec["id"] in held:
                continue
            why = failed.get(spec["id"], "not in the solid")
            for m in members:
                out[int(m)] = why if m == spec["id"] else (f"merged into branch {spec['id']}, which was "
                                                          f"left out: {why}")
        for b in self.tree:  # stubs left out before any pipe was made
            if b.id not in placed:
                out[b.id] = failed.get(b.id, "not in the solid")
        return out

    @property
    def solid_share(self) -> float | None:
        """Share of the tree's centreline length (0-1) that the solid holds; None without a solid."""
        if self.solid is None or self.tree is None:
            return None
        return self._share_held(self.solid_left_out)

    def _share_held(self, left_out: dict[int, str]) -> float:
        total = sum(b.length_mm for b in self.tree)
        kept = sum(b.length_mm for b in self.tree if b.id not in left_out)
        return float(kept / total) if total > 0 else 0.0

    def __repr__(self) -> str:
        n = len(self.ok_branches)
        e = self.errors
        nan = float("nan")
        return (f"Reconstruction(frames=({self.phase.frame_a}, {self.phase.frame_b}), "
                f"{n}/{len(self.branches)} branches, reprojection {e.get('mean_px', nan):.2f} px "
                f"({e.get('mean_mm', nan):.3f} mm), solid={'yes' if self.solid is not None else 'no'}, "
                f"{sum(self.timings.values()):.1f} s)")

    def report(self) -> dict[str, Any]:
        """The ``report.json`` object (docs/formats.md)."""
        ref = self.refinement
        views = {}
        for key, v, h in zip(("view_a", "view_b"), self.views, self.header_views, strict=True):
            views[key] = {"matrix": np.round(v.matrix, 8).tolist(), "refined": bool(ref is not None
                                                                                 and ref.applied),
                          "header": h.to_dict(), "used": v.to_dict()}
        solid = None
        left_out = self.solid_left_out
        if self.solid is not None:
            chk = self.solid.validity()
            solid = {"valid": bool(chk["valid"]), "watertight": bool(chk["watertight"]),
                     "solids": int(chk.get("solids", 1)), "volume_mm3": round(float(self.solid.volume), 3),
                     "failed": {str(k): v for k, v in self.solid.failed.items()},
                     "tree_share": round(self._share_held(left_out), 4) if self.tree is not None else 0.0}
        branches = []
        for b in self.branches:
            d = b.to_dict()
            # whether the solid (STEP/STL/GLB) holds the branch: null where there is no solid
            # or no 3D branch; the reason where it does not
            d["in_solid"] = None if self.solid is None or not b.ok else b.id not in left_out
            d["solid_note"] = left_out.get(b.id) if d["in_solid"] is False else None
            branches.append(d)
        phase = self.phase.to_dict()
        return {
            "vesselcad": _version(),
            "sources": list(self.sources),
            "segmentation": self.segmentation,
            "frame_a": int(self.phase.frame_a), "frame_b": int(self.phase.frame_b),
            "phase_error_mm": phase["error_mm"], "phase_error_px": phase["error_px"],
            "phase": phase,
            **views,
            "refinement": None if ref is None else ref.to_dict(),
            "graphs": {"a": _graph_summary(self.graphs[0]), "b": _graph_summary(self.graphs[1])},
            "ostium": self.ostium(),
            "matching": {"landmark_pairs": len(self.match.landmark_pairs),
                         "branch_pairs": len(self.match.pairs),
                         "unmatched": [{"kind": u.kind, "view": u.view, "index": u.index, "reason": u.reason,
                                        "range_px": u.range and [round(x, 2) for x in u.range]}
                                       for u in self.match.unmatched],
                         "surface": _surface_summary(self.match.surface)},
            "branches": branches,
            "reprojection": {k: round(v, 4) for k, v in self.errors.items()},
            "tree": None if self.tree is None else {"branches": len(self.tree),
                                                    "length_mm": round(self.tree.total_length_mm, 3)},
            "solid": solid,
            "warnings": list(self.warnings),
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
        }

    def ostium(self) -> dict[str, Any]:
        """The tree's start: each view's graph root (px) and, where the two were matched, the 3D point.

        Returns
        -------
        dict
            ``{'a_px', 'b_px', 'matched', 'point_mm', 'error_mm'}``; the 3D point and its
            reconstruction error are None when the two roots were not matched to each other.
        """
        roots = [g.landmarks[g.root].point_px if g.root is not None else None for g in self.graphs]
        pair = next((m for m in self.match.landmark_pairs
                     if (m.a, m.b) == (self.graphs[0].root, self.graphs[1].root)), None)
        return {"a_px": None if roots[0] is None else np.round(roots[0], 2).tolist(),
                "b_px": None if roots[1] is None else np.round(roots[1], 2).tolist(),
                "matched": pair is not None,
                "point_mm": None if pair is None else np.round(pair.point_mm, 3).tolist(),
                "error_mm": None if pair is None else round(float(pair.error_mm), 4)}

    def write(self, out: str | os.PathLike, *, html: bool = True, progress: bool = False) -> dict[str, Path]:
        """Write ``tree.step/.stl/.glb``, ``centrelines.json/.vtp``, ``overlay.png``, ``phase.png``
        and ``report.json/.html`` into ``out``.

        Every file is written atomically; files that need the solid are skipped (with a
        warning in the report) when there is none. The solid's volume (the STL's check,
        report.json) is integrated in the booleans' helper process while the pictures are
        drawn (docs/solids.md, step 6). Returns the paths written.
        """
        from .report import write_outputs

        return write_outputs(self, Path(out), html=html, progress=progress)


#: Views closer than this (angle between the viewing directions) cannot be reconstructed;
#: below ``_WEAK_DEG`` depth is poorly conditioned (the paper's pairs are >= 30 deg apart).
_MIN_VIEW_DEG, _WEAK_DEG = 15.0, 25.0


def _check_pair(ra: XARun, rb: XARun, warn: list[str]) -> None:
    """Stop early, with the reason, on pairs of runs that cannot give a tree."""
    va, vb = ra.view, rb.view
    cos = float(np.clip(np.dot(va.detector_direction, vb.detector_direction), -1.0, 1.0))
    angle = float(np.degrees(np.arccos(abs(cos))))
    same = ra.series_uid and ra.series_uid == rb.series_uid
    views = (f"run A ({va.primary_deg:+.1f} deg, {va.secondary_deg:+.1f} deg) and run B "
             f"({vb.primary_deg:+.1f} deg, {vb.secondary_deg:+.1f} deg)")
    if same and ra.frames.shape == rb.frames.shape and np.array_equal(ra.frames, rb.frames):
        raise ReconstructionError(f"runs: run A and run B are the same acquisition (SeriesInstanceUID "
                                  f"{ra.series_uid}); give two runs taken at two C-arm angles")
    if angle < _MIN_VIEW_DEG:
        raise ReconstructionError(
            f"views: {views} look along directions only {angle:.1f} deg apart; two-view reconstruction "
            f"needs C-arm angles at least {_MIN_VIEW_DEG:.0f} deg (better {_WEAK_DEG:.0f}+) apart. If the "
            "headers are wrong, give --geometry-a/-b")
    if angle < _WEAK_DEG:
        warn.append(f"views: {views} are only {angle:.1f} deg apart; depth along the shared direction is "
                    "poorly determined")
    if ra.patient_id and rb.patient_id and ra.patient_id != rb.patient_id:
        warn.append(f"runs: different PatientID in run A ({ra.patient_id!r}) and run B ({rb.patient_id!r})")


def _version() -> str:
    from . import __version__

    return __version__


_SHA256: dict[str, str] = {}


def _segmentation_summary(seg: Segmenter, tta: str, frame_search: str) -> dict[str, Any]:
    """Which model labelled the frames, and how (report.json's ``segmentation``)."""
    import hashlib

    path = getattr(seg, "path", None)
    digest = None
    if path is not None and Path(path).is_file():
        key = str(Path(path).resolve())
        if key not in _SHA256:
            _SHA256[key] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        digest = _SHA256[key]
    return {"labels": "model", "model": None if path is None else Path(path).name, "sha256": digest,
            "layout": getattr(seg, "layout", None), "tta": tta, "frame_search": frame_search}


def _surface_summary(surface: Any) -> dict[str, Any] | None:
    """The heart's surface the matching fitted (docs/centreline2d.md), for report.json."""
    if surface is None:
        return None
    axes = semi_axes(surface.coefficients, surface.scale)
    return {"semi_axes_mm": None if axes is None else [round(float(a), 2) for a in axes],
            "spread_mm": round(float(surface.sigma_mm), 3), "inliers": round(float(surface.inliers), 3)}


def _graph_summary(g: CentrelineGraph) -> dict[str, Any]:
    return {"branches": len(g.branches), "branch_points": int(len(g.branch_points)),
            "end_points": int(len(g.end_points)), "crossings": len(g.crossings),
            "length_px": round(float(g.total_length_px), 2)}


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _as_run(run: Any, geometry: Any, name: str) -> XARun:
    if isinstance(run, XARun):
        if geometry is None:
            return run
        view = geometry if isinstance(geometry, CArmView) else CArmView.from_dict(
            {**run.view.to_dict(), **dict(geometry)}, f"geometry_{name[-1]}")
        return replace(run, view=view)
    if isinstance(run, (str, os.PathLike)):
        if isinstance(geometry, CArmView):
            geometry = geometry.to_dict()
        return load_run(run, geometry=geometry)
    raise ArgumentError(f"{name}: expected an XARun or the path of a run, got {type(run).__name__}")


def _check_labels(labels: Any, run: XARun, name: str) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.shape != run.frames.shape or not np.issubdtype(arr.dtype, np.integer):
        raise ArgumentError(f"{name}: expected integer labels of shape {run.frames.shape} (one per frame of "
                            f"the run), got {arr.dtype} {arr.shape}")
    return arr.astype(np.uint8, copy=False)


def _resampled_labels(labels: np.ndarray, view: CArmView) -> np.ndarray:
    """Labels (N, H, W) reduced to the view's size: each pixel the class covering most of it.

    Ties go to the higher class (a vessel half inside a pixel keeps it), so a
    vessel keeps its width in mm; labels already at the view's size are returned as they are.
    """
    import cv2

    n, h, w = labels.shape
    if (h, w) == (view.rows, view.cols):
        return labels
    out = np.zeros((n, view.rows, view.cols), np.uint8)
    best = np.full(out.shape, -1.0, np.float32)
    for c in np.flatnonzero(np.bincount(labels.ravel(), minlength=1)):  # the classes present, rising
        share = np.stack([cv2.resize((f == c).astype(np.float32), (view.cols, view.rows),
                                     interpolation=cv2.INTER_AREA) for f in labels])
        take = share >= best - 1e-6  # classes come in rising order: ties to the higher one
        out[take], best[take] = c, share[take]
    return out


def _radius_along(points: np.ndarray, view: CArmView, pts_px: np.ndarray, rad_px: np.ndarray) -> np.ndarray:
    """Radius (mm, at each 3D point's own depth) from the 2D radius of the nearest 2D sample."""
    proj = view.project(points)
    _, idx = cKDTree(pts_px).query(np.nan_to_num(proj))
    spacing = float(np.mean(view.pixel_spacing_mm))
    return rad_px[idx] * spacing * view.depth(points) / view.sid_mm


def _branch_3d(k: int, pair: BranchPair, views: tuple[CArmView, CArmView], method: str) -> BranchResult:
    from .centreline3d import intersect_centrelines

    res = BranchResult(id=k, pair=pair)
    va, vb = views
    try:
        # The 2D fits are smoothed by the noise the pieces show, not floored at their pixel
        # quantization (``min_noise_px=PIXEL_NOISE_PX``: smoother and faster, but the steps
        # downstream were tuned on the zig-zagging curves; docs/results.md, issue 13, 2026-12-07).
        curve = intersect_centrelines(va, pair.points_a_px, vb, pair.points_b_px, method=method)
        pts = curve.sample_every(0.5)
    except VesselcadError as exc:
        res.status = f"3D centreline failed: {exc}"
        return res
    except Exception as exc:  # OCCT can fail on degenerate input; one branch never loses the rest
        res.status = f"3D centreline failed ({type(exc).__name__}): {exc}"
        return res
    pts, cut = _without_hooks(pts)
    if _length(pts) < MIN_LENGTH_MM:
        res.status = f"shorter than {MIN_LENGTH_MM} mm in 3D"
        return res
    if cut:
        res.warnings.append(cut)
    ra = _radius_along(pts, va, pair.points_a_px, pair.radius_a_px)
    rb = _radius_along(pts, vb, pair.points_b_px, pair.radius_b_px)
    r = ndimage.median_filter(0.5 * (ra + rb), size=min(9, len(pts) | 1), mode="nearest")
    res.points_mm = pts
    res.radius_mm = np.maximum(r, MIN_RADIUS_MM)
    rp = reprojection_error(pts, [va, vb], [pair.points_a_px, pair.points_b_px])
    # Ends that leave the 2D pieces (a skeleton bending into a junction) are trimmed, not fatal.
    per = np.maximum(distance_to_polyline(va.project(pts), pair.points_a_px),
                     distance_to_polyline(vb.project(pts), pair.points_b_px))
    good = np.flatnonzero(per <= MAX_REPROJECTION_MAX_PX)
    if len(good) >= 2 and (good[0] > 0 or good[-1] < len(pts) - 1):
        trimmed = 0.5 * (good[0] + len(pts) - 1 - good[-1])
        pts, ra, rb = (x[good[0]:good[-1] + 1] for x in (pts, ra, rb))
        res.points_mm, res.radius_mm = pts, res.radius_mm[good[0]:good[-1] + 1]
        res.warnings.append(f"ends trimmed by {trimmed:.1f} mm where they left the 2D centrelines")
        rp = reprojection_error(pts, [va, vb], [pair.points_a_px, pair.points_b_px])
    res.reprojection = rp
    res.ill_conditioned = float(curve.ill_conditioned_fraction)
    res.warnings = list(curve.warnings) + res.warnings
    far = float(np.max(np.linalg.norm(pts - 0.5 * (np.asarray(va.offset_mm) + np.asarray(vb.offset_mm)),
                                      axis=1)))
    if rp.mean_px > MAX_REPROJECTION_MEAN_PX or rp.max_px > MAX_REPROJECTION_MAX_PX:
        res.status = (f"rejected: reprojection {rp.mean_px:.2f} px mean, {rp.max_px:.2f} px max (limits "
                      f"{MAX_REPROJECTION_MEAN_PX}, {MAX_REPROJECTION_MAX_PX} px): the two 2D pieces are not "
                      "one consistent 3D curve (wrong match or a span along the epipolar lines)")
    elif far > MAX_RADIUS_FROM_ISOCENTRE_MM:
        res.status = (f"rejected: reaches {far:.0f} mm from the isocentre (limit "
                      f"{MAX_RADIUS_FROM_ISOCENTRE_MM:.0f} mm)")
    return res


def _without_hooks(pts: np.ndarray, reach_mm: float = HOOK_REACH_MM, max_turn_deg: float = HOOK_TURN_DEG
                   ) -> tuple[np.ndarray, str]:
    """``pts`` without a hook at either end, and a note of what was cut ('' if nothing).

    A turn sharper than ``max_turn_deg`` between consecutive samples (0.5 mm
    apart: a bend radius under ~0.5 mm, which no vessel has) within ``reach_mm``
    of an end is where a skeleton bent into a junction, or the bridge at a free
    end swung back: the end is cut there.
    """
    if len(pts) < 4:
        return pts, ""
    steps = np.diff(pts, axis=0)
    size = np.linalg.norm(steps, axis=1)
    unit = steps / np.maximum(size, 1e-12)[:, None]
    s = np.r_[0.0, np.cumsum(size)]
    sharp = np.flatnonzero((unit[1:] * unit[:-1]).sum(1) < np.cos(np.radians(max_turn_deg))) + 1
    head = sharp[s[sharp] <= reach_mm]
    tail = sharp[s[-1] - s[sharp] <= reach_mm]
    lo = int(head.max()) if head.size else 0
    hi = int(tail.min()) + 1 if tail.size else len(pts)
    if hi - lo < 2 or (lo == 0 and hi == len(pts)):
        return pts, ""
    return pts[lo:hi], (f"hooked ends cut ({s[lo]:.1f} mm at the start, {s[-1] - s[hi - 1]:.1f} mm at the "
                        f"end): turns sharper than {max_turn_deg:g} degrees within {reach_mm:g} mm of an end")


def _link_parents(results: list[BranchResult], views: tuple[CArmView, CArmView] | None = None,
                  adjust: Callable[[], None] | None = None,
                  graphs: tuple[CentrelineGraph, CentrelineGraph] | None = None,
                  roots: tuple[int | None, int | None] | None = None) -> None:
    """Parent of each branch: the branch whose end is its start landmark, else the nearest one.

    Candidate links (child start within 2 mm + 1.5 radii of another branch's
    centreline) are accepted cheapest first while they keep the forest acyclic.
    Given the views, a branch still without a parent whose start lies on another
    branch in both images (within :data:`JOIN_PX`) is joined to it there. Given the
    graphs too, a branch still without a parent is joined to another branch up to
    :data:`MAX_JOIN_GAP_MM` away in 3D where both views' skeletons run between the two
    without a detour (:func:`_joins_along_skeletons`: a stretch of vessel the matching
    did not pair, between two pieces it did), unless it starts at ``roots``, the
    matched root landmarks (the ostium stays the inlet of its tree). A child
    whose 3D start is then outside its parent's lumen (the two curves disagree in
    depth near the junction, where a vessel runs along the epipolar lines) has its
    start moved onto the parent, up to :data:`MAX_JOIN_GAP_MM`: the solid needs the
    child to start inside its parent; a parent whose own start was moved carries the
    children that met it along, however far. A child whose start lies farther from
    its parent (two branches that meet in both images but not in depth) stays linked
    where it is, and its warnings say so. ``adjust()``, if given, runs between choosing
    the parents (on the curves as they were) and moving the starts (onto the curves
    as it leaves them).
    """
    ok = [b for b in results if b.ok]
    if not ok:
        return
    trees = {b.id: cKDTree(b.points_mm) for b in ok}
    by_id = {b.id: b for b in ok}
    cand = []
    for c in ok:
        start = c.points_mm[0]
        for p in ok:
            if p.id == c.id:
                continue
            d, i = trees[p.id].query(start)
            tol = 2.0 + 1.5 * float(p.radius_mm[i])
            if c.pair.start == p.pair.end and None not in c.pair.start:
                d, i = 0.0, len(p.points_mm) - 1  # the junction is the parent's end
            elif d > tol:
                continue
            cand.append((float(d), c.id, p.id, int(i), ""))
    root = {b.id: b.id for b in ok}

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    links: dict[int, tuple[int, int, str]] = {}
    walks: dict[tuple[int, int], Any] = {}
    flips: set[tuple[int, int]] = set()  # joins that take the branch the other way round

    def accept(candidates: list[tuple[float, int, int, int, str]]) -> None:
        turned: set[int] = set()  # branches turned round in this batch (its indices are to them as were)
        for _cost, c, p, i, why in sorted(candidates):
            if c in links:
                continue
            rc, rp = find(c), find(p)
            if rc == rp:
                continue
            if p in turned:
                i = len(by_id[p].points_mm) - 1 - i
            root[rc] = rp
            links[c] = (p, i, why)
            by_id[c].parent = p
            if (c, p) in flips:
                _reverse(by_id[c], views)
                turned.add(c)
                n = len(by_id[c].points_mm)
                for x, (q, j, w) in list(links.items()):  # its children so far leave it where they did
                    if q == c:
                        links[x] = (q, n - 1 - j, w)

    accept(cand)
    if views is not None:
        accept(_joins_in_both_views(ok, views, set(links)))
        if graphs is not None and SKELETON_DETOUR is not None:
            known = roots is not None and None not in roots
            ostium = {b.id for b in ok if known and b.pair.start == tuple(roots)}
            fallback: list[Any] = []
            accept(_joins_along_skeletons(ok, views, graphs, set(links) | ostium, find, walks, flips,
                                          fallback))
            # a branch that walked back over itself and could not be joined from its end either
            # is joined as before, folded back at its start
            late = [join for join, _ in fallback if join[1] not in links]
            for join, both in fallback:
                if join[1] not in links:
                    walks[(join[1], join[2])] = both
                    flips.discard((join[1], join[2]))
            accept(late)
    if adjust is not None:
        adjust()
    def depth(c: int) -> int:
        return 1 + depth(links[c][0]) if c in links else 0

    shifted: dict[int, np.ndarray] = {}  # how far each branch's points were moved below
    for c in sorted(links, key=depth):  # parents first: a moved parent moves its children's targets
        p, i, why = links[c]
        child, par = by_id[c], by_id[p]
        target = par.points_mm[i]
        gap = float(np.linalg.norm(child.points_mm[0] - target))
        # a child that met its parent where the parent's start has since been moved goes with it
        # (lca 2006, the model's labels: two vessels from one junction, the one linked to the other
        # 2.2 mm from its start, which was then moved 10 mm onto the vessel they leave)
        carried = float(np.linalg.norm(shifted[p][i])) if p in shifted else 0.0
        if (c, p) in walks and MAX_BRIDGE_MM is not None and gap > max(MAX_JOIN_GAP_MM, par.radius_mm[i]):
            target, paths = _departure(par, views, walks[(c, p)])
            before = len(child.points_mm)
            off = _bridge(child, target, views, paths)
            if off is None:
                child.warnings.append(f"{why}the gap bridged along them ({gap:.1f} mm)")
                added = len(child.points_mm) - before  # its own children leave it where they did
                for x, (q, j, w) in list(links.items()):
                    if q == c:
                        links[x] = (q, j + added, w)
            else:
                child.parent = None
                child.warnings.append(f"not {why[:-2]}: no single 3D curve follows both paths (the "
                                      f"best stays {off[0]:.1f} and {off[1]:.1f} px off them, mean), so "
                                      "the gap was not bridged")
        elif par.radius_mm[i] < gap <= MAX_JOIN_GAP_MM + carried:
            before = child.points_mm
            moved = _moved_start(child.points_mm, target)
            if views is not None and ON_VESSEL_ROUNDS:
                back = _back_on_vessels(moved, child.points_mm, views,
                                        (child.pair.points_a_px, child.pair.points_b_px))
                # not where the vessel would then leave its parent's end backwards (a start
                # that runs back along the parent: OCCT's union can hang on it, lca 2003)
                forward = par.points_mm[min(i + 1, len(par.points_mm) - 1)] - par.points_mm[max(i - 1, 0)]
                a0, a1 = _leaving_angle(moved, forward), _leaving_angle(back, forward)
                at_end = _length(par.points_mm[i:]) <= 2.0 * float(par.radius_mm[i])
                if not at_end or a1 <= max(a0, ON_VESSEL_MAX_ANGLE_DEG):
                    moved = back
            child.points_mm = moved
            if moved.shape == before.shape:
                shifted[c] = moved - before
            child.warnings.append(f"{why}start moved {gap:.1f} mm onto branch {p}, outside of whose "
                                  "lumen it was" + (f" (where that branch was moved {carried:.1f} mm)"
                                                    if carried > par.radius_mm[i] else ""))
        elif gap > par.radius_mm[i] and not ((c, p) in walks and MAX_BRIDGE_MM is not None):
            # too far to move without bending the branch out of shape: the link stays (what the
            # images say), the start where it is, and the branch says so (the solid, which needs
            # the start inside the parent, leaves it out)
            child.warnings.append(f"{why}its 3D start lies {gap:.1f} mm from branch {p}, farther than the "
                                  f"{MAX_JOIN_GAP_MM:g} mm a start is moved onto its parent: left where it "
                                  "is (the two disagree in depth there)")


def _ostium(match: GraphMatch, phase: PhaseMatch) -> np.ndarray | None:
    """The ostium in 3D: the matched roots of the two graphs, else the catheter tip the phase
    matching triangulated (the catheter is engaged in the ostium); None when neither is known."""
    root = match.root_pair
    if root is not None:
        return np.asarray(root.point_mm, float)
    if phase.objects and phase.objects[0] == "catheter" and np.isfinite(phase.point_mm).all():
        return np.asarray(phase.point_mm, float)
    return None


def _drop_off_surface(results: list[BranchResult], surface: Any, ostium: np.ndarray | None,
                      sigmas: float | None, views: tuple[CArmView, CArmView] | None = None) -> None:
    """Leave out the branches that lie off the heart's surface (see :data:`OFF_SURFACE_SIGMAS`),
    then trim the ends of the others that leave it (see :data:`OFF_SURFACE_END_SIGMAS`)."""
    if surface is None or sigmas is None:
        return
    limit = max(float(sigmas) * float(surface.sigma_mm), OFF_SURFACE_MIN_MM)
    _drop_whole_off_surface(results, surface, ostium, sigmas, limit)
    if OFF_SURFACE_END_SIGMAS is not None and views is not None:
        _trim_off_surface_ends(results, surface, ostium, views)


def _trim_off_surface_ends(results: list[BranchResult], surface: Any, ostium: np.ndarray | None,
                           views: tuple[CArmView, CArmView]) -> None:
    """Trim the runs of samples at either end of each kept branch that lie off the heart's surface."""
    from .matching import SURFACE_SIGMA_MIN_MM

    limit = float(OFF_SURFACE_END_SIGMAS) * max(float(surface.sigma_mm), SURFACE_SIGMA_MIN_MM)
    for b in results:
        if not b.ok:
            continue
        pts = b.points_mm
        d = np.nan_to_num(surface.distance(pts), nan=np.inf)
        if ostium is not None:
            d[np.linalg.norm(pts - ostium, axis=1) <= OFF_SURFACE_OSTIUM_MM] = 0.0
        off = d > limit
        if not (off[0] or off[-1]):
            continue
        lo, hi = (0, 0) if off.all() else (int(np.argmin(off)), len(pts) - int(np.argmin(off[::-1])))
        if _length(pts[lo:hi]) < OFF_SURFACE_END_KEEP_MM:
            continue  # (nearly) all of it off: the median rule above judges the whole branch
        gone = [f"its first {_length(pts[:lo + 1]):.1f} mm"] if lo else []
        gone += [f"its last {_length(pts[hi - 1:]):.1f} mm"] if hi < len(pts) else []
        b.warnings.append(f"{' and '.join(gone)} trimmed: more than {limit:.1f} mm from the heart's surface "
                          f"fitted to the tree's vessels (up to {float(d[off].max()):.1f} mm); most likely "
                          "the pair runs on along another vessel there")
        b.points_mm, b.radius_mm = pts[lo:hi], b.radius_mm[lo:hi]
        b.reprojection = reprojection_error(b.points_mm, list(views),
                                            [b.pair.points_a_px, b.pair.points_b_px])


def _drop_whole_off_surface(results: list[BranchResult], surface: Any, ostium: np.ndarray | None,
                            sigmas: float, limit: float) -> None:
    """Leave out the branches whose median distance from the heart's surface exceeds ``limit``."""
    for b in results:
        if not b.ok:
            continue
        pts = b.points_mm
        far = (np.ones(len(pts), bool) if ostium is None
               else np.linalg.norm(pts - ostium, axis=1) > OFF_SURFACE_OSTIUM_MM)
        if far.sum() < 4:  # within reach of the ostium: nothing to judge by
            continue
        d = float(np.median(surface.distance(pts[far])))
        if d > limit:
            b.status = (f"off the heart's surface: its 3D centreline lies {d:.1f} mm (median) from the "
                        f"surface fitted to the tree's vessels, more than {limit:.1f} mm ({sigmas:g} x the "
                        f"fit's spread of {surface.sigma_mm:.2f} mm); most likely two vessels that share "
                        "epipolar lines paired wrongly")


def _epipolar_angle_deg(points_mm: np.ndarray, view: CArmView, other: CArmView) -> np.ndarray:
    """Angle (degrees) between a 3D curve's projected tangent and the epipolar line, per sample."""
    p = view.project(points_mm)
    sine = EpipolarPair(view, other).conditioning(view, p, np.gradient(p, axis=0))
    return np.degrees(np.arcsin(np.clip(sine, 0.0, 1.0)))


def _depth_from_surface(results: list[BranchResult], views: tuple[CArmView, CArmView],
                        surface: Any) -> None:
    """Depth of the ill-conditioned samples from the heart's surface (see :data:`SURFACE_DEPTH_DEG`).

    Each sample moves along view A's ray (its view A projection stays) to the ray's
    crossing with the surface nearest it, weighted 1 where the tangent runs within
    ``SURFACE_DEPTH_DEG[0]`` of the epipolar lines in either view, 0 from
    ``SURFACE_DEPTH_DEG[1]`` on; the moves are smoothed along the branch (Gaussian,
    two samples) so the curve stays smooth. A branch so changed says so in its warnings, and
    its reprojection error is measured again. Nothing moves when the tree's points scatter
    about the surface by more than :data:`SURFACE_DEPTH_MAX_SIGMA_MM`.
    """
    if surface is None or not surface.sigma_mm <= SURFACE_DEPTH_MAX_SIGMA_MM:
        return
    va, vb = views
    lo, hi = SURFACE_DEPTH_DEG
    for b in results:
        if not b.ok or len(b.points_mm) < 3:
            continue
        pts = b.points_mm
        ang = np.minimum(_epipolar_angle_deg(pts, va, vb), _epipolar_angle_deg(pts, vb, va))
        w = np.clip((hi - ang) / (hi - lo), 0.0, 1.0)
        if not w.any():
            continue
        ray = pts - va.source
        depth = np.linalg.norm(ray, axis=1)
        ray /= depth[:, None]
        t = surface.intersect_rays(np.broadcast_to(va.source, pts.shape), ray, depth)
        move = t - depth
        w = np.where(np.isfinite(move) & (np.abs(move) <= SURFACE_DEPTH_MAX_MM), w, 0.0)
        if not w.any():
            continue
        move = ndimage.gaussian_filter1d(np.where(w > 0, move, 0.0) * w, 2.0, mode="nearest")
        b.points_mm = va.source + (depth + move)[:, None] * ray
        # the reported reprojection is the moved curve's (view B sees the moves, along its lines)
        b.reprojection = reprojection_error(b.points_mm, [va, vb], [b.pair.points_a_px, b.pair.points_b_px])
        share = float(np.mean(w > 0))
        b.warnings.append(f"{share:.0%} of the branch runs within {hi:g} deg of the epipolar lines: its "
                          f"depth there taken from the heart's surface fitted to the tree (moved up to "
                          f"{float(np.abs(move).max()):.1f} mm along view A's rays)")


def _joins_in_both_views(ok: list[BranchResult], views: tuple[CArmView, CArmView], linked: set[int]
                         ) -> list[tuple[float, int, int, int, str]]:
    """Candidate links of the branches without a parent whose start lies on another
    branch in both images: (cost px, child, parent, index of the parent's point, note).

    The point is the other branch's 3D point whose projections are nearest the
    start in both views (within :data:`JOIN_REPROJECTION_PX`: its own depth can be
    off near its ends), or its end where the start is at its 2D end (a vessel that
    continues it). Not where the other branch starts too: two daughters of one
    parent that was not reconstructed.
    """
    va, vb = views
    proj = {b.id: (va.project(b.points_mm), vb.project(b.points_mm)) for b in ok}
    joins = []
    for c in ok:
        if c.id in linked:
            continue
        sa, sb = c.pair.points_a_px[0], c.pair.points_b_px[0]
        for p in ok:
            if p.id == c.id:
                continue
            on = max(float(distance_to_polyline(sa[None], p.pair.points_a_px)[0]),
                     float(distance_to_polyline(sb[None], p.pair.points_b_px)[0]))
            if on > JOIN_PX:
                continue
            end_px = max(np.linalg.norm(sa - p.pair.points_a_px[-1]),
                         np.linalg.norm(sb - p.pair.points_b_px[-1]))
            if end_px <= JOIN_PX:
                i, off = len(p.points_mm) - 1, 0.0
            else:
                pa, pb = proj[p.id]
                offs = np.maximum(np.linalg.norm(pa - sa, axis=1), np.linalg.norm(pb - sb, axis=1))
                i = int(np.argmin(offs))
                off = float(offs[i])
            along = float(np.linalg.norm(np.diff(p.points_mm[:i + 1], axis=0), axis=1).sum())
            if off <= JOIN_REPROJECTION_PX and along > p.radius_mm[0]:
                note = f"starts on branch {p.id} in both views ({on:.1f} px): "
                joins.append((on + off, c.id, p.id, i, note))
    return joins


def _joins_along_skeletons(ok: list[BranchResult], views: tuple[CArmView, CArmView],
                           graphs: tuple[CentrelineGraph, CentrelineGraph], linked: set[int],
                           tree_of: Callable[[int], int],
                           paths: dict[tuple[int, int], Any] | None = None,
                           flips: set[tuple[int, int]] | None = None,
                           fallback: list[tuple[tuple[float, int, int, int, str], Any]] | None = None
                           ) -> list[tuple[float, int, int, int, str]]:
    """Candidate links across a stretch the matching left unpaired: (gap mm, child, parent,
    index of the parent's point, note); ``paths``, if given, receives each candidate's two
    skeleton paths (px, from the parent's point to the child's start, each with a flag per
    sample: a skeleton pixel where branches meet) under (child, parent); ``flips``, if
    given, receives (child, parent) for the candidates that join the child from its end
    (the paths then lead to its end, which becomes its start when the link is accepted);
    ``fallback``, if given, receives the candidates refused because their paths walk back
    over the child, with their paths (to be taken where the child stays unlinked).

    For each branch without a parent (not in ``linked``: those linked already, and the
    one starting at the ostium, which stays its tree's root), the nearest 3D point of
    every branch of another tree (``tree_of``) within :data:`MAX_BRIDGE_MM` (at least
    :data:`MAX_JOIN_GAP_MM`) of its start, not within the first radius of that branch
    (two daughters of a parent that was not reconstructed start near each other). It is a
    candidate when in each view the skeleton passes within :data:`JOIN_PX` of both
    projections and runs between them no longer than :data:`SKELETON_DETOUR` times the straight line plus
    :data:`SKELETON_DETOUR_PX`: the two pieces are one vessel in both images, not two
    vessels that pass close in 3D (those join in the images, if at all, by a detour
    through other vessels). Where the paths walk back over the branch's own 2D piece in
    both views (:data:`OWN_WALK_PX`, :data:`OWN_WALK_SHARE`), the branch runs towards the
    other one: the candidate goes to ``fallback``, and, unless it has another candidate
    as it runs, the branch is tried from its end, which must qualify the same way.
    """
    from scipy import sparse
    from scipy.sparse import csgraph

    from .centreline2d import _pixel_graph

    reach = MAX_JOIN_GAP_MM if MAX_BRIDGE_MM is None else max(MAX_BRIDGE_MM, MAX_JOIN_GAP_MM)

    def candidates(c: BranchResult, back: bool) -> list[tuple[float, BranchResult, BranchResult, int, bool]]:
        start = c.points_mm[-1 if back else 0]
        out = []
        for p in ok:
            if tree_of(p.id) == tree_of(c.id):
                continue
            d = np.linalg.norm(p.points_mm - start, axis=1)
            i = int(np.argmin(d))
            if d[i] <= reach and _length(p.points_mm[:i + 1]) > p.radius_mm[0]:
                out.append((float(d[i]), c, p, i, back))
        return out

    cands = [cand for c in ok if c.id not in linked for cand in candidates(c, False)]
    if not cands:
        return []
    nets: list[tuple[cKDTree, Any] | None] = []
    for g in graphs:
        rr, cc, adj = _pixel_graph(g.skeleton)
        if not len(rr):
            nets.append(None)
            continue
        xy = np.stack([cc, rr], axis=1).astype(float)
        coo = adj.tocoo()
        steps = np.linalg.norm(xy[coo.row] - xy[coo.col], axis=1)  # 1 or sqrt(2) px
        nets.append((cKDTree(xy), sparse.csr_matrix((steps, (coo.row, coo.col)), shape=adj.shape)))
    joins = []
    backwards: set[int] = set()  # branches whose paths walk back over them
    forward: set[int] = set()  # branches with a candidate as they run
    tried_back: set[int] = set()
    while cands:
        gap, c, p, i, back = cands.pop(0)
        detours, walks, over = [], [], []
        for k, (view, piece) in enumerate(zip(views, (c.pair.points_a_px, c.pair.points_b_px), strict=True)):
            if nets[k] is None:
                break
            pts2d = np.asarray(piece, float)[::-1] if back else np.asarray(piece, float)
            kd, net = nets[k]
            q = view.project(p.points_mm[i][None])[0]
            (d0, j0), (d1, j1) = kd.query(pts2d[0]), kd.query(q)
            straight = float(np.linalg.norm(q - pts2d[0]))
            limit = SKELETON_DETOUR * straight + SKELETON_DETOUR_PX
            if max(d0, d1) > JOIN_PX:
                break
            dist, pred = csgraph.dijkstra(net, indices=int(j1), limit=limit + 1.0, return_predecessors=True)
            run = float(dist[int(j0)])
            if not run <= limit:
                break
            detours.append(run)
            # the skeleton's path from the parent's point to the branch's start
            path = [int(j0)]
            while path[-1] != int(j1):
                path.append(int(pred[path[-1]]))
            path = np.asarray(path[::-1])
            fork = np.diff(net.indptr)[path] >= 3  # skeleton pixels where branches meet
            walk = np.vstack([q, kd.data[path], pts2d[0]])
            walks.append((walk, np.r_[False, fork, False]))
            if OWN_WALK_PX is not None:
                own = _own_walk(walk, pts2d)
                over.append(own > OWN_WALK_PX and own >= OWN_WALK_SHARE * _length(pts2d))
        else:
            turned = "its end (it ran towards the other branch) " if back else ""
            note = (f"{JOINED_NOTE} {gap:.1f} mm {'from ' + turned if back else ''}to branch {p.id}, where "
                    f"both views' skeletons run between the two ({detours[0]:.0f} and {detours[1]:.0f} px): ")
            join = (gap, c.id, p.id, i, note)
            if over and all(over):  # walks back over the branch in both views
                if not back:
                    backwards.add(c.id)
                    if fallback is not None:
                        fallback.append((join, (walks[0], walks[1])))
            else:
                joins.append(join)
                forward.add(c.id)
                if paths is not None:
                    paths[(c.id, p.id)] = (walks[0], walks[1])
                if back and flips is not None:
                    flips.add((c.id, p.id))
        if not cands:  # the branches that walked back over themselves (and only so), from their ends
            for b in ok:
                if b.id in backwards and b.id not in forward and b.id not in tried_back:
                    tried_back.add(b.id)
                    cands.extend(candidates(b, True))
    return joins


def _own_walk(walk: np.ndarray, piece: np.ndarray) -> float:
    """How far (px) a skeleton path to a branch's start runs on that branch's own 2D piece
    (within :data:`JOIN_PX`), its last :data:`JOIN_PX` aside."""
    step = np.linalg.norm(np.diff(walk, axis=0), axis=1)
    left = np.r_[np.cumsum(step[::-1])[::-1], 0.0]  # path length from each sample to the start
    on = (distance_to_polyline(walk, np.asarray(piece, float)) <= JOIN_PX) & (left > JOIN_PX)
    return float(np.sum(step[on[:-1] & on[1:]]))


def _reverse(branch: BranchResult, views: tuple[CArmView, CArmView] | None) -> None:
    """``branch`` walked the other way: its points, radii and pair (end landmark first)."""
    from .matching import _flip

    branch.points_mm = branch.points_mm[::-1].copy()
    branch.radius_mm = branch.radius_mm[::-1].copy()
    branch.pair = _flip(branch.pair)
    if views is not None:
        branch.reprojection = reprojection_error(branch.points_mm, list(views),
                                                 [branch.pair.points_a_px, branch.pair.points_b_px])


def _departure(parent: BranchResult, views: tuple[CArmView, CArmView],
               walks: Any) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Where a bridge leaves its parent, and the skeleton paths from there.

    Each view's skeleton path (``walks``: samples in px from the projection of the
    parent's point nearest the child's start, and a flag per sample for skeleton pixels
    where branches meet) may first run along the parent's own 2D piece before it turns
    into the gap. In each view the path leaves the parent at the last fork pixel of its
    first run of samples on the parent's piece (within :data:`JOIN_PX`), or at that run's
    end where it has none (a child leaving at an acute angle stays within a few pixels
    of its parent for a while: the fork is where the skeletons part). The bridge leaves
    the parent at its 3D point whose projections lie nearest the two departures, and
    each path is cut to start there.
    """
    proj, keep = [], []
    for view, (walk, fork), piece in zip(views, walks, (parent.pair.points_a_px, parent.pair.points_b_px),
                                         strict=True):
        on = distance_to_polyline(walk, np.asarray(piece, float)) <= JOIN_PX
        k = len(walk) - 2 if on[:-1].all() else max(int(np.argmin(on)) - 1, 0)
        forks = np.flatnonzero(fork[: k + 1])
        if len(forks):
            k = int(forks[-1])
        proj.append(view.project(parent.points_mm))
        keep.append((walk[k], walk[k + 1:]))
    cost = sum(np.sum((pr - q) ** 2, axis=1) for pr, (q, _) in zip(proj, keep, strict=True))
    j = int(np.argmin(cost))
    paths = tuple(np.vstack([pr[j], rest]) for pr, (_, rest) in zip(proj, keep, strict=True))
    return parent.points_mm[j], (paths[0], paths[1])


def _bridge(child: BranchResult, target: np.ndarray, views: tuple[CArmView, CArmView],
            walks: tuple[np.ndarray, np.ndarray]) -> tuple[float, float] | None:
    """Prepend to ``child`` a stretch of centreline from ``target`` (on its parent) to its start.

    A join across a stretch the matching left unpaired, where both views' skeletons
    run between the two (``walks``: each view's skeleton path in px, from the
    target's projection to the child's start). The stretch starts as a cubic Hermite
    curve (leaving ``target`` along the chord, arriving along the child's first
    direction), sampled every 0.5 mm, and is brought onto the two skeleton paths by the
    damped Gauss-Newton steps of :func:`_onto_paths` (the depth stays as the curve put
    it where the two views do not decide it), then sampled every 0.5 mm again. Its
    radius is the child's first one. The child's pair gets the two paths ahead of its
    pieces, so that its reprojection is measured against what both images show there.

    Returns None when it did so; where the stretch stays more than :data:`BRIDGE_MAX_PX`
    (mean) off either path (the two paths are not one vessel: one of them turns onto
    another vessel at a crossing), ``child`` is left as it was and the two mean
    distances (px) are returned.
    """
    pts = child.points_mm
    p0, p1 = np.asarray(target, float), pts[0]
    chord = p1 - p0
    length = float(np.linalg.norm(chord))
    ahead = pts[min(4, len(pts) - 1)] - pts[0]
    t1 = ahead / max(float(np.linalg.norm(ahead)), 1e-9) * length
    u = np.linspace(0.0, 1.0, max(int(np.ceil(length / 0.5)), 2) + 1)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    curve = h00 * p0 + h10 * chord + h01 * p1 + h11 * t1
    ends = np.zeros(len(curve), bool)
    ends[[0, -1]] = True
    curve = _onto_paths(curve, ~ends, views, walks)
    off = [float(np.mean(distance_to_polyline(view.project(curve[1:-1]), np.asarray(walk, float))))
           for view, walk in zip(views, walks, strict=True)]
    if max(off) > BRIDGE_MAX_PX:
        return off[0], off[1]
    curve = resample_by_arclength(curve, 0.5)  # the steps leave the samples unevenly spaced
    child.points_mm = np.vstack([curve[:-1], pts])
    child.radius_mm = np.r_[np.full(len(curve) - 1, child.radius_mm[0]), child.radius_mm]
    pair = child.pair
    ra, rb = np.asarray(pair.radius_a_px, float), np.asarray(pair.radius_b_px, float)
    child.pair = replace(
        pair, points_a_px=np.vstack([walks[0][:-1], pair.points_a_px]),
        points_b_px=np.vstack([walks[1][:-1], pair.points_b_px]),
        radius_a_px=np.r_[np.full(len(walks[0]) - 1, ra[0]), ra],
        radius_b_px=np.r_[np.full(len(walks[1]) - 1, rb[0]), rb])
    child.reprojection = reprojection_error(child.points_mm, list(views),
                                            [child.pair.points_a_px, child.pair.points_b_px])
    return None


def _onto_paths(points: np.ndarray, free: np.ndarray, views: tuple[CArmView, CArmView],
                paths: Sequence[np.ndarray], ramp: np.ndarray | None = None) -> np.ndarray:
    """``points`` whose ``free`` ones take ``ON_VESSEL_ROUNDS`` damped Gauss-Newton steps
    towards the 3D point whose projections are the nearest points of the 2D ``paths``
    (px, one per view). ``ON_VESSEL_DAMPING`` keeps the depth where the views do not
    decide it; the steps are smoothed along the curve (5 samples) and scaled by ``ramp``
    (one factor per free point), if given."""
    x = points[free].copy()
    if not len(x):
        return points
    lines = []
    for path in paths:
        dense = resample_by_arclength(np.asarray(path, float), 0.25)
        lines.append((dense, cKDTree(dense)))
    eps = 1e-3
    for _ in range(ON_VESSEL_ROUNDS):
        rows, res = [], []
        for view, (dense, tree) in zip(views, lines, strict=True):
            proj = view.project(x)
            _, k = tree.query(proj)
            res.append(dense[k] - proj)
            rows.append(np.stack([(view.project(x + eps * e) - proj) / eps for e in np.eye(3)], axis=2))
        jac = np.concatenate(rows, axis=1)  # (n, 4, 3): px per mm
        r = np.concatenate(res, axis=1)  # (n, 4) px
        a = np.einsum("nij,nik->njk", jac, jac) + ON_VESSEL_DAMPING * np.eye(3)
        step = np.linalg.solve(a, np.einsum("nij,ni->nj", jac, r)[..., None])[..., 0]
        step = ndimage.uniform_filter1d(step, size=min(5, len(step)), axis=0, mode="nearest")
        x += step if ramp is None else ramp * step
    out = points.copy()
    out[free] = x
    return out


def _back_on_vessels(moved: np.ndarray, original: np.ndarray, views: tuple[CArmView, CArmView],
                     pieces: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """A moved start (:func:`_moved_start`) brought back onto the child's vessel in both images.

    The shift is a smooth guess: its projections leave the vessel where it is not
    along it. In each view the child's vessel is its 2D piece (``pieces``), led in by a
    straight segment from the new start's projection (on the parent) to the piece's
    nearer end: for a join, the skeleton runs there without a detour. Each shifted point
    (not the first, on the parent) is moved by regularized Gauss-Newton steps towards
    the 3D point whose projections are the nearest points of those two paths
    (``ON_VESSEL_DAMPING`` keeps the depth where the views do not decide it), the steps
    smoothed along the curve and ramped in over the first ``ON_VESSEL_RAMP_MM`` (no kink
    at the new start, inside the parent); ``ON_VESSEL_ROUNDS`` rounds. Where the shift has faded out
    the curve is the child's own, which already reprojects onto its pieces: the steps
    vanish there.
    """
    changed = np.flatnonzero(np.linalg.norm(moved - original, axis=1) > 1e-9)
    if len(changed) < 2:
        return moved
    free = np.zeros(len(moved), bool)
    free[1: changed[-1] + 1] = True
    along = np.cumsum(np.linalg.norm(np.diff(moved[: changed[-1] + 1], axis=0), axis=1))
    ramp = np.clip(along / ON_VESSEL_RAMP_MM, 0.0, 1.0)[:, None]  # no kink at the new start
    paths = []
    for view, piece in zip(views, pieces, strict=True):
        piece = np.asarray(piece, float)
        first = view.project(original[:1])[0]
        if np.linalg.norm(piece[-1] - first) < np.linalg.norm(piece[0] - first):
            piece = piece[::-1]
        paths.append(np.vstack([view.project(moved[:1]), piece]))
    return _onto_paths(moved, free, views, paths, ramp)


def _leaving_angle(points: np.ndarray, forward: np.ndarray, reach_mm: float = 2.0) -> float:
    """Angle (degrees) between ``forward`` and the chord from a curve's start to its point
    ``reach_mm`` along it (its direction as it leaves its start)."""
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    chord = points[min(int(np.searchsorted(s, reach_mm)), len(points) - 1)] - points[0]
    den = float(np.linalg.norm(chord) * np.linalg.norm(forward))
    return float(np.degrees(np.arccos(np.clip(chord @ forward / den, -1.0, 1.0)))) if den > 0 else 0.0


def _moved_start(points: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``points`` with the first one moved to ``target``, the shift fading out (raised
    cosine) over three times its size (at least 5 mm, at most half the curve)."""
    shift = np.asarray(target, float) - points[0]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    span = min(max(3.0 * float(np.linalg.norm(shift)), 5.0), 0.5 * float(s[-1]))
    w = np.where(s < span, 0.5 * (1.0 + np.cos(np.pi * np.minimum(s / max(span, 1e-9), 1.0))), 0.0)
    return points + w[:, None] * shift


class _FrameLabeller:
    """Labels of a run's frames, computed by the model only for the frames asked for.

    The coarse-to-fine frame search of ``reconstruct``: the phase matching needs
    the labels of the frames it may choose, and it chooses among the frames
    filled with contrast (``match_phase``'s ``prefer_fill``). So every
    ``COARSE_PROBE``-th frame is labelled first (:meth:`coarse`), then every
    ``COARSE_STRIDE``-th frame near those whose vessel area is at least
    ``COARSE_KEEP`` of their largest; then (:meth:`neighbours`, :meth:`label`)
    the frames around the pairs the phase matching picks (``_choose_pair``).
    """

    def __init__(self, seg: Segmenter, run: XARun, progress: bool) -> None:
        self.seg, self.run, self.progress = seg, run, progress
        self.labels = np.zeros(run.frames.shape, np.uint8)
        self.known = np.zeros(run.n_frames, bool)

    @property
    def complete(self) -> bool:
        return bool(self.known.all())

    def label(self, idx: Any) -> int:
        """Label these frames (those not labelled yet); how many were new."""
        idx = np.unique(np.asarray(idx, dtype=np.int64))
        idx = idx[(idx >= 0) & (idx < self.run.n_frames)]
        idx = idx[~self.known[idx]]
        if len(idx):
            self.labels[idx] = self.seg(self.run.frames[idx], progress=self.progress, tta=False)
            self.known[idx] = True
        return len(idx)

    def coarse(self, extra: int | None = None) -> None:
        """The coarse pass (all frames for short or slow runs)."""
        n = self.run.n_frames
        dt = np.diff(self.run.frame_times_ms)
        fps = 1000.0 / float(np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
        if n < COARSE_MIN_FRAMES or fps < COARSE_MIN_FPS:
            self.label(np.arange(n))
            return
        step = COARSE_PROBE
        probes = np.unique(np.r_[np.arange(0, n, step), n - 1,
                                 [] if extra is None else [extra]]).astype(np.int64)
        self.label(probes)
        area = (self.labels[probes] == 1).sum(axis=(1, 2))
        if area.max() == 0:
            self.label(np.arange(n))  # no vessel in any probe: let the phase matching see everything
            return
        near = np.zeros(n, bool)
        for p in probes[area >= COARSE_KEEP * area.max()]:
            near[max(p - step + 1, 0): p + step] = True
        self.label(np.flatnonzero(near & (np.arange(n) % COARSE_STRIDE == 0)))

    def neighbours(self, frames: list[int]) -> int:
        """Label the frames next to these; how many were new."""
        f = np.asarray(frames, dtype=np.int64)
        return self.label(np.r_[f - 1, f + 1])


def _choose_pair(ra: XARun, rb: XARun, la: np.ndarray, lb: np.ndarray,
                 lz: tuple[_FrameLabeller, _FrameLabeller] | None, objects: Any,
                 frames: tuple[int, int] | None, options: dict[str, Any]) -> tuple[PhaseMatch, float]:
    """The phase matching, coarse to fine when ``lz`` labels the frames as it goes.

    Returns the match and the seconds spent labelling frames.
    """
    t_seg = 0.0
    while True:
        coarse = lz is not None and not (lz[0].complete and lz[1].complete)
        try:
            phase = match_phase(ra, rb, la, lb, objects=objects, pair=frames, **options,
                                **({"labelled_a": lz[0].known.copy(), "labelled_b": lz[1].known.copy()}
                                   if coarse else {}))
        except VesselcadError as exc:
            if not coarse:
                raise ReconstructionError(f"motion phase matching: {exc}. Pass frames=(i, j) (CLI: --frames "
                                          "I J) to choose the frame pair yourself") from None
            phase = None
        if not coarse:
            return phase, t_seg
        t0 = time.perf_counter()
        if phase is None or (frames is None and (phase.fill_a[phase.frame_a] < PREFER_FILL
                                                 or phase.fill_b[phase.frame_b] < PREFER_FILL)):
            # the labelled frames hold no filled pair with key points: label them all
            new = lz[0].label(np.arange(ra.n_frames)) + lz[1].label(np.arange(rb.n_frames))
        elif frames is not None:
            new = 0
        else:
            ok = phase.eligible_a[:, None] & phase.eligible_b[None, :] & np.isfinite(phase.score)
            order = np.argsort(np.where(ok, phase.score, np.inf), axis=None)[:COARSE_TOP]
            ia, ib = np.unravel_index(order[ok.ravel()[order]], ok.shape)
            new = lz[0].neighbours(ia) + lz[1].neighbours(ib)
            # the chosen pair's surroundings whole: one frame's key point can be far off and
            # hide a good pair next to it from the coarse grid
            reach = np.arange(-COARSE_REACH, COARSE_REACH + 1)
            new += lz[0].label(phase.frame_a + reach) + lz[1].label(phase.frame_b + reach)
        t_seg += time.perf_counter() - t0
        if not new:
            return phase, t_seg


def _summary(results: list[BranchResult]) -> dict[str, float]:
    # Rejected branches keep their points for the report picture but are not part of the tree.
    rps = [b.reprojection for b in results if b.ok and b.reprojection is not None]
    if not rps:
        return {}
    px = np.concatenate([r.px for r in rps])
    mm = np.concatenate([r.mm for r in rps])
    return {"mean_px": float(px.mean()), "sd_px": float(px.std()), "max_px": float(px.max()),
            "mean_mm": float(mm.mean()), "sd_mm": float(mm.std()), "max_mm": float(mm.max())}


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="branch", leave=False)


def reconstruct(
    run_a: XARun | str | os.PathLike,
    run_b: XARun | str | os.PathLike,
    *,
    method: str = "nurbs",
    frames: tuple[int, int] | None = None,
    model: str | os.PathLike | Segmenter | None = None,
    labels: tuple[Any, Any] | None = None,
    objects: str | list[str] = "auto",
    geometry_a: Any = None,
    geometry_b: Any = None,
    refine: bool = True,
    solid: bool = True,
    progress: bool = False,
    tta: str | bool = "chosen",
    frame_search: str = "all",
    off_surface_sigmas: float | None = OFF_SURFACE_SIGMAS,
    max_side: int | None = WORK_MAX_SIDE,
) -> Reconstruction:
    """3D vessel tree from two X-ray angiography runs of the same vessels (the whole method).

    Parameters
    ----------
    run_a, run_b : XARun or path
        The two runs (DICOM XA files, frame folders, or loaded runs).
    method : {"nurbs", "epipolar"}
        3D centrelines by intersecting extruded NURBS surfaces in OCCT (the
        paper's method), or by the point-wise epipolar baseline.
    frames : (int, int), optional
        Use this frame pair instead of the one motion phase matching picks
        (its phase error is still reported).
    model : path, {'fp32', 'int8', 'fast', 'fast-int8'} or Segmenter, optional
        Segmentation model (ONNX file or the name of a bundled one, see
        :class:`Segmenter`), or a loaded ``Segmenter`` to reuse across calls;
        default: the bundled gated U-Net, in int8 on the CPU (``Segmenter()``).
    labels : (array, array), optional
        Segmentation labels of every frame of each run (N, H, W) instead of
        running the model (0 background, 1 vessel, 2 catheter, 3 balloon, 4 lead).
        The phase matching weighs the vessels' epipolar consistency at
        ``match_phase``'s default (10 mm) with given labels and at
        :data:`MODEL_VESSEL_WEIGHT_MM` (30 mm) with the model's, whose
        catheter tips are less reliable (``report.json``: ``phase.vessel_weight``).
    objects : 'auto', str or list of str
        Stationary object(s) for phase matching: 'balloon', 'catheter', 'lead';
        'vessels' for none (the pair is chosen by the vessels' epipolar
        consistency alone). 'auto' falls back to the vessels, with a warning,
        when no object is found in both runs (``match_phase``).
    geometry_a, geometry_b : dict, CArmView or path, optional
        Geometry overrides per run (CArmView entries, or a view.json), e.g.
        when an export lacks SID/SOD.
    refine : bool
        Refine the relative C-arm pose (small rotation of view B about the
        isocentre and a table shift) by minimizing the reconstruction error of
        the matched landmarks and branches; kept only if it clearly lowers
        the error (``Reconstruction.refinement`` has before/after numbers).
    solid : bool
        Also build the fused OCCT solid.
    progress : bool
        Progress bars for the long stages.
    tta : {'chosen', 'all', 'none'}
        Test-time augmentation of the segmentation (``Segmenter(tta=True)``:
        the mean over the frame and its three mirror images, each at the
        frame's size and at 0.75 of it, eight network calls a frame).
        ``'chosen'`` (default): every frame is segmented once for the phase
        matching, and the two chosen frames again with it before their
        centrelines are traced; ``'all'``: every frame with it (better
        catheter labels for the phase matching, ~7x the segmentation time);
        ``'none'``. ``True`` and
        ``False`` mean ``'chosen'`` and ``'none'``. Only with the model (not
        with ``labels``).
    frame_search : {'all', 'coarse'}
        Which frames the model labels for the phase matching. ``'all'``
        (default): every frame, as the method describes. ``'coarse'``: coarse
        to fine, for throughput (batches), on runs of at least ``COARSE_MIN_FRAMES``
        frames at 12 fps or more: every fourth frame, then every frame
        within three frames of those that show the vessels filled (at least
        ``COARSE_KEEP`` of their largest area), then the frames around the
        best pairs until nothing is added (about three quarters of the
        frames of a phantom run; should no filled pair be found that way,
        all of them). Wash-in and wash-out frames, which the phase matching
        does not choose while filled ones have key points, are mostly left
        out; on 48 phantom cases it chose the same pair as ``'all'`` every
        time, 13 % faster end to end. Only with the model (``tta='all'``
        labels every frame).
    off_surface_sigmas : float or None
        A 3D branch whose points lie, by their median, farther than this many
        times the spread of the heart's surface fitted by the matching
        (``GraphMatch.surface``), and at least ``OFF_SURFACE_MIN_MM``, from that
        surface is left out with the status "off the heart's surface" (a
        pairing of two vessels that share epipolar lines); points within
        ``OFF_SURFACE_OSTIUM_MM`` of the ostium do not count. The ends of the
        branches kept are trimmed where they lie farther from that surface
        than ``OFF_SURFACE_END_SIGMAS`` times its spread (at least 2 mm).
        Default 4; None keeps every branch whole (vessels that do not run on
        one surface).
    max_side : int or None
        Runs whose frames have more rows or columns than this (default
        :data:`WORK_MAX_SIDE`, 512) are reduced to it by area averaging
        before anything else (:meth:`XARun.resampled`: the same detector with
        larger pixels), and ``labels`` given with them likewise (each pixel
        the class covering most of it). Every later stage, the pictures,
        ``Reconstruction.views``, ``frames`` and ``labels`` and the pixel
        figures of the report are then at that size; ``header_views`` keep
        the files' own size. None works on the frames as they are.

    Returns
    -------
    Reconstruction

    Raises
    ------
    ArgumentError
        Bad arguments (unknown method, labels of the wrong shape, frame pair out of range).
    InputFileError, DicomError, MissingGeometryError
        A run cannot be read.
    ReconstructionError
        A stage that every later stage needs failed (no stationary object, no
        vessel, no matched branch); the message names the stage.
    """
    if method not in ("nurbs", "epipolar"):
        raise ArgumentError(f"method: expected 'nurbs' or 'epipolar', got {method!r}")
    if isinstance(tta, (bool, np.bool_)):
        tta = "chosen" if tta else "none"
    if tta not in TTA_MODES:
        raise ArgumentError(f"tta: expected one of {TTA_MODES}, got {tta!r}")
    if frame_search not in FRAME_SEARCH_MODES:
        raise ArgumentError(f"frame_search: expected one of {FRAME_SEARCH_MODES}, got {frame_search!r}")
    sig = off_surface_sigmas
    if sig is not None and (isinstance(sig, (bool, np.bool_)) or not isinstance(sig, (int, float))
                            or not np.isfinite(sig) or sig <= 0):
        raise ArgumentError(f"off_surface_sigmas: expected a number > 0 or None, got {off_surface_sigmas!r}")
    if max_side is not None and (isinstance(max_side, (bool, np.bool_))
                                 or not isinstance(max_side, (int, np.integer)) or max_side < 64):
        raise ArgumentError(f"max_side: expected a whole number >= 64 or None, got {max_side!r}")
    # checked before the segmentation (minutes on long runs), not only by match_phase after it
    if isinstance(objects, str):
        ok = objects in ("auto", "vessels", *OBJECTS)
    else:
        ok = isinstance(objects, (list, tuple)) and 0 < len(objects) and set(objects) <= set(OBJECTS)
    if not ok:
        raise ArgumentError(f"objects: expected 'auto', 'vessels' or some of {list(OBJECTS)}, "
                            f"got {objects!r}")
    timings: dict[str, float] = {}
    warn: list[str] = []
    t = time.perf_counter()
    ra = _as_run(run_a, geometry_a, "run_a")
    rb = _as_run(run_b, geometry_b, "run_b")
    headers = (ra.view, rb.view)  # the files' geometry at the files' size
    full = (ra, rb)
    if max_side is not None:
        ra, rb = ra.resampled(int(max_side)), rb.resampled(int(max_side))
        for run, big, name in ((ra, full[0], "A"), (rb, full[1], "B")):
            if run is not big:
                warn.append(f"run {name}: frames of {big.view.rows}x{big.view.cols} px reduced to "
                            f"{run.view.rows}x{run.view.cols} px (max_side={max_side}), the size the "
                            "method's pixel parameters are set for")
    if frames is not None:
        try:
            fa, fb = (int(x) for x in frames)
        except (TypeError, ValueError):
            raise ArgumentError(f"frames: expected two frame indices, got {frames!r}") from None
        if not (0 <= fa < ra.n_frames and 0 <= fb < rb.n_frames):
            raise ArgumentError(f"frames: ({fa}, {fb}) is outside the runs' {ra.n_frames} and "
                                f"{rb.n_frames} frames")
        frames = (fa, fb)
    _check_pair(ra, rb, warn)
    timings["load"] = time.perf_counter() - t

    t = time.perf_counter()
    lz: tuple[_FrameLabeller, _FrameLabeller] | None = None
    if labels is not None:
        if not isinstance(labels, (tuple, list)) or len(labels) != 2:
            raise ArgumentError("labels: expected a pair (labels of run A, labels of run B)")
        la = _resampled_labels(_check_labels(labels[0], full[0], "labels[0]"), ra.view)
        lb = _resampled_labels(_check_labels(labels[1], full[1], "labels[1]"), rb.view)
        seg_info: dict[str, Any] = {"labels": "given"}
    else:
        seg = model if isinstance(model, Segmenter) else Segmenter(model)
        seg_info = _segmentation_summary(seg, tta, frame_search)
        if frame_search == "coarse" and tta != "all":
            lz = (_FrameLabeller(seg, ra, progress), _FrameLabeller(seg, rb, progress))
            lz[0].coarse(None if frames is None else frames[0])
            lz[1].coarse(None if frames is None else frames[1])
            la, lb = lz[0].labels, lz[1].labels
        else:
            la = seg(ra.frames, progress=progress, tta=tta == "all")
            lb = seg(rb.frames, progress=progress, tta=tta == "all")
    timings["segmentation"] = time.perf_counter() - t

    if solid:
        # the booleans' helper process imports OCCT (~1 s, one core) while the next stages run
        from .kernel.solid import start_fuse_worker

        start_fuse_worker()
    t = time.perf_counter()
    phase, t_seg = _choose_pair(ra, rb, la, lb, lz, objects, frames,
                                {} if labels is not None else {"vessel_weight": MODEL_VESSEL_WEIGHT_MM})
    warn += [f"phase: {w}" for w in phase.warnings]
    timings["phase"] = time.perf_counter() - t - t_seg
    timings["segmentation"] += t_seg

    fa, fb = phase.frame_a, phase.frame_b
    lab_a, lab_b = la[fa], lb[fb]
    if labels is None and tta == "chosen":
        # the two frames the tree comes from: mirror test-time augmentation
        t = time.perf_counter()
        lab_a, lab_b = seg(ra.frames[fa], tta=True), seg(rb.frames[fb], tta=True)
        timings["segmentation"] += time.perf_counter() - t

    t = time.perf_counter()
    graphs = []
    # The catheter tips the phase matching tracked through both runs and triangulated: the other
    # view confirms them, where one frame's labels can put the tip on a piece of vessel labelled
    # catheter or on another catheter (docs/centreline2d.md, step 7).
    tips = [None, None]
    if "catheter" in phase.objects:
        for k, (kps, f) in enumerate(((phase.keypoints_a, fa), (phase.keypoints_b, fb))):
            p = np.asarray(kps["catheter"][f], float)
            tips[k] = p if np.isfinite(p).all() else None
    for lab, run, name, tip in ((lab_a, ra, "A", tips[0]), (lab_b, rb, "B", tips[1])):
        if not (lab == 1).any():
            raise ReconstructionError(f"centreline graphs: no vessel pixels in frame "
                                      f"{fa if name == 'A' else fb} of run {name} ({run.source or 'run'})")
        with _warnings.catch_warnings(record=True) as caught:
            _warnings.simplefilter("always", VesselcadWarning)
            graphs.append(centreline_graph(lab == 1, run.view, labels=lab, tip=tip))
        warn += [f"graph {name}: {w.message}" for w in caught]
    ga, gb = graphs
    timings["graphs"] = time.perf_counter() - t

    t = time.perf_counter()
    views = (ra.view, rb.view)
    refinement = None
    if refine:
        kp = None
        if phase.objects:
            obj = phase.objects[0]
            kp = (phase.keypoints_a[obj][fa], phase.keypoints_b[obj][fb])
        # No frame pair's key point agrees: the heart sat elsewhere in run B at every pair.
        confirmed = bool(np.isfinite(phase.least_error_mm) and phase.least_error_mm > DISAGREE_MM)
        refinement = refine_geometry(ra.view, ga, rb.view, gb, keypoints=kp, keypoint_confirmed=confirmed)
        if refinement.applied:
            views = (refinement.view_a, refinement.view_b)
        warn += [f"refinement: {w}" for w in refinement.warnings]
    timings["refinement"] = time.perf_counter() - t

    t = time.perf_counter()
    match = match_graphs(views[0], ga, views[1], gb)
    warn += [f"matching: {w}" for w in match.warnings]
    timings["matching"] = time.perf_counter() - t
    if not match.pairs:
        raise ReconstructionError(
            f"matching: no branch of view A could be paired with one of view B "
            f"({len(ga.branches)} and {len(gb.branches)} branches, {len(match.landmark_pairs)} landmark "
            "pairs); check the geometry (angles, SID/SOD) and the segmentation in report pictures")

    t = time.perf_counter()
    results = []
    bar = _progress(len(match.pairs), "3D centrelines", progress)
    for k, pair in enumerate(match.pairs):
        results.append(_branch_3d(k, pair, views, method))
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    _drop_off_surface(results, match.surface, _ostium(match, phase), off_surface_sigmas, views)
    # the depth from the surface moves points in view B: the parents are chosen before it
    _link_parents(results, views, adjust=lambda: _depth_from_surface(results, views, match.surface),
                  graphs=(ga, gb), roots=match.roots)
    timings["centrelines_3d"] = time.perf_counter() - t
    for b in results:
        if not b.ok:
            warn.append(f"branch {b.id} (graph branches {b.pair.a}/{b.pair.b}): {b.status}")

    t = time.perf_counter()
    tree = None
    ok = [b for b in results if b.ok]
    if ok:
        tree = VesselTree([TreeBranch(id=b.id, parent=b.parent, points=b.points_mm, radius=b.radius_mm,
                                      name=f"branch_{b.id}", landmarks=b.pair.start, segments=(b.id,))
                           for b in ok])
        tree = _reattached(tree)  # no child leaves from its parent's very start (a junction's chain)
        for b in ok:
            if tree[b.id].parent != b.parent:
                b.parent = tree[b.id].parent
                b.warnings += tree[b.id].warnings
    else:
        warn.append("no branch could be reconstructed in 3D")
    timings["tree"] = time.perf_counter() - t

    t = time.perf_counter()
    vsolid = None
    if solid and tree is not None:
        try:
            vsolid = tree.solid(progress=progress)
            warn += [f"solid: {w}" for w in vsolid.union_warnings]
            for bid, why in vsolid.failed.items():
                warn.append(f"solid: branch {bid} left out: {why}")
        except Exception as exc:  # the centrelines are still worth having
            warn.append(f"solid: could not be built ({type(exc).__name__}: {exc})")
    timings["solid"] = time.perf_counter() - t

    return Reconstruction(
        tree=tree, solid=vsolid, phase=phase, graphs=(ga, gb), match=match, branches=results,
        views=views, header_views=headers, refinement=refinement,
        frames=(ra.frames[fa], rb.frames[fb]), labels=(lab_a, lab_b), errors=_summary(results),
        timings=timings, warnings=warn, sources=(ra.source, rb.source), segmentation=seg_info,
    )
