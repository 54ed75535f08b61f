"""Real-shaped input for the solid stage: expert vessel masks of real angiograms -> 2D centreline
graph -> the tree draped on a 60 mm sphere cap (a stand-in for the heart surface) -> one solid.

There are no real 3D trees in the data; this exercises rebuild, merge, radius guards and fusion on
real skeleton noise, real widths and real branching. With ``--mesh N`` it also meshes each solid for
CFD (vc.cfd, N prism layers, 3-diameter flow extensions) and reports the mesh quality. Usage (numbers
of CIMAT images):

    python examples/real_mask_to_solid.py 17 9 3 25 --data ../shared/data/xca-real/train --out real-out
    python examples/real_mask_to_solid.py 17 25 --mesh 3
"""

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

import vesselcad as vc
from vesselcad.render import render_mesh

VIEW = vc.CArmView(primary_deg=0.0, secondary_deg=0.0, sid_mm=1000.0, sod_mm=750.0,
                   pixel_spacing_mm=(0.4, 0.4), rows=300, cols=300)
SCALE = 0.4 * 750 / 1000  # mm at the isocentre per pixel


def draped_tree(mask_path: Path, sphere_mm: float = 60.0) -> tuple[vc.VesselTree, vc.CentrelineGraph]:
    """The centreline graph of a 300 x 300 vessel mask, its root's component draped on a sphere cap."""
    mask = cv2.imread(str(mask_path), 0) > 127
    g = vc.centreline_graph(mask, VIEW)
    by_end = {b.end: b.index for b in g.branches}
    # keep the root's component
    keep, frontier = set(), [b.index for b in g.branches if b.start == g.root]
    while frontier:
        i = frontier.pop()
        keep.add(i)
        frontier += [b.index for b in g.branches if b.start == g.branches[i].end and b.index not in keep]
    br = []
    for b in g.branches:
        if b.index not in keep or len(b.points_px) < 3:
            continue
        xy = (b.points_px - 150) * SCALE
        z = np.sqrt(np.maximum(sphere_mm**2 - (xy**2).sum(1), 0))
        parent = by_end.get(b.start)
        br.append({"id": b.index, "parent": parent if parent in keep else None,
                   "points": np.c_[xy, z].tolist(), "radius": np.maximum(b.radius_mm, 0.2).tolist()})
    ids = {b["id"] for b in br}
    for b in br:
        if b["parent"] not in ids:
            b["parent"] = None
    return vc.VesselTree.from_json({"units": "mm", "frame": "LPS", "branches": br}), g


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("images", type=int, nargs="+")
    ap.add_argument("--data", type=Path, default=Path("../shared/data/xca-real/train"))
    ap.add_argument("--out", type=Path, default=Path("real-out"))
    ap.add_argument("--mesh", type=int, default=None, metavar="LAYERS",
                    help="also make a CFD volume mesh with this many prism layers")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for n in args.images:
        tree, g = draped_tree(args.data / f"{n}_gt.png")
        br = tree.branches
        t = time.time()
        solid = tree.solid()
        chk = solid.check()
        print(f"CIMAT {n}: {len(g.branches)} graph branches, {len(br)} in root tree, "
              f"{len(solid.branch_ids)} pipes, "
              f"failed {solid.failed}, watertight {chk['watertight']}, {time.time()-t:.1f} s, "
              f"{len(solid.warnings)} warnings e.g. {solid.warnings[:2]}")
        render_mesh(solid.to_trimesh(tolerance=0.05, angular_deflection=0.5), args.out / f"real_{n}.png",
                    title=f"CIMAT {n} expert mask centrelines on a sphere cap: {solid}")
        if args.mesh is not None:
            t = time.time()
            surf = vc.cfd.surface_mesh(solid, flow_extensions=3)
            mesh = vc.cfd.volume_mesh(solid, flow_extensions=3, boundary_layers=args.mesh)
            sj = {k: round(q["scaled_jacobian_min"], 3) for k, q in mesh.quality.items()
                  if "scaled_jacobian_min" in q}
            inv = sum(q.get("inverted", 0) for q in mesh.quality.values())
            print(f"  CFD: surface {len(surf.faces)} triangles, watertight {surf.is_watertight}, "
                  f"{len(mesh.boundaries) - 1} outlets; volume {mesh.n_cells} cells, "
                  f"min scaled Jacobian {sj}, "
                  f"inverted {inv}, {time.time() - t:.1f} s; warnings {mesh.warnings[-2:]}")
            mesh.write(args.out / f"real_{n}.vtu")
            inlet = mesh.boundaries[0]
            from vesselcad.render import render_cfd_mesh

            render_cfd_mesh(mesh, args.out / f"real_{n}_cfd.png",
                            origin=inlet.centre - 3 * inlet.radius_mm * inlet.normal, normal=inlet.normal,
                            title=f"CIMAT {n}: {mesh.n_cells} cells")


if __name__ == "__main__":
    main()
