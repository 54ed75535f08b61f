"""Phantom anatomy: a heart ellipsoid carrying a coronary or venous tree, and devices.

Vessels are grown as smooth curves on the epicardial surface (an ellipsoid):
a heading is turned by a steering term toward anatomical waypoints (the
interventricular and atrioventricular grooves, the apex) plus a smooth random
turn rate (sum of sinusoids in arc length), which gives tortuous C2 curves
with a curvature radius never below ``MIN_CURVATURE_RADIUS_MM``. Each child
vessel starts on a point of its parent at a bifurcation angle drawn from the
literature ranges. All lengths are mm in LPS patient coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Heart", "Vessel", "Anatomy", "make_anatomy", "ANATOMIES", "STEP_MM"]

ANATOMIES = ("lca", "rca", "cs")
STEP_MM = 0.5
MIN_CURVATURE_RADIUS_MM = 9.0
_BLEND_CURVATURE_RADIUS_MM = 30.0


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass
class Heart:
    """Epicardial ellipsoid: centre, long axis ``e1`` (base to apex), short axes."""

    centre: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    e3: np.ndarray
    a: float  # semi-axis along e1
    b: float  # semi-axis along e2
    c: float  # semi-axis along e3

    @property
    def axes_matrix(self) -> np.ndarray:
        """Columns are the semi-axis vectors."""
        return np.stack([self.a * self.e1, self.b * self.e2, self.c * self.e3], axis=1)

    def point(self, s: float, theta_deg: float, lift_mm: float = 0.0) -> np.ndarray:
        """Surface point at long-axis coordinate ``s`` in [-1, 1] and angle ``theta``.

        ``theta`` = 0 is anterior, 90 left lateral, 180 posterior, -90 right.
        """
        th = np.radians(theta_deg)
        rho = np.sqrt(max(1.0 - s * s, 0.0))
        p = self.centre + self.a * s * self.e1 + rho * (
            self.b * np.cos(th) * self.e2 + self.c * np.sin(th) * self.e3
        )
        return p + lift_mm * self.normal(p)

    def to_local(self, p: np.ndarray) -> np.ndarray:
        rel = p - self.centre
        return np.stack([rel @ self.e1 / self.a, rel @ self.e2 / self.b, rel @ self.e3 / self.c], -1)

    def project(self, p: np.ndarray) -> np.ndarray:
        """Radial projection onto the surface."""
        q = self.to_local(p)
        return self.centre + (p - self.centre) / np.linalg.norm(q, axis=-1, keepdims=True)

    def normal(self, p: np.ndarray) -> np.ndarray:
        """Outward unit normal of the ellipsoid level set through ``p`` (shape (..., 3))."""
        rel = p - self.centre
        g = (
            (rel @ self.e1)[..., None] / self.a**2 * self.e1
            + (rel @ self.e2)[..., None] / self.b**2 * self.e2
            + (rel @ self.e3)[..., None] / self.c**2 * self.e3
        )
        return _unit(g)


@dataclass
class Vessel:
    """One branch at rest: dense centreline (``STEP_MM`` spacing) and radius."""

    name: str
    parent: int | None
    points: np.ndarray  # (n, 3)
    radius: np.ndarray  # (n,)
    parent_index: int = 0  # index of the parent point the branch starts on
    path_mm: float = 0.0  # distance from the ostium (along the tree) of points[0]


@dataclass
class Device:
    """A device centreline (catheter, lead) with radius and attenuation."""

    kind: str  # "catheter" or "lead"
    points: np.ndarray
    radius: np.ndarray


@dataclass
class Anatomy:
    """Everything of one phantom case at rest (end-diastole, end-expiration)."""

    kind: str
    heart: Heart
    vessels: list[Vessel]
    devices: list[Device] = field(default_factory=list)
    balloon_centre: np.ndarray | None = None
    balloon_axes: np.ndarray | None = None  # (3, 3) columns = semi-axis vectors
    keypoint: np.ndarray | None = None  # the stationary object's key point
    keypoint_kind: str = "catheter_tip"


# ----------------------------------------------------------------- the walk
def _turn_noise(rng: np.random.Generator, n_steps: int, amplitude: float) -> np.ndarray:
    """Smooth random turn rate (1/mm) along arc length: a few sinusoids."""
    arc = np.arange(n_steps) * STEP_MM
    out = np.zeros(n_steps)
    for _ in range(4):
        wavelength = rng.uniform(10.0, 45.0)
        out += rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * arc / wavelength + rng.uniform(0, 2 * np.pi))
    return amplitude * out / 2.0


def _walk(
    heart: Heart,
    start: np.ndarray,
    heading: np.ndarray,
    waypoints: list[np.ndarray],
    length_mm: float,
    rng: np.random.Generator,
    tortuosity: float,
) -> np.ndarray:
    """Grow a curve on the heart surface from ``start`` along ``heading``."""
    n_steps = max(int(length_mm / STEP_MM), 2)
    noise = _turn_noise(rng, n_steps, tortuosity)
    kmax = 1.0 / MIN_CURVATURE_RADIUS_MM
    p = heart.project(start)
    nrm = heart.normal(p)
    h = _unit(heading - (heading @ nrm) * nrm)
    pts = [p]
    wp = 0
    for i in range(n_steps - 1):
        nrm = heart.normal(p)
        h = _unit(h - (h @ nrm) * nrm)
        kappa = noise[i]
        if wp < len(waypoints):
            to = waypoints[wp] - p
            if np.linalg.norm(to) < 8.0 and wp < len(waypoints) - 1:
                wp += 1
                to = waypoints[wp] - p
            to = to - (to @ nrm) * nrm
            if np.linalg.norm(to) > 1e-6:
                to = _unit(to)
                ang = np.arctan2(np.cross(h, to) @ nrm, h @ to)
                kappa += 0.08 * ang
        kappa = float(np.clip(kappa, -kmax, kmax))
        side = np.cross(nrm, h)
        dtheta = kappa * STEP_MM
        h = np.cos(dtheta) * h + np.sin(dtheta) * side
        p = heart.project(p + STEP_MM * h)
        pts.append(p)
    pts = np.asarray(pts)
    # Radial projection shortens steps slightly; resample to exact spacing.
    return _resample(pts, STEP_MM)


def _attach(pts: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Move the beginning of a surface curve onto ``start`` (which may lie off the surface).

    The offset fades out with a smoothstep over a length chosen so that the
    added curvature stays below 1 / _BLEND_CURVATURE_RADIUS_MM.
    """
    offset = start - pts[0]
    dist = float(np.linalg.norm(offset))
    if dist < 1e-9:
        return pts
    blend_len = max(2.0, np.sqrt(6.0 * dist * _BLEND_CURVATURE_RADIUS_MM))
    arc = np.arange(len(pts)) * STEP_MM
    x = np.clip(1.0 - arc / blend_len, 0.0, 1.0)
    w = x * x * (3 - 2 * x)
    out = pts + w[:, None] * offset
    out[0] = start
    return out


def _resample(points: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(arc[-1] / step), 1) + 1
    target = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(target, arc, points[:, k]) for k in range(3)], axis=1)


def _arc_hermite(p0: np.ndarray, p1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Hermite segment ending along ``t1`` whose start tangent mirrors ``t1`` about the
    chord, so the curve is close to a circular arc (even curvature)."""
    chord = p1 - p0
    c = _unit(chord)
    t0 = _unit(2.0 * (c @ t1) * c - t1)
    theta = float(np.arccos(np.clip(t0 @ t1, -1.0, 1.0)))
    if theta < 1e-3:
        return _hermite(p0, t0, p1, t1)
    radius = np.linalg.norm(chord) / (2.0 * np.sin(theta / 2.0))
    return _hermite(p0, t0, p1, t1, scale=4.0 * np.tan(theta / 4.0) * radius)


def _hermite(p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray,
             scale: float | None = None) -> np.ndarray:
    """Cubic Hermite segment sampled at ~STEP_MM; ``scale`` is the tangent length."""
    length = np.linalg.norm(p1 - p0)
    m = length if scale is None else scale
    u = np.linspace(0.0, 1.0, max(int(4 * length / STEP_MM), 8))[:, None]
    h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
    h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2
    pts = h00 * p0 + h10 * m * t0 + h01 * p1 + h11 * m * t1
    return _resample(pts, STEP_MM)


def _spline_path(anchors: list[np.ndarray]) -> np.ndarray:
    """Smooth path through anchor points (centripetal Catmull-Rom), ~STEP_MM spacing."""
    from scipy.interpolate import make_interp_spline

    a = np.asarray(anchors)
    chord = np.sqrt(np.linalg.norm(np.diff(a, axis=0), axis=1))
    u = np.concatenate([[0.0], np.cumsum(chord)])
    spl = make_interp_spline(u, a, k=3, bc_type="natural")
    dense = spl(np.linspace(0, u[-1], 2000))
    return _resample(dense, STEP_MM)


# ------------------------------------------------------------- tree builder
class _TreeBuilder:
    def __init__(self, heart: Heart, rng: np.random.Generator):
        self.heart = heart
        self.rng = rng
        self.vessels: list[Vessel] = []

    def add(self, name: str, points: np.ndarray, r0: float, r1: float,
            parent: int | None = None, parent_index: int = 0) -> int:
        n = len(points)
        frac = np.linspace(0.0, 1.0, n)
        wobble = 1.0 + 0.04 * np.sin(2 * np.pi * frac * self.rng.uniform(1, 3) + self.rng.uniform(0, 6))
        radius = np.clip((r0 + (r1 - r0) * frac) * wobble, 0.8, 2.5)
        path = 0.0
        if parent is not None:
            path = self.vessels[parent].path_mm + parent_index * STEP_MM
        self.vessels.append(Vessel(name, parent, points, radius, parent_index, path))
        return len(self.vessels) - 1

    def child(self, name: str, parent: int, frac: float, angle_deg: float,
              waypoints: list[np.ndarray], length: float, r_ratio: tuple[float, float],
              r_end: float, tortuosity: float = 0.022) -> int | None:
        par = self.vessels[parent]
        idx = int(np.clip(round(frac * (len(par.points) - 1)), 1, len(par.points) - 2))
        start = par.points[idx]
        tangent = _unit(par.points[idx + 1] - par.points[idx - 1])
        nrm = self.heart.normal(start)
        side = np.cross(nrm, tangent)
        ang = np.radians(abs(angle_deg))
        # Branch off on the side of the first waypoint, so no branch loops back.
        candidates = [np.cos(ang) * tangent + sgn * np.sin(ang) * side for sgn in (1.0, -1.0)]
        to_wp = _unit(waypoints[0] - start)
        heading = max(candidates, key=lambda h: float(h @ to_wp))
        pts = _walk(self.heart, start, heading, waypoints, length, self.rng, tortuosity)
        pts = _attach(pts, start)
        r0 = float(par.radius[idx]) * self.rng.uniform(*r_ratio)
        return self.add(name, pts, r0, min(r_end, r0), parent, idx)


def _make_heart(rng: np.random.Generator) -> Heart:
    # Long axis toward the patient's left, anterior and inferior (LPS: +x, -y, -z).
    e1 = _unit(np.array([0.55, -0.45, -0.70]) + rng.normal(0, 0.06, 3))
    ant = np.array([0.0, -1.0, 0.0])
    e2 = _unit(ant - (ant @ e1) * e1)
    e3 = np.cross(e1, e2)
    if e3[0] < 0:  # theta = +90 deg must be the left lateral wall
        e3 = -e3
    centre = rng.normal(0, 4.0, 3)
    return Heart(centre, e1, e2, e3, a=rng.uniform(52, 60), b=rng.uniform(40, 45), c=rng.uniform(38, 43))


def _lca(tb: _TreeBuilder, rng: np.random.Generator) -> np.ndarray:
    H = tb.heart
    ostium = H.point(-0.93, 30.0, lift_mm=9.0)
    bif = H.point(-0.66, rng.uniform(15, 28))
    t_end = _tangent_heading(H, bif, H.point(-0.5, 10.0))
    lm = _arc_hermite(ostium, bif, t_end)
    lm_i = tb.add("LM", lm, rng.uniform(2.1, 2.4), rng.uniform(1.9, 2.1))
    lad_wp = [H.point(-0.3, 4), H.point(0.3, 0), H.point(0.85, -5), H.point(0.99, 40)]
    lad = tb.child("LAD", lm_i, 1.0, -rng.uniform(25, 45), lad_wp, rng.uniform(120, 150),
                   (0.85, 0.95), 0.9)
    lcx_wp = [H.point(-0.62, 60), H.point(-0.62, 105), H.point(-0.6, 145)]
    lcx = tb.child("LCx", lm_i, 1.0, rng.uniform(75, 100), lcx_wp, rng.uniform(80, 110),
                   (0.75, 0.9), 0.9)
    n_diag = int(rng.integers(2, 5))
    for k, f in enumerate(np.sort(rng.uniform(0.12, 0.6, n_diag))):
        p = tb.vessels[lad].points[int(f * (len(tb.vessels[lad].points) - 1))]
        s, th = _chart(H, p)
        wp = [H.point(min(s + 0.55, 0.9), th + rng.uniform(45, 75))]
        d = tb.child(f"D{k + 1}", lad, f, rng.uniform(35, 60), wp, rng.uniform(45, 80), (0.6, 0.75), 0.8)
        if rng.random() < 0.5 and d is not None:
            p2 = tb.vessels[d].points[len(tb.vessels[d].points) // 2]
            s2, th2 = _chart(H, p2)
            tb.child(f"D{k + 1}a", d, 0.5, -rng.uniform(35, 55), [H.point(min(s2 + 0.4, 0.9), th2 - 10)],
                     rng.uniform(20, 35), (0.7, 0.85), 0.8)
    n_om = int(rng.integers(2, 5))
    for k, f in enumerate(np.sort(rng.uniform(0.25, 0.9, n_om))):
        p = tb.vessels[lcx].points[int(f * (len(tb.vessels[lcx].points) - 1))]
        s, th = _chart(H, p)
        wp = [H.point(0.6, th + rng.uniform(-10, 10))]
        tb.child(f"OM{k + 1}", lcx, f, -rng.uniform(55, 80), wp, rng.uniform(45, 75), (0.65, 0.8), 0.8)
    if len(tb.vessels) < 8:
        tb.child("S1", lad, 0.3, rng.uniform(40, 60), [H.point(0.2, -30)], 30, (0.5, 0.6), 0.8)
    return ostium


def _tangent_heading(H: Heart, p: np.ndarray, toward: np.ndarray) -> np.ndarray:
    """Unit direction from ``p`` toward ``toward`` within the surface's tangent plane."""
    nrm = H.normal(p)
    d = toward - p
    return _unit(d - (d @ nrm) * nrm)


def _chart(H: Heart, p: np.ndarray) -> tuple[float, float]:
    q = H.to_local(p)
    return float(np.clip(q[0], -1, 1)), float(np.degrees(np.arctan2(q[2], q[1])))


def _rca(tb: _TreeBuilder, rng: np.random.Generator) -> np.ndarray:
    H = tb.heart
    ostium = H.point(-0.95, -35.0, lift_mm=9.0)
    groove = H.point(-0.66, -45.0)
    h0 = _tangent_heading(H, groove, H.point(-0.66, -80))
    prox = _arc_hermite(ostium, groove, h0)
    wp = [H.point(-0.64, -90), H.point(-0.62, -135), H.point(-0.6, -178), H.point(-0.5, 165)]
    body = _walk(H, groove, h0, wp, rng.uniform(115, 140), rng, 0.02)
    rca = tb.add("RCA", np.vstack([prox, body[1:]]), rng.uniform(1.9, 2.3), 1.3)
    tb.child("conus", rca, 0.06, -rng.uniform(50, 80), [H.point(-0.5, 10)], rng.uniform(20, 35),
             (0.45, 0.55), 0.8)
    n_am = int(rng.integers(2, 5))
    for k, f in enumerate(np.sort(rng.uniform(0.25, 0.6, n_am))):
        p = tb.vessels[rca].points[int(f * (len(tb.vessels[rca].points) - 1))]
        s, th = _chart(H, p)
        tb.child(f"AM{k + 1}", rca, f, -rng.uniform(55, 80), [H.point(0.55, th + rng.uniform(-5, 10))],
                 rng.uniform(40, 65), (0.6, 0.75), 0.8)
    pda = tb.child("PDA", rca, 0.82, -rng.uniform(50, 70), [H.point(-0.2, 180), H.point(0.6, 178)],
                   rng.uniform(65, 90), (0.75, 0.85), 0.8)
    for k in range(int(rng.integers(1, 3))):
        tb.child(f"PDA-S{k + 1}", pda, 0.3 + 0.3 * k, rng.uniform(40, 60) * (-1) ** k,
                 [H.point(0.3, 180 + 25 * (-1) ** k)], rng.uniform(20, 30), (0.65, 0.8), 0.8)
    for k in range(int(rng.integers(1, 3))):
        tb.child(f"PLV{k + 1}", rca, 0.93 + 0.03 * k, rng.uniform(40, 60),
                 [H.point(0.3, 150 - 20 * k)], rng.uniform(35, 55), (0.6, 0.75), 0.8)
    return ostium


def _cs(tb: _TreeBuilder, rng: np.random.Generator) -> np.ndarray:
    H = tb.heart
    ostium = H.point(-0.64, -160.0)
    wp = [H.point(-0.63, 175), H.point(-0.63, 135), H.point(-0.62, 95), H.point(-0.6, 50)]
    cs_pts = _walk(H, ostium, _unit(H.point(-0.63, 175) - ostium), wp, rng.uniform(120, 145), rng, 0.015)
    cs = tb.add("CS-GCV", cs_pts, rng.uniform(2.3, 2.5), 1.7)
    tb.child("AIV", cs, 1.0, -rng.uniform(10, 25), [H.point(-0.2, 8), H.point(0.6, 3)],
             rng.uniform(60, 85), (0.75, 0.85), 0.9)
    tb.child("MCV", cs, 0.05, -rng.uniform(60, 85), [H.point(-0.2, -178), H.point(0.6, 180)],
             rng.uniform(60, 85), (0.6, 0.7), 0.9)
    tb.child("PVLV", cs, rng.uniform(0.22, 0.32), -rng.uniform(55, 80),
             [H.point(0.5, rng.uniform(140, 155))], rng.uniform(50, 70), (0.6, 0.75), 0.8)
    for k, f in enumerate(np.sort(rng.uniform(0.45, 0.85, int(rng.integers(2, 4))))):
        p = tb.vessels[cs].points[int(f * (len(tb.vessels[cs].points) - 1))]
        s, th = _chart(H, p)
        v = tb.child(f"LMV{k + 1}", cs, f, -rng.uniform(55, 80), [H.point(0.55, th + rng.uniform(-8, 8))],
                     rng.uniform(45, 70), (0.55, 0.7), 0.8)
        if rng.random() < 0.6 and v is not None:
            tb.child(f"LMV{k + 1}a", v, 0.55, rng.uniform(35, 55) * rng.choice([-1, 1]),
                     [H.point(0.7, th + 20)], rng.uniform(20, 30), (0.7, 0.85), 0.8)
    while len(tb.vessels) < 8:
        tb.child(f"T{len(tb.vessels)}", cs, rng.uniform(0.35, 0.7), -rng.uniform(50, 70),
                 [H.point(-0.2, 120)], rng.uniform(20, 30), (0.5, 0.6), 0.8)
    return ostium


def _twigs(tb: _TreeBuilder, rng: np.random.Generator, n: int) -> None:
    """Short thin side branches off random points of the existing vessels (real trees
    show many more small branches than the named ones)."""
    H = tb.heart
    for k in range(n):
        if len(tb.vessels) >= 30:
            return
        parent = int(rng.integers(len(tb.vessels)))
        par = tb.vessels[parent]
        n = len(par.points)
        ok = np.nonzero(par.radius[int(0.1 * n) : int(0.9 * n)] >= 1.0)[0] + int(0.1 * n)
        if n < 40 or ok.size == 0:
            continue
        f = float(rng.choice(ok)) / (n - 1)
        s, th = _chart(H, par.points[int(f * (len(par.points) - 1))])
        target = H.point(float(np.clip(s + rng.uniform(0.1, 0.3), -0.7, 0.95)),
                         th + rng.choice([-1.0, 1.0]) * rng.uniform(15, 35))
        tb.child(f"{par.name}-t{k + 1}", parent, f, rng.uniform(40, 75), [target],
                 rng.uniform(12, 30), (0.5, 0.6), 0.8)


def make_anatomy(rng: np.random.Generator, kind: str, twigs: int | None = None) -> Anatomy:
    """Random but anatomically plausible tree and devices for ``kind`` in ANATOMIES.

    ``twigs`` small side branches are added to the named vessels (default: 3 to 8,
    drawn; at most 30 vessels in all). Giving it changes the random stream after
    the tree, so the rest of a case differs from the default's.
    """
    heart = _make_heart(rng)
    tb = _TreeBuilder(heart, rng)
    builder = {"lca": _lca, "rca": _rca, "cs": _cs}[kind]
    ostium = builder(tb, rng)
    drawn = int(rng.integers(3, 9))  # drawn always: the default cases stay as they were
    _twigs(tb, rng, drawn if twigs is None else int(twigs))
    vessels = tb.vessels
    anatomy = Anatomy(kind, heart, vessels)
    H = heart
    base = H.centre - 1.0 * H.a * H.e1
    up = np.array([0.0, 0.0, 1.0])
    if kind in ("lca", "rca"):
        # Guiding catheter: from the descending aorta over the arch, down the
        # ascending aorta into the ostium. Its tip is the stationary key point.
        root = base + 12.0 * up - 8.0 * H.e2
        anchors = [
            root + np.array([35.0, 45.0, -200.0]),
            root + np.array([30.0, 45.0, 0.0]),
            root + np.array([15.0, 25.0, 75.0]),
            root + np.array([-10.0, -5.0, 70.0]),
            root + np.array([-8.0, -10.0, 25.0]),
            ostium + 14.0 * _unit(ostium - H.point(-0.7, 30.0 if kind == "lca" else -35.0)) + 6.0 * up,
            ostium,
        ]
        cath = _spline_path(anchors)
        anatomy.devices.append(Device("catheter", cath, np.full(len(cath), 1.0)))
        anatomy.keypoint = ostium.copy()
        anatomy.keypoint_kind = "catheter_tip"
        if rng.random() < 0.35:
            anatomy.devices.append(_rv_lead(H, rng))
    else:
        cs = vessels[0]
        k_bal = int(rng.uniform(10.0, 16.0) / STEP_MM)
        centre = cs.points[k_bal]
        t = _unit(cs.points[k_bal + 2] - cs.points[k_bal - 2])
        n1 = _unit(np.cross(t, up))
        n2 = np.cross(t, n1)
        rb = float(cs.radius[k_bal]) + rng.uniform(0.8, 1.3)
        anatomy.balloon_centre = centre
        anatomy.balloon_axes = np.stack([rng.uniform(4.5, 6.0) * t, rb * n1, rb * n2], axis=1)
        ra = H.point(-0.85, -120.0, lift_mm=15.0)
        anchors = [
            ra + np.array([-10.0, 5.0, 190.0]),
            ra + np.array([-8.0, 0.0, 60.0]),
            ra,
            cs.points[0] - 12.0 * t + np.array([0.0, 0.0, 4.0]),
        ]
        lead_in = _spline_path(anchors)
        cath = np.vstack([lead_in, cs.points[1 : k_bal + 1]])
        anatomy.devices.append(Device("catheter", cath, np.full(len(cath), 1.0)))
        anatomy.keypoint = centre.copy()
        anatomy.keypoint_kind = "balloon_centre"
        anatomy.devices.append(_rv_lead(H, rng))
    return anatomy


def _rv_lead(H: Heart, rng: np.random.Generator) -> Device:
    """A right-ventricular pacing lead from the superior vena cava to the RV apex."""
    svc = H.point(-0.9, -100.0, lift_mm=25.0)
    anchors = [
        svc + np.array([-5.0, 0.0, 200.0]),
        svc + np.array([0.0, 0.0, 40.0]),
        svc,
        H.point(-0.2, -70.0, lift_mm=-10.0),
        H.point(0.75, rng.uniform(-45, -25), lift_mm=-6.0),
    ]
    pts = _spline_path(anchors)
    radius = np.full(len(pts), 0.55)
    radius[-int(4.0 / STEP_MM):] = 0.9  # tip electrode
    return Device("lead", pts, radius)
