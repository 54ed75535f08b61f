"""Benchmark: vessel-tree solids from phantom ground-truth trees (issue: vessel solids).

For each phantom tree (frame 0 of run A's ground truth) this builds
``VesselTree.solid()`` and measures

- validity: ``BRepCheck_Analyzer`` + one solid + no free edge (B-rep), and the
  STL's ``is_watertight`` and Euler characteristic (trimesh);
- volume error of the B-rep against an independent reference of the *same tubes*
  (the spines and radius laws the pipes were swept along): each tube meshed
  analytically (area-preserving 128-gons every 0.2 mm) and all of them united
  with manifold3d's mesh boolean;
- Hausdorff distance between the B-rep surface and the analytic tube union:
  B-rep -> analytic from the nodes of a 0.01 mm tessellation (nodes lie on the
  exact surface) against the tubes' signed distance; analytic -> B-rep from
  points on the union's boundary to that tessellation (rtree), or, where that
  is above the tessellation's 0.01 mm (its chords stray on tight bends), the
  exact distance to the B-rep faces (``VesselSolid.distance``);
- deviation from the raw ground-truth tubes (the input polylines and radii),
  which adds the centreline rebuild (0.05 mm) and the rounded merges;
- the shortest B-rep edge of the solid (a mesher must resolve it: wall seams placed
  clear of junctions keep it long, docs/solids.md);
- seconds per tree (``tree.solid()``, OCCT's libraries loaded before the first),
  STEP and STL sizes, STL volume error.

Usage::

    pip install ".[bench]"
    python benchmarks/solids.py --trees 30 [--json out.json] [--render docs/img]
    python benchmarks/solids.py --trees 12 --seed 3100 --twigs 30   # trees of ~20 branches
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import vesselcad as vc  # noqa: E402
from vesselcad.phantom import generate_case  # noqa: E402

ANATOMIES = ("lca", "rca", "cs")
FINE_TOL_MM = 0.01  # tessellation tolerance of the distance measures


# ----------------------------------------------------------- analytic tubes
class Tube:
    """A capped tube given by dense centreline samples, unit tangents and radii."""

    def __init__(self, centre: np.ndarray, radius: np.ndarray, caps: tuple[bool, bool] = (True, True)):
        self.c = np.asarray(centre, float)
        self.r = np.asarray(radius, float)
        self.caps = caps  # whether each end is an open end of the vessel (not a cut)
        d = np.gradient(self.c, axis=0)
        self.t = d / np.linalg.norm(d, axis=1)[:, None]
        self.tree = cKDTree(self.c)
        self.reach = float(self.r.max()) + 1.0

    @classmethod
    def from_spec(cls, spec: dict, step: float = 0.02) -> Tube:
        spine, law = spec["spine"], spec["radius"]
        a, b = float(spine.t[3]), float(spine.t[-4])
        s = np.linspace(a, b, max(int((b - a) / step), 2) + 1)
        return cls(spine(s), np.ravel(law(s)), (True, spec.get("end") != "dome"))  # a dome is no end disc

    @classmethod
    def from_polyline(cls, points: np.ndarray, radius: np.ndarray, step: float = 0.02) -> Tube:
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        s = np.r_[0, np.cumsum(seg)]
        u = np.linspace(0, s[-1], max(int(s[-1] / step), 2) + 1)
        return cls(np.stack([np.interp(u, s, points[:, k]) for k in range(3)], 1), np.interp(u, s, radius))

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (negative inside) of points to the capped tube; +inf far away."""
        out = np.full(len(p), np.inf)
        dist, j = self.tree.query(p, distance_upper_bound=self.reach + 0.5)
        near = np.isfinite(dist)
        if not near.any():
            return out
        q, j = p[near], j[near]
        best_d = np.full(len(q), np.inf)
        best_r = np.zeros(len(q))
        n = len(self.c)
        for lo in (np.maximum(j - 1, 0), j):  # the two segments around the nearest sample
            hi = np.minimum(lo + 1, n - 1)
            a, b = self.c[lo], self.c[hi]
            ab = b - a
            den = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
            w = np.clip(np.einsum("ij,ij->i", q - a, ab) / den, 0, 1)
            foot = a + w[:, None] * ab
            d = np.linalg.norm(q - foot, axis=1)
            r = self.r[lo] + w * (self.r[hi] - self.r[lo])
            better = d - r < best_d - best_r
            best_d = np.where(better, d, best_d)
            best_r = np.where(better, r, best_r)
        side = best_d - best_r
        # An end plane bounds the tube only where the nearest axis point is that end:
        # a tube that turns by more than 90 degrees comes back behind its own start
        # plane a few millimetres along (the lead-ins of daughters at a parent's end).
        start = np.where(j <= 1, -np.einsum("ij,j->i", q - self.c[0], self.t[0]), -np.inf)
        end = np.where(j >= n - 2, np.einsum("ij,j->i", q - self.c[-1], self.t[-1]), -np.inf)
        out[near] = np.maximum(side, np.maximum(start, end))
        return out

    def boundary_samples(self, step: float = 0.25, n_angle: int = 48) -> np.ndarray:
        """Points on the tube's wall and caps."""
        k = max(int(step / 0.02), 1)
        idx = np.unique(np.r_[np.arange(0, len(self.c), k), len(self.c) - 1])
        c, t, r = self.c[idx], self.t[idx], self.r[idx]
        ref = np.eye(3)[int(np.argmin(np.abs(t[0])))]
        n = np.cross(t, ref)
        n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
        b = np.cross(t, n)
        ang = np.linspace(0, 2 * np.pi, n_angle, endpoint=False)
        wall = (c[:, None] + r[:, None, None] * (np.cos(ang)[None, :, None] * n[:, None]
                                                  + np.sin(ang)[None, :, None] * b[:, None])).reshape(-1, 3)
        caps = []
        for idx, open_end in zip((0, -1), self.caps, strict=True):
            if not open_end:
                continue
            for frac in np.linspace(0, 0.95, 6):
                ring = np.cos(ang)[:, None] * n[idx] + np.sin(ang)[:, None] * b[idx]
                caps.append(c[idx] + frac * r[idx] * ring)
        return np.vstack([wall, *caps])

    def mesh(self, step: float = 0.2, n_seg: int = 128) -> tuple[np.ndarray, np.ndarray]:
        """Closed triangle mesh: area-preserving n-gons every ``step`` mm, parallel-transported frame."""
        k = max(int(step / 0.02), 1)
        idx = np.unique(np.r_[np.arange(0, len(self.c), k), len(self.c) - 1])
        c, t, r = self.c[idx], self.t[idx], self.r[idx]
        n = np.empty_like(t)
        ref = np.eye(3)[int(np.argmin(np.abs(t[0])))]
        n[0] = np.cross(t[0], ref)
        n[0] /= np.linalg.norm(n[0])
        for i in range(1, len(t)):  # parallel transport by projection (steps of 0.2 mm)
            v = n[i - 1] - (n[i - 1] @ t[i]) * t[i]
            n[i] = v / np.linalg.norm(v)
        b = np.cross(t, n)
        scale = np.sqrt(2 * np.pi / (n_seg * np.sin(2 * np.pi / n_seg)))  # polygon area = pi r^2
        ang = np.linspace(0, 2 * np.pi, n_seg, endpoint=False)
        ring = c[:, None] + (scale * r)[:, None, None] * (np.cos(ang)[None, :, None] * n[:, None]
                                                          + np.sin(ang)[None, :, None] * b[:, None])
        m = len(c)
        verts = np.vstack([ring.reshape(-1, 3), c[0], c[-1]])
        i = np.arange(m - 1)[:, None] * n_seg
        a0 = i + np.arange(n_seg)[None]
        a1 = i + (np.arange(n_seg)[None] + 1) % n_seg
        faces = [np.stack([a0, a1, a1 + n_seg], -1).reshape(-1, 3), np.stack([a0, a1 + n_seg, a0 + n_seg], -1)
                 .reshape(-1, 3)]
        s0, s1 = m * n_seg, m * n_seg + 1
        j = np.arange(n_seg)
        faces.append(np.stack([np.full(n_seg, s0), (j + 1) % n_seg, j], -1))
        last = (m - 1) * n_seg
        faces.append(np.stack([np.full(n_seg, s1), last + j, last + (j + 1) % n_seg], -1))
        return verts, np.vstack(faces)


class Dome:
    """The hemisphere closing a vessel whose children start at its end (``spec['end'] == 'dome'``)."""

    def __init__(self, centre: np.ndarray, axis: np.ndarray, radius: float):
        self.c = np.asarray(centre, float)
        self.t = np.asarray(axis, float) / np.linalg.norm(axis)
        self.r = float(radius)
        ref = np.eye(3)[int(np.argmin(np.abs(self.t)))]
        self.n = np.cross(self.t, ref) / np.linalg.norm(np.cross(self.t, ref))
        self.b = np.cross(self.t, self.n)

    @classmethod
    def from_spec(cls, spec: dict) -> Dome:
        spine, law = spec["spine"], spec["radius"]
        e = float(spine.t[-4])
        return cls(spine(e), spine.derivative()(e), float(np.ravel(law(e))[0]))

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (negative inside) to the half ball; exact on and outside its round side."""
        q = p - self.c
        return np.maximum(np.linalg.norm(q, axis=1) - self.r, -(q @ self.t))

    def _rings(self, n_polar: int, n_angle: int) -> np.ndarray:
        theta = np.linspace(0.5 * np.pi, 0.0, n_polar + 1)[:-1]  # from the rim towards the pole
        ang = np.linspace(0, 2 * np.pi, n_angle, endpoint=False)
        radial = np.cos(ang)[:, None] * self.n + np.sin(ang)[:, None] * self.b
        return (self.c + self.r * (np.cos(theta)[:, None, None] * self.t
                                   + np.sin(theta)[:, None, None] * radial[None]))

    def boundary_samples(self, step: float = 0.25, n_angle: int = 48) -> np.ndarray:
        """Points on the round side."""
        n_polar = max(int(0.5 * np.pi * self.r / step), 4)
        return np.vstack([self._rings(n_polar, n_angle).reshape(-1, 3), self.c + self.r * self.t])

    def mesh(self, n_polar: int = 32, n_seg: int = 128) -> tuple[np.ndarray, np.ndarray]:
        """Closed triangle mesh of the half ball (rings of n-gons, pole, flat disc)."""
        rings = self._rings(n_polar, n_seg)
        m = len(rings)
        verts = np.vstack([rings.reshape(-1, 3), self.c + self.r * self.t, self.c])
        pole, centre = m * n_seg, m * n_seg + 1
        j = np.arange(n_seg)
        faces = []
        for k in range(m - 1):
            a0, a1 = k * n_seg + j, k * n_seg + (j + 1) % n_seg
            faces += [np.c_[a0, a1, a1 + n_seg], np.c_[a0, a1 + n_seg, a0 + n_seg]]
        last = (m - 1) * n_seg
        faces.append(np.c_[last + j, last + (j + 1) % n_seg, np.full(n_seg, pole)])
        faces.append(np.c_[np.full(n_seg, centre), (j + 1) % n_seg, j])
        f = np.vstack(faces)
        v = verts[f]
        normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        if np.einsum("ij,ij->i", normal, v.mean(axis=1) - self.c).sum() < 0:
            f = f[:, ::-1]  # outward
        return verts, f


def without_self_approach(tube: Tube) -> list[Tube]:
    """The tube as pieces that do not come near themselves (found here, independently of
    the code under test): where the axis comes back within the two radii + 1 mm at points
    more than half a turn apart along it, cut it into pieces shorter than that (0.1 mm
    overlap). Keeps the reference mesh free of self-intersections, and ``Tube.sdf`` (which
    looks at the segments around the nearest axis sample only) exact near such places."""
    step = 0.02
    k = max(int(0.5 / step), 1)
    c, r = tube.c[::k], tube.r[::k]
    pairs = cKDTree(c).query_pairs(2.0 * float(r.max()) + 1.0, output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        bad = ((np.linalg.norm(c[i] - c[j], axis=1) < r[i] + r[j] + 1.0)
               & (np.abs(i - j) * k * step > np.pi * (r[i] + r[j])))
        pairs = pairs[bad]
    if not len(pairs):
        return [tube]
    piece = int(np.pi * 2.0 * float(tube.r.min()) / step)
    bounds = list(range(0, len(tube.c) - 1, piece)) + [len(tube.c) - 1]
    pad = 5
    return [Tube(tube.c[max(a - pad, 0):b + 1 + pad], tube.r[max(a - pad, 0):b + 1 + pad],
                 (a == 0, b == len(tube.c) - 1)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def union_sdf(tubes: list[Tube | Dome], p: np.ndarray) -> np.ndarray:
    return np.min(np.stack([t.sdf(p) for t in tubes]), axis=0)


def solid_tubes(solid: vc.VesselSolid) -> list[Tube | Dome]:
    """The analytic tubes (split where a pipe comes back near itself) and domes of the
    branches a solid holds, from the spines and radius laws they were swept along."""
    kept = [s for s in solid.specs if s["id"] not in solid.failed]
    tubes: list[Tube | Dome] = [p for s in kept for p in without_self_approach(Tube.from_spec(s))]
    return tubes + [Dome.from_spec(s) for s in kept if s.get("end") == "dome"]


def reference_volume(tubes: list[Tube | Dome]) -> float:
    import manifold3d as mf

    parts = []
    for t in tubes:
        v, f = t.mesh()
        m = mf.Manifold(mf.Mesh(vert_properties=v.astype(np.float32), tri_verts=f.astype(np.uint32)))
        if m.status() != mf.Error.NoError:
            raise RuntimeError(f"reference tube mesh is not manifold: {m.status()}")
        parts.append(m)
    return float(mf.Manifold.batch_boolean(parts, mf.OpType.Add).volume())


# ----------------------------------------------------------- one tree
def measure(anatomy: str, seed: int, render_dir: Path | None = None, twigs: int | None = None) -> dict:
    import trimesh

    case = generate_case(seed, anatomy, n_frames=1, rows=128, cols=128, twigs=twigs)
    truth = case.run_a.trees[0]
    tree = vc.VesselTree.from_truth(case)
    t0 = time.perf_counter()
    solid = tree.solid()
    seconds = time.perf_counter() - t0
    chk = solid.check()
    tubes = solid_tubes(solid)
    # B-rep -> analytic: tessellation nodes lie on the exact surface.
    fine = solid.to_trimesh(tolerance=FINE_TOL_MM, angular_deflection=0.15)
    d_fwd = np.abs(union_sdf(tubes, np.asarray(fine.vertices)))
    # analytic -> B-rep: points on the union's boundary.
    samples = []
    for i, t in enumerate(tubes):
        pts = t.boundary_samples()
        others = [u for j, u in enumerate(tubes) if j != i]
        keep = union_sdf(others, pts) >= 0 if others else np.ones(len(pts), bool)
        samples.append(pts[keep])
    pts = np.vstack(samples)
    rng = np.random.default_rng(seed)
    pts = pts[rng.choice(len(pts), min(len(pts), 15000), replace=False)]
    _, d_back, _ = trimesh.proximity.closest_point(fine, pts)
    # The tessellation's chords can stray from the surface by more than its
    # tolerance on tight bends: where it puts a point farther than that, measure
    # the exact distance to the B-rep instead.
    far = d_back > FINE_TOL_MM
    d_back[far] = solid.distance(pts[far])
    # raw ground-truth tubes (input polylines with their radii)
    raw = [Tube.from_polyline(np.asarray(b["points"]), np.asarray(b["radius"])) for b in truth["branches"]]
    d_raw = np.abs(union_sdf(raw, np.asarray(fine.vertices)))
    ref = reference_volume(tubes)
    with tempfile.TemporaryDirectory() as tmp:
        step, stl = Path(tmp) / "tree.step", Path(tmp) / "tree.stl"
        solid.export_step(step)
        solid.export_stl(stl)
        mesh = trimesh.load(stl)
        step_kb, stl_kb = step.stat().st_size / 1024, stl.stat().st_size / 1024
    if render_dir is not None:
        from vesselcad.render import render_mesh

        render_dir.mkdir(parents=True, exist_ok=True)
        picture = solid.to_trimesh(tolerance=0.05, angular_deflection=0.5)  # coarse: no decimation
        render_mesh(picture, render_dir / f"solid_{anatomy}_{seed}.png",
                    title=f"phantom {anatomy.upper()} seed {seed}: {len(solid.branch_ids)} pipes "
                          f"({len(truth['branches'])} branches), one solid, {chk['volume_mm3']:.0f} mm³")
    vol = chk["volume_mm3"]
    return {
        "anatomy": anatomy, "seed": seed, "branches": len(truth["branches"]), "pipes": len(solid.branch_ids),
        "failed": len(solid.failed), "valid": chk["valid"], "watertight": chk["watertight"],
        "stl_watertight": bool(mesh.is_watertight), "euler": int(mesh.euler_number),
        "volume_mm3": vol, "reference_mm3": ref, "volume_err_pct": 100 * (vol - ref) / ref,
        "stl_volume_err_pct": 100 * (mesh.volume - vol) / vol,
        "hausdorff_mm": float(max(d_fwd.max(), d_back.max())), "brep_to_tube_mm": float(d_fwd.max()),
        "tube_to_brep_mm": float(d_back.max()),
        "shortest_edge_mm": chk["shortest_edge_mm"],
        "raw_truth_max_mm": float(d_raw.max()), "raw_truth_p99_mm": float(np.percentile(d_raw, 99)),
        "seconds": seconds, "timings": {k: round(v, 3) for k, v in solid.timings_s.items()},
        "step_kb": step_kb, "stl_kb": stl_kb, "warnings": solid.warnings,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trees", type=int, default=30)
    ap.add_argument("--seed", type=int, default=3000)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--render", type=Path, help="write PNGs of the first two trees here")
    ap.add_argument("--twigs", type=int, help="small side branches per phantom tree (default: the phantom's "
                                              "3-8; 30 gives trees of ~16-26 branches)")
    args = ap.parse_args(argv)
    from tqdm.auto import tqdm

    import vesselcad.kernel  # noqa: F401  load OCCT (~0.7 s) before the first tree is timed

    jobs = [(ANATOMIES[i % 3], args.seed + i) for i in range(args.trees)]
    rows = []
    for k, (anat, seed) in enumerate(tqdm(jobs, desc="trees", unit="tree")):
        try:
            rows.append(measure(anat, seed, args.render if (args.render and k < 2) else None, args.twigs))
        except Exception as exc:  # one bad tree never hides the others
            rows.append({"anatomy": anat, "seed": seed, "error": f"{type(exc).__name__}: {exc}"})
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}, "
          f"numpy {np.__version__}\n")
    print("| anatomy | seed | branches | pipes | failed | valid solid | STL watertight | Euler | volume mm³ "
          "| vol. err vs ref % | STL vol. err % | Hausdorff mm | raw truth max (p99) mm | shortest edge mm "
          "| s | STEP KB | STL KB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['anatomy']} | {r['seed']} | error: {r['error']} |" + " |" * 14)
            continue
        print(f"| {r['anatomy']} | {r['seed']} | {r['branches']} | {r['pipes']} | {r['failed']} | "
              f"{'yes' if r['watertight'] else 'NO'} | {'yes' if r['stl_watertight'] else 'NO'} | "
              f"{r['euler']} | "
              f"{r['volume_mm3']:.1f} | {r['volume_err_pct']:+.4f} | {r['stl_volume_err_pct']:+.2f} | "
              f"{r['hausdorff_mm']:.4f} | {r['raw_truth_max_mm']:.3f} ({r['raw_truth_p99_mm']:.3f}) | "
              f"{r['shortest_edge_mm']:.3f} | {r['seconds']:.1f} | {r['step_kb']:.0f} | {r['stl_kb']:.0f} |")
    ok = [r for r in rows if "error" not in r]
    good = [r for r in ok if r["watertight"] and r["stl_watertight"] and r["failed"] == 0]
    if ok:
        ve = np.abs([r["volume_err_pct"] for r in ok])
        hd = np.array([r["hausdorff_mm"] for r in ok])
        sec = np.array([r["seconds"] for r in ok])
        nb = np.array([r["pipes"] for r in ok])
        per20 = sec / nb * 20
        print()
        print("| measure | goal | result |")
        print("|---|---|---|")
        print(f"| trees giving one valid watertight solid, no branch left out | 100% | "
              f"{len(good)}/{len(rows)} ({100 * len(good) / len(rows):.0f}%) |")
        print(f"| Euler characteristic 2 (STL) | – | {sum(r['euler'] == 2 for r in ok)}/{len(ok)} |")
        print(f"| volume error vs mesh-boolean reference, abs | <= 1% | mean {ve.mean():.4f}%, "
              f"max {ve.max():.4f}% |")
        print(f"| Hausdorff B-rep <-> analytic tubes | <= 0.05 mm | mean {hd.mean():.4f}, "
              f"max {hd.max():.4f} mm |")
        nbr = np.array([r["branches"] for r in ok])
        big = (nbr >= 18) & (nbr <= 22)
        near20 = (f"; trees of 18-22 branches: {sec[big].mean():.1f} s mean ({big.sum()} trees)"
                  if big.any() else "")
        print(f"| seconds per tree | <= 3 s for 20 branches | mean {sec.mean():.1f} s "
              f"({nbr.mean():.1f} branches, {nb.mean():.1f} pipes), max {sec.max():.1f} s; "
              f"scaled to 20 pipes: mean {per20.mean():.1f} s{near20} |")
        short = np.array([r["shortest_edge_mm"] for r in ok])
        print(f"| shortest B-rep edge (the mesher resolves it) | – | min {short.min():.3f} mm, median "
              f"{np.median(short):.3f} mm; {np.count_nonzero(short < 0.1)}/{len(ok)} trees below 0.1 mm |")
        print(f"| STEP / STL size | – | mean {np.mean([r['step_kb'] for r in ok]):.0f} KB / "
              f"{np.mean([r['stl_kb'] for r in ok]):.0f} KB |")
        print(f"| deviation from the raw truth tubes (rebuild + merges) | – | max "
              f"{max(r['raw_truth_max_mm'] for r in ok):.3f} mm, p99 mean "
              f"{np.mean([r['raw_truth_p99_mm'] for r in ok]):.3f} mm |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
