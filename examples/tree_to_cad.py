"""A vessel tree (centrelines with radii) to CAD: STEP, STL, GLB, VTP and a picture.

Uses the ground-truth tree of a phantom case; replace it with
``vc.VesselTree.from_json("centrelines.json")`` for your own tree.

    python examples/tree_to_cad.py --out tree-out
"""

from __future__ import annotations

import argparse
from pathlib import Path

import vesselcad as vc
from vesselcad.phantom import generate_case
from vesselcad.render import render_mesh


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("tree-out"))
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--anatomy", default="lca", choices=["lca", "rca", "cs"])
    args = ap.parse_args()

    case = generate_case(args.seed, args.anatomy, n_frames=1, rows=128, cols=128)
    tree = vc.VesselTree.from_truth(case)          # or VesselTree.from_json("centrelines.json")
    solid = tree.solid(progress=True)              # one fused, checked OCCT solid
    report = solid.check()
    print(tree)
    print(solid, "valid" if report["watertight"] else "NOT watertight", solid.timings_s)
    for w in solid.warnings:
        print("  warning:", w)
    for bid, why in solid.failed.items():
        print(f"  branch {bid} left out: {why}")

    args.out.mkdir(parents=True, exist_ok=True)
    solid.export_step(args.out / "tree.step")      # AP214, faces named '<branch>:wall|inlet|outlet'
    solid.export_stl(args.out / "tree.stl")        # binary
    solid.export_glb(args.out / "tree.glb")
    tree.to_json(args.out / "centrelines.json")
    tree.to_vtp(args.out / "centrelines.vtp")      # vmtk-style radius array
    render_mesh(solid.to_trimesh(), args.out / "tree.png", title=repr(solid))
    for cap in solid.caps():
        print(f"  {cap['role']:7s} {cap['name']:12s} r = {cap['radius']:.2f} mm at {cap['centre'].round(1)}")

    # Keep modelling in build123d or cadquery: both see the same OCCT solid.
    part = solid.to_build123d()
    print("build123d volume", round(part.volume, 1), "mm^3; cadquery",
          round(solid.to_cadquery().val().Volume(), 1), "mm^3")


if __name__ == "__main__":
    main()
