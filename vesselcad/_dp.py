"""Compiled dynamic programs of the cross-view matching (numba).

The continuation's anchored alignment (:func:`vesselcad.continuation._align`)
and the candidates' monotone alignment (:func:`vesselcad.matching._dtw`) run
row by row over small arrays: written with numpy, each row costs a few dozen
array calls and the matching spent most of its time in their overhead. Here
they are plain loops compiled by numba (cached on disk after the first call).

The dynamic programs do the same floating-point operations in the same
order as the array code they replace (cumulative sums and running minima left
to right, sums of three squares as ``(x*x + y*y) + z*z``). The error tables of
sample pairs (:func:`pair_errors`) agree with
:func:`vesselcad.geometry.reconstruction_error` to about 1e-13 px (the array
code's matrix products round differently); on 45 phantom cases the matches
were the same, but for one tie.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit


def _compiled(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba, cached on disk where numba finds a writable folder.

    numba looks beside this file, then in the user's cache folder (``NUMBA_CACHE_DIR``
    chooses another). Where none is writable (a read-only install and home) the
    functions are compiled afresh in each process instead of failing at import.
    """
    try:
        return njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True)(fn)


@_compiled
def _dist3(p0: float, p1: float, p2: float, q0: float, q1: float, q2: float, cap: float) -> float:
    d0, d1, d2 = p0 - q0, p1 - q1, p2 - q2
    return min(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), cap)


@_compiled
def _scan_rows(D0: np.ndarray, h: np.ndarray, ptr: np.ndarray, rows: int, D: np.ndarray) -> None:
    """``D[t] = min(D0[t], D[t-1] + h[t])`` per row as running sums and minima; pointer 3 where moved."""
    L = D0.shape[1]
    for k in range(rows):
        hc = 0.0
        m = np.inf
        for t in range(L):
            hc = h[k, 0] if t == 0 else hc + h[k, t]
            a = D0[k, t] - hc
            m = a if t == 0 else min(m, a)
            d = hc + m
            if d < D0[k, t] - 1e-12:
                ptr[k, t] = 3
            D[k, t] = min(d, D0[k, t])


@_compiled
def align(E: np.ndarray, X: np.ndarray, swapped: bool, map_a: np.ndarray, map_b: np.ndarray, idx: np.ndarray,
          n_len: np.ndarray, succ_m: np.ndarray, link_to: np.ndarray, link_from: np.ndarray,
          used_b: np.ndarray, a_seq: np.ndarray, cb: int, tb: int, tau: float, lw: float,
          b_share: float, stop_px: float, blocked_cost: float, cap_mm: float
          ) -> tuple[float, np.ndarray]:
    """Anchored local alignment (see :func:`vesselcad.continuation._align`).

    ``E`` and ``X`` are indexed ``[map_a[a], map_b[b]]``, or
    ``[map_b[b], map_a[a]]`` where ``swapped``. Returns the best score and
    the aligned cells ``(row of a_seq, chain,
    position)`` from the anchor on; no cells where nothing gains.
    """
    C, L = idx.shape
    n = a_seq.shape[0]
    inf = np.inf
    bt = b_share * tau
    shift = (b_share - 1.0) * tau
    blocked = np.empty((C, L), np.bool_)
    col = np.empty((C, L), np.int64)
    for c in range(C):
        for t in range(L):
            s = idx[c, t]
            if s >= 0:
                blocked[c, t] = used_b[s]
                col[c, t] = map_b[s]
            else:
                blocked[c, t] = True
                col[c, t] = map_b[0]
    last = n_len - 1
    # Moves into each cell: 1 A-advance, 2 diagonal, 3 B-advance, 4 / 5 through a branch point of
    # view B (diagonal / B-advance; the predecessor chain in jptr).
    ptr = np.zeros((n, C, L), np.int8)
    jptr = np.full((n, C, 2), -1, np.int64)
    D_prev = np.full((C, L), inf)
    D_prev[cb, tb] = 0.0
    X_prev = np.zeros((C, L, 3))
    alive = np.zeros(C, np.bool_)
    alive[cb] = True
    act_m = np.zeros(C, np.bool_)
    act = np.zeros(C, np.int64)
    prev_act = np.zeros(C, np.int64)
    n_prev = 0
    pos = np.zeros(C, np.int64)
    cc = np.empty((C, L))
    x = np.empty((C, L, 3))
    h = np.empty((C, L))
    D0 = np.empty((C, L))
    D = np.empty((C, L))
    ptr_i = np.zeros((C, L), np.int8)
    n_links = link_to.shape[0]
    sel = np.zeros(n_links, np.bool_)
    vv = np.empty(n_links)
    best = 0.0
    bi, bc, btt = -1, -1, -1
    rows = 0
    for i in range(n):
        # The chains in reach: those alive and the ones they lead into.
        for c in range(C):
            act_m[c] = alive[c]
        for c in range(C):
            if alive[c]:
                for d in range(C):
                    if succ_m[c, d]:
                        act_m[d] = True
        na = 0
        for c in range(C):
            if act_m[c]:
                act[na] = c
                pos[c] = na
                na += 1
        ra = map_a[a_seq[i]]
        # A step of view A earns tau, a step of view B b_share * tau: a longer path in view B
        # (another vessel beyond a branch point) is not preferred for its length alone.
        for k in range(na):
            ch = act[k]
            for t in range(L):
                cl = col[ch, t]
                i0, i1 = (cl, ra) if swapped else (ra, cl)
                x[k, t, 0] = X[i0, i1, 0]
                x[k, t, 1] = X[i0, i1, 1]
                x[k, t, 2] = X[i0, i1, 2]
                cc[k, t] = blocked_cost if blocked[ch, t] else E[i0, i1] - bt
            h[k, 0] = cc[k, 0] + lw * 0.0
            for t in range(1, L):
                h[k, t] = cc[k, t] + lw * _dist3(x[k, t, 0], x[k, t, 1], x[k, t, 2], x[k, t - 1, 0],
                                                 x[k, t - 1, 1], x[k, t - 1, 2], cap_mm)
        for k in range(na):
            ch = act[k]
            for t in range(L):
                if i == 0:
                    D0[k, t] = D_prev[ch, t]
                    ptr_i[k, t] = 0
                else:
                    D0[k, t] = D_prev[ch, t] + cc[k, t] + shift + lw * _dist3(
                        x[k, t, 0], x[k, t, 1], x[k, t, 2],
                        X_prev[ch, t, 0], X_prev[ch, t, 1], X_prev[ch, t, 2], cap_mm)
                    ptr_i[k, t] = 1
            if i > 0:
                for t in range(1, L):
                    dg = D_prev[ch, t - 1] + 2.0 * cc[k, t] + shift + lw * _dist3(
                        x[k, t, 0], x[k, t, 1], x[k, t, 2],
                        X_prev[ch, t - 1, 0], X_prev[ch, t - 1, 1], X_prev[ch, t - 1, 2], cap_mm)
                    if dg < D0[k, t]:
                        D0[k, t] = dg
                        ptr_i[k, t] = 2
        # Moves through a branch point of view B: from the last sample of a chain (alive at the
        # previous step: diagonal; in this step: a B-advance) to the first of one it leads into.
        any_sel = False
        for j in range(n_links):
            sel[j] = act_m[link_to[j]] and alive[link_from[j]]
            any_sel = any_sel or sel[j]
        if i > 0:
            for j in range(n_links):
                if sel[j]:
                    f = link_from[j]
                    r = pos[link_to[j]]
                    le = last[f]
                    v = D_prev[f, le] + 2.0 * cc[r, 0] + shift + lw * _dist3(
                        x[r, 0, 0], x[r, 0, 1], x[r, 0, 2],
                        X_prev[f, le, 0], X_prev[f, le, 1], X_prev[f, le, 2], cap_mm)
                    if v < D0[r, 0]:
                        D0[r, 0] = v
                        ptr_i[r, 0] = 4
                        jptr[i, act[r], 0] = f
        _scan_rows(D0, h, ptr_i, na, D)
        if any_sel:  # a predecessor alive at the last step is worked on in this one too
            better_any = False
            for j in range(n_links):
                if sel[j]:
                    f = link_from[j]
                    r = pos[link_to[j]]
                    rf = pos[f]
                    le = last[f]
                    vv[j] = D[rf, le] + cc[r, 0] + lw * _dist3(
                        x[r, 0, 0], x[r, 0, 1], x[r, 0, 2], x[rf, le, 0], x[rf, le, 1], x[rf, le, 2],
                        cap_mm)
                    if not vv[j] < D[r, 0] - 1e-12:
                        vv[j] = np.nan  # not better
                    else:
                        better_any = True
            if better_any:
                # In order: where two predecessors improve one chain the later one is kept.
                for j in range(n_links):
                    if sel[j] and not np.isnan(vv[j]):
                        r = pos[link_to[j]]
                        D0[r, 0] = vv[j]
                        ptr_i[r, 0] = 5
                        jptr[i, act[r], 1] = link_from[j]
                _scan_rows(D0, h, ptr_i, na, D)
        m = inf
        mr, mt = -1, -1
        for k in range(na):
            ch = act[k]
            for t in range(L):
                if blocked[ch, t]:
                    D[k, t] = inf
            if i == 0 and ch == cb:
                D[k, tb] = 0.0
                ptr_i[k, tb] = 0
            for t in range(L):
                ptr[i, ch, t] = ptr_i[k, t]
                if D[k, t] < m:
                    m = D[k, t]
                    mr, mt = k, t
        if i > 0 and m < best:
            best = m
            bi, bc, btt = i, act[mr], mt
        rows = i + 1
        if m > best + stop_px:
            break
        for k in range(n_prev):
            for t in range(L):
                D_prev[prev_act[k], t] = inf
        for k in range(na):
            ch = act[k]
            prev_act[k] = ch
            for t in range(L):
                D_prev[ch, t] = D[k, t]
                X_prev[ch, t, 0] = x[k, t, 0]
                X_prev[ch, t, 1] = x[k, t, 1]
                X_prev[ch, t, 2] = x[k, t, 2]
        n_prev = na
        for c in range(C):
            alive[c] = False
        for k in range(na):
            rm = inf
            for t in range(L):
                rm = min(rm, D[k, t])
            if rm <= best + stop_px:
                alive[act[k]] = True
    none = np.zeros((0, 3), np.int64)
    if bi < 0:
        return best, none
    # Trace back to the anchor.
    i, c_, t_ = bi, bc, btt
    cells = np.empty((rows * (L + 1) + 1, 3), np.int64)
    nc = 0
    while True:
        if nc >= cells.shape[0]:
            return best, none
        cells[nc, 0], cells[nc, 1], cells[nc, 2] = i, c_, t_
        nc += 1
        p = ptr[i, c_, t_]
        if i == 0 and c_ == cb and t_ == tb:
            break
        if p == 1:
            i -= 1
        elif p == 2:
            i, t_ = i - 1, t_ - 1
        elif p == 3:
            t_ -= 1
        elif p == 4:
            c_ = jptr[i, c_, 0]
            i, t_ = i - 1, last[c_]
        elif p == 5:
            c_ = jptr[i, c_, 1]
            t_ = last[c_]
        else:  # a start cell other than the anchor cannot occur
            return best, none
        if i < 0 or i >= rows:
            return best, none
    return best, cells[:nc][::-1].copy()


@_compiled
def _norm3(X: np.ndarray, i: int, j: int, k: int, m: int, cap: float) -> float:
    return _dist3(X[i, j, 0], X[i, j, 1], X[i, j, 2], X[k, m, 0], X[k, m, 1], X[k, m, 2], cap)


@_compiled
def dtw(E: np.ndarray, X: np.ndarray, lw: float, cap: float) -> np.ndarray:
    """Accumulated cost of monotone alignments from (0, 0) (see :func:`vesselcad.matching._dtw`).

    ``E`` (n, m) with n <= m and ``X`` (n, m, 3), both C-ordered.
    """
    n, m = E.shape
    D = np.empty((n, m))
    # First row: E[0, 0] plus the running sum of E[0, 0], h[0, 1], h[0, 2], ...
    c = E[0, 0]
    D[0, 0] = E[0, 0] + c
    for j in range(1, m):
        c = c + (E[0, j] + lw * _norm3(X, 0, j, 0, j - 1, cap))
        D[0, j] = E[0, 0] + c
    a = np.empty(m)
    hc = np.empty(m)
    for i in range(1, n):
        s = 0.0
        for j in range(m):
            hj = E[i, j] + lw * (_norm3(X, i, j, i, j - 1, cap) if j > 0 else 0.0)
            s = hj if j == 0 else s + hj
            hc[j] = s
            a[j] = D[i - 1, j] + E[i, j] + lw * _norm3(X, i, j, i - 1, j, cap)
            if j > 0:
                b = D[i - 1, j - 1] + 2.0 * E[i, j] + lw * _norm3(X, i, j, i - 1, j - 1, cap)
                a[j] = min(a[j], b)
            a[j] -= hc[j]
        r = a[0]
        for j in range(m):
            r = a[j] if j == 0 else min(r, a[j])
            D[i, j] = r + hc[j]
    return D


@_compiled
def backtrack(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monotone path of an accumulated-cost matrix (see :func:`vesselcad.epipolar.backtrack`)."""
    na, nb = D.shape
    path_i = np.empty(na + nb, np.int64)
    path_j = np.empty(na + nb, np.int64)
    i, j = na - 1, nb - 1
    k = 0
    path_i[k], path_j[k] = i, j
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            # The cheapest of diagonal, up, left: the first of equals, a NaN before all (np.argmin).
            v0, v1, v2 = D[i - 1, j - 1], D[i - 1, j], D[i, j - 1]
            mv = 0
            if np.isnan(v0):
                mv = 0
            elif np.isnan(v1):
                mv = 1
            elif np.isnan(v2):
                mv = 2
            elif v1 < v0 and v1 <= v2:
                mv = 1
            elif v2 < v0 and v2 < v1:
                mv = 2
            if mv == 0:
                i, j = i - 1, j - 1
            elif mv == 1:
                i -= 1
            else:
                j -= 1
        k += 1
        path_i[k], path_j[k] = i, j
    return path_i[: k + 1][::-1].copy(), path_j[: k + 1][::-1].copy()


@_compiled
def pair_errors(oa: np.ndarray, da: np.ndarray, ob: np.ndarray, db: np.ndarray, Pa: np.ndarray,
                Pb: np.ndarray, qa: np.ndarray, qb: np.ndarray, cap_px: float, far_mm: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruction error (px) and ray mid-point (mm) of every pair of pixels of two views.

    The same geometry as :func:`vesselcad.geometry.triangulate` and
    :meth:`vesselcad.geometry.CArmView.project` in one pass: rays from the
    sources ``oa``, ``ob`` along the unit directions ``da`` (na, 3) and ``db``
    (nb, 3) through the pixels ``qa`` (na, 2) and ``qb`` (nb, 2); ``Pa``,
    ``Pb`` the 3x4 projection matrices. The error is the larger of the two
    reprojection distances, capped at ``cap_px``; parallel rays or a point
    behind a source give ``cap_px`` and a point at ``far_mm``.
    """
    na, nb = da.shape[0], db.shape[0]
    E = np.empty((na, nb))
    X = np.empty((na, nb, 3))
    w0 = oa - ob
    for i in range(na):
        a0, a1, a2 = da[i, 0], da[i, 1], da[i, 2]
        d = a0 * w0[0] + a1 * w0[1] + a2 * w0[2]
        for j in range(nb):
            b0, b1, b2 = db[j, 0], db[j, 1], db[j, 2]
            b = a0 * b0 + a1 * b1 + a2 * b2
            e = b0 * w0[0] + b1 * w0[1] + b2 * w0[2]
            den = 1.0 - b * b
            if not den > 1e-14:
                E[i, j] = cap_px
                X[i, j, 0] = X[i, j, 1] = X[i, j, 2] = far_mm
                continue
            t = (b * e - d) / den
            s = (e - b * d) / den
            x0 = 0.5 * ((oa[0] + t * a0) + (ob[0] + s * b0))
            x1 = 0.5 * ((oa[1] + t * a1) + (ob[1] + s * b1))
            x2 = 0.5 * ((oa[2] + t * a2) + (ob[2] + s * b2))
            X[i, j, 0], X[i, j, 1], X[i, j, 2] = x0, x1, x2
            err = 0.0
            for P, q, k in ((Pa, qa, i), (Pb, qb, j)):
                w = P[2, 0] * x0 + P[2, 1] * x1 + P[2, 2] * x2 + P[2, 3]
                if not w > 0.0:
                    err = np.inf
                    break
                u = (P[0, 0] * x0 + P[0, 1] * x1 + P[0, 2] * x2 + P[0, 3]) / w - q[k, 0]
                v = (P[1, 0] * x0 + P[1, 1] * x1 + P[1, 2] * x2 + P[1, 3]) / w - q[k, 1]
                err = max(err, np.sqrt(u * u + v * v))
            E[i, j] = min(err, cap_px)
    return E, X
