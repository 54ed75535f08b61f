"""Hard-example focus: where a trained model mislabels devices on a rendered pool.

A training round that starts from a model can centre part of its phantom crops
on the pixels that model gets wrong (``train.py --hard-focus``). Here "wrong"
means a disagreement that involves a device class: a catheter, balloon or lead
pixel labelled something else, or a pixel labelled catheter, balloon or lead
that is not one. Vessel/background disagreements (thin vessels, edges) are
left out: they are the bulk of the errors and what the real images train.

Disagreements thinner than 3 px (a tube drawn a pixel wider or narrower) are
dropped by a 3 x 3 opening: on the round-12 model they made nearly every
device pixel "hard" (1400 such pixels a frame). The map is stored on the same
4-pixel grid as :func:`torch_aug.focus_grid` (a grid cell is hard when any
pixel of its 4 x 4 block is).

Usage::

    python -m segmentation_onnx.hard_focus --pool pool.npz --model segmentation_onnx/gated_unet.onnx \
        --out hard.npz
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from scipy import ndimage

from .data import Pool

__all__ = ["device_errors", "hard_grid", "load_hard", "main"]

DEVICE_CLASSES = (2, 3, 4)
GRID = 4


def device_errors(truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Pixels where ``pred`` and ``truth`` disagree and either says catheter, balloon or lead.

    Parameters
    ----------
    truth, pred : np.ndarray
        (..., H, W) label maps (0 background, 1 vessel, 2 catheter, 3 balloon, 4 lead).

    Returns
    -------
    np.ndarray
        bool, the shape of ``truth``.
    """
    truth, pred = np.asarray(truth), np.asarray(pred)
    if truth.shape != pred.shape:
        raise ValueError(f"truth {truth.shape} and prediction {pred.shape} differ in shape")
    dev_t = np.isin(truth, DEVICE_CLASSES)
    dev_p = np.isin(pred, DEVICE_CLASSES)
    return (truth != pred) & (dev_t | dev_p)


def hard_grid(errors: np.ndarray, min_width: int = 3) -> np.ndarray:
    """(N, H, W) bool error masks to the (N, ceil(H/4), ceil(W/4)) grid of hard cells.

    Errors are first opened with a ``min_width`` square (thinner slivers dropped);
    a cell with any error left is hard.
    """
    errors = np.asarray(errors, bool)
    if min_width > 1:
        errors = ndimage.binary_opening(errors, np.ones((1, min_width, min_width), bool))
    n, h, w = errors.shape
    hp, wp = -(-h // GRID) * GRID, -(-w // GRID) * GRID
    pad = np.zeros((n, hp, wp), bool)
    pad[:, :h, :w] = errors
    return pad.reshape(n, hp // GRID, GRID, wp // GRID, GRID).any(axis=(2, 4))


def load_hard(path: str | os.PathLike, n_frames: int) -> np.ndarray:
    """Read a map written by :func:`main`; checks that it covers ``n_frames`` pool frames."""
    z = np.load(path)
    grid = np.unpackbits(z["bits"], axis=-1, count=int(z["cols"])).astype(bool)
    if len(grid) != n_frames:
        raise ValueError(f"{path}: hard-focus map has {len(grid)} frames, the pool {n_frames}")
    return grid


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pool", required=True, help="rendered pool (.npz from segmentation_onnx.data)")
    ap.add_argument("--model", required=True, help="ONNX model whose errors to find (or 'fp32'/'int8')")
    ap.add_argument("--out", required=True, help="output .npz")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)

    from tqdm.auto import tqdm

    import vesselcad as vc
    from vesselcad.io.atomic import atomic_path

    pool = Pool.load(a.pool)
    seg = vc.Segmenter(a.model, threads=a.threads)
    grids, n_err = [], 0
    for s in tqdm(range(0, len(pool.frames), a.batch), desc="hard focus", unit="batch", mininterval=10):
        frames = np.stack(pool.frames[s:s + a.batch])
        truth = np.stack(pool.labels[s:s + a.batch])
        pred = seg(frames)
        err = device_errors(truth, pred)
        n_err += int(err.sum())
        grids.append(hard_grid(err))
    grid = np.concatenate(grids)
    out = Path(a.out)
    with atomic_path(out, keep_name=True) as tmp:
        np.savez_compressed(tmp, bits=np.packbits(grid, axis=-1), cols=grid.shape[-1])
    share = float(grid.reshape(len(grid), -1).any(1).mean())
    print(f"{len(grid)} frames, {n_err} device-error pixels, {int(grid.sum())} hard cells "
          f"(errors 3 px wide or more), frames with any: {share:.1%} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
