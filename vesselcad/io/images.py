"""A run given as a folder of PNG/JPEG/TIFF frames plus a ``view.json``."""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ArgumentError, InputFileError, VesselcadWarning
from ..geometry import CArmView
from .run import XARun

__all__ = ["load_frames_dir", "read_image", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def _natural_key(name: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read one frame as a 2D uint8/uint16 grey image.

    Colour images are converted to luminance; 8- and 16-bit images keep their depth.

    Raises
    ------
    InputFileError
        If the file is missing or is not a readable image.
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: no such image file")
    data = np.fromfile(p, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputFileError(f"{p}: not a readable PNG/JPEG/TIFF image")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[..., :3]
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype not in (np.uint8, np.uint16):
        if np.issubdtype(img.dtype, np.floating):
            raise InputFileError(f"{p}: floating-point images are not supported; save as 8/16-bit")
        img = np.clip(img, 0, 65535).astype(np.uint16)
    return img


def load_frames_dir(path: str | os.PathLike, geometry: Any = None) -> XARun:
    """Load a folder of frames (in natural name order) and its ``view.json``.

    ``view.json`` holds ``CArmView`` keyword arguments (``rows``/``cols`` may be
    left out: they come from the images) and optionally ``frame_time_ms``.
    ``geometry`` entries override the file's.
    """
    from .dicom import _geometry_dict

    folder = Path(path)
    files = sorted(
        (f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file()),
        key=lambda f: _natural_key(f.name),
    )
    if not files:
        raise InputFileError(f"{folder}: no PNG/JPEG/TIFF frames in this folder")
    view_file = folder / "view.json"
    data: dict[str, Any] = {}
    if view_file.exists():
        try:
            data = json.loads(view_file.read_text())
        except (OSError, ValueError) as exc:
            raise InputFileError(f"{view_file}: not a readable JSON file ({exc})") from None
        if not isinstance(data, dict):
            raise InputFileError(f"{view_file}: expected a JSON object of CArmView entries")
    data.update(_geometry_dict(geometry))
    frames = []
    for f in files:
        img = read_image(f)
        if frames and img.shape != frames[0].shape:
            raise InputFileError(f"{f}: frame is {img.shape[1]}x{img.shape[0]} but {files[0].name} "
                                 f"is {frames[0].shape[1]}x{frames[0].shape[0]}")
        frames.append(img)
    dtype = np.uint16 if any(fr.dtype == np.uint16 for fr in frames) else np.uint8
    stack = np.stack([fr.astype(dtype) for fr in frames])
    data.setdefault("rows", stack.shape[1])
    data.setdefault("cols", stack.shape[2])
    frame_time = data.pop("frame_time_ms", None)
    needed = [k for k in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm")
              if k not in data]
    if needed:
        raise InputFileError(
            f"{view_file}: missing CArmView entries {needed} (write them into view.json or pass "
            "geometry={...} to load_run)")
    try:
        view = CArmView.from_dict(data, source=str(view_file))
    except ArgumentError as exc:
        raise InputFileError(str(exc)) from None
    if (view.rows, view.cols) != stack.shape[1:]:
        raise InputFileError(f"{view_file}: rows/cols {view.rows}x{view.cols} do not match the "
                             f"frames' {stack.shape[1]}x{stack.shape[2]}")
    if frame_time is None:
        if len(files) > 1:
            warnings.warn(f"{view_file}: no frame_time_ms; assuming 15 frames/s",
                          VesselcadWarning, stacklevel=3)
        frame_time = 1000.0 / 15.0
    return XARun(frames=stack, view=view, frame_times_ms=np.arange(len(files)) * float(frame_time),
                 bits_stored=16 if dtype == np.uint16 else 8, source=str(folder))
