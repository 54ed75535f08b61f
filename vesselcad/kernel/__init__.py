"""OCCT door of vesselcad: every OCP/build123d call lives under this package.

- :mod:`.nurbs`: numpy/scipy splines to ``Geom_BSplineCurve``/``Geom_BSplineSurface``,
  the extruded ray surfaces of the paper's Fig. 5b, faces, validity checks.
- :mod:`.intersect`: the surface-surface intersection of two extruded surfaces.
- :mod:`.centreline`: :class:`Centreline3D`, the 3D centreline as a B-spline curve.
"""

from .centreline import Centreline3D

__all__ = ["Centreline3D"]
