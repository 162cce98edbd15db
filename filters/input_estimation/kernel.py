"""The compiled scan loops of study 000's filters (``filters.input_estimation``, seed 000): one run
at a time, each run's scans in one loop.

- ``inertial_mie`` is ``InertialMIE.run`` (filters A and A-full): per scan the prediction with the
  input level (eqs 3-4 with G u), the update on the converted position (R_I at the measured values),
  the state's sensitivity to a level error; once armed, every onset hypothesis n of the data window
  (innovations up to n, pseudo-residuals after, eqs 24-33 in 3 x 3 matrices), the pick of n_hat
  (eq 29), the test (eq 31: the per-axis sum or the full quadratic form, with the old level's
  covariance carried through G = I + A^-1 W T J_v), the quiet window's soft update and the
  compensation of state, covariance, level and sensitivity (eqs 34-38, M by the exact recursion).
- ``los_mie`` is ``LOSMIE.run`` (filters B and C) with the paper's diagonal pseudo-residual
  covariance: the three per-axis filters in the LOS frame re-pointed at the prediction every scan
  (eqs 3-16), the per-axis MIE in scalars (eqs 23-33), B's pooled or C's per-axis test, the soft
  update, the compensation with M through the frames (notes 2.4 H) and the frame re-pointed at the
  compensated position (eqs 39-44). ``pseudo_residual_covariance: full`` (the GLS variant) has no
  compiled loop: LOSMIE runs its numpy scans for it.

The numpy loops (``engine="numpy"``) stay as the reference. What differs, at rounding level: 3 x 3
inverses in closed form (numpy: LAPACK's LU), products over block-diagonal matrices without their
zero blocks, sums in index order. A detection whose statistic falls within rounding of its threshold
could flip; tests/test_mie_kernel.py holds the engines to ~1e-13 of each column's RMS on study 000's
scenario (~1e-11 after 901 scans of an ADS-B flight) with the same detections and onsets, for every
test and MIE switch. ADS-B jet, 100 runs x 901 scans: A 5.3 s -> 0.30 s, B 3.9 -> 0.19 s, C 4.4 ->
0.20 s (benchmarks/bench_study000.py for study 000's own scenario).

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
    """Load (or compile, the first time on a machine) both loops for the argument types the filters
    pass, on one run of three scans, before a filter's clock starts (the job's compute-seconds
    column compares the variants; the first one would otherwise carry numba's start)."""
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
    los_mie(0, R, zI, np.ones(3), F, Q, G, 1.0, 1.0, 3, 1, 3, 16.0, False, True, True, True,
            np.zeros((R, K, 9)), np.zeros((R, K, 9, 9)), np.zeros((R, K, 3)), np.zeros((R, K), np.int8),
            np.zeros((R, K, 3), np.int8), np.zeros((R, K)), np.zeros((R, K), np.int64), np.zeros((R, K)))
    _warm = True


# ---- filters B and C: the decoupled LOS filter (LOSMIE), diagonal pseudo-residual covariance ------

@njit(forceinline=True, **_JIT)
def _los_frame(p0, p1, p2, T):
    """T3(phi, theta) of the position (p0, p1, p2) (filters.coordinates.los_rotation of
    line_of_sight_angles); returns the range and the elevation."""
    horizontal = math.hypot(p0, p1)
    rng = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    phi = math.atan2(p1, p0)
    theta = math.atan2(p2, horizontal)
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    T[0, 0], T[0, 1], T[0, 2] = cp * ct, sp * ct, st
    T[1, 0], T[1, 1], T[1, 2] = -sp, cp, 0.0
    T[2, 0], T[2, 1], T[2, 2] = -cp * st, -sp * st, ct
    return rng, theta


@njit(forceinline=True, **_JIT)
def _rotate_rows(R3, x, tmp):
    """x (3, m) <- R3 x."""
    for c in range(x.shape[1]):
        for a in range(3):
            tmp[a] = R3[a, 0] * x[0, c] + R3[a, 1] * x[1, c] + R3[a, 2] * x[2, c]
        for a in range(3):
            x[a, c] = tmp[a]


@njit(forceinline=True, **_JIT)
def _los_store(r, k, T, x, P, u, out_x, out_P, level_out):
    """LOS frame -> inertial, kinematic-major: x_I = T' x, P_I = T9' blkdiag(P_a) T9."""
    for kin in range(3):
        for b in range(3):
            out_x[r, k, 3 * kin + b] = T[0, b] * x[0, kin] + T[1, b] * x[1, kin] + T[2, b] * x[2, kin]
    for kin in range(3):
        for c in range(3):
            for l in range(3):
                for d in range(3):
                    out_P[r, k, 3 * kin + c, 3 * l + d] = (T[0, c] * P[0, kin, l] * T[0, d] + T[1, c] * P[1, kin, l] * T[1, d]
                                                           + T[2, c] * P[2, kin, l] * T[2, d])
    for b in range(3):
        level_out[r, k, b] = T[0, b] * u[0] + T[1, b] * u[1] + T[2, b] * u[2]


@njit(**_JIT)
def los_mie(first_run, stop_run, zI, polar_var, F, Q, G, dt, sigma_m, span, min_samples, rearm_after, threshold,
            per_axis, level_uncertainty, compensate, level_correlation,
            out_x, out_P, level_out, detected_out, axis_out, stat_out, onset_out, nis_out):
    """Runs first_run..stop_run-1 of ``LOSMIE.run`` with the diagonal pseudo-residual covariance:
    per-axis 3-state filters in the LOS frame re-pointed every scan (eqs 3-16), the per-axis MIE
    (eqs 23-33, scalars), the pooled (B) or per-axis (C) test, the soft update and the compensation
    with the frame re-pointed at the compensated position (eqs 34-44)."""
    K = zI.shape[1]
    x = np.zeros((3, 3))            # (axis, kinematic) in the current LOS frame
    P = np.zeros((3, 3, 3))         # per-axis 3 x 3 blocks
    u = np.zeros(3)
    level_cov = np.zeros((3, 3))
    T = np.zeros((3, 3))
    T_new = np.zeros((3, 3))
    dT = np.zeros((3, 3))
    sens = np.zeros((3, 3, 3))      # (axis, kinematic, input)
    Y = np.zeros((3, 3, 3))
    Y2 = np.zeros((3, 3, 3))
    k_c = np.zeros(3, dtype=np.int64)
    frames = np.zeros((K, 3, 3))
    x_hist = np.zeros((K, 3, 3))
    pvv_hist = np.zeros((K, 3))
    nu_hist = np.zeros((K, 3))
    s_hist = np.ones((K, 3))
    r_hist = np.zeros((K, 3))
    gain_hist = np.zeros((K, 3, 3))
    sens_v_hist = np.zeros((K, 3, 3))
    tmp = np.zeros(3)
    S = np.zeros(3)
    Rd = np.zeros(3)
    gain = np.zeros((3, 3))
    nu = np.zeros(3)
    zL = np.zeros(3)
    H_max = span - min_samples + 1
    D = span
    onsets = np.zeros(H_max, dtype=np.int64)
    hyp = np.zeros(H_max, dtype=np.int64)
    L = np.zeros((H_max, 3))
    u_hat = np.zeros((H_max, 3))
    sigma_u = np.zeros((H_max, 3))
    u_old = np.zeros((H_max, 3))
    old_var = np.zeros((H_max, 3))
    gain_eps = np.zeros((H_max, 3, 3))
    cov_n = np.zeros((H_max, 3, 3))
    rot = np.zeros((3, 3))
    m1 = np.zeros((3, 3))
    Wt = np.zeros((D, 3))
    e = np.zeros((D, 3))
    dz = np.zeros((D, 3))
    armed = np.zeros(3, dtype=np.bool_)
    best_axes = np.zeros(3, dtype=np.int64)
    ok = np.zeros(3, dtype=np.bool_)
    det_axes = np.zeros(3, dtype=np.bool_)
    quiet = np.zeros(3, dtype=np.bool_)
    delta = np.zeros(3)
    soft = np.zeros(3, dtype=np.bool_)
    eps_n = np.zeros(3)
    eps_k = np.zeros(3)
    post = np.zeros(3)
    sigma = np.zeros(3)
    sigma_level = np.zeros(3)
    dx = np.zeros((3, 3))
    dP = np.zeros((3, 3, 3))
    du = np.zeros(3)
    new_cov = np.zeros(3)
    M = np.zeros((3, 3, 3))
    Tn_t = np.zeros((3, 3))
    pos = np.zeros(3)
    for r in range(first_run, stop_run):
        # ---- k = 1: two-point start in the LOS frame of z_I(1)
        rng1, th1 = _los_frame(zI[r, 1, 0], zI[r, 1, 1], zI[r, 1, 2], T)
        Rd[0] = polar_var[0]
        Rd[1] = (rng1 * math.cos(th1)) ** 2 * polar_var[1]
        Rd[2] = rng1**2 * polar_var[2]
        for a in range(3):
            x[a, 0] = T[a, 0] * zI[r, 1, 0] + T[a, 1] * zI[r, 1, 1] + T[a, 2] * zI[r, 1, 2]
            x[a, 1] = (T[a, 0] * (zI[r, 1, 0] - zI[r, 0, 0]) + T[a, 1] * (zI[r, 1, 1] - zI[r, 0, 1])
                       + T[a, 2] * (zI[r, 1, 2] - zI[r, 0, 2])) / dt
            x[a, 2] = 0.0
            for i in range(3):
                for j in range(3):
                    P[a, i, j] = 0.0
                    sens[a, i, j] = 0.0
            P[a, 0, 0], P[a, 0, 1] = Rd[a], Rd[a] / dt
            P[a, 1, 0], P[a, 1, 1] = Rd[a] / dt, 2 * Rd[a] / dt**2
            P[a, 2, 2] = sigma_m**2
            u[a] = 0.0
            k_c[a] = 1
            for c in range(3):
                level_cov[a, c] = 0.0
                frames[1, a, c] = T[a, c]
                sens_v_hist[1, a, c] = 0.0
                gain_hist[1, a, c] = 0.0
            x_hist[1, a, 0], x_hist[1, a, 1], x_hist[1, a, 2] = x[a, 0], x[a, 1], x[a, 2]
            pvv_hist[1, a] = P[a, 1, 1]
            r_hist[1, a] = Rd[a]
            nu_hist[1, a] = 0.0
            s_hist[1, a] = 1.0
        _los_store(r, 1, T, x, P, u, out_x, out_P, level_out)
        for k in range(2, K):
            # eqs 3-4 (+ G u) in frame k-1, each axis on its own
            for a in range(3):
                x0, x1, x2 = x[a, 0], x[a, 1], x[a, 2]
                for i in range(3):
                    x[a, i] = (x0 * F[i, 0] + x1 * F[i, 1] + x2 * F[i, 2]) + u[a] * G[i]
                for i in range(3):
                    for j in range(3):
                        m1[i, j] = F[i, 0] * P[a, 0, j] + F[i, 1] * P[a, 1, j] + F[i, 2] * P[a, 2, j]
                for i in range(3):
                    for j in range(3):
                        P[a, i, j] = (m1[i, 0] * F[j, 0] + m1[i, 1] * F[j, 1] + m1[i, 2] * F[j, 2]) + Q[i, j]
            # eqs 5-7: the frame of the predicted position; state, level and its covariance rotated
            for b in range(3):
                pos[b] = T[0, b] * x[0, 0] + T[1, b] * x[1, 0] + T[2, b] * x[2, 0]
            rng, th = _los_frame(pos[0], pos[1], pos[2], T_new)
            _mul3t(T_new, T, dT)
            _rotate_rows(dT, x, tmp)
            for a in range(3):
                tmp[a] = dT[a, 0] * u[0] + dT[a, 1] * u[1] + dT[a, 2] * u[2]
            for a in range(3):
                u[a] = tmp[a]
            _mul3(dT, level_cov, m1)
            _mul3t(m1, dT, level_cov)
            for a in range(3):
                for c in range(3):
                    T[a, c] = T_new[a, c]
            # eqs 8-11, 15: per-axis scalar update with the diagonal LOS noise
            for a in range(3):
                zL[a] = T[a, 0] * zI[r, k, 0] + T[a, 1] * zI[r, k, 1] + T[a, 2] * zI[r, k, 2]
            Rd[0] = polar_var[0]
            Rd[1] = (rng * math.cos(th)) ** 2 * polar_var[1]
            Rd[2] = rng**2 * polar_var[2]
            for a in range(3):
                S[a] = P[a, 0, 0] + Rd[a]
                for i in range(3):
                    gain[a, i] = P[a, i, 0] / S[a]
                nu[a] = zL[a] - x[a, 0]
                for i in range(3):
                    x[a, i] = x[a, i] + gain[a, i] * nu[a]
                for i in range(3):
                    for j in range(3):
                        P[a, i, j] = P[a, i, j] - gain[a, i] * gain[a, j] * S[a]
            # the state's sensitivity to a level error: Y = F sens + G I, rotated in and out by dT
            for a in range(3):
                for i in range(3):
                    for j in range(3):
                        Y[a, i, j] = (F[i, 0] * sens[a, 0, j] + F[i, 1] * sens[a, 1, j] + F[i, 2] * sens[a, 2, j]
                                      + (G[i] if a == j else 0.0))
            for a in range(3):
                for i in range(3):
                    for j in range(3):
                        Y2[a, i, j] = dT[a, 0] * Y[0, i, j] + dT[a, 1] * Y[1, i, j] + dT[a, 2] * Y[2, i, j]
            for a in range(3):
                for i in range(3):
                    for j in range(3):
                        Y[a, i, j] = Y2[a, i, 0] * dT[j, 0] + Y2[a, i, 1] * dT[j, 1] + Y2[a, i, 2] * dT[j, 2]
            for a in range(3):
                for i in range(3):
                    for j in range(3):
                        sens[a, i, j] = Y[a, i, j] - gain[a, i] * Y[a, 0, j]
            for a in range(3):
                for c in range(3):
                    frames[k, a, c] = T[a, c]
                    x_hist[k, a, c] = x[a, c]
                    gain_hist[k, a, c] = gain[a, c]
                    sens_v_hist[k, a, c] = sens[a, 1, c]
                pvv_hist[k, a] = P[a, 1, 1]
                nu_hist[k, a] = nu[a]
                s_hist[k, a] = S[a]
                r_hist[k, a] = Rd[a]
            nis_out[r, k] = nu[0] ** 2 / S[0] + nu[1] ** 2 / S[1] + nu[2] ** 2 / S[2]
            H = 0
            for d in range(span, min_samples - 1, -1):
                if k - d >= 1:
                    hyp[H] = d
                    onsets[H] = k - d
                    H += 1
            any_armed = False
            for a in range(3):
                armed[a] = (k - k_c[a]) >= rearm_after
                any_armed = any_armed or armed[a]
            if H == 0 or not any_armed:
                _los_store(r, k, T, x, P, u, out_x, out_P, level_out)
                continue
            # ---- the MIE: every onset hypothesis at once, per axis (scalars)
            first_scan = k - D + 1
            for w in range(D):
                i = first_scan + w
                for b in range(3):
                    dz[w, b] = zI[r, i, b] - zI[r, i - 1, b]
            for h in range(H):
                n = onsets[h]
                for a in range(3):
                    innov = 0.0
                    for w in range(D):
                        i = first_scan + w
                        if i <= n and i >= 2:
                            innov += nu_hist[i, a] ** 2 / s_hist[i, a]
                    tpvv = dt * dt * pvv_hist[n, a]
                    A_ha = 0.0
                    b_ha = 0.0
                    quad = 0.0
                    w_sum = 0.0
                    w_sq = 0.0
                    for w in range(D):
                        i = first_scan + w
                        e[w, a] = (frames[n, a, 0] * dz[w, 0] + frames[n, a, 1] * dz[w, 1]
                                   + frames[n, a, 2] * dz[w, 2]) - dt * x_hist[n, a, 1]
                        S_w = tpvv + r_hist[i, a] + r_hist[i - 1, a]
                        N_w = (i - n - 0.5) * dt * dt if i > n else 0.0
                        Wt[w, a] = N_w / S_w
                        A_ha += N_w * Wt[w, a]
                        b_ha += Wt[w, a] * e[w, a]
                        if i > n:
                            quad += e[w, a] * e[w, a] / S_w
                        w_sum += Wt[w, a]
                        w_sq += Wt[w, a] * Wt[w, a]
                    adjacent = 0.0
                    for w in range(D - 1):
                        adjacent += Wt[w, a] * Wt[w + 1, a] * r_hist[first_scan + w, a]
                    cross = tpvv * (w_sum * w_sum - w_sq) - 2.0 * adjacent
                    u_hat[h, a] = b_ha / A_ha
                    sigma_u[h, a] = 1.0 / A_ha + cross / (A_ha * A_ha)
                    L[h, a] = -0.5 * innov - 0.5 * quad + 0.5 * u_hat[h, a] * u_hat[h, a] * A_ha
                    tmp[a] = w_sum / A_ha                   # c of eq 32's cross terms, per axis
                # the old level and its covariance in frame n
                _mul3t(frames[n], T, rot)
                for a in range(3):
                    u_old[h, a] = rot[a, 0] * u[0] + rot[a, 1] * u[1] + rot[a, 2] * u[2]
                _mul3(rot, level_cov, m1)
                _mul3t(m1, rot, cov_n[h])
                if level_correlation:
                    for a in range(3):
                        for c in range(3):
                            gain_eps[h, a, c] = (1.0 if a == c else 0.0) + tmp[a] * dt * sens_v_hist[n, a, c]
                    for a in range(3):
                        total = 0.0
                        for bb in range(3):
                            for c in range(3):
                                total += gain_eps[h, a, bb] * cov_n[h, bb, c] * gain_eps[h, a, c]
                        old_var[h, a] = total
                else:
                    for a in range(3):
                        for c in range(3):
                            gain_eps[h, a, c] = 1.0 if a == c else 0.0
                        old_var[h, a] = cov_n[h, a, a]
            # the pick and the test
            stat = np.nan
            if not per_axis:
                best = 0
                best_total = -np.inf
                for h in range(H):
                    valid = True
                    total = 0.0
                    for a in range(3):
                        valid = valid and armed[a] and onsets[h] >= k_c[a]
                        total += L[h, a]
                    if not valid:
                        total = -np.inf
                    if h == 0 or total > best_total:
                        best, best_total = h, total
                good = math.isfinite(best_total)
                value = 0.0
                for a in range(3):
                    best_axes[a] = best
                    delta[a] = u_hat[best, a] - u_old[best, a]
                    value += delta[a] * delta[a] / (sigma_u[best, a] + (old_var[best, a] if level_uncertainty else 0.0))
                fire = good and value > threshold
                for a in range(3):
                    det_axes[a] = fire
                    quiet[a] = good and not fire
                if good:
                    stat = value
            else:
                any_ok = False
                top = -np.inf
                for a in range(3):
                    best = 0
                    best_score = -np.inf
                    for h in range(H):
                        score = L[h, a] if (armed[a] and onsets[h] >= k_c[a]) else -np.inf
                        if h == 0 or score > best_score:
                            best, best_score = h, score
                    best_axes[a] = best
                    ok[a] = math.isfinite(best_score)
                    delta[a] = u_hat[best, a] - u_old[best, a]
                    value = delta[a] * delta[a] / (sigma_u[best, a] + (old_var[best, a] if level_uncertainty else 0.0))
                    det_axes[a] = ok[a] and value > threshold
                    quiet[a] = ok[a] and not det_axes[a]
                    if ok[a]:
                        any_ok = True
                        if value > top:
                            top = value
                if any_ok:
                    stat = top
            any_det = det_axes[0] or det_axes[1] or det_axes[2]
            onset = -1
            if any_det:
                onset = 2**62
                for a in range(3):
                    if det_axes[a] and onsets[best_axes[a]] < onset:
                        onset = onsets[best_axes[a]]
            if compensate and level_uncertainty and level_correlation:
                any_soft = False
                for a in range(3):
                    soft[a] = quiet[a] and (k - k_c[a]) % rearm_after == 0
                    any_soft = any_soft or soft[a]
                if any_soft:
                    for a in range(3):
                        bh = best_axes[a]
                        g = gain_eps[bh, a, a]
                        s_old = cov_n[bh, a, a]
                        denom = g * g * s_old + sigma_u[bh, a]
                        safe = denom if denom > 0 else 1.0
                        eps_n[a] = -g * s_old * delta[a] / safe if soft[a] else 0.0
                        post[a] = s_old - (g * s_old) ** 2 / safe
                        eps_k[a] = 0.0
                    for h in range(H):
                        on_any = False
                        for a in range(3):
                            on_any = on_any or (soft[a] and best_axes[a] == h)
                        if not on_any:
                            continue
                        _mul3t(T, frames[k - hyp[h]], rot)
                        for a in range(3):
                            total = 0.0
                            for c in range(3):
                                total += rot[a, c] * (eps_n[c] * (1.0 if (soft[c] and best_axes[c] == h) else 0.0))
                            eps_k[a] += total
                    for a in range(3):
                        u[a] = u[a] - eps_k[a]
                    for a in range(3):
                        for i in range(3):
                            x[a, i] = x[a, i] - (sens[a, i, 0] * eps_k[0] + sens[a, i, 1] * eps_k[1]
                                                 + sens[a, i, 2] * eps_k[2])
                    for a in range(3):
                        tmp[a] = (post[a] if post[a] > 0.0 else 0.0) if soft[a] else level_cov[a, a]
                    for a in range(3):
                        for c in range(3):
                            level_cov[a, c] = tmp[a] if a == c else 0.0
            if compensate and any_det:
                # ---- compensation (eqs 34-44) for the detected axes
                for a in range(3):
                    bh = best_axes[a]
                    if not det_axes[a]:
                        delta[a] = 0.0
                    sigma[a] = sigma_u[bh, a] if det_axes[a] else 0.0
                    sigma_level[a] = sigma[a]
                    if level_uncertainty and level_correlation and det_axes[a]:
                        total = 0.0
                        for bb in range(3):
                            for c in range(3):
                                total += ((gain_eps[bh, a, bb] - (1.0 if a == bb else 0.0)) * cov_n[bh, bb, c]
                                          * (gain_eps[bh, a, c] - (1.0 if a == c else 0.0)))
                        sigma_level[a] = sigma[a] + total
                    du[a] = 0.0
                    new_cov[a] = 0.0
                    for i in range(3):
                        dx[a, i] = 0.0
                        for j in range(3):
                            dP[a, i, j] = 0.0
                for h in range(H):
                    use_any = False
                    for a in range(3):
                        use_any = use_any or (det_axes[a] and best_axes[a] == h)
                    if not use_any:
                        continue
                    n = onsets[h]
                    # M_n(k) by the recursion of notes 2.4 H (eq 19 with the rotations)
                    for a in range(3):
                        for i in range(3):
                            for j in range(3):
                                M[a, i, j] = 1.0 if (i == 2 and a == j) else 0.0
                    for a in range(3):
                        for c in range(3):
                            Tn_t[a, c] = frames[n, c, a]
                    for i_scan in range(n + 1, k + 1):
                        _mul3(frames[i_scan - 1], Tn_t, m1)
                        for a in range(3):
                            for i in range(3):
                                for j in range(3):
                                    Y[a, i, j] = (F[i, 0] * M[a, 0, j] + F[i, 1] * M[a, 1, j] + F[i, 2] * M[a, 2, j]
                                                  + G[i] * m1[a, j])
                        _mul3t(frames[i_scan], frames[i_scan - 1], dT)
                        for a in range(3):
                            for i in range(3):
                                for j in range(3):
                                    Y2[a, i, j] = dT[a, 0] * Y[0, i, j] + dT[a, 1] * Y[1, i, j] + dT[a, 2] * Y[2, i, j]
                        for a in range(3):
                            for i in range(3):
                                for j in range(3):
                                    M[a, i, j] = Y2[a, i, j] - gain_hist[i_scan, a, i] * Y2[a, 0, j]
                    for a in range(3):
                        for i in range(3):
                            for j in range(3):
                                M[a, i, j] = M[a, i, j] * (1.0 if (det_axes[j] and best_axes[j] == h) else 0.0)
                    _mul3t(T, frames[n], rot)
                    for a in range(3):
                        for i in range(3):
                            for j in range(3):
                                used = det_axes[j] and best_axes[j] == h
                                sens[a, i, j] = ((0.0 if used else sens[a, i, j])
                                                 + (M[a, i, 0] * rot[j, 0] + M[a, i, 1] * rot[j, 1] + M[a, i, 2] * rot[j, 2]))
                    for a in range(3):
                        for i in range(3):
                            dx[a, i] += M[a, i, 0] * delta[0] + M[a, i, 1] * delta[1] + M[a, i, 2] * delta[2]
                            for l in range(3):
                                dP[a, i, l] += (M[a, i, 0] * sigma[0] * M[a, l, 0] + M[a, i, 1] * sigma[1] * M[a, l, 1]
                                                + M[a, i, 2] * sigma[2] * M[a, l, 2])
                    for a in range(3):
                        total = 0.0
                        for c in range(3):
                            used = det_axes[c] and best_axes[c] == h
                            total += rot[a, c] * (delta[c] * (1.0 if used else 0.0))
                        du[a] += total
                        if det_axes[a] and best_axes[a] == h:
                            new_cov[a] += sigma_level[a]
                for a in range(3):
                    u[a] = u[a] + du[a]
                    for i in range(3):
                        x[a, i] = x[a, i] + dx[a, i]
                        for j in range(3):
                            P[a, i, j] = P[a, i, j] + dP[a, i, j]
                for a in range(3):
                    for c in range(3):
                        keep = (not det_axes[a]) and (not det_axes[c])
                        level_cov[a, c] = level_cov[a, c] * (1.0 if keep else 0.0) + (new_cov[a] if a == c else 0.0)
                # eqs 39-44: re-point the frame at the compensated position (P is not rotated)
                _los_frame(x[0, 0], x[1, 0], x[2, 0], dT)
                _rotate_rows(dT, x, tmp)
                for a in range(3):
                    tmp[a] = dT[a, 0] * u[0] + dT[a, 1] * u[1] + dT[a, 2] * u[2]
                for a in range(3):
                    u[a] = tmp[a]
                _mul3(dT, level_cov, m1)
                _mul3t(m1, dT, level_cov)
                for a in range(3):
                    for i in range(3):
                        for j in range(3):
                            Y[a, i, j] = dT[a, 0] * sens[0, i, j] + dT[a, 1] * sens[1, i, j] + dT[a, 2] * sens[2, i, j]
                for a in range(3):
                    for i in range(3):
                        for j in range(3):
                            sens[a, i, j] = Y[a, i, 0] * dT[j, 0] + Y[a, i, 1] * dT[j, 1] + Y[a, i, 2] * dT[j, 2]
                _mul3(dT, T, m1)
                for a in range(3):
                    for c in range(3):
                        T[a, c] = m1[a, c]
                for a in range(3):
                    if det_axes[a] or not per_axis:
                        k_c[a] = k
            detected_out[r, k] = 1 if any_det else 0
            for a in range(3):
                axis_out[r, k, a] = 1 if det_axes[a] else 0
            stat_out[r, k] = stat
            onset_out[r, k] = onset
            for a in range(3):
                for c in range(3):
                    frames[k, a, c] = T[a, c]
                    x_hist[k, a, c] = x[a, c]
                    sens_v_hist[k, a, c] = sens[a, 1, c]
                pvv_hist[k, a] = P[a, 1, 1]
            _los_store(r, k, T, x, P, u, out_x, out_P, level_out)
