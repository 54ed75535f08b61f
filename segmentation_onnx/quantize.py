"""Check inputs and int8 quantization of an exported model (onnxruntime only, no torch)."""

from __future__ import annotations

import os

import numpy as np

__all__ = ["sample_inputs", "quantize_int8"]


def sample_inputs(n: int = 4, seed: int = 0) -> list[np.ndarray]:
    """Normalized phantom frames (512 and 304 px) used to check and calibrate an export."""
    from vesselcad.phantom import render
    from vesselcad.segment import normalize_frames

    out = []
    for k in range(n):
        rows = 512 if k % 2 == 0 else 304
        fr = render(seed + k, rows=rows, cols=rows, n_frames=1).frames
        out.append(normalize_frames(fr)[:, None].astype(np.float32))
    return out


def quantize_int8(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Static int8 quantization (QDQ, per-channel weights) calibrated on a few frames."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = iter([{"image": x} for x in sample_inputs(8, seed=100)])

        def get_next(self):
            return next(self.items, None)

    quantize_static(str(src), str(dst), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
