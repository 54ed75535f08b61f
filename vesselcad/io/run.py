"""The in-memory form of one X-ray angiography run."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import ArgumentError
from ..geometry import CArmView

__all__ = ["XARun"]


@dataclass
class XARun:
    """One cine run of a single C-arm view.

    Attributes
    ----------
    frames : numpy.ndarray, shape (N, H, W), uint8 or uint16
        Frames in display convention (MONOCHROME2: contrast-filled vessels dark).
    view : CArmView
        Projection geometry; ``view.rows == H`` and ``view.cols == W``.
    frame_times_ms : numpy.ndarray, shape (N,)
        Acquisition time of each frame relative to the first, in ms.
    bits_stored : int
        Significant bits per pixel (8 to 16).
    r_wave_frames : numpy.ndarray of int or None
        0-based indices of frames at ECG R-waves (RWavePointer (0028,6040)), if known.
    patient_id, patient_name, study_uid, series_uid, study_date : str
        Identifiers kept from the source file ('' when unknown).
    source : str
        Where the run was read from ('' for runs built in memory).
    """

    frames: np.ndarray
    view: CArmView
    frame_times_ms: np.ndarray
    bits_stored: int = 8
    r_wave_frames: np.ndarray | None = None
    patient_id: str = ""
    patient_name: str = ""
    study_uid: str = ""
    series_uid: str = ""
    study_date: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames)
        if frames.ndim == 2:
            frames = frames[None]
        if frames.ndim != 3 or frames.shape[0] == 0:
            raise ArgumentError(f"frames: expected shape (N, H, W) with N >= 1, got {frames.shape}")
        if frames.dtype not in (np.uint8, np.uint16):
            raise ArgumentError(f"frames: expected uint8 or uint16 pixels, got {frames.dtype}")
        if not isinstance(self.view, CArmView):
            raise ArgumentError(f"view: expected a CArmView, got {type(self.view).__name__}")
        if frames.shape[1:] != (self.view.rows, self.view.cols):
            raise ArgumentError(
                f"frames: shape {frames.shape[1:]} does not match the view's "
                f"(rows, cols) = ({self.view.rows}, {self.view.cols})"
            )
        times = np.asarray(self.frame_times_ms, dtype=np.float64).reshape(-1)
        if times.shape != (frames.shape[0],) or not np.all(np.isfinite(times)):
            raise ArgumentError(
                f"frame_times_ms: expected {frames.shape[0]} finite times, got shape {times.shape}"
            )
        if not 1 <= int(self.bits_stored) <= 16 or (
            frames.dtype == np.uint8 and int(self.bits_stored) > 8
        ):
            raise ArgumentError(
                f"bits_stored: {self.bits_stored} does not fit {frames.dtype} pixels"
            )
        if self.r_wave_frames is not None:
            rw = np.asarray(self.r_wave_frames, dtype=np.int64).reshape(-1)
            if rw.size and (rw.min() < 0 or rw.max() >= frames.shape[0]):
                raise ArgumentError(f"r_wave_frames: indices must lie in [0, {frames.shape[0]})")
            self.r_wave_frames = rw
        self.frames = frames
        self.frame_times_ms = times
        self.bits_stored = int(self.bits_stored)

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.frames.shape[0])

    def resampled(self, max_side: int) -> XARun:
        """This run with its frames reduced to at most ``max_side`` pixels a side.

        Each frame is area averaged (``cv2.resize`` with ``INTER_AREA``: for a
        whole factor, the mean of each block of pixels) to
        ``round(rows / s) x round(cols / s)`` with ``s = max(rows, cols) / max_side``,
        and the view is :meth:`CArmView.resized` to it (the same detector with
        larger pixels), so that 3D points project onto the same image content.
        A run that already fits is returned as it is.

        Parameters
        ----------
        max_side : int
            The largest number of rows or columns to keep (at least 16).

        Returns
        -------
        XARun
            The resampled run (same dtype, frame times, R-waves and identifiers),
            or ``self``.

        Raises
        ------
        ArgumentError
            For a ``max_side`` that is not a whole number >= 16.

        Examples
        --------
        >>> run.view.rows, run.view.pixel_spacing_mm        # doctest: +SKIP
        (1024, (0.154, 0.154))
        >>> small = run.resampled(512)                       # doctest: +SKIP
        >>> small.view.rows, small.view.pixel_spacing_mm     # doctest: +SKIP
        (512, (0.308, 0.308))
        """
        import cv2

        if (isinstance(max_side, (bool, np.bool_)) or not isinstance(max_side, (int, np.integer))
                or max_side < 16):
            raise ArgumentError(f"max_side: expected a whole number >= 16, got {max_side!r}")
        h, w = self.frames.shape[1:]
        if max(h, w) <= max_side:
            return self
        s = max(h, w) / float(max_side)
        rows, cols = max(1, int(round(h / s))), max(1, int(round(w / s)))
        frames = np.stack([cv2.resize(f, (cols, rows), interpolation=cv2.INTER_AREA) for f in self.frames])
        return replace(self, frames=frames, view=self.view.resized(rows, cols))

    def __repr__(self) -> str:
        v = self.view
        return (
            f"XARun({self.n_frames} frames {v.rows}x{v.cols}, "
            f"primary={v.primary_deg:+.1f} deg, secondary={v.secondary_deg:+.1f} deg, "
            f"source={self.source!r})"
        )
