"""Benchmark: CFD meshes of real-shaped trees (issue: CFD meshing API).

There are no real 3D vessel trees in the data. The nearest thing: the expert
vessel masks of real angiograms (CIMAT, ``../shared/data/xca-real/train``)
turned into centreline graphs and draped on a 60 mm sphere cap, as
``examples/real_mask_to_solid.py`` does. Their skeleton-graph topology (a
parent ends where its children start), their noise, widths and crossings are
real; the depth is not. For each mask this meshes the tree the way a user
would (``vc.cfd.surface_mesh(tree)``, ``vc.cfd.volume_mesh(tree,
flow_extensions=2)``, and the same with ``--layers`` prism layers) and prints
seconds, element counts, the lowest scaled Jacobian and inverted elements,
plus any place where the prism layers had to be thinned.

Usage::

    python benchmarks/cfd_real.py 17 25 3 9 [--data ../shared/data/xca-real/train] [--layers 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import vesselcad as vc  # noqa: E402


def _draped_tree(mask: Path) -> vc.VesselTree:
    path = ROOT / "examples" / "real_mask_to_solid.py"  # one definition of the draping
    spec = importlib.util.spec_from_file_location("real_mask_to_solid", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.draped_tree(mask)[0]


def measure(mask: Path, layers: int) -> list[str]:
    """One table row: surface, tetrahedra, layers."""
    tree = _draped_tree(mask)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = time.perf_counter()
        surf = vc.cfd.surface_mesh(tree)
        row = [mask.stem.split("_")[0], str(len(tree.branches)), f"{time.perf_counter() - t:.1f}",
               str(len(surf.faces)), "yes" if surf.is_watertight else "no"]
        t = time.perf_counter()
        tets = vc.cfd.volume_mesh(tree, flow_extensions=2.0)
        q = tets.quality["tetra"]
        row += [f"{time.perf_counter() - t:.1f}", str(q["count"]), f"{q['scaled_jacobian_min']:.3f}",
                str(q["inverted"])]
        t = time.perf_counter()
        try:
            mesh = vc.cfd.volume_mesh(tree, flow_extensions=2.0, boundary_layers=layers)
            qt, qw = mesh.quality["tetra"], mesh.quality["wedge"]
            row += [f"{time.perf_counter() - t:.1f}", str(qt["count"] + qw["count"]),
                    f"{qt['scaled_jacobian_min']:.3f} / {qw['scaled_jacobian_min']:.3f}",
                    str(qt["inverted"] + qw["inverted"])]
        except vc.MeshError as exc:
            row += [f"failed: {str(exc)[:120]}", "–", "–", "–"]
    thinned = [str(w.message) for w in caught if "prism layers" in str(w.message)]
    row.append("; ".join(thinned)[:200] or "–")
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=int, nargs="+", help="CIMAT image numbers (their <n>_gt.png masks)")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "xca-real" / "train")
    ap.add_argument("--layers", type=int, default=3)
    args = ap.parse_args(argv)
    missing = [n for n in args.images if not (args.data / f"{n}_gt.png").exists()]
    if missing:
        print(f"no masks {missing} in {args.data}", file=sys.stderr)
        return 2
    import gmsh

    print(f"machine: {platform.machine()}, {len(os.sched_getaffinity(0))} cores, "
          f"python {platform.python_version()}, gmsh {gmsh.__version__}")
    print()
    print(f"| CIMAT | branches | surface s | triangles | watertight | tets s | tets | min SJ | inverted "
          f"| {args.layers} layers + 2 D ext. s | elements | min SJ tet / wedge | inverted "
          "| layers thinned |")
    print("|---" * 14 + "|")
    for n in args.images:
        print("| " + " | ".join(measure(args.data / f"{n}_gt.png", args.layers)) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
