"""The 3D vessel tree: branches with centreline B-splines and radius laws, topology, files.

A :class:`VesselTree` is what the reconstruction produces and what the solid
is built from (paper §2.4 step 4). It reads and writes ``centrelines.json``
(docs/solids.md), exports centrelines with radius as VTP (vmtk's point-data
names), and prepares the branches for the pipes:

1. **rebuild** (:meth:`VesselTree.rebuilt`): each branch becomes a clamped
   cubic B-spline with the fewest uniform knots that keep every input point
   within ``tol_mm`` (default 0.05 mm), end points held (points noisier than
   that: within what the data allow, :func:`fit_spine`); its radius becomes a
   smooth law along the same parameter (P-spline, 4 mm knots).
2. **merge** (:meth:`VesselTree.merged`): where a branch ends at the start of a
   child that continues it (end tangents within ``max_angle_deg``), the two
   become one vessel: a single C2 curve whose bend at the join is a blend of
   curvature radius three vessel radii. The other children of the join become
   side branches of the merged vessel.
3. **pipes** (:meth:`VesselTree.solid`): the radius is clamped where the
   centreline bends tighter than ``radius / 0.8`` (so no pipe folds onto itself),
   each child starts on its parent's centreline (inside the parent), and the
   NURBS pipes are fused into one solid in ``vesselcad.kernel``.

Vessels of one tree that touch away from their junction (a reconstruction
error, or random phantom twigs) are reported by :meth:`VesselTree.solid`;
:meth:`VesselTree.separated` moves them apart (the CFD mesher does so by
default).

Every branch keeps the reasons for what was changed in ``warnings``.
"""

from __future__ import annotations

import json
import os
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import interpolate, ndimage

from .errors import ArgumentError, GeometryError, InputFileError
from .splines import arc_length, fit_pspline

__all__ = ["TreeBranch", "VesselTree", "fit_spine", "fit_radius_law", "curvature"]

#: Default rebuild tolerance (mm).
TOL_MM = 0.05
#: Largest angle (deg) between a branch's end tangent and a child's start tangent
#: for the two to be merged into one vessel.
MAX_MERGE_ANGLE_DEG = 30.0
#: Pipes never fold: radius <= CURVATURE_FACTOR / curvature.
CURVATURE_FACTOR = 0.8
#: A child's start radius is kept below this share of its parent's radius, so the
#: child's start circle lies strictly inside the parent (no tangent faces).
CHILD_RADIUS_SHARE = 0.9
#: Where OCCT's union of a child with the tree fails or does not finish, the child is
#: tried once more with its start narrowed to this share of its parent's radius: a child
#: nearly as wide as its parent leaving it at a shallow angle runs its wall within a
#: tenth of a millimetre of the parent's for millimetres, which can keep OCCT's surface
#: intersection busy for minutes (docs/solids.md, "Junctions OCCT cannot finish").
RETRY_CHILD_RADIUS_SHARE = 0.7
#: A child that starts at its parent's end starts on the parent's axis one parent radius
#: back inside it, along it: its first circle and the parent's wall run side by side,
#: a tenth of a radius apart where the start is clamped to CHILD_RADIUS_SHARE, and OCCT's
#: union of the two can then run for minutes. Its radius law is therefore necked down to
#: this share of the parent's radius at its very start, back to the law within
#: END_NECK_RADII parent radii (all of it inside the parent, so the solid's surface does
#: not change; docs/solids.md, "Junctions OCCT cannot finish"). None: no neck.
END_NECK_SHARE: float | None = 0.5
END_NECK_RADII = 0.5
#: A child that starts at its parent's end and would swallow it (its circle, as clamped at its
#: start, around the parent's somewhere short of the parent's end: a junction's blob widens
#: both) is kept within this share of the parent's radius while its axis runs along the
#: parent's inside it (within half the parent's radius of its axis); it then leaves through the
#: parent's domed end and takes its own radius again within about 2 mm. Else the two walls
#: cross at a grazing angle all round, and OCCT's fuse can leave them touching along a line
#: (end-to-end cs 2111 with true labels: a valid B-rep 3.6 % larger than its tubes' union).
#: None: not kept inside.
END_INSIDE_SHARE: float | None = 0.9
#: Siblings that start at their parent's end get lead-ins from staggered depths inside it: the
#: first one parent radius back, each next END_STAGGER_RADII radius less (at least 0.4 radius: the
#: neck, END_NECK_RADII long, stays inside the parent).
#: Lead-ins from one point along one direction have walls that coincide over their first
#: millimetre, and OCCT's general fuse can then lose vessels (model lca 2021: four branches lost,
#: 32 s; staggered, one general fuse of 6 s). None: no stagger.
END_STAGGER_RADII: float | None = 0.3
#: A child shorter than this many times its radius and its parent's together at its start
#: is a stub: in the solid it starts the child that continues it, or, childless, is left
#: out (:meth:`VesselTree.pipe_specs`).
STUB_RADII = 1.5
#: A child starting farther than this many parent radii from the parent's
#: centreline is not pulled onto it.
MAX_START_GAP_RADII = 2.0
#: A root's pipe starts this many of its radii upstream of the first wall of a child that
#: leaves next to its inlet (else that wall would cut the inlet disc); a root that would need
#: more than INLET_EXTENSION_MAX_RADII of its radius of extension is left as it is (a child
#: heading back past the ostium). None: never extended.
INLET_CLEARANCE_RADII: float | None = 0.25
INLET_EXTENSION_MAX_RADII = 3.0
#: A child that leaves the inlet more than this (degrees from the root's start direction) runs
#: back past the ostium: no extension would clear the inlet, and the root is left as it is.
INLET_MAX_CHILD_ANGLE_DEG = 150.0
#: Smallest radius a pipe gets (mm).
MIN_RADIUS_MM = 0.05
#: Where no rebuild keeps a branch's points within the tolerance (they are noisier than it),
#: the tolerance becomes this many times the densest fit's largest deviation (:func:`fit_spine`).
#: None: the densest fit, as the rebuild did before 2026-12-07 (tests of frozen trees use it).
NOISY_TOL_FACTOR: float | None = 1.5
#: A fitted centreline longer than the polyline of its points by more than this share swings
#: round between them (:func:`fit_spine`: such a fit counts as missing the tolerance). None: not
#: checked (as before 2026-12-07).
SWING_SHARE: float | None = 0.02
#: Wall-to-wall distance :meth:`VesselTree.separated` leaves between vessels that touched (mm).
CLEARANCE_MM = 0.2


# ------------------------------------------------------------------- fitting
def fit_spine(points: Any, tol_mm: float = TOL_MM, max_knot_step_mm: float = 20.0
              ) -> tuple[interpolate.BSpline, float]:
    """Cubic B-spline through 3D points with the fewest uniform knots that meet ``tol_mm``.

    Where no fit meets it (the points are noisier than the tolerance), the
    tolerance becomes :data:`NOISY_TOL_FACTOR` times the densest fit's largest
    deviation: the densest fit would follow the noise. A fit longer than the
    polyline of the points by more than :data:`SWING_SHARE` swings round between
    samples (a knot span with one sample beside spans of many) and does not
    count as meeting any tolerance.

    Parameters
    ----------
    points : (n, 3) array_like
        Ordered centreline samples (mm).
    tol_mm : float
        Largest allowed distance between an input point and the curve at its parameter.
    max_knot_step_mm : float
        Knot spacing never exceeds this (keeps long straight runs well conditioned).

    Returns
    -------
    spline : scipy.interpolate.BSpline
        Clamped cubic, vector valued; its parameter is the chord length of the
        input samples (mm), equal to the arc length to within the sampling's
        sagitta. The end points are held.
    max_error_mm : float
        Largest deviation of an input point.
    """
    p = _as_points(points, "points")
    if not tol_mm > 0:
        raise ArgumentError(f"tol_mm: expected a positive number, got {tol_mm!r}")
    p = _dedupe(p)
    if len(p) < 2:
        raise ArgumentError("points: a branch needs at least two distinct points")
    s = arc_length(p)
    if len(p) < 4:  # too few to fit a cubic: densify the polyline (exact for a segment)
        t = np.linspace(0.0, s[-1], 4)
        p = np.stack([np.interp(t, s, p[:, k]) for k in range(3)], axis=1)
        s = t
    length = float(s[-1])
    # Hold the ends: weight them like many samples.
    ends = np.r_[[0] * 20, [len(p) - 1] * 20]
    x = np.r_[s, s[ends]]
    y = np.vstack([p, p[ends]])

    def fit(step: float) -> tuple[interpolate.BSpline, float, bool]:
        # A whisper of curvature penalty keeps knot spans with few samples from oscillating.
        spl = fit_pspline(x, y, step, 1e-6, domain=(0.0, length))
        err = float(np.max(np.linalg.norm(spl(s) - p, axis=1)))
        # ... not always: a span with one sample, beside spans of many, can still swing round
        # between samples (a loop the pipe's radius clamp then pinches to a thread)
        swings = False
        if SWING_SHARE is not None:
            q = spl(np.linspace(0.0, length, max(int(length / 0.05), 50) + 1))
            swings = float(np.sum(np.linalg.norm(np.diff(q, axis=0), axis=1))) > (1.0 + SWING_SHARE) * length
        return spl, err, swings

    def meets(fitted: tuple[interpolate.BSpline, float, bool], limit: float) -> bool:
        return fitted[1] <= limit and not fitted[2]

    # Number of knot spans: at most one per 0.5 mm and one per two samples.
    lo_n, hi_n = 1, max(min(int(np.ceil(length / 0.5)), (len(p) - 1) // 2), 1)
    hi_n = max(hi_n, int(np.ceil(length / max_knot_step_mm)))
    densest = fit(length / hi_n)
    limit = tol_mm
    if not meets(densest, tol_mm):
        if NOISY_TOL_FACTOR is None:
            return densest[0], densest[1]
        # The points are noisier than the tolerance: the densest fit would follow their noise
        # (and swing between samples where they are sparse). The tolerance becomes what the
        # data allow, and the fewest knots that keep it are taken.
        limit = max(tol_mm, NOISY_TOL_FACTOR * densest[1])
    best = densest if meets(densest, limit) else None
    lo_n = max(lo_n, int(np.ceil(length / max_knot_step_mm)))
    while lo_n < hi_n:
        mid = (lo_n + hi_n) // 2
        cand = fit(length / mid)
        if meets(cand, limit):
            hi_n, best = mid, cand
        else:
            lo_n = mid + 1
    if best is None:  # nothing found (every fit swings): the densest, as it is
        best = densest
    return best[0], best[1]


def fit_radius_law(param: Any, radius: Any, length: float, knot_step_mm: float = 4.0,
                   smoothing: float = 0.1) -> interpolate.BSpline:
    """Smooth cubic radius law r(s) over [0, length] (P-spline), never below ``MIN_RADIUS_MM``."""
    s = np.asarray(param, dtype=float)
    r = np.asarray(radius, dtype=float)
    if r.shape != s.shape or r.size == 0 or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ArgumentError("radius: expected positive finite values, one per point")
    spl = fit_pspline(s, r[:, None], min(knot_step_mm, max(length, 1e-6)), smoothing, domain=(0.0, length))
    c = np.maximum(np.asarray(spl.c), MIN_RADIUS_MM)
    return interpolate.BSpline(spl.t, c, spl.k)


def curvature(spline: interpolate.BSpline, s: Any) -> np.ndarray:
    """Curvature (1/mm) of a 3D spline at parameters ``s``."""
    d1 = spline.derivative(1)(s)
    d2 = spline.derivative(2)(s)
    num = np.linalg.norm(np.cross(d1, d2), axis=-1)
    return num / np.maximum(np.linalg.norm(d1, axis=-1) ** 3, 1e-30)


def _as_points(points: Any, name: str) -> np.ndarray:
    try:
        p = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise ArgumentError(f"{name}: expected an (n, 3) array of numbers") from None
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ArgumentError(f"{name}: expected an (n, 3) array with n >= 2, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ArgumentError(f"{name}: contains NaN or infinite values")
    return p


def _dedupe(p: np.ndarray) -> np.ndarray:
    keep = np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9]
    return p[keep]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-30)


# ------------------------------------------------------------------- branches
@dataclass(eq=False)
class TreeBranch:
    """One vessel branch, ordered from its proximal (parent) end.

    Attributes
    ----------
    id : int
    parent : int or None
    points : (n, 3) array
        Centreline samples (mm, LPS).
    radius : (n,) array
        Radius at each sample (mm).
    name : str
    parent_s_mm : float or None
        Where on the parent's centreline (arc length, mm) this branch starts.
    landmarks : (int or None, int or None)
        Source landmarks (e.g. matched 2D landmark indices) of the start and end.
    segments : tuple of int
        Ids of the input branches merged into this one (itself when not merged).
    spline : scipy.interpolate.BSpline or None
        The rebuilt centreline (parameter = arc length, mm) once fitted.
    radius_law : scipy.interpolate.BSpline or None
        Radius along the same parameter.
    fit_error_mm : float
        Largest distance of an input point from the rebuilt centreline.
    warnings : list of str
    """

    id: int
    parent: int | None
    points: np.ndarray
    radius: np.ndarray
    name: str = ""
    parent_s_mm: float | None = None
    landmarks: tuple[int | None, int | None] = (None, None)
    segments: tuple[int, ...] = ()
    spline: interpolate.BSpline | None = None
    radius_law: interpolate.BSpline | None = None
    fit_error_mm: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def is_fitted(self) -> bool:
        return self.spline is not None

    @property
    def length_mm(self) -> float:
        """Centreline length (mm)."""
        if self.spline is None:
            return float(arc_length(self.points)[-1])
        s = np.linspace(*self.domain, 2001)
        return float(arc_length(self.spline(s))[-1])

    @property
    def domain(self) -> tuple[float, float]:
        """Parameter range of the rebuilt centreline."""
        if self.spline is None:
            return 0.0, float(arc_length(self.points)[-1])
        k = self.spline.k
        return float(self.spline.t[k]), float(self.spline.t[-k - 1])

    def sample(self, step_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """Points and radii every ``step_mm`` along the branch (ends included)."""
        if not step_mm > 0:
            raise ArgumentError(f"step_mm: expected a positive number, got {step_mm!r}")
        if self.spline is None:
            s = arc_length(self.points)
            t = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / step_mm)) + 1, 2))
            pts = np.stack([np.interp(t, s, self.points[:, k]) for k in range(3)], axis=1)
            return pts, np.interp(t, s, self.radius)
        a, b = self.domain
        t = np.linspace(a, b, max(int(np.ceil((b - a) / step_mm)) + 1, 2))
        return self.spline(t), self.radius_at(t)

    def radius_at(self, s: Any) -> np.ndarray:
        """Radius (mm) at centreline parameters ``s``."""
        s = np.asarray(s, dtype=float)
        if self.radius_law is None:
            return np.interp(s, arc_length(self.points), self.radius)
        return np.asarray(self.radius_law(s)).reshape(s.shape)

    @property
    def curve(self) -> Any:
        """The rebuilt centreline as an OCCT ``Geom_BSplineCurve``."""
        from .kernel.nurbs import bspline_curve

        if self.spline is None:
            raise ArgumentError(f"branch {self.id}: not rebuilt yet (call VesselTree.rebuilt())")
        return bspline_curve(self.spline)

    def tangent(self, end: str) -> np.ndarray:
        """Unit tangent (along the branch) at ``end`` in {'start', 'end'}."""
        if self.spline is not None:
            a, b = self.domain
            return _unit(self.spline.derivative()(a if end == "start" else b))
        pts, _ = self.sample(0.5)
        k = min(4, len(pts) - 1)
        return _unit(pts[k] - pts[0]) if end == "start" else _unit(pts[-1] - pts[-1 - k])

    def __repr__(self) -> str:
        return (f"TreeBranch(id={self.id}, name={self.name!r}, parent={self.parent}, "
                f"length={self.length_mm:.1f} mm, points={len(self.points)})")


# ------------------------------------------------------------------- the tree
class VesselTree:
    """A 3D vessel tree: branches with parents, centrelines and radii in LPS mm.

    Parameters
    ----------
    branches : list of TreeBranch
        Ids unique; every parent id present; no cycles.

    Examples
    --------
    >>> tree = VesselTree.from_json("centrelines.json")   # doctest: +SKIP
    >>> solid = tree.solid()                               # doctest: +SKIP
    >>> solid.export_step("tree.step")                     # doctest: +SKIP
    """

    def __init__(self, branches: list[TreeBranch]):
        self.branches: list[TreeBranch] = list(branches)
        self._index = {b.id: b for b in self.branches}
        if len(self._index) != len(self.branches):
            raise ArgumentError("branches: branch ids must be unique")
        for b in self.branches:
            if b.parent is not None and b.parent not in self._index:
                raise ArgumentError(f"branch {b.id}: parent {b.parent} is not a branch of the tree")
        self.order()  # raises on cycles

    # -------------------------------------------------------------- topology
    def __len__(self) -> int:
        return len(self.branches)

    def __iter__(self) -> Iterator[TreeBranch]:
        return iter(self.branches)

    def __getitem__(self, branch_id: int) -> TreeBranch:
        try:
            return self._index[branch_id]
        except KeyError:
            raise ArgumentError(f"branch_id: no branch {branch_id!r} in the tree") from None

    @property
    def roots(self) -> list[int]:
        """Ids of branches without a parent."""
        return [b.id for b in self.branches if b.parent is None]

    def children(self, branch_id: int) -> list[int]:
        """Ids of the branches whose parent is ``branch_id``."""
        return [b.id for b in self.branches if b.parent == branch_id]

    def order(self) -> list[int]:
        """Branch ids parents-first (breadth first from each root)."""
        kids: dict[int | None, list[int]] = {}
        for b in self.branches:
            kids.setdefault(b.parent, []).append(b.id)
        out: list[int] = []
        queue = deque(kids.get(None, []))
        while queue:
            i = queue.popleft()
            out.append(i)
            queue.extend(kids.get(i, []))
        if len(out) != len(self.branches):
            raise ArgumentError("branches: the parent links form a cycle")
        return out

    def to_networkx(self) -> Any:
        """A ``networkx.DiGraph`` parent -> child with the branch objects as node data."""
        import networkx as nx

        g = nx.DiGraph()
        for b in self.branches:
            g.add_node(b.id, branch=b, name=b.name)
        for b in self.branches:
            if b.parent is not None:
                g.add_edge(b.parent, b.id, parent_s_mm=b.parent_s_mm)
        return g

    @property
    def total_length_mm(self) -> float:
        return float(sum(b.length_mm for b in self.branches))

    def __repr__(self) -> str:
        return f"VesselTree(branches={len(self)}, roots={self.roots}, length={self.total_length_mm:.0f} mm)"

    # -------------------------------------------------------------- files
    @classmethod
    def from_dict(cls, data: Any, source: str = "centrelines") -> VesselTree:
        """Tree from a ``centrelines.json`` object (see docs/solids.md)."""
        if not isinstance(data, dict) or not isinstance(data.get("branches"), list):
            raise InputFileError(f"{source}: expected an object with a 'branches' list")
        units = data.get("units", "mm")
        if units != "mm":
            raise InputFileError(f"{source}: units must be 'mm', got {units!r}")
        frame = data.get("frame", "LPS")
        if frame != "LPS":
            raise InputFileError(f"{source}: frame must be 'LPS', got {frame!r}")
        branches = []
        for k, b in enumerate(data["branches"]):
            where = f"{source}: branches[{k}]"
            if not isinstance(b, dict) or "points" not in b or "radius" not in b or "id" not in b:
                raise InputFileError(f"{where}: needs 'id', 'points' and 'radius'")
            try:
                pts = _as_points(b["points"], "points")
            except ArgumentError as exc:
                raise InputFileError(f"{where} (id {b.get('id')}): {exc}") from None
            rad = np.asarray(b["radius"], dtype=float)
            if rad.shape != (len(pts),) or not np.all(np.isfinite(rad)) or np.any(rad <= 0):
                raise InputFileError(f"{where} (id {b['id']}): 'radius' must hold {len(pts)} "
                                     "positive numbers")
            lm = b.get("landmarks") or (None, None)
            branches.append(TreeBranch(
                id=int(b["id"]), parent=None if b.get("parent") is None else int(b["parent"]),
                points=pts, radius=rad, name=str(b.get("name") or f"branch_{b['id']}"),
                parent_s_mm=None if b.get("parent_s_mm") is None else float(b["parent_s_mm"]),
                landmarks=(lm[0], lm[1]), segments=(int(b["id"]),)))
        try:
            return cls(branches)
        except ArgumentError as exc:
            raise InputFileError(f"{source}: {exc}") from None

    @classmethod
    def from_json(cls, source: str | os.PathLike | dict) -> VesselTree:
        """Read ``centrelines.json`` (a path, or the already parsed object)."""
        if isinstance(source, dict):
            return cls.from_dict(source)
        path = Path(source)
        if not path.is_file():
            raise InputFileError(f"{path}: no such file")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputFileError(f"{path}: not a readable JSON file ({exc})") from None
        return cls.from_dict(data, str(path))

    @classmethod
    def from_truth(cls, source: Any, frame: int = 0, run: str = "a") -> VesselTree:
        """Ground-truth tree of a phantom case.

        Parameters
        ----------
        source : PhantomCase, dict or path
            A case from ``vesselcad.phantom.generate_case``, a ``truth.json``
            object or its path, or a single ``centrelines.json`` tree object.
        frame : int
            Frame whose tree to take.
        run : {'a', 'b'}
        """
        if run not in ("a", "b"):
            raise ArgumentError(f"run: expected 'a' or 'b', got {run!r}")
        name = "truth"
        if isinstance(source, (str, os.PathLike)):
            name = str(source)
            try:
                source = json.loads(Path(source).read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise InputFileError(f"{name}: not a readable truth.json ({exc})") from None
        if hasattr(source, "run_a") and hasattr(source, "run_b"):
            trees = getattr(source, f"run_{run}").trees
        elif isinstance(source, dict) and f"trees_{run}" in source:
            trees = source[f"trees_{run}"]
        elif isinstance(source, dict) and "branches" in source:
            return cls.from_dict(source, name)
        else:
            raise ArgumentError("source: expected a PhantomCase, a truth.json object/path or a tree object")
        if not -len(trees) <= int(frame) < len(trees):
            raise ArgumentError(f"frame: expected 0..{len(trees) - 1}, got {frame}")
        return cls.from_dict(trees[int(frame)], f"{name}: trees_{run}[{frame}]")

    def to_dict(self, step_mm: float = 0.5) -> dict[str, Any]:
        """The ``centrelines.json`` object; rebuilt branches are sampled every ``step_mm``."""
        if not (isinstance(step_mm, (int, float)) and step_mm > 0):
            raise ArgumentError(f"step_mm: expected a positive number, got {step_mm!r}")
        out = []
        for b in self.branches:
            if b.spline is not None:
                pts, rad = b.sample(step_mm)
            else:
                pts, rad = b.points, b.radius
            item: dict[str, Any] = {"id": b.id, "parent": b.parent, "name": b.name,
                                    "parent_s_mm": None if b.parent_s_mm is None else round(b.parent_s_mm, 4),
                                    "points": np.round(pts, 5).tolist(), "radius": np.round(rad, 5).tolist()}
            if any(x is not None for x in b.landmarks):
                item["landmarks"] = list(b.landmarks)
            out.append(item)
        return {"units": "mm", "frame": "LPS", "branches": out}

    def to_json(self, path: str | os.PathLike, step_mm: float = 0.5) -> None:
        """Write ``centrelines.json`` atomically."""
        from .io.atomic import atomic_write_text

        atomic_write_text(path, json.dumps(self.to_dict(step_mm)))

    def to_vtp(self, path: str | os.PathLike, step_mm: float = 0.5) -> None:
        """Write the centrelines as VTK PolyData (.vtp), one polyline per branch.

        Point data: ``MaximumInscribedSphereRadius`` (radius, mm; vmtk's name),
        ``Abscissas`` (arc length from the branch start, mm). Cell data:
        ``BranchId``, ``ParentId`` (-1 for a root), ``CenterlineIds`` (index).
        """
        from .io.vtp import write_polylines

        lines, radius, absc = [], [], []
        for b in self.branches:
            pts, rad = b.sample(step_mm)
            lines.append(pts)
            radius.append(rad)
            absc.append(arc_length(pts))
        write_polylines(path, lines,
                        point_data={"MaximumInscribedSphereRadius": radius, "Abscissas": absc},
                        cell_data={"BranchId": [b.id for b in self.branches],
                                   "ParentId": [-1 if b.parent is None else b.parent for b in self.branches],
                                   "CenterlineIds": list(range(len(self.branches)))})

    # -------------------------------------------------------------- rebuild, merge
    def rebuilt(self, tol_mm: float = TOL_MM) -> VesselTree:
        """A copy whose branches are rebuilt as cubic B-splines within ``tol_mm`` (see module doc)."""
        out = []
        for b in self.branches:
            spl, err = fit_spine(b.points, tol_mm)
            s = _project_params(spl, b.points)
            a, e = float(spl.t[3]), float(spl.t[-4])
            law = fit_radius_law(s, b.radius, e - a)
            nb = replace(b, spline=spl, radius_law=law, fit_error_mm=err, warnings=list(b.warnings),
                         segments=b.segments or (b.id,))
            if err > tol_mm:
                nb.warnings.append(f"centreline kept {err:.3f} mm from its points (tolerance {tol_mm} mm): "
                                   "the points are noisier than the tolerance")
            out.append(nb)
        tree = VesselTree(out)
        tree._locate_children()
        return tree

    def merged(self, max_angle_deg: float = MAX_MERGE_ANGLE_DEG, tol_mm: float = TOL_MM) -> VesselTree:
        """A copy in which branches that continue each other are one vessel (see module doc).

        A branch ``p`` and a child ``c`` are merged when ``c`` starts within one
        radius (at least 1 mm) of ``p``'s end and their tangents there differ by
        at most ``max_angle_deg``; among several such children the straightest
        (then the widest) continues ``p``. The merged vessel keeps ``p``'s id and
        ``segments`` lists both ids; ``c``'s other children are re-attached.
        """
        tree = self if all(b.is_fitted for b in self.branches) else self.rebuilt(tol_mm)
        branches = {b.id: replace(b, warnings=list(b.warnings)) for b in tree.branches}
        changed = True
        while changed:
            changed = False
            for pid in VesselTree(list(branches.values())).order():
                p = branches[pid]
                cand = []
                a, e = p.domain
                end_r = float(p.radius_at(e))
                for c in branches.values():
                    if c.parent != pid or c.parent_s_mm is None:
                        continue
                    if c.parent_s_mm < e - max(end_r, 1.0):
                        continue
                    ang = np.degrees(np.arccos(np.clip(p.tangent("end") @ c.tangent("start"), -1.0, 1.0)))
                    if ang <= max_angle_deg:
                        cand.append((ang, -float(c.radius_at(c.domain[0])), c.id))
                if not cand:
                    continue
                cand.sort()
                cid = cand[0][2]
                merged = _merge_pair(p, branches[cid], tol_mm)
                branches[pid] = merged
                for other in branches.values():
                    if other.parent == cid:
                        other.parent = pid
                        other.parent_s_mm = None
                del branches[cid]
                changed = True
                break
        out = VesselTree(list(branches.values()))
        out._locate_children()
        return out

    def _locate_children(self) -> None:
        """Set ``parent_s_mm`` of every child by projecting its start onto the parent."""
        for b in self.branches:
            if b.parent is None:
                continue
            par = self._index[b.parent]
            if par.spline is None:
                continue
            s = _project_params(par.spline, b.points[:1])[0] if b.spline is None else \
                _project_params(par.spline, b.spline(b.domain[0])[None])[0]
            b.parent_s_mm = float(s)

    def separated(self, clearance_mm: float = CLEARANCE_MM, tol_mm: float = TOL_MM, merge: bool = True,
                  max_merge_angle_deg: float = MAX_MERGE_ANGLE_DEG, max_rounds: int = 200) -> VesselTree:
        """A copy in which vessels that touch away from a junction are moved apart.

        Two vessels of one tree never share a wall away from their junction,
        but a reconstruction (or a phantom) can bring them closer than their
        radii: the solid then joins them (a handle with a sharp crease, a
        flow path that is not there, and boundary-layer prisms that fold).
        Each such contact (:meth:`solid` warns about them) is cleared by
        moving the two centrelines apart along their common normal until their
        walls are at least ``clearance_mm`` apart; the thinner vessel moves
        more (shares inverse to the radii). The shift is spread smoothly along
        each vessel (Gaussian, sigma two radii, at least 1 mm, and at least
        sqrt(5 r h) for a shift of h mm so the vessel bends no tighter than
        about five radii), a child follows its parent at its start and
        reaches its own shift over a few radii, and the rounds repeat until
        no contact is left. Siblings (or a vessel and its grandparent) that
        leave one point fused are opened at least like a 23-degree split; a
        child and its own parent are never pushed apart. Radii are not
        changed. Every moved branch gets a warning saying by how much and
        from which vessel.

        Parameters
        ----------
        clearance_mm : float
            Smallest wall-to-wall distance left between vessels (mm).
        tol_mm, merge, max_merge_angle_deg
            As for :meth:`pipe_specs` (the tree is rebuilt and merged first).
        max_rounds : int
            Upper bound on the push rounds.

        Returns
        -------
        VesselTree
            Rebuilt (and merged) like the input of :meth:`solid`; unchanged
            branches keep their centrelines exactly.
        """
        if not (isinstance(clearance_mm, int | float) and np.isfinite(clearance_mm) and clearance_mm >= 0):
            raise ArgumentError(f"clearance_mm: expected a number >= 0, got {clearance_mm!r}")
        if not (isinstance(max_rounds, int) and max_rounds > 0):
            raise ArgumentError(f"max_rounds: expected a positive integer, got {max_rounds!r}")
        tree = self.rebuilt(tol_mm) if not all(b.is_fitted for b in self.branches) else self
        if merge:
            tree = tree.merged(max_merge_angle_deg, tol_mm)
        order = tree.order()
        if len(order) < 2:
            return tree
        step = 0.25
        params, pts, rad, tan = [], [], [], []
        for bid in order:
            b = tree[bid]
            a, e = b.domain
            s = np.linspace(a, e, max(int(np.ceil((e - a) / step)), 1) + 1)
            params.append(s)
            pts.append(b.spline(s))
            rad.append(b.radius_at(s))
            d1 = b.spline.derivative()(s)
            tan.append(d1 / np.linalg.norm(d1, axis=1, keepdims=True))
        sizes = np.array([len(s) for s in params])
        first = np.r_[0, np.cumsum(sizes)[:-1]]
        spans = [slice(a, a + m) for a, m in zip(first, sizes, strict=True)]
        p0 = np.vstack(pts)
        r, t = np.concatenate(rad), np.vstack(tan)
        o = np.repeat(np.arange(len(order)), sizes)
        n = np.concatenate([np.arange(k) for k in sizes])
        slot = {bid: k for k, bid in enumerate(order)}
        attach: dict[int, int] = {}
        ramp: dict[int, np.ndarray] = {}
        for k, bid in enumerate(order):
            b = tree[bid]
            if b.parent is None:
                continue
            q = slot[b.parent]
            ps = params[q]
            attach[k] = first[q] + int(np.argmin(np.abs(ps - (b.parent_s_mm or ps[0]))))
            reach = 2.0 * (float(r[attach[k]]) + float(rad[k][0]))
            x = np.clip((params[k] - params[k][0]) / reach, 0.0, 1.0)
            ramp[k] = x * x * (3 - 2 * x)
        linked = {(min(k, q), max(k, q)) for k, bid in enumerate(order)
                  if (par := tree[bid].parent) is not None for q in [slot[par]]}

        def push_apart(widths: np.ndarray) -> tuple[np.ndarray, dict[int, set[int]]]:
            """Rounds of pushes from the input centrelines, spread with Gaussians of these sigmas (mm)."""
            p = p0.copy()
            partners: dict[int, set[int]] = {k: set() for k in range(len(order))}
            for _round in range(max_rounds):
                i, j, gap = _contact_pairs(p, r, o, n, clearance_mm, linked, step, diverge=True)
                if not len(i):
                    break
                for a_, b_ in set(zip(o[i].tolist(), o[j].tolist(), strict=True)):
                    partners[a_].add(b_)
                    partners[b_].add(a_)
                v = p[i] - p[j]
                normal = np.cross(t[i], t[j])
                nn = np.linalg.norm(normal, axis=1)
                # one side per pair of vessels (axes through each other leave v . normal ~ 0)
                along = np.einsum("ij,ij->i", v, normal)
                key = o[i] * len(order) + o[j]
                keys, inv = np.unique(key, return_inverse=True)
                side = np.sign(np.bincount(inv, along, len(keys)))[inv]
                side[side == 0] = 1.0
                across = v - np.einsum("ij,ij->i", v, t[i])[:, None] * t[i]
                u = np.where((nn > 0.25)[:, None], normal * (side / np.maximum(nn, 1e-12))[:, None], across)
                un = np.linalg.norm(u, axis=1)
                weak = un < 1e-9
                if np.any(weak):  # axes through each other and parallel: any direction across
                    helper = np.where((np.abs(t[i][weak, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0],
                                      [0.0, 1.0, 0.0])
                    u[weak] = np.cross(t[i][weak], helper)
                    un[weak] = np.linalg.norm(u[weak], axis=1)
                u /= un[:, None]
                need = clearance_mm - gap + 0.02
                share_i = r[j] / (r[i] + r[j])
                push = np.zeros_like(p)
                count = np.zeros(len(p))
                np.add.at(push, i, (share_i * need)[:, None] * u)
                np.add.at(push, j, -((1.0 - share_i) * need)[:, None] * u)
                np.add.at(count, i, 1.0)
                np.add.at(count, j, 1.0)
                push /= np.maximum(count, 1.0)[:, None]
                moved = np.zeros_like(p)
                for k, sl in enumerate(spans):
                    d = push[sl]
                    peak = float(np.linalg.norm(d, axis=1).max())
                    if peak > 0:
                        sigma = widths[k] / step
                        sm = ndimage.gaussian_filter1d(d, sigma, axis=0, mode="nearest")
                        d = sm * min(peak / max(float(np.linalg.norm(sm, axis=1).max()), 1e-12), 5.0)
                        big = np.linalg.norm(d, axis=1)
                        d *= np.minimum(1.0, 0.5 / np.maximum(big, 1e-12))[:, None]
                    if k in attach:  # follow the parent at the start, own shift after a few radii
                        w = ramp[k][:, None]
                        d = d * w + moved[attach[k]] * (1.0 - w)
                    moved[sl] = d
                p += moved
            return p, partners

        # A bump of height h spread with sigma bends the vessel with a radius of about sigma^2 / h:
        # a first pass measures each vessel's shift, the second spreads it so the bend stays
        # gentler than five radii (the solid would otherwise pinch the radius there).
        mean_r = np.array([float(np.mean(x)) for x in rad])
        widths = np.maximum(2.0 * mean_r, 1.0)
        p, partners = push_apart(widths)
        peak_shift = np.array([float(np.linalg.norm(p[sl] - p0[sl], axis=1).max()) for sl in spans])
        wider = np.maximum(widths, np.sqrt(5.0 * mean_r * peak_shift))
        if np.any(wider > widths + 1e-9):
            p, partners = push_apart(wider)
        i, j, _gap = _contact_pairs(p, r, o, n, clearance_mm, linked, step, diverge=True)
        left = np.unique(o[np.r_[i, j]])
        out = []
        for k, (bid, sl) in enumerate(zip(order, spans, strict=True)):
            b = tree[bid]
            shift = np.linalg.norm(p[sl] - p0[sl], axis=1)
            if shift.max() < 1e-3:  # (a child following a parent that barely moved)
                out.append(replace(b, warnings=list(b.warnings)))
                continue
            names = ", ".join(f"{tree[order[q]].id} ({tree[order[q]].name})" for q in sorted(partners[k]))
            why = (f"moved up to {shift.max():.2f} mm to keep {clearance_mm:g} mm from branch"
                   f"{'es' if len(partners[k]) > 1 else ''} {names}" if names else
                   f"moved up to {shift.max():.2f} mm with its parent")
            if names and k in left:
                why += " (not fully cleared)"
            elif names:
                why += ", which it touched away from a junction"
            nb = replace(b, points=p[sl].copy(), radius=r[sl].copy(), spline=None, radius_law=None,
                         parent_s_mm=None, warnings=list(b.warnings) + [why])
            out.append(nb)
        result = []
        for b in out:
            if b.spline is None:  # refit the moved centreline and its radius
                spl, err = fit_spine(b.points, tol_mm)
                law = fit_radius_law(_project_params(spl, b.points), b.radius, float(spl.t[-4] - spl.t[3]))
                b = replace(b, spline=spl, radius_law=law, fit_error_mm=err)
            result.append(b)
        final = VesselTree(result)
        final._locate_children()
        return final

    # -------------------------------------------------------------- solid
    def pipe_specs(self, tol_mm: float = TOL_MM, merge: bool = True,
                   max_merge_angle_deg: float = MAX_MERGE_ANGLE_DEG) -> list[dict[str, Any]]:
        """Spines and radius laws ready for the pipes, parents first.

        Rebuilds (and merges) if needed, clamps the radius against curvature and
        at child starts, and moves a child's start onto its parent's centreline
        when it lies off it. Returns dicts ``{'id', 'name', 'segments', 'parent', 'spine',
        'radius', 'cuts', 'end', 'warnings', 'stubs', 'r_parent', 'neck_mm', 'radius_unnecked',
        'not_inside'}`` and, for a domed end, ``'dome_openings'`` (``kernel.pipes.dome_openings``);
        ``segments`` are the ids of the tree's branches the spec holds (more
        than its own where branches were merged, or a stub became its start);
        ``cuts`` are the spine parameters (mm)
        where a pipe that would overlap itself is cut into pieces (empty for
        almost every branch); ``end`` is ``'dome'`` for a vessel whose children
        start at its end (closed with a hemisphere there), else ``'flat'``;
        a child shorter than ``STUB_RADII`` times its and its parent's radii
        where it starts (a 1 mm piece between two close junctions of a
        reconstruction, which can cost OCCT's fuse minutes inside the parent's
        domed end) becomes the start of the child that continues it, or,
        without children, is left out: ``stubs`` maps such ids of this
        branch's children to the reason; ``r_parent`` is the parent's radius
        (mm) where a child starts (None for a root); ``neck_mm`` is the length
        of a child's start that is necked down inside its parent (a child
        starting at its parent's end, ``END_NECK_SHARE``; else 0): the radius law
        there is not the vessel's, and the surface does not show it;
        ``radius_unnecked`` is the law before that (the same object where
        there is no neck); ``not_inside`` is None, or, for a child kept inside
        its parent's end (``END_INSIDE_SHARE``: it would have swallowed it),
        the law and neck length it would have had otherwise (:meth:`solid`
        tries it where the union with the child kept inside fails).
        """
        tree = self.rebuilt(tol_mm) if not all(b.is_fitted for b in self.branches) else self
        tree = _reattached(tree)
        if merge:
            tree = tree.merged(max_merge_angle_deg, tol_mm)
        tree, stubs = _without_stubs(tree)
        specs = []
        by_id: dict[int, dict[str, Any]] = {}
        swept: dict[int, TreeBranch] = {}  # each branch as its pipe is swept (parents come first)
        at_end_before: dict[int, int] = {}  # children already started at each parent's end
        for bid in tree.order():
            b = tree[bid]
            spine, warns = _smooth_kinks(b.spline, b.radius_law)
            b = replace(b, spline=spine)
            law, warns = b.radius_law, list(b.warnings) + warns
            r_parent, at_end = None, False
            if b.parent is not None:
                # attach to the parent's pipe as swept (its radius clamped, its start moved)
                earlier = at_end_before.get(b.parent, 0)
                back = 1.0 if END_STAGGER_RADII is None else max(1.0 - END_STAGGER_RADII * earlier, 0.4)
                spine, law, w, r_parent, at_end = _start_inside(b, swept[b.parent], back)
                at_end_before[b.parent] = earlier + at_end
                warns += w
                if at_end and by_id[b.parent]["end"] != "dome":
                    # no disc at the parent's end to meet the children's walls at a knife-edge
                    by_id[b.parent]["end"] = "dome"
                    by_id[b.parent]["warnings"].append("its children start at its end: closed there "
                                                       "with a hemisphere, not a disc")
            plain = None  # the law not kept inside the parent's end, where it is
            if at_end and END_INSIDE_SHARE is not None:
                law, w, plain = _keep_inside(spine, law, r_parent, swept[b.parent], END_INSIDE_SHARE)
            else:
                law, w = _clamp_radius(spine, law, r_parent)
            warns += w
            unnecked = law
            law, neck = _necked(law, r_parent, at_end)
            w, cuts = _self_approach(spine, law)
            warns += w
            swept[bid] = replace(b, spline=spine, radius_law=law)
            specs.append({"id": b.id, "name": b.name, "parent": b.parent, "spine": spine,
                          "segments": tuple(int(x) for x in (b.segments or (b.id,))),
                          "radius": law, "cuts": cuts, "end": "flat", "warnings": warns,
                          "stubs": stubs.get(b.id, {}), "r_parent": r_parent, "neck_mm": neck,
                          "radius_unnecked": unnecked,
                          "not_inside": None if plain is None else _necked(plain, r_parent, at_end)})
            by_id[b.id] = specs[-1]
        if INLET_CLEARANCE_RADII is not None:
            for spec in specs:
                if spec["parent"] is None:
                    _extend_inlet(spec, [c for c in specs if c["parent"] == spec["id"]])
        from .kernel.pipes import dome_openings

        for spec in specs:
            if spec["end"] == "dome":  # where the children leave through it (its sphere's pole kept clear)
                sp, law = spec["spine"], spec["radius"]
                b = float(sp.t[-sp.k - 1])
                kids = [(c["spine"], c["radius"]) for c in specs if c["parent"] == spec["id"]]
                spec["dome_openings"] = dome_openings(sp(b), float(np.ravel(law(b))[0]), kids)
        return specs

    def solid(self, tol_mm: float = TOL_MM, merge: bool = True,
              max_merge_angle_deg: float = MAX_MERGE_ANGLE_DEG, station_step_mm: float = 2.0,
              progress: bool = False) -> Any:
        """One fused, valid, watertight OCCT solid of the tree (:class:`vesselcad.kernel.VesselSolid`).

        Parameters
        ----------
        tol_mm : float
            Rebuild tolerance of the centrelines.
        merge : bool
            Merge branches that continue each other first (:meth:`merged`).
        max_merge_angle_deg : float
        station_step_mm : float
            Largest spacing of the exact circular sections of the pipes.
        progress : bool
            Show a progress bar over the branches.

        Returns
        -------
        VesselSolid
            ``failed`` lists branches left out (with the reason); ``warnings``
            gathers the branches' warnings (radius clamps, moved starts).
        """
        from .kernel.pipes import branch_pipe, seam_angles
        from .kernel.solid import fuse_pipes, start_fuse_worker

        if not self.branches:
            raise ArgumentError("tree: no branches")
        if not (isinstance(station_step_mm, (int, float)) and station_step_mm > 0):
            raise ArgumentError(f"station_step_mm: expected a positive number, got {station_step_mm!r}")
        import time

        t0 = time.perf_counter()
        if len(self.branches) > 1:
            start_fuse_worker()  # the booleans' helper process starts while the pipes are built
        specs = self.pipe_specs(tol_mm, merge, max_merge_angle_deg)
        # the seams are placed on the vessels as they show: a neck hidden inside a parent moves none
        seams = seam_angles([{**s, "radius": s["radius_unnecked"]} for s in specs])
        for s in specs:
            s["seam_deg"] = seams[s["id"]]  # wall seams clear of the other vessels' walls
        t1 = time.perf_counter()
        roots = [s for s in specs if s["parent"] is None]
        failed: dict[int, str] = {sid: why for s in specs for sid, why in s.get("stubs", {}).items()}
        if len(roots) > 1:
            # the tree with the most centreline is kept (not the most branches: a few short pieces
            # would otherwise win over a long vessel with its side branches)
            sizes = {r["id"]: 0 for r in roots}
            lengths = {r["id"]: 0.0 for r in roots}
            owner: dict[int, int] = {}
            for s in specs:
                owner[s["id"]] = s["id"] if s["parent"] is None else owner[s["parent"]]
                sizes[owner[s["id"]]] += 1
                sp = s["spine"]
                lengths[owner[s["id"]]] += float(arc_length(sp(np.linspace(sp.t[sp.k], sp.t[-sp.k - 1],
                                                                           201)))[-1])
            keep = max(lengths, key=lambda k: lengths[k])

            def size(root: int) -> str:
                return f"{_n_branches(sizes[root])}, {lengths[root]:.0f} mm"

            for s in specs:
                if owner[s["id"]] != keep:
                    if s["parent"] is None:
                        whose = f"the root of another tree ({size(s['id'])})"
                    else:
                        whose = f"in the tree of root {owner[s['id']]}"
                    failed[s["id"]] = (f"{whose}; one solid holds one tree: the longest, from root {keep} "
                                       f"({size(keep)})")
        pipes, warnings = [], []
        it = specs
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(specs, desc="pipes", unit="branch")
        for s in it:
            warnings += [f"branch {s['id']} ({s['name']}): {w}" for w in s["warnings"]]
            if s["id"] in failed:
                continue
            if s["parent"] is not None and s["parent"] in failed:
                failed[s["id"]] = f"its parent branch {s['parent']} was left out"
                continue
            try:
                pipes.append(branch_pipe(s["id"], s["name"], s["parent"], s["spine"], s["radius"],
                                         station_step_mm, s.get("cuts", ()), s.get("end", "flat"),
                                         s.get("seam_deg", 0.0), s.get("neck_mm", 0.0),
                                         s.get("dome_openings")))
            except Exception as exc:  # one bad branch never loses the rest
                failed[s["id"]] = f"pipe could not be built: {exc}"
                if s.get("cuts"):  # its start, up to where it first comes back near itself, is kept
                    short = _cut_short(s, station_step_mm, str(exc))
                    if short is not None:
                        pipes.append(short)
                        del failed[s["id"]]
                        warnings.append(f"branch {s['id']} ({s['name']}): {s['warnings'][-1]}")
        t2 = time.perf_counter()
        if not pipes:
            why = "; ".join(f"branch {s['id']} ({s['name']}): {failed[s['id']]}"
                            for s in roots if s["id"] in failed)
            raise GeometryError(f"tree: no pipe could be built ({why or 'no branches'})")
        by_id = {s["id"]: s for s in specs}
        narrowed: dict[int, tuple[Any, interpolate.BSpline, float, str]] = {}

        def narrower(p: Any) -> tuple[Any, str] | None:
            """The branch's pipe once more (a second try where OCCT's union fails or hangs): a
            child kept inside its parent's end with its law as clamped, not kept inside; any
            other child with its start narrowed to RETRY_CHILD_RADIUS_SHARE of its parent's radius."""
            s = by_id.get(p.branch_id)
            if s is None or s.get("r_parent") is None:
                return None
            neck = s.get("neck_mm", 0.0)
            if s.get("not_inside") is not None:
                law, neck = s["not_inside"]
                note = "tried again not kept inside its parent's end"
                said = ("not kept inside its parent's end: OCCT's union with it kept inside failed or did "
                        "not finish")
            else:
                law, _ = _clamp_radius(s["spine"], s["radius"], s["r_parent"], RETRY_CHILD_RADIUS_SHARE)
                if law is s["radius"]:
                    return None  # already that narrow: nothing to try
                r0 = float(np.asarray(s["radius"](s["spine"].t[s["spine"].k])).reshape(-1)[0])
                r1 = float(np.asarray(law(s["spine"].t[s["spine"].k])).reshape(-1)[0])
                note = (f"tried again with its start narrowed from {r0:.2f} to {r1:.2f} mm "
                        f"({RETRY_CHILD_RADIUS_SHARE:.0%} of its parent's radius)")
                said = (f"start narrowed to {RETRY_CHILD_RADIUS_SHARE:.0%} of its parent's radius: OCCT's "
                        "union with the wider start failed or did not finish")
            try:
                q = branch_pipe(s["id"], s["name"], s["parent"], s["spine"], law, station_step_mm,
                                s.get("cuts", ()), s.get("end", "flat"), s.get("seam_deg", 0.0), neck,
                                s.get("dome_openings"))
            except Exception:  # noqa: BLE001 - no second pipe: the branch is left out as it was
                return None
            narrowed[s["id"]] = (q, law, neck, said)
            return q, note

        out = fuse_pipes(pipes, retry=narrower)
        for q in out.pipes:  # a branch that went in on its second try: its spec says so
            if q.branch_id in narrowed and narrowed[q.branch_id][0] is q:
                spec = by_id[q.branch_id]
                _, spec["radius"], spec["neck_mm"], said = narrowed[q.branch_id]
                spec["warnings"].append(said)
        out.failed = {**failed, **out.failed}
        out.warnings = warnings + _contacts(specs) + out.warnings
        out.timings_s = {"rebuild": t1 - t0, "pipes": t2 - t1, **out.timings_s}
        out.specs = specs
        return out


# ------------------------------------------------------------------- helpers
def _cut_short(spec: dict[str, Any], station_step_mm: float, why: str) -> Any:
    """The pipe of a branch that overlaps itself, up to where it first comes back near itself (None
    if that fails too).

    Where OCCT's union of the pieces of such a pipe fails or loses a piece (a
    vessel that turns back on itself with its two legs a fraction of a radius
    apart: a doubled stretch of a reconstruction, model lca 2021, true-label
    rca 2104), the branch keeps its longest start that does not overlap itself:
    up to the sample before the first one whose wall meets the wall of an
    earlier stretch (a hairpin keeps its first leg, a loop all of itself but
    the stretch that crosses back), with an open end there, rather than being
    left out with all its children. ``spec`` is changed to match (spine,
    radius law, no cuts, a flat end) and says so in its warnings.
    """
    from .kernel.pipes import branch_pipe

    spine, law = spec["spine"], spec["radius"]
    a, e = float(spine.t[spine.k]), float(spine.t[-spine.k - 1])
    s, _, _, i, j, _ = _overlaps(spine, law)
    if len(i) == 0:
        return None
    # the last sample before the first one whose wall meets an earlier stretch of the wall:
    # the longest start that does not overlap itself
    cut = float(s[max(int(j.min()) - 1, 0)])
    neck = float(spec.get("neck_mm", 0.0))
    if not neck + 0.5 < cut - a:
        return None
    spine, law = _truncated(spine, cut), _truncated(law, cut)
    try:
        pipe = branch_pipe(spec["id"], spec["name"], spec["parent"], spine, law, station_step_mm, (), "flat",
                           spec.get("seam_deg", 0.0), neck)
    except Exception:  # noqa: BLE001 - no shorter pipe either: the branch is left out as it was
        return None
    spec.update(spine=spine, radius=law, cuts=[], end="flat")
    spec["warnings"].append(f"cut short at {cut - a:.1f} of {e - a:.1f} mm, where it comes back near "
                            f"itself: OCCT's union of its pieces failed ({why})")
    return pipe


def _inlet_reach(root: dict[str, Any], child: dict[str, Any], step_mm: float = 0.1) -> float:
    """How far (mm, along the root's start direction) a child's wall reaches upstream of the
    root's inlet plane, over the child's stretch near the inlet disc (negative: it stays
    downstream; infinite: it leaves more than ``INLET_MAX_CHILD_ANGLE_DEG`` from the root's
    direction, back past the ostium)."""
    spine, law = root["spine"], root["radius"]
    a = float(spine.t[spine.k])
    c0 = np.asarray(spine(a), float)
    t0 = _unit(np.asarray(spine.derivative()(a), float))
    r0 = float(np.ravel(law(a))[0])
    cs = child["spine"]
    lo, hi = float(cs.t[cs.k]), float(cs.t[-cs.k - 1])
    u = np.linspace(lo, hi, max(int(np.ceil((hi - lo) / step_mm)) + 1, 2))
    x, tan = cs(u), cs.derivative()(u)
    tan = tan / np.linalg.norm(tan, axis=1)[:, None]
    r = np.ravel(child["radius"](u))
    near = np.linalg.norm(x - c0, axis=1) <= r0 + r + 0.5 * r0
    if not near.any():
        return -np.inf
    if tan[0] @ t0 < np.cos(np.radians(INLET_MAX_CHILD_ANGLE_DEG)):
        return np.inf  # it heads back past the ostium
    axial = (x - c0) @ t0 - r * np.sqrt(np.clip(1.0 - (tan @ t0) ** 2, 0.0, 1.0))
    return float(-np.min(axial[near]))


def _extend_inlet(root: dict[str, Any], children: list[dict[str, Any]]) -> None:
    """Extend a root's pipe straight upstream where a child's wall would cut its inlet disc.

    A vessel that leaves next to the ostium (the skeleton's root is a
    bifurcation there: both vessels leave the aorta together) has a wall that
    runs behind the root's flat inlet, which it cuts into a partial disc (10 of
    48 model trees of the end-to-end phantom cases; OCCT's union of one of them
    ran 14 s). The root's spine and radius are prepended with a straight piece
    of its start radius along its start tangent, long enough to put the inlet
    ``INLET_CLEARANCE_RADII`` root radii upstream of every child's wall: the
    inlet is then a whole disc, as flow solvers expect. The reconstructed
    centreline is unchanged; the spec's warnings say by how much.
    """
    spine, law = root["spine"], root["radius"]
    a = float(spine.t[spine.k])
    if not children or abs(float(law.t[law.k]) - a) > 1e-9:  # (the law starts where the spine does)
        return
    r0 = float(np.ravel(law(a))[0])
    clearance = INLET_CLEARANCE_RADII * r0
    reach = {c["id"]: _inlet_reach(root, c) for c in children}
    length = max(reach.values()) + clearance
    if length > INLET_EXTENSION_MAX_RADII * r0:
        who = ", ".join(str(i) for i, x in reach.items() if x > INLET_EXTENSION_MAX_RADII * r0 - clearance)
        root["warnings"].append(f"branch {who} leaves next to the ostium and heads back past it: its wall "
                                "cuts the inlet disc (no short extension of the inlet clears it)")
        return
    if length <= 0.0:
        return
    d = np.asarray(spine.derivative()(a), float)
    span = length / float(np.linalg.norm(d))  # parameter span of the straight piece
    root["spine"] = _prepended(spine, span, lambda i, k: spine(a) - span * d * (k - i) / k)
    root["radius"] = root["radius_unnecked"] = _prepended(law, span, lambda i, k: r0)  # (roots have no neck)
    who = ", ".join(str(i) for i, x in reach.items() if x > -clearance)
    root["warnings"].append(f"inlet moved {length:.2f} mm upstream along the vessel's start direction: "
                            f"branch {who} leaves next to the ostium, and its wall would cut the inlet "
                            "disc")


def _prepended(spline: interpolate.BSpline, span: float, coef: Callable[[int, int], Any]
               ) -> interpolate.BSpline:
    """A clamped B-spline with a piece of parameter span ``span`` put before its start: the piece's
    control points are ``coef(i, k)`` for i = 0..k-1, the last one the spline's first (the two meet
    at a knot of multiplicity k, through the spline's first control point)."""
    k, t = spline.k, np.asarray(spline.t, float)
    a = float(t[k])
    c = np.asarray(spline.c, float)
    head = np.stack([np.broadcast_to(np.asarray(coef(i, k), float), c.shape[1:]) for i in range(k)])
    knots = np.r_[[a - span] * (k + 1), [a] * k, t[k + 1:]]
    return interpolate.BSpline(knots, np.concatenate([head, c]), k)


def _truncated(spline: interpolate.BSpline, x: float) -> interpolate.BSpline:
    """The part of a clamped B-spline before parameter ``x``, exactly (knot insertion), clamped at ``x``."""
    k, t = spline.k, np.asarray(spline.t, float)
    c = np.asarray(spline.c, float)
    flat = c.reshape(len(c), -1)
    extra = k - int(np.sum(np.isclose(t, x, rtol=0.0, atol=1e-12)))  # copies of x to reach multiplicity k
    cols, tt = [], t
    for j in range(flat.shape[1]):
        tt, cc, _ = interpolate.insert(x, (t, flat[:, j], k), m=extra) if extra > 0 else (t, flat[:, j], k)
        cols.append(np.asarray(cc))
    below = int(np.searchsorted(np.asarray(tt), x - 1e-12, side="left"))
    knots = np.r_[np.asarray(tt)[:below], [x] * (k + 1)]
    n = len(knots) - k - 1
    coef = np.stack([cc[:n] for cc in cols], axis=1).reshape((n, *c.shape[1:]))
    return interpolate.BSpline(knots, coef, k)


def _necked(law: interpolate.BSpline, r_parent: float | None, at_end: bool
            ) -> tuple[interpolate.BSpline, float]:
    """A child's law necked at its start where it starts at its parent's end
    (:data:`END_NECK_SHARE`), and the neck's length (0: none)."""
    if at_end and r_parent is not None and END_NECK_SHARE is not None:
        out = _neck(law, r_parent, END_NECK_SHARE, END_NECK_RADII * r_parent)
        if out is not law:
            return out, END_NECK_RADII * r_parent
    return law, 0.0


def _neck(law: interpolate.BSpline, r_parent: float, share: float, length: float) -> interpolate.BSpline:
    """``law`` (cubic) minus a smooth dip that takes its start down to ``share * r_parent``.

    The dip is D (1 - u)^3 over ``[a, a + length]`` (u from 0 to 1), zero after:
    it meets zero with value, slope and curvature at ``a + length`` (C2), so the
    result is ``law`` with one knot inserted there, exactly.
    """
    k = law.k
    a, e = float(law.t[k]), float(law.t[-k - 1])
    drop = float(np.ravel(law(a))[0]) - share * r_parent
    end = a + length
    if drop <= 0.0 or not end < e:
        return law
    t = law.t
    if not np.any(np.isclose(t, end, rtol=0.0, atol=1e-9)):
        t = np.sort(np.r_[t, end])
    dip = interpolate.BSpline(np.r_[[a] * 4, [end] * 4], np.array([drop, 0.0, 0.0, 0.0]), 3,
                              extrapolate=False)
    # Both pieces lie in the spline space of ``t``: the least squares fit on enough
    # points per span reproduces their difference exactly.
    inner = np.unique(t)
    x = np.unique(np.linspace(inner[:-1], inner[1:], 6).ravel())
    y = np.ravel(law(x)) - np.nan_to_num(np.ravel(dip(x)))  # the dip is NaN (here 0) past its end
    return interpolate.make_lsq_spline(x, y, t, k)


def _n_branches(n: int) -> str:
    return f"{n} branch" if n == 1 else f"{n} branches"


def _project_params(spline: interpolate.BSpline, points: np.ndarray, step: float = 0.05) -> np.ndarray:
    """Parameters of the nearest curve points (dense sampling + one Newton step)."""
    k = spline.k
    a, b = float(spline.t[k]), float(spline.t[-k - 1])
    u = np.linspace(a, b, max(int((b - a) / step), 2) + 1)
    c = spline(u)
    from scipy.spatial import cKDTree

    _, idx = cKDTree(c).query(points)
    s = u[idx]
    d1 = spline.derivative(1)(s)
    d2 = spline.derivative(2)(s)
    diff = spline(s) - points
    num = np.einsum("ij,ij->i", diff, d1)
    den = np.einsum("ij,ij->i", d1, d1) + np.einsum("ij,ij->i", diff, d2)
    s = s - np.where(np.abs(den) > 1e-12, num / np.where(np.abs(den) > 1e-12, den, 1.0), 0.0)
    return np.clip(s, a, b)


def _without_stubs(tree: VesselTree) -> tuple[VesselTree, dict[int, dict[int, str]]]:
    """The tree without stubs: children shorter than ``STUB_RADII`` (r_parent + r_child) at their start.

    A stub with children becomes the start of the child that continues it most
    straightly (end and start tangents less than 90 degrees apart; merged as
    in :meth:`VesselTree.merged`, whatever the angle); its other children then
    start on that vessel. A stub whose children all turn back is kept (they
    start at its end, which may lie outside the parent); a stub without
    children is left out. Returns the tree and, per parent id, the left-out
    stubs with the reason.
    """
    branches = {b.id: replace(b, warnings=list(b.warnings)) for b in tree.branches}
    stubs: dict[int, dict[int, str]] = {}
    touched = False
    changed = True
    while changed:
        changed = False
        for b in list(branches.values()):
            if b.parent is None or b.parent not in branches:
                continue
            par = branches[b.parent]
            s = b.parent_s_mm if b.parent_s_mm is not None else par.domain[1]
            rp, rc = float(par.radius_at(s)), float(b.radius_at(b.domain[0]))
            if b.length_mm >= STUB_RADII * (rp + rc):
                continue
            kids = [c for c in branches.values() if c.parent == b.id]
            cos = [float(b.tangent("end") @ c.tangent("start")) for c in kids]
            if kids and max(cos) < 0.0:
                continue  # its children turn back: kept, they start at its end
            touched = changed = True
            if kids:
                c = kids[int(np.argmax(cos))]
                joined = _merge_pair(b, c, TOL_MM)
                joined.warnings.append(f"starts with branch {b.id}, a stub of {b.length_mm:.1f} mm "
                                       f"(shorter than {STUB_RADII:g} x its radius and its parent's "
                                       f"together) between two junctions")
                branches[c.id] = replace(joined, id=c.id, name=c.name, parent=par.id, parent_s_mm=None)
                for o in kids:
                    if o.id != c.id:
                        o.parent, o.parent_s_mm = c.id, None
                new_parent = c.id
            else:
                stubs.setdefault(par.id, {})[b.id] = (
                    f"a stub of {b.length_mm:.1f} mm, shorter than {STUB_RADII:g} x its radius and its "
                    f"parent's together ({rc:.1f} + {rp:.1f} mm) where it starts: left out of the solid "
                    f"(inside branch {par.id} but for its end cap)")
                new_parent = par.id
            for sid, why in stubs.pop(b.id, {}).items():  # stubs left out of the stub itself
                stubs.setdefault(new_parent, {})[sid] = why
            del branches[b.id]
            break
    if not touched:
        return tree, {}
    out = VesselTree(list(branches.values()))
    out._locate_children()
    return out, stubs


def _reattached(tree: VesselTree) -> VesselTree:
    """The tree with every child that starts where its parent starts attached to the parent's parent.

    Several vessels leaving one point of a vessel can come out of a
    reconstruction as a chain: the second leaves from the very start of the
    first, the third from the start of the second (reconstruct on a four-way
    junction, model cs 2102). Such a child leaves its parent's start backwards,
    through the parent's start cap, inside the grandparent: no vessel does
    that, and OCCT's union of the two caps and walls there can run for
    minutes. A child whose start lies within ``max(r, 1 mm)`` of arc length
    of its parent's start (``r`` the parent's radius there), and nearer its
    start than its end (a child at the end of a stub is left to
    ``_without_stubs``), is attached to the grandparent instead, where the
    parent is; repeated up a chain. Roots keep such children. The moved
    children say so in their warnings; the input is not changed.
    """
    branches = {b.id: b for b in tree.branches}
    moved = False
    changed = True
    while changed:
        changed = False
        for b in list(branches.values()):
            par = branches.get(b.parent) if b.parent is not None else None
            if par is None or par.parent is None or len(par.points) < 2 or len(b.points) < 1:
                continue
            d = np.linalg.norm(par.points - b.points[0], axis=1)
            i = int(np.argmin(d))
            steps = np.linalg.norm(np.diff(par.points, axis=0), axis=1)
            along = float(steps[:i].sum())
            r = float(par.radius[i])
            if along > min(max(r, 1.0), 0.5 * float(steps.sum())) or d[i] > max(MAX_START_GAP_RADII * r, 2.0):
                continue
            nb = replace(b, parent=par.parent, parent_s_mm=None, warnings=list(b.warnings))
            nb.warnings.append(f"starts where its parent branch {par.id} starts ({along:.1f} mm along it): "
                               f"attached to branch {par.parent}, where branch {par.id} leaves it")
            branches[b.id] = nb
            moved = changed = True
    if not moved:
        return tree
    out = VesselTree([branches[b.id] for b in tree.branches])
    out._locate_children()
    return out


def _merge_pair(p: TreeBranch, c: TreeBranch, tol_mm: float) -> TreeBranch:
    """One vessel from ``p`` and its continuing child ``c``: C2, with a round bend at the join."""
    ps = float(c.parent_s_mm) if c.parent_s_mm is not None else p.domain[1]
    ps = min(ps, p.domain[1])
    tp = _unit(p.spline.derivative()(ps))
    tc = c.tangent("start")
    theta = float(np.arccos(np.clip(tp @ tc, -1.0, 1.0)))
    r_j = float(p.radius_at(ps))
    blend = 3.0 * r_j * np.tan(theta / 2.0) + 0.5  # tangent length of a fillet of radius 3 r
    pa, pb = p.domain
    ca, cb = c.domain
    s_p = max(pa, ps - blend)
    s_c = min(cb - 0.5 * (cb - ca), ca + blend)
    step = 0.25
    sp_ = np.linspace(pa, s_p, max(int((s_p - pa) / step), 1) + 1)
    sc_ = np.linspace(s_c, cb, max(int((cb - s_c) / step), 1) + 1)
    p0, p1 = p.spline(s_p), c.spline(s_c)
    t0, t1 = _unit(p.spline.derivative()(s_p)), _unit(c.spline.derivative()(s_c))
    chord = float(np.linalg.norm(p1 - p0))
    u = np.linspace(0.0, 1.0, max(int(chord / step), 4) + 1)[1:-1, None]
    h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
    h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2
    bridge = h00 * p0 + h10 * chord * t0 + h01 * p1 + h11 * chord * t1
    pts = np.vstack([p.spline(sp_), bridge, c.spline(sc_)])
    rad = np.r_[p.radius_at(sp_), np.interp(np.linspace(0, 1, len(bridge)), [0, 1],
                                             [float(p.radius_at(s_p)), float(c.radius_at(s_c))]),
                c.radius_at(sc_)]
    spl, err = fit_spine(pts, tol_mm)
    s = _project_params(spl, pts)
    law = fit_radius_law(s, rad, float(spl.t[-4] - spl.t[3]))
    # deviation of the merged centreline from the two inputs near the join
    near = np.vstack([p.spline(np.linspace(s_p, ps, 20)), c.spline(np.linspace(ca, s_c, 20))])
    dev = float(np.max(np.linalg.norm(spl(_project_params(spl, near)) - near, axis=1)))
    warnings = list(p.warnings) + list(c.warnings)
    warnings.append(f"merged with branch {c.id} ({c.name}) at {np.degrees(theta):.1f} deg; "
                    f"the rounded join departs {dev:.3f} mm from the input centrelines")
    return replace(p, points=pts, radius=rad, name=f"{p.name}/{c.name}" if c.name else p.name,
                   landmarks=(p.landmarks[0], c.landmarks[1]), segments=tuple(p.segments) + tuple(c.segments),
                   spline=spl, radius_law=law, fit_error_mm=max(err, p.fit_error_mm, c.fit_error_mm),
                   warnings=warnings)


def _start_inside(b: TreeBranch, par: TreeBranch, back: float = 1.0
                  ) -> tuple[interpolate.BSpline, interpolate.BSpline, list[str], float, bool]:
    """Spine and radius law of a child that starts on its parent's centreline, the
    parent's radius there, and whether the child starts at the parent's end.

    A start farther than ``MAX_START_GAP_RADII`` parent radii (and 2 mm) from the
    parent is left alone: such a branch is not attached, and the fusion reports it.
    A child that starts at its parent's very end (a bifurcation where neither
    daughter continues the parent) gets a lead-in that starts ``back`` parent
    radii back inside the parent (one for the first sibling there, see
    ``END_STAGGER_RADII``) and bends into the child: otherwise its start circle
    would cross the parent's end circle at their common centre, which booleans
    do not survive.
    """
    start = b.spline(b.domain[0])
    s_par = _project_params(par.spline, start[None])[0]
    foot = par.spline(s_par)
    gap = float(np.linalg.norm(start - foot))
    r_par = float(par.radius_at(s_par))
    pa, pe = par.domain
    at_end = s_par > pe - r_par and pe - pa > 2.0 * r_par
    if gap <= 0.02 * r_par + 1e-6 and not at_end:
        return b.spline, b.radius_law, [], r_par, False
    if gap > max(MAX_START_GAP_RADII * r_par, 2.0):
        return (b.spline, b.radius_law, [f"starts {gap:.1f} mm from its parent's centreline: not attached"],
                r_par, False)
    a, e = b.domain
    s = np.linspace(a, e, max(int((e - a) / 0.25), 4) + 1)
    pts = b.spline(s)
    join = min(a + 2.0 * r_par + gap, a + 0.5 * (e - a))
    keep = s >= join
    if at_end:
        # Hermite lead-in from the parent's axis ``back`` radii before its end (along the
        # parent) to the child at ``join`` (along the child).
        s_foot = pe - back * r_par
        p0, p1 = par.spline(s_foot), pts[keep][0]
        t0, t1 = _unit(par.spline.derivative()(s_foot)), _unit(b.spline.derivative()(s[keep][0]))
        chord = float(np.linalg.norm(p1 - p0))
        u = np.linspace(0.0, 1.0, max(int(chord / 0.25), 4) + 1)[:-1, None]
        lead = ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * chord * t0
                + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * chord * t1)
        r_par = float(par.radius_at(s_foot))
        note = f"starts at its parent's end: lead-in from {pe - s_foot:.2f} mm back inside the parent"
    else:
        # Prepend the foot point: refit a spine that leaves the parent's axis and joins
        # the child smoothly within a few radii.
        lead = np.linspace(0.0, 1.0, 12)[:-1, None] * (pts[keep][0] - foot) + foot
        note = f"start moved {gap:.2f} mm onto the parent's centreline"
    new_pts = np.vstack([lead, pts[keep]])
    rad = np.r_[np.full(len(lead), float(b.radius_at(join))), b.radius_at(s[keep])]
    spl, _ = fit_spine(new_pts, TOL_MM)
    law = fit_radius_law(_project_params(spl, new_pts), rad, float(spl.t[-4] - spl.t[3]))
    return spl, law, [note], r_par, at_end


def _contact_pairs(p: np.ndarray, r: np.ndarray, o: np.ndarray, n: np.ndarray,
                   clearance: float = 0.0, linked: set[tuple[int, int]] | None = None, step: float = 0.25,
                   diverge: bool = False, junction: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample pairs of two vessels whose walls come closer than ``clearance`` away from a junction.

    ``p``, ``r``: axis samples and radii of all vessels; ``o``: the vessel of
    each sample; ``n``: its index along that vessel (0 at the start, ``step``
    mm apart). Two vessels touch where their axes come closer than the sum of
    their radii (plus ``clearance``). Where that begins at the start of one of
    them (a child starting inside its parent, two daughters leaving one point)
    and runs on without a break, it is their junction and left out (walls that
    cut into each other again after their junction are not).

    ``linked`` holds the (lower, higher) vessel numbers of parent and child;
    for any other pair (siblings, a vessel and its grandparent) the junction
    ends where two vessels leaving one point at 30 degrees would be apart,
    ``L = junction (r_i + r_j)`` from the start (``junction`` = 2): siblings
    that run on side by side, fused, touch. With ``diverge``, such a pair
    must also open up at least like a 23-degree split once their junction
    ends (where their walls are ``clearance`` apart, at ``s0 <= L``): the
    walls are asked to be ``clearance + 0.4 (s - s0)`` apart at ``s`` mm from
    the start, up to ``clearance`` plus the smaller radius (a shallow split
    leaves a knife-edge crease that prism layers cannot follow); the gaps
    returned for those samples are reduced by the extra asked, so
    ``clearance - gap`` is what is missing.

    Returns the sample indices ``i`` (of the vessel listed first, lower
    ``o``), ``j`` and the gaps (mm, negative where the walls cut into each
    other).
    """
    from scipy.spatial import cKDTree

    empty = np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    rmax = float(r.max())
    reach = 2.0 * rmax + clearance + (rmax if diverge else 0.0)
    pairs = cKDTree(p).query_pairs(reach, output_type="ndarray")
    if not len(pairs):
        return empty
    i, j = pairs[:, 0], pairs[:, 1]
    swap = o[i] > o[j]
    i, j = np.where(swap, j, i), np.where(swap, i, j)
    gap = np.linalg.norm(p[i] - p[j], axis=1) - r[i] - r[j]
    near_enough = (o[i] != o[j]) & (gap < clearance + (np.minimum(r[i], r[j]) if diverge else 0.0))
    i, j, gap = i[near_enough], j[near_enough], gap[near_enough]
    if not len(i):
        return empty
    touch = gap < clearance

    def junction_run(idx: np.ndarray, cap: int) -> int:
        """Length of the unbroken run of contact samples from a vessel's start (0 if none)."""
        if not len(idx):
            return 0
        have = np.zeros(int(idx.max()) + 2, bool)
        have[idx] = True
        return min(int(np.argmin(have)), cap) if have[0] else 0

    def away(na: np.ndarray, nb: np.ndarray, src: np.ndarray, cap: int) -> np.ndarray:
        """Samples past the junction runs (counted over the samples ``src``)."""
        return (na >= junction_run(na[src], cap)) & (nb >= junction_run(nb[src], cap))

    keep = np.zeros(len(i), bool)
    out_gap = gap.copy()
    width = int(o.max()) + 1
    pair_of = o[i] * width + o[j]
    for key in np.unique(pair_of):
        sel = np.flatnonzero(pair_of == key)
        na, nb = n[i[sel]], n[j[sel]]
        t = touch[sel]
        cap = len(p)
        free = linked is not None and (int(key) // width, int(key) % width) not in linked
        if free and t.any():
            near = t & ((na == na[t].min()) | (nb == nb[t].min()))
            cap = int(np.ceil(junction * float(np.max(r[i[sel]][near] + r[j[sel]][near])) / step))
        keep[sel] = t & away(na, nb, t, cap)
        cut = t & (gap[sel] < 0)
        if clearance > 0 and cut.any():  # walls that cut into each other again after the junction
            keep[sel] |= cut & away(na, nb, cut, cap)
        if diverge and free:
            run_a, run_b = junction_run(na[t], len(p)), junction_run(nb[t], len(p))
            if run_a or run_b:  # they leave one point: open up at least like a 23-degree split
                s_mm = np.where(run_a > 0, na, nb) if not (run_a and run_b) else np.minimum(na, nb)
                s_mm = s_mm * step
                s0 = min(cap, max(run_a, run_b)) * step
                extra = np.clip(0.4 * (s_mm - s0), 0.0, np.minimum(r[i[sel]], r[j[sel]]))
                short = (s_mm >= s0) & (gap[sel] < clearance + extra)
                keep[sel[short]] = True
                out_gap[sel[short]] = gap[sel[short]] - extra[short]
    return i[keep], j[keep], out_gap[keep]


def _spec_samples(specs: list[dict[str, Any]], step: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    pts, rad, owner, index = [], [], [], []
    for k, sp in enumerate(specs):
        spine, law = sp["spine"], sp["radius"]
        a, b = float(spine.t[spine.k]), float(spine.t[-spine.k - 1])
        u = np.linspace(a, b, max(int((b - a) / step), 1) + 1)
        pts.append(spine(u))
        rad.append(np.ravel(law(u)))
        owner.append(np.full(len(u), k))
        index.append(np.arange(len(u)))
    return np.vstack(pts), np.concatenate(rad), np.concatenate(owner), np.concatenate(index)


def _contacts(specs: list[dict[str, Any]], step: float = 0.25) -> list[str]:
    """Warnings for vessels whose walls meet away from their junctions.

    Any contact that is not a junction (:func:`_contact_pairs`) gives the union
    a sharp crease (or a handle), which CFD boundary layers cannot follow. One
    warning per pair of vessels, at their deepest overlap.
    """
    if len(specs) < 2:
        return []
    p, r, o, _n = _spec_samples(specs, step)
    slot = {sp["id"]: k for k, sp in enumerate(specs)}
    linked = {(min(k, slot[sp["parent"]]), max(k, slot[sp["parent"]])) for k, sp in enumerate(specs)
              if sp.get("parent") in slot}
    # a little more lenient than separated() (2.0), so what it clears is not reported after a refit
    i, j, gap = _contact_pairs(p, r, o, _n, 0.0, linked, step, junction=2.5)
    out = []
    for a, b in sorted({(int(x), int(y)) for x, y in zip(o[i], o[j], strict=True)}):
        sel = np.flatnonzero((o[i] == a) & (o[j] == b))
        k = sel[np.argmin(gap[sel])]
        x, y, z = 0.5 * (p[i[k]] + p[j[k]])
        first, second = specs[a], specs[b]
        out.append(f"branches {first['id']} ({first['name']}) and {second['id']} ({second['name']}) touch "
                   f"away from a junction, around ({x:.1f}, {y:.1f}, {z:.1f}) mm (the walls cut up to "
                   f"{-gap[k]:.2f} mm into each other): the solid joins them there (a handle, with a sharp "
                   "crease that CFD boundary layers may not follow; VesselTree.separated() moves them apart)")
    return out


def _overlaps(spine: interpolate.BSpline, law: interpolate.BSpline
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of 0.5 mm samples where a pipe comes back near itself (see :func:`_self_approach`).

    Returns the samples' parameters, points and radii, and for each such pair
    (``i < j``) the two indices and the wall-to-wall gap (negative).
    """
    from scipy.spatial import cKDTree

    a, e = float(spine.t[3]), float(spine.t[-4])
    s = np.linspace(a, e, max(int((e - a) / 0.5), 2) + 1)
    p = spine(s)
    r = np.ravel(law(s))
    pairs = cKDTree(p).query_pairs(2.0 * float(r.max()), output_type="ndarray")
    none = np.zeros(0, int)
    if len(pairs) == 0:
        return s, p, r, none, none, np.zeros(0)
    i, j = pairs.min(axis=1), pairs.max(axis=1)
    gap = np.linalg.norm(p[i] - p[j], axis=1) - r[i] - r[j]
    far = np.abs(s[i] - s[j]) > np.pi * (r[i] + r[j])
    bad = far & (gap < 0)
    return s, p, r, i[bad], j[bad], gap[bad]


def _self_approach(spine: interpolate.BSpline, law: interpolate.BSpline) -> tuple[list[str], list[float]]:
    """Where a branch's pipe would overlap itself, and where to cut it so no piece does.

    A pipe whose centreline comes back near itself (closer than the two radii,
    farther apart along the curve than half a turn around both) is not a valid
    sweep: its wall crosses itself, which ``BRepCheck_Analyzer`` does not see
    and booleans do not survive. Cutting the spine between every such pair of
    points (at the middle of the arc between them, where a loop turns) gives
    pieces that are each clean and whose union is the true vessel.

    Returns
    -------
    warnings : list of str
    cuts : list of float
        Spine parameters (mm) to cut the pipe at, ascending; empty when it is clean.
    """
    s, p, r, i, j, gap = _overlaps(spine, law)
    if len(i) == 0:
        return [], []
    k = int(np.argmin(gap))
    # Stab every overlapping pair's interval with a cut, earliest-ending first (greedy
    # interval stabbing; the cut goes to the middle of the first unstabbed interval).
    lo, hi = s[i], s[j]
    cuts: list[float] = []
    for m in np.argsort(hi, kind="stable"):
        if not any(lo[m] < c < hi[m] for c in cuts):
            cuts.append(0.5 * float(lo[m] + hi[m]))
    cuts.sort()
    return [f"the pipe overlaps itself: the centreline at {s[i[k]]:.1f} mm and at {s[j[k]]:.1f} mm comes "
            f"within {float(np.linalg.norm(p[i[k]] - p[j[k]])):.2f} mm (radii {r[i[k]]:.2f} and "
            f"{r[j[k]]:.2f} mm); swept in {len(cuts) + 1} pieces (cut at "
            + ", ".join(f"{c:.1f}" for c in cuts) + " mm) that are fused"], cuts


def _smooth_kinks(spine: interpolate.BSpline, law: interpolate.BSpline
                  ) -> tuple[interpolate.BSpline, list[str]]:
    """The spine smoothed where it bends tighter than its radius allows, within half a radius.

    A vessel does not bend around a radius smaller than its own; a reconstructed
    centreline does, where its points carry local errors (a kink of a few tenths
    of a millimetre). Clamping the radius there would pinch the pipe to a thread
    (a non-manifold tessellation), so the spine is first refitted with a rising
    curvature penalty, as long as no point moves by more than half the local
    radius; what remains is left to the radius clamp.
    """
    k = spine.k
    a, e = float(spine.t[k]), float(spine.t[-k - 1])
    s = np.linspace(a, e, max(int((e - a) / 0.25), 8) + 1)
    r = np.asarray(law(s)).reshape(-1)
    if np.all(r * curvature(spine, s) <= CURVATURE_FACTOR):
        return spine, []
    p = np.asarray(spine(s))
    ends = np.r_[[0] * 20, [len(s) - 1] * 20]  # hold the ends
    x, y = np.r_[s, s[ends]], np.vstack([p, p[ends]])
    n_spans = max(len(spine.t) - 2 * k - 1, 1)
    step = (e - a) / n_spans
    best, shift = spine, np.zeros(len(s))
    for lam in 10.0 ** np.arange(-3, 4):
        cand = fit_pspline(x, y, step, float(lam), domain=(a, e))
        moved = np.linalg.norm(np.asarray(cand(s)) - p, axis=1)
        if np.any(moved > 0.5 * r):
            break
        best, shift = cand, moved
        if np.all(r * curvature(cand, s) <= CURVATURE_FACTOR):
            break
    if best is spine:
        return spine, []
    return best, [f"centreline smoothed by up to {shift.max():.2f} mm where it bent tighter than its "
                  f"radius / {CURVATURE_FACTOR}"]


def _clamp_samples(spine: interpolate.BSpline) -> np.ndarray:
    """The spine parameters (about 0.1 mm apart) on which radius limits are laid."""
    k = spine.k
    a, e = float(spine.t[k]), float(spine.t[-k - 1])
    return np.linspace(a, e, max(int((e - a) / 0.1), 8) + 1)


def _clamp_radius(spine: interpolate.BSpline, law: interpolate.BSpline, r_parent: float | None,
                  share: float = CHILD_RADIUS_SHARE, along: np.ndarray | None = None
                  ) -> tuple[interpolate.BSpline, list[str]]:
    """Radius law clamped against curvature (no folding) and, for a child whose parent has
    radius ``r_parent`` at its start, below ``share`` of the parent's radius there.

    ``along``: a further limit on :func:`_clamp_samples` (mm, inf where none) that keeps a
    child inside its parent's end (:func:`_keep_inside`): its reduction is widened towards
    the child's start only.
    """
    s = _clamp_samples(spine)
    a, e = float(s[0]), float(s[-1])
    r = np.asarray(law(s)).reshape(-1)
    curv_lim = CURVATURE_FACTOR / np.maximum(curvature(spine, s), 1e-9)
    limit = curv_lim
    back = np.zeros(len(s), bool)  # where the limit is kept inside the parent: widened backwards only
    warnings = []
    if r_parent is not None:
        ramp = np.clip((s - a) / max(2.0 * r_parent, 1e-6), 0.0, 1.0)
        start_lim = share * r_parent + ramp * 1e3
        if r[0] > start_lim[0] * 1.05:
            warnings.append(f"start radius {r[0]:.2f} mm reduced to {start_lim[0]:.2f} mm "
                            f"({share:.0%} of the parent's) so it starts inside the parent")
        limit = np.minimum(limit, start_lim)
    if along is not None:
        back = along < limit
        limit = np.minimum(limit, along)
    if np.any(r > curv_lim):
        bad = s[r > curv_lim]
        warnings.append(f"radius reduced by up to {float(np.max(r - curv_lim)):.2f} mm over "
                        f"{bad.min():.1f}-{bad.max():.1f} mm, where the centreline bends tighter than "
                        f"radius / {CURVATURE_FACTOR}")
    if not np.any(r > limit):
        return law, warnings
    # Subtract a smooth reduction that covers the clamp (a max filter widened by
    # 1.5 mm, then a 0.5 mm Gaussian), so the refit does not ring; where the fit
    # still overshoots the limit, deepen the reduction there and fit again. The limit
    # inside a parent's end is widened towards the child's start only (0.5 mm forward):
    # past the parent's end the child is seen, and takes its own radius again within ~2 mm.
    step = float(s[1] - s[0])
    need = np.maximum(r - limit, 0.0)
    half = int(round(1.5 / step))
    m, fwd = int(round(1.0 / step)), int(round(0.5 / step))  # 1.5 mm back, 0.5 mm forward
    for _ in range(8):
        wide = np.maximum(
            ndimage.maximum_filter1d(np.where(back, 0.0, need), 2 * half + 1, mode="nearest"),
            ndimage.maximum_filter1d(np.where(back, need, 0.0), 2 * m + 1, origin=fwd - m, mode="nearest"))
        target = r - ndimage.gaussian_filter1d(wide, 0.5 / step, mode="nearest")
        spl = fit_pspline(s, target[:, None], 0.5, 0.0, domain=(a, e))
        excess = np.asarray(spl(s)).reshape(-1) - limit
        if excess.max() <= 1e-3 * float(np.min(limit)):
            break
        need = need + np.maximum(excess, 0.0)
    lowest = MIN_RADIUS_MM
    if back.any():
        # the steep notch inside the parent must not ring below half its radius (the neck's
        # depth) at the child's start
        lowest = max(lowest, min(0.5 * float(r_parent), float(limit.min())))
    c = np.maximum(np.asarray(spl.c), lowest)
    return interpolate.BSpline(spl.t, c, spl.k), warnings


def _keep_inside(spine: interpolate.BSpline, law: interpolate.BSpline, r_parent: float, parent: TreeBranch,
                 share: float) -> tuple[interpolate.BSpline, list[str], interpolate.BSpline | None]:
    """The radius law of a child that starts at ``parent``'s end, clamped (:func:`_clamp_radius`)
    and, where it would swallow the parent's end, kept within ``share`` of the parent's radius
    while it runs along it inside it (:data:`END_INSIDE_SHARE`); its warnings; and the law
    clamped but not kept inside where it was (else None)."""
    plain, warnings = _clamp_radius(spine, law, r_parent)
    s = _clamp_samples(spine)
    kept = np.asarray(plain(s)).reshape(-1)
    along, swallows = _inside_limit(spine, s, kept, parent, share)  # its start alone, held, does not
    if not swallows:
        return plain, warnings, None
    inside, warnings = _clamp_radius(spine, law, r_parent, along=along)
    over = kept > along * 1.05
    if over.any():
        warnings.append(f"radius kept within {share:.0%} of its parent's over {s[over].min() - s[0]:.1f}-"
                        f"{s[over].max() - s[0]:.1f} mm, where it runs along it inside its end (it would "
                        "have swallowed the parent's end)")
    return inside, warnings, plain


def _inside_limit(spine: interpolate.BSpline, s: np.ndarray, r: np.ndarray, parent: TreeBranch, share: float
                  ) -> tuple[np.ndarray, bool]:
    """Largest radius (mm) at the spine parameters ``s`` of a child starting at ``parent``'s
    end that keeps its wall within ``share`` of the parent's radius (inf where no limit
    applies), and whether the child's radii ``r`` there swallow the parent short of its end
    (a circle of the child around the parent's).

    It applies where the child's axis lies within half the parent's radius of the parent's
    axis and projects onto the parent short of its end. A child that starts at its parent's
    end runs along the parent's axis from inside it (``_start_inside``'s lead-in); were it
    wider than the parent there (a junction's blob widens both), its wall would cross the
    parent's at a grazing angle all round, and OCCT's fuse can leave the two walls touching
    along a line (end-to-end cs 2111 with true labels: the STL's 101 edges in four
    triangles). Kept inside, the child leaves through the parent's domed end, at a steep angle.
    """
    pts = spine(s)
    sp = _project_params(parent.spline, pts)
    pe = float(parent.domain[1])
    off = np.linalg.norm(pts - parent.spline(sp), axis=1)
    rp = np.asarray(parent.radius_at(sp), float).reshape(-1)
    before_end = sp < pe - 1e-6
    along = before_end & (off <= 0.5 * rp)
    swallows = bool(np.any(before_end & (r >= rp + off)))
    return np.where(along, share * rp - off, np.inf), swallows
