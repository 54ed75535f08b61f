"""Cross-view matching of two centreline graphs (paper §2.4 steps 1-2).

Landmarks of the two views are compared by the paper's reconstruction error
(§2.3): triangulate the pair, reproject, take the larger 2D error. A branch
of one view and a branch (or a chain of branches through branch points) of
the other whose end landmarks agree are aligned sample by sample by a
monotone (ordering-preserving) dynamic-programming path through the matrix of
reconstruction errors of their samples, with the 3D length of the path as a
tie-break where a vessel runs along an epipolar line. Where only one end
agrees (the other cut by an overlap, hidden, or seen as a branch point in one
view only) the pair is anchored at that end and aligned as far as the two
curves agree (a local alignment). Among all candidates, the consistent set of
largest total gain (paired length times agreement) is chosen by a small
integer program: each landmark paired at most once and each branch used once,
so the topology of both trees is respected without asking them to be
identical: a chain paired with one branch marks a branch point seen in one
view only (its side branch hidden or too short in the
other). The choice is then made again with every candidate weighted by how
far its 3D points lie from an ellipsoid fitted robustly to the first
choice's points: the heart's surface, on which coronary vessels run
(:mod:`vesselcad.surface`). Whatever is not paired is returned with its reason.

See docs/centreline2d.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np
from scipy import interpolate

from . import _dp
from .centreline2d import CentrelineGraph
from .epipolar import backtrack
from .errors import ArgumentError
from .geometry import CArmView, check_view, reconstruction_error
from .splines import PIXEL_NOISE_PX, arc_length, fit_curve_2d
from .surface import QuadricSurface, fit_quadric_surface

__all__ = ["LandmarkMatch", "BranchPair", "Unmatched", "GraphMatch", "match_graphs"]

#: Landmark pairs are accepted up to this reconstruction error (px) plus the
#: mean of their two radii (junction centres are only located to about a radius).
LANDMARK_TOL_PX = 3.0
#: Mean reconstruction error (px) along a branch pair above which it is rejected.
BRANCH_TOL_PX = 3.0
#: Per-sample errors are capped at this (px) so that one far sample cannot dominate.
CAP_PX = 12.0
#: Weight (px of error per mm) of the 3D length of an alignment path.
LENGTH_WEIGHT = 1.0
#: 3D steps are capped at this (mm).
CAP_MM = 10.0
#: Branches are compared on samples this far apart (px).
STEP_PX = 2.0
#: Longest chain of branches (through branch points seen in one view only) matched to one branch.
MAX_CHAIN = 3
#: Gain factor per extra branch in a chain (prefers direct branch-to-branch pairs).
CHAIN_FACTOR = 0.9
#: Gain factor of a pair anchored at one end only (prefers pairs whose both ends agree).
OPEN_FACTOR = 0.8
#: An open-ended alignment runs on while the reconstruction error stays below this share of
#: ``branch_tol_px``.
OPEN_TAU = 0.5
#: Width (log of the radius ratio) of the gain factor for radius agreement between the views.
RADIUS_SIGMA = 0.5
#: The gain factor of a pair's mean reconstruction error e is ``exp(-COST_SCALE * e / e_ref)``,
#: e_ref the ``COST_REF_PERCENTILE`` percentile of all candidates' errors (the views' own noise:
#: about 0.27 px with exact geometry and phase, more with motion or a miscalibrated C-arm).
COST_SCALE = 0.8
COST_REF_PERCENTILE = 10.0
#: e_ref is at least this (px).
COST_REF_MIN_PX = 0.1
#: Shortest open-ended pair (px along each view).
MIN_OPEN_PX = 16.0
#: A pair's 3D length over its longer 2D length (mm at the isocentre) up to which it is
#: plausible without penalty: a vessel foreshortened this much in *both* views.
FORESHORTENING_FREE = 1.2
#: Width of the gain factor past ``FORESHORTENING_FREE`` (see :func:`_foreshortening_factor`).
FORESHORTENING_SIGMA = 0.2
#: A candidate whose gain per px of its shorter aligned length is below this is not chosen: the
#: product of its plausibility factors (error, radii, foreshortening, heart's surface) is so low
#: that it is wrong as a rule, and taking it only because nothing else claims its branches and
#: landmarks asserts wrong landmark pairs (docs/centreline2d.md, "Weak candidates"; None: any).
MIN_GAIN_DENSITY: float | None = 0.03
#: Pairs whose foreshortening factor is below this are dropped.
MIN_FORESHORTENING = 0.1
#: The 3D length of a pair is measured on chords this long (px), not on the noisy sample steps.
CHORD_PX = 8.0
#: Smallest spread (mm) of a tree's points about the heart's ellipsoid: real hearts are no ellipsoid
#: closer than this (grooves, the proximal vessels leaving the aorta).
SURFACE_SIGMA_MIN_MM = 2.0
#: Width of the surface prior in units of that spread (docs/centreline2d.md, "The heart's surface").
SURFACE_WIDTH = 1.5
#: Rounds of seeding unpaired stretches once the continuation finds nothing more (0: none).
SEED_ROUNDS = 3
#: A paired sample whose radius (mm at the isocentre) is at least this many times its partner's
#: may be paired a second time: two vessels overlapping in that view (None: never).
OVERLAP_RATIO: float | None = 1.2
#: Shortest second pairing of a stretch (px in both views).
OVERLAP_MIN_PX = 20.0
#: The two vessels of a stretch paired twice are put on the side that agrees better with the
#: other view when it does by this much (mean px over the stretch, both pairs summed).
OVERLAP_SIDE_PX = 0.1
#: Whether to move the two pieces of a stretch paired twice off its middle.
OVERLAP_CENTRE = True


@dataclass
class LandmarkMatch:
    """A landmark of view A paired with a landmark of view B.

    Attributes
    ----------
    a, b : int
        Landmark indices in ``graph_a`` and ``graph_b``.
    error_px, error_mm : float
        Reconstruction error of the pair (paper §2.3).
    point_mm : numpy.ndarray, shape (3,)
        Triangulated position, LPS mm.
    """

    a: int
    b: int
    error_px: float
    error_mm: float
    point_mm: np.ndarray


@dataclass
class BranchPair:
    """The same vessel segment seen in both views, ready for :func:`vesselcad.intersect_centrelines`.

    The two point lists run in the same direction (proximal to distal, from
    the matched root outward) between corresponding end points.

    Attributes
    ----------
    a, b : int
        Branch indices in ``graph_a.branches`` and ``graph_b.branches``.
    a_range, b_range : tuple of float
        Arc-length interval (px) of each branch that is paired, measured along
        the branch's own point order. A branch is paired in pieces when the
        other view shows a branch point on it that this view lacks.
    reversed_a, reversed_b : bool
        True when the pair runs against the branch's own point order.
    start, end : tuple of (int or None, int or None)
        Landmark indices (view A, view B) at each end; None where the end is
        a point inside a branch (the other view's branch point).
    points_a_px, points_b_px : numpy.ndarray, shape (n, 2)
        The paired pieces, in pair order. Where a stretch of one view is
        paired twice (two vessels overlapping there), its two pieces lie off
        the skeleton, one on each side (docs/centreline2d.md, "Overlaps").
    radius_a_px, radius_b_px : numpy.ndarray, shape (n,)
        Radius profiles along those pieces.
    radius_mm : float
        Median radius in mm at the isocentre over both views.
    error_px, error_mm : float
        Mean reconstruction error along the alignment of the two pieces.
    found_by : str
        How the pair was found: ``'landmarks'`` (both ends at agreeing
        landmarks), ``'one end'`` (from one agreeing landmark, as far as the
        views agree), ``'continuation'`` (grown past another pair's end),
        ``'seed'`` (grown from a seed on the heart's surface, no landmark or
        pair behind it) or ``'overlap'`` (a second partner of a stretch that
        is two vessels overlapping in one view).
    """

    a: int
    b: int
    a_range: tuple[float, float]
    b_range: tuple[float, float]
    reversed_a: bool
    reversed_b: bool
    start: tuple[int | None, int | None]
    end: tuple[int | None, int | None]
    points_a_px: np.ndarray
    points_b_px: np.ndarray
    radius_a_px: np.ndarray
    radius_b_px: np.ndarray
    radius_mm: float
    error_px: float
    error_mm: float
    found_by: str = "landmarks"

    @property
    def length_a_px(self) -> float:
        return float(self.a_range[1] - self.a_range[0])

    @property
    def length_b_px(self) -> float:
        return float(self.b_range[1] - self.b_range[0])

    def splines(self, noise_px: float | None = None) -> tuple[interpolate.BSpline, interpolate.BSpline]:
        """Cubic B-splines (px) of the two pieces, both in pair order.

        Smoothed by ``noise_px``, or by the noise estimated on each piece but at
        least ``vesselcad.splines.PIXEL_NOISE_PX`` (the pieces are skeleton pixels).
        """
        sa, _ = fit_curve_2d(self.points_a_px, noise_px, f"branch {self.a} (view A)", PIXEL_NOISE_PX)
        sb, _ = fit_curve_2d(self.points_b_px, noise_px, f"branch {self.b} (view B)", PIXEL_NOISE_PX)
        return sa, sb


@dataclass
class Unmatched:
    """A landmark or (a piece of) a branch left without a partner, and why.

    Attributes
    ----------
    view : {'a', 'b'}
    kind : {'landmark', 'branch'}
    index : int
    reason : str
    range : tuple of float or None
        For branches, the unpaired arc-length interval (px, branch order).
    """

    view: str
    kind: str
    index: int
    reason: str
    range: tuple[float, float] | None = None


@dataclass
class GraphMatch:
    """Result of :func:`match_graphs`.

    Attributes
    ----------
    landmark_pairs : list of LandmarkMatch
    pairs : list of BranchPair
    unmatched : list of Unmatched
    roots : tuple of int or None
        The matched root landmarks (view A, view B) of the main tree.
    warnings : list of str
    surface : QuadricSurface or None
        The heart's surface fitted to the paired 3D points (``surface_prior``).
    """

    landmark_pairs: list[LandmarkMatch]
    pairs: list[BranchPair]
    unmatched: list[Unmatched]
    roots: tuple[int | None, int | None]
    warnings: list[str] = field(default_factory=list)
    surface: QuadricSurface | None = None

    @property
    def branch_pairs(self) -> list[tuple[int, int]]:
        """(index in graph_a.branches, index in graph_b.branches) of every pair."""
        return [(p.a, p.b) for p in self.pairs]

    @property
    def landmark_indices(self) -> np.ndarray:
        """(K, 2) landmark index pairs (view A, view B)."""
        return np.array([(m.a, m.b) for m in self.landmark_pairs], dtype=np.int64).reshape(-1, 2)

    @property
    def root_pair(self) -> LandmarkMatch | None:
        """The landmark pair of the matched roots (the ostium, triangulated), or None."""
        return next((m for m in self.landmark_pairs if (m.a, m.b) == tuple(self.roots)), None)

    def __repr__(self) -> str:
        return (f"GraphMatch({len(self.landmark_pairs)} landmark pairs, {len(self.pairs)} branch pairs, "
                f"{len(self.unmatched)} unmatched, roots={self.roots})")


# ------------------------------------------------------------------ paths
@dataclass
class _Path:
    """A chain of branches between two landmarks, sampled every STEP_PX."""

    nodes: list[int]  # landmarks along the chain (first ... last)
    edges: list[int]  # branch indices
    rev: list[bool]  # each branch walked against its own point order
    pts: np.ndarray  # (n, 2) samples
    s: np.ndarray  # (n,) arc length of the samples along the chain
    bounds: np.ndarray  # arc length at each node (len(nodes),)
    arcs: list[np.ndarray]  # own arc-length of each branch (branch point order)
    radius: np.ndarray  # (n,) radius (px) at the samples

    @property
    def length(self) -> float:
        return float(self.bounds[-1])

    def reversed(self) -> _Path:
        L = self.length
        return _Path(self.nodes[::-1], self.edges[::-1], [not r for r in self.rev[::-1]],
                     self.pts[::-1].copy(), L - self.s[::-1], L - self.bounds[::-1], self.arcs[::-1],
                     self.radius[::-1].copy())


def _chain(graph: CentrelineGraph, arcs: list[np.ndarray], nodes: list[int], edges: list[int],
           rev: list[bool]) -> _Path:
    parts, radii, bounds = [], [], [0.0]
    for k, r in zip(edges, rev, strict=False):
        br = graph.branches[k]
        parts.append(br.points_px[::-1] if r else br.points_px)
        radii.append(br.radius_px[::-1] if r else br.radius_px)
        bounds.append(bounds[-1] + float(arcs[k][-1]))
    pts = np.concatenate([parts[0]] + [q[1:] for q in parts[1:]])
    rad = np.concatenate([radii[0]] + [q[1:] for q in radii[1:]])
    arc = arc_length(pts)
    total = float(arc[-1])
    n = max(int(np.ceil(total / STEP_PX)) + 1, 3)
    s = np.linspace(0.0, total, n)
    samp = np.stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])], axis=1)
    b = np.asarray(bounds) * (total / max(bounds[-1], 1e-12))
    return _Path(nodes, edges, rev, samp, s, b, [arcs[k] for k in edges], np.interp(s, arc, rad))


def _enumerate_paths(graph: CentrelineGraph, arcs: list[np.ndarray], max_edges: int) -> list[_Path]:
    """Single branches, and chains of up to ``max_edges`` branches through branch points."""
    inc: dict[int, list[tuple[int, int, bool]]] = {lm.index: [] for lm in graph.landmarks}
    for b in graph.branches:
        inc[b.start].append((b.index, b.end, False))
        inc[b.end].append((b.index, b.start, True))
    out = []
    seen: set[tuple[int, ...]] = set()
    for u in inc:
        stack = [([u], [], [])]
        while stack:
            nodes, edges, rev = stack.pop()
            if edges:
                key = tuple(edges) if edges[0] <= edges[-1] else tuple(edges[::-1])
                if key not in seen:
                    seen.add(key)
                    out.append(_chain(graph, arcs, list(nodes), list(edges), list(rev)))
            if len(edges) >= max_edges:
                continue
            if edges and nodes[-1] == graph.root:
                continue  # no vessel runs on through the ostium: the branches at a root all start there
            for k, v, r in inc[nodes[-1]]:
                if k in edges or v in nodes:
                    continue
                stack.append((nodes + [v], edges + [k], rev + [r]))
    return out


def _dtw(E: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Accumulated cost of monotone alignments from (0, 0) (see :func:`match_graphs`).

    A step into cell (i, j) costs the reconstruction error there (twice on a
    diagonal step, so every path into (i, j) has weight i + j + 2) plus
    ``LENGTH_WEIGHT`` times the 3D distance between the triangulated points
    of the two cells: among correspondences that reproject equally well (a
    vessel running along an epipolar line) the shortest 3D curve wins.
    """
    if E.shape[0] > E.shape[1]:  # the recursion is symmetric: loop over the shorter side
        return _dtw(E.T, X.transpose(1, 0, 2)).T
    return _dp.dtw(np.ascontiguousarray(E), np.ascontiguousarray(X), LENGTH_WEIGHT, CAP_MM)


def _errors(va: CArmView, vb: CArmView, pa: _Path, pb: _Path) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruction errors (px, capped) and triangulated points (mm) of all sample pairs."""
    return _pair_errors(va, pa.pts, vb, pb.pts)


def _pair_errors(va: CArmView, qa: np.ndarray, vb: CArmView, qb: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Errors (px, capped at ``CAP_PX``) and ray mid-points (mm) of all pairs of pixels ``qa`` x ``qb``.

    :func:`vesselcad.geometry.reconstruction_error`'s pixel error, compiled
    (:mod:`vesselcad._dp`); where no point exists (parallel rays) the error
    is the cap and the point lies far off (1e6 mm).
    """
    oa, da = va.ray(qa)
    ob, db = vb.ray(qb)
    return _dp.pair_errors(oa, da, ob, db, va.matrix, vb.matrix, np.ascontiguousarray(qa, dtype=float),
                           np.ascontiguousarray(qb, dtype=float), CAP_PX, 1e6)


def _compare(va: CArmView, vb: CArmView, pa: _Path, pb: _Path
             ) -> tuple[float, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Mean error along the best alignment, the triangulated sample pairs and the alignment."""
    E, X = _errors(va, vb, pa, pb)
    pi, pj = backtrack(_dtw(E, X))
    # Mean reconstruction error along the path (the length term only chooses the path).
    return float(np.mean(E[pi, pj])), X, (pi, pj)


def _check_graph(graph: Any, name: str) -> CentrelineGraph:
    if not isinstance(graph, CentrelineGraph):
        raise ArgumentError(f"{name}: expected a vesselcad.CentrelineGraph, got {type(graph).__name__}")
    return graph


def _depths(graph: CentrelineGraph) -> dict[int, int]:
    depth: dict[int, int] = {}
    g = graph.graph
    roots = [graph.root] if graph.root is not None else []
    for comp in nx.connected_components(g):
        r = next((x for x in roots if x in comp), min(comp))
        depth.update(nx.single_source_shortest_path_length(g, r))
    return depth


def match_graphs(view_a: CArmView, graph_a: CentrelineGraph, view_b: CArmView,
                 graph_b: CentrelineGraph, *, landmark_tol_px: float = LANDMARK_TOL_PX,
                 branch_tol_px: float = BRANCH_TOL_PX, continuation: bool = True,
                 surface_prior: bool = True) -> GraphMatch:
    """Pair the landmarks and branches of two views' centreline graphs.

    Every branch of one view is a candidate partner of every branch, or chain
    of up to three branches, of the other view whose two end landmarks agree
    with its own (reconstruction error within ``LANDMARK_TOL_PX`` plus the
    mean radius). Each candidate is scored by aligning its samples with a
    monotone path through their matrix of reconstruction errors (with a
    shortest-3D-curve tie-break). A branch whose far end has no agreeing
    partner is also paired from its agreeing end for as long as the two curves
    agree (error below half of ``branch_tol_px``). The consistent set of
    candidates with the largest total paired length times agreement is then
    chosen (an integer program solved with HiGHS; candidates whose gain per
    px is below ``MIN_GAIN_DENSITY`` are left out): every landmark is paired
    with at most one landmark and every branch used once, so the result
    respects the topology of both trees; a chain matched to one branch marks
    a branch point seen in one view only. Two roots that agree are the
    ostium in both views and are paired even where no chosen branch pair
    starts at them. Finally each accepted pair is
    continued past its ends, along both views' skeleton graphs, for as long
    as the two views agree (``continuation``). With ``surface_prior`` an
    ellipsoid is fitted to the 3D points of that first choice (robustly: the
    heart's surface, on which coronary arteries and veins run), every
    candidate's gain is weighted by how far its 3D points leave it, and the
    choice is made again; the continuation pays for leaving it too. Where the
    continuation finds nothing more, unpaired stretches whose middle sample
    has one partner in the other view that agrees and lies on that surface
    are seeded there and grown both ways (``SEED_ROUNDS`` rounds;
    docs/centreline2d.md, "Seeds"). Last, a paired stretch at least
    ``OVERLAP_RATIO`` times as wide as its partner (two vessels overlapping
    in that view) may be paired a second time, and its two pieces are moved
    apart to the two vessels' sides (docs/centreline2d.md, "Overlaps").

    Parameters
    ----------
    view_a, view_b : CArmView
        The two views (their geometry defines the reconstruction error).
    graph_a, graph_b : CentrelineGraph
        From :func:`vesselcad.centreline_graph` on the matched-phase frames.
    landmark_tol_px, branch_tol_px : float
        Largest reconstruction error (px) of a landmark pair (plus the mean of
        their radii) and mean error along a branch pair. Raise them to find
        the pairs of a roughly calibrated geometry before refining it.
    continuation : bool
        Grow the accepted pairs past their ends along both views' skeleton
        graphs, through branch points of either view, as far as the views
        agree (:mod:`vesselcad.continuation`): reaches vessels whose landmarks
        are lost in one view (default True).
    surface_prior : bool
        Prefer pairs whose 3D points lie on a smooth surface through the
        tree (docs/centreline2d.md, "The heart's surface"; default True).
        Turn it off for vessels that do not run on one surface.

    Returns
    -------
    GraphMatch
        ``branch_pairs`` lists (index in ``graph_a.branches``, index in
        ``graph_b.branches``); ``surface`` is the fitted ellipsoid (None where
        the prior was off, too few points were paired or no ellipsoid of a
        heart's size fits them); ``pairs`` hold the ordered pieces ready for
        :func:`vesselcad.intersect_centrelines`, proximal first (the order of
        view A's tree); ``unmatched`` lists every landmark and branch left out,
        with the reason.

    Raises
    ------
    ArgumentError
        Arguments of the wrong type.
    """
    check_view(view_a, "view_a")
    check_view(view_b, "view_b")
    for tol, name in ((landmark_tol_px, "landmark_tol_px"), (branch_tol_px, "branch_tol_px")):
        if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol > 0):
            raise ArgumentError(f"{name}: expected a positive number of pixels, got {tol!r}")
    for flag, name in ((continuation, "continuation"), (surface_prior, "surface_prior")):
        if not isinstance(flag, bool):
            raise ArgumentError(f"{name}: expected True or False, got {flag!r}")
    ga = _check_graph(graph_a, "graph_a")
    gb = _check_graph(graph_b, "graph_b")
    if not ga.branches or not gb.branches:
        un = [Unmatched("a", "branch", b.index, "view B has no centreline") for b in ga.branches]
        un += [Unmatched("b", "branch", b.index, "view A has no centreline") for b in gb.branches]
        return GraphMatch([], [], un, (ga.root, gb.root), ["one of the graphs has no branches"])
    pa_lm, pb_lm = ga.landmark_points, gb.landmark_points
    rec = reconstruction_error(view_a, pa_lm[:, None, :], view_b, pb_lm[None, :, :])
    lm_err = np.nan_to_num(rec.error_px, nan=np.inf)
    ra_px = np.array([lm.radius_px for lm in ga.landmarks])
    rb_px = np.array([lm.radius_px for lm in gb.landmarks])
    kind_a = np.array([lm.kind for lm in ga.landmarks])
    kind_b = np.array([lm.kind for lm in gb.landmarks])
    # A root is the tree's start (the ostium) whatever its degree: where the skeleton runs on
    # through the ostium (a side branch leaving it the other way) it has two branches.
    for kinds, g in ((kind_a, ga), (kind_b, gb)):
        if g.root is not None:
            kinds[g.root] = "end"
    ok_lm = (lm_err <= landmark_tol_px + 0.5 * (ra_px[:, None] + rb_px[None, :]))
    ok_lm &= kind_a[:, None] == kind_b[None, :]
    # Two roots that agree are the ostium in both views: neither pairs with anything else.
    if ga.root is not None and gb.root is not None and ok_lm[ga.root, gb.root]:
        ok_lm[ga.root, :] = False
        ok_lm[:, gb.root] = False
        ok_lm[ga.root, gb.root] = True

    arcs_a = [arc_length(b.points_px) for b in ga.branches]
    arcs_b = [arc_length(b.points_px) for b in gb.branches]
    paths_a = _enumerate_paths(ga, arcs_a, MAX_CHAIN)
    paths_b = _enumerate_paths(gb, arcs_b, MAX_CHAIN)
    ends = lambda ps: (np.array([p.nodes[0] for p in ps]), np.array([p.nodes[-1] for p in ps]))  # noqa: E731
    ua, va_ = ends(paths_a)
    ub, vb_ = ends(paths_b)
    single_a = np.array([len(p.edges) == 1 for p in paths_a])
    single_b = np.array([len(p.edges) == 1 for p in paths_b])
    shape_ok = single_a[:, None] | single_b[None, :]
    fwd = ok_lm[ua][:, ub] & ok_lm[va_][:, vb_] & shape_ok
    bwd = ok_lm[ua][:, vb_] & ok_lm[va_][:, ub] & shape_ok
    mm_a = float(np.mean(view_a.mm_per_px))
    mm_b = float(np.mean(view_b.mm_per_px))
    cands: list[_Cand] = []
    for (i, j), flip in [(ij, False) for ij in zip(*np.nonzero(fwd), strict=False)] + [
            (ij, True) for ij in zip(*np.nonzero(bwd), strict=False)]:
        pa, pb = paths_a[i], paths_b[j]
        if flip:
            pb = pb.reversed()
        if pa.nodes[0] == pa.nodes[-1] or pb.nodes[0] == pb.nodes[-1]:
            continue
        cost, X, path = _compare(view_a, view_b, pa, pb)
        if cost > branch_tol_px:
            continue
        fs = _foreshortening_factor(X[path], pa.length, pb.length, mm_a, mm_b)
        if fs < MIN_FORESHORTENING:
            continue
        extra = len(pa.edges) + len(pb.edges) - 2
        gain = min(pa.length, pb.length) * (1.0 - cost / branch_tol_px) * (CHAIN_FACTOR ** extra) * fs
        cand = _Cand.closed(gain, cost, pa, pb, path)
        cand.points_mm = X[path]
        cand.gain *= _radius_agreement(cand, mm_a, mm_b)
        cands.append(cand)
    cands += _open_candidates(view_a, view_b, paths_a, paths_b, ok_lm, branch_tol_px, mm_a, mm_b)
    # The error factor's rate depends on all candidates' errors: applied once they are known (the
    # gains above carry the linear ramp of _cost_factor already).
    rate = _cost_rate([c.cost for c in cands])
    for c in cands:
        c.gain *= float(np.exp(-rate * c.cost))
    cands.sort(key=lambda c: -c.gain)

    accepted, map_ab, map_ba, only_a, only_b, used_a, used_b = _select(cands)
    surface = None
    if surface_prior:
        # The heart's surface: fitted to the first choice's 3D points, it rescores every candidate
        # by how far its points leave it, and the choice is made again.
        pts = [_finite_rows([c.points_mm]) for c in accepted]
        surface = fit_quadric_surface(np.vstack([np.zeros((0, 3))] + pts),
                                      np.repeat(np.arange(len(pts)), [len(q) for q in pts]))
        if surface is not None:
            sigma = max(surface.sigma_mm, SURFACE_SIGMA_MIN_MM)
            for c in cands:
                c.gain *= _surface_factor(surface, sigma, c.points_mm)
            cands.sort(key=lambda c: -c.gain)
            accepted, map_ab, map_ba, only_a, only_b, used_a, used_b = _select(cands)

    # Two roots that agree are the ostium in both views (the catheter's tip): a landmark pair of
    # their own, whether or not a branch pair starting there was chosen (the first stretch of the
    # vessel may be foreshortened or hidden under the catheter in one view). With no branch pair
    # to confirm them they must agree within the thinner vessel's radius, not the mean of the two.
    if (ga.root is not None and gb.root is not None and ok_lm[ga.root, gb.root]
            and lm_err[ga.root, gb.root] <= landmark_tol_px + 0.5 * min(ra_px[ga.root], rb_px[gb.root])
            and ga.root not in map_ab and gb.root not in map_ba and ga.root not in only_a
            and gb.root not in only_b):
        map_ab[ga.root] = gb.root
        map_ba[gb.root] = ga.root

    # Orientation: proximal first, by view A's tree (depth from the root).
    depth_a = _depths(ga)
    pairs: list[BranchPair] = []
    for c in accepted:
        pieces = _pieces(view_a, view_b, ga, gb, c, mm_a, mm_b)
        far = c.pa.nodes[len(c.edges_a)]
        if depth_a.get(c.pa.nodes[0], 0) > depth_a.get(far, 0):
            pieces = [_flip(q) for q in pieces[::-1]]
        pairs.extend(pieces)
    if continuation:
        more = _continuations(view_a, view_b, ga, gb, pairs, branch_tol_px, mm_a, mm_b, rate,
                              surface)
        pairs.extend(more)
        used_a = used_a | {p.a for p in more}
        used_b = used_b | {p.b for p in more}
    if OVERLAP_CENTRE:
        _centre_overlaps(pairs, ga, gb, view_a, view_b, mm_a, mm_b)
    order = {id(p): k for k, p in enumerate(pairs)}
    pairs.sort(key=lambda p: (depth_a.get(p.start[0], 0) if p.start[0] is not None else 1e9, order[id(p)]))

    lmm = [LandmarkMatch(a=int(a), b=int(b), error_px=float(rec.error_px[a, b]),
                         error_mm=float(rec.error_mm[a, b]), point_mm=np.asarray(rec.points_mm[a, b]))
           for a, b in map_ab.items()]
    lmm.sort(key=lambda m: (depth_a.get(m.a, 0), m.a))
    unmatched: list[Unmatched] = []
    for g, tag, other, mapped, only, used in ((ga, "a", "B", map_ab, only_a, used_a),
                                               (gb, "b", "A", map_ba, only_b, used_b)):
        for lm in g.landmarks:
            if lm.index in mapped:
                continue
            if lm.index in only:
                why = (f"branch point seen in view {tag.upper()} only (its side branch is hidden, "
                       f"too short or crosses another vessel in view {other})")
            else:
                why = f"no landmark of view {other} agrees with it on a consistent branch"
            unmatched.append(Unmatched(tag, "landmark", lm.index, why))
        covered: dict[int, list[tuple[float, float]]] = {}
        for p in pairs:
            covered.setdefault(p.a if tag == "a" else p.b, []).append(p.a_range if tag == "a" else p.b_range)
        for b in g.branches:
            if b.index not in used:
                unmatched.append(Unmatched(tag, "branch", b.index, (
                    f"no branch of view {other} between matching landmarks agrees with it "
                    f"(hidden, foreshortened, overlapping or not segmented in view {other})"),
                    (0.0, float(b.length_px))))
                continue
            for lo, hi in _gaps(covered.get(b.index, []), float(b.length_px)):
                unmatched.append(Unmatched(tag, "branch", b.index, (
                    f"this part has no partner: view {other} stops agreeing with it (the vessel ends, "
                    f"is hidden or overlaps another vessel there in view {other})"), (lo, hi)))
    roots = (ga.root, map_ab.get(ga.root) if ga.root is not None else None)
    warnings_ = []
    if ga.root is not None and gb.root is not None and map_ab.get(ga.root) not in (None, gb.root):
        warnings_.append("the roots of the two graphs were not matched to each other")
    return GraphMatch(lmm, pairs, unmatched, roots, warnings_, surface)


@dataclass
class _Cand:
    """A candidate pairing of a path of view A with a path of view B."""

    gain: float
    cost: float
    pa: _Path
    pb: _Path
    end: tuple[int, int]  # last aligned samples (i, j)
    path: tuple[np.ndarray, np.ndarray]  # the alignment: sample indices (view A, view B)
    ends: list[tuple[int, int]]  # landmark pairs it asserts
    inner_a: list[int]  # landmarks it passes through (seen in one view only)
    inner_b: list[int]
    edges_a: list[int]  # branches it uses
    edges_b: list[int]
    points_mm: np.ndarray | None = None  # triangulated points along the alignment

    @property
    def length(self) -> float:
        """The shorter of the two aligned lengths (px)."""
        return float(min(self.pa.s[self.end[0]], self.pb.s[self.end[1]]))

    @classmethod
    def closed(cls, gain: float, cost: float, pa: _Path, pb: _Path,
               path: tuple[np.ndarray, np.ndarray]) -> _Cand:
        return cls(gain, cost, pa, pb, (len(pa.s) - 1, len(pb.s) - 1), path,
                   [(pa.nodes[0], pb.nodes[0]), (pa.nodes[-1], pb.nodes[-1])],
                   pa.nodes[1:-1], pb.nodes[1:-1], list(pa.edges), list(pb.edges))


def _open_candidates(va: CArmView, vb: CArmView, paths_a: list[_Path], paths_b: list[_Path],
                     ok_lm: np.ndarray, tol: float, mm_a: float, mm_b: float) -> list[_Cand]:
    """Branch pairs anchored at one agreeing landmark whose far end is free.

    A vessel end cut by an overlap, a branch point seen in one view only or a
    vessel that leaves the field in one view leaves the far end without a
    partner. A branch of one view (either way round) is then aligned with a
    prefix of a branch of the other (or a prefix of it with all of the other):
    a local alignment whose step cost is the reconstruction error minus
    ``OPEN_TAU * tol``, so that it runs as long as the two curves agree.
    """
    all_a = [q for p in paths_a if len(p.edges) == 1 for q in (p, p.reversed())]
    all_b = [q for p in paths_b if len(p.edges) == 1 for q in (p, p.reversed())]
    first_a = np.array([p.nodes[0] for p in all_a], dtype=np.int64)
    first_b = np.array([p.nodes[0] for p in all_b], dtype=np.int64)
    ii, jj = np.nonzero(ok_lm[first_a][:, first_b])
    if len(ii) == 0:
        return []
    # Quick test on the first MIN_OPEN_PX of both branches (all pairs at once): each sample of one
    # must have a partner in the other within tau on average, or no alignment can start.
    k = int(np.ceil(MIN_OPEN_PX / STEP_PX)) + 1
    head = lambda ps: np.stack([p.pts[np.minimum(np.arange(k), len(p.pts) - 1)] for p in ps])  # noqa: E731
    ha, hb = head(all_a), head(all_b)
    E0 = np.nan_to_num(reconstruction_error(va, ha[ii][:, :, None, :], vb, hb[jj][:, None, :, :]).error_px,
                       nan=CAP_PX)
    tau = OPEN_TAU * tol
    keep = (E0.min(axis=2).mean(axis=1) <= tau) & (E0.min(axis=1).mean(axis=1) <= tau)
    out: list[_Cand] = []
    for i, j in zip(ii[keep], jj[keep], strict=True):
        pa, pb = all_a[i], all_b[j]
        if pa.nodes[0] == pa.nodes[-1] or pb.nodes[0] == pb.nodes[-1]:
            continue
        E, X = _errors(va, vb, pa, pb)
        D = _dtw(E - tau, X)
        n, m = D.shape
        last = np.r_[D[-1, :], D[:, -1]]
        k = int(np.argmin(last))
        ie, je = (n - 1, k) if k < m else (k - m, m - 1)
        if ie == n - 1 and je == m - 1:
            continue  # a whole-branch alignment: a closed candidate where its ends agree
        if min(pa.s[ie], pb.s[je]) < MIN_OPEN_PX:
            continue
        pi, pj = backtrack(D[: ie + 1, : je + 1])
        cost = float(np.mean(E[pi, pj]))
        if cost > tol:
            continue
        fs = _foreshortening_factor(X[pi, pj], pa.s[ie], pb.s[je], mm_a, mm_b)
        if fs < MIN_FORESHORTENING:
            continue
        gain = min(pa.s[ie], pb.s[je]) * (1.0 - cost / tol) * OPEN_FACTOR * fs
        cand = _Cand(gain, cost, pa, pb, (ie, je), (pi, pj), [(pa.nodes[0], pb.nodes[0])], [], [],
                     list(pa.edges), list(pb.edges), X[pi, pj])
        cand.gain *= _radius_agreement(cand, mm_a, mm_b)
        out.append(cand)
    return out


def _foreshortening_factor(points_mm: np.ndarray, length_a_px: float, length_b_px: float,
                          mm_a: float, mm_b: float) -> float:
    """Plausibility (0..1] of a pairing from how much both views would foreshorten its 3D curve.

    A projection never lengthens a curve, and a vessel is strongly
    foreshortened in both views only when it runs nearly along both viewing
    directions. A wrong pairing of two curves that share an epipolar band
    reprojects perfectly but zig-zags in depth: its 3D curve is much longer
    than either 2D curve. The factor is 1 while the 3D length (on chords of
    about ``CHORD_PX``, so that pixel noise in depth adds no length) is at
    most ``FORESHORTENING_FREE`` times the longer of the two 2D lengths (mm at
    the isocentre), and falls as a Gaussian of width ``FORESHORTENING_SIGMA``
    beyond.

    Parameters
    ----------
    points_mm : numpy.ndarray, shape (n, 3)
        Triangulated points along the pair, in order.
    length_a_px, length_b_px : float
        The pair's length in each view (px).
    mm_a, mm_b : float
        mm per px at the isocentre of each view.
    """
    longest = max(length_a_px * mm_a, length_b_px * mm_b)
    if len(points_mm) < 2 or longest <= 0:
        return 1.0
    n_chords = max(int(np.ceil(max(length_a_px, length_b_px) / CHORD_PX)), 1)
    idx = np.unique(np.round(np.linspace(0, len(points_mm) - 1, n_chords + 1)).astype(np.int64))
    length_3d = float(np.sum(np.linalg.norm(np.diff(points_mm[idx], axis=0), axis=1)))
    excess = max(length_3d / longest - FORESHORTENING_FREE, 0.0)
    return float(np.exp(-(excess / FORESHORTENING_SIGMA) ** 2))


def _radius_agreement(c: _Cand, mm_a: float, mm_b: float) -> float:
    """Gain factor from the agreement of the two views' radii (mm at the isocentre) along the pair."""
    pi, pj = c.path
    return _radius_factor(float(np.median(c.pa.radius[pi])) * mm_a, float(np.median(c.pb.radius[pj])) * mm_b)


def _radius_factor(ra_mm: float, rb_mm: float) -> float:
    """Gain factor (0..1] from the two views' radii of a pair (mm at the isocentre)."""
    if RADIUS_SIGMA <= 0:
        return 1.0
    return float(np.exp(-(np.log(max(ra_mm, 1e-6) / max(rb_mm, 1e-6)) / RADIUS_SIGMA) ** 2))


def _finite_rows(parts: list[np.ndarray | None]) -> np.ndarray:
    """The triangulated points of candidates, stacked, without the failed ones (stored as 1e6)."""
    pts = [p for p in parts if p is not None and len(p)]
    if not pts:
        return np.zeros((0, 3))
    P = np.vstack(pts)
    return P[np.all(np.abs(P) < 1e5, axis=1)]


def _surface_factor(surface: QuadricSurface, sigma: float, points_mm: np.ndarray | None) -> float:
    """Gain factor (0..1] from how far a candidate's 3D points lie from the heart's surface.

    A Gaussian of the median distance (robust to the proximal vessel, which
    leaves the aorta off the surface, in a candidate that starts at the
    ostium) with width ``SURFACE_WIDTH`` times ``sigma``.
    """
    p = _finite_rows([points_mm])
    if not len(p):
        return 1.0
    d = float(np.median(surface.distance(p)))
    return float(np.exp(-0.5 * (d / (SURFACE_WIDTH * sigma)) ** 2))


def _cost_factor(cost: float, tol: float, rate: float) -> float:
    """Gain factor (0..1] from a pair's mean reconstruction error ``cost`` (px) and its tolerance.

    ``exp(-rate * cost)`` times the linear ramp ``1 - cost / tol``: with exact
    geometry the right partner of a vessel reprojects to about 0.3-0.4 px along
    the whole alignment, a wrong one that shares its epipolar band to about
    0.5-0.6 px, so a tenth of a pixel of mean error must weigh more than the
    ramp alone gives it; ``rate`` scales with the views' noise
    (:func:`_cost_rate`, docs/centreline2d.md, "Score").
    """
    return float(np.exp(-rate * cost)) * max(1.0 - cost / tol, 0.0)


def _cost_rate(costs: list[float]) -> float:
    """Rate of :func:`_cost_factor` for candidates with these mean errors (px)."""
    if not costs:
        return 0.0
    ref = max(float(np.percentile(costs, COST_REF_PERCENTILE)), COST_REF_MIN_PX)
    return COST_SCALE / ref


def _select_greedy(cands: list[_Cand]) -> tuple:
    """Accept candidates in order, skipping any that conflicts with those already taken."""
    map_ab: dict[int, int] = {}
    map_ba: dict[int, int] = {}
    only_a: set[int] = set()  # branch points seen in view A only
    only_b: set[int] = set()
    used_a: set[int] = set()
    used_b: set[int] = set()
    accepted = []
    for c in cands:
        if used_a & set(c.edges_a) or used_b & set(c.edges_b):
            continue
        if any(map_ab.get(x, y) != y or map_ba.get(y, x) != x or x in only_a or y in only_b
               for x, y in c.ends):
            continue
        if any(n in map_ab for n in c.inner_a) or any(n in map_ba for n in c.inner_b):
            continue
        for x, y in c.ends:
            map_ab[x], map_ba[y] = y, x
        only_a.update(c.inner_a)
        only_b.update(c.inner_b)
        used_a.update(c.edges_a)
        used_b.update(c.edges_b)
        accepted.append(c)
    return accepted, map_ab, map_ba, only_a, only_b, used_a, used_b


def _select(cands: list[_Cand]) -> tuple:
    """The consistent set of candidates of largest total gain (a small integer program).

    Binary variables: one per candidate and one per landmark pair that some
    candidate asserts. A candidate needs its landmark pairs; every landmark is
    paired at most once and a landmark a candidate passes through (a branch
    point seen in one view only) is not paired at all; every branch is used by
    at most one candidate. Solved with HiGHS (scipy.optimize.milp); should it
    find no solution in time, candidates are taken greedily by gain.
    Candidates whose gain per px of aligned length is below
    ``MIN_GAIN_DENSITY`` take no part.
    """
    from scipy import sparse
    from scipy.optimize import Bounds, LinearConstraint, milp

    if MIN_GAIN_DENSITY is not None:
        cands = [c for c in cands if c.gain >= MIN_GAIN_DENSITY * c.length]
    if not cands:
        return [], {}, {}, set(), set(), set(), set()
    pairs: dict[tuple[int, int], int] = {}
    for c in cands:
        for xy in c.ends:
            pairs.setdefault(xy, len(pairs))
    nc, npair = len(cands), len(pairs)
    rows: list[int] = []
    cols: list[int] = []
    vals: list[float] = []
    ub: list[float] = []

    def row(entries: list[tuple[int, float]], hi: float) -> None:
        r = len(ub)
        for j, v in entries:
            rows.append(r)
            cols.append(j)
            vals.append(v)
        ub.append(hi)

    groups: dict[tuple[str, int], list[tuple[int, float]]] = {}
    for k, c in enumerate(cands):
        for xy in c.ends:
            row([(k, 1.0), (nc + pairs[xy], -1.0)], 0.0)
        for tag, items in (("ea", c.edges_a), ("eb", c.edges_b), ("na", c.inner_a), ("nb", c.inner_b)):
            for e in items:
                groups.setdefault((tag, e), []).append((k, 1.0))
    for (x, y), j in pairs.items():
        groups.setdefault(("na", x), []).append((nc + j, 1.0))
        groups.setdefault(("nb", y), []).append((nc + j, 1.0))
    for entries in groups.values():
        if len(entries) > 1:
            row(entries, 1.0)
    A = sparse.csr_array((vals, (rows, cols)), shape=(len(ub), nc + npair))
    cost = np.r_[-np.array([c.gain for c in cands]), np.full(npair, 1e-6)]
    res = milp(cost, constraints=LinearConstraint(A, -np.inf, np.array(ub)), integrality=np.ones(nc + npair),
               bounds=Bounds(0, 1), options={"time_limit": 2.0})
    if res.x is None:
        return _select_greedy(cands)
    chosen = [cands[k] for k in np.flatnonzero(res.x[:nc] > 0.5)]
    chosen.sort(key=lambda c: -c.gain)
    return _select_greedy(chosen)


def _continuations(va: CArmView, vb: CArmView, ga: CentrelineGraph, gb: CentrelineGraph,
                   pairs: list[BranchPair], tol: float, mm_a: float, mm_b: float,
                   cost_rate: float = 0.0, surface: QuadricSurface | None = None) -> list[BranchPair]:
    """Pairs grown from the ends of ``pairs`` along both skeleton graphs (:mod:`vesselcad.continuation`)."""
    from . import continuation as cont

    cha, chb = cont.chains(ga), cont.chains(gb)
    used_a = np.zeros(len(cha.pts), bool)
    used_b = np.zeros(len(chb.pts), bool)
    for p in pairs:
        for ch, used, k, (lo, hi) in ((cha, used_a, p.a, p.a_range), (chb, used_b, p.b, p.b_range)):
            on = ch.branch == k
            used[on & (ch.arc >= lo - 0.5 * STEP_PX) & (ch.arc <= hi + 0.5 * STEP_PX)] = True
    anchors = []
    for p in pairs:
        for at_end in (True, False):
            ends = []
            for ch, k, (lo, hi), rev in ((cha, p.a, p.a_range, p.reversed_a),
                                         (chb, p.b, p.b_range, p.reversed_b)):
                # Leaving the pair past its last point runs the way the pair runs, past its first point back.
                forward = (not rev) if at_end else rev
                ends.extend(ch.position(k, hi if forward else lo, forward))
            anchors.append(tuple(ends))
    free_a, free_b = ~used_a, ~used_b
    for ca, ta, cb, tb in anchors:
        free_a[cha.idx[ca, ta]] = free_b[chb.idx[cb, tb]] = True
    se = _surface_penalty(cont.sample_errors(va, vb, cha, chb, free_a, free_b), surface, tol)
    # Grow from view A's side, then from view B's (a vessel that view A shows as one branch but
    # view B through a branch point, or the other way round), until neither finds more.
    found: list[cont.Continuation] = []
    seeded: list[bool] = []
    swap = lambda anc: [(cb, tb, ca, ta) for ca, ta, cb, tb in anc]  # noqa: E731
    for _round in range(4):
        got, new = cont.continue_pairs(se, cha, chb, used_a, used_b, anchors, tol, mm_a, mm_b,
                                         cost_rate)
        anchors = anchors + new
        got_b, new_b = cont.continue_pairs(se.T, chb, cha, used_b, used_a, swap(anchors), tol, mm_b,
                                             mm_a, cost_rate)
        anchors = anchors + swap(new_b)
        found += got + [cont.Continuation(c.gain, c.cost, c.ib, c.ia, c.err, c.anchor) for c in got_b]
        seeded += [False] * (len(got) + len(got_b))
        if not got_b:
            break
    # Seeds: stretches both views show but no anchor reached, paired where the partner on the
    # heart's surface is unambiguous, then grown both ways (docs/centreline2d.md, "Seeds").
    for _round in range(SEED_ROUNDS if surface is not None else 0):
        seeds = cont.seeds(se, cha, chb, used_a, used_b) + swap(cont.seeds(se.T, chb, cha, used_b, used_a))
        if not seeds:
            break
        got, new = cont.continue_pairs(se, cha, chb, used_a, used_b, seeds, tol, mm_a, mm_b, cost_rate)
        # From view B's side: the new anchors, and the seeds nothing grew from on view A's side.
        grown = {c.anchor for c in got}
        rest = [s for s in seeds if s not in grown]
        got_b, new_b = cont.continue_pairs(se.T, chb, cha, used_b, used_a, swap(rest + new), tol, mm_b,
                                             mm_a, cost_rate)
        found += got + [cont.Continuation(c.gain, c.cost, c.ib, c.ia, c.err, c.anchor) for c in got_b]
        seeded += [True] * (len(got) + len(got_b))
        if not got and not got_b:
            break
    how = ["seed" if x else "continuation" for x in seeded]
    if OVERLAP_RATIO is not None:
        more = _overlaps(va, vb, cha, chb, pairs, found, used_a, used_b, anchors, tol, mm_a, mm_b,
                         cost_rate, surface)
        found += more
        how += ["overlap"] * len(more)
    out: list[BranchPair] = []
    for c, found_by in zip(found, how, strict=True):
        ka, kb = cha.branch[c.ia], chb.branch[c.ib]
        brk = np.flatnonzero((np.diff(ka) != 0) | (np.diff(kb) != 0)) + 1
        for lo, hi in zip(np.r_[0, brk], np.r_[brk, len(ka)], strict=True):
            sa, sb = c.ia[lo:hi], c.ib[lo:hi]
            if len(np.unique(sa)) < 2 or len(np.unique(sb)) < 2:
                continue
            ends_a, ends_b = cha.arc[sa[[0, -1]]], chb.arc[sb[[0, -1]]]
            n = max(int(np.ceil(max(abs(np.diff(ends_a))[0], abs(np.diff(ends_b))[0]))) + 1, 2)
            pts_a, r_a = _along(ga.branches[int(ka[lo])], ends_a, n)
            pts_b, r_b = _along(gb.branches[int(kb[lo])], ends_b, n)
            err = float(c.err[lo:hi].mean())
            q = BranchPair(
                a=int(ka[lo]), b=int(kb[lo]), a_range=(float(ends_a.min()), float(ends_a.max())),
                b_range=(float(ends_b.min()), float(ends_b.max())), reversed_a=bool(ends_a[1] < ends_a[0]),
                reversed_b=bool(ends_b[1] < ends_b[0]), start=(None, None), end=(None, None),
                points_a_px=pts_a, points_b_px=pts_b, radius_a_px=r_a, radius_b_px=r_b,
                radius_mm=float(np.median(np.concatenate([r_a * mm_a, r_b * mm_b]))),
                error_px=err, error_mm=err * 0.5 * (mm_a + mm_b),
                found_by=found_by)
            out.append(_flip(q) if q.reversed_a else q)
    return out


def _surface_penalty(se: Any, surface: QuadricSurface | None, tol: float) -> Any:
    """Sample errors with the heart's surface's penalty: leaving it by more than ``SURFACE_WIDTH``
    sigma costs like reconstruction error (capped at ``CAP_PX``)."""
    if surface is not None:
        width = SURFACE_WIDTH * max(surface.sigma_mm, SURFACE_SIGMA_MIN_MM)
        d = np.nan_to_num(surface.distance(se.X), nan=np.inf)
        se.E = np.minimum(se.E + OPEN_TAU * tol * np.maximum(d / width - 1.0, 0.0) ** 2, CAP_PX)
    return se


def _partner_radius(cha: Any, chb: Any, pairs: list[BranchPair], found: list, mm_a: float, mm_b: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Radius (mm at the isocentre) of each paired sample's partner in the other view (NaN: unpaired)."""
    ra = np.full(len(cha.pts), np.nan)
    rb = np.full(len(chb.pts), np.nan)
    for p in pairs:
        for ch, out, k, (lo, hi), rev, other, mm in (
                (cha, ra, p.a, p.a_range, p.reversed_a, p.radius_b_px, mm_b),
                (chb, rb, p.b, p.b_range, p.reversed_b, p.radius_a_px, mm_a)):
            on = np.flatnonzero((ch.branch == k) & (ch.arc >= lo - 0.5 * STEP_PX)
                                & (ch.arc <= hi + 0.5 * STEP_PX))
            t = np.clip((ch.arc[on] - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
            if rev:
                t = 1.0 - t
            out[on] = np.interp(t, np.linspace(0.0, 1.0, len(other)), other) * mm
    for c in found:
        ra[c.ia] = chb.radius[c.ib] * mm_b
        rb[c.ib] = cha.radius[c.ia] * mm_a
    return ra, rb


def _overlaps(va: CArmView, vb: CArmView, cha: Any, chb: Any, pairs: list[BranchPair], found: list,
              used_a: np.ndarray, used_b: np.ndarray, anchors: list, tol: float, mm_a: float, mm_b: float,
              cost_rate: float, surface: QuadricSurface | None) -> list:
    """Second partners for paired stretches that are two vessels overlapping in one view."""
    from . import continuation as cont

    part_a, part_b = _partner_radius(cha, chb, pairs, found, mm_a, mm_b)
    with np.errstate(invalid="ignore"):
        wide_a = used_a & (cha.radius * mm_a >= OVERLAP_RATIO * part_a)
        wide_b = used_b & (chb.radius * mm_b >= OVERLAP_RATIO * part_b)
    out: list = []
    swap = lambda anc: [(cb, tb, ca, ta) for ca, ta, cb, tb in anc]  # noqa: E731
    for side in ("a", "b"):
        wide = wide_a if side == "a" else wide_b
        if not wide.any():
            continue
        # Only the wide samples of this view are open, only the unpaired ones of the other.
        if side == "a":
            ua, ub = ~wide_a, used_b.copy()
        else:
            ua, ub = used_a.copy(), ~wide_b
        free_a, free_b = ~ua, ~ub
        for ca, ta, cb, tb in anchors:
            free_a[cha.idx[ca, ta]] = free_b[chb.idx[cb, tb]] = True
        se = _surface_penalty(cont.sample_errors(va, vb, cha, chb, free_a, free_b), surface, tol)
        got, _ = cont.continue_pairs(se, cha, chb, ua, ub, list(anchors), tol, mm_a, mm_b, cost_rate,
                                     radii=False)
        got_b, _ = cont.continue_pairs(se.T, chb, cha, ub, ua, swap(anchors), tol, mm_b, mm_a, cost_rate,
                                       radii=False)
        # Seeds too (with or without the heart's surface: only the wide stretches are open, and a
        # seed needs one partner there that agrees clearly better than any other).
        sd = cont.seeds(se, cha, chb, ua, ub) + swap(cont.seeds(se.T, chb, cha, ub, ua))
        got_s, new = cont.continue_pairs(se, cha, chb, ua, ub, sd, tol, mm_a, mm_b, cost_rate, radii=False)
        got_t, _ = cont.continue_pairs(se.T, chb, cha, ub, ua, swap(sd + new), tol, mm_b, mm_a, cost_rate,
                                       radii=False)
        out += got + got_s + [cont.Continuation(c.gain, c.cost, c.ib, c.ia, c.err, c.anchor)
                              for c in got_b + got_t]
    # Short pieces are left out: a few samples of a blob agree with many vessels of the other view,
    # and a stub paired there would become the parent of a subtree in 3D.
    length = lambda s: STEP_PX * (len(np.unique(s)) - 1)  # noqa: E731
    return [c for c in out if min(length(c.ia), length(c.ib)) >= OVERLAP_MIN_PX]


def _pair_arcs(p: BranchPair, view: str) -> np.ndarray:
    """Own-order arc length (px) of each of a pair's points in one view."""
    lo, hi = p.a_range if view == "a" else p.b_range
    rev = p.reversed_a if view == "a" else p.reversed_b
    t = np.linspace(0.0, 1.0, len(p.points_a_px))
    return hi - (hi - lo) * t if rev else lo + (hi - lo) * t


def _centre_overlaps(pairs: list[BranchPair], ga: CentrelineGraph, gb: CentrelineGraph, va: CArmView,
                     vb: CArmView, mm_a: float, mm_b: float) -> None:
    """Move the two pieces of a stretch paired twice (two vessels overlapping in one view) apart.

    The stretch's skeleton runs down the middle of the two overlapping
    vessels. Each vessel's centre lies its partner's radius (converted to
    this view) in from the edge of the stretch, one on each side; which on
    which side is what agrees better with the other view (left in the middle
    where the two choices agree about as well: the vessel runs across the
    epipolar lines there). The points of ``pairs`` are moved in place.
    """
    # Every stretch is moved from where the skeleton put it (a piece may share two stretches).
    orig = {id(p): (p.points_a_px.copy(), p.points_b_px.copy()) for p in pairs}
    for view, g, mm_x, mm_o in (("a", ga, mm_a, mm_b), ("b", gb, mm_b, mm_a)):
        on: dict[int, list[int]] = {}
        for k, p in enumerate(pairs):
            on.setdefault(p.a if view == "a" else p.b, []).append(k)
        for br, ks in on.items():
            if len(ks) < 2:
                continue
            b = g.branches[br]
            arc = arc_length(b.points_px)
            tan = np.gradient(b.points_px, arc, axis=0) if len(arc) > 1 else np.zeros_like(b.points_px)
            for i, k1 in enumerate(ks):
                for k2 in ks[i + 1:]:
                    _centre_two(pairs[k1], pairs[k2], view, b, arc, tan, mm_x, mm_o, va, vb, orig)


def _centre_two(p: BranchPair, q: BranchPair, view: str, b: Any, arc: np.ndarray, tan: np.ndarray,
                mm_x: float, mm_o: float, va: CArmView, vb: CArmView,
                orig: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
    """:func:`_centre_overlaps` for two pairs that share a stretch of branch ``b`` in ``view``."""
    if any(len(x.points_a_px) != len(x.points_b_px) for x in (p, q)):
        return  # point i of one view is point i of the other in every pair the matching builds
    sp, sq = _pair_arcs(p, view), _pair_arcs(q, view)
    lo = max(sp.min(), sq.min())
    hi = min(sp.max(), sq.max())
    if hi - lo < 2.0 * STEP_PX:
        return
    idx = np.flatnonzero((sp >= lo) & (sp <= hi))
    if len(idx) < 2:
        return
    s = sp[idx]
    order = np.argsort(sq)
    pts = "points_a_px" if view == "a" else "points_b_px"
    x0p, o0p = orig[id(p)] if view == "a" else orig[id(p)][::-1]
    x0q, o0q = orig[id(q)] if view == "a" else orig[id(q)][::-1]
    rad_o = "radius_b_px" if view == "a" else "radius_a_px"
    R = np.interp(s, arc, b.radius_px)
    t = np.stack([np.interp(s, arc, tan[:, 0]), np.interp(s, arc, tan[:, 1])], axis=1)
    nrm = np.stack([-t[:, 1], t[:, 0]], axis=1) / np.maximum(np.linalg.norm(t, axis=1), 1e-9)[:, None]
    rp = getattr(p, rad_o)[idx] * mm_o / mm_x
    rq = np.interp(s, sq[order], getattr(q, rad_o)[order]) * mm_o / mm_x
    off_p, off_q = np.clip(R - rp, 0.0, R), np.clip(R - rq, 0.0, R)
    xp, op = x0p[idx], o0p[idx]
    xq = np.stack([np.interp(s, sq[order], x0q[order, c]) for c in (0, 1)], axis=1)
    oq = np.stack([np.interp(s, sq[order], o0q[order, c]) for c in (0, 1)], axis=1)

    def err(x: np.ndarray, o: np.ndarray) -> np.ndarray:
        if view == "a":
            return reconstruction_error(va, x, vb, o).error_px
        return reconstruction_error(va, o, vb, x).error_px

    # Each piece's radius there is its own vessel's (the other view's), not the stretch's.
    rad_x = "radius_a_px" if view == "a" else "radius_b_px"
    jq = np.flatnonzero((sq >= lo) & (sq <= hi))
    so = np.argsort(s)
    getattr(p, rad_x)[idx] = np.minimum(getattr(p, rad_x)[idx], rp)
    getattr(q, rad_x)[jq] = np.minimum(getattr(q, rad_x)[jq], getattr(q, rad_o)[jq] * mm_o / mm_x)
    sign = np.array([1.0, -1.0])
    e = [float(np.mean(err(xp + sg * off_p[:, None] * nrm, op) + err(xq - sg * off_q[:, None] * nrm, oq)))
         for sg in sign]
    best = int(np.argmin(e))
    if not e[best] < e[1 - best] - OVERLAP_SIDE_PX:
        return
    sg = sign[best]
    new_p = getattr(p, pts).copy()
    new_p[idx] = xp + sg * off_p[:, None] * nrm
    setattr(p, pts, new_p)
    off_jq = np.interp(sq[jq], s[so], off_q[so])
    nq = np.stack([np.interp(sq[jq], s[so], nrm[so, c]) for c in (0, 1)], axis=1)
    new_q = getattr(q, pts).copy()
    new_q[jq] = x0q[jq] - sg * off_jq[:, None] * nq
    setattr(q, pts, new_q)


def _along(branch: Any, ends: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points and radii along a branch between two arc-length positions (in that order)."""
    arc = arc_length(branch.points_px)
    s = np.linspace(float(ends[0]), float(ends[1]), n)
    pts = np.stack([np.interp(s, arc, branch.points_px[:, 0]), np.interp(s, arc, branch.points_px[:, 1])],
                   axis=1)
    return pts, np.interp(s, arc, branch.radius_px)


def _gaps(ranges: list[tuple[float, float]], length: float) -> list[tuple[float, float]]:
    """Parts of [0, length] longer than two sample steps that no range covers."""
    out, at = [], 0.0
    for lo, hi in sorted(ranges):
        if lo - at > 2.0 * STEP_PX:
            out.append((at, lo))
        at = max(at, hi)
    if length - at > 2.0 * STEP_PX:
        out.append((at, length))
    return out


def _flip(p: BranchPair) -> BranchPair:
    """The same pair walked the other way."""
    return BranchPair(
        a=p.a, b=p.b, a_range=p.a_range, b_range=p.b_range, reversed_a=not p.reversed_a,
        reversed_b=not p.reversed_b, start=p.end, end=p.start, points_a_px=p.points_a_px[::-1].copy(),
        points_b_px=p.points_b_px[::-1].copy(), radius_a_px=p.radius_a_px[::-1].copy(),
        radius_b_px=p.radius_b_px[::-1].copy(), radius_mm=p.radius_mm, error_px=p.error_px,
        error_mm=p.error_mm, found_by=p.found_by)


def _pieces(va: CArmView, vb: CArmView, ga: CentrelineGraph, gb: CentrelineGraph, c: _Cand,
            mm_a: float, mm_b: float) -> list[BranchPair]:
    """Cut a matched path pair at every node of either path into per-branch pieces."""
    pa, pb = c.pa, c.pb
    ie, je = c.end
    pi, pj = c.path
    sa, sb = pa.s[pi], pb.s[pj]
    la, lb = float(pa.s[ie]), float(pb.s[je])
    closed = len(c.ends) == 2
    # Cut positions in both paths' arc length.
    cuts = [(0.0, 0.0, pa.nodes[0], pb.nodes[0])]
    inner = [(float(x), float(np.interp(x, sa, sb)), n, None)
             for x, n in zip(pa.bounds[1:-1], pa.nodes[1:-1], strict=True) if x < la - 1e-6]
    inner += [(float(np.interp(y, sb, sa)), float(y), None, n)
              for y, n in zip(pb.bounds[1:-1], pb.nodes[1:-1], strict=True) if y < lb - 1e-6]
    cuts += sorted(inner)
    cuts.append((la, lb, pa.nodes[-1] if closed else None, pb.nodes[-1] if closed else None))
    out = []
    for (a0, b0, na0, nb0), (a1, b1, na1, nb1) in zip(cuts[:-1], cuts[1:], strict=False):
        if a1 - a0 < 1e-6 or b1 - b0 < 1e-6:
            continue
        ka = int(np.clip(np.searchsorted(pa.bounds, 0.5 * (a0 + a1)) - 1, 0, len(pa.edges) - 1))
        kb = int(np.clip(np.searchsorted(pb.bounds, 0.5 * (b0 + b1)) - 1, 0, len(pb.edges) - 1))
        n = max(int(np.ceil(max(a1 - a0, b1 - b0))) + 1, 2)
        pts_a, r_a, rng_a = _piece(ga, pa, ka, a0, a1, n)
        pts_b, r_b, rng_b = _piece(gb, pb, kb, b0, b1, n)
        out.append(BranchPair(
            a=pa.edges[ka], b=pb.edges[kb], a_range=rng_a, b_range=rng_b, reversed_a=pa.rev[ka],
            reversed_b=pb.rev[kb], start=(na0, nb0), end=(na1, nb1), points_a_px=pts_a, points_b_px=pts_b,
            radius_a_px=r_a, radius_b_px=r_b,
            radius_mm=float(np.median(np.concatenate([r_a * mm_a, r_b * mm_b]))),
            error_px=c.cost, error_mm=c.cost * 0.5 * (mm_a + mm_b),
            found_by="landmarks" if closed else "one end"))
    return out


def _piece(g: CentrelineGraph, p: _Path, k: int, s0: float, s1: float, n: int
           ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Points, radii and own-order arc range of chain interval [s0, s1] inside its k-th branch."""
    b = g.branches[p.edges[k]]
    arc = p.arcs[k]
    L = float(arc[-1])
    scale = L / max(float(p.bounds[k + 1] - p.bounds[k]), 1e-12)
    t0, t1 = (s0 - p.bounds[k]) * scale, (s1 - p.bounds[k]) * scale
    t = np.linspace(t0, t1, n)
    own = L - t if p.rev[k] else t
    pts = np.stack([np.interp(own, arc, b.points_px[:, 0]), np.interp(own, arc, b.points_px[:, 1])], axis=1)
    r = np.interp(own, arc, b.radius_px)
    lo, hi = sorted((float(own[0]), float(own[-1])))
    return pts, r, (max(lo, 0.0), min(hi, L))


def plot_graph_match(graph_a: CentrelineGraph, graph_b: CentrelineGraph, match: GraphMatch | None,
                     path: Any, *, images: tuple[np.ndarray, np.ndarray] | None = None,
                     title: str = "") -> Any:
    """Picture of both views: skeleton, branches, landmarks by type, matched landmarks numbered alike.

    Paired branches share a colour across the views; unpaired branches are
    grey and dashed. End points are circles, branch points squares, crossings
    crosses; a matched landmark pair carries the same number in both views.
    Written atomically as PNG; returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io.atomic import atomic_path

    fig, axes = plt.subplots(1, 2, figsize=(13, 6.6))
    cmap = plt.get_cmap("tab20")
    colour_a: dict[int, Any] = {}
    colour_b: dict[int, Any] = {}
    number_a: dict[int, int] = {}
    number_b: dict[int, int] = {}
    if match is not None:
        for k, p in enumerate(match.pairs):
            colour_a.setdefault(p.a, cmap(k % 20))
            colour_b.setdefault(p.b, cmap(k % 20))
        for k, lm in enumerate(match.landmark_pairs):
            number_a[lm.a] = k
            number_b[lm.b] = k
    for ax, g, img, colours, numbers, name in ((axes[0], graph_a, None if images is None else images[0],
                                                colour_a, number_a, "A"),
                                               (axes[1], graph_b, None if images is None else images[1],
                                                colour_b, number_b, "B")):
        if img is not None:
            ax.imshow(img, cmap="gray")
        else:
            ax.imshow(np.zeros((g.view.rows, g.view.cols)), cmap="gray", vmin=0, vmax=1)
        sk_r, sk_c = np.nonzero(g.skeleton)
        ax.plot(sk_c, sk_r, ",", color="yellow", alpha=0.35)
        if match is not None:
            for p in match.pairs:
                pts = p.points_a_px if name == "A" else p.points_b_px
                ax.plot(pts[:, 0], pts[:, 1], "-", lw=2.2, color=colours[p.a if name == "A" else p.b])
        for b in g.branches:
            if b.index not in colours:
                ax.plot(b.points_px[:, 0], b.points_px[:, 1], "--", lw=1.2, color="0.6")
        for lm in g.landmarks:
            x, y = lm.point_px
            matched = lm.index in numbers
            ax.plot(x, y, "o" if lm.kind == "end" else "s", ms=7 if matched else 5,
                    mfc="cyan" if lm.kind == "end" else "magenta", mec="white" if matched else "none")
            if matched:
                ax.annotate(str(numbers[lm.index]), (x, y), xytext=(4, -4), textcoords="offset points",
                            color="white", fontsize=8, fontweight="bold")
        for c in g.crossings:
            ax.plot(*c.point_px, "x", color="orange", ms=8, mew=2)
        if g.root is not None:
            ax.plot(*g.landmarks[g.root].point_px, "*", color="red", ms=13)
        ax.set_title(f"view {name}: {len(g.branches)} branches, {len(g.branch_points)} branch points, "
                     f"{len(g.end_points)} ends, {len(g.crossings)} crossings", fontsize=9)
        ax.set_axis_off()
    if match is not None:
        fig.suptitle((title + "\n" if title else "") + f"{len(match.landmark_pairs)} matched landmarks "
                     f"(same number in both views), {len(match.pairs)} branch pairs (same colour); "
                     "circle end, square branch point, x crossing, star root", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return path
