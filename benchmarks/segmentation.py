"""Segmentation benchmark: gated U-Net vs plain U-Net (fp32 and int8), phantom and real images.

Prints one table:

* per-class IoU and mIoU on the fixed held-out phantom test set (120 phantoms
  never trained on x 2 frames = 240 frames, 512 x 512);
* vessel Dice on the real validation split (10 CIMAT angiograms never trained on);
* guiding catheters on 8 real flat-panel (ARCADE) images never trained on, drawn by hand
  (``segmentation_onnx/real_labels``): the share of their pixels labelled catheter and vessel,
  and the share of those images where the catheter tip that motion phase matching takes from
  the labels is found at all and within 20 px of the drawn tip;
* milliseconds per 512 x 512 frame with onnxruntime on ``--threads`` CPU threads;
* the same for the half-width pair ("fast": channels 8-16-32-64-128, both distilled from the
  bundled gated U-Net, ``gated_unet_fast.onnx`` and ``unet_fast.onnx``);
* the same for the int8 models: the bundled ``gated_unet_int8.onnx`` and
  ``gated_unet_fast_int8.onnx`` and the plain U-Nets quantized the same way
  (``segmentation_onnx.quantize.quantize_int8``, 7-bit weights);
* every model again with test-time augmentation (``Segmenter(tta=True)``: the mean class
  probabilities of the frame and its three mirror images, each at the frame's size and at 0.75
  of it; ``--no-tta`` skips these rows);

next to the goals of issue 12 and, clearly apart, the paper's mIoU figures
(measured on the paper's own real data, not comparable number for number).
``--render DIR`` also writes the overlay pictures used in docs/.

Usage::

    python benchmarks/segmentation.py [--threads 2] [--json out.json] [--render docs/img]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from segmentation_onnx.data import render_test_set
from segmentation_onnx.evaluate import (
    TIP_TOLERANCE_PX,
    evaluate_phantom,
    evaluate_real,
    evaluate_real_catheters,
    time_inference,
)
from vesselcad.segment import bundled_model_path

GOALS = {"iou_vessel": 0.85, "iou_catheter": 0.75, "iou_balloon": 0.80, "dice_mean": 0.80,
         "ms_per_512_frame": 80.0}
PAPER = "paper (own real data, mIoU %): U-Net 67.45 / CMU-Net 68.17 / gated U-Net 70.33"


def _write_png(path: Path, rgb: np.ndarray) -> Path:
    import cv2

    from vesselcad.io.atomic import atomic_write_bytes

    atomic_write_bytes(path, cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes())
    return path


def render_pictures(out: Path, model: Path) -> list[Path]:
    """Overlays on the real validation images (manual mask outlined) and on held-out ARCADE frames."""
    import cv2

    from segmentation_onnx.data import REAL_VAL_IDS, find_real_dir, load_real
    from vesselcad.segment import Segmenter, overlay_labels

    seg = Segmenter(model)
    out.mkdir(parents=True, exist_ok=True)
    imgs, masks = load_real(REAL_VAL_IDS[:6])
    tiles = [overlay_labels(im, seg(im), truth=gt) for im, gt in zip(imgs, masks, strict=True)]
    grid = np.vstack([np.hstack(tiles[0:3]), np.hstack(tiles[3:6])])
    paths = []
    paths.append(_write_png(out / "seg_real_validation.png", grid))
    # flat-panel frames whose catheters were drawn for testing and never trained on
    from segmentation_onnx.catheter_labels import load_polylines

    _, test = load_polylines()
    unl = [find_real_dir() / "unlabelled" / f"{name}.png" for name in test[:6]]
    if unl:
        tiles = []
        for f in unl:
            im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            ov = overlay_labels(im, seg(im))
            tiles.append(cv2.resize(np.hstack([np.repeat(im[..., None], 3, 2), ov]), None, fx=0.5, fy=0.5))
        grid = np.vstack([np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles) - 1, 2)])
        paths.append(_write_png(out / "seg_arcade_unlabelled.png", grid))
    return paths


def render_fast_picture(out: Path, model: Path, fast: Path) -> Path:
    """The default network (top row) and the fast one (bottom row) on two real validation images and two
    held-out ARCADE frames (red vessel, green catheter; white outline: the manual vessel mask)."""
    import cv2

    from segmentation_onnx.catheter_labels import load_polylines
    from segmentation_onnx.data import find_real_dir, load_real
    from vesselcad.segment import Segmenter, overlay_labels

    imgs, masks = load_real((4, 20))
    _, test = load_polylines()
    frames = [(im, gt) for im, gt in zip(imgs, masks, strict=True)]
    frames += [(cv2.imread(str(find_real_dir() / "unlabelled" / f"{n}.png"), cv2.IMREAD_GRAYSCALE), None)
               for n in test[:2]]
    rows = []
    for m in (model, fast):
        seg = Segmenter(m)
        rows.append(np.hstack([cv2.resize(overlay_labels(im, seg(im), truth=gt), (256, 256),
                                          interpolation=cv2.INTER_AREA) for im, gt in frames]))
    out.mkdir(parents=True, exist_ok=True)
    return _write_png(out / "seg_fast_vs_default.png", np.vstack(rows))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--phantoms", type=int, default=120)
    ap.add_argument("--cache", default=str(Path.home() / ".cache/vesselcad/seg_test_set.npz"))
    ap.add_argument("--no-int8", action="store_true")
    ap.add_argument("--no-fast", action="store_true", help="skip the half-width models")
    ap.add_argument("--no-tta", action="store_true", help="skip the rows with mirror test-time augmentation")
    ap.add_argument("--json")
    ap.add_argument("--render", help="write overlay pictures into this folder")
    a = ap.parse_args()

    t0 = time.time()
    frames, labels = render_test_set(a.phantoms, cache=a.cache)
    print(f"phantom test set: {len(frames)} frames ({time.time() - t0:.0f} s)")
    models = {"gated U-Net fp32": bundled_model_path("gated_unet.onnx"),
              "plain U-Net fp32": bundled_model_path("unet.onnx")}
    if not a.no_fast:  # the half-width pair (vc.Segmenter("fast") and its plain twin)
        models["gated U-Net fast fp32"] = bundled_model_path("gated_unet_fast.onnx")
        models["plain U-Net fast fp32"] = bundled_model_path("unet_fast.onnx")
    tmpdir = Path(tempfile.mkdtemp())
    if not a.no_int8:
        from segmentation_onnx.quantize import quantize_int8

        # the bundled int8 models (vc.Segmenter("int8"), "fast-int8"); the baselines quantized the
        # same way here
        models["gated U-Net int8"] = bundled_model_path("gated_unet_int8.onnx")
        quantize_int8(models["plain U-Net fp32"], tmpdir / "unet_int8.onnx")
        models["plain U-Net int8"] = tmpdir / "unet_int8.onnx"
        if not a.no_fast:
            models["gated U-Net fast int8"] = bundled_model_path("gated_unet_fast_int8.onnx")
            quantize_int8(models["plain U-Net fast fp32"], tmpdir / "unet_fast_int8.onnx")
            models["plain U-Net fast int8"] = tmpdir / "unet_fast_int8.onnx"
    rows = {}
    for tta in (False,) if a.no_tta else (False, True):
        for name, path in models.items():
            r = evaluate_phantom(path, frames, labels, threads=a.threads, tta=tta)
            r.update(evaluate_real(path, threads=a.threads, tta=tta))
            r.update(evaluate_real_catheters(path, threads=a.threads, tta=tta))
            r["ms_per_512_frame"] = time_inference(path, threads=a.threads, tta=tta)
            r["size_mb"] = path.stat().st_size / 1e6
            rows[name + (" + TTA (mirrors x sizes 1, 0.75)" if tta else "")] = r
    cols = [("iou_vessel", "vessel IoU"), ("iou_catheter", "catheter IoU"), ("iou_balloon", "balloon IoU"),
            ("iou_lead", "lead IoU"), ("miou", "mIoU"), ("dice_mean", "real Dice"),
            ("cath_recall", "real catheter → catheter"), ("cath_as_vessel", "real catheter → vessel"),
            ("tip_found", "real tip found"), ("tip_near", f"real tip ≤ {TIP_TOLERANCE_PX:.0f} px"),
            ("ms_per_512_frame", f"ms/512² ({a.threads} thr)"), ("size_mb", "MB")]
    head = "| model | " + " | ".join(c[1] for c in cols) + " |"
    print(head)
    print("|" + "---|" * (len(cols) + 1))
    for name, r in rows.items():
        cells = [f"{r[k]:.1f}" if k in ("ms_per_512_frame", "size_mb") else f"{r[k]:.3f}" for k, _ in cols]
        print(f"| {name} | " + " | ".join(cells) + " |")
    goal = [f"≥ {GOALS[k]}" if k in GOALS and k != "ms_per_512_frame" else
            (f"≤ {GOALS[k]:.0f}" if k in GOALS else "") for k, _ in cols]
    print("| goal | " + " | ".join(goal) + " |")
    print(PAPER)
    print("real Dice per image (gated fp32):", rows["gated U-Net fp32"]["dice_per_image"])
    print(f"total {time.time() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    if a.render:
        for p in render_pictures(Path(a.render), models["gated U-Net fp32"]):
            print("wrote", p)
        if "gated U-Net fast fp32" in models:
            print("wrote", render_fast_picture(Path(a.render), models["gated U-Net fp32"],
                                               models["gated U-Net fast fp32"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
