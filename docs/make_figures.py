"""Regenerate the pictures in docs/img: ``python docs/make_figures.py``.

- geometry.png: both views' source, detector and isocentre in LPS, with axes.
- phantom_preview.png: the contact sheet of ``vesselcad phantom --preview``.
- phantom_vs_real.png: phantom frames next to real angiograms (CIMAT, ARCADE).
- centreline_graph_real.png: centreline graphs of real manual vessel masks (CIMAT).
- cfd_crease.png: prism layers at a 10-degree branch, crease kept and rounded (``--crease``
  makes only this one).
- surface_prior.png: the heart's surface of the matching, phantom lca 1015 (``--surface`` makes
  only this one).
- seg_real_1024.png: the bundled model's labels of a real 1024² 10-bit angiogram (NEMA WG04 XA1)
  on the frame as stored and on the frame reduced to 512² as ``reconstruct`` does (``--large``
  makes only this one).
- junction_kept_inside.png: the junction of branches 16 and 9 of tests/data/mesh_partial_rca_2111.json
  (cs 2111), meshed as fused before and after children that would swallow their parent's end were
  kept inside it (``--junction`` makes only this one).
- pixel_fit_real.png: a branch of a real expert mask (CIMAT 9), its skeleton pixels and the 2D fit
  smoothed by the noise the fourth differences estimate and by at least the pixel quantization
  (``--fit`` makes only this one).
- report_html.png: ``vesselcad demo``'s report.html as headless Chromium shows it (offline);
  only with ``--report`` (needs Chromium and playwright, as tests/test_report_browser.py).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import vesselcad as vc  # noqa: E402
from vesselcad.phantom import generate_case, write_case  # noqa: E402
from vesselcad.phantom.preview import overlay  # noqa: E402

HERE = Path(__file__).resolve().parent
REAL = HERE.parents[1] / "shared" / "data" / "xca-real"
DICOM = HERE.parents[1] / "shared" / "data" / "dicom"


def _detector_corners(view: vc.CArmView) -> np.ndarray:
    c = [[0, 0], [view.cols - 1, 0], [view.cols - 1, view.rows - 1], [0, view.rows - 1], [0, 0]]
    return view.pixel_to_detector(np.asarray(c, float))


def geometry_figure(path: Path) -> None:
    views = {
        "A: RAO 30 CRA 20": vc.CArmView(primary_deg=-30, secondary_deg=20, sid_mm=1100, sod_mm=750,
                                        pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512),
        "B: LAO 45 CAU 20": vc.CArmView(primary_deg=45, secondary_deg=-20, sid_mm=1100, sod_mm=750,
                                        pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512),
    }
    fig = plt.figure(figsize=(10, 5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for (name, v), colour in zip(views.items(), ("tab:red", "tab:blue"), strict=True):
        s, c = v.source, v.detector_centre
        det = _detector_corners(v)
        ax.plot(*det.T, color=colour)
        ax.plot(*np.c_[s, c], color=colour, ls="--", lw=0.8)
        ax.scatter(*s, color=colour, marker="*", s=80, label=f"{name}: source")
        # Column (u) and row (v) axes from the first pixel.
        o = det[0]
        ax.quiver(*o, *(80 * v.col_axis), color=colour, lw=1.5)
        ax.quiver(*o, *(80 * v.row_axis), color=colour, lw=1.5, linestyle=":")
        ax.text(*(o + 90 * v.col_axis), "col", color=colour, fontsize=7)
        ax.text(*(o + 90 * v.row_axis), "row", color=colour, fontsize=7)
    ax.scatter(0, 0, 0, color="k", s=20, label="isocentre")
    for vec, lab in ((np.eye(3)[0], "L (x)"), (np.eye(3)[1], "P (y)"), (np.eye(3)[2], "S (z)")):
        ax.quiver(0, 0, 0, *(150 * vec), color="k", lw=1)
        ax.text(*(165 * vec), lab, fontsize=8)
    ax.set_xlabel("x (mm, patient left)")
    ax.set_ylabel("y (mm, posterior)")
    ax.set_zlabel("z (mm, head)")
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=18, azim=-60)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("C-arm views in LPS (source *, detector frame)", fontsize=9)

    ax2 = fig.add_subplot(1, 2, 2)
    pa = vc.CArmView(primary_deg=0, secondary_deg=0, sid_mm=1100, sod_mm=750,
                     pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512)
    marks = {"left (+x)": [40, 0, 0], "right (-x)": [-40, 0, 0], "head (+z)": [0, 0, 40],
             "feet (-z)": [0, 0, -40], "isocentre": [0, 0, 0]}
    for name, p in marks.items():
        col, row = pa.project(np.asarray(p, float))
        ax2.plot(col, row, "o")
        ax2.annotate(name, (col, row), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax2.set_xlim(0, 511)
    ax2.set_ylim(511, 0)
    ax2.set_aspect("equal")
    ax2.set_xlabel("column (px)")
    ax2.set_ylabel("row (px)")
    ax2.set_title("PA view (0, 0): patient's left on the image right, head up", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def phantom_vs_real(path: Path) -> None:
    real_c = [cv2.imread(str(REAL / "train" / f"{k}.png"), 0) for k in (5, 21)]
    real_a = [cv2.imread(str(REAL / "unlabelled" / f"arcade_{k}.png"), 0) for k in (1, 11)]
    cases = [generate_case(s, kind, n_frames=12) for s, kind in ((1, "lca"), (2, "cs"), (3, "rca"))]
    tiles = [("phantom LCA", cases[0].run_a), ("phantom CS", cases[1].run_b), ("phantom RCA", cases[2].run_a)]
    fig, axes = plt.subplots(2, 4, figsize=(13, 6.8))
    for ax, (name, rr) in zip(axes[0, :3], tiles, strict=True):
        i = int(np.argmax((rr.labels == 1).sum(axis=(1, 2))))
        ax.imshow(rr.frames[i], cmap="gray", vmin=0, vmax=255)
        ax.set_title(f"{name} (512², frame {i})", fontsize=9)
    rr = tiles[0][1]
    i = int(np.argmax((rr.labels == 1).sum(axis=(1, 2))))
    axes[0, 3].imshow(overlay(rr.frames[i], rr.labels[i]))
    axes[0, 3].set_title("phantom LCA with labels", fontsize=9)
    for ax, img, name in zip(axes[1], real_a + real_c, ["real ARCADE 512²", "real ARCADE 512²",
                                                         "real CIMAT 300²", "real CIMAT 300²"], strict=True):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        ax.set_title(name, fontsize=9)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def centreline_graph_real(path: Path) -> None:
    """Centreline graphs of two real expert vessel masks (CIMAT 300x300 angiograms)."""
    view = vc.CArmView(primary_deg=0.0, secondary_deg=0.0, sid_mm=1000.0, sod_mm=750.0,
                       pixel_spacing_mm=(0.3, 0.3), rows=300, cols=300)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6.2))
    for ax, k in zip(axes, (17, 9), strict=True):
        img = cv2.imread(str(REAL / "train" / f"{k}.png"), 0)
        mask = cv2.imread(str(REAL / "train" / f"{k}_gt.png"), 0) > 127
        g = vc.centreline_graph(mask, view)
        ax.imshow(img, cmap="gray")
        for b in g.branches:
            ax.plot(b.points_px[:, 0], b.points_px[:, 1], "-", lw=1.6)
        for lm in g.landmarks:
            ax.plot(*lm.point_px, "o" if lm.kind == "end" else "s", ms=6,
                    mfc="cyan" if lm.kind == "end" else "magenta", mec="white")
        for c in g.crossings:
            ax.plot(*c.point_px, "x", color="orange", ms=9, mew=2)
        ax.plot(*g.landmarks[g.root].point_px, "*", color="red", ms=14)
        ax.set_title(f"CIMAT {k}: {len(g.branches)} branches, {len(g.branch_points)} branch points, "
                     f"{len(g.end_points)} ends, {len(g.crossings)} crossings", fontsize=9)
        ax.set_axis_off()
    fig.suptitle("vc.centreline_graph on real expert masks: branches coloured, ends cyan, branch points "
                 "magenta, crossings orange, root red", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def pixel_fit_figure(path: Path) -> None:
    """A real skeleton's 2D fit, with and without the pixel-quantization floor (docs/centreline3d.md)."""
    from vesselcad.splines import MIN_NOISE_PX, PIXEL_NOISE_PX, fit_curve_2d

    view = vc.CArmView(primary_deg=0.0, secondary_deg=0.0, sid_mm=1000.0, sod_mm=750.0,
                       pixel_spacing_mm=(0.3, 0.3), rows=300, cols=300)
    mask = cv2.imread(str(REAL / "train" / "9_gt.png"), 0) > 127
    b = max(vc.centreline_graph(mask, view).branches, key=lambda b: b.length_px)
    pts = b.points_px
    c0, r0 = pts[len(pts) // 2]
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    titles = ("noise as estimated (4th differences)", "at least 1/sqrt(12) px")
    for ax, floor, title in zip(axes, (MIN_NOISE_PX, PIXEL_NOISE_PX), titles, strict=True):
        spline, sigma = fit_curve_2d(pts, min_noise_px=floor)
        v = spline(np.linspace(spline.t[3], spline.t[-4], 4000))
        ax.imshow(mask, cmap="gray", vmin=0, vmax=2)
        ax.plot(pts[:, 0], pts[:, 1], "s", ms=5, mfc="none", mec="tab:orange", label="skeleton pixels")
        ax.plot(v[:, 0], v[:, 1], "-", color="tab:red", lw=1.5,
                label=f"fit: sigma {sigma:.3f} px, {len(spline.t) - 4} control points")
        ax.set_xlim(c0 - 20, c0 + 20)
        ax.set_ylim(r0 + 20, r0 - 20)
        ax.set_title(f"CIMAT 9, branch {b.index}: {title}", fontsize=10)
        ax.legend(loc="lower right", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def large_frame_figure(path: Path) -> None:
    """Labels of a real 1024² angiogram as stored and reduced to 512² (``reconstruct(max_side=512)``)."""
    geometry = {"sid_mm": 1100.0, "sod_mm": 750.0, "pixel_spacing_mm": (0.2, 0.2), "primary_deg": 0.0,
                "secondary_deg": 0.0}  # the file has no geometry tags; the labels do not depend on them
    run = vc.load_run(DICOM / "wg04_xa1" / "XA1_UNC.dcm", geometry=geometry)
    small = run.resampled(512)
    seg = vc.Segmenter()
    colours = np.array([[0, 0, 0], [255, 60, 60], [60, 255, 60], [60, 60, 255], [255, 255, 0]]) / 255.0
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.4))
    panels = ((run.frames[0], None, f"XA1 as stored: {run.view.rows}² px, {run.bits_stored} bit"),
              (run.frames[0], seg(run.frames[0], tta=True), "labels of the frame as stored"),
              (small.frames[0], seg(small.frames[0], tta=True), "labels of the frame reduced to 512²\n"
               "(reconstruct's max_side)"))
    for ax, (img, lab, title) in zip(axes, panels, strict=True):
        ax.imshow(img, cmap="gray")
        if lab is not None:
            rgba = np.zeros((*lab.shape, 4))
            rgba[..., :3] = colours[lab]
            rgba[..., 3] = 0.45 * (lab > 0)
            ax.imshow(rgba)
            title += f"\nvessel {np.mean(lab == 1):.1%}, catheter {np.mean(lab == 2):.1%} of the pixels"
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.suptitle("bundled model (int8, mirror TTA) on a real 1024² 10-bit angiogram (NEMA WG04 XA1, a "
                 "cerebral study): vessel red, catheter green", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=70)
    plt.close(fig)


def report_screenshot(path: Path) -> None:
    sys.path.insert(0, str(HERE.parent / "tests"))
    from browser import visit_report

    from vesselcad.cli import main as cli

    with tempfile.TemporaryDirectory() as tmp:
        cli(["demo", "--out", tmp, "--quiet"])
        visit = visit_report(Path(tmp) / "report.html", page_png=path)
    if not visit.rendered or visit.errors:
        raise RuntimeError(f"report.html did not render cleanly: {visit.errors or visit.status}")


def _section(points: np.ndarray, cells: np.ndarray, edges: np.ndarray, z: float
             ) -> tuple[list[np.ndarray], np.ndarray]:
    """Polygons (x, y) where the plane at height ``z`` cuts cells (convex ones), and which cells."""
    a, b = points[cells[:, edges[:, 0]]], points[cells[:, edges[:, 1]]]  # (n, e, 3)
    da, db = a[..., 2] - z, b[..., 2] - z
    cut = (da * db) < 0
    t = np.where(cut, da / np.where(cut, da - db, 1.0), 0.0)
    p = a + t[..., None] * (b - a)
    out = []
    which = np.flatnonzero(cut.sum(axis=1) >= 3)
    for k in which:
        q = p[k, cut[k], :2]
        c = q.mean(axis=0)
        out.append(q[np.argsort(np.arctan2(q[:, 1] - c[1], q[:, 0] - c[0]))])
    return out, which


def crease_figure(path: Path) -> None:
    """Section through the prism layers at a 10-degree branch (tests/test_creases.py), the crease
    kept (``crease_radius=0``) and rounded (the default), coloured by scaled Jacobian."""
    import warnings

    from matplotlib.collections import PolyCollection

    from vesselcad.cfd.quality import scaled_jacobian

    t = np.radians(10.0)

    def line(p0, d, length, n=30):
        return (np.asarray(p0, float) + np.linspace(0, length, n)[:, None] * np.asarray(d, float)).tolist()

    tree = vc.VesselTree.from_json({"units": "mm", "frame": "LPS", "branches": [
        {"id": 0, "parent": None, "name": "parent", "points": line([0, 0, 0], [1, 0, 0], 30),
         "radius": [1.5] * 30},
        {"id": 1, "parent": 0, "name": "child", "points": line([8, 0, 0], [np.cos(t), np.sin(t), 0], 20),
         "radius": [0.5] * 30}]})
    solid = tree.solid()
    crease = solid.creases()[0].point
    edges = {"tetra": np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]),
             "wedge": np.array([[0, 1], [1, 2], [2, 0], [3, 4], [4, 5], [5, 3], [0, 3], [1, 4], [2, 5]])}
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.4), sharey=True)
    for ax, radius in zip(axes, (0.0, 0.1), strict=True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", vc.VesselcadWarning)
            mesh = vc.cfd.volume_mesh(solid, boundary_layers=3, crease_radius=radius)
        polys, sj = [], []
        for kind, e in edges.items():
            c = mesh.cells[kind]
            near = np.all(np.abs(mesh.points[c].mean(axis=1)[:, :2] - crease[:2]) < [1.6, 0.9], axis=1)
            c = c[near]
            q = scaled_jacobian(mesh.points, c, kind)
            cut, which = _section(mesh.points, c, e, float(crease[2]) + 1e-3)
            polys += cut
            sj += list(q[which])
        coll = PolyCollection(polys, array=np.clip(sj, -0.2, 1.0), cmap="viridis", edgecolors="k",
                              linewidths=0.2, clim=(-0.2, 1.0))
        ax.add_collection(coll)
        ax.set_xlim(crease[0] - 0.7, crease[0] + 0.7)
        ax.set_ylim(crease[1] - 0.3, crease[1] + 0.3)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        worst = min(mesh.quality[k]["scaled_jacobian_min"] for k in ("wedge", "tetra"))
        inverted = sum(mesh.quality[k]["inverted"] for k in ("wedge", "tetra"))
        what = "crease kept (crease_radius=0)" if radius == 0 else f"crease rounded (crease_radius={radius})"
        ax.set_title(f"{what}\nmin scaled Jacobian {worst:.2f}, {inverted} inverted")
    axes[0].set_ylabel("y (mm)")
    fig.colorbar(coll, ax=axes, label="scaled Jacobian (section z = 0 at the crease)", shrink=0.85)
    fig.suptitle("3 prism layers where a r 0.5 mm vessel leaves a r 1.5 mm one at 10 degrees")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def surface_figure(path: Path) -> None:
    """Paired 3D points of phantom lca 1015 (truth labels) without and with the surface prior."""
    import warnings

    from scipy.spatial import cKDTree

    from vesselcad.phantom import LABELS
    from vesselcad.splines import resample_by_arclength
    from vesselcad.surface import semi_axes

    case = generate_case(1015, "lca", n_frames=10, synchronized=True)
    la, lb = case.run_a.labels, case.run_b.labels
    i = int(np.argmax((la == LABELS["vessel"]).sum(axis=(1, 2))))
    va, vb = case.run_a.view, case.run_b.view
    truth = np.vstack([resample_by_arclength(np.asarray(b["points"], float), 0.25)
                       for b in case.run_a.trees[i]["branches"] if len(b["points"]) > 1])
    tree = cKDTree(truth)
    fig = plt.figure(figsize=(13, 6.2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", vc.VesselcadWarning)
        ga = vc.centreline_graph(la[i] == LABELS["vessel"], va, labels=la[i])
        gb = vc.centreline_graph(lb[i] == LABELS["vessel"], vb, labels=lb[i])
        for k, prior in enumerate((False, True)):
            m = vc.match_graphs(va, ga, vb, gb, surface_prior=prior)
            pts = [vc.intersect_centrelines(va, p.points_a_px, vb, p.points_b_px,
                                            method="epipolar").sample_every(0.5) for p in m.pairs]
            x = np.vstack(pts)
            off = tree.query(x)[0] > 1.5
            ax = fig.add_subplot(1, 2, k + 1, projection="3d")
            ax.plot(*truth[::4].T, ".", ms=1, color="0.75", label="truth centreline")
            ax.plot(*x[~off].T, ".", ms=2, color="tab:blue", label="paired, on the truth")
            ax.plot(*x[off].T, ".", ms=2, color="tab:red", label="paired, > 1.5 mm off")
            surf = m.surface if prior else vc.match_graphs(va, ga, vb, gb).surface
            if surf is not None:  # the fitted ellipsoid where the tree is: points near it on a grid
                lo, hi = truth.min(axis=0) - 5, truth.max(axis=0) + 5
                g = np.stack(np.meshgrid(*[np.linspace(a, b, 45) for a, b in zip(lo, hi, strict=True)]),
                             -1).reshape(-1, 3)
                near = g[surf.distance(g) < 0.6]
                ax.plot(*near.T, ".", ms=0.6, color="tab:green", alpha=0.35, label="fitted ellipsoid")
            title = "surface prior" if prior else "no surface prior"
            ax.set_title(f"{title}: {100 * off.mean():.0f} % of the paired length off the truth")
            ax.set_xlabel("x mm")
            ax.set_ylabel("y mm")
            ax.set_zlabel("z mm")
            ax.view_init(elev=20, azim=-60)
            if k == 0:
                ax.legend(loc="upper left", fontsize=8, markerscale=4)
    axes = semi_axes(surf.coefficients, surf.scale)
    fig.suptitle(f"Phantom lca 1015, truth labels: the ellipsoid fitted to the first choice "
                 f"(semi-axes {axes[0]:.0f} / {axes[1]:.0f} / {axes[2]:.0f} mm, spread "
                 f"{surf.sigma_mm:.2f} mm) reweights the candidates")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def junction_figure(path: Path) -> None:
    """cs 2111's junction of branch 16 and its child 9, as fused without and with END_INSIDE_SHARE."""
    import warnings

    import vesselcad.tree as vt

    data = HERE.parent / "tests" / "data" / "mesh_partial_rca_2111.json"
    centre = np.array([1.6, -6.3, 40.6])  # branch 16's end
    fig = plt.figure(figsize=(12, 5.6))
    for k, share in enumerate((None, vt.END_INSIDE_SHARE)):
        saved, vt.END_INSIDE_SHARE = vt.END_INSIDE_SHARE, share
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", vc.VesselcadWarning)
                solid = vc.VesselTree.from_json(data).solid()
                mesh = solid.to_trimesh(tolerance=0.02, check_closed=False)  # the fused shape's own mesh
        finally:
            vt.END_INSIDE_SHARE = saved
        near = np.linalg.norm(mesh.triangles_center - centre, axis=1) < 7.0
        sub = mesh.submesh([np.flatnonzero(near)], append=True)
        v, f = sub.vertices, sub.faces
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=f, linewidth=0.0, shade=True,
                        color="tab:red" if share is None else "tab:blue")
        for lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            lim(c - 6.0, c + 6.0)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=15, azim=-110)
        ax.set_xlabel("x mm")
        ax.set_ylabel("y mm")
        ax.set_zlabel("z mm")
        what = ("as measured (before): OCCT's mesher covers its walls in part" if share is None
                else f"child kept within {share:.0%} of the parent inside its end (now)")
        ax.set_title(f"{what}\nB-rep {solid.volume:.0f} mm³, the mesh as fused, within 7 mm of 16's end",
                     fontsize=10)
    fig.suptitle("cs 2111 (true labels): child 9 starts at the end of branch 16, both widened by the "
                 "junction's blob.\nAs measured its wall grazed the parent's all round; the fused walls "
                 "touched along a line (the B-rep 3.6 % larger than its tubes)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    out = HERE / "img"
    out.mkdir(exist_ok=True)
    if "--crease" in sys.argv[1:]:
        crease_figure(out / "cfd_crease.png")
        return 0
    if "--surface" in sys.argv[1:]:
        surface_figure(out / "surface_prior.png")
        return 0
    if "--large" in sys.argv[1:]:
        large_frame_figure(out / "seg_real_1024.png")
        return 0
    if "--junction" in sys.argv[1:]:
        junction_figure(out / "junction_kept_inside.png")
        return 0
    if "--report" in sys.argv[1:]:
        report_screenshot(out / "report_html.png")
        return 0
    if "--fit" in sys.argv[1:]:
        pixel_fit_figure(out / "pixel_fit_real.png")
        return 0
    geometry_figure(out / "geometry.png")
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_case(generate_case(1, "cs", n_frames=40), tmp, preview=True)
        (out / "phantom_preview.png").write_bytes(Path(paths["preview"]).read_bytes())
    phantom_vs_real(out / "phantom_vs_real.png")
    centreline_graph_real(out / "centreline_graph_real.png")
    surface_figure(out / "surface_prior.png")
    large_frame_figure(out / "seg_real_1024.png")
    junction_figure(out / "junction_kept_inside.png")
    pixel_fit_figure(out / "pixel_fit_real.png")
    print("wrote", *sorted(p.name for p in out.glob("*.png")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
