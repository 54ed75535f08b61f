"""File formats: DICOM XA runs, frame folders (one module per format)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..errors import InputFileError
from .atomic import atomic_path, atomic_write_bytes, atomic_write_text
from .dicom import GEOMETRY_TAGS, read_dicom_frames, save_run, view_from_dataset
from .images import load_frames_dir, read_image
from .run import XARun

__all__ = [
    "XARun",
    "load_run",
    "save_run",
    "read_dicom_frames",
    "read_image",
    "view_from_dataset",
    "GEOMETRY_TAGS",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
]


def load_run(path: str | os.PathLike, geometry: Any = None) -> XARun:
    """Load one X-ray angiography run.

    Parameters
    ----------
    path : str or path-like
        A single- or multi-frame XA DICOM file (any common transfer syntax), or
        a folder of PNG/JPEG/TIFF frames (natural name order) with a ``view.json``.
    geometry : dict, str or path-like, optional
        ``CArmView`` entries (``primary_deg``, ``secondary_deg``, ``sid_mm``,
        ``sod_mm``, ``pixel_spacing_mm``, ``rows``, ``cols``) and optionally
        ``frame_time_ms``, or the path of a view.json holding them. Given
        entries override or fill the file's tags; real exports often lack
        SID, SOD or pixel spacing.

    Returns
    -------
    XARun

    Raises
    ------
    MissingGeometryError
        The file lacks geometry tags; the message names each tag and how to supply it.
    DicomError, DecoderError, InputFileError
        Not a readable XA file, no decoder for its encoding, or missing path.

    Examples
    --------
    >>> run = load_run("run.dcm", geometry={"sid_mm": 1100.0, "sod_mm": 750.0,
    ...                                     "pixel_spacing_mm": (0.3, 0.3)})  # doctest: +SKIP
    """
    from .dicom import load_dicom_run

    p = Path(path)
    if p.is_dir():
        return load_frames_dir(p, geometry=geometry)
    if not p.exists():
        raise InputFileError(f"{p}: no such file or folder")
    return load_dicom_run(p, geometry=geometry)
