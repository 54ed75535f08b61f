"""Knife-edge creases of a fused vessel tree, and rounding them with OCCT fillets.

Where a vessel leaves its parent at a shallow angle, the two walls meet along
the junction curve at a sharp *crease*: seen from the tissue, a thin wedge of
a few tens of degrees between the two lumens (the carina). The fused solid is
right to have it, but boundary-layer prisms extruded from both walls into the
fluid cannot follow it: every wall node gets one extrusion direction, and the
prism at the crease node is squeezed to a scaled Jacobian of about sin(a/2)
for a wedge of angle a (docs/cfd.md). Real carinas are round. Rolling a ball
of radius rho along such a junction edge (``BRepFilletAPI_MakeFillet``; the
edge is concave seen from the fluid, so the fillet adds fluid) replaces the
crease by a tube-like blend tangent to both walls, and the layers fan around it.

The wedge angle along an edge is measured from the outward normals of its two
faces at samples of the edge (through the edge's p-curves, so no projection):
a = 180 deg - angle(n1, n2). It equals the angle at which a thin vessel leaves
its parent at the crease (tests/test_creases.py checks that on an exact
branch).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Curve2d
from OCP.BRepFilletAPI import BRepFilletAPI_MakeFillet
from OCP.BRepGProp import BRepGProp_Face
from OCP.GCPnts import GCPnts_AbscissaPoint
from OCP.gp import gp_Pnt, gp_Vec
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SOLID
from OCP.TopExp import TopExp
from OCP.TopoDS import TopoDS, TopoDS_Edge, TopoDS_Face
from OCP.TopTools import TopTools_IndexedDataMapOfShapeListOfShape

from ..errors import ArgumentError
from .nurbs import is_valid

if TYPE_CHECKING:
    from .solid import FaceTag, VesselSolid

__all__ = ["Crease", "find_creases", "round_creases", "CREASE_ANGLE_DEG", "CREASE_RADIUS_FRACTION"]

#: Junction edges whose tissue wedge gets sharper than this somewhere are rounded (deg).
CREASE_ANGLE_DEG = 45.0
#: Fillet radius as a share of the thinner vessel's radius at the crease.
CREASE_RADIUS_FRACTION = 0.1
_SAMPLES = 24  # samples per edge for the wedge angle, at least ...
_SAMPLE_STEP_MM = 0.1  # ... and one every this much of its length
_MAX_VOLUME_SHARE = 0.005  # a fillet that changes the volume more than this went wrong


@dataclass(repr=False)
class Crease:
    """One junction edge of a fused solid and how sharp it gets.

    Attributes
    ----------
    edge : TopoDS_Edge
    faces : (TopoDS_Face, TopoDS_Face)
        The two walls meeting there (the thinner vessel's first).
    branches : (int, int)
        Their branches (thinner one first).
    angle_deg : float
        Smallest tissue wedge angle along the edge (180 deg: the walls are tangent).
    point : (3,) ndarray
        Where it is smallest (mm).
    radius_mm : float
        Radius of the thinner vessel there.
    """

    edge: TopoDS_Edge
    faces: tuple[TopoDS_Face, TopoDS_Face]
    branches: tuple[int, int]
    angle_deg: float
    point: np.ndarray
    radius_mm: float

    def __repr__(self) -> str:
        x, y, z = self.point
        return (f"Crease(branches={self.branches}, angle_deg={self.angle_deg:.1f}, "
                f"at=({x:.2f}, {y:.2f}, {z:.2f}), radius_mm={self.radius_mm:.3f})")


def _normal(face: BRepGProp_Face, u: float, v: float) -> np.ndarray:
    """Outward unit normal of a face of a solid at (u, v) (the face's orientation applied)."""
    p, n = gp_Pnt(), gp_Vec()
    face.Normal(u, v, p, n)
    out = np.array([n.X(), n.Y(), n.Z()])
    return out / max(float(np.linalg.norm(out)), 1e-300)


def _wedge(edge: TopoDS_Edge, f1: TopoDS_Face, f2: TopoDS_Face) -> tuple[float, np.ndarray]:
    """Smallest tissue wedge angle (deg) along an edge shared by two faces, and where.

    Sampled at least ``_SAMPLES`` times and every ``_SAMPLE_STEP_MM`` of the edge (a
    whole junction loop is one edge when no seam crosses it), then refined around the
    smallest sample (bounded scalar search).
    """
    from scipy.optimize import minimize_scalar

    c3 = BRepAdaptor_Curve(edge)
    c1, c2 = BRepAdaptor_Curve2d(edge, f1), BRepAdaptor_Curve2d(edge, f2)
    g1, g2 = BRepGProp_Face(f1), BRepGProp_Face(f2)  # once per edge, not per sample

    def angle(t: float) -> float:
        uv1, uv2 = c1.Value(float(t)), c2.Value(float(t))
        n1, n2 = _normal(g1, uv1.X(), uv1.Y()), _normal(g2, uv2.X(), uv2.Y())
        return 180.0 - float(np.degrees(np.arccos(np.clip(n1 @ n2, -1.0, 1.0))))

    t0, t1 = c3.FirstParameter(), c3.LastParameter()
    n = max(_SAMPLES, int(np.ceil(GCPnts_AbscissaPoint.Length_s(c3) / _SAMPLE_STEP_MM)) + 1)
    ts = np.linspace(t0, t1, n)
    values = np.array([angle(t) for t in ts])
    k = int(np.argmin(values))
    best, t_best = float(values[k]), float(ts[k])
    lo, hi = ts[max(k - 1, 0)], ts[min(k + 1, n - 1)]
    if hi > lo:
        res = minimize_scalar(angle, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6 * (t1 - t0)})
        if res.fun < best:
            best, t_best = float(res.fun), float(res.x)
    p = c3.Value(t_best)
    return best, np.array([p.X(), p.Y(), p.Z()])


def _radius_lookup(solid: VesselSolid) -> Any:
    """``f(branch_id, point) -> radius`` of a branch's vessel at its axis point nearest ``point``."""
    samples: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for s in solid.specs:
        spine, radius = s["spine"], s["radius"]
        k = spine.k
        a, b = float(spine.t[k]), float(spine.t[-k - 1])
        u = np.linspace(a, b, max(int((b - a) / 0.1), 2) + 1)
        samples[int(s["id"])] = (np.asarray(spine(u)), np.ravel(radius(u)))
    pipes = {p.branch_id: p for p in solid.pipes}

    def lookup(branch: int, point: np.ndarray) -> float:
        if branch in samples:
            xyz, r = samples[branch]
            return float(r[np.argmin(np.sum((xyz - point) ** 2, axis=1))])
        p = pipes[branch]
        return float(min(p.start_radius, p.end_radius))

    return lookup


def find_creases(solid: VesselSolid, max_angle_deg: float = 180.0) -> list[Crease]:
    """Junction edges of a fused tree (walls of two branches meeting, or of two pieces of one
    branch that passes over itself), sharpest first.

    Parameters
    ----------
    solid : VesselSolid
    max_angle_deg : float
        Keep the edges whose smallest tissue wedge angle is below this.

    Returns
    -------
    list of Crease
    """
    if not (isinstance(max_angle_deg, int | float) and 0 < max_angle_deg <= 180):
        raise ArgumentError(f"max_angle_deg: expected a number in (0, 180], got {max_angle_deg!r}")
    tags = {hash(f): (f, t) for f, t in solid.faces}
    radius_at = _radius_lookup(solid)
    ancestors = TopTools_IndexedDataMapOfShapeListOfShape()
    TopExp.MapShapesAndAncestors_s(solid.shape, TopAbs_EDGE, TopAbs_FACE, ancestors)
    out = []
    for i in range(1, ancestors.Extent() + 1):
        edge = TopoDS.Edge_s(ancestors.FindKey(i))
        faces = [TopoDS.Face_s(f) for f in ancestors.FindFromIndex(i)]
        if len(faces) != 2 or faces[0].IsSame(faces[1]) or BRep_Tool.Degenerated_s(edge):
            continue
        tagged = [tags.get(hash(f)) for f in faces]
        if any(x is None or not x[0].IsSame(f) for x, f in zip(tagged, faces, strict=True)):
            continue
        t1, t2 = (x[1] for x in tagged if x is not None)
        # walls of two branches, or of two pieces of one branch that crosses itself (a vessel
        # that comes back over itself is swept in pieces; where the pieces join, the walls
        # are tangent and the wedge is 180 deg)
        if t1.role != "wall" or t2.role != "wall":
            continue
        angle, point = _wedge(edge, faces[0], faces[1])
        if angle >= max_angle_deg:
            continue
        r1, r2 = radius_at(t1.branch_id, point), radius_at(t2.branch_id, point)
        if r1 <= r2:
            out.append(Crease(edge, (faces[0], faces[1]), (t1.branch_id, t2.branch_id), angle, point, r1))
        else:
            out.append(Crease(edge, (faces[1], faces[0]), (t2.branch_id, t1.branch_id), angle, point, r2))
    out.sort(key=lambda c: c.angle_deg)
    return out


def _fillet(shape: Any, creases: list[Crease], fraction: float) -> tuple[Any, Any] | None:
    """The shape with these creases filleted, and the fillet operation; None if OCCT fails or
    gives an invalid solid or an implausible volume change."""
    from .solid import _count_solids, shape_volume

    op = BRepFilletAPI_MakeFillet(shape)
    for c in creases:
        op.Add(fraction * c.radius_mm, c.edge)
    try:
        op.Build()
    except Exception:  # OCCT raises Standard_Failure subclasses
        return None
    if not op.IsDone():
        return None
    out = op.Shape()
    if _count_solids(out) != 1 or not is_valid(out):
        return None
    before, after = shape_volume(shape), shape_volume(out)
    # the junction edges are concave seen from the fluid: a fillet adds a little fluid
    if not 0.0 < after - before < _MAX_VOLUME_SHARE * before:
        return None
    return out, op


def round_creases(solid: VesselSolid, max_angle_deg: float = CREASE_ANGLE_DEG,
                  radius_fraction: float = CREASE_RADIUS_FRACTION) -> VesselSolid:
    """The solid with its sharp junction creases rounded (see the module docstring).

    Parameters
    ----------
    solid : VesselSolid
    max_angle_deg : float
        Round the junction edges whose tissue wedge gets sharper than this.
    radius_fraction : float
        Fillet radius as a share of the thinner vessel's radius at the crease.

    Returns
    -------
    VesselSolid
        A new solid (``solid`` itself when no edge is that sharp). Every face
        keeps its tag; a fillet face is tagged ``wall`` of the thinner branch.
        ``warnings`` names what was rounded and any crease OCCT could not
        round (then left as it was: the rest is still rounded).
    """
    from .solid import FaceTag, VesselSolid, _subshapes

    if not (isinstance(radius_fraction, int | float) and 0 < radius_fraction < 1):
        raise ArgumentError(f"radius_fraction: expected a number in (0, 1), got {radius_fraction!r}")
    # Between two branches only: where a vessel passes over itself the crease is as sharp as
    # the crossing, and rounding it there made the prisms beside it worse (cs 3005: 0.099
    # against 0.126 with it kept; its 18 deg bound sin 9 deg = 0.16 is above the goal).
    creases = [c for c in find_creases(solid, max_angle_deg) if c.branches[0] != c.branches[1]]
    if not creases:
        return solid
    names = {p.branch_id: p.name for p in solid.pipes}
    done = _fillet(solid.shape, creases, radius_fraction)
    kept, skipped = list(creases), []
    if done is None:  # one edge at a time, sharpest first, keeping those OCCT can round together
        kept = []
        for c in creases:
            trial = _fillet(solid.shape, [*kept, c], radius_fraction)
            if trial is None:
                skipped.append(c)
            else:
                kept, done = [*kept, c], trial
    if done is None:
        notes = [f"could not round the {len(creases)} sharp junction creases (sharpest "
                 f"{creases[0].angle_deg:.0f} deg): left as they are"]
        return VesselSolid(solid.shape, list(solid.faces), solid.pipes, dict(solid.failed),
                           list(solid.warnings) + notes, dict(solid.timings_s), solid.specs,
                           dict(solid.extensions), union_warnings=list(solid.union_warnings))
    shape, op = done
    new = TopoDS.Solid_s(_subshapes(shape, TopAbs_SOLID)[0])
    images: dict[int, list[tuple[TopoDS_Face, FaceTag]]] = {}
    for f, t in solid.faces:
        for g in [f, *op.Modified(f)]:
            images.setdefault(hash(g), []).append((g, t))
    generated: dict[int, list[tuple[Any, FaceTag]]] = {}
    for c in kept:
        wall = FaceTag(c.branches[0], names.get(c.branches[0], str(c.branches[0])), "wall")
        for g in op.Generated(c.edge):
            generated.setdefault(hash(g), []).append((g, wall))
    faces = []
    for f in _subshapes(new, TopAbs_FACE):
        hit = [t for g, t in images.get(hash(f), []) + generated.get(hash(f), []) if g.IsSame(f)]
        if not hit:  # a fillet face OCCT did not report: the wall of the thinnest branch it touches
            hit = [FaceTag(kept[0].branches[0], names.get(kept[0].branches[0], "?"), "wall")]
        faces.append((TopoDS.Face_s(f), hit[0]))
    notes = ["rounded the junction crease of branches "
             + "; ".join(f"{c.branches[0]} ({names.get(c.branches[0], '?')}) and {c.branches[1]} "
                         f"({names.get(c.branches[1], '?')}), {c.angle_deg:.0f} deg, with a "
                         f"{radius_fraction * c.radius_mm:.3f} mm fillet" for c in kept)]
    notes += [f"could not round the {c.angle_deg:.0f} deg junction crease of branches {c.branches[0]} and "
              f"{c.branches[1]} at ({c.point[0]:.1f}, {c.point[1]:.1f}, {c.point[2]:.1f}) mm: left as it is"
              for c in skipped]
    return VesselSolid(new, faces, solid.pipes, dict(solid.failed), list(solid.warnings) + notes,
                       dict(solid.timings_s), solid.specs, dict(solid.extensions),
                       union_warnings=list(solid.union_warnings))
