"""Headless pictures of vessel meshes (matplotlib, flat shading, coloured by branch)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .errors import ArgumentError
from .io.atomic import atomic_path

__all__ = ["render_mesh"]


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
