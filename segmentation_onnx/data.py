"""Training data: phantom frames with all five classes, mixed with real angiograms (vessel class only).

* **Phantom pool.** :func:`render_pool` renders frames of random phantoms with
  :func:`vesselcad.phantom.render` (random anatomy - left/right coronary tree
  or coronary sinus -, devices, C-arm angles, contrast phase, motion,
  background, noise, 8 or 12 bits) over worker processes. Frames without
  opacified vessels are kept but thinned out (a run starts before the
  contrast arrives, so the model must see them).
* **Real images.** The 40 CIMAT angiograms with manual vessel masks
  (``xca-real/train``). :data:`REAL_VAL_IDS` (10 of them) are never trained on.
  Their catheters are not labelled, so on real images the loss only asks
  "vessel or not" (target code :data:`NOT_VESSEL`).
* **Augmentation** is done batch-wise on the training device by
  :class:`segmentation_onnx.torch_aug.BatchAugmenter`.

No torch in this module.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vesselcad.io.atomic import atomic_path

__all__ = ["REAL_VAL_IDS", "NOT_VESSEL", "IGNORE", "Pool", "find_real_dir", "load_real", "render_pool",
           "render_test_set"]

#: CIMAT image ids kept out of training (real validation split; fixed, spread over the set).
REAL_VAL_IDS: tuple[int, ...] = (4, 8, 12, 16, 20, 24, 28, 32, 36, 40)
#: Target code of a real-image pixel that is not vessel (background, catheter or anything else).
NOT_VESSEL = 5
#: Target code of a pixel without a label.
IGNORE = 255
#: Seeds of the held-out phantom test set start here; training pools use small seeds.
TEST_SEED0 = 10_000_000


def find_real_dir(path: str | os.PathLike | None = None) -> Path:
    """Folder holding ``train/N.png`` and ``train/N_gt.png`` (the CIMAT set).

    Looks at ``path``, then ``$VESSELCAD_XCA_REAL``, then ``../shared/data/xca-real``
    beside the repository, then ``<repo>/.data/xca-real``.
    """
    here = Path(__file__).resolve().parents[1]
    cands = [path, os.environ.get("VESSELCAD_XCA_REAL"), here.parent / "shared/data/xca-real",
             here / ".data/xca-real"]
    for c in cands:
        if c and (Path(c) / "train" / "1.png").is_file():
            return Path(c)
    raise FileNotFoundError("real angiograms (xca-real/train/N.png) not found; pass --real-dir or set "
                            "VESSELCAD_XCA_REAL")


def load_real(ids: tuple[int, ...] | list[int], root: str | os.PathLike | None = None
              ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Real images (uint8) and their vessel masks (bool) for the given CIMAT ids."""
    d = find_real_dir(root) / "train"
    imgs, masks = [], []
    for i in ids:
        im = cv2.imread(str(d / f"{i}.png"), cv2.IMREAD_GRAYSCALE)
        gt = cv2.imread(str(d / f"{i}_gt.png"), cv2.IMREAD_GRAYSCALE)
        if im is None or gt is None:
            raise FileNotFoundError(f"{d}: image or mask of id {i} missing")
        imgs.append(im)
        masks.append(gt > 127)
    return imgs, masks


@dataclass
class Pool:
    """Rendered phantom frames (raw pixels, any integer dtype) with labels and the bits used per pixel."""

    frames: list[np.ndarray]
    labels: list[np.ndarray]
    bits: list[int]

    def save(self, path: str | os.PathLike) -> None:
        """Write an ``.npz`` atomically (stacked uint16 frames when all frames share one shape: fast
        to load); like :func:`numpy.savez`, ``.npz`` is appended to a name without it."""
        if len({f.shape for f in self.frames}) == 1:
            frames, labels = np.stack(self.frames).astype(np.uint16), np.stack(self.labels)
        else:
            frames, labels = np.array(self.frames, dtype=object), np.array(self.labels, dtype=object)
        path = os.fspath(path)
        with atomic_path(path if path.endswith(".npz") else f"{path}.npz", keep_name=True) as tmp:
            np.savez(tmp, frames=frames, labels=labels, bits=np.array(self.bits))

    @classmethod
    def load(cls, path: str | os.PathLike) -> Pool:
        z = np.load(path, allow_pickle=True)
        return cls(list(z["frames"]), list(z["labels"]), [int(b) for b in z["bits"]])


def _render_one(args: tuple[int, int, int, float]) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    from vesselcad.phantom import render

    seed, rows, n_frames, keep_empty = args
    rng = np.random.default_rng([seed, 77])
    bits = 12 if rng.uniform() < 0.3 else 8
    run = render(seed, rows=rows, cols=rows, n_frames=n_frames, bits=bits)
    frames, labels = [], []
    for fr, lab in zip(run.frames, run.labels, strict=True):
        has_vessel = (lab == 1).mean() > 0.002
        if has_vessel or rng.uniform() < keep_empty:
            frames.append(fr)
            labels.append(lab)
    return frames, labels, bits


def render_pool(seeds: range | list[int], *, rows: int = 512, frames_per_seed: int = 6,
                keep_empty: float = 0.25, workers: int | None = None, progress: bool = True) -> Pool:
    """Render phantom frames for training (parallel over seeds).

    Parameters
    ----------
    seeds : iterable of int
        One random phantom (anatomy, devices, view, appearance) per seed.
    rows : int
        Frame size (square).
    frames_per_seed : int
        Frames rendered per phantom, spread over its run.
    keep_empty : float
        Share of the frames without opacified vessel that are kept.
    workers : int, optional
        Processes (default: all cores).
    """
    jobs = [(int(s), int(rows), int(frames_per_seed), float(keep_empty)) for s in seeds]
    frames: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    bits: list[int] = []
    workers = workers or os.cpu_count() or 1
    it = None
    with ProcessPoolExecutor(max_workers=workers) as ex:
        it = ex.map(_render_one, jobs, chunksize=2)
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(it, total=len(jobs), desc="render phantom", unit="phantom")
        for fr, lab, b in it:
            frames += fr
            labels += lab
            bits += [b] * len(fr)
    return Pool(frames, labels, bits)


def _test_one(seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    from vesselcad.phantom import render

    run = render(seed, rows=512, cols=512, n_frames=8)
    area = (run.labels == 1).reshape(len(run.labels), -1).sum(axis=1)
    best = int(np.argmax(area))
    other = int(np.random.default_rng(seed).integers(len(run.labels)))
    if other == best:
        other = (best + 4) % len(run.labels)
    return [run.frames[best], run.frames[other]], [run.labels[best], run.labels[other]]


def render_test_set(n_phantoms: int = 120, workers: int | None = None,
                    cache: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The fixed held-out phantom test set: 2 frames (512 x 512, 8 bit) per phantom.

    Seeds ``TEST_SEED0 ..``, never used for training. Of each phantom's eight
    frames spread over its run, the most opacified one and one drawn at random
    are kept, so the set holds frames with and without contrast. Cached as
    ``.npz`` when ``cache`` is given.
    """
    if cache is not None and Path(cache).is_file():
        z = np.load(cache)
        if len(z["frames"]) == 2 * n_phantoms:
            return z["frames"], z["labels"]
    seeds = range(TEST_SEED0, TEST_SEED0 + int(n_phantoms))
    with ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1) as ex:
        out = list(ex.map(_test_one, seeds))
    frames = np.stack([f for fr, _ in out for f in fr])
    labels = np.stack([lab for _, la in out for lab in la])
    if cache is not None:
        Path(cache).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache, frames=frames, labels=labels)
    return frames, labels


def main(argv: list[str] | None = None) -> int:
    """``python -m segmentation_onnx.data --out pool.npz``: render a training pool once."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m segmentation_onnx.data", description=main.__doc__)
    ap.add_argument("--out", required=True)
    ap.add_argument("--phantoms", type=int, default=600)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=6, help="frames per phantom")
    ap.add_argument("--rows", type=int, default=512)
    ap.add_argument("--workers", type=int, default=None)
    a = ap.parse_args(argv)
    pool = render_pool(range(a.first_seed, a.first_seed + a.phantoms), rows=a.rows,
                       frames_per_seed=a.frames, workers=a.workers)
    pool.save(a.out)
    print(f"{len(pool.frames)} frames -> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
