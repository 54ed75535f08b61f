"""DICOM X-ray angiography (XA) runs: reading every common transfer syntax, writing XA.

Pixel decoders (see docs/io.md): pydicom decodes uncompressed data itself;
python-gdcm (BSD) covers JPEG baseline, JPEG lossless, JPEG-LS and JPEG 2000;
pylibjpeg-openjpeg (MIT) covers JPEG 2000 and pylibjpeg-rle (MIT) RLE;
imagecodecs (BSD) is the fallback for 12-bit JPEG Extended (process 2/4),
which GDCM refuses. The GPL-licensed pylibjpeg-libjpeg is not required.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import (
    ArgumentError,
    DecoderError,
    DicomError,
    GeometryError,
    InputFileError,
    MissingGeometryError,
    VesselcadWarning,
)
from ..geometry import _VIEW_KEYS, CArmView
from .atomic import atomic_path
from .run import XARun

__all__ = ["load_dicom_run", "read_dicom_frames", "save_run", "view_from_dataset", "GEOMETRY_TAGS"]

#: The DICOM attribute behind each CArmView keyword: (keyword, tag).
GEOMETRY_TAGS: dict[str, tuple[str, str]] = {
    "primary_deg": ("PositionerPrimaryAngle", "(0018,1510)"),
    "secondary_deg": ("PositionerSecondaryAngle", "(0018,1511)"),
    "sid_mm": ("DistanceSourceToDetector", "(0018,1110)"),
    "sod_mm": ("DistanceSourceToPatient", "(0018,1111)"),
    "pixel_spacing_mm": ("ImagerPixelSpacing", "(0018,1164)"),
    "rows": ("Rows", "(0028,0010)"),
    "cols": ("Columns", "(0028,0011)"),
}

_XA_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.12.1",  # X-Ray Angiographic Image Storage
    "1.2.840.10008.5.1.4.1.1.12.1.1",  # Enhanced XA Image Storage
    "1.2.840.10008.5.1.4.1.1.12.2",  # X-Ray Radiofluoroscopic Image Storage
    "1.2.840.10008.5.1.4.1.1.12.2.1",  # Enhanced XRF Image Storage
    "1.2.840.10008.5.1.4.1.1.12.3",  # X-Ray Angiographic Bi-Plane Image Storage (retired)
}
_XA_MODALITIES = {"XA", "RF"}
XA_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.1"

# Which package decodes which transfer syntax (used in DecoderError messages).
_DECODER_HINT = {
    "1.2.840.10008.1.2.5": "pylibjpeg-rle (pip install pylibjpeg pylibjpeg-rle)",
    "1.2.840.10008.1.2.4.50": "python-gdcm (pip install python-gdcm)",
    "1.2.840.10008.1.2.4.51": "imagecodecs (pip install imagecodecs)",
    "1.2.840.10008.1.2.4.57": "python-gdcm (pip install python-gdcm)",
    "1.2.840.10008.1.2.4.70": "python-gdcm (pip install python-gdcm)",
    "1.2.840.10008.1.2.4.80": "python-gdcm (pip install python-gdcm)",
    "1.2.840.10008.1.2.4.81": "python-gdcm (pip install python-gdcm)",
    "1.2.840.10008.1.2.4.90": "pylibjpeg-openjpeg or python-gdcm (pip install pylibjpeg-openjpeg)",
    "1.2.840.10008.1.2.4.91": "pylibjpeg-openjpeg or python-gdcm (pip install pylibjpeg-openjpeg)",
}
_IMAGECODECS_SYNTAXES = {
    "1.2.840.10008.1.2.4.50",  # JPEG baseline
    "1.2.840.10008.1.2.4.51",  # JPEG extended (12-bit)
    "1.2.840.10008.1.2.4.57",  # JPEG lossless
    "1.2.840.10008.1.2.4.70",  # JPEG lossless SV1
}


# --------------------------------------------------------------------- reading
def _read_dataset(path: Path, stop_before_pixels: bool = False) -> Any:
    import pydicom
    from pydicom.errors import InvalidDicomError

    if not path.exists():
        raise InputFileError(f"{path}: no such file")
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder, expected a DICOM file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pydicom warns about odd but harmless values
            try:
                ds = pydicom.dcmread(path, stop_before_pixels=stop_before_pixels)
            except InvalidDicomError:
                # ACR-NEMA style files have no preamble; accept them only if they
                # still look like an image.
                ds = pydicom.dcmread(path, force=True, stop_before_pixels=stop_before_pixels)
                if "Rows" not in ds or "Columns" not in ds:
                    raise DicomError(
                        f"{path}: not a DICOM file (no 'DICM' preamble and no image attributes)"
                    ) from None
    except DicomError:
        raise
    except PermissionError as exc:
        raise InputFileError(f"{path}: cannot be read ({exc})") from None
    except Exception as exc:  # pydicom raises many types on damaged input
        raise DicomError(f"{path}: not a readable DICOM file ({type(exc).__name__}: {exc})") from None
    return ds


def _check_is_xa(ds: Any, path: Path) -> None:
    modality = str(ds.get("Modality", "") or "").upper()
    sop = str(ds.get("SOPClassUID", "") or "")
    if modality in _XA_MODALITIES or sop in _XA_SOP_CLASSES:
        return
    raise DicomError(
        f"{path}: not an X-ray angiography file: Modality (0008,0060) is {modality or 'absent'!r} "
        f"and SOPClassUID (0008,0016) is {sop or 'absent'!r}; expected Modality 'XA' or 'RF' "
        "or an XA/XRF SOP class"
    )


def _decode_with_imagecodecs(ds: Any, n_frames: int) -> np.ndarray:
    import imagecodecs
    from pydicom.encaps import generate_frames

    out = [
        imagecodecs.jpeg8_decode(frame)
        for frame in generate_frames(ds.PixelData, number_of_frames=n_frames)
    ]
    return np.stack(out)


def read_dicom_frames(path: str | os.PathLike, dataset: Any = None) -> np.ndarray:
    """Decode the pixel data of an XA file to ``(N, H, W)`` uint8/uint16 frames.

    Frames are returned in MONOCHROME2 convention (MONOCHROME1 is inverted,
    colour is converted to luminance), whatever the transfer syntax.

    Parameters
    ----------
    path : str or path-like
        The DICOM file.
    dataset : pydicom.Dataset, optional
        The already-read dataset of ``path`` (saves reading it twice).

    Raises
    ------
    DicomError
        Not DICOM, no pixel data, zero frames, truncated pixel data.
    DecoderError
        No installed decoder handles the transfer syntax; names the package to install.
    """
    p = Path(path)
    ds = _read_dataset(p) if dataset is None else dataset
    if "PixelData" not in ds:
        raise DicomError(f"{p}: no Pixel Data (7FE0,0010): the file holds no image")
    for kw, tag in (("Rows", "(0028,0010)"), ("Columns", "(0028,0011)"),
                    ("BitsAllocated", "(0028,0100)")):
        if kw not in ds or not ds.get(kw):
            raise DicomError(f"{p}: missing or zero {kw} {tag}")
    raw_frames = ds.get("NumberOfFrames")
    try:
        n_frames = 1 if raw_frames in (None, "") else int(raw_frames)
    except (TypeError, ValueError):
        raise DicomError(f"{p}: NumberOfFrames (0028,0008) is not a number: {raw_frames!r}") from None
    if n_frames < 1:
        raise DicomError(f"{p}: NumberOfFrames (0028,0008) is {n_frames}: the run has no frames")
    tsuid = str(ds.file_meta.get("TransferSyntaxUID", "1.2.840.10008.1.2.1")) if hasattr(
        ds, "file_meta") else "1.2.840.10008.1.2.1"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = ds.pixel_array
    except Exception as exc:
        msg = str(exc)
        if tsuid in _IMAGECODECS_SYNTAXES:
            try:
                arr = _decode_with_imagecodecs(ds, n_frames)
            except ImportError:
                arr = None
            except Exception as exc2:
                raise DicomError(f"{p}: pixel data cannot be decoded ({exc2})") from None
            if arr is None:
                raise DecoderError(
                    f"{p}: no installed decoder handles transfer syntax {tsuid}; install "
                    f"{_DECODER_HINT.get(tsuid, 'python-gdcm')}"
                ) from None
        elif "less than expected" in msg or "truncated" in msg.lower() or "fewer" in msg:
            raise DicomError(f"{p}: truncated Pixel Data (7FE0,0010): {msg.splitlines()[0]}") from None
        elif ("No plugin" in msg or "missing required dependencies" in msg
              or "Unable to decode" in msg or "not supported" in msg.lower()):
            raise DecoderError(
                f"{p}: no installed decoder handles transfer syntax {tsuid}; install "
                f"{_DECODER_HINT.get(tsuid, 'python-gdcm')} ({msg.splitlines()[0]})"
            ) from None
        else:
            raise DicomError(f"{p}: pixel data cannot be decoded ({type(exc).__name__}: {msg})") from None
    arr = np.asarray(arr)
    spp = int(ds.get("SamplesPerPixel", 1) or 1)
    if spp == 3:
        warnings.warn(f"{p}: colour image (SamplesPerPixel (0028,0002) = 3) converted to grey",
                      VesselcadWarning, stacklevel=3)
        arr = arr.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
        arr = np.round(arr).astype(np.uint16 if arr.max() > 255 else np.uint8)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[0] != n_frames:
        raise DicomError(f"{p}: decoded pixel data has shape {arr.shape}, expected "
                             f"{n_frames} frames of {ds.Rows}x{ds.Columns}")
    if arr.dtype.kind == "i":
        warnings.warn(f"{p}: signed pixels (PixelRepresentation (0028,0103) = 1) shifted to unsigned",
                      VesselcadWarning, stacklevel=3)
        arr = (arr.astype(np.int32) - int(arr.min())).astype(np.uint16)
    if arr.dtype.itemsize > 2:
        arr = np.clip(arr, 0, 65535).astype(np.uint16)
    if arr.dtype == np.uint16 and int(ds.get("BitsStored", 16)) <= 8:
        arr = arr.astype(np.uint8)
    if str(ds.get("PhotometricInterpretation", "MONOCHROME2")).upper() == "MONOCHROME1":
        bits = int(ds.get("BitsStored", arr.dtype.itemsize * 8))
        arr = ((1 << bits) - 1 - arr.astype(np.int64)).clip(0).astype(arr.dtype)
    return np.ascontiguousarray(arr)


def _number(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _geometry_dict(geometry: Any) -> dict[str, Any]:
    """Normalise the ``geometry=`` argument (dict, view.json path or None)."""
    if geometry is None:
        return {}
    if isinstance(geometry, CArmView):
        return geometry.to_dict()
    if isinstance(geometry, str | os.PathLike):
        p = Path(geometry)
        try:
            data = json.loads(p.read_text())
        except FileNotFoundError:
            raise InputFileError(f"geometry: no such view file {p}") from None
        except (OSError, ValueError) as exc:
            raise InputFileError(f"geometry: {p} is not a readable JSON file ({exc})") from None
        geometry = data
    if not isinstance(geometry, dict):
        raise ArgumentError(
            f"geometry: expected a dict of CArmView entries or a view.json path, got "
            f"{type(geometry).__name__}"
        )
    unknown = [k for k in geometry if k not in _VIEW_KEYS and k not in ("frame_time_ms", "offset_mm")]
    if unknown:
        raise ArgumentError(f"geometry: unknown entries {unknown}; expected some of {list(_VIEW_KEYS)}")
    return dict(geometry)


def view_from_dataset(dataset: Any, geometry: Any = None, source: str = "") -> CArmView:
    """The :class:`CArmView` of an XA dataset, with ``geometry`` overriding or filling tags.

    Parameters
    ----------
    dataset : pydicom.Dataset
    geometry : dict, str, path-like or CArmView, optional
        CArmView entries (or a view.json path) that override the file's tags.
    source : str
        Name used in messages (the file path).

    Raises
    ------
    MissingGeometryError
        Lists every missing tag by keyword and number and how to supply it.
    DicomError
        A geometry tag holds an impossible value (e.g. SOD >= SID).
    """
    src = source or str(getattr(dataset, "filename", "") or "dataset")
    given = _geometry_dict(geometry)
    given.pop("frame_time_ms", None)
    values: dict[str, Any] = {}
    for key, (kw, _tag) in GEOMETRY_TAGS.items():
        if key in given:
            values[key] = given[key]
            continue
        raw = dataset.get(kw)
        if key == "pixel_spacing_mm":
            if raw is None and dataset.get("PixelSpacing") is not None:
                raw = dataset.get("PixelSpacing")
                warnings.warn(
                    f"{src}: ImagerPixelSpacing (0018,1164) is absent; using PixelSpacing "
                    "(0028,0030) as the detector pixel spacing", VesselcadWarning, stacklevel=3)
            if raw is not None:
                try:  # DS or multi-valued DS
                    vals = [float(x) for x in ([raw] if isinstance(raw, str | float | int) else raw)]
                except (TypeError, ValueError):
                    vals = []
                if len(vals) == 1:
                    vals = vals * 2
                if len(vals) == 2 and all(v > 0 and math.isfinite(v) for v in vals):
                    values[key] = (vals[0], vals[1])
            continue
        num = _number(raw) if raw is not None and raw != "" else None
        if num is not None:
            values[key] = num
    if given.get("offset_mm") is not None:
        values["offset_mm"] = given["offset_mm"]
    missing = [k for k in _VIEW_KEYS if k not in values]
    if missing:
        names = ", ".join(f"{GEOMETRY_TAGS[k][0]} {GEOMETRY_TAGS[k][1]} [{k}]" for k in missing)
        example = ", ".join(f'"{k}": ...' for k in missing)
        raise MissingGeometryError(
            f"{src}: cannot build the C-arm geometry: missing {names}. Supply them with "
            f"load_run(path, geometry={{{example}}}) or a view.json file "
            "(load_run(path, geometry='view.json'); CLI: --geometry view.json)",
            missing,
        )
    try:
        return CArmView(**values)
    except GeometryError as exc:
        raise DicomError(
            f"{src}: impossible geometry from tags/overrides ({exc}); check "
            "DistanceSourceToDetector (0018,1110), DistanceSourceToPatient (0018,1111) and "
            "ImagerPixelSpacing (0018,1164)"
        ) from None


def _frame_times(ds: Any, n: int, src: str, geometry: dict[str, Any]) -> np.ndarray:
    if "frame_time_ms" in geometry:
        ft = _number(geometry["frame_time_ms"])
        if ft is None or ft <= 0:
            raise ArgumentError(f"geometry: frame_time_ms must be a positive number, got "
                                f"{geometry['frame_time_ms']!r}")
        return np.arange(n) * ft
    vec = ds.get("FrameTimeVector")
    if vec is not None:
        try:
            inc = np.array([float(x) for x in ([vec] if isinstance(vec, str | float | int) else vec)])
        except (TypeError, ValueError):
            inc = np.array([])
        if inc.size == n and np.all(np.isfinite(inc)):
            inc[0] = 0.0
            return np.cumsum(inc)
        warnings.warn(f"{src}: FrameTimeVector (0018,1065) has {inc.size} entries for {n} frames; "
                      "ignored", VesselcadWarning, stacklevel=3)
    ft = _number(ds.get("FrameTime"))
    if ft is not None and ft > 0:
        return np.arange(n) * ft
    rate = _number(ds.get("CineRate")) or _number(ds.get("RecommendedDisplayFrameRate"))
    if rate is not None and rate > 0:
        return np.arange(n) * (1000.0 / rate)
    if n > 1:
        warnings.warn(
            f"{src}: no FrameTime (0018,1063), FrameTimeVector (0018,1065) or CineRate (0018,0040); "
            "assuming 15 frames/s (pass geometry={'frame_time_ms': ...} to set it)",
            VesselcadWarning, stacklevel=3)
    return np.arange(n) * (1000.0 / 15.0)


def load_dicom_run(path: str | os.PathLike, geometry: Any = None) -> XARun:
    """Read a single- or multi-frame XA DICOM file as an :class:`XARun`.

    See :func:`vesselcad.load_run`, which dispatches here for files.
    """
    with warnings.catch_warnings():
        # pydicom warns about odd but harmless values of real files (non-standard UIDs);
        # vesselcad's own warnings come from this module and still pass.
        warnings.filterwarnings("ignore", category=UserWarning, module=r"pydicom\.")
        return _load_dicom_run(Path(path), geometry)


def _load_dicom_run(p: Path, geometry: Any) -> XARun:
    ds = _read_dataset(p)
    _check_is_xa(ds, p)
    geom = _geometry_dict(geometry)
    view = view_from_dataset(ds, geom, source=str(p))
    frames = read_dicom_frames(p, dataset=ds)
    if frames.shape[1:] != (view.rows, view.cols):
        raise DicomError(f"{p}: frames are {frames.shape[2]}x{frames.shape[1]} pixels but the "
                         f"geometry says cols={view.cols}, rows={view.rows}")
    n = frames.shape[0]
    times = _frame_times(ds, n, str(p), geom)
    r_wave = None
    if ds.get("RWavePointer") is not None:
        rw = ds.RWavePointer
        rw = [int(x) - 1 for x in ([rw] if isinstance(rw, str | float | int) else rw)]
        r_wave = np.array([x for x in rw if 0 <= x < n], dtype=np.int64)
    bits = int(ds.get("BitsStored", frames.dtype.itemsize * 8) or 8)
    bits = min(bits, frames.dtype.itemsize * 8)
    return XARun(
        frames=frames,
        view=view,
        frame_times_ms=times,
        bits_stored=bits,
        r_wave_frames=r_wave,
        patient_id=str(ds.get("PatientID", "") or ""),
        patient_name=str(ds.get("PatientName", "") or ""),
        study_uid=str(ds.get("StudyInstanceUID", "") or ""),
        series_uid=str(ds.get("SeriesInstanceUID", "") or ""),
        study_date=str(ds.get("StudyDate", "") or ""),
        source=str(p),
    )


# --------------------------------------------------------------------- writing
def _uid(*parts: Any) -> str:
    """A deterministic DICOM UID (2.25 form) derived from ``parts``."""
    digest = hashlib.sha256(repr(parts).encode()).digest()[:16]
    return f"2.25.{int.from_bytes(digest, 'big')}"


def _ds_str(x: float) -> str:
    """Format a float for a DS element (at most 16 characters)."""
    s = f"{x:.10g}"
    if len(s) > 16:
        s = f"{x:.6e}"
    return s


def save_run(run: XARun, path: str | os.PathLike, *, compress: bool = False) -> Path:
    """Write a run as a standard multi-frame X-Ray Angiographic Image (XA) file.

    The file carries every tag :func:`vesselcad.load_run` reads: positioner
    angles, SID, SOD, ImagerPixelSpacing, FrameTime or FrameTimeVector,
    RWavePointer, patient and study identifiers. UIDs not present on the run
    are derived deterministically from its content, so the same run gives the
    same bytes. The file is written atomically.

    Parameters
    ----------
    run : XARun
    path : str or path-like
    compress : bool
        Write RLE Lossless instead of Explicit VR Little Endian.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, RLELossless

    if not isinstance(run, XARun):
        raise ArgumentError(f"run: expected an XARun, got {type(run).__name__}")
    frames = run.frames
    n, rows, cols = frames.shape
    view = run.view
    content_key = hashlib.sha256(frames.tobytes()).hexdigest()[:16]
    study_uid = run.study_uid or _uid("study", content_key, view.to_dict())
    series_uid = run.series_uid or _uid("series", content_key, view.to_dict())
    sop_uid = _uid("sop", series_uid, content_key)

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XA_IMAGE_STORAGE
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    meta.ImplementationVersionName = "VESSELCAD_010"

    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.SOPClassUID = XA_IMAGE_STORAGE
    ds.SOPInstanceUID = sop_uid
    ds.StudyDate = run.study_date
    ds.ContentDate = run.study_date
    ds.StudyTime = ""
    ds.ContentTime = ""
    ds.AccessionNumber = ""
    ds.Modality = "XA"
    ds.Manufacturer = "vesselcad"
    ds.ReferringPhysicianName = ""
    ds.PatientName = run.patient_name
    ds.PatientID = run.patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.BodyPartExamined = "HEART"  # unpaired: Laterality (0020,0060) stays absent
    ds.KVP = ""
    ds.XRayTubeCurrent = ""
    ds.ExposureTime = ""
    ds.Exposure = ""
    ds.RadiationSetting = "GR"
    ds.DistanceSourceToDetector = _ds_str(view.sid_mm)
    ds.DistanceSourceToPatient = _ds_str(view.sod_mm)
    ds.EstimatedRadiographicMagnificationFactor = _ds_str(view.magnification)
    ds.ImagerPixelSpacing = [_ds_str(s) for s in view.pixel_spacing_mm]
    ds.PositionerMotion = "STATIC"
    ds.PositionerPrimaryAngle = _ds_str(view.primary_deg)
    ds.PositionerSecondaryAngle = _ds_str(view.secondary_deg)
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = ""
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.PatientOrientation = ""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.NumberOfFrames = n
    times = np.asarray(run.frame_times_ms, dtype=np.float64)
    steps = np.diff(times)
    if n < 2 or np.allclose(steps, steps[0], rtol=0, atol=1e-6):
        ds.FrameTime = _ds_str(float(steps[0]) if n > 1 else 1000.0 / 15.0)
        ds.FrameIncrementPointer = 0x00181063
        ds.CineRate = int(round(1000.0 / float(ds.FrameTime)))
    else:
        ds.FrameTimeVector = [_ds_str(0.0)] + [_ds_str(float(s)) for s in steps]
        ds.FrameIncrementPointer = 0x00181065
    ds.Rows = rows
    ds.Columns = cols
    ds.BitsAllocated = 8 if frames.dtype == np.uint8 else 16
    ds.BitsStored = run.bits_stored
    ds.HighBit = run.bits_stored - 1
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "LOG"
    ds.RescaleIntercept = "0"
    ds.RescaleSlope = "1"
    ds.RescaleType = "US"
    ds.LossyImageCompression = "00"
    if run.r_wave_frames is not None and len(run.r_wave_frames):
        ds.RWavePointer = [int(i) + 1 for i in run.r_wave_frames]
    pixel_bytes = np.ascontiguousarray(frames).tobytes()
    ds.PixelData = pixel_bytes + (b"\0" if len(pixel_bytes) % 2 else b"")
    if compress:
        ds.compress(RLELossless, generate_instance_uid=False)
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    return Path(path)
