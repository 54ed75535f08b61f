"""Refinement of the relative C-arm pose of two runs from matched landmarks and branches.

Real DICOM angles are off by a degree or two, and the patient or table moves
between two runs acquired a minute apart. Both show up as a reconstruction
error (paper §2.3) that no frame pair can remove. :func:`refine_geometry`
keeps view A as it is and corrects view B by a small rotation about the
isocentre (primary and secondary angle) and a shift of its isocentre
(``CArmView.offset_mm``), bounded, by robust least squares over:

- matched landmark pairs (branch and end points): both 2D reprojection errors
  of their triangulated position;
- points along matched branch pairs: for samples of view A's piece, the
  smallest reconstruction error against view B's piece (a curve has no
  point-to-point correspondence, but its epipolar transfer must meet the
  other view's curve);
- optionally the stationary object's key point in both frames.

The stationary object (catheter tip, balloon) moves with the heart. Where its
two views disagree at the chosen frames by more than ``keypoint_tol_px``, the
heart sits elsewhere in run B than the files' geometry says: breathing (runs
too short to share a respiratory phase: free breathing moves the heart 10-20
mm, mostly cranio-caudally), or the patient or table moved between the runs.
Two views see such a shift only across the epipolar lines, and the matching
would otherwise pair whatever agrees with the wrong geometry. So view B is
first shifted by the shortest move that makes the two rays of the key point
meet (:func:`keypoint_shift`), and everything else starts from there. Where
the key point gives no shift (it agrees, there is none, or the landmarks do
not back it), the vessels' own branch and end points are asked: view B is
scanned across the epipolar lines for the shift at which most of them agree
(:func:`landmark_shift`), and moved there when that shift makes clearly more
of them agree than none.

Correspondences come from :func:`vesselcad.match_graphs` with relaxed
tolerances, and are found again after each round. The result is kept only
if it lowers the error clearly; before and after figures are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from .centreline2d import CentrelineGraph
from .errors import ArgumentError
from .geometry import CArmView, check_view, reconstruction_error, triangulate
from .matching import _check_graph, match_graphs
from .splines import resample_by_arclength

__all__ = ["Refinement", "keypoint_shift", "landmark_shift", "refine_geometry"]

#: Tolerances (px) used to find correspondences on the unrefined geometry.
RELAXED_LANDMARK_TOL_PX = 8.0
RELAXED_BRANCH_TOL_PX = 6.0
#: The stationary object's key point may disagree by this reconstruction error (px) at the chosen
#: frames before view B is shifted to make it agree (``refine_geometry(keypoint_tol_px=...)``).
KEYPOINT_TOL_PX = 2.0
#: The largest shift made for the key point (mm): free breathing moves the heart 10-20 mm.
MAX_KEYPOINT_SHIFT_MM = 20.0
#: The key point's shift is kept only if more pairs of the two graphs' landmarks (branch and end
#: points, every pair) reconstruct within this error (px) with it than without it.
LANDMARK_CHECK_TOL_PX = 2.0
#: When no frame pair of the runs agrees (``keypoint_confirmed``), the key point's shift is made
#: unless fewer than this share of the landmark pairs agree with it as without it (a key point
#: that is two different points of the catheter in every frame: the vessels say so clearly).
KEYPOINT_CONFIRMED_SHARE = 0.6
#: Where the key point gave no shift, view B is scanned across the epipolar lines (up to this many
#: mm either way, in steps of ``LANDMARK_SCAN_STEP_MM``) for the shift at which most landmarks of
#: view A have a landmark of the same kind in view B within ``LANDMARK_SCAN_TOL_PX``.
LANDMARK_SCAN_MM = 10.0
LANDMARK_SCAN_STEP_MM = 0.25
LANDMARK_SCAN_TOL_PX = 1.5
#: The scan's shift is made only if it gives this many more agreeing landmarks than no shift, and
#: this many times as many.
LANDMARK_SCAN_GAIN = 3
LANDMARK_SCAN_RATIO = 1.4


@dataclass
class Refinement:
    """Result of :func:`refine_geometry`.

    Attributes
    ----------
    applied : bool
        True when the refined geometry is used (it lowered the error clearly).
    view_a, view_b : CArmView
        The views to use (the given ones when not applied).
    rotation_deg : (float, float)
        Correction of view B's primary and secondary angle.
    offset_mm : numpy.ndarray, shape (3,)
        Shift of view B's isocentre (LPS mm): table or patient motion, or
        breathing; the key point's shift included.
    before_px, after_px : float
        Mean reconstruction error over the correspondences before (on the
        files' geometry) and after.
    keypoint_px : (float, float)
        Reconstruction error of the stationary object's key point on the
        files' geometry and on the views returned (NaN without a key point).
    keypoint_shift_mm : numpy.ndarray, shape (3,)
        The part of ``offset_mm`` made to bring the key point's two rays
        together (zeros when it agreed within ``keypoint_tol_px``, or when the
        landmarks did not agree better with it).
    keypoint_landmarks : (int, int)
        When the key point disagreed: the pairs of landmarks of the two
        graphs within ``LANDMARK_CHECK_TOL_PX`` on the files' geometry and with
        the key point's shift (the shift is kept only if the second is larger).
    landmark_shift_mm : numpy.ndarray, shape (3,)
        The part of ``offset_mm`` found by scanning view B across the epipolar
        lines for the shift at which most landmarks agree
        (:func:`landmark_shift`; zeros when not made).
    landmark_counts : (int, int) or None
        Where that scan ran: view A's landmarks with an agreeing landmark of
        view B without the scan's shift and with it.
    landmarks, curve_points : int
        Number of landmark pairs and branch samples used.
    warnings : list of str
    """

    applied: bool
    view_a: CArmView
    view_b: CArmView
    rotation_deg: tuple[float, float] = (0.0, 0.0)
    offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    before_px: float = float("nan")
    after_px: float = float("nan")
    landmarks: int = 0
    curve_points: int = 0
    warnings: list[str] = field(default_factory=list)
    keypoint_px: tuple[float, float] = (float("nan"), float("nan"))
    keypoint_shift_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    keypoint_landmarks: tuple[int, int] | None = None
    landmark_shift_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    landmark_counts: tuple[int, int] | None = None

    def to_dict(self) -> dict[str, Any]:
        def r(x: float) -> float | None:
            return round(float(x), 4) if np.isfinite(x) else None

        return {"applied": self.applied, "rotation_deg": [round(float(x), 4) for x in self.rotation_deg],
                "offset_mm": np.round(self.offset_mm, 3).tolist(), "before_px": r(self.before_px),
                "after_px": r(self.after_px), "landmarks": self.landmarks,
                "curve_points": self.curve_points, "warnings": list(self.warnings),
                "keypoint_px": [r(x) for x in self.keypoint_px],
                "keypoint_shift_mm": np.round(self.keypoint_shift_mm, 3).tolist(),
                "keypoint_landmarks": (None if self.keypoint_landmarks is None
                                       else list(self.keypoint_landmarks)),
                "landmark_shift_mm": np.round(self.landmark_shift_mm, 3).tolist(),
                "landmark_counts": None if self.landmark_counts is None else list(self.landmark_counts)}


def _moved(view: CArmView, p: np.ndarray) -> CArmView:
    d = view.to_dict()
    d["primary_deg"] = view.primary_deg + float(p[0])
    d["secondary_deg"] = view.secondary_deg + float(p[1])
    d["offset_mm"] = (np.asarray(view.offset_mm) + p[2:5]).tolist()
    return CArmView.from_dict(d)


def keypoint_shift(view_a: CArmView, point_a_px: Any, view_b: CArmView, point_b_px: Any) -> np.ndarray:
    """The shortest shift of view B's isocentre that makes one point's two rays meet.

    The ray of ``point_a_px`` in view A and that of ``point_b_px`` in view B
    generally miss each other; shifting view B (source and detector together,
    ``CArmView.offset_mm``) by ``t`` moves its ray by ``t``. The shortest such
    ``t`` runs along the rays' common perpendicular, by their distance. A
    shift within the plane of the two rays moves the point along them instead
    and cannot be seen in the two images.

    Parameters
    ----------
    view_a, view_b : CArmView
    point_a_px, point_b_px : array_like, shape (2,)
        The same point's ``(col, row)`` pixel in each view.

    Returns
    -------
    numpy.ndarray, shape (3,)
        The shift (LPS mm) to add to view B's ``offset_mm``; zeros when the
        rays are parallel.
    """
    check_view(view_a, "view_a")
    check_view(view_b, "view_b")
    pts = []
    for p, name in ((point_a_px, "point_a_px"), (point_b_px, "point_b_px")):
        try:
            q = np.asarray(p, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ArgumentError(f"{name}: expected one finite (col, row) pixel, got {p!r}") from None
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ArgumentError(f"{name}: expected one finite (col, row) pixel, got {q.tolist()}")
        pts.append(q)
    pa, pb = pts
    oa, da = view_a.ray(pa)
    ob, db = view_b.ray(pb)
    n = np.cross(da, db)
    norm = float(np.linalg.norm(n))
    if norm < 1e-9:
        return np.zeros(3)
    n /= norm
    return -float(np.dot(ob - oa, n)) * n


def landmark_shift(view_a: CArmView, graph_a: CentrelineGraph, view_b: CArmView, graph_b: CentrelineGraph,
                   *, max_mm: float = LANDMARK_SCAN_MM, step_mm: float = LANDMARK_SCAN_STEP_MM,
                   tol_px: float = LANDMARK_SCAN_TOL_PX) -> tuple[np.ndarray, int, int]:
    """The shift of view B across the epipolar lines at which most landmarks of the two views agree.

    A heart that sits elsewhere in run B than in run A (breathing between two
    runs, the table or the patient moved) moves every landmark of view B off
    the epipolar lines of its partner in view A. Two views see such a shift
    only across the epipolar lines: along the direction ``u`` perpendicular to
    the baseline (source A to source B) and to the mean viewing direction.
    View B's isocentre is moved along ``u`` from ``-max_mm`` to ``max_mm`` in
    steps of ``step_mm``; at each shift every landmark of view A counts when a
    landmark of the same kind (branch or end point) in view B reconstructs
    with it within ``tol_px`` (paper §2.3). Branch points are points of the
    anatomy, not of the picture: the right shift makes many of them agree at
    once, a wrong one only those that fall on each other's epipolar lines by
    chance.

    Parameters
    ----------
    view_a, view_b : CArmView
    graph_a, graph_b : CentrelineGraph
    max_mm, step_mm : float
        Range and step of the scan (mm at the isocentre).
    tol_px : float
        Reconstruction error (px) within which two landmarks agree.

    Returns
    -------
    shift : numpy.ndarray, shape (3,)
        The shift (LPS mm) to add to view B's ``offset_mm``: the middle of the
        widest run of steps with the largest count (the one nearest to no
        shift where runs tie).
    count_none, count_best : int
        View A's landmarks that agree without the shift and with it.

    Raises
    ------
    ArgumentError
        A view or graph of the wrong type, or a non-positive range, step or tolerance.
    """
    check_view(view_a, "view_a")
    check_view(view_b, "view_b")
    graph_a, graph_b = _check_graph(graph_a, "graph_a"), _check_graph(graph_b, "graph_b")
    for val, name in ((max_mm, "max_mm"), (step_mm, "step_mm"), (tol_px, "tol_px")):
        if not (isinstance(val, (int, float)) and np.isfinite(val) and val > 0):
            raise ArgumentError(f"{name}: expected a positive number, got {val!r}")
    pa, pb = graph_a.landmark_points, graph_b.landmark_points
    if not (len(pa) and len(pb)):
        return np.zeros(3), 0, 0
    ka = np.array([lm.kind for lm in graph_a.landmarks])
    kb = np.array([lm.kind for lm in graph_b.landmarks])
    same = ka[:, None] == kb[None, :]
    u = np.cross(view_b.source - view_a.source, view_a.detector_direction + view_b.detector_direction)
    norm = float(np.linalg.norm(u))
    if norm < 1e-9:
        return np.zeros(3), 0, 0
    u /= norm
    n = int(np.floor(max_mm / step_mm))
    steps = np.arange(-n, n + 1) * step_mm
    counts = np.empty(len(steps), dtype=np.int64)
    for k, s in enumerate(steps):
        err = reconstruction_error(view_a, pa[:, None, :], _moved(view_b, np.r_[0.0, 0.0, s * u]),
                                   pb[None, :, :]).error_px
        counts[k] = np.count_nonzero(np.where(same, err, np.inf).min(axis=1) < tol_px)
    best = counts.max()
    # Runs of steps at the best count: the widest one, then the one nearest to no shift.
    on = np.r_[False, counts == best, False].astype(np.int8)
    starts, ends = np.flatnonzero(np.diff(on) == 1), np.flatnonzero(np.diff(on) == -1)
    mids = 0.5 * (steps[starts] + steps[ends - 1])
    k = min(range(len(starts)), key=lambda i: (-(ends[i] - starts[i]), abs(mids[i])))
    return mids[k] * u, int(counts[n]), int(best)


def _landmarks_agreeing(va: CArmView, ga: CentrelineGraph, vb: CArmView, gb: CentrelineGraph) -> int:
    """Pairs of the two graphs' landmarks (all against all) within ``LANDMARK_CHECK_TOL_PX``."""
    pa, pb = ga.landmark_points, gb.landmark_points
    if not (len(pa) and len(pb)):
        return 0
    err = reconstruction_error(va, pa[:, None, :], vb, pb[None, :, :]).error_px
    return int(np.count_nonzero(err < LANDMARK_CHECK_TOL_PX))


def _correspondences(va: CArmView, ga: CentrelineGraph, vb: CArmView, gb: CentrelineGraph,
                     relaxed: bool, step_px: float) -> tuple[np.ndarray, np.ndarray, list]:
    kw = ({"landmark_tol_px": RELAXED_LANDMARK_TOL_PX, "branch_tol_px": RELAXED_BRANCH_TOL_PX}
          if relaxed else {})
    m = match_graphs(va, ga, vb, gb, **kw)
    idx = m.landmark_indices
    lm_a = ga.landmark_points[idx[:, 0]] if len(idx) else np.empty((0, 2))
    lm_b = gb.landmark_points[idx[:, 1]] if len(idx) else np.empty((0, 2))
    curves = []
    for p in m.pairs:
        a = resample_by_arclength(p.points_a_px, step_px)
        b = resample_by_arclength(p.points_b_px, 1.0)
        if len(a) >= 3 and len(b) >= 3:
            curves.append((a[1:-1], b))
    return lm_a, lm_b, curves


def _residuals(va: CArmView, vb: CArmView, lm_a: np.ndarray, lm_b: np.ndarray, curves: list,
               kp: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    parts = []
    pa, pb = lm_a, lm_b
    if kp is not None:
        pa, pb = np.vstack([pa, kp[0][None]]), np.vstack([pb, kp[1][None]])
    if len(pa):
        X = triangulate(va, pa, vb, pb)
        parts += [(va.project(X) - pa).ravel(), (vb.project(X) - pb).ravel()]
    for a, b in curves:
        e = reconstruction_error(va, a[:, None, :], vb, b[None, :, :]).error_px
        parts.append(np.nanmin(np.nan_to_num(e, nan=1e3), axis=1))
    return np.concatenate(parts) if parts else np.zeros(0)


def _mean_error(va: CArmView, vb: CArmView, lm_a: np.ndarray, lm_b: np.ndarray, curves: list) -> float:
    errs = []
    if len(lm_a):
        errs.append(reconstruction_error(va, lm_a, vb, lm_b).error_px)
    for a, b in curves:
        e = reconstruction_error(va, a[:, None, :], vb, b[None, :, :]).error_px
        errs.append(np.nanmin(np.nan_to_num(e, nan=1e3), axis=1))
    return float(np.mean(np.concatenate(errs))) if errs else float("nan")


def refine_geometry(
    view_a: CArmView,
    graph_a: CentrelineGraph,
    view_b: CArmView,
    graph_b: CentrelineGraph,
    *,
    keypoints: tuple[Any, Any] | None = None,
    max_rotation_deg: float = 3.0,
    max_shift_mm: float = 10.0,
    min_gain_px: float = 0.2,
    min_error_px: float = 1.0,
    prior: float = 0.2,
    rounds: int = 2,
    keypoint_tol_px: float | None = KEYPOINT_TOL_PX,
    max_keypoint_shift_mm: float = MAX_KEYPOINT_SHIFT_MM,
    keypoint_confirmed: bool = False,
    landmark_scan: bool = True,
) -> Refinement:
    """Correct view B's pose relative to view A from the two centreline graphs.

    Parameters
    ----------
    view_a, view_b : CArmView
        The geometry from the files.
    graph_a, graph_b : CentrelineGraph
        Centreline graphs of the matched-phase frames.
    keypoints : ((2,), (2,)), optional
        A stationary object's key point (col, row) in frame A and frame B.
    max_rotation_deg, max_shift_mm : float
        Bounds of the angle corrections and of the isocentre shift fitted to
        the correspondences (after the key point's shift).
    min_gain_px : float
        The fit is applied only if it lowers the mean reconstruction error
        by at least this much and by at least 20 %.
    min_error_px : float
        No fit when the geometry (after the key point's shift) already
        explains the correspondences to this mean reconstruction error (px).
    prior : float
        Weight of the pull toward the starting geometry (per degree, per
        ``max_shift_mm / max_rotation_deg`` mm, relative to the residuals' RMS).
    rounds : int
        Correspondences are found again after each round.
    keypoint_tol_px : float or None
        When the key point's reconstruction error on the files' geometry
        exceeds this (px), view B is first shifted by
        :func:`keypoint_shift` (breathing, table or patient motion between
        the runs) and the shift is kept whatever the fit does. None: never.
    max_keypoint_shift_mm : float
        A key point that would need a longer shift is taken to be two
        different objects: no shift, a warning.
    keypoint_confirmed : bool
        True when the phase matching found no frame pair whose key point
        agrees (``PhaseMatch.least_error_mm`` above ``phase.DISAGREE_MM``):
        the heart sat elsewhere at every pair, and the key point's shift is
        made unless the landmarks clearly oppose it (fewer than
        ``KEYPOINT_CONFIRMED_SHARE`` of the landmark pairs agree with it as
        without it).
    landmark_scan : bool
        Where the key point gave no shift, scan view B across the epipolar
        lines for the shift at which most landmarks agree
        (:func:`landmark_shift`) and make it when it gives at least
        ``LANDMARK_SCAN_GAIN`` more agreeing landmarks than none and
        ``LANDMARK_SCAN_RATIO`` times as many (default True).

    Returns
    -------
    Refinement
    """
    check_view(view_a, "view_a")
    check_view(view_b, "view_b")
    for val, name in ((max_rotation_deg, "max_rotation_deg"), (max_shift_mm, "max_shift_mm"),
                      (max_keypoint_shift_mm, "max_keypoint_shift_mm")):
        if not (isinstance(val, (int, float)) and np.isfinite(val) and val > 0):
            raise ArgumentError(f"{name}: expected a positive number, got {val!r}")
    if keypoint_tol_px is not None and not (isinstance(keypoint_tol_px, (int, float))
                                            and np.isfinite(keypoint_tol_px) and keypoint_tol_px >= 0):
        raise ArgumentError(f"keypoint_tol_px: expected a number >= 0 or None, got {keypoint_tol_px!r}")
    for flag, name in ((keypoint_confirmed, "keypoint_confirmed"), (landmark_scan, "landmark_scan")):
        if not isinstance(flag, (bool, np.bool_)):
            raise ArgumentError(f"{name}: expected True or False, got {flag!r}")
    kp = None
    if keypoints is not None:
        kp = (np.asarray(keypoints[0], float).reshape(2), np.asarray(keypoints[1], float).reshape(2))
        if not (np.all(np.isfinite(kp[0])) and np.all(np.isfinite(kp[1]))):
            kp = None
    out = Refinement(applied=False, view_a=view_a, view_b=view_b)

    def kp_error(vb: CArmView) -> float:
        if kp is None:
            return float("nan")
        return float(reconstruction_error(view_a, kp[0], vb, kp[1]).error_px)

    # The key point first: a heart shifted between the runs, seen across the epipolar lines.
    start_b, shift = view_b, np.zeros(3)
    kp_before = kp_error(view_b)
    if kp is not None and keypoint_tol_px is not None and kp_before > keypoint_tol_px:
        t = keypoint_shift(view_a, kp[0], view_b, kp[1])
        moved = _moved(view_b, np.r_[0.0, 0.0, t])
        # The vessels' branch and end points must agree better with the shift: a key point that
        # is two different points of the catheter (a tip the segmentation cut short in one view)
        # disagrees while the vessels agree.
        check = (_landmarks_agreeing(view_a, graph_a, view_b, graph_b),
                 _landmarks_agreeing(view_a, graph_a, moved, graph_b))
        out.keypoint_landmarks = check
        if np.linalg.norm(t) > max_keypoint_shift_mm:
            out.warnings.append(
                f"the stationary object's key point disagrees by {kp_before:.1f} px and would need view B "
                f"shifted by {np.linalg.norm(t):.1f} mm (more than {max_keypoint_shift_mm:g} mm): taken to "
                "be two different objects, not shifted")
        elif check[1] <= check[0] and not (keypoint_confirmed
                                           and check[1] >= KEYPOINT_CONFIRMED_SHARE * check[0]):
            out.warnings.append(
                f"the stationary object's key point disagrees by {kp_before:.1f} px, but the vessels' branch "
                f"and end points agree no better with view B shifted to fit it ({check[1]} against "
                f"{check[0]} landmark pairs within {LANDMARK_CHECK_TOL_PX:g} px"
                + (", although no frame pair of the runs agrees" if keypoint_confirmed else "")
                + "): taken to be two different points of the object, not shifted")
        else:
            start_b, shift = moved, t
            out.warnings.append(
                f"the stationary object's key point disagreed by {kp_before:.1f} px between the chosen "
                "frames (the heart moved between the runs: breathing, or the patient or table): view B "
                f"shifted by {np.linalg.norm(t):.1f} mm {np.round(t, 1).tolist()} (LPS) to make it agree; a "
                "shift along the epipolar lines cannot be seen in two views and is not corrected "
                f"({check[1]} against {check[0]} landmark pairs within {LANDMARK_CHECK_TOL_PX:g} px"
                + ("; no frame pair of the runs agrees" if keypoint_confirmed else "") + ")")
    out.keypoint_px = (kp_before, kp_error(start_b))
    out.keypoint_shift_mm = shift.copy()
    if landmark_scan and not np.any(shift):
        # No shift from the key point (it agrees, or it was two different points): the vessels'
        # landmarks may still show a heart moved across the epipolar lines.
        t, n0, n1 = landmark_shift(view_a, graph_a, view_b, graph_b)
        out.landmark_counts = (n0, n1)
        if n1 >= max(n0 + LANDMARK_SCAN_GAIN, LANDMARK_SCAN_RATIO * n0) and np.any(t):
            start_b, shift = _moved(view_b, np.r_[0.0, 0.0, t]), t
            out.landmark_shift_mm = t.copy()
            out.keypoint_px = (kp_before, kp_error(start_b))
            out.warnings.append(
                f"the vessels' branch and end points agree best with view B shifted by "
                f"{np.linalg.norm(t):.1f} mm {np.round(t, 1).tolist()} (LPS) across the epipolar lines ({n1} "
                f"against {n0} of view A's {len(graph_a.landmarks)} landmarks within "
                f"{LANDMARK_SCAN_TOL_PX:g} px): the heart moved between the runs; shifted")
    if np.any(shift):
        out.applied, out.view_b, out.offset_mm = True, start_b, shift.copy()

    step_px = 6.0
    lm_a, lm_b, curves = _correspondences(view_a, graph_a, start_b, graph_b, True, step_px)
    out.landmarks, out.curve_points = len(lm_a), int(sum(len(a) for a, _ in curves))
    if len(lm_a) + out.curve_points < 8 or not curves:
        used = "key point's shift alone is used" if np.any(shift) else "files' geometry is used"
        out.warnings.append(f"too few correspondences to refine the geometry ({len(lm_a)} landmark pairs, "
                            f"{out.curve_points} branch samples); the {used}")
        return out
    before = _mean_error(view_a, start_b, lm_a, lm_b, curves)
    if before < min_error_px:
        out.after_px = before
        out.before_px = _mean_error(view_a, view_b, lm_a, lm_b, curves) if np.any(shift) else before
        return out
    lo = np.r_[-max_rotation_deg, -max_rotation_deg, [-max_shift_mm] * 3]
    hi = -lo
    p = np.zeros(5)
    scale = np.r_[1.0, 1.0, [max_shift_mm / max_rotation_deg] * 3]
    for _ in range(max(int(rounds), 1)):
        def fun(q: np.ndarray, la=lm_a, lb=lm_b, cv=curves) -> np.ndarray:
            r = _residuals(view_a, _moved(start_b, q), la, lb, cv, kp)
            # A pull toward the starting geometry pins the directions the images cannot see (e.g.
            # the baseline length) and keeps small motion differences from being fitted as pose.
            return np.r_[r, prior * np.sqrt(len(r)) * q / scale]

        sol = least_squares(fun, p, bounds=(lo, hi), loss="soft_l1", f_scale=2.0, x_scale=scale,
                            diff_step=1e-4, max_nfev=60)
        p = sol.x
        lm_a, lm_b, curves = _correspondences(view_a, graph_a, _moved(start_b, p), graph_b, True, step_px)
        if not curves:
            break
    vb = _moved(start_b, p)
    # Compare on the same correspondences (found with the refined geometry).
    after = _mean_error(view_a, vb, lm_a, lm_b, curves) if curves else float("inf")
    before_same = _mean_error(view_a, start_b, lm_a, lm_b, curves) if curves else before
    start_err = max(before, before_same)
    out.landmarks, out.curve_points = len(lm_a), int(sum(len(a) for a, _ in curves))
    if np.isfinite(after) and after <= 0.8 * start_err and start_err - after >= min_gain_px:
        out.applied = True
        out.view_b = vb
        out.rotation_deg = (float(p[0]), float(p[1]))
        out.offset_mm = shift + p[2:5]
        out.keypoint_px = (kp_before, kp_error(vb))
        out.after_px = after
    else:
        out.after_px = start_err
    files_err = _mean_error(view_a, view_b, lm_a, lm_b, curves) if curves and np.any(shift) else start_err
    out.before_px = max(start_err, files_err) if np.any(shift) else start_err
    if out.applied and out.view_b is vb and np.any(np.isclose(np.abs(p), hi, rtol=0.02)):
        out.warnings.append("a correction reached its bound (max_rotation_deg / max_shift_mm): the files' "
                            "geometry may be further off than refinement allows")
    return out
