"""Geometric core: 3D centrelines from two views, against analytic curves."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import vesselcad as vc
from vesselcad.metrics import centreline_error, reprojection_error

VA = vc.CArmView(-30.0, 20.0, 1100.0, 750.0, (0.4, 0.4), 512, 512)  # RAO 30 CRA 20
VB = vc.CArmView(45.0, -20.0, 1100.0, 750.0, (0.4, 0.4), 512, 512)  # LAO 45 CAU 20


def circle_arc(n: int = 4001) -> np.ndarray:
    """Arc of radius 25 mm over 200 degrees in a tilted plane through the isocentre."""
    t = np.radians(np.linspace(0.0, 200.0, n))
    e1 = np.array([1.0, 0.0, 0.3]) / np.linalg.norm([1.0, 0.0, 0.3])
    e2 = np.cross(e1, np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1]))
    e2 /= np.linalg.norm(e2)
    return 25.0 * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2) + [5.0, -3.0, 2.0]


def helix(n: int = 4001) -> np.ndarray:
    """1.5 turns of a helix of radius 10 mm and pitch 20 mm along a slanted axis."""
    t = np.linspace(0.0, 3 * np.pi, n)
    local = np.stack([10.0 * np.cos(t), 10.0 * np.sin(t), 20.0 * t / (2 * np.pi)], axis=1)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return local @ rot.T + [0.0, 0.0, -20.0]


def segment(n: int = 4001) -> np.ndarray:
    return np.linspace([-30.0, 10.0, -25.0], [25.0, -15.0, 30.0], n)


def truth_distance(points: np.ndarray, truth_dense: np.ndarray) -> np.ndarray:
    """Distance to a very dense truth polyline (vertex distance; spacing << tolerance)."""
    return cKDTree(truth_dense).query(points)[0]


def skeleton_like(curve: np.ndarray, view: vc.CArmView) -> np.ndarray:
    """Exact projection thinned to about one point per pixel, like a skeleton path."""
    px = view.project(curve)
    seg = np.linalg.norm(np.diff(px, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.searchsorted(s, np.arange(0.0, s[-1], 1.0))
    keep = np.unique(np.append(keep, len(px) - 1))
    return px[keep]


@pytest.mark.parametrize("make", [circle_arc, helix, segment], ids=["arc", "helix", "segment"])
def test_exact_projections_recovered_within_0_05_mm(make):
    truth = make()
    curve = vc.intersect_centrelines(VA, skeleton_like(truth, VA), VB, skeleton_like(truth, VB))
    samples = curve.sample(400)
    d = truth_distance(samples, truth)
    assert d.max() <= 0.05, (d.max(), curve)
    # Ordered from the proximal end (the first input point) to the distal one.
    assert np.linalg.norm(samples[0] - truth[0]) < 0.05
    assert np.linalg.norm(samples[-1] - truth[-1]) < 0.05
    # The whole truth is covered.
    assert cKDTree(samples).query(truth[::20])[0].max() < 0.3


def test_result_is_occt_geometry_and_faces_are_valid():
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.Geom import Geom_BSplineCurve
    from OCP.GProp import GProp_GProps

    truth = circle_arc()
    curve = vc.intersect_centrelines(VA, VA.project(truth[::10]), VB, VB.project(truth[::10]))
    assert isinstance(curve.curve, Geom_BSplineCurve)
    assert curve.curve.Degree() == 3
    fa, fb = curve.faces
    assert BRepCheck_Analyzer(fa).IsValid() and BRepCheck_Analyzer(fb).IsValid()
    # OCCT's length of the curve = the arc's analytic length 25 * 200 deg.
    assert curve.length == pytest.approx(25.0 * np.radians(200.0), rel=1e-3)
    edge = curve.to_build123d()
    assert edge.length == pytest.approx(curve.length, rel=1e-6)
    props = GProp_GProps()
    BRepGProp.LinearProperties_s(edge.wrapped, props)
    assert props.Mass() == pytest.approx(curve.length, rel=1e-6)


def test_extruded_surface_is_the_ray_surface():
    from vesselcad.kernel.nurbs import extruded_surface
    from vesselcad.splines import fit_curve_2d

    spline, _ = fit_curve_2d(VA.project(circle_arc()[::20]))
    surface = extruded_surface(VA, spline, 600.0, 900.0)
    for u in np.linspace(spline.t[0], spline.t[-1], 7):
        for v in (600.0, 750.0, 900.0):
            p = surface.Value(float(u), float(v))
            xyz = np.array([p.X(), p.Y(), p.Z()])
            # Every point of the surface projects onto the 2D curve at the same u,
            # and its V parameter is its depth along the central ray.
            assert np.allclose(VA.project(xyz), spline(u), atol=1e-8)
            assert VA.depth(xyz) == pytest.approx(v, abs=1e-8)


def test_epipolar_baseline_agrees_on_exact_input():
    truth = circle_arc()
    pa, pb = skeleton_like(truth, VA), skeleton_like(truth, VB)
    c = vc.intersect_centrelines(VA, pa, VB, pb, method="epipolar")
    assert c.method == "epipolar" and c.faces is None
    assert truth_distance(c.sample(300), truth).max() <= 0.05


def test_intersection_samples_lie_on_both_surfaces_and_match_the_baseline():
    """Every sample of the surface intersection projects onto both views' fitted curves (to 1e-6 px),
    and the point-wise baseline finds the same points on the same windows (to its 0.25 px
    linear interpolation on curve B)."""
    from scipy.optimize import minimize_scalar

    from vesselcad import centreline3d as c3

    rng = np.random.default_rng(3)
    truth = helix()
    pa, pb = skeleton_like(truth, VA), skeleton_like(truth, VB)
    pa, pb = pa + rng.normal(0.0, 0.5, pa.shape), pb + rng.normal(0.0, 0.5, pb.shape)
    br = c3._Branch(VA, pa, VB, pb, None, 10.0, 150.0)
    walked, _ = c3._intersect_nurbs(br)
    base = c3._intersect_epipolar(br)
    assert walked and len(walked) == len(base)
    for w, e in zip(walked, base, strict=True):
        u, X = w[:, 0], w[:, 1:]
        # On view A's ray at u (so on surface A), and onto curve B (so on surface B).
        assert np.allclose(VA.project(X), br.spl_a(u), atol=1e-6)
        grid = np.linspace(*br.dom_b, 20001)
        dense = br.spl_b(grid)
        for q in VB.project(X)[:: max(len(X) // 15, 1)]:
            t0 = grid[np.argmin(np.sum((dense - q) ** 2, axis=1))]
            near = minimize_scalar(lambda t, q=q: float(np.sum((br.spl_b(t) - q) ** 2)),
                                   bounds=(t0 - 0.01, t0 + 0.01), method="bounded", options={"xatol": 1e-12})
            assert np.sqrt(near.fun) < 1e-6
        # Same parameter grid; the same points up to the baseline's interpolation.
        common, iw, ie = np.intersect1d(u, e[:, 0], return_indices=True)
        assert len(common) >= 0.9 * len(u)
        assert np.abs(X[iw] - e[ie, 1:]).max() < 0.01


def test_noisy_skeleton_accuracy():
    rng = np.random.default_rng(7)
    truth = helix()
    pa, pb = skeleton_like(truth, VA), skeleton_like(truth, VB)
    pa = pa + rng.normal(0.0, 0.3, pa.shape)
    pb = pb + rng.normal(0.0, 0.3, pb.shape)
    c = vc.intersect_centrelines(VA, pa, VB, pb)
    assert 0.15 < c.noise_px[0] < 0.5  # the estimated noise is about the true 0.3 px
    d = truth_distance(c.sample_every(0.5), truth)
    # The tail sits in the bridged spans where the helix turns along the epipolar planes.
    assert d.mean() <= 0.15 and np.percentile(d, 95) <= 0.6


def test_pixel_skeletons_give_a_smooth_3d_curve_with_the_quantization_floor():
    # Both projections rounded to pixel centres (a skeleton's staircase): fitted by the noise the
    # fourth differences see (0.18 px here), the 2D curves follow the steps and the 3D curve
    # zig-zags in depth (second differences of 0.16 mm rms between samples 0.5 mm apart); with
    # the floor of 1/sqrt(12) px they follow the true projections and the 3D curve the true one.
    from vesselcad.splines import PIXEL_NOISE_PX

    t = np.linspace(0.0, 1.0, 3000)
    truth = np.stack([-25 + 50 * t, 8 * np.sin(3 * t), 10 * t + 4 * np.cos(4 * t)], axis=1)

    def pixels(view):
        q = np.round(view.project(truth))
        return q[np.r_[True, np.any(np.diff(q, axis=0) != 0, axis=1)]]

    out = {}
    for floor in (0.01, PIXEL_NOISE_PX):
        c = vc.intersect_centrelines(VA, pixels(VA), VB, pixels(VB), min_noise_px=floor)
        s = c.sample_every(0.5)
        bend = np.linalg.norm(np.diff(s, n=2, axis=0), axis=1)  # the truth's own: < 0.01 mm
        out[floor] = (truth_distance(s, truth), np.sqrt(np.mean(bend**2)), c.noise_px)
    d, zigzag, noise = out[PIXEL_NOISE_PX]
    assert min(noise) >= PIXEL_NOISE_PX
    assert out[0.01][1] > 0.05  # zig-zag of the step-following fits
    assert zigzag < 0.02
    assert d.mean() < 0.1 and d.max() < 0.4  # the largest at the ends, on their end pixels
    assert d.mean() < out[0.01][0].mean()


def test_branch_in_an_epipolar_plane_is_bridged_not_raised():
    # A segment inside the epipolar plane through the isocentre: both surfaces are
    # the same plane there, so only the end points fix the depth.
    base = VB.source - VA.source
    direction = np.cross(np.cross(base, -VA.source), base)  # in the plane, across the baseline
    direction = 0.3 * base / np.linalg.norm(base) + direction / np.linalg.norm(direction)
    truth = np.linspace(-20.0, 20.0, 2001)[:, None] * direction / np.linalg.norm(direction)
    c = vc.intersect_centrelines(VA, VA.project(truth), VB, VB.project(truth))
    assert c.ill_conditioned_fraction == pytest.approx(1.0)
    assert c.warnings
    assert truth_distance(c.sample(200), truth).max() < 0.5


def ray_segment(view: vc.CArmView, pixel: tuple[float, float], depths: tuple[float, float],
                n: int = 401) -> np.ndarray:
    """A straight vessel along ``view``'s X-ray through ``pixel``, between two distances from its source."""
    o, d = view.ray(np.asarray(pixel, dtype=float))
    return o + np.outer(np.linspace(*depths, n), d)


@pytest.mark.parametrize("method", ["nurbs", "epipolar"])
def test_vessel_seen_end_on_is_the_segment_along_that_ray(method):
    # 30 mm running along view A's ray: a skeleton of one pixel there, a line in view B.
    truth = ray_segment(VA, (240.3, 275.6), (735.0, 765.0))
    end_on = np.round(VA.project(truth))  # every point on pixel (240, 276)
    assert len(np.unique(end_on, axis=0)) == 1
    long_b = skeleton_like(truth, VB)
    c = vc.intersect_centrelines(VA, end_on, VB, long_b, method=method)
    assert "seen end-on in view A" in c.warnings[0] and len(c.warnings) == 1
    # the ray through the pixel centre lies within 0.5 px (0.3 mm at the source's distance) of the truth
    assert truth_distance(c.sample(100), truth).max() < 0.35
    assert c.length == pytest.approx(30.0, abs=0.6)
    assert np.linalg.norm(c.sample(2)[0] - truth[0]) < 0.6  # proximal first, like the input
    # the other way round: view B sees it end-on
    truth_b = ray_segment(VB, (300.0, 200.0), (740.0, 760.0))
    c = vc.intersect_centrelines(VA, skeleton_like(truth_b, VA), VB, np.round(VB.project(truth_b)),
                                 method=method)
    assert "seen end-on in view B" in c.warnings[0]
    assert truth_distance(c.sample(100), truth_b).max() < 0.35


def test_end_on_with_a_curve_off_its_epipolar_line_warns_and_out_of_depth_raises():
    truth = ray_segment(VA, (240.0, 276.0), (735.0, 765.0))
    point = VA.project(truth)
    line_b = skeleton_like(truth, VB)
    bent = line_b + np.linspace(0.0, 1.0, len(line_b))[:, None] * [0.0, 12.0]  # 12 px off at its far end
    c = vc.intersect_centrelines(VA, point, VB, bent)
    assert any("not one vessel seen end-on" in w for w in c.warnings)
    far = ray_segment(VA, (240.0, 276.0), (1000.0, 1060.0))  # 250 mm beyond the isocentre
    with pytest.raises(vc.ArgumentError, match="depth_range_mm"):
        vc.intersect_centrelines(VA, VA.project(far), VB, VB.project(far))
    with pytest.raises(vc.ArgumentError, match="identical"):
        vc.intersect_centrelines(VA, point, VA, skeleton_like(segment(), VA))
    # bad input beside a one-point curve is named as such, not taken for the one point's fault
    for bad, match in (("abc", r"pts_b_px: expected an \(n, 2\)"), (np.zeros((5, 3)), r"pts_b_px: expected"),
                       (np.r_[line_b, [[np.nan, 1.0]]], "pts_b_px: contains non-finite")):
        with pytest.raises(vc.ArgumentError, match=match):
            vc.intersect_centrelines(VA, point, VB, bad)


@pytest.mark.parametrize(
    "pts, match",
    [
        (np.array([[10.0, 10.0]]), "at least 2"),
        (np.array([[10.0, 10.0], [np.nan, 3.0], [4.0, 5.0]]), "non-finite"),
        (np.zeros((5, 3)), r"\(n, 2\)"),
        ("abc", r"\(n, 2\)"),
    ],
)
def test_bad_points_are_rejected(pts, match):
    good = VB.project(segment()[::100])
    with pytest.raises(vc.ArgumentError, match=match):
        vc.intersect_centrelines(VA, pts, VB, good)


def test_bad_views_and_options_are_rejected():
    p = segment()[::100]
    with pytest.raises(vc.ArgumentError, match="identical"):
        vc.intersect_centrelines(VA, VA.project(p), VA, VA.project(p))
    with pytest.raises(vc.ArgumentError, match="view_b"):
        vc.intersect_centrelines(VA, VA.project(p), "LAO 30", VB.project(p))
    with pytest.raises(vc.ArgumentError, match="method"):
        vc.intersect_centrelines(VA, VA.project(p), VB, VB.project(p), method="magic")
    with pytest.raises(vc.ArgumentError, match="other way round"):
        vc.intersect_centrelines(VA, VA.project(p), VB, VB.project(p)[::-1])
    with pytest.raises(vc.ArgumentError, match="min_angle_deg"):
        vc.intersect_centrelines(VA, VA.project(p), VB, VB.project(p), min_angle_deg=60.0)


def test_reprojection_error_metric_on_known_offsets():
    line = segment()
    pa = VA.project(line)
    # Shift the 2D centreline by exactly 2 px perpendicular to its direction.
    d = pa[-1] - pa[0]
    normal = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    err = reprojection_error(line, VA, pa + 2.0 * normal)
    assert err.mean_px == pytest.approx(2.0, abs=1e-6)
    assert err.max_px == pytest.approx(2.0, abs=1e-6)
    assert err.mean_mm == pytest.approx(2.0 * 0.4 * 750.0 / 1100.0, abs=1e-6)
    both = reprojection_error(line, [VA, VB], [pa, VB.project(line)])
    assert both.max_px < 1e-6


def test_mask_reprojection_against_a_drawn_band():
    # PA view: a 3D line along x at the isocentre projects onto row 255.5 (between two pixel rows).
    pa = vc.CArmView(0.0, 0.0, 1100.0, 750.0, (0.3, 0.3), 512, 512)
    line = np.c_[np.linspace(-20.0, 20.0, 81), np.zeros(81), np.zeros(81)]
    np.testing.assert_allclose(pa.project(line)[:, 1], 255.5, atol=1e-9)
    near = np.zeros((512, 512), bool)
    near[250:261, 100:411] = True  # an 11-row band: its centreline is row 255
    far = np.zeros((512, 512), bool)
    far[258:269, 100:411] = True  # rows 258-268: centreline row 263, the projection off the band
    m = vc.mask_reprojection(line, pa, near)
    assert m.mean_px == pytest.approx(0.5, abs=1e-6) and m.max_px == pytest.approx(0.5, abs=1e-6)
    assert m.mean_mm == pytest.approx(0.5 * 0.3 * 750.0 / 1100.0, abs=1e-9)
    assert m.on_vessel_share == 1.0
    both = vc.mask_reprojection([line, line[:41]], [pa, pa], [near, far])  # 81 + 41 samples in each view
    assert both.px.shape == (2 * 122,)
    np.testing.assert_allclose(both.px[both.view == 1], 7.5, atol=1e-6)
    assert both.on_vessel_share == pytest.approx(0.5)
    assert both.to_dict()["views"][1] == {"mean_mm": pytest.approx(7.5 * 0.3 * 750 / 1100), "on_vessel": 0.0}
    tree = vc.VesselTree([vc.TreeBranch(id=0, parent=None, points=line, radius=np.full(81, 1.0))])
    assert vc.mask_reprojection(tree, [pa], [near]).mean_px == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(vc.ArgumentError, match=r"masks\[0\].*shape"):
        vc.mask_reprojection(line, pa, near[:500])
    with pytest.raises(vc.ArgumentError, match=r"masks\[1\]: no vessel centreline"):
        vc.mask_reprojection(line, [pa, pa], [near, np.zeros((512, 512), bool)])
    with pytest.raises(vc.ArgumentError, match="one mask per view"):
        vc.mask_reprojection(line, [pa, pa], [near])
    with pytest.raises(vc.ArgumentError, match="curves"):
        vc.mask_reprojection("tree.json", pa, near)


def test_centreline_error_metric_on_known_offsets():
    truth = segment()
    unit = np.cross(truth[-1] - truth[0], [0.0, 0.0, 1.0])
    unit /= np.linalg.norm(unit)
    near = centreline_error(truth + 0.5 * unit, truth)
    assert near.mean_mm == pytest.approx(0.5, abs=1e-6) and near.coverage == 1.0
    far = centreline_error(truth + 2.0 * unit, truth)
    assert far.coverage == 0.0
    half = centreline_error(truth[: len(truth) // 2], truth)
    assert half.coverage == pytest.approx(0.5, abs=0.02)
