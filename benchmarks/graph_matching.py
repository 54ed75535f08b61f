"""Benchmark: 2D centreline graphs and cross-view matching against phantom ground truth.

For each phantom case (synchronized runs, so the matched-phase pair is exact),
the frame with the fullest opacification is taken from both runs; the
ground-truth label masks (vessel, catheter) go through
``vc.centreline_graph`` and ``vc.match_graphs``, and the result is compared
with the phantom's 3D truth tree projected into both views:

- truth landmarks: the ostium, every bifurcation (a child's first point) and
  every vessel end, projected into each view, visible where the vessel mask
  lies within 2 px plus half the vessel radius (the ostium lies under the
  catheter's tip, 3-4 px from the first vessel pixel); a detected landmark stands for
  the truth landmark it is associated with (one-to-one, within 3 px plus the
  vessel radius);
- precision: share of matched landmark pairs whose two landmarks stand for the
  same truth landmark; same-point precision: share of matched landmark pairs
  whose two landmarks are views of one 3D point of the truth centreline
  (within 3 px plus the vessel radius in each view), truth landmark or not
  (a junction where two vessels touch in 2D, the cut end of a loop); recall:
  share of the truth landmarks detected in both views that are matched to each
  other;
- correctly paired length: share of the truth centreline length (samples every
  0.5 mm, visible in both masks) whose projections lie on the two pieces of
  one branch pair (within 1 px plus the radius in each view);
- where the rest lies: the truth length visible in both masks that is not
  correctly paired, split by what each view has there (within 1 px plus the
  radius): *held in one view* (that view's stretch belongs to a pair, of
  another vessel or of this one run past its partner, the other view's is on
  the skeleton and free: two vessels overlapping in one view, as a rule),
  *held in both* (both views' stretches belong to pairs, not to one pair),
  *off the skeleton* (in one view or both), *free in both* (both views'
  skeletons run there and no pair holds either);
- topology: share of branch pairs between two correctly matched landmarks
  whose start is an ancestor of its end in the truth tree;
- roots: share of views whose graph root lies within 3 px plus the radius of
  the projected ostium;
- branch point offset: distance (px, median over both views) of each detected
  branch point from the true bifurcation it stands for, in px and in local
  vessel radii (thinning puts a junction where the vessels' pixels part, not
  where their centrelines meet);
- 3D off truth: every branch pair turned into a 3D curve by the geometric
  core (``vc.intersect_centrelines``, epipolar method; not timed), the share
  of that 3D length farther than 1.5 mm from the truth centreline: what a
  wrong pairing (two views agreeing along the epipolar lines) costs in 3D;
- time: ``centreline_graph`` on both views plus ``match_graphs``.

Run ``python benchmarks/graph_matching.py --cases 30`` (``--json`` for raw
numbers, ``--plot DIR`` for a picture per case).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

import vesselcad as vc
from vesselcad.phantom import LABELS, generate_case
from vesselcad.splines import resample_by_arclength

KINDS = ("lca", "rca", "cs")
#: A reconstructed branch point farther than this from the truth centreline is off truth (mm).
OFF_MM = 1.5


def truth_landmarks(tree: dict) -> tuple[np.ndarray, list[tuple[int, float]], list[str], np.ndarray]:
    """3D truth landmarks: (points, (vessel, s_mm) of each, kind, radius mm)."""
    pts, where, kind, rad = [], [], [], []
    for b in tree["branches"]:
        p = np.asarray(b["points"], float)
        r = np.asarray(b["radius"], float)
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
        if b["parent"] is None:
            pts.append(p[0])
            where.append((b["id"], 0.0))
            kind.append("end")
            rad.append(r[0])
        else:
            par = tree["branches"][b["parent"]]
            pts.append(p[0])
            where.append((b["parent"], float(b["parent_s_mm"])))
            kind.append("branch")
            pp = np.asarray(par["points"], float)
            ps = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pp, axis=0), axis=1))]
            rad.append(float(np.interp(float(b["parent_s_mm"]), ps, np.asarray(par["radius"], float))))
        pts.append(p[-1])
        where.append((b["id"], float(s[-1])))
        kind.append("end")
        rad.append(r[-1])
    return np.array(pts), where, kind, np.array(rad)


def dense_branches(tree: dict, step_mm: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each truth vessel's centreline resampled every ``step_mm``, with its radius (mm) there."""
    out = []
    for b in tree["branches"]:
        p = np.asarray(b["points"], float)
        if len(p) < 2:
            continue
        d = resample_by_arclength(p, step_mm)
        r = np.asarray(b["radius"], float)
        out.append((d, np.interp(np.linspace(0, 1, len(d)), np.linspace(0, 1, len(r)), r)))
    return out


def radius_px(view: vc.CArmView, points: np.ndarray, radius_mm: np.ndarray) -> np.ndarray:
    """Radius (mm, at ``points``) as it appears in ``view`` (px)."""
    return radius_mm * view.sid_mm / view.depth(points) / float(np.mean(view.pixel_spacing_mm))


def is_ancestor(tree: dict, t1: tuple[int, float], t2: tuple[int, float]) -> bool:
    """Whether truth position t1 lies on the path from the root to t2."""
    k, s = t2
    while k is not None:
        if k == t1[0] and s >= t1[1] - 1.0:
            return True
        b = tree["branches"][k]
        k, s = b["parent"], (b["parent_s_mm"] or 0.0)
    return False


def associate(det: np.ndarray, truth: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """One-to-one association of detected landmarks to truth landmarks (index or -1)."""
    out = np.full(len(det), -1)
    if len(det) == 0 or len(truth) == 0:
        return out
    d = np.linalg.norm(det[:, None] - truth[None], axis=-1)
    cost = np.where(d <= tol[None], d, 1e6)
    r, c = linear_sum_assignment(cost)
    ok = cost[r, c] < 1e6
    out[r[ok]] = c[ok]
    return out


def evaluate(seed: int, kind: str, plot_dir: str | None = None, continuation: bool = True,
             segmenter: vc.Segmenter | None = None, tta: bool = False) -> dict:
    case = generate_case(seed, kind, n_frames=10, synchronized=True)
    la, lb = case.run_a.labels, case.run_b.labels
    i = int(np.argmax((la == LABELS["vessel"]).sum(axis=(1, 2))))
    va, vb = case.run_a.view, case.run_b.view
    tree = case.run_a.trees[i]
    # The truth masks define what is visible and the truth length, whatever labels the graphs get.
    masks = [(la[i] == LABELS["vessel"], la[i]), (lb[i] == LABELS["vessel"], lb[i])]
    used = masks
    if segmenter is not None:
        lab = segmenter(np.stack([case.run_a.frames[i], case.run_b.frames[i]]), tta=tta)
        used = [(lab[0] == LABELS["vessel"], lab[0]), (lab[1] == LABELS["vessel"], lab[1])]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", vc.VesselcadWarning)
        ga = vc.centreline_graph(used[0][0], va, labels=used[0][1])
        gb = vc.centreline_graph(used[1][0], vb, labels=used[1][1])
    t1 = time.perf_counter()
    m = vc.match_graphs(va, ga, vb, gb, continuation=continuation)
    t2 = time.perf_counter()

    T3, where, tkind, trad = truth_landmarks(tree)
    res: dict = {"seed": seed, "anatomy": kind, "t_graph_s": t1 - t0, "t_match_s": t2 - t1,
                 "t_total_s": t2 - t0, "branches_a": len(ga.branches), "branches_b": len(gb.branches),
                 "crossings": len(ga.crossings) + len(gb.crossings), "tree": ga.is_tree() and gb.is_tree()}
    assoc = []
    roots_ok = 0
    for g, v, (mask, _) in ((ga, va, masks[0]), (gb, vb, masks[1])):
        tp = v.project(T3)
        r_px = radius_px(v, T3, trad)
        # Visible: vessel pixels within 2 px plus half the radius. The ostium lies under the
        # catheter's tip, 3-4 px from the first vessel pixel (radius 7-10 px); a landmark hidden
        # under a device or another class by more than half a vessel width is not visible.
        gap = ndimage.distance_transform_edt(~mask)
        ij = np.clip(np.round(tp).astype(int), 0, [v.cols - 1, v.rows - 1])
        visible = gap[ij[:, 1], ij[:, 0]] <= 2.0 + 0.5 * r_px
        a = associate(g.landmark_points, np.where(visible[:, None], tp, 1e9), 3.0 + r_px)
        assoc.append((a, visible))
        # where the detected branch points lie against the true bifurcations they stand for
        for k, lm in enumerate(g.landmarks):
            if lm.kind == "branch" and a[k] >= 0 and tkind[a[k]] == "branch":
                off = float(np.linalg.norm(lm.point_px - tp[a[k]]))
                res.setdefault("branch_offset_px", []).append(off)
                res.setdefault("branch_offset_radii", []).append(off / float(r_px[a[k]]))
        if g.root is not None:  # truth landmark 0 is the ostium
            roots_ok += bool(np.linalg.norm(g.landmarks[g.root].point_px - tp[0]) <= 3.0 + r_px[0])
    (aa, vis_a), (ab, vis_b) = assoc
    det_a = set(aa[aa >= 0].tolist())
    det_b = set(ab[ab >= 0].tolist())
    both = det_a & det_b
    correct = [lm for lm in m.landmark_pairs if aa[lm.a] >= 0 and aa[lm.a] == ab[lm.b]]
    res["roots_ok"] = roots_ok
    res["truth_landmarks"] = int(np.sum(vis_a & vis_b))
    res["detected_a"] = len(det_a)
    res["detected_b"] = len(det_b)
    res["matchable"] = len(both)
    res["matched"] = len(m.landmark_pairs)
    res["correct"] = len(correct)
    correct_set = {(lm.a, lm.b) for lm in correct}
    # Same-point precision: a matched pair whose two landmarks are views of one 3D point of
    # the truth centreline (within 3 px plus the vessel radius in each view), whether or not
    # that point is a truth landmark: a 2D junction where two vessels touch, the cut end of a
    # loop, or a junction centre more than a radius from the bifurcation are such points.
    dense = dense_branches(tree, 0.25)
    dp, dr = np.vstack([d for d, _ in dense]), np.concatenate([r for _, r in dense])
    near_pt = []
    ends = ([lm.a for lm in m.landmark_pairs], [lm.b for lm in m.landmark_pairs])
    for g, v, idx in ((ga, va, ends[0]), (gb, vb, ends[1])):
        q = v.project(dp)
        rp = radius_px(v, dp, dr)
        pts = g.landmark_points[idx] if idx else np.zeros((0, 2))
        near_pt.append(np.linalg.norm(pts[:, None] - q[None], axis=-1) <= 3.0 + rp[None])
    res["same_point"] = int(np.sum((near_pt[0] & near_pt[1]).any(axis=1))) if m.landmark_pairs else 0

    # Correctly paired length: truth samples every 0.5 mm, visible in both masks.
    tot = ok = 0.0
    pieces_a = [p.points_a_px for p in m.pairs]
    pieces_b = [p.points_b_px for p in m.pairs]
    # what each view has near a sample: the skeleton, a pair's piece
    near = []
    for g, pieces in ((ga, pieces_a), (gb, pieces_b)):
        skel = [b.points_px for b in g.branches]
        near.append((cKDTree(np.vstack(skel)) if skel else None,
                     cKDTree(np.vstack(pieces)) if pieces else None))
    rest = dict.fromkeys(("held_one", "held_both", "off_skeleton", "free"), 0.0)
    for dense, r in dense_branches(tree, 0.5):
        on = np.ones(len(dense), bool)
        near_pair = np.ones((len(m.pairs), len(dense)), bool)
        skel_ok, held = [], []
        for v, (mask, _), pieces, (t_skel, t_held) in ((va, masks[0], pieces_a, near[0]),
                                                       (vb, masks[1], pieces_b, near[1])):
            q = v.project(dense)
            rp = radius_px(v, dense, r)
            ij = np.clip(np.round(q).astype(int), 0, [v.cols - 1, v.rows - 1])
            on &= mask[ij[:, 1], ij[:, 0]]
            for k, piece in enumerate(pieces):
                d = np.min(np.linalg.norm(q[:, None] - piece[None], axis=-1), axis=1)
                near_pair[k] &= d <= 1.0 + rp
            skel_ok.append(t_skel.query(q)[0] <= 1.0 + rp if t_skel else np.zeros(len(q), bool))
            held.append(t_held.query(q)[0] <= 1.0 + rp if t_held else np.zeros(len(q), bool))
        paired = on & near_pair.any(axis=0) if len(m.pairs) else np.zeros(len(dense), bool)
        tot += on.sum() * 0.5
        ok += paired.sum() * 0.5
        miss = on & ~paired
        off = miss & ~(skel_ok[0] & skel_ok[1])
        miss &= ~off
        rest["off_skeleton"] += off.sum() * 0.5
        rest["held_one"] += (miss & (held[0] ^ held[1])).sum() * 0.5
        rest["held_both"] += (miss & held[0] & held[1]).sum() * 0.5
        rest["free"] += (miss & ~held[0] & ~held[1]).sum() * 0.5
    res["truth_length_mm"] = tot
    res["paired_length_mm"] = ok
    res["unpaired_mm"] = rest

    # Topology: branch pairs between two correct landmark pairs follow the truth tree's order.
    topo_n = topo_ok = 0
    for p in m.pairs:
        if None in p.start or None in p.end:
            continue
        if p.start in correct_set and p.end in correct_set:
            topo_n += 1
            topo_ok += is_ancestor(tree, where[aa[p.start[0]]], where[aa[p.end[0]]])
    res["topology_pairs"] = topo_n
    res["topology_ok"] = topo_ok
    # 3D: every pair through the geometric core, length off the truth centreline.
    truth3d = cKDTree(np.vstack([resample_by_arclength(np.asarray(b["points"], float), 0.25)
                                 for b in tree["branches"] if len(b["points"]) > 1]))
    on3 = off3 = 0.0
    for p in m.pairs:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", vc.VesselcadWarning)
                c3 = vc.intersect_centrelines(va, p.points_a_px, vb, p.points_b_px, method="epipolar")
        except vc.VesselcadError:
            continue
        d, _ = truth3d.query(c3.sample_every(0.5))
        off3 += float(np.sum(d > OFF_MM)) * 0.5
        on3 += float(np.sum(d <= OFF_MM)) * 0.5
    res["pairs_3d_on_mm"] = on3
    res["pairs_3d_off_mm"] = off3
    if plot_dir:
        vc.plot_graph_match(ga, gb, m, os.path.join(plot_dir, f"graph_match_{kind}_{seed}.png"),
                            images=(case.run_a.frames[i], case.run_b.frames[i]),
                            title=f"phantom {kind} seed {seed}, frame {i}")
    return res


def _median_of(rows: list[dict], key: str) -> float:
    """Median of the per-case lists ``row[key]`` pooled (NaN when none)."""
    vals = [v for r in rows for v in r.get(key, [])]
    return float(np.median(vals)) if vals else float("nan")


def summarize(rows: list[dict]) -> list[dict]:
    groups = {k: [r for r in rows if r["anatomy"] == k] for k in KINDS}
    groups["all"] = rows
    out = []
    for name, rs in groups.items():
        if not rs:
            continue
        matched = sum(r["matched"] for r in rs)
        correct = sum(r["correct"] for r in rs)
        matchable = sum(r["matchable"] for r in rs)
        truth = sum(r["truth_landmarks"] for r in rs)
        det = sum(r["detected_a"] + r["detected_b"] for r in rs)
        t = np.array([r["t_total_s"] for r in rs])
        out.append({
            "anatomy": name, "cases": len(rs),
            "precision": correct / max(matched, 1),
            "same_point": sum(r["same_point"] for r in rs) / max(matched, 1),
            "recall": correct / max(matchable, 1),
            "detected": det / max(2 * truth, 1),
            "paired_length": sum(r["paired_length_mm"] for r in rs)
            / max(sum(r["truth_length_mm"] for r in rs), 1e-9),
            "topology": sum(r["topology_ok"] for r in rs) / max(sum(r["topology_pairs"] for r in rs), 1),
            "trees": sum(r["tree"] for r in rs) / len(rs),
            "roots": sum(r.get("roots_ok", 0) for r in rs) / (2 * len(rs)),
            "branch_offset_px": _median_of(rs, "branch_offset_px"),
            "branch_offset_radii": _median_of(rs, "branch_offset_radii"),
            "off_3d": sum(r["pairs_3d_off_mm"] for r in rs)
            / max(sum(r["pairs_3d_off_mm"] + r["pairs_3d_on_mm"] for r in rs), 1e-9),
            **{f"rest_{k}": sum(r["unpaired_mm"][k] for r in rs)
               / max(sum(r["truth_length_mm"] for r in rs), 1e-9) for k in rs[0]["unpaired_mm"]},
            "t_mean_s": float(t.mean()), "t_p95_s": float(np.percentile(t, 95)),
            "t_graph_s": float(np.mean([r["t_graph_s"] for r in rs])),
            "t_match_s": float(np.mean([r["t_match_s"] for r in rs])),
        })
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=30, help="number of phantom cases (anatomies rotate)")
    ap.add_argument("--seed", type=int, default=1000, help="first seed")
    ap.add_argument("--json", help="write per-case numbers here")
    ap.add_argument("--plot", help="directory for one PNG per case")
    ap.add_argument("--no-continuation", action="store_true",
                    help="landmark-anchored pairs only (match_graphs(..., continuation=False))")
    ap.add_argument("--labels", choices=("truth", "model"), default="truth",
                    help="graphs from the phantom's label masks (default) or from the segmentation model's "
                         "labels of the same frames (truth still defines what is visible)")
    ap.add_argument("--model", default=None, help="with --labels model: ONNX file or 'int8' (default: the "
                    "bundled fp32 model)")
    ap.add_argument("--tta", action="store_true", help="with --labels model: mirror test-time augmentation")
    args = ap.parse_args(argv)
    segmenter = vc.Segmenter(args.model) if args.labels == "model" else None
    if args.plot:
        os.makedirs(args.plot, exist_ok=True)
    # Warm-up (imports, first-call costs) outside the timing.
    evaluate(args.seed + 10_000, "lca")
    rows = []
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None
    it = range(args.cases)
    for k in (tqdm(it, desc="cases", file=sys.stderr) if tqdm else it):
        rows.append(evaluate(args.seed + k, KINDS[k % 3], args.plot, not args.no_continuation,
                             segmenter, args.tta))
    summ = summarize(rows)
    print("| anatomy | cases | precision | same-point precision | recall | detected | paired length "
          "| topology | trees | roots | branch point offset px (radii) | 3D off truth | s/case (mean, p95) "
          "| graph s | match s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in summ:
        print(f"| {s['anatomy']} | {s['cases']} | {s['precision']:.3f} | {s['same_point']:.3f} "
              f"| {s['recall']:.3f} "
              f"| {s['detected']:.3f} "
              f"| {100 * s['paired_length']:.1f}% | {s['topology']:.3f} | {100 * s['trees']:.0f}% "
              f"| {100 * s['roots']:.0f}% "
              f"| {s['branch_offset_px']:.2f} ({s['branch_offset_radii']:.2f}) "
              f"| {100 * s['off_3d']:.1f}% "
              f"| {s['t_mean_s']:.3f}, {s['t_p95_s']:.3f} | {s['t_graph_s']:.3f} | {s['t_match_s']:.3f} |")
    print()
    print("Where the truth length both masks show lies when it is not correctly paired (shares of it):")
    print()
    print("| anatomy | paired | held in one view, free in the other | held in both | off the skeleton "
          "| free in both |")
    print("|---|---|---|---|---|---|")
    for s in summ:
        print(f"| {s['anatomy']} | {100 * s['paired_length']:.1f}% | {100 * s['rest_held_one']:.1f}% "
              f"| {100 * s['rest_held_both']:.1f}% | {100 * s['rest_off_skeleton']:.1f}% "
              f"| {100 * s['rest_free']:.1f}% |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "summary": summ}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
