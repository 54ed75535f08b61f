"""Benchmark: the whole pipeline (``vc.reconstruct`` + outputs) on phantom cases against their truth.

Each case: a phantom (anatomies rotating lca / rca / cs, the anatomy's default
paper-like view pair, unsynchronized runs of 40-60 frames, 512x512) written as
two DICOM files, read back and reconstructed, with all outputs written
(STEP, STL, GLB, centrelines, report.json, report.html). Variants:

- ``truth``: the phantom's label masks in place of segmentation (isolates the
  geometric stages);
- ``truth+1.5deg``: the same with up to 1.5 degrees of angle error written
  into the DICOM headers (the truth stays in the true frame);
- ``model``: the bundled ONNX segmentation model on every frame (the product);
- any of these with ``/vessels``: phase matching without a stationary object
  (``objects="vessels"``: the vessels' epipolar consistency alone, as on a real
  run whose catheter tip is not found).

``--fps`` and ``--frames`` set the runs' frame rate (default 15) and length
(default 40-60 frames, varying from case to case): real runs are acquired at
7.5-30 frames/s and hold 15-60 frames, so a run may cover two heartbeats or
ten, and fewer cardiac phases to choose the pair from.

``--synchronized`` generates both runs at identical cardiac and respiratory
phases (a true biplane pair instead of two runs a minute apart): the frame
pairs are then exactly in phase, and the difference to the default run is
what motion between the chosen frames costs, the most that better phase
matching or motion compensation could gain.

Metrics (ARCHITECTURE.md): 3D centreline error (reconstructed samples every
0.5 mm to the true centreline of run A's tree at the chosen frame; mean and
p95), reprojection error (mean over both views, px and mm), coverage (share
of the true tree's length within 1 mm of the reconstruction), visible (share
of the true tree's length that the label masks of both chosen frames show: the
most any reconstruction from them can cover), ostium (the
two views' matched roots, triangulated, to the true ostium: median, and
cases within 3 mm), valid and watertight solid, the STL as written (watertight
by trimesh's test, its volume over the solid's), the B-rep's volume against an
independent reference of the same tubes (``benchmarks/solids.py``: the kept
branches' spines and radius laws meshed analytically and united with
manifold3d; a valid B-rep whose walls touch can hold more or less than
its tubes: cs 2111 with true labels held 3.6 % more), wall time per case and per
stage; and issue 13's check on real runs done with the phantom's masks: the
tree reprojected into the chosen frames against their vessel masks
(``vc.mask_reprojection``: distance to the masks' centrelines in mm at the
isocentre, share of the samples on vessel pixels), which the model variant
never saw. Where the error and the missing length lie
(``vesselcad.phantom.compare.error_anatomy``): the share of the samples on
branches whose median error exceeds 3 mm (wrong pairings, as a rule), their
share of the summed error and the mean without them; the share of the true
length farther than 5 mm from every reconstructed branch (missed, not merely
inaccurate), split into runs at the vessels' distal ends, gaps inside them,
runs at their starts and whole vessels.

Run ``python benchmarks/end_to_end.py --cases 12`` (``--json FILE`` for raw numbers,
``--variants truth,model`` to choose, ``--model FILE|int8`` for the model variant's network).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import vesselcad as vc
from vesselcad.phantom import generate_case, write_case
from vesselcad.phantom.compare import compare_with_truth, error_anatomy
from vesselcad.pipeline import reconstruct

KINDS = ("lca", "rca", "cs")
STAGES = ("segmentation", "phase", "graphs", "refinement", "matching", "centrelines_3d", "solid", "write")


def run_case(seed: int, kind: str, n_frames: int, variant: str, workdir: Path,
             segmenter: vc.Segmenter | None = None, tta: str = "chosen",
             frame_search: str = "all", synchronized: bool = False, fps: float = 15.0,
             size: int = 512, noise_draw: int = 0) -> dict:
    base, _, option = variant.partition("/")
    mis = 1.5 if base.endswith("1.5deg") else 0.0
    case = generate_case(seed, kind, n_frames, miscalibration_deg=mis, synchronized=synchronized, fps=fps,
                         rows=size, cols=size, noise_draw=noise_draw)
    d = workdir / f"{seed}_{variant.replace('/', '_')}"
    paths = write_case(case, d)
    labels = None if base == "model" else (case.run_a.labels, case.run_b.labels)
    objects = "vessels" if option == "vessels" else "auto"
    t0 = time.perf_counter()
    row = {"seed": seed, "anatomy": kind, "frames": n_frames, "fps": fps, "size": size,
           "noise_draw": noise_draw, "variant": variant}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec = reconstruct(paths["run_a"], paths["run_b"], labels=labels, model=segmenter, tta=tta,
                              frame_search=frame_search,
                              objects=objects)
            rec.write(d / "out")
    except vc.VesselcadError as exc:
        row.update(status=f"failed: {exc}", seconds=time.perf_counter() - t0)
        return row
    row["seconds"] = time.perf_counter() - t0
    row["timings"] = dict(rec.timings)
    row["truth"] = compare_with_truth(rec, case)
    row["error_anatomy"] = error_anatomy(rec, case)
    row["reprojection"] = dict(rec.errors)
    row["branches"] = [len(rec.ok_branches), len(rec.branches)]
    # issue 13's check on real runs: the tree reprojected into the chosen frames against vessel
    # masks the reconstruction never saw (here the phantom's own, vessel and balloon pixels)
    fa, fb = rec.phase.frame_a, rec.phase.frame_b
    if rec.tree is not None:
        row["mask_reprojection"] = vc.mask_reprojection(
            rec, rec.views, [np.isin(case.run_a.labels[fa], (1, 3)), np.isin(case.run_b.labels[fb], (1, 3))]
        ).to_dict()
    chk = rec.solid.check() if rec.solid is not None else {}
    row["solid_ok"] = bool(chk.get("valid") and chk.get("watertight"))
    # the STL as a user gets it (trimesh reads it and merges its vertices): closed and manifold
    # (every edge in two triangles), and its volume against the B-rep's
    stl = d / "out" / "tree.stl"
    if rec.solid is not None and stl.exists():
        import trimesh

        mesh = trimesh.load(stl)
        row["stl"] = {"watertight": bool(mesh.is_watertight),
                      "volume_ratio": float(mesh.volume / rec.solid.volume)}
    if rec.solid is not None:
        # the B-rep's volume against the union of the tubes it was swept from (not timed)
        from solids import reference_volume, solid_tubes

        row["volume_vs_tubes"] = float(rec.solid.volume / reference_volume(solid_tubes(rec.solid)) - 1.0)
    row["solid_pipes"] = 0 if rec.solid is None else len(rec.solid.branch_ids)
    row["in_solid"] = rec.solid_share or 0.0  # share of the tree's centreline length the solid holds
    row["refined"] = bool(rec.refinement is not None and rec.refinement.applied)
    # frames the model labelled for the phase matching (all of them without the coarse search)
    n_all = rec.phase.fill_a.size + rec.phase.fill_b.size
    row["labelled_share"] = (1.0 if rec.phase.labelled_a is None
                             else float(rec.phase.labelled_a.sum() + rec.phase.labelled_b.sum()) / n_all)
    row["status"] = "ok"
    return row


def table(rows: list[dict]) -> str:
    out = ["| variant | cases | 3D mean mm | 3D p95 mm | reproj px | reproj mm | coverage | visible "
           "| ostium mm | solid valid+watertight | tree in solid | refined | s/case (mean, max) | "
           + " | ".join(STAGES) + " |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(STAGES)]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == variant]
        ok = [r for r in rs if r["status"] == "ok"]
        if not ok:
            out.append(f"| {variant} | {len(rs)} | failed |")
            continue
        mean3 = np.nanmean([r["truth"]["mean_mm"] for r in ok])
        p953 = np.nanmean([r["truth"]["p95_mm"] for r in ok])
        rpx = np.mean([r["reprojection"].get("mean_px", np.nan) for r in ok])
        rmm = np.mean([r["reprojection"].get("mean_mm", np.nan) for r in ok])
        cov = np.mean([r["truth"]["coverage"] for r in ok])
        vis = np.mean([r["truth"].get("visible", np.nan) for r in ok])
        ost = np.array([r["truth"].get("ostium_mm", np.nan) for r in ok], float)
        ost_s = (f"{np.nanmedian(ost):.2f} ({np.sum(ost <= 3.0)}/{len(ok)} ≤ 3)" if np.isfinite(ost).any()
                 else "-")
        solid = sum(r["solid_ok"] for r in ok)
        held = np.mean([r.get("in_solid", np.nan) for r in ok])
        ref = sum(r["refined"] for r in ok)
        secs = [r["seconds"] for r in rs]
        st = " | ".join(f"{np.mean([r['timings'].get(s, 0.0) for r in ok]):.2f}" for s in STAGES)
        out.append(f"| {variant} | {len(rs)} ({len(rs) - len(ok)} failed) | {mean3:.3f} | {p953:.3f} | "
                   f"{rpx:.3f} | {rmm:.3f} | {cov:.1%} | {vis:.1%} | {ost_s} | {solid}/{len(rs)} "
                   f"| {held:.0%} | {ref}/{len(ok)} | "
                   f"{np.mean(secs):.1f}, "
                   f"{np.max(secs):.1f} | {st} |")
    return "\n".join(out)


def mask_table(rows: list[dict]) -> str:
    out = ["| variant | cases | mean mm (mean of cases) | max mm (mean of cases) | on vessel | "
           "cases ≤ 0.62 mm and ≥ 95% on vessel |", "|---|---|---|---|---|---|"]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        ms = [r["mask_reprojection"] for r in rows if r["variant"] == variant and "mask_reprojection" in r]
        if not ms:
            continue
        good = sum(m["mean_mm"] <= 0.62 and m["on_vessel"] >= 0.95 for m in ms)
        mean, top = np.mean([m["mean_mm"] for m in ms]), np.mean([m["max_mm"] for m in ms])
        on = np.mean([m["on_vessel"] for m in ms])
        out.append(f"| {variant} | {len(ms)} | {mean:.3f} | {top:.2f} | {on:.1%} | {good}/{len(ms)} |")
    return "\n".join(out)


def stl_table(rows: list[dict]) -> str:
    """The STL files as written: watertight by trimesh's test, volume against the solid's."""
    out = ["| variant | cases with an STL | STL watertight (trimesh) | STL volume / solid's (min, median) "
           "| B-rep volume vs its tubes' union (largest error; cases beyond 1 %) |",
           "|---|---|---|---|---|"]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        ss = [r["stl"] for r in rows if r["variant"] == variant and "stl" in r]
        if not ss:
            continue
        ratio = [x["volume_ratio"] for x in ss]
        tubes = np.array([r["volume_vs_tubes"] for r in rows
                          if r["variant"] == variant and "volume_vs_tubes" in r])
        worst = "–"
        if len(tubes):
            worst = f"{100 * tubes[np.argmax(np.abs(tubes))]:+.2f} %; {int((np.abs(tubes) > 0.01).sum())}"
        out.append(f"| {variant} | {len(ss)} | {sum(x['watertight'] for x in ss)}/{len(ss)} | "
                   f"{np.min(ratio):.4f}, {np.median(ratio):.4f} | {worst} |")
    return "\n".join(out)


def anatomy_table(rows: list[dict]) -> str:
    """Where the 3D error and the missing length lie (means over the cases)."""
    keys = ("off_samples", "off_error", "mean_mm_without_off", "missed", "missed_distal", "missed_inside",
            "missed_proximal", "missed_whole")
    out = ["| variant | samples on branches > 3 mm off | their share of the error | 3D mean without them "
           "| truth > 5 mm from the tree | at vessels' distal ends | gaps inside | at vessels' starts "
           "| whole vessels |", "|---|---|---|---|---|---|---|---|---|"]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        es = [r["error_anatomy"] for r in rows if r["variant"] == variant and "error_anatomy" in r]
        if not es:
            continue
        m = {k: np.nanmean([e[k] for e in es]) for k in keys}
        out.append(f"| {variant} | {m['off_samples']:.1%} | {m['off_error']:.1%} | "
                   f"{m['mean_mm_without_off']:.3f} | " + " | ".join(f"{m[k]:.1%}" for k in keys[3:]) + " |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=12)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--variants", default="truth,truth+1.5deg,model")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--model", metavar="ONNX", help="segmentation model of the 'model' variant: a file, "
                    "'fp32' or 'int8' (default: Segmenter()'s, the bundled int8 model on the CPU)")
    ap.add_argument("--frame-search", choices=["all", "coarse"], default="all",
                    help="model variant: frames labelled for the phase matching, all (default) or coarse "
                    "to fine (reconstruct(frame_search=...))")
    ap.add_argument("--tta", choices=["chosen", "all", "none"], default="chosen",
                    help="model variant: mirror test-time augmentation of the chosen frames (default), of "
                    "every frame, or none (reconstruct(tta=...))")
    ap.add_argument("--synchronized", action="store_true",
                    help="both runs at identical cardiac and respiratory phases (a true biplane pair): "
                    "what motion between the chosen frames costs")
    ap.add_argument("--fps", type=float, default=15.0,
                    help="frame rate of both runs (default 15; real runs are acquired at 7.5-30)")
    ap.add_argument("--frames", type=int, metavar="N",
                    help="frames per run (default: 40-60, varying from case to case; real runs hold 15-60)")
    ap.add_argument("--size", type=int, default=512, metavar="PX",
                    help="rows and columns of the rendered runs (default 512; the same 140 mm field at "
                    "the isocentre in finer pixels for more, as 1024² exports; reconstruct reduces "
                    "frames larger than its max_side, 512)")
    ap.add_argument("--noise-draw", type=int, default=0, metavar="K",
                    help="the phantom's K-th draw of its quantum noise (default 0): the same cases with "
                    "other noise pixels; with the model's labels half the cases move by over 1 mm between "
                    "draws (docs/results.md, 2026-12-06)")
    args = ap.parse_args()
    if not args.fps > 0:
        ap.error(f"--fps: expected a positive frame rate, got {args.fps}")
    if args.noise_draw < 0:
        ap.error(f"--noise-draw: expected an integer >= 0, got {args.noise_draw}")
    if args.size < 128:
        ap.error(f"--size: expected at least 128 px, got {args.size}")
    if args.frames is not None and args.frames < 2:
        ap.error(f"--frames: expected at least 2 frames per run, got {args.frames}")
    variants = args.variants.split(",")
    bad = [v for v in variants if v.partition("/")[0] not in ("truth", "truth+1.5deg", "model")
           or v.partition("/")[2] not in ("", "vessels")]
    if bad:
        ap.error(f"--variants: unknown {bad}; expected truth, truth+1.5deg, model, each optionally /vessels")
    segmenter = vc.Segmenter(args.model) if any(v.startswith("model") for v in variants) else None
    rows = []
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.cases):
            seed, kind = args.first_seed + i, KINDS[i % 3]
            n_frames = 40 + (i * 7) % 21 if args.frames is None else args.frames
            for v in variants:
                r = run_case(seed, kind, n_frames, v, Path(tmp), segmenter, tta=args.tta,
                             frame_search=args.frame_search, synchronized=args.synchronized, fps=args.fps,
                             size=args.size, noise_draw=args.noise_draw)
                rows.append(r)
                t = r.get("truth", {})
                print(f"seed {seed} {kind} {n_frames} frames {v}: {r['status'][:80]}; 3D mean "
                      f"{t.get('mean_mm', float('nan')):.3f} mm, coverage {t.get('coverage', 0):.1%}, "
                      f"ostium {t.get('ostium_mm', float('nan')):.2f} mm, "
                      f"{r['seconds']:.1f} s", file=sys.stderr, flush=True)
    sync = "synchronized" if args.synchronized else "unsynchronized"
    frames = "40-60" if args.frames is None else str(args.frames)
    print(f"# end to end: {args.cases} phantom cases x {len(variants)} variants, {args.size}², "
          f"noise draw {args.noise_draw}, {sync} "
          f"{frames} frames at {args.fps:g} fps, model variant with mirror TTA of {args.tta} frames, "
          f"frame search {args.frame_search}")
    print(f"# {platform.platform()}, python {platform.python_version()}, {os.cpu_count()} CPUs, "
          f"{time.time() - t0:.0f} s total\n")
    print(table(rows))
    print("\nThe tree reprojected into the chosen frames against the phantom's vessel masks (vessel and "
          "balloon pixels; independent of the model's labels): issue 13's check on real runs, goal mean "
          "≤ 0.62 mm with ≥ 95% of the reprojected centreline on vessel:\n")
    print(mask_table(rows))
    print("\nThe STL as written (tree.stl read by trimesh, its vertices merged):\n")
    print(stl_table(rows))
    shares = [r["labelled_share"] for r in rows
              if r.get("status") == "ok" and r["variant"].startswith("model")]
    if shares:
        print(f"\nFrames the model labelled for the phase matching (model variants): {np.mean(shares):.1%} "
              f"(min {min(shares):.1%}, max {max(shares):.1%})")
    print("\nWhere the error and the missing length lie (vesselcad.phantom.compare.error_anatomy; shares of "
          "the reconstructed samples, of their summed error and of the true length, means of the cases):\n")
    print(anatomy_table(rows))
    print("\nPer anatomy (3D mean mm / coverage):\n")
    print("| variant | " + " | ".join(KINDS) + " |\n|---|" + "---|" * len(KINDS))
    for v in variants:
        cells = []
        for k in KINDS:
            ok = [r for r in rows if r["variant"] == v and r["anatomy"] == k and r["status"] == "ok"]
            cells.append(f"{np.nanmean([r['truth']['mean_mm'] for r in ok]):.3f} / "
                         f"{np.mean([r['truth']['coverage'] for r in ok]):.1%}" if ok else "-")
        print(f"| {v} | " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
