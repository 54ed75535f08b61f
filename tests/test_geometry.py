"""C-arm geometry against an independent hand computation of the DICOM convention."""

import json
import math

import numpy as np
import pytest

import vesselcad as vc

ANGLES = [(0, 0), (30, 0), (-30, 0), (0, 25), (0, -25), (45, -20), (-30, 20), (90, 0), (77, -45)]


def make_view(a, b, rows=512, cols=480, spacing=(0.3, 0.35)):
    return vc.CArmView(primary_deg=a, secondary_deg=b, sid_mm=1100.0, sod_mm=750.0,
                       pixel_spacing_mm=spacing, rows=rows, cols=cols)


def hand_project(a_deg, b_deg, sid, sod, spacing, rows, cols, X):
    """Written from ARCHITECTURE.md's formulas only: no rotation matrices."""
    a, b = math.radians(a_deg), math.radians(b_deg)
    d = np.array([math.sin(a) * math.cos(b), -math.cos(a) * math.cos(b), math.sin(b)])
    u = np.array([math.cos(a), math.sin(a), 0.0])
    v = np.cross(u, d)  # = R (0,0,-1) for this convention
    s = -sod * d
    c = (sid - sod) * d
    lam = ((c - s) @ d) / ((X - s) @ d)
    hit = s + lam * (X - s)
    col = (hit - c) @ u / spacing[1] + (cols - 1) / 2
    row = (hit - c) @ v / spacing[0] + (rows - 1) / 2
    return np.array([col, row])


@pytest.mark.parametrize("a,b", ANGLES)
def test_projection_matches_hand_computation(a, b):
    rng = np.random.default_rng(1)
    view = make_view(a, b)
    X = rng.uniform(-80, 80, (25, 3))
    got = view.project(X)
    want = np.array([hand_project(a, b, 1100.0, 750.0, (0.3, 0.35), 512, 480, x) for x in X])
    np.testing.assert_allclose(got, want, atol=1e-9, rtol=0)
    h = np.c_[X, np.ones(len(X))] @ view.matrix.T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], want, atol=1e-9, rtol=0)


def test_image_orientation_and_signs():
    pa = make_view(0, 0, rows=512, cols=512)
    centre = np.array([255.5, 255.5])
    np.testing.assert_allclose(pa.project([0, 0, 0]), centre, atol=1e-12)
    # PA: patient's left on the image right, head up.
    assert pa.project([10, 0, 0])[0] > centre[0]
    assert pa.project([0, 0, 10])[1] < centre[1]
    np.testing.assert_allclose(pa.detector_direction, [0, -1, 0], atol=1e-15)  # detector anterior
    # LAO 90: detector on the patient's left; posterior lies on the image right.
    lao90 = make_view(90, 0, rows=512, cols=512)
    np.testing.assert_allclose(lao90.detector_direction, [1, 0, 0], atol=1e-15)
    assert lao90.project([0, 10, 0])[0] > centre[0]
    # RAO 30: detector on the patient's right-anterior side.
    rao = make_view(-30, 0, rows=512, cols=512)
    assert rao.detector_direction[0] < 0 and rao.detector_direction[1] < 0
    # Cranial: detector toward the head; caudal: toward the feet.
    assert make_view(0, 20).detector_direction[2] > 0
    assert make_view(0, -20).detector_direction[2] < 0
    # Source and detector on opposite sides of the isocentre at SOD and SID - SOD.
    v = make_view(45, -20)
    assert np.linalg.norm(v.source) == pytest.approx(750.0)
    assert np.linalg.norm(v.detector_centre) == pytest.approx(350.0)
    assert v.magnification == pytest.approx(1100 / 750)
    assert v.mm_per_px == pytest.approx((0.3 * 750 / 1100, 0.35 * 750 / 1100))


def test_pixel_to_detector_and_ray_are_consistent():
    view = make_view(-30, 20)
    X = np.random.default_rng(2).uniform(-60, 60, (40, 3))
    px = view.project(X)
    on_det = view.pixel_to_detector(px)
    # Detector points lie in the detector plane, on the ray through X.
    np.testing.assert_allclose((on_det - view.detector_centre) @ view.detector_direction, 0, atol=1e-9)
    origin, dirs = view.ray(px)
    to_x = (X - origin) / np.linalg.norm(X - origin, axis=1, keepdims=True)
    np.testing.assert_allclose(dirs, to_x, atol=1e-12)
    behind = view.project(view.source - 10 * view.detector_direction)
    assert np.all(np.isnan(behind))


@pytest.mark.parametrize("pair", [((0, 0), (30, 0)), ((-30, 20), (45, -20)), ((30, 0), (90, 0))])
def test_triangulation_recovers_points(pair):
    va, vb = make_view(*pair[0]), make_view(*pair[1], rows=400, cols=600, spacing=(0.2, 0.2))
    X = np.random.default_rng(3).uniform(-70, 70, (100, 3))
    got = vc.triangulate(va, va.project(X), vb, vb.project(X))
    np.testing.assert_allclose(got, X, atol=1e-9, rtol=0)
    rec = vc.reconstruction_error(va, va.project(X), vb, vb.project(X))
    assert np.max(rec.error_px) < 1e-9 and np.max(rec.error_mm) < 1e-9


def test_reconstruction_error_broadcasts_and_converts_units():
    va, vb = make_view(0, 0), make_view(90, 0)
    X = np.random.default_rng(4).uniform(-50, 50, (7, 3))
    pa, pb = va.project(X), vb.project(X)
    rec = vc.reconstruction_error(va, pa[:, None, :], vb, pb[None, :, :])
    assert rec.error_mm.shape == (7, 7) and rec.points_mm.shape == (7, 7, 3)
    np.testing.assert_allclose(np.diag(rec.error_mm), 0, atol=1e-9)
    off = rec.error_mm[~np.eye(7, dtype=bool)]
    assert np.all(off > 0.1)
    # A 1-px shift along a column: error in mm is spacing * SOD / SID (max of both views).
    shifted = vc.reconstruction_error(va, pa + [1.0, 0.0], vb, pb)
    assert np.all(shifted.error_px > 0)
    assert np.all(shifted.error_mm <= 0.35 * 750 / 1100 + 1e-9)
    # Independently: reproject by hand, convert each view's pixel error with its spacing.
    P = shifted.points_mm
    ra = np.array([hand_project(0, 0, 1100.0, 750.0, (0.3, 0.35), 512, 480, x) for x in P])
    rb = np.array([hand_project(90, 0, 1100.0, 750.0, (0.3, 0.35), 512, 480, x) for x in P])
    da, db = ra - (pa + [1.0, 0.0]), rb - pb
    mm = lambda d: np.hypot(d[:, 0] * 0.35, d[:, 1] * 0.3) * 750 / 1100  # noqa: E731
    np.testing.assert_allclose(shifted.error_mm, np.maximum(mm(da), mm(db)), atol=1e-9)
    np.testing.assert_allclose(shifted.error_px, np.maximum(np.hypot(*da.T), np.hypot(*db.T)), atol=1e-9)


def test_json_round_trip(tmp_path):
    view = make_view(-30, 20)
    view.to_json(tmp_path / "view.json")
    assert vc.CArmView.from_json(tmp_path / "view.json") == view
    assert json.loads((tmp_path / "view.json").read_text())["pixel_spacing_mm"] == [0.3, 0.35]
    np.testing.assert_array_equal(vc.CArmView.from_dict(view.to_dict()).matrix, view.matrix)


@pytest.mark.parametrize("kwargs,word", [
    ({"sod_mm": 1200.0}, "sod_mm"),
    ({"pixel_spacing_mm": (0.0, 0.3)}, "pixel_spacing_mm"),
    ({"rows": 0}, "rows"),
    ({"cols": 10.5}, "cols"),
    ({"primary_deg": "LAO"}, "primary_deg"),
    ({"secondary_deg": 95.0}, "secondary_deg"),
])
def test_bad_geometry_is_rejected(kwargs, word):
    args = dict(primary_deg=0.0, secondary_deg=0.0, sid_mm=1100.0, sod_mm=750.0,
                pixel_spacing_mm=(0.3, 0.3), rows=512, cols=512)
    args.update(kwargs)
    with pytest.raises(vc.GeometryError, match=word):
        vc.CArmView(**args)


def test_bad_points_are_rejected():
    view = make_view(0, 0)
    with pytest.raises(vc.ArgumentError, match="points_mm"):
        view.project([[1.0, 2.0]])
    with pytest.raises(vc.ArgumentError, match="view_a"):
        vc.triangulate("not a view", [[0, 0]], view, [[0, 0]])


@pytest.mark.parametrize("rows, cols, spacing", [(1024, 1024, (0.2, 0.2)), (768, 1000, (0.25, 0.2))])
def test_a_run_reduced_to_max_side_sees_the_same_points(rows, cols, spacing):
    # Bright 6x6 px squares drawn at the projections of three 3D points; after area averaging
    # to at most 512 px a side, each square's intensity-weighted centre lies where the resized
    # view projects the same 3D point (the detector kept, pixel centres onto pixel centres).
    view = vc.CArmView(25.0, -10.0, 1100.0, 760.0, spacing, rows, cols)
    pts = np.array([[0.0, 0.0, 0.0], [30.0, -20.0, 10.0], [-25.0, 35.0, -15.0]])
    frame = np.zeros((rows, cols), np.uint16)
    corners = np.round(view.project(pts) - 2.5).astype(int)  # a 6-px square centred on the point
    for c, r in corners:
        frame[r:r + 6, c:c + 6] = 4000
    centres = corners + 2.5  # the squares' true centres (px of the full frame)
    run = vc.XARun(frames=frame[None], view=view, frame_times_ms=[0.0], bits_stored=12)
    small = run.resampled(512)
    assert max(small.frames.shape[1:]) == 512 and small.frames.dtype == np.uint16
    assert small.view.rows * small.view.pixel_spacing_mm[0] == pytest.approx(rows * spacing[0])
    assert small.view.cols * small.view.pixel_spacing_mm[1] == pytest.approx(cols * spacing[1])
    f = small.frames[0].astype(float)
    scale = np.array([small.view.cols / cols, small.view.rows / rows])
    # the same 3D points through the resized view, plus the squares' rounding, scaled
    got = small.view.project(pts) + (centres - view.project(pts)) * scale
    for (c, r) in got:
        r0, c0 = int(r) - 6, int(c) - 6
        win = f[r0:r0 + 14, c0:c0 + 14]
        yy, xx = np.mgrid[r0:r0 + 14, c0:c0 + 14]
        assert (xx * win).sum() / win.sum() == pytest.approx(c, abs=0.02)
        assert (yy * win).sum() / win.sum() == pytest.approx(r, abs=0.02)
    assert f.sum() * (rows * cols) / f.size == pytest.approx(3 * 36 * 4000, rel=1e-3)  # area kept
    assert run.resampled(2048) is run  # already small enough
    with pytest.raises(vc.ArgumentError, match="max_side"):
        run.resampled(8)
    with pytest.raises(vc.GeometryError, match="rows"):
        view.resized(0, 10)
