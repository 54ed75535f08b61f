"""One fused vessel-tree solid: boolean union of the branch pipes, checks, export, interop.

:func:`fuse_pipes` unions the branch solids made by :mod:`.pipes` with OCCT's
general fuse (all arguments at once, parallel, oriented bounding boxes, a small
fuzzy value), takes back the branches it lost (added one by one, or a second
general fuse without them and then they one by one), falls back to pairwise
fusing in tree order when that fails, and leaves out (and reports) a branch
whose union fails or that does not touch the rest of the tree. The booleans run in a helper process
(:mod:`.fuse_worker`) with time limits (:data:`FUSE_TIMEOUT_S`,
:data:`STEP_FUSE_TIMEOUT_S`): a union OCCT takes minutes over falls back or
leaves its branch out, named. :class:`VesselSolid` keeps, for every face of the
result, the branch and the role (wall, inlet, outlet) it came from; the names
go into STEP, and the CFD mesher uses the caps.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.BRepAlgoAPI import BRepAlgoAPI_Check, BRepAlgoAPI_Fuse
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepClass3d import BRepClass3d_SolidClassifier
from OCP.BRepGProp import BRepGProp
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools, BRepTools_WireExplorer
from OCP.BRepTopAdaptor import BRepTopAdaptor_FClass2d
from OCP.GeomAbs import GeomAbs_Plane
from OCP.gp import gp_Pnt, gp_Pnt2d
from OCP.GProp import GProp_GProps
from OCP.IFSelect import IFSelect_RetDone
from OCP.Interface import Interface_Static
from OCP.Message import Message, Message_Gravity
from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds
from OCP.ShapeFix import ShapeFix_Shape
from OCP.ShapeUpgrade import ShapeUpgrade_ShapeDivideClosed, ShapeUpgrade_UnifySameDomain
from OCP.STEPConstruct import STEPConstruct
from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
from OCP.TCollection import TCollection_HAsciiString
from OCP.TopAbs import (
    TopAbs_EDGE,
    TopAbs_FACE,
    TopAbs_IN,
    TopAbs_ON,
    TopAbs_REVERSED,
    TopAbs_SOLID,
    TopAbs_WIRE,
)
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape, TopoDS_Solid
from OCP.TopTools import (
    TopTools_IndexedDataMapOfShapeListOfShape,
    TopTools_IndexedMapOfShape,
    TopTools_ListOfShape,
)

from ..errors import ArgumentError, GeometryError, OutputError, VesselcadWarning
from ..io.atomic import atomic_path
from .fuse_worker import FuseWorker
from .nurbs import is_valid

__all__ = ["BranchPipe", "FaceTag", "VesselSolid", "fuse_pipes", "shape_volume", "shape_area",
           "read_step", "read_brep"]

#: Fuzzy value of the boolean union (mm): absorbs round-off, far below any feature.
FUZZY_MM = 1e-5
#: Edges shorter than this (mm) are merged by :meth:`VesselSolid.without_short_edges`
#: (the CFD mesher's default): far below any element, above OCCT's round-off.
SHORT_EDGE_MM = 0.02
#: The default mesh deflection is the smallest pipe-end radius / 50, but not below
#: this radius / 50 (mm).
MESH_MIN_RADIUS_MM = 0.3
#: Holes of a triangulation whose rim is at most this many times the linear deflection long
#: are closed by a fan of triangles instead of meshing the solid again finer.
SMALL_HOLE_DEFLECTIONS = 10.0
#: A fold of one face's triangulation (edges in four triangles, the face's triangles lying
#: over each other: a hemispherical end cap meshed round its pole) is cut out and the hole
#: triangulated again where the triangles cut out span at most this (mm; None: never).
FOLD_REFILL_MM: float | None = 1.0
#: A triangulation whose enclosed volume falls short of the solid's by more than inscribed facets
#: can (``theta**2 / 4`` of facets turning by theta, the larger of the angular deflection's and
#: the linear deflection's on the thinnest vessel) plus this share is redone once through a
#: healed copy of the solid (and a divided one, below), and said if it stays so (about 2.8 % with
#: the default deflections).
MESH_VOLUME_TOLERANCE = 0.005
#: Where the healed copy's triangulation still falls short of the volume, the solid is meshed once
#: more through a copy whose closed faces (pipe walls, closed around the vessel at a seam) OCCT's
#: ``ShapeUpgrade_ShapeDivideClosed`` has cut this many times each (3: four open pieces): the
#: mesher covers a closed wall only in part where a child's opening crosses its seam (end-to-end
#: rca 2104 with true labels: 20 % of a 53 mm² wall), not an open piece. The best of the
#: triangulations tried is kept.
MESH_DIVIDE_CLOSED_POINTS = 3
#: Time limit (s) of OCCT's face unification after the union (normally ~0.2 s per
#: tree; it can loop forever, see :func:`_tidy`).
TIDY_TIMEOUT_S = 20.0
#: Seconds OCCT's general fuse of all branch pipes may take at most (None: unbounded, in this
#: process); a union that takes longer is abandoned for the branch-by-branch union. Below that
#: cap a tree of n pipes gets FUSE_TIMEOUT_BASE_S + n * FUSE_TIMEOUT_PER_PIPE_S (its fuse
#: normally takes 0.2-0.5 s a pipe on 2 cores: a tree that overruns this is hung on one junction).
FUSE_TIMEOUT_S: float | None = 60.0
FUSE_TIMEOUT_BASE_S = 20.0
FUSE_TIMEOUT_PER_PIPE_S = 2.0
#: Seconds one union of a single branch with the tree may take; a branch whose union takes longer
#: is left out (and named).
STEP_FUSE_TIMEOUT_S: float | None = 20.0
#: Seconds the helper process may take over a volume started by :meth:`VesselSolid._start_volume`
#: before the caller integrates it itself (normally 0.3-1.4 s).
VOLUME_TIMEOUT_S = 60.0
# the helper process of the bounded booleans: None until needed, False where it cannot run
_WORKER: FuseWorker | None | bool = None
#: Linear (mm) and angular (rad) deflection of the throwaway triangulation that
#: classifies probe points (:func:`_inside`; where it strays from the surface near
#: a point, the point is classified exactly).
PROBE_DEFLECTION_MM = 0.2
PROBE_ANGLE_RAD = 0.8
#: A union must hold at least this share of the volume of its largest argument
#: (a boolean that loses a part loses far more; the slack covers quick integration).
VOLUME_SLACK = 0.99


@dataclass
class BranchPipe:
    """One branch's closed pipe, ready to be fused.

    Attributes
    ----------
    branch_id : int
    name : str
    parent : int or None
    solid : TopoDS_Solid
    walls : tuple of TopoDS_Face
        The wall faces: one, or one per piece of a pipe that had to be swept in
        pieces because it comes back near itself (their union, not overlapping).
    start_cap, end_cap : TopoDS_Face
    start, end : (3,) arrays
        Spine end points (mm).
    start_tangent, end_tangent : (3,) arrays
        Unit spine tangents there (pointing along the vessel, proximal to distal).
    start_radius, end_radius : float
    tube_volume_mm3 : float
        Integral of pi r(s)^2 ds along the spine: the pipe's exact volume (sections
        normal to the spine); for a pipe in pieces, the volume of their union.
        Used to sanity-check booleans without integrating.
    probes : (k, 3) array, k <= 3
        Points on the spine: three start radii from the start (clear of the
        parent the pipe starts in), the middle, one end radius before the end.
        A union that holds the pipe holds them; checked after fusing. Only those
        OCCT classifies inside the pipe itself count (:meth:`trusted_probes`:
        not so near a thin, tightly bent start that the classification could
        not be trusted).
    end_shape : str
        ``'flat'`` (a disc closes the end) or ``'dome'`` (a hemisphere: the
        vessel's children start at its end, so its end is no outlet).
    rings_uv, rings : (k, m, 2) and (k, m, 3) arrays
        ``m`` points of the wall round each probe (wall parameters, positions):
        where no other vessel covers them, a union that holds the pipe keeps
        them on its boundary (:func:`_missing` checks this first; empty: not known).
    axis, axis_radius : (n, 3) and (n,) arrays
        The spine sampled densely (every 0.25 mm at most) and the radius there:
        the analytic tube, to tell which ring points other vessels cover.
    """

    branch_id: int
    name: str
    parent: int | None
    solid: TopoDS_Solid
    walls: tuple[TopoDS_Face, ...]
    start_cap: TopoDS_Face
    end_cap: TopoDS_Face
    start: np.ndarray
    end: np.ndarray
    start_tangent: np.ndarray
    end_tangent: np.ndarray
    start_radius: float
    end_radius: float
    tube_volume_mm3: float
    probes: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    end_shape: str = "flat"
    rings_uv: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 2)))
    rings: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 3)))
    axis: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    axis_radius: np.ndarray = field(default_factory=lambda: np.empty(0))
    _own: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _axis_tree: Any = field(default=None, init=False, repr=False, compare=False)

    @property
    def wall(self) -> TopoDS_Face:
        """The first (usually the only) wall face."""
        return self.walls[0]

    def trusted(self) -> np.ndarray:
        """Which :attr:`probes` OCCT classifies inside the pipe itself (bool per probe).

        Classified on first use only: a union that holds every probe needs no
        such check (on phantom trees this saves ~20 ms a pipe).
        """
        if self._own is None:
            self._own = _inside(self.solid, self.probes)
        return self._own

    def trusted_probes(self) -> np.ndarray:
        """The :attr:`probes` that :meth:`trusted` keeps."""
        return self.probes[self.trusted()]

    def tube_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) of ``points`` to the pipe's analytic tube,
        a capped tube round :attr:`axis`; +inf beyond 2 mm of it. From the nearest axis
        sample: within ~0.01 mm near the wall, up to half the sample spacing near the axis."""
        from scipy.spatial import cKDTree

        points = np.asarray(points, float).reshape(-1, 3)
        if not len(self.axis):
            return np.full(len(points), np.inf)
        if self._axis_tree is None:
            self._axis_tree = cKDTree(self.axis)
        return _axis_sdf(self._axis_tree, self.axis, self.axis_radius, points, self.start_tangent,
                         self.end_tangent if self.end_shape == "flat" else None,
                         float(self.axis_radius.max()) + 2.0)


def _axis_sdf(tree: Any, axis: np.ndarray, radius: np.ndarray, points: np.ndarray,
              start_tangent: np.ndarray, end_tangent: np.ndarray | None,
              reach: float = np.inf) -> np.ndarray:
    """Signed distance (mm, negative inside) of ``points`` to the tube round ``axis`` samples
    (their k-d ``tree``, their ``radius``), from the nearest sample; the planes of its flat
    ends bound it (at the end only where ``end_tangent`` is given: a dome is the last
    sample's sphere); +inf beyond ``reach`` of every sample."""
    dist, idx = tree.query(points, distance_upper_bound=reach)
    far = ~np.isfinite(dist)
    idx = np.where(far, 0, idx)
    sdf = np.where(far, np.inf, dist - radius[idx])
    start_cap = np.einsum("ij,j->i", axis[0] - points, start_tangent)
    sdf = np.where(idx == 0, np.maximum(sdf, start_cap), sdf)
    if end_tangent is not None:
        end_cap = np.einsum("ij,j->i", points - axis[-1], end_tangent)
        sdf = np.where(idx == len(axis) - 1, np.maximum(sdf, end_cap), sdf)
    return sdf


@dataclass(frozen=True)
class FaceTag:
    """What a face of the fused solid is: ``role`` in {'wall', 'inlet', 'outlet', 'cap'}."""

    branch_id: int
    name: str
    role: str


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence OCCT's console messenger (the STEP translator prints statistics)."""
    printers = Message.DefaultMessenger_s().Printers()
    saved = []
    for i in range(1, printers.Length() + 1):
        p = printers.Value(i)
        saved.append((p, p.GetTraceLevel()))
        p.SetTraceLevel(Message_Gravity.Message_Fail)
    try:
        yield
    finally:
        for p, level in saved:
            p.SetTraceLevel(level)


#: Relative accuracy of :func:`shape_volume` and :func:`shape_area` (OCCT's adaptive Gauss
#: integration). 1e-6 instead of 1e-7: 2.5x faster on a 17-branch tree (3.4 -> 1.4 s), the
#: volume 2.5e-7 and the area 7e-7 from the 1e-7 figures (docs/solids.md).
PROPS_EPS = 1e-6


def _props(shape: TopoDS_Shape, kind: str) -> GProp_GProps:
    g = GProp_GProps()
    if kind == "volume":
        BRepGProp.VolumeProperties_s(shape, g, PROPS_EPS, True)
    else:
        BRepGProp.SurfaceProperties_s(shape, g, PROPS_EPS)
    return g


def shape_volume(shape: TopoDS_Shape) -> float:
    """Volume (mm^3) by adaptive Gauss integration (relative accuracy :data:`PROPS_EPS`)."""
    return float(_props(shape, "volume").Mass())


def shape_area(shape: TopoDS_Shape) -> float:
    """Surface area (mm^2)."""
    return float(_props(shape, "area").Mass())


def edge_lengths(shape: TopoDS_Shape) -> list[float]:
    """Lengths (mm) of the distinct edges of a shape, degenerated ones (poles) left out."""
    edges = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(shape, TopAbs_EDGE, edges)
    out = []
    for i in range(1, edges.Extent() + 1):
        edge = TopoDS.Edge_s(edges.FindKey(i))
        if not BRep_Tool.Degenerated_s(edge):
            g = GProp_GProps()
            BRepGProp.LinearProperties_s(edge, g)
            out.append(float(g.Mass()))
    return out


def _subshapes(shape: TopoDS_Shape, kind: Any) -> list[TopoDS_Shape]:
    out = []
    ex = TopExp_Explorer(shape, kind)
    while ex.More():
        out.append(ex.Current())
        ex.Next()
    return out


def _count_solids(shape: TopoDS_Shape) -> int:
    return len(_subshapes(shape, TopAbs_SOLID))


def _first_solid(shape: TopoDS_Shape) -> TopoDS_Solid | None:
    solids = _subshapes(shape, TopAbs_SOLID)
    return TopoDS.Solid_s(solids[0]) if len(solids) == 1 else None


def _list(shapes: list[TopoDS_Shape]) -> TopTools_ListOfShape:
    out = TopTools_ListOfShape()
    for s in shapes:
        out.Append(s)
    return out


def _general_fuse(shapes: list[TopoDS_Shape], fuzzy: float, parallel: bool = True,
                  timeout_s: float | None = None) -> Any:
    """OCCT's general fuse of ``shapes`` (the first one the argument, the rest tools).

    With ``timeout_s``, it runs in the helper process of :mod:`.fuse_worker` and
    raises :class:`TimeoutError` when it takes longer (the helper is killed); the
    returned object then replays the face history (``Shape``, ``IsDeleted``,
    ``Modified``). Where no helper process can run, it runs here, unbounded.
    Returns None when OCCT reports failure.
    """
    global _WORKER
    worker = _worker() if timeout_s is not None else None
    if worker is not None:
        try:
            return worker.fuse(shapes, fuzzy, parallel, timeout_s)
        except TimeoutError:  # (an OSError too)
            raise
        except OSError:  # no helper process can run here: fuse in this process from now on
            _WORKER = False
    op = BRepAlgoAPI_Fuse()
    op.SetArguments(_list(shapes[:1]))
    op.SetTools(_list(shapes[1:]))
    op.SetFuzzyValue(fuzzy)
    op.SetRunParallel(parallel)
    op.SetUseOBB(True)
    op.SetToFillHistory(True)
    op.Build()
    return op if op.IsDone() else None


def start_fuse_worker() -> None:
    """Start the helper process that runs the booleans with a time limit (it takes about a
    second to import OCCT; :meth:`VesselTree.solid` starts it before building the pipes)."""
    global _WORKER
    worker = _worker() if FUSE_TIMEOUT_S is not None else None
    if worker is None:
        return
    try:
        worker.start()
    except OSError:
        _WORKER = False


def _worker() -> FuseWorker | None:
    """The helper of the bounded booleans (made on first use), None where it cannot run."""
    global _WORKER
    if _WORKER is None:
        _WORKER = FuseWorker()
    return _WORKER or None


class _History:
    """Face provenance through a chain of OCCT operations (input face -> result faces)."""

    def __init__(self) -> None:
        self.ops: list[Any] = []
        # a face that (re-)entered the chain as an argument of a later operation
        self.since: dict[int, int] = {}

    def images(self, face: TopoDS_Shape) -> list[TopoDS_Shape]:
        current = [face]
        for op in self.ops[self.since.get(hash(face), 0):]:
            nxt: list[TopoDS_Shape] = []
            for f in current:
                gone = op.IsDeleted(f) if hasattr(op, "IsDeleted") else op.IsRemoved(f)
                if gone:
                    continue
                mod = list(op.Modified(f))
                nxt.extend(mod if mod else [f])
            current = nxt
        return current


@dataclass(eq=False)
class VesselSolid:
    """A vessel tree as one OCCT solid.

    Attributes
    ----------
    shape : OCP.TopoDS.TopoDS_Solid
        The fused solid (B-spline walls, planar caps); drop to OCP with it.
    faces : list of (TopoDS_Face, FaceTag)
        Every face of ``shape`` with the branch and role it came from.
    pipes : list of BranchPipe
        The branch pipes that went into the union (before fusing).
    failed : dict of int -> str
        Branches left out, with the reason.
    warnings : list of str
    timings_s : dict of str -> float
    specs : list of dict
        The spines and radius laws the pipes were swept along (when made by
        ``VesselTree.solid``): ``{'id', 'name', 'parent', 'spine', 'radius', 'cuts', 'warnings'}``.
    extensions : dict of (int, str) -> float
        Flow extensions added by :meth:`with_flow_extensions`: length (mm) per
        ``(branch_id, 'inlet' | 'outlet')``.
    union_warnings : list of str
        What the boolean union itself reported (a fallback, a time limit; also in
        ``warnings``).
    """

    shape: TopoDS_Solid
    faces: list[tuple[TopoDS_Face, FaceTag]] = field(default_factory=list)
    pipes: list[BranchPipe] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    specs: list[dict[str, Any]] = field(default_factory=list, repr=False)
    extensions: dict[tuple[int, str], float] = field(default_factory=dict)
    union_warnings: list[str] = field(default_factory=list)
    _meshed: tuple[float, float, bool] | None = field(default=None, init=False, repr=False)
    _triangles: Any = field(default=None, init=False, repr=False)
    # the copy (shape, tagged faces) that meshes of the solid go through, once one needed it
    _healed: Any = field(default=None, init=False, repr=False)
    # which copy that is: 0 the solid itself, 1 healed, 2 closed faces divided
    _repair: int = field(default=0, init=False, repr=False)
    # volume, area and check() of ``shape``, computed once (a VesselSolid never changes its shape;
    # ``dataclasses.replace`` makes a new one with this empty)
    _measures: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    # ------------------------------------------------------------ measures
    @property
    def wrapped(self) -> TopoDS_Solid:
        """The OCCT shape (build123d's name for it)."""
        return self.shape

    @property
    def volume(self) -> float:
        """Volume in mm^3."""
        if "volume" not in self._measures:
            later = self._measures.pop("volume_later", None)
            v = later() if later is not None else None
            self._measures["volume"] = shape_volume(self.shape) if v is None else v
        return self._measures["volume"]

    def _start_volume(self) -> None:
        """Start integrating the volume in the booleans' helper process, for :attr:`volume`
        to read later: OCCT's integration (0.3-1.4 s on end-to-end trees) then runs while this
        process draws the pictures and triangulates the solid (``Reconstruction.write``).
        Nothing happens where the volume is known or no helper is running (``volume`` then
        integrates it here, as before)."""
        if "volume" in self._measures or "volume_later" in self._measures or FUSE_TIMEOUT_S is None:
            return
        worker = _worker()
        if worker is None:
            return
        try:
            later = worker.volume(self.shape, PROPS_EPS, VOLUME_TIMEOUT_S)
        except OSError:  # the helper ended as the job went out: integrated here
            return
        if later is not None:  # None: no helper running (one is started for booleans only)
            self._measures["volume_later"] = later

    @property
    def area(self) -> float:
        """Surface area in mm^2 (walls and caps)."""
        if "area" not in self._measures:
            self._measures["area"] = shape_area(self.shape)
        return self._measures["area"]

    @property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (mm)."""
        box = Bnd_Box()
        BRepBndLib.AddOptimal_s(self.shape, box, False, False)
        return np.array(box.Get()).reshape(2, 3)

    @property
    def branch_ids(self) -> list[int]:
        """Branches present in the solid."""
        return sorted({t.branch_id for _f, t in self.faces})

    def caps(self) -> list[dict[str, Any]]:
        """Open ends of the tree.

        Returns
        -------
        list of dict
            ``{'role', 'branch_id', 'name', 'centre', 'normal', 'radius', 'extension_mm'}``;
            ``normal`` points out of the solid, ``centre`` is the centre of the
            end face (at the end of a flow extension when there is one). The
            inlet comes first, then the outlets in branch order.
        """
        out = []
        by_id = {p.branch_id: p for p in self.pipes}
        seen = set()
        for _f, tag in self.faces:
            # an end face cut in two by another vessel is still one end
            if tag.role not in ("inlet", "outlet") or (tag.branch_id, tag.role) in seen:
                continue
            seen.add((tag.branch_id, tag.role))
            p = by_id[tag.branch_id]
            if tag.role == "inlet":
                centre, normal, radius = p.start.copy(), -p.start_tangent, p.start_radius
            else:
                centre, normal, radius = p.end.copy(), p.end_tangent.copy(), p.end_radius
            ext = self.extensions.get((p.branch_id, tag.role), 0.0)
            out.append({"role": tag.role, "branch_id": p.branch_id, "name": p.name,
                        "centre": centre + ext * normal, "normal": normal, "radius": radius,
                        "extension_mm": ext})
        out.sort(key=lambda c: (c["role"] != "inlet", c["branch_id"]))
        return out

    def with_flow_extensions(self, inlet: float = 0.0, outlet: float = 0.0) -> VesselSolid:
        """The solid with straight cylindrical flow extensions at its open ends.

        Each extension is the end face swept along the end tangent (an exact
        B-rep cylinder sharing the end circle with the wall), ``inlet`` or
        ``outlet`` diameters long, as vmtk's flow extensions give CFD users:
        boundary conditions then sit on straight, developed flow.

        Parameters
        ----------
        inlet, outlet : float
            Extension lengths in diameters of the end (0: none).

        Returns
        -------
        VesselSolid
            A new solid; its extension walls are tagged ``wall`` of the branch
            and its new end faces ``inlet``/``outlet``; :meth:`caps` reports the
            moved ends and ``extensions`` the lengths.
        """
        for label, v in (("inlet", inlet), ("outlet", outlet)):
            if not (isinstance(v, int | float) and np.isfinite(v) and v >= 0):
                raise ArgumentError(f"with_flow_extensions: {label} must be a number of diameters >= 0, "
                                    f"got {v!r}")
        if self.extensions:
            raise ArgumentError("with_flow_extensions: this solid already has flow extensions")
        return _extend(self, {"inlet": float(inlet), "outlet": float(outlet)})

    def without_short_edges(self, min_length_mm: float = SHORT_EDGE_MM) -> VesselSolid:
        """The solid with its very short edges merged into their neighbours (a new solid).

        Where three walls meet almost at one point, or a seam leaves a wall just
        beside such a point, the union leaves an edge of a few micrometres (the
        dome of a real-shaped root and its two daughters: 5.5 um) that a mesher
        must resolve with elements that small. ``ShapeFix_Wireframe`` drops
        every edge shorter than ``min_length_mm`` and joins its neighbours at one
        vertex (their tolerance grows to about that length); the result is
        checked with ``BRepCheck_Analyzer``, and the solid is returned unchanged
        (with a warning) if the fix does not keep it one valid solid. An edge
        that ShapeFix cannot drop is left (real mask 24: four of five, one of
        12 um between a dome and a wall left); the warning says how many merged.

        Parameters
        ----------
        min_length_mm : float
            Edges shorter than this (mm) are merged; degenerated edges (poles) are kept.

        Returns
        -------
        VesselSolid
            ``self`` when no edge is that short; every face keeps its tag.
        """
        if not (isinstance(min_length_mm, int | float) and 0 < min_length_mm < 1):
            raise ArgumentError(f"min_length_mm: expected a number in (0, 1) mm, got {min_length_mm!r}")
        short = [x for x in edge_lengths(self.shape) if x < min_length_mm]
        if not short:
            return self
        from OCP.ShapeFix import ShapeFix_Wireframe

        fix = ShapeFix_Wireframe(self.shape)
        fix.SetPrecision(float(min_length_mm))
        fix.SetMaxTolerance(float(min_length_mm))
        fix.ModeDropSmallEdges = True
        fix.FixSmallEdges()
        new = fix.Shape()
        solid = _first_solid(new)
        left = [x for x in edge_lengths(new) if x < min_length_mm] if solid is not None else short
        if (solid is None or _count_solids(new) != 1 or not is_valid(solid)
                or len(left) >= len(short)):
            return replace(self, faces=list(self.faces), warnings=[
                *self.warnings, f"could not merge the {len(short)} edges shorter than {min_length_mm} mm "
                f"(shortest {min(short) * 1000:.1f} um): left as they are"])
        faces = _retagged(fix.Context(), self.faces, solid)
        note = (f"merged {len(short) - len(left)} edges shorter than {min_length_mm} mm (shortest "
                f"{min(short) * 1000:.1f} um) into their neighbours")
        return replace(self, shape=solid, faces=faces, warnings=[*self.warnings, note])

    def creases(self, max_angle_deg: float = 180.0) -> list[Any]:
        """Junction edges (walls of two branches meeting) and how sharp they get, sharpest first.

        See :func:`vesselcad.kernel.creases.find_creases`.
        """
        from .creases import find_creases

        return find_creases(self, max_angle_deg)

    def round_creases(self, max_angle_deg: float = 45.0, radius_fraction: float = 0.1) -> VesselSolid:
        """The solid with its sharp junction creases rounded by OCCT fillets (a new solid).

        Where a vessel leaves its parent at a shallow angle the walls meet at a
        knife-edge that boundary-layer prisms cannot follow; a fillet of
        ``radius_fraction`` times the thinner vessel's radius rounds every
        junction edge whose tissue wedge gets sharper than ``max_angle_deg``.
        See :func:`vesselcad.kernel.creases.round_creases`.
        """
        from .creases import round_creases

        return round_creases(self, max_angle_deg, radius_fraction)

    def face_properties(self) -> list[dict[str, Any]]:
        """Each face's tag, area (mm^2) and centroid (mm), in :attr:`faces` order.

        Lets other tools (the CFD mesher, which reads the solid through its own
        OCCT) find which of their faces is which. ``area`` and ``centroid`` are
        integrated adaptively (1e-7); ``area_default`` and ``centroid_default``
        with OCCT's default rule, as other OCCT-based tools (gmsh's
        ``occ.getMass``/``getCenterOfMass``) report them: on a trimmed B-spline
        face with a hole they can be several per cent off, the same way.
        """
        out = []
        for face, tag in self.faces:
            g = _props(face, "area")
            c = g.CentreOfMass()
            q = GProp_GProps()
            BRepGProp.SurfaceProperties_s(face, q)
            d = q.CentreOfMass()
            out.append({"branch_id": tag.branch_id, "name": tag.name, "role": tag.role,
                        "area": float(g.Mass()), "centroid": np.array([c.X(), c.Y(), c.Z()]),
                        "area_default": float(q.Mass()), "centroid_default": np.array([d.X(), d.Y(), d.Z()])})
        return out

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Exact distances (mm) from points to the solid's boundary (its B-rep faces).

        Unlike a distance to a tessellation, this is free of chord error
        (``BRepExtrema_DistShapeShape`` against the outer shell); about 0.1 s
        per point on a tree, so meant for checks on a few points.

        Parameters
        ----------
        points : (n, 3) array_like
            Points in mm, inside or outside the solid.

        Returns
        -------
        (n,) ndarray
        """
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepClass3d import BRepClass3d
        from OCP.BRepExtrema import BRepExtrema_DistShapeShape

        try:
            pts = np.asarray(points, dtype=float)
        except (TypeError, ValueError):
            kind = type(points).__name__
            raise ArgumentError(f"distance: expected finite (n, 3) points, got {kind}") from None
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
            raise ArgumentError(f"distance: expected finite (n, 3) points, got shape {pts.shape}")
        shell = BRepClass3d.OuterShell_s(self.shape)
        out = np.empty(len(pts))
        for k, q in enumerate(pts):
            vertex = BRepBuilderAPI_MakeVertex(gp_Pnt(*map(float, q))).Vertex()
            dist = BRepExtrema_DistShapeShape(vertex, shell)
            if not dist.IsDone():
                raise GeometryError(f"distance: OCCT could not measure the distance of point {k}")
            out[k] = dist.Value()
        return out

    def check(self, self_interference: bool = False) -> dict[str, Any]:
        """Validity report of the solid.

        Parameters
        ----------
        self_interference : bool
            Also run ``BRepAlgoAPI_Check`` (self-intersecting faces; slow on big trees).

        Returns
        -------
        dict
            ``valid`` (``BRepCheck_Analyzer``), ``solids`` (count), ``free_edges``
            (open boundary edges, 0 when closed), ``self_interference`` (None when
            not run), ``volume_mm3``, ``area_mm2``, ``watertight`` (valid, one
            solid, no free edge, positive volume), ``shortest_edge_mm`` (the
            shortest edge that is not degenerated, such as a pole: a mesher must
            resolve it with elements that small).

        Computed once per solid (its shape never changes); each call returns a copy.
        """
        key = ("check", bool(self_interference))
        if key not in self._measures:
            if self_interference:
                chk = BRepAlgoAPI_Check(self.shape, True, True)
                self._measures[key] = {**self.check(), "self_interference": not chk.IsValid()}
            else:
                self._measures[key] = {
                    **self.validity(), "self_interference": None, "volume_mm3": self.volume,
                    "area_mm2": self.area,
                    "shortest_edge_mm": min(edge_lengths(self.shape), default=float("nan"))}
        return dict(self._measures[key])

    def validity(self) -> dict[str, Any]:
        """The validity part of :meth:`check`: ``valid``, ``solids``, ``free_edges``, ``watertight``.

        Without the area and the shortest edge, which take OCCT another integration
        (0.6 s on a 17-branch tree); ``report.json`` needs only these and the volume.
        Computed once per solid; each call returns a copy.
        """
        if "validity" not in self._measures:
            valid = is_valid(self.shape)
            fb = ShapeAnalysis_FreeBounds(self.shape, 1e-5, False, False)
            free = (len(_subshapes(fb.GetClosedWires(), TopAbs_EDGE))
                    + len(_subshapes(fb.GetOpenWires(), TopAbs_EDGE)))
            n = _count_solids(self.shape)
            self._measures["validity"] = {"valid": valid, "solids": n, "free_edges": free,
                                          "watertight": bool(valid and n == 1 and free == 0
                                                             and self.volume > 0)}
        return dict(self._measures["validity"])

    # ------------------------------------------------------------ meshes
    def _mesh(self, linear_deflection: float | None, angular_deflection: float,
              closed: bool = True) -> float:
        # a thread-thin end (a radius clamped at a kink) must not make the whole tree's mesh
        # millions of triangles
        r_thin = max(min([p.end_radius for p in self.pipes] + [p.start_radius for p in self.pipes] or [1.0]),
                     MESH_MIN_RADIUS_MM)
        if linear_deflection is None:
            linear_deflection = r_thin / 50.0
        if not (linear_deflection > 0 and angular_deflection > 0):
            raise ArgumentError("linear_deflection, angular_deflection: expected positive numbers, got "
                                f"{linear_deflection!r}, {angular_deflection!r}")
        key = (float(linear_deflection), float(angular_deflection))
        if self._meshed is not None and self._meshed[:2] == key and (self._meshed[2] or not closed):
            return key[0]  # STL and GLB of one solid share one triangulation
        # OCCT's mesher now and then leaves a face's triangles unconnected to its
        # neighbours at one particular deflection (a real-shaped tree: holes at
        # 0.00483 mm, none at 0.0045 or 0.0049): check that every triangle edge is
        # shared by exactly two triangles and retry a little finer (still within the
        # asked deflection) before giving up with a warning. On some fused trees it
        # covers a periodic wall face only in part, at every deflection, and the part
        # closes on a neighbour's part along a line (edges in four triangles:
        # end-to-end rca 2111 with true labels, a face meshed 51 of its 221 mm², the
        # mesh 19 % short of the solid's volume): where a triangulation without holes has
        # such edges or does not enclose the solid's volume (``MESH_VOLUME_TOLERANCE``: a
        # face covered in part can close on its neighbours with every edge in two
        # triangles), the solid is meshed through a copy healed by OCCT's
        # ShapeFix_Shape, which mends those faces' parametrization (the mesh then holds
        # the whole face), and where that is no better through a copy whose closed faces
        # are cut into open pieces (a child's opening across a wall's seam: rca 2104 with
        # true labels, a face meshed 10 of its 53 mm²); the best triangulation is kept and
        # its copy used from then on for every mesh of the solid, pictures included; the
        # exported B-rep is the solid as it is.
        # (Without ``closed``, for a picture: one triangulation, unchecked.)
        shape, faces = self._healed if self._healed is not None else (self.shape, self.faces)
        stage = self._repair
        best: tuple | None = None  # (score, triangles, ratio, defects, shape, faces, stage)
        defects, ratio = (0, 0), 1.0
        theta = min(key[1], np.sqrt(8.0 * key[0] / r_thin))  # largest turn between facets
        vol_tol = MESH_VOLUME_TOLERANCE + theta**2 / 4.0
        for factor in (1.0, 0.93, 0.85, 0.75, 0.6) if closed else (1.0,):
            while True:
                # Drop any earlier triangulation: OCCT keeps an existing one if it is finer.
                BRepTools.Clean_s(shape)
                BRepMesh_IncrementalMesh(shape, key[0] * factor, False, key[1], True)
                self._triangles = self._collect_triangles(shape, faces)
                if not closed:
                    break
                defects = _mesh_defects(*self._triangles[:2])
                if defects[0]:
                    # a triangle or two left out (a rim of hundredths of a millimetre: end-to-end
                    # rca 2011 with the model's labels) is closed, not meshed again finer
                    v, t, b, r = self._triangles
                    t, b, r = _fill_small_holes(v, t, b, r, SMALL_HOLE_DEFLECTIONS * key[0] * factor)
                    if len(t) > len(self._triangles[1]):
                        self._triangles = (v, t, b, r)
                        defects = _mesh_defects(v, t)
                if defects[0]:
                    break  # holes: tried again finer
                ratio = self._volume_ratio()
                score = (abs(ratio - 1.0) > vol_tol, defects[1], abs(ratio - 1.0))
                if best is None or score < best[0]:
                    best = (score, self._triangles, ratio, defects, shape, faces, stage)
                if score[:2] != (False, 0) and (stage == 0 or stage == 1 and best[0][0]):
                    # the same deflection through the healed copy, then, while the volume is
                    # short (a face covered in part; walls that touch along a line are not
                    # mended by cutting faces), through the divided one
                    stage += 1
                    shape, faces = self._healed = self._repaired(stage)
                    continue
                _, self._triangles, ratio, defects, shape, faces, stage = best
                self._healed = None if stage == 0 else (shape, faces)
                break
            if not closed or not defects[0]:
                # Without holes the rest is the same at every deflection (lca 2003 with the
                # model's labels, healed or not: two edges in four triangles at 0.0045-0.05 mm,
                # where five ever finer tries took the write 30 s; rca 2104 with true labels: a
                # face meshed 10 of its 53 mm², the mesh closed but 5.9 % short of the solid at
                # 0.0036-0.02 mm, healed or not): said, not tried finer.
                break
        if closed and defects[1] and not defects[0]:
            # edges no longer than the deflection in more than two triangles (a fold of a few
            # micrometres where two faces' triangulations overlap around a node: lca 2003 with the
            # model's labels, two edges of 3 um) collapse in the triangulation kept
            v, t, b, r = self._triangles
            t, b, r = _collapse_short_edges(v, t, b, r, key[0] * factor)
            if len(t) < len(self._triangles[1]):
                mended = _mesh_defects(v, t)
                if mended[0] == 0 and mended[1] < defects[1]:
                    self._triangles, defects = (v, t, b, r), mended
                    ratio = self._volume_ratio()
        if closed and defects[1] and not defects[0] and FOLD_REFILL_MM is not None:
            # what is left: a face's triangles folded over each other (edges in four triangles of
            # one face, up to a few tenths of a millimetre: the hemispherical end of a branch with a
            # child's opening near its pole, end-to-end lca 2012 with the model's labels)
            v, t, b, r = self._triangles
            t, b, r = _refill_folds(v, t, b, r, FOLD_REFILL_MM)
            if len(t) != len(self._triangles[1]):
                mended = _mesh_defects(v, t)
                if mended[0] == 0 and mended[1] < defects[1]:
                    self._triangles, defects = (v, t, b, r), mended
                    ratio = self._volume_ratio()
        if defects[0]:
            warnings.warn(f"OCCT's triangulation of the solid has holes at deflections {0.6 * key[0]:.3g}-"
                          f"{key[0]:.3g} mm: the STL/GLB/trimesh will not be watertight (the B-rep is; "
                          "try another tolerance)", VesselcadWarning, stacklevel=3)
        elif closed and (defects[1] or abs(ratio - 1.0) > vol_tol):
            what = []
            if defects[1]:
                what.append(f"{defects[1]} edge(s) shared by more than two triangles (no hole, but not "
                            "manifold there)")
            if abs(ratio - 1.0) > vol_tol:
                what.append("a face OCCT's mesher covered only in part")
            warnings.warn(f"the solid's triangulation has {' and '.join(what)}: the STL/GLB/trimesh encloses "
                          f"{ratio:.1%} of the solid's volume (the B-rep is one valid solid)",
                          VesselcadWarning, stacklevel=3)
        self._meshed = (*key, closed)
        self._repair = stage
        return key[0] * factor

    def _volume_ratio(self) -> float:
        """The current triangulation's enclosed volume over the solid's."""
        p = self._triangles[0][self._triangles[1]]
        vol = float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum()) / 6.0
        return vol / self.volume

    def _repaired(self, stage: int) -> tuple[TopoDS_Shape, list[tuple[TopoDS_Face, FaceTag]]]:
        """A copy of the solid for meshing and its faces with the tags of the faces they came
        from: ``stage`` 1 healed by OCCT's ``ShapeFix_Shape``, 2 with its closed faces cut into
        pieces by ``ShapeUpgrade_ShapeDivideClosed`` (:data:`MESH_DIVIDE_CLOSED_POINTS`). A new
        shape; unchanged faces are shared."""
        if stage == 1:
            fix = ShapeFix_Shape(self.shape)
            fix.Perform()
            new = fix.Shape()
            return new, _retagged(fix.Context(), self.faces, new)
        div = ShapeUpgrade_ShapeDivideClosed(self.shape)
        div.SetNbSplitPoints(MESH_DIVIDE_CLOSED_POINTS)
        div.Perform()
        new = div.Result()
        return new, _retagged(div.GetContext(), self.faces, new)

    def _collect_triangles(self, shape: TopoDS_Shape | None = None,
                           faces: list[tuple[TopoDS_Face, FaceTag]] | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nodes, triangles (outward), branch ids and role codes of the current triangulation
        (of the solid, or of ``shape`` with its tagged ``faces``)."""
        if shape is None:
            shape, faces = self.shape, self.faces
        verts, tris, branch, role = [], [], [], []
        offset = 0
        codes = {"wall": 0, "inlet": 1, "outlet": 2, "cap": 3}
        edge_faces = None
        for face, tag in faces:
            mesh = _face_triangulation(face)
            if mesh is None:
                # OCCT's mesher leaves some tiny planar slivers empty (an end disc that
                # another vessel almost covers: 8e-6 mm², edges of 2-45 um): close them
                # from their boundary as the neighbours discretized it
                if edge_faces is None:
                    edge_faces = TopTools_IndexedDataMapOfShapeListOfShape()
                    TopExp.MapShapesAndAncestors_s(shape, TopAbs_EDGE, TopAbs_FACE, edge_faces)
                mesh = _sliver_triangulation(face, edge_faces)
            if mesh is None:
                raise GeometryError(f"to_trimesh: OCCT could not mesh a face of branch {tag.branch_id}")
            nodes, t, _ = mesh
            verts.append(nodes)
            tris.append(t + offset)
            branch.append(np.full(len(t), tag.branch_id))
            role.append(np.full(len(t), codes[tag.role]))
            offset += len(nodes)
        v, t, b, r = np.vstack(verts), np.vstack(tris), np.concatenate(branch), np.concatenate(role)
        # A sphere's pole is a degenerated edge: OCCT puts two nodes there and a
        # triangle between them; it has no area and no place in a closed mesh.
        c = np.round(v, 6)[t]
        keep = ~((c[:, 0] == c[:, 1]).all(1) | (c[:, 1] == c[:, 2]).all(1) | (c[:, 2] == c[:, 0]).all(1))
        # A face whose triangulation folds back on itself has a triangle twice, once each way
        # (a zero-volume fin; end-to-end lca 2003 and rca 2111): such pairs cancel.
        keep[np.flatnonzero(keep)[~_unpaired_triangles(_merged_ids(v, 6)[t[keep]])]] = False
        return v, t[keep], b[keep], r[keep]

    def to_trimesh(self, tolerance: float | None = None, angular_deflection: float = 0.3,
                   check_closed: bool = True) -> Any:
        """Triangulate the solid into a ``trimesh.Trimesh`` (vertices merged across faces).

        Parameters
        ----------
        tolerance : float, optional
            Largest distance (mm) between the triangles and the exact surface
            (OCCT linear deflection); default the smallest radius / 50 (radii under
            :data:`MESH_MIN_RADIUS_MM` count as that), which
            with the default angular deflection keeps the mesh volume within 1%
            of the solid's (about -0.7% on phantom trees, docs/results.md).
        angular_deflection : float
            Largest angle (rad) between the normals of neighbouring facets.
        check_closed : bool
            The triangulation is checked to be closed (every edge shared by two
            triangles) and to enclose the solid's volume (less what inscribed
            facets lose): tiny holes are closed by fans; larger holes make it
            redone at up to 0.6 times the deflection; edges in more than two
            triangles or too little volume make it redone once through a copy of
            the solid healed by ``ShapeFix_Shape`` and, if that is no better, once
            through a copy with its closed faces cut into open pieces
            (:data:`MESH_DIVIDE_CLOSED_POINTS`), keeping the best; edges in more
            than two triangles no longer than the deflection then collapse. A
            ``VesselcadWarning`` says what remains (docs/solids.md, "Meshes are
            derived products").
            False: OCCT's first triangulation as it is, for pictures (coarse
            meshes are the ones OCCT leaves open most often; report.html's 3D
            view at 0.05 mm took 3.6 s of retries on a 17-branch tree, 0.5 s
            without).

        Returns
        -------
        trimesh.Trimesh
            ``face_attributes['branch']`` and ``['role']`` give each triangle's
            branch id and role code (0 wall, 1 inlet, 2 outlet).
        """
        import trimesh

        self._mesh(tolerance, angular_deflection, closed=bool(check_closed))
        verts, tris, branch, role = self._triangles
        attrs = {"branch": branch.copy(), "role": role.copy()}
        mesh = trimesh.Trimesh(verts.copy(), tris.copy(), process=False, face_attributes=attrs)
        # Faces share their edge discretisation, so equal nodes coincide to round-off.
        mesh.merge_vertices(digits_vertex=6)
        return mesh

    # ------------------------------------------------------------ export
    def export_step(self, path: str | os.PathLike, name: str = "vessel_tree") -> None:
        """Write STEP AP214 in mm, atomically.

        The product and the solid are named ``name``; every face is named
        ``<branch name>:<role>`` (``LAD:wall``, ``LM:inlet``, ``D1:outlet``), which
        CAD systems show as face names and CFD pre-processors can group by.
        """
        with _quiet():
            writer = STEPControl_Writer()  # creating it first initialises the STEP statics
            Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
            Interface_Static.SetCVal_s("write.step.unit", "MM")
            Interface_Static.SetCVal_s("write.step.product.name", name)
            if writer.Transfer(self.shape, STEPControl_AsIs) != IFSelect_RetDone:
                raise OutputError(f"{path}: OCCT could not translate the solid to STEP")
            finder = writer.WS().TransferWriter().FinderProcess()
            named = [(self.shape, name)] + [(f, f"{t.name}:{t.role}") for f, t in self.faces]
            for shape, label in named:
                item = STEPConstruct.FindEntity_s(finder, shape)
                if item is not None and hasattr(item, "SetName"):
                    item.SetName(TCollection_HAsciiString(label))
            with atomic_path(path) as tmp:
                if writer.Write(str(tmp)) != IFSelect_RetDone:
                    raise OutputError(f"{path}: OCCT could not write the STEP file")

    def export_stl(self, path: str | os.PathLike, linear_deflection: float | None = None,
                   angular_deflection: float = 0.3, ascii: bool = False) -> None:
        """Write an STL (binary unless ``ascii``) of the triangulated solid, atomically.

        ``linear_deflection`` (mm) defaults to the smallest radius (at least 0.3 mm) / 50;
        see :meth:`to_trimesh`.
        """
        # From the checked triangulation (OCCT's own writer would also write the
        # zero-area triangle at a dome's pole, which opens the mesh for readers).
        mesh = self.to_trimesh(linear_deflection, angular_deflection)
        data = mesh.export(file_type="stl_ascii" if ascii else "stl")
        with atomic_path(path) as tmp:
            if isinstance(data, str):
                tmp.write_text(data)
            else:
                tmp.write_bytes(data)

    def export_glb(self, path: str | os.PathLike, tolerance: float | None = None) -> None:
        """Write a binary glTF (GLB) of the triangulated solid (trimesh), atomically."""
        mesh = self.to_trimesh(tolerance)
        data = mesh.export(file_type="glb")
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)

    def export_brep(self, path: str | os.PathLike) -> None:
        """Write OCCT's native BREP file, atomically."""
        with atomic_path(path) as tmp:
            if not BRepTools.Write_s(self.shape, str(tmp)):
                raise OutputError(f"{path}: OCCT could not write the BREP file")

    # ------------------------------------------------------------ interop
    def to_build123d(self) -> Any:
        """The solid as a build123d ``Solid`` (keeps modelling in build123d)."""
        import build123d

        return build123d.Solid(self.shape)

    def to_cadquery(self, assembly: bool = False) -> Any:
        """The solid as a ``cq.Workplane``, or with ``assembly=True`` a ``cq.Assembly``
        holding the fused tree (``"tree"``) and each branch pipe before fusion, named
        after its branch."""
        import cadquery as cq

        if not assembly:
            return cq.Workplane("XY").newObject([cq.Solid(self.shape)])
        asm = cq.Assembly(name="vessel_tree")
        asm.add(cq.Solid(self.shape), name="tree")
        for p in self.pipes:
            if p.branch_id not in self.failed:
                asm.add(cq.Solid(p.solid), name=f"branch_{p.branch_id}_{p.name}")
        return asm

    def __repr__(self) -> str:
        return (f"VesselSolid(branches={len(self.branch_ids)}, faces={len(self.faces)}, "
                f"failed={sorted(self.failed)}, volume={self.volume:.1f} mm^3)")


def _retagged(ctx: Any, faces: list[tuple[TopoDS_Face, FaceTag]], shape: TopoDS_Shape
              ) -> list[tuple[TopoDS_Face, FaceTag]]:
    """The faces of ``shape``, which a shape-healing tool (its ``ShapeBuild_ReShape`` context
    ``ctx``) made from a solid with the tagged ``faces``, each with the tag of the face it came
    from (a face it split: each piece; none found: branch -1, "unknown")."""
    tags: dict[int, list[tuple[TopoDS_Shape, FaceTag]]] = {}
    for f, t in faces:
        g = ctx.Apply(f)
        for h in [g, *_subshapes(g, TopAbs_FACE)]:
            tags.setdefault(hash(h), []).append((h, t))
    out = []
    for f in _subshapes(shape, TopAbs_FACE):
        hit = [t for g, t in tags.get(hash(f), []) if g.IsSame(f)]
        out.append((TopoDS.Face_s(f), hit[0] if hit else FaceTag(-1, "unknown", "wall")))
    return out


def _edge_use(verts: np.ndarray, tris: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """How the triangles use their edges (nodes equal to 1e-6 mm merged).

    Returns the merged id of each node, the triangles' directed edges in merged ids
    (edges whose two nodes merged left out), the triangle of each, the index of each
    among the distinct edges, and how many triangles use each distinct edge (either
    way round).
    """
    ids = _merged_ids(verts, 6)
    t = ids[tris]
    d = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    owner = np.tile(np.arange(len(t)), 3)
    ok = d[:, 0] != d[:, 1]
    d, owner = d[ok], owner[ok]
    e = np.sort(d, axis=1)
    # each edge one int64 key (ids below n = the vertex count, so a * n + b is unique), one 1D sort
    _u, inv, counts = np.unique(e[:, 0] * np.int64(len(verts)) + e[:, 1], return_inverse=True,
                                return_counts=True)
    return ids, d, owner, np.asarray(inv).ravel(), counts


def _mesh_defects(verts: np.ndarray, tris: np.ndarray) -> tuple[int, int]:
    """Edges of the triangles (nodes equal to 1e-6 mm merged) used once (holes) and used more
    than twice (walls that touch); a closed manifold mesh has neither. No triangles: one hole."""
    if not len(tris):
        return 1, 0
    counts = _edge_use(verts, tris)[4]
    return int(np.sum(counts == 1)), int(np.sum(counts > 2))


def _collapse_short_edges(verts: np.ndarray, tris: np.ndarray, branch: np.ndarray, role: np.ndarray,
                         max_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Collapse the edges in more than two triangles that are at most ``max_length`` (mm) long.

    Such an edge is below the triangulation's resolution (the linear deflection): a fold
    where two faces' triangulations overlap around a node. The nodes of each group of such
    edges become one of them (nodes move by at most the group's length), and the
    triangles that collapse with them are dropped. Returns the triangles (indices into
    ``verts``, unchanged), branch ids and role codes; as given where there is no such edge.
    """
    ids, d, _owner, inv, counts = _edge_use(verts, tris)
    e = d[counts[inv] > 2]
    if not len(e):
        return tris, branch, role
    first = np.unique(ids, return_index=True)[1]  # the first node of each merged id (0, 1, ...)
    p = verts[first[e]]
    e = e[np.linalg.norm(p[:, 0] - p[:, 1], axis=1) <= max_length]
    if not len(e):
        return tris, branch, role
    from scipy import sparse
    from scipy.sparse import csgraph

    # groups of such edges: connected components of their nodes
    n = int(ids.max()) + 1
    g = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    k, comp = csgraph.connected_components(g, directed=False)
    # each merged node's representative: the lowest id of its group, then its first node
    lead = np.full(k, n)
    np.minimum.at(lead, comp, np.arange(n))
    t = first[lead[comp[ids[tris]]]]
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])
    return t[keep], branch[keep], role[keep]


def _fill_small_holes(verts: np.ndarray, tris: np.ndarray, branch: np.ndarray, role: np.ndarray,
                      max_perimeter: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Close the holes of a triangulation whose rim is at most ``max_perimeter`` (mm) long.

    A hole is a loop of edges each in one triangle (nodes equal to 1e-6 mm merged); it is
    closed by a fan of triangles oriented against its rim (so the mesh stays consistently
    oriented), tagged like the triangle at its rim's first edge. Larger holes, and rims
    that do not form simple loops, are left. Returns the triangles, branch ids and role
    codes with the new triangles appended.
    """
    ids, d, owner, inv, counts = _edge_use(verts, tris)
    rim = np.flatnonzero(counts[inv] == 1)
    if not len(rim):
        return tris, branch, role
    rep = np.empty(ids.max() + 1, np.int64)
    rep[ids] = np.arange(len(verts))  # a node for each merged id
    nxt: dict[int, int] = {}
    first_owner: dict[int, int] = {}
    for k in rim:  # few (a handful where OCCT's mesher leaves a triangle out)
        a, b = int(d[k, 0]), int(d[k, 1])
        if a in nxt:
            return tris, branch, role  # a rim node with two open edges leaving it: not a simple loop
        nxt[a] = b
        first_owner[a] = int(owner[k])
    new_t, new_b, new_r = [], [], []
    done: set[int] = set()
    for start in list(nxt):
        if start in done:
            continue
        loop = [start]
        while (b := nxt.get(loop[-1])) is not None and b != start and len(loop) <= len(nxt):
            loop.append(b)
        done.update(loop)
        if b != start or len(loop) < 3:
            continue
        p = verts[rep[loop]]
        if np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1).sum() > max_perimeter:
            continue
        # the rim runs a -> b in its triangles; the fan runs b -> a
        fan = [(loop[0], loop[i + 1], loop[i]) for i in range(1, len(loop) - 1)]
        new_t.append(rep[np.asarray(fan)])
        src = first_owner[start]
        new_b.append(np.full(len(fan), branch[src]))
        new_r.append(np.full(len(fan), role[src]))
    if not new_t:
        return tris, branch, role
    return (np.vstack([tris, *new_t]), np.concatenate([branch, *new_b]), np.concatenate([role, *new_r]))


def _refill_folds(verts: np.ndarray, tris: np.ndarray, branch: np.ndarray, role: np.ndarray,
                  max_extent: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut out the folds of a closed triangulation and triangulate the holes again.

    A fold is a connected group of triangles that touch a node of an edge used by more
    than two triangles (with any triangle whose corners are all corners of those). A
    group is replaced only if its triangles all come from one face tag (branch and
    role: one face's triangulation folded over itself, not two walls that touch), span
    at most ``max_extent`` (mm) along each axis, and have one simple loop of open
    edges; the loop is projected onto its best-fitting plane and ear-clipped, the new
    triangles oriented as the group's rim and tagged as the group was. Returns the
    triangles, branch ids and role codes (as given where nothing was replaced).
    """
    from scipy import sparse
    from scipy.sparse import csgraph

    ids, d, _owner, inv, counts = _edge_use(verts, tris)
    bad = counts[inv] > 2
    if not bad.any():
        return tris, branch, role
    n = int(ids.max()) + 1
    t_ids = ids[tris]
    core = np.zeros(n, bool)
    core[d[bad].ravel()] = True
    touched = core[t_ids].any(axis=1)
    near = np.zeros(n, bool)
    near[t_ids[touched].ravel()] = True
    # with the triangles whose corners all lie on those (an island the others surround)
    touched = np.flatnonzero(touched | near[t_ids].all(axis=1))
    # groups: triangles joined through shared nodes
    rows = np.repeat(np.arange(len(touched)), 3)
    inc = sparse.coo_matrix((np.ones(len(rows)), (rows, t_ids[touched].ravel())),
                            shape=(len(touched), n)).tocsr()
    k, comp = csgraph.connected_components(inc @ inc.T, directed=False)
    rep = np.empty(n, np.int64)
    rep[ids] = np.arange(len(verts))  # a node for each merged id
    drop = np.zeros(len(tris), bool)
    new_t, new_b, new_r = [], [], []
    for g in range(k):  # few (one or two folds where there are any)
        group = touched[comp == g]
        if len({(int(x), int(y)) for x, y in zip(branch[group], role[group], strict=True)}) != 1:
            continue
        if np.ptp(verts[tris[group].ravel()], axis=0).max() > max_extent:
            continue
        # the group's open rim: its directed edges whose reverse it does not hold
        e = np.concatenate([t_ids[group][:, [0, 1]], t_ids[group][:, [1, 2]], t_ids[group][:, [2, 0]]])
        e = e[e[:, 0] != e[:, 1]]
        fwd = e[:, 0] * np.int64(n) + e[:, 1]
        back = e[:, 1] * np.int64(n) + e[:, 0]
        net = {}
        for f_, b_ in zip(fwd.tolist(), back.tolist(), strict=True):
            net[f_] = net.get(f_, 0) + 1
            net[b_] = net.get(b_, 0) - 1
        rim = [(key // n, key % n) for key, c in net.items() if c > 0]
        if any(c > 1 for c in net.values()):
            continue
        nxt: dict[int, int] = {}
        for a, b_ in rim:
            if a in nxt:
                nxt = {}
                break
            nxt[a] = b_
        if len(nxt) < 3:
            continue
        loop = [next(iter(nxt))]
        while (b_ := nxt.get(loop[-1])) is not None and b_ != loop[0] and len(loop) <= len(nxt):
            loop.append(b_)
        if b_ != loop[0] or len(loop) != len(nxt):
            continue  # not one simple loop
        p = verts[rep[loop]]
        centre = p.mean(axis=0)
        axes = np.linalg.svd(p - centre)[2][:2]
        fill = _ear_clip((p - centre) @ axes.T)
        if fill is None:
            continue
        fill = np.asarray(loop)[fill]
        # the rim runs a -> b in the group's triangles, which the fill replaces: the fill runs a -> b too
        on_rim = {(int(a), int(b_)) for a, b_ in zip(loop, loop[1:] + loop[:1], strict=True)}
        edges = [(int(x[i]), int(x[(i + 1) % 3])) for x in fill for i in range(3)]
        if sum(e_ in on_rim for e_ in edges) < sum(e_[::-1] in on_rim for e_ in edges):
            fill = fill[:, ::-1]
        drop[group] = True
        new_t.append(rep[fill])
        new_b.append(np.full(len(fill), branch[group[0]]))
        new_r.append(np.full(len(fill), role[group[0]]))
    if not new_t:
        return tris, branch, role
    keep = ~drop
    return (np.vstack([tris[keep], *new_t]), np.concatenate([branch[keep], *new_b]),
            np.concatenate([role[keep], *new_r]))


def _unpaired_triangles(tris: np.ndarray) -> np.ndarray:
    """Which triangles to keep when triangles on the same three nodes cancel in pairs of
    opposite orientation (and copies of one orientation count once).

    ``tris`` are node ids (m, 3); returns (m,) bools: of each set of triangles on the same
    nodes, one triangle is kept if one orientation outnumbers the other, none if they are
    as many.
    """
    keep = np.ones(len(tris), bool)
    if not len(tris):
        return keep
    # orientation: even (+1) if the corners are a rotation of their sorted order
    k = np.argmin(tris, axis=1)
    rolled = np.take_along_axis(tris, (k[:, None] + np.arange(3)[None]) % 3, axis=1)
    sign = np.where(rolled[:, 1] < rolled[:, 2], 1, -1)
    srt = np.sort(tris, axis=1).astype(np.int64)
    n = int(srt.max()) + 1
    if n < 2**21:  # each triangle one int64 key, one 1D sort (a row-wise unique is ten times slower)
        key = (srt[:, 0] * n + srt[:, 1]) * n + srt[:, 2]
    else:
        key = np.unique(srt, axis=0, return_inverse=True)[1].ravel()
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = ks[1:] == ks[:-1]
    if not same.any():
        return keep
    starts = np.flatnonzero(np.r_[True, ~same])
    group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(ks)]))
    inv = np.empty(len(key), np.int64)
    inv[order] = group
    counts = np.bincount(group)
    for g in np.flatnonzero(counts > 1):  # few (none on most solids)
        members = np.flatnonzero(inv == g)
        net = int(sign[members].sum())
        keep[members] = False
        if net:
            keep[members[sign[members] == np.sign(net)][0]] = True
    return keep


def _merged_ids(verts: np.ndarray, digits: int) -> np.ndarray:
    """An id per vertex, equal for vertices equal when rounded to ``digits`` decimals (mm).

    The grouping of ``np.unique(np.round(verts, digits), axis=0)``, from a lexicographic
    sort of integer coordinates (several times faster than sorting float rows).
    """
    q = np.round(np.asarray(verts, float) * 10.0**digits).astype(np.int64)
    order = np.lexsort(q.T[::-1])
    qs = q[order]
    new = np.ones(len(q), bool)
    new[1:] = (qs[1:] != qs[:-1]).any(axis=1)
    ids = np.empty(len(q), np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


def _extend(solid: VesselSolid, diameters: dict[str, float]) -> VesselSolid:
    from OCP.BRep import BRep_Builder
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.BRepOffsetAPI import BRepOffsetAPI_ThruSections
    from OCP.GeomAbs import GeomAbs_Plane
    from OCP.gp import gp_Trsf, gp_Vec
    from OCP.TopoDS import TopoDS_Shell

    from .pipes import _oriented_solid

    ends = {(c["branch_id"], c["role"]): c for c in solid.caps()}
    wanted = {key: 2.0 * c["radius"] * diameters.get(key[1], 0.0) for key, c in ends.items()}
    # an end face that another vessel cuts (several faces, or not the whole disc) gets no extension
    pieces: dict[tuple[int, str], list[TopoDS_Face]] = {}
    for face, tag in solid.faces:
        if tag.role in ("inlet", "outlet"):
            pieces.setdefault((tag.branch_id, tag.role), []).append(face)
    notes: list[str] = []
    for key, faces_ in pieces.items():
        disc = np.pi * ends[key]["radius"] ** 2
        if wanted.get(key, 0.0) > 0 and (len(faces_) > 1 or abs(shape_area(faces_[0]) - disc) > 0.05 * disc):
            wanted[key] = 0.0
            notes.append(f"no flow extension at the {key[1]} of branch {key[0]} ({ends[key]['name']}): "
                         "another vessel cuts its end face")
    free, more = _free_extension_lengths(solid, ends, wanted)
    notes += more
    keep: list[tuple[TopoDS_Shape, FaceTag]] = []
    added: list[tuple[TopoDS_Shape, FaceTag]] = []
    lengths: dict[tuple[int, str], float] = {}
    added_volume = 0.0
    for face, tag in solid.faces:
        key = (tag.branch_id, tag.role)
        length = free.get(key, 0.0)
        if length <= 0:
            keep.append((face, tag))
            continue
        end = ends[key]
        # A ruled loft from the end circle to its translate: the wall is a B-spline
        # surface on the very edge the vessel wall ends with (no boolean needed),
        # and OCCT integrates it exactly (a prism's extrusion surface it does not).
        rim = BRepTools.OuterWire_s(face)
        rim_edges = _subshapes(rim, TopAbs_EDGE)
        move = gp_Trsf()
        move.SetTranslation(gp_Vec(*(end["normal"] * length)))
        loft = BRepOffsetAPI_ThruSections(True, True, 1e-6)
        loft.AddWire(rim)
        loft.AddWire(TopoDS.Wire_s(BRepBuilderAPI_Transform(rim, move, True).Shape()))
        loft.CheckCompatibility(False)
        loft.Build()
        if not loft.IsDone():
            raise GeometryError(f"flow extension of branch {tag.branch_id} ({tag.role}): OCCT could not "
                                "sweep the end circle")
        body = loft.Shape()
        for f in _subshapes(body, TopAbs_FACE):
            on_rim = any(e.IsSame(r) for e in _subshapes(f, TopAbs_EDGE) for r in rim_edges)
            planar = BRepAdaptor_Surface(TopoDS.Face_s(f)).GetType() == GeomAbs_Plane
            if planar and on_rim:
                continue  # the loft's own copy of the end face
            added.append((f, FaceTag(tag.branch_id, tag.name, tag.role if planar else "wall")))
        added_volume += shape_volume(body)
        lengths[(tag.branch_id, tag.role)] = length
    if not lengths:
        return solid
    shell = TopoDS_Shell()
    builder = BRep_Builder()
    builder.MakeShell(shell)
    for f, _t in keep + added:
        builder.Add(shell, f)
    shell.Closed(True)
    new = TopoDS_Solid()
    builder.MakeSolid(new)
    builder.Add(new, shell)  # the faces keep their outward orientations
    if not is_valid(new):
        new = _first_solid(_oriented_solid(shell))
    expected = solid.volume + added_volume
    if (new is None or not is_valid(new)
            or abs(shape_volume(new) - expected) > 1e-3 * expected):
        raise GeometryError("with_flow_extensions: the extended solid is not valid (a flow extension "
                            "probably runs into the tree; use shorter extensions)")
    faces = []
    tags = keep + added
    for f in _subshapes(new, TopAbs_FACE):
        tag = next((t for g, t in tags if g.IsSame(f)), FaceTag(-1, "unknown", "wall"))
        faces.append((TopoDS.Face_s(f), tag))
    return VesselSolid(new, faces, solid.pipes, dict(solid.failed), list(solid.warnings) + notes,
                       dict(solid.timings_s), solid.specs, lengths, union_warnings=list(solid.union_warnings))


def _free_extension_lengths(solid: VesselSolid, ends: dict[tuple[int, str], dict[str, Any]],
                            wanted: dict[tuple[int, str], float]
                            ) -> tuple[dict[tuple[int, str], float], list[str]]:
    """Extension lengths shortened where a straight extension would run into the tree.

    Tested on the centrelines: a point of an extension's axis collides with a
    vessel (or an earlier extension) when it is closer to that vessel's axis
    than the sum of the two radii (+ 10%). Samples of the extended branch
    itself within two radii of its end do not count.
    """
    pts, rad, owner, arc = [], [], [], []
    for spec in solid.specs:
        if spec["id"] in solid.failed:
            continue
        sp, law = spec["spine"], spec["radius"]
        a, b = float(sp.t[sp.k]), float(sp.t[-sp.k - 1])
        u = np.linspace(a, b, max(int((b - a) / 0.25), 2) + 1)
        pts.append(sp(u))
        rad.append(np.ravel(law(u)))
        owner.append(np.full(len(u), spec["id"]))
        arc.append(np.stack([u - a, b - u], axis=1))  # distance along the branch from its start / end
    if not pts:
        return {k: v for k, v in wanted.items() if v > 0}, []
    xyz, rad_all, own, along = np.vstack(pts), np.concatenate(rad), np.concatenate(owner), np.vstack(arc)
    out: dict[tuple[int, str], float] = {}
    notes: list[str] = []
    for key, length in wanted.items():
        if length <= 0:
            continue
        c = ends[key]
        r, n, centre = c["radius"], c["normal"], c["centre"]
        s = np.linspace(0.0, length, max(int(length / 0.1), 2) + 1)
        axis = centre + s[:, None] * n
        near_end = (own == key[0]) & (along[:, 0 if key[1] == "inlet" else 1] < 2.0 * r)
        obstacle = ~near_end & ((xyz - centre) @ n > -rad_all)
        if np.any(obstacle):
            d = np.linalg.norm(axis[:, None, :] - xyz[obstacle][None, :, :], axis=2)
            hit = np.any(d < 1.1 * (r + rad_all[obstacle])[None, :], axis=1)
            if np.any(hit):
                first = int(np.argmax(hit))
                short = max(s[first] - r, 0.0)
                who = sorted({int(o) for o in own[obstacle][np.any(d[first:first + 1] < 1.1 * (
                    r + rad_all[obstacle])[None, :], axis=0)]})
                if short < r:  # less than half a diameter: not worth a face
                    notes.append(f"no flow extension at the {key[1]} of branch {key[0]} ({c['name']}): it "
                                 f"would run into branch {who}")
                    continue
                notes.append(f"flow extension at the {key[1]} of branch {key[0]} ({c['name']}) shortened "
                             f"from {length:.1f} to {short:.1f} mm: it would run into branch {who}")
                length = short
        out[key] = length
        # later extensions must keep clear of this one too
        s2 = np.linspace(0.0, length, max(int(length / 0.25), 2) + 1)
        xyz = np.vstack([xyz, centre + s2[:, None] * n])
        rad_all = np.concatenate([rad_all, np.full(len(s2), r)])
        own = np.concatenate([own, np.full(len(s2), -1 - len(out))])
        along = np.vstack([along, np.full((len(s2), 2), np.inf)])
    return out, notes


def _tag_faces(shape: TopoDS_Shape, pipes: list[BranchPipe], history: _History,
               root: int | None) -> list[tuple[TopoDS_Face, FaceTag]]:
    origin: dict[int, list[tuple[TopoDS_Shape, FaceTag]]] = {}
    # A vessel whose children start at its end (a skeleton graph's parent ends at the
    # junction; the children's lead-ins start within its radius of that end) has no
    # outlet there: what is left of its end disc is wall.
    forks = {p.branch_id for p in pipes for q in pipes
             if q.parent == p.branch_id and np.linalg.norm(q.start - p.end) <= 1.5 * p.end_radius}
    forks |= {p.branch_id for p in pipes if p.end_shape == "dome"}
    for p in pipes:
        roles = [*((w, "wall") for w in p.walls),
                 (p.start_cap, "inlet" if p.branch_id == root else "cap"),
                 (p.end_cap, "cap" if p.branch_id in forks else "outlet")]
        for f, role in roles:
            for img in history.images(f):
                origin.setdefault(hash(img), []).append((img, FaceTag(p.branch_id, p.name, role)))
    out = []
    for f in _subshapes(shape, TopAbs_FACE):
        tag = next((t for s, t in origin.get(hash(f), []) if s.IsSame(f)), None)
        if tag is None:
            tag = FaceTag(-1, "unknown", "wall")
        out.append((TopoDS.Face_s(f), tag))
    return out


def _finishes(work: Callable[[], Any], timeout_s: float) -> bool | None:
    """Whether ``work()`` returns within ``timeout_s`` seconds, tried in a forked copy of
    this process (killed when time is up; a crash counts as not finishing). ``None``
    where the platform cannot fork (Windows): the caller then runs ``work`` unbounded.
    """
    if not hasattr(os, "fork"):
        return None
    with warnings.catch_warnings():
        # the parallel boolean leaves OCCT pool threads idle; the child only runs
        # single-threaded shape healing and leaves with os._exit
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # pragma: no cover - runs in the child
        code = 1
        try:
            work()
            code = 0
        finally:
            os._exit(code)
    deadline = time.monotonic() + timeout_s
    pause = 0.002
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status) == 0
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return False
        time.sleep(pause)
        pause = min(2 * pause, 0.05)


def _unify(shape: TopoDS_Shape, faces: bool) -> ShapeUpgrade_UnifySameDomain:
    unify = ShapeUpgrade_UnifySameDomain(shape, True, faces, False)
    unify.SetLinearTolerance(1e-6)
    return unify


def _tidy(shape: TopoDS_Shape, history: _History, warnings_out: list[str] | None = None
          ) -> TopoDS_Shape:
    """Merge the faces and edges the boolean split that lie on one surface or curve.

    OCCT's face unification can loop forever on some unions (one is kept in
    tests/data/unify_hang_rca_2001.json): it is first tried in a forked child with a time limit of
    :data:`TIDY_TIMEOUT_S`; if that does not finish, only edges are merged (bounded
    the same way), and if even that fails, the union stays as the boolean left it.
    """
    for faces in (True, False):
        ok = _finishes(lambda faces=faces: _unify(shape, faces).Build(), TIDY_TIMEOUT_S)
        if ok is False:
            if warnings_out is not None:
                what = "face" if faces else "edge"
                warnings_out.append(f"OCCT's {what} unification did not finish within "
                                    f"{TIDY_TIMEOUT_S:g} s" + (": merged edges only" if faces else
                                                                ": the union is left as fused"))
            continue
        unify = _unify(shape, faces)
        unify.Build()
        history.ops.append(unify.History())
        return unify.Shape()
    return shape


def fuse_pipes(pipes: list[BranchPipe], fuzzy_mm: float = FUZZY_MM, parallel: bool = True,
               retry: Callable[[BranchPipe], tuple[BranchPipe, str] | None] | None = None) -> VesselSolid:
    """Union of branch pipes (listed parents before children) as one :class:`VesselSolid`.

    Parameters
    ----------
    pipes : list of BranchPipe
        The first one is the root. Children should start inside their parent.
    fuzzy_mm : float
        Fuzzy value of the boolean (mm).
    parallel : bool
        Let OCCT use all cores for the boolean.
    retry : callable, optional
        Where, fusing branch by branch in tree order (the fallback), the union of
        one branch with the tree fails or runs past :data:`STEP_FUSE_TIMEOUT_S`,
        ``retry(pipe)`` may give another pipe of that branch and what was changed
        (``VesselTree.solid``: its start narrowed), tried once before the branch is
        left out. None: no second try.

    Returns
    -------
    VesselSolid
        ``failed`` names the branches left out and why; the rest is always returned;
        ``pipes`` holds the pipes that went into the union (a retried branch's second pipe).

    Raises
    ------
    GeometryError
        No pipe at all, or even the root pipe is not a valid solid.
    """
    if not pipes:
        raise GeometryError("fuse_pipes: no branch pipe to fuse")
    if retry is not None and not callable(retry):
        raise ArgumentError("retry: expected None or a callable taking a BranchPipe, got "
                            f"{type(retry).__name__}")
    t0 = time.perf_counter()
    root = pipes[0].branch_id
    failed: dict[int, str] = {}
    warnings: list[str] = []
    history = _History()
    result: TopoDS_Shape | None = None
    kept = list(pipes)
    general = False
    why = "general fuse failed"  # what sends the union the branch-by-branch way
    lost_ids: list[int] = []  # branches the general fuse lost and adding back did not restore
    limit: float | None = None
    if len(pipes) == 1:
        result = pipes[0].solid
    else:
        limit = (None if FUSE_TIMEOUT_S is None
                 else min(FUSE_TIMEOUT_S, FUSE_TIMEOUT_BASE_S + FUSE_TIMEOUT_PER_PIPE_S * len(pipes)))
        try:
            op = _general_fuse([p.solid for p in pipes], fuzzy_mm, parallel, limit)
        except TimeoutError:
            op = None
            why = f"OCCT's general fuse did not finish within {limit:g} s"
        if op is not None:
            shape = op.Shape()
            trial = _History()
            trial.ops.append(op)
            # OCCT can report success and still lose parts: every wall must survive
            # and every pipe's probe points must lie inside (validity is checked once
            # the union is tidied, below). Pipes it lost are added one at a time
            # (rca 3025: two touching siblings gone, back in 0.9 s; pairwise: 5.7 s).
            missing = _missing(shape, pipes, trial)
            if missing and root not in missing:
                lost = [p for p in pipes if p.branch_id in missing]
                why = f"the general fuse lost branches {missing} and adding them back failed"
                try:
                    shape = _add_one_by_one(shape, lost, trial, fuzzy_mm)
                except TimeoutError:
                    shape = None
                    why = (f"the general fuse lost branches {missing} and adding them back did not finish "
                           f"within {STEP_FUSE_TIMEOUT_S:g} s")
                if shape is not None and not _missing(shape, pipes, trial):
                    warnings.append(f"the general fuse lost branches {missing}: added them one by one")
                    missing = []
                else:
                    lost_ids = list(missing)
            if shape is not None and not missing:
                history, general = trial, True
                if _count_solids(shape) == 1:
                    result = shape
                else:  # pieces: fuse them into the root's piece, report what stays apart
                    result = _keep_root_piece(shape, pipes, history, failed, fuzzy_mm)
                    kept = [p for p in pipes if p.branch_id not in failed]
    t1 = time.perf_counter()
    if result is not None:
        result = _tidy(result, history, warnings)
    if general and not is_valid(result):
        result, general, kept = None, False, list(pipes)
        failed.clear()
        why = "the general fuse gave an invalid solid"
    if result is None and len(pipes) > 1:
        # Where the general fuse lost branches and could not take them back (cs 2011 of the
        # end-to-end benchmark, model labels: its union in five pieces, so no branch added to
        # it made one solid), the rest of the tree usually fuses whole without them: a second
        # general fuse, then only the lost subtrees one by one (18 s there instead of 24 s).
        base = _fuse_without(pipes, lost_ids, fuzzy_mm, parallel, limit) if lost_ids else None
        history = _History()
        if base is not None:
            start, history, done = base
            held = {p.branch_id for p in done}
            todo = [p for p in pipes if p.branch_id not in held]
            warnings.append(f"{why}; fused the tree again without them and the branches after them "
                            f"({sorted(p.branch_id for p in todo)}), then added those one by one in tree "
                            "order")
            result, kept = _pairwise(todo, fuzzy_mm, history, failed, retry, warnings, start=(start, done))
        else:
            warnings.append(f"{why}; fused the branches one by one in tree order")
            result, kept = _pairwise(pipes, fuzzy_mm, history, failed, retry, warnings)
        swapped = {q.branch_id: q for q in kept}
        pipes = [swapped.get(p.branch_id, p) for p in pipes]
        t1 = time.perf_counter()
        result = _tidy(result, history, warnings)
    if not general and not is_valid(result):
        fix = ShapeFix_Shape(result)
        fix.Perform()
        result = fix.Shape()
        warnings.append("the fused solid needed ShapeFix")
    solid = _first_solid(result)
    if solid is None:
        raise GeometryError(f"fuse_pipes: the union is {_count_solids(result)} solids, not one")
    faces = _tag_faces(solid, kept, history, root)
    out = VesselSolid(solid, faces, list(pipes), failed, warnings,
                      {"fuse": t1 - t0, "tidy": time.perf_counter() - t1}, union_warnings=list(warnings))
    return out


def _quick_volume(shape: TopoDS_Shape) -> float:
    """Volume by OCCT's adaptive integration to a relative 1e-3 (on trees within ~1e-5
    of :func:`shape_volume`, and 1.5-2x faster than OCCT's default rule, which is
    ~0.1 % off)."""
    g = GProp_GProps()
    BRepGProp.VolumeProperties_s(shape, g, 1e-3, True)
    return float(g.Mass())


def _missing(shape: TopoDS_Shape, pipes: list[BranchPipe], history: _History) -> list[int]:
    """The pipes a union does not hold (branch ids, in the order given).

    A pipe is held if the union kept a face of its walls and, because OCCT can
    return a valid solid that dropped most of a branch near a junction and kept
    a sliver of its wall, or dropped two vessels that touch each other
    altogether, every one of its probe points (three start radii along its
    axis, its middle, one end radius before its end) lies inside the union:
    shown cheaply by the wall round each probe staying on the union's
    boundary (:func:`_rings_held`, ~3 ms a pipe), else by classifying the
    probes (:func:`_inside`, a coarse triangulation of the union: ~0.3 s a tree).
    """
    faces = {hash(f): f for f in _subshapes(shape, TopAbs_FACE)}
    kept = {p.branch_id: [TopoDS.Face_s(faces[hash(f)]) for w in p.walls for f in history.images(w)
                          if hash(f) in faces and faces[hash(f)].IsSame(f)] for p in pipes}
    missing = [p.branch_id for p in pipes if not kept[p.branch_id]]
    rest = [p for p in pipes if p.branch_id not in missing and len(p.probes)
            and not _rings_held(p, kept[p.branch_id], pipes)]
    if rest:
        inside = _inside(shape, np.vstack([p.probes for p in rest]))
        ends = np.cumsum([len(p.probes) for p in rest])
        held = np.split(inside, ends[:-1])
        # a probe outside the union counts only if it is inside its own pipe
        missing += [p.branch_id for p, ok in zip(rest, held, strict=True)
                    if not ok.all() and np.any(~ok & p.trusted())]
    return [p.branch_id for p in pipes if p.branch_id in missing]


#: Ring points nearer than this (mm) to another vessel's wall tell nothing (which side they
#: are on depends on the tubes' approximation, ~0.01 mm, and the fuzzy union).
RING_MARGIN_MM = 0.05


def _rings_held(pipe: BranchPipe, walls: list[TopoDS_Face], pipes: list[BranchPipe]) -> bool:
    """Whether the union's boundary keeps ``pipe``'s wall round every probe (a cheap,
    conservative test: False also when it cannot tell, and the probes are then classified).

    Each probe's ring of wall points that no other vessel covers (by
    :data:`RING_MARGIN_MM`, on the analytic tubes) must lie on the union's
    faces that came from the pipe's wall (``walls``; a 2D classification in
    the wall's parameters). Such a ring round the axis, with the wall's
    outward orientation, bounds the union there: the probe on the axis is
    inside it. A probe whose ring is all covered or near other walls tells
    nothing; the pipe is held only if every probe tells and all say so.
    """
    if pipe.rings.size == 0 or len(pipe.rings) != len(pipe.probes):
        return False
    pts = pipe.rings.reshape(-1, 3)
    clear = np.full(len(pts), np.inf)
    for q in pipes:
        if q is not pipe:
            clear = np.minimum(clear, q.tube_distance(pts))
    free = (clear > RING_MARGIN_MM).reshape(pipe.rings.shape[:2])
    if not free.any(axis=1).all():
        return False
    classifiers = [BRepTopAdaptor_FClass2d(f, 1e-9) for f in walls]
    for (u, v) in pipe.rings_uv[free]:
        at = gp_Pnt2d(float(u), float(v))
        if not any(c.Perform(at) in (TopAbs_IN, TopAbs_ON) for c in classifiers):
            return False
    return True


def _add_one_by_one(shape: TopoDS_Shape, pipes: list[BranchPipe], history: _History,
                    fuzzy: float) -> TopoDS_Shape | None:
    """``shape`` fused with each of ``pipes`` in turn (None if a union fails or falls apart;
    TimeoutError past :data:`STEP_FUSE_TIMEOUT_S`)."""
    for p in pipes:
        op = _general_fuse([shape, p.solid], fuzzy, timeout_s=STEP_FUSE_TIMEOUT_S)
        if op is None or _count_solids(op.Shape()) != 1:
            return None
        history.ops.append(op)
        for f in (*p.walls, p.start_cap, p.end_cap):  # its faces' history starts here
            history.since[hash(f)] = len(history.ops) - 1
        shape = op.Shape()
    return shape


def _inside(shape: TopoDS_Shape, points: np.ndarray, stop_at_outside: bool = False) -> np.ndarray:
    """Which ``points`` lie inside ``shape``.

    A coarse, throwaway triangulation (:data:`PROBE_DEFLECTION_MM`) answers by its
    generalized winding number (1 inside, 0 outside) for every point that lies
    clear of the thin slivers between the triangles and the exact surface: each
    triangle near a point is measured against its face (the surface at the
    middle of the triangle and of its edges, taken at their surface parameters,
    against the same points of the triangle: ``delta``), and the point must be
    farther than ``2 delta + 0.05`` mm from it (a triangle farther away than
    twice its longest edge counts as clear). OCCT's mesher does leave triangles
    cutting through a vessel at this coarseness (up to 4 mm off a long root
    wall), which this catches. The other points (and all of them for a shape
    that already carries a triangulation, which is left alone) go to OCCT's
    exact point classification (1e-6 mm), 10-60 ms each on a tree. With
    ``stop_at_outside`` that stops at the first point found outside (the
    points after it come back False).
    """
    out = np.zeros(len(points), bool)
    if not len(points):
        return out
    points = np.asarray(points, float)
    todo = np.arange(len(points))
    mesh = _probe_mesh(shape)
    if mesh is not None:
        sure = np.zeros(len(points), bool)
        step = max(1, 200_000 // max(len(mesh.tris), 1))  # points per chunk: bounded memory
        for i in range(0, len(points), step):
            w, near_ok = mesh.winding_and_clearance(points[i:i + step])
            sure[i:i + step] = near_ok & (np.abs(w - np.round(w)) < 0.05)
            out[i:i + step] = sure[i:i + step] & (np.round(w) == 1)
        if stop_at_outside and np.any(sure & ~out):
            first = int(np.flatnonzero(sure & ~out)[0])
            out[first:] = False
            todo = todo[:first]
        todo = todo[~sure[todo]]
    if len(todo):
        cls = BRepClass3d_SolidClassifier(shape)
        for k in todo:
            cls.Perform(gp_Pnt(*map(float, points[k])), 1e-6)
            out[k] = cls.State() == TopAbs_IN
            if stop_at_outside and not out[k]:
                out[k:] = False
                break
    return out


class _ProbeMesh:
    """A triangulation of a shape's faces with what is needed to trust it: node
    coordinates and surface parameters, each triangle's face."""

    def __init__(self, verts: np.ndarray, uv: np.ndarray, tris: np.ndarray, face_of: np.ndarray,
                 surfaces: list[Any]) -> None:
        self.verts, self.uv, self.tris, self.face_of, self.surfaces = verts, uv, tris, face_of, surfaces
        corners = self.verts[self.tris]
        e = corners[:, [1, 2, 0]] - corners
        self.longest = np.linalg.norm(e, axis=2).max(axis=1)
        self.centre = corners.mean(axis=1)
        self.reach = np.linalg.norm(corners - self.centre[:, None, :], axis=2).max(axis=1)
        self.delta = np.full(len(tris), np.nan)  # measured lazily, for triangles near a point

    def _measure(self, idx: np.ndarray) -> None:
        """``delta`` of triangles ``idx``: surface vs triangle at the centroid and edge midpoints."""
        if not len(idx):
            return
        bary = np.array([[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]])
        t = self.tris[idx]
        xyz = np.einsum("sk,tkj->tsj", bary, self.verts[t]).reshape(-1, 3)
        uv = np.einsum("sk,tkj->tsj", bary, self.uv[t]).reshape(-1, 2)
        face = np.repeat(self.face_of[idx], len(bary))
        on = np.array([self.surfaces[f].Value(u, v).Coord() for f, u, v in zip(face.tolist(), *uv.T.tolist(),
                                                                             strict=True)])
        self.delta[idx] = np.linalg.norm(on - xyz, axis=1).reshape(len(idx), -1).max(axis=1)

    def winding_and_clearance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Winding number at each point and whether it is clear of every triangle's sliver."""
        w = _winding(self.verts, self.tris, points)
        # triangles possibly within 2 x their longest edge (+ 0.05 mm) of a point, by bounding spheres
        gap = np.linalg.norm(points[:, None, :] - self.centre[None, :, :], axis=2) - self.reach[None, :]
        pi, ti = np.nonzero(gap <= 2.0 * self.longest[None, :] + 0.05)
        d = _distance_to_triangles(self.verts[self.tris[ti]], points[pi])
        near = d <= 2.0 * self.longest[ti] + 0.05
        pi, ti, d = pi[near], ti[near], d[near]
        self._measure(np.unique(ti[np.isnan(self.delta[ti])]))
        ok = np.ones(len(points), bool)
        ok[pi[d <= 2.0 * self.delta[ti] + 0.05]] = False
        return w, ok


def _probe_mesh(shape: TopoDS_Shape) -> _ProbeMesh | None:
    """A coarse, throwaway triangulation of ``shape`` (removed again); None if the
    shape already has one or a face did not mesh."""
    faces = [TopoDS.Face_s(f) for f in _subshapes(shape, TopAbs_FACE)]
    loc = TopLoc_Location()
    if any(BRep_Tool.Triangulation_s(f, loc) is not None for f in faces):
        return None
    BRepMesh_IncrementalMesh(shape, PROBE_DEFLECTION_MM, False, PROBE_ANGLE_RAD, True)
    try:
        verts, uvs, tris, face_of, offset = [], [], [], [], 0
        for j, face in enumerate(faces):
            mesh = _face_triangulation(face, uv=True)
            if mesh is None:
                return None
            nodes, t, uv = mesh
            verts.append(nodes)
            uvs.append(uv)
            tris.append(t + offset)
            face_of.append(np.full(len(t), j))
            offset += len(nodes)
        # the faces' surfaces with their locations applied
        return _ProbeMesh(np.vstack(verts), np.vstack(uvs), np.vstack(tris), np.concatenate(face_of),
                          [BRep_Tool.Surface_s(f) for f in faces])
    finally:
        BRepTools.Clean_s(shape)


def _face_triangulation(face: TopoDS_Face, uv: bool = False
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """A face's triangulation: nodes (n, 3) in place, triangles (m, 3) from 0 and
    oriented outward, and with ``uv`` the nodes' surface parameters (n, 2); None
    if the face has none (or no parameters when asked)."""
    loc = TopLoc_Location()
    tri = BRep_Tool.Triangulation_s(face, loc)
    if tri is None or (uv and not tri.HasUVNodes()):
        return None
    n = tri.NbNodes()
    node, triangle = tri.Node, tri.Triangle  # one bound method each: the loops are the cost
    nodes = np.array([node(i).Coord() for i in range(1, n + 1)], dtype=float).reshape(-1, 3)
    if not loc.IsIdentity():  # the location's affine map, applied to all nodes at once
        trsf = loc.Transformation()
        m = np.array([[trsf.Value(r, c) for c in range(1, 5)] for r in range(1, 4)])
        nodes = nodes @ m[:, :3].T + m[:, 3]
    t = np.array([triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)],
                 dtype=np.int64).reshape(-1, 3) - 1
    if face.Orientation() == TopAbs_REVERSED:
        t = t[:, ::-1]
    params = np.array([tri.UVNode(i).Coord() for i in range(1, n + 1)]) if uv else None
    return nodes, t, params


def _sliver_triangulation(face: TopoDS_Face, edge_faces: Any
                          ) -> tuple[np.ndarray, np.ndarray, None] | None:
    """Triangles of a planar face without holes that OCCT's mesher left empty, made from
    its boundary as the neighbouring faces' triangulations discretize its edges (so the
    mesh stays closed); like :func:`_face_triangulation`, oriented outward. None if the
    face is not such a face or a neighbour has no polygon on an edge."""
    ad = BRepAdaptor_Surface(face)
    if ad.GetType() != GeomAbs_Plane or len(_subshapes(face, TopAbs_WIRE)) != 1:
        return None
    pos = ad.Plane().Position()
    origin = np.array(pos.Location().Coord())
    axes = np.array([pos.XDirection().Coord(), pos.YDirection().Coord()])
    loop: list[np.ndarray] = []
    walk = BRepTools_WireExplorer(BRepTools.OuterWire_s(face), face)
    while walk.More():
        edge = walk.Current()
        pts = None
        for other in edge_faces.FindFromKey(edge):
            if other.IsSame(face):
                continue
            loc = TopLoc_Location()
            tri = BRep_Tool.Triangulation_s(TopoDS.Face_s(other), loc)
            poly = BRep_Tool.PolygonOnTriangulation_s(edge, tri, loc) if tri is not None else None
            if poly is not None:
                trsf = loc.Transformation()
                pts = np.array([tri.Node(poly.Node(i)).Transformed(trsf).Coord()
                                for i in range(1, poly.NbNodes() + 1)])
                break
        if pts is None:
            return None
        if walk.Orientation() == TopAbs_REVERSED:
            pts = pts[::-1]
        loop.append(pts[:-1])
        walk.Next()
    if not loop:
        return None
    nodes3 = np.vstack(loop)
    tris = _ear_clip((nodes3 - origin) @ axes.T)
    if tris is None:
        return None
    if face.Orientation() == TopAbs_REVERSED:
        tris = tris[:, ::-1]
    return nodes3, tris, None


def _ear_clip(uv: np.ndarray) -> np.ndarray | None:
    """Counter-clockwise triangles (indices) of a simple polygon given by its (n, 2) corners."""
    n = len(uv)
    if n < 3:
        return None
    area2 = np.sum(uv[:, 0] * np.roll(uv[:, 1], -1) - np.roll(uv[:, 0], -1) * uv[:, 1])
    order = list(range(n)) if area2 > 0 else list(range(n))[::-1]

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    out = []
    guard = 0
    while len(order) > 3 and guard < n * n:
        guard += 1
        m = len(order)
        for k in range(m):
            i, j, h = order[k - 1], order[k], order[(k + 1) % m]
            a, b, c = uv[i], uv[j], uv[h]
            if cross(a, b, c) <= 0:
                continue  # reflex (or flat) corner
            inside = any(cross(a, b, uv[q]) >= 0 and cross(b, c, uv[q]) >= 0 and cross(c, a, uv[q]) >= 0
                         for q in order if q not in (i, j, h))
            if not inside:
                out.append((i, j, h))
                order.pop(k)
                break
        else:
            return None
    if len(order) == 3:
        out.append(tuple(order))
    return np.array(out, dtype=np.int64)


def _winding(verts: np.ndarray, tris: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalized winding number of a triangle mesh at ``points`` (van Oosterom and
    Strackee's solid angles over 4 pi)."""
    a, b, c = (verts[tris[:, k]][None, :, :] - points[:, None, :] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    det = np.einsum("pij,pij->pi", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pij,pij->pi", a, b) * lc + np.einsum("pij,pij->pi", b, c) * la
           + np.einsum("pij,pij->pi", c, a) * lb)
    return np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)


def _distance_to_triangles(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance of each point (n, 3) to its triangle (n, 3, 3), degenerate ones included."""
    import trimesh

    return np.linalg.norm(trimesh.triangles.closest_point(corners, points) - points, axis=1)


def _holds(shape: TopoDS_Shape, points: np.ndarray) -> bool:
    """Whether all ``points`` lie inside ``shape``."""
    return bool(np.all(_inside(shape, points, stop_at_outside=True)))


def _keep_root_piece(shape: TopoDS_Shape, pipes: list[BranchPipe], history: _History,
                     failed: dict[int, str], fuzzy: float) -> TopoDS_Shape:
    """One solid from a union that came out in pieces.

    The general fuse sometimes returns a branch as a separate solid although it
    overlaps the tree; fusing that piece with the root's piece alone usually
    succeeds. Pieces that still stay apart are left out and reported.
    """
    solids = _subshapes(shape, TopAbs_SOLID)
    walls = {p.branch_id: [hash(f) for w in p.walls for f in history.images(w)] for p in pipes}
    parent_of = {p.branch_id: p.parent for p in pipes}
    root = pipes[0].branch_id

    def owner(solid: TopoDS_Shape) -> set[int]:
        faces = {hash(f) for f in _subshapes(solid, TopAbs_FACE)}
        return {b for b, hs in walls.items() if faces.intersection(hs)}

    keep = next((s for s in solids if root in owner(s)), solids[0])
    for s in solids:
        if s.IsSame(keep):
            continue
        try:
            op = _general_fuse([keep, s], fuzzy, timeout_s=STEP_FUSE_TIMEOUT_S)
        except TimeoutError:
            for b in owner(s):
                failed[b] = (f"OCCT's union of its piece with the rest of the tree did not finish within "
                             f"{STEP_FUSE_TIMEOUT_S:g} s")
            continue
        merged = op.Shape() if op is not None else None
        if merged is not None and _count_solids(merged) == 1 and is_valid(merged):
            history.ops.append(op)
            keep = _subshapes(merged, TopAbs_SOLID)[0]
            continue
        piece = owner(s)
        for b in piece:  # the piece's top branch is apart from its parent; the rest hang from it
            failed[b] = ("does not touch the rest of the tree (its start is not inside its parent)"
                         if parent_of[b] not in piece else f"its parent branch {parent_of[b]} was left out")
    return keep


def _fuse_without(pipes: list[BranchPipe], lost: list[int], fuzzy_mm: float, parallel: bool,
                  limit: float | None) -> tuple[TopoDS_Shape, _History, list[BranchPipe]] | None:
    """The general fuse of ``pipes`` without the ``lost`` branches and their subtrees.

    Returns the union, its history and the pipes in it if it is one valid solid that
    holds every one of them (:func:`_missing`); None if it is not, fails or runs past
    ``limit`` s. The root is never among ``lost``.
    """
    drop = set(lost)
    for p in pipes:  # parents come before their children
        if p.parent is not None and p.parent in drop:
            drop.add(p.branch_id)
    rest = [p for p in pipes if p.branch_id not in drop]
    history = _History()
    if len(rest) == 1:
        return rest[0].solid, history, rest
    try:
        op = _general_fuse([p.solid for p in rest], fuzzy_mm, parallel, limit)
    except TimeoutError:
        return None
    if op is None:
        return None
    shape = op.Shape()
    history.ops.append(op)
    if _count_solids(shape) != 1 or _missing(shape, rest, history) or not is_valid(shape):
        return None
    return shape, history, rest


def _pairwise(pipes: list[BranchPipe], fuzzy_mm: float, history: _History, failed: dict[int, str],
              retry: Callable[[BranchPipe], tuple[BranchPipe, str] | None] | None = None,
              notes: list[str] | None = None,
              start: tuple[TopoDS_Shape, list[BranchPipe]] | None = None
              ) -> tuple[TopoDS_Shape, list[BranchPipe]]:
    """The pipes fused one by one in tree order; a branch whose union fails or runs past
    :data:`STEP_FUSE_TIMEOUT_S` gets one more try with ``retry``'s pipe (what it changed is
    added to ``notes``), else it is left out (in ``failed``). ``start``: a union to add all
    of ``pipes`` to and the pipes it holds (default: the first pipe alone). Returns the
    union and the pipes in it."""
    if start is None:
        current: TopoDS_Shape = pipes[0].solid
        current_volume = pipes[0].tube_volume_mm3
        kept = [pipes[0]]
        pipes = pipes[1:]
    else:
        current, kept = start[0], list(start[1])
        current_volume = _quick_volume(current)
    ops = []

    def union(p: BranchPipe) -> tuple[Any, TopoDS_Shape, float] | str:
        """The union with the tree so far, or why it is not one."""
        try:
            op = _general_fuse([current, p.solid], fuzzy_mm, timeout_s=STEP_FUSE_TIMEOUT_S)
        except TimeoutError:
            return f"OCCT's boolean union with the tree did not finish within {STEP_FUSE_TIMEOUT_S:g} s"
        shape = op.Shape() if op is not None else None
        volume = _quick_volume(shape) if shape is not None else 0.0
        if (shape is None or _count_solids(shape) != 1 or not is_valid(shape)
                or volume < VOLUME_SLACK * max(current_volume, p.tube_volume_mm3)
                or not _holds(shape, np.vstack([p.trusted_probes(), *(q.trusted_probes()[:1] for q in kept
                                                                       if q.branch_id == p.parent)]))):
            return "the boolean union with the tree failed"
        return op, shape, volume

    for p in pipes:
        if p.parent is not None and p.parent in failed:
            failed[p.branch_id] = f"its parent branch {p.parent} was left out"
            continue
        done = union(p)
        if isinstance(done, str) and retry is not None and (second := retry(p)) is not None:
            again = union(second[0])
            if not isinstance(again, str):
                if notes is not None:
                    notes.append(f"branch {p.branch_id}: {done}; {second[1]}: fused")
                p, done = second[0], again
        if isinstance(done, str):
            failed[p.branch_id] = done
            continue
        op, current, current_volume = done
        ops.append(op)
        kept.append(p)
    history.ops.extend(ops)
    return current, kept


def read_step(path: str | os.PathLike) -> TopoDS_Shape:
    """Read a STEP file into one OCCT shape (for checks and round trips)."""
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader()
    if reader.ReadFile(str(path)) != IFSelect_RetDone:
        raise OutputError(f"{path}: not a readable STEP file")
    reader.TransferRoots()
    return reader.OneShape()


def read_brep(path: str | os.PathLike) -> TopoDS_Shape:
    """Read an OCCT BREP file."""
    from OCP.BRep import BRep_Builder

    shape = TopoDS_Shape()
    if not BRepTools.Read_s(shape, str(path), BRep_Builder()):
        raise OutputError(f"{path}: not a readable BREP file")
    return shape

