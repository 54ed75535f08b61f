"""Motion phase matching (paper §2.3) against phantom ground truth."""

import json

import cv2
import numpy as np
import pytest

import vesselcad as vc
from vesselcad.phantom import LABELS, generate_case
from vesselcad.phase import (
    ecg_phase,
    epipolar_consistency,
    error_matrix,
    find_keypoints,
    image_margins,
    match_phase,
    plot_error_matrix,
)


@pytest.fixture(scope="module")
def sync_cs():
    case = generate_case(5, "cs", n_frames=16, synchronized=True, rows=256, cols=256)
    run_a, run_b = case.xa_runs()
    return case, run_a, run_b


def test_synchronized_pair_is_diagonal_with_tiny_error(sync_cs):
    case, run_a, run_b = sync_cs
    m = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    assert m.objects == ["balloon"]
    assert m.frame_a == m.frame_b
    assert m.error_mm < 0.05
    assert m.matrix.shape == (16, 16)
    # Every diagonal pair is consistent (to a fraction of the 0.54 mm pixel at 256²);
    # the chosen one has filled vessels.
    assert np.nanmax(np.diag(m.matrix)) < 0.1
    area = (case.run_a.labels == LABELS["vessel"]).sum(axis=(1, 2))
    assert area[m.frame_a] >= 0.5 * area.max()


def test_geometry_that_does_not_fit_the_images_is_said(sync_cs):
    import dataclasses

    case, run_a, run_b = sync_cs
    # View B's isocentre moved 30 mm across the plane of the two sources and the isocentre (a table
    # shift the images cannot absorb): no pair's balloon rays meet any more.
    normal = np.cross(run_a.view.source, run_b.view.source)
    moved = dict(run_b.view.to_dict(), offset_mm=(30.0 * normal / np.linalg.norm(normal)).tolist())
    shifted = dataclasses.replace(run_b, view=vc.CArmView.from_dict(moved))
    ok = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    assert not any("no frame pair agrees" in w for w in ok.warnings)
    bad = match_phase(run_a, shifted, case.run_a.labels, case.run_b.labels)
    assert bad.error_mm > 5.0
    said = [w for w in bad.warnings if "no frame pair agrees" in w]
    assert len(said) == 1 and "balloon" in said[0] and "geometry" in said[0]


def test_balloon_centres_match_the_truth(sync_cs):
    case, _, _ = sync_cs
    track = find_keypoints(case.run_a.labels, "balloon")
    assert track.found.all()
    assert np.max(np.linalg.norm(track.points_px - case.run_a.keypoints, axis=1)) < 0.3


def test_catheter_tips_match_the_truth():
    case = generate_case(3, "lca", n_frames=6)
    for rr in (case.run_a, case.run_b):
        track = find_keypoints(rr.labels, "catheter")
        assert track.found.all()
        assert np.max(np.linalg.norm(track.points_px - rr.keypoints, axis=1)) < 2.0


def _catheter_frame(length: int = 200) -> np.ndarray:
    """256² labels: a catheter 5 px wide from the top edge down to row ``length`` (excluded).

    Its key point is the centre of the tip's cap, about one radius (2.5 px) short of the end.
    """
    lab = np.zeros((1, 256, 256), np.uint8)
    lab[0, :length, 126:131] = LABELS["catheter"]
    return lab


def test_catheter_cut_by_vessels_keeps_its_tip():
    # The segmentation gives 50 px of the catheter, where vessels cross it, to the vessel class:
    # the cut end at row 80 faces the rest of the catheter and is not its tip.
    lab = _catheter_frame()
    lab[0, 80:130, :] = LABELS["vessel"]
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 197.5]) < 2.0
    # Background in the gap: the two pieces are not one device, the piece from the edge ends at 80.
    lab[0, 80:130, :] = 0
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 77.5]) < 2.0


def test_spur_of_a_catheter_crossing_the_field_is_no_tip():
    # A second catheter runs through the whole field (top edge to bottom edge); a few of its edge
    # pixels labelled as another class leave a notch or a bump, and its skeleton a 4 px spur. The
    # spur's end is no tip: the guiding catheter's end (row 90, its cap's centre at 87.5) is.
    lab = np.zeros((1, 256, 256), np.uint8)
    lab[0, :, 198:203] = LABELS["catheter"]
    lab[0, 120:125, 203:207] = LABELS["catheter"]
    lab[0, :90, 58:63] = LABELS["catheter"]
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [60.0, 87.5]) < 2.0
    # The same bump on a catheter that enters once and ends in the field is kept as it is: a
    # device that ends past a junction can end in a short branch.
    single = _catheter_frame()
    single[0, 120:125, 131:135] = LABELS["catheter"]
    tip = find_keypoints(single, "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 197.5]) < 2.0


def test_catheter_leaving_the_field_as_vessel_is_no_tip():
    # A catheter shaft comes down from the top edge (column 200); the segmentation labels its last
    # 20 px before the bottom edge vessel, so its skeleton ends in the field, 230 px along it from
    # the border. The guiding catheter enters at the left edge and ends at the ostium (100, 120),
    # 100 px from its border: its end, not the shaft's, is the tip.
    v, c = LABELS["vessel"], LABELS["catheter"]
    lab = np.zeros((1, 256, 256), np.uint8)
    cv2.line(lab[0], (0, 120), (100, 120), c, 5)
    cv2.line(lab[0], (103, 121), (180, 180), v, 7)
    lab[0, :236, 198:203] = c
    lab[0, 236:, 198:203] = v
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [100.0, 120.0]) < 4.0
    # A catheter that ends 20 px before the edge over background keeps its end as the tip.
    lab[0, 236:, 198:203] = 0
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [200.0, 233.5]) < 2.0
    # ... and so does one that runs into a vessel turning away from the edge: the gap ahead of
    # its end is background.
    cv2.line(lab[0], (200, 237), (250, 242), v, 5)
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [200.0, 233.5]) < 3.0


def test_catheter_whose_filled_shaft_is_taken_for_vessel_keeps_its_tip():
    # A guiding catheter comes up from the bottom edge and leaves at the top (its ascending
    # shaft, column 60); its descending part comes back down from the top edge (column 30),
    # crosses the shaft and ends at the ostium (120, 140), where the vessel tree starts.
    # The segmentation takes the contrast-filled descending part for vessel down to 8 px past
    # the crossing: the distal piece, labelled catheter, reaches the edge only across that
    # short labelled gap, and its free end is the tip (within the catheter's width of the end
    # of the drawn line, whose square end is no round cap).
    v, c = LABELS["vessel"], LABELS["catheter"]
    lab = np.zeros((1, 256, 256), np.uint8)
    cv2.line(lab[0], (30, 0), (30, 80), v, 5)
    cv2.line(lab[0], (30, 80), (70, 107), v, 5)
    cv2.line(lab[0], (70, 107), (120, 140), c, 5)
    cv2.line(lab[0], (123, 142), (200, 200), v, 7)
    cv2.line(lab[0], (60, 0), (60, 255), c, 5)
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [120.0, 140.0]) < 4.0
    # The same piece with background in the gap is no part of the device that enters: no tip.
    lab[0][(lab[0] == v) & (np.arange(256)[None, :] > 50) & (np.arange(256)[None, :] < 75)] = 0
    lab[0, :, 58:63] = c
    assert np.isnan(find_keypoints(lab, "catheter").points_px[0]).all()


def _bordered_frame(top: int, bottom: int, left: int, right: int, seed: int = 0) -> np.ndarray:
    """256² grey frame (background ~150, noise, dark vessels reaching the edges) inside a black
    export border of the given widths, each followed by a 2 px ramp brighter than half the field."""
    rng = np.random.default_rng(seed)
    f = 150.0 + 8.0 * rng.standard_normal((256, 256))
    cv2.line(f, (0, 40), (255, 90), 60.0, 7)  # contrast-filled vessels crossing the field
    cv2.line(f, (200, 0), (170, 255), 60.0, 9)
    for w, band, ramp in ((top, np.s_[:top], np.s_[top:top + 2]),
                          (bottom, np.s_[256 - bottom:], np.s_[254 - bottom:256 - bottom]),
                          (left, np.s_[:, :left], np.s_[:, left:left + 2]),
                          (right, np.s_[:, 256 - right:], np.s_[:, 254 - right:256 - right])):
        if w:
            f[ramp] = 90.0
            f[band] = 2.0
    return np.clip(f, 0, 255).astype(np.uint8)


def test_image_margins_of_a_black_export_border(sync_cs):
    frames = np.stack([_bordered_frame(10, 0, 14, 6), _bordered_frame(0, 7, 0, 0, seed=1)])
    np.testing.assert_array_equal(image_margins(frames), [[10, 0, 14, 6], [0, 7, 0, 0]])
    # Vessels reaching the edge and the phantom's vignette are no border.
    case, _, _ = sync_cs
    assert not image_margins(case.run_a.frames).any()
    with pytest.raises(vc.ArgumentError, match="frames"):
        image_margins(np.zeros((2, 4, 4)))


def test_catheter_entering_through_a_black_border_has_its_tip():
    # An exported cine with a 12 px black frame: the catheter's labels start below it, 14 px
    # from the array's edge. From the labels alone no end lies at the edge ('ambiguous'); with
    # the frames its entry is at the border's inner edge and the tip is found.
    lab = _catheter_frame()
    lab[0, :14] = 0
    track = find_keypoints(lab, "catheter")
    assert np.isnan(track.points_px[0]).all() and track.reason[0] == "ambiguous"
    frames = _bordered_frame(12, 12, 12, 12)[None]
    tip = find_keypoints(lab, "catheter", frames=frames).points_px[0]
    assert np.linalg.norm(tip - [128.0, 197.5]) < 2.0
    with pytest.raises(vc.ArgumentError, match="frames"):
        find_keypoints(lab, "catheter", frames=frames[:, :128])


def test_catheter_ending_near_the_edge_has_its_tip():
    # A catheter that enters and ends 16 px from the edge (the ostium near the image edge) has
    # its tip there.
    tip = find_keypoints(_catheter_frame(16), "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 13.5]) < 2.0


def test_lead_crossing_the_catheter_keeps_its_tip():
    lab = _catheter_frame()
    lab[0, 100:105, :] = LABELS["lead"]  # drawn over the catheter
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 197.5]) < 2.0


def test_catheter_fragment_beside_a_lead_is_not_the_tip():
    # A lead comes down to row 230; a short piece labelled catheter touches it 200 px from the
    # edge. Only the lead joins that piece to the image edge: the catheter's tip is at row 150.
    lab = _catheter_frame(150)
    lab[0, :231, 58:63] = LABELS["lead"]
    lab[0, 200:205, 63:90] = LABELS["catheter"]
    tip = find_keypoints(lab, "catheter").points_px[0]
    assert np.linalg.norm(tip - [128.0, 147.5]) < 2.0


def test_frames_without_the_object_are_skipped(sync_cs):
    case, run_a, run_b = sync_cs
    la = case.run_a.labels.copy()
    lb = case.run_b.labels.copy()
    la[[3, 7, 8]] = np.where(la[[3, 7, 8]] == LABELS["balloon"], 0, la[[3, 7, 8]])
    lb[[2, 5]] = np.where(lb[[2, 5]] == LABELS["balloon"], 0, lb[[2, 5]])
    # The key-point rule alone (at 256² the vessel term weighs a few lines of rasterization
    # noise against 0.1 mm of key-point error and may take the neighbouring frame).
    m = match_phase(run_a, run_b, la, lb, objects="balloon", vessel_weight=0.0)
    assert np.all(np.isnan(m.matrix[[3, 7, 8], :])) and np.all(np.isnan(m.matrix[:, [2, 5]]))
    assert m.frame_a not in (3, 7, 8) and m.frame_b not in (2, 5)
    assert m.frame_a == m.frame_b and m.error_mm < 0.05
    assert np.all(np.isnan(m.keypoints_a["balloon"][[3, 7, 8]]))


def test_frames_not_labelled_are_never_chosen(sync_cs):
    # A coarse-to-fine search labels only some frames: the others (all background) have no key
    # point, are never chosen, and count neither in the fill nor in the object's presence.
    case, run_a, run_b = sync_cs
    known_a = np.arange(16) % 2 == 1
    known_b = np.arange(16) % 4 != 0
    la = np.where(known_a[:, None, None], case.run_a.labels, 0).astype(np.uint8)
    lb = np.where(known_b[:, None, None], case.run_b.labels, 0).astype(np.uint8)
    m = match_phase(run_a, run_b, la, lb, labelled_a=known_a, labelled_b=known_b, vessel_weight=0.0)
    assert m.objects == ["balloon"]
    assert known_a[m.frame_a] and known_b[m.frame_b]
    assert m.frame_a == m.frame_b and m.error_mm < 0.05  # synchronized runs: the diagonal
    assert np.all(np.isnan(m.keypoints_a["balloon"][~known_a]))
    assert np.all(m.fill_a[~known_a] == 0) and m.fill_a[known_a].max() == 1.0
    area = (case.run_a.labels == LABELS["vessel"]).sum(axis=(1, 2))
    assert m.fill_a[m.frame_a] == pytest.approx(area[m.frame_a] / area[known_a].max())
    assert not (m.eligible_a & ~known_a).any()
    d = m.to_dict()
    assert (d["labelled_frames_a"], d["labelled_frames_b"]) == (8, 12)
    every = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    assert every.to_dict()["labelled_frames_a"] is None
    # the vessel term too is only measured on labelled pairs
    m = match_phase(run_a, run_b, la, lb, labelled_a=known_a, labelled_b=known_b)
    assert np.isnan(m.consistency[~known_a]).all()
    assert np.isfinite(m.consistency[np.ix_(known_a, known_b)]).all()
    for bad in (known_a[:5], np.zeros(16, bool), np.ones(16)):
        with pytest.raises(vc.ArgumentError, match="labelled_a"):
            match_phase(run_a, run_b, la, lb, labelled_a=bad)


def test_no_object_gives_a_clear_error(sync_cs):
    case, run_a, run_b = sync_cs
    only_vessels_a = np.where(case.run_a.labels == LABELS["vessel"], 1, 0).astype(np.uint8)
    only_vessels_b = np.where(case.run_b.labels == LABELS["vessel"], 1, 0).astype(np.uint8)
    # without devices 'auto' falls back to the vessels; with those turned off nothing is left
    with pytest.raises(vc.PhaseError, match="no stationary object"):
        match_phase(run_a, run_b, only_vessels_a, only_vessels_b, vessel_weight=0.0)
    with pytest.raises(vc.PhaseError, match="no vessel pixels"):
        match_phase(run_a, run_b, np.zeros_like(only_vessels_a), only_vessels_b)
    with pytest.raises(vc.ArgumentError, match="vessel_weight"):
        match_phase(run_a, run_b, only_vessels_a, only_vessels_b, objects="vessels", vessel_weight=0.0)
    with pytest.raises(vc.PhaseError, match="balloon"):
        match_phase(run_a, run_b, only_vessels_a, case.run_b.labels, objects="balloon")
    with pytest.raises(vc.ArgumentError, match="labels_b"):
        match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels[:3])
    with pytest.raises(vc.ArgumentError, match="objects"):
        match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, objects="stent")


def test_error_matrix_matches_pairwise_hand_triangulation():
    va = vc.CArmView(primary_deg=0, secondary_deg=0, sid_mm=1100, sod_mm=750,
                     pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512)
    vb = vc.CArmView(primary_deg=30, secondary_deg=0, sid_mm=1100, sod_mm=750,
                     pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512)
    rng = np.random.default_rng(0)
    pa, pb = rng.uniform(100, 400, (7, 2)), rng.uniform(100, 400, (5, 2))
    m = error_matrix(va, pa, vb, pb)
    for i in range(7):
        for j in range(5):
            oa, da = va.ray(pa[i])
            ob, db = vb.ray(pb[j])
            # closest points by solving the 2x2 normal equations
            A = np.array([[da @ da, -da @ db], [da @ db, -db @ db]])
            t, s = np.linalg.solve(A, [(ob - oa) @ da, (ob - oa) @ db])
            X = 0.5 * (oa + t * da + ob + s * db)
            e = max(np.linalg.norm(va.project(X) - pa[i]), np.linalg.norm(vb.project(X) - pb[j]))
            assert m[i, j] == pytest.approx(e * 0.4 * 750 / 1100, rel=1e-9, abs=1e-9)


def test_ecg_phase_from_r_waves_tracks_the_true_cardiac_phase():
    case = generate_case(2, "rca", n_frames=40, rows=64, cols=64)
    run_a, _ = case.xa_runs()
    ph = ecg_phase(run_a)
    assert ph is not None
    true = case.run_a.phases[:, 0]
    d = np.abs(ph - true)
    # R-waves are known to the nearest frame (15 fps at 55-100 bpm: half a frame <= 0.056 cycle).
    assert np.max(np.minimum(d, 1 - d)) < 0.07


def _ecg_run(r_wave_ms, n=60, fps=15.0):
    """A tiny run whose RWavePointer holds the frame nearest to each R-wave time."""
    t = np.arange(n) * 1000.0 / fps
    frames = np.zeros((n, 8, 8), np.uint8)
    view = vc.CArmView(0.0, 0.0, 1100.0, 750.0, (0.4, 0.4), 8, 8)
    r = np.asarray(r_wave_ms)
    return vc.XARun(frames, view, t, r_wave_frames=np.rint(r / t[1]).astype(int)), t


def test_ecg_phase_of_a_steady_rhythm_averages_the_frame_rounding_out():
    # 73 bpm at 15 fps: RR is 12.33 frames, so each R-wave is rounded by a different fraction of a frame.
    rr, t0 = 60000.0 / 73.0, 137.0
    run, t = _ecg_run(t0 + rr * np.arange(5))
    true = np.mod((t - t0) / rr, 1.0)
    fitted, per_beat = ecg_phase(run), ecg_phase(run, steady_tolerance=0.0)

    def err(p):
        d = np.abs(p - true)
        return np.minimum(d, 1 - d)

    # Rounding alone moves an R-wave by up to half a frame, 0.5 / 12.33 = 0.041 cycle.
    assert err(per_beat).max() > 0.02
    assert err(fitted).max() < 0.5 * err(per_beat).max()
    assert err(fitted).max() < 0.02


def test_ecg_phase_of_an_irregular_rhythm_interpolates_between_r_waves():
    # RR alternating 600 / 1000 ms (e.g. bigeminy): no straight line fits, so each beat is its own cycle.
    r = np.cumsum([200.0, 600.0, 1000.0, 600.0, 1000.0])
    run, t = _ecg_run(r)
    ph = ecg_phase(run)
    frames = run.r_wave_frames
    tr = t[frames]
    assert np.allclose(ph[frames], 0.0)  # every R-wave frame starts a cycle
    mid = frames[1] + 4  # 4 frames (267 ms) into the 600 ms beat that starts at frame 12 (800 ms)
    assert ph[mid] == pytest.approx((t[mid] - tr[1]) / (tr[2] - tr[1]))


def test_ecg_fixes_the_cardiac_phase_of_the_chosen_pair():
    case = generate_case(11, "rca", n_frames=40, rows=256, cols=256)
    run_a, run_b = case.xa_runs()
    pa, pb = case.run_a.phases[:, 0], case.run_b.phases[:, 0]
    m = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, use_ecg=True, vessel_weight=0.0)
    assert m.ecg and m.window == 0 and m.to_dict()["window"] == 0
    d = abs(pa[m.frame_a] - pb[m.frame_b])
    assert min(d, 1 - d) <= 0.05  # true cardiac phases within 5 % of a cycle
    image_only = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, use_ecg=False,
                             vessel_weight=0.0)
    assert not image_only.ecg and image_only.window == 4 and image_only.consistency is None
    # By default the vessels replace the ECG (window 0).
    default = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    assert not default.ecg and default.window == 0 and default.consistency is not None


def test_unusable_pairs_name_their_cause(sync_cs):
    case, run_a, run_b = sync_cs
    la, lb = case.run_a.labels, case.run_b.labels
    # The same run twice: every pair of rays coincides, nothing can be triangulated.
    with pytest.raises(vc.PhaseError, match="cannot be triangulated"):
        match_phase(run_a, run_a, la, la)
    # The balloon in only two frames of run A: no diagonal of five pairs for the image-only window.
    few = la.copy()
    few[2:][few[2:] == LABELS["balloon"]] = LABELS["background"]
    with pytest.raises(vc.PhaseError, match="window"):
        match_phase(run_a, run_b, few, lb, objects="balloon", use_ecg=False, vessel_weight=0.0,
                    min_contrast=0.0, prefer_fill=1.1)
    m = match_phase(run_a, run_b, few, lb, objects="balloon", use_ecg=False, vessel_weight=0.0, window=0,
                    min_contrast=0.0, prefer_fill=1.1)
    assert m.frame_a in (0, 1)


def test_match_phase_rejects_bad_ecg_arguments(sync_cs):
    case, run_a, run_b = sync_cs
    with pytest.raises(vc.VesselcadError, match="ecg_tolerance"):
        match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, ecg_tolerance=0.0)
    with pytest.raises(vc.VesselcadError, match="ecg_weight"):
        match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, ecg_weight=-1.0)
    with pytest.raises(vc.VesselcadError, match="steady_tolerance"):
        ecg_phase(run_a, steady_tolerance=-1.0)
    with pytest.raises(vc.VesselcadError, match="run"):
        ecg_phase("a.dcm")


def test_unsynchronized_matching_beats_frame_zero_and_plots(tmp_path):
    case = generate_case(9, "cs", n_frames=40, rows=256, cols=256)
    run_a, run_b = case.xa_runs()
    m = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    assert m.error_mm < m.matrix[0, 0]
    assert m.error_mm <= np.nanmedian(m.matrix)
    assert 0.0 <= m.confidence <= 1.0 and m.runner_up is not None
    png = plot_error_matrix(m, tmp_path / "phase.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    forced = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, pair=(0, 0))
    assert (forced.frame_a, forced.frame_b) == (0, 0)
    assert forced.error_mm == pytest.approx(m.matrix[0, 0])


def test_cli_demo_runs_end_to_end(tmp_path, capsys):
    import json

    import trimesh

    from vesselcad.cli import main

    code = main(["demo", "--out", str(tmp_path), "--frames", "12", "--size", "384", "--anatomy", "cs",
                 "--labels", "truth", "--json", "--quiet"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    for name in ("run_a.dcm", "run_b.dcm", "truth.json", "preview.png", "phase.png", "demo.json",
                 "overlay.png", "report.json", "report.html", "centrelines.json"):
        assert (tmp_path / name).is_file(), name
    report = json.loads((tmp_path / "report.json").read_text())
    assert 0 <= report["frame_a"] < 12 and 0 <= report["frame_b"] < 12
    assert summary["frames"] == [report["frame_a"], report["frame_b"]]
    # scored against the phantom's truth by the independent metric
    t = summary["truth"]
    assert 0.0 <= t["coverage"] <= 1.0 and t["truth_length_mm"] > 100
    if (tmp_path / "tree.stl").is_file():
        assert trimesh.load(tmp_path / "tree.stl").is_watertight
        assert summary["solid_tree_share"] == report["solid"]["tree_share"]


def test_pair_choice_prefers_filled_frames():
    # seed 2000 (lca, 40 frames): without the fill preference the best phase pair has a frame below
    # 90 % of its run's largest vessel area (run B at 89 %, in wash-in or wash-out).
    case = generate_case(2000, "lca", 40, rows=256, cols=256)
    ra, rb = case.xa_runs()
    la, lb = case.run_a.labels, case.run_b.labels
    area_a = (la == 1).sum(axis=(1, 2)) / (la == 1).sum(axis=(1, 2)).max()
    area_b = (lb == 1).sum(axis=(1, 2)) / (lb == 1).sum(axis=(1, 2)).max()
    off = match_phase(ra, rb, la, lb, prefer_fill=1.1)
    assert min(area_a[off.frame_a], area_b[off.frame_b]) < 0.9
    m = match_phase(ra, rb, la, lb)
    assert area_a[m.frame_a] >= 0.9 and area_b[m.frame_b] >= 0.9
    assert m.to_dict()["fill"] == [round(float(area_a[m.frame_a]), 3), round(float(area_b[m.frame_b]), 3)]
    # Still a pair at the same motion phase: the two frames' true trees agree (both frames are in
    # diastasis, 0.25 cycle apart, where the phantom's heart is still).
    tree_a = np.vstack([b["points"] for b in case.run_a.trees[m.frame_a]["branches"]])
    tree_b = np.vstack([b["points"] for b in case.run_b.trees[m.frame_b]["branches"]])
    assert np.mean(np.linalg.norm(tree_a - tree_b, axis=1)) < 0.5
    with pytest.raises(vc.ArgumentError, match="prefer_fill"):
        match_phase(ra, rb, la, lb, prefer_fill=-1)


def _curve_masks(view, curves, thickness=3):
    """Binary masks (N, H, W) of 3D polylines drawn in one view."""
    import cv2

    out = np.zeros((len(curves), view.rows, view.cols), np.uint8)
    for k, c in enumerate(curves):
        q = np.round(view.project(c)).astype(np.int32)
        cv2.polylines(out[k], [q.reshape(-1, 1, 2)], False, 1, thickness)
    return out


def test_epipolar_consistency_sees_motion_across_the_planes_but_not_along_the_baseline():
    # A wavy 3D vessel (it turns back within the pencil of epipolar planes several times) seen at
    # 30 degrees apart; in run B it is moved 5 mm along the baseline (each point stays in its
    # plane: nothing to see) or 2 mm across the planes (the turning points move to other planes).
    va = vc.CArmView(0.0, 0.0, 1100.0, 750.0, (0.4, 0.4), 384, 384)
    vb = vc.CArmView(30.0, 0.0, 1100.0, 750.0, (0.4, 0.4), 384, 384)
    s = np.linspace(-40, 40, 800)
    curve = np.column_stack([s, 10 * np.sin(s / 6.0), 25 * np.sin(s / 9.0)])
    base = (vb.source - va.source) / np.linalg.norm(vb.source - va.source)
    across = np.cross(base, -va.source)
    across /= np.linalg.norm(across)  # normal of the epipolar plane through the isocentre
    la = _curve_masks(va, [curve])
    lb = _curve_masks(vb, [curve, curve + 5.0 * base, curve + 2.0 * across])
    c = epipolar_consistency(va, la, vb, lb)
    assert c.shape == (1, 3)
    assert c[0, 0] < 0.05  # the same tree: the same crossings on (nearly) every line
    assert c[0, 1] < c[0, 0] + 0.03  # along the baseline: unchanged
    assert c[0, 2] > c[0, 0] + 0.1  # across the planes: seen
    with pytest.raises(vc.VesselcadError, match="n_lines"):
        epipolar_consistency(va, la, vb, lb, n_lines=2)
    with pytest.raises(vc.VesselcadError, match="epipolar planes"):
        epipolar_consistency(va, la, va, la)
    with pytest.raises(vc.VesselcadError, match="labels_b"):
        epipolar_consistency(va, la, vb, lb[:, :100])


def test_vessels_choose_a_pair_whose_trees_agree():
    # Unsynchronized coronary sinus runs: the balloon key point and the ECG pick frames whose true
    # trees are 1.3 mm apart; with the vessel crossings the chosen trees agree within 0.5 mm.
    case = generate_case(14, "cs", n_frames=40, rows=256, cols=256)
    run_a, run_b = case.xa_runs()
    m = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    tree_a = np.vstack([b["points"] for b in case.run_a.trees[m.frame_a]["branches"]])
    tree_b = np.vstack([b["points"] for b in case.run_b.trees[m.frame_b]["branches"]])
    assert np.mean(np.linalg.norm(tree_a - tree_b, axis=1)) < 0.5
    assert m.vessel_weight == 10.0 and not m.ecg
    assert m.to_dict()["vessel_consistency"] == pytest.approx(m.consistency[m.frame_a, m.frame_b], abs=1e-4)
    with pytest.raises(vc.VesselcadError, match="vessel_weight"):
        match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, vessel_weight=-1.0)


def test_vessels_alone_choose_the_pair_without_a_stationary_object(tmp_path):
    # A real run often shows no usable catheter tip (it leaves the field, or the segmentation calls its
    # filled end vessel). The vessels' epipolar consistency alone must still find frames whose true
    # trees agree (the phantom's truth: same vessel points in both runs' frames).
    case = generate_case(14, "cs", n_frames=40, rows=256, cols=256)
    run_a, run_b = case.xa_runs()
    vessels_a = np.where(case.run_a.labels == LABELS["vessel"], 1, 0).astype(np.uint8)
    vessels_b = np.where(case.run_b.labels == LABELS["vessel"], 1, 0).astype(np.uint8)
    m = match_phase(run_a, run_b, vessels_a, vessels_b)
    forced = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels, objects="vessels")
    assert (m.frame_a, m.frame_b) == (forced.frame_a, forced.frame_b)
    assert any("no stationary object" in w for w in m.warnings)
    assert not forced.objects and not any("no stationary object" in w for w in forced.warnings)
    tree_a = np.vstack([b["points"] for b in case.run_a.trees[m.frame_a]["branches"]])
    tree_b = np.vstack([b["points"] for b in case.run_b.trees[m.frame_b]["branches"]])
    assert np.mean(np.linalg.norm(tree_a - tree_b, axis=1)) < 0.5
    assert np.isnan(m.error_mm) and np.isnan(m.matrix).all() and "vessels" in m.basis
    summary = m.to_dict()
    json.dumps(summary, allow_nan=False)  # report.json stays valid JSON: no NaN
    assert summary["error_mm"] is None and summary["point_mm"] is None and summary["objects"] == []
    assert plot_error_matrix(m, tmp_path / "phase.png").stat().st_size > 1000


def test_the_phase_picture_of_short_runs_numbers_whole_frames(tmp_path, monkeypatch):
    # Runs of a few frames (or one still image each): the axes give frame numbers, never 0.5.
    import matplotlib.figure

    case = generate_case(3, "lca", n_frames=3, rows=128, cols=128)
    run_a, run_b = case.xa_runs()
    m = match_phase(run_a, run_b, case.run_a.labels, case.run_b.labels)
    ticks = []

    def savefig(fig, *args, **kwargs):
        for ax in fig.axes:
            if ax.get_xlabel() == "frame of run B":
                lo_x, hi_x = sorted(ax.get_xlim())
                lo_y, hi_y = sorted(ax.get_ylim())
                ticks.extend(t for t in ax.get_xticks() if lo_x <= t <= hi_x)
                ticks.extend(t for t in ax.get_yticks() if lo_y <= t <= hi_y)
        return original(fig, *args, **kwargs)

    original = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    plot_error_matrix(m, tmp_path / "phase.png")
    assert len(ticks) >= 4
    assert all(float(t).is_integer() for t in ticks)
