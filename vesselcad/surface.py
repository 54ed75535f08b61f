"""A smooth surface through a vessel tree's 3D points: the epicardial prior of the matching.

Coronary arteries and cardiac veins run on the heart's surface (the
epicardium), a smooth closed surface that a quadric (an ellipsoid where it
is fitted to points on all sides) follows to within millimetres over the
region one tree covers; the proximal vessel leaving the aorta and the
grooves in which the main vessels run are the largest departures. A wrong
pairing of two views' curves that share an epipolar band reprojects well
but lies at the wrong depth, so its 3D points leave that surface, typically
by 5-10 mm. :func:`fit_quadric_surface` fits the quadric
``x^T A x + 2 b^T x = 1``, restricted to ellipsoids of a heart's size, to the
points of a first matching: a random-sample (MSAC) start, then iteratively
reweighted least squares (Tukey's biweight on the distances, scale from their
median absolute value), so the wrong pairs among them do not bend it;
:meth:`QuadricSurface.distance` gives the first-order (Sampson) distance of
points to it, exact on the surface and accurate to ``d^2 / R`` for a point
``d`` off a surface of curvature radius ``R``.

See docs/centreline2d.md ("The heart's surface").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ArgumentError

__all__ = ["QuadricSurface", "fit_quadric_surface", "semi_axes"]

#: Tukey biweight tuning constant (95 % efficiency for Gaussian residuals).
TUKEY_C = 4.685
#: Reweighting rounds of the robust fit.
ROUNDS = 6
#: Semi-axes (mm) of the ellipsoids taken for a heart (adult hearts: about 30-80 mm).
AXIS_RANGE_MM = (15.0, 200.0)
#: A sample's quadric is scored by the mean square distance of the points, each at most this far (mm).
OUTLIER_MM = 3.0
#: Random samples of the start: of single points (12 points all inliers in one of them
#: when 75 % are: 99.8 %), of groups (3 groups, 50 % of them inliers: 99.97 %).
TRIALS_POINTS = 200
TRIALS_GROUPS = 60
#: Each sample has at least this many groups and points.
SAMPLE_GROUPS = 3
SAMPLE_POINTS = 12
#: A sample's quadric is scored on at most this many of the points.
SCORE_POINTS = 400


@dataclass(frozen=True)
class QuadricSurface:
    """The quadric ``q(u) = 1`` in normalized coordinates ``u = (x - centre) / scale``.

    Attributes
    ----------
    coefficients : numpy.ndarray, shape (9,)
        ``(A, B, C, D, E, F, G, H, I)`` of ``A u^2 + B v^2 + C w^2 + 2 D u v
        + 2 E u w + 2 F v w + 2 G u + 2 H v + 2 I w = 1``.
    centre : numpy.ndarray, shape (3,)
        Mean of the fitted points (mm).
    scale : float
        Their standard deviation (mm).
    sigma_mm : float
        Robust spread of the inliers' distances to the surface (1.4826 times
        their median): how closely the points follow a quadric.
    inliers : float
        Share of the points with a nonzero final weight.
    """

    coefficients: np.ndarray
    centre: np.ndarray
    scale: float
    sigma_mm: float
    inliers: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (mm, first order) of ``points`` (shape (..., 3)) to the surface."""
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (3,):
            raise ArgumentError(f"points: expected shape (..., 3), got {p.shape}")
        flat = p.reshape(-1, 3)
        return _distance(flat, self.coefficients, self.centre, self.scale).reshape(p.shape[:-1])

    def intersect_rays(self, origins: np.ndarray, directions: np.ndarray, near: np.ndarray) -> np.ndarray:
        """Where rays meet the surface: for each ray the crossing nearest a given parameter.

        Parameters
        ----------
        origins, directions : numpy.ndarray, shape (n, 3)
            Rays ``origin + t * direction`` (mm; directions need not be unit vectors).
        near : numpy.ndarray, shape (n,)
            Of a ray's two crossings, the one whose ``t`` is nearer this is returned.

        Returns
        -------
        numpy.ndarray, shape (n,)
            ``t`` of that crossing; NaN where the ray misses the surface.
        """
        o = np.asarray(origins, dtype=float)
        d = np.asarray(directions, dtype=float)
        t0 = np.asarray(near, dtype=float)
        if o.ndim != 2 or o.shape[1:] != (3,) or d.shape != o.shape or t0.shape != o.shape[:1]:
            raise ArgumentError(f"origins, directions, near: expected shapes (n, 3), (n, 3), (n,), got "
                                f"{o.shape}, {d.shape}, {t0.shape}")
        a_, b_, c_, d_, e_, f_, g_, h_, i_ = self.coefficients
        m = np.array([[a_, d_, e_], [d_, b_, f_], [e_, f_, c_]])
        g = np.array([g_, h_, i_])
        u0 = (o - self.centre) / self.scale
        v = d / self.scale
        # q(u0 + t v) = 1: a t^2 + b t + c = 0
        a = np.einsum("ni,ij,nj->n", v, m, v)
        b = 2.0 * (np.einsum("ni,ij,nj->n", u0, m, v) + v @ g)
        c = np.einsum("ni,ij,nj->n", u0, m, u0) + 2.0 * (u0 @ g) - 1.0
        with np.errstate(invalid="ignore", divide="ignore"):
            root = np.sqrt(b * b - 4.0 * a * c)
            t1, t2 = (-b - root) / (2.0 * a), (-b + root) / (2.0 * a)
        return np.where(np.abs(t1 - t0) <= np.abs(t2 - t0), t1, t2)


def _design(u: np.ndarray) -> np.ndarray:
    x, y, z = u.T
    return np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z], axis=1)


def _distance(p: np.ndarray, q: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    u = (p - centre) / scale
    value = _design(u) @ q - 1.0
    a, b, c, d, e, f, g, h, i = q
    x, y, z = u.T
    grad = np.stack([a * x + d * y + e * z + g, b * y + d * x + f * z + h, c * z + e * x + f * y + i], axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        return np.abs(value) / np.maximum(2.0 * np.linalg.norm(grad, axis=1), 1e-12) * scale


def semi_axes(q: np.ndarray, scale: float) -> np.ndarray | None:
    """Semi-axes (mm, ascending) of the quadric ``q`` if it is an ellipsoid, else None.

    Parameters
    ----------
    q : numpy.ndarray, shape (9,)
        :attr:`QuadricSurface.coefficients`.
    scale : float
        :attr:`QuadricSurface.scale` (mm per unit of the normalized coordinates).

    Raises
    ------
    ArgumentError
        ``q`` not of 9 finite numbers or ``scale`` not positive.
    """
    q = np.asarray(q, dtype=float)
    if q.shape != (9,) or not np.all(np.isfinite(q)):
        raise ArgumentError(f"q: expected 9 finite quadric coefficients, got shape {q.shape}")
    if not (np.isfinite(scale) and scale > 0):
        raise ArgumentError(f"scale: expected a positive number of mm, got {scale!r}")
    a, b, c, d, e, f, g, h, i = q
    A = np.array([[a, d, e], [d, b, f], [e, f, c]])
    lam = np.linalg.eigvalsh(A)
    if lam[0] * lam[-1] <= 0:
        return None
    k = 1.0 + float(np.array([g, h, i]) @ np.linalg.solve(A, [g, h, i]))
    if k * lam[0] <= 0:
        return None
    return np.sort(np.sqrt(k / lam)) * scale


def _plausible(q: np.ndarray | None, scale: float) -> bool:
    if q is None:
        return False
    ax = semi_axes(q, scale)
    return ax is not None and AXIS_RANGE_MM[0] <= ax[0] and ax[-1] <= AXIS_RANGE_MM[1]


def _score(p: np.ndarray, q: np.ndarray, centre: np.ndarray, scale: float) -> float:
    """Truncated mean square distance (MSAC): points beyond ``OUTLIER_MM`` count as that far."""
    return float(np.mean(np.minimum(_distance(p, q, centre, scale), OUTLIER_MM) ** 2))


def _solve(M: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Weighted least squares of ``M q = 1`` (weights ``w``) by the normal equations (9 x 9)."""
    A = M.T @ (M * w[:, None])
    try:
        q = np.linalg.solve(A, M.T @ w)
    except np.linalg.LinAlgError:
        return None
    return q if np.all(np.isfinite(q)) else None


def fit_quadric_surface(points: np.ndarray, groups: np.ndarray | None = None, *,
                        min_points: int = 60, trials: int | None = None, seed: int = 0
                        ) -> QuadricSurface | None:
    """Robust least-squares quadric through 3D points.

    An MSAC start (of the ellipsoids with semi-axes in ``AXIS_RANGE_MM``
    through a random sample of at least ``SAMPLE_GROUPS`` groups and
    ``SAMPLE_POINTS`` points, over ``trials`` samples, and through all
    points, the one of least mean square distance to the points, each
    counted at most ``OUTLIER_MM`` away) is
    refined by iteratively reweighted least squares (Tukey's biweight): the
    fit stands up to a third or more of the points lying off the surface,
    as long as the sample finds a set of inliers.

    Parameters
    ----------
    points : numpy.ndarray, shape (n, 3)
        Points in mm; rows with a non-finite coordinate are ignored.
    groups : numpy.ndarray of int, shape (n,), optional
        Points that stand or fall together (the samples of one curve): the
        random samples take whole groups. Default: every point alone.
    min_points : int
        Fewest finite points (and fewest inliers at every round) for a fit.
    trials : int, optional
        Random samples of the start (default ``TRIALS_GROUPS`` with
        ``groups``, ``TRIALS_POINTS`` without).
    seed : int
        Seed of their generator (the fit is deterministic).

    Returns
    -------
    QuadricSurface or None
        None where too few points are left or they do not determine a quadric
        (fewer than 9 independent directions, e.g. all on one line).

    Raises
    ------
    ArgumentError
        ``points`` not of shape (n, 3), ``groups`` not one label per point,
        ``min_points`` below 9 or ``trials`` below 1.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> u = rng.normal(size=(400, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> s = fit_quadric_surface(u * [55.0, 42.0, 40.0])
    >>> round(float(s.distance(np.array([[0.0, 0.0, 45.0]]))[0]), 2)  # 5 mm off, first order
    4.72
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ArgumentError(f"points: expected shape (n, 3), got {p.shape}")
    if groups is None:
        g = np.arange(len(p))
    else:
        g = np.asarray(groups)
        if g.shape != (len(p),) or not np.issubdtype(g.dtype, np.integer):
            raise ArgumentError(f"groups: expected one integer label per point ({len(p)}), got {g.shape}")
    if trials is None:
        trials = TRIALS_POINTS if groups is None else TRIALS_GROUPS
    for value, name, low in ((min_points, "min_points", 9), (trials, "trials", 1)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise ArgumentError(f"{name}: expected an integer of at least {low}, got {value!r}")
    ok = np.all(np.isfinite(p), axis=1)
    p, g = p[ok], g[ok]
    if len(p) < min_points:
        return None
    centre = p.mean(axis=0)
    scale = float(p.std())
    if scale <= 0:
        return None
    M = _design((p - centre) / scale)
    ev = np.linalg.eigvalsh(M.T @ M)
    if ev[0] <= 1e-10 * ev[-1]:
        return None
    labels, member = np.unique(g, return_inverse=True)
    order = np.argsort(member, kind="stable")
    starts = np.r_[0, np.cumsum(np.bincount(member))]
    rng = np.random.default_rng(seed)
    probe = p if len(p) <= SCORE_POINTS else p[rng.choice(len(p), SCORE_POINTS, replace=False)]
    best_q = _solve(M, np.ones(len(p)))
    best = _score(probe, best_q, centre, scale) if _plausible(best_q, scale) else np.inf
    for _ in range(trials):
        pick = rng.permutation(len(labels))
        sizes = starts[pick + 1] - starts[pick]
        k = max(SAMPLE_GROUPS, int(np.searchsorted(np.cumsum(sizes), SAMPLE_POINTS)) + 1)
        if k > len(labels):
            break
        rows = np.concatenate([order[starts[j]:starts[j + 1]] for j in pick[:k]])
        q = _solve(M[rows], np.ones(len(rows)))
        if not _plausible(q, scale):
            continue
        score = _score(probe, q, centre, scale)
        if score < best:
            best, best_q = score, q
    if not np.isfinite(best):
        return None
    q = best_q
    sigma = 1.4826 * float(np.median(_distance(p, q, centre, scale))) + 1e-9
    d = _distance(p, q, centre, scale)
    for _ in range(ROUNDS):
        w = np.maximum(1.0 - (d / (TUKEY_C * sigma)) ** 2, 0.0) ** 2
        if np.count_nonzero(w) < min_points:
            return None
        step = _solve(M, w)
        if not _plausible(step, scale):
            break  # stay with the last ellipsoid
        q = step
        d = _distance(p, q, centre, scale)
        sigma = 1.4826 * float(np.median(d[w > 0])) + 1e-9
    r = d / (TUKEY_C * sigma)
    return QuadricSurface(q, centre, scale, sigma, float(np.mean(r < 1.0)))
