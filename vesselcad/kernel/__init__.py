"""OCCT door of vesselcad: every OCP/build123d call lives under this package.

- :mod:`.nurbs`: numpy/scipy splines to ``Geom_BSplineCurve``/``Geom_BSplineSurface``,
  the extruded ray surfaces of the paper's Fig. 5b, faces, validity checks.
- :mod:`.intersect`: the surface-surface intersection of two extruded surfaces.
- :mod:`.centreline`: :class:`Centreline3D`, the 3D centreline as a B-spline curve.
- :mod:`.pipes`: variable-radius NURBS pipes (exact circular sections, rotation-minimizing frames).
- :mod:`.solid`: the fused tree solid (:class:`VesselSolid`), checks, STEP/STL/GLB/BREP, interop.
- :mod:`.creases`: sharp junction creases of the solid and rounding them (fillets) for CFD meshes.
"""

from .centreline import Centreline3D
from .solid import BranchPipe, FaceTag, VesselSolid, fuse_pipes

__all__ = ["Centreline3D", "VesselSolid", "BranchPipe", "FaceTag", "fuse_pipes"]
