"""Biplane phantom cases: two XA runs of a moving vessel tree with full ground truth."""

from __future__ import annotations

import io
import json
import os
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ArgumentError, OutputError
from ..geometry import CArmView
from ..io.atomic import atomic_write_bytes, atomic_write_text
from ..io.dicom import _uid, save_run
from ..io.run import XARun
from .anatomy import ANATOMIES, STEP_MM, Anatomy, make_anatomy
from .motion import MotionParams, contraction, deform, random_motion, resp_shift
from .xray import ellipsoid_chord, ray_march, smooth_noise, tube_image

__all__ = [
    "PhantomCase",
    "RenderedRun",
    "generate_case",
    "render",
    "write_case",
    "default_views",
    "LABELS",
]

#: Label values of the per-frame masks.
LABELS = {"background": 0, "vessel": 1, "catheter": 2, "balloon": 3, "lead": 4}

# Linear attenuation (1/mm) of what is drawn; iodinated contrast at full strength.
MU_CONTRAST = 0.26
MU_CATHETER = 0.30
MU_LEAD = 1.6
MU_BALLOON = 0.16
MU_HEART = 0.006  # soft tissue in place of lung
LUNG_DEFICIT = 0.010  # lung is this much less attenuating than soft tissue
VISIBLE_CONTRAST = 0.25  # vessel pixels count as "vessel" from this opacification on

#: Default view pairs (primary, secondary) in degrees, like the paper's.
_DEFAULT_ANGLES = {
    "cs": ((0.0, 0.0), (30.0, 0.0)),  # PA + LAO 30
    "lca": ((-30.0, 20.0), (45.0, -20.0)),  # RAO 30 CRA 20 + LAO 45 CAU 20
    "rca": ((30.0, 0.0), (90.0, 0.0)),  # LAO 30 + LAO 90
}


def default_views(anatomy: str, rows: int = 512, cols: int = 512) -> tuple[CArmView, CArmView]:
    """The default (true) view pair of an anatomy: SID 1100 mm, SOD 750 mm, 0.4 mm pixels.

    For 512 pixels this is 0.27 mm per pixel at the isocentre (a 140 mm field),
    typical of cardiac flat-panel cine.
    """
    if anatomy not in ANATOMIES:
        raise ArgumentError(f"anatomy: expected one of {ANATOMIES}, got {anatomy!r}")
    spacing = 0.4 * 512.0 / max(rows, cols)
    return tuple(  # type: ignore[return-value]
        CArmView(primary_deg=a, secondary_deg=b, sid_mm=1100.0, sod_mm=750.0,
                 pixel_spacing_mm=(spacing, spacing), rows=rows, cols=cols)
        for a, b in _DEFAULT_ANGLES[anatomy]
    )


@dataclass
class RenderedRun:
    """Frames, labels and ground truth of one rendered view."""

    frames: np.ndarray  # (N, H, W) uint8/uint16
    labels: np.ndarray  # (N, H, W) uint8, values in LABELS
    view: CArmView
    frame_times_ms: np.ndarray
    phases: np.ndarray  # (N, 2) cardiac, respiratory
    trees: list[dict[str, Any]]  # centrelines.json object per frame
    keypoints: np.ndarray  # (N, 2) px of the stationary object's key point
    r_wave_frames: np.ndarray
    bits_stored: int


@dataclass
class PhantomCase:
    """A biplane phantom case: two runs and their ground truth."""

    seed: int
    anatomy_kind: str
    anatomy: Anatomy
    motion: MotionParams
    run_a: RenderedRun
    run_b: RenderedRun
    header_view_a: CArmView
    header_view_b: CArmView
    synchronized: bool
    table_shift_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def xa_runs(self) -> tuple[XARun, XARun]:
        """The two runs as :class:`XARun` with the (possibly miscalibrated) header views."""
        out = []
        for tag, rr, hv in (("a", self.run_a, self.header_view_a), ("b", self.run_b, self.header_view_b)):
            out.append(XARun(
                frames=rr.frames, view=hv, frame_times_ms=rr.frame_times_ms,
                bits_stored=rr.bits_stored, r_wave_frames=rr.r_wave_frames,
                patient_id=f"PHANTOM-{self.seed:06d}", patient_name=f"Phantom^{self.anatomy_kind.upper()}",
                study_uid=_uid("phantom-study", self.seed, self.anatomy_kind),
                series_uid=_uid("phantom-series", self.seed, self.anatomy_kind, tag),
                study_date="20260101", source=f"phantom seed {self.seed} run {tag}",
            ))
        return out[0], out[1]

    def truth(self) -> dict[str, Any]:
        """The ``truth.json`` object of ARCHITECTURE.md (plus a few extra keys)."""
        return {
            "view_a": self.run_a.view.to_dict(),
            "view_b": self.run_b.view.to_dict(),
            "header_view_a": self.header_view_a.to_dict(),
            "header_view_b": self.header_view_b.to_dict(),
            "frames": int(self.run_a.frames.shape[0]),
            "phases_a": _r(self.run_a.phases, 6),
            "phases_b": _r(self.run_b.phases, 6),
            "trees_a": self.run_a.trees,
            "trees_b": self.run_b.trees,
            "keypoints_a": _r(self.run_a.keypoints, 4),
            "keypoints_b": _r(self.run_b.keypoints, 4),
            "keypoint_kind": self.anatomy.keypoint_kind,
            "anatomy": self.anatomy_kind,
            "seed": self.seed,
            "synchronized": self.synchronized,
            "table_shift_mm": _r(self.table_shift_mm, 4),
            "frame_times_ms_a": _r(self.run_a.frame_times_ms, 4),
            "frame_times_ms_b": _r(self.run_b.frame_times_ms, 4),
            "motion": {k: round(float(v), 6) for k, v in vars(self.motion).items()},
            "labels": LABELS,
        }


def _r(a: Any, nd: int) -> Any:
    return np.round(np.asarray(a, dtype=np.float64), nd).tolist()


# ------------------------------------------------------------- appearance
@dataclass
class _Appearance:
    photons: float
    mu_contrast: float
    texture: float
    gamma: float
    blur: float
    lo_margin: float
    hi_margin: float
    vignette: float


def _random_appearance(rng: np.random.Generator) -> _Appearance:
    return _Appearance(
        photons=rng.uniform(900, 2500),
        mu_contrast=MU_CONTRAST * rng.uniform(0.7, 1.1),
        texture=rng.uniform(0.7, 1.3),
        gamma=rng.uniform(1.25, 1.65),
        blur=rng.uniform(0.55, 0.9),
        lo_margin=rng.uniform(0.05, 0.3),
        hi_margin=rng.uniform(0.3, 0.7),
        vignette=rng.uniform(0.1, 0.3),
    )


def _body_density(diaphragm_only: bool):
    """Attenuation density of the thorax (1/mm): body, lungs, spine; or the sub-diaphragm layer."""

    def dome(x, y):
        # Right hemidiaphragm (x < 0) higher than the left.
        return -52.0 + 6.0 * np.tanh(-x / 40.0) - (x * x) / 900.0 - (y * y) / 1400.0

    def density(p):
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        body = ((x / 175.0) ** 2 + ((y - 20.0) / 125.0) ** 2) <= 1.0
        lung = np.zeros_like(x, dtype=bool)
        for cx in (-78.0, 78.0):
            lung |= ((x - cx) / 62.0) ** 2 + ((y - 15.0) / 78.0) ** 2 + ((z - 35.0) / 120.0) ** 2 <= 1
        below = z < dome(x, y)
        if diaphragm_only:
            return np.where(body & lung & below, LUNG_DEFICIT, 0.0)
        spine = ((x / 22.0) ** 2 + ((y - 82.0) / 18.0) ** 2) <= 1.0
        vert = 0.75 + 0.25 * np.cos(np.pi * z / 27.0) ** 2
        mu = np.where(body, 0.020, 0.0) - np.where(body & lung, LUNG_DEFICIT, 0.0)
        return mu + np.where(spine, 0.015 * vert, 0.0)

    return density


def _ribs() -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    lines, radii, mus = [], [], []
    phi = np.linspace(-0.15 * np.pi, 1.15 * np.pi, 420)
    for k in range(-4, 6):
        z0 = 27.0 * k + 5.0
        for side in (-1.0, 1.0):
            x = side * (20.0 + 150.0 * np.sin(phi / 1.3 + 0.2))
            y = 20.0 + 112.0 * np.cos(phi)
            z = z0 - 28.0 * (1 - np.cos(phi)) / 2  # ribs descend anteriorly
            pts = np.stack([x, y, z], axis=1)
            lines.append(pts)
            radii.append(np.full(len(pts), 5.0))
            mus.append(np.full(len(pts), 0.016))
    return lines, radii, mus


def _static_layers(view: CArmView, rng: np.random.Generator, app: _Appearance):
    body = ray_march(view, _body_density(False))
    dia = ray_march(view, _body_density(True))
    lines, radii, mus = _ribs()
    ribs, _, _ = tube_image(view, lines, radii, mus)
    ribs = cv2.GaussianBlur(ribs, (0, 0), 2.5 * view.rows / 512.0)  # soft cortical edges
    shape = (view.rows, view.cols)
    scale = view.rows / 512.0
    tex = app.texture * (
        0.12 * smooth_noise(rng, shape, 60 * scale)
        + 0.05 * smooth_noise(rng, shape, 14 * scale)
        + 0.025 * smooth_noise(rng, shape, 3 * scale)
    )
    rr, cc = np.mgrid[0 : view.rows, 0 : view.cols]
    rad2 = ((cc - (view.cols - 1) / 2) ** 2 + (rr - (view.rows - 1) / 2) ** 2) / (
        0.5 * max(view.rows, view.cols)) ** 2
    vignette = app.vignette * rad2
    return (body + ribs + tex + vignette).astype(np.float32), dia.astype(np.float32)


# ------------------------------------------------------------------ bolus
def _bolus(path_mm: np.ndarray, t_s: float, duration_s: float, max_path: float) -> np.ndarray:
    """Contrast opacification in [0, 1] along the tree at time ``t_s``."""
    fill = min(1.2, 0.35 * duration_s)
    t0 = 0.06 * duration_s
    v = max_path / fill
    washout = max(0.72 * duration_s, t0 + fill + 0.1)
    tau_in = max(0.06, 0.12 * fill)
    tau_out = max(0.3, 0.15 * duration_s)
    arrive = np.clip((t_s - t0 - path_mm / v) / tau_in + 0.5, 0, 1)
    leave = np.clip((t_s - washout - path_mm / (1.5 * v)) / tau_out, 0, 1)
    s = lambda x: x * x * (3 - 2 * x)  # noqa: E731
    return s(arrive) * (1 - s(leave))


# ---------------------------------------------------------------- one run
def _render_run(anat: Anatomy, view: CArmView, phases: np.ndarray, times_ms: np.ndarray,
                motion: MotionParams, app: _Appearance, rng: np.random.Generator,
                bits: int, shift_mm: np.ndarray, progress: Any = None, noise_draw: int = 0) -> RenderedRun:
    n = len(phases)
    rows, cols = view.rows, view.cols
    # The detector's blur and quantum noise are set for 512 px across the field (as the texture's
    # scales in _static_layers): a finer grid of the same field blurs over more pixels and each of
    # its pixels catches fewer photons, so that a 1024-px run averaged 2 x 2 looks like a 512-px one.
    scale = max(rows, cols) / 512.0
    blur_px, post_blur_px = app.blur * scale, 0.45 * scale
    photons_px = app.photons / scale ** 2
    static, dia = _static_layers(view, rng, app)
    heart = anat.heart
    vessels = anat.vessels
    v_pts = [v.points for v in vessels]
    v_rad = [v.radius for v in vessels]
    path = [v.path_mm + np.arange(len(v.points)) * STEP_MM for v in vessels]
    max_path = float(max(p.max() for p in path))
    duration_s = max(float(times_ms[-1]) / 1000.0, 1e-3) if n > 1 else 1.0
    truth_idx = [np.unique(np.r_[np.arange(0, len(p), int(round(1.0 / STEP_MM))), len(p) - 1])
                 for p in v_pts]
    # Heart shadow on a coarse grid, resized.
    g = 96
    gc, gr = np.meshgrid(np.linspace(0, cols - 1, g), np.linspace(0, rows - 1, g))
    lo = hi = None
    frames = np.zeros((n, rows, cols), np.uint16 if bits > 8 else np.uint8)
    labels = np.zeros((n, rows, cols), np.uint8)
    trees, keypoints = [], []
    noise_rng = np.random.default_rng(int(rng.integers(2**63)) + noise_draw)
    for i in range(n):
        cph, rph = float(phases[i, 0]), float(phases[i, 1])
        t_s = float(times_ms[i]) / 1000.0

        def move(p, cph=cph, rph=rph):
            return deform(p, heart, cph, rph, motion) + shift_mm

        moved = [move(p) for p in v_pts]
        conc = [_bolus(p, t_s, duration_s, max_path) for p in path]
        mu = [app.mu_contrast * c for c in conc]
        vessel_img, vessel_in, vessel_c = tube_image(view, moved, v_rad, mu, aux=conc)
        cath_img = np.zeros((rows, cols), np.float32)
        lab = np.zeros((rows, cols), np.uint8)
        lab[vessel_in & (vessel_c >= VISIBLE_CONTRAST)] = LABELS["vessel"]
        for dev in anat.devices:
            mu_dev = MU_CATHETER if dev.kind == "catheter" else MU_LEAD
            img, ins, _ = tube_image(view, [move(dev.points)], [dev.radius],
                                     [np.full(len(dev.points), mu_dev)])
            cath_img += img
            lab[ins] = LABELS[dev.kind]
        if anat.balloon_centre is not None:
            c_b = move(anat.balloon_centre)
            ax_pts = move(anat.balloon_centre + anat.balloon_axes.T) - c_b
            # Only the pixels around the balloon's projection can see it.
            corners = view.project(c_b + np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T
                                   @ np.abs(ax_pts))
            c0, r0 = np.clip(np.floor(np.nanmin(corners, 0)).astype(int) - 2, 0, [cols, rows])
            c1, r1 = np.clip(np.ceil(np.nanmax(corners, 0)).astype(int) + 3, 0, [cols, rows])
            if c1 > c0 and r1 > r0:
                cc_b, rr_b = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
                ch = ellipsoid_chord(view, c_b, ax_pts.T, cc_b, rr_b)
                cath_img[r0:r1, c0:c1] += (MU_BALLOON * ch).astype(np.float32)
                lab[r0:r1, c0:c1][ch > 0] = LABELS["balloon"]
        cfac = float(contraction(np.asarray(cph)))
        h_c = move(heart.centre)
        h_axes = heart.axes_matrix * np.array(
            [1 - motion.longitudinal * cfac, 1 - motion.radial * cfac, 1 - motion.radial * cfac])
        shadow = ellipsoid_chord(view, h_c, h_axes, gc, gr).astype(np.float32)
        shadow = cv2.resize(shadow, (cols, rows), interpolation=cv2.INTER_LINEAR)
        d_shift = view.project(resp_shift(rph, motion)) - view.project(np.zeros(3))
        dia_i = cv2.warpAffine(dia, np.float32([[1, 0, d_shift[0]], [0, 1, d_shift[1]]]),
                               (cols, rows), borderMode=cv2.BORDER_REPLICATE)
        A = static + dia_i + MU_HEART * shadow + vessel_img + cath_img
        A = cv2.GaussianBlur(A, (0, 0), blur_px)
        if lo is None:  # window fixed per run from the first frame's background
            bg = static + dia_i + MU_HEART * shadow
            p_lo, p_hi = np.percentile(bg, [1.0, 99.5])
            lo = float(p_lo - app.lo_margin * (p_hi - p_lo))
            hi = float(p_hi + app.hi_margin * (p_hi - p_lo))
        # Quantum noise: relative std 1/sqrt(N) of the transmitted photons.
        photons = photons_px * np.exp(-(A - lo))
        A = A + noise_rng.standard_normal(A.shape).astype(np.float32) / np.sqrt(np.maximum(photons, 1.0))
        A = cv2.GaussianBlur(A, (0, 0), post_blur_px)
        grey = np.clip((hi - A) / (hi - lo), 0, 1) ** app.gamma
        top = (1 << bits) - 1
        frames[i] = np.round(grey * (0.9 * top) + 0.04 * top).astype(frames.dtype)
        labels[i] = lab
        branches = []
        for k, v in enumerate(vessels):
            idx = truth_idx[k]
            branches.append({
                "id": k, "parent": v.parent, "name": v.name,
                "parent_s_mm": None if v.parent is None else round(v.parent_index * STEP_MM, 4),
                "points": np.round(moved[k][idx], 4).tolist(),
                "radius": np.round(v.radius[idx], 4).tolist(),
            })
        trees.append({"units": "mm", "frame": "LPS", "branches": branches})
        keypoints.append(view.project(move(anat.keypoint)))
        if progress is not None:
            progress.update(1)
    # RWavePointer: the frame nearest to each R-wave (cardiac phase wrapping through 0).
    ph_c = np.mod(phases[:, 0], 1.0)
    after = np.nonzero(np.diff(ph_c) < 0)[0] + 1
    r_wave = np.where(ph_c[after] <= 1.0 - ph_c[after - 1], after, after - 1)
    step = float(np.median(np.diff(phases[:, 0]))) if n > 1 else 1.0
    if n and ph_c[0] < 0.5 * step and (r_wave.size == 0 or r_wave[0] != 0):
        r_wave = np.r_[0, r_wave]
    return RenderedRun(frames, labels, view, np.asarray(times_ms, float), phases, trees,
                       np.asarray(keypoints), r_wave.astype(np.int64), bits)


def _phases(rng: np.random.Generator, n: int, fps: float, hr: float, resp_period: float,
            c0: float, r0: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / fps
    ph = np.stack([np.mod(c0 + t * hr / 60.0, 1.0), np.mod(r0 + t / resp_period, 1.0)], axis=1)
    return ph, t * 1000.0


def _perturb(view: CArmView, rng: np.random.Generator, deg: float) -> CArmView:
    if deg <= 0:
        return view
    d = view.to_dict()
    d["primary_deg"] = round(d["primary_deg"] + rng.uniform(-deg, deg), 3)
    d["secondary_deg"] = round(d["secondary_deg"] + rng.uniform(-deg, deg), 3)
    return CArmView.from_dict(d)


def generate_case(
    seed: int,
    anatomy: str = "lca",
    n_frames: int = 60,
    *,
    synchronized: bool = False,
    views: tuple[CArmView, CArmView] | None = None,
    rows: int = 512,
    cols: int = 512,
    fps: float = 15.0,
    bits: int = 8,
    miscalibration_deg: float = 0.0,
    table_shift_mm: float = 0.0,
    twigs: int | None = None,
    progress: bool = False,
    noise_draw: int = 0,
) -> PhantomCase:
    """Generate a seeded biplane phantom case (deterministic for a given seed and options).

    Parameters
    ----------
    seed : int
        Random seed; the same seed and options give identical data.
    anatomy : {'lca', 'rca', 'cs'}
        Left coronary tree, right coronary artery, or coronary sinus with tributaries.
    n_frames : int
        Frames per run.
    synchronized : bool
        If True both runs see identical cardiac and respiratory phases (a true
        biplane pair); otherwise run B is acquired later, at other phases.
    views : (CArmView, CArmView), optional
        True views of runs A and B; default :func:`default_views`.
    rows, cols : int
        Image size (when ``views`` is not given).
    fps : float
        Frame rate.
    bits : {8, 12}
        Bits stored per pixel.
    miscalibration_deg : float
        Up to this error (uniform) is added to the angles written in the DICOM
        headers (``header_view_*``); the images follow the true views.
    table_shift_mm : float
        Length of a random patient/table shift between run A and run B.
    twigs : int, optional
        Small side branches added to the named vessels (default: 3 to 8, drawn;
        the tree holds at most 30 vessels). Bigger trees for benchmarks.
    progress : bool
        Show a progress bar.
    noise_draw : int
        Which draw of the quantum noise (0, the default, as always): the same
        case (anatomy, motion, geometry, contrast, labels, truth) with other
        noise pixels, to measure how much a result owes to the noise
        (``benchmarks/end_to_end.py --noise-draw``).

    Returns
    -------
    PhantomCase
    """
    if anatomy not in ANATOMIES:
        raise ArgumentError(f"anatomy: expected one of {ANATOMIES}, got {anatomy!r}")
    if int(n_frames) < 1:
        raise ArgumentError(f"n_frames: expected >= 1, got {n_frames}")
    if bits not in (8, 12):
        raise ArgumentError(f"bits: expected 8 or 12, got {bits}")
    if not fps > 0:
        raise ArgumentError(f"fps: expected > 0, got {fps}")
    if not 0 <= miscalibration_deg <= 10:
        raise ArgumentError(f"miscalibration_deg: expected 0..10, got {miscalibration_deg}")
    if twigs is not None and (isinstance(twigs, bool) or not (isinstance(twigs, int | np.integer)
                                                            and 0 <= twigs <= 30)):
        raise ArgumentError(f"twigs: expected an integer 0..30 or None, got {twigs!r}")
    if isinstance(noise_draw, bool) or not isinstance(noise_draw, int | np.integer) or noise_draw < 0:
        raise ArgumentError(f"noise_draw: expected an integer >= 0, got {noise_draw!r}")
    rng = np.random.default_rng([int(seed), 0x7E55E1])
    if views is None:
        views = default_views(anatomy, rows, cols)
    view_a, view_b = views
    anat = make_anatomy(rng, anatomy, twigs)
    motion = random_motion(rng)
    hr_a = rng.uniform(55, 100)
    resp_a = rng.uniform(3.5, 5.5)
    ph_a, t_a = _phases(rng, n_frames, fps, hr_a, resp_a, rng.uniform(), rng.uniform())
    if synchronized:
        ph_b, t_b = ph_a.copy(), t_a.copy()
        shift = np.zeros(3)
    else:
        hr_b = hr_a * rng.uniform(0.95, 1.05)
        resp_b = resp_a * rng.uniform(0.9, 1.1)
        ph_b, t_b = _phases(rng, n_frames, fps, hr_b, resp_b, rng.uniform(), rng.uniform())
        direction = rng.normal(size=3)
        shift = table_shift_mm * direction / np.linalg.norm(direction)
    app_a = _random_appearance(rng)
    app_b = _random_appearance(rng) if not synchronized else app_a
    header_a = _perturb(view_a, rng, miscalibration_deg)
    header_b = _perturb(view_b, rng, miscalibration_deg)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=2 * n_frames, desc=f"phantom {anatomy} seed {seed}", unit="frame")
    rng_a = np.random.default_rng([int(seed), 0xA])
    rng_b = np.random.default_rng([int(seed), 0xB])
    # The two runs are independent (own generators): render them on two threads;
    # OpenCV and large numpy operations release the GIL.
    with ThreadPoolExecutor(max_workers=2) as pool:
        fut_a = pool.submit(_render_run, anat, view_a, ph_a, t_a, motion, app_a, rng_a, bits,
                            np.zeros(3), bar, int(noise_draw))
        fut_b = pool.submit(_render_run, anat, view_b, ph_b, t_b, motion, app_b, rng_b, bits,
                            shift, bar, int(noise_draw))
        run_a, run_b = fut_a.result(), fut_b.result()
    if bar is not None:
        bar.close()
    return PhantomCase(int(seed), anatomy, anat, motion, run_a, run_b, header_a, header_b,
                       synchronized, shift)


def render(
    seed: int,
    view: CArmView | None = None,
    *,
    anatomy: str | None = None,
    n_frames: int = 1,
    rows: int = 512,
    cols: int = 512,
    bits: int = 8,
) -> RenderedRun:
    """Render one view of a random phantom in memory (for training data samplers).

    Anatomy, motion phases, contrast timing and appearance are all drawn from
    ``seed``; the frames are spread over the whole run so the opacification
    varies. Returns frames with per-frame labels (values in :data:`LABELS`).
    """
    rng = np.random.default_rng([int(seed), 0x5EED])
    kind = anatomy or str(rng.choice(ANATOMIES))
    if kind not in ANATOMIES:
        raise ArgumentError(f"anatomy: expected one of {ANATOMIES}, got {kind!r}")
    if view is None:
        view = CArmView(primary_deg=rng.uniform(-40, 90), secondary_deg=rng.uniform(-30, 30),
                        sid_mm=rng.uniform(950, 1200), sod_mm=rng.uniform(700, 800),
                        pixel_spacing_mm=(0.4 * 512 / rows, 0.4 * 512 / cols), rows=rows, cols=cols)
    anat = make_anatomy(rng, kind)
    motion = random_motion(rng)
    fps = 15.0
    ph, t = _phases(rng, max(n_frames, 1), fps, rng.uniform(55, 100), rng.uniform(3.5, 5.5),
                    rng.uniform(), rng.uniform())
    if n_frames == 1:  # a single frame anywhere in a 4 s run
        t = np.array([rng.uniform(0.5, 3.5) * 1000.0])
    app = _random_appearance(rng)
    return _render_run(anat, view, ph, t, motion, app, rng, bits, np.zeros(3))


# ------------------------------------------------------------------ output
def _npz_bytes(**arrays: np.ndarray) -> bytes:
    """A compressed .npz with fixed timestamps (byte-identical for identical arrays)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(2026, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def write_case(case: PhantomCase, out_dir: str | os.PathLike, *, preview: bool = False) -> dict[str, Path]:
    """Write ``run_a.dcm``, ``run_b.dcm``, ``truth.json``, ``labels_a.npz``, ``labels_b.npz``.

    With ``preview=True`` also ``preview.png`` (a contact sheet with label
    overlays). Every file is written atomically. Returns the written paths.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    run_a, run_b = case.xa_runs()
    paths = {
        "run_a": save_run(run_a, out / "run_a.dcm"),
        "run_b": save_run(run_b, out / "run_b.dcm"),
    }
    atomic_write_text(out / "truth.json", json.dumps(case.truth(), separators=(",", ":")) + "\n")
    paths["truth"] = out / "truth.json"
    for tag, rr in (("a", case.run_a), ("b", case.run_b)):
        atomic_write_bytes(out / f"labels_{tag}.npz", _npz_bytes(labels=rr.labels))
        paths[f"labels_{tag}"] = out / f"labels_{tag}.npz"
    if preview:
        from .preview import contact_sheet

        paths["preview"] = contact_sheet(case, out / "preview.png")
    return paths
