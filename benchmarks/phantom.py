"""Phantom benchmark: generation time, realism against real angiograms, ground-truth coverage.

Usage::

    python benchmarks/phantom.py [--cases 6] [--frames 60] [--real ../shared/data/xca-real]

Prints three markdown tables:

1. time to generate a 2 x N-frame 512x512 case (goal: <= 10 s on 2 cores for N = 60);
2. image statistics of phantom frames next to the real CIMAT (300x300, with
   manual masks) and ARCADE (512x512, unlabelled) angiograms;
3. how well the ground truth agrees with the label masks (share of projected
   3D centreline samples on vessel pixels, share hidden behind devices, key
   points on the stationary object).
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from skimage.morphology import skeletonize

import vesselcad as vc
from vesselcad.phantom import LABELS, generate_case


def image_stats(img: np.ndarray, vessel: np.ndarray | None) -> dict[str, float]:
    """Background mean/std, vessel contrast, high-pass noise, vessel width (px)."""
    im = img.astype(np.float64)
    if im.max() > 255:
        im = im * 255.0 / im.max()
    hp = im - cv2.GaussianBlur(im, (0, 0), 1.5)
    out = {"mean": im.mean(), "std": im.std(), "noise": hp.std()}
    if vessel is not None and vessel.any():
        out.update(
            bg_mean=im[~vessel].mean(), bg_std=im[~vessel].std(),
            contrast=np.median(im[~vessel]) - np.median(im[vessel]),
            noise=hp[~vessel].std(),
        )
        dist = cv2.distanceTransform(vessel.astype(np.uint8), cv2.DIST_L2, 5)
        out["width_px"] = float(np.median(2 * dist[skeletonize(vessel)]))
    return out


def fmt(values: list[float], nd: int = 1) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.{nd}f} ± {v.std():.{nd}f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="cases (anatomies cycle lca, rca, cs)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--real", default=str(Path(__file__).resolve().parents[2] / "shared/data/xca-real"))
    args = ap.parse_args()

    kinds = ["lca", "rca", "cs"]
    timing, phantom_stats = [], []
    cov_rows = []
    for k in range(args.cases):
        kind = kinds[k % 3]
        t0 = time.perf_counter()
        case = generate_case(100 + k, kind, n_frames=args.frames)
        dt = time.perf_counter() - t0
        timing.append((kind, 100 + k, len(case.anatomy.vessels), dt))
        truth = case.truth()
        for tag in ("a", "b"):
            rr = getattr(case, f"run_{tag}")
            view = vc.CArmView.from_dict(truth[f"view_{tag}"])
            vessel_px = (rr.labels == LABELS["vessel"]).sum(axis=(1, 2))
            i = int(np.argmax(vessel_px))
            phantom_stats.append(image_stats(rr.frames[i], rr.labels[i] == LABELS["vessel"]))
            pts = np.concatenate([np.asarray(b["points"]) for b in truth[f"trees_{tag}"][i]["branches"]])
            ij = np.round(view.project(pts)).astype(int)
            ok = (ij[:, 0] >= 0) & (ij[:, 0] < view.cols) & (ij[:, 1] >= 0) & (ij[:, 1] < view.rows)
            lab = rr.labels[i][ij[ok, 1], ij[ok, 0]]
            hidden = lab >= LABELS["catheter"]
            kp = np.round(rr.keypoints).astype(int)
            want = LABELS["balloon"] if kind == "cs" else LABELS["catheter"]
            kp_ok = rr.labels[np.arange(len(kp)), kp[:, 1], kp[:, 0]] == want
            cov_rows.append((kind, (lab[~hidden] == LABELS["vessel"]).mean(), hidden.mean(), ok.mean(),
                             kp_ok.mean()))

    real = Path(args.real)
    cimat, arcade = [], []
    for gt in sorted(glob.glob(str(real / "train" / "*_gt.png"))):
        img = cv2.imread(gt.replace("_gt", ""), cv2.IMREAD_GRAYSCALE)
        cimat.append(image_stats(img, cv2.imread(gt, cv2.IMREAD_GRAYSCALE) > 127))
    for f in sorted(glob.glob(str(real / "unlabelled" / "*.png"))):
        arcade.append(image_stats(cv2.imread(f, cv2.IMREAD_GRAYSCALE), None))

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, numpy {np.__version__}")
    print()
    print(f"### Generation time, 2 x {args.frames} frames, 512x512, 8-bit (goal <= 10 s)\n")
    print("| anatomy | seed | branches | seconds |")
    print("|---|---|---|---|")
    for kind, seed, nb, dt in timing:
        print(f"| {kind} | {seed} | {nb} | {dt:.2f} |")
    times = [t[3] for t in timing]
    print(f"| **all** | | | **{np.mean(times):.2f} mean, {np.max(times):.2f} max** |")
    print()
    print("### Image statistics: phantom (fullest-opacified frame of each run) vs real angiograms\n")
    print("| source | n | background mean | background std | vessel contrast | hp noise | vessel width px |")
    print("|---|---|---|---|---|---|---|")

    def row(name, stats, masked):
        if not stats:
            return
        g = lambda key: fmt([s[key] for s in stats]) if key in stats[0] else "–"  # noqa: E731
        if masked:
            print(f"| {name} | {len(stats)} | {g('bg_mean')} | {g('bg_std')} | {g('contrast')} | "
                  f"{fmt([s['noise'] for s in stats], 2)} | {g('width_px')} |")
        else:
            print(f"| {name} | {len(stats)} | {g('mean')} (whole image) | {g('std')} (whole image) | – | "
                  f"{fmt([s['noise'] for s in stats], 2)} | – |")

    row("phantom 512² (labels)", phantom_stats, True)
    row("real CIMAT 300² (manual masks)", cimat, True)
    row("real ARCADE 512² (no masks)", arcade, False)
    print()
    print("### Ground truth vs label masks (fullest-opacified frame; key points: all frames)\n")
    print("| anatomy | runs | centreline samples on vessel pixels (not under a device) | "
          "samples under a device | samples in field | key points on object |")
    print("|---|---|---|---|---|---|")
    for kind in kinds:
        rows = [r for r in cov_rows if r[0] == kind]
        if rows:
            a = np.asarray([r[1:] for r in rows])
            print(f"| {kind} | {len(rows)} | {a[:, 0].mean():.4f} (min {a[:, 0].min():.4f}) | "
                  f"{a[:, 1].mean():.3f} (max {a[:, 1].max():.3f}) | {a[:, 2].mean():.3f} | "
                  f"{a[:, 3].mean():.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
