"""Motion phase matching (paper §2.3): the frame pair of two runs at the same motion phase.

A stationary object (the centre of an injection/occlusion balloon, or the tip
of a catheter or pacing lead) is located in every frame of both runs from the
segmentation labels. Its key points are triangulated for every frame pair
(mid-point of the shortest segment between the two rays) and reprojected;
the pair's error is the larger of the two 2D errors in mm at the isocentre.
The pair with the least error is at the same cardiac and respiratory phase.
A single key point sees only its own motion across the epipolar planes, so
the vessels add their own evidence (:func:`epipolar_consistency`): a still
tree crosses every plane through both sources equally often in both views.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from .errors import ArgumentError, VesselcadError
from .geometry import CArmView, reconstruction_error
from .io.atomic import atomic_path
from .io.run import XARun

__all__ = [
    "PhaseError",
    "PhaseMatch",
    "KeyPointTrack",
    "OBJECTS",
    "find_keypoints",
    "image_margins",
    "error_matrix",
    "diagonal_mean",
    "epipolar_consistency",
    "match_phase",
    "ecg_phase",
    "plot_error_matrix",
]

#: Stationary objects, their label value and key point.
OBJECTS = {"balloon": 3, "catheter": 2, "lead": 4}
#: ``match_phase`` warns when no eligible pair's key point triangulates better than this (mm at
#: the isocentre): on consistent runs the best pair agrees to 0.0-0.45 mm (phantom,
#: 12 cases, also with 1.5° of header angle error; 1.2 mm with 3°), while geometry that does not
#: fit the images (wrong angles or SID/SOD, a large table shift, another object in one run) leaves
#: 4-13 mm (docs/phase.md, "When no pair agrees").
DISAGREE_MM = 2.0
_VESSEL = 1
#: ``match_phase``'s ``prefer_fill``: frames filled to this share of the run's largest vessel area
#: are preferred (docs/phase.md, "Restrictions").
PREFER_FILL = 0.9
_IN_PLANE = np.zeros((3, 3, 3), bool)
_IN_PLANE[1] = True  # 8-connectivity within a frame, never across frames


class PhaseError(VesselcadError, ValueError):
    """No usable stationary object, or no eligible frame pair."""


@dataclass
class KeyPointTrack:
    """Key points of one stationary object in every frame of a run.

    Attributes
    ----------
    object : str
        'balloon', 'catheter' or 'lead'.
    points_px : numpy.ndarray, shape (N, 2)
        ``(col, row)`` per frame; NaN where the object is missing or ambiguous.
    reason : list of str
        Per frame, '' when found, else why not ('absent', 'ambiguous', 'too small', 'no free end').
    """

    object: str
    points_px: np.ndarray
    reason: list[str]

    @property
    def found(self) -> np.ndarray:
        """Boolean mask of frames with a key point."""
        return np.all(np.isfinite(self.points_px), axis=1)


@dataclass
class PhaseMatch:
    """The result of motion phase matching.

    Attributes
    ----------
    frame_a, frame_b : int
        The chosen frame pair.
    error_mm, error_px : float
        Its reconstruction error (paper §2.3); NaN when no stationary object
        was used (``objects`` empty: chosen by the vessels alone).
    matrix : numpy.ndarray, shape (N_A, N_B)
        Reconstruction error of every pair in mm (NaN where a key point is
        missing, everywhere without a stationary object).
    score : numpy.ndarray, shape (N_A, N_B)
        What the pair is chosen by: ``matrix`` averaged along the diagonal
        over ``match_phase``'s ``window`` (equal to ``matrix`` for window 0),
        plus ``ecg_weight`` times the ECG phase difference when the ECG is used.
    objects : list of str
        The stationary object(s) used; with several, a pair's error is the
        largest. Empty when the pair was chosen by the vessels alone.
    keypoints_a, keypoints_b : dict of str to (N, 2) arrays
        Key points per object.
    eligible_a, eligible_b : numpy.ndarray of bool
        Frames allowed by the contrast (and ECG) restrictions.
    runner_up : (int, int) or None
        Best pair outside the chosen pair's +-1 frame neighbourhood.
    runner_up_error_mm, margin_mm : float
        Its score and the margin to the chosen pair's score (NaN without a runner-up).
    confidence : float
        ``1 - score / runner_up_score`` in [0, 1]: 0 ambiguous, 1 unique.
    point_mm : numpy.ndarray, shape (3,)
        The triangulated key point of the (first) object at the chosen pair
        (NaN without one).
    warnings : list of str
    fill_a, fill_b : numpy.ndarray
        Vessel area of every frame as a share of the run's largest (contrast
        filling; all ones when the labels have no vessel class).
    window : int
        The diagonal window the pair was chosen with.
    ecg : bool
        Whether the ECG restriction and weight were applied.
    consistency : numpy.ndarray, shape (N_A, N_B), or None
        :func:`epipolar_consistency` of the vessel masks of every pair (mean
        difference of vessel crossings per epipolar line), None when not used.
    vessel_weight : float
        Millimetres added to a pair's score per unit of ``consistency`` (0: not used).
    labelled_a, labelled_b : numpy.ndarray of bool, or None
        The frames whose labels were given (``match_phase``'s ``labelled_a``,
        ``labelled_b``); None: all.
    least_error_mm : float
        The smallest key point reconstruction error over the eligible pairs
        (NaN without a stationary object); above :data:`DISAGREE_MM` no pair
        agrees.
    """

    frame_a: int
    frame_b: int
    error_mm: float
    error_px: float
    matrix: np.ndarray
    score: np.ndarray
    objects: list[str]
    keypoints_a: dict[str, np.ndarray]
    keypoints_b: dict[str, np.ndarray]
    eligible_a: np.ndarray
    eligible_b: np.ndarray
    runner_up: tuple[int, int] | None
    runner_up_error_mm: float
    margin_mm: float
    confidence: float
    point_mm: np.ndarray
    warnings: list[str] = field(default_factory=list)
    fill_a: np.ndarray | None = None
    fill_b: np.ndarray | None = None
    window: int = 0
    ecg: bool = False
    consistency: np.ndarray | None = None
    vessel_weight: float = 0.0
    labelled_a: np.ndarray | None = None
    labelled_b: np.ndarray | None = None
    least_error_mm: float = float("nan")

    @property
    def basis(self) -> str:
        """What the pair was chosen by, in words (for reports)."""
        if not self.objects:
            return "the vessels' epipolar consistency alone (no stationary object)"
        return ", ".join(self.objects)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (without the matrix)."""
        return {
            "frame_a": self.frame_a, "frame_b": self.frame_b,
            "error_mm": _round_or_none(self.error_mm), "error_px": _round_or_none(self.error_px),
            "objects": self.objects,
            "runner_up": None if self.runner_up is None else list(self.runner_up),
            "runner_up_error_mm": None if not np.isfinite(self.runner_up_error_mm)
            else round(self.runner_up_error_mm, 4),
            "margin_mm": None if not np.isfinite(self.margin_mm) else round(self.margin_mm, 4),
            "confidence": round(self.confidence, 4),
            "eligible_frames_a": int(self.eligible_a.sum()), "eligible_frames_b": int(self.eligible_b.sum()),
            "point_mm": np.round(self.point_mm, 3).tolist() if np.isfinite(self.point_mm).all() else None,
            "fill": None if self.fill_a is None else [round(float(self.fill_a[self.frame_a]), 3),
                                                      round(float(self.fill_b[self.frame_b]), 3)],
            "window": self.window, "ecg": self.ecg,
            "labelled_frames_a": None if self.labelled_a is None else int(self.labelled_a.sum()),
            "labelled_frames_b": None if self.labelled_b is None else int(self.labelled_b.sum()),
            "vessel_consistency": None if self.consistency is None
            else round(float(self.consistency[self.frame_a, self.frame_b]), 4),
            "vessel_weight": self.vessel_weight,
            "warnings": list(self.warnings),
        }


def _round_or_none(x: float, digits: int = 4) -> float | None:
    """``round(x)``, or None (JSON null) for NaN: no key point, no error."""
    return round(float(x), digits) if np.isfinite(x) else None


# ---------------------------------------------------------------- key points
def _check_labels(labels: Any, name: str) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[0] == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise ArgumentError(f"{name}: expected integer label maps of shape (N, H, W), got "
                            f"{arr.dtype} {arr.shape}")
    return arr


def _components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    return ndimage.label(mask, structure=_IN_PLANE)


#: A margin row or column is darker than this share of the frame's central median ...
MARGIN_DARK = 0.5
#: ... and the outermost one darker than this share (a black frame, not dark anatomy at the edge).
MARGIN_EDGE_DARK = 0.2
#: Margins are looked for within this share of the frame's height or width from each edge.
MARGIN_MAX_SHARE = 0.15


def image_margins(frames: Any) -> np.ndarray:
    """Widths of the dark borders of each frame: export frames, shutters, collimator blades.

    Exported cines often carry a black frame of 5-15 px, and a collimated or
    shuttered field ends in a dark band; a device enters the image at the
    inner edge of that band, not at the array's edge. Per frame and side, the
    margin is the run of rows (columns) from the edge whose mean over the
    middle 60 % of the side is darker than :data:`MARGIN_DARK` times the
    median of the frame's central half, at most :data:`MARGIN_MAX_SHARE` of
    the frame, where the outermost is darker than :data:`MARGIN_EDGE_DARK`
    times that median (dark anatomy reaching the edge is no margin). A
    circular intensifier field gives the rows and columns where the circle
    covers less than the middle of the side (on the real 12-frame XA cine
    12-13 / 76 / 55-75 / 60 px: more than the circle leaves at mid-height).
    Frames without a dark border (the phantom's) give zeros.

    Parameters
    ----------
    frames : array_like, shape (N, H, W) or (H, W)
        Grey frames, any numeric dtype (dark = low values, as stored for display).

    Returns
    -------
    numpy.ndarray, shape (N, 4), int
        ``(top, bottom, left, right)`` margin widths in px.
    """
    f = np.asarray(frames)
    if f.ndim == 2:
        f = f[None]
    if f.ndim != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.number) or min(f.shape[1:]) < 8:
        raise ArgumentError(f"frames: expected grey frames of shape (N, H, W), got {f.dtype} {f.shape}")
    n, h, w = f.shape
    ref = np.median(f[:, h // 4: h - h // 4, w // 4: w - w // 4].reshape(n, -1), axis=1).astype(float)
    c0, c1, r0, r1 = w // 5, w - w // 5, h // 5, h - h // 5
    kh, kw = max(int(MARGIN_MAX_SHARE * h), 1), max(int(MARGIN_MAX_SHARE * w), 1)
    flip = f[:, ::-1, ::-1]
    profiles = (f[:, :kh, c0:c1].mean(axis=2, dtype=float), flip[:, :kh, c0:c1].mean(axis=2, dtype=float),
                f[:, r0:r1, :kw].mean(axis=1, dtype=float), flip[:, r0:r1, :kw].mean(axis=1, dtype=float))
    out = np.zeros((n, 4), int)
    for k, prof in enumerate(profiles):  # four sides
        dark = prof < MARGIN_DARK * ref[:, None]
        out[:, k] = np.where(prof[:, 0] < MARGIN_EDGE_DARK * ref, np.cumprod(dark, axis=1).sum(axis=1), 0)
    return out


def _balloon_centres(labels: np.ndarray, min_area_px: int) -> tuple[np.ndarray, list[str]]:
    """Centroid of the largest balloon component per frame (all frames at once)."""
    n = labels.shape[0]
    comp, k = _components(labels == OBJECTS["balloon"])
    out = np.full((n, 2), np.nan)
    reason = ["absent"] * n
    if k == 0:
        return out, reason
    f_, r_, c_ = np.nonzero(comp)
    ids = comp[f_, r_, c_]
    area = np.bincount(ids, minlength=k + 1)[1:].astype(np.float64)
    centre = np.stack([np.bincount(ids, weights=v, minlength=k + 1)[1:] for v in (f_, r_, c_)], 1)
    centre /= area[:, None]
    frame = centre[:, 0].round().astype(int)
    order = np.lexsort((-area, frame))  # per frame, largest first
    frame_s, area_s, centre_s = frame[order], area[order], centre[order]
    first = np.r_[True, frame_s[1:] != frame_s[:-1]]
    second = np.r_[False, first[:-1]] & ~first  # the runner-up component of a frame
    big = dict(zip(frame_s[first], zip(area_s[first], centre_s[first], strict=True), strict=True))
    runner = dict(zip(frame_s[second], area_s[second], strict=True))
    for f, (a, c) in big.items():
        if a < min_area_px:
            reason[f] = "too small"
        elif runner.get(f, 0.0) > 0.5 * a:
            reason[f] = "ambiguous"  # two balloon-sized blobs: do not guess
        else:
            out[f] = (c[2], c[1])  # (col, row)
            reason[f] = ""
    return out, reason


def _sample(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear sample of a float mask at (col, row) points."""
    m = mask.astype(np.float32)
    return ndimage.map_coordinates(m, [pts[:, 1], pts[:, 0]], order=1, mode="constant", cval=0.0)


# A device cut in two where it crosses other structures (see _breaks).
_BREAK_GAP_SHARE = 0.3  # of the image's longer side
_BREAK_ANGLE_DEG = 30.0
_BREAK_LABELLED = 0.7
# Pieces of one device split off where it crosses itself or vessels (see _joins): largest gap.
_JOIN_MIN_PX = 6.0
_JOIN_RADII = 4.0  # device radii
# Largest share of the path from the border to a device's tip that may run on other devices.
_MAX_OFF_SHARE = 0.5
# ndimage.binary_dilation's default structure (the 4-neighbour cross), for cv2.dilate.
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
# A free end at most this far (px, or device radii if more) along the skeleton from a junction
# is a spur (see _tip), not a tip.
_SPUR_MIN_PX = 6.0
_SPUR_RADII = 2.5
# A device piece whose border contacts span more than this share of the image's longer side
# crosses the field (enters and leaves it).
_CROSSING_SHARE = 0.25
# A free end that points at the image's edge at most this share of its longer side away, across
# a mostly labelled gap, is where the device leaves the image (see _edge_exits), not its tip.
_EXIT_SHARE = 0.1
_EXIT_LABELLED = 0.8


def _tip(frame: np.ndarray, value: int, border: int, min_length_px: int,
         margins: Sequence[int] = (0, 0, 0, 0)) -> tuple[np.ndarray | None, str]:
    """Sub-pixel distal tip of a tubular device in one frame.

    The tip is the free end of the skeleton farthest (along the skeleton) from
    where the device leaves the image (its edge, inside the dark ``margins``
    top, bottom, left, right); it is refined by following the end direction to
    the mask boundary and stepping back one local radius (the device ends in a
    round cap). Ends that face another across a labelled gap (a cut,
    :func:`_breaks`) or the image's edge (the device leaves the field as
    another class, :func:`_edge_exits`) are no tips.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, dijkstra
    from skimage.morphology import skeletonize

    mask = frame == value
    rows, cols = np.nonzero(mask)
    if rows.size < min_length_px:
        return None, "absent" if rows.size == 0 else "too small"
    # Devices drawn on top of this one (a lead crossing the catheter) cut its mask: skeletonize
    # the union of all devices so the pieces stay connected, then keep only free ends that lie
    # on this device away from the others.
    devices = np.isin(frame, list(OBJECTS.values()))
    rows, cols = np.nonzero(devices)
    r0, r1 = max(rows.min() - 2, 0), min(rows.max() + 3, mask.shape[0])
    c0, c1 = max(cols.min() - 2, 0), min(cols.max() + 3, mask.shape[1])
    sub = mask[r0:r1, c0:c1]
    # three steps of the 4-neighbour cross (ndimage.binary_dilation(..., iterations=3)), in OpenCV
    others = cv2.dilate((devices[r0:r1, c0:c1] & ~sub).view(np.uint8), _CROSS, iterations=3).view(bool)
    skel = skeletonize(devices[r0:r1, c0:c1])
    sr, sc = np.nonzero(skel)
    if sr.size < 2:
        return None, "too small"
    index = -np.ones(skel.shape, np.int64)
    index[sr, sc] = np.arange(sr.size)
    src, dst, wts = [], [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        rr, cc = sr + dr, sc + dc
        ok = (rr >= 0) & (rr < skel.shape[0]) & (cc >= 0) & (cc < skel.shape[1])
        j = np.full(sr.size, -1)
        j[ok] = index[rr[ok], cc[ok]]
        hit = j >= 0
        src.append(np.nonzero(hit)[0])
        dst.append(j[hit])
        wts.append(np.full(hit.sum(), np.hypot(dr, dc)))
    src, dst, wts = np.concatenate(src), np.concatenate(dst), np.concatenate(wts)
    own = sub[sr, sc]
    gr, gc = sr + r0, sc + c0
    xy = np.stack([gc, gr], axis=1).astype(float)
    # Skeletons stop about one radius short of where the mask meets the image edge.
    # exact Euclidean distances (OpenCV's precise mask: scipy's distance_transform_edt to float32,
    # 7x faster)
    dt = cv2.distanceTransform(np.pad(sub, 1).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    dt = dt.astype(np.float64)
    border = border + int(np.ceil(dt.max()))
    top, bottom, left, right = (int(m) for m in margins)
    at_border = (gr < border + top) | (gc < border + left) | (gr >= mask.shape[0] - border - bottom) | (
        gc >= mask.shape[1] - border - right)
    if not at_border.any():
        return None, "ambiguous"  # both ends inside the image: which is distal is unknown
    n = sr.size
    graph = coo_matrix((np.r_[wts, wts], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
    degree = np.diff(graph.indptr)
    # A segmentation that gives a few pixels of a device's edge to another class (a vessel it
    # crosses) leaves a notch, and the skeleton a spur: a free end a few pixels from a junction
    # of a device that goes on. A catheter crossing the whole field then had its spur's end for
    # a tip (phantom rca view A, model labels: 300 px off). Spurs are pruned (_prune_spurs) only on
    # a piece that meets the image border at two places far apart (a device crossing the whole
    # field): a device that enters once may end in a short branch past a junction.
    spur_px = max(_SPUR_MIN_PX, _SPUR_RADII * float(dt.max()))
    _, comp0 = connected_components(graph, directed=False)
    crossing = np.zeros(comp0.max() + 1, bool)
    for c in np.unique(comp0[at_border]):  # a few pieces per frame
        pts = xy[at_border & (comp0 == c)]
        crossing[c] = np.ptp(pts, axis=0).max() > _CROSSING_SHARE * max(mask.shape)
    keep = _prune_spurs(graph, xy, ~at_border & own & ~others[sr, sc] & crossing[comp0], spur_px)
    if not keep.all():
        kept = keep[src] & keep[dst]
        src, dst, wts = src[kept], dst[kept], wts[kept]
        graph = coo_matrix((np.r_[wts, wts], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
        degree = np.diff(graph.indptr)
    free = np.nonzero((degree == 1) & ~at_border & own & ~others[sr, sc])[0]
    # Where the segmentation gives a crossing to another class (vessels over the catheter),
    # the device is cut in two: the cut ends face each other; bridge them.
    i, j, cut_free = _breaks(free, frame, xy, graph)
    cut = np.zeros(n, bool)
    cut[free[cut_free]] = True
    # A free end pointing at the image's edge across pixels of another class is where the device
    # leaves the image (its last centimetres labelled vessel): a border point, not a tip.
    exits = free[_edge_exits(free, frame, xy, graph, margins) & ~cut_free]
    if exits.size:
        at_border = at_border.copy()
        at_border[exits] = True
        cut[exits] = True
    bridge = np.linalg.norm(xy[free[i]] - xy[free[j]], axis=1)
    on = np.r_[own[src] & own[dst], np.zeros(i.size, bool)]  # edges on this device; bridges are not
    src, dst, wts = np.r_[src, free[i]], np.r_[dst, free[j]], np.r_[wts, bridge]
    graph = coo_matrix((np.r_[wts, wts], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
    # A device enters the image at its border; its pieces that do (the projection can
    # split it, e.g. the aortic arch above the field) lead to the free distal end.
    _, comp = connected_components(graph, directed=False)
    entering = np.isin(comp, np.unique(comp[at_border]))
    # A piece split off where the device crosses itself or vessels (a guiding catheter's
    # contrast-filled shaft labelled vessel where its distal part crosses it) is joined to the
    # nearest piece that enters the image across a short labelled gap.
    join_px = max(_JOIN_MIN_PX, _JOIN_RADII * float(dt.max()))
    joins = _joins(xy, comp, entering, frame, join_px)
    if joins.size:
        a, b = joins.T
        gap = np.linalg.norm(xy[a] - xy[b], axis=1)
        on = np.r_[on, np.zeros(a.size, bool)]
        src, dst, wts = np.r_[src, a], np.r_[dst, b], np.r_[wts, gap]
        graph = coo_matrix((np.r_[wts, wts], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
        _, comp = connected_components(graph, directed=False)
        entering = np.isin(comp, np.unique(comp[at_border]))
    ends = free[entering[free] & ~cut[free]]
    if ends.size == 0:
        return None, "no free end"
    dist, pred, _ = dijkstra(graph, directed=False, indices=np.nonzero(at_border)[0], min_only=True,
                             return_predecessors=True)
    # The path in from the border may cross other devices (a lead over the catheter) or a
    # bridged cut, but mostly runs on this device: a fragment of its class that only another
    # device joins to the border (a vessel piece taken for catheter beside a lead) is no tip.
    off = np.where(on, 1e-9, wts)
    off_graph = coo_matrix((np.r_[off, off], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
    off_dist = dijkstra(off_graph, directed=False, indices=np.nonzero(at_border)[0], min_only=True)
    ends = ends[off_dist[ends] <= _MAX_OFF_SHARE * dist[ends]]
    if ends.size == 0:
        return None, "no free end"
    tip = ends[np.argmax(np.where(np.isfinite(dist[ends]), dist[ends], -1))]
    if not np.isfinite(dist[tip]):
        return None, "no free end"
    # Walk back along the skeleton to get the end direction and the local radius.
    path = [tip]
    while len(path) < 10 and pred[path[-1]] >= 0:
        path.append(pred[path[-1]])
    p_tip = np.array([gc[tip], gr[tip]], float)
    p_back = np.array([gc[path[-1]], gr[path[-1]]], float)
    direction = p_tip - p_back
    if np.linalg.norm(direction) < 1e-6:
        return None, "too small"
    direction /= np.linalg.norm(direction)
    mid = path[min(4, len(path) - 1)]
    radius = float(dt[sr[mid], sc[mid]])
    steps = np.arange(0.0, 4.0 * radius + 4.0, 0.1)
    ray = p_tip + steps[:, None] * direction
    inside = _sample(mask, ray) >= 0.5
    last = int(np.argmin(inside)) if not inside.all() else len(steps) - 1
    boundary = ray[max(last - 1, 0)] + 0.05 * direction  # half a step past the last inside sample
    # A round cap ends half a pixel beyond the last covered pixel centre, one radius past its centre.
    return boundary + (0.5 - radius) * direction, ""


def _labelled_share(frame: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    """Share of the pixels on the straight gap between (x, y) points p and q that carry a label."""
    m = max(int(np.linalg.norm(q - p)), 2)
    t = np.linspace(0.0, 1.0, m + 1)[1:-1, None]
    pts = np.rint(p + t * (q - p)).astype(int)
    return float((frame[pts[:, 1], pts[:, 0]] != 0).mean())


def _joins(xy: np.ndarray, comp: np.ndarray, entering: np.ndarray, frame: np.ndarray,
           join_px: float) -> np.ndarray:
    """Edges (k, 2) joining skeleton pieces that do not enter the image to pieces that do.

    Each such piece is joined once, by its skeleton point nearest to an entering
    piece (or to a piece joined before it), when that gap is at most ``join_px``
    and its straight line is mostly labelled (not background).
    """
    from scipy.spatial import cKDTree

    reach = entering.copy()
    out: list[tuple[int, int]] = []
    for _ in range(16):  # a few pieces per frame: grow the reached set piece by piece
        if reach.all():
            break
        free = np.nonzero(~reach)[0]
        d, k = cKDTree(xy[reach]).query(xy[free], distance_upper_bound=join_px)
        ok = np.isfinite(d)
        if not ok.any():
            break
        targets = np.nonzero(reach)[0]
        order = np.argsort(d[ok])
        a_all, b_all = free[ok][order], targets[k[ok][order]]
        _, first = np.unique(comp[a_all], return_index=True)
        joined = False
        for i in first[np.argsort(d[ok][order][first])]:
            a, b = int(a_all[i]), int(b_all[i])
            if _labelled_share(frame, xy[a], xy[b]) < _BREAK_LABELLED:
                continue
            out.append((a, b))
            reach |= comp == comp[a]
            joined = True
            break  # re-measure from the grown set
        if not joined:
            break
    return np.array(out, int).reshape(-1, 2)


def _prune_spurs(graph: Any, xy: np.ndarray, candidate: np.ndarray, spur_px: float) -> np.ndarray:
    """Skeleton nodes kept after removing spurs (boolean per node).

    Junction pixels (degree >= 3) that touch are one junction. A terminal
    branch (from a free end in ``candidate`` to one junction) of at most
    ``spur_px`` is a spur where the junction has at least two other branches
    (the device goes on through it: all such spurs go). Where it has one (a
    skeleton often ends in a short fork), the longest short branch stays: it
    leads to the device's end.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = xy.shape[0]
    keep = np.ones(n, bool)
    g = graph.tocoo()
    degree = np.diff(graph.tocsr().indptr)
    junction = degree >= 3
    if not junction.any():
        return keep
    src, dst = g.row, g.col
    inner = junction[src] & junction[dst]
    _, cluster = connected_components(coo_matrix((np.ones(inner.sum()), (src[inner], dst[inner])),
                                                 shape=(n, n)), directed=False)
    plain = ~junction[src] & ~junction[dst]
    _, branch = connected_components(coo_matrix((np.ones(plain.sum()), (src[plain], dst[plain])),
                                                shape=(n, n)), directed=False)
    nb = int(branch.max()) + 1
    on_branch = ~junction
    size = np.bincount(branch[on_branch], minlength=nb)
    # a branch's length: its nodes plus the step into the junction
    length = np.bincount(branch[src[plain]], weights=np.linalg.norm(xy[src[plain]] - xy[dst[plain]], axis=1),
                         minlength=nb) / 2.0 + 1.0
    free_end = np.bincount(branch[on_branch & (degree == 1) & candidate], minlength=nb) > 0
    link = junction[dst] & ~junction[src]  # branch node -> junction node
    pairs = np.unique(np.stack([branch[src[link]], cluster[dst[link]]], axis=1), axis=0)
    touches = np.bincount(pairs[:, 0], minlength=nb)
    terminal = free_end & (touches == 1) & (size > 0)
    short = terminal & (length <= spur_px)
    if not short.any():
        return keep
    drop = np.zeros(nb, bool)
    for c in np.unique(pairs[short[pairs[:, 0]], 1]):  # junctions with short branches: a few
        at = pairs[pairs[:, 1] == c, 0]
        spurs = at[short[at]]
        if at.size - spurs.size < 2:  # the device ends here: the longest short branch stays
            spurs = spurs[spurs != spurs[np.argmax(length[spurs])]]
        drop[spurs] = True
    keep[on_branch & drop[branch]] = False
    return keep


def _end_directions(ends: np.ndarray, xy: np.ndarray, graph: Any, back: int = 10) -> np.ndarray:
    """Unit directions (x, y) out of a skeleton at its free ends, over ``back`` skeleton steps."""
    out = np.zeros((ends.size, 2))
    ptr, nbr = graph.indptr, graph.indices
    for k, e in enumerate(ends):  # a short walk per free end (a handful per frame)
        prev, cur = -1, e
        for _ in range(back):
            nxt = [v for v in nbr[ptr[cur]:ptr[cur + 1]] if v != prev]
            if not nxt:
                break
            prev, cur = cur, nxt[0]
        d = xy[e] - xy[cur]
        norm = np.linalg.norm(d)
        out[k] = d / norm if norm > 0 else 0.0
    return out


def _edge_exits(ends: np.ndarray, frame: np.ndarray, xy: np.ndarray, graph: Any,
                margins: Sequence[int]) -> np.ndarray:
    """Free ends where a device leaves the image through pixels given to another class.

    A segmentation model often labels a catheter's last centimetres before the
    image edge vessel (phantom rca view A: the shaft crossing the field ends
    35 px above the bottom edge); its free end there was taken for the tip,
    300 px from it. Such an end points at the image's edge (inside the dark
    ``margins`` top, bottom, left, right): the ray along its end direction
    leaves the field within ``_EXIT_SHARE`` of the image's longer side, and
    that stretch is mostly labelled (``_EXIT_LABELLED``, not background). A
    device that simply ends near the edge leaves background there.

    Returns
    -------
    bool array
        Per end: the device leaves the image there.
    """
    out = np.zeros(ends.size, bool)
    if ends.size == 0:
        return out
    h, w = frame.shape
    top, bottom, left, right = (int(m) for m in margins)
    lo = np.array([left, top], float) - 0.5
    hi = np.array([w - right, h - bottom], float) - 0.5
    d = _end_directions(ends, xy, graph)
    p = xy[ends]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf)).min(axis=1)
    reach = _EXIT_SHARE * max(h, w)
    near = np.nonzero((np.abs(d).sum(axis=1) > 0) & (t <= reach))[0]
    if near.size == 0:
        return out
    # labelled within a pixel of the ray: a skeleton's end direction is off by a few degrees
    labelled = ndimage.maximum_filter(frame != 0, size=3)
    for k in near:  # a handful per frame
        q = np.clip(p[k] + max(t[k] - 0.5, 0.0) * d[k], 0, [w - 1, h - 1])
        out[k] = _labelled_share(labelled, p[k], q) >= _EXIT_LABELLED
    return out


def _breaks(ends: np.ndarray, frame: np.ndarray, xy: np.ndarray, graph: Any
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Free ends where the segmentation cut a device in two: the pairs to bridge and all cut ends.

    Where a device crosses vessels or another device, the segmentation often
    gives the crossing to the other class. The two cut ends then face each
    other (each lies ahead of the other, within ``_BREAK_ANGLE_DEG`` of its
    end direction), at most ``_BREAK_GAP_SHARE`` of the image's longer side
    apart (a catheter crossing a bundle of vessels loses up to ~140 px of a
    512² frame), and the straight gap between them is mostly labelled (not
    background). Each end is bridged to its nearest such partner; every end
    that faces one is a cut end (a fork of the skeleton at the cut gives two).

    Returns
    -------
    i, j : int arrays
        Pairs (indices into ``ends``) to bridge.
    cut : bool array
        Per end: faces a partner across a labelled gap.
    """
    none = np.zeros(0, int)
    cut = np.zeros(ends.size, bool)
    if ends.size < 2:
        return none, none, cut
    d = _end_directions(ends, xy, graph)
    p = xy[ends]
    v = p[None, :, :] - p[:, None, :]  # v[i, j]: from end i to end j
    gap = np.linalg.norm(v, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / gap[:, :, None]
    ahead = np.einsum("ijk,ik->ij", u, d) >= np.cos(np.radians(_BREAK_ANGLE_DEG))  # j ahead of i
    facing = ahead & ahead.T & (gap > 0) & (gap <= _BREAK_GAP_SHARE * max(frame.shape))
    pairs = []
    taken = np.zeros(ends.size, bool)
    for i, j in sorted(zip(*np.nonzero(np.triu(facing)), strict=True), key=lambda ij: gap[ij]):
        if _labelled_share(frame, p[i], p[j]) < _BREAK_LABELLED:
            continue
        cut[[i, j]] = True
        if not (taken[i] or taken[j]):
            pairs.append((i, j))
            taken[[i, j]] = True
    if not pairs:
        return none, none, cut
    i, j = np.array(pairs).T
    return i, j, cut


def find_keypoints(labels: Any, obj: str, *, min_area_px: int = 12, border_px: int = 4,
                   frames: Any = None) -> KeyPointTrack:
    """Key points of a stationary object in every frame of a label stack.

    Parameters
    ----------
    labels : array_like, shape (N, H, W)
        Segmentation labels (0 background, 1 vessel, 2 catheter, 3 balloon, 4 lead).
    obj : {'balloon', 'catheter', 'lead'}
        The balloon gives the centroid of its largest component (sub-pixel);
        a catheter or lead gives its distal tip (sub-pixel, see ``_tip``).
    min_area_px : int
        Smaller objects count as absent.
    border_px : int
        Skeleton pixels this close to the image edge are where a device enters.
    frames : array_like, shape (N, H, W), optional
        The grey frames the labels belong to: a device then enters at the
        inner edge of their dark borders (:func:`image_margins`; exported cines
        carry a black frame, collimated fields a dark band), not only at the
        array's edge.

    Returns
    -------
    KeyPointTrack
        NaN and a reason in frames where the object is missing or ambiguous.
    """
    lab = _check_labels(labels, "labels")
    if obj not in OBJECTS:
        raise ArgumentError(f"obj: expected one of {list(OBJECTS)}, got {obj!r}")
    shape = np.shape(frames)
    if frames is not None and (shape if len(shape) != 2 else (1, *shape)) != lab.shape:
        raise ArgumentError(f"frames: shape {np.shape(frames)} does not match the labels' {lab.shape}")
    if obj == "balloon":
        pts, reason = _balloon_centres(lab, min_area_px)
        return KeyPointTrack(obj, pts, reason)
    margins = np.zeros((lab.shape[0], 4), int) if frames is None else image_margins(frames)
    pts = np.full((lab.shape[0], 2), np.nan)
    reason = []
    for i in range(lab.shape[0]):  # one skeleton per frame
        p, why = _tip(lab[i], OBJECTS[obj], border_px, min_area_px, margins[i])
        if p is not None:
            pts[i] = p
        reason.append(why)
    return KeyPointTrack(obj, pts, reason)


# ------------------------------------------------------------ error matrix
def error_matrix(view_a: CArmView, points_a_px: Any, view_b: CArmView, points_b_px: Any) -> np.ndarray:
    """Reconstruction error (mm at the isocentre) of every key point pair, shape (N_A, N_B).

    Vectorised: one broadcast triangulation of all pairs; NaN where a key point is NaN.
    """
    pa = np.asarray(points_a_px, dtype=np.float64)
    pb = np.asarray(points_b_px, dtype=np.float64)
    return reconstruction_error(view_a, pa[:, None, :], view_b, pb[None, :, :]).error_mm


def ecg_phase(run: XARun, *, steady_tolerance: float = 0.75) -> np.ndarray | None:
    """Cardiac phase in [0, 1) per frame from the run's R-waves, or None.

    RWavePointer gives each R-wave as the number of the frame nearest to it, so
    every R-wave time is off by up to half a frame (0.056 cycle at 100 bpm and
    15 fps). When the R-waves fit a steady heart rate (a straight line through
    their times, every residual within ``steady_tolerance`` frame intervals:
    the rounding plus a little beat-to-beat variation), the phase comes from
    that line, which averages the rounding out over the run's beats (on the
    phantom: mean error 0.011 cycle instead of 0.018, largest 0.045 instead
    of 0.056). Otherwise (an irregular rhythm, or only two R-waves) it is
    linear in time between consecutive R-waves, with the mean RR interval
    before the first and after the last. Needs at least two R-waves.

    Parameters
    ----------
    run : XARun
        A run with ``r_wave_frames`` (from RWavePointer) and ``frame_times_ms``.
    steady_tolerance : float
        Largest residual of the straight-line fit, in frame intervals, for
        the heart rate to count as steady (0: always interpolate between R-waves).

    Returns
    -------
    numpy.ndarray or None
        Shape (N,), or None when the run has fewer than two R-waves.
    """
    if not isinstance(run, XARun):
        raise ArgumentError(f"run: expected an XARun, got {type(run).__name__}")
    if not steady_tolerance >= 0.0:
        raise ArgumentError(f"steady_tolerance: expected frame intervals >= 0, got {steady_tolerance}")
    if run.r_wave_frames is None or len(run.r_wave_frames) < 2:
        return None
    t = run.frame_times_ms
    tr = t[np.asarray(run.r_wave_frames)]
    rr = float(np.mean(np.diff(tr)))
    if rr <= 0:
        return None
    if len(tr) >= 3 and steady_tolerance > 0:
        beat = np.arange(len(tr), dtype=float)
        slope, start = np.polyfit(beat, tr, 1)
        frame_ms = float(np.median(np.diff(t))) if len(t) > 1 else rr
        residual = np.abs(tr - (start + slope * beat))
        if slope > 0 and residual.max() <= steady_tolerance * frame_ms:
            return np.mod((t - start) / slope, 1.0)
    n_before = int(np.ceil((tr[0] - t[0]) / rr)) + 1
    n_after = int(np.ceil((t[-1] - tr[-1]) / rr)) + 1
    knots = np.r_[tr[0] - rr * np.arange(n_before, 0, -1), tr, tr[-1] + rr * np.arange(1, n_after + 1)]
    k = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
    return np.mod((t - knots[k]) / (knots[k + 1] - knots[k]), 1.0)


def diagonal_mean(matrix: np.ndarray, window: int) -> np.ndarray:
    """Weighted mean of ``matrix`` over ``(i + k, j + k)`` for ``k`` in ``[-window, window]``.

    Pairs in phase stay in phase when both runs advance a frame (at similar
    frame and heart rates), while a pair whose single key point agrees by
    coincidence does not: the mean along the diagonal rejects coincidences.
    Weights fall off linearly (``window + 1 - |k|``) because the farther pairs
    drift apart with any heart-rate difference between the runs. NaN and
    out-of-range entries are ignored; fewer than ``window + 1`` valid entries
    give NaN.
    """
    if window <= 0:
        return matrix.copy()
    n_a, n_b = matrix.shape
    padded = np.full((n_a + 2 * window, n_b + 2 * window), np.nan)
    padded[window:window + n_a, window:window + n_b] = matrix
    ks = np.arange(-window, window + 1)
    stack = np.stack([padded[window + k:window + k + n_a, window + k:window + k + n_b] for k in ks])
    weights = (window + 1.0 - np.abs(ks))[:, None, None]
    valid = np.isfinite(stack)
    total = np.nansum(stack * weights, axis=0)
    norm = (valid * weights).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = total / norm
    return np.where((valid.sum(axis=0) >= window + 1) & np.isfinite(matrix), out, np.nan)


def _fill(labels: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
    """Vessel area per frame as a share of the run's largest (1 everywhere without vessels).

    With ``known`` (the labelled frames), the others get 0.
    """
    area = (labels == _VESSEL).sum(axis=(1, 2)).astype(float)
    if known is not None:
        area[~known] = 0.0
    if area.max() == 0:
        return np.ones(labels.shape[0]) if known is None else known.astype(float)
    return area / area.max()


#: Sampling step along each epipolar line (px) of :func:`epipolar_consistency`.
_LINE_STEP_PX = 0.7


def _epipolar_lines(view_a: CArmView, view_b: CArmView, n_lines: int
                    ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """Sample points of ``n_lines`` shared epipolar planes in each view.

    The planes of the pencil through both sources are indexed by their angle
    about the baseline, over the range both images see; each plane projects to
    a straight line in each view. Returns per view ``(points (K, T, 2), inside
    (K, T))``, or None when the two sources coincide.
    """
    sa, sb = view_a.source, view_b.source
    base = sb - sa
    if np.linalg.norm(base) < 1e-6:
        return None
    b = base / np.linalg.norm(base)
    centre = 0.5 * (np.asarray(view_a.offset_mm, float) + np.asarray(view_b.offset_mm, float))
    w = (centre - sa) - ((centre - sa) @ b) * b
    radius = float(np.linalg.norm(w))
    if radius < 1e-6:
        return None
    e1 = w / radius
    e2 = np.cross(b, e1)
    along = float((centre - sa) @ b)
    limits = []
    for v in (view_a, view_b):
        corners = np.array([[0, 0], [v.cols - 1, 0], [0, v.rows - 1], [v.cols - 1, v.rows - 1]], float)
        q = v.pixel_to_detector(corners) - sa
        limits.append(np.arctan2(q @ e2, q @ e1))
    lo = max(limits[0].min(), limits[1].min())
    hi = min(limits[0].max(), limits[1].max())
    if not hi > lo:
        return None
    kappa = np.linspace(lo, hi, n_lines + 2)[1:-1]
    normal = np.cos(kappa)[:, None] * e1 + np.sin(kappa)[:, None] * e2
    p1_3d = sa + along * b + radius * normal  # two points of each plane, near the heart
    p2_3d = p1_3d + 80.0 * b
    out = []
    for v in (view_a, view_b):
        p1, p2 = v.project(p1_3d), v.project(p2_3d)
        d = p2 - p1
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        # Clip each line to the image rectangle (slab method), then sample it evenly.
        lo_t = np.full(n_lines, -np.inf)
        hi_t = np.full(n_lines, np.inf)
        for k, size in ((0, v.cols), (1, v.rows)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t0 = (-0.5 - p1[:, k]) / d[:, k]
                t1 = (size - 0.5 - p1[:, k]) / d[:, k]
            flat = np.abs(d[:, k]) < 1e-12
            inside_k = (p1[:, k] >= -0.5) & (p1[:, k] <= size - 0.5)
            t_lo = np.where(flat, np.where(inside_k, -np.inf, np.inf), np.minimum(t0, t1))
            t_hi = np.where(flat, np.where(inside_k, np.inf, -np.inf), np.maximum(t0, t1))
            lo_t, hi_t = np.maximum(lo_t, t_lo), np.minimum(hi_t, t_hi)
        n = int(np.ceil(np.hypot(v.cols, v.rows) / _LINE_STEP_PX)) + 1
        t = lo_t[:, None] + _LINE_STEP_PX * np.arange(n)[None, :]
        inside = (t <= hi_t[:, None]) & np.isfinite(t)
        pts = p1[:, None, :] + np.where(inside, t, 0.0)[..., None] * d[:, None, :]
        out.append((pts, inside))
    return out[0], out[1]


def _crossings(mask: np.ndarray, pts: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Vessel crossings of every epipolar line in every frame: (N, K) run counts."""
    n, h, w = mask.shape
    c = np.clip(np.rint(pts[..., 0]).astype(np.intp), 0, w - 1)
    r = np.clip(np.rint(pts[..., 1]).astype(np.intp), 0, h - 1)
    s = mask[:, r, c] & inside[None]

    def neighbours(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        left, right = np.zeros_like(x), np.zeros_like(x)
        left[..., 1:], right[..., :-1] = x[..., :-1], x[..., 1:]
        return left, right

    # Along each line, close one-sample gaps and drop one-sample runs (label noise).
    left, right = neighbours(s)
    s = s | (left & right)
    left, right = neighbours(s)
    s = s & (left | right)
    starts = s[..., 1:] & ~s[..., :-1]
    return starts.sum(axis=2) + s[..., 0]


def epipolar_consistency(view_a: CArmView, labels_a: Any, view_b: CArmView, labels_b: Any,
                         *, n_lines: int = 256) -> np.ndarray:
    """How well the vessel masks of every frame pair agree along shared epipolar lines.

    Each plane through both X-ray sources projects to one line in each view,
    and a 3D vessel tree crosses it equally often in both projections: the
    number of vessel crossings along an epipolar line is the same in both
    views of a still tree (apart from overlaps and vessels leaving the
    field). It changes where a vessel turns back within the plane pencil or
    ends, and those places move between the planes when the heart is at
    another cardiac or respiratory phase in the two frames, along the whole
    tree and not only at the one stationary key point. The measure is the
    mean absolute difference of the crossing counts over ``n_lines`` planes
    spanning the field both views see (0 for a perfect pair).

    Parameters
    ----------
    view_a, view_b : CArmView
        Geometry of the two runs.
    labels_a, labels_b : array_like, shape (N, H, W) or (H, W)
        Segmentation labels per frame (vessel = 1).
    n_lines : int
        Number of epipolar planes sampled (>= 8).

    Returns
    -------
    numpy.ndarray, shape (N_A, N_B)
        Mean crossing-count difference per line for every frame pair.

    Raises
    ------
    ArgumentError
        Bad labels or ``n_lines``; views whose sources coincide or whose fields
        share no epipolar plane.
    """
    if isinstance(n_lines, bool) or not isinstance(n_lines, (int, np.integer)) or n_lines < 8:
        raise ArgumentError(f"n_lines: expected an integer >= 8, got {n_lines!r}")
    la, lb = _check_labels(labels_a, "labels_a"), _check_labels(labels_b, "labels_b")
    for name, lab, v, vname in (("labels_a", la, view_a, "view_a"), ("labels_b", lb, view_b, "view_b")):
        if not isinstance(v, CArmView):
            raise ArgumentError(f"{vname}: expected a CArmView, got {type(v).__name__}")
        if lab.shape[1:] != (v.rows, v.cols):
            raise ArgumentError(f"{name}: frames of {lab.shape[1:]} do not match {vname}'s "
                                f"{v.rows} x {v.cols} pixels")
    lines = _epipolar_lines(view_a, view_b, int(n_lines))
    if lines is None:
        raise ArgumentError("view_a/view_b: the two views share no epipolar planes (same source "
                            "position, or fields that see no common plane)")
    (pa, ia), (pb, ib) = lines
    na = _crossings(la == _VESSEL, pa, ia).astype(np.float32)
    nb = _crossings(lb == _VESSEL, pb, ib).astype(np.float32)
    return np.abs(na[:, None, :] - nb[None, :, :]).mean(axis=2).astype(np.float64)


def match_phase(
    run_a: XARun,
    run_b: XARun,
    labels_a: Any,
    labels_b: Any,
    *,
    objects: str | Sequence[str] = "auto",
    min_contrast: float = 0.5,
    prefer_fill: float = PREFER_FILL,
    use_ecg: bool | None = None,
    ecg_tolerance: float = 0.06,
    ecg_weight: float = 10.0,
    vessel_weight: float = 10.0,
    pair: tuple[int, int] | None = None,
    window: int | None = None,
    labelled_a: Any = None,
    labelled_b: Any = None,
) -> PhaseMatch:
    """Choose the frame pair of two runs at the same motion phase (paper §2.3).

    Parameters
    ----------
    run_a, run_b : XARun
        The two runs (their views give the projection geometry).
    labels_a, labels_b : array_like, shape (N, H, W)
        Segmentation labels of every frame (``vc.Segmenter()(run.frames)``).
    objects : 'auto', str or sequence of str
        Stationary object(s): 'balloon', 'catheter', 'lead'. 'auto' takes the
        first of these found in at least a quarter of the frames of both runs.
        With several objects a pair's error is the largest over them.
        'vessels': no stationary object; the pair is chosen by the vessels'
        :func:`epipolar_consistency` alone (``vessel_weight`` must be > 0).
        'auto' falls back to that, with a warning, when no object is found in
        both runs (a real run whose catheter tip leaves the field, or that the
        segmentation labels vessel); ``matrix``, ``error_mm`` and ``point_mm``
        are then NaN.
    min_contrast : float
        Only frames whose vessel area is at least this share of the run's
        largest are eligible, so the chosen pair shows filled vessels (0: all).
    prefer_fill : float
        When some eligible pair has key points and both frames at least this
        share of the run's largest vessel area, only such pairs are considered:
        a frame in wash-in or wash-out can keep 60-85 % of the area while a
        whole proximal or distal part is empty, and a vessel missing in one
        view cannot be reconstructed (1 or above: off).
    use_ecg : bool or None
        When both runs carry ECG R-waves (RWavePointer), only pairs whose ECG
        cardiac phases (:func:`ecg_phase`) differ by at most ``ecg_tolerance``
        (cycle fraction) are eligible, if any such pair has key points, and
        the phase difference is added to the score with ``ecg_weight``.
        None (default): only when the vessel term (``vessel_weight``) is not
        used. R-waves are stored to the nearest frame, so the ECG phase of a
        frame is off by 0.01-0.03 cycle, up to 1-2 mm of systolic motion; the
        vessels themselves tell the phase better (docs/phase.md).
    ecg_tolerance : float
        Largest ECG phase difference of an eligible pair, in (0, 0.5].
    ecg_weight : float
        Millimetres added to a pair's score per cycle of ECG phase difference
        (>= 0): at 10, a pair 0.05 cycle apart must agree 0.5 mm better than
        an in-phase one to win. The key point alone constrains one direction
        of motion, so among pairs within the tolerance it would otherwise
        often pick one that is off in cardiac phase but agrees by coincidence.
    vessel_weight : float
        Millimetres added to a pair's score per unit of
        :func:`epipolar_consistency` of its vessel masks (mean difference of
        vessel crossings per epipolar line; >= 0, 0: off). A single key point
        sees only its own motion across the epipolar planes; the vessels show
        the motion of the whole tree. At 10, a pair whose masks differ by one
        crossing on a tenth of the lines must agree 1 mm better at the key
        point to win. Used when the labels of both runs hold vessel pixels.
    pair : (int, int), optional
        Force this frame pair (its error is still reported).
    window : int, optional
        The pair is chosen by the weighted mean error over ``(i + k, j + k)``,
        ``|k| <= window`` (see :func:`diagonal_mean`): a single key point
        constrains only its motion across the epipolar plane, so some pair at
        another phase often agrees by coincidence; its neighbours do not.
        ``window=0`` is the paper's choice by the single pair's error. None
        (default): 0 when the vessel term or the ECG restriction applies (they
        fix the phase along the whole tree, resp. the cardiac phase), else 4.
    labelled_a, labelled_b : array_like of bool, shape (N,), optional
        The frames whose labels were computed, when only some were (a
        coarse-to-fine search, ``reconstruct``): the others are never chosen,
        have no key point and count neither in the run's largest vessel area
        nor in an object's presence. Default: every frame.

    Returns
    -------
    PhaseMatch

    Raises
    ------
    PhaseError
        No requested object is found in both runs, or no eligible pair has key points.
    """
    for name, run in (("run_a", run_a), ("run_b", run_b)):
        if not isinstance(run, XARun):
            raise ArgumentError(f"{name}: expected an XARun, got {type(run).__name__}")
    la, lb = _check_labels(labels_a, "labels_a"), _check_labels(labels_b, "labels_b")
    for name, lab, run in (("labels_a", la, run_a), ("labels_b", lb, run_b)):
        if lab.shape != run.frames.shape:
            raise ArgumentError(f"{name}: shape {lab.shape} does not match the run's frames "
                                f"{run.frames.shape}")
    known = []
    for name, mask, n_run in (("labelled_a", labelled_a, la.shape[0]),
                              ("labelled_b", labelled_b, lb.shape[0])):
        k = np.ones(n_run, bool) if mask is None else np.asarray(mask)
        if k.shape != (n_run,) or k.dtype != bool or not k.any():
            raise ArgumentError(f"{name}: expected None or {n_run} booleans with at least one True, got "
                                f"{mask!r:.60}")
        known.append(k)
    known_a, known_b = known
    if window is not None and (isinstance(window, bool) or not isinstance(window, (int, np.integer))
                               or window < 0):
        raise ArgumentError(f"window: expected None or a non-negative integer, got {window!r}")
    if not 0.0 <= min_contrast <= 1.0:
        raise ArgumentError(f"min_contrast: expected a share in [0, 1], got {min_contrast}")
    if not 0.0 < ecg_tolerance <= 0.5:
        raise ArgumentError(f"ecg_tolerance: expected a cycle fraction in (0, 0.5], got {ecg_tolerance}")
    if not ecg_weight >= 0.0:
        raise ArgumentError(f"ecg_weight: expected mm per cycle >= 0, got {ecg_weight}")
    if not (np.isfinite(vessel_weight) and vessel_weight >= 0.0):
        raise ArgumentError(f"vessel_weight: expected mm >= 0, got {vessel_weight}")
    if use_ecg is not None and not isinstance(use_ecg, (bool, np.bool_)):
        raise ArgumentError(f"use_ecg: expected True, False or None, got {use_ecg!r}")
    if not prefer_fill >= 0.0:
        raise ArgumentError(f"prefer_fill: expected a share >= 0, got {prefer_fill}")
    if isinstance(objects, str) and objects == "vessels":
        wanted: list[str] = []
        if vessel_weight <= 0.0:
            raise ArgumentError("vessel_weight: objects='vessels' chooses the pair by the vessels alone; "
                                "expected vessel_weight > 0, got 0")
    elif isinstance(objects, str) and objects == "auto":
        wanted = list(OBJECTS)
    elif isinstance(objects, str):
        wanted = [objects]
    else:
        wanted = list(objects)
    bad = [o for o in wanted if o not in OBJECTS]
    if bad or (not wanted and objects != "vessels"):
        raise ArgumentError(f"objects: expected 'auto', 'vessels' or some of {list(OBJECTS)}, "
                            f"got {objects!r}")
    has_vessels = bool((la[known_a] == _VESSEL).any() and (lb[known_b] == _VESSEL).any())

    warnings_: list[str] = []
    tracks_a, tracks_b = {}, {}
    for obj in wanted:
        present_a = (la[known_a] == OBJECTS[obj]).any(axis=(1, 2)).mean()
        present_b = (lb[known_b] == OBJECTS[obj]).any(axis=(1, 2)).mean()
        if objects == "auto" and (present_a < 0.25 or present_b < 0.25):
            continue
        ta = _track_known(la, obj, run_a.frames, known_a)
        tb = _track_known(lb, obj, run_b.frames, known_b)
        if ta.found.any() and tb.found.any():
            tracks_a[obj], tracks_b[obj] = ta, tb
            if objects == "auto":
                break
        elif objects != "auto":
            missing = "run A" if not ta.found.any() else "run B"
            raise PhaseError(f"objects: no {obj} key point found in any frame of {missing}")
    vessels_only = not tracks_a
    if vessels_only and wanted:
        if not (has_vessels and vessel_weight > 0.0):
            raise PhaseError(
                f"labels_a/labels_b: no stationary object ({', '.join(wanted)}) found in both runs"
                + ("" if has_vessels else ", and no vessel pixels in one run")
                + "; motion phase matching needs a balloon, catheter or lead visible in both, or the "
                "vessels (vessel_weight > 0), or pass pair=")
        warnings_.append(f"no stationary object ({', '.join(wanted)}) found in both runs: the frame pair "
                         "is chosen by the vessels' epipolar consistency alone")
    elif vessels_only and not has_vessels:
        raise PhaseError("labels_a/labels_b: objects='vessels' but one run has no vessel pixels")
    used = list(tracks_a)
    n_a, n_b = la.shape[0], lb.shape[0]
    if vessels_only:
        matrix = np.full((n_a, n_b), np.nan)
        valid = np.ones((n_a, n_b), bool)
    else:
        mats = [error_matrix(run_a.view, tracks_a[o].points_px, run_b.view, tracks_b[o].points_px)
                for o in used]
        matrix = mats[0] if len(mats) == 1 else np.max(np.stack(mats), axis=0)
        valid = np.isfinite(matrix)

    fill_a, fill_b = _fill(la, known_a), _fill(lb, known_b)
    elig_a, elig_b = fill_a >= min_contrast, fill_b >= min_contrast
    elig_a &= known_a
    elig_b &= known_b
    allowed = elig_a[:, None] & elig_b[None, :] & valid
    full_a, full_b = fill_a >= prefer_fill, fill_b >= prefer_fill
    if prefer_fill <= 1.0 and (allowed & full_a[:, None] & full_b[None, :]).any():
        elig_a, elig_b = elig_a & full_a, elig_b & full_b
        allowed &= full_a[:, None] & full_b[None, :]
    consistency = None
    if vessel_weight > 0.0 and has_vessels:
        try:
            if known_a.all() and known_b.all():
                consistency = epipolar_consistency(run_a.view, la, run_b.view, lb)
            else:  # only the labelled frames (the others cannot be chosen)
                consistency = np.full((n_a, n_b), np.nan)
                consistency[np.ix_(known_a, known_b)] = epipolar_consistency(
                    run_a.view, la[known_a], run_b.view, lb[known_b])
        except ArgumentError as exc:
            if vessels_only:
                raise PhaseError(f"run_a/run_b: no stationary object to match, and the vessels' epipolar "
                                 f"consistency cannot be measured: {exc}") from None
            warnings_.append(f"vessel consistency not used: {exc}")
    ecg_diff = None
    if use_ecg or (use_ecg is None and consistency is None):
        pa, pb = ecg_phase(run_a), ecg_phase(run_b)
        if pa is not None and pb is not None:
            d = np.abs(pa[:, None] - pb[None, :])
            d = np.minimum(d, 1 - d)
            ecg_ok = d <= ecg_tolerance
            if (allowed & ecg_ok).any():
                allowed &= ecg_ok
                ecg_diff = d
            else:
                warnings_.append("ECG phases leave no pair with key points; ECG restriction ignored")
    if window is None:
        window = 0 if ecg_diff is not None or consistency is not None else 4
    # A short run cannot hold a window of window + 1 valid pairs on a diagonal: shrink it.
    window = min(int(window), (min(run_a.n_frames, run_b.n_frames) - 1) // 2)
    score = diagonal_mean(np.zeros((n_a, n_b)) if vessels_only else matrix, window)
    if ecg_diff is not None:
        score = score + ecg_weight * ecg_diff
    if consistency is not None:
        score = score + vessel_weight * consistency
    allowed &= np.isfinite(score)
    if not allowed.any():
        if not valid.any():
            raise PhaseError(f"run_a/run_b: key points found in both runs ({', '.join(used)}) cannot be "
                             "triangulated: the two views' rays do not cross (one viewing direction "
                             "for both runs?); pass pair= or check the runs' geometry")
        if not (elig_a[:, None] & elig_b[None, :] & valid).any():
            raise PhaseError("labels_a/labels_b: no frame pair has key points in both runs among the "
                             "eligible frames; lower min_contrast or pass pair=")
        # The fill and ECG rules never empty the choice, so only the diagonal window is left.
        raise PhaseError(f"window: no diagonal of {window + 1} eligible pairs with key points "
                         "(too few frames with key points); pass window=0 or pair=")
    masked = np.where(allowed, score, np.inf)
    if pair is not None:
        i, j = int(pair[0]), int(pair[1])
        if not (0 <= i < n_a and 0 <= j < n_b):
            raise ArgumentError(f"pair: ({i}, {j}) is outside the runs' {n_a} x {n_b} frames")
        if not vessels_only and not np.isfinite(matrix[i, j]):
            warnings_.append(f"forced pair ({i}, {j}) has no key point in one of the frames")
    else:
        i, j = (int(x) for x in np.unravel_index(np.argmin(masked), masked.shape))
    near = np.zeros_like(allowed)
    near[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2] = True
    rest = np.where(near, np.inf, masked)
    runner: tuple[int, int] | None = None
    runner_err = float("nan")
    if np.isfinite(rest).any():
        ri, rj = (int(x) for x in np.unravel_index(np.argmin(rest), rest.shape))
        runner, runner_err = (ri, rj), float(rest[ri, rj])
    best = float(matrix[i, j])
    best_score = float(score[i, j])
    margin = runner_err - best_score if runner is not None else float("nan")
    confidence = (float(np.clip(1.0 - best_score / runner_err, 0.0, 1.0)) if runner is not None
                  and runner_err > 0 else (1.0 if runner is None else 0.0))
    if vessels_only:
        error_px, point_mm = float("nan"), np.full(3, np.nan)
    else:
        rec = reconstruction_error(run_a.view, tracks_a[used[0]].points_px[i], run_b.view,
                                   tracks_b[used[0]].points_px[j])
        error_px, point_mm = float(rec.error_px), np.asarray(rec.points_mm)
    if runner is not None and confidence < 0.2:
        warnings_.append(f"ambiguous phase match: runner-up pair {runner} is only {margin:.3f} mm worse")
    least = float(np.min(np.where(allowed, matrix, np.inf))) if not vessels_only else float("nan")
    if least > DISAGREE_MM:
        warnings_.append(
            f"no frame pair agrees: the {'/'.join(used)} key point's reconstruction error is at least "
            f"{least:.1f} mm over the eligible pairs ({best:.1f} mm at the chosen pair ({i}, {j}); "
            f"consistent runs: under {DISAGREE_MM:g} mm). The runs' geometry (angles, SID/SOD, pixel "
            "spacing) does not fit the images, the patient or table moved between the runs, the runs are "
            "too short to share a breathing phase, or the key points lie on different objects: the 3D "
            "result is unreliable; check the geometry and the phase picture (reconstruct's geometry "
            "refinement shifts view B to make the key point agree)")
    return PhaseMatch(
        frame_a=i, frame_b=j, error_mm=best, error_px=error_px, matrix=matrix, score=score,
        objects=used,
        keypoints_a={o: t.points_px for o, t in tracks_a.items()},
        keypoints_b={o: t.points_px for o, t in tracks_b.items()},
        eligible_a=elig_a, eligible_b=elig_b, runner_up=runner, runner_up_error_mm=runner_err,
        margin_mm=margin, confidence=confidence, point_mm=point_mm, warnings=warnings_,
        fill_a=fill_a, fill_b=fill_b, window=window, ecg=ecg_diff is not None,
        consistency=consistency, vessel_weight=float(vessel_weight) if consistency is not None else 0.0,
        labelled_a=None if labelled_a is None else known_a.copy(),
        labelled_b=None if labelled_b is None else known_b.copy(), least_error_mm=least,
    )


def _track_known(labels: np.ndarray, obj: str, frames: np.ndarray, known: np.ndarray) -> KeyPointTrack:
    """Key points of ``obj`` in the labelled frames only (NaN in the others)."""
    if known.all():
        return find_keypoints(labels, obj, frames=frames)
    idx = np.flatnonzero(known)
    t = find_keypoints(labels[idx], obj, frames=frames[idx])
    pts = np.full((labels.shape[0], 2), np.nan)
    pts[idx] = t.points_px
    reason = ["not labelled (coarse-to-fine search)"] * labels.shape[0]
    for k, i in enumerate(idx):
        reason[i] = t.reason[k]
    return KeyPointTrack(obj, pts, reason)


def plot_error_matrix(match: PhaseMatch, path: str | os.PathLike, *, title: str = "") -> Path:
    """Heat map of the error matrix (like the paper's Fig. 2b), chosen pair marked. Atomic PNG.

    With the vessel term (``match.consistency``), a second panel shows the
    vessel masks' epipolar consistency of every pair, which the choice also weighs.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    panels = []
    if match.objects:
        panels.append((match.matrix, "reconstruction error (mm)",
                       title or f"motion phase error matrix ({', '.join(match.objects)}); "
                       "grey: not eligible" + ("" if match.labelled_a is None and match.labelled_b is None
                                               else ", blank: no key point or frame not labelled")))
    if match.consistency is not None:
        panels.append((match.consistency, "vessel crossings differing per epipolar line",
                       (title + "\n" if title and not match.objects else "")
                       + f"vessel consistency (x {match.vessel_weight:g} mm in the score)"
                       + ("" if match.objects else "; no stationary object: the only term")))
    fig, axes = plt.subplots(1, len(panels), figsize=(6.4 * len(panels), 5.2), squeeze=False)
    shade = ~(match.eligible_a[:, None] & match.eligible_b[None, :])
    for ax, (m, label, heading) in zip(axes[0], panels, strict=True):
        finite = m[np.isfinite(m)]
        vmax = float(np.percentile(finite, 95)) if finite.size else 1.0
        im = ax.imshow(m, cmap="viridis", vmin=0.0, vmax=vmax, origin="upper", aspect="auto",
                       interpolation="nearest")
        fig.colorbar(im, ax=ax, label=label)
        ax.imshow(np.ma.masked_where(~shade, np.ones_like(m)), cmap="Greys", alpha=0.35, vmin=0, vmax=1,
                  aspect="auto", interpolation="nearest")
        value = m[match.frame_a, match.frame_b]
        ax.plot(match.frame_b, match.frame_a, "o", ms=12, mfc="none", mec="red", mew=2,
                label=f"chosen ({match.frame_a}, {match.frame_b}): {value:.3f}")
        if match.runner_up is not None:
            ax.plot(match.runner_up[1], match.runner_up[0], "x", ms=9, color="white", mew=2,
                    label=f"runner-up {match.runner_up}: {m[match.runner_up]:.3f}")
        ax.set_xlabel("frame of run B")
        ax.set_ylabel("frame of run A")
        for axis in (ax.xaxis, ax.yaxis):  # frame numbers: no ticks between frames on short runs
            axis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(heading, fontsize=9)
        ax.legend(fontsize=8, loc="lower right")
    # fixed margins: tight_layout measured every text for 0.15 s a picture
    fig.subplots_adjust(left=0.07 if len(panels) > 1 else 0.12, right=0.98, bottom=0.1, top=0.9,
                        wspace=0.25)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return Path(path)

