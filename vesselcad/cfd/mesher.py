"""Surface and volume meshes of a vessel tree for CFD, with gmsh.

gmsh reads the fused B-rep solid (OCCT's BREP file, through gmsh's own OCC
kernel), meshes its B-spline walls and planar caps with element sizes from a
:class:`~vesselcad.cfd.sizing.RadiusField`, optionally extrudes prism boundary
layers inward from the wall mesh along its normals (thickness proportional to
the local radius), and fills the rest with tetrahedra. Faces are recognised by
their centroid and area against the solid's tagged faces, so every mesh facet
knows its branch and its role (wall, inlet, outlet).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ArgumentError, InputFileError, MeshError, VesselcadWarning
from .quality import NODES_PER_CELL, crossing_triangles, quality_report
from .sizing import RadiusField

__all__ = ["Boundary", "CFDMesh", "surface_mesh", "volume_mesh", "load_solid", "inverted_sites",
           "WALL_ID", "INLET_ID", "FLUID_ID"]

#: CellEntityIds / physical tags (vmtk's convention): the fluid volume 0 in VTK
#: files (physical volume 1 "fluid" in .msh), the wall 1, the inlet 2 and the
#: outlets 3, 4, ... in branch order.
FLUID_ID, WALL_ID, INLET_ID = 0, 1, 2

#: Rounds of local thinning of the prism layers where they would cross (each to 35 %).
MAX_LAYER_THINNING = 3
#: Junction creases whose tissue wedge gets sharper than this (deg) are rounded before meshing
#: (:meth:`VesselSolid.round_creases`) ...
CREASE_ANGLE_DEG = 45.0
#: ... by a fillet of this share of the thinner vessel's radius (the default of ``crease_radius``).
CREASE_RADIUS = 0.1

_GMSH_TYPES = {2: "triangle", 3: "quad", 4: "tetra", 6: "wedge", 7: "pyramid"}


@dataclass
class Boundary:
    """One open end of the tree in the mesh: where a CFD boundary condition goes.

    Attributes
    ----------
    name : str
        ``'inlet'`` or ``'outlet_<k>'`` (k from 1, in branch order); the
        physical group / patch name.
    id : int
        CellEntityIds value and .msh physical tag of the cap's facets.
    role : str
        ``'inlet'`` or ``'outlet'``.
    branch_id : int
    branch : str
        The branch name (e.g. ``'LAD'``).
    centre : (3,) array
        Centre of the cap (mm, LPS).
    normal : (3,) array
        Outward unit normal of the cap.
    area_mm2 : float
        Area of the meshed cap.
    exact_area_mm2 : float
        Area of the B-rep cap face.
    radius_mm : float
        Radius of the vessel at the cap (from its centreline).
    extension_mm : float
        Length of the flow extension ending at this cap (0 without).
    """

    name: str
    id: int
    role: str
    branch_id: int
    branch: str
    centre: np.ndarray
    normal: np.ndarray
    area_mm2: float
    exact_area_mm2: float
    radius_mm: float
    extension_mm: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (numbers rounded to 1e-6 mm)."""
        return {"name": self.name, "id": self.id, "role": self.role, "branch_id": self.branch_id,
                "branch": self.branch, "centre": np.round(self.centre, 6).tolist(),
                "normal": np.round(self.normal, 8).tolist(), "area_mm2": round(self.area_mm2, 6),
                "exact_area_mm2": round(self.exact_area_mm2, 6),
                "equivalent_radius_mm": round(float(np.sqrt(self.area_mm2 / np.pi)), 6),
                "radius_mm": round(self.radius_mm, 6), "extension_mm": round(self.extension_mm, 6)}


@dataclass
class CFDMesh:
    """A labelled CFD mesh of a vessel tree.

    Attributes
    ----------
    points : (N, 3) array
        Node coordinates (mm, LPS).
    cells : dict of str -> (n, k) int array
        Volume elements by meshio type (``'tetra'``, ``'wedge'``, ``'pyramid'``);
        empty for a surface mesh.
    facets : dict of str -> (m, k) int array
        Boundary elements (``'triangle'``, ``'quad'``), oriented outward.
    facet_ids : dict of str -> (m,) int array
        Group id of each facet (see :attr:`groups`).
    facet_branch : dict of str -> (m,) int array
        Branch id of each facet.
    groups : dict of str -> int
        Group name -> id: ``'fluid'`` 0, ``'wall'`` 1, ``'inlet'`` 2, ``'outlet_k'`` 2 + k.
    boundaries : list of Boundary
        The inlet first, then the outlets.
    quality : dict
        Per element type: count, scaled Jacobian min/mean, inverted count,
        aspect ratio max/mean (see :func:`vesselcad.cfd.quality.quality_report`).
    timings_s : dict of str -> float
    settings : dict
        The arguments the mesh was made with.
    warnings : list of str
    """

    points: np.ndarray
    cells: dict[str, np.ndarray]
    facets: dict[str, np.ndarray]
    facet_ids: dict[str, np.ndarray]
    facet_branch: dict[str, np.ndarray]
    groups: dict[str, int]
    boundaries: list[Boundary]
    quality: dict[str, dict[str, float]] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    # ------------------------------------------------------------ views
    @property
    def n_cells(self) -> int:
        """Number of volume elements."""
        return int(sum(len(c) for c in self.cells.values()))

    @property
    def is_volume(self) -> bool:
        return self.n_cells > 0

    def surface(self) -> Any:
        """The boundary as a ``trimesh.Trimesh`` (quads split), labels in ``face_attributes``.

        ``face_attributes['label']`` is the group id of each triangle (1 wall,
        2 inlet, 3... outlets) and ``['branch']`` its branch id; ``metadata``
        holds ``'groups'`` and ``'boundaries'`` (dicts).
        """
        import trimesh

        tris, ids, br = [], [], []
        for kind, f in self.facets.items():
            if kind == "triangle":
                tris.append(f)
                ids.append(self.facet_ids[kind])
                br.append(self.facet_branch[kind])
            elif kind == "quad":
                tris.append(np.vstack([f[:, [0, 1, 2]], f[:, [0, 2, 3]]]))
                ids.append(np.tile(self.facet_ids[kind], 2))
                br.append(np.tile(self.facet_branch[kind], 2))
        faces = np.vstack(tris)
        used = np.unique(faces)
        remap = np.full(len(self.points), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        mesh = trimesh.Trimesh(self.points[used], remap[faces], process=False,
                               face_attributes={"label": np.concatenate(ids), "branch": np.concatenate(br)})
        mesh.metadata["groups"] = {k: v for k, v in self.groups.items() if k != "fluid"}
        mesh.metadata["boundaries"] = [b.to_dict() for b in self.boundaries]
        mesh.metadata["quality"] = self.quality
        return mesh

    def boundary_conditions(self) -> dict[str, Any]:
        """The boundary-condition sidecar: groups, each inlet/outlet, mesh counts and quality."""
        return {
            "units": "mm", "frame": "LPS",
            "groups": dict(self.groups),
            "inlets": [b.to_dict() for b in self.boundaries if b.role == "inlet"],
            "outlets": [b.to_dict() for b in self.boundaries if b.role == "outlet"],
            "wall": {"id": self.groups["wall"], "area_mm2": round(self.group_area("wall"), 6)},
            "mesh": {"nodes": int(len(self.points)),
                     "elements": {k: int(len(v)) for k, v in {**self.cells, **self.facets}.items()},
                     "quality": self.quality},
            "settings": self.settings,
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
            "warnings": list(self.warnings),
        }

    def group_area(self, name: str) -> float:
        """Area (mm^2) of the facets of one group (``'wall'``, ``'inlet'``, ``'outlet_2'``...)."""
        if name not in self.groups or name == "fluid":
            raise ArgumentError(f"group_area: no boundary group {name!r}; groups: {sorted(self.groups)}")
        gid = self.groups[name]
        total = 0.0
        for kind, f in self.facets.items():
            sel = f[self.facet_ids[kind] == gid]
            total += float(_facet_areas(self.points, sel).sum())
        return total

    def volume_mm3(self) -> float:
        """Volume of the fluid (sum of element volumes), mm^3."""
        total = 0.0
        for kind, c in self.cells.items():
            total += float(_cell_volumes(self.points, c, kind).sum())
        return total

    # ------------------------------------------------------------ output
    def to_meshio(self) -> Any:
        """A ``meshio.Mesh`` with volume cells and boundary facets; ``CellEntityIds``
        (vmtk's name) holds 0 for the fluid and the group ids for the facets."""
        import meshio

        blocks, ids = [], []
        for kind, c in self.cells.items():
            blocks.append((kind, c))
            ids.append(np.full(len(c), self.groups["fluid"], dtype=np.int32))
        for kind, f in self.facets.items():
            blocks.append((kind, f))
            ids.append(self.facet_ids[kind].astype(np.int32))
        return meshio.Mesh(self.points, blocks, cell_data={"CellEntityIds": ids})

    def write(self, path: str | os.PathLike, msh_version: float = 4.1, boundary_conditions: bool = True
              ) -> Path:
        """Write the mesh, atomically; the format follows the suffix.

        ``.msh`` (gmsh, ``msh_version`` 4.1 or 2.2 for OpenFOAM's ``gmshToFoam``;
        physical groups ``fluid``, ``wall``, ``inlet``, ``outlet_k``), ``.vtu``,
        ``.vtk``, ``.xdmf`` (meshio, ``CellEntityIds``), and for surface meshes
        also ``.stl`` (ASCII, one named solid per group, as snappyHexMesh reads
        patches), ``.ply``, ``.obj``, ``.glb``.

        Parameters
        ----------
        path : path-like
        msh_version : {4.1, 2.2}
        boundary_conditions : bool
            Also write the sidecar ``<name>.bc.json`` beside the mesh.

        Returns
        -------
        Path
            The sidecar's path (or the mesh's when ``boundary_conditions`` is False).
        """
        from .io import write_mesh

        return write_mesh(self, path, msh_version=msh_version, boundary_conditions=boundary_conditions)

    def __repr__(self) -> str:
        counts = ", ".join(f"{k}={len(v)}" for k, v in {**self.cells, **self.facets}.items())
        return f"CFDMesh(nodes={len(self.points)}, {counts}, boundaries={[b.name for b in self.boundaries]})"


# ---------------------------------------------------------------- geometry helpers
def _facet_areas(points: np.ndarray, f: np.ndarray) -> np.ndarray:
    if len(f) == 0:
        return np.zeros(0)
    p = points[f]
    a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if f.shape[1] == 4:
        a += 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]), axis=1)
    return a


def _facet_normals(points: np.ndarray, f: np.ndarray) -> np.ndarray:
    p = points[f]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if f.shape[1] == 4:
        n += np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])
    return n


def _cell_volumes(points: np.ndarray, c: np.ndarray, kind: str) -> np.ndarray:
    p = points[c]

    def tet(a: int, b: int, cc: int, d: int) -> np.ndarray:
        return np.einsum("ij,ij->i", np.cross(p[:, b] - p[:, a], p[:, cc] - p[:, a]), p[:, d] - p[:, a]) / 6

    if kind == "tetra":
        return tet(0, 1, 2, 3)
    if kind == "pyramid":
        return tet(0, 1, 2, 4) + tet(0, 2, 3, 4)
    if kind == "wedge":
        return tet(0, 1, 2, 3) + tet(1, 2, 3, 4) + tet(2, 3, 4, 5)
    raise ArgumentError(f"unknown cell type {kind!r}")


# ---------------------------------------------------------------- input
def load_solid(source: Any, flow_extensions: float | Sequence[float] = 0.0,
               separate_contacts: bool = True, crease_radius: float = CREASE_RADIUS) -> Any:
    """The :class:`~vesselcad.kernel.VesselSolid` to mesh, from whatever the user has.

    Parameters
    ----------
    source : VesselSolid, VesselTree, or path
        A solid, a tree, a ``centrelines.json`` file, a phantom ``truth.json``,
        or a folder holding one of them (``vesselcad reconstruct`` output or a
        ``vesselcad phantom`` case).
    flow_extensions : float or (float, float)
        Flow extension length in diameters at the inlet and outlets (one
        number for both, or ``(inlet, outlet)``).
    separate_contacts : bool
        For a tree (or a file holding one): first move apart vessels that touch
        away from a junction (:meth:`VesselTree.separated`, 0.2 mm wall
        clearance), so the fluid domain has no false connection between them
        and no knife-edge crease that folds the boundary layers. A moved branch
        is named in the warnings with how far it moved. A solid is meshed as
        it is.
    crease_radius : float
        Round the knife-edge junction creases (where a vessel leaves its parent
        so shallowly that the walls meet at less than ``CREASE_ANGLE_DEG``) with
        a fillet of this share of the thinner vessel's radius
        (:meth:`VesselSolid.round_creases`): boundary-layer prisms cannot follow
        a knife-edge. 0 keeps the creases. Applies to solids as well.

    Edges shorter than ``SHORT_EDGE_MM`` (0.02 mm) are then merged into their
    neighbours (:meth:`VesselSolid.without_short_edges`), solids included.
    """
    from ..kernel.solid import VesselSolid
    from ..tree import VesselTree

    inlet, outlet = _extension_lengths(flow_extensions)
    if isinstance(source, VesselSolid):
        solid = source
    elif isinstance(source, VesselTree):
        solid = (source.separated() if separate_contacts else source).solid()
    elif isinstance(source, str | os.PathLike):
        path = Path(source)
        if path.is_dir():
            for name in ("centrelines.json", "truth.json"):
                if (path / name).is_file():
                    path = path / name
                    break
            else:
                raise InputFileError(f"{source}: no centrelines.json or truth.json in this folder")
        if not path.is_file():
            raise InputFileError(f"{source}: no such file or folder")
        if path.name == "truth.json":
            tree = VesselTree.from_truth(path)
        else:
            tree = VesselTree.from_json(path)
        solid = (tree.separated() if separate_contacts else tree).solid()
    else:
        raise ArgumentError("source: expected a VesselSolid, a VesselTree or a path, got "
                            f"{type(source).__name__}")
    if solid.failed:
        msg = f"branches left out of the solid: {sorted(solid.failed)}"
        warnings.warn(msg, VesselcadWarning, stacklevel=3)
    if crease_radius > 0:
        solid = solid.round_creases(CREASE_ANGLE_DEG, crease_radius)
    # edges of a few micrometres (three walls meeting almost at one point) would ask for
    # elements that small beside the prism layers
    solid = solid.without_short_edges()
    if inlet > 0 or outlet > 0:
        solid = solid.with_flow_extensions(inlet=inlet, outlet=outlet)
    return solid


def _extension_lengths(value: float | Sequence[float]) -> tuple[float, float]:
    if isinstance(value, int | float):
        pair = (float(value), float(value))
    elif isinstance(value, Sequence) and len(value) == 2 and all(isinstance(v, int | float) for v in value):
        pair = (float(value[0]), float(value[1]))
    else:
        raise ArgumentError("flow_extensions: expected a number of diameters or (inlet, outlet), got "
                            f"{value!r}")
    if not all(np.isfinite(v) and v >= 0 for v in pair):
        raise ArgumentError(f"flow_extensions: diameters must be finite and >= 0, got {value!r}")
    return pair


# ---------------------------------------------------------------- gmsh session
@contextlib.contextmanager
def _gmsh_session(verbose: bool, threads: int) -> Iterator[Any]:
    import gmsh

    own = not gmsh.isInitialized()
    if own:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    name = f"vesselcad_{os.getpid()}_{time.monotonic_ns()}"
    views_before = set(gmsh.view.getTags())
    gmsh.model.add(name)
    try:
        gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
        gmsh.option.setNumber("General.Verbosity", 5 if verbose else 2)
        gmsh.option.setNumber("General.NumThreads", threads)
        yield gmsh
    finally:
        with contextlib.suppress(Exception):
            gmsh.model.mesh.removeSizeCallback()
        with contextlib.suppress(Exception):
            gmsh.model.setCurrent(name)
            gmsh.model.remove()
        with contextlib.suppress(Exception):
            for v in set(gmsh.view.getTags()) - views_before:
                gmsh.view.remove(v)
        if own:
            gmsh.finalize()


def _elements(gmsh: Any, dim: int, tag: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{meshio type: (element tags, node tags (n, k))} of one entity."""
    out = {}
    types, etags, ntags = gmsh.model.mesh.getElements(dim, tag)
    for t, e, n in zip(types, etags, ntags, strict=True):
        kind = _GMSH_TYPES.get(int(t))
        if kind is None:
            continue
        nodes = np.asarray(n, dtype=np.int64).reshape(-1, NODES_PER_CELL[kind])
        out[kind] = (np.asarray(e, dtype=np.int64), nodes)
    return out


def _node_coords(gmsh: Any) -> tuple[np.ndarray, np.ndarray]:
    tags, xyz, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(tags)
    return np.asarray(tags, dtype=np.int64)[order], np.asarray(xyz, float).reshape(-1, 3)[order]


def _lookup(tags: np.ndarray, want: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(tags, want)
    if np.any(idx >= len(tags)) or np.any(tags[np.minimum(idx, len(tags) - 1)] != want):
        raise MeshError("gmsh returned elements on nodes it does not list")
    return idx


# ---------------------------------------------------------------- main work
@dataclass
class _Face:
    tag: int
    role: str  # wall | inlet | outlet
    branch_id: int
    name: str
    cap: int | None = None  # index into the caps list
    area: float = 0.0  # of the B-rep face (mm^2)


def _match_faces(gmsh: Any, solid: Any, caps: list[dict[str, Any]]) -> dict[int, _Face]:
    """Which solid face each gmsh surface is (by centroid and area)."""
    from scipy.optimize import linear_sum_assignment

    props = solid.face_properties()
    # gmsh integrates with OCCT's default rule (several per cent off on a trimmed B-spline
    # face with a hole, e.g. a fillet ring): compare with the same rule
    cent = np.array([p["centroid_default"] for p in props])
    area = np.array([p["area_default"] for p in props])
    cap_index = {(c["branch_id"], c["role"]): i for i, c in enumerate(caps)}
    tags = [t for _d, t in gmsh.model.getEntities(2)]
    if len(tags) != len(props):
        raise MeshError(f"gmsh reads {len(tags)} faces from the solid's {len(props)}")
    g_cent = np.array([gmsh.model.occ.getCenterOfMass(2, t) for t in tags])
    g_area = np.array([gmsh.model.occ.getMass(2, t) for t in tags])
    # compare centroids relative to the face size and areas relatively, one to one
    # (the rest is the two OCCT builds' round-off)
    scale = np.sqrt(np.maximum(g_area, 1e-12))[:, None]
    score = (np.linalg.norm(g_cent[:, None, :] - cent[None, :, :], axis=2) / scale
             + np.abs(g_area[:, None] - area[None, :]) / np.maximum(g_area, 1e-12)[:, None])
    rows, cols = linear_sum_assignment(score)
    out: dict[int, _Face] = {}
    for r, i in zip(rows, cols, strict=True):
        tag = tags[r]
        if score[r, i] > 0.1:
            raise MeshError(f"gmsh surface {tag} (area {g_area[r]:.4g} mm^2) matches no face of the solid")
        p = props[i]
        role = p["role"] if p["role"] in ("inlet", "outlet") else "wall"
        out[tag] = _Face(tag, role, p["branch_id"], p["name"],
                         cap_index.get((p["branch_id"], role)) if role != "wall" else None, p["area"])
    return out


def _short_curves(gmsh: Any, field: RadiusField, edge_factor: float, min_size: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Places where B-rep edges come much closer together than the elements around them.

    Where two seams or two junction curves cross close together the fused solid
    has edges of a few micrometres; where a junction curve passes a seam
    without touching it (18 um on a phantom tree) the two edges are as close
    but no edge is short. Elements must shrink smoothly to such gaps or they
    come out as needles and slivers (and the boundary-layer prisms on them).
    Returns the points and the sizes they need.
    """
    from scipy.spatial import cKDTree

    pts, size = [], []
    samples, owner = [], []
    vertices = np.array([gmsh.model.getValue(0, v, []) for _d, v in gmsh.model.getEntities(0)]).reshape(-1, 3)
    for _d, c in gmsh.model.getEntities(1):
        length = gmsh.model.occ.getMass(1, c)
        ends = [np.array(gmsh.model.getValue(0, v, [])) for v in gmsh.model.getAdjacencies(1, c)[1]]
        if not ends or length <= 1e-9:  # a degenerated edge (a dome's pole) is no gap
            continue
        mid = np.mean(ends, axis=0)
        target = max(edge_factor * float(field(mid[None])[0]), min_size)
        if length < 0.5 * target:
            for p in (*ends, mid):
                pts.append(p)
                size.append(max(length, 1e-4))
        lo, hi = gmsh.model.getParametrizationBounds(1, c)
        u = np.linspace(lo[0], hi[0], max(int(np.ceil(length / 0.04)), 2) + 1)
        samples.append(np.array(gmsh.model.getValue(1, c, u)).reshape(-1, 3))
        owner.append(np.full(len(u), c))
    if samples and len(vertices):
        xyz, who = np.vstack(samples), np.concatenate(owner)
        reach = 0.5 * max(edge_factor * float(field.radius.max()), min_size)
        pairs = cKDTree(xyz).query_pairs(reach, output_type="ndarray")
        pairs = pairs[who[pairs[:, 0]] != who[pairs[:, 1]]]
        if len(pairs):
            a, b = xyz[pairs[:, 0]], xyz[pairs[:, 1]]
            gap = np.linalg.norm(a - b, axis=1)
            target = np.maximum(edge_factor * field(0.5 * (a + b)), min_size)
            to_vertex = cKDTree(vertices).query(0.5 * (a + b))[0]
            # close for the elements, and not merely two edges leaving one vertex (unless
            # within 17 degrees of each other); samples at a vertex itself do not count
            tight = (gap < 0.5 * target) & (gap < 0.3 * to_vertex) & (to_vertex > 1e-3)
            for k in np.flatnonzero(tight):
                pts += [a[k], b[k]]
                size += [max(float(gap[k]), 5e-3)] * 2
    return np.array(pts).reshape(-1, 3), np.array(size)


def _orient_outward(gmsh: Any, faces: dict[int, _Face], caps: list[dict[str, Any]], field: RadiusField
                    ) -> None:
    """Reverse the mesh of any surface whose triangles point into the vessel."""
    tags, xyz = _node_coords(gmsh)
    for tag, face in faces.items():
        els = _elements(gmsh, 2, tag).get("triangle")
        if els is None:
            raise MeshError(f"gmsh left surface {tag} ({face.name}:{face.role}) without triangles")
        tri = _lookup(tags, els[1])
        n = _facet_normals(xyz, tri)
        centre = xyz[tri].mean(axis=1)
        if face.cap is not None:
            s = float(np.sum(n @ caps[face.cap]["normal"]))
        else:
            _r, _b, axis = field.query(centre)
            s = float(np.sum(np.einsum("ij,ij->i", n, centre - axis)))
        if s < 0:
            gmsh.model.mesh.reverse([(2, tag)])


def _radius_view(gmsh: Any, walls: list[int], field: RadiusField | None, thinning: _Thinning) -> int:
    """A list-based scalar view on the wall triangles that scales the layers: the local
    radius (1 with ``field=None``) times the thinning factor."""
    tags, xyz = _node_coords(gmsh)
    blocks = []
    for tag in walls:
        tri = _lookup(tags, _elements(gmsh, 2, tag)["triangle"][1])
        x = xyz[tri]
        flat = x.reshape(-1, 3)
        r = (field(flat) if field is not None else np.ones(len(flat))) * thinning(flat)
        blocks.append(np.concatenate([x[:, :, 0], x[:, :, 1], x[:, :, 2], r.reshape(-1, 3)], axis=1))
    data = np.vstack(blocks)
    view = gmsh.view.add("vesselcad_radius")
    gmsh.view.addListData(view, "ST", len(data), data.ravel().tolist())
    return gmsh.view.getIndex(view)


def _cap_of(points: np.ndarray, caps: list[dict[str, Any]], layer_mm: Callable[[float], float]) -> int | None:
    """The cap whose plane holds all these points, if any.

    Within 5% of its radius, plus the boundary layers' thickness: where a cap's
    rim runs along another vessel's wall the layer ribbon leaves the plane by
    up to that much.
    """
    for i, c in enumerate(caps):
        off = points - c["centre"]
        axial = np.abs(off @ c["normal"])
        radial = np.linalg.norm(off - np.outer(off @ c["normal"], c["normal"]), axis=1)
        if axial.max() <= 0.05 * c["radius"] + layer_mm(c["radius"]) and radial.max() <= 1.05 * c["radius"]:
            return i
    return None


def _gmsh_mesh(solid: Any, caps: list[dict[str, Any]], field: RadiusField, *, volume: bool,
               edge_factor: float, lo: float, hi: float, cap_segments: int, boundary_layers: int,
               first_layer: float, first_layer_mm: float | None, growth: float, optimize: bool,
               threads: int | None, verbose: bool, gmsh_options: dict[str, float] | None,
               thinning: _Thinning, timings: dict[str, float], on_surface: Callable[[], None]) -> CFDMesh:
    """One gmsh session: import the solid, mesh it, extract the result (raises
    :class:`_LayersCross` where the prism layers would cross)."""
    with _gmsh_session(verbose, threads or os.cpu_count() or 1) as gmsh, \
            tempfile.TemporaryDirectory(prefix="vesselcad_mesh_") as tmp:
        t1 = time.perf_counter()
        brep = Path(tmp) / "tree.brep"
        solid.export_brep(brep)
        gmsh.model.occ.importShapes(str(brep))
        gmsh.model.occ.synchronize()
        faces = _match_faces(gmsh, solid, caps)
        exact: dict[int, float] = {}
        for f in faces.values():
            if f.cap is not None:  # an end cut in two by another vessel has two faces
                exact[f.cap] = exact.get(f.cap, 0.0) + f.area
        overrides = {}
        for face in faces.values():
            if face.cap is None:
                continue
            rim = 2 * np.pi * caps[face.cap]["radius"] / cap_segments
            for _d, curve in gmsh.model.getBoundary([(2, face.tag)], oriented=False):
                overrides[(1, abs(curve))] = lambda s, rim=rim: min(s, rim)
        for opt, val in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 0),
                         ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.Algorithm", 6),
                         ("Mesh.Algorithm3D", 1), ("Mesh.Optimize", int(optimize)),
                         ("Mesh.OptimizeNetgen", int(optimize))):
            gmsh.option.setNumber(opt, val)
        for opt, val in (gmsh_options or {}).items():
            gmsh.option.setNumber(opt, val)
        refine = _short_curves(gmsh, field, edge_factor, lo)
        gmsh.model.mesh.setSizeCallback(field.size_callback(edge_factor, lo, hi, overrides, refine))
        gmsh.model.mesh.generate(2)
        _orient_outward(gmsh, faces, caps, field)
        timings["surface"] = time.perf_counter() - t1
        on_surface()
        walls = [t for t, f in faces.items() if f.role == "wall"]
        if volume:
            t2 = time.perf_counter()
            if boundary_layers > 0:
                inner = _boundary_layers(gmsh, faces, walls, field, boundary_layers, first_layer,
                                         first_layer_mm, growth, thinning)
                gmsh.model.mesh.generate(2)  # the layers' side and top surfaces
                crossing = _layer_crossings(gmsh, inner)
                if len(crossing):
                    raise _LayersCross(crossing)
            gmsh.model.mesh.generate(3)
            timings["volume"] = time.perf_counter() - t2
        total = sum(growth**i for i in range(boundary_layers)) if volume else 0.0

        def layer_mm(radius: float) -> float:
            return total * (first_layer_mm if first_layer_mm is not None else first_layer * radius)

        return _extract(gmsh, faces, caps, field, volume, exact, layer_mm)


def _mesh(source: Any, *, volume: bool, edge_factor: float, min_size: float | None,
          max_size: float | None, flow_extensions: float | Sequence[float], cap_segments: int,
          boundary_layers: int, first_layer: float, first_layer_mm: float | None, growth: float,
          optimize: bool, threads: int | None, verbose: bool, progress: bool,
          gmsh_options: dict[str, float] | None = None, separate_contacts: bool = True,
          crease_radius: float = CREASE_RADIUS) -> CFDMesh:
    settings = {"edge_factor": edge_factor, "min_size": min_size, "max_size": max_size,
                "flow_extensions": flow_extensions if isinstance(flow_extensions, int | float)
                else list(flow_extensions), "cap_segments": cap_segments,
                "boundary_layers": boundary_layers, "first_layer": first_layer,
                "first_layer_mm": first_layer_mm, "growth": growth, "optimize": optimize,
                "separate_contacts": bool(separate_contacts), "crease_radius": crease_radius}
    if not (isinstance(crease_radius, int | float) and 0 <= crease_radius < 1):
        raise ArgumentError("crease_radius: expected a share of the vessel radius in [0, 1), "
                            f"got {crease_radius!r}")
    _check_args(edge_factor, min_size, max_size, cap_segments, boundary_layers, first_layer, first_layer_mm,
                growth)
    stages = ["solid", "surface mesh"] + (["volume mesh"] if volume else []) + ["quality"]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(stages), desc="cfd mesh", unit="stage")

    def step(name: str) -> None:
        if bar is not None:
            bar.set_postfix_str(name)
            bar.update(1)

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    solid = load_solid(source, flow_extensions, separate_contacts, crease_radius)
    caps = solid.caps()
    field = RadiusField.from_solid(solid)
    r_min, r_max = float(field.radius.min()), float(field.radius.max())
    lo = min_size if min_size is not None else edge_factor * r_min / 2
    hi = max_size if max_size is not None else edge_factor * r_max * 2
    timings["solid"] = time.perf_counter() - t0
    step("solid")
    thinning = _Thinning()
    try:
        for attempt in range(MAX_LAYER_THINNING + 1):
            try:
                first = attempt == 0
                mesh = _gmsh_mesh(solid, caps, field, volume=volume, edge_factor=edge_factor, lo=lo, hi=hi,
                                  cap_segments=cap_segments, boundary_layers=boundary_layers,
                                  first_layer=first_layer, first_layer_mm=first_layer_mm, growth=growth,
                                  optimize=optimize, threads=threads, verbose=verbose,
                                  gmsh_options=gmsh_options, thinning=thinning, timings=timings,
                                  on_surface=(lambda: step("surface mesh")) if first else (lambda: None))
            except _LayersCross as crossing:
                if attempt == MAX_LAYER_THINNING:
                    raise MeshError(_crossing_message(crossing.points, field, thinning)) from None
                thinning.add(crossing.points, field)
                continue
            break
        if volume:
            step("volume mesh")
    except MeshError:
        raise
    except Exception as exc:  # gmsh raises plain Exceptions with its last error message
        hint = ""
        overlaps = [w for w in solid.warnings if "overlap" in w]
        if "intersect" in str(exc) and overlaps:
            hint = f" (the solid's surface crosses itself: {'; '.join(overlaps)})"
        raise MeshError(f"gmsh could not mesh the tree: {str(exc).strip()}{hint}") from None
    finally:
        if bar is not None:
            bar.close()
    t3 = time.perf_counter()
    cells = {**mesh.cells, **mesh.facets}
    mesh.quality = quality_report(mesh.points, cells)
    timings["quality"] = time.perf_counter() - t3
    timings["total"] = time.perf_counter() - t0
    mesh.timings_s = timings
    mesh.settings = settings
    mesh.warnings = list(solid.warnings) + [f"branch {b} left out: {why}" for b, why in solid.failed.items()]
    if thinning.sites:
        msg = _thinning_message(thinning, field, {p.branch_id: p.name for p in solid.pipes})
        mesh.warnings.append(msg)
        warnings.warn(msg, VesselcadWarning, stacklevel=3)
    for b in mesh.boundaries:
        full = np.pi * b.radius_mm**2
        if abs(b.exact_area_mm2 - full) > 0.05 * full:
            mesh.warnings.append(f"{b.name} (branch {b.branch}) is not a whole disc: "
                                 f"{b.exact_area_mm2:.3g} mm^2 of pi r^2 = {full:.3g} mm^2 "
                                 "(the vessel end touches another vessel)")
    inverted = sum(q.get("inverted", 0) for q in mesh.quality.values())
    if inverted:
        names = {p.branch_id: p.name for p in solid.pipes}
        sites = []
        for (x, y, z), n, branches in inverted_sites(mesh):
            next_to = ", ".join(f"{b} ({names.get(b, '?')})" for b in branches)
            plural = "es" if len(branches) > 1 else ""
            sites.append(f"{n} at ({x:.1f}, {y:.1f}, {z:.1f}) mm next to branch{plural} {next_to}")
        msg = f"the volume mesh has {inverted} inverted elements: {'; '.join(sites)}"
        mesh.warnings.append(msg)
        warnings.warn(msg, VesselcadWarning, stacklevel=3)
    return mesh


def inverted_sites(mesh: CFDMesh, radius_mm: float = 1.0, threshold: float = 0.0
                   ) -> list[tuple[np.ndarray, int, list[int]]]:
    """Where a volume mesh has inverted elements (scaled Jacobian <= 0), and which branches' walls are there.

    Parameters
    ----------
    mesh : CFDMesh
        A volume mesh.
    radius_mm : float
        Inverted elements closer than this are one site; wall facets closer
        than this to a site name its branches.
    threshold : float
        Elements whose scaled Jacobian is at most this count (0: inverted
        ones; e.g. 0.1 for the poor ones as well).

    Returns
    -------
    list of (centre, count, branch ids)
        One entry per site, most elements first; ``centre`` (mm) is the mean of
        the elements' centroids.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from .quality import scaled_jacobian

    if not isinstance(mesh, CFDMesh):
        raise ArgumentError(f"inverted_sites: expected a CFDMesh, got {type(mesh).__name__}")
    if not (isinstance(radius_mm, int | float) and radius_mm > 0):
        raise ArgumentError(f"radius_mm: expected a positive number, got {radius_mm!r}")
    if not (isinstance(threshold, int | float) and -1.0 <= threshold <= 1.0):
        raise ArgumentError(f"threshold: expected a scaled Jacobian in [-1, 1], got {threshold!r}")
    centres = [mesh.points[c[scaled_jacobian(mesh.points, c, kind) <= threshold]].mean(axis=1)
               for kind, c in mesh.cells.items() if len(c)]
    pts = np.vstack(centres) if centres else np.empty((0, 3))
    if not len(pts):
        return []
    pairs = cKDTree(pts).query_pairs(radius_mm, output_type="ndarray")
    link = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    _n, label = connected_components(link, directed=False)
    walls = [(mesh.points[f[mesh.facet_ids[k] == mesh.groups["wall"]]].mean(axis=1),
              mesh.facet_branch[k][mesh.facet_ids[k] == mesh.groups["wall"]]) for k, f in mesh.facets.items()]
    wall_xyz = np.vstack([w[0] for w in walls])
    wall_branch = np.concatenate([w[1] for w in walls])
    near = cKDTree(wall_xyz)
    out = []
    for k in np.unique(label):
        centre = pts[label == k].mean(axis=0)
        hits = near.query_ball_point(centre, radius_mm)
        out.append((centre, int(np.sum(label == k)), sorted({int(b) for b in wall_branch[hits]})))
    out.sort(key=lambda site: -site[1])
    return out


def _check_args(edge_factor: float, min_size: float | None, max_size: float | None, cap_segments: int,
                boundary_layers: int, first_layer: float, first_layer_mm: float | None, growth: float
                ) -> None:
    def pos(name: str, v: Any) -> None:
        if not (isinstance(v, int | float) and np.isfinite(v) and v > 0):
            raise ArgumentError(f"{name}: expected a positive number, got {v!r}")

    pos("edge_factor", edge_factor)
    pos("first_layer", first_layer)
    pos("growth", growth)
    for name, v in (("min_size", min_size), ("max_size", max_size), ("first_layer_mm", first_layer_mm)):
        if v is not None:
            pos(name, v)
    if min_size is not None and max_size is not None and min_size > max_size:
        raise ArgumentError(f"min_size ({min_size}) is larger than max_size ({max_size})")
    if not (isinstance(cap_segments, int) and cap_segments >= 8):
        raise ArgumentError(f"cap_segments: expected an integer >= 8, got {cap_segments!r}")
    if not (isinstance(boundary_layers, int) and 0 <= boundary_layers <= 50):
        raise ArgumentError(f"boundary_layers: expected an integer in 0..50, got {boundary_layers!r}")
    if boundary_layers:
        total = first_layer * sum(growth**i for i in range(boundary_layers))
        if first_layer_mm is None and total >= 0.5:
            raise ArgumentError(f"boundary layers of {total:.2f} x the radius would fill half the vessel; "
                                "use fewer layers, a thinner first layer or a smaller growth")


def _boundary_layers(gmsh: Any, faces: dict[int, _Face], walls: list[int], field: RadiusField, n: int,
                     first: float, first_mm: float | None, growth: float, thinning: _Thinning) -> int:
    """Prism layers extruded inward from the wall mesh; caps rebuilt as layer ribbons + inner discs.

    Returns the tag of the volume left for the tetrahedra (inside the layers)."""
    heights = np.cumsum(growth ** np.arange(n)) * (first_mm if first_mm is not None else first)
    view = (-1 if first_mm is not None and not thinning.sites
            else _radius_view(gmsh, walls, field if first_mm is None else None, thinning))
    # The wall meshes point outward (_orient_outward): negative heights go into the vessel.
    ext = gmsh.model.geo.extrudeBoundaryLayer([(2, w) for w in walls], [1] * n, (-heights).tolist(),
                                              True, False, view)
    top = [ext[i - 1] for i in range(1, len(ext)) if ext[i][0] == 3]
    gmsh.model.geo.synchronize()
    rims = [c[1] for c in gmsh.model.getBoundary(top, combined=True, oriented=False)]
    loops = gmsh.model.geo.addCurveLoops(rims)
    discs = [gmsh.model.geo.addPlaneSurface([loop]) for loop in loops]
    shell = gmsh.model.geo.addSurfaceLoop([t[1] for t in top] + discs)
    inner = gmsh.model.geo.addVolume([shell])
    gmsh.model.geo.synchronize()
    occ_volumes = [(3, t) for _d, t in gmsh.model.occ.getEntities(3)]
    caps = [(2, t) for t, f in faces.items() if f.role != "wall"]
    gmsh.model.removeEntities(occ_volumes)
    gmsh.model.mesh.clear(caps)
    gmsh.model.removeEntities(caps)
    for tag in list(faces):
        if faces[tag].role != "wall":
            del faces[tag]
    return inner


def _layer_crossings(gmsh: Any, inner: int) -> np.ndarray:
    """Where the surface that bounds the tetrahedra (the layers' top, the cap discs) crosses
    itself: the centres of the crossing triangles (k, 3), empty when it does not."""
    tags, xyz = _node_coords(gmsh)
    tris = []
    for _d, s in gmsh.model.getBoundary([(3, inner)], combined=True, oriented=False):
        tri = _elements(gmsh, 2, abs(s)).get("triangle")
        if tri is not None:
            tris.append(_lookup(tags, tri[1]))
    if not tris:
        return np.zeros((0, 3))
    t = np.vstack(tris)
    i, j = crossing_triangles(xyz, t)
    return xyz[t[np.r_[i, j]]].mean(axis=1)


@dataclass
class _Thinning:
    """Where the prism layers are made thinner than asked, and by how much.

    Each site thins the layers by its factor at its centre, blending back to
    the full thickness over ``BLEND_RADII`` local radii (smoothstep)."""

    BLEND_RADII = 2.0
    STEP = 0.35  # each retry thins a crossing site to this share of what it had

    sites: list[tuple[np.ndarray, float, float]] = field(default_factory=list)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        out = np.ones(len(points))
        for centre, radius, factor in self.sites:
            s = np.clip(np.linalg.norm(points - centre, axis=1) / (self.BLEND_RADII * radius), 0.0, 1.0)
            out = np.minimum(out, factor + (1.0 - factor) * s * s * (3.0 - 2.0 * s))
        return out

    def add(self, points: np.ndarray, field: RadiusField) -> None:
        """New sites at ``points`` (clustered one local radius apart)."""
        radius = field(points)
        new: list[tuple[np.ndarray, float, float]] = []
        for p, r in zip(points, radius, strict=True):
            if any(np.linalg.norm(p - c) < rc for c, rc, _f in new):
                continue
            new.append((p, float(r), self.STEP * float(self(p[None])[0])))
        self.sites.extend(new)


def _where(points: np.ndarray, field: RadiusField, names: dict[int, str] | None = None) -> str:
    """'(x, y, z) mm next to branch b (name)' for each point."""
    _r, branch, _axis = field.query(points)
    out = []
    for (x, y, z), b in zip(points, branch, strict=True):
        name = f" ({names[int(b)]})" if names and int(b) in names else ""
        out.append(f"({x:.1f}, {y:.1f}, {z:.1f}) mm next to branch {int(b)}{name}")
    return "; ".join(out)


def _thinning_message(thinning: _Thinning, field: RadiusField, names: dict[int, str]) -> str:
    pts = np.array([c for c, _r, _f in thinning.sites])
    least = min(f for _c, _r, f in thinning.sites)
    return (f"the prism layers would cross where the wall folds onto itself; thinned there (down to "
            f"{least:.0%} of the asked thickness, back to full within {_Thinning.BLEND_RADII:g} radii): "
            + _where(pts, field, names))


def _crossing_message(points: np.ndarray, field: RadiusField, thinning: _Thinning) -> str:
    centre = points[np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1))][None]
    least = min((f for _c, _r, f in thinning.sites), default=1.0)
    return (f"the prism layers cross themselves near {_where(centre, field)} ({len(points)} triangles), "
            f"even thinned to {least:.0%} of their thickness there; mesh with fewer or thinner layers "
            "(boundary_layers, first_layer) or without them")


class _LayersCross(Exception):  # noqa: N818 - internal signal, never leaves _mesh
    def __init__(self, points: np.ndarray) -> None:
        super().__init__(f"{len(points)} crossing triangles")
        self.points = points


def _extract(gmsh: Any, faces: dict[int, _Face], caps: list[dict[str, Any]], field: RadiusField,
             volume: bool, exact: dict[int, float], layer_mm: Callable[[float], float]) -> CFDMesh:
    tags, xyz = _node_coords(gmsh)
    cells: dict[str, list[np.ndarray]] = {}
    if volume:
        vols = gmsh.model.getEntities(3)
        for _d, v in vols:
            for kind, (_e, nodes) in _elements(gmsh, 3, v).items():
                cells.setdefault(kind, []).append(nodes)
        boundary = [abs(t) for _d, t in gmsh.model.getBoundary(vols, combined=True, oriented=False)]
    else:
        boundary = [t for _d, t in gmsh.model.getEntities(2)]
    # groups: inlet(s) first, then outlets in branch order (caps() order)
    names: list[str] = []
    n_in = sum(c["role"] == "inlet" for c in caps)
    k_out = 0
    for c in caps:
        if c["role"] == "inlet":
            names.append("inlet" if n_in == 1 else f"inlet_{len(names) + 1}")
        else:
            k_out += 1
            names.append(f"outlet_{k_out}")
    groups = {"fluid": FLUID_ID, "wall": WALL_ID}
    for i, nm in enumerate(names):
        groups[nm] = INLET_ID + i
    facets: dict[str, list[np.ndarray]] = {}
    ids: dict[str, list[np.ndarray]] = {}
    branch: dict[str, list[np.ndarray]] = {}
    cap_area = np.zeros(len(caps))
    for tag in boundary:
        els = _elements(gmsh, 2, tag)
        if not els:
            raise MeshError(f"boundary surface {tag} has no mesh")
        idx = {k: _lookup(tags, v[1]) for k, v in els.items()}
        face = faces.get(tag)
        cap = face.cap if face is not None else _cap_of(xyz[np.unique(np.concatenate(
            [v.ravel() for v in idx.values()]))], caps, layer_mm)
        if face is None and cap is None:
            pts = xyz[np.unique(np.concatenate([v.ravel() for v in idx.values()]))]
            near = min(caps, key=lambda c: float(np.linalg.norm(pts.mean(axis=0) - c["centre"])))
            off = pts - near["centre"]
            raise MeshError(f"boundary surface {tag} is neither wall nor a cap (nearest cap: {near['role']} "
                            f"of branch {near['branch_id']}, r {near['radius']:.3f} mm; its points lie "
                            f"{np.abs(off @ near['normal']).max():.3f} mm off that plane and "
                            f"{np.linalg.norm(off, axis=1).max():.3f} mm from its centre)")
        for kind, f in idx.items():
            if cap is not None:  # planar: orient each facet by the cap normal
                flip = _facet_normals(xyz, f) @ caps[cap]["normal"] < 0
                f = f.copy()
                f[flip] = f[flip][:, ::-1]
                gid, bid = groups[names[cap]], caps[cap]["branch_id"]
                cap_area[cap] += float(_facet_areas(xyz, f).sum())
                b = np.full(len(f), bid)
            else:
                gid = WALL_ID
                b = (np.full(len(f), face.branch_id) if face is not None
                     else field.query(xyz[f].mean(axis=1))[1])
            facets.setdefault(kind, []).append(f)
            ids.setdefault(kind, []).append(np.full(len(f), gid))
            branch.setdefault(kind, []).append(b)
    # compact the nodes to those in use
    all_f = {k: np.vstack(v) for k, v in facets.items()}
    all_c = {k: np.vstack([_lookup(tags, c) for c in v]) for k, v in cells.items()}
    used = np.unique(np.concatenate([v.ravel() for v in (*all_f.values(), *all_c.values())]))
    remap = np.full(len(xyz), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    boundaries = [Boundary(names[i], groups[names[i]], c["role"], c["branch_id"], c["name"],
                           np.asarray(c["centre"], float), np.asarray(c["normal"], float), float(cap_area[i]),
                           exact.get(i, float(np.pi * c["radius"] ** 2)), float(c["radius"]),
                           float(c["extension_mm"]))
                  for i, c in enumerate(caps)]
    return CFDMesh(xyz[used], {k: remap[v] for k, v in all_c.items()},
                   {k: remap[v] for k, v in all_f.items()},
                   {k: np.concatenate(v) for k, v in ids.items()},
                   {k: np.concatenate(v) for k, v in branch.items()}, groups, boundaries)


# ---------------------------------------------------------------- public API
def surface_mesh(source: Any, edge_factor: float = 0.3, flow_extensions: float | Sequence[float] = 0.0, *,
                 min_size: float | None = None, max_size: float | None = None, cap_segments: int = 32,
                 optimize: bool = True, threads: int | None = None, verbose: bool = False,
                 progress: bool = False, gmsh_options: dict[str, float] | None = None,
                 separate_contacts: bool = True, crease_radius: float = CREASE_RADIUS) -> Any:
    """A closed, labelled triangle surface of a vessel tree for CFD.

    Parameters
    ----------
    source : VesselSolid, VesselTree or path
        See :func:`load_solid`.
    edge_factor : float
        Target edge length as a multiple of the local vessel radius (vmtk's
        edge length factor; 0.3 gives about 21 edges around a vessel).
    flow_extensions : float or (float, float)
        Straight cylindrical extensions in diameters at the inlet and outlets,
        added to the B-rep before meshing.
    min_size, max_size : float, optional
        Bounds on the edge length (mm); default half the smallest and twice the
        largest target.
    cap_segments : int
        At least this many edges around each cap rim (keeps the meshed cap area
        within 1% of the exact disc).
    optimize : bool
        Let gmsh optimise the elements.
    threads : int, optional
        Threads gmsh may use (default all cores).
    verbose : bool
        Let gmsh print its log.
    progress : bool
        Show a progress bar over the stages.
    gmsh_options : dict, optional
        Further gmsh options (``{"Mesh.Algorithm3D": 10}``), set after vesselcad's.
    separate_contacts : bool
        Move vessels that touch away from a junction apart first (trees only;
        see :func:`load_solid`).
    crease_radius : float
        Round knife-edge junction creases with fillets of this share of the
        vessel radius first (0: keep them; see :func:`load_solid`).

    Returns
    -------
    trimesh.Trimesh
        Watertight, outward-oriented triangles. ``face_attributes['label']``:
        1 wall, 2 inlet, 3... outlets (``metadata['groups']`` maps names to
        these ids); ``face_attributes['branch']``: branch id; ``metadata
        ['boundaries']``: each inlet/outlet with id, centre, normal, area and
        branch; ``metadata['cfd_mesh']``: the :class:`CFDMesh` (for writing
        .msh/.vtu and the boundary-condition sidecar).

    Raises
    ------
    MeshError
        gmsh could not mesh the solid.
    """
    mesh = _mesh(source, volume=False, edge_factor=edge_factor, min_size=min_size, max_size=max_size,
                 flow_extensions=flow_extensions, cap_segments=cap_segments, boundary_layers=0,
                 first_layer=0.02, first_layer_mm=None, growth=1.2, optimize=optimize, threads=threads,
                 verbose=verbose, progress=progress, gmsh_options=gmsh_options,
                 separate_contacts=separate_contacts, crease_radius=crease_radius)
    tm = mesh.surface()
    tm.metadata["cfd_mesh"] = mesh
    return tm


def volume_mesh(source: Any, edge_factor: float = 0.3, flow_extensions: float | Sequence[float] = 0.0, *,
                boundary_layers: int = 0, first_layer: float = 0.02, first_layer_mm: float | None = None,
                growth: float = 1.2, min_size: float | None = None, max_size: float | None = None,
                cap_segments: int = 32, optimize: bool = True, threads: int | None = None,
                verbose: bool = False, progress: bool = False, gmsh_options: dict[str, float] | None = None,
                separate_contacts: bool = True, crease_radius: float = CREASE_RADIUS) -> CFDMesh:
    """A tetrahedral (and, with boundary layers, prismatic) volume mesh of a vessel tree.

    Parameters
    ----------
    source, edge_factor, flow_extensions, min_size, max_size, cap_segments, optimize, threads, verbose, \
progress, gmsh_options, separate_contacts, crease_radius
        As for :func:`surface_mesh`.
    boundary_layers : int
        Number of prism layers along the wall (0: tetrahedra only).
    first_layer : float
        Thickness of the first layer as a fraction of the local radius.
    first_layer_mm : float, optional
        Thickness of the first layer in mm, the same everywhere (overrides
        ``first_layer``).
    growth : float
        Thickness ratio of successive layers.

    Returns
    -------
    CFDMesh
        Physical groups ``fluid``, ``wall``, ``inlet``, ``outlet_1..k``; element
        quality in ``quality``; write with :meth:`CFDMesh.write`.

    Raises
    ------
    MeshError
        gmsh could not mesh the solid.
    """
    return _mesh(source, volume=True, edge_factor=edge_factor, min_size=min_size, max_size=max_size,
                 flow_extensions=flow_extensions, cap_segments=cap_segments, boundary_layers=boundary_layers,
                 first_layer=first_layer, first_layer_mm=first_layer_mm, growth=growth, optimize=optimize,
                 threads=threads, verbose=verbose, progress=progress, gmsh_options=gmsh_options,
                 separate_contacts=separate_contacts, crease_radius=crease_radius)
