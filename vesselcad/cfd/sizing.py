"""Local vessel radius anywhere near a tree, for element sizes that follow the radius.

vmtk sizes a vessel mesh by an edge length proportional to the distance to the
centreline; :class:`RadiusField` gives the same from the spines and radius laws
the solid was swept along (and from its flow extensions), and
:meth:`RadiusField.size_callback` turns it into a fast gmsh mesh-size callback.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ArgumentError

__all__ = ["RadiusField"]

#: Candidates looked at per query: the owner of a point is the vessel whose
#: surface is relatively closest (smallest distance / radius), not simply the
#: nearest axis sample (a small branch's axis can be nearer a big parent's wall).
_K = 8


class RadiusField:
    """Radius of the vessel that a point belongs to.

    Parameters
    ----------
    points : (N, 3) array
        Centreline samples (mm).
    radius : (N,) array
        Vessel radius at each sample (mm).
    branch : (N,) int array, optional
        Branch id of each sample.
    """

    def __init__(self, points: np.ndarray, radius: np.ndarray, branch: np.ndarray | None = None):
        p = np.asarray(points, float)
        r = np.asarray(radius, float).ravel()
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or len(r) != len(p):
            raise ArgumentError(f"RadiusField: expected (N,3) points and (N,) radii with N >= 2, got "
                                f"{p.shape} and {r.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(r)) and np.all(r > 0)):
            raise ArgumentError("RadiusField: points must be finite and radii positive")
        self.points = p
        self.radius = r
        self.branch = np.zeros(len(p), int) if branch is None else np.asarray(branch, int).ravel()
        self._tree = cKDTree(p)

    @classmethod
    def from_solid(cls, solid: Any, step_mm: float = 0.2) -> RadiusField:
        """Samples of the spines and radius laws of a :class:`~vesselcad.kernel.VesselSolid`.

        Branches left out of the solid are skipped; flow extensions are sampled
        along their axes with the end radius.
        """
        if not solid.specs:
            raise ArgumentError("RadiusField.from_solid: the solid carries no spines (make it with "
                                "VesselTree.solid())")
        pts, rad, ids = [], [], []
        for spec in solid.specs:
            if spec["id"] in solid.failed:
                continue
            spine, law = spec["spine"], spec["radius"]
            a, b = float(spine.t[spine.k]), float(spine.t[-spine.k - 1])
            a += float(spec.get("neck_mm", 0.0))  # a necked start inside the parent is not this vessel's
            u = np.linspace(a, b, max(int(np.ceil((b - a) / step_mm)), 2) + 1)
            pts.append(spine(u))
            rad.append(np.ravel(law(u)))
            ids.append(np.full(len(u), spec["id"]))
        for cap in solid.caps():
            length = cap["extension_mm"]
            if length > 0:
                s = np.linspace(0.0, length, max(int(np.ceil(length / step_mm)), 1) + 1)
                start = cap["centre"] - length * cap["normal"]
                pts.append(start + s[:, None] * cap["normal"])
                rad.append(np.full(len(s), cap["radius"]))
                ids.append(np.full(len(s), cap["branch_id"]))
        return cls(np.vstack(pts), np.concatenate(rad), np.concatenate(ids))

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Radius, branch id and nearest axis point of the vessel each point belongs to.

        Parameters
        ----------
        points : (M, 3) array

        Returns
        -------
        radius : (M,) array
        branch : (M,) int array
        axis : (M, 3) array
            The centreline sample the point was assigned to.
        """
        q = np.atleast_2d(np.asarray(points, float))
        k = min(_K, len(self.points))
        d, i = self._tree.query(q, k=k)
        d, i = d.reshape(len(q), k), i.reshape(len(q), k)
        best = i[np.arange(len(q)), np.argmin(d / self.radius[i], axis=1)]
        return self.radius[best], self.branch[best], self.points[best]

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Radius (mm) of the vessel each of ``points`` (M, 3) belongs to."""
        return self.query(points)[0]

    def size_callback(self, edge_factor: float, min_size: float, max_size: float,
                      overrides: dict[tuple[int, int], Callable[[float], float]] | None = None,
                      refine: tuple[np.ndarray, np.ndarray] | None = None, grading: float = 0.3
                      ) -> Callable[[int, int, float, float, float, float], float]:
        """A gmsh ``setSizeCallback`` function: ``edge_factor`` x local radius, clipped.

        The field is tabulated once on a voxel grid around the vessels (spacing
        a quarter of the smallest radius), so that each of the hundreds of
        thousands of calls gmsh makes costs one array lookup; points off the
        grid fall back to an exact query.

        Parameters
        ----------
        edge_factor : float
            Target edge length / local radius.
        min_size, max_size : float
            Bounds on the edge length (mm).
        overrides : dict, optional
            ``{(dim, tag): f}`` where ``f(size) -> size`` adjusts the size on one
            gmsh entity (used to resolve cap rims finely).
        refine : ((M, 3) array, (M,) array), optional
            Points that need elements of the given size (the ends of very short
            B-rep edges); the size grows away from them by ``grading`` per mm,
            so that the elements around a short edge stay well shaped.
        grading : float
            Growth of the size away from the ``refine`` points (mm per mm).
        """
        overrides = overrides or {}
        h = max(0.25 * float(self.radius.min()), 0.02)
        lo = self.points.min(axis=0) - self.radius.max() - 2 * h
        hi = self.points.max(axis=0) + self.radius.max() + 2 * h
        shape = np.ceil((hi - lo) / h).astype(int) + 1
        if int(np.prod(shape)) > 60_000_000:  # a huge, thin tree: coarser grid
            h *= (np.prod(shape) / 60_000_000) ** (1 / 3)
            shape = np.ceil((hi - lo) / h).astype(int) + 1
        grid = np.full(tuple(shape), np.nan, dtype=np.float32)
        # Voxels within (radius + 4 voxels) of an axis sample: the only places gmsh asks.
        near = np.zeros(tuple(shape), dtype=bool)
        reach = np.ceil((self.radius + 4 * h) / h).astype(int)
        base = np.round((self.points - lo) / h).astype(int)
        for rr in np.unique(reach):
            o = np.arange(-rr, rr + 1)
            off = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
            off = off[np.linalg.norm(off, axis=1) <= rr + 1]
            sel = base[reach == rr]
            step = max(1, 2_000_000 // len(off))
            for c0 in range(0, len(sel), step):
                c = (sel[c0:c0 + step, None, :] + off[None, :, :]).reshape(-1, 3)
                c = c[np.all((c >= 0) & (c < shape), axis=1)]
                near[c[:, 0], c[:, 1], c[:, 2]] = True
        idx = np.argwhere(near)
        size = np.clip(edge_factor * self(lo + idx * h), min_size, max_size)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = size
        inv = 1.0 / h
        x0, y0, z0 = (float(v) for v in lo)
        nx, ny, nz = (int(v) for v in shape)
        exact = self
        ref_tree, ref_size = None, None
        near_ref = np.zeros((1, 1, 1), dtype=bool)
        near_pts: dict[int, list[tuple[float, float, float, float, float]]] = {}
        if refine is not None and len(refine[0]):
            ref_pts, ref_size = np.asarray(refine[0], float), np.asarray(refine[1], float)
            # A point listed several times (one per close partner) needs the least of its sizes.
            ref_pts, inv_ = np.unique(ref_pts, axis=0, return_inverse=True)
            least_size = np.full(len(ref_pts), np.inf)
            np.minimum.at(least_size, inv_.ravel(), ref_size)
            ref_size = least_size
            ref_tree = cKDTree(ref_pts)
            # graded sizes tabulated on the grid; exact queries only right next to the points
            d, m = ref_tree.query(lo + idx * h, distance_upper_bound=(max_size - ref_size.min()) / grading)
            ok = np.isfinite(d)
            graded = ref_size[m[ok]] + grading * d[ok]
            cur = grid[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
            grid[idx[ok, 0], idx[ok, 1], idx[ok, 2]] = np.minimum(cur, graded)
            near_ref = np.zeros(tuple(shape), dtype=bool)
            close = ok & (d <= 2 * h)
            near_ref[idx[close, 0], idx[close, 1], idx[close, 2]] = True
            # The points that can be nearest to any point of such a voxel: a point of the voxel
            # lies within r = 0.87 h of its centre, so its nearest refine point lies within
            # d + 2 r of the centre (d: the centre's nearest). Kept by distance from the centre,
            # with the least distance each can have from a point of the voxel.
            vox, dv = idx[close], d[close]
            centres = lo + vox * h
            r_vox = 0.5 * np.sqrt(3.0) * h
            cands = ref_tree.query_ball_point(centres, dv + 2.0 * r_vox + 1e-9)
            keys = ((vox[:, 0] * ny + vox[:, 1]) * nz + vox[:, 2]).tolist()
            for key, c, cs in zip(keys, centres, cands, strict=True):
                cs = np.asarray(cs, dtype=int)
                dc = np.linalg.norm(ref_pts[cs] - c, axis=1)
                o = np.argsort(dc, kind="stable")
                near_pts[key] = [(*ref_pts[m].tolist(), float(ref_size[m]), max(float(e) - r_vox, 0.0) ** 2)
                                 for m, e in zip(cs[o], dc[o], strict=True)]

        def callback(dim: int, tag: int, x: float, y: float, z: float, lc: float) -> float:
            i, j, k = int((x - x0) * inv + 0.5), int((y - y0) * inv + 0.5), int((z - z0) * inv + 0.5)
            inside = 0 <= i < nx and 0 <= j < ny and 0 <= k < nz
            s = float(grid[i, j, k]) if inside else float("nan")
            if s != s:  # NaN: not tabulated
                s = min(max(edge_factor * float(exact(np.array([[x, y, z]]))[0]), min_size), max_size)
            if ref_tree is not None:
                if not inside:
                    d, m = ref_tree.query((x, y, z))
                    s = min(s, float(ref_size[m] + grading * d))
                elif near_ref[i, j, k]:
                    # the nearest refine point, among the few that can be (no tree query: gmsh
                    # asks here up to a million times where a fillet brings short edges)
                    best, size = math.inf, 0.0
                    for px, py, pz, ps, least in near_pts[(i * ny + j) * nz + k]:
                        if least >= best:  # this one and all after it are farther
                            break
                        d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
                        if d2 < best:
                            best, size = d2, ps
                    s = min(s, size + grading * math.sqrt(best))
            f = overrides.get((dim, tag))
            if f is not None:
                s = f(s)
            return s if lc <= 0 else min(s, lc)  # lc: gmsh's own size (e.g. from short curves)

        return callback
