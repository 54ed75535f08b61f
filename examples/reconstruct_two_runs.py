"""Two XA runs to a 3D vessel tree with the Python API, and what to look at in the result.

With your own files::

    python examples/reconstruct_two_runs.py RUN_A.dcm RUN_B.dcm --out recon
    python examples/reconstruct_two_runs.py RUN_A.dcm RUN_B.dcm --geometry view.json  # export lacks SID/SOD

Without arguments it writes a small phantom case first and reconstructs that.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import vesselcad as vc


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="*", type=Path, help="two XA DICOM files (default: a phantom case)")
    ap.add_argument("--out", type=Path, default=Path("recon"))
    ap.add_argument("--geometry", type=Path, help="view.json filling tags the files lack")
    args = ap.parse_args()

    if not args.runs:
        from vesselcad.phantom import generate_case, write_case

        paths = write_case(generate_case(3, "rca", 16, rows=384, cols=384), args.out / "input")
        args.runs = [paths["run_a"], paths["run_b"]]
    if len(args.runs) != 2:
        ap.error("give two runs")

    # Read the runs first to see what the files say about the C-arm.
    run_a = vc.load_run(args.runs[0], geometry=args.geometry)
    run_b = vc.load_run(args.runs[1], geometry=args.geometry)
    for name, run in (("A", run_a), ("B", run_b)):
        v = run.view
        print(f"run {name}: {run.n_frames} frames, primary {v.primary_deg:+.1f} deg, secondary "
              f"{v.secondary_deg:+.1f} deg, SID {v.sid_mm:.0f} mm, SOD {v.sod_mm:.0f} mm")

    rec = vc.reconstruct(run_a, run_b, progress=True)   # refine=True, solid=True, method="nurbs"
    print(rec)
    print(f"frames {rec.phase.frame_a} and {rec.phase.frame_b}, phase error {rec.phase.error_mm:.2f} mm")
    if rec.refinement is not None:
        r = rec.refinement
        print(f"geometry refinement {'applied' if r.applied else 'not applied'}: "
              f"{r.before_px:.2f} -> {r.after_px:.2f} px")
    for b in rec.branches:                              # every matched pair, kept or rejected, and why
        print(f"  branch {b.id}: {b.status}"
              + (f", {b.reprojection.mean_px:.2f} px mean reprojection" if b.reprojection else ""))
    for w in rec.warnings:
        print("  warning:", w)

    written = rec.write(args.out)                       # STEP/STL/GLB, centrelines, report.json/.html
    print("wrote", ", ".join(sorted(p.name for p in written.values())), "in", args.out)

    # The tree is plain data: centreline points (LPS mm) and radii per branch, parents first.
    tree = json.loads((args.out / "centrelines.json").read_text())
    for b in tree["branches"][:5]:
        print(f"  branch {b['id']} (parent {b['parent']}): {len(b['points'])} points, radius "
              f"{min(b['radius']):.2f}-{max(b['radius']):.2f} mm")
    if rec.solid is not None:
        cq = rec.solid.to_cadquery()                    # keep modelling in CadQuery (or .to_build123d())
        print("CadQuery object:", type(cq).__name__)
    print("open", args.out / "report.html")


if __name__ == "__main__":
    main()
