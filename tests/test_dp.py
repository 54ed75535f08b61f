"""The matching's compiled dynamic programs (vesselcad._dp) against their definitions."""

from __future__ import annotations

import numpy as np
import pytest

import vesselcad as vc
from vesselcad import continuation as cont
from vesselcad.epipolar import backtrack
from vesselcad.matching import CAP_MM, CAP_PX, LENGTH_WEIGHT, _dtw, _pair_errors

VIEW_A = vc.CArmView(primary_deg=30.0, secondary_deg=0.0, sid_mm=1100.0, sod_mm=750.0,
                     pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512)
VIEW_B = vc.CArmView(primary_deg=-30.0, secondary_deg=25.0, sid_mm=1100.0, sod_mm=750.0,
                     pixel_spacing_mm=(0.4, 0.4), rows=512, cols=512)


def dtw_by_definition(E, X):
    """D[i, j]: the cheapest monotone path from (0, 0), cell by cell (no array tricks)."""
    n, m = E.shape
    step = lambda p, q: LENGTH_WEIGHT * min(float(np.linalg.norm(X[p] - X[q])), CAP_MM)  # noqa: E731
    D = np.full((n, m), np.inf)
    D[0, 0] = 2.0 * E[0, 0]
    for i in range(n):
        for j in range(m):
            if i == j == 0:
                continue
            best = np.inf
            if i > 0:
                best = min(best, D[i - 1, j] + E[i, j] + step((i, j), (i - 1, j)))
            if j > 0:
                best = min(best, D[i, j - 1] + E[i, j] + step((i, j), (i, j - 1)))
            if i > 0 and j > 0:
                best = min(best, D[i - 1, j - 1] + 2.0 * E[i, j] + step((i, j), (i - 1, j - 1)))
            D[i, j] = best
    return D


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (6, 1), (5, 9), (11, 4), (8, 8)])
def test_dtw_follows_its_recursion(shape):
    rng = np.random.default_rng(sum(shape))
    E = rng.uniform(0.0, 3.0, shape)
    X = rng.normal(0.0, 4.0, shape + (3,))  # steps of ~7 mm: some capped at CAP_MM
    np.testing.assert_allclose(_dtw(E, X), dtw_by_definition(E, X), rtol=0, atol=1e-9)


def test_backtrack_walks_the_cheapest_steps_back_to_the_start():
    # A staircase of zero cost through a matrix of ones: (0,0) (1,1) (1,2) (2,3) (3,3) (4,4).
    path = [(0, 0), (1, 1), (1, 2), (2, 3), (3, 3), (4, 4)]
    E = np.ones((5, 5))
    for p in path:
        E[p] = 0.0
    pi, pj = backtrack(dtw_by_definition(E, np.zeros((5, 5, 3))))
    assert list(zip(pi.tolist(), pj.tolist(), strict=True)) == path


def test_backtrack_prefers_the_diagonal_among_equals_and_runs_along_the_edges():
    pi, pj = backtrack(np.zeros((3, 4)))
    assert list(zip(pi.tolist(), pj.tolist(), strict=True)) == [(0, 0), (0, 1), (1, 2), (2, 3)]
    pi, pj = backtrack(np.zeros((1, 3)))
    assert pi.tolist() == [0, 0, 0] and pj.tolist() == [0, 1, 2]
    with pytest.raises(vc.ArgumentError, match="D"):
        backtrack(np.zeros((0, 3)))


def test_pair_errors_of_true_correspondences_are_zero_at_the_3d_point():
    rng = np.random.default_rng(3)
    P = rng.uniform(-40.0, 40.0, (7, 3))
    qa, qb = VIEW_A.project(P), VIEW_B.project(P)
    E, X = _pair_errors(VIEW_A, qa, VIEW_B, qb)
    assert E.shape == (7, 7) and X.shape == (7, 7, 3)
    np.testing.assert_allclose(np.diag(E), 0.0, atol=1e-6)
    np.testing.assert_allclose(X[np.arange(7), np.arange(7)], P, atol=1e-6)
    # Every other pair: the numpy reconstruction error (geometry module), capped.
    ref = vc.reconstruction_error(VIEW_A, qa[:, None], VIEW_B, qb[None])
    np.testing.assert_allclose(E, np.minimum(ref.error_px, CAP_PX), rtol=0, atol=1e-9)
    np.testing.assert_allclose(X, ref.points_mm, rtol=0, atol=1e-9)
    assert E.max() == CAP_PX  # points tens of mm apart disagree by more than the cap


def test_pair_errors_of_parallel_rays_are_the_cap_far_away():
    q = np.array([[256.0, 256.0], [100.0, 300.0]])
    E, X = _pair_errors(VIEW_A, q, VIEW_A, q)  # one view twice: every ray pair is parallel or skew
    assert E[0, 0] == CAP_PX and E[1, 1] == CAP_PX
    assert np.all(X[[0, 1], [0, 1]] == 1e6)


def toy_chains():
    """View B: branch 0 (samples 0-4) meets branches 1 (5-9) and 2 (10-14) at one branch point.

    Samples 4, 5 and 10 are that branch point; chain 2k walks branch k forward, 2k + 1 back.
    """
    idx = np.array([[0, 1, 2, 3, 4], [4, 3, 2, 1, 0], [5, 6, 7, 8, 9], [9, 8, 7, 6, 5],
                    [10, 11, 12, 13, 14], [14, 13, 12, 11, 10]])
    start = np.array([0, 1, 1, 2, 1, 3])
    end = np.array([1, 0, 2, 1, 3, 1])
    succ = [[d for d in range(6) if start[d] == end[c] and d // 2 != c // 2] for c in range(6)]
    pred = [[c for c in range(6) if d in succ[c]] for d in range(6)]
    pts = np.zeros((15, 2))
    return cont.Chains(pts, np.ones(15), np.repeat(np.arange(3), 5), np.tile(np.arange(5.0), 3), idx,
                       np.full(6, 5), start, end, succ, pred)


def toy_errors():
    """View A's samples 0-8 run along branch 0 and then branch 2 of view B (error 0.1, else 5)."""
    pos_b = np.r_[np.arange(5), np.arange(4, 9), np.arange(4, 9)]  # position along the vessel
    on_2 = np.r_[np.ones(5, bool), np.zeros(5, bool), np.ones(5, bool)]
    E = np.where((np.arange(9)[:, None] == pos_b[None]) & on_2[None], 0.1, 5.0)
    Ep = np.full((10, 16), CAP_PX)
    Ep[:-1, :-1] = E
    return cont.SampleErrors(Ep, np.zeros((10, 16, 3)), np.arange(9), np.arange(15))


def test_alignment_follows_view_b_through_its_branch_point():
    chb, se = toy_chains(), toy_errors()
    res = cont._align(se, chb, np.zeros(15, bool), np.arange(9), 0, 0, 1.0)
    assert res is not None
    score, ia, ib, err = res
    assert score < 0
    # Along branch 0, a B-advance through the branch point onto branch 2, then along it.
    assert ia.tolist() == [0, 1, 2, 3, 4, 4, 5, 6, 7, 8]
    assert ib.tolist() == [0, 1, 2, 3, 4, 10, 11, 12, 13, 14]
    np.testing.assert_allclose(err, 0.1)
    # The same with the roles of the views swapped (transposed tables).
    se_ba = cont.SampleErrors(np.ascontiguousarray(se.E.T), np.ascontiguousarray(se.X.transpose(1, 0, 2)),
                              se.map_b, se.map_a)
    assert se_ba.T.swapped
    res_t = cont._align(se_ba.T, chb, np.zeros(15, bool), np.arange(9), 0, 0, 1.0)
    assert res_t[1].tolist() == ia.tolist() and res_t[2].tolist() == ib.tolist()


def test_alignment_stops_before_a_sample_already_paired():
    chb, se = toy_chains(), toy_errors()
    used = np.zeros(15, bool)
    used[12] = True
    _, ia, ib, _ = cont._align(se, chb, used, np.arange(9), 0, 0, 1.0)
    assert 12 not in ib.tolist()
    assert ib.tolist() == [0, 1, 2, 3, 4, 10, 11]


def test_without_a_writable_cache_folder_the_kernels_still_compile(monkeypatch):
    # numba refuses cache=True at import where no folder is writable (read-only install and home):
    # every folder it tries reports that it cannot be written.
    from numba.core import caching

    from vesselcad._dp import _compiled

    def unwritable(self):
        raise PermissionError(13, "Permission denied", self.get_cache_path())

    monkeypatch.setattr(caching._CacheLocator, "ensure_cache_path", unwritable)
    with pytest.raises(RuntimeError, match="no locator"):
        caching.FunctionCache(lambda x: x)

    def twice(x):
        return 2.0 * x

    fn = _compiled(twice)
    assert fn(1.5) == 3.0
    assert fn._cache.__class__.__name__ == "NullCache"
