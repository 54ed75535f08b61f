"""Variable-radius NURBS pipes: one closed OCCT solid per vessel branch.

The wall of a branch is a rational B-spline surface of degree (2, 3):

- around the vessel (U in [0, 4]) every V-section through a *station* is an
  exact circle, the classic 9-pole rational quadratic with weights 1 and
  sqrt(2)/2, in the plane normal to the spine;
- along the vessel (V = arc length of the spine, mm) each of the nine pole
  tracks is the cubic interpolant of its station values. Stations are at most
  ``station_step_mm`` apart, closer where the vessel bends tightly or its
  radius changes quickly: one is added wherever the wall midway between two
  stations would stray more than ``SECTION_TOL_MM`` (2 micrometres) from the
  exact section there (``benchmarks/solids.py`` measures the distance to the
  analytic tube).

The section frames are rotation minimizing (double reflection, Wang et al.
2008), so the wall does not twist and the seam stays straight. The solid is
the wall plus two planar caps that share its boundary edges.

Why not ``BRepOffsetAPI_MakePipeShell`` with a radius law: it works, but its
approximated walls are degree 6 x 6..11 with tens of poles per 10 mm, which
makes every later boolean several times slower than on these surfaces, and the
sections are no longer exact circles.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from OCP.BRep import BRep_Builder, BRep_Tool
from OCP.BRepBuilderAPI import (
    BRepBuilderAPI_MakeEdge,
    BRepBuilderAPI_MakeFace,
    BRepBuilderAPI_MakeVertex,
    BRepBuilderAPI_MakeWire,
    BRepBuilderAPI_Sewing,
)
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.Geom import Geom_BSplineSurface, Geom_SphericalSurface
from OCP.gp import gp_Ax2, gp_Ax3, gp_Circ, gp_Dir, gp_Pnt, gp_Sphere
from OCP.ShapeFix import ShapeFix_Face, ShapeFix_Solid
from OCP.TColgp import TColgp_Array2OfPnt
from OCP.TColStd import TColStd_Array2OfReal
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape, TopoDS_Shell, TopoDS_Solid
from scipy import interpolate

from ..errors import GeometryError
from . import solid as _solid
from .nurbs import _int_array, _real_array, is_valid, knots_and_mults
from .solid import FUZZY_MM, BranchPipe, _axis_sdf, _general_fuse, _History, _quick_volume, _subshapes

__all__ = ["rotation_minimizing_normals", "tube_stations", "tube_surface", "tube_solid", "branch_pipe",
           "seam_angles", "TUBE_TOL_MM", "SECTION_TOL_MM"]

#: Tolerance given to the faces and edges of a tube (mm).
TUBE_TOL_MM = 1e-6
#: Largest distance between a tube's wall and its exact circular section midway
#: between two stations (mm); stations are added where it would be larger.
SECTION_TOL_MM = 2e-3

_FRAME_STEP_MM = 0.25  # spacing of the rotation-minimizing frame samples
_MAX_REFINE = 8  # rounds of station insertion
_MIN_STATION_GAP_MM = 0.05  # stations are never added closer than this
_SEAM_STEP_MM = 0.25  # spacing of the seam samples that seam_angles scores
#: The union of the pieces of a pipe that overlaps itself must keep some wall of every
#: piece, and its volume must lie within this share of the union of the pieces' tubes
#: (:func:`_union_volume`, a sampled estimate good to ~0.5 %), else it counts as failed:
#: OCCT returns a valid solid that dropped a piece (true-label rca 2104), or that kept two
#: walls a few hundredths of a mm apart without cutting them (a hairpin; the volume of both
#: legs). None: the union is taken as OCCT gives it.
PIECES_VOLUME_SLACK: float | None = 0.04
_UNION_SAMPLES = 8000  # points per piece of that estimate

_ANGLES = np.radians(np.arange(0, 361, 45, dtype=float))
_POLE_RADIUS = np.array([1.0, np.sqrt(2.0)] * 4 + [1.0])
_WEIGHTS = np.array([1.0, np.sqrt(0.5)] * 4 + [1.0])
_U_KNOTS = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
_U_MULTS = np.array([3, 2, 2, 2, 3])
_RING_U = np.arange(0.25, 4.0, 0.5)  # 8 wall parameters round a section, off the seam and the knots


def rotation_minimizing_normals(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Normals of a rotation-minimizing frame along a sampled curve (double reflection).

    Parameters
    ----------
    points : (n, 3) array
        Curve samples, ordered.
    tangents : (n, 3) array
        Unit tangents at the samples.

    Returns
    -------
    (n, 3) array
        Unit normals, perpendicular to the tangents; the first one is the unit
        vector perpendicular to the first tangent closest to the world axis the
        tangent is least aligned with.
    """
    t = np.asarray(tangents, dtype=float)
    p = np.asarray(points, dtype=float)
    axis = np.eye(3)[int(np.argmin(np.abs(t[0])))]
    n0 = axis - (axis @ t[0]) * t[0]
    n0 = n0 / np.linalg.norm(n0)
    if len(p) < 2:
        return n0[None, :].copy()
    # Each step reflects the last frame twice (Householder matrices R2 R1, a
    # rotation taking t[i-1] exactly to t[i]); the frames are the running
    # products applied to the first normal, computed by a log-depth scan
    # (the recurrence itself is sequential: ~15x slower in Python).
    eye = np.eye(3)
    v1 = np.diff(p, axis=0)
    c1 = np.einsum("ij,ij->i", v1, v1)
    move = c1 >= 1e-24  # repeated points keep the frame
    r1 = eye - (2.0 / np.where(move, c1, 1.0))[:, None, None] * np.einsum("ij,ik->ijk", v1, v1)
    t_l = np.einsum("ijk,ik->ij", r1, t[:-1])
    v2 = t[1:] - t_l
    c2 = np.einsum("ij,ij->i", v2, v2)
    turn = c2 > 1e-24  # the tangent turns: reflect once more
    r2 = eye - (2.0 * turn / np.where(turn, c2, 1.0))[:, None, None] * np.einsum("ij,ik->ijk", v2, v2)
    # then the projection normal to t[i] (round-off, except after a repeated point,
    # whose frame is kept as it was); the normalization commutes with these linear maps
    proj = eye - np.einsum("ij,ik->ijk", t[1:], t[1:])
    steps = np.where(move[:, None, None], proj @ r2 @ r1, eye)
    d = 1
    while d < len(steps):  # steps[i] becomes the product of steps[i], steps[i-1], ..., steps[0]
        steps[d:] = steps[d:] @ steps[:-d]
        d *= 2
    n = np.vstack([n0, steps @ n0])
    return n / np.linalg.norm(n, axis=1)[:, None]


def _frames(spine: interpolate.BSpline, v0: float, v1: float, step: float, seam_deg: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-minimizing normals on a uniform grid of ``v0..v1`` (spacing <= ``step``),
    turned by ``seam_deg`` about the tangent (the wall's seam lies along them)."""
    n = max(int(np.ceil((v1 - v0) / step)), 3) + 1
    grid = np.linspace(v0, v1, n)
    d1 = spine.derivative()(grid)
    speed = np.linalg.norm(d1, axis=1)
    if np.any(speed < 1e-9):
        raise GeometryError("tube: the spine has a zero tangent (a cusp or repeated points)")
    tan = d1 / speed[:, None]
    normals = rotation_minimizing_normals(spine(grid), tan)
    if seam_deg:
        # the double reflection commutes with a turn about the tangent: turning every
        # normal is turning the first one
        phi = np.radians(float(seam_deg))
        normals = np.cos(phi) * normals + np.sin(phi) * np.cross(tan, normals)
    return grid, normals


def _section_poles(spine: interpolate.BSpline, radius: Any, v: np.ndarray, grid: np.ndarray,
                   grid_normals: np.ndarray) -> np.ndarray:
    """The (len(v), 9, 3) poles of the exact circles normal to the spine at ``v``."""
    d1 = spine.derivative()(v)
    tan = d1 / np.linalg.norm(d1, axis=1)[:, None]
    # the frame between grid samples: linear blend, made normal to the exact tangent
    nrm = np.stack([np.interp(v, grid, grid_normals[:, k]) for k in range(3)], axis=1)
    nrm -= np.einsum("ij,ij->i", nrm, tan)[:, None] * tan
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    bin_ = np.cross(tan, nrm)
    r = np.asarray(radius(v), dtype=float).reshape(-1)
    if np.any(~np.isfinite(r)) or np.any(r <= 0):
        raise GeometryError("tube: the radius law must be positive and finite")
    dirs = (np.cos(_ANGLES)[None, :, None] * nrm[:, None, :]
            + np.sin(_ANGLES)[None, :, None] * bin_[:, None, :])
    return spine(v)[:, None, :] + (r[:, None] * _POLE_RADIUS[None, :])[:, :, None] * dirs


def seam_angles(specs: list[dict[str, Any]], n_angles: int = 36) -> dict[int, float]:
    """Where each branch's wall seam should lie so that it keeps clear of the other vessels.

    A wall's seam (its U = 0 edge) that meets another vessel's wall leaves a B-rep
    vertex on their junction curve; one close to where three walls meet, or to
    another seam's vertex, leaves a very short edge there, and the mesher then
    needs tiny elements beside thicker prism layers (a 0.05 scaled Jacobian at a
    coronary sinus junction). For every branch, parents first, ``n_angles`` seam
    positions are scored by their clearance along the seam (sampled every
    0.25 mm, and down an end dome's meridian), measured with the other tubes'
    distance functions (from their centreline samples and radii):

    - seam points deep inside another tube do not count (the union removes them);
    - where the seam meets a wall (it leaves or enters a tube: a vertex), the
      distance to the *next* nearest wall and to the seams placed before, and
      less where it meets the wall at a shallow angle (below 30 degrees it skims
      it: slivers);
    - elsewhere, the distance to the nearest wall.

    A pipe cut into pieces (it comes back near itself) counts its own other
    pieces as other tubes. The smallest clearance, capped at the branch's median
    radius and taken in 0.05 mm classes, is maximized; among equals, the seam
    with the fewest vertices, then the one nearest the frame's normal (0 deg).

    Parameters
    ----------
    specs : list of dict
        ``VesselTree.pipe_specs()`` output (parents first): ``'id'``, ``'spine'``,
        ``'radius'`` and optionally ``'end'`` and ``'cuts'``.
    n_angles : int
        Seam positions tried around each vessel.

    Returns
    -------
    dict of int -> float
        Seam angle (degrees, ``[0, 360)``) per branch id, for :func:`branch_pipe`.
    """
    from scipy.spatial import cKDTree

    if not (isinstance(n_angles, int) and n_angles >= 1):
        raise GeometryError(f"seam_angles: n_angles must be a positive integer, got {n_angles!r}")
    data = {int(s["id"]): _seam_candidates(s, n_angles) for s in specs}
    chosen: dict[int, float] = {}
    placed: list[np.ndarray] = []  # the seams chosen so far
    parent = {int(s["id"]): s.get("parent") for s in specs}

    def kin(a: int, b: int) -> bool:  # vessels that meet at a junction: parent, child, sibling, grand-
        pa, pb = parent.get(a), parent.get(b)
        return (pa == b or pb == a or (pa is not None and pa == pb)
                or (pa is not None and parent.get(pa) == b) or (pb is not None and parent.get(pb) == a))

    for s in specs:
        me = data[int(s["id"])]
        others = [data[int(q["id"])] for q in specs if q is not s]
        # a vessel that touches this one away from any junction: a seam must not run inside it
        # (OCCT then kept a stretch of that seam's wall inside the other vessel, 0.3 mm deep)
        strangers = [not kin(int(s["id"]), int(q["id"])) for q in specs if q is not s]
        clear, crossings = _seam_clearance(me, others, cKDTree(np.vstack(placed)) if placed else None,
                                           strangers)
        score = np.floor(np.minimum(clear.min(axis=0), me["cap"]) / 0.05)
        best = np.flatnonzero(score == score.max())
        best = best[crossings[best] == crossings[best].min()]
        k = int(best[np.argmin(np.minimum(best, n_angles - best))])
        chosen[int(s["id"])] = 360.0 * k / n_angles
        placed.append(me["pts"][:, k, :])
    return chosen


def _seam_candidates(spec: dict[str, Any], n_angles: int) -> dict[str, Any]:
    """Sampled seam candidates of one pipe (``pts``: (n, K, 3), a column per angle) and
    what :func:`_seam_clearance` needs of it as a neighbour."""
    from scipy.spatial import cKDTree

    spine = spec["spine"]
    a, b = float(spine.t[spine.k]), float(spine.t[-spine.k - 1])
    grid, nrm = _frames(spine, a, b, _SEAM_STEP_MM)
    d1 = spine.derivative()(grid)
    tan = d1 / np.linalg.norm(d1, axis=1)[:, None]
    centre, r = spine(grid), np.ravel(spec["radius"](grid)).astype(float)
    theta = 2.0 * np.pi * np.arange(n_angles) / n_angles
    dirs = (np.cos(theta)[None, :, None] * nrm[:, None, :]
            + np.sin(theta)[None, :, None] * np.cross(tan, nrm)[:, None, :])
    pts = centre[:, None, :] + r[:, None, None] * dirs
    u = grid
    if spec.get("end") == "dome":  # the dome's seam runs on from the wall's to its pole
        poles = np.array([dome_pole(tan[-1], d, spec.get("dome_openings")) for d in dirs[-1]])  # (K, 3)
        omega = np.arccos(np.clip(np.sum(dirs[-1] * poles, axis=1), -1.0, 1.0))[None, :, None]  # (1, K, 1)
        f = np.linspace(0.0, 1.0, 5)[1:, None, None]  # along each great circle to the pole
        arc = (np.sin((1.0 - f) * omega) * dirs[-1][None] + np.sin(f * omega) * poles[None]) / np.sin(omega)
        pts = np.concatenate([pts, centre[-1] + r[-1] * arc], axis=0)
        u = np.r_[grid, np.full(len(f), grid[-1])]
    reach = float(r.max())
    cuts = np.sort(np.asarray(spec.get("cuts", ()), dtype=float))
    piece = np.searchsorted(cuts, u)  # which piece of a pipe cut into pieces each sample is on
    return {"pts": pts, "centre": centre, "r": r, "tree": cKDTree(centre), "reach": reach,
            "cap": float(np.median(r)), "lo": centre.min(axis=0) - reach, "hi": centre.max(axis=0) + reach,
            "piece": piece, "wall_piece": piece[:len(grid)], "pieces": len(cuts) + 1,
            # where neighbouring pieces meet (they share a circle there), they are no obstacle
            "near_cut": (np.min(np.abs(u[:, None] - cuts[None, :]), axis=1) < 3.0 * reach
                         if len(cuts) else np.zeros(len(u), bool))}


def _tube_distance(points: np.ndarray, tree: Any, r: np.ndarray, reach: float) -> np.ndarray:
    """Signed distance of points to a tube's wall, given the k-d tree of its centreline
    samples and their radii; inf beyond ``reach``."""
    dist, idx = tree.query(points, distance_upper_bound=reach)
    return dist - np.r_[r, 0.0][idx]


def _seam_clearance(me: dict[str, Any], others: list[dict[str, Any]], placed: Any,
                    strangers: list[bool]) -> tuple[np.ndarray, np.ndarray]:
    """Clearance (mm) of every seam candidate sample, (n, K), and the vertices per candidate;
    samples inside a tube flagged in ``strangers`` (one that touches this one away from any
    junction) get none."""
    from scipy.spatial import cKDTree

    pts, cap = me["pts"], me["cap"]
    n, n_angles = pts.shape[:2]
    flat = pts.reshape(-1, 3)
    dists = []  # signed distance of every sample to each nearby tube's wall
    inside_stranger = np.zeros((n, n_angles), bool)
    for other, stranger in zip(others, strangers, strict=True):
        if np.any(me["lo"] - cap > other["hi"]) or np.any(me["hi"] + cap < other["lo"]):
            continue
        box = np.flatnonzero(np.all((flat > other["lo"] - cap) & (flat < other["hi"] + cap), axis=1))
        if len(box):
            d = np.full(len(flat), np.inf)
            d[box] = _tube_distance(flat[box], other["tree"], other["r"], other["reach"] + cap)
            dists.append(d.reshape(n, n_angles))
            if stranger:
                inside_stranger |= dists[-1] < 0
    for j in range(me["pieces"] if me["pieces"] > 1 else 0):  # a pipe's own other pieces
        use = (me["piece"] != j) & ~me["near_cut"]
        own = me["wall_piece"] == j
        d = np.full((n, n_angles), np.inf)
        d[use] = _tube_distance(pts[use].reshape(-1, 3), cKDTree(me["centre"][own]), me["r"][own],
                                2.0 * me["reach"]).reshape(-1, n_angles)
        dists.append(d)
    if not dists:
        return np.full((n, n_angles), cap), np.zeros(n_angles, int)
    dd = np.stack(dists)  # (Q, n, K)
    union = dd.min(axis=0)  # signed distance to the union of the other tubes
    mag = np.sort(np.abs(dd), axis=0)
    m1 = mag[0]
    m2 = mag[1] if len(dd) > 1 else np.full_like(m1, np.inf)
    h = _SEAM_STEP_MM
    flip = (union[1:] < 0) != (union[:-1] < 0)
    at_wall = (union < 0) & (union >= -h)
    at_wall[1:] |= flip
    at_wall[:-1] |= flip
    clear = np.where(inside_stranger, 0.0, np.where(union < -h, np.inf, np.where(at_wall, m2, m1)))
    with np.errstate(invalid="ignore"):  # how steeply the seam meets the wall (sine of the angle)
        slope = np.abs(np.gradient(np.where(np.isfinite(union), union, 1e3), h, axis=0))
    clear = np.where(at_wall, np.minimum(clear, cap * np.minimum(slope / 0.5, 1.0)), clear)
    if placed is not None and at_wall.any():
        clear[at_wall] = np.minimum(clear[at_wall], placed.query(pts[at_wall], distance_upper_bound=cap)[0])
    if me["pieces"] > 1:  # its seam on one piece against its own seam on the others
        for k in np.flatnonzero(at_wall.any(axis=0)):
            for j in range(me["pieces"]):
                hit = np.flatnonzero(at_wall[:, k] & (me["piece"] == j))
                rest = pts[me["piece"] != j, k]
                if len(hit) and len(rest):
                    ds = cKDTree(rest).query(pts[hit, k], distance_upper_bound=cap)[0]
                    clear[hit, k] = np.minimum(clear[hit, k], ds)
    return clear, np.count_nonzero(flip, axis=0)


def tube_stations(spine: interpolate.BSpline, radius: Any, station_step_mm: float = 2.0,
                  v_range: tuple[float, float] | None = None, tol_mm: float = SECTION_TOL_MM,
                  seam_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Station parameters and the (m, 9, 3) circle poles of a tube.

    Stations start evenly spaced (at most ``station_step_mm`` apart); where the
    cubic interpolation of the poles between two stations strays more than
    ``tol_mm`` from the exact section halfway between them (a tight bend, a
    quickly changing radius) a station is added there, until none does. As the
    weights are the same along V, a pole deviation bounds the wall's.

    Parameters
    ----------
    spine : scipy.interpolate.BSpline
        3D centreline, parameter = arc length (mm).
    radius : scipy.interpolate.BSpline or callable
        Radius (mm) as a function of the spine parameter.
    station_step_mm : float
        Largest spacing of the exact circular sections.
    v_range : (float, float), optional
        Part of the spine to sweep; default its whole domain.
    tol_mm : float
        Largest distance between the wall and the exact section midway between stations.
    seam_deg : float
        Where the seam (U = 0) lies around the vessel: degrees from the
        rotation-minimizing frame's first normal (see :func:`seam_angles`).
    """
    if not (isinstance(seam_deg, int | float) and np.isfinite(seam_deg)):
        raise GeometryError(f"tube: seam_deg must be a finite number, got {seam_deg!r}")
    for name, value in (("station_step_mm", station_step_mm), ("tol_mm", tol_mm)):
        if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
            raise GeometryError(f"tube: {name} must be a positive number, got {value!r}")
    k = spine.k
    v0, v1 = v_range if v_range is not None else (float(spine.t[k]), float(spine.t[-k - 1]))
    length = v1 - v0
    if not length > 0:
        raise GeometryError(f"tube: empty spine range ({v0}, {v1})")
    n_st = max(int(np.ceil(length / station_step_mm)) + 1, 4)
    v = np.linspace(v0, v1, n_st)
    # the frame is propagated on a dense grid so the reflections stay accurate
    grid, grid_normals = _frames(spine, v0, v1, min(station_step_mm / 4.0, _FRAME_STEP_MM), seam_deg)
    poles = _section_poles(spine, radius, v, grid, grid_normals)
    for _ in range(_MAX_REFINE):
        mid = 0.5 * (v[1:] + v[:-1])
        track = interpolate.make_interp_spline(v, poles.reshape(len(v), -1), k=3)
        exact = _section_poles(spine, radius, mid, grid, grid_normals)
        dev = np.linalg.norm(track(mid).reshape(-1, 9, 3) - exact, axis=2).max(axis=1)
        bad = (dev > tol_mm) & (np.diff(v) > 2.0 * _MIN_STATION_GAP_MM)
        if not bad.any():
            break
        order = np.argsort(np.r_[v, mid[bad]])
        v = np.r_[v, mid[bad]][order]
        poles = np.concatenate([poles, exact[bad]])[order]
    return v, poles


def tube_surface(spine: interpolate.BSpline, radius: interpolate.BSpline | np.ndarray,
                 station_step_mm: float = 2.0, v_range: tuple[float, float] | None = None,
                 seam_deg: float = 0.0) -> Geom_BSplineSurface:
    """The wall of a variable-radius pipe as a rational degree (2, 3) ``Geom_BSplineSurface``.

    U in [0, 4] runs once around the vessel (outward normal), V is the spine parameter;
    the seam (U = 0) lies ``seam_deg`` from the rotation-minimizing frame's normal.
    See :func:`tube_stations` for the arguments.
    """
    v, poles = tube_stations(spine, radius, station_step_mm, v_range, seam_deg=seam_deg)
    track = interpolate.make_interp_spline(v, poles.reshape(len(v), -1), k=3)
    cp = np.asarray(track.c).reshape(-1, 9, 3)
    n_v = cp.shape[0]
    arr = TColgp_Array2OfPnt(1, 9, 1, n_v)
    w = TColStd_Array2OfReal(1, 9, 1, n_v)
    for j in range(n_v):
        for i in range(9):
            arr.SetValue(i + 1, j + 1, gp_Pnt(*map(float, cp[j, i])))
            w.SetValue(i + 1, j + 1, float(_WEIGHTS[i]))
    vk, vm = knots_and_mults(track.t)
    return Geom_BSplineSurface(arr, w, _real_array(_U_KNOTS), _real_array(vk), _int_array(_U_MULTS),
                               _int_array(vm), 2, 3)


#: Largest tilt (degrees) of an end dome's pole from its tip: the pole stays well inside the rim.
DOME_MAX_TILT_DEG = 60.0
#: Tilt (degrees) of the pole of an end dome from its tip where the edge of a child's opening
#: passes near the tip (None: always at the tip, as before 2026-12-07).
DOME_TILT_DEG: float | None = 45.0
#: An end dome's pole stays at its tip unless the edge of a child's opening passes within this
#: angle (degrees, seen from the dome's centre) of it.
DOME_POLE_CLEARANCE_DEG = 15.0


def dome_openings(centre: np.ndarray, radius: float,
                  children: list[tuple[interpolate.BSpline, interpolate.BSpline]]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where the children leave through a vessel's end dome, roughly.

    Each child's opening is taken as the circle round the direction (from
    ``centre``) in which its axis leaves the sphere of ``radius``, of angular
    radius arcsin(r / ``radius``), r the child's radius there.

    Parameters
    ----------
    centre : (3,) array
        The dome's centre (the parent's end point).
    radius : float
        The dome's radius (mm).
    children : list of (spine, radius law)
        The vessels that start inside the parent (arc-length parameter).

    Returns
    -------
    directions : (n, 3) array
        Unit directions of the openings' centres (children that never leave the
        sphere, or start outside it, are left out).
    angles : (n,) array
        Their angular radii (radians).
    """
    c = np.asarray(centre, float)
    exits, rho = [], []
    for spine, law in children:
        a, b = float(spine.t[spine.k]), float(spine.t[-spine.k - 1])
        s = np.linspace(a, b, max(int((b - a) / 0.05), 2) + 1)
        d = np.linalg.norm(spine(s) - c, axis=1)
        out = np.flatnonzero(d >= radius)
        if not len(out) or out[0] == 0:
            continue
        p = spine(s[out[0]]) - c
        exits.append(p / np.linalg.norm(p))
        rho.append(np.arcsin(min(float(np.ravel(law(s[out[0]]))[0]) / radius, 1.0)))
    return np.array(exits, float).reshape(-1, 3), np.array(rho, float)


def dome_pole(tangent: np.ndarray, seam: np.ndarray,
              openings: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """The direction of an end dome's pole (the sphere's singular point).

    Children that start at a vessel's end leave through its dome near the tip,
    where the pole would be, and OCCT's booleans and mesher fail where the edge
    of a child's opening passes through the pole (the union in pieces, a child
    lost; a triangulation folded over itself). Where the edge of an opening
    (``openings``, :func:`dome_openings`) passes within
    :data:`DOME_POLE_CLEARANCE_DEG` of the tip, the pole is tilted
    :data:`DOME_TILT_DEG` from it, across the wall's seam (towards ``tangent``
    x ``seam`` or its opposite: the sphere's seam then runs from the wall's
    seam point over the dome), to the side whose smallest angle to the edge of
    any opening is larger.

    Parameters
    ----------
    tangent : (3,) array
        The vessel's unit tangent at its end (the dome's tip).
    seam : (3,) array
        Unit direction of the wall's seam point on the dome's rim (normal to ``tangent``).
    openings : (directions, angles) or None

    Returns
    -------
    (3,) array
        Unit direction of the pole (``tangent`` without openings, or with
        ``DOME_TILT_DEG = None``).
    """
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    if DOME_TILT_DEG is None or openings is None or not len(openings[0]):
        return t
    side = np.cross(t, np.asarray(seam, float))
    side /= np.linalg.norm(side)
    tilt = np.radians(min(float(DOME_TILT_DEG), DOME_MAX_TILT_DEG))
    cand = np.array([t, np.cos(tilt) * t + np.sin(tilt) * side, np.cos(tilt) * t - np.sin(tilt) * side])
    ang = np.arccos(np.clip(cand @ np.asarray(openings[0], float).T, -1.0, 1.0))
    clearance = np.degrees(np.abs(ang - np.asarray(openings[1], float)[None, :]).min(axis=1))
    if clearance[0] >= DOME_POLE_CLEARANCE_DEG:
        return t  # no opening's edge near the tip
    return cand[1 + int(clearance[2] > clearance[1])]


def dome_face(wall: Geom_BSplineSurface, centre: np.ndarray, tangent: np.ndarray, radius: float,
              v: float | None = None, openings: tuple[np.ndarray, np.ndarray] | None = None
              ) -> TopoDS_Face:
    """A hemisphere that closes a tube wall at its end, as a face on an exact ``Geom_SphericalSurface``.

    Its rim is the wall's end section (an exact circle of ``radius`` around
    ``centre`` in the plane normal to ``tangent``) and its seam starts where the
    wall's does, so the two sew into one shell; it meets the wall
    tangent-continuously. (A rational B-spline hemisphere is as exact, but
    OCCT's mesher leaves a hole at its collapsed pole row.)

    Parameters
    ----------
    wall : Geom_BSplineSurface
        A wall made by :func:`tube_surface`.
    centre, tangent : (3,) arrays
        The spine's end point and unit tangent there (pointing out of the tube).
    radius : float
        The section's radius (mm).
    v : float, optional
        The wall parameter of the section (default: the wall's last V).
    openings : (directions, angles), optional
        Where children leave through the dome (:func:`dome_openings`): the
        sphere's pole, its parametrization's singular point, is then tilted
        away from the tip (:func:`dome_pole`), and the sphere's seam runs from
        the wall's seam point to it. Default: the pole at the tip.
    """
    _u0, _u1, _v0, v1 = wall.Bounds()
    p = wall.Value(0.0, v1 if v is None else float(v))
    seam = np.array([p.X(), p.Y(), p.Z()]) - np.asarray(centre, float)
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    seam -= (seam @ t) * t
    seam /= np.linalg.norm(seam)
    z = dome_pole(t, seam, openings)
    tilt = float(np.degrees(np.arccos(np.clip(z @ t, -1.0, 1.0))))
    if tilt < 1e-6:
        axes = gp_Ax3(gp_Pnt(*map(float, centre)), gp_Dir(*map(float, t)), gp_Dir(*map(float, seam)))
        sphere = gp_Sphere(axes, float(radius))
        return BRepBuilderAPI_MakeFace(sphere, 0.0, 2.0 * np.pi, 0.0, 0.5 * np.pi).Face()
    # the sphere's meridian U = 0 through the wall's seam point; the face bounded by the rim circle
    x = seam - (seam @ z) * z
    x /= np.linalg.norm(x)
    c = gp_Pnt(*map(float, centre))
    axes = gp_Ax3(c, gp_Dir(*map(float, z)), gp_Dir(*map(float, x)))
    if float(np.cross(t, seam) @ z) < 0.0:  # tilted the other way: the parameters turn the other way too
        axes.YReverse()
    surface = Geom_SphericalSurface(axes, float(radius))
    rim = BRepBuilderAPI_MakeEdge(gp_Circ(gp_Ax2(c, gp_Dir(*map(float, t)), gp_Dir(*map(float, seam))),
                                          float(radius))).Edge()
    wire = BRepBuilderAPI_MakeWire(rim).Wire()
    tip = BRepBuilderAPI_MakeVertex(gp_Pnt(*map(float, np.asarray(centre, float) + radius * t))).Vertex()
    for w in (wire, TopoDS.Wire_s(wire.Reversed())):  # the side that holds the tip
        fix = ShapeFix_Face(BRepBuilderAPI_MakeFace(surface, w, True).Face())
        fix.Perform()
        face = fix.Face()
        if BRepExtrema_DistShapeShape(tip, face).Value() < 1e-7:
            return face
    raise GeometryError("dome_face: no hemisphere on the tilted sphere")


def _boundary_circles(face: TopoDS_Face) -> list:
    """The two closed V-boundary edges of a tube wall (the seam is skipped)."""
    out = []
    ex = TopExp_Explorer(face, TopAbs_EDGE)
    seen = []
    while ex.More():
        e = TopoDS.Edge_s(ex.Current())
        if not BRep_Tool.IsClosed_s(e, face) and not any(e.IsSame(s) for s in seen):
            seen.append(e)
            out.append(e)
        ex.Next()
    return out


def _oriented_solid(shell: TopoDS_Shell) -> TopoDS_Shape:
    """A solid bounded by ``shell``, its faces oriented outward by ``ShapeFix_Solid``."""
    solid = TopoDS_Solid()
    builder = BRep_Builder()
    builder.MakeSolid(solid)
    builder.Add(solid, shell)
    fix = ShapeFix_Solid(solid)
    fix.Perform()
    return fix.Solid()


def tube_solid(surface: Geom_BSplineSurface, v_range: tuple[float, float] | None = None,
               end_dome: tuple[np.ndarray, np.ndarray, float] | None = None
               ) -> tuple[TopoDS_Solid, TopoDS_Face, TopoDS_Face, TopoDS_Face]:
    """Close a tube wall with two planar caps (or a planar start and a dome at the end).

    Parameters
    ----------
    surface : Geom_BSplineSurface
        A wall made by :func:`tube_surface`.
    v_range : (float, float), optional
        Part of the wall to close (V = spine parameter); default all of it.
    end_dome : (centre, tangent, radius[, openings]), optional
        Close the end with the hemisphere of :func:`dome_face` instead of
        a disc (the spine's end point, its unit tangent, the end radius and
        optionally where children leave through it).

    Returns
    -------
    solid : TopoDS_Solid
    wall, start_cap, end_cap : TopoDS_Face
        The faces of the solid (the caps at V = first and last parameter).
    """
    u0, u1, v0, v1 = surface.Bounds()
    if v_range is not None:
        if not v0 <= v_range[0] < v_range[1] <= v1:
            raise GeometryError(f"tube: v_range {v_range} is not inside the wall's ({v0}, {v1})")
        v0, v1 = map(float, v_range)
    wall = BRepBuilderAPI_MakeFace(surface, u0, u1, v0, v1, TUBE_TOL_MM).Face()
    circles = _boundary_circles(wall)
    if len(circles) != 2:
        raise GeometryError(f"tube: expected two boundary circles on the wall, found {len(circles)}")

    def first_param(edge):
        p = BRep_Tool.Pnt_s(TopExp.FirstVertex_s(edge))
        q = surface.Value(0.0, v0)
        return (p.X() - q.X()) ** 2 + (p.Y() - q.Y()) ** 2 + (p.Z() - q.Z()) ** 2

    circles.sort(key=first_param)  # the start circle (V = v0) first
    caps = []
    for e in circles:
        mk = BRepBuilderAPI_MakeFace(BRepBuilderAPI_MakeWire(e).Wire(), True)
        if not mk.IsDone():
            raise GeometryError("tube: the end section is not planar")
        caps.append(mk.Face())
    fixed = None
    if end_dome is not None:
        centre, tangent, r_end, *openings = end_dome
        caps[1] = dome_face(surface, centre, tangent, r_end, v=v1, openings=openings[0] if openings else None)
    else:
        shell = TopoDS_Shell()
        builder = BRep_Builder()
        builder.MakeShell(shell)
        for f in (wall, *caps):
            builder.Add(shell, f)
        fixed = _oriented_solid(shell)
    if fixed is None or not is_valid(fixed):
        # Fall back to sewing (re-creates shared edges within tolerance).
        sew = BRepBuilderAPI_Sewing(1e-5)
        for f in (wall, *caps):
            sew.Add(f)
        sew.Perform()
        ex = TopExp_Explorer(sew.SewedShape(), TopAbs_SHELL)
        if not ex.More():
            raise GeometryError("tube: could not close the wall into a shell")
        fixed = _oriented_solid(TopoDS.Shell_s(ex.Current()))
        if not is_valid(fixed):
            raise GeometryError("tube: the closed pipe is not a valid solid")
        wall, *caps = (TopoDS.Face_s(sew.Modified(f)) for f in (wall, *caps))  # the faces as sewn
    return TopoDS.Solid_s(fixed), wall, caps[0], caps[1]


def branch_pipe(branch_id: int, name: str, parent: int | None, spine: interpolate.BSpline,
                radius: interpolate.BSpline, station_step_mm: float = 2.0,
                cuts: tuple[float, ...] | list[float] = (), end: str = "flat",
                seam_deg: float = 0.0, neck_mm: float = 0.0,
                dome_openings: tuple[np.ndarray, np.ndarray] | None = None) -> BranchPipe:
    """The closed pipe of one branch (see :func:`tube_surface`) with its end data.

    Parameters
    ----------
    branch_id, name, parent
        Identify the branch (carried into the fused solid's face names).
    spine : scipy.interpolate.BSpline
        Clamped cubic 3D centreline, parameter = arc length (mm).
    radius : scipy.interpolate.BSpline
        Radius law over the same parameter (mm).
    station_step_mm : float
        Largest spacing of the exact circular sections.
    cuts : sequence of float
        Spine parameters (mm) where to cut a pipe that comes back near itself
        (``VesselTree.pipe_specs`` finds them): the pieces are trimmed from
        copies of one wall surface, so neighbours share their cut circle
        exactly, and are fused into the branch's solid.
    end : {'flat', 'dome'}
        How the pipe is closed at its end: a disc (an open end of the vessel:
        an outlet), or a hemisphere (a vessel whose children start at its end:
        no disc is left there to meet their walls at a knife-edge).
    seam_deg : float
        Where the wall's seam lies around the vessel (degrees from the
        rotation-minimizing frame's first normal); :func:`seam_angles` keeps
        it clear of the other vessels' walls.
    neck_mm : float
        Length of the pipe's start that lies inside its parent necked down
        (``VesselTree.pipe_specs``: a child starting at its parent's end): the
        pipe's ``start_radius`` and its probe points are taken from there on.
    dome_openings : (directions, angles), optional
        Where children leave through the end dome (:func:`dome_openings`;
        :func:`dome_face` tilts the sphere's pole away from the tip then).

    Returns
    -------
    BranchPipe
    """
    if not station_step_mm > 0:
        raise GeometryError(f"station_step_mm: expected a positive number, got {station_step_mm!r}")
    if end not in ("flat", "dome"):
        raise GeometryError(f"end: expected 'flat' or 'dome', got {end!r}")
    k = spine.k
    a, b = float(spine.t[k]), float(spine.t[-k - 1])
    cuts = sorted(float(c) for c in cuts)
    if any(not a < c < b for c in cuts):
        raise GeometryError(f"branch {branch_id}: cuts {cuts} must lie inside the spine ({a:.3f}, {b:.3f})")
    surface = tube_surface(spine, radius, station_step_mm, seam_deg=seam_deg)
    d = spine.derivative()
    if not (isinstance(neck_mm, (int, float)) and 0.0 <= neck_mm < b - a):
        raise GeometryError(f"branch {branch_id}: neck_mm must lie in [0, {b - a:.3f}), got {neck_mm!r}")
    a_seen = a + float(neck_mm)  # where the pipe's own radius starts
    r0, r1 = float(np.ravel(radius(a_seen))[0]), float(np.ravel(radius(b))[0])
    t1 = d(b) / np.linalg.norm(d(b))
    dome = (spine(b), t1, r1, dome_openings) if end == "dome" else None
    if not cuts:
        solid, wall, cap0, cap1 = tube_solid(surface, end_dome=dome)
        walls: tuple[TopoDS_Face, ...] = (wall,)
        # Exact volume of a pipe with sections normal to its spine: integral of pi r^2 ds.
        u = np.linspace(a, b, max(int((b - a) / 0.1), 8) + 1)
        ds = np.linalg.norm(d(u), axis=1)
        area = np.pi * np.ravel(radius(u)) ** 2
        volume = float(np.sum(0.5 * (area[1:] * ds[1:] + area[:-1] * ds[:-1]) * np.diff(u)))
        if dome is not None:
            volume += 2.0 / 3.0 * np.pi * r1**3
    else:
        bounds = [a, *cuts, b]
        expected = None if PIECES_VOLUME_SLACK is None else _union_volume(spine, radius, bounds, dome)
        solid, walls, cap0, cap1, volume = _pieces(surface, bounds, branch_id, dome, expected)

    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.linalg.norm(v)

    # probe points on the axis, clear of the start (inside the parent) and the end cap
    lo, hi = a_seen + min(3.0 * r0, 0.5 * (b - a_seen)), b - min(r1, 0.25 * (b - a))
    at = np.linspace(lo, hi, 3) if hi > lo else np.full(3, 0.5 * (a + b))
    # round each probe, wall points (U, V = spine parameter) for the union's cheap check
    rings_uv = np.stack(np.broadcast_arrays(_RING_U[None, :], at[:, None]), axis=-1)
    rings = np.array([[surface.Value(float(u), float(v)).Coord() for u, v in ring] for ring in rings_uv])
    s_axis = np.linspace(a, b, max(int(np.ceil((b - a) / 0.25)), 2) + 1)
    return BranchPipe(branch_id, name, parent, solid, walls, cap0, cap1, spine(a), spine(b),
                      unit(d(a)), unit(d(b)), r0, r1, volume, spine(at), end, rings_uv, rings,
                      spine(s_axis), np.ravel(radius(s_axis)))


def _union_volume(spine: interpolate.BSpline, radius: interpolate.BSpline, bounds: list[float],
                  end_dome: tuple[np.ndarray, np.ndarray, float] | None = None) -> float:
    """Volume (mm^3) of the union of the tube pieces between consecutive ``bounds``
    (and the end dome), estimated independently of OCCT.

    Each piece's exact volume (the integral of pi r^2 along its spine) times the
    share of it that no earlier piece holds, from :data:`_UNION_SAMPLES` points
    drawn in it (spine parameter by section area, radius by the square root, the
    bend's Jacobian as weight; a fixed seed). A point lies in another piece where
    its nearest spine sample (every 0.02 mm at most) is nearer than that sample's
    radius, on the inner side of the piece's end planes.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    d1, d2 = spine.derivative(), spine.derivative(2)
    held: list[tuple[cKDTree, np.ndarray, np.ndarray, np.ndarray]] = []
    total = 0.0
    n = _UNION_SAMPLES
    for v0, v1 in zip(bounds[:-1], bounds[1:], strict=True):
        u = np.linspace(v0, v1, max(int(np.ceil((v1 - v0) / 0.02)), 8) + 1)
        c, r = spine(u), np.ravel(radius(u))
        du = d1(u)
        speed = np.linalg.norm(du, axis=1)
        t = du / np.maximum(speed, 1e-12)[:, None]
        area = np.pi * r**2 * speed
        cdf = np.r_[0.0, np.cumsum(0.5 * (area[1:] + area[:-1]) * np.diff(u))]
        vol = float(cdf[-1])
        # points drawn in the piece: parameter by section area, then a point of that disc
        at = np.interp(rng.uniform(0.0, vol, n), cdf, u)
        pc, pt = spine(at), d1(at)
        sp = np.maximum(np.linalg.norm(pt, axis=1), 1e-12)
        pt /= sp[:, None]
        k = d2(at)
        curv = (k - np.sum(k * pt, axis=1)[:, None] * pt) / sp[:, None] ** 2  # curvature vector
        e1 = np.cross(pt, np.where(np.abs(pt[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        e2 = np.cross(pt, e1)
        ang = rng.uniform(0.0, 2 * np.pi, n)
        rho = np.ravel(radius(at)) * np.sqrt(rng.uniform(0.0, 1.0, n))
        off = rho[:, None] * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
        pts = pc + off
        w = 1.0 - np.sum(curv * off, axis=1)  # the sweep's Jacobian: denser inside a bend
        free = np.ones(n, bool)
        for tree, hc, hr, ht in held:
            free &= ~_in_piece(pts, tree, hc, hr, ht)
        total += vol * float(np.sum(w * free)) / float(np.sum(w))
        held.append((cKDTree(c), c, r, t))
    if end_dome is not None:
        centre, tangent = np.asarray(end_dome[0], float), np.asarray(end_dome[1], float)
        r1 = float(end_dome[2])
        q = rng.normal(size=(n, 3))
        q *= (r1 * rng.uniform(0.0, 1.0, n) ** (1.0 / 3.0) / np.linalg.norm(q, axis=1))[:, None]
        q[q @ tangent < 0] *= -1.0  # the half ball beyond the end
        pts = centre + q
        free = np.ones(n, bool)
        for tree, hc, hr, ht in held[:-1]:  # the last piece ends at the dome's flat side
            free &= ~_in_piece(pts, tree, hc, hr, ht)
        total += 2.0 / 3.0 * np.pi * r1**3 * float(np.mean(free))
    return total


def _in_piece(points: np.ndarray, tree: Any, centres: np.ndarray, radii: np.ndarray,
              tangents: np.ndarray) -> np.ndarray:
    """Which ``points`` lie in a tube piece given by its spine samples (see :func:`_union_volume`)."""
    return _axis_sdf(tree, centres, radii, points, tangents[0], tangents[-1]) < 0.0


def _pieces(surface: Geom_BSplineSurface, bounds: list[float], branch_id: int,
            end_dome: tuple[np.ndarray, np.ndarray, float] | None = None, expected: float | None = None
            ) -> tuple[TopoDS_Solid, tuple[TopoDS_Face, ...], TopoDS_Face, TopoDS_Face, float]:
    """Union of the pieces of a tube wall between consecutive ``bounds``, with its
    wall faces, its two end caps and its volume (checked against ``expected``, the
    volume of the union of the pieces' tubes, if given: see :data:`PIECES_VOLUME_SLACK`)."""
    # Each piece gets its own copy of the surface: OCCT takes faces on one surface
    # object for the same domain and would not intersect the pieces where they cross.
    parts = [tube_solid(surface.Copy(), (v0, v1), end_dome if v1 == bounds[-1] else None)
             for v0, v1 in zip(bounds[:-1], bounds[1:], strict=True)]
    try:
        op = _general_fuse([p[0] for p in parts], FUZZY_MM, timeout_s=_solid.STEP_FUSE_TIMEOUT_S)
    except TimeoutError:
        raise GeometryError(f"branch {branch_id}: OCCT's union of the {len(parts)} pieces of a pipe that "
                            f"overlaps itself did not finish within {_solid.STEP_FUSE_TIMEOUT_S:g} s"
                            ) from None
    shape = op.Shape() if op is not None else None
    solids = _subshapes(shape, TopAbs_SOLID) if shape is not None else []
    if len(solids) != 1 or not is_valid(solids[0]):
        raise GeometryError(f"branch {branch_id}: the {len(parts)} pieces of a pipe that overlaps itself "
                            f"did not fuse into one valid solid")
    history = _History()
    history.ops.append(op)
    faces = {hash(f): f for f in _subshapes(solids[0], TopAbs_FACE)}

    def kept(face: TopoDS_Face) -> list[TopoDS_Face]:
        return [TopoDS.Face_s(faces[hash(f)]) for f in history.images(face)
                if hash(f) in faces and faces[hash(f)].IsSame(f)]

    # OCCT can return one valid solid that is not the union (a vessel that doubles back
    # along itself, its two walls a few hundredths of a mm apart: rca 2104 lost its second
    # piece; a hairpin of one radius kept both walls, uncut, and the volume of both legs)
    volume = _quick_volume(solids[0])
    if expected is not None:
        lost = [k + 1 for k, p in enumerate(parts) if not kept(p[1])]
        if lost:
            raise GeometryError(f"branch {branch_id}: OCCT's union of the pieces of a pipe that overlaps "
                                f"itself lost piece {', '.join(map(str, lost))} of {len(parts)}")
        if abs(volume - expected) > float(PIECES_VOLUME_SLACK) * expected:
            raise GeometryError(f"branch {branch_id}: OCCT's union of the pieces of a pipe that overlaps "
                                f"itself holds {volume:.2f} mm^3, not the {expected:.2f} mm^3 of their tubes")
    walls: list[TopoDS_Face] = []
    for f in (f for p in parts for f in kept(p[1])):
        if not any(f.IsSame(w) for w in walls):
            walls.append(f)
    caps = []
    for cap in (parts[0][2], parts[-1][3]):
        images = kept(cap)
        if not images and op.IsDeleted(cap):
            # the vessel ends inside itself (a distal end that comes back onto its own
            # wall): no end face is left there; the original face stands for it (no
            # face of the solid is tagged with it, so the end is no outlet)
            images = [cap]
        caps.append(images)
    if not walls or any(len(c) != 1 for c in caps):
        raise GeometryError(f"branch {branch_id}: the union of the pieces of a pipe that overlaps itself "
                            f"lost its wall or split an end face")
    return TopoDS.Solid_s(solids[0]), tuple(walls), caps[0][0], caps[1][0], volume
