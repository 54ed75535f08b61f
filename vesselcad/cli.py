"""The ``vesselcad`` command line. It only parses arguments and calls the Python API.

Exit codes: 0 success; 2 bad input or arguments (a VesselcadError, message on stderr);
3 the runs were read but gave no tree (the message names the stage; report pictures
are written where possible); 4 ``batch``: some cases failed (the others are done).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import VesselcadError

__all__ = ["main"]


def _cmd_phantom(args: argparse.Namespace) -> int:
    from .phantom import generate_case, write_case

    t0 = time.perf_counter()
    case = generate_case(
        args.seed, args.anatomy, args.frames, synchronized=args.synchronized,
        rows=args.size, cols=args.size, bits=args.bits,
        miscalibration_deg=args.miscalibration, table_shift_mm=args.table_shift,
        progress=not args.quiet,
    )
    paths = write_case(case, args.out, preview=args.preview)
    if not args.quiet:
        print(f"phantom {args.anatomy} seed {args.seed}: {len(case.anatomy.vessels)} branches, "
              f"2 x {args.frames} frames of {args.size}x{args.size} in {time.perf_counter() - t0:.1f} s")
        for name, p in paths.items():
            print(f"  {name:9s} {p}")
    return 0


def _print_reconstruction(rec, paths: dict, out: Path) -> None:
    e = rec.errors
    ph = rec.phase
    print(f"frames ({ph.frame_a}, {ph.frame_b}) by {ph.basis}: "
          + (f"phase error {ph.error_mm:.3f} mm, " if np.isfinite(ph.error_mm) else "")
          + f"confidence {ph.confidence:.2f}")
    print(f"2D graphs: {len(rec.graphs[0].branches)} and {len(rec.graphs[1].branches)} branches; "
          f"{len(rec.match.pairs)} branch pairs matched, {len(rec.ok_branches)} reconstructed in 3D")
    if e:
        print(f"reprojection error {e['mean_px']:.2f} +- {e['sd_px']:.2f} px ({e['mean_mm']:.3f} +- "
              f"{e['sd_mm']:.3f} mm), max {e['max_px']:.2f} px")
    if rec.refinement is not None:
        r = rec.refinement
        print(f"geometry refinement: {'applied' if r.applied else 'not applied'} (error {r.before_px:.2f} -> "
              f"{r.after_px:.2f} px)")
    if rec.solid is not None:
        print(f"solid: {rec.solid!r}")
        out_ids = rec.solid_left_out
        if out_ids:
            ids = ", ".join(map(str, sorted(out_ids)))
            print(f"  it holds {rec.solid_share:.0%} of the tree's centreline length; "
                  f"{len(out_ids)} branches left out ({ids}: dashed in overlay.png, reasons in report.json)")
    print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in rec.timings.items()))
    for w in rec.warnings[:12]:
        print(f"  warning: {w}")
    if len(rec.warnings) > 12:
        print(f"  ... {len(rec.warnings) - 12} more warnings in {out / 'report.json'}")
    print("wrote " + ", ".join(sorted(paths)) + f" in {out}")


def _max_side(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n != 0 and n < 64:
        raise argparse.ArgumentTypeError(f"expected 0 or a whole number >= 64, got {text!r}")
    return n


def _reconstruct_args(args: argparse.Namespace) -> dict:
    from .pipeline import OFF_SURFACE_SIGMAS

    return {"method": args.method, "frames": args.frames, "model": args.model, "objects": args.objects,
            "refine": not args.no_refine, "solid": not args.no_solid, "progress": not args.quiet,
            "tta": args.tta, "frame_search": args.frame_search,
            "off_surface_sigmas": None if args.keep_off_surface else OFF_SURFACE_SIGMAS,
            "max_side": args.max_side or None}


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from .pipeline import reconstruct

    out = Path(args.out)
    rec = reconstruct(args.run_a, args.run_b, geometry_a=args.geometry_a or args.geometry,
                      geometry_b=args.geometry_b or args.geometry, **_reconstruct_args(args))
    paths = rec.write(out, html=not args.no_html)
    if args.json:
        print(json.dumps({"out": str(out), "files": sorted(str(p) for p in paths.values()),
                          **{k: v for k, v in rec.report().items() if k in (
                              "frame_a", "frame_b", "phase_error_mm", "reprojection", "tree", "warnings",
                              "timings_s")}}))
    elif not args.quiet:
        _print_reconstruction(rec, paths, out)
    return 0 if rec.tree is not None else 3


def _read_mask(path: str, name: str, shape: tuple[int, int], file_shape: tuple[int, int] | None = None
               ) -> np.ndarray:
    """A vessel mask from an image file (grey > 127 is vessel) or a .npy array (non-zero)."""
    import cv2

    from .errors import InputFileError

    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{name} {p}: no such file")
    if p.suffix.lower() == ".npy":
        try:
            mask = np.load(p, allow_pickle=False) != 0
        except (ValueError, OSError, EOFError) as exc:
            raise InputFileError(f"{name} {p}: not a numpy array file ({exc})") from None
    else:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputFileError(f"{name} {p}: not an image file OpenCV can read")
        mask = img > 127
    if mask.shape != shape and mask.shape != file_shape:
        also = "" if file_shape in (None, shape) else f" ({file_shape[0]} x {file_shape[1]} in the file)"
        raise InputFileError(f"{name} {p}: shape {mask.shape}, but the chosen frame has {shape[0]} rows "
                             f"and {shape[1]} columns{also}")
    return mask


def _cmd_check(args: argparse.Namespace) -> int:
    from .errors import InputFileError
    from .geometry import CArmView
    from .io import atomic_write_text
    from .metrics import mask_reprojection
    from .tree import VesselTree

    out = Path(args.dir)
    try:
        report = json.loads((out / "report.json").read_text(encoding="utf-8"))
        views = [CArmView.from_dict(report[k]["used"], source=f"{out / 'report.json'} {k}")
                 for k in ("view_a", "view_b")]
        # the frames' size in the files (reconstruct may have worked on them reduced: max_side)
        sizes = [(int(h["rows"]), int(h["cols"])) if isinstance(h := report[k].get("header"), dict) else None
                 for k in ("view_a", "view_b")]
    except FileNotFoundError:
        raise InputFileError(f"{out}: no report.json (the folder `vesselcad reconstruct` wrote)") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputFileError(f"{out / 'report.json'}: not a vesselcad report ({exc})") from None
    tree = VesselTree.from_json(out / "centrelines.json")
    masks = [_read_mask(path, f"--mask-{k}", (v.rows, v.cols), size)
             for k, path, v, size in zip("ab", (args.mask_a, args.mask_b), views, sizes, strict=True)]
    m = mask_reprojection(tree, views, masks)
    result = {"frames": [report.get("frame_a"), report.get("frame_b")],
              "masks": [str(args.mask_a), str(args.mask_b)], **m.to_dict()}
    atomic_write_text(out / "mask_check.json", json.dumps(result, indent=1) + "\n")
    if args.json:
        print(json.dumps(result))
    elif not args.quiet:
        print(f"tree reprojected into frames {result['frames'][0]} (A) and {result['frames'][1]} (B) against "
              f"the masks: {m.mean_px:.2f} +- {m.sd_px:.2f} px ({m.mean_mm:.3f} +- {m.sd_mm:.3f} mm) from "
              f"their centrelines, max {m.max_mm:.2f} mm; {m.on_vessel_share:.1%} of it on vessel")
        for k, v in zip("AB", result["views"], strict=True):
            print(f"  view {k}: {v['mean_mm']:.3f} mm, {v['on_vessel']:.1%} on vessel")
        print(f"wrote {out / 'mask_check.json'}")
    return 0


def _cmd_batch(args: argparse.Namespace) -> int:
    from .batch import run_batch

    args.frames = None
    opts = {k: v for k, v in _reconstruct_args(args).items() if k not in ("frames", "progress")}
    res = run_batch(args.input, args.out, jobs=args.jobs, force=args.force, scheduler=args.scheduler,
                    html=not args.no_html, progress=not args.quiet, **opts)
    if args.json:
        failed = [{k: r.get(k) for k in ("case", "status", "message")} for r in res.failed]
        print(json.dumps({"out": str(res.out), "seconds": round(res.seconds, 2), "counts": res.counts,
                          "failed": failed}))
    elif not args.quiet:
        print(f"{len(res.cases)} cases in {res.seconds:.1f} s: " + ", ".join(
            f"{v} {k}" for k, v in res.counts.items() if v))
        for r in res.failed:
            print(f"  {r['case']}: {r['status']}: {r.get('message', '')}")
        print(f"summary: {res.out / 'summary.csv'}, {res.out / 'summary.json'}")
    return 4 if res.failed else 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .io import atomic_write_text
    from .phantom import generate_case, write_case
    from .phantom.compare import compare_with_truth
    from .pipeline import reconstruct

    out = Path(args.out)
    t0 = time.perf_counter()
    case = generate_case(args.seed, args.anatomy, args.n_frames, rows=args.size, cols=args.size,
                         miscalibration_deg=args.miscalibration, progress=not args.quiet)
    paths = write_case(case, out, preview=True)
    labels = (case.run_a.labels, case.run_b.labels) if args.labels == "truth" else None
    rec = reconstruct(paths["run_a"], paths["run_b"], labels=labels, **_reconstruct_args(args))
    written = rec.write(out, html=not args.no_html)
    truth = compare_with_truth(rec, case)
    summary = {
        "out": str(out), "anatomy": args.anatomy, "seed": args.seed, "labels": args.labels,
        "truth_branches": len(case.anatomy.vessels),
        "frames": [rec.phase.frame_a, rec.phase.frame_b],
        "true_phase_difference": truth.pop("phase_difference"),
        "truth": truth,
        "reprojection": {k: round(v, 4) for k, v in rec.errors.items()},
        "branches": [len(rec.ok_branches), len(rec.branches)],
        "solid_tree_share": None if rec.solid_share is None else round(rec.solid_share, 4),
        "seconds": round(time.perf_counter() - t0, 2),
        "timings_s": {k: round(v, 3) for k, v in rec.timings.items()},
    }
    atomic_write_text(out / "demo.json", json.dumps(summary, indent=2) + "\n")
    if args.json:
        print(json.dumps(summary))
    elif not args.quiet:
        print(f"phantom {args.anatomy} seed {args.seed}: {summary['truth_branches']} vessels, runs of "
              f"{args.n_frames} frames written as DICOM and read back ({args.labels} labels)")
        _print_reconstruction(rec, written, out)
        d = summary["true_phase_difference"]
        print(f"against the phantom's truth: 3D centreline error {truth['mean_mm']:.3f} mm mean, "
              f"{truth['p95_mm']:.3f} mm p95, {truth['max_mm']:.3f} mm max; {truth['coverage']:.0%} of the "
              f"true tree's length reconstructed; true phase difference {d['cardiac']:.3f} cardiac, "
              f"{d['respiratory']:.3f} respiratory cycles")
        print(f"open {out / 'report.html'} in a browser; {summary['seconds']} s in all")
    return 0 if rec.tree is not None else 3


def _cmd_info(args: argparse.Namespace) -> int:
    from .io import load_run

    run = load_run(args.run, geometry=args.geometry)
    v = run.view
    info = {
        "source": run.source,
        "frames": run.n_frames,
        "rows": v.rows,
        "cols": v.cols,
        "bits_stored": run.bits_stored,
        "frame_time_ms": (round(float(np.median(np.diff(run.frame_times_ms))), 4)
                          if run.n_frames > 1 else None),
        "r_wave_frames": None if run.r_wave_frames is None else run.r_wave_frames.tolist(),
        "view": v.to_dict(),
        "magnification": round(v.magnification, 6),
        "mm_per_px_isocentre": [round(x, 6) for x in v.mm_per_px],
        "source_mm": np.round(v.source, 3).tolist(),
        "detector_centre_mm": np.round(v.detector_centre, 3).tolist(),
        "patient_id": run.patient_id,
        "study_uid": run.study_uid,
    }
    if args.json:
        print(json.dumps(info))
    else:
        for key, value in info.items():
            print(f"{key:22s} {value}")
    return 0


def _cmd_mesh(args: argparse.Namespace) -> int:
    import warnings

    from . import cfd
    from .errors import ArgumentError, VesselcadWarning

    suffix = Path(args.out).suffix.lower()
    volume_ok = {".msh", ".vtu", ".vtk", ".xdmf"}
    if suffix not in volume_ok | ({".stl", ".ply", ".obj", ".glb"} if args.surface_only else set()):
        raise ArgumentError(f"--out {args.out}: a {'surface' if args.surface_only else 'volume'} mesh "
                            f"cannot be written as {suffix or 'a file without suffix'}; use "
                            + ", ".join(sorted(volume_ok))
                            + (", .stl, .ply, .obj, .glb" if args.surface_only else ""))
    ext = (args.inlet_extension if args.inlet_extension is not None else args.flow_extensions,
           args.flow_extensions)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", VesselcadWarning)
        common = {"edge_factor": args.edge_factor, "flow_extensions": ext, "progress": not args.quiet,
                  "separate_contacts": not args.keep_contacts, "crease_radius": args.crease_radius}
        if args.surface_only:
            mesh = cfd.surface_mesh(args.source, **common).metadata["cfd_mesh"]
        else:
            mesh = cfd.volume_mesh(args.source, boundary_layers=args.boundary_layers,
                                   first_layer=args.first_layer, first_layer_mm=args.first_layer_mm,
                                   growth=args.growth, **common)
    side = mesh.write(args.out, msh_version=args.msh_version)
    if args.png:
        from .render import render_mesh

        surf = mesh.surface()
        names = {gid: name for name, gid in mesh.groups.items()}
        render_mesh(surf, args.png, color_by="label", labels=names, views=((25, -60), (-35, 30)),
                    edge_width=0.1 if len(surf.faces) < 20000 else 0,
                    title=f"{args.out}: {len(surf.faces)} boundary triangles, {mesh.n_cells} cells")
    summary = {"out": str(args.out), "boundary_conditions": str(side),
               "nodes": int(len(mesh.points)),
               "elements": {k: int(len(v)) for k, v in {**mesh.cells, **mesh.facets}.items()},
               "quality": mesh.quality, "boundaries": [b.to_dict() for b in mesh.boundaries],
               "seconds": round(mesh.timings_s.get("total", 0.0), 2),
               "warnings": mesh.warnings + [str(w.message) for w in caught]}
    if args.json:
        print(json.dumps(summary))
    elif not args.quiet:
        counts = ", ".join(f"{n} {k}" for k, n in summary["elements"].items())
        print(f"{args.out}: {summary['nodes']} nodes, {counts} in {summary['seconds']} s")
        for kind, q in mesh.quality.items():
            if "scaled_jacobian_min" in q:
                print(f"  {kind:8s} scaled Jacobian min {q['scaled_jacobian_min']:.3f} mean "
                      f"{q['scaled_jacobian_mean']:.3f}, inverted {q['inverted']}, aspect ratio max "
                      f"{q['aspect_ratio_max']:.2f}")
        for b in mesh.boundaries:
            print(f"  {b.name:10s} id {b.id:2d}  branch {b.branch:10s} area {b.area_mm2:8.3f} mm^2  "
                  f"centre {np.round(b.centre, 2).tolist()}  normal {np.round(b.normal, 3).tolist()}")
        print(f"  boundary conditions: {side}")
        for w in summary["warnings"]:
            print(f"  warning: {w}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vesselcad", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"vesselcad {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    ph = sub.add_parser("phantom", help="generate a biplane phantom case with ground truth")
    ph.add_argument("--seed", type=int, required=True)
    ph.add_argument("--out", required=True, help="output folder")
    ph.add_argument("--anatomy", choices=["lca", "rca", "cs"], default="lca")
    ph.add_argument("--frames", type=int, default=60, help="frames per run (default 60)")
    ph.add_argument("--size", type=int, default=512, help="image size in pixels (default 512)")
    ph.add_argument("--bits", type=int, choices=[8, 12], default=8)
    ph.add_argument("--synchronized", action="store_true",
                    help="both runs at identical cardiac/respiratory phases (true biplane)")
    ph.add_argument("--miscalibration", type=float, default=0.0, metavar="DEG",
                    help="max angle error written into the DICOM headers")
    ph.add_argument("--table-shift", type=float, default=0.0, metavar="MM",
                    help="patient/table shift between run A and run B")
    ph.add_argument("--preview", action="store_true", help="also write preview.png")
    ph.add_argument("--quiet", action="store_true")
    ph.set_defaults(func=_cmd_phantom)

    inf = sub.add_parser("info", help="load one run (DICOM or frame folder) and print its geometry")
    inf.add_argument("run", help="XA DICOM file or folder of frames with view.json")
    inf.add_argument("--geometry", metavar="VIEW_JSON",
                     help="view.json whose CArmView entries override or fill the file's tags")
    inf.add_argument("--json", action="store_true", help="print one JSON object")
    inf.set_defaults(func=_cmd_info)

    def recon_options(q: argparse.ArgumentParser, pair_flag: str | None = "--frames") -> None:
        q.add_argument("--method", choices=["nurbs", "epipolar"], default="nurbs",
                       help="3D centrelines by NURBS surface intersection (default) or the epipolar baseline")
        if pair_flag:
            q.add_argument(pair_flag, dest="frames", type=int, nargs=2, metavar=("I", "J"),
                           help="use frame I of run A and frame J of run B instead of phase matching")
        q.add_argument("--model", metavar="ONNX",
                       help="segmentation model: an .onnx file, or a bundled one: 'int8' (default: the "
                       "gated U-Net quantized, the same accuracy, 1.6-11x faster than fp32 on CPUs), "
                       "'fp32' (full precision), 'fast' / 'fast-int8' (the half-width network, ~3x "
                       "faster, a little less accurate)")
        q.add_argument("--objects", default="auto",
                       help="stationary object for phase matching: auto, balloon, catheter, lead, or "
                       "vessels (none: the vessels' epipolar consistency alone; auto falls back to it "
                       "when no object is found in both runs)")
        q.add_argument("--tta", choices=["chosen", "all", "none"], default="chosen",
                       help="test-time augmentation of the segmentation (the mean over the frame and "
                       "its three mirror images, each at its size and at 0.75 of it): the two chosen "
                       "frames (default), every frame (~7x the segmentation time), or none")
        q.add_argument("--frame-search", choices=["all", "coarse"], default="all",
                       help="which frames the model labels for the phase matching: all (default), or "
                       "coarse to fine, about three quarters of a 15 fps run (faster, for batches)")
        q.add_argument("--keep-off-surface", action="store_true",
                       help="keep branches, and branch ends, that lie off the heart's surface fitted to "
                       "the tree (by default they are left out as wrong pairings; use it for vessels "
                       "that do not run on one surface)")
        q.add_argument("--max-side", type=_max_side, default=512, metavar="PX",
                       help="frames with more rows or columns are reduced to this size (area average) "
                       "before anything else: the size the method's pixel parameters are set for "
                       "(default 512; 0 keeps the frames as they are)")
        q.add_argument("--no-refine", action="store_true", help="keep the files' geometry as it is")
        q.add_argument("--no-solid", action="store_true", help="centrelines only, no CAD solid")
        q.add_argument("--no-html", action="store_true", help="skip report.html")
        q.add_argument("--quiet", action="store_true", help="no progress bars or summary")
        q.add_argument("--json", action="store_true", help="print a JSON summary")

    rc = sub.add_parser("reconstruct", help="3D vessel tree from two runs (DICOM XA or frame folders)")
    rc.add_argument("run_a", metavar="A", help="run A: XA DICOM file or folder of frames with view.json")
    rc.add_argument("run_b", metavar="B", help="run B")
    rc.add_argument("--out", required=True, help="output folder")
    rc.add_argument("--geometry", metavar="VIEW_JSON",
                    help="view.json whose entries override or fill both files' geometry tags")
    rc.add_argument("--geometry-a", metavar="VIEW_JSON", help="the same for run A only")
    rc.add_argument("--geometry-b", metavar="VIEW_JSON", help="the same for run B only")
    recon_options(rc)
    rc.set_defaults(func=_cmd_reconstruct)

    ba = sub.add_parser("batch", help="many cases (a folder of case folders or a CSV manifest), in "
                        "parallel, resumable; one failure never stops the rest")
    ba.add_argument("input", metavar="INPUT",
                    help="folder of case folders (two runs each) or CSV manifest (case,run_a,run_b"
                    "[,geometry,geometry_a,geometry_b,frame_a,frame_b])")
    ba.add_argument("--out", required=True, help="output folder: one sub-folder per case, summary.csv/.json")
    ba.add_argument("--jobs", "-j", type=int, default=1, help="worker processes (default 1)")
    ba.add_argument("--force", action="store_true", help="re-run cases that finished before")
    ba.add_argument("--scheduler", metavar="ADDRESS",
                    help="run on this Dask distributed scheduler (e.g. tcp://host:8786) instead of local "
                    "processes; workers must see INPUT and --out at the same paths")
    recon_options(ba, pair_flag=None)  # frame pairs per case: manifest columns frame_a, frame_b
    ba.set_defaults(func=_cmd_batch)

    de = sub.add_parser("demo", help="generate a phantom case and reconstruct it end to end")
    de.add_argument("--out", default="vesselcad-demo", help="output folder (default vesselcad-demo)")
    de.add_argument("--seed", type=int, default=0)
    de.add_argument("--anatomy", choices=["lca", "rca", "cs"], default="lca")
    de.add_argument("--frames", dest="n_frames", type=int, default=40, help="frames per run (40)")
    de.add_argument("--size", type=int, default=512, help="image size in pixels (512)")
    de.add_argument("--miscalibration", type=float, default=0.0, metavar="DEG",
                    help="max angle error written into the DICOM headers")
    de.add_argument("--labels", choices=["model", "truth"], default="model",
                    help="segment with the bundled model (default) or use the phantom's true labels")
    recon_options(de, "--pair")
    de.set_defaults(func=_cmd_demo)

    ck = sub.add_parser("check", help="measure a reconstruction against vessel masks of its two chosen "
                                      "frames (traced by hand, say)")
    ck.add_argument("dir", metavar="DIR", help="a folder `vesselcad reconstruct` wrote (report.json, "
                                               "centrelines.json)")
    ck.add_argument("--mask-a", required=True, metavar="FILE",
                    help="vessel mask of run A's chosen frame: an image (grey > 127 = vessel) or .npy")
    ck.add_argument("--mask-b", required=True, metavar="FILE", help="the same for run B's chosen frame")
    ck.add_argument("--quiet", action="store_true")
    ck.add_argument("--json", action="store_true", help="print the result as one JSON object")
    ck.set_defaults(func=_cmd_check)

    me = sub.add_parser("mesh", help="CFD mesh (gmsh) of a tree: labelled caps, flow extensions, "
                                     "boundary layers")
    me.add_argument("source", metavar="DIR_OR_TREE",
                    help="centrelines.json, a phantom truth.json, or a folder holding one")
    me.add_argument("--out", required=True,
                    help="mesh file: .msh, .vtu, .vtk, .xdmf (surface-only also .stl, .ply, .obj)")
    me.add_argument("--surface-only", action="store_true", help="a labelled triangle surface, no volume")
    me.add_argument("--flow-extensions", type=float, default=0.0, metavar="N",
                    help="straight extensions of N diameters at the outlets (and inlet) (0)")
    me.add_argument("--inlet-extension", type=float, default=None, metavar="N",
                    help="inlet extension in diameters when it differs from --flow-extensions")
    me.add_argument("--boundary-layers", type=int, default=0, metavar="N",
                    help="prism layers at the wall (0)")
    me.add_argument("--first-layer", type=float, default=0.02, metavar="F",
                    help="first layer thickness as a fraction of the local radius (0.02)")
    me.add_argument("--first-layer-mm", type=float, default=None, metavar="MM",
                    help="first layer thickness in mm, the same everywhere (overrides --first-layer)")
    me.add_argument("--growth", type=float, default=1.2, help="layer thickness ratio (1.2)")
    me.add_argument("--edge-factor", type=float, default=0.3, metavar="F",
                    help="element size as a fraction of the local radius (0.3)")
    me.add_argument("--keep-contacts", action="store_true",
                    help="do not move apart vessels that touch away from a junction (they are by default, "
                         "by the least needed for 0.2 mm between their walls; the moves are listed in the "
                         "warnings)")
    me.add_argument("--crease-radius", type=float, default=0.1, metavar="F",
                    help="round junction creases sharper than 45 degrees (a vessel leaving its parent at a "
                         "shallow angle) with a fillet of F times the vessel radius; 0 keeps them (0.1)")
    me.add_argument("--msh-version", type=float, choices=[2.2, 4.1], default=4.1,
                    help="gmsh file version; 2.2 for OpenFOAM's gmshToFoam (4.1)")
    me.add_argument("--png", metavar="FILE", help="also draw the labelled surface into a PNG")
    me.add_argument("--quiet", action="store_true")
    me.add_argument("--json", action="store_true", help="print a JSON summary")
    me.set_defaults(func=_cmd_mesh)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``vesselcad`` console script."""
    args = _parser().parse_args(argv)
    for name in ("frames", "n_frames"):
        value = getattr(args, name, None)
        if isinstance(value, int) and value < 1:
            print("vesselcad: error: --frames must be >= 1", file=sys.stderr)
            return 2
    from .pipeline import ReconstructionError

    try:
        return int(args.func(args))
    except ReconstructionError as exc:
        print(f"vesselcad: no tree: {exc}", file=sys.stderr)
        return 3
    except VesselcadError as exc:
        print(f"vesselcad: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
