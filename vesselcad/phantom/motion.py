"""Cardiac and respiratory motion of the phantom.

Cardiac phase 0 is end-diastole (R-wave); the heart contracts radially toward
its long axis, shortens with the base (the atrioventricular plane) descending
toward the nearly still apex, and twists about the long axis (apex more than
base) during systole (about the first 35 % of the cycle),
relaxes until 60 %, and rests in diastasis. Respiratory phase 0 is
end-expiration; inspiration moves the heart caudally (and slightly
anteriorly) by the respiratory amplitude. Displacements are vectorised over
points; the cardiac part fades out away from the heart so devices in the
great vessels move mostly with respiration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .anatomy import Heart

__all__ = ["MotionParams", "contraction", "respiration", "deform", "random_motion"]


@dataclass(frozen=True)
class MotionParams:
    """Amplitudes of the phantom motion (per case)."""

    radial: float = 0.11  # fractional radial contraction at peak systole
    longitudinal: float = 0.08  # fractional base-apex shortening
    twist_deg: float = 7.0  # apex rotation at peak systole
    resp_mm: float = 15.0  # cranio-caudal amplitude end-expiration -> end-inspiration


def random_motion(rng: np.random.Generator) -> MotionParams:
    """Motion amplitudes drawn from physiological ranges."""
    return MotionParams(
        radial=rng.uniform(0.08, 0.14),
        longitudinal=rng.uniform(0.06, 0.10),
        twist_deg=rng.uniform(4.0, 10.0),
        resp_mm=rng.uniform(10.0, 20.0),
    )


def contraction(phase: np.ndarray) -> np.ndarray:
    """Systolic contraction in [0, 1] for cardiac phase in [0, 1) (C1 smooth)."""
    ph = np.mod(phase, 1.0)
    up = 0.5 * (1 - np.cos(np.pi * ph / 0.35))
    down = 0.5 * (1 + np.cos(np.pi * (ph - 0.35) / 0.25))
    return np.where(ph < 0.35, up, np.where(ph < 0.6, down, 0.0))


def respiration(phase: np.ndarray) -> np.ndarray:
    """Inspiration level in [0, 1] for respiratory phase in [0, 1); 0 at end-expiration."""
    return np.sin(np.pi * np.mod(phase, 1.0)) ** 2


def resp_shift(phase: float, params: MotionParams) -> np.ndarray:
    """Rigid respiratory displacement (LPS mm) at a respiratory phase."""
    r = float(respiration(np.asarray(phase)))
    return params.resp_mm * r * np.array([0.0, -0.15, -1.0])


def deform(points: np.ndarray, heart: Heart, cardiac_phase: float, resp_phase: float,
           params: MotionParams) -> np.ndarray:
    """Positions at the given phases of rest positions ``points`` (shape (..., 3))."""
    c = float(contraction(np.asarray(cardiac_phase)))
    rel = points - heart.centre
    along = rel @ heart.e1
    radial = rel - along[..., None] * heart.e1
    # Twist about the long axis, growing from base (along=-a) to apex (along=+a).
    theta = np.radians(params.twist_deg) * c * np.clip((along + heart.a) / (2 * heart.a), 0, 1.2)
    cos_t, sin_t = np.cos(theta)[..., None], np.sin(theta)[..., None]
    radial_rot = radial * cos_t + np.cross(heart.e1, radial) * sin_t
    radial_new = (1.0 - params.radial * c) * radial_rot
    # The apex stays nearly still; the base (AV plane) descends toward it (10-15 mm).
    along_new = heart.a - (heart.a - along) * (1.0 - params.longitudinal * c)
    moved = heart.centre + along_new[..., None] * heart.e1 + radial_new
    # Fade the cardiac displacement out beyond the heart (normalised radius 1.3 -> 2.5).
    q = heart.to_local(points)
    rho = np.linalg.norm(q, axis=-1)
    w = np.clip((2.5 - rho) / 1.2, 0.0, 1.0)[..., None]
    w = w * w * (3 - 2 * w)
    return points + w * (moved - points) + resp_shift(resp_phase, params)
