"""Radar geometry: polar <-> Cartesian conversion, converted-measurement covariance, and the
line-of-sight (LOS) frame of seed 000 (eqs 11-16, 39-44; literature notes 2.1-2.2).

Angles: azimuth phi from +x toward +y, elevation theta from the x-y plane. Arrays are batched
on leading axes; the last axis holds (range, azimuth, elevation) or (x, y, z).
"""

from __future__ import annotations

import numpy as np
from filters.kalman import einsum


def polar_to_cartesian(polar: np.ndarray) -> np.ndarray:
    """(..., 3) range, azimuth, elevation -> (..., 3) x, y, z: the converted measurement z_I."""
    r, phi, theta = polar[..., 0], polar[..., 1], polar[..., 2]
    c = np.cos(theta)
    return np.stack([r * c * np.cos(phi), r * c * np.sin(phi), r * np.sin(theta)], axis=-1)


def line_of_sight_angles(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., 3) position -> range, azimuth, elevation."""
    horizontal = np.hypot(p[..., 0], p[..., 1])
    return np.linalg.norm(p, axis=-1), np.arctan2(p[..., 1], p[..., 0]), np.arctan2(p[..., 2], horizontal)


def los_rotation(phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """T3(phi, theta) (..., 3, 3): inertial -> LOS frame, rows = LOS, cross-range (azimuth), elevation.

    Seed eq 12 as printed has lost two minus signs and is not orthogonal; this is the orthogonal
    matrix of notes 2.2 (T3 T3' = I, T3 p = (r, 0, 0)).
    """
    cp, sp, ct, st = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
    zero = np.zeros_like(cp)
    return np.stack([
        np.stack([cp * ct, sp * ct, st], axis=-1),
        np.stack([-sp, cp, zero], axis=-1),
        np.stack([-cp * st, -sp * st, ct], axis=-1),
    ], axis=-2)


def los_noise_variances(range_: np.ndarray, theta: np.ndarray, polar_variances: np.ndarray) -> np.ndarray:
    """Diagonal of R^k (eq 15): (sigma_r^2, r^2 cos^2(theta) sigma_phi^2, r^2 sigma_theta^2), (..., 3)."""
    s_r, s_phi, s_theta = polar_variances[..., 0], polar_variances[..., 1], polar_variances[..., 2]
    return np.stack([np.broadcast_to(s_r, range_.shape), (range_ * np.cos(theta))**2 * s_phi,
                     range_**2 * s_theta], axis=-1)


def converted_covariance(polar: np.ndarray, polar_variances: np.ndarray) -> np.ndarray:
    """R_I = J R_p J' (..., 3, 3) at the given (range, azimuth, elevation) (notes 2.1).

    Uses J = T3' diag(1, r cos theta, r), so R_I = T3' diag(R^k) T3.
    """
    r, phi, theta = polar[..., 0], polar[..., 1], polar[..., 2]
    T = los_rotation(phi, theta)
    d = los_noise_variances(r, theta, polar_variances)
    return einsum("...ca,...c,...cb->...ab", T, d, T)
