"""Fixed-interval (Rauch-Tung-Striebel) smoothing of position samples with a constant-acceleration model.

Why: a recorded trajectory (ADS-B) is a quantised, jittered sample of the true path. A truth for
tracking experiments needs position, velocity and acceleration at the scan times, consistent with
each other. The RTS smoother over a white-jerk constant-acceleration model gives exactly that: the
conditional mean of the kinematic state given *all* samples, at any time inside the record,
including times between samples (the scan times are inserted as steps without a measurement).

Each axis is an independent (p, v, a) chain; all axes are smoothed in one pass (batched).
"""

from __future__ import annotations

import numpy as np


def constant_acceleration_transition(dt: np.ndarray) -> np.ndarray:
    """F (..., 3, 3) of (p, v, a) over ``dt`` (...,) seconds."""
    dt = np.asarray(dt, dtype=float)
    F = np.zeros(dt.shape + (3, 3))
    F[..., 0, 0] = F[..., 1, 1] = F[..., 2, 2] = 1.0
    F[..., 0, 1] = F[..., 1, 2] = dt
    F[..., 0, 2] = dt * dt / 2.0
    return F


def white_jerk_process_noise(dt: np.ndarray, jerk_psd: float) -> np.ndarray:
    """Q (..., 3, 3) of (p, v, a) over ``dt`` for a white jerk of power spectral density ``jerk_psd``
    [m^2/s^5] (the continuous Wiener-process-acceleration model, Bar-Shalom et al. 2001, 6.2.3)."""
    dt = np.asarray(dt, dtype=float)[..., None, None]
    powers = np.array([[5, 4, 3], [4, 3, 2], [3, 2, 1]])
    denominators = np.array([[20.0, 8.0, 6.0], [8.0, 3.0, 2.0], [6.0, 2.0, 1.0]])
    return jerk_psd * dt ** powers / denominators


def smooth_constant_acceleration(time: np.ndarray, position: np.ndarray, noise_std: np.ndarray, jerk_psd: float,
                                 initial_std: tuple[float, float, float] = (1e3, 300.0, 50.0)) -> np.ndarray:
    """RTS-smoothed (p, v, a) per axis at every time of ``time`` (``smooth_with_covariance``'s mean)."""
    return smooth_with_covariance(time, position, noise_std, jerk_psd, initial_std, covariance=False)[0]


def smooth_with_covariance(time: np.ndarray, position: np.ndarray, noise_std: np.ndarray, jerk_psd: float,
                           initial_std: tuple[float, float, float] = (1e3, 300.0, 50.0), covariance: bool = True
                           ) -> tuple[np.ndarray, np.ndarray | None]:
    """RTS-smoothed (p, v, a) per axis at every time of ``time``, and its covariance.

    Parameters
    ----------
    time : (N,) non-decreasing [s]
    position : (N, A) position sample per axis [m]; NaN where a step has none on that axis (that is
        how states at scan times between samples are obtained, and how one axis's bad samples are
        left out while the others are used)
    noise_std : (A,) standard deviation of a position sample per axis [m]
    jerk_psd : white-jerk power spectral density [m^2/s^5], the same on every axis
    initial_std : prior std of (p, v, a) around (first sample, 0, 0); wide, so the data decide

    covariance : also the smoothed covariance (None when False)

    Returns
    -------
    (N, A, 3) smoothed (p, v, a) per step and axis; (N, A, 3, 3) its covariance given all samples,
    P_s[k] = P_f[k] + C_k (P_s[k+1] - P_pred[k+1]) C_k' (Rauch, Tung, Striebel 1965): how well the
    samples and the model pin the state down (a truth's own uncertainty; it grows between sparse samples).
    """
    time = np.asarray(time, dtype=float)
    position = np.asarray(position, dtype=float)
    measured = np.isfinite(position)
    variance = np.asarray(noise_std, dtype=float) ** 2
    N, A = position.shape
    if not measured.any(axis=0).all():
        raise ValueError("smooth_constant_acceleration: an axis has no position sample")
    if np.any(np.diff(time) < 0):
        raise ValueError("smooth_constant_acceleration: time must be non-decreasing")
    dt = np.diff(time, prepend=time[0])
    F = constant_acceleration_transition(dt)                     # (N, 3, 3); F[0] = I
    Q = white_jerk_process_noise(dt, jerk_psd)
    x = np.zeros((A, 3))
    x[:, 0] = position[np.argmax(measured, axis=0), np.arange(A)]
    P = np.broadcast_to(np.diag(np.square(initial_std)), (A, 3, 3)).copy()
    x_pred = np.empty((N, A, 3))
    P_pred = np.empty((N, A, 3, 3))
    x_filt = np.empty((N, A, 3))
    P_filt = np.empty((N, A, 3, 3))
    for k in range(N):
        if k:
            x = x @ F[k].T
            P = F[k] @ P @ F[k].T + Q[k]
        x_pred[k], P_pred[k] = x, P
        if measured[k].any():
            on = measured[k]                                                # axes with a sample
            gain = np.where(on[:, None], P[:, :, 0] / (P[:, 0, 0] + variance)[:, None], 0.0)   # (A, 3)
            x = x + gain * np.where(on, position[k] - x[:, 0], 0.0)[:, None]
            P = P - gain[:, :, None] * P[:, None, 0, :]
            P = 0.5 * (P + np.swapaxes(P, -1, -2))
        x_filt[k], P_filt[k] = x, P
    # RTS gains C_k = P_filt[k] F[k+1]' P_pred[k+1]^-1 for all k at once (P_pred symmetric)
    C = np.swapaxes(np.linalg.solve(P_pred[1:], F[1:, None] @ P_filt[:-1]), -1, -2)   # (N-1, A, 3, 3)
    smoothed = np.empty_like(x_filt)
    smoothed[-1] = x_filt[-1]
    for k in range(N - 2, -1, -1):
        smoothed[k] = x_filt[k] + (C[k] @ (smoothed[k + 1] - x_pred[k + 1])[..., None])[..., 0]
    if not covariance:
        return smoothed, None
    P_smooth = np.empty_like(P_filt)
    P_smooth[-1] = P_filt[-1]
    for k in range(N - 2, -1, -1):
        P_smooth[k] = P_filt[k] + C[k] @ (P_smooth[k + 1] - P_pred[k + 1]) @ np.swapaxes(C[k], -1, -2)
    return smoothed, 0.5 * (P_smooth + np.swapaxes(P_smooth, -1, -2))
