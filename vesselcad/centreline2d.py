"""2D centreline graphs: skeleton, landmarks, branches, radius, crossings.

A vessel mask is thinned to a one-pixel skeleton (scikit-image), the skeleton
is turned into a graph whose nodes are landmarks (end points and branch
points, one per junction pixel cluster) and whose edges are branches (ordered
pixel paths), spurs are pruned relative to the local vessel radius, and the
apparent junctions of two vessels that only cross in projection are resolved
so that the graph is a tree. Every branch gets a radius profile (distance
transform of the mask) and a cubic B-spline fit in pixels.

See docs/centreline2d.md for the method, its parameters and its limits.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import cv2
import networkx as nx
import numpy as np
from scipy import interpolate, ndimage, sparse
from scipy.sparse import csgraph
from skimage import morphology

from .errors import ArgumentError, VesselcadWarning
from .geometry import CArmView, check_view
from .splines import PIXEL_NOISE_PX, arc_length, fit_curve_2d

__all__ = ["Landmark", "Branch2D", "Crossing", "CentrelineGraph", "centreline_graph", "catheter_tip"]

#: A terminal branch is a spur when it reaches less than this many local
#: radii beyond the surface of the vessel it leaves.
SPUR_RADII = 1.5
#: ... or less than this many pixels.
MIN_SPUR_PX = 4.0
#: Connected vessel pieces whose skeleton is shorter than this are dropped.
MIN_COMPONENT_PX = 12.0
#: Holes in the mask smaller than this (px) are filled before thinning.
MAX_HOLE_PX = 30
#: Branch points joined by an edge shorter than this many px (or local radii)
#: are one junction.
MERGE_PX = 3.0
#: Two branch points joined by an edge shorter than this many local radii
#: (plus MERGE_PX) are candidates for a crossing of two vessels.
CROSSING_RADII = 2.5
#: Largest bend (degrees) of a vessel passing through a crossing.
CROSSING_MAX_BEND_DEG = 35.0
#: Smallest angle (degrees) between two crossing vessels.
CROSSING_MIN_ANGLE_DEG = 15.0
#: The catheter tip is on the skeleton within a vessel radius plus this (px); a node this close
#: along the skeleton to the tip's nearest point is used as the root rather than a new one.
TIP_MARGIN_PX = 4.0
#: A catheter whose pixels 6-24 px beyond a vessel radius from its tip lie inside the vessel
#: mask for more than this share has cannulated the vessel (a coronary sinus catheter): the
#: ostium is where it enters, not its tip.
CANNULATED_SHARE = 0.5
#: ... counting a catheter pixel as inside where the vessel mask reaches this far (px) beyond the
#: catheter's edge.
CANNULATED_WALL_PX = 1.5
#: The vessel end nearest the catheter tip is the root when it lies within this (px); the
#: proximal vessel is often not yet (or no longer) filled with contrast next to the tip.
TIP_REACH_PX = 120.0
#: The distal end of the catheter that enters from the image border (as the phase matching finds
#: it) is its tip when it lies within this of the vessel mask (px).
TIP_ON_VESSEL_PX = 10.0
#: A catheter end within this (px) of that tip is the catheter going on past a vessel that hides
#: a stretch of it (a coronary sinus catheter inside the sinus): the tip, when the first is off
#: the vessel mask.
TIP_PIECE_PX = 40.0
#: Otherwise that tip is still the tip when it lies within this of the vessel mask (px: a model's
#: labels leave a few px of background between the catheter and the vessel it engages); farther,
#: the end of the catheter's skeleton nearest the vessels is.
TIP_NEAR_VESSEL_PX = 40.0
#: A balloon in the vessels (at least BALLOON_MIN_MM2 at the isocentre: an occlusion balloon of
#: 8-12 x 5-8 mm shows 30-80 mm²) farther than BALLOON_TIP_PX from the catheter
#: tip found: the catheter's last stretch before the balloon that carries it was labelled vessel,
#: and the balloon's end nearest the tip is taken for the tip.
BALLOON_MIN_MM2 = 25.0
BALLOON_TIP_PX = 80.0

@dataclass
class Landmark:
    """A node of the centreline graph.

    Attributes
    ----------
    index : int
    kind : {'end', 'branch'}
        End point (one branch) or branch point (three or more; two for a
        root inside a branch, where the skeleton runs through the ostium).
    point_px : numpy.ndarray, shape (2,)
        ``(col, row)`` in pixels (the centroid of a junction's pixel cluster).
    radius_px : float
        Vessel radius at the landmark (distance transform).
    degree : int
        Number of branches that meet here.
    """

    index: int
    kind: str
    point_px: np.ndarray
    radius_px: float
    degree: int


@dataclass
class Branch2D:
    """An edge of the centreline graph: one vessel segment between two landmarks.

    Points run from ``start`` to ``end``; after rooting, ``start`` is the
    proximal end (nearer the root along the tree).

    Attributes
    ----------
    index : int
    start, end : int
        Landmark indices.
    points_px : numpy.ndarray, shape (n, 2)
        Ordered ``(col, row)`` pixels, from the start landmark to the end landmark.
    radius_px, radius_mm : numpy.ndarray, shape (n,)
        Radius at each point, in pixels and in mm at the isocentre plane.
    crossings : list of int
        Indices into :attr:`CentrelineGraph.crossings` this branch passes through.
    spline : scipy.interpolate.BSpline
        Cubic B-spline of the points (px), parametrized by arc length, its
        smoothing chosen from the pixel noise (fitted on first access).
    noise_px : float
        Pixel noise used for that smoothing: given, or estimated from the
        points but at least ``vesselcad.splines.PIXEL_NOISE_PX`` (the
        skeleton's pixel quantization).
    """

    index: int
    start: int
    end: int
    points_px: np.ndarray
    radius_px: np.ndarray
    radius_mm: np.ndarray
    crossings: list[int] = field(default_factory=list)
    noise_request: float | None = field(default=None, repr=False)
    _fit: tuple[interpolate.BSpline, float] | None = field(default=None, repr=False, compare=False)

    def _fitted(self) -> tuple[interpolate.BSpline, float]:
        if self._fit is None:
            self._fit = fit_curve_2d(self.points_px, self.noise_request, f"branch {self.index}",
                                     PIXEL_NOISE_PX)
        return self._fit

    @property
    def spline(self) -> interpolate.BSpline:
        return self._fitted()[0]

    @property
    def noise_px(self) -> float:
        return self._fitted()[1]

    @property
    def length_px(self) -> float:
        """Arc length of the pixel path."""
        return float(arc_length(self.points_px)[-1])


@dataclass
class Crossing:
    """Two vessels that cross in the projection (resolved, not a branch point).

    Attributes
    ----------
    point_px : numpy.ndarray, shape (2,)
    branches : tuple of int
        The two branches passing through.
    angle_deg : float
        Angle between the two vessels.
    """

    point_px: np.ndarray
    branches: tuple[int, int]
    angle_deg: float


@dataclass
class CentrelineGraph:
    """Centreline graph of one view: landmarks (nodes) and branches (edges).

    Attributes
    ----------
    view : CArmView
    landmarks : list of Landmark
    branches : list of Branch2D
    crossings : list of Crossing
    root : int or None
        Landmark index of the root (ostium / catheter tip end) of the largest tree.
    graph : networkx.MultiGraph
        Nodes are landmark indices (attributes ``kind``, ``point``); edges carry
        ``branch`` (the index into :attr:`branches`) and ``length``.
    skeleton : numpy.ndarray, shape (H, W) bool
        The thinned mask.
    radius_map_px : numpy.ndarray, shape (H, W) float32
        Distance transform minus half a pixel: the vessel radius at centreline pixels.
    warnings : list of str
    """

    view: CArmView
    landmarks: list[Landmark]
    branches: list[Branch2D]
    crossings: list[Crossing]
    root: int | None
    graph: nx.MultiGraph
    skeleton: np.ndarray
    radius_map_px: np.ndarray
    warnings: list[str] = field(default_factory=list)

    def _points(self, kind: str) -> np.ndarray:
        pts = [lm.point_px for lm in self.landmarks if lm.kind == kind]
        return np.array(pts, dtype=float).reshape(-1, 2)

    @property
    def branch_points(self) -> np.ndarray:
        """(K, 2) ``(col, row)`` px of the branch points."""
        return self._points("branch")

    @property
    def end_points(self) -> np.ndarray:
        """(M, 2) ``(col, row)`` px of the end points."""
        return self._points("end")

    @property
    def landmark_points(self) -> np.ndarray:
        """(N, 2) ``(col, row)`` px of all landmarks, in landmark index order."""
        return np.array([lm.point_px for lm in self.landmarks], dtype=float).reshape(-1, 2)

    @property
    def total_length_px(self) -> float:
        """Summed length of all branches in pixels."""
        return float(sum(b.length_px for b in self.branches))

    def is_tree(self) -> bool:
        """True when every connected component of :attr:`graph` is a tree."""
        return self.graph.number_of_edges() == self.graph.number_of_nodes() - nx.number_connected_components(
            self.graph)

    def __repr__(self) -> str:
        k = sum(lm.kind == "branch" for lm in self.landmarks)
        return (f"CentrelineGraph({len(self.branches)} branches, {k} branch points, "
                f"{len(self.landmarks) - k} end points, {len(self.crossings)} crossings, root={self.root})")


# ----------------------------------------------------------------- skeleton
def _edt(mask: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance of each True pixel to the nearest False pixel (OpenCV, float32)."""
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _as_mask(mask: Any, name: str, shape: tuple[int, int] | None) -> np.ndarray:
    try:
        arr = np.asarray(mask)
    except Exception as exc:  # noqa: BLE001 - anything that is not array-like
        raise ArgumentError(f"{name}: expected an (H, W) boolean array ({exc})") from None
    if arr.ndim != 2:
        raise ArgumentError(f"{name}: expected an (H, W) array, got shape {arr.shape}")
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number):
            raise ArgumentError(f"{name}: expected a boolean or numeric array, got dtype {arr.dtype}")
        arr = arr != 0
    if shape is not None and arr.shape != shape:
        raise ArgumentError(f"{name}: shape {arr.shape} does not match the view's (rows, cols) {shape}")
    return arr


def _pixel_graph(skel: np.ndarray) -> tuple[np.ndarray, np.ndarray, sparse.csr_matrix]:
    """Skeleton pixels and their adjacency (8-neighbours, no redundant diagonals).

    A diagonal neighbour is dropped when the two pixels share a 4-neighbour on
    the skeleton: the step is already connected through that pixel, and the
    diagonal would make a triangle and a false branch point.
    """
    rr, cc = np.nonzero(skel)
    n = len(rr)
    pad = np.pad(skel, 1)
    idx = np.full(pad.shape, -1, np.int64)
    idx[rr + 1, cc + 1] = np.arange(n)
    src, dst = [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        j = idx[rr + 1 + dr, cc + 1 + dc]
        ok = j >= 0
        if dr and dc:
            ok &= ~(pad[rr + 1 + dr, cc + 1] | pad[rr + 1, cc + 1 + dc])
        src.append(np.nonzero(ok)[0])
        dst.append(j[ok])
    s, d = np.concatenate(src), np.concatenate(dst)
    adj = sparse.coo_matrix((np.ones(len(s), np.int8), (s, d)), shape=(n, n)).tocsr()
    adj = (adj + adj.T).tocsr()
    return rr, cc, adj


class _Work:
    """Mutable landmark graph used while pruning and resolving (internal)."""

    def __init__(self) -> None:
        self.nodes: dict[int, np.ndarray] = {}
        self.edges: dict[int, tuple[int, int, np.ndarray]] = {}
        self.crossing_of: dict[int, list[int]] = {}
        self.crossings: list[tuple[np.ndarray, float]] = []
        self._next_node = 0
        self._next_edge = 0
        self.root_hint: int | None = None  # a node chosen as root (the ostium inside a branch)

    def add_node(self, p: np.ndarray) -> int:
        k = self._next_node
        self._next_node += 1
        self.nodes[k] = np.asarray(p, float)
        return k

    def add_edge(self, u: int, v: int, pts: np.ndarray, crossings: list[int] | None = None) -> int:
        k = self._next_edge
        self._next_edge += 1
        self.edges[k] = (u, v, np.asarray(pts, float))
        self.crossing_of[k] = list(crossings or [])
        return k

    def remove_edge(self, k: int) -> None:
        del self.edges[k]
        self.crossing_of.pop(k, None)

    def incident(self) -> dict[int, list[int]]:
        inc: dict[int, list[int]] = {n: [] for n in self.nodes}
        for k, (u, v, _) in self.edges.items():
            inc[u].append(k)
            if v != u:
                inc[v].append(k)
            else:
                inc[u].append(k)
        return inc

    def to_nx(self) -> nx.MultiGraph:
        """The current graph as networkx (edge keys = edge ids, attribute ``length`` in px)."""
        g = nx.MultiGraph()
        g.add_nodes_from(self.nodes)
        for k, (u, v, pts) in self.edges.items():
            g.add_edge(u, v, key=k, length=_length(pts))
        return g

    def degree(self, n: int) -> int:
        return sum((u == n) + (v == n) for u, v, _ in self.edges.values())

    def oriented(self, k: int, n: int) -> np.ndarray:
        """Points of edge ``k`` running away from node ``n``."""
        u, _, pts = self.edges[k]
        return pts if u == n else pts[::-1]

    def other(self, k: int, n: int) -> int:
        u, v, _ = self.edges[k]
        return v if u == n else u

    def splice(self, n: int) -> None:
        """Replace a degree-2 node by one edge through it."""
        inc = self.incident()[n]
        if len(inc) != 2 or inc[0] == inc[1]:
            return
        k1, k2 = inc
        a = self.other(k1, n)
        b = self.other(k2, n)
        pts = np.concatenate([self.oriented(k1, n)[::-1], self.oriented(k2, n)[1:]])
        cr = self.crossing_of[k1] + self.crossing_of[k2]
        self.remove_edge(k1)
        self.remove_edge(k2)
        del self.nodes[n]
        if self.root_hint == n:
            self.root_hint = None
        self.add_edge(a, b, pts, cr)


def _length(pts: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))) if len(pts) > 1 else 0.0


def _build(skel: np.ndarray) -> _Work:
    """Landmark graph of a skeleton: junction clusters and end pixels as nodes, chains as edges."""
    w = _Work()
    rr, cc, adj = _pixel_graph(skel)
    n = len(rr)
    if n == 0:
        return w
    deg = np.asarray(adj.sum(axis=1)).ravel()
    xy = np.stack([cc, rr], axis=1).astype(float)
    junction = deg >= 3
    # Junction clusters: connected junction pixels are one branch point.
    jidx = np.nonzero(junction)[0]
    cluster = np.full(n, -1, np.int64)
    if jidx.size:
        sub = adj[jidx][:, jidx]
        n_cl, lab = csgraph.connected_components(sub, directed=False)
        cluster[jidx] = lab
        cl_node = [w.add_node(xy[jidx[lab == k]].mean(axis=0)) for k in range(n_cl)]
    else:
        cl_node = []
    # Chains: the remaining pixels; each component is a path (or a ring).
    cidx = np.nonzero(~junction)[0]
    if cidx.size == 0:
        return w
    csub = adj[cidx][:, cidx]
    n_ch, chlab = csgraph.connected_components(csub, directed=False)
    cdeg = np.asarray(csub.sum(axis=1)).ravel()
    order_all = np.argsort(chlab, kind="stable")
    bounds = np.searchsorted(chlab[order_all], np.arange(n_ch + 1))
    adj_j = adj[:, jidx] if jidx.size else None
    for k in range(n_ch):
        loc = order_all[bounds[k]:bounds[k + 1]]
        ends = loc[cdeg[loc] <= 1]
        if ends.size == 0:  # a ring without junctions: cut it open anywhere
            start_local = loc[0]
        else:
            start_local = ends[0]
        path = cidx[csgraph.depth_first_order(csub, int(start_local), directed=False,
                                              return_predecessors=False)]
        pts = xy[path]
        # Attach each end to an adjacent junction cluster, or make it an end point.
        attach = []
        for end_pix in (path[0], path[-1]):
            node = None
            if adj_j is not None:
                nb = adj_j[end_pix].indices
                if nb.size:
                    node = cl_node[int(cluster[jidx[nb[0]]])]
            attach.append(node)
        if len(path) == 1 and attach[0] is not None:
            # One pixel between two junction clusters: join them through it.
            nb = adj_j[path[0]].indices
            nodes = sorted({cl_node[int(cluster[jidx[i]])] for i in nb})
            if len(nodes) >= 2:
                attach = [nodes[0], nodes[1]]
        u = attach[0] if attach[0] is not None else w.add_node(pts[0])
        v = attach[1] if attach[1] is not None else w.add_node(pts[-1])
        full = np.concatenate([[w.nodes[u]], pts, [w.nodes[v]]])
        # Drop the duplicated end pixel of free ends.
        if attach[0] is None:
            full = full[1:]
        if attach[1] is None:
            full = full[:-1]
        w.add_edge(u, v, full)
    # Junction clusters touching each other only diagonally are not connected
    # through a chain pixel: join them with a straight edge.
    if jidx.size:
        sub = adj[jidx][:, jidx]
        lab = cluster[jidx]
        a, b = sub.nonzero()
        pairs = {(int(lab[i]), int(lab[j])) for i, j in zip(a, b, strict=False) if lab[i] < lab[j]}
        for p, q in pairs:
            w.add_edge(cl_node[p], cl_node[q], np.array([w.nodes[cl_node[p]], w.nodes[cl_node[q]]]))
    return w


# ------------------------------------------------------------ graph surgery
def _radius_at(rmap: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return ndimage.map_coordinates(rmap, [pts[:, 1], pts[:, 0]], order=1, mode="nearest")


def _prune_spurs(w: _Work, rmap: np.ndarray) -> int:
    removed = 0
    changed = True
    while changed:
        changed = False
        inc = w.incident()
        deg = {n: len(v) for n, v in inc.items()}
        cand = []
        for k, (u, v, pts) in w.edges.items():
            if u == v:
                continue
            for end, junc in ((u, v), (v, u)):
                if deg[end] == 1 and deg[junc] >= 3:
                    r_j = float(_radius_at(rmap, w.nodes[junc][None])[0])
                    beyond = _length(pts) - r_j
                    if beyond < max(MIN_SPUR_PX, SPUR_RADII * r_j):
                        cand.append((_length(pts), k, end, junc))
        # Remove the shortest spur of each junction first, one per junction per pass.
        done: set[int] = set()
        for _, k, end, junc in sorted(cand):
            if junc in done or k not in w.edges or w.degree(junc) < 3:
                continue
            w.remove_edge(k)
            del w.nodes[end]
            done.add(junc)
            removed += 1
            changed = True
        for junc in done:
            if junc in w.nodes and w.degree(junc) == 2:
                w.splice(junc)
    return removed


def _merge_close_junctions(w: _Work, rmap: np.ndarray) -> None:
    """Contract short edges between branch points into one junction."""
    changed = True
    while changed:
        changed = False
        inc = w.incident()
        for k, (u, v, pts) in sorted(w.edges.items(), key=lambda it: _length(it[1][2])):
            if u == v or len(inc[u]) < 3 or len(inc[v]) < 3:
                continue
            r = float(np.max(_radius_at(rmap, np.array([w.nodes[u], w.nodes[v]]))))
            if _length(pts) <= max(MERGE_PX, 0.5 * r):
                _contract(w, k)
                changed = True
                break


def _contract(w: _Work, k: int) -> None:
    u, v, pts = w.edges[k]
    mid = pts[len(pts) // 2] if len(pts) > 2 else 0.5 * (w.nodes[u] + w.nodes[v])
    w.remove_edge(k)
    w.nodes[u] = np.asarray(mid, float)
    for e, (a, b, p) in list(w.edges.items()):
        if a == v or b == v:
            a2 = u if a == v else a
            b2 = u if b == v else b
            p = p.copy()
            if a == v:
                p[0] = mid
            if b == v:
                p[-1] = mid
            if a == u:
                p[0] = mid
            if b == u:
                p[-1] = mid
            w.edges[e] = (a2, b2, p)
        elif a == u or b == u:
            p = p.copy()
            if a == u:
                p[0] = mid
            if b == u:
                p[-1] = mid
            w.edges[e] = (a, b, p)
    del w.nodes[v]


def _out_tangent(pts: np.ndarray, reach: float) -> np.ndarray:
    """Unit direction from the first point to the point ``reach`` px along the path."""
    s = arc_length(pts)
    j = int(np.searchsorted(s, min(reach, s[-1])))
    j = min(max(j, 1), len(pts) - 1)
    d = pts[j] - pts[0]
    return d / max(float(np.linalg.norm(d)), 1e-12)


def _bend(t_in_out: np.ndarray, t_out: np.ndarray) -> float:
    """Bend (deg) of a vessel that leaves a node along ``t_out`` after arriving from ``t_in_out``.

    Both are outgoing directions; a straight vessel has them opposite (bend 0).
    """
    c = float(np.clip(np.dot(-t_in_out, t_out), -1.0, 1.0))
    return float(np.degrees(np.arccos(c)))


def _angle_between_lines(t1: np.ndarray, t2: np.ndarray) -> float:
    """Angle (deg, 0..90) between two undirected lines given by direction vectors of any length."""
    t1 = t1 / max(float(np.linalg.norm(t1)), 1e-12)
    t2 = t2 / max(float(np.linalg.norm(t2)), 1e-12)
    c = abs(float(np.clip(np.dot(t1, t2), -1.0, 1.0)))
    return float(np.degrees(np.arccos(c)))


def _best_pairing(tans: list[np.ndarray]) -> tuple[tuple[int, int], tuple[int, int], float, float]:
    """Split four outgoing directions into two through-going vessels (least total bend)."""
    best = None
    for p1, p2 in (((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))):
        b1 = _bend(tans[p1[0]], tans[p1[1]])
        b2 = _bend(tans[p2[0]], tans[p2[1]])
        if best is None or max(b1, b2) < best[2]:
            ang = _angle_between_lines(tans[p1[1]] - tans[p1[0]], tans[p2[1]] - tans[p2[0]])
            best = (p1, p2, max(b1, b2), ang)
    assert best is not None
    return best


def _resolve_crossings(w: _Work, rmap: np.ndarray) -> None:
    """Replace X junctions (one 4-way node, or two 3-way nodes with a short edge) by crossings."""
    changed = True
    while changed:
        changed = False
        inc = w.incident()
        # Case 1: one node where four branches meet.
        for n, ks in inc.items():
            if len(ks) != 4 or len(set(ks)) != 4:
                continue
            r = float(_radius_at(rmap, w.nodes[n][None])[0])
            reach = max(6.0, 3.0 * r)
            paths = [w.oriented(k, n) for k in ks]
            tans = [_out_tangent(p, reach) for p in paths]
            p1, p2, bend, ang = _best_pairing(tans)
            if bend > CROSSING_MAX_BEND_DEG or ang < CROSSING_MIN_ANGLE_DEG:
                continue
            ci = len(w.crossings)
            w.crossings.append((w.nodes[n].copy(), ang))
            new = []
            for i, j in (p1, p2):
                pts = np.concatenate([paths[i][::-1], paths[j][1:]])
                cr = w.crossing_of[ks[i]] + w.crossing_of[ks[j]] + [ci]
                new.append((w.other(ks[i], n), w.other(ks[j], n), pts, cr))
            for k in ks:
                w.remove_edge(k)
            del w.nodes[n]
            for a, b, pts, cr in new:
                w.add_edge(a, b, pts, cr)
            changed = True
            break
        if changed:
            continue
        # Case 2: two 3-way nodes joined by a short edge.
        for k, (u, v, spts) in sorted(w.edges.items(), key=lambda it: _length(it[1][2])):
            if u == v or len(inc[u]) != 3 or len(inc[v]) != 3:
                continue
            r = float(np.max(_radius_at(rmap, np.array([w.nodes[u], w.nodes[v]]))))
            if _length(spts) > CROSSING_RADII * r + MERGE_PX:
                continue
            au = [e for e in inc[u] if e != k]
            bv = [e for e in inc[v] if e != k]
            if len(au) != 2 or len(bv) != 2 or set(au) & set(bv):
                continue
            reach = max(6.0, 3.0 * r)
            pa = [w.oriented(e, u) for e in au]
            pb = [w.oriented(e, v) for e in bv]
            ta = [_out_tangent(p, reach) for p in pa]
            tb = [_out_tangent(p, reach) for p in pb]
            best = None
            for perm in ((0, 1), (1, 0)):
                b1 = _bend(ta[0], tb[perm[0]])
                b2 = _bend(ta[1], tb[perm[1]])
                if best is None or max(b1, b2) < best[0]:
                    best = (max(b1, b2), perm)
            assert best is not None
            bend, perm = best
            ang = _angle_between_lines(tb[perm[0]] - ta[0], tb[perm[1]] - ta[1])
            if bend > CROSSING_MAX_BEND_DEG or ang < CROSSING_MIN_ANGLE_DEG:
                continue
            ci = len(w.crossings)
            w.crossings.append((spts[len(spts) // 2].copy(), ang))
            new = []
            for i in (0, 1):
                j = perm[i]
                pts = np.concatenate([pa[i][::-1], spts[1:], pb[j][1:]])
                cr = w.crossing_of[au[i]] + w.crossing_of[k] + w.crossing_of[bv[j]] + [ci]
                new.append((w.other(au[i], u), w.other(bv[j], v), pts, cr))
            for e in au + bv + [k]:
                w.remove_edge(e)
            del w.nodes[u], w.nodes[v]
            for a, b, pts, cr in new:
                w.add_edge(a, b, pts, cr)
            changed = True
            break


def _drop_small_components(w: _Work) -> float:
    g = w.to_nx()
    dropped = 0.0
    for comp in list(nx.connected_components(g)):
        length = sum(d["length"] for _, _, d in g.subgraph(comp).edges(data=True))
        if length < MIN_COMPONENT_PX:
            dropped += length
            for _, _, key in g.subgraph(comp).edges(keys=True):
                w.remove_edge(key)
            for n in comp:
                del w.nodes[n]
    return dropped


def _break_cycles(w: _Work, root_of: dict[int, int]) -> int:
    """Cut each edge that closes a cycle at its end farther from the root (it becomes an end point)."""
    g = w.to_nx()
    cut = 0
    for comp in nx.connected_components(g):
        sub = g.subgraph(comp)
        if sub.number_of_edges() == len(comp) - 1:
            continue
        root = root_of.get(min(comp), next(iter(comp)))
        root = root if root in comp else next(iter(comp))
        dist, paths = nx.single_source_dijkstra(sub, root, weight="length")
        tree_edges = set()
        for _n, p in paths.items():
            if len(p) >= 2:
                a, b = p[-2], p[-1]
                best = min(sub[a][b].items(), key=lambda kv: kv[1]["length"])[0]
                tree_edges.add(best)
        for _, _, key in list(sub.edges(keys=True)):
            if key in tree_edges or key not in w.edges:
                continue
            u, v, pts = w.edges[key]
            far = u if dist.get(u, 0) >= dist.get(v, 0) else v
            # Detach the far end: a new end point a pixel short of the junction.
            oriented = w.oriented(key, far)[::-1]  # runs toward `far`
            if len(oriented) > 2:
                oriented = oriented[:-1]
            near = w.other(key, far)
            crs = w.crossing_of[key]
            w.remove_edge(key)
            new_end = w.add_node(oriented[-1])
            w.add_edge(near, new_end, oriented, crs)
            if w.degree(far) == 2:
                w.splice(far)
            cut += 1
    return cut


# --------------------------------------------------------------------- API
def centreline_graph(
    mask: Any,
    view: CArmView,
    *,
    labels: Any = None,
    noise_px: float | None = None,
    tip: Any = None,
) -> CentrelineGraph:
    """Centreline graph of a vessel mask.

    Parameters
    ----------
    mask : array_like, shape (H, W)
        Vessel pixels (bool, or non-zero = vessel), ``(H, W) == (view.rows, view.cols)``.
    view : CArmView
        The view the mask was taken in (pixel size and magnification for mm radii).
    labels : array_like, shape (H, W), optional
        The frame's segmentation classes (0 background, 1 vessel, 2 catheter,
        3 balloon, 4 lead). Devices hide the vessels they lie over: a balloon
        touching the vessel is counted as vessel (it sits inside one), and
        catheter or lead pixels that close a gap in the vessel mask are too.
        The root (the ostium) is found from the catheter tip: the vessel end
        there, a node split into the branch where the skeleton runs through
        the tip, or, for a catheter inside the vessel, the end where it
        enters (docs/centreline2d.md).
    noise_px : float, optional
        Pixel noise of the skeleton for the B-spline smoothing; estimated per
        branch when omitted.
    tip : (2,) array_like, optional
        The catheter tip ``(col, row)`` to root the tree at, when known better
        than one frame's labels tell (``reconstruct`` passes the phase
        matching's key point, which the other view confirmed); with
        ``labels`` only. Default: found in ``labels``.

    Returns
    -------
    CentrelineGraph
        Branches ordered from the root outwards where a root is known.

    Raises
    ------
    ArgumentError
        Wrong view, mask of the wrong shape or type.

    Examples
    --------
    >>> graph = vc.centreline_graph(labels == 1, view, labels=labels)  # doctest: +SKIP
    >>> graph.branch_points.shape, graph.branches[0].radius_mm[:3]  # doctest: +SKIP
    """
    check_view(view, "view")
    shape = (view.rows, view.cols)
    m = _as_mask(mask, "mask", shape)
    cath = None
    on_balloon = None  # balloon pixels that sit in the vessels
    if labels is not None:
        lab = np.asarray(labels)
        if lab.shape != shape or not np.issubdtype(lab.dtype, np.integer):
            raise ArgumentError(f"labels: expected an integer (H, W) = {shape} class image, got "
                                f"{lab.dtype} {lab.shape}")
        cath = lab == 2
        if m.any():
            balloon = lab == 3
            if balloon.any():
                # A balloon sits inside a vessel: its components that touch the vessel are vessel.
                lab_b, _ = ndimage.label(balloon)
                touch = np.unique(lab_b[ndimage.binary_dilation(m, iterations=2) & balloon])
                on_balloon = np.isin(lab_b, touch[touch > 0])
                m = m | on_balloon
            m = _fill_occlusions(m, (lab == 2) | (lab == 4))
    given_tip = None
    if tip is not None:
        try:
            given_tip = np.asarray(tip, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ArgumentError(f"tip: expected a finite (col, row) point, got {tip!r}") from None
        if given_tip.shape != (2,) or not np.isfinite(given_tip).all():
            raise ArgumentError(f"tip: expected a finite (col, row) point, got {tip!r}")
        if labels is None:
            raise ArgumentError("tip: needs labels (the catheter it is the tip of)")
        given_tip = np.clip(given_tip, 0, [shape[1] - 1, shape[0] - 1])
    if noise_px is not None and not (np.isfinite(noise_px) and noise_px >= 0):
        raise ArgumentError(f"noise_px: expected a finite value >= 0, got {noise_px!r}")
    notes: list[str] = []
    m = _fill_small_holes(m, MAX_HOLE_PX)
    dist = _edt(np.pad(m, 1))[1:-1, 1:-1]
    rmap = np.maximum(dist - 0.5, 0.0).astype(np.float32)
    skel = morphology.skeletonize(m)
    w = _build(skel)
    n_spurs = _prune_spurs(w, rmap)
    dropped = _drop_small_components(w)
    if dropped:
        notes.append(f"dropped {dropped:.0f} px of isolated skeleton pieces shorter than "
                     f"{MIN_COMPONENT_PX} px")
    _merge_close_junctions(w, rmap)
    _resolve_crossings(w, rmap)
    for n in [n for n in w.nodes if w.degree(n) == 2]:
        w.splice(n)
    # Root: the end point nearest the catheter, else the widest end of the longest component.
    tip = None
    if given_tip is not None:
        tip = given_tip
    elif cath is not None and cath.any():
        # The distal end of the catheter that enters from the image border (the phase matching's
        # key point: robust to a catheter cut by vessels and to pieces labelled catheter on the
        # vessels) where it touches the vessels; off them, a catheter end near it (docs/
        # centreline2d.md step 7).
        from .phase import find_keypoints

        kp = find_keypoints(lab[None], "catheter").points_px[0]
        tip = kp if np.isfinite(kp).all() else None
        gap = _edt(~m)[int(round(tip[1])), int(round(tip[0]))] if tip is not None and m.any() else np.inf
        if gap > TIP_ON_VESSEL_PX:
            # Not on the vessels: the catheter goes on beyond a vessel that hides a stretch of it (a
            # catheter end within TIP_PIECE_PX, nearest the vessels), or the tip is short of the
            # vessel (model labels: its last px counted as background). Only without a border-
            # entering catheter near the vessels is any catheter end taken: a model's specks of
            # catheter on the vessels far from the catheter would be taken for its tip.
            near_tip = catheter_tip(cath, m, around=tip, within=TIP_PIECE_PX) if tip is not None else None
            if near_tip is not None:
                tip = near_tip
            elif gap > TIP_NEAR_VESSEL_PX:
                tip = catheter_tip(cath, m)
    if on_balloon is not None:
        # Only a balloon-sized one counts (a model's specks do not), with the pieces of at least a
        # tenth of its size (a balloon the labels split).
        lab_b, _ = ndimage.label(on_balloon)
        size = np.bincount(lab_b.ravel())[1:]
        on_balloon = (np.isin(lab_b, 1 + np.flatnonzero(size >= 0.1 * size.max()))
                      if size.max() * float(np.prod(view.mm_per_px)) >= BALLOON_MIN_MM2 else None)
    if tip is not None and on_balloon is not None:
        # The balloon sits at the end of the catheter that carries it (a coronary sinus occlusion
        # balloon). A tip found far short of it means the catheter's last stretch was labelled
        # vessel: the vessels reached past it are the catheter; the balloon's end nearest the tip
        # is then the most proximal point known to be in the vessel.
        br, bc = np.nonzero(on_balloon)
        d_bal = np.hypot(bc - tip[0], br - tip[1])
        k = int(np.argmin(d_bal))
        if d_bal[k] > BALLOON_TIP_PX:
            tip = np.array([bc[k], br[k]], float)
    entry = None
    if tip is not None:
        if _cannulated(cath, m, rmap, tip):
            entry = _edt(~cath)  # the ostium is where the catheter enters the vessel
        else:
            w.root_hint = _root_at_tip(w, rmap, tip, m)  # the skeleton runs through the ostium: a node there
    root_of = _choose_roots(w, rmap, tip, entry)
    n_cut = 0
    for _ in range(50):  # splicing after a cut renumbers edges: repeat until no loop is left
        cut = _break_cycles(w, root_of)
        n_cut += cut
        if not cut:
            break
    if n_cut:
        notes.append(f"{n_cut} loop(s) that are not crossings were cut open at the end farther from the root")
        root_of = _choose_roots(w, rmap, tip, entry)
    graph = _finish(w, rmap, view, root_of, skel, noise_px)
    graph.warnings.extend(notes)
    if n_spurs:
        graph.warnings.append(f"pruned {n_spurs} spur(s)")
    for note in notes:
        warnings.warn(note, VesselcadWarning, stacklevel=2)
    return graph


def _fill_small_holes(m: np.ndarray, max_px: int) -> np.ndarray:
    """Fill background regions enclosed by the mask that have at most ``max_px`` pixels."""
    holes = ndimage.binary_fill_holes(m) & ~m
    if not holes.any():
        return m
    lab, n = ndimage.label(holes)
    size = np.bincount(lab.ravel(), minlength=n + 1)
    small = size <= max_px
    small[0] = False
    return m | small[lab]


def _fill_occlusions(m: np.ndarray, occ: np.ndarray) -> np.ndarray:
    """Count device pixels as vessel where they close a gap in the vessel mask.

    A morphological closing of the vessel mask with a disk a little wider
    than the device's half-width, kept only on device pixels: a catheter or
    lead lying across a vessel cuts it, and the closing joins the two sides
    through the device and nowhere else.
    """
    if not occ.any():
        return m
    half = float(_edt(occ).max())
    radius = int(np.clip(np.ceil(half) + 2, 3, 12))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    closed = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_CONSTANT,
                              borderValue=0).astype(bool)
    return m | (occ & closed)


def catheter_tip(catheter: np.ndarray, near: np.ndarray | None = None, *, around: np.ndarray | None = None,
                 within: float = np.inf) -> np.ndarray | None:
    """``(col, row)`` of the catheter tip: the end of its skeleton inside the image nearest ``near`` pixels.

    Parameters
    ----------
    catheter : (H, W) bool array
    near : (H, W) bool array, optional
        Pixels (the vessels) the tip is nearest to; else the first end found.
    around : (2,) array, optional
        Only skeleton ends within ``within`` px of this point ``(col, row)`` count.
    within : float

    Returns None when the mask has no (such) catheter end away from the image border.
    """
    sk = morphology.skeletonize(catheter)
    if not sk.any():
        return None
    rr, cc, adj = _pixel_graph(sk)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    h, w = catheter.shape
    inner = (rr > 2) & (rr < h - 3) & (cc > 2) & (cc < w - 3)
    ends = np.nonzero((deg == 1) & inner)[0]
    if around is not None and ends.size:
        ends = ends[np.hypot(cc[ends] - around[0], rr[ends] - around[1]) <= within]
    if ends.size == 0:
        return None
    pts = np.stack([cc[ends], rr[ends]], axis=1).astype(float)
    if near is not None and near.any():
        d = _edt(~near)[rr[ends], cc[ends]]
        return pts[int(np.argmin(d))]
    return pts[0]


def _cannulated(cath: np.ndarray, m: np.ndarray, rmap: np.ndarray, tip: np.ndarray) -> bool:
    """Whether the catheter runs inside the vessel behind its tip (``CANNULATED_SHARE``).

    A catheter pixel is inside the vessel where the vessel mask reaches at
    least ``CANNULATED_WALL_PX`` beyond the catheter's own edge: catheter pixels
    that are vessel only because they close a gap in it (the catheter lying
    across the vessel, or the model labelling a vessel's stretch catheter)
    have no vessel round them.
    """
    rr, cc = np.nonzero(cath)
    d = np.hypot(cc - tip[0], rr - tip[1])
    r = float(_radius_at(rmap, np.asarray(tip, float)[None])[0])
    ring = (d >= r + 6.0) & (d <= r + 24.0)
    if not ring.any():
        return False
    rr, cc = rr[ring], cc[ring]
    inside = m[rr, cc] & (rmap[rr, cc] >= _edt(cath)[rr, cc] + CANNULATED_WALL_PX)
    return bool(np.mean(inside) > CANNULATED_SHARE)


def _root_at_tip(w: _Work, rmap: np.ndarray, tip: np.ndarray, m: np.ndarray) -> int | None:
    """The node at the catheter tip where the skeleton runs through the ostium, split in if needed.

    In a projection the ostium is often not a vessel end: a side branch (or
    the left main's two daughters) leaves it in the other direction, and the
    skeleton runs on through it. The catheter's last pixels cover the vessel's
    first ones (its label wins), so the tip itself often lies a catheter
    radius or more off the vessel mask: the vessel pixel nearest the tip
    (within ``TIP_ON_VESSEL_PX``) stands for it. When the skeleton passes
    within a vessel radius (plus ``TIP_MARGIN_PX``) of that pixel and no end
    point *of the same skeleton piece* lies within about the tip's distance
    from the skeleton plus a radius (a skeleton stops about a radius short of
    a vessel's end), the branch is split at its point nearest that pixel, or an
    existing node there is used. None otherwise. (An end of another piece near
    the tip, a stub the catheter cut off, does not make the tree's own end the
    root: that end can lie far down the tree.)
    """
    if not w.edges:
        return None
    rr, cc = np.nonzero(m)
    if not len(rr):
        return None
    gap = np.hypot(cc - tip[0], rr - tip[1])
    i = int(np.argmin(gap))
    if gap[i] > TIP_ON_VESSEL_PX:
        return None  # the tip is not at the vessel
    at_vessel = np.array([cc[i], rr[i]], float)
    keys = list(w.edges)
    pts = [w.edges[k][2] for k in keys]
    flat = np.concatenate(pts)
    owner = np.repeat(np.arange(len(keys)), [len(p) for p in pts])
    at = np.concatenate([np.arange(len(p)) for p in pts])
    d = np.linalg.norm(flat - at_vessel, axis=1)
    q = int(np.argmin(d))
    r = float(_radius_at(rmap, flat[q][None])[0])
    if d[q] > r + TIP_MARGIN_PX:
        return None  # that vessel pixel is on no skeleton piece (a dropped one)
    reach = float(np.linalg.norm(flat[q] - tip))
    piece = nx.node_connected_component(w.to_nx(), w.edges[keys[owner[q]]][0])
    ends = [n for n in piece if w.degree(n) == 1]
    if ends and min(float(np.linalg.norm(w.nodes[n] - tip)) for n in ends) <= reach + r + TIP_MARGIN_PX:
        return None  # an end lies at the tip: the usual root
    k, j = keys[owner[q]], int(at[q])
    u, v, line = w.edges[k]
    if _length(line[: j + 1]) <= TIP_MARGIN_PX:
        return u
    if _length(line[j:]) <= TIP_MARGIN_PX:
        return v
    crs = w.crossing_of[k]
    w.remove_edge(k)
    n = w.add_node(line[j])
    halves = (line[: j + 1], line[j:])
    side = [int(np.argmin([np.min(np.linalg.norm(h - w.crossings[c][0], axis=1)) for h in halves]))
            for c in crs]
    w.add_edge(u, n, halves[0], [c for c, sd in zip(crs, side, strict=True) if sd == 0])
    w.add_edge(n, v, halves[1], [c for c, sd in zip(crs, side, strict=True) if sd == 1])
    return n


def _choose_roots(w: _Work, rmap: np.ndarray, tip: np.ndarray | None,
                  entry: np.ndarray | None = None) -> dict[int, int]:
    """Root node per connected component (key: smallest node id of the component).

    The end point nearest the catheter tip (within a few vessel widths) is the
    root of its component, or, where the skeleton runs through the ostium, the
    node :func:`_root_at_tip` found or put there (``w.root_hint``). In a vessel the
    catheter has cannulated, ``entry`` (distance map to the catheter's pixels)
    picks the end the catheter passes through instead. Elsewhere the widest
    end point (the ostium is the widest end of a coronary tree, and of the
    coronary sinus).
    """
    g = w.to_nx()
    roots: dict[int, int] = {}
    for comp in nx.connected_components(g):
        if w.root_hint is not None and w.root_hint in comp:
            roots[min(comp)] = w.root_hint
            continue
        ends = [n for n in comp if g.degree(n) == 1] or list(comp)
        pts = np.array([w.nodes[n] for n in ends])
        r = _radius_at(rmap, pts)
        if tip is not None:
            d = np.linalg.norm(pts - tip, axis=1)
            if entry is not None:
                # Of the ends the catheter passes through (within a vessel radius), the one
                # nearest its tip.
                ij = np.round(pts).astype(np.int64)
                on = entry[np.clip(ij[:, 1], 0, entry.shape[0] - 1),
                           np.clip(ij[:, 0], 0, entry.shape[1] - 1)] <= r + TIP_MARGIN_PX
                if on.any():
                    k = int(np.flatnonzero(on)[np.argmin(d[on])])
                    roots[min(comp)] = ends[k]
                    continue
            k = int(np.argmin(d))
            if d[k] <= TIP_REACH_PX:
                roots[min(comp)] = ends[k]
                continue
        roots[min(comp)] = ends[int(np.argmax(r))]
    return roots


def _finish(w: _Work, rmap: np.ndarray, view: CArmView, root_of: dict[int, int], skel: np.ndarray,
            noise_px: float | None) -> CentrelineGraph:
    g0 = w.to_nx()
    comps = sorted(nx.connected_components(g0), key=lambda c: -sum(
        _length(w.edges[k][2]) for _, _, k in g0.subgraph(c).edges(keys=True)))
    # Number landmarks breadth-first from each root (largest component first).
    order: list[int] = []
    parent_dist: dict[int, float] = {}
    main_root = None
    for comp in comps:
        root = root_of.get(min(comp))
        if root is None or root not in comp:
            root = next(iter(comp))
        if main_root is None:
            main_root = root
        for n in nx.bfs_tree(g0, root):
            order.append(n)
        for n, d in nx.single_source_shortest_path_length(g0, root).items():
            parent_dist[n] = d
    new_id = {n: i for i, n in enumerate(order)}
    mm_per_px = float(np.mean(view.mm_per_px))
    deg = dict(g0.degree())
    landmarks = []
    for n in order:
        p = w.nodes[n]
        landmarks.append(Landmark(index=new_id[n], kind="end" if deg[n] <= 1 else "branch",
                                  point_px=np.asarray(p, float),
                                  radius_px=float(_radius_at(rmap, p[None])[0]), degree=int(deg[n])))
    edges = []
    for k, (u, v, pts) in w.edges.items():
        if parent_dist.get(u, 0) > parent_dist.get(v, 0) or (
                parent_dist.get(u, 0) == parent_dist.get(v, 0) and new_id[u] > new_id[v]):
            u, v, pts = v, u, pts[::-1]
        edges.append((new_id[u], new_id[v], pts, w.crossing_of[k]))
    edges.sort(key=lambda e: (e[0], e[1]))
    crossing_members: dict[int, list[int]] = {}
    branches = []
    for i, (u, v, pts, crs) in enumerate(edges):
        pts = np.asarray(pts, float)
        r_px = np.maximum(_radius_at(rmap, pts), 0.5)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        pts, r_px = pts[keep], r_px[keep]
        branches.append(Branch2D(index=i, start=u, end=v, points_px=pts, radius_px=r_px,
                                 radius_mm=r_px * mm_per_px, crossings=sorted(set(crs)),
                                 noise_request=noise_px))
        for c in set(crs):
            crossing_members.setdefault(c, []).append(i)
    crossings = []
    remap = {}
    for c, (p, ang) in enumerate(w.crossings):
        members = crossing_members.get(c, [])
        if len(members) == 2:
            remap[c] = len(crossings)
            crossings.append(Crossing(point_px=np.asarray(p, float), branches=(members[0], members[1]),
                                      angle_deg=float(ang)))
    for b in branches:
        b.crossings = [remap[c] for c in b.crossings if c in remap]
    g = nx.MultiGraph()
    for lm in landmarks:
        g.add_node(lm.index, kind=lm.kind, point=lm.point_px)
    for b in branches:
        g.add_edge(b.start, b.end, key=b.index, branch=b.index, length=b.length_px)
    return CentrelineGraph(view=view, landmarks=landmarks, branches=branches, crossings=crossings,
                           root=None if main_root is None else new_id[main_root], graph=g,
                           skeleton=skel, radius_map_px=rmap)
