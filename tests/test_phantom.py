"""The phantom against its own ground truth: labels, key points, determinism, anatomy ranges."""

import json

import numpy as np
import pytest

import vesselcad as vc
from vesselcad.cli import main
from vesselcad.phantom import LABELS, generate_case, render, write_case
from vesselcad.phantom.anatomy import make_anatomy


@pytest.fixture(scope="module", params=["lca", "rca", "cs"])
def case(request):
    return generate_case(11, request.param, n_frames=10)


def _tree_samples(tree):
    return np.concatenate([np.asarray(b["points"]) for b in tree["branches"]])


def test_truth_trees_project_onto_vessel_masks(case):
    truth = case.truth()
    for tag in ("a", "b"):
        rr = getattr(case, f"run_{tag}")
        view = vc.CArmView.from_dict(truth[f"view_{tag}"])
        i = int(np.argmax((rr.labels == LABELS["vessel"]).sum(axis=(1, 2))))  # fullest opacification
        px = view.project(_tree_samples(truth[f"trees_{tag}"][i]))
        ij = np.round(px).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < view.cols) & (ij[:, 1] >= 0) & (ij[:, 1] < view.rows)
        assert ok.mean() > 0.9  # the tree is in the field of view
        lab = rr.labels[i][ij[ok, 1], ij[ok, 0]]
        # Devices lie in front of (or inside) vessels and take their pixels: the catheter
        # tip in the ostium, the CS catheter up to its balloon. Those samples are few.
        hidden = lab >= LABELS["catheter"]
        assert hidden.mean() <= 0.15, (case.anatomy_kind, tag, hidden.mean())
        on_vessel = lab[~hidden] == LABELS["vessel"]
        assert on_vessel.mean() >= 0.98, (case.anatomy_kind, tag, on_vessel.mean())


def test_keypoints_project_onto_the_stationary_object(case):
    want = LABELS["balloon"] if case.anatomy_kind == "cs" else LABELS["catheter"]
    for rr in (case.run_a, case.run_b):
        ij = np.round(rr.keypoints).astype(int)
        got = rr.labels[np.arange(len(ij)), ij[:, 1], ij[:, 0]]
        assert np.all(got == want)


def test_keypoints_are_the_projection_of_the_3d_object(case):
    # Synchronized truth check: the key point of frame i in both runs triangulates with
    # error ~0 only when the phases match; unsynchronized runs give a clear error.
    truth = case.truth()
    va, vb = (vc.CArmView.from_dict(truth[k]) for k in ("view_a", "view_b"))
    ka, kb = np.asarray(truth["keypoints_a"]), np.asarray(truth["keypoints_b"])
    err = vc.reconstruction_error(va, ka[:, None], vb, kb[None]).error_mm
    assert err.shape == (10, 10) and np.all(np.isfinite(err))
    assert err.max() > 0.5  # runs at different phases do not triangulate consistently


def test_error_is_zero_when_synchronized_and_grows_with_phase_offset():
    c = generate_case(4, "cs", n_frames=40, synchronized=True, rows=128, cols=128)
    t = c.truth()
    assert t["phases_a"] == t["phases_b"] and t["trees_a"] == t["trees_b"]
    va, vb = (vc.CArmView.from_dict(t[k]) for k in ("view_a", "view_b"))
    ka, kb = np.asarray(t["keypoints_a"]), np.asarray(t["keypoints_b"])
    err = vc.reconstruction_error(va, ka[:, None], vb, kb[None]).error_mm
    assert np.diag(err).max() < 1e-3  # truth key points are rounded to 1e-4 px
    ph = np.asarray(t["phases_a"])
    circ = lambda d: np.minimum(np.abs(d), 1 - np.abs(d))  # noqa: E731
    dist = circ(ph[:, None, 0] - ph[None, :, 0]) + circ(ph[:, None, 1] - ph[None, :, 1])
    bins = [err[(dist >= lo) & (dist < hi)].mean() for lo, hi in ((0, 0.05), (0.05, 0.2), (0.2, 2))]
    assert bins[0] < bins[1] < bins[2], bins


def test_same_seed_same_bytes(tmp_path):
    for d in ("one", "two"):
        write_case(generate_case(7, "cs", n_frames=4, rows=96, cols=96), tmp_path / d)
    names = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert names == ["labels_a.npz", "labels_b.npz", "run_a.dcm", "run_b.dcm", "truth.json"]
    for n in names:
        assert (tmp_path / "one" / n).read_bytes() == (tmp_path / "two" / n).read_bytes(), n
    other = generate_case(8, "cs", n_frames=4, rows=96, cols=96)
    assert not np.array_equal(other.run_a.frames, generate_case(7, "cs", n_frames=4, rows=96,
                                                                cols=96).run_a.frames)


def test_written_case_reads_back(tmp_path):
    c = generate_case(2, "lca", n_frames=6, rows=128, cols=128, bits=12, miscalibration_deg=2.0)
    write_case(c, tmp_path)
    run_a = vc.load_run(tmp_path / "run_a.dcm")
    assert run_a.frames.dtype == np.uint16 and run_a.frames.max() <= 4095 and run_a.bits_stored == 12
    np.testing.assert_array_equal(run_a.frames, c.run_a.frames)
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert run_a.view == vc.CArmView.from_dict(truth["header_view_a"])
    true_a = vc.CArmView.from_dict(truth["view_a"])
    assert abs(run_a.view.primary_deg - true_a.primary_deg) <= 2.0
    assert abs(run_a.view.secondary_deg - true_a.secondary_deg) <= 2.0
    assert truth["frames"] == 6 and len(truth["trees_a"]) == 6 and len(truth["keypoints_b"]) == 6
    tree = truth["trees_a"][0]
    assert tree["units"] == "mm" and tree["frame"] == "LPS"
    ph = np.asarray(truth["phases_a"])
    assert ph.shape == (6, 2) and np.all((ph >= 0) & (ph < 1))
    labels = np.load(tmp_path / "labels_a.npz")["labels"]
    assert labels.shape == (6, 128, 128) and set(np.unique(labels)) <= set(range(5))
    # The R-wave frames in the header are the frames nearest to cardiac phase 0.
    c = generate_case(2, "rca", n_frames=30, rows=64, cols=64)
    run = c.xa_runs()[0]
    ph_c = c.run_a.phases[:, 0]
    step = np.median(np.diff(ph_c) % 1.0)
    wraps = (np.diff(ph_c) < 0).sum()
    assert run.r_wave_frames is not None and wraps <= len(run.r_wave_frames) <= wraps + 1
    assert np.all(np.minimum(ph_c[run.r_wave_frames], 1 - ph_c[run.r_wave_frames]) <= step / 2 + 1e-9)


@pytest.mark.parametrize("kind", ["lca", "rca", "cs"])
def test_anatomy_ranges(kind):
    for seed in range(6):
        an = make_anatomy(np.random.default_rng(seed), kind)
        assert 8 <= len(an.vessels) <= 30
        radii = np.concatenate([v.radius for v in an.vessels])
        assert radii.min() >= 0.8 - 1e-9 and radii.max() <= 2.5 + 1e-9
        for v in an.vessels:
            if v.parent is not None:  # children start on their parent's centreline
                np.testing.assert_allclose(v.points[0], an.vessels[v.parent].points[v.parent_index])
            seg = np.diff(v.points, axis=0)
            t = seg / np.linalg.norm(seg, axis=1, keepdims=True)
            turn = np.arccos(np.clip((t[1:] * t[:-1]).sum(1), -1, 1))
            step = np.linalg.norm(seg, axis=1)[1:]
            assert np.all(turn / step < 1 / 6.0), v.name  # curvature radius above 6 mm


def test_render_api_for_training():
    rr = render(3, n_frames=2, rows=96, cols=96)
    assert rr.frames.shape == (2, 96, 96) and rr.labels.shape == (2, 96, 96)
    assert (rr.labels == LABELS["vessel"]).any()


def test_bad_arguments():
    with pytest.raises(vc.ArgumentError, match="anatomy"):
        generate_case(1, "aorta")
    with pytest.raises(vc.ArgumentError, match="bits"):
        generate_case(1, "lca", bits=10)


def test_cli_phantom(tmp_path, capsys):
    rc = main(["phantom", "--seed", "1", "--out", str(tmp_path), "--anatomy", "rca", "--frames", "3",
               "--size", "96", "--preview", "--quiet"])
    assert rc == 0
    assert {p.name for p in tmp_path.iterdir()} >= {"run_a.dcm", "run_b.dcm", "truth.json",
                                                     "labels_a.npz", "labels_b.npz", "preview.png"}
    assert main(["phantom", "--seed", "1", "--out", str(tmp_path), "--frames", "0"]) == 2
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(vc.OutputError, match="a_file"):
        write_case(generate_case(1, "lca", n_frames=1, rows=64, cols=64), blocker / "sub")


def test_children_start_on_their_parent_in_every_frame(case):
    for tree in (case.truth()["trees_a"][0], case.truth()["trees_b"][-1]):
        branches = tree["branches"]
        for b in branches:
            if b["parent"] is None:
                continue
            parent = np.asarray(branches[b["parent"]]["points"])
            gap = np.linalg.norm(parent - np.asarray(b["points"][0]), axis=1).min()
            assert gap < 0.6  # parent polyline stored every 1 mm; the start lies on its curve
            assert 0 <= b["parent_s_mm"] <= len(parent) + 1


def test_twigs_set_the_number_of_small_side_branches():
    def names(twigs):
        case = generate_case(5, "lca", n_frames=1, rows=64, cols=64, twigs=twigs)
        return [b["name"] for b in case.run_a.trees[0]["branches"]]

    named = names(0)
    assert named and not any("-t" in n for n in named)  # the named vessels only
    default, many = names(None), names(30)
    assert default[: len(named)] == named and any("-t" in n for n in default)
    assert len(named) < len(default) < len(many) <= 30
    for bad in (-1, 31, 2.5, "5", True):
        with pytest.raises(vc.ArgumentError, match="twigs"):
            generate_case(5, "lca", n_frames=1, rows=64, cols=64, twigs=bad)


def test_visible_share_of_the_truth_in_two_frames(case):
    from vesselcad.phantom.compare import visible_share

    i = int(np.argmax((case.run_a.labels == LABELS["vessel"]).sum(axis=(1, 2))))
    full = visible_share(case, i, i)
    assert full >= 0.85, (case.anatomy_kind, full)  # the fullest frames show nearly the whole tree
    saved = case.run_b.labels[i].copy()
    try:
        case.run_b.labels[i][:] = LABELS["background"]
        assert visible_share(case, i, i) == 0.0  # nothing shown in view B: nothing to reconstruct
        # View B shows only its left half: about the tree's length projected there.
        half = case.run_b.view.cols // 2
        case.run_b.labels[i][:] = saved
        case.run_b.labels[i][:, half:] = LABELS["background"]
        tree = case.run_a.trees[i]
        seg_len, left = 0.0, 0.0
        for b, bb in zip(tree["branches"], case.run_b.trees[i]["branches"], strict=True):
            p = np.asarray(b["points"], float)
            q = case.run_b.view.project(np.asarray(bb["points"], float))
            seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
            seg_len += seg.sum()
            left += seg[(q[:-1, 0] < half - 2) & (q[1:, 0] < half - 2)].sum()
        got = visible_share(case, i, i)
        assert got <= full and abs(got - full * left / seg_len) < 0.08, (got, full, left / seg_len)
    finally:
        case.run_b.labels[i][:] = saved


def test_visible_share_bad_frames():
    from vesselcad.phantom.compare import visible_share

    c = generate_case(3, "rca", n_frames=2, rows=64, cols=64)
    for bad in (2, -1, 1.0, True):
        with pytest.raises(vc.ArgumentError, match="frame_a"):
            visible_share(c, bad, 0)
    with pytest.raises(vc.ArgumentError, match="max_gap_px"):
        visible_share(c, 0, 0, max_gap_px=-1)


def test_truth_comparison_measures_distances_to_the_curves_not_to_their_samples(case):
    from types import SimpleNamespace

    from vesselcad.phantom.compare import compare_with_truth
    from vesselcad.splines import resample_by_arclength

    i = 0
    truth = case.run_a.trees[i]["branches"]
    # A "reconstruction" of the first branches lying exactly on the true curves, sampled at a
    # step that falls between the truth's own samples: its error is 0, not the half-step gap
    # to the nearest sample (up to 0.25 mm with 0.5 mm samples).
    chosen = [np.asarray(b["points"], float) for b in truth[:3]]
    rec = SimpleNamespace(phase=SimpleNamespace(frame_a=i, frame_b=i), match=SimpleNamespace(root_pair=None),
                          branches=[SimpleNamespace(ok=True, points_mm=resample_by_arclength(p, 0.37))
                                    for p in chosen])
    got = compare_with_truth(rec, case)
    assert got["mean_mm"] < 1e-6 and got["max_mm"] < 1e-6
    # Coverage: the share of the truth's length those branches make up (each other branch's
    # first one or two millimetres lie within 1 mm of its parent, which covers it too: allow that).
    length = [float(np.linalg.norm(np.diff(np.asarray(b["points"], float), axis=0), axis=1).sum())
              for b in truth]
    share = sum(length[:3]) / sum(length)
    assert share - 0.005 <= got["coverage"] <= share + 2.5 * len(truth) / sum(length)
    # Moved 3 mm off (beyond the 1 mm of the coverage), along one axis: every sample 3 mm or
    # less from the true curve (nearer where that curve runs along the axis), none covering it.
    moved = SimpleNamespace(**{**vars(rec), "branches": [
        SimpleNamespace(ok=True, points_mm=b.points_mm + [0.0, 0.0, 3.0]) for b in rec.branches]})
    off = compare_with_truth(moved, case)
    assert off["max_mm"] <= 3.0 + 1e-9 and off["mean_mm"] > 1.0


def test_error_anatomy_splits_the_error_and_the_missed_length_as_drawn():
    from types import SimpleNamespace

    from vesselcad.phantom.compare import error_anatomy

    def line(a, b, step=0.5):
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = int(round(np.linalg.norm(b - a) / step)) + 1
        return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)

    # Four true vessels, far apart but for the trunk and its child, which meet at (50, 0, 0).
    truth = [line([0, 0, 0], [100, 0, 0]),       # trunk, 100 mm
             line([50, 0, 0], [50, 60, 0]),      # its child, 60 mm
             line([0, -50, 0], [0, -50, 40]),    # 40 mm, paired wrongly only
             line([0, 100, 0], [60, 100, 0])]    # 60 mm, found from 30 mm on
    case = SimpleNamespace(run_a=SimpleNamespace(trees=[{"branches": [{"points": t} for t in truth]}]))
    recon = [line([0, 0, 0], [20.2, 0, 0]), line([40.2, 0, 0], [100, 0, 0]),   # a 20 mm gap
             line([50, 0, 0], [50, 30, 0]),                                    # stops half-way
             line([10, -50, 0], [10, -50, 40]),                               # 10 mm off its vessel
             line([30, 100, 0], [60, 100, 0])]                                # starts 30 mm late
    rec = SimpleNamespace(phase=SimpleNamespace(frame_a=0),
                          branches=[SimpleNamespace(ok=True, points_mm=p) for p in recon])
    got = error_anatomy(rec, case)
    # Samples every 0.5 mm along each reconstructed branch, its end included.
    n = [int(np.ceil(length / 0.5)) + 1 for length in (20.2, 59.8, 30, 40, 30)]
    # The off branch: 10 mm from the truth at every sample, the others on it.
    assert got["off_samples"] == pytest.approx(n[3] / sum(n), abs=1e-4)
    assert got["off_error"] == pytest.approx(1.0)
    assert got["mean_mm_without_off"] == pytest.approx(0.0, abs=1e-6)
    # Missed (farther than 5 mm from every reconstructed branch), as shares of the true length:
    # inside the gap 20.2-40.2 mm its middle 10 mm, the child's last 25 mm, the wrongly paired
    # vessel whole (40 mm), the late one's first 25 mm.
    total = 100 + 60 + 40 + 60
    tol = 2 * 0.5 / total  # a sample at each end of a run
    assert got["missed_inside"] == pytest.approx(10 / total, abs=tol)
    assert got["missed_distal"] == pytest.approx(25 / total, abs=tol)
    assert got["missed_whole"] == pytest.approx(40 / total, abs=tol)
    assert got["missed_proximal"] == pytest.approx(25 / total, abs=tol)
    assert got["missed"] == pytest.approx(100 / total, abs=4 * tol)
    # Nothing reconstructed: all of it missed, as whole branches.
    none = error_anatomy(SimpleNamespace(phase=rec.phase, branches=[]), case)
    assert none["missed"] == none["missed_whole"] == 1.0
    for bad in ({"off_mm": 0}, {"missed_mm": float("nan")}, {"step_mm": True}):
        with pytest.raises(vc.ArgumentError, match=next(iter(bad))):
            error_anatomy(rec, case, **bad)


def test_a_finer_grid_of_the_same_field_averaged_down_looks_like_the_coarse_one():
    # The same case rendered at 512 and 1024 px (one field, pixels half as large): the 1024-px
    # frame area averaged 2 x 2 has the 512-px frame's vessel edges (blur scaled with the grid)
    # and background noise (fewer photons a smaller pixel), within the phantom's own spread.
    import cv2

    def edge_and_noise(run):
        f, lab = run.frames[0].astype(np.float32), run.labels[0]
        if f.shape[0] != 512:
            f = cv2.resize(f, (512, 512), interpolation=cv2.INTER_AREA)
            lab = cv2.resize((lab == 1).astype(np.float32), (512, 512), interpolation=cv2.INTER_AREA) >= 0.5
        v = (lab == 1) if lab.dtype != bool else lab
        edge = v & ~cv2.erode(v.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        grad = np.hypot(cv2.Sobel(f, cv2.CV_32F, 1, 0), cv2.Sobel(f, cv2.CV_32F, 0, 1))
        background = ~cv2.dilate(v.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        return grad[edge].mean(), (f - cv2.GaussianBlur(f, (0, 0), 1.5))[background].std()

    coarse = edge_and_noise(generate_case(2001, "rca", n_frames=2).run_a)
    fine = edge_and_noise(generate_case(2001, "rca", n_frames=2, rows=1024, cols=1024).run_a)
    # measured 1.05 and 0.77 (with the blur and photons per pixel not scaled: edges 1.20 times as
    # steep); the noise's bounds are the spread of the phantom's photon counts (900-2500: 1.67x)
    assert 0.9 < fine[0] / coarse[0] < 1.1
    assert 0.6 < fine[1] / coarse[1] < 1.4


def test_another_noise_draw_changes_only_the_noise():
    # The same case with its quantum noise drawn again: labels, key points and true trees are the
    # same, the frames differ by zero-mean noise of the size of the phantom's own (a few grey levels).
    a = generate_case(9, "rca", n_frames=3, rows=128, cols=128)
    b = generate_case(9, "rca", n_frames=3, rows=128, cols=128, noise_draw=1)
    assert np.array_equal(generate_case(9, "rca", n_frames=3, rows=128, cols=128, noise_draw=0).run_a.frames,
                          a.run_a.frames)
    for ra, rb in ((a.run_a, b.run_a), (a.run_b, b.run_b)):
        assert np.array_equal(ra.labels, rb.labels) and np.array_equal(ra.keypoints, rb.keypoints)
        assert ra.trees == rb.trees
        d = rb.frames.astype(float) - ra.frames.astype(float)
        assert np.mean(d != 0) > 0.5  # every pixel drew its own noise
        assert abs(d.mean()) < 0.2 and 1.0 < d.std() < 10.0
    with pytest.raises(vc.ArgumentError, match="noise_draw"):
        generate_case(9, "rca", n_frames=1, rows=64, cols=64, noise_draw=-1)
