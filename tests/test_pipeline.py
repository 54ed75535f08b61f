"""The whole pipeline (vc.reconstruct, outputs, CLI) on an analytic 3D tree seen in two views.

The tree is five quadratic Bezier vessels with known radii, projected with the
contract's geometry into two label stacks (vessel + a catheter ending at the
ostium as the stationary object) and two DICOM files. Everything reconstructed
is compared with those analytic curves, never with the code's own output.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from analytic_tree import RADIUS_MM, TREE
from scipy.spatial import cKDTree

import vesselcad as vc
import vesselcad.refine as refine_module
from vesselcad.cli import main
from vesselcad.metrics import distance_to_polyline
from vesselcad.pipeline import ReconstructionError, reconstruct

VIEW_A = vc.CArmView(primary_deg=30.0, secondary_deg=0.0, sid_mm=1100.0, sod_mm=750.0,
                     pixel_spacing_mm=(0.4, 0.4), rows=384, cols=384)
VIEW_B = vc.CArmView(primary_deg=-30.0, secondary_deg=25.0, sid_mm=1100.0, sod_mm=750.0,
                     pixel_spacing_mm=(0.4, 0.4), rows=384, cols=384)
CATHETER = [(-30, 0, 45), (-40, -4, 70), (-45, -8, 110)]


def bezier(ctrl, n=400):
    c = np.asarray(ctrl, float)
    t = np.linspace(0, 1, n)[:, None]
    return (1 - t) ** 2 * c[0] + 2 * (1 - t) * t * c[1] + t ** 2 * c[2]


TRUTH = np.vstack([bezier(c) for _, c in TREE.values()])
TRUTH_LENGTH = sum(np.linalg.norm(np.diff(bezier(c), axis=0), axis=1).sum() for _, c in TREE.values())


def labels_of(view):
    lab = np.zeros((view.rows, view.cols), np.uint8)
    r_scale = view.magnification / view.pixel_spacing_mm[0]
    cath = view.project(bezier(CATHETER))
    cv2.polylines(lab, [np.round(cath * 16).astype(np.int32)], False, 2, 5, cv2.LINE_8, shift=4)
    for name, (_, ctrl) in TREE.items():
        p = view.project(bezier(ctrl))
        cv2.polylines(lab, [np.round(p * 16).astype(np.int32)], False, 1,
                      int(round(2 * RADIUS_MM[name] * r_scale)), cv2.LINE_8, shift=4)
    return lab


def run_of(view, n=3):
    lab = labels_of(view)
    frames = np.where(lab > 0, 60, 200).astype(np.uint8)
    run = vc.XARun(frames=np.repeat(frames[None], n, 0), view=view,
                   frame_times_ms=np.arange(n) * 66.7)
    return run, np.repeat(lab[None], n, 0)


@pytest.fixture(scope="module")
def recon():
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    return reconstruct(ra, rb, labels=(la, lb), solid=True)


def test_view_offset_moves_the_whole_c_arm():
    shift = np.array([5.0, -3.0, 2.0])
    moved = vc.CArmView(30.0, 10.0, 1100.0, 750.0, (0.3, 0.3), 512, 512, offset_mm=shift)
    still = vc.CArmView(30.0, 10.0, 1100.0, 750.0, (0.3, 0.3), 512, 512)
    X = np.random.default_rng(0).normal(size=(20, 3)) * 40
    np.testing.assert_allclose(moved.project(X + shift), still.project(X), atol=1e-9)
    np.testing.assert_allclose(moved.depth(X + shift), still.depth(X), atol=1e-9)
    np.testing.assert_allclose(moved.source, still.source + shift, atol=1e-12)
    assert "offset_mm" not in still.to_dict()  # files without a shift are unchanged
    assert vc.CArmView.from_dict(moved.to_dict()) == moved
    with pytest.raises(vc.GeometryError, match="offset_mm"):
        vc.CArmView(30.0, 10.0, 1100.0, 750.0, (0.3, 0.3), 512, 512, offset_mm=(1.0, np.nan, 0.0))


def _seen_across(view_a, view_b):
    """Unit vector along the common perpendicular of the two views' central rays."""
    n = np.cross(view_a.detector_direction, view_b.detector_direction)
    return n / np.linalg.norm(n)


def test_keypoint_shift_brings_the_two_rays_of_a_moved_point_together():
    # A point seen in view A at X and in view B after the heart moved by s: shifting view B by -s
    # explains both images. Two views see only the part of s across the epipolar lines (along the
    # rays' common perpendicular); along the rays it is a shift in depth they cannot tell.
    X = np.array([-20.0, 5.0, 30.0])
    n = _seen_across(VIEW_A, VIEW_B)
    along_a = (X - VIEW_A.source) / np.linalg.norm(X - VIEW_A.source)  # A's ray through X
    for s, expected in ((6.0 * n, -6.0 * n), (12.0 * along_a, np.zeros(3))):
        pa = VIEW_A.project(X[None])[0]
        pb = VIEW_B.project((X + s)[None])[0]
        t = vc.keypoint_shift(VIEW_A, pa, VIEW_B, pb)
        moved = vc.CArmView.from_dict({**VIEW_B.to_dict(), "offset_mm": t.tolist()})
        assert vc.reconstruction_error(VIEW_A, pa[None], moved, pb[None]).error_px[0] < 1e-6
        assert np.linalg.norm(t - expected) < 0.25, (t, expected)
    with pytest.raises(vc.ArgumentError, match="point_b_px"):
        vc.keypoint_shift(VIEW_A, (1.0, 2.0), VIEW_B, (np.nan, 2.0))
    with pytest.raises(vc.ArgumentError, match="point_a_px"):
        vc.keypoint_shift(VIEW_A, "left", VIEW_B, (1.0, 2.0))


def test_a_heart_moved_between_the_runs_is_found_from_the_stationary_object():
    # Run B acquired with the heart (tree and catheter) 6 mm away, across the epipolar lines (a
    # breath, the patient or the table), the files' geometry exact: the catheter tip disagrees by
    # ~10 px, so view B is shifted to make it agree, and the tree lands near the analytic one.
    # The shift found is 5.1 mm, not 6: the tip seen is where the trunk's contrast starts to hide
    # the catheter, a point 3 mm up the catheter in view A and elsewhere in view B.
    s = 6.0 * _seen_across(VIEW_A, VIEW_B)
    (ra, la) = run_of(VIEW_A)
    lb = labels_of(vc.CArmView.from_dict({**VIEW_B.to_dict(), "offset_mm": (-s).tolist()}))
    frames = np.where(lb > 0, 60, 200).astype(np.uint8)
    rb = vc.XARun(frames=np.repeat(frames[None], 3, 0), view=VIEW_B, frame_times_ms=np.arange(3) * 66.7)
    lb = np.repeat(lb[None], 3, 0)
    rec = reconstruct(ra, rb, labels=(la, lb), solid=False)
    ref = rec.refinement
    assert ref.applied and ref.keypoint_px[0] > 8 and ref.keypoint_px[1] < 0.5
    np.testing.assert_allclose(ref.offset_mm, -s, atol=1.0)
    assert any("key point disagreed" in w for w in rec.warnings)
    err, _ = cKDTree(TRUTH).query(np.vstack([b.points_mm for b in rec.ok_branches]))
    assert err.mean() < 1.5 and len(rec.ok_branches) >= 4
    rep = rec.report()["refinement"]
    np.testing.assert_allclose(rep["keypoint_shift_mm"], ref.keypoint_shift_mm, atol=1e-3)
    # Without it (no refinement) the two views pair no vessel at all.
    with pytest.raises(ReconstructionError, match="no branch of view A could be paired"):
        reconstruct(ra, rb, labels=(la, lb), solid=False, refine=False)


def test_a_key_point_on_two_different_points_of_the_catheter_moves_nothing(monkeypatch):
    # The files' geometry exact, but view B's catheter cut 9 mm short of its tip (a tip the
    # segmentation lost): the key points disagree by more than 2 px while every vessel agrees, so
    # the branch and end points agree no better with a shift, and none is made.
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    cut = np.zeros(VIEW_B.rows * VIEW_B.cols, np.uint8).reshape(VIEW_B.rows, VIEW_B.cols)
    tip = VIEW_B.project(bezier(CATHETER)[:40])
    cv2.polylines(cut, [np.round(tip * 16).astype(np.int32)], False, 1, 7, cv2.LINE_8, shift=4)
    lb = np.where((lb == 2) & (cut[None] > 0), 0, lb)
    rec = reconstruct(ra, rb, labels=(la, lb), solid=False)
    ref = rec.refinement
    assert ref.keypoint_px[0] > 2.0 and not np.any(ref.keypoint_shift_mm)
    assert ref.keypoint_landmarks[1] <= ref.keypoint_landmarks[0]
    assert any("agree no better" in w for w in rec.warnings)
    err, _ = cKDTree(TRUTH).query(np.vstack([b.points_mm for b in rec.ok_branches]))
    assert err.mean() < 0.5
    # When no frame pair of the runs agrees (the phase matching's warning), the heart sat elsewhere
    # at every pair and the shift is made unless the landmarks clearly oppose it: here 1 landmark
    # pair agrees with it against 8 without, so not even then.
    ph = rec.phase
    kp = (ph.keypoints_a["catheter"][ph.frame_a], ph.keypoints_b["catheter"][ph.frame_b])
    told = vc.refine_geometry(VIEW_A, rec.graphs[0], VIEW_B, rec.graphs[1], keypoints=kp,
                              keypoint_confirmed=True)
    assert told.keypoint_landmarks[1] < 0.6 * told.keypoint_landmarks[0]
    assert not np.any(told.keypoint_shift_mm)
    assert any("although no frame pair of the runs agrees" in w for w in told.warnings)
    # A weaker opposition (as 8 against 12 landmark pairs on a phantom case of 15 frames) is
    # overruled: with the share lowered below this case's, the shift is made.
    monkeypatch.setattr(refine_module, "KEYPOINT_CONFIRMED_SHARE", 0.1)
    told = vc.refine_geometry(VIEW_A, rec.graphs[0], VIEW_B, rec.graphs[1], keypoints=kp,
                              keypoint_confirmed=True)
    assert np.any(told.keypoint_shift_mm) and told.keypoint_px[1] < 0.5
    assert any("no frame pair of the runs agrees" in w for w in told.warnings)


def _across_epipolar(view_a, view_b):
    """Unit vector perpendicular to the baseline and to the mean viewing direction."""
    u = np.cross(view_b.source - view_a.source, view_a.detector_direction + view_b.detector_direction)
    return u / np.linalg.norm(u)


def test_a_heart_moved_between_the_runs_is_found_from_the_landmarks(tmp_path):
    # No stationary object (objects="vessels"), run B acquired with the heart 3 mm away across the
    # epipolar lines: the branch and end points of the two graphs agree best with view B shifted
    # back by those 3 mm, and the tree lands on the analytic one. Measured: 2.75 mm found (the
    # middle of the steps where all 6 of view A's landmarks agree; none agree without it), the
    # tree 0.55 mm from the analytic one, 21 mm without refinement.
    s = 3.0 * _across_epipolar(VIEW_A, VIEW_B)
    (ra, la) = run_of(VIEW_A)
    lb = labels_of(vc.CArmView.from_dict({**VIEW_B.to_dict(), "offset_mm": (-s).tolist()}))
    lb = np.where(lb == 2, 0, lb)
    la = np.where(la == 2, 0, la)
    frames = np.where(lb > 0, 60, 200).astype(np.uint8)
    rb = vc.XARun(frames=np.repeat(frames[None], 3, 0), view=VIEW_B, frame_times_ms=np.arange(3) * 66.7)
    ga = vc.centreline_graph(la[0] == 1, VIEW_A)
    gb = vc.centreline_graph(lb == 1, VIEW_B)
    t, n0, n1 = vc.landmark_shift(VIEW_A, ga, VIEW_B, gb)
    assert np.linalg.norm(t + s) < 0.5, (t, -s)
    assert n1 >= n0 + 3 and n1 >= 0.6 * len(ga.landmarks)
    rec = reconstruct(ra, rb, labels=(la, np.repeat(lb[None], 3, 0)), solid=False, objects="vessels")
    ref = rec.refinement
    assert ref.applied and np.linalg.norm(ref.landmark_shift_mm + s) < 0.5
    assert ref.landmark_counts[1] >= ref.landmark_counts[0] + 3
    assert any("agree best with view B shifted" in w for w in rec.warnings)
    err, _ = cKDTree(TRUTH).query(np.vstack([b.points_mm for b in rec.ok_branches]))
    assert err.mean() < 0.6 and len(rec.ok_branches) >= 4
    np.testing.assert_allclose(rec.report()["refinement"]["landmark_shift_mm"], ref.landmark_shift_mm,
                               atol=1e-3)
    rec.write(tmp_path)
    assert "mm of it across the epipolar lines" in (tmp_path / "report.html").read_text()
    # On the files' geometry the same views agree at no shift: nothing is moved.
    gb0 = vc.centreline_graph(labels_of(VIEW_B) == 1, VIEW_B)
    t0, m0, m1 = vc.landmark_shift(VIEW_A, ga, VIEW_B, gb0)
    assert np.linalg.norm(t0) < 0.5 and m1 < m0 + 3
    with pytest.raises(vc.ArgumentError, match="step_mm"):
        vc.landmark_shift(VIEW_A, ga, VIEW_B, gb, step_mm=0.0)
    with pytest.raises(vc.ArgumentError, match="graph_b"):
        vc.landmark_shift(VIEW_A, ga, VIEW_B, "graph")
    with pytest.raises(vc.ArgumentError, match="landmark_scan"):
        vc.refine_geometry(VIEW_A, ga, VIEW_B, gb, landmark_scan="yes")


def test_reconstructed_centrelines_lie_on_the_analytic_tree(recon):
    assert len(recon.ok_branches) >= 4
    pts = np.vstack([b.points_mm for b in recon.ok_branches])
    err, _ = cKDTree(TRUTH).query(pts)
    # Measured: mean 0.37 mm, p95 ~2 mm; the worst span is a vessel running close to the epipolar
    # direction (bridged, not intersected), see docs/usage.md.
    assert err.mean() < 0.5 and np.percentile(err, 95) < 2.5
    cov, _ = cKDTree(pts).query(TRUTH)
    assert np.mean(cov <= 1.0) > 0.75  # share of the true tree's samples reconstructed
    assert recon.errors["mean_px"] < 0.5


def test_radius_and_topology_follow_the_tree(recon):
    # Radii within 0.35 mm of the nearest vessel's (a vessel 2-3 px wide).
    names = list(TREE)
    owner = np.repeat(np.arange(len(names)), 400)
    kd = cKDTree(TRUTH)
    for b in recon.ok_branches:
        _, i = kd.query(b.points_mm)
        true_r = np.array([RADIUS_MM[names[k]] for k in owner[i]])
        assert np.median(np.abs(b.radius_mm - true_r)) < 0.35
    tree = recon.tree
    assert len(tree.roots) == 1  # one connected tree
    root = tree[tree.roots[0]]
    assert np.linalg.norm(root.points[0] - np.array(TREE["trunk"][1][0])) < 3.0  # starts at the ostium


def test_solid_is_one_valid_watertight_tree(recon):
    chk = recon.solid.check()
    assert chk["valid"] and chk["watertight"]
    assert not recon.solid.failed
    # Volume against the analytic vessels' cylinders (sum of pi r^2 L, overlaps counted twice).
    # Measured 1.15 of it (1.13 before vessels that end at a fork were closed with a hemisphere:
    # + 2/3 pi r^3 each, less what the children cover): the pieces reconstructed between landmarks
    # overlap at every junction and their lead-ins run inside the parent. The bounds catch lost
    # pieces and inflated radii (radius error itself is checked above).
    vol = sum(np.pi * RADIUS_MM[n] ** 2 * np.linalg.norm(np.diff(bezier(c), axis=0), axis=1).sum()
              for n, (_, c) in TREE.items())
    assert 0.45 * vol < recon.solid.volume < 1.25 * vol


def test_report_follows_the_contract(recon, tmp_path):
    paths = recon.write(tmp_path)
    for name in ("tree.step", "tree.stl", "tree.glb", "centrelines.json", "centrelines.vtp",
                 "report.json", "report.html", "overlay.png", "phase.png"):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
    rep = json.loads(paths["report.json"].read_text())
    assert (rep["frame_a"], rep["frame_b"]) == (recon.phase.frame_a, recon.phase.frame_b)
    np.testing.assert_allclose(rep["view_a"]["matrix"], VIEW_A.matrix, rtol=1e-7)
    assert rep["view_a"]["refined"] is False
    assert all({"id", "reprojection_px", "reprojection_mm", "status"} <= set(b) for b in rep["branches"])
    assert set(rep["timings_s"]) >= {"segmentation", "phase", "matching", "centrelines_3d", "solid"}
    assert rep["segmentation"] == {"labels": "given"}
    surf = rep["matching"]["surface"]
    assert surf is None or set(surf) == {"semi_axes_mm", "spread_mm", "inliers"}
    # The ostium: the trunk's start, where the catheter ends, found as the root in both views and
    # matched; its triangulated point lies on the analytic start within a vessel radius.
    ost = rep["ostium"]
    assert ost["matched"] is True
    assert np.linalg.norm(np.subtract(ost["point_mm"], TREE["trunk"][1][0])) < RADIUS_MM["trunk"]
    for key, view in (("a_px", VIEW_A), ("b_px", VIEW_B)):
        start_px = view.project(np.asarray([TREE["trunk"][1][0]], float))[0]
        r_px = RADIUS_MM["trunk"] * view.magnification / view.pixel_spacing_mm[0]
        assert np.linalg.norm(np.subtract(ost[key], start_px)) < 3.0 + r_px
    html = paths["report.html"].read_text()
    assert "data:image/png;base64," in html and 'id="view3d"' in html
    assert "Segmentation: labels given to reconstruct (no model)" in html
    # self-contained: no address to fetch (the embedded base64 images may spell "http" by chance)
    body = re.sub(r"data:[a-z/+.-]+;base64,[A-Za-z0-9+/=]+", "", html.split("<body")[1])
    assert "http" not in body
    tree = vc.VesselTree.from_json(paths["centrelines.json"])
    err, _ = cKDTree(TRUTH).query(np.vstack([b.points for b in tree]))
    assert err.mean() < 0.5


def test_what_an_export_says_of_its_file_goes_into_the_report(recon, tmp_path, monkeypatch):
    # A mesh export that warns (a triangulation with holes, or not manifold somewhere) says so
    # in report.json's warnings, under the file's name, and still to the caller.
    import dataclasses

    rec = dataclasses.replace(recon, warnings=list(recon.warnings))
    cls = type(rec.solid)
    real = cls.export_stl

    def noisy(self, path, *a, **k):
        warnings.warn("the solid's triangulation has 2 edge(s) shared by more than two triangles",
                      vc.VesselcadWarning, stacklevel=2)
        return real(self, path, *a, **k)

    monkeypatch.setattr(cls, "export_stl", noisy)
    with pytest.warns(vc.VesselcadWarning, match="shared by more than two"):
        paths = rec.write(tmp_path)
    rep = json.loads(paths["report.json"].read_text())
    said = "tree.stl: the solid's triangulation has 2 edge(s) shared by more than two triangles"
    assert said in rep["warnings"]
    assert (tmp_path / "tree.stl").stat().st_size > 0
    assert len(recon.warnings) < len(rec.warnings)  # the shared fixture is untouched


def test_overlay_marks_starts_joined_across_an_unpaired_stretch(recon, tmp_path):
    # A branch whose warnings say it was joined to another tree gets a magenta diamond at its
    # start in both views; the picture is otherwise the same.
    import dataclasses

    from PIL import Image

    from vesselcad.report import plot_overlays

    k = next(i for i, b in enumerate(recon.branches) if b.ok and b.parent is not None)
    branches = list(recon.branches)
    branches[k] = dataclasses.replace(branches[k], warnings=[
        *branches[k].warnings, "joined across 5.0 mm to branch 0, where both views' skeletons run between "
        "the two (20 and 22 px): start moved 5.0 mm onto branch 0, outside of whose lumen it was"])
    plain = np.asarray(Image.open(plot_overlays(recon, tmp_path / "plain.png")).convert("RGB")).astype(int)
    joined = np.asarray(Image.open(plot_overlays(dataclasses.replace(recon, branches=branches),
                                                 tmp_path / "joined.png")).convert("RGB")).astype(int)
    diff = np.any(plain != joined, axis=2)

    def magenta(im):
        return (im[..., 0] > 240) & (im[..., 1] < 20) & (im[..., 2] > 240)

    assert not magenta(plain).any()
    cols = np.flatnonzero(magenta(joined).any(axis=0))
    half = joined.shape[1] // 2
    assert (cols < half).any() and (cols >= half).any()      # one marker in each view
    assert not (magenta(joined) & ~diff).any()
    assert diff.sum() < 1000                                   # the two markers, nothing else


def test_report_and_overlay_say_which_branches_the_solid_leaves_out(recon, tmp_path):
    # The analytic tree's solid holds every reconstructed branch ...
    import dataclasses

    from PIL import Image

    from vesselcad.report import _PALETTE, plot_overlays
    from vesselcad.tree import TreeBranch

    rep = recon.report()
    assert all(b["in_solid"] is (True if b["status"] == "ok" else None) for b in rep["branches"])
    assert all(b["solid_note"] is None for b in rep["branches"])
    assert rep["solid"]["tree_share"] == 1.0 and recon.solid_left_out == {}
    # ... but not a leaf moved 60 mm away: another, shorter tree, which one solid cannot hold
    leaf = max({b.id for b in recon.tree} - {b.parent for b in recon.tree})
    tree = vc.VesselTree([TreeBranch(id=b.id, parent=None if b.id == leaf else b.parent,
                                     points=b.points + (60.0 if b.id == leaf else 0.0), radius=b.radius,
                                     name=b.name, landmarks=b.landmarks, segments=b.segments)
                          for b in recon.tree])
    rec = dataclasses.replace(recon, tree=tree, solid=tree.solid(), warnings=list(recon.warnings))
    assert set(rec.solid_left_out) == {leaf}
    assert "root of another tree" in rec.solid_left_out[leaf]
    lengths = {b.id: float(np.linalg.norm(np.diff(b.points, axis=0), axis=1).sum()) for b in recon.tree}
    assert rec.solid_share == pytest.approx(1.0 - lengths[leaf] / sum(lengths.values()), rel=1e-6)
    rep = rec.report()
    row = next(b for b in rep["branches"] if b["id"] == leaf)
    assert row["in_solid"] is False and "root of another tree" in row["solid_note"]
    assert all(b["in_solid"] is True for b in rep["branches"] if b["status"] == "ok" and b["id"] != leaf)
    assert rep["solid"]["tree_share"] == pytest.approx(rec.solid_share, abs=1e-4)
    # a pipe that went into the union is held even where none of its faces is left (a branch wholly
    # inside other vessels); one the union gave up is not
    inner = next(b.id for b in recon.tree if b.parent is not None and b.id != leaf)
    faces = [(f, t) for f, t in rec.solid.faces if t.branch_id != inner]
    assert 0 < len(faces) < len(rec.solid.faces)
    hidden = dataclasses.replace(rec, solid=dataclasses.replace(rec.solid, faces=faces))
    assert inner not in hidden.solid.branch_ids and set(hidden.solid_left_out) == {leaf}
    given_up = dataclasses.replace(hidden, solid=dataclasses.replace(
        hidden.solid, failed={**rec.solid.failed, inner: "the boolean union with the tree failed"}))
    assert given_up.solid_left_out[inner] == "the boolean union with the tree failed"
    # the overlay draws the left-out branch dashed: about half its colour's pixels in each view
    colour = _PALETTE[leaf % len(_PALETTE)].astype(int)

    def coloured(r):
        im = np.asarray(Image.open(plot_overlays(r, tmp_path / f"{id(r)}.png")).convert("RGB")).astype(int)
        near = np.abs(im - colour).max(axis=2) < 30
        half = im.shape[1] // 2
        return near[:, :half].sum(), near[:, half:].sum()

    for solid_px, dashed_px in zip(coloured(recon), coloured(rec), strict=True):
        assert 0.3 * solid_px < dashed_px < 0.8 * solid_px
    html = rec.write(tmp_path / "out")["report.html"].read_text()
    assert f"holding <b>{rep['solid']['tree_share']:.0%}</b>" in html
    assert "<td>no: the root of another tree" in html
    # the 3D view draws the left-out centreline apart (orange): its segments, and only its
    import base64

    def floats(tag):
        text = re.search(f'id="{tag}">([^<]*)<', html).group(1)
        return np.frombuffer(base64.b64decode(text), "<f4").reshape(-1, 3)

    pts = next(b for b in rec.branches if b.id == leaf).points_mm
    np.testing.assert_allclose(floats("lines-out-vertices"), np.repeat(pts, 2, axis=0)[1:-1], atol=1e-4)
    n_held = sum(2 * (len(b.points_mm) - 1) for b in rec.ok_branches if b.id != leaf)
    assert len(floats("lines-vertices")) == n_held


def test_cli_reconstruct_from_dicom(tmp_path):
    import build123d
    import trimesh

    ra, _ = run_of(VIEW_A)
    rb, _ = run_of(VIEW_B)
    # Real files: the frames are rendered with the catheter darker so the model finds it.
    vc.save_run(ra, tmp_path / "a.dcm")
    vc.save_run(rb, tmp_path / "b.dcm")
    (_, la), (_, lb) = run_of(VIEW_A), run_of(VIEW_B)
    rec = reconstruct(tmp_path / "a.dcm", tmp_path / "b.dcm", labels=(la, lb), frames=(1, 1))
    assert rec.sources[0].endswith("a.dcm") and (rec.phase.frame_a, rec.phase.frame_b) == (1, 1)
    out = tmp_path / "out"
    rec.write(out)
    shape = build123d.import_step(str(out / "tree.step"))
    solids = shape.solids()
    assert len(solids) == 1 and solids[0].is_valid()
    mesh = trimesh.load(out / "tree.stl")
    assert mesh.is_watertight


def test_cli_reconstruct_exit_codes(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "missing_a.dcm"), str(tmp_path / "missing_b.dcm"),
                 "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "missing_a.dcm" in capsys.readouterr().err


def test_bad_arguments_are_named():
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    with pytest.raises(vc.ArgumentError, match="method"):
        reconstruct(ra, rb, labels=(la, lb), method="magic")
    for objects in ("stent", ["catheter", "vessels"], []):
        with pytest.raises(vc.ArgumentError, match="objects"):
            reconstruct(ra, rb, labels=(la, lb), objects=objects)
    with pytest.raises(vc.ArgumentError, match=r"labels\[1\]"):
        reconstruct(ra, rb, labels=(la, lb[:1]))
    with pytest.raises(vc.ArgumentError, match="frames"):
        reconstruct(ra, rb, labels=(la, lb), frames=(0, 9))
    with pytest.raises(vc.ArgumentError, match="run_a"):
        reconstruct(42, rb, labels=(la, lb))
    empty = np.zeros_like(la)
    with pytest.raises(ReconstructionError, match="phase"):
        reconstruct(ra, rb, labels=(empty, empty))


def test_runs_that_cannot_give_a_tree_say_why(tmp_path, capsys):
    # A real XA cine (no SID/SOD/spacing in its header) given twice, then as two "runs" only
    # 8 degrees apart: both stop before any work with the reason, exit code 3.
    cine = Path(__file__).parent / "data" / "dicom" / "xa_catheter_12frames_jpeg_lossless.dcm"
    geo = tmp_path / "view.json"
    geo.write_text(json.dumps({"sid_mm": 1000.0, "sod_mm": 750.0, "pixel_spacing_mm": [0.3, 0.3]}))
    assert main(["reconstruct", str(cine), str(cine), "--geometry", str(geo), "--out", str(tmp_path / "o"),
                 "--quiet"]) == 3
    assert "same acquisition" in capsys.readouterr().err
    run_a = vc.load_run(cine, geometry=geo)
    run_b = vc.load_run(cine, geometry={**json.loads(geo.read_text()), "primary_deg": 85.0})
    run_b.series_uid = "1.2.826.0.1.3680043.2.1"  # another series at nearly the same angles
    with pytest.raises(ReconstructionError, match=r"\+77.0 deg.*\+85.0 deg.*only [0-9.]+ deg apart"):
        reconstruct(run_a, run_b)
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(vc.CArmView(**{**VIEW_A.to_dict(), "primary_deg": 50.0}))
    rec = reconstruct(ra, rb, labels=(la, lb), solid=False, refine=False)  # 20 degrees: a warning
    assert any("only 20.0 deg apart" in w for w in rec.warnings)


def test_runs_without_a_stationary_object_are_matched_by_their_vessels(tmp_path):
    # The catheter out of both runs' labels (a real run whose tip the segmentation does not find):
    # the pair comes from the vessels alone, said in the warnings; report.json stays valid JSON and
    # the tree still lies on the analytic one.
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    la, lb = np.where(la == 2, 0, la), np.where(lb == 2, 0, lb)
    rec = reconstruct(ra, rb, labels=(la, lb), solid=False)
    assert rec.phase.objects == [] and any("no stationary object" in w for w in rec.warnings)
    rep = json.loads(json.dumps(rec.report(), allow_nan=False))
    assert rep["phase_error_mm"] is None and rep["phase"]["objects"] == []
    assert [b["found_by"] for b in rep["branches"]] == ["landmarks"] * len(rep["branches"])
    paths = rec.write(tmp_path)
    assert "epipolar consistency alone" in paths["report.html"].read_text()
    assert json.loads(paths["report.json"].read_text())["phase"]["error_mm"] is None
    err, _ = cKDTree(TRUTH).query(np.vstack([b.points for b in rec.tree]))
    assert err.mean() < 0.5


def test_report_names_the_model_that_labelled_the_frames():
    # a user reading report.json can tell which file made the labels (the int8 model by default
    # on the CPU) and whether it was changed since
    import hashlib

    from vesselcad.pipeline import _segmentation_summary
    from vesselcad.segment import bundled_model_path

    info = _segmentation_summary(vc.Segmenter(threads=1), "chosen", "coarse")
    want = hashlib.sha256(bundled_model_path("gated_unet_int8.onnx").read_bytes()).hexdigest()
    assert info["labels"] == "model" and info["model"] == "gated_unet_int8.onnx" and info["sha256"] == want
    assert info["layout"] in ("nchwc", "nchw") and (info["tta"], info["frame_search"]) == ("chosen", "coarse")
    assert _segmentation_summary(vc.Segmenter("fp32", threads=1), "none", "all")["model"] == "gated_unet.onnx"


def test_chosen_frames_are_segmented_again_with_mirror_tta():
    # Every frame is segmented once (fast, for the phase matching); the two chosen frames
    # again with mirror test-time augmentation, and the tree comes from those labels.
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    calls = []

    class Recording(vc.Segmenter):
        def __init__(self):  # no model: labels of the analytic tree, calls recorded
            pass

        def __call__(self, frames, *, return_proba=False, progress=False, tta=None):
            x = np.asarray(frames)
            calls.append((x.shape, tta))
            lab = la if np.array_equal(x.reshape(-1, *x.shape[-2:])[0], ra.frames[0]) else lb
            if x.ndim == 2:  # one chosen frame: its catheter is left out, to tell the calls apart
                return np.where(lab[0] == 2, 0, lab[0]).astype(np.uint8)
            return lab

    rec = reconstruct(ra, rb, model=Recording(), solid=False, refine=False)
    assert calls == [((3, 384, 384), False), ((3, 384, 384), False), ((384, 384), True), ((384, 384), True)]
    # report.json says how the labels were made (a model without a file here)
    assert rec.report()["segmentation"] == {"labels": "model", "model": None, "sha256": None, "layout": None,
                                            "tta": "chosen", "frame_search": "all"}
    # the model's labels: the vessels weigh more in the phase matching than given labels do
    assert rec.phase.vessel_weight == 30.0
    assert reconstruct(ra, rb, labels=(la, lb), solid=False, refine=False).phase.vessel_weight == 10.0
    assert not (rec.labels[0] == 2).any() and not (rec.labels[1] == 2).any()
    assert ((rec.labels[0] == 1) == (la[0] == 1)).all()
    for mode, frames_tta in (("none", False), (False, False), ("all", True)):
        calls.clear()
        rec = reconstruct(ra, rb, model=Recording(), solid=False, refine=False, tta=mode)
        assert calls == [((3, 384, 384), frames_tta), ((3, 384, 384), frames_tta)]
        assert (rec.labels[0] == la[0]).all()
    with pytest.raises(vc.ArgumentError, match="tta"):
        reconstruct(ra, rb, model=Recording(), tta="yes")


def test_report_gives_the_hearts_surface_as_fitted():
    # An ellipsoid of semi-axes 40, 45 and 58 mm seen over a cap: the report's summary of the
    # matching's surface gives those axes, no spread and every point an inlier.
    from vesselcad.pipeline import _surface_summary
    from vesselcad.surface import fit_quadric_surface

    rng = np.random.default_rng(2)
    u = rng.normal(size=(600, 3))
    u = u[u[:, 2] > 0.2]
    s = fit_quadric_surface(u / np.linalg.norm(u, axis=1, keepdims=True) * [45.0, 58.0, 40.0])
    summary = _surface_summary(s)
    assert summary["semi_axes_mm"] == [40.0, 45.0, 58.0]
    assert summary["spread_mm"] == 0.0 and summary["inliers"] == 1.0
    assert _surface_summary(None) is None


def _branch(k, pts3d, pts_mm=None, start=(None, None), end=(None, None)):
    """A reconstructed branch whose 2D pieces are the projections of ``pts3d`` and whose
    3D points are ``pts_mm`` (default: the true ones)."""
    from vesselcad.matching import BranchPair
    from vesselcad.pipeline import BranchResult

    pa, pb = VIEW_A.project(pts3d), VIEW_B.project(pts3d)
    n = len(pts3d)
    pair = BranchPair(a=k, b=k, a_range=(0.0, 1.0), b_range=(0.0, 1.0), reversed_a=False, reversed_b=False,
                      start=start, end=end, points_a_px=pa, points_b_px=pb,
                      radius_a_px=np.full(n, 4.0), radius_b_px=np.full(n, 4.0), radius_mm=1.0,
                      error_px=0.0, error_mm=0.0)
    pts = np.array(pts3d if pts_mm is None else pts_mm, float)
    return BranchResult(id=k, pair=pair, points_mm=pts, radius_mm=np.full(n, 1.0))


def _drawn_graphs(*vessels):
    """Both views' centreline graphs of masks drawn from 3D ``(points, radius_mm)`` vessels."""
    graphs = []
    for view in (VIEW_A, VIEW_B):
        mask = np.zeros((view.rows, view.cols), np.uint8)
        for pts, r_mm in vessels:
            r_px = r_mm * view.magnification / view.pixel_spacing_mm[0]
            cv2.polylines(mask, [np.round(view.project(pts) * 16).astype(np.int32)], False, 1,
                          int(round(2 * r_px)), cv2.LINE_8, shift=4)
        graphs.append(vc.centreline_graph(mask.astype(bool), view))
    return tuple(graphs)


def test_a_branch_starting_on_another_in_both_views_is_joined_to_it_there():
    from vesselcad.pipeline import _link_parents

    s = np.linspace(0.0, 1.0, 81)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]       # along x, 60 mm
    fork = np.array([0.0, 0.0, 0.0])                                  # sample 40
    child = fork + s * [0.0, 25.0, 15.0]                              # 29 mm, leaves at the fork
    # its reconstructed start is 6 mm off (depth error fading over its first 12 mm)
    err = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(child, axis=0), axis=1))] / 12.0, 0, 1)
    wrong = child + err[:, None] * [0.0, 0.0, 6.0]
    stray = np.array([0.0, -40.0, 30.0]) + s * [0.0, -20.0, 0.0]     # somewhere else in both views
    results = [_branch(0, parent), _branch(1, child, wrong), _branch(2, stray)]
    _link_parents(results, (VIEW_A, VIEW_B))
    assert results[1].parent == 0 and results[2].parent is None
    # moved onto the fork, the shift fading out within 3 x 6 mm but at most half the branch
    # (14.6 mm of 29.2)
    assert np.linalg.norm(results[1].points_mm[0] - fork) < 0.8
    assert np.abs(results[1].points_mm[-35:] - wrong[-35:]).max() == 0.0
    assert "starts on branch 0 in both views" in results[1].warnings[0]
    # without the views (or where 3D proximity decides) nothing moves
    results = [_branch(0, parent), _branch(1, child, wrong)]
    _link_parents(results)
    assert results[1].parent is None


def test_a_branch_that_meets_another_in_both_views_but_not_in_depth_says_so():
    # The fork of the test above with the child's start 14 mm off in depth: it starts on the
    # parent in both images, but moving it that far would bend it out of shape. It stays linked
    # and where it is (the solid leaves it out: its start is not inside the parent), and its
    # warnings now say why (they said nothing).
    from vesselcad.pipeline import MAX_JOIN_GAP_MM, _link_parents

    s = np.linspace(0.0, 1.0, 81)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]
    err = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(child, axis=0), axis=1))] / 20.0, 0, 1)
    wrong = child + err[:, None] * [0.0, 0.0, 14.0]
    assert MAX_JOIN_GAP_MM < 14.0
    results = [_branch(0, parent), _branch(1, child, wrong)]
    _link_parents(results, (VIEW_A, VIEW_B))
    assert results[1].parent == 0
    np.testing.assert_array_equal(results[1].points_mm, wrong)
    assert any(w.startswith("starts on branch 0 in both views")
               and "its 3D start lies 14.0 mm from branch 0, farther than" in w for w in results[1].warnings)


def test_a_branch_linked_near_a_start_that_is_then_moved_goes_with_it(monkeypatch):
    # Two vessels leave the fork F of a parent along x; both were reconstructed 5.5 mm off in
    # depth at their starts, the second 4.2 mm beside the first (2 mm wide: the second's start
    # is within 2 mm + 1.5 radii of it, not the other way round). The second is linked to the
    # first, the first to the parent (it starts on it in both images), and the first's start is
    # moved 5.5 mm onto F. The second's start then lies 6.9 mm from where it was linked, beyond
    # the (here) 6 mm a start is moved on its own: it goes with the first, onto F (end-to-end
    # lca 2006 with the model's labels: 10 and 12 mm).
    import vesselcad.pipeline as pipeline

    monkeypatch.setattr(pipeline, "MAX_JOIN_GAP_MM", 6.0)
    s = np.linspace(0.0, 1.0, 81)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    one = s * [0.0, 25.0, 15.0]
    two = s * [0.0, -20.0, 18.0]
    fade = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(one, axis=0), axis=1))] / 15.0, 0, 1)
    one_wrong = one + fade[:, None] * [0.0, 0.0, 5.5]
    two_wrong = two + fade[:, None] * [4.2, 0.0, 5.5]
    results = [_branch(0, parent), _branch(1, one, one_wrong), _branch(2, two, two_wrong)]
    results[1].radius_mm = np.full(len(one), 2.0)
    pipeline._link_parents(results, (VIEW_A, VIEW_B))
    assert results[1].parent == 0 and results[2].parent == 1
    assert np.linalg.norm(results[1].points_mm[0]) < 0.8                 # the first onto F
    assert np.linalg.norm(results[2].points_mm[0] - results[1].points_mm[0]) < 0.8  # the second with it
    assert any("(where that branch was moved 5." in w for w in results[2].warnings)


def test_a_moved_start_is_brought_back_onto_the_vessels_of_both_images(monkeypatch):
    # The child of the test above, its reconstructed start 6 mm off in depth. Moving the start
    # onto the fork is a smooth shift that does not follow the vessel: in the images its first
    # millimetres leave the drawn child. With the views' skeletons they are brought back onto
    # it: within a pixel of the drawn centreline in both views, and nearer the true child in 3D.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 81)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    fork = np.zeros(3)
    child = fork + s * [0.0, 25.0, 15.0]
    err = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(child, axis=0), axis=1))] / 12.0, 0, 1)
    wrong = child + err[:, None] * [0.0, 0.0, 6.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0))

    def moved(rounds):
        monkeypatch.setattr(pipeline, "ON_VESSEL_ROUNDS", rounds)
        results = [_branch(0, parent), _branch(1, child, wrong)]
        pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
        assert results[1].parent == 0
        return results[1].points_mm

    def off_px(pts):  # distance of the projections to the drawn child's centreline, worst view
        return np.maximum(distance_to_polyline(VIEW_A.project(pts), VIEW_A.project(child)),
                          distance_to_polyline(VIEW_B.project(pts), VIEW_B.project(child)))

    rounds = pipeline.ON_VESSEL_ROUNDS
    shifted, back = moved(0), moved(rounds)
    assert np.linalg.norm(back[0] - fork) < 0.8 and (back[0] == shifted[0]).all()  # the start stays
    assert off_px(shifted).max() > 2.5                                            # the shift alone
    assert off_px(back).max() < 1.0
    assert distance_to_polyline(back, child).max() < 0.5 * distance_to_polyline(shifted, child).max()
    assert np.abs(back[-35:] - wrong[-35:]).max() == 0.0                          # past the shift


def test_a_moved_start_is_not_turned_back_along_its_parents_end(monkeypatch):
    # A child at its parent's end whose 2D pieces lead back alongside the parent: brought onto
    # them, its first 2 mm would leave the parent at ~140 degrees (OCCT's union can hang on such
    # a junction), so the smooth shift stays. Mid-parent, the same child is brought back.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 81)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [30.0, 0.0, 0.0]       # ends at the origin
    back = np.array([-0.8, 0.6, 0.0])                                 # 143 deg from +x
    child = s * 25.0 * back
    err = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(child, axis=0), axis=1))] / 12.0, 0, 1)
    wrong = child + err[:, None] * [0.0, 0.0, 6.0]

    def moved(rounds, par):
        monkeypatch.setattr(pipeline, "ON_VESSEL_ROUNDS", rounds)
        results = [_branch(0, par), _branch(1, child, wrong)]
        pipeline._link_parents(results, (VIEW_A, VIEW_B))
        assert results[1].parent == 0
        return results[1].points_mm

    rounds = pipeline.ON_VESSEL_ROUNDS
    np.testing.assert_array_equal(moved(rounds, parent), moved(0, parent))
    longer = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]       # the origin mid-parent
    assert np.abs(moved(rounds, longer) - moved(0, longer)).max() > 0.5


def test_two_daughters_of_a_missing_parent_are_not_joined_to_each_other():
    from vesselcad.pipeline import _link_parents

    s = np.linspace(0.0, 1.0, 61)[:, None]
    one = s * [30.0, 10.0, 0.0]
    two = s * [-25.0, 15.0, 10.0]
    results = [_branch(0, one, one + [0.0, 0.0, 5.0]), _branch(1, two, two - [0.0, 0.0, 5.0])]
    _link_parents(results, (VIEW_A, VIEW_B))
    assert results[0].parent is None and results[1].parent is None


def test_a_branch_whose_first_mm_were_not_paired_is_joined_where_both_skeletons_lead():
    # The child leaves the parent at the fork F, but its first 7 mm were not paired (a stretch
    # along the epipolar lines, say): its 3D start is 7 mm from the parent, too far for the 3D
    # rule (2 mm + 1.5 radii) and 25-40 px off the parent in the images. The skeletons of both
    # views run from its start straight to F: joined there. A stray vessel whose start lies
    # 6 mm from the parent but that hangs from it elsewhere (through Q, 31 mm round) stays apart.
    from vesselcad.pipeline import _link_parents

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]     # F = (0, 0, 0) is sample 60
    child = s * [0.0, 25.0, 15.0]                                   # 29.2 mm from F
    seen = child[np.linalg.norm(child, axis=1) >= 7.0]              # the paired part
    g = np.array([10.0, -4.0, -4.5])                                # 6.0 mm from the parent
    stray = g + s * [0.0, -20.0, -10.0]
    q = np.array([25.0, 0.0, 0.0]) + s * (g - [25.0, 0.0, 0.0])     # the stray's real parent

    graphs = _drawn_graphs((parent, 1.5), (child, 1.0), (stray, 1.0), (q, 1.0))

    def branches():
        return [_branch(0, parent), _branch(1, seen), _branch(2, stray)]

    results = branches()
    _link_parents(results, (VIEW_A, VIEW_B))
    assert [b.parent for b in results] == [None, None, None]
    results = branches()
    _link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    assert [b.parent for b in results] == [None, 0, None]
    assert np.linalg.norm(results[1].points_mm[0]) < 0.3           # moved onto F
    assert np.abs(results[1].points_mm[-20:] - seen[-20:]).max() == 0.0
    assert results[1].warnings[0].startswith("joined across 7.0 mm to branch 0")
    assert results[2].points_mm[0] == pytest.approx(g)
    # a branch that starts at the matched roots (the ostium) stays the root of its tree
    results = [_branch(0, parent), _branch(1, seen, start=(0, 0)), _branch(2, stray)]
    _link_parents(results, (VIEW_A, VIEW_B), graphs=graphs, roots=(0, 0))
    assert [b.parent for b in results] == [None, None, None]
    results = [_branch(0, parent), _branch(1, seen, start=(0, 0)), _branch(2, stray)]
    _link_parents(results, (VIEW_A, VIEW_B), graphs=graphs, roots=(0, 1))
    assert [b.parent for b in results] == [None, 0, None]


def test_a_gap_beyond_the_moving_reach_is_bridged_along_both_skeletons(monkeypatch):
    # The child of the test above, its first 15 mm not paired: beyond MAX_JOIN_GAP_MM, so its
    # start is not moved. Both skeletons run from it to the fork F without a detour, and the
    # gap is bridged: a new stretch from the parent to the child's start that follows the
    # drawn child in both images, the paired part left as it was.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]                                   # from F = (0, 0, 0)
    seen = child[np.linalg.norm(child, axis=1) >= 15.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0))
    results = [_branch(0, parent), _branch(1, seen)]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    b = results[1]
    assert b.parent == 0
    np.testing.assert_array_equal(b.points_mm[-len(seen):], seen)    # the paired part as it was
    bridge = b.points_mm[:-len(seen)]
    assert 14.0 / 0.5 <= len(bridge) <= 16.0 / 0.5 + 1               # samples every 0.5 mm
    assert np.linalg.norm(bridge[0]) < 1.0                            # leaves the parent at F
    assert distance_to_polyline(bridge, child).max() < 1.0            # along the true child
    assert distance_to_polyline(bridge, child).mean() < 0.3
    assert np.all(np.linalg.norm(np.diff(b.points_mm, axis=0), axis=1) < 0.6)
    assert "the gap bridged" in b.warnings[-1] and b.warnings[-1].startswith("joined across 15.")
    # its 2D pieces now start at the fork too, and the whole branch reprojects onto them
    for view, piece in ((VIEW_A, b.pair.points_a_px), (VIEW_B, b.pair.points_b_px)):
        assert np.linalg.norm(piece[0] - view.project(np.zeros((1, 3)))[0]) < 3.0
    assert b.reprojection.mean_px < 0.5 and b.reprojection.max_px < 2.0
    # without bridges the join reaches MAX_JOIN_GAP_MM only: the child stays apart
    monkeypatch.setattr(pipeline, "MAX_BRIDGE_MM", None)
    results = [_branch(0, parent), _branch(1, seen)]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    assert results[1].parent is None


def test_a_branch_that_runs_towards_its_parent_is_joined_from_its_end(monkeypatch):
    # The child of the tests above, paired from 4 to 18 mm along it but walked the wrong way
    # (from 18 mm back to 4 mm: a pair grown from a seed has no proximal end to go by). Joined at
    # its start, the skeleton path from the fork F runs over the branch's own pieces and the
    # bridge along it, then the branch back along the bridge: a centreline folded onto itself
    # (true labels rca 2104). Such a branch is joined from its end instead: turned round, its
    # start moved onto F, running outward from F without coming back.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]                                   # from F = (0, 0, 0)
    along = np.linalg.norm(child, axis=1)
    seen = child[(along >= 4.0) & (along <= 18.0)][::-1]            # 18 mm -> 4 mm
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0))

    def joined():
        results = [_branch(0, parent), _branch(1, seen)]
        pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
        return results[1]

    b = joined()
    assert b.parent == 0
    far = np.linalg.norm(b.points_mm, axis=1)                       # distance from F
    assert far[0] < 0.5 and far[-1] == pytest.approx(18.0, abs=0.3)
    assert np.all(np.diff(far) > 0.0)                               # outward all the way
    assert distance_to_polyline(b.points_mm, child).max() < 0.3
    assert "from its end" in b.warnings[-1]
    np.testing.assert_array_equal(b.pair.points_a_px, VIEW_A.project(seen)[::-1])
    assert b.reprojection.mean_px < 0.5
    # not checked: bridged from its start, and folded back on itself
    monkeypatch.setattr(pipeline, "OWN_WALK_PX", None)
    b = joined()
    far = np.linalg.norm(b.points_mm, axis=1)
    assert b.parent == 0 and "the gap bridged" in b.warnings[-1]
    assert far.max() > 17.0 and far[-1] < 4.5                       # out to 18 mm and back to 4


def test_a_branch_that_cannot_be_joined_from_its_end_is_joined_as_before():
    # The backwards child of the test above, but its 3D end lies 30 mm off in depth (its last
    # 2 mm; the images as before): no branch of the other tree lies within reach of its end, so
    # it is joined at its start after all, bridged and folded, rather than left apart.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]
    along = np.linalg.norm(child, axis=1)
    seen = child[(along >= 4.0) & (along <= 18.0)][::-1]
    off = seen.copy()
    off[-8:] += [0.0, 0.0, 30.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0))
    results = [_branch(0, parent), _branch(1, seen, off)]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    b = results[1]
    assert b.parent == 0 and "the gap bridged" in b.warnings[-1] and "from its end" not in b.warnings[-1]
    assert np.linalg.norm(b.points_mm[0]) < 1.0                   # bridged from F, as it ran
    np.testing.assert_array_equal(b.points_mm[-len(off):], off)


def test_a_branch_turned_round_keeps_its_children_where_they_leave_it():
    # As above, the child paired from 10 mm back to 4 mm, and a vessel of its own leaving it at
    # its third sample (0.5 mm from its start, 9.5 mm from F; linked there before the join).
    # Turned round, the vessel keeps leaving it at that point (not at the branch's third sample
    # from its new start on F, 9 mm away, onto which its start would be moved).
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]
    along = np.linalg.norm(child, axis=1)
    seen = child[(along >= 4.0) & (along <= 10.0)][::-1]           # 10 mm -> 4 mm
    side = seen[2] + np.linspace(0.0, 1.0, 41)[:, None] * [12.0, 4.0, -3.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0), (side, 1.0))
    results = [_branch(0, parent), _branch(1, seen), _branch(2, side)]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    assert [b.parent for b in results] == [None, 0, 1]
    assert np.linalg.norm(results[1].points_mm[0]) < 0.5              # turned round, onto F
    assert np.linalg.norm(results[1].points_mm[-3] - seen[2]) < 1e-9  # where the side vessel leaves
    np.testing.assert_array_equal(results[2].points_mm, side)         # not moved


def test_a_bridged_branch_keeps_its_children_where_they_leave_it():
    # The bridged child of the test above, with a vessel of its own whose start lies 1.5 mm beside
    # its 11th sample (linked there, and moved onto it: outside its lumen). The bridge puts 30
    # samples ahead of the branch's own: the vessel still starts at that sample (the index as
    # it was would point 15 mm back along the branch, too far to move to).
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]
    seen = child[np.linalg.norm(child, axis=1) >= 15.0]
    side = seen[10] + [1.5, 0.0, 0.0] + np.linspace(0.0, 1.0, 41)[:, None] * [12.0, 0.0, 0.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0), (side, 1.0))
    results = [_branch(0, parent), _branch(1, seen), _branch(2, side)]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    assert [b.parent for b in results] == [None, 0, 1]
    assert "the gap bridged" in results[1].warnings[-1]
    assert np.linalg.norm(results[2].points_mm[0] - seen[10]) < 0.3
    assert "start moved 1.5 mm onto branch 1" in results[2].warnings[-1]


def test_a_bridge_whose_two_paths_are_not_one_vessel_is_not_built():
    # The same gap, but view B's path runs through a point 12 mm off the child (another vessel,
    # as where a skeleton path turns at a crossing): no 3D curve lies on both paths, the
    # bridge stays ~1.8 px off B's (0.25 px off A's), and the branch is left as it was.
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    child = s * [0.0, 25.0, 15.0]
    seen, gap = child[np.linalg.norm(child, axis=1) >= 15.0], child[np.linalg.norm(child, axis=1) <= 15.0]
    mid = gap[len(gap) // 2] + [12.0, 0.0, 0.0]
    u = np.linspace(0.0, 1.0, 30)[:, None]
    other = np.vstack([u * mid, mid + u * (gap[-1] - mid)])
    b = _branch(1, seen)
    before, pieces = b.points_mm.copy(), b.pair.points_a_px.copy()
    off = pipeline._bridge(b, np.zeros(3), (VIEW_A, VIEW_B), (VIEW_A.project(gap), VIEW_B.project(other)))
    assert off is not None and off[1] > pipeline.BRIDGE_MAX_PX > off[0]
    np.testing.assert_array_equal(b.points_mm, before)
    np.testing.assert_array_equal(b.pair.points_a_px, pieces)
    # the true path in both views: bridged
    true_paths = (VIEW_A.project(gap), VIEW_B.project(gap))
    assert pipeline._bridge(b, np.zeros(3), (VIEW_A, VIEW_B), true_paths) is None
    assert distance_to_polyline(b.points_mm[:-len(seen)], child).max() < 0.5


def test_joins_along_the_skeletons_can_be_switched_off(monkeypatch):
    import vesselcad.pipeline as pipeline

    s = np.linspace(0.0, 1.0, 121)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [60.0, 0.0, 0.0]
    child = s * [0.0, 25.0, 15.0]
    graphs = _drawn_graphs((parent, 1.5), (child, 1.0))
    monkeypatch.setattr(pipeline, "SKELETON_DETOUR", None)
    results = [_branch(0, parent), _branch(1, child[np.linalg.norm(child, axis=1) >= 7.0])]
    pipeline._link_parents(results, (VIEW_A, VIEW_B), graphs=graphs)
    assert results[1].parent is None


def test_a_daughter_of_a_junction_whose_depth_disagrees_starts_inside_its_parent():
    # Parent and daughter meet at one junction landmark pair; the daughter's 3D start came
    # out 5 mm off in depth (outside the parent's 1 mm lumen): moved onto the parent's end.
    from vesselcad.pipeline import _link_parents

    s = np.linspace(0.0, 1.0, 61)[:, None]
    parent = np.array([-30.0, 0.0, 0.0]) + s * [30.0, 0.0, 0.0]
    child = s * [20.0, 20.0, 0.0]
    err = np.clip(1.0 - np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(child, axis=0), axis=1))] / 10.0, 0, 1)
    results = [_branch(0, parent, end=(3, 4)),
               _branch(1, child, child + err[:, None] * [0.0, 0.0, 5.0], start=(3, 4))]
    _link_parents(results)
    assert results[1].parent == 0
    assert np.linalg.norm(results[1].points_mm[0] - parent[-1]) < 1e-9
    assert results[1].warnings == ["start moved 5.0 mm onto branch 0, outside of whose lumen it was"]
    # farther than MAX_JOIN_GAP_MM: linked, left where it is, and said (the solid reports it)
    far = [_branch(0, parent, end=(3, 4)), _branch(1, child, child + [0.0, 0.0, 12.0], start=(3, 4))]
    _link_parents(far)
    assert far[1].parent == 0 and far[1].warnings == [
        "its 3D start lies 12.0 mm from branch 0, farther than the 10 mm a start is moved onto its parent: "
        "left where it is (the two disagree in depth there)"]
    np.testing.assert_array_equal(far[1].points_mm, child + [0.0, 0.0, 12.0])


def test_branches_off_the_hearts_surface_are_left_out_but_not_near_the_ostium():
    # The heart's surface: a sphere of radius 60 mm (q(u) = 1 with u = x / 30 mm), fitted with a
    # spread of 0.5 mm: the limit is max(4 x 0.5, 1.5) = 2 mm from it.
    from vesselcad.pipeline import _drop_off_surface
    from vesselcad.surface import QuadricSurface

    scale, radius = 30.0, 60.0
    c = (scale / radius) ** 2
    sphere = QuadricSurface(coefficients=np.array([c, c, c, 0, 0, 0, 0, 0, 0], float),
                            centre=np.zeros(3), scale=scale, sigma_mm=0.5, inliers=1.0)
    t = np.linspace(0.0, 0.6, 61)[:, None]  # 36 mm of arc
    def arc(r, phi0, theta0):  # along a meridian of the sphere of radius r
        th = theta0 + t[:, 0]
        return r * np.stack([np.sin(th) * np.cos(phi0), np.sin(th) * np.sin(phi0), np.cos(th)], axis=1)
    ostium = arc(radius, 0.0, 0.0)[0]
    on = arc(radius, 0.0, 0.3)                     # on the surface
    near = arc(radius + 1.5, 1.0, 0.6)             # 1.5 mm out: within the limit
    inside = arc(radius - 4.0, 2.0, 0.6)           # 4 mm inside: a wrong pairing
    proximal = arc(radius + 8.0, 0.0, 0.0)[:20]    # 8 mm off, but within 25 mm of the ostium
    results = [_branch(k, p) for k, p in enumerate((on, near, inside, proximal))]
    _drop_off_surface(results, sphere, ostium, 4.0)
    assert [b.ok for b in results] == [True, True, False, True]
    # the surface's first-order distance at 56 mm from the centre: (60^2 - 56^2) / (2 x 56) = 4.14 mm
    assert "off the heart's surface" in results[2].status and "lies 4.1 mm" in results[2].status
    # without the ostium the proximal piece is judged like the others; sigmas=None keeps all
    results = [_branch(k, p) for k, p in enumerate((on, near, inside, proximal))]
    _drop_off_surface(results, sphere, None, 4.0)
    assert [b.ok for b in results] == [True, True, False, False]
    results = [_branch(k, p) for k, p in enumerate((on, inside))]
    _drop_off_surface(results, sphere, ostium, None)
    _drop_off_surface(results, None, ostium, 4.0)
    assert all(b.ok for b in results)
    # a wider spread (a real heart is no ellipsoid) widens the limit: 4 x 1.2 = 4.8 mm
    wide = QuadricSurface(coefficients=sphere.coefficients, centre=np.zeros(3), scale=scale, sigma_mm=1.2,
                          inliers=1.0)
    results = [_branch(0, inside)]
    _drop_off_surface(results, wide, ostium, 4.0)
    assert results[0].ok
    (ra, la), (rb, lb) = run_of(VIEW_A), run_of(VIEW_B)
    for bad in (0, -1.0, float("nan"), True, "4"):
        with pytest.raises(vc.ArgumentError, match="off_surface_sigmas"):
            reconstruct(ra, rb, labels=(la, lb), off_surface_sigmas=bad)


def test_branch_ends_that_leave_the_hearts_surface_are_trimmed():
    # A sphere of radius 60 mm fitted with a spread of 0.5 mm: the whole-branch limit is
    # max(4 x 0.5, 1.5) = 2 mm (median), the ends' limit OFF_SURFACE_END_SIGMAS x max(0.5, 2) = 2 mm.
    from vesselcad.pipeline import OFF_SURFACE_END_SIGMAS, _drop_off_surface
    from vesselcad.surface import QuadricSurface

    assert OFF_SURFACE_END_SIGMAS == 1.0
    scale, radius = 30.0, 60.0
    c = (scale / radius) ** 2
    sphere = QuadricSurface(coefficients=np.array([c, c, c, 0, 0, 0, 0, 0, 0], float),
                            centre=np.zeros(3), scale=scale, sigma_mm=0.5, inliers=1.0)
    th = np.linspace(0.3, 0.9, 73)  # 36 mm of a meridian, samples 0.5 mm apart
    rho = np.full(len(th), radius)
    rho[-12:] = radius - np.linspace(0.5, 6.0, 12)  # its last 12 samples sink to 6 mm inside
    rho[:3] = radius + 3.0                          # its first 3 samples 3 mm outside
    pts = rho[:, None] * np.stack([np.sin(th), np.zeros(len(th)), np.cos(th)], axis=1)
    # first-order distance of a point at distance rho from the centre: |rho^2 - R^2| / (2 rho)
    d = np.abs(rho ** 2 - radius ** 2) / (2 * rho)
    beyond = np.flatnonzero(d[-12:] > 2.0).min() + len(th) - 12  # first sample of the tail past 2 mm
    ostium = np.array([0.0, 0.0, radius])
    results = [_branch(0, pts)]
    _drop_off_surface(results, sphere, ostium, 4.0, (VIEW_A, VIEW_B))
    b = results[0]
    assert b.ok
    # the ostium lies 17.7 mm from the first sample (within 25 mm): the start is left alone
    np.testing.assert_allclose(b.points_mm, pts[:beyond])
    assert len(b.radius_mm) == beyond
    assert len(b.warnings) == 1 and "its last" in b.warnings[0] and "trimmed" in b.warnings[0]
    assert b.reprojection is not None and b.reprojection.max_px < 1e-6
    # without the ostium both ends go
    results = [_branch(0, pts)]
    _drop_off_surface(results, sphere, None, 4.0, (VIEW_A, VIEW_B))
    np.testing.assert_allclose(results[0].points_mm, pts[3:beyond])
    gone = lambda q: np.linalg.norm(np.diff(q, axis=0), axis=1).sum()  # noqa: E731
    assert results[0].warnings[0].startswith(f"its first {gone(pts[:4]):.1f} mm and its last "
                                             f"{gone(pts[beyond - 1:]):.1f} mm trimmed")
    # a wider spread (2.5 mm) widens the ends' limit to 2.5 mm; sigmas=None trims nothing
    wide = QuadricSurface(coefficients=sphere.coefficients, centre=np.zeros(3), scale=scale, sigma_mm=2.5,
                          inliers=1.0)
    results = [_branch(0, pts)]
    _drop_off_surface(results, wide, ostium, 4.0, (VIEW_A, VIEW_B))
    np.testing.assert_allclose(results[0].points_mm, pts[:np.flatnonzero(d[-12:] > 2.5).min() + len(th) - 12])
    results = [_branch(0, pts)]
    _drop_off_surface(results, sphere, ostium, None, (VIEW_A, VIEW_B))
    assert len(results[0].points_mm) == len(th) and results[0].warnings == []
    # a branch that would keep less than OFF_SURFACE_END_KEEP_MM is not trimmed: the median rule
    # judges it (here its median lies 4.1 mm inside: left out)
    deep = (radius - 4.0) * np.stack([np.sin(th), np.zeros(len(th)), np.cos(th)], axis=1)
    results = [_branch(0, deep)]
    _drop_off_surface(results, sphere, None, 4.0, (VIEW_A, VIEW_B))
    assert not results[0].ok and len(results[0].points_mm) == len(th)


def test_depth_along_the_epipolar_lines_comes_from_the_hearts_surface():
    # A sphere of radius 60 mm around the isocentre as the heart's surface. A vessel on it that
    # lies in one epipolar plane projects onto one epipolar line in both views: the views say
    # nothing about its depth. Pushed 2 mm deeper along view A's rays (a wrong depth that
    # reprojects the same in view A), it goes back onto the sphere, to the true points; a vessel
    # crossing the epipolar planes keeps the depth the views gave it.
    from vesselcad.pipeline import _depth_from_surface
    from vesselcad.surface import QuadricSurface

    scale, radius = 30.0, 60.0
    c = (scale / radius) ** 2
    sphere = QuadricSurface(coefficients=np.array([c, c, c, 0, 0, 0, 0, 0, 0], float),
                            centre=np.zeros(3), scale=scale, sigma_mm=0.5, inliers=1.0)
    sa, sb = VIEW_A.source, VIEW_B.source
    x = radius * (sa + sb) / np.linalg.norm(sa + sb)  # the sphere's point facing both sources
    n = np.cross(sb - sa, x - sa)
    n /= np.linalg.norm(n)
    d0 = float(np.dot(n, -sa))  # the epipolar plane through x: its circle on the sphere
    centre, rc = -d0 * n, np.sqrt(radius**2 - d0**2)
    e1 = (x - centre) / np.linalg.norm(x - centre)
    e2 = np.cross(n, e1)
    phi = np.linspace(-0.2, 0.2, 49)[:, None]
    along = centre + rc * (np.cos(phi) * e1 + np.sin(phi) * e2)  # 24 mm in the epipolar plane
    # a great circle through x whose tangent there is the plane's normal (across the planes)
    across = radius * (np.cos(phi / 3) * (x / radius) + np.sin(phi / 3) * n)
    assert np.allclose(np.linalg.norm(along, axis=1), radius) and abs(float(np.dot(along[1] - sa, n))) < 1e-9

    def pushed(p, mm):
        ray = (p - sa) / np.linalg.norm(p - sa, axis=1, keepdims=True)
        return p + mm * ray

    results = [_branch(0, along, pushed(along, 2.0)), _branch(1, across, pushed(across, 2.0))]
    _depth_from_surface(results, (VIEW_A, VIEW_B), sphere)
    assert np.abs(results[0].points_mm - along).max() < 1e-6
    assert results[0].reprojection.max_px < 1e-6  # measured again, on the moved curve
    assert "within 10 deg of the epipolar lines" in results[0].warnings[0]
    assert np.array_equal(results[1].points_mm, pushed(across, 2.0)) and results[1].warnings == []
    # a surface farther along the rays than SURFACE_DEPTH_MAX_MM (a 20 mm sphere here): untouched
    small = QuadricSurface(coefficients=np.array([2.25, 2.25, 2.25, 0, 0, 0, 0, 0, 0], float),
                           centre=np.zeros(3), scale=scale, sigma_mm=0.5, inliers=1.0)
    results = [_branch(0, along, pushed(along, 2.0))]
    _depth_from_surface(results, (VIEW_A, VIEW_B), small)
    assert np.array_equal(results[0].points_mm, pushed(along, 2.0))
    _depth_from_surface(results, (VIEW_A, VIEW_B), None)  # no surface: nothing to do
    assert np.array_equal(results[0].points_mm, pushed(along, 2.0))
    # a surface the tree's points scatter about by more than SURFACE_DEPTH_MAX_SIGMA_MM: untouched
    loose = QuadricSurface(coefficients=sphere.coefficients, centre=np.zeros(3), scale=scale, sigma_mm=2.0,
                           inliers=1.0)
    _depth_from_surface(results, (VIEW_A, VIEW_B), loose)
    assert np.array_equal(results[0].points_mm, pushed(along, 2.0))


def test_hooked_centreline_ends_are_cut_and_smooth_ones_kept():
    from vesselcad.pipeline import _without_hooks

    x = np.arange(0.0, 30.01, 0.5)
    line = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    # a last sample that swings back 0.5 mm (a 155-degree turn at the line's end) and, 3 mm
    # from the start, a sample 0.6 mm aside (a 100-degree turn there): both cut at the turn
    hooked = np.vstack([line, line[-1] + [-0.45, 0.2, 0.0]])
    hooked[6] += [0.0, 0.6, 0.0]
    out, note = _without_hooks(hooked)
    assert np.array_equal(out, hooked[6:-1])
    assert note.startswith("hooked ends cut (3.3 mm at the start, 0.5 mm at the end)")
    # a coronary-like bend (radius 5 mm, 90 degrees) and a hook 8 mm from the end stay
    t = np.linspace(0.0, np.pi / 2, 16)
    bend = np.vstack([line, line[-1] + 5.0 * np.column_stack([np.sin(t), 1 - np.cos(t), 0 * t])[1:]])
    assert _without_hooks(bend)[1] == ""
    far = line.copy()
    far[-17] += [0.0, 0.6, 0.0]
    assert _without_hooks(far)[1] == ""


def test_coarse_frame_search_skips_unfilled_frames_and_finds_an_agreeing_pair():
    # A 48-frame phantom pair at 15 fps: the model labels every fourth frame, then the frames near
    # those that show the vessels filled, then the frames round the best pairs. Frames are labelled
    # once; every frame left out is one the phase matching would not choose (its true vessel area
    # below 90 % of the run's largest), and the chosen frames' true trees agree as closely as with
    # every frame labelled (the phantom's truth: the same vessel points in both runs' frames).
    from vesselcad.phantom import generate_case

    case = generate_case(14, "cs", n_frames=48, rows=256, cols=256)
    ra, rb = case.xa_runs()
    truth = {}
    for run, lab in ((ra, case.run_a.labels), (rb, case.run_b.labels)):
        truth.update({run.frames[i].tobytes(): lab[i] for i in range(run.n_frames)})
    calls = []

    class Truth(vc.Segmenter):
        def __init__(self):  # no model: the phantom's labels of the frames asked for
            pass

        def __call__(self, frames, *, return_proba=False, progress=False, tta=None):
            x = np.asarray(frames)
            stack = x.reshape(-1, *x.shape[-2:])
            if x.ndim == 3:
                calls.extend(f.tobytes() for f in stack)
            out = np.stack([truth[f.tobytes()] for f in stack])
            return out[0] if x.ndim == 2 else out

    def trees_apart(rec):
        ta = np.vstack([b["points"] for b in case.run_a.trees[rec.phase.frame_a]["branches"]])
        tb = np.vstack([b["points"] for b in case.run_b.trees[rec.phase.frame_b]["branches"]])
        return float(np.mean(np.linalg.norm(ta - tb, axis=1)))

    rec = reconstruct(ra, rb, model=Truth(), solid=False, refine=False, frame_search="coarse")
    assert len(calls) == len(set(calls)) < 0.85 * (ra.n_frames + rb.n_frames)
    ka, kb = rec.phase.labelled_a, rec.phase.labelled_b
    assert ka.sum() + kb.sum() == len(calls)
    for known, lab in ((ka, case.run_a.labels), (kb, case.run_b.labels)):
        area = (lab == 1).sum(axis=(1, 2))
        assert (area[~known] < 0.9 * area.max()).all()
    fa, fb = rec.phase.frame_a, rec.phase.frame_b
    assert ka[max(fa - 1, 0): fa + 2].all() and kb[max(fb - 1, 0): fb + 2].all()
    assert rec.report()["phase"]["labelled_frames_a"] == ka.sum()
    calls.clear()
    full = reconstruct(ra, rb, model=Truth(), solid=False, refine=False)  # default: every frame
    assert len(calls) == ra.n_frames + rb.n_frames and full.phase.labelled_a is None
    assert trees_apart(rec) < 0.5 and trees_apart(full) < 0.5
    # a forced pair is labelled and used even where the coarse pass left it out (wash-in, wash-out)
    pick = []
    for known, lab in ((ka, case.run_a.labels), (kb, case.run_b.labels)):
        area = (lab == 1).sum(axis=(1, 2))
        pick.append(int(np.flatnonzero(~known & (area > 0.2 * area.max()))[0]))
    calls.clear()
    with pytest.raises(ReconstructionError, match="matching"):  # half-filled frames of two phases
        reconstruct(ra, rb, model=Truth(), solid=False, refine=False, frames=tuple(pick),
                    frame_search="coarse")
    assert ra.frames[pick[0]].tobytes() in calls and rb.frames[pick[1]].tobytes() in calls
    assert len(calls) < 0.85 * (ra.n_frames + rb.n_frames)
    with pytest.raises(vc.ArgumentError, match="frame_search"):
        reconstruct(ra, rb, model=Truth(), frame_search="some")


def test_cli_keep_off_surface_and_max_side_reach_reconstruct():
    from vesselcad.cli import _parser, _reconstruct_args
    from vesselcad.pipeline import OFF_SURFACE_SIGMAS

    def parsed(argv):
        args = _parser().parse_args(argv)
        args.frames = getattr(args, "frames", None)  # batch has no pair override (as _cmd_batch)
        return _reconstruct_args(args)

    for cmd in (["reconstruct", "a.dcm", "b.dcm", "--out", "o"], ["batch", "in", "--out", "o"]):
        assert parsed(cmd)["off_surface_sigmas"] == OFF_SURFACE_SIGMAS
        assert parsed([*cmd, "--keep-off-surface"])["off_surface_sigmas"] is None
        assert parsed(cmd)["max_side"] == 512 and parsed([*cmd, "--max-side", "768"])["max_side"] == 768
        assert parsed([*cmd, "--max-side", "0"])["max_side"] is None  # the frames as they are
        with pytest.raises(SystemExit):
            parsed([*cmd, "--max-side", "32"])


def test_cli_check_measures_a_written_tree_against_mask_files(tmp_path, capsys):
    # A folder as `reconstruct` writes it: a 40 mm line along x through the isocentre (PA view:
    # row 255.5), masks traced 0.5 px and 7.5 px off it (11-row bands centred on rows 255 and 263).
    view = vc.CArmView(0.0, 0.0, 1100.0, 750.0, (0.3, 0.3), 512, 512)
    line = np.c_[np.linspace(-20.0, 20.0, 81), np.zeros(81), np.zeros(81)]
    vc.VesselTree([vc.TreeBranch(id=0, parent=None, points=line, radius=np.full(81, 1.0))]).to_json(
        tmp_path / "centrelines.json")
    (tmp_path / "report.json").write_text(json.dumps(
        {"frame_a": 7, "frame_b": 9, "view_a": {"used": view.to_dict()}, "view_b": {"used": view.to_dict()}}))
    near = np.zeros((512, 512), np.uint8)
    near[250:261, 100:411] = 255
    far = np.zeros((512, 512), bool)
    far[258:269, 100:411] = True
    cv2.imwrite(str(tmp_path / "a.png"), near)
    np.save(tmp_path / "b.npy", far)
    args = ["check", str(tmp_path), "--mask-a", str(tmp_path / "a.png"), "--mask-b", str(tmp_path / "b.npy")]
    assert main([*args, "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["frames"] == [7, 9]
    assert got["views"][0]["mean_mm"] == pytest.approx(0.5 * 0.3 * 750 / 1100, abs=1e-9)
    assert got["views"][1]["mean_mm"] == pytest.approx(7.5 * 0.3 * 750 / 1100, abs=1e-6)
    assert [v["on_vessel"] for v in got["views"]] == [1.0, 0.0] and got["on_vessel"] == 0.5
    assert json.loads((tmp_path / "mask_check.json").read_text())["mean_px"] == pytest.approx(4.0)
    # what a user gets wrong: a mask of another size, a missing mask, a folder without a report
    cv2.imwrite(str(tmp_path / "small.png"), near[:300])
    assert main([*args[:4], "--mask-b", str(tmp_path / "small.png")]) == 2
    assert "--mask-b" in capsys.readouterr().err
    assert main([*args[:4], "--mask-b", str(tmp_path / "none.png")]) == 2
    assert "none.png: no such file" in capsys.readouterr().err
    assert main(["check", str(tmp_path / "nowhere"), "--mask-a", "a", "--mask-b", "b"]) == 2
    assert "no report.json" in capsys.readouterr().err


def test_runs_of_1024_px_are_reconstructed_at_the_working_size(tmp_path, capsys):
    # The fixture's tree exported as 1024-px frames of the same field (0.15 mm pixels at the
    # detector instead of 0.4 at 384 px): reconstruct works on them reduced to 512 px (0.3 mm)
    # and the tree lies on the analytic one as closely as from the 384-px runs.
    big = [vc.CArmView(v.primary_deg, v.secondary_deg, v.sid_mm, v.sod_mm, (0.15, 0.15), 1024, 1024)
           for v in (VIEW_A, VIEW_B)]
    (ra, la), (rb, lb) = run_of(big[0]), run_of(big[1])
    rec = reconstruct(ra, rb, labels=(la, lb), solid=False)
    assert [(v.rows, v.cols) for v in rec.views] == [(512, 512)] * 2
    assert rec.views[0].pixel_spacing_mm == pytest.approx((0.3, 0.3))
    assert [(v.rows, v.cols) for v in rec.header_views] == [(1024, 1024)] * 2
    assert rec.frames[0].shape == rec.labels[0].shape == (512, 512)
    assert any("1024x1024 px reduced to 512x512 px" in w for w in rec.warnings)
    pts = np.vstack([b.points_mm for b in rec.ok_branches])
    err, _ = cKDTree(TRUTH).query(pts)
    assert err.mean() < 0.5 and np.percentile(err, 95) < 2.5
    cov, _ = cKDTree(pts).query(TRUTH)
    assert np.mean(cov <= 1.0) > 0.75
    names = list(TREE)
    owner = np.repeat(np.arange(len(names)), 400)
    for b in rec.ok_branches:  # the vessels' widths survive the reduction of the labels
        _, i = cKDTree(TRUTH).query(b.points_mm)
        assert np.median(np.abs(b.radius_mm - np.array([RADIUS_MM[names[k]] for k in owner[i]]))) < 0.35
    # masks of the frames as read (1024 px) measure the tree through the views resized to them
    fa, fb = rec.phase.frame_a, rec.phase.frame_b
    m = vc.mask_reprojection(rec, rec.views, [la[fa] == 1, lb[fb] == 1])
    assert m.mean_mm < 0.1 and m.on_vessel_share > 0.95
    with pytest.raises(vc.ArgumentError, match="masks"):
        vc.mask_reprojection(rec, rec.views, [la[fa, :700] == 1, lb[fb] == 1])
    # the CLI's check takes masks at the files' size, from what reconstruct wrote
    rec.write(tmp_path)
    np.save(tmp_path / "a.npy", la[fa] == 1)
    np.save(tmp_path / "b.npy", lb[fb] == 1)
    assert main(["check", str(tmp_path), "--mask-a", str(tmp_path / "a.npy"), "--mask-b",
                 str(tmp_path / "b.npy"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mean_mm"] == pytest.approx(m.mean_mm, abs=1e-4)
    with pytest.raises(vc.ArgumentError, match="max_side"):
        reconstruct(ra, rb, labels=(la, lb), max_side=10)
