"""The compiled scan loop of filter A (``filters.input_estimation.InertialMIE``, seed 000): the
coupled 9-state Kalman filter on converted measurements and its modified input estimation, one run
at a time, each run's scans in one loop.

``inertial_mie`` is ``InertialMIE.run``'s loop written out in scalars: per scan the prediction with
the input level (eqs 3-4 with G u), the update on the converted position (R_I at the measured
values), the state's sensitivity to a level error; once armed, every onset hypothesis n of the data
window (innovations up to n, pseudo-residuals after, eqs 24-33 in 3 x 3 matrices), the pick of n_hat
(eq 29), the test (eq 31, the per-axis sum or the full quadratic form, with the old level's
covariance carried through G = I + A^-1 W T J_v), the quiet window's soft update and the
compensation of state, covariance, level and sensitivity (eqs 34-38, M by the exact recursion).
The numpy loop (``engine="numpy"``) stays as the reference. What differs, at rounding level: the
3 x 3 inverses in closed form (numpy: LAPACK's LU), products over the block-diagonal F9, G9 and H
without their zero blocks, sums in index order. A detection whose statistic falls within rounding of
the threshold could flip; tests/test_mie_kernel.py holds the engines to ~1e-9 on study 000's
scenario and an ADS-B flight, with the same detections.

Each run is computed on its own, in a fixed order: a run's numbers do not depend on the other runs
of the batch (mc.chunk_runs stays bit-identical). Compiled with ``cache=True``, without fastmath.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)


@njit(forceinline=True, **_JIT)
def _inverse3(M, out):
    """The inverse of a 3 x 3 matrix by its adjugate (NaN where singular: inf / NaN propagate)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]) / det
    out[1, 1] = (M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]) / det
    out[2, 1] = (M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]) / det
    out[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) / det
    out[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) / det
    out[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) / det


@njit(forceinline=True, **_JIT)
def _mul3(A, B, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(forceinline=True, **_JIT)
def _mul3t(A, B, out):
    """A B' for 3 x 3 matrices."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[j, 0] + A[i, 1] * B[j, 1] + A[i, 2] * B[j, 2]


@njit(forceinline=True, **_JIT)
def _quad3(v, M, w):
    """v' M w."""
    total = 0.0
    for i in range(3):
        total += v[i] * (M[i, 0] * w[0] + M[i, 1] * w[1] + M[i, 2] * w[2])
    return total


@njit(forceinline=True, **_JIT)
def _response(F, G, M, Y):
    """Y = F9 M + G9 for a (9, 3) M: each axis block's kinematic rows moved by F, plus G on its own
    input column."""
    for a in range(3):
        for i in range(3):
            for j in range(3):
                value = F[i, 0] * M[3 * a, j] + F[i, 1] * M[3 * a + 1, j] + F[i, 2] * M[3 * a + 2, j]
                Y[3 * a + i, j] = value + (G[i] if j == a else 0.0)


@njit(**_JIT)
def inertial_mie(first_run, stop_run, zI, RI, F, Q, G, dt, sigma_m, span, min_samples, rearm_after, threshold,
                 full_test, level_uncertainty, compensate, level_correlation,
                 out_x, out_P, level_out, detected_out, stat_out, onset_out, nis_out):
    """Runs first_run..stop_run-1 through every scan. zI (R, K, 3) converted positions, RI (R, K, 3, 3)
    their covariances; F, Q (3, 3), G (3,) one axis's Singer model; outputs as InertialMIE.run
    fills them (state and covariance in kinematic-major order)."""
    K = zI.shape[1]
    x = np.zeros(9)
    P = np.zeros((9, 9))
    T1 = np.zeros((9, 9))
    u = np.zeros(3)
    level_cov = np.zeros((3, 3))
    sens = np.zeros((9, 3))
    Y = np.zeros((9, 3))
    S = np.zeros((3, 3))
    S_inv = np.zeros((3, 3))
    gain = np.zeros((9, 3))
    gainS = np.zeros((9, 3))
    nu = np.zeros(3)
    x_hist = np.zeros((K, 9))
    pvv_hist = np.zeros((K, 3, 3))
    nu_hist = np.zeros((K, 3))
    sinv_hist = np.zeros((K, 3, 3))
    gain_hist = np.zeros((K, 9, 3))
    sens_v_hist = np.zeros((K, 3, 3))
    H_max = span - min_samples + 1
    scores = np.zeros(H_max)
    inputs = np.zeros((H_max, 3))
    covs = np.zeros((H_max, 3, 3))
    old_covs = np.zeros((H_max, 3, 3))
    gains = np.zeros((H_max, 3, 3))
    onsets = np.zeros(H_max, dtype=np.int64)
    D = span
    weighted = np.zeros((D, 3, 3))
    weighted_r = np.zeros((D, 3, 3))
    A = np.zeros((3, 3))
    A_inv = np.zeros((3, 3))
    W = np.zeros((3, 3))
    b = np.zeros(3)
    e = np.zeros(3)
    v_n = np.zeros(3)
    tpvv = np.zeros((3, 3))
    Sw = np.zeros((3, 3))
    Si = np.zeros((3, 3))
    m1 = np.zeros((3, 3))
    m2 = np.zeros((3, 3))
    m3 = np.zeros((3, 3))
    cross = np.zeros((3, 3))
    u_hat = np.zeros(3)
    delta = np.zeros(3)
    V = np.zeros((3, 3))
    V_inv = np.zeros((3, 3))
    M = np.zeros((9, 3))
    Mc = np.zeros((9, 3))
    for r in range(first_run, stop_run):
        # ---- k = 1: two-point start, P's blocks from R_I (axis-major state: a * 3 + kinematic)
        for s in range(9):
            x[s] = 0.0
            for t in range(9):
                P[s, t] = 0.0
            for j in range(3):
                sens[s, j] = 0.0
        for a in range(3):
            x[3 * a] = zI[r, 1, a]
            x[3 * a + 1] = (zI[r, 1, a] - zI[r, 0, a]) / dt
            u[a] = 0.0
            for c in range(3):
                level_cov[a, c] = 0.0
                P[3 * a, 3 * c] = RI[r, 1, a, c]
                P[3 * a, 3 * c + 1] = RI[r, 1, a, c] / dt
                P[3 * a + 1, 3 * c] = RI[r, 1, a, c] / dt
                P[3 * a + 1, 3 * c + 1] = (RI[r, 1, a, c] + RI[r, 0, a, c]) / dt**2
        for a in range(3):
            P[3 * a + 2, 3 * a + 2] = sigma_m**2
        k_c = 1
        x_hist[1] = x
        for a in range(3):
            for c in range(3):
                sens_v_hist[1, a, c] = 0.0          # no response before the first update
        for a in range(3):
            for c in range(3):
                pvv_hist[1, a, c] = P[3 * a + 1, 3 * c + 1]
        _store(r, 1, x, P, u, out_x, out_P, level_out)
        for k in range(2, K):
            # eqs 3-4 with the level: x = F9 x + G9 u, P = (F9 P) F9' + Q9
            for a in range(3):
                x0, x1, x2 = x[3 * a], x[3 * a + 1], x[3 * a + 2]
                for i in range(3):
                    x[3 * a + i] = F[i, 0] * x0 + F[i, 1] * x1 + F[i, 2] * x2 + G[i] * u[a]
            for a in range(3):
                for i in range(3):
                    for t in range(9):
                        T1[3 * a + i, t] = (F[i, 0] * P[3 * a, t] + F[i, 1] * P[3 * a + 1, t]
                                            + F[i, 2] * P[3 * a + 2, t])
            for s in range(9):
                for c in range(3):
                    for j in range(3):
                        value = F[j, 0] * T1[s, 3 * c] + F[j, 1] * T1[s, 3 * c + 1] + F[j, 2] * T1[s, 3 * c + 2]
                        P[s, 3 * c + j] = value + (Q[s % 3, j] if s // 3 == c else 0.0)
            # the update on the converted position
            for a in range(3):
                for c in range(3):
                    S[a, c] = P[3 * a, 3 * c] + RI[r, k, a, c]
            _inverse3(S, S_inv)
            for s in range(9):
                for j in range(3):
                    gain[s, j] = P[s, 0] * S_inv[0, j] + P[s, 3] * S_inv[1, j] + P[s, 6] * S_inv[2, j]
            for a in range(3):
                nu[a] = zI[r, k, a] - x[3 * a]
            for s in range(9):
                x[s] = x[s] + (gain[s, 0] * nu[0] + gain[s, 1] * nu[1] + gain[s, 2] * nu[2])
            for s in range(9):
                for j in range(3):
                    gainS[s, j] = gain[s, 0] * S[0, j] + gain[s, 1] * S[1, j] + gain[s, 2] * S[2, j]
            for s in range(9):
                for t in range(9):
                    P[s, t] = P[s, t] - (gainS[s, 0] * gain[t, 0] + gainS[s, 1] * gain[t, 1] + gainS[s, 2] * gain[t, 2])
            for s in range(9):
                for t in range(s + 1, 9):
                    value = 0.5 * (P[s, t] + P[t, s])
                    P[s, t] = value
                    P[t, s] = value
            # the filter's response to a level error: sens = Y - K (H Y), Y = F9 sens + G9
            _response(F, G, sens, Y)
            for s in range(9):
                for j in range(3):
                    sens[s, j] = Y[s, j] - (gain[s, 0] * Y[0, j] + gain[s, 1] * Y[3, j] + gain[s, 2] * Y[6, j])
            nis_out[r, k] = _quad3(nu, S_inv, nu)
            _remember(k, x, P, nu, S_inv, gain, sens, x_hist, pvv_hist, nu_hist, sinv_hist, gain_hist, sens_v_hist)
            # ---- the MIE once armed, over the onset hypotheses d = span .. min_samples with k - d >= 1
            H = 0
            for d in range(span, min_samples - 1, -1):
                if k - d >= 1:
                    onsets[H] = k - d
                    H += 1
            if H == 0 or (k - k_c) < rearm_after:
                _store(r, k, x, P, u, out_x, out_P, level_out)
                continue
            first = k - span + 1
            for h in range(H):
                n = onsets[h]
                innov = 0.0
                for i in range(max(first, 2), n + 1):
                    innov += _quad3(nu_hist[i], sinv_hist[i], nu_hist[i])
                for a in range(3):
                    v_n[a] = x_hist[n, 3 * a + 1]
                    for c in range(3):
                        tpvv[a, c] = dt * dt * pvv_hist[n, a, c]
                        A[a, c] = 0.0
                        W[a, c] = 0.0
                    b[a] = 0.0
                quad = 0.0
                m = 0
                for i in range(n + 1, k + 1):
                    for a in range(3):
                        e[a] = zI[r, i, a] - zI[r, i - 1, a] - dt * v_n[a]
                        for c in range(3):
                            Sw[a, c] = tpvv[a, c] + RI[r, i, a, c] + RI[r, i - 1, a, c]
                    _inverse3(Sw, Si)
                    N_i = (i - n - 0.5) * dt * dt
                    for a in range(3):
                        b[a] += N_i * (Si[a, 0] * e[0] + Si[a, 1] * e[1] + Si[a, 2] * e[2])
                        for c in range(3):
                            A[a, c] += N_i * N_i * Si[a, c]
                            W[a, c] += N_i * Si[a, c]
                            weighted[m, a, c] = N_i * Si[a, c]
                            weighted_r[m, a, c] = RI[r, i, a, c]
                    quad += _quad3(e, Si, e)
                    m += 1
                _inverse3(A, A_inv)
                if level_correlation:             # gain_eps = I + A^-1 W (T J_v(n))
                    _mul3(A_inv, W, m1)
                    for a in range(3):
                        for c in range(3):
                            m2[a, c] = dt * sens_v_hist[n, a, c]
                    _mul3(m1, m2, m3)
                    for a in range(3):
                        for c in range(3):
                            gains[h, a, c] = (1.0 if a == c else 0.0) + m3[a, c]
                    _mul3(gains[h], level_cov, m1)
                    _mul3t(m1, gains[h], old_covs[h])
                else:
                    for a in range(3):
                        for c in range(3):
                            gains[h, a, c] = 1.0 if a == c else 0.0
                            old_covs[h, a, c] = level_cov[a, c]
                for a in range(3):
                    u_hat[a] = A_inv[a, 0] * b[0] + A_inv[a, 1] * b[1] + A_inv[a, 2] * b[2]
                    inputs[h, a] = u_hat[a]
                L = -0.5 * innov - 0.5 * quad + 0.5 * _quad3(u_hat, A, u_hat)
                for a in range(3):
                    for c in range(3):
                        cross[a, c] = 0.0
                for ai in range(m):
                    for aj in range(ai + 1, m):
                        for a in range(3):
                            for c in range(3):
                                m1[a, c] = tpvv[a, c] - (weighted_r[ai, a, c] if aj == ai + 1 else 0.0)
                        _mul3(weighted[ai], m1, m2)
                        _mul3(m2, weighted[aj], m3)
                        for a in range(3):
                            for c in range(3):
                                cross[a, c] += m3[a, c] + m3[c, a]
                scores[h] = L if n >= k_c else -np.inf
                _mul3(A_inv, cross, m1)
                _mul3(m1, A_inv, m2)
                for a in range(3):
                    for c in range(3):
                        covs[h, a, c] = A_inv[a, c] + m2[a, c]
            best = 0
            for h in range(1, H):
                if scores[h] > scores[best]:
                    best = h
            ok = math.isfinite(scores[best])
            for a in range(3):
                delta[a] = inputs[best, a] - u[a]
                for c in range(3):
                    V[a, c] = covs[best, a, c] + (old_covs[best, a, c] if level_uncertainty else 0.0)
            if full_test:
                _inverse3(V, V_inv)
                stat = _quad3(delta, V_inv, delta)
            else:
                stat = 0.0
                for a in range(3):
                    stat += delta[a] * delta[a] / V[a, a]
            det = ok and stat > threshold
            stat_out[r, k] = stat if ok else np.nan
            detected_out[r, k] = 1 if det else 0
            onset_out[r, k] = onsets[best] if det else -1
            Gb = gains[best]
            sigma_u = covs[best]
            if compensate and level_uncertainty and level_correlation and ok and not det \
                    and (k - k_c) % rearm_after == 0:
                # the quiet test's MMSE estimate of the old level's error eps from Delta = xi - G eps
                _mul3t(level_cov, Gb, m1)                                  # SG = Sigma_old G'
                _mul3(Gb, m1, m2)
                for a in range(3):
                    for c in range(3):
                        m2[a, c] = sigma_u[a, c] + m2[a, c]
                _inverse3(m2, m3)
                _mul3(m1, m3, m2)                                           # gain = SG (sigma_u + G SG)^-1
                for a in range(3):
                    e[a] = -(m2[a, 0] * delta[0] + m2[a, 1] * delta[1] + m2[a, 2] * delta[2])   # eps
                for a in range(3):
                    u[a] = u[a] - e[a]
                for s in range(9):
                    x[s] = x[s] - (sens[s, 0] * e[0] + sens[s, 1] * e[1] + sens[s, 2] * e[2])
                _mul3t(m2, m1, m3)
                for a in range(3):
                    for c in range(3):
                        level_cov[a, c] = level_cov[a, c] - m3[a, c]
            if compensate and det:
                # M_n(k) by the recursion from B (eqs 34-37), in this run
                n = onsets[best]
                for s in range(9):
                    for j in range(3):
                        M[s, j] = 1.0 if s == 3 * j + 2 else 0.0
                for i in range(n + 1, k + 1):
                    _response(F, G, M, Y)
                    for s in range(9):
                        for j in range(3):
                            M[s, j] = Y[s, j] - (gain_hist[i, s, 0] * Y[0, j] + gain_hist[i, s, 1] * Y[3, j]
                                                 + gain_hist[i, s, 2] * Y[6, j])
                for s in range(9):
                    x[s] = x[s] + (M[s, 0] * delta[0] + M[s, 1] * delta[1] + M[s, 2] * delta[2])
                for s in range(9):
                    for j in range(3):
                        Mc[s, j] = M[s, 0] * sigma_u[0, j] + M[s, 1] * sigma_u[1, j] + M[s, 2] * sigma_u[2, j]
                for s in range(9):
                    for t in range(9):
                        P[s, t] = P[s, t] + (Mc[s, 0] * M[t, 0] + Mc[s, 1] * M[t, 1] + Mc[s, 2] * M[t, 2])
                for a in range(3):
                    u[a] = u[a] + delta[a]
                # the new level's covariance keeps (G - I) Sigma_old (G - I)' when carried
                if level_uncertainty and level_correlation:
                    for a in range(3):
                        for c in range(3):
                            m1[a, c] = Gb[a, c] - (1.0 if a == c else 0.0)
                    _mul3(m1, level_cov, m2)
                    _mul3t(m2, m1, m3)
                    for a in range(3):
                        for c in range(3):
                            level_cov[a, c] = sigma_u[a, c] + m3[a, c]
                else:
                    for a in range(3):
                        for c in range(3):
                            level_cov[a, c] = sigma_u[a, c]
                for s in range(9):
                    for j in range(3):
                        sens[s, j] = M[s, j]
                k_c = k
            x_hist[k] = x
            for a in range(3):
                for c in range(3):
                    pvv_hist[k, a, c] = P[3 * a + 1, 3 * c + 1]
                    sens_v_hist[k, a, c] = sens[3 * a + 1, c]
            _store(r, k, x, P, u, out_x, out_P, level_out)


@njit(forceinline=True, **_JIT)
def _remember(k, x, P, nu, S_inv, gain, sens, x_hist, pvv_hist, nu_hist, sinv_hist, gain_hist, sens_v_hist):
    for s in range(9):
        x_hist[k, s] = x[s]
        for j in range(3):
            gain_hist[k, s, j] = gain[s, j]
    for a in range(3):
        nu_hist[k, a] = nu[a]
        for c in range(3):
            pvv_hist[k, a, c] = P[3 * a + 1, 3 * c + 1]
            sinv_hist[k, a, c] = S_inv[a, c]
            sens_v_hist[k, a, c] = sens[3 * a + 1, c]


@njit(forceinline=True, **_JIT)
def _store(r, k, x, P, u, out_x, out_P, level_out):
    """The inertial outputs in kinematic-major order (x, y, z, vx, ..., az): out index kin * 3 + axis."""
    for kin in range(3):
        for a in range(3):
            out_x[r, k, 3 * kin + a] = x[3 * a + kin]
            for kin2 in range(3):
                for c in range(3):
                    out_P[r, k, 3 * kin + a, 3 * kin2 + c] = P[3 * a + kin, 3 * c + kin2]
    for a in range(3):
        level_out[r, k, a] = u[a]


_warm = False


def warm_up() -> None:
    """Load (or compile, the first time on a machine) ``inertial_mie`` for the argument types
    ``InertialMIE`` passes, on one run of three scans, before the filter's clock starts."""
    global _warm
    if _warm:
        return
    R, K = 1, 3
    zI = np.zeros((R, K, 3)) + 1000.0
    RI = np.broadcast_to(np.eye(3), (R, K, 3, 3)).copy()
    F, Q, G = np.eye(3), np.eye(3), np.ones(3)
    inertial_mie(0, R, zI, RI, F, Q, G, 1.0, 1.0, 3, 1, 3, 16.0, False, True, True, True,
                 np.zeros((R, K, 9)), np.zeros((R, K, 9, 9)), np.zeros((R, K, 3)), np.zeros((R, K), np.int8),
                 np.zeros((R, K)), np.zeros((R, K), np.int64), np.zeros((R, K)))
    _warm = True
