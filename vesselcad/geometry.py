"""C-arm projection geometry (pure numpy).

The convention is the one in ``docs/geometry.md``: patient coordinates are
DICOM LPS millimetres with the origin at the C-arm isocentre; a view with
PositionerPrimaryAngle ``alpha`` (LAO positive) and PositionerSecondaryAngle
``beta`` (cranial positive) has rotation ``R = Rz(alpha) @ Rx(-beta)``, the
detector on ``d = R @ (0, -1, 0)``, the X-ray source at ``-SOD * d``, image
columns along ``u = R @ (1, 0, 0)`` and image rows (downwards) along
``v = R @ (0, 0, -1)``. A 2D point is always ``(col, row)`` in pixels.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .errors import ArgumentError, GeometryError, InputFileError

__all__ = [
    "CArmView",
    "Reconstruction2View",
    "as_points",
    "triangulate",
    "reconstruction_error",
]

_VIEW_KEYS = (
    "primary_deg",
    "secondary_deg",
    "sid_mm",
    "sod_mm",
    "pixel_spacing_mm",
    "rows",
    "cols",
)


def as_points(points: Any, dim: int, name: str) -> np.ndarray:
    """Return ``points`` as a float64 array whose last axis has length ``dim``.

    Parameters
    ----------
    points : array_like
        Points of shape ``(..., dim)``; a single point of shape ``(dim,)`` is allowed.
    dim : int
        Required length of the last axis (2 for pixels, 3 for mm).
    name : str
        Argument name used in the error message.

    Returns
    -------
    numpy.ndarray
        The points as float64, same shape as given.

    Raises
    ------
    ArgumentError
        If the array cannot be converted or its last axis is not ``dim``.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ArgumentError(f"{name}: expected numbers of shape (..., {dim}), got {exc}") from None
    if arr.ndim == 0 or arr.shape[-1] != dim:
        raise ArgumentError(f"{name}: expected an array of shape (..., {dim}), got shape {arr.shape}")
    return arr


def _rot_z(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _finite_number(value: Any, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise GeometryError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(out):
        raise GeometryError(f"{name}: expected a finite number, got {value!r}")
    return out


@dataclass(frozen=True)
class CArmView:
    """Projective model of one C-arm view, matching the DICOM XA tags.

    Parameters
    ----------
    primary_deg : float
        PositionerPrimaryAngle (0018,1510) in degrees; LAO positive, RAO negative.
    secondary_deg : float
        PositionerSecondaryAngle (0018,1511) in degrees; cranial positive, caudal negative.
    sid_mm : float
        DistanceSourceToDetector (0018,1110) in mm.
    sod_mm : float
        DistanceSourceToPatient (0018,1111) in mm (source to isocentre).
    pixel_spacing_mm : tuple of float
        ImagerPixelSpacing (0018,1164) ``(row spacing, column spacing)`` in mm
        at the detector.
    rows, cols : int
        Image size in pixels.
    offset_mm : tuple of float, optional
        Position of the C-arm's isocentre in the patient frame (LPS mm),
        default ``(0, 0, 0)``. Non-zero when the patient or table moved
        between two runs: the whole C-arm (source and detector) is shifted by
        it. Set by geometry refinement; DICOM files never carry it.

    Examples
    --------
    >>> view = CArmView(primary_deg=30.0, secondary_deg=0.0, sid_mm=1100.0,
    ...                 sod_mm=750.0, pixel_spacing_mm=(0.3, 0.3), rows=512, cols=512)
    >>> view.project([0.0, 0.0, 0.0])
    array([255.5, 255.5])
    """

    primary_deg: float
    secondary_deg: float
    sid_mm: float
    sod_mm: float
    pixel_spacing_mm: tuple[float, float]
    rows: int
    cols: int
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "primary_deg", _finite_number(self.primary_deg, "primary_deg"))
        set_(self, "secondary_deg", _finite_number(self.secondary_deg, "secondary_deg"))
        set_(self, "sid_mm", _finite_number(self.sid_mm, "sid_mm"))
        set_(self, "sod_mm", _finite_number(self.sod_mm, "sod_mm"))
        if abs(self.secondary_deg) >= 90.0:
            raise GeometryError(
                f"secondary_deg: expected |angle| < 90 degrees, got {self.secondary_deg}"
            )
        if self.sod_mm <= 0 or self.sid_mm <= self.sod_mm:
            raise GeometryError(
                "sid_mm/sod_mm: expected 0 < sod_mm < sid_mm (the isocentre lies between "
                f"source and detector), got sid_mm={self.sid_mm}, sod_mm={self.sod_mm}"
            )
        try:
            spacing = tuple(float(s) for s in np.broadcast_to(self.pixel_spacing_mm, (2,)))
        except (TypeError, ValueError):
            raise GeometryError(
                "pixel_spacing_mm: expected (row_spacing, col_spacing) in mm, got "
                f"{self.pixel_spacing_mm!r}"
            ) from None
        if not all(math.isfinite(s) and s > 0 for s in spacing):
            raise GeometryError(f"pixel_spacing_mm: expected two positive numbers, got {spacing}")
        set_(self, "pixel_spacing_mm", spacing)
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or int(value) < 1:
                raise GeometryError(f"{name}: expected a positive integer, got {value!r}")
            set_(self, name, int(value))
        try:
            off = tuple(float(x) for x in np.asarray(self.offset_mm, dtype=float).reshape(3))
        except (TypeError, ValueError):
            raise GeometryError(f"offset_mm: expected three numbers (mm), got {self.offset_mm!r}") from None
        if not all(math.isfinite(x) for x in off):
            raise GeometryError(f"offset_mm: expected three finite numbers, got {off}")
        set_(self, "offset_mm", off)

    # ------------------------------------------------------------------ frames
    @property
    def rotation(self) -> np.ndarray:
        """``R = Rz(primary) @ Rx(-secondary)``, shape (3, 3)."""
        if "R" not in self._cache:
            self._cache["R"] = _rot_z(math.radians(self.primary_deg)) @ _rot_x(
                -math.radians(self.secondary_deg)
            )
        return self._cache["R"].copy()

    @property
    def detector_direction(self) -> np.ndarray:
        """Unit vector from the isocentre toward the detector centre, ``R @ (0,-1,0)``."""
        return self.rotation @ np.array([0.0, -1.0, 0.0])

    @property
    def col_axis(self) -> np.ndarray:
        """Unit vector along which the column index grows, ``R @ (1,0,0)``."""
        return self.rotation @ np.array([1.0, 0.0, 0.0])

    @property
    def row_axis(self) -> np.ndarray:
        """Unit vector along which the row index grows (image down), ``R @ (0,0,-1)``."""
        return self.rotation @ np.array([0.0, 0.0, -1.0])

    @property
    def source(self) -> np.ndarray:
        """X-ray source position in LPS mm, ``offset - SOD * d``."""
        return np.asarray(self.offset_mm) - self.sod_mm * self.detector_direction

    @property
    def detector_centre(self) -> np.ndarray:
        """Detector centre in LPS mm, ``offset + (SID - SOD) * d``."""
        return np.asarray(self.offset_mm) + (self.sid_mm - self.sod_mm) * self.detector_direction

    @property
    def magnification(self) -> float:
        """Geometric magnification at the isocentre, SID / SOD."""
        return self.sid_mm / self.sod_mm

    @property
    def mm_per_px(self) -> tuple[float, float]:
        """Pixel size ``(row, col)`` in mm at the isocentre plane."""
        dr, dc = self.pixel_spacing_mm
        return (dr / self.magnification, dc / self.magnification)

    @property
    def matrix(self) -> np.ndarray:
        """3x4 projection matrix mapping homogeneous LPS mm to ``(col, row, 1)``."""
        if "P" not in self._cache:
            d, u, v = self.detector_direction, self.col_axis, self.row_axis
            dr, dc = self.pixel_spacing_mm
            o = np.asarray(self.offset_mm)
            last = np.append(d, self.sod_mm - o @ d)  # w = (X - source) . d
            fc, fr = self.sid_mm / dc, self.sid_mm / dr
            row0 = np.append(fc * u, -fc * (u @ o)) + (self.cols - 1) / 2.0 * last
            row1 = np.append(fr * v, -fr * (v @ o)) + (self.rows - 1) / 2.0 * last
            self._cache["P"] = np.vstack([row0, row1, last])
        return self._cache["P"].copy()

    def resized(self, rows: int, cols: int) -> CArmView:
        """The same C-arm and detector sampled on a grid of ``rows`` x ``cols`` pixels.

        The detector's extent is kept (``rows * spacing`` along each axis), so a
        frame resampled to that size by area averaging (pixel centres mapped
        onto pixel centres, as ``cv2.resize`` with ``INTER_AREA`` does) is seen
        through the returned view as the original frame is through this one.

        Parameters
        ----------
        rows, cols : int
            The new image size, each at least 1.

        Returns
        -------
        CArmView
            A view whose pixel spacing is scaled by ``self.rows / rows`` and
            ``self.cols / cols``; angles, distances and offset unchanged.

        Raises
        ------
        GeometryError
            For a size that is not a whole number >= 1.

        Examples
        --------
        >>> view = CArmView(primary_deg=30.0, secondary_deg=0.0, sid_mm=1100.0,
        ...                 sod_mm=750.0, pixel_spacing_mm=(0.2, 0.2), rows=1024, cols=1024)
        >>> half = view.resized(512, 512)
        >>> half.pixel_spacing_mm, half.project([0.0, 0.0, 0.0])
        ((0.4, 0.4), array([255.5, 255.5]))
        """
        size = []
        for name, n in (("rows", rows), ("cols", cols)):
            if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
                raise GeometryError(f"{name}: expected a whole number >= 1, got {n!r}")
            size.append(int(n))
        dr, dc = self.pixel_spacing_mm
        return CArmView(primary_deg=self.primary_deg, secondary_deg=self.secondary_deg,
                        sid_mm=self.sid_mm, sod_mm=self.sod_mm,
                        pixel_spacing_mm=(dr * self.rows / size[0], dc * self.cols / size[1]),
                        rows=size[0], cols=size[1], offset_mm=self.offset_mm)

    # --------------------------------------------------------------- mappings
    def project(self, points_mm: Any) -> np.ndarray:
        """Project 3D points onto the image.

        Parameters
        ----------
        points_mm : array_like, shape (..., 3)
            Points in LPS mm.

        Returns
        -------
        numpy.ndarray, shape (..., 2)
            ``(col, row)`` in pixels. Points at or behind the source plane
            (which no ray reaches) give NaN.
        """
        pts = as_points(points_mm, 3, "points_mm")
        P = self.matrix
        h = pts @ P[:, :3].T + P[:, 3]
        w = h[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            out = h[..., :2] / w
        return np.where(w > 0, out, np.nan)

    def depth(self, points_mm: Any) -> np.ndarray:
        """Distance of points from the source along the central ray, in mm, shape (...)."""
        pts = as_points(points_mm, 3, "points_mm")
        d = self.detector_direction
        return pts @ d + (self.sod_mm - np.asarray(self.offset_mm) @ d)

    def pixel_to_detector(self, points_px: Any) -> np.ndarray:
        """3D position (LPS mm) on the detector plane of pixel coordinates ``(col, row)``.

        Parameters
        ----------
        points_px : array_like, shape (..., 2)

        Returns
        -------
        numpy.ndarray, shape (..., 3)
        """
        px = as_points(points_px, 2, "points_px")
        dr, dc = self.pixel_spacing_mm
        dcol = (px[..., 0:1] - (self.cols - 1) / 2.0) * dc
        drow = (px[..., 1:2] - (self.rows - 1) / 2.0) * dr
        return self.detector_centre + dcol * self.col_axis + drow * self.row_axis

    def ray(self, points_px: Any) -> tuple[np.ndarray, np.ndarray]:
        """Rays from the source through pixels.

        Returns
        -------
        origin : numpy.ndarray, shape (3,)
            The source position.
        directions : numpy.ndarray, shape (..., 3)
            Unit direction vectors from the source toward each pixel.
        """
        target = self.pixel_to_detector(points_px)
        vec = target - self.source
        return self.source, vec / np.linalg.norm(vec, axis=-1, keepdims=True)

    def px_to_mm(self, delta_px: Any) -> np.ndarray:
        """Length in mm at the isocentre of 2D pixel displacement vectors ``(dcol, drow)``."""
        delta = as_points(delta_px, 2, "delta_px")
        mr, mc = self.mm_per_px
        return np.hypot(delta[..., 0] * mc, delta[..., 1] * mr)

    # ------------------------------------------------------------------- I/O
    def to_dict(self) -> dict[str, Any]:
        """The ``CArmView`` keyword arguments as plain JSON-able values."""
        out = {k: getattr(self, k) for k in _VIEW_KEYS}
        out["pixel_spacing_mm"] = list(self.pixel_spacing_mm)
        if any(self.offset_mm):
            out["offset_mm"] = list(self.offset_mm)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "view") -> CArmView:
        """Build a view from its keyword arguments; ``source`` names the origin in errors."""
        if not isinstance(data, dict):
            raise GeometryError(f"{source}: expected a mapping of CArmView arguments")
        missing = [k for k in _VIEW_KEYS if k not in data]
        if missing:
            raise GeometryError(f"{source}: missing CArmView entries {missing}")
        unknown = [k for k in data if k not in (*_VIEW_KEYS, "offset_mm")]
        if unknown:
            raise GeometryError(
                f"{source}: unknown CArmView entries {unknown}; expected {list(_VIEW_KEYS)}"
            )
        extra = {"offset_mm": data["offset_mm"]} if data.get("offset_mm") is not None else {}
        return cls(**{k: data[k] for k in _VIEW_KEYS}, **extra)

    def to_json(self, path: str | os.PathLike) -> None:
        """Write the view as JSON (written atomically)."""
        from .io.atomic import atomic_write_text

        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> CArmView:
        """Read a view written by :meth:`to_json` (or any JSON of the keyword arguments)."""
        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except FileNotFoundError:
            raise InputFileError(f"{p}: no such view file") from None
        except (OSError, ValueError) as exc:
            raise InputFileError(f"{p}: not a readable JSON view file ({exc})") from None
        return cls.from_dict(data, source=str(p))

    @classmethod
    def from_dicom(cls, dataset: Any, geometry: dict[str, Any] | None = None) -> CArmView:
        """Build the view of a pydicom dataset of an XA file.

        Parameters
        ----------
        dataset : pydicom.Dataset
        geometry : dict, optional
            ``CArmView`` entries that override or fill the file's tags.

        Raises
        ------
        MissingGeometryError
            Naming every missing tag and how to supply it.
        """
        from .io.dicom import view_from_dataset

        return view_from_dataset(dataset, geometry=geometry)


class Reconstruction2View(NamedTuple):
    """Triangulated points and the paper's reconstruction error (§2.3).

    Attributes
    ----------
    points_mm : numpy.ndarray, shape (..., 3)
        Mid-points of the shortest segments between the two rays.
    error_px : numpy.ndarray, shape (...)
        Larger of the two 2D reprojection errors, in pixels.
    error_mm : numpy.ndarray, shape (...)
        Larger of the two 2D reprojection errors, in mm at the isocentre.
    error_a_px, error_b_px : numpy.ndarray, shape (...)
        The 2D reprojection error in each view, in pixels.
    """

    points_mm: np.ndarray
    error_px: np.ndarray
    error_mm: np.ndarray
    error_a_px: np.ndarray
    error_b_px: np.ndarray


def check_view(view: Any, name: str) -> CArmView:
    """Return ``view`` if it is a :class:`CArmView`, else raise ArgumentError naming ``name``."""
    if not isinstance(view, CArmView):
        raise ArgumentError(f"{name}: expected a vesselcad.CArmView, got {type(view).__name__}")
    return view


def triangulate(view_a: CArmView, points_a_px: Any, view_b: CArmView, points_b_px: Any) -> np.ndarray:
    """Triangulate corresponding pixels of two views.

    Each point is the mid-point of the shortest segment between the ray of
    view A and the ray of view B. The inputs broadcast against each other, so
    ``points_a[:, None]`` with ``points_b[None, :]`` triangulates all pairs.

    Parameters
    ----------
    view_a, view_b : CArmView
    points_a_px, points_b_px : array_like, shape (..., 2)
        ``(col, row)`` pixels in each view.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        LPS mm; NaN where the two rays are parallel.
    """
    check_view(view_a, "view_a")
    check_view(view_b, "view_b")
    oa, da = view_a.ray(points_a_px)
    ob, db = view_b.ray(points_b_px)
    da, db = np.broadcast_arrays(da, db)
    w0 = oa - ob
    b = np.einsum("...i,...i->...", da, db)
    d = da @ w0
    e = db @ w0
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom > 1e-14, (b * e - d) / denom, np.nan)
        s = np.where(denom > 1e-14, (e - b * d) / denom, np.nan)
    pa = oa + t[..., None] * da
    pb = ob + s[..., None] * db
    return 0.5 * (pa + pb)


def reconstruction_error(
    view_a: CArmView, points_a_px: Any, view_b: CArmView, points_b_px: Any
) -> Reconstruction2View:
    """Triangulate pixel pairs and measure the paper's reconstruction error.

    The 3D point is the ray mid-point (see :func:`triangulate`); it is
    reprojected into both views and the error is the larger of the two 2D
    distances (paper §2.3), in pixels and in mm at the isocentre plane.
    Inputs broadcast, so the error of all N_A x N_B pairs is one call.

    Parameters
    ----------
    view_a, view_b : CArmView
    points_a_px, points_b_px : array_like, shape (..., 2)

    Returns
    -------
    Reconstruction2View
    """
    pa = as_points(points_a_px, 2, "points_a_px")
    pb = as_points(points_b_px, 2, "points_b_px")
    pts = triangulate(view_a, pa, view_b, pb)
    da = view_a.project(pts) - pa
    db = view_b.project(pts) - pb
    ea_px, eb_px = np.linalg.norm(da, axis=-1), np.linalg.norm(db, axis=-1)
    ea_mm, eb_mm = view_a.px_to_mm(da), view_b.px_to_mm(db)
    return Reconstruction2View(
        points_mm=pts,
        error_px=np.maximum(ea_px, eb_px),
        error_mm=np.maximum(ea_mm, eb_mm),
        error_a_px=ea_px,
        error_b_px=eb_px,
    )
