"""Batch augmentation in torch, on the training device (GPU or CPU).

Augmentation of whole batches on the device that trains (GPU or CPU). It
replaced per-sample OpenCV augmentation in data-loader processes, which was the
bottleneck on a GPU (about 24 steps/s with 7 loader processes, the GPU mostly
idle). Frames, labels and real images stay on the device; each batch is drawn,
augmented, normalized (as :func:`vesselcad.segment.normalize_frames` does at
inference) and warped to crops with :func:`torch.nn.functional.grid_sample`.

Photometric: extra vessel opacification, the guiding catheter's contrast
randomized (filled with contrast or not, so the network must tell
catheter from vessel by shape and context, not by grey level), low-frequency
shading, gamma 0.6-1.6, blur, signal-dependent noise, black intensifier circle
or shutter blades. Geometric: one affine warp (log-uniform scale 0.55-1.9, any
rotation, mirror) to the crop, centred on a foreground pixel 75% of the time.
With ``focus_fraction`` > 0 that share of the phantom crops is centred on a
*focus* pixel instead: a catheter pixel within ``FOCUS_RADIUS`` px of a vessel
pixel (the ostium, where a contrast-filled catheter runs into the tree, and
catheter-vessel crossings) or a balloon pixel, where the model errs most;
with a *hard* map (:mod:`.hard_focus`, ``train.py --hard-focus``) also the
pixels where the model being fine-tuned mislabels a device, weighted higher.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .data import NOT_VESSEL, Pool

__all__ = ["BatchAugmenter", "normalize", "warp", "focus_grid"]

#: A catheter pixel this close to a vessel pixel (px of the pool frame) is a focus pixel.
FOCUS_RADIUS = 12


def focus_grid(labels: torch.Tensor, radius: int = FOCUS_RADIUS, chunk: int = 32) -> torch.Tensor:
    """Focus pixels of label maps on a 4-pixel grid.

    Parameters
    ----------
    labels : torch.Tensor
        (N, H, W) phantom labels (0 background, 1 vessel, 2 catheter, 3 balloon, 4 lead).
    radius : int
        A catheter pixel within this many pixels (Chebyshev) of a vessel pixel is a focus pixel.
    chunk : int
        Frames processed at once.

    Returns
    -------
    torch.Tensor
        (N, ceil(H/4), ceil(W/4)) bool: balloon pixels and catheter pixels near a vessel.
    """
    out = []
    k = 2 * radius + 1  # a square's max filter, separable
    for s in range(0, len(labels), chunk):
        lab = labels[s:s + chunk]
        near = F.max_pool2d((lab == 1).float()[:, None], (1, k), stride=1, padding=(0, radius))
        near = F.max_pool2d(near, (k, 1), stride=1, padding=(radius, 0))[:, 0] > 0
        out.append((((lab == 2) & near) | (lab == 3))[:, ::4, ::4])
    return torch.cat(out)


def normalize(x: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`vesselcad.segment.normalize_frames` for a batch ``(B, 1, H, W)``."""
    b, _, h, w = x.shape
    step = max(1, int(math.sqrt(h * w / 40_000)))
    sub = x[:, 0, ::step, ::step].reshape(b, -1)
    lo_v = sub.min(dim=1, keepdim=True).values
    hi_v = sub.max(dim=1, keepdim=True).values
    exposed = (sub > lo_v) & (sub < hi_v)
    use = torch.where(exposed.float().mean(dim=1, keepdim=True) >= 0.5, exposed, torch.ones_like(exposed))
    masked = torch.where(use, sub, torch.full_like(sub, float("nan")))
    q = torch.nanquantile(masked, torch.tensor([0.01, 0.99], device=x.device, dtype=x.dtype), dim=1)
    lo, hi = q[0], q[1]
    scale = torch.maximum(hi - lo, 1e-6 * torch.clamp(hi.abs(), min=1.0))
    out = (x - lo[:, None, None, None]) / scale[:, None, None, None] * 2.0 - 1.0
    return out.clamp(-2.0, 2.0)


def warp(x: torch.Tensor, target: torch.Tensor, centre: torch.Tensor, scale: torch.Tensor,
         angle: torch.Tensor, flip: torch.Tensor, crop: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Affine warps of images and targets into ``crop`` squares .

    The crop pixel ``u`` comes from the input pixel ``p`` with
    ``u = M p + crop/2 - M c``, ``M = s R(angle) diag(flip, 1)``, ``c`` the centre
    (x, y) in input pixels; bilinear for images, nearest for targets, borders
    reflected about the edge pixels (OpenCV's ``BORDER_REFLECT_101``).

    Parameters
    ----------
    x : tensor (B, 1, H, W) float
    target : tensor (B, H, W) integer
    centre : tensor (B, 2)
        (x, y) pixel of the input that lands in the crop's centre.
    scale, angle, flip : tensors (B,)
        Zoom factor, rotation (radians), and +1 / -1 for a mirror of x.
    """
    b, _, h, w = x.shape
    c, s = torch.cos(angle) * scale, torch.sin(angle) * scale
    m = torch.stack([torch.stack([c * flip, -s], -1), torch.stack([s * flip, c], -1)], -2)  # (B, 2, 2)
    minv = torch.linalg.inv(m)
    v = torch.arange(crop, device=x.device, dtype=x.dtype) - crop / 2
    uu, vv = torch.meshgrid(v, v, indexing="xy")  # uu: column offset, vv: row offset
    off = torch.stack([uu, vv], -1).reshape(-1, 2)  # (crop*crop, 2)
    p = centre[:, None, :] + off[None] @ minv.transpose(1, 2)  # input pixel (x, y)
    gx = p[..., 0] / max(w - 1, 1) * 2 - 1
    gy = p[..., 1] / max(h - 1, 1) * 2 - 1
    grid = torch.stack([gx, gy], -1).reshape(b, crop, crop, 2)
    xi = F.grid_sample(x, grid, mode="bilinear", padding_mode="reflection", align_corners=True)
    ti = F.grid_sample(target[:, None].float(), grid, mode="nearest", padding_mode="reflection",
                       align_corners=True)
    return xi, ti[:, 0].round().to(torch.int64)


def _gauss_blur(x: torch.Tensor, sigma: torch.Tensor, radius: int = 4) -> torch.Tensor:
    """Separable Gaussian blur with one sigma per sample (grouped convolution), reflected borders."""
    b = x.shape[0]
    k = torch.arange(-radius, radius + 1, device=x.device, dtype=x.dtype)
    ker = torch.exp(-0.5 * (k[None] / sigma[:, None].clamp(min=1e-3)) ** 2)
    ker = ker / ker.sum(1, keepdim=True)
    y = F.pad(x.transpose(0, 1), (radius, radius, radius, radius), mode="reflect")  # (1, B, H+, W+)
    y = F.conv2d(y, ker[:, None, None, :], groups=b)
    y = F.conv2d(y, ker[:, None, :, None], groups=b)
    return y.transpose(0, 1)


class BatchAugmenter:
    """Draws augmented training batches (phantom + real) on one torch device.

    Parameters
    ----------
    pool : Pool
        Phantom frames (all the same size) and labels.
    real_images, real_masks : lists of arrays
        Real images (uint8, all the same size) and vessel masks; may be empty.
    crop : int
        Side of the square crops.
    real_fraction : float
        Expected share of real images in a batch.
    device : torch.device
    seed : int
    augment : bool
        False: no photometric augmentation; crops are plain windows of the
        normalized frame at integer offsets (for checks).
    focus_fraction : float
        Share of the phantom crops centred on a focus pixel (:func:`focus_grid`)
        where the frame has one; 0 (default) draws as before.
    hard : np.ndarray, optional
        (N, ceil(H/4), ceil(W/4)) bool grid of the pool frames' *hard* cells
        (:mod:`.hard_focus`: where a trained model mislabels devices); with
        ``focus_fraction`` > 0 they join the focus pixels, each weighing
        ``hard_weight`` times a focus pixel when a focus centre is drawn.
    hard_weight : float
        Weight of a hard cell against a focus pixel (default 4).
    """

    def __init__(self, pool: Pool, real_images: list[np.ndarray], real_masks: list[np.ndarray], *,
                 crop: int = 256, real_fraction: float = 0.35, device: torch.device | str = "cpu",
                 seed: int = 0, augment: bool = True, focus_fraction: float = 0.0,
                 labelled_images: list[np.ndarray] | None = None,
                 labelled_targets: list[np.ndarray] | None = None, labelled_fraction: float = 0.0,
                 hard: np.ndarray | None = None, hard_weight: float = 4.0):
        dev = torch.device(device)
        if not 0.0 <= labelled_fraction <= 1.0:
            raise ValueError(f"labelled_fraction must lie in [0, 1], got {labelled_fraction}")
        if not 0.0 <= focus_fraction <= 1.0:
            raise ValueError(f"focus_fraction must lie in [0, 1], got {focus_fraction}")
        self.focus_fraction = float(focus_fraction)
        self.device, self.crop, self.augment = dev, int(crop), augment
        self.real_fraction = float(real_fraction)
        shapes = {f.shape for f in pool.frames}
        if len(shapes) != 1:
            raise ValueError(f"pool frames must share one shape, got {sorted(shapes)}")
        self.frames = torch.from_numpy(np.stack(pool.frames).astype(np.int16)).to(dev)
        self.labels = torch.from_numpy(np.stack(pool.labels).astype(np.uint8)).to(dev)
        self.focus = focus_grid(self.labels).float() if self.focus_fraction > 0 else None
        if hard is not None:
            if self.focus is None:
                raise ValueError("hard-focus cells need focus_fraction > 0")
            hard_t = torch.from_numpy(np.asarray(hard, bool)).to(dev)
            if hard_t.shape != self.focus.shape:
                raise ValueError(f"hard-focus grid {tuple(hard_t.shape)} does not fit the pool's "
                                 f"{tuple(self.focus.shape)}")
            if hard_weight < 0:
                raise ValueError(f"hard_weight must be >= 0, got {hard_weight}")
            self.focus = self.focus + float(hard_weight) * hard_t.float()
        self.inv_max = torch.tensor([1.0 / (2**b - 1) for b in pool.bits], device=dev)
        if real_images:
            self.real = torch.from_numpy(np.stack(real_images).astype(np.uint8)).to(dev)
            self.real_mask = torch.from_numpy(np.stack(real_masks).astype(bool)).to(dev)
        else:
            self.real = self.real_mask = None
        if labelled_images:
            self.lab_real = torch.from_numpy(np.stack(labelled_images).astype(np.uint8)).to(dev)
            self.lab_target = torch.from_numpy(np.stack(labelled_targets).astype(np.uint8)).to(dev)
            self.labelled_fraction = float(labelled_fraction)
        else:
            self.lab_real = self.lab_target = None
            self.labelled_fraction = 0.0
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(int(seed))

    # random helpers (all on the device, from one generator)
    def _u(self, n: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return torch.rand(n, device=self.device, generator=self.gen) * (hi - lo) + lo

    def _bern(self, n: int, p: float) -> torch.Tensor:
        return (self._u(n) < p).float()

    def _photometric(self, x: torch.Tensor, lab: torch.Tensor | None) -> torch.Tensor:
        """``x`` (B, 1, H, W) transmitted intensity in ~[0, 1]; ``lab`` phantom labels or None."""
        b, _, h, w = x.shape
        col = lambda t: t[:, None, None, None]  # noqa: E731
        if lab is not None:
            # more iodine in the vessels; catheter filled with more or less contrast
            sig = torch.full((b,), 0.8, device=x.device)
            v = _gauss_blur((lab == 1).float()[:, None], sig)
            cth = _gauss_blur((lab == 2).float()[:, None], sig)
            a_v = self._u(b, 0.0, 0.45) * self._bern(b, 0.6)
            a_c = self._u(b, -0.35, 0.35) * self._bern(b, 0.5)
            x = x * (1.0 - col(a_v) * v) * (1.0 - col(a_c) * cth)
        gy = torch.linspace(-0.5, 0.5, h, device=x.device)[:, None]
        gx = torch.linspace(-0.5, 0.5, w, device=x.device)[None, :]
        a = torch.randn(b, 3, device=x.device, generator=self.gen) * 0.25 * self._bern(b, 0.5)[:, None]
        x = x * torch.exp(col(a[:, 0]) * gx + col(a[:, 1]) * gy + col(a[:, 2]) * gx**2)
        x = x.clamp(min=1e-4) ** col(self._u(b, 0.6, 1.6))
        blur = self._bern(b, 0.4)
        if blur.any():
            xb = _gauss_blur(x, self._u(b, 0.3, 1.3))
            x = torch.where(col(blur) > 0, xb, x)
        s_n = self._u(b, 0.005, 0.04) * self._bern(b, 0.6)
        x = x + torch.randn(x.shape, device=x.device, generator=self.gen) * col(s_n) * x.clamp(min=0).sqrt()
        # image-intensifier circle (25%) or shutter blades (20%); masks broadcast to (B, 1, H, W)
        u = self._u(b)
        yy = torch.arange(h, device=x.device, dtype=x.dtype)[:, None]
        xx = torch.arange(w, device=x.device, dtype=x.dtype)[None, :]
        cy, cx = col(self._u(b, 0.45, 0.55) * h), col(self._u(b, 0.45, 0.55) * w)
        r = col(self._u(b, 0.5, 0.72) * min(h, w))
        outside = ((yy - cy) ** 2 + (xx - cx) ** 2 > r * r) & col(u < 0.25)
        x = torch.where(outside, col(self._u(b, 0.0, 0.03)), x)
        shut = (u >= 0.25) & (u < 0.45)
        for side in range(4):
            on = col(shut & (self._u(b) < 0.5))
            t = col((self._u(b, 0.01, 0.12) * (h if side < 2 else w)).floor())
            val = torch.where(self._u(b) < 0.7, self._u(b, 0.0, 0.05), self._u(b, 0.8, 1.0))
            m = [yy < t, yy >= h - t, xx < t, xx >= w - t][side] & on
            x = torch.where(m, col(val), x)
        return x

    def _crops(self, x: torch.Tensor, target: torch.Tensor,
               focus: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        b, _, h, w = x.shape
        if self.augment:
            scale = torch.exp(self._u(b, math.log(0.55), math.log(1.9)))
            angle = self._u(b, 0.0, 2 * math.pi)
            flip = torch.where(self._u(b) < 0.5, -1.0, 1.0)
        else:
            scale, angle, flip = torch.ones(b, device=x.device), torch.zeros(b, device=x.device), \
                torch.ones(b, device=x.device)
        centre = torch.stack([self._u(b, 0, w), self._u(b, 0, h)], -1)
        # centre 75% of the crops on a foreground pixel (any class 1..4, on a 4-pixel grid)
        t4 = target[:, ::4, ::4]
        cols = t4.shape[2]
        fg_w = ((t4 >= 1) & (t4 <= 4)).reshape(b, -1).float()
        use_f = torch.zeros(b, dtype=torch.bool, device=x.device)
        if focus is not None and self.augment:
            f_w = focus.reshape(b, -1).float()
            use_f = (f_w.sum(1) > 0) & (self._u(b) < self.focus_fraction)
            fg_w = torch.where(use_f[:, None], f_w, fg_w)
        has = fg_w.sum(1) > 0
        if has.any():
            k = torch.multinomial(fg_w + (~has[:, None]).float(), 1, generator=self.gen)[:, 0]
            fg_xy = torch.stack([(k % cols) * 4, torch.div(k, cols, rounding_mode="floor") * 4], -1).float()
            jitter = torch.randn(b, 2, device=x.device, generator=self.gen)
            jitter = jitter * (0.1 * self.crop / scale)[:, None]
            use = (has & ((self._u(b) < 0.75) | use_f))[:, None]
            centre = torch.where(use, fg_xy + jitter, centre)
        if not self.augment:  # plain windows of the frame: integer offsets, inside it where it fits
            half = self.crop / 2
            lim = torch.tensor([max(w - half, half), max(h - half, half)], device=x.device)
            centre = torch.minimum(torch.clamp(centre.round(), min=half), lim)
        return warp(x, target, centre, scale, angle, flip, self.crop)

    def batch(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` augmented crops: images (n, 1, crop, crop) float32, targets (n, crop, crop) int64."""
        has_real = self.real is not None or self.lab_real is not None
        n_real = int((self._u(n) < self.real_fraction).sum()) if has_real else 0
        n_lab = int((self._u(n_real) < self.labelled_fraction).sum()) if self.lab_real is not None else 0
        if self.real is None:
            n_lab = n_real
        xs, ts = [], []
        n_ph = n - n_real
        n_real -= n_lab
        if n_ph:
            k = torch.randint(len(self.frames), (n_ph,), device=self.device, generator=self.gen)
            lab = self.labels[k].long()
            x = self.frames[k].float()[:, None] * self.inv_max[k][:, None, None, None]
            if self.augment:
                x = self._photometric(x, lab)
            xi, ti = self._crops(normalize(x), lab, None if self.focus is None else self.focus[k])
            xs.append(xi)
            ts.append(ti)
        if n_real:  # vessel masks: vessel / not vessel
            self._real_crops(self.real, lambda k: torch.where(self.real_mask[k], 1, NOT_VESSEL),
                             n_real, xs, ts)
        if n_lab:  # partial full-class targets (catheters drawn by hand, IGNORE elsewhere)
            self._real_crops(self.lab_real, lambda k: self.lab_target[k], n_lab, xs, ts)
        return torch.cat(xs), torch.cat(ts)

    def _real_crops(self, images: torch.Tensor, targets, n: int, xs: list, ts: list) -> None:
        """Append ``n`` augmented crops of randomly drawn real 8-bit ``images`` (targets: ``targets(k)``)."""
        k = torch.randint(len(images), (n,), device=self.device, generator=self.gen)
        x = images[k].float()[:, None] / 255.0
        if self.augment:
            x = self._photometric(x, None)
        xi, ti = self._crops(normalize(x), targets(k).long())
        xs.append(xi)
        ts.append(ti)
