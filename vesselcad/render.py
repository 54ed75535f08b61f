"""Headless pictures of vessel meshes (matplotlib, flat shading, coloured by branch)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .errors import ArgumentError
from .io.atomic import atomic_path

__all__ = ["render_mesh", "render_cfd_mesh", "section_polygons"]


def render_mesh(mesh: Any, path: str | os.PathLike, *, title: str = "", views: tuple = ((20, -60), (5, 30)),
                max_faces: int = 60000, dpi: int = 110, color_by: str = "branch",
                labels: dict[int, str] | None = None, edge_width: float = 0.0) -> None:
    """Render a triangle mesh to a PNG from one or more viewpoints, atomically.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        E.g. ``VesselSolid.to_trimesh()``; ``face_attributes['branch']``, when
        present, colours the triangles by branch.
    path : str or path-like
        Output PNG.
    title : str
    views : sequence of (elevation_deg, azimuth_deg)
        One panel per viewpoint (matplotlib's 3D camera angles).
    max_faces : int
        Larger meshes are thinned to this many evenly spaced triangles, which
        leaves gaps: pass a coarser tessellation for pictures instead.
    dpi : int
    color_by : str
        The ``face_attributes`` entry whose values colour the triangles.
    labels : dict of int -> str, optional
        Names of those values, drawn as a legend (e.g. a CFD mesh's groups).
    edge_width : float
        Line width of the triangle edges (0: none), to show a mesh's elements.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    faces = np.asarray(getattr(mesh, "faces", None))
    verts = np.asarray(getattr(mesh, "vertices", None))
    if faces.ndim != 2 or verts.ndim != 2 or len(faces) == 0:
        raise ArgumentError("mesh: expected a non-empty trimesh.Trimesh")
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-30)[:, None]
    attrs = getattr(mesh, "face_attributes", {}) or {}
    branch = np.asarray(attrs.get(color_by, np.zeros(len(faces), int)))
    if len(faces) > max_faces:
        keep = np.linspace(0, len(faces) - 1, max_faces).astype(int)
        tri, normals, branch = tri[keep], normals[keep], branch[keep]
    cmap = plt.get_cmap("tab20")
    values, codes = np.unique(branch, return_inverse=True)
    palette = np.asarray(cmap(np.arange(len(values)) % 20))[:, :3]
    if labels:  # named groups (a CFD mesh): grey wall, distinct colours for the caps
        others = iter(np.asarray(plt.get_cmap("tab10")(np.r_[2, 3, 1, 4, 0, 6, 8, 9, 5]))[:, :3])
        grey = (0.78, 0.78, 0.78)
        palette = np.array([grey if labels.get(int(v)) == "wall" else next(others, (0.3, 0.3, 0.3))
                            for v in values])
    base = palette[codes]
    fig = plt.figure(figsize=(5.2 * len(views), 5.2))
    lo, hi = verts.min(0), verts.max(0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    for k, (elev, azim) in enumerate(views, start=1):
        ax = fig.add_subplot(1, len(views), k, projection="3d")
        e, a = np.radians(elev), np.radians(azim)
        eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        light = eye + np.array([0.0, 0.0, 0.6])
        light /= np.linalg.norm(light)
        shade = 0.35 + 0.65 * np.abs(normals @ light)
        coll = Poly3DCollection(tri, facecolors=np.clip(base * shade[:, None], 0, 1), linewidths=edge_width,
                                edgecolors=(0.1, 0.1, 0.1, 0.6) if edge_width > 0 else None)
        ax.add_collection3d(coll)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            setter(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (L) mm")
        ax.set_ylabel("y (P) mm")
        ax.set_zlabel("z (H) mm")
        ax.tick_params(labelsize=7)
    if labels:
        from matplotlib.patches import Patch

        handles = [Patch(color=palette[i], label=labels.get(int(v), str(v))) for i, v in enumerate(values)]
        fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)


_CELL_EDGES = {
    "tetra": [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)],
    "wedge": [(0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)],
    "pyramid": [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)],
}


def section_polygons(points: np.ndarray, cells: dict[str, np.ndarray], origin: np.ndarray, normal: np.ndarray
                     ) -> dict[str, list[np.ndarray]]:
    """Cut volume cells by a plane: the polygon of each cut cell, in plane coordinates.

    Parameters
    ----------
    points : (N, 3) array
    cells : dict of meshio cell type -> (n, k) node indices
    origin, normal : (3,) arrays
        The plane.

    Returns
    -------
    dict of cell type -> list of (m, 2) arrays
        Polygons in an orthonormal (e1, e2) frame of the plane.
    """
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    signed = (np.asarray(points, float) - origin) @ n
    out: dict[str, list[np.ndarray]] = {}
    for kind, c in cells.items():
        if kind not in _CELL_EDGES or len(c) == 0:
            continue
        s = signed[c]
        cut = c[(s.min(axis=1) < 0) & (s.max(axis=1) > 0)]
        if len(cut) == 0:
            continue
        a = np.array([i for i, _ in _CELL_EDGES[kind]])
        b = np.array([j for _, j in _CELL_EDGES[kind]])
        sa, sb = signed[cut[:, a]], signed[cut[:, b]]
        crosses = (sa < 0) != (sb < 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(crosses, sa / (sa - sb), np.nan)
        p = points[cut[:, a]] + t[..., None] * (points[cut[:, b]] - points[cut[:, a]])  # (m, E, 3)
        uv = np.stack([(p - origin) @ e1, (p - origin) @ e2], axis=-1)
        centre = np.nanmean(uv, axis=1, keepdims=True)
        ang = np.arctan2(uv[..., 1] - centre[..., 1], uv[..., 0] - centre[..., 0])
        order = np.argsort(np.where(crosses, ang, np.inf), axis=1)
        uv = np.take_along_axis(uv, order[..., None], axis=1)
        counts = crosses.sum(axis=1)
        out[kind] = [poly[:k] for poly, k in zip(uv, counts, strict=True)]
    return out


def render_cfd_mesh(mesh: Any, path: str | os.PathLike, *, origin: np.ndarray, normal: np.ndarray,
                    title: str = "", dpi: int = 120) -> None:
    """Picture of a CFD mesh: the labelled boundary, a close-up of the inlet and a section.

    Parameters
    ----------
    mesh : vesselcad.cfd.CFDMesh
    path : str or path-like
        Output PNG (written atomically).
    origin, normal : (3,) arrays
        The section plane; boundary-layer prisms and tetrahedra get their own colours.
    title : str
    dpi : int
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Patch
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    surf = mesh.surface()
    names = {gid: name for name, gid in mesh.groups.items()}
    label_all = np.asarray(surf.face_attributes["label"])
    tri_all = surf.vertices[surf.faces]
    values = np.unique(label_all)
    # no greys among the caps: tab20 without its grey pair, cycled
    caps_cmap = np.asarray(plt.get_cmap("tab20")(np.r_[4, 6, 2, 8, 0, 12, 16, 18, 10, 5, 7, 3, 9, 1, 13, 17,
                                                       19, 11]))[:, :3]
    others = (caps_cmap[i % len(caps_cmap)] for i in range(len(values)))
    grey = (0.8, 0.8, 0.8)
    palette = {int(v): grey if names.get(int(v)) == "wall" else tuple(next(others)) for v in values}
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    fig = plt.figure(figsize=(15, 5.4))

    def panel(k: int, centre: np.ndarray, half: float, elev: float, azim: float, edges: float, name: str):
        ax = fig.add_subplot(1, 3, k, projection="3d")
        keep = np.all(np.abs(tri_all.mean(axis=1) - centre) < half, axis=1)
        tri, lab = tri_all[keep], label_all[keep]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-30)[:, None]
        shade = 0.45 + 0.55 * np.abs(nrm @ light)
        col = np.array([palette[int(v)] for v in lab]).reshape(-1, 3) * shade[:, None]
        ax.add_collection3d(Poly3DCollection(tri, facecolors=np.clip(col, 0, 1), linewidths=edges,
                                             edgecolors=(0.15, 0.15, 0.15, 0.6) if edges else None))
        for setter, cc in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            setter(cc - half, cc + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x (L) mm", fontsize=8)
        ax.set_ylabel("y (P) mm", fontsize=8)
        ax.set_zlabel("z (H) mm", fontsize=8)
        ax.set_title(name, fontsize=9)

    lo, hi = surf.vertices.min(0), surf.vertices.max(0)
    panel(1, (lo + hi) / 2, (hi - lo).max() / 2 * 1.02, 20, -60, 0.0, "boundary by group")
    inlet = mesh.boundaries[0]
    nrm = inlet.normal / np.linalg.norm(inlet.normal)
    elev = float(np.degrees(np.arcsin(np.clip(nrm[2], -1, 1))))
    azim = float(np.degrees(np.arctan2(nrm[1], nrm[0])))
    panel(2, inlet.centre - 1.5 * inlet.radius_mm * nrm, 2.2 * inlet.radius_mm, 0.6 * elev + 10, azim + 25,
          0.2, f"{inlet.name} ({inlet.branch}), close up")
    ax3 = fig.add_subplot(1, 3, 3)
    polys = section_polygons(mesh.points, mesh.cells, np.asarray(origin, float), np.asarray(normal, float))
    # keep the vessel the plane was put across (within 3 radii of the origin)
    reach = 3.0 * float(np.max([b.radius_mm for b in mesh.boundaries] or [np.inf]))
    polys = {k: [p for p in v if np.linalg.norm(p.mean(axis=0)) < reach] for k, v in polys.items()}
    polys = {k: v for k, v in polys.items() if v}
    colour = {"tetra": (0.62, 0.76, 0.96), "wedge": (0.99, 0.86, 0.45), "pyramid": (0.7, 0.9, 0.6)}
    for kind, ps in polys.items():
        ax3.add_collection(PolyCollection(ps, facecolors=colour[kind], edgecolors=(0.1, 0.1, 0.1),
                                          linewidths=0.25))
    ax3.autoscale()
    ax3.set_aspect("equal")
    ax3.set_xlabel("mm")
    ax3.set_title("section: " + ", ".join(f"{len(v)} {k}" for k, v in polys.items()), fontsize=9)
    handles = [Patch(color=palette[int(v)], label=names.get(int(v), str(v))) for v in values]
    handles += [Patch(color=colour[k], label=k) for k in polys]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 10), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)
