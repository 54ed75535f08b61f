"""Score ONNX segmentation models exactly as the package runs them (``vesselcad.Segmenter``).

* per-class IoU and mIoU (dataset-level, over all pixels) on the fixed held-out
  phantom test set (:func:`segmentation_onnx.data.render_test_set`: 120 phantoms
  never trained on, 2 frames each, 512 x 512);
* vessel Dice and IoU on the real validation split (10 CIMAT angiograms,
  :data:`segmentation_onnx.data.REAL_VAL_IDS`, never trained on), per image and
  pooled;
* guiding catheters on 8 real flat-panel images never trained on (hand-drawn,
  :mod:`segmentation_onnx.catheter_labels`): share labelled catheter / vessel;
* inference time per 512 x 512 frame with onnxruntime on a given number of threads.

Needs onnxruntime only (no torch). Example::

    python -m segmentation_onnx.evaluate segmentation_onnx/gated_unet.onnx segmentation_onnx/unet.onnx
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from vesselcad.segment import CLASSES, Segmenter

from .data import REAL_VAL_IDS, load_real, render_test_set


def iou_per_class(pred: np.ndarray, truth: np.ndarray, n: int = len(CLASSES)) -> np.ndarray:
    """Dataset-level IoU of each class (NaN where a class occurs in neither)."""
    idx = truth.astype(np.int64).ravel() * n + pred.astype(np.int64).ravel()
    cm = np.bincount(idx, minlength=n * n).reshape(n, n)
    tp = np.diag(cm).astype(float)
    den = cm.sum(0) + cm.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, tp / den, np.nan)


def evaluate_phantom(model: str | os.PathLike, frames: np.ndarray, labels: np.ndarray,
                     threads: int | None = None, tta: bool = False) -> dict[str, float]:
    """Per-class IoU (``iou_<class>``) and ``miou`` (mean over the five classes); ``tta``: with
    mirror test-time augmentation (``Segmenter(tta=True)``)."""
    pred = Segmenter(model, threads=threads, tta=tta)(frames)
    iou = iou_per_class(pred, labels)
    return {**{f"iou_{c}": float(v) for c, v in zip(CLASSES, iou, strict=True)},
            "miou": float(np.nanmean(iou))}


def evaluate_real(model: str | os.PathLike, real_dir: str | os.PathLike | None = None,
                  threads: int | None = None, tta: bool = False) -> dict[str, object]:
    """Vessel Dice/IoU on the real validation split: mean of the images and pooled pixels."""
    imgs, masks = load_real(REAL_VAL_IDS, real_dir)
    seg = Segmenter(model, threads=threads, tta=tta)
    dices, ious, inter, tot, union = [], [], 0, 0, 0
    for im, gt in zip(imgs, masks, strict=True):
        p = seg(im) == 1
        i, s, u = np.logical_and(p, gt).sum(), p.sum() + gt.sum(), np.logical_or(p, gt).sum()
        dices.append(2 * i / max(s, 1))
        ious.append(i / max(u, 1))
        inter, tot, union = inter + i, tot + s, union + u
    return {"dice_mean": float(np.mean(dices)), "dice_pooled": float(2 * inter / tot),
            "iou_mean": float(np.mean(ious)), "dice_per_image": [round(float(d), 4) for d in dices]}


#: A catheter tip found within this distance (px) of the drawn one counts as found there: the
#: drawn tips were read by eye (about 10 px) and the targets leave 12 px around them unlabelled.
TIP_TOLERANCE_PX = 20.0


def catheter_tip_errors(labels: np.ndarray, tips_xy: np.ndarray, frames: np.ndarray | None = None
                        ) -> np.ndarray:
    """Distance (px) from the catheter tip that motion phase matching finds in each label map
    (:func:`vesselcad.phase.find_keypoints`, class 2, given the grey ``frames`` as
    ``match_phase`` gives them: a catheter enters at the inner edge of a dark image border) to
    the given true tip ``(x, y)``; NaN where it finds none."""
    from vesselcad.phase import find_keypoints

    found = find_keypoints(labels, "catheter", frames=frames).points_px
    return np.hypot(*(found - np.asarray(tips_xy, float)).T)


def evaluate_real_catheters(model: str | os.PathLike, real_dir: str | os.PathLike | None = None,
                            threads: int | None = None, tta: bool = False) -> dict[str, float]:
    """Guiding catheters on the held-out real flat-panel images (hand-drawn, never trained on).

    On the 8 test images of ``real_labels/arcade_catheters.json``
    (:mod:`segmentation_onnx.catheter_labels`), pooled over their pixels:
    ``cath_recall`` the share of catheter pixels labelled catheter,
    ``cath_as_vessel`` the share labelled vessel, ``cath_iou`` the catheter IoU over
    the labelled pixels (catheter, vessel and background of the targets), and
    ``vessel_kept`` the share of the target's vessel pixels (the tree the catheter
    feeds, as the round-7 model drew it) still labelled vessel. Per image, the tip that
    motion phase matching would take from the labels: ``tip_found`` the share of images
    where it finds one, ``tip_near`` the share where it lies within
    :data:`TIP_TOLERANCE_PX` of the drawn tip, ``tip_median_px`` the median distance of
    those found (NaN if none).
    """
    from .catheter_labels import load_polylines, load_targets

    imgs, tgts, names = load_targets(real_dir=real_dir, split="test")
    lines, _ = load_polylines()
    seg = Segmenter(model, threads=threads, tta=tta)
    pred = seg(np.stack(imgs))
    t = np.stack(tgts)
    cath, ves, known = t == 2, t == 1, t <= 4
    pc = (pred == 2) & known
    d = catheter_tip_errors(pred, np.array([lines[n][-1] for n in names], float), np.stack(imgs))
    ok = np.isfinite(d)
    return {"cath_recall": float((pred[cath] == 2).mean()), "cath_as_vessel": float((pred[cath] == 1).mean()),
            "cath_iou": float((pc & cath).sum() / max((pc | cath).sum(), 1)),
            "vessel_kept": float((pred[ves] == 1).mean()),
            "tip_found": float(ok.mean()), "tip_near": float((d[ok] <= TIP_TOLERANCE_PX).sum() / len(d)),
            "tip_median_px": float(np.median(d[ok])) if ok.any() else float("nan")}


def time_inference(model: str | os.PathLike, threads: int = 2, size: int = 512,
                   repeats: int = 10, tta: bool = False) -> float:
    """Median milliseconds per ``size`` x ``size`` frame (one frame per call, after a warm-up)."""
    from vesselcad.phantom import render

    frame = render(12345, rows=size, cols=size).frames[0]
    seg = Segmenter(model, threads=threads, batch_size=1, tta=tta)
    seg(frame)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        seg(frame)
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1000)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m segmentation_onnx.evaluate",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+", help=".onnx files")
    ap.add_argument("--phantoms", type=int, default=120, help="test phantoms (2 frames each)")
    ap.add_argument("--cache", default=str(Path.home() / ".cache/vesselcad/seg_test_set.npz"))
    ap.add_argument("--real-dir")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write the scores here")
    ap.add_argument("--tta", action="store_true", help="with mirror test-time augmentation")
    a = ap.parse_args(argv)
    frames, labels = render_test_set(a.phantoms, cache=a.cache)
    rows = {}
    for m in a.models:
        r = evaluate_phantom(m, frames, labels, threads=a.threads, tta=a.tta)
        r.update(evaluate_real(m, a.real_dir, threads=a.threads, tta=a.tta))
        r.update(evaluate_real_catheters(m, a.real_dir, threads=a.threads, tta=a.tta))
        r["ms_per_512_frame"] = time_inference(m, threads=a.threads, tta=a.tta)
        rows[Path(m).name] = r
        shown = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
        print(Path(m).name, json.dumps(shown))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
