"""Benchmark: CFD meshes of phantom trees (issue: CFD meshing API).

For each phantom tree (frame 0 of run A's ground truth) this builds the solid
as the meshing API does (``vc.cfd.load_solid``: vessels that touch away from a
junction moved apart first, ``VesselTree.separated``; ``--keep-contacts`` meshes
``VesselTree.solid()`` as it is; not timed here, see benchmarks/solids.py) and then

- a labelled surface mesh (``vc.cfd.surface_mesh``, edge factor 0.3): seconds,
  triangles, and whether it is a *watertight labelled surface*: closed,
  consistently oriented, positive volume within 2% of the B-rep's, exactly one
  inlet and one outlet per open end of the solid, every cap's facets lying in
  its plane (within 1 um) with the meshed cap area within 1% of the exact disc
  (ends that another vessel cuts, "cut ends" in the table, are not discs: their
  facets must lie in the plane, their area is not compared);
- a tetrahedral volume mesh (``vc.cfd.volume_mesh``): seconds, elements, min /
  mean scaled Jacobian (Verdict's definition, computed by vesselcad.cfd.quality
  and checked against numpy determinants for sign), inverted elements;
- the same with prism boundary layers (``--layers``, first layer 0.02 r,
  growth 1.2) and flow extensions (``--extensions`` diameters).

Usage::

    python benchmarks/cfd.py --trees 6 [--json out.json] [--render docs/img]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import vesselcad as vc  # noqa: E402
from vesselcad.phantom import generate_case  # noqa: E402

ANATOMIES = ("lca", "rca", "cs")


def labelled_surface_ok(mesh: vc.cfd.CFDMesh, solid) -> tuple[bool, str]:
    """Independent checks of a labelled boundary; returns (ok, first failure)."""
    surf = mesh.surface()
    if not (surf.is_watertight and surf.is_winding_consistent):
        return False, "not closed or not consistently oriented"
    if not abs(surf.volume - solid.volume) <= 0.02 * solid.volume:
        return False, f"volume {surf.volume:.1f} vs B-rep {solid.volume:.1f}"
    caps = solid.caps()
    roles = [b.role for b in mesh.boundaries]
    if roles.count("inlet") != 1 or roles.count("outlet") != sum(c["role"] == "outlet" for c in caps):
        return False, f"caps {roles}"
    label = surf.face_attributes["label"]
    if not set(np.unique(label)) <= set(mesh.groups.values()):
        return False, "unlabelled facets"
    for b in mesh.boundaries:
        sel = label == b.id
        pts = surf.vertices[surf.faces[sel]].reshape(-1, 3)
        if len(pts) == 0 or np.abs((pts - b.centre) @ b.normal).max() > 1e-3:
            return False, f"{b.name} facets off its plane"
        whole = abs(b.exact_area_mm2 - np.pi * b.radius_mm**2) <= 0.05 * np.pi * b.radius_mm**2
        if whole and abs(surf.area_faces[sel].sum() - b.exact_area_mm2) > 0.01 * b.exact_area_mm2:
            return False, f"{b.name} area {surf.area_faces[sel].sum():.3f} vs {b.exact_area_mm2:.3f}"
    return True, ""


def positive(mesh: vc.cfd.CFDMesh) -> bool:
    """All volume elements positive by plain determinants (tets; wedges as three tets)."""
    p = mesh.points
    for kind, c in mesh.cells.items():
        split = {
            "tetra": [(0, 1, 2, 3)],
            "wedge": [(0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)],
            "pyramid": [(0, 1, 2, 4), (0, 2, 3, 4)],
        }[kind]
        for a, b, cc, d in split:
            m = np.stack([p[c[:, b]] - p[c[:, a]], p[c[:, cc]] - p[c[:, a]], p[c[:, d]] - p[c[:, a]]], axis=1)
            if np.any(np.linalg.det(m) <= 0):
                return False
    return True


def summarise(mesh: vc.cfd.CFDMesh) -> dict:
    q = mesh.quality
    vol = {k: v for k, v in q.items() if "scaled_jacobian_min" in v}
    return {
        "seconds": mesh.timings_s["total"],
        "surface_s": mesh.timings_s.get("surface", 0.0),
        "volume_s": mesh.timings_s.get("volume", 0.0),
        "counts": {k: v["count"] for k, v in q.items()},
        "sj_min": min(v["scaled_jacobian_min"] for v in vol.values()),
        "sj_min_by_type": {k: v["scaled_jacobian_min"] for k, v in vol.items()},
        "sj_mean_tetra": q["tetra"]["scaled_jacobian_mean"],
        "inverted": sum(v["inverted"] for v in vol.values()),
        "positive": positive(mesh),
    }


def measure(anatomy: str, seed: int, layers: int, extensions: float, surface_only: bool = False,
            keep_contacts: bool = False) -> dict:
    case = generate_case(seed, anatomy, n_frames=1, rows=128, cols=128)
    tree = vc.VesselTree.from_truth(case)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        solid = vc.cfd.load_solid(tree, separate_contacts=not keep_contacts)
    moved = [float(m) for w in solid.warnings for m in re.findall(r"moved up to ([\d.]+) mm to keep", w)]
    row: dict = {
        "anatomy": anatomy,
        "seed": seed,
        "pipes": len(solid.branch_ids),
        "failed": len(solid.failed),
        "outlets": sum(c["role"] == "outlet" for c in solid.caps()),
        "contacts": sum("touch away from a junction" in w for w in solid.warnings),
        "moved": len(moved),
        "moved_max_mm": max(moved, default=0.0),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            t0 = time.perf_counter()
            surf = vc.cfd.surface_mesh(solid)
            mesh = surf.metadata["cfd_mesh"]
            ok, why = labelled_surface_ok(mesh, solid)
            row["surface"] = {
                "seconds": time.perf_counter() - t0,
                "triangles": len(surf.faces),
                "labelled_watertight": ok,
                "why": why,
                "cut_ends": sum("not a whole disc" in w for w in mesh.warnings),
            }
        except vc.VesselcadError as exc:
            row["surface"] = {"error": str(exc)[:160]}
        volumes = () if surface_only else (
            ("tets", {}),
            ("layers", {"boundary_layers": layers, "flow_extensions": extensions}),
        )
        for key, kwargs in volumes:
            try:
                row[key] = summarise(vc.cfd.volume_mesh(solid, **kwargs))
            except vc.VesselcadError as exc:
                row[key] = {"error": str(exc)[:160]}
    return row


def render(out: Path) -> None:
    """The Y bifurcation of tests/test_cfd.py with boundary layers and flow extensions."""
    from vesselcad.render import render_cfd_mesh

    def line(p0, d, length, n=30):
        d = np.asarray(d, float) / np.linalg.norm(d)
        return (np.asarray(p0, float) + np.linspace(0, length, n)[:, None] * d).tolist()

    a = np.radians(25.0)
    left, right = [np.sin(a), 0, np.cos(a)], [-np.sin(a), 0, np.cos(a)]
    tree = vc.VesselTree.from_json(
        {
            "units": "mm",
            "frame": "LPS",
            "branches": [
                {
                    "id": 0,
                    "parent": None,
                    "name": "main",
                    "points": line([0, 0, 0], [0, 0, 1], 20),
                    "radius": [2.0] * 30,
                },
                {
                    "id": 1,
                    "parent": 0,
                    "name": "left",
                    "points": line([0, 0, 20], left, 25),
                    "radius": [1.4] * 30,
                },
                {
                    "id": 2,
                    "parent": 0,
                    "name": "right",
                    "points": line([0, 0, 20], right, 25),
                    "radius": [1.4] * 30,
                },
            ],
        }
    )
    mesh = vc.cfd.volume_mesh(tree, boundary_layers=4, flow_extensions=1)
    sj_min = min(q["scaled_jacobian_min"] for q in mesh.quality.values() if "scaled_jacobian_min" in q)
    counts = ", ".join(f"{len(v)} {k}" for k, v in {**mesh.cells}.items())
    out.mkdir(parents=True, exist_ok=True)
    render_cfd_mesh(
        mesh,
        out / "cfd_bifurcation.png",
        origin=np.array([0.0, 0.0, 10.0]),
        normal=np.array([0.0, 0.0, 1.0]),
        title=f"Y bifurcation, 4 boundary layers, 1-diameter flow extensions: {counts}; "
        f"min scaled Jacobian {sj_min:.2f}",
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trees", type=int, default=6)
    ap.add_argument("--seed", type=int, default=3000)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--extensions", type=float, default=2.0)
    ap.add_argument("--surface-only", action="store_true", help="skip the volume meshes")
    ap.add_argument("--keep-contacts", action="store_true",
                    help="mesh the solid as built, without moving touching vessels apart")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--render", type=Path, help="write the picture of a meshed bifurcation here")
    args = ap.parse_args(argv)
    from tqdm.auto import tqdm

    if args.render:
        render(args.render)
    jobs = [(ANATOMIES[i % 3], args.seed + i) for i in range(args.trees)]
    rows = []
    for anat, seed in tqdm(jobs, desc="trees", unit="tree"):
        try:
            rows.append(measure(anat, seed, args.layers, args.extensions, args.surface_only,
                                args.keep_contacts))
        except Exception as exc:  # one bad tree never hides the others
            rows.append({"anatomy": anat, "seed": seed, "error": f"{type(exc).__name__}: {exc}"})
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}, "
        f"gmsh {__import__('gmsh').__version__}\n"
    )
    print(
        f"| anatomy | seed | pipes (left out) | contacts left / moved (max mm) | outlets (cut ends) "
        f"| surface s | triangles "
        f"| labelled watertight | tets s | tets | min SJ | mean SJ | inverted "
        f"| {args.layers} layers + {args.extensions:g} D ext. s "
        f"| elements | min SJ tet / wedge | inverted |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['anatomy']} | {r['seed']} | error: {r['error']} |" + " |" * 14)
            continue
        skipped = {"error": "skipped (--surface-only)"}
        s, t, b = r["surface"], r.get("tets", skipped), r.get("layers", skipped)
        cut = r["surface"].get("cut_ends", "–")
        cols = [r["anatomy"], r["seed"], f"{r['pipes']} ({r['failed']})",
                f"{r['contacts']} / {r['moved']} ({r['moved_max_mm']:.2f})", f"{r['outlets']} ({cut})"]
        if "error" in s:
            cols += ["–", "–", f"error: {s['error']}"]
        else:
            cols += [
                f"{s['seconds']:.1f}",
                s["triangles"],
                "yes" if s["labelled_watertight"] else f"NO: {s['why']}",
            ]
        if "error" in t:
            cols += ["–", "–", "–", "–", f"error: {t['error']}"]
        else:
            cols += [
                f"{t['seconds']:.1f}",
                t["counts"]["tetra"],
                f"{t['sj_min']:.3f}",
                f"{t['sj_mean_tetra']:.3f}",
                t["inverted"],
            ]
        if "error" in b:
            cols += ["–", "–", f"error: {b['error']}", "–"]
        else:
            n = sum(v for k, v in b["counts"].items() if k in ("tetra", "wedge", "pyramid"))
            sj = b["sj_min_by_type"]
            cols += [
                f"{b['seconds']:.1f}",
                n,
                f"{sj.get('tetra', float('nan')):.3f} / {sj.get('wedge', float('nan')):.3f}",
                b["inverted"],
            ]
        print("| " + " | ".join(str(c) for c in cols) + " |")
    ok = [r for r in rows if "error" not in r]
    surf = [r["surface"] for r in ok if "error" not in r["surface"]]
    tets = [r["tets"] for r in ok if "error" not in r.get("tets", {"error": ""})]
    lay = [r["layers"] for r in ok if "error" not in r.get("layers", {"error": ""})]
    print()
    print("| measure | goal | result |")
    print("|---|---|---|")
    good = sum(s["labelled_watertight"] for s in surf)
    print(f"| watertight labelled surfaces | 100% | {good}/{len(rows)} ({100 * good / len(rows):.0f}%) |")
    for name, ms in (("tetrahedra only", tets), (f"{args.layers} prism layers + flow extensions", lay)):
        if not ms:
            print(f"| volume meshes, {name} | – | none |")
            continue
        sj = np.array([m["sj_min"] for m in ms])
        print(f"| volume meshes, {name}: made | – | {len(ms)}/{len(rows)} |")
        print(
            f"| ... min scaled Jacobian > 0.1 | all | {int(np.sum(sj > 0.1))}/{len(ms)} "
            f"(lowest {sj.min():.3f}) |"
        )
        print(
            f"| ... inverted elements (numpy determinants all > 0) | 0 | "
            f"{sum(m['inverted'] for m in ms)} ({sum(m['positive'] for m in ms)}/{len(ms)} all positive) |"
        )
        secs = np.array([m["seconds"] for m in ms])
        n = np.array(
            [sum(v for k, v in m["counts"].items() if k in ("tetra", "wedge", "pyramid")) for m in ms]
        )
        print(
            f"| ... seconds (surface + volume) | – | mean {secs.mean():.0f} s, max {secs.max():.0f} s; "
            f"{n.mean() / 1e3:.0f}k elements mean |"
        )
    if surf:
        print(
            f"| surface mesh seconds | – | mean {np.mean([s['seconds'] for s in surf]):.1f} s, "
            f"{np.mean([s['triangles'] for s in surf]) / 1e3:.0f}k triangles mean |"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
