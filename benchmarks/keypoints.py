"""Benchmark: catheter-tip key points (motion phase matching) from the model's labels against the truth.

Usage::

    python benchmarks/keypoints.py [--first-seed 200] [--cases 63] [--frames 8] [--model int8]

For each coronary phantom case (anatomies cycle cs, lca, rca as in
``benchmarks/phase.py``; the coronary sinus cases, whose key point is the
balloon, are skipped) every second frame of both runs is segmented and
``vesselcad.phase.find_keypoints(labels, "catheter", frames=...)`` is compared
with the phantom's true tip: mean and median distance (px), the share within
5 and 20 px, the share of frames with a tip, per anatomy and view, and the
same on the phantom's true labels (the detector's own floor). Per frame rows
with ``--per-frame``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

import vesselcad as vc
from vesselcad.phantom import generate_case
from vesselcad.phase import find_keypoints

KINDS = ("cs", "lca", "rca")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first-seed", type=int, default=200)
    ap.add_argument("--cases", type=int, default=63)
    ap.add_argument("--frames", type=int, default=8, help="frames per run (every second one is used)")
    ap.add_argument("--model", default="int8", help="segmentation model: an .onnx file, 'fp32' or 'int8'")
    ap.add_argument("--per-frame", action="store_true")
    args = ap.parse_args()
    seg = vc.Segmenter(args.model)
    rows = []  # (kind, view, source, error per frame)
    t0 = time.time()
    for k in range(args.cases):
        kind = KINDS[k % 3]
        if kind == "cs":
            continue
        seed = args.first_seed + k
        case = generate_case(seed, kind, n_frames=args.frames)
        for view, run, truth in zip("AB", case.xa_runs(), (case.run_a, case.run_b), strict=True):
            frames = run.frames[::2]
            for source, labels in (("model", seg(frames)), ("truth", truth.labels[::2])):
                tips = find_keypoints(labels, "catheter", frames=frames).points_px
                err = np.linalg.norm(tips - truth.keypoints[::2], axis=1)
                rows.append((kind, view, source, err))
                if args.per_frame:
                    print(seed, kind, view, source, np.round(err, 1), file=sys.stderr, flush=True)
    print(f"# catheter tips: seeds {args.first_seed}-{args.first_seed + args.cases - 1} (lca, rca), "
          f"frames 0, 2, ... of {args.frames}-frame runs, model {args.model}; {platform.platform()}, "
          f"python {platform.python_version()}, {os.cpu_count()} CPUs, {time.time() - t0:.0f} s\n")
    print("| labels | anatomy | view | frames | mean px | median px | ≤ 5 px | ≤ 20 px | found |")
    print("|---|---|---|---|---|---|---|---|---|")
    for source in ("model", "truth"):
        groups = [(kd, v) for kd in ("lca", "rca") for v in "AB"] + [("all", "")]
        for kd, v in groups:
            sel = [r[3] for r in rows if r[2] == source and (kd == "all" or (r[0] == kd and r[1] == v))]
            if not sel:
                continue
            e = np.concatenate(sel)
            fin = e[np.isfinite(e)]
            mean = f"{fin.mean():.1f}" if fin.size else "-"
            med = f"{np.median(fin):.1f}" if fin.size else "-"
            name = f"**{kd}**" if kd == "all" else kd
            print(f"| {source} | {name} | {v} | {e.size} | {mean} | {med} | {np.mean(e <= 5):.1%} | "
                  f"{np.mean(e <= 20):.1%} | {np.isfinite(e).mean():.1%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
