"""Check inputs and int8 quantization of an exported model (onnxruntime only, no torch).

``python -m segmentation_onnx.quantize SRC.onnx DST.onnx`` writes the static
int8 model (``gated_unet_int8.onnx`` is made this way from ``gated_unet.onnx``;
needs the ``onnx`` package: extras ``train`` or ``dev``).
"""

from __future__ import annotations

import argparse
import os

import numpy as np

__all__ = ["sample_inputs", "quantize_int8", "main"]


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


def quantize_int8(src: str | os.PathLike, dst: str | os.PathLike, *, reduce_range: bool = True) -> None:
    """Static int8 quantization (QDQ, per-channel weights) calibrated on 8 phantom frames.

    Activations are uint8, weights int8. With ``reduce_range`` (default) the
    weights use 7 bits (-64..64): x86 CPUs without VNNI multiply uint8 by int8
    with an instruction (``vpmaddubsw``) that adds two products into a
    saturating int16, and 2 x 255 x 64 still fits where 2 x 255 x 127 does not
    (the full-range model lost vessel IoU 0.79 -> 0.62 on an AMD EPYC).

    Parameters
    ----------
    src, dst : path-like
        The fp32 ONNX model and the file to write.
    reduce_range : bool
        7-bit weights (saturation-free on every x86 CPU).
    """
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = iter([{"image": x} for x in sample_inputs(8, seed=100)])

        def get_next(self):
            return next(self.items, None)

    quantize_static(str(src), str(dst), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    reduce_range=reduce_range, activation_type=QuantType.QUInt8,
                    weight_type=QuantType.QInt8)


def main(argv: list[str] | None = None) -> int:
    """Command line: quantize one model."""
    ap = argparse.ArgumentParser(description="static int8 quantization of a segmentation model")
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--full-range", action="store_true",
                    help="8-bit weights (saturates on CPUs without VNNI)")
    a = ap.parse_args(argv)
    quantize_int8(a.src, a.dst, reduce_range=not a.full_range)
    print(f"wrote {a.dst} ({os.path.getsize(a.dst) / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
