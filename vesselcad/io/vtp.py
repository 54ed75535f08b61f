"""VTK XML PolyData (.vtp) of polylines with point and cell data (ASCII, no VTK needed).

vmtk and ParaView read these directly; vesselcad writes centrelines with the
radius array under vmtk's name ``MaximumInscribedSphereRadius``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from xml.etree import ElementTree as ET

import numpy as np

from ..errors import ArgumentError, InputFileError
from .atomic import atomic_write_text

__all__ = ["write_polylines", "read_polylines"]


def _fmt(values: np.ndarray) -> str:
    return " ".join(repr(float(v)) if np.issubdtype(values.dtype, np.floating) else str(int(v))
                    for v in values.ravel())


def write_polylines(path: str | os.PathLike, lines: Sequence[np.ndarray],
                    point_data: dict[str, Sequence[np.ndarray]] | None = None,
                    cell_data: dict[str, Sequence[float]] | None = None) -> None:
    """Write polylines as a .vtp file, atomically.

    Parameters
    ----------
    path : str or path-like
    lines : sequence of (n_i, 3) arrays
        One polyline per cell.
    point_data : dict of name -> sequence of (n_i,) arrays, optional
        Scalar arrays per point, one array per line.
    cell_data : dict of name -> sequence of numbers, optional
        One value per line (integers are written as Int64).
    """
    lines = [np.asarray(p, dtype=float) for p in lines]
    if any(p.ndim != 2 or p.shape[1] != 3 for p in lines):
        raise ArgumentError("lines: expected (n, 3) arrays")
    point_data = point_data or {}
    cell_data = cell_data or {}
    n_pts = sum(len(p) for p in lines)
    root = ET.Element("VTKFile", type="PolyData", version="1.0", byte_order="LittleEndian",
                      header_type="UInt64")
    poly = ET.SubElement(root, "PolyData")
    piece = ET.SubElement(poly, "Piece", NumberOfPoints=str(n_pts), NumberOfVerts="0",
                          NumberOfLines=str(len(lines)), NumberOfStrips="0", NumberOfPolys="0")
    pd = ET.SubElement(piece, "PointData")
    for name, arrays in point_data.items():
        vals = np.concatenate([np.asarray(a, dtype=float).ravel() for a in arrays]) if arrays else np.zeros(0)
        if len(vals) != n_pts:
            raise ArgumentError(f"point_data[{name!r}]: expected {n_pts} values, got {len(vals)}")
        ET.SubElement(pd, "DataArray", type="Float64", Name=name, format="ascii").text = _fmt(vals)
    cd = ET.SubElement(piece, "CellData")
    for name, values in cell_data.items():
        vals = np.asarray(values)
        if len(vals) != len(lines):
            raise ArgumentError(f"cell_data[{name!r}]: expected {len(lines)} values, got {len(vals)}")
        kind = "Int64" if np.issubdtype(vals.dtype, np.integer) else "Float64"
        ET.SubElement(cd, "DataArray", type=kind, Name=name, format="ascii").text = _fmt(vals)
    pts = ET.SubElement(piece, "Points")
    allp = np.vstack(lines) if lines else np.zeros((0, 3))
    ET.SubElement(pts, "DataArray", type="Float64", NumberOfComponents="3", format="ascii").text = _fmt(allp)
    cells = ET.SubElement(piece, "Lines")
    ET.SubElement(cells, "DataArray", type="Int64", Name="connectivity", format="ascii").text = \
        _fmt(np.arange(n_pts))
    ET.SubElement(cells, "DataArray", type="Int64", Name="offsets", format="ascii").text = \
        _fmt(np.cumsum([len(p) for p in lines]))
    ET.indent(root)
    atomic_write_text(path, '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n")


def read_polylines(path: str | os.PathLike) -> tuple[list[np.ndarray], dict[str, list[np.ndarray]],
                                                      dict[str, np.ndarray]]:
    """Read a .vtp written by :func:`write_polylines` (ASCII polylines).

    Returns
    -------
    lines, point_data, cell_data
    """
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputFileError(f"{path}: not a readable VTK XML file ({exc})") from None
    piece = root.find("PolyData/Piece")
    if piece is None:
        raise InputFileError(f"{path}: no PolyData piece")

    def arr(el: ET.Element) -> np.ndarray:
        return np.array((el.text or "").split(), dtype=float)

    pts = arr(piece.find("Points/DataArray")).reshape(-1, 3)
    conn = arr(piece.find("Lines/DataArray[@Name='connectivity']")).astype(int)
    offs = arr(piece.find("Lines/DataArray[@Name='offsets']")).astype(int)
    starts = np.r_[0, offs[:-1]]
    lines = [pts[conn[a:b]] for a, b in zip(starts, offs, strict=True)]
    point_data = {el.get("Name"): [arr(el)[conn[a:b]] for a, b in zip(starts, offs, strict=True)]
                  for el in piece.findall("PointData/DataArray")}
    cell_data = {el.get("Name"): arr(el) for el in piece.findall("CellData/DataArray")}
    return lines, point_data, cell_data
