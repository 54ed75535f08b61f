"""3D centrelines from two 2D branch curves (paper §2.4 step 3).

The method (``method="nurbs"``): each view's 2D branch curve, fitted as a cubic
B-spline in pixels, is lifted onto the detector and swept toward the X-ray
source into a degree (3, 1) B-spline surface (:func:`vesselcad.kernel.nurbs.extruded_surface`).
The 3D centreline is the intersection curve of the two surfaces, computed by
OCCT's surface-surface intersector.

Taken whole, the two surfaces meet in more than the centreline: wherever a 2D
curve crosses the same epipolar line twice, the folds of the two surfaces
intersect crosswise ("ghost" curves), and where a branch runs along an
epipolar plane the surfaces are nearly tangent. So the branch is first split,
along a globally ordered epipolar correspondence (:mod:`vesselcad.epipolar`),
into pieces on which the tangent keeps at least ``min_angle_deg`` from the
epipolar line in both views. On such a piece the epipolar angle is strictly
monotone in both views, so the two trimmed surfaces have exactly one
intersection curve, which OCCT walks from a start point (the walking points,
interpolated onto a grid, are polished onto both surfaces). The ill-conditioned
spans between pieces (and at the ends) are bridged along view A's rays by a
cubic in depth that continues the neighbouring pieces (or meets the
triangulated end points), moved onto the right side of curve B's folds by a
dynamic program where needed and refined against curve B. All samples are fitted by one cubic B-spline over
view A's curve parameter (C2, so the joins are smooth), returned as a
``Geom_BSplineCurve`` inside :class:`~vesselcad.kernel.Centreline3D`.

The baseline (``method="epipolar"``) is the classic point-wise method the
paper compares against: dense samples along curve A, sub-pixel intersection of
each sample's epipolar line with curve B under the same ordering, mid-point
triangulation, then the same bridging and B-spline fit.

A vessel seen end-on in one view (running along that view's X-ray, its whole
2D curve within less than :data:`END_ON_PX` of one point) has no surface there to
intersect: either method then returns the straight segment along that ray
which the other view's rays cross (docs/centreline3d.md, "Seen end-on").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import interpolate, linalg

from .epipolar import EpipolarPair, ordered_correspondence, sample_curve
from .errors import ArgumentError
from .geometry import CArmView, triangulate
from .splines import MIN_NOISE_PX, fit_curve_2d, fit_pspline

if TYPE_CHECKING:  # OCCT is imported on first use, keeping `import vesselcad` light
    from .kernel.centreline import Centreline3D

__all__ = ["intersect_centrelines", "METHODS"]

METHODS = ("nurbs", "epipolar")

#: A 2D curve all within less than this distance (px) of one point (one skeleton pixel) is the
#: vessel seen end-on (along the X-ray), when the other view's curve spans at least
#: ``END_ON_MIN_PX`` end to end. Two pixels apart or more, the regular path bridges between
#: the triangulated ends, which follows a short foreshortened stretch better.
END_ON_PX = 0.5
END_ON_MIN_PX = 4.0
#: Largest distance (px) of the other view's curve from the end-on ray's epipolar line
#: before a warning says the two curves are not one vessel seen end-on.
_END_ON_MISS_PX = 3.0

#: Grid step (px) of the ordered correspondence, and its largest sample count.
_DTW_STEP_PX = 1.0
_DTW_MAX = 300
#: Curve-parameter step (px) of the samples the final fit sees.
_FIT_STEP_PX = 0.5
#: Depth grid (mm) searched along view A's rays to track a bridged span, its margin
#: beyond the span's first guess and its end depths, the candidates kept per ray, and the
#: depth step (mm per ~1 px) that costs as much as one noise-sigma of image distance.
_TRACK_STEP_MM = 0.25
_TRACK_MARGIN_MM = 40.0
_TRACK_BAND = 8
_TRACK_STEP_SCALE_MM = 0.5
_TRACK_PRIOR_MM = 10.0
_TRACK_ROW_PX = 2.0
_TRACK_MIN_PX = 8.0
_TRACK_SWITCH_MM = 1.5
#: Scale (mm) of the smoothness prior on the second difference of the bridged depth
#: per half-pixel step.
PRIOR_MM = 0.02


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive index ranges of the True runs of a boolean array."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _merge(intervals: list[tuple[float, float]], gap: float) -> list[tuple[float, float]]:
    out: list[list[float]] = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1] + gap:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _monotone_window(u: np.ndarray, theta: np.ndarray, lo: float, hi: float,
                     at: float) -> tuple[float, float]:
    """The part of ``[lo, hi]`` around ``at`` on which ``theta(u)`` is strictly monotone.

    ``u`` is a dense parameter grid of the curve and ``theta`` its epipolar
    angle there; the window is also clipped to the grid's range.
    """
    sel = np.flatnonzero((u >= lo) & (u <= hi))
    if len(sel) < 3:
        return max(lo, float(u[0])), min(hi, float(u[-1]))
    step = np.sign(np.diff(theta[sel]))
    k = int(np.clip(np.searchsorted(u[sel], at) - 1, 0, len(step) - 1))
    if step[k] == 0:
        return float(u[sel[max(k, 0)]]), float(u[sel[min(k + 1, len(sel) - 1)]])
    same = step == step[k]
    first = k - int(np.argmin(same[k::-1])) + 1 if not same[: k + 1].all() else 0
    last = k + int(np.argmin(same[k:])) if not same[k:].all() else len(step)
    return float(u[sel[first]]), float(u[sel[last]])


def _turns(theta: np.ndarray, w: np.ndarray, u: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """For each step ``u[k] -> u[k+1]`` of a path: does the epipolar angle step against ``direction``?

    ``theta`` is the curve's epipolar angle at the dense parameters ``w``
    (every quarter pixel; the path itself samples every pixel or more).
    """
    d_th = np.diff(theta)
    up = np.concatenate([[0], np.cumsum(d_th > 0)])
    down = np.concatenate([[0], np.cumsum(d_th < 0)])
    # Dense index range covered by each path step (a step may be zero length).
    p = np.clip(np.searchsorted(w, u, side="right") - 1, 0, len(w) - 1)
    lo, hi = np.minimum(p[:-1], p[1:]), np.maximum(p[:-1], p[1:]) + 1
    hi = np.minimum(hi, len(w) - 1)
    against = np.where(direction[:-1] > 0, down[hi] - down[lo], up[hi] - up[lo])
    return against > 0


class _Branch:
    """One branch pair prepared for either method: fits, samples, correspondence, pieces."""

    def __init__(self, view_a: CArmView, pts_a: Any, view_b: CArmView, pts_b: Any,
                 noise_px: float | None, min_angle_deg: float, depth_range_mm: float,
                 min_noise_px: float = MIN_NOISE_PX) -> None:
        self.pair = EpipolarPair(view_a, view_b)
        self.view_a, self.view_b = view_a, view_b
        self.spl_a, self.sig_a = fit_curve_2d(pts_a, noise_px, "pts_a_px", min_noise_px)
        self.spl_b, self.sig_b = fit_curve_2d(pts_b, noise_px, "pts_b_px", min_noise_px)
        self.dom_a = (float(self.spl_a.t[3]), float(self.spl_a.t[-4]))
        self.dom_b = (float(self.spl_b.t[3]), float(self.spl_b.t[-4]))
        self.depth_window = (view_a.sod_mm - depth_range_mm, view_a.sod_mm + depth_range_mm), (
            view_b.sod_mm - depth_range_mm, view_b.sod_mm + depth_range_mm)
        la, lb = self.dom_a[1] - self.dom_a[0], self.dom_b[1] - self.dom_b[0]
        self.ua, self.pa, ta = sample_curve(self.spl_a, max(_DTW_STEP_PX, la / _DTW_MAX))
        self.ub, self.pb, tb = sample_curve(self.spl_b, max(_DTW_STEP_PX, lb / _DTW_MAX))
        self.b_dense_u = np.linspace(*self.dom_b, max(int(np.ceil(lb / 0.25)) + 1, 4))
        self.b_dense = self.spl_b(self.b_dense_u)
        th_a = self.pair.theta_px(view_a, self.pa)
        th_b = self.pair.theta_px(view_b, self.pb)
        cond_a = self.pair.conditioning(view_a, self.pa, ta)
        cond_b = self.pair.conditioning(view_b, self.pb, tb)
        per_px = self.pair.theta_per_px(view_a, self.pa)
        # Both curves must start at the same end: the end points' epipolar
        # angles agree pairwise, and a reversed input shows as a crossed match.
        same = abs(th_a[0] - th_b[0]) + abs(th_a[-1] - th_b[-1])
        crossed = abs(th_a[0] - th_b[-1]) + abs(th_a[-1] - th_b[0])
        if crossed + 10.0 * per_px < same:
            raise ArgumentError(
                "pts_b_px: runs the other way round from pts_a_px (its first point matches the last "
                "point of pts_a_px); pass both branch curves from the same (proximal) end"
            )
        i, j = ordered_correspondence(th_a, th_b)
        self.path = (i, j)
        tol = (2.0 + 3.0 * max(self.sig_a, self.sig_b)) * per_px
        dir_a = np.sign(np.gradient(th_a))[i]
        dir_b = np.sign(np.gradient(th_b))[j]
        thr = np.sin(np.radians(min_angle_deg))
        good = (cond_a[i] >= thr) & (cond_b[j] >= thr) & (np.abs(th_a[i] - th_b[j]) <= tol) & (dir_a == dir_b)
        # Between two path samples a fitted curve may still turn back along the
        # epipolar lines (a wiggle narrower than the sample step, seen with
        # noisy input): the surfaces fold there and an intersection walk runs
        # onto the fold. Such steps end a piece.
        wa = np.linspace(*self.dom_a, max(int(np.ceil(la / 0.25)) + 1, 4))
        th_wa = self.pair.theta_px(view_a, self.spl_a(wa))
        th_wb = self.pair.theta_px(view_b, self.b_dense)
        turn = (_turns(th_wa, wa, self.ua[i], dir_a) | _turns(th_wb, self.b_dense_u, self.ub[j], dir_b))
        good[:-1] &= ~turn
        good[1:] &= ~turn
        self.pieces: list[dict[str, Any]] = []
        for k0, k1 in _runs(good):
            i0, i1, j0, j1 = i[k0], i[k1], j[k0], j[k1]
            if i1 - i0 < 2 or j1 - j0 < 2:
                continue
            ks = np.arange(k0, k1 + 1)
            X = triangulate(view_a, self.pa[i[ks]], view_b, self.pb[j[ks]])
            da, db = view_a.depth(X), view_b.depth(X)
            mid = ks[len(ks) // 2] - k0
            # Curve B's window: the path's range plus a margin, cut to the run around the
            # piece's middle on which B's epipolar angle is monotone (near the ends of a noisy
            # fit it can hook back); view A's range cut to the angles that run reaches. On these
            # windows the correspondence is one-to-one for both methods alike.
            u_b = _monotone_window(self.b_dense_u, th_wb, float(self.ub[j0]) - 1.5, float(self.ub[j1]) + 1.5,
                                   float(self.ub[j[ks[len(ks) // 2]]]))
            on_b = (self.b_dense_u >= u_b[0]) & (self.b_dense_u <= u_b[1])
            th_lo, th_hi = float(th_wb[on_b].min()), float(th_wb[on_b].max())
            in_a = (wa >= self.ua[i0]) & (wa <= self.ua[i1]) & (th_wa >= th_lo) & (th_wa <= th_hi)
            if np.count_nonzero(in_a) < 2:
                continue
            self.pieces.append({
                "u_a": (max(float(wa[in_a][0]) - 0.25, float(self.ua[i0])),
                        min(float(wa[in_a][-1]) + 0.25, float(self.ua[i1]))),
                "u_b": u_b,
                "depth_a": (max(float(da.min()) - 10.0, 1.0), float(da.max()) + 10.0),
                "depth_b": (max(float(db.min()) - 10.0, 1.0), float(db.max()) + 10.0),
                "start": (float(self.ua[i[ks[mid]]]), float(da[mid]),
                          float(self.ub[j[ks[mid]]]), float(db[mid])),
                # Every path point of the piece as a possible start (u_a, depth_a, u_b, depth_b).
                "starts": np.column_stack([self.ua[i[ks]], da, self.ub[j[ks]], db]),
            })

    # ----------------------------------------------------------- helpers
    def ray_steps_a(self, u: np.ndarray) -> np.ndarray:
        """Per unit of depth (mm), the step along view A's ray through the curve at ``u``, shape (n, 3)."""
        return (self.view_a.pixel_to_detector(self.spl_a(u)) - self.view_a.source) / self.view_a.sid_mm

    def rays_a(self, u: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Points on view A's rays through the curve at ``u``, at depth ``depth`` mm."""
        return self.view_a.source + np.asarray(depth, float)[:, None] * self.ray_steps_a(u)

    def ub_at(self, u: float, depth: float) -> float:
        """Curve B's parameter nearest the projection of view A's ray point at ``u``, ``depth``.

        Searched near the ordered correspondence, which is reliable at the ends
        of well-conditioned pieces.
        """
        i, j = self.path
        w_est = float(np.interp(u, self.ua[i], self.ub[j]))
        q = self.view_b.project(self.rays_a(np.array([u]), np.array([depth])))[0]
        half = 3.0 + 3.0 * max(self.sig_a, self.sig_b)
        sel = np.flatnonzero(np.abs(self.b_dense_u - w_est) <= half)
        if not len(sel):
            return w_est
        return float(self.b_dense_u[sel[np.argmin(np.linalg.norm(self.b_dense[sel] - q, axis=1))]])

    def end_depths(self) -> tuple[float, float]:
        """Depth (view A) of the triangulated first and last points of the two curves."""
        ends_a = self.spl_a(np.array(self.dom_a))
        ends_b = self.spl_b(np.array(self.dom_b))
        X = triangulate(self.view_a, ends_a, self.view_b, ends_b)
        d = self.view_a.depth(X)
        return float(d[0]), float(d[1])


def _walk_piece(surf_a: Any, surf_b: Any, p: dict[str, Any], start: tuple) -> list[np.ndarray]:
    """Walk one piece from ``start``; the monotone part of each line as (u_a, x, y, z, u_b) rows."""
    from .kernel.intersect import PiecePair, intersect_piece

    piece = PiecePair(p["u_a"], p["u_b"], p["depth_a"], p["depth_b"], tuple(float(v) for v in start))
    out = []
    for line in intersect_piece(surf_a, surf_b, piece):
        if len(line) < 3:
            continue
        # One-to-one pieces give one line on which both parameters advance
        # together; walking points that step back (jitter at the piece's
        # trimmed ends) are dropped.
        line = line[np.argsort(line[:, 3])]
        u_b = line[:, 5]
        forward = (u_b[-1] - u_b[0]) >= 0
        run = np.maximum.accumulate(u_b) if forward else np.minimum.accumulate(u_b)
        keep = (u_b == run) & np.concatenate([[True], np.diff(line[:, 3]) > 1e-9])
        if np.count_nonzero(keep) >= 2:
            out.append(np.column_stack([line[keep, 3], line[keep, :3], u_b[keep]]))
    return out


def _polish(br: _Branch, u: np.ndarray, X: np.ndarray, w: np.ndarray, iterations: int = 4
            ) -> tuple[np.ndarray, np.ndarray]:
    """Points of the surfaces' intersection at view A's parameters ``u``, to machine precision.

    ``X`` and ``w`` (curve B's parameters) are guesses interpolated between the
    intersector's walking points. On view A's ray at ``u`` the point whose
    projection into view B lies on curve B is found by Newton's method in
    (depth, ``w``): the same curve, without the interpolation's error.
    Returns the points (rows NaN where it does not converge within 1 mm of
    the guess) and curve B's parameters.
    """
    va, vb = br.view_a, br.view_b
    s = va.source
    ray = br.ray_steps_a(u)
    d = va.depth(X)
    w = np.clip(w, *br.dom_b)
    dspl_b = br.spl_b.derivative()
    for _ in range(iterations):
        q = vb.project(s + d[:, None] * ray)
        dq = (vb.project(s + (d + 0.01)[:, None] * ray) - q) / 0.01
        f = q - br.spl_b(w)
        dc = -dspl_b(w)
        det = dq[:, 0] * dc[:, 1] - dq[:, 1] * dc[:, 0]
        ok = np.isfinite(det) & (np.abs(det) > 1e-12)
        det = np.where(ok, det, 1.0)
        step_d = np.where(ok, -(dc[:, 1] * f[:, 0] - dc[:, 0] * f[:, 1]) / det, 0.0)
        step_w = np.where(ok, -(-dq[:, 1] * f[:, 0] + dq[:, 0] * f[:, 1]) / det, 0.0)
        d = d + np.clip(step_d, -1.0, 1.0)
        w = np.clip(w + np.clip(step_w, -1.0, 1.0), *br.dom_b)
    X_new = s + d[:, None] * ray
    # Where Newton does not land on curve B near the guess (the walk's last points at a trimmed
    # end can lie off the intersection) the sample is dropped: NaN rows.
    res = np.linalg.norm(vb.project(X_new) - br.spl_b(w), axis=1)
    good = np.isfinite(res) & (res < 1e-6) & (np.linalg.norm(X_new - X, axis=1) < 1.0)
    return np.where(good[:, None], X_new, np.nan), w


def _piece_grid(p: dict[str, Any]) -> np.ndarray:
    """View A's curve parameters at which a piece is sampled for the final fit (both methods)."""
    u0, u1 = p["u_a"]
    return np.linspace(u0, u1, max(int(np.ceil((u1 - u0) / _FIT_STEP_PX)) + 1, 2))


def _intersect_nurbs(br: _Branch) -> tuple[list[np.ndarray], tuple[Any, Any]]:
    """Per piece: OCCT intersection of the two trimmed surfaces -> samples (u_a, x, y, z)."""
    from .kernel.nurbs import extruded_surface, make_face

    (da0, da1), (db0, db1) = br.depth_window
    for p in br.pieces:  # the surfaces must reach every piece's depth window
        da0, da1 = min(da0, p["depth_a"][0]), max(da1, p["depth_a"][1])
        db0, db1 = min(db0, p["depth_b"][0]), max(db1, p["depth_b"][1])
    surf_a = extruded_surface(br.view_a, br.spl_a, da0, da1)
    surf_b = extruded_surface(br.view_b, br.spl_b, db0, db1)
    samples: list[np.ndarray] = []
    for p in br.pieces:
        walked = _walk_piece(surf_a, surf_b, p, p["start"])
        # A walk can stop short of the piece's ends or leave a hole inside it; walk
        # again from a start in each uncovered part (the lines are one curve, so
        # their union is too).
        # OCCT's walk can stop at a point where it would go on from elsewhere, so
        # each round starts from another place in the hole.
        lo, hi = p["u_a"]
        for at in (0.5, 0.25, 0.75):
            # Each walked line is one continuous stretch of the curve.
            covered = _merge([(float(w[0, 0]), float(w[-1, 0])) for w in walked], gap=2.0)
            edges = np.array([lo] + [x for ab in covered for x in ab] + [hi])
            holes = [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a > 2.0]
            if not holes:
                break
            st = p["starts"]
            for a, b in holes:
                k = int(np.argmin(np.abs(st[:, 0] - (a + at * (b - a)))))
                walked += _walk_piece(surf_a, surf_b, p, tuple(st[k]))
        if walked:
            # The lines are stretches of one curve: where they overlap keep one line's points
            # (interleaving two lines' nearly equal points would make the interpolation ring).
            parts, reach = [], -np.inf
            for line in sorted(walked, key=lambda q: float(q[0, 0])):
                line = line[line[:, 0] > reach + 0.1]
                if len(line):
                    parts.append(line)
                    reach = float(line[-1, 0])
            allp = np.vstack(parts)
            # A line's points on the trimmed window's edge in curve B are where the walk
            # left the piece, not always on the intersection: the polish recovers them.
            w0, w1 = p["u_b"]
            allp = allp[(allp[:, 4] > w0 + 1e-6) & (allp[:, 4] < w1 - 1e-6)]
            if len(allp) < 2:
                continue
            # Split where no line covers the curve (a hole that no walk reached).
            covered = _merge([(float(q[0, 0]), float(q[-1, 0])) for q in parts], gap=2.0)
            which = np.searchsorted([a for a, _ in covered], allp[:, 0], side="right")
            piece_grid = _piece_grid(p)
            for k, (c0, c1) in enumerate(covered, start=1):
                part = allp[which == k]
                u, X, w = part[:, 0], part[:, 1:4], part[:, 4]
                if len(u) < 2 or u[-1] - u[0] < 0.5:
                    continue
                # The walk's points are exact but unevenly spaced: resample them on the
                # piece's grid (the one the epipolar baseline samples too) over the lines'
                # reach and a pixel beyond (a walk can stop just short of a trimmed end);
                # beyond the kept points the guesses are extrapolated and the polish decides.
                grid = piece_grid[(piece_grid >= c0 - 1.0) & (piece_grid <= c1 + 1.0)]
                if len(grid) < 2:
                    continue
                Xg = interpolate.CubicSpline(u, X, axis=0, extrapolate=True)(grid) if len(u) >= 4 else (
                    interpolate.interp1d(u, X, axis=0, fill_value="extrapolate")(grid))
                wg = interpolate.interp1d(u, w, fill_value="extrapolate")(grid)
                Xp, wp = _polish(br, grid, Xg, wg)
                ok = np.isfinite(Xp[:, 0]) & (wp >= p["u_b"][0]) & (wp <= p["u_b"][1])
                # Each run of polished samples is kept on its own, so a dropped sample
                # leaves a hole that the bridging fills.
                for r0, r1 in _runs(ok):
                    if r1 > r0:
                        samples.append(np.column_stack([grid[r0 : r1 + 1], Xp[r0 : r1 + 1]]))
    return samples, (make_face(surf_a), make_face(surf_b))


def _intersect_epipolar(br: _Branch) -> list[np.ndarray]:
    """Per piece: epipolar line of each A sample crossed with curve B, mid-point triangulation."""
    samples: list[np.ndarray] = []
    for p in br.pieces:
        ua = _piece_grid(p)
        pa = br.spl_a(ua)
        th = br.pair.theta_px(br.view_a, pa)
        # Curve B densely (0.25 px) over the piece, where its epipolar angle is
        # monotone: the crossing with each epipolar line is unique (ordering
        # constraint) and found by sub-pixel linear interpolation.
        w0, w1 = p["u_b"]
        w = np.linspace(w0, w1, max(int(np.ceil((w1 - w0) / 0.25)) + 1, 2))
        th_b = br.pair.theta_px(br.view_b, br.spl_b(w))
        # Keep the monotone run of the window around its middle (on this finer grid
        # the window's edge may still touch a turning point).
        lo, hi = _monotone_window(w, th_b, w0, w1, 0.5 * (w0 + w1))
        run = (w >= lo) & (w <= hi)
        th_b, w = th_b[run], w[run]
        if th_b[-1] < th_b[0]:
            th_b, w = th_b[::-1], w[::-1]
        inside = (th >= th_b[0]) & (th <= th_b[-1])
        if np.count_nonzero(inside) < 2:
            continue
        wb = np.interp(th[inside], th_b, w)
        X = triangulate(br.view_a, pa[inside], br.view_b, br.spl_b(wb))
        samples.append(np.column_stack([ua[inside], X]))
    return samples


def _bridge(br: _Branch, samples: list[np.ndarray]) -> tuple[list[np.ndarray], list[tuple[float, float]]]:
    """Fill the parameter spans of view A that no piece covers; returns bridges and spans."""
    a0, a1 = br.dom_a
    covered = _merge([(float(s[0, 0]), float(s[-1, 0])) for s in samples], gap=1.0)
    spans: list[tuple[float, float]] = []
    cursor = a0
    for a, b in covered:
        if a - cursor > 1e-6:
            spans.append((cursor, a))
        cursor = max(cursor, b)
    if a1 - cursor > 1e-6:
        spans.append((cursor, a1))
    if not spans:
        return [], []
    if samples:
        allu = np.concatenate([s[:, 0] for s in samples])
        alld = br.view_a.depth(np.concatenate([s[:, 1:] for s in samples]))
        order = np.argsort(allu)
        allu, alld = allu[order], alld[order]
    else:
        allu = alld = np.empty(0)
    end0, end1 = br.end_depths()

    def side(u: float, toward: float) -> tuple[float, float] | None:
        """Depth and slope of the covered data next to ``u`` (looking away from ``toward``)."""
        sel = (allu >= u - 6.0) & (allu <= u) if toward > u else (allu >= u) & (allu <= u + 6.0)
        if np.count_nonzero(sel) < 3:
            return None
        g, c = np.polyfit(allu[sel] - u, alld[sel], 1)
        return float(c), float(g)

    bridges = []
    for u0, u1 in spans:
        left = side(u0, u1) if u0 > a0 + 1e-6 else None
        right = side(u1, u0) if u1 < a1 - 1e-6 else None
        d0 = left[0] if left else end0
        d1 = right[0] if right else end1
        g0 = left[1] if left else None
        g1 = right[1] if right else None
        h = u1 - u0
        x = np.linspace(u0, u1, max(int(np.ceil(h / _FIT_STEP_PX)) + 1, 2))
        if g0 is not None and g1 is not None:
            depth = interpolate.CubicHermiteSpline([u0, u1], [d0, d1], [g0, g1])(x)
        elif g0 is not None or g1 is not None:
            # Quadratic through both end values with the one known slope.
            t = (x - u0) / h
            if g0 is not None:
                depth = d0 + g0 * h * t + (d1 - d0 - g0 * h) * t**2
            else:
                depth = d1 - g1 * h * (1 - t) + (d0 - d1 + g1 * h) * (1 - t) ** 2
        else:
            depth = np.interp(x, [u0, u1], [d0, d1])
        fixed_l = fixed_r = None
        if left is not None:
            fixed_l = left[0] - left[1] * _FIT_STEP_PX * np.array([2.0, 1.0])
        if right is not None:
            fixed_r = right[0] + right[1] * _FIT_STEP_PX * np.array([1.0, 2.0])
        # The fixed neighbours are the ends of the covered data, so drop the span's own ends there.
        xs, ds = x, depth
        if left is not None:
            xs, ds = xs[1:], ds[1:]
            fixed_l = np.append(fixed_l, depth[0])
        if right is not None and len(xs) > 1:
            xs, ds = xs[:-1], ds[:-1]
            fixed_r = np.insert(fixed_r, 0, depth[-1])
        if len(xs):
            # Curve B's parameters at the span's two ends bound where its samples
            # may match: the ordered correspondence is ambiguous inside the span.
            ub_l = br.ub_at(u0, d0) if left is not None else br.dom_b[0]
            ub_r = br.ub_at(u1, d1) if right is not None else br.dom_b[1]
            w_est = np.interp(xs, br.ua[br.path[0]], br.ub[br.path[1]])
            if h >= _TRACK_MIN_PX:  # shorter spans cannot hold a fold
                tracked, w_tracked = _track_bridge(br, xs, ds, (ub_l, ub_r), (d0, d1),
                                                   (left is not None, right is not None))
                # The tracking decides on which side of curve B's folds the span
                # lies; its fine shape follows the pixel noise. So it replaces the
                # first guess only where that guess sits on another fold.
                if np.max(np.abs(tracked - ds)) > _TRACK_SWITCH_MM:
                    ds, w_est = tracked, w_tracked
            ds = _refine_bridge(br, xs, ds, fixed_l, fixed_r,
                                (None if left is not None else end0, None if right is not None else end1),
                                w_est)
            depth = np.interp(x, xs, ds) if len(xs) > 1 else depth
            if left is not None:
                depth[0] = d0
            if right is not None:
                depth[-1] = d1
        bridges.append(np.column_stack([x, br.rays_a(x, depth)]))
    return bridges, spans


def _to_polyline(q: np.ndarray, pb: np.ndarray, wu: np.ndarray, tree: Any) -> tuple[np.ndarray, np.ndarray]:
    """Distance of image points ``q`` to the polyline ``pb`` and the curve parameter there.

    The nearest vertex (k-d ``tree`` of ``pb``), then the nearest point on the
    two segments at it; ``wu`` are the vertices' curve parameters.
    """
    fin = np.all(np.isfinite(q), axis=1)  # points behind view B's source project to NaN
    q = np.where(fin[:, None], q, pb[0])
    _, k = tree.query(q)
    dist = np.full(len(q), np.inf)
    uq = wu[k].astype(float)
    for a_i, b_i in ((np.maximum(k - 1, 0), k), (k, np.minimum(k + 1, len(pb) - 1))):
        ab = pb[b_i] - pb[a_i]
        t = np.clip(np.einsum("ij,ij->i", q - pb[a_i], ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12),
                    0.0, 1.0)
        dd = np.linalg.norm(q - pb[a_i] - t[:, None] * ab, axis=1)
        better = dd < dist
        dist = np.where(better, dd, dist)
        uq = np.where(better, wu[a_i] + t * (wu[b_i] - wu[a_i]), uq)
    return np.where(fin, dist, np.inf), uq


def _track_bridge(br: _Branch, x: np.ndarray, depth: np.ndarray, ub_range: tuple[float, float],
                  d_ends: tuple[float, float], fixed: tuple[bool, bool]) -> tuple[np.ndarray, np.ndarray]:
    """Starting depths and curve B parameters over an ill-conditioned span (dynamic programming).

    Around the first guess ``depth`` (a cubic that continues the neighbouring
    pieces) a grid of depth offsets along each of view A's rays is projected
    into view B. Where the branch runs along the epipolar lines, several depths
    project onto curve B: the true point and the other sides of curve B's
    folds, which a local refinement cannot tell apart. The chain chosen here
    lies on curve B (between its parameters at the span's ends), advances along
    it in order, starts and ends at the span's known depths and parameters, and
    otherwise keeps the first guess's shape; the regularized refinement starts
    from it.
    """
    from scipy.spatial import cKDTree

    half = 3.0 + 3.0 * max(br.sig_a, br.sig_b)
    fallback = depth, np.interp(x, br.ua[br.path[0]], br.ub[br.path[1]])
    sel = (br.b_dense_u >= min(ub_range) - half) & (br.b_dense_u <= max(ub_range) + half)
    if np.count_nonzero(sel) < 3 or len(x) < 2:
        return fallback
    pb, wu = br.b_dense[sel], br.b_dense_u[sel]
    tree = cKDTree(pb)
    thr = 1.0 + 3.0 * max(br.sig_a, br.sig_b)
    rising = ub_range[1] >= ub_range[0]
    back_px = 0.5 + 3.0 * max(br.sig_a, br.sig_b)  # how far curve B may seem to step back
    # A first guess that already lies on curve B and advances along it in order
    # is on the right side of any fold: nothing to track.
    dist0, u_first = _to_polyline(br.view_b.project(br.rays_a(x, depth)), pb, wu, tree)
    steps = np.diff(u_first) if rising else -np.diff(u_first)
    if np.all(dist0 <= thr) and np.all(steps >= -back_px):
        return fallback
    # Every ~1 px along the span (the refinement works on the full grid).
    stride = max(int(round(_TRACK_ROW_PX / max(x[1] - x[0], 1e-9))), 1)
    idx = np.unique(np.append(np.arange(0, len(x), stride), len(x) - 1))
    xt, dt = x[idx], depth[idx]
    offs = np.arange(-_TRACK_MARGIN_MM, _TRACK_MARGIN_MM + 1e-9, _TRACK_STEP_MM)
    n, g = len(xt), len(offs)
    dg = dt[:, None] + offs[None, :]
    X = br.view_a.source + dg[:, :, None] * br.ray_steps_a(xt)[:, None, :]
    dist, uq = _to_polyline(br.view_b.project(X.reshape(-1, 3)), pb, wu, tree)
    dist, ug = dist.reshape(n, g), uq.reshape(n, g)
    sig = max(br.sig_a, br.sig_b, 0.3)
    cost = (np.minimum(dist, 3.0 * thr) / sig) ** 2 + (offs[None, :] / _TRACK_PRIOR_MM) ** 2
    # End conditions: the known depth (a covered neighbour, else the
    # triangulated branch end, looser) and curve B's parameter there.
    for row, d_end, u_end, is_fixed in ((0, d_ends[0], ub_range[0], fixed[0]),
                                        (n - 1, d_ends[1], ub_range[1], fixed[1])):
        s_d = 0.5 if is_fixed else 2.0
        cost[row] += ((dg[row] - d_end) / s_d) ** 2 + ((ug[row] - u_end) / half) ** 2
    band = np.arange(-_TRACK_BAND, _TRACK_BAND + 1)
    src = np.clip(np.arange(g)[:, None] + band[None, :], 0, g - 1)  # predecessor levels
    trans = ((offs[src] - offs[:, None]) / _TRACK_STEP_SCALE_MM) ** 2
    acc = cost[0]
    back = np.zeros((n, g), dtype=np.intp)
    for i in range(1, n):
        du = ug[i][:, None] - ug[i - 1][src]
        ok = (du >= -back_px) if rising else (du <= back_px)
        tot = np.where(ok, acc[src] + trans, np.inf)
        j = np.argmin(tot, axis=1)
        back[i] = src[np.arange(g), j]
        acc = tot[np.arange(g), j] + cost[i]
    if not np.isfinite(acc).any():
        return fallback
    chain = np.empty(n, dtype=np.intp)
    chain[-1] = int(np.argmin(acc))
    for i in range(n - 1, 0, -1):
        chain[i - 1] = back[i, chain[i]]
    rows = np.arange(n)
    return np.interp(x, xt, dg[rows, chain]), np.interp(x, xt, ug[rows, chain])


def _refine_bridge(br: _Branch, x: np.ndarray, depth: np.ndarray, fixed_left: np.ndarray | None,
                   fixed_right: np.ndarray | None, anchors: tuple[float | None, float | None],
                   w_est: np.ndarray, iterations: int = 6) -> np.ndarray:
    """Depths along view A's rays over an ill-conditioned span, by regularized Gauss-Newton.

    Minimizes the squared distance (px) of the projections into view B from
    curve B, weighted by the 2D noise, plus a smoothness prior on the second
    differences of the depth (which continue the fixed neighbouring depths).
    Where the conditioning vanishes the prior takes over; elsewhere the data
    still decide, so an exact input is recovered exactly up to the tangency.
    """
    n = len(x)
    left = np.empty(0) if fixed_left is None else fixed_left
    right = np.empty(0) if fixed_right is None else fixed_right
    nl, nr = len(left), len(right)
    sigma_px = max(br.sig_a, br.sig_b, 0.01)  # the estimated pixel noise of the input
    w_data = 1.0 / sigma_px**2
    w_prior = 1.0 / PRIOR_MM**2
    m = nl + n + nr
    # Each sample may only match curve B near the point the tracking put it
    # on: inside a fold the other side of curve B is close in the image but
    # far along the curve, and must not capture the sample.
    pb, wu = br.b_dense, br.b_dense_u
    half = 3.0 + 3.0 * max(br.sig_a, br.sig_b)
    m_win = int(np.ceil(2 * half / (wu[1] - wu[0]))) + 2
    base = np.clip(np.searchsorted(wu, w_est - half), 0, max(len(wu) - m_win, 0))
    win = np.minimum(base[:, None] + np.arange(m_win)[None, :], len(wu) - 1)
    d = depth.astype(float).copy()
    s_b = br.view_b
    src, ray = br.view_a.source, br.ray_steps_a(x)
    for _ in range(iterations):
        q = s_b.project(src + d[:, None] * ray)
        q2 = s_b.project(src + (d + 0.01)[:, None] * ray)
        dq = (q2 - q) / 0.01
        k = win[np.arange(n), np.argmin(np.linalg.norm(pb[win] - q[:, None], axis=2), axis=1)]
        k = np.clip(k, 1, len(pb) - 2)
        # Nearest point on the two segments around the nearest sample.
        best = None
        for a_idx, b_idx in ((k - 1, k), (k, k + 1)):
            a, b = pb[a_idx], pb[b_idx]
            ab = b - a
            ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
            t = np.clip(np.einsum("ij,ij->i", q - a, ab) / ab2, 0.0, 1.0)
            c = a + t[:, None] * ab
            dist = np.linalg.norm(q - c, axis=1)
            nrm = np.stack([-ab[:, 1], ab[:, 0]], axis=1) / np.sqrt(ab2)[:, None]
            if best is None:
                best = (dist, c, nrm)
            else:
                sel = dist < best[0]
                best = (np.where(sel, dist, best[0]), np.where(sel[:, None], c, best[1]),
                        np.where(sel[:, None], nrm, best[2]))
        _, c, nrm = best
        r = np.einsum("ij,ij->i", nrm, q - c)
        J = np.einsum("ij,ij->i", nrm, dq)
        full = np.concatenate([left, d, right])
        # Normal equations of the free depths: pentadiagonal (prior) plus diagonal
        # (data, anchors), solved in banded form.
        diag = w_data * J**2
        grad = w_data * J * r
        if m >= 3:
            dtd_main = np.convolve(np.ones(m - 2), [1.0, 4.0, 1.0])  # diag of D^T D
            dtd_off1 = -2.0 * np.convolve(np.ones(m - 2), [1.0, 1.0])  # first off-diagonal
            dtd_off2 = np.ones(m - 2)
            free = slice(nl, nl + n)
            diag = diag + w_prior * dtd_main[free]
            off1 = w_prior * dtd_off1[nl : nl + n - 1]
            off2 = w_prior * dtd_off2[nl : nl + n - 2] if n >= 3 else np.empty(0)
            grad = grad + w_prior * np.convolve(np.diff(full, 2), [1.0, -2.0, 1.0])[free]
        else:
            off1, off2 = np.zeros(max(n - 1, 0)), np.zeros(max(n - 2, 0))
        # Weak anchors at the branch ends (triangulated end points).
        for pos, val in ((0, anchors[0]), (n - 1, anchors[1])):
            if val is not None:
                diag[pos] += 1.0 / 2.0**2
                grad[pos] += (d[pos] - val) / 2.0**2
        ab = np.zeros((3, n))
        ab[2] = diag + 1e-9
        ab[1, 1:] = off1
        ab[0, 2:] = off2
        step = linalg.solveh_banded(ab, -grad)
        d = d + np.clip(step, -20.0, 20.0)
        if np.max(np.abs(step)) < 1e-6:
            break
    return d


def intersect_centrelines(
    view_a: CArmView,
    pts_a_px: Any,
    view_b: CArmView,
    pts_b_px: Any,
    method: str = "nurbs",
    *,
    noise_px: float | None = None,
    min_noise_px: float = MIN_NOISE_PX,
    min_angle_deg: float = 10.0,
    depth_range_mm: float = 150.0,
    knot_spacing_px: float = 2.0,
) -> Centreline3D:
    """3D centreline of one vessel branch seen in two views.

    Parameters
    ----------
    view_a, view_b : CArmView
        The two views (different C-arm angles).
    pts_a_px, pts_b_px : array_like, shape (n, 2), or scipy.interpolate.BSpline
        The branch's 2D centreline in each view as ordered ``(col, row)``
        pixels, both running from the same (proximal) end, e.g. a skeleton
        path; or a clamped cubic 2D B-spline.
    method : {"nurbs", "epipolar"}
        ``"nurbs"``: intersection of the two extruded NURBS surfaces in OCCT
        (the paper's method). ``"epipolar"``: the point-wise epipolar baseline.
    noise_px : float, optional
        Noise sigma of the 2D points (px); estimated from the points if omitted.
    min_noise_px : float
        Floor under that estimate: ``vesselcad.splines.PIXEL_NOISE_PX`` for
        skeleton pixels (their quantization, which the estimate misses: the
        2D fits would follow the pixel steps and the 3D curve zig-zag in
        depth); the default keeps exact projections exact.
    min_angle_deg : float
        Spans where a 2D tangent runs closer than this to the epipolar line are
        ill-conditioned and are bridged instead of intersected.
    depth_range_mm : float
        Half depth of the surfaces around the isocentre (the patient).
    knot_spacing_px : float
        Knot spacing of the final 3D B-spline, in px of view A's curve.

    Returns
    -------
    Centreline3D
        Ordered like ``pts_a_px``; ``curve`` is the ``Geom_BSplineCurve``.
        Where one curve lies within less than :data:`END_ON_PX` of one point while
        the other spans at least :data:`END_ON_MIN_PX` (the vessel seen end-on in
        the first view), the straight segment along that view's ray that the
        other view's rays cross, parametrized by the other curve's chord length,
        with a warning saying so (and ``faces`` None).

    Raises
    ------
    ArgumentError
        Fewer than 2 distinct points, non-finite or non-numeric values, identical
        views, curves given from opposite ends, an unknown method or out-of-range
        options; an end-on segment whose ends lie outside ``depth_range_mm`` of the
        isocentre.

    Examples
    --------
    >>> import numpy as np, vesselcad as vc
    >>> a = vc.CArmView(30.0, 0.0, 1100.0, 750.0, (0.3, 0.3), 512, 512)
    >>> b = vc.CArmView(-30.0, 20.0, 1100.0, 750.0, (0.3, 0.3), 512, 512)
    >>> p = np.stack([np.linspace(-20, 20, 81), np.zeros(81), np.linspace(0, 10, 81)], axis=1)
    >>> c = vc.intersect_centrelines(a, a.project(p), b, b.project(p))
    >>> bool(np.abs(c.sample(5) - p[::20]).max() < 0.01)
    True
    """
    if method not in METHODS:
        raise ArgumentError(f"method: expected one of {METHODS}, got {method!r}")
    if not 0.0 < float(min_angle_deg) < 45.0:
        raise ArgumentError(f"min_angle_deg: expected a value in (0, 45), got {min_angle_deg!r}")
    if not float(depth_range_mm) > 0:
        raise ArgumentError(f"depth_range_mm: expected a positive value, got {depth_range_mm!r}")
    if not float(knot_spacing_px) > 0:
        raise ArgumentError(f"knot_spacing_px: expected a positive value, got {knot_spacing_px!r}")
    from .kernel.centreline import Centreline3D

    for pts, name in ((pts_a_px, "pts_a_px"), (pts_b_px, "pts_b_px")):
        if _curve_points(pts) is None:  # not (n, 2) finite points: the fit's checks name what is wrong
            fit_curve_2d(pts, noise_px, name, min_noise_px)
    end_on = _end_on_view(pts_a_px, pts_b_px)
    if end_on is not None:
        return _end_on_centreline(view_a, pts_a_px, view_b, pts_b_px, end_on, method, float(depth_range_mm))
    br = _Branch(view_a, pts_a_px, view_b, pts_b_px, noise_px, float(min_angle_deg), float(depth_range_mm),
                 min_noise_px)
    faces = None
    if method == "nurbs":
        samples, faces = _intersect_nurbs(br)
    else:
        samples = _intersect_epipolar(br)
    bridges, spans = _bridge(br, samples)
    data = np.vstack(samples + bridges)
    a0, a1 = br.dom_a
    spline = fit_pspline(data[:, 0], data[:, 1:], knot_step=float(knot_spacing_px), lam=1e-3, domain=(a0, a1))
    length = a1 - a0
    ill = float(sum(b - a for a, b in spans) / length) if length > 0 else 1.0
    warnings = []
    if not samples:
        warnings.append("no well-conditioned piece: the branch runs along the epipolar planes; "
                        "its depth is interpolated between the triangulated end points")
    elif ill > 0.5:
        warnings.append(f"{ill:.0%} of the branch is ill-conditioned (within {min_angle_deg:g} deg "
                        "of the epipolar lines) and bridged")
    return Centreline3D(
        spline=spline,
        method=method,
        ill_conditioned_fraction=ill,
        ill_conditioned_spans=[((a - a0) / length, (b - a0) / length) for a, b in spans],
        n_pieces=len(samples),
        noise_px=(br.sig_a, br.sig_b),
        faces=faces,
        warnings=warnings,
    )


def _curve_points(x: Any) -> np.ndarray | None:
    """``x`` (points or a 2D BSpline) as finite (n, 2) points, or None if it is not that."""
    try:
        if isinstance(x, interpolate.BSpline):
            k = x.k
            p = np.asarray(x(np.linspace(x.t[k], x.t[-k - 1], 200)), dtype=float)
        else:
            p = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        return None
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2 or not np.isfinite(p).all():
        return None
    return p


def _end_on_view(pts_a: Any, pts_b: Any) -> str | None:
    """'a' or 'b' where that view's curve is one point and the other's a curve, else None.

    Input that is not valid points is left to the regular path's checks.
    """
    pa, pb = _curve_points(pts_a), _curve_points(pts_b)
    if pa is None or pb is None:
        return None
    spread = [float(np.linalg.norm(p - p.mean(axis=0), axis=1).max()) for p in (pa, pb)]
    chord = [float(np.linalg.norm(p[-1] - p[0])) for p in (pa, pb)]
    if spread[0] < END_ON_PX and chord[1] >= END_ON_MIN_PX:
        return "a"
    if spread[1] < END_ON_PX and chord[0] >= END_ON_MIN_PX:
        return "b"
    return None


def _end_on_centreline(view_a: CArmView, pts_a: Any, view_b: CArmView, pts_b: Any, which: str,
                       method: str, depth_range_mm: float) -> Centreline3D:
    """The straight segment along the end-on view's ray that the other view's rays cross.

    The 3D points of a vessel that one view sees as a point lie on that
    view's ray through it; where along the ray each lies, the other view's
    rays say (they cross it at the view pair's angle, well conditioned).
    The segment runs between the crossings of the other curve's first and
    last rays, parametrized by that curve's chord length.
    """
    from .kernel.centreline import Centreline3D

    EpipolarPair(view_a, view_b)  # the views' own checks (identical views)
    pa, pb = _curve_points(pts_a), _curve_points(pts_b)
    if pa is None or pb is None:  # _end_on_view checked them; kept for type checkers
        raise ArgumentError("pts_a_px, pts_b_px: expected (n, 2) arrays of finite (col, row) pixels")
    (vp, pp, name_p), (vq, pq, name_q) = (((view_a, pa, "A"), (view_b, pb, "B")) if which == "a"
                                          else ((view_b, pb, "B"), (view_a, pa, "A")))
    point = pp.mean(axis=0)
    o, d = vp.ray(point)
    # Where each ray q crosses ray p: the mid-point of their shortest segment lies at the same
    # distance along ray p as the segment's end on it (the segment is perpendicular to ray p).
    t = (triangulate(vp, point, vq, pq) - o) @ d
    lo, hi = vp.sod_mm - depth_range_mm, vp.sod_mm + depth_range_mm
    if not (lo <= t[0] <= hi and lo <= t[-1] <= hi):
        raise ArgumentError(
            f"pts_{name_q.lower()}_px: its rays cross view {name_p}'s end-on ray {t[0]:.0f}-{t[-1]:.0f} mm "
            f"from view {name_p}'s source, outside {lo:.0f}-{hi:.0f} mm "
            "(depth_range_mm around the isocentre)")
    ends = o + np.outer([t[0], t[-1]], d)
    chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pq, axis=0), axis=1))]
    length = float(chord[-1])
    spline = interpolate.BSpline(np.r_[[0.0] * 4, [length] * 4], np.linspace(ends[0], ends[1], 4), 3)
    miss = float(np.max(np.linalg.norm(vq.project(o + np.outer(t, d)) - pq, axis=1)))
    warnings = [f"seen end-on in view {name_p} (one point there): a straight segment along its X-ray, "
                f"placed by view {name_q}'s curve"]
    if miss > _END_ON_MISS_PX:
        warnings.append(f"view {name_q}'s curve leaves the end-on ray's epipolar line by up to "
                        f"{miss:.1f} px: the two curves are not one vessel seen end-on")
    return Centreline3D(spline=spline, method=method, ill_conditioned_fraction=0.0, ill_conditioned_spans=[],
                        n_pieces=1, noise_px=(0.0, 0.0), faces=None, warnings=warnings)
