"""Compiled (numba) Kalman filter loops: ``kalman_cartesian`` is ``filters.tracker.KalmanTracker``'s
scan loop on Cartesian positions (positions, or radar measurements converted), engine ``numba``;
``inverse_and_logdet`` the small innovation-covariance inverse the compiled loops share.

``kalman_cartesian``, per run and scan k >= 2 (Bar-Shalom, Li & Kirubarajan 2001, 5.2.3):
x' = F x, P' = F (P F') + Q (``kalman.predict``, not symmetrised); on a detection, with H picking
each axis's position, S = H P' H' + R_k, K = P' H' S^-1, x = x' + K nu, P = sym(P' - K H P') and
the NIS nu' S^-1 nu; a missed scan keeps the prediction (NIS NaN).

numpy filtered all runs at once, one batched LAPACK solve of S per scan (0.48 ms for 100 runs of
3 x 3: the call, not the arithmetic) and ~15 broadcast passes: 0.7-0.8 s of each Kalman variant
of a 100-run, 901-scan ADS-B job (2026-12-03). What differs here, at rounding level: S inverted
by its Cholesky factor in closed form (numpy: LU), products as sums in index order (numpy: BLAS).
tests/test_tracker_kernel.py holds the engines together for every motion model and both
measurement kinds.

Each run is computed on its own in a fixed order: a run's numbers do not depend on the other runs
of the batch. Compiled with ``cache=True``, without fastmath.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)


@njit(forceinline=True, **_JIT)
def inverse_and_logdet(S, d, S_inv):
    """S_inv and log det S of the (d, d) innovation covariance, d = 2 or 3: 2 x 2 in closed form as
    ``kalman.inverse_2x2``; 3 x 3 by its Cholesky factor L, S^-1 = L^-T L^-1 (``kalman.inverse_and_logdet``).
    A matrix that is not positive definite gives NaN (numpy raised LinAlgError there)."""
    if d == 2:
        det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
        S_inv[0, 0] = S[1, 1] / det
        S_inv[0, 1] = -S[0, 1] / det
        S_inv[1, 0] = -S[1, 0] / det
        S_inv[1, 1] = S[0, 0] / det
        return math.log(det) if det > 0 else math.nan
    l00 = math.sqrt(S[0, 0]) if S[0, 0] > 0 else math.nan
    l10 = S[1, 0] / l00
    l20 = S[2, 0] / l00
    r11 = S[1, 1] - l10 * l10
    l11 = math.sqrt(r11) if r11 > 0 else math.nan
    l21 = (S[2, 1] - l20 * l10) / l11
    r22 = S[2, 2] - l20 * l20 - l21 * l21
    l22 = math.sqrt(r22) if r22 > 0 else math.nan
    i00 = 1.0 / l00                                     # L^-1, lower triangular
    i11 = 1.0 / l11
    i22 = 1.0 / l22
    i10 = -l10 * i00 / l11
    i21 = -l21 * i11 / l22
    i20 = -(l20 * i00 + l21 * i10) / l22
    S_inv[0, 0] = i00 * i00 + i10 * i10 + i20 * i20     # (L^-1)' L^-1
    S_inv[0, 1] = i10 * i11 + i20 * i21
    S_inv[0, 2] = i20 * i22
    S_inv[1, 1] = i11 * i11 + i21 * i21
    S_inv[1, 2] = i21 * i22
    S_inv[2, 2] = i22 * i22
    S_inv[1, 0] = S_inv[0, 1]
    S_inv[2, 0] = S_inv[0, 2]
    S_inv[2, 1] = S_inv[1, 2]
    return 2.0 * (math.log(l00) + math.log(l11) + math.log(l22))



@njit(forceinline=True, **_JIT)
def quadratic_form(S_inv, nu):
    """nu' S^-1 nu, the sums in index order."""
    total = 0.0
    for p in range(nu.shape[0]):
        s = 0.0
        for q in range(nu.shape[0]):
            s += S_inv[p, q] * nu[q]
        total += nu[p] * s
    return total


@njit(forceinline=True, **_JIT)
def update_positions(x, P, z, noise, stride, S, S_inv, gain, nu, tmp):
    """The Kalman update of (x, P) in place on a measurement z (d,) of the positions, state index
    p * ``stride`` for axis p (H picks them), noise (d, d): nu = z - H x, S = H P H' + R,
    K = P H' S^-1, x += K nu, P = sym(P - K (P H')') (``kalman.update``). Returns
    (nu' S^-1 nu, log det S); S, S_inv, gain (n, d), nu (d,) and tmp (n, n) are work arrays."""
    n = x.shape[0]
    d = z.shape[0]
    for p in range(d):
        nu[p] = z[p] - x[stride * p]
        for q in range(d):
            S[p, q] = P[stride * p, stride * q] + noise[p, q]
    logdet = inverse_and_logdet(S, d, S_inv)
    for a in range(n):                                  # K = P H' S^-1
        for q in range(d):
            s = 0.0
            for p in range(d):
                s += P[a, stride * p] * S_inv[p, q]
            gain[a, q] = s
    mahalanobis = quadratic_form(S_inv, nu)
    for a in range(n):
        s = 0.0
        for q in range(d):
            s += gain[a, q] * nu[q]
        x[a] += s
    for a in range(n):                                  # P - K (P H')'
        for b in range(n):
            s = 0.0
            for q in range(d):
                s += gain[a, q] * P[b, stride * q]
            tmp[a, b] = P[a, b] - s
    for a in range(n):
        P[a, a] = tmp[a, a]
        for b in range(a + 1, n):
            v = 0.5 * (tmp[a, b] + tmp[b, a])
            P[a, b] = v
            P[b, a] = v
    return mahalanobis, logdet


@njit(**_JIT)
def kalman_cartesian(first, stop, z, noise, detected, F, Q, kinematics, x_start, P_start,
                     out_state, out_covariance, out_nis):
    """Scans 2..K-1 of runs first..stop-1. z (R, K, d) positions (NaN where missed), noise
    (R, K, d, d), detected (R, K); F, Q (n, n) over the axis-major state ((p, v[, a]) per axis,
    ``kinematics`` components each, so axis p's position is state index p * kinematics); the state
    at scan 1: x_start (R, n), P_start (R, n, n). Writes scans 2.. of out_state (R, K, n),
    out_covariance (R, K, n, n) and out_nis (R, K)."""
    K = z.shape[1]
    d = z.shape[2]
    n = x_start.shape[1]
    x = np.empty(n)
    x_pred = np.empty(n)
    P = np.empty((n, n))
    tmp = np.empty((n, n))
    S = np.empty((d, d))
    S_inv = np.empty((d, d))
    gain = np.empty((n, d))
    nu = np.empty(d)
    for r in range(first, stop):
        for a in range(n):
            x[a] = x_start[r, a]
            for b in range(n):
                P[a, b] = P_start[r, a, b]
        for k in range(2, K):
            for a in range(n):                          # x' = F x
                s = 0.0
                for b in range(n):
                    s += F[a, b] * x[b]
                x_pred[a] = s
            for a in range(n):                          # P F'
                for b in range(n):
                    s = 0.0
                    for c in range(n):
                        s += P[a, c] * F[b, c]
                    tmp[a, b] = s
            for a in range(n):                          # F (P F') + Q
                x[a] = x_pred[a]
                for b in range(n):
                    s = 0.0
                    for c in range(n):
                        s += F[a, c] * tmp[c, b]
                    P[a, b] = s + Q[a, b]
            if detected[r, k]:
                nis, _ = update_positions(x, P, z[r, k], noise[r, k], kinematics, S, S_inv, gain, nu, tmp)
                out_nis[r, k] = nis
            else:
                out_nis[r, k] = math.nan
            for a in range(n):
                out_state[r, k, a] = x[a]
                for b in range(n):
                    out_covariance[r, k, a, b] = P[a, b]


_warm = False


def warm_up() -> None:
    """Load (or compile, the first time on a machine) the loop on one run of three scans, before a
    filter's clock starts (the job's compute-seconds column compares the variants)."""
    global _warm
    if _warm:
        return
    R, K, d, n = 1, 3, 2, 4
    kalman_cartesian(0, R, np.zeros((R, K, d)), np.broadcast_to(np.eye(d), (R, K, d, d)).copy(),
                     np.ones((R, K), np.bool_), np.eye(n), np.eye(n), 2, np.zeros((R, n)),
                     np.broadcast_to(np.eye(n), (R, n, n)).copy(), np.zeros((R, K, n)), np.zeros((R, K, n, n)),
                     np.zeros((R, K)))
    _warm = True
