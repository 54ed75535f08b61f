"""Writing CFD meshes: gmsh .msh (2.2 / 4.1), VTU/VTK/XDMF (meshio), named STL patches, sidecar JSON."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ArgumentError, OutputError
from ..io.atomic import atomic_path, atomic_write_text

__all__ = ["write_mesh", "sidecar_path", "write_stl_patches"]

_GMSH_CODE = {"triangle": 2, "quad": 3, "tetra": 4, "wedge": 6, "pyramid": 7}
_MESHIO = {".vtu": "vtu", ".vtk": "vtk", ".xdmf": "xdmf"}
_SURFACE_ONLY = {".ply", ".obj", ".glb", ".off"}


def sidecar_path(path: str | os.PathLike) -> Path:
    """``mesh.msh`` -> ``mesh.bc.json`` (the boundary-condition sidecar beside a mesh)."""
    p = Path(path)
    return p.with_name(p.stem + ".bc.json")


def write_mesh(mesh: Any, path: str | os.PathLike, msh_version: float = 4.1,
               boundary_conditions: bool = True) -> Path:
    """Write a :class:`~vesselcad.cfd.CFDMesh` (see :meth:`CFDMesh.write`)."""
    target = Path(path)
    suffix = target.suffix.lower()
    if msh_version not in (2.2, 4.1):
        raise ArgumentError(f"msh_version: expected 2.2 or 4.1, got {msh_version!r}")
    if suffix == ".msh":
        _write_msh(mesh, target, msh_version)
    elif suffix in _MESHIO:
        m = mesh.to_meshio()
        with atomic_path(target, keep_name=True) as tmp:
            try:
                m.write(tmp, file_format=_MESHIO[suffix])
            except Exception as exc:  # meshio raises assorted errors
                raise OutputError(f"{target}: meshio could not write it ({exc})") from None
            # XDMF keeps its arrays in a sibling .h5 (same stem) that travels along
            h5 = tmp.with_suffix(".h5")
            if h5.exists():
                os.replace(h5, target.with_suffix(".h5"))
    elif suffix == ".stl":
        if mesh.is_volume:
            raise ArgumentError(f"{target}: STL holds surfaces only; write a volume mesh as .msh, .vtu "
                                "or .xdmf")
        write_stl_patches(mesh, target)
    elif suffix in _SURFACE_ONLY:
        if mesh.is_volume:
            raise ArgumentError(f"{target}: {suffix} holds surfaces only; write a volume mesh as .msh, .vtu "
                                "or .xdmf")
        data = mesh.surface().export(file_type=suffix[1:])
        with atomic_path(target) as tmp:
            tmp.write_bytes(data if isinstance(data, bytes) else data.encode())
    else:
        raise ArgumentError(f"{target}: unknown mesh format {suffix!r}; use .msh, .vtu, .vtk, .xdmf"
                            + ("" if mesh.is_volume else ", .stl, .ply, .obj, .glb"))
    if not boundary_conditions:
        return target
    side = sidecar_path(target)
    doc = mesh.boundary_conditions()
    doc["mesh_file"] = target.name
    atomic_write_text(side, json.dumps(doc, indent=2) + "\n")
    return side


def _write_msh(mesh: Any, target: Path, version: float) -> None:
    """A discrete gmsh model holding the arrays, with named physical groups, written by gmsh."""
    import gmsh

    from .mesher import _gmsh_session

    with _gmsh_session(False, 1) as g, atomic_path(target, keep_name=True) as tmp:
        node_tags = np.arange(1, len(mesh.points) + 1)
        # one discrete surface per group (gmshToFoam makes one patch per physical surface)
        gids = [gid for name, gid in mesh.groups.items() if name != "fluid"]
        surfaces = {gid: k + 1 for k, gid in enumerate(gids)}
        for ent in surfaces.values():
            g.model.addDiscreteEntity(2, ent)
        if mesh.is_volume:
            g.model.addDiscreteEntity(3, 1, list(surfaces.values()))
            g.model.mesh.addNodes(3, 1, node_tags, mesh.points.ravel())
        else:  # the nodes live on the wall entity; the caps' elements refer to them
            g.model.mesh.addNodes(2, surfaces[min(surfaces)], node_tags, mesh.points.ravel())
        next_el = 1
        for gid, ent in surfaces.items():
            for kind, f in mesh.facets.items():
                sel = f[mesh.facet_ids[kind] == gid]
                if len(sel):
                    tags = np.arange(next_el, next_el + len(sel))
                    g.model.mesh.addElementsByType(ent, _GMSH_CODE[kind], tags, (sel + 1).ravel())
                    next_el += len(sel)
        if mesh.is_volume:
            for kind, c in mesh.cells.items():
                tags = np.arange(next_el, next_el + len(c))
                g.model.mesh.addElementsByType(1, _GMSH_CODE[kind], tags, (c + 1).ravel())
                next_el += len(c)
            g.model.addPhysicalGroup(3, [1], 1, name="fluid")
        by_group = {gid: [ent] for gid, ent in surfaces.items()}
        for name, gid in mesh.groups.items():
            if name != "fluid":
                g.model.addPhysicalGroup(2, by_group[gid], gid, name=name)
        gmsh.option.setNumber("Mesh.MshFileVersion", version)
        gmsh.option.setNumber("Mesh.Binary", 0)
        gmsh.option.setNumber("Mesh.SaveAll", 0)
        gmsh.write(str(tmp))


def write_stl_patches(mesh: Any, path: str | os.PathLike) -> None:
    """ASCII STL with one ``solid <group name>`` per group (wall, inlet, outlet_k).

    OpenFOAM's snappyHexMesh and cfMesh read each named solid as a patch.
    """
    target = Path(path)
    surf = mesh.surface()
    names = {gid: name for name, gid in mesh.groups.items() if name != "fluid"}
    label = surf.face_attributes["label"]
    normals = surf.face_normals
    tri = surf.vertices[surf.faces]
    out = []
    for gid in sorted(names):
        sel = np.flatnonzero(label == gid)
        out.append(f"solid {names[gid]}\n")
        rows = np.concatenate([normals[sel], tri[sel].reshape(-1, 9)], axis=1)
        out.extend(
            "facet normal {:.9e} {:.9e} {:.9e}\n outer loop\n"
            "  vertex {:.9e} {:.9e} {:.9e}\n  vertex {:.9e} {:.9e} {:.9e}\n  vertex {:.9e} {:.9e} {:.9e}\n"
            " endloop\nendfacet\n".format(*r) for r in rows.tolist())
        out.append(f"endsolid {names[gid]}\n")
    atomic_write_text(target, "".join(out))
