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
* **Augmentation** (:class:`Sampler`): gamma, extra vessel opacification,
  blur, noise, low-frequency shading, black circular image-intensifier or
  rectangular shutter borders on the raw frame; then the same per-frame
  normalization as inference (:func:`vesselcad.segment.normalize_frames`); then
  one affine warp (log-uniform scale 0.55-1.9, any rotation, flips) to the crop,
  centred on a foreground pixel most of the time.

No torch in this module's import path except :class:`Sampler`'s base class.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vesselcad.segment import normalize_frames

__all__ = ["REAL_VAL_IDS", "NOT_VESSEL", "IGNORE", "Pool", "find_real_dir", "load_real", "render_pool",
           "render_test_set", "Sampler"]

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
    """Rendered phantom frames (raw pixels) with labels and the bits stored per pixel."""

    frames: list[np.ndarray]
    labels: list[np.ndarray]
    bits: list[int]

    def save(self, path: str | os.PathLike) -> None:
        np.savez(path, frames=np.array(self.frames, dtype=object), labels=np.array(self.labels, dtype=object),
                 bits=np.array(self.bits))

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


# ---------------------------------------------------------------- augmentation
def _raw_augment(img: np.ndarray, lab: np.ndarray | None, bits: int, rng: np.random.Generator,
                 phantom: bool) -> np.ndarray:
    """Photometric augmentation of one raw frame; returns float32 in ~[0, 1]."""
    x = img.astype(np.float32) / float(2**bits - 1)
    h, w = x.shape
    if phantom and lab is not None and rng.uniform() < 0.6:
        # more (or less) iodine: darken the opacified vessels by a random factor
        v = cv2.GaussianBlur((lab == 1).astype(np.float32), (0, 0), 0.8)
        x *= 1.0 - rng.uniform(0.0, 0.45) * v
    if rng.uniform() < 0.5:  # low-frequency shading (heel effect, thickness), built at 32 x 32
        gy, gx = np.mgrid[0:32, 0:32].astype(np.float32) / 31.0 - 0.5
        a = rng.normal(0, 0.25, 3)
        shade = np.exp(a[0] * gx + a[1] * gy + a[2] * gx**2).astype(np.float32)
        x *= cv2.resize(shade, (w, h), interpolation=cv2.INTER_LINEAR)
    x = cv2.pow(np.clip(x, 1e-4, None), float(rng.uniform(0.6, 1.6)))
    if rng.uniform() < 0.4:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.3))
    if rng.uniform() < 0.6:
        noise = np.empty_like(x)
        cv2.setRNGSeed(int(rng.integers(2**31)))
        cv2.randn(noise, 0.0, float(rng.uniform(0.005, 0.04)))
        x = x + noise * cv2.sqrt(np.clip(x, 0, None))
    u = rng.uniform()
    if u < 0.25:  # image-intensifier circle with black corners
        cy, cx = rng.uniform(0.45, 0.55, 2) * (h, w)
        r = rng.uniform(0.5, 0.72) * min(h, w)
        yy, xx = np.ogrid[0:h, 0:w]
        x[(yy - cy) ** 2 + (xx - cx) ** 2 > r * r] = rng.uniform(0.0, 0.03)
    elif u < 0.45:  # shutter / collimator blades
        for side in range(4):
            if rng.uniform() < 0.5:
                t = int(rng.uniform(0.01, 0.12) * (h if side < 2 else w))
                val = rng.uniform(0.0, 0.05) if rng.uniform() < 0.7 else rng.uniform(0.8, 1.0)
                if side == 0:
                    x[:t] = val
                elif side == 1:
                    x[h - t:] = val
                elif side == 2:
                    x[:, :t] = val
                else:
                    x[:, w - t:] = val
    return x


def _warp(x: np.ndarray, target: np.ndarray, crop: int, rng: np.random.Generator,
          fg: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """One random affine warp of the normalized image and its target into a ``crop`` square."""
    h, w = x.shape
    s = float(np.exp(rng.uniform(np.log(0.55), np.log(1.9))))
    ang = rng.uniform(0, 2 * np.pi)
    if fg is not None and len(fg) and rng.uniform() < 0.75:
        cy, cx = fg[rng.integers(len(fg))] + rng.normal(0, 0.1 * crop / s, 2)
    else:
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
    c, sn = np.cos(ang) * s, np.sin(ang) * s
    fx = -1.0 if rng.uniform() < 0.5 else 1.0
    m = np.array([[c * fx, -sn, 0.0], [sn * fx, c, 0.0]])
    m[:, 2] = np.array([crop / 2, crop / 2]) - m[:, :2] @ np.array([cx, cy])
    xi = cv2.warpAffine(x, m, (crop, crop), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    ti = cv2.warpAffine(target, m, (crop, crop), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REFLECT_101)
    return xi, ti


def make_sample(img: np.ndarray, lab: np.ndarray, bits: int, phantom: bool, crop: int,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One augmented training crop: normalized image (float32) and target (uint8).

    Target codes: phantom 0..4 (:data:`vesselcad.segment.CLASSES`); real 1 vessel,
    :data:`NOT_VESSEL` anything else.
    """
    x = _raw_augment(img, lab if phantom else None, bits, rng, phantom)
    z = normalize_frames(x[None])[0]
    target = lab.astype(np.uint8) if phantom else np.where(lab, 1, NOT_VESSEL).astype(np.uint8)
    fg_mask = (target >= 1) & (target <= 4)
    ys, xs = np.nonzero(fg_mask[::4, ::4])
    fg = np.stack([ys, xs], 1) * 4 if len(ys) else None
    return _warp(z, target, crop, rng, fg)


try:  # torch is only needed to train
    from torch.utils.data import Dataset as _Dataset
except ImportError:  # pragma: no cover
    _Dataset = object  # type: ignore[assignment,misc]


class Sampler(_Dataset):  # type: ignore[misc]
    """Map-style dataset of augmented crops; item ``i`` is deterministic for a given seed.

    Parameters
    ----------
    pool : Pool
        Phantom frames.
    real_images, real_masks : lists
        Real training images and vessel masks.
    length : int
        Items per epoch (training draws from it with a seeded sampler).
    crop : int
        Crop side (multiple of 16).
    real_fraction : float
        Probability that an item is a real image.
    seed : int
        Base seed.
    """

    def __init__(self, pool: Pool, real_images: list[np.ndarray], real_masks: list[np.ndarray], *,
                 length: int, crop: int = 256, real_fraction: float = 0.35, seed: int = 0):
        self.pool, self.real_images, self.real_masks = pool, real_images, real_masks
        self.length, self.crop, self.real_fraction, self.seed = int(length), int(crop), real_fraction, seed

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int):
        import torch

        rng = np.random.default_rng([self.seed, int(i)])
        if self.real_images and rng.uniform() < self.real_fraction:
            k = int(rng.integers(len(self.real_images)))
            x, t = make_sample(self.real_images[k], self.real_masks[k], 8, False, self.crop, rng)
        else:
            k = int(rng.integers(len(self.pool.frames)))
            x, t = make_sample(self.pool.frames[k], self.pool.labels[k], self.pool.bits[k], True,
                               self.crop, rng)
        return torch.from_numpy(x[None].copy()), torch.from_numpy(t.astype(np.int64))


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
