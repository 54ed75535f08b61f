"""Contact sheet of a phantom case: frames of both runs with label overlays."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import atomic_path

__all__ = ["contact_sheet", "overlay"]

# RGB of vessel, catheter, balloon, lead (labels 1..4).
_COLOURS = np.array([[0, 0, 0], [230, 40, 40], [40, 200, 60], [250, 200, 0], [60, 140, 255]], np.uint8)


def overlay(frame: np.ndarray, labels: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """RGB image of a grey frame with label colours blended in."""
    f = frame.astype(np.float32)
    f = 255.0 * (f - f.min()) / max(float(np.ptp(f)), 1.0)
    rgb = np.repeat(f[..., None], 3, axis=2)
    m = labels > 0
    rgb[m] = (1 - alpha) * rgb[m] + alpha * _COLOURS[labels[m]]
    return rgb.astype(np.uint8)


def contact_sheet(case: Any, path: str | os.PathLike, n_columns: int = 4) -> Path:
    """Write a PNG: for each run, frames (top) and the same frames with labels (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = (("A", case.run_a), ("B", case.run_b))
    n = case.run_a.frames.shape[0]
    idx = np.unique(np.linspace(0, n - 1, n_columns).round().astype(int))
    fig, axes = plt.subplots(4, len(idx), figsize=(2.6 * len(idx), 10.8), squeeze=False)
    for r, (name, rr) in enumerate(runs):
        v = rr.view
        for c, i in enumerate(idx):
            ax = axes[2 * r, c]
            ax.imshow(rr.frames[i], cmap="gray")
            ax.set_title(f"run {name} frame {i}\n{v.primary_deg:+.0f}/{v.secondary_deg:+.0f} deg", fontsize=8)
            ax = axes[2 * r + 1, c]
            ax.imshow(overlay(rr.frames[i], rr.labels[i]))
            kp = rr.keypoints[i]
            ax.plot(kp[0], kp[1], "+", color="cyan", ms=8, mew=1.2)
            ax.set_title("labels + key point", fontsize=8)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.suptitle(f"phantom {case.anatomy_kind} seed {case.seed}: red vessel, green catheter, "
                 "yellow balloon, blue lead, cyan + key point", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return Path(path)
