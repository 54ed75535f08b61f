"""Continuation of matched branch pairs along both views' skeleton graphs (issue 3).

The landmark-anchored pairing of :mod:`vesselcad.matching` needs a landmark
that agrees across the views at one end at least. In a projection many
vessel ends and bifurcations are lost (an overlap swallows a bifurcation, a
device cuts a vessel, a junction is moved by a crossing), so whole stretches
of vessel stay unpaired although both views show them.

Any accepted pair is itself a correspondence: the vessel goes on past each
end of its two pieces in both views. From every such end (and from every
matched landmark) the unpaired continuation in view A (the rest of the
branch, then each branch beyond the next branch point, up to
``MAX_JUNCTIONS`` of them) is aligned with *the skeleton graph* of view B by
an anchored local alignment: a dynamic program over the directed samples of
every branch of view B, whose moves follow the skeleton through branch points
(never turning back), so a vessel that view B shows as several branches
(a false branch point at an overlap, a side branch hidden in view A) is
followed as one. Each step costs the reconstruction error minus a threshold
(plus the 3D-length tie-break of :func:`vesselcad.matching._dtw`), so the
alignment runs exactly as far as the two views agree. Anchored at a known
correspondence, it does not suffer the basic ambiguity of two views (any two
curves spanning the same epipolar band reproject perfectly onto each other):
a wrong partner must start at the same point and keep agreeing.

Continuations are accepted best first (paired length times agreement times
radius agreement); each accepted one adds its far end as a new anchor, and
the same is done with the roles of the views swapped, until nothing more
agrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from . import _dp
from .centreline2d import CentrelineGraph
from .geometry import CArmView
from .matching import (
    CAP_MM,
    CAP_PX,
    LENGTH_WEIGHT,
    MIN_FORESHORTENING,
    STEP_PX,
    _cost_factor,
    _foreshortening_factor,
    _pair_errors,
    _radius_factor,
)
from .matching import OPEN_TAU as TAU  # a continuation runs while the error stays below TAU * tol
from .splines import arc_length

#: Share of the per-step reward that a step along view B earns (a step along view A earns it all).
B_SHARE = 0.3
#: Branch points of view A a continuation may pass.
MAX_JUNCTIONS = 1
#: Stop the dynamic program once every state is this much worse than the best so far (px).
STOP_PX = 8.0
#: Shortest continuation kept (px in both views).
MIN_PX = 8.0
#: Continuations whose radius agreement factor is below this are dropped.
MIN_RADIUS_AGREEMENT = 0.2
#: Branch points passed in the two views within this many alignment cells are the same one.
JOIN_CELLS = 8
#: Unpaired stretches of a view at least this long (px) get a seed at their middle sample.
SEED_MIN_PX = 20.0
#: A seed's partner agrees within this reconstruction error (px; with the surface's penalty).
SEED_MAX_PX = 1.5
#: Every other agreeing sample of the other view must score at least this many times worse ...
SEED_RATIO = 2.0
#: ... than the best, and at least this (px) times the ratio (the samples lie 2 px apart, so an
#: epipolar line passes a vessel's nearest sample by up to 1 px).
SEED_FLOOR_PX = 0.25
#: Samples of the other view within this distance (px) of the best partner are that vessel.
SEED_SAME_PX = 6.0
_BLOCKED = 1e4


@dataclass
class Chains:
    """One view's branches sampled every ``STEP_PX``, each as two directed chains.

    Chain ``2k`` walks branch ``k`` in its own point order, chain ``2k + 1``
    the other way; ``succ[c]`` lists the chains that continue chain ``c``
    through the landmark at its end (other branches only: no turning back).
    """

    pts: np.ndarray  # (S, 2) samples
    radius: np.ndarray  # (S,) radius px
    branch: np.ndarray  # (S,) branch index
    arc: np.ndarray  # (S,) arc length along the branch (own order)
    idx: np.ndarray  # (C, L) sample index at each chain position, -1 past the end
    n: np.ndarray  # (C,) chain lengths
    start_node: np.ndarray  # (C,)
    end_node: np.ndarray  # (C,)
    succ: list[list[int]]
    pred: list[list[int]]

    @property
    def n_chains(self) -> int:
        return len(self.n)

    @cached_property
    def succ_matrix(self) -> np.ndarray:
        """(C, C) flags: chain ``d`` continues chain ``c`` (``succ`` as a matrix)."""
        m = np.zeros((len(self.n), len(self.n)), bool)
        for c, ds in enumerate(self.succ):
            m[c, ds] = True
        return m

    @cached_property
    def links(self) -> tuple[np.ndarray, np.ndarray]:
        """Every (chain, predecessor) pair, by chain and then in ``pred``'s order."""
        to = [t for t, fs in enumerate(self.pred) for _ in fs]
        frm = [f for fs in self.pred for f in fs]
        return np.asarray(to, dtype=np.int64), np.asarray(frm, dtype=np.int64)

    def position(self, branch: int, arc: float, forward: bool) -> tuple[int, int]:
        """Chain and position of the sample nearest ``arc`` on ``branch``, walking forward or back."""
        c = 2 * branch + (0 if forward else 1)
        s = self.arc[self.idx[c, : self.n[c]]]
        return c, int(np.argmin(np.abs(s - arc)))


def chains(graph: CentrelineGraph) -> Chains:
    """Sample a centreline graph into directed chains (see :class:`Chains`)."""
    pts, rad, br, arcs, offs = [], [], [], [], [0]
    for b in graph.branches:
        a = arc_length(b.points_px)
        L = float(a[-1])
        n = max(int(np.ceil(L / STEP_PX)) + 1, 2)
        s = np.linspace(0.0, L, n)
        pts.append(np.stack([np.interp(s, a, b.points_px[:, 0]), np.interp(s, a, b.points_px[:, 1])], axis=1))
        rad.append(np.interp(s, a, b.radius_px))
        br.append(np.full(n, b.index))
        arcs.append(s)
        offs.append(offs[-1] + n)
    nb = len(graph.branches)
    lens = np.diff(offs)
    width = int(lens.max()) if nb else 1
    idx = np.full((2 * nb, width), -1, dtype=np.int64)
    start = np.empty(2 * nb, dtype=np.int64)
    end = np.empty(2 * nb, dtype=np.int64)
    for k, b in enumerate(graph.branches):
        seq = np.arange(offs[k], offs[k + 1])
        idx[2 * k, : lens[k]] = seq
        idx[2 * k + 1, : lens[k]] = seq[::-1]
        start[2 * k], end[2 * k] = b.start, b.end
        start[2 * k + 1], end[2 * k + 1] = b.end, b.start
    out: dict[int, list[int]] = {}
    for c in range(2 * nb):
        out.setdefault(int(start[c]), []).append(c)
    succ = [[d for d in out.get(int(end[c]), []) if d // 2 != c // 2] for c in range(2 * nb)]
    pred: list[list[int]] = [[] for _ in range(2 * nb)]
    for c, ds in enumerate(succ):
        for d in ds:
            pred[d].append(c)
    cat = (lambda x: np.concatenate(x)) if nb else (lambda x: np.zeros(0))
    return Chains(cat(pts).reshape(-1, 2), cat(rad), cat(br).astype(np.int64), cat(arcs), idx,
                  np.asarray(lens, dtype=np.int64).repeat(2) if nb else np.zeros(0, np.int64), start, end,
                  succ, pred)


@dataclass
class Continuation:
    """An accepted alignment: samples of view A (``ia``) against samples of view B (``ib``)."""

    gain: float
    cost: float
    ia: np.ndarray  # (m,) sample indices in view A's chains, along the alignment (repeats allowed)
    ib: np.ndarray  # (m,) sample indices in view B's chains
    err: np.ndarray  # (m,) reconstruction error px of each aligned cell
    anchor: tuple[int, int, int, int] = (-1, -1, -1, -1)  # where it started (chain, position in A, in B)


def _a_paths(ch: Chains, used: np.ndarray, c0: int, t0: int) -> list[np.ndarray]:
    """Sample sequences of view A from (c0, t0) onward through up to ``MAX_JUNCTIONS`` branch points.

    Each starts with the anchor sample (which may be paired) and stops before
    the first sample already paired; past a branch point it goes on along
    each other branch (never back the way it came).
    """
    out: list[np.ndarray] = []
    stack = [(c0, t0, [ch.idx[c0, t0 : t0 + 1]], 0)]
    while stack:
        c, t, parts, depth = stack.pop()
        seq = ch.idx[c, t + 1 : ch.n[c]]
        stop = np.flatnonzero(used[seq])
        parts = parts + [seq[: stop[0]] if len(stop) else seq]
        nxt = [] if len(stop) or depth >= MAX_JUNCTIONS else [d for d in ch.succ[c] if not used[ch.idx[d, 1]]]
        if not nxt:
            out.append(np.concatenate(parts))
        # A successor's first sample is the branch point again: go on from its second.
        stack.extend((d, 0, parts, depth + 1) for d in nxt)
    return [p for p in out if len(p) > 1]


def _align(se: SampleErrors, chb: Chains, used_b: np.ndarray, a_seq: np.ndarray,
           cb: int, tb: int, tau: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
    """Anchored local alignment of view A's samples ``a_seq`` with view B's chains from (cb, tb).

    Returns (score, A samples, B samples, errors) of the best alignment, or
    None when none gains anything. Row 0 is the anchor (score 0).
    """
    link_to, link_from = chb.links
    # The compiled program reads the arrays in their stored (C) order: one compilation.
    E, X = (se.E.T, se.X.transpose(1, 0, 2)) if se.swapped else (se.E, se.X)
    best, cells = _dp.align(E, X, se.swapped, se.map_a, se.map_b, chb.idx, chb.n, chb.succ_matrix,
                            link_to, link_from, used_b, a_seq, cb, tb, tau, LENGTH_WEIGHT, B_SHARE,
                            STOP_PX, _BLOCKED, CAP_MM)
    if len(cells) == 0:
        return None
    ib = chb.idx[cells[:, 1], cells[:, 2]]
    ia = a_seq[cells[:, 0]]
    return best, ia, ib, se.at(ia, ib)


@dataclass
class SampleErrors:
    """Reconstruction error (px, capped) and triangulated point (mm) of pairs of samples of two views.

    Only samples still free (or anchors) are computed; any other pair reads
    as the cap (those samples are blocked anyway).
    """

    E: np.ndarray  # (na + 1, nb + 1), last row and column: the cap
    X: np.ndarray  # (na + 1, nb + 1, 3)
    map_a: np.ndarray  # (S_a,) row of each sample of view A (na where not computed)
    map_b: np.ndarray  # (S_b,)
    swapped: bool = False  # E and X are transposed views (the roles of the views swapped)

    def row(self, a: int, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ra, cb = self.map_a[a], self.map_b[b]
        return self.E[ra][cb], self.X[ra][cb]

    def at(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self.E[self.map_a[a], self.map_b[b]]

    @property
    def T(self) -> SampleErrors:
        return SampleErrors(self.E.T, self.X.transpose(1, 0, 2), self.map_b, self.map_a, not self.swapped)


def sample_errors(va: CArmView, vb: CArmView, cha: Chains, chb: Chains, free_a: np.ndarray,
                  free_b: np.ndarray) -> SampleErrors:
    """Errors and points of every pair of the samples flagged in ``free_a`` and ``free_b``."""
    ia, ib = np.flatnonzero(free_a), np.flatnonzero(free_b)
    E, X = _pair_errors(va, cha.pts[ia], vb, chb.pts[ib])
    Ep = np.full((len(ia) + 1, len(ib) + 1), CAP_PX)
    Ep[:-1, :-1] = E
    Xp = np.zeros((len(ia) + 1, len(ib) + 1, 3))
    Xp[:-1, :-1] = X
    map_a = np.full(len(free_a), len(ia), dtype=np.int64)
    map_a[ia] = np.arange(len(ia))
    map_b = np.full(len(free_b), len(ib), dtype=np.int64)
    map_b[ib] = np.arange(len(ib))
    return SampleErrors(Ep, Xp, map_a, map_b)


def continue_pairs(se: SampleErrors, cha: Chains, chb: Chains, used_a: np.ndarray,
                   used_b: np.ndarray, anchors: list[tuple[int, int, int, int]], tol: float,
                   mm_a: float, mm_b: float, cost_rate: float = 0.0, radii: bool = True
                   ) -> tuple[list[Continuation], list[tuple[int, int, int, int]]]:
    """Grow pairs from ``anchors`` (chain and position in view A, in view B) as far as the views agree.

    ``se`` comes from :func:`sample_errors` (view A samples by view B
    samples; pass its transpose ``se.T`` to grow from view B). ``used_a``
    and ``used_b`` (sample flags) are updated in place. The far end of each
    new pair, and every point where it passes a branch point in either view,
    become anchors in turn (the other branches there may continue from it);
    they are returned with the new pairs. ``cost_rate`` is the rate of the
    gains' error factor (``matching._cost_factor``; 0: the linear ramp only).
    With ``radii=False`` the two views' radii are not compared (a stretch of
    two vessels overlapping in one view is wider there than either vessel).
    """
    tau = TAU * tol
    out: list[Continuation] = []
    new_anchors: list[tuple[int, int, int, int]] = []
    queue = list(anchors)
    cache: dict[tuple, tuple | None] = {}
    while queue:
        cands = []
        for ca, ta, cb, tb in queue:
            for seq in _a_paths(cha, used_a, ca, ta):
                if len(seq) < 3:
                    continue
                key = (cb, tb, seq.tobytes())
                res = cache.get(key, False)
                # Blocking samples only removes alternatives: a best alignment that uses no newly
                # paired sample stays the best.
                if res is False or (res is not None and _touches(res[2], used_b)):
                    res = _align(se, chb, used_b, seq, cb, tb, tau)
                    cache[key] = res
                if res is None:
                    continue
                score, ia, ib, err = res
                la = STEP_PX * (len(np.unique(ia)) - 1)
                lb = STEP_PX * (len(np.unique(ib)) - 1)
                cost = float(err.mean())
                if min(la, lb) < MIN_PX or cost > tol:
                    continue
                ra = float(np.median(cha.radius[ia])) * mm_a
                rb = float(np.median(chb.radius[ib])) * mm_b
                agree = _radius_factor(ra, rb) if radii else 1.0
                if agree < MIN_RADIUS_AGREEMENT:
                    continue
                fs = _foreshortening_factor(se.X[se.map_a[ia], se.map_b[ib]], la, lb, mm_a, mm_b)
                if fs < MIN_FORESHORTENING:
                    continue
                gain = min(la, lb) * _cost_factor(cost, tol, cost_rate) * agree * fs
                cands.append(Continuation(gain, cost, ia, ib, err, (ca, ta, cb, tb)))
        cands.sort(key=lambda c: -c.gain)
        queue = []
        for cont in cands:
            anchor = cont.anchor
            na, nb = cont.ia[1:], cont.ib[1:]
            na = na[na != cont.ia[0]]
            nb = nb[nb != cont.ib[0]]
            if used_a[na].any() or used_b[nb].any():
                if anchor not in queue:
                    queue.append(anchor)  # try again with what is left
                continue
            used_a[na] = True
            used_b[nb] = True
            out.append(cont)
            if anchor not in queue:
                queue.append(anchor)  # other branches may continue from the same anchor
            for new in _anchors_along(cha, chb, cont):
                queue.append(new)
                new_anchors.append(new)
    return out, new_anchors


def seeds(se: SampleErrors, cha: Chains, chb: Chains, used_a: np.ndarray,
          used_b: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Anchors in the middle of view A's unpaired stretches whose partner in view B is unambiguous.

    For every run of unpaired samples of one branch at least ``SEED_MIN_PX``
    long, its middle sample is paired with the unpaired sample of view B that
    agrees best (``se`` holds the errors, with the heart surface's penalty
    where :func:`vesselcad.matching._continuations` added it), provided it
    agrees within ``SEED_MAX_PX`` and every other agreeing sample farther
    than ``SEED_SAME_PX`` from it scores at least ``SEED_RATIO`` times worse.
    Each seed gives two anchors, one for each direction of view A, with the
    direction of view B whose next sample agrees better with view A's next.
    """
    out: list[tuple[int, int, int, int]] = []
    rows, cols = se.E.shape[0] - 1, se.E.shape[1] - 1
    cand_b = np.flatnonzero(~used_b & (se.map_b < cols))
    if not len(cand_b):
        return out
    for k in np.unique(cha.branch):
        s = np.flatnonzero(cha.branch == k)
        f = ~used_a[s] & (se.map_a[s] < rows)
        edges = np.flatnonzero(np.diff(np.r_[0, f.astype(np.int8), 0]))
        for lo, hi in zip(edges[::2], edges[1::2], strict=True):
            if (hi - lo - 1) * STEP_PX < SEED_MIN_PX:
                continue
            a = int(s[(lo + hi - 1) // 2])
            e = se.E[se.map_a[a], se.map_b[cand_b]]
            ok = e < SEED_MAX_PX
            if not ok.any():
                continue
            eb, bb = e[ok], cand_b[ok]
            j = int(np.argmin(eb))
            b = int(bb[j])
            far = np.linalg.norm(chb.pts[bb] - chb.pts[b], axis=1) > SEED_SAME_PX
            if (eb[far] < SEED_RATIO * max(float(eb[j]), SEED_FLOOR_PX)).any():
                continue
            kb = int(chb.branch[b])
            pos_b = [(cb, int(np.flatnonzero(chb.idx[cb] == b)[0])) for cb in (2 * kb, 2 * kb + 1)]
            for ca in (2 * int(k), 2 * int(k) + 1):
                ta = int(np.flatnonzero(cha.idx[ca] == a)[0])
                # View B's direction is the one whose next sample agrees with view A's next.
                a1 = cha.idx[ca, min(ta + 1, int(cha.n[ca]) - 1)]
                errs = [se.at(np.array([a1]), chb.idx[cb, min(tb + 1, int(chb.n[cb]) - 1)][None])[0]
                        for cb, tb in pos_b]
                out.append((ca, ta) + pos_b[int(np.argmin(errs))])
    return out


def _anchors_along(cha: Chains, chb: Chains, cont: Continuation) -> list[tuple[int, int, int, int]]:
    """Anchors on an accepted continuation: its far end and where it passes branch points.

    Where both views pass a branch point within ``JOIN_CELLS`` cells of each
    other it is the same bifurcation: the anchor puts both views at it, so the
    other branches there can be paired with each other. So it does where the
    continuation ends at a branch point of one view that the other view passed
    within ``JOIN_CELLS`` cells of the end.
    """
    ka, kb = cha.branch[cont.ia], chb.branch[cont.ib]
    ta = np.flatnonzero(np.diff(ka) != 0)  # last cells before view A passes a branch point
    tb = np.flatnonzero(np.diff(kb) != 0)
    out = []
    for k in ta:
        near = tb[np.abs(tb - k) <= JOIN_CELLS]
        kk = int(near[np.argmin(np.abs(near - k))]) if len(near) else int(k)
        out.append(_tip(cha, cont.ia[: k + 1]) + _tip(chb, cont.ib[: kk + 1]))
    for k in tb:
        near = ta[np.abs(ta - k) <= JOIN_CELLS]
        if not len(near):
            out.append(_tip(cha, cont.ia[: k + 1]) + _tip(chb, cont.ib[: k + 1]))
    end_a, end_b = _tip(cha, cont.ia), _tip(chb, cont.ib)
    out.append(end_a + end_b)
    # One view ends at a branch point that the other passed within JOIN_CELLS cells of the end (it
    # ran on a few samples into one of the branches there): the same bifurcation, so the other
    # branches there continue from both views' branch points (from the far end, the view that ran
    # on could only go on along the branch it entered).
    last = len(cont.ia) - 1
    if end_a[1] == cha.n[end_a[0]] - 1:
        late = tb[last - tb <= JOIN_CELLS]
        if len(late):
            out.append(end_a + _tip(chb, cont.ib[: late[-1] + 1]))
    if end_b[1] == chb.n[end_b[0]] - 1:
        late = ta[last - ta <= JOIN_CELLS]
        if len(late):
            out.append(_tip(cha, cont.ia[: late[-1] + 1]) + end_b)
    return out


def _touches(samples: np.ndarray, used: np.ndarray) -> bool:
    """Whether an alignment's samples (past its anchor) include one now paired."""
    rest = samples[1:]
    return bool(used[rest[rest != samples[0]]].any())


def _tip(ch: Chains, samples: np.ndarray) -> tuple[int, int]:
    """Chain and position of the last sample, oriented along the direction of travel."""
    s = int(samples[-1])
    k = int(ch.branch[s])
    prev = next((int(q) for q in samples[::-1] if ch.branch[q] == k and q != s), None)
    forward = prev is None or prev < s
    c = 2 * k + (0 if forward else 1)
    t = int(np.flatnonzero(ch.idx[c] == s)[0])
    return c, t
