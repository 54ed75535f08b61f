"""Surface-surface intersection of two extruded ray surfaces with OCCT's intersector.

Each call intersects two trimmed pieces of the views' extruded B-spline
surfaces on which the epipolar correspondence is one-to-one, so there is
exactly one intersection curve. OCCT's parametric-parametric intersector
(``IntPatch_Intersection``, the engine behind ``GeomAPI_IntSS``) walks that
curve from a start point with a bounded step; every walking point lies on
both surfaces within the tolerance and carries its (u, v) on each. We use the
walking line directly rather than ``GeomAPI_IntSS``'s approximated curve:
the same intersector, ten times faster, and the surface parameters come free.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from OCP.Adaptor3d import Adaptor3d_TopolTool
from OCP.Geom import Geom_BSplineSurface, Geom_RectangularTrimmedSurface
from OCP.GeomAdaptor import GeomAdaptor_Surface
from OCP.IntPatch import IntPatch_Intersection

__all__ = ["PiecePair", "intersect_piece"]

#: Intersection tolerance (mm): far below any pixel.
TOL_MM = 1e-7
#: Largest parametric step of the walk (fraction of the ranges) and its chordal
#: deflection (mm): the walking points are exact; between them the caller
#: interpolates and polishes onto both surfaces (``vesselcad.centreline3d``).
UV_MAX_STEP = 0.05
FLECHE = 1e-2


@dataclass(frozen=True)
class PiecePair:
    """Parameter windows of one well-conditioned piece in each view, and a start point.

    ``u`` is the 2D curve parameter (px of chord length), ``depth`` is the V
    parameter of the extruded surfaces (mm from the source along the central ray).
    """

    u_a: tuple[float, float]
    u_b: tuple[float, float]
    depth_a: tuple[float, float]
    depth_b: tuple[float, float]
    start: tuple[float, float, float, float]  # (u_a, depth_a, u_b, depth_b)


def intersect_piece(surface_a: Geom_BSplineSurface, surface_b: Geom_BSplineSurface, piece: PiecePair
                    ) -> list[np.ndarray]:
    """Walk the intersection of the two surfaces restricted to one piece pair.

    Returns
    -------
    list of numpy.ndarray, shape (n, 7)
        One array per walking line: x, y, z (LPS mm), u_a, depth_a, u_b, depth_b.
    """
    ta = Geom_RectangularTrimmedSurface(surface_a, *piece.u_a, *piece.depth_a)
    tb = Geom_RectangularTrimmedSurface(surface_b, *piece.u_b, *piece.depth_b)
    ga, gb = GeomAdaptor_Surface(ta), GeomAdaptor_Surface(tb)
    da, db = Adaptor3d_TopolTool(ga), Adaptor3d_TopolTool(gb)
    inter = IntPatch_Intersection()
    inter.SetTolerances(TOL_MM, TOL_MM, UV_MAX_STEP, FLECHE)
    ua, va, ub, vb = (float(x) for x in piece.start)
    inter.Perform(ga, da, gb, db, ua, va, ub, vb, TOL_MM, TOL_MM)
    lines: list[np.ndarray] = []
    if not inter.IsDone():
        return lines
    for i in range(1, inter.NbLines() + 1):
        line = inter.Line(i)
        if not hasattr(line, "NbPnts"):
            continue
        n = line.NbPnts()
        out = np.empty((n, 7))
        for k in range(1, n + 1):
            p = line.Point(k)
            xyz = p.Value()
            out[k - 1, :3] = (xyz.X(), xyz.Y(), xyz.Z())
            out[k - 1, 3:] = p.Parameters()
        if n >= 2:
            lines.append(out)
    return lines
