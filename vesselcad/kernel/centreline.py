"""``Centreline3D``: a reconstructed 3D centreline as an OCCT B-spline curve."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from OCP.GCPnts import GCPnts_AbscissaPoint
from OCP.Geom import Geom_BSplineCurve
from OCP.GeomAdaptor import GeomAdaptor_Curve
from OCP.TopoDS import TopoDS_Face
from scipy import interpolate

from ..errors import ArgumentError
from .nurbs import bspline_curve, make_edge

__all__ = ["Centreline3D"]


@dataclass(eq=False)
class Centreline3D:
    """A 3D vessel centreline, ordered from the proximal end (the first input point).

    Attributes
    ----------
    curve : OCP.Geom.Geom_BSplineCurve
        The curve for OCCT; its parameter is the chord length (px) of the
        view-A 2D curve, so ``curve.Value(u)`` projects onto that curve at ``u``
        (for a vessel seen end-on in view A, the view-B curve's chord length).
    method : str
        ``"nurbs"`` (surface intersection) or ``"epipolar"`` (point-wise baseline).
    ill_conditioned_fraction : float
        Share of the branch (view-A length) where the 2D tangent runs within
        ``min_angle_deg`` of the epipolar line, bridged from its neighbours.
    ill_conditioned_spans : list of (float, float)
        Those spans as ``(start, end)`` fractions of the view-A curve.
    n_pieces : int
        Well-conditioned pieces intersected (or matched) independently.
    noise_px : (float, float)
        2D noise sigma used to smooth each view's input.
    faces : (TopoDS_Face, TopoDS_Face) or None
        The two extruded faces of the whole branch (nurbs method).
    warnings : list of str
    """

    spline: interpolate.BSpline
    method: str = "nurbs"
    ill_conditioned_fraction: float = 0.0
    ill_conditioned_spans: list[tuple[float, float]] = field(default_factory=list)
    n_pieces: int = 0
    noise_px: tuple[float, float] = (0.0, 0.0)
    faces: tuple[TopoDS_Face, TopoDS_Face] | None = None
    warnings: list[str] = field(default_factory=list)
    _curve: Geom_BSplineCurve | None = field(default=None, repr=False)

    @property
    def curve(self) -> Geom_BSplineCurve:
        """The OCCT ``Geom_BSplineCurve`` (built once, exactly from :attr:`spline`)."""
        if self._curve is None:
            self._curve = bspline_curve(self.spline)
        return self._curve

    @property
    def domain(self) -> tuple[float, float]:
        """Parameter range of the curve."""
        k = self.spline.k
        return float(self.spline.t[k]), float(self.spline.t[-k - 1])

    @property
    def length(self) -> float:
        """Arc length in mm (OCCT's adaptive integration)."""
        return float(GCPnts_AbscissaPoint.Length_s(GeomAdaptor_Curve(self.curve)))

    def __call__(self, u: Any) -> np.ndarray:
        """Points at curve parameters ``u``, shape (..., 3)."""
        return self.spline(np.asarray(u, dtype=float))

    def _arclength_table(self, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
        u = np.linspace(*self.domain, n)
        p = self.spline(u)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        return u, s

    def sample(self, n: int) -> np.ndarray:
        """``n`` points equally spaced in arc length from the proximal end, shape (n, 3) mm."""
        if not isinstance(n, (int, np.integer)) or n < 2:
            raise ArgumentError(f"n: expected an integer >= 2, got {n!r}")
        u, s = self._arclength_table(max(2000, 4 * int(n)))
        return self.spline(np.interp(np.linspace(0.0, s[-1], int(n)), s, u))

    def sample_every(self, step_mm: float = 0.5) -> np.ndarray:
        """Points every ``step_mm`` of arc length (both ends included), shape (m, 3)."""
        if not step_mm > 0:
            raise ArgumentError(f"step_mm: expected a positive number, got {step_mm!r}")
        u, s = self._arclength_table()
        n = max(int(np.ceil(s[-1] / step_mm)) + 1, 2)
        return self.spline(np.interp(np.linspace(0.0, s[-1], n), s, u))

    def to_build123d(self) -> Any:
        """The curve as a build123d ``Edge``."""
        import build123d

        return build123d.Edge(make_edge(self.curve))

    def __repr__(self) -> str:
        return (f"Centreline3D(method={self.method!r}, length={self.length:.2f} mm, "
                f"poles={len(self.spline.t) - self.spline.k - 1}, "
                f"ill_conditioned={self.ill_conditioned_fraction:.0%})")
