"""Export a trained checkpoint to ONNX and check it against torch.

The ONNX graph takes ``image`` (N, 1, H, W) float32 - frames normalized by
:func:`vesselcad.segment.normalize_frames`, H and W multiples of 16 - and gives
``logits`` (N, 5, H, W); batch, height and width are dynamic (opset 17). The
export is verified: onnxruntime and torch must agree within ``--atol``
(default 1e-4) on real-looking input of two sizes, else the file is not
written. ``--int8`` also writes a statically quantized copy (QDQ, calibrated
on phantom and real frames).

Example::

    python -m segmentation_onnx.export runs/gated/last.pt segmentation_onnx/gated_unet.onnx
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from .model import build_model
from .quantize import quantize_int8, sample_inputs


def load_checkpoint(path: str | os.PathLike) -> torch.nn.Module:
    """The model of a training checkpoint (eval mode, CPU)."""
    ck = torch.load(path, map_location="cpu")
    model = build_model(ck["arch"], tuple(ck["widths"]))
    model.load_state_dict(ck["model"])
    return model.eval()


def export(model: torch.nn.Module, path: str | os.PathLike, *, atol: float = 1e-4) -> dict[str, float]:
    """Write ``model`` as ONNX to ``path`` (atomically) after checking it against torch.

    Returns
    -------
    dict
        ``max_abs_diff`` of the logits over the check inputs, and the file size in MB.
    """
    import onnxruntime as ort

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval().cpu()
    fd, tmp_name = tempfile.mkstemp(suffix=".onnx", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        dummy = torch.zeros(1, 1, 256, 256)
        torch.onnx.export(model, dummy, str(tmp), opset_version=17, input_names=["image"],
                          output_names=["logits"], do_constant_folding=True, dynamo=False,
                          dynamic_axes={"image": {0: "batch", 2: "height", 3: "width"},
                                        "logits": {0: "batch", 2: "height", 3: "width"}})
        sess = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        worst = 0.0
        with torch.no_grad():
            for x in sample_inputs(2):
                ref = model(torch.from_numpy(x)).numpy()
                got = sess.run(None, {"image": x})[0]
                worst = max(worst, float(np.abs(ref - got).max()))
        if not worst <= atol:
            raise RuntimeError(f"ONNX export differs from torch by {worst:.2e} > {atol:.0e}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return {"max_abs_diff": worst, "size_mb": path.stat().st_size / 1e6}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m segmentation_onnx.export",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("out", help=".onnx file")
    ap.add_argument("--atol", type=float, default=1e-4)
    ap.add_argument("--int8", help="also write a statically quantized model here")
    a = ap.parse_args(argv)
    info = export(load_checkpoint(a.checkpoint), a.out, atol=a.atol)
    if a.int8:
        quantize_int8(a.out, a.int8)
        info["int8_size_mb"] = Path(a.int8).stat().st_size / 1e6
    print(json.dumps(info))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
