"""The compiled IMM cycle of study 001's estimators (``filters.imm``): one numba pass per scan over
the runs and their models, for 4-state models (x, vx, y, vy) and 2-D position measurements.

``cycle`` is ``filters.imm.imm_cycle`` (seed 001 eqs 1-6: mode probabilities from the log
weights, predicted probabilities, mixing, each model's Kalman predict and update, likelihood,
log weight); ``summary`` is what ``_IMMBase.run`` records each scan (``combine``: the combined
estimate and covariance, the mode probabilities; ``combined_prediction_nis``). Per run: its
running slots are listed; each prior slot's (dx, P + dx dx') row is formed once; the predicted
probabilities, the mixing weights and the mixing sums are formed for all the run's targets at once
(slot-major loops whose innermost loop runs over the targets, which LLVM vectorises, each target's
sum still adding slot after slot); then each target's prediction and update are written out in
scalars and stored straight into its slot. For the usual bank (one constant-velocity F, H picking
the positions, symmetric Q: ``cv_structure``) the 4 x 4 products are written on the upper
triangles with F's and H's exact zeros and ones left out (``_cv_cycle``); any other 4-state bank
takes the general products (``_predict_update``). No (runs x models x models x 16) temporaries as
in the numpy cycle, one call per scan.

What is kept from the numpy cycle (``engine="numpy"``, still there as the reference):

- the arithmetic and its order where numpy's is sequential: sums over slots add slot after slot
  (``_slot_sum``; the numpy cycle's reductions over the slot axis), the mixing is centred on the
  first running slot (eq 6 exact), the weights are ``joint / predicted`` (a division each, as
  numpy), a model nothing switches to is mixed with the posterior weights, the covariance update
  is ``P - K (P H')'`` symmetrised, the closed-form 2 x 2 inverse and log-determinant;
- padding slots get what the numpy cycle gives them (-1, zeros, -inf);
- each run is computed on its own, from its own valid slots only, in a fixed order: a run's
  numbers do not depend on the other runs of the batch, on their number or on the padded width of
  the slot axis (a VSIMM union of 8 beside groups of 5), bit for bit.

What differs, at rounding level: the order of the products' terms (numpy's matmul and einsum
pick their own loops or BLAS kernels for the 4 x 4 and 13 x 13 products), and the NIS solves its
2 x 2 system in closed form instead of LAPACK's LU. The two engines agree to ~1e-15 relative
(tests/test_imm_kernel.py); a VSIMM switching decision could flip where a ratio falls within
rounding of its threshold, which the tests' scenarios do not reach.

Compiled with ``cache=True`` and without ``fastmath``: IEEE arithmetic in the written order (no
reassociation, no fused multiply-adds), so a run's result does not depend on how LLVM splits a
loop into vector body and remainder. numba keeps the machine code beside this file
(``__pycache__``, or ``NUMBA_CACHE_DIR``), valid while this file's content, numba's version and
the processor are the same. The first process on a machine compiles (seconds,
benchmarks/imm_limits.md); the next ones load it. The helpers are inlined by LLVM
(``forceinline``): called, each passed its arrays' descriptors and cost ~30 % more.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)
LOG_2PI = float(np.log(2.0 * np.pi))
# where entry (u, v) of P + dx dx' sits in a slot's row of mixing terms (after dx, columns 0-3):
# the upper triangle first (4-13, what the constant-velocity cycle needs), then the lower (14-19)
_COL = np.array([[4, 5, 6, 7], [14, 8, 9, 10], [15, 17, 11, 12], [16, 18, 19, 13]])


@njit(forceinline=True, **_JIT)
def _probabilities(logw, slots, na, mu):
    """mu[i] (i < na): the weights of slots[:na] normalised (``ModeSet.probabilities``)."""
    top = -np.inf
    for i in range(na):
        v = logw[slots[i]]
        if v > top or v != v:
            top = v
    if not math.isfinite(top):
        top = 0.0
    total = 0.0
    for i in range(na):
        w = np.exp(logw[slots[i]] - top)
        mu[i] = w
        total += w
    for i in range(na):
        mu[i] = mu[i] / total


@njit(forceinline=True, **_JIT)
def _predict_update(xm, Pm, F, Q, off, H, z, Rn, seen, xp, Pp, xo, Po, T, G):
    """x' = F x + off, P' = F (P F') + Q; the Kalman update with z (2,) and R (2, 2) into (xo, Po);
    returns the log-likelihood (0 where ``seen`` is False: the prediction is the posterior)."""
    for i in range(4):
        s = 0.0
        for j in range(4):
            s += xm[j] * F[i, j]
        xp[i] = s + off[i]
    for i in range(4):                       # T = P F'
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += Pm[4 * i + k] * F[j, k]
            T[4 * i + j] = s
    for i in range(4):                       # P' = F T + Q
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += F[i, k] * T[4 * k + j]
            Pp[4 * i + j] = s + Q[i, j]
    if not seen:
        for i in range(4):
            xo[i] = xp[i]
        for i in range(16):
            Po[i] = Pp[i]
        return 0.0
    for i in range(4):                       # P H' (into T[:8], 4 x 2)
        for j in range(2):
            s = 0.0
            for k in range(4):
                s += Pp[4 * i + k] * H[j, k]
            T[2 * i + j] = s
    nu0 = z[0] - (xp[0] * H[0, 0] + xp[1] * H[0, 1] + xp[2] * H[0, 2] + xp[3] * H[0, 3])
    nu1 = z[1] - (xp[0] * H[1, 0] + xp[1] * H[1, 1] + xp[2] * H[1, 2] + xp[3] * H[1, 3])
    # S = H (P H') + R, its closed-form inverse and determinant
    s00 = (H[0, 0] * T[0] + H[0, 1] * T[2] + H[0, 2] * T[4] + H[0, 3] * T[6]) + Rn[0, 0]
    s01 = (H[0, 0] * T[1] + H[0, 1] * T[3] + H[0, 2] * T[5] + H[0, 3] * T[7]) + Rn[0, 1]
    s10 = (H[1, 0] * T[0] + H[1, 1] * T[2] + H[1, 2] * T[4] + H[1, 3] * T[6]) + Rn[1, 0]
    s11 = (H[1, 0] * T[1] + H[1, 1] * T[3] + H[1, 2] * T[5] + H[1, 3] * T[7]) + Rn[1, 1]
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    for i in range(4):                       # gain K = (P H') S^-1 (into G, 4 x 2)
        G[2 * i] = T[2 * i] * i00 + T[2 * i + 1] * i10
        G[2 * i + 1] = T[2 * i] * i01 + T[2 * i + 1] * i11
    for i in range(4):
        xo[i] = xp[i] + (G[2 * i] * nu0 + G[2 * i + 1] * nu1)
    for i in range(4):                       # P - K (P H')'
        for j in range(4):
            Po[4 * i + j] = Pp[4 * i + j] - (G[2 * i] * T[2 * j] + G[2 * i + 1] * T[2 * j + 1])
    for i in range(4):                       # symmetrise: 0.5 (P + P') (the diagonal is unchanged)
        for j in range(i + 1, 4):
            v = 0.5 * (Po[4 * i + j] + Po[4 * j + i])
            Po[4 * i + j] = v
            Po[4 * j + i] = v
    mahalanobis = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i10 * nu0 + i11 * nu1)
    return -0.5 * (mahalanobis + np.log(det) + 2.0 * LOG_2PI)


def cv_structure(F: np.ndarray, Q: np.ndarray, H: np.ndarray) -> float | None:
    """The step dt when F (4, 4) is the shared constant-velocity transition [[1, dt], [0, 1]] per
    axis, H the position picker [[1, 0, 0, 0], [0, 0, 1, 0]] and Q (4, 4 or M, 4, 4) symmetric,
    the case ``_cv_cycle`` writes out; else None."""
    if F.shape != (4, 4) or H.shape != (2, 4):
        return None
    dt = float(F[0, 1])
    cv = np.kron(np.eye(2), np.array([[1.0, dt], [0.0, 1.0]]))
    picker = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    symmetric = np.array_equal(Q, np.swapaxes(Q, -1, -2))
    return dt if np.array_equal(F, cv) and np.array_equal(H, picker) and symmetric else None


@njit(forceinline=True, **_JIT)
def _cv_cycle(acc, b, ref, dt, Q, off, z, Rn, seen, xp, Pp, xo, Po):
    """Eq 6's last step, prediction and update of one model for the constant-velocity F of step dt
    and the position-picking H, in scalars on the upper triangles (P symmetric): the products of
    ``_predict_update`` with F's and H's exact zeros and ones left out. acc[:14, b] the model's
    mixing sums (``_COL``: dx, then the upper triangle of P + dx dx'), ref the centring state.
    Writes xp (4), Pp (4, 4), xo, Po; returns the log-likelihood (0 where ``seen`` is False)."""
    x0 = acc[0, b]
    x1 = acc[1, b]
    x2 = acc[2, b]
    x3 = acc[3, b]
    a00 = acc[4, b]
    a01 = acc[5, b]
    a02 = acc[6, b]
    a03 = acc[7, b]
    a11 = acc[8, b]
    a12 = acc[9, b]
    a13 = acc[10, b]
    a22 = acc[11, b]
    a23 = acc[12, b]
    a33 = acc[13, b]
    # eq 6, centred: sum w (P + dx dx') - dx_mix dx_mix'
    p00 = a00 - x0 * x0
    p01 = a01 - x0 * x1
    p02 = a02 - x0 * x2
    p03 = a03 - x0 * x3
    p11 = a11 - x1 * x1
    p12 = a12 - x1 * x2
    p13 = a13 - x1 * x3
    p22 = a22 - x2 * x2
    p23 = a23 - x2 * x3
    p33 = a33 - x3 * x3
    x0 += ref[0]
    x1 += ref[1]
    x2 += ref[2]
    x3 += ref[3]
    # x' = F x + off; T = P F'; P' = F T + Q (upper triangle)
    y0 = (x0 + x1 * dt) + off[0]
    y1 = x1 + off[1]
    y2 = (x2 + x3 * dt) + off[2]
    y3 = x3 + off[3]
    t00 = p00 + p01 * dt
    t02 = p02 + p03 * dt
    t10 = p01 + p11 * dt
    t12 = p12 + p13 * dt
    t22 = p22 + p23 * dt
    t32 = p23 + p33 * dt
    q00 = (t00 + dt * t10) + Q[0, 0]
    q01 = (p01 + dt * p11) + Q[0, 1]
    q02 = (t02 + dt * t12) + Q[0, 2]
    q03 = (p03 + dt * p13) + Q[0, 3]
    q11 = p11 + Q[1, 1]
    q12 = t12 + Q[1, 2]
    q13 = p13 + Q[1, 3]
    q22 = (t22 + dt * t32) + Q[2, 2]
    q23 = (p23 + dt * p33) + Q[2, 3]
    q33 = p33 + Q[3, 3]
    xp[0] = y0
    xp[1] = y1
    xp[2] = y2
    xp[3] = y3
    Pp[0, 0] = q00
    Pp[0, 1] = Pp[1, 0] = q01
    Pp[0, 2] = Pp[2, 0] = q02
    Pp[0, 3] = Pp[3, 0] = q03
    Pp[1, 1] = q11
    Pp[1, 2] = Pp[2, 1] = q12
    Pp[1, 3] = Pp[3, 1] = q13
    Pp[2, 2] = q22
    Pp[2, 3] = Pp[3, 2] = q23
    Pp[3, 3] = q33
    if not seen:
        for i in range(4):
            xo[i] = xp[i]
            for j in range(4):
                Po[i, j] = Pp[i, j]
        return 0.0
    # P H' = columns 0 and 2 of P'; S = H P H' + R; closed-form inverse
    nu0 = z[0] - y0
    nu1 = z[1] - y2
    s00 = q00 + Rn[0, 0]
    s01 = q02 + Rn[0, 1]
    s10 = q02 + Rn[1, 0]
    s11 = q22 + Rn[1, 1]
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    # gain K = (P H') S^-1, rows (c_i0, c_i1) = (P'_i0, P'_i2)
    k00 = q00 * i00 + q02 * i10
    k01 = q00 * i01 + q02 * i11
    k10 = q01 * i00 + q12 * i10
    k11 = q01 * i01 + q12 * i11
    k20 = q02 * i00 + q22 * i10
    k21 = q02 * i01 + q22 * i11
    k30 = q03 * i00 + q23 * i10
    k31 = q03 * i01 + q23 * i11
    xo[0] = y0 + (k00 * nu0 + k01 * nu1)
    xo[1] = y1 + (k10 * nu0 + k11 * nu1)
    xo[2] = y2 + (k20 * nu0 + k21 * nu1)
    xo[3] = y3 + (k30 * nu0 + k31 * nu1)
    # P - K (P H')', symmetrised 0.5 (A + A')
    Po[0, 0] = q00 - (k00 * q00 + k01 * q02)
    Po[1, 1] = q11 - (k10 * q01 + k11 * q12)
    Po[2, 2] = q22 - (k20 * q02 + k21 * q22)
    Po[3, 3] = q33 - (k30 * q03 + k31 * q23)
    Po[0, 1] = Po[1, 0] = 0.5 * ((q01 - (k00 * q01 + k01 * q12)) + (q01 - (k10 * q00 + k11 * q02)))
    Po[0, 2] = Po[2, 0] = 0.5 * ((q02 - (k00 * q02 + k01 * q22)) + (q02 - (k20 * q00 + k21 * q02)))
    Po[0, 3] = Po[3, 0] = 0.5 * ((q03 - (k00 * q03 + k01 * q23)) + (q03 - (k30 * q00 + k31 * q02)))
    Po[1, 2] = Po[2, 1] = 0.5 * ((q12 - (k10 * q02 + k11 * q22)) + (q12 - (k20 * q01 + k21 * q12)))
    Po[1, 3] = Po[3, 1] = 0.5 * ((q13 - (k10 * q03 + k11 * q23)) + (q13 - (k30 * q01 + k31 * q12)))
    Po[2, 3] = Po[3, 2] = 0.5 * ((q23 - (k20 * q03 + k21 * q23)) + (q23 - (k30 * q02 + k31 * q22)))
    mahalanobis = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i10 * nu0 + i11 * nu1)
    return -0.5 * (mahalanobis + np.log(det) + 2.0 * LOG_2PI)


@njit(**_JIT)
def cycle(prior_index, prior_x, prior_P, prior_logw, targets, z, noise, detected, tpm, F, Q, offsets, H,
          structured, dt):
    """One IMM cycle for every run (``filters.imm.imm_cycle``).

    prior_index (R, A) int64 (-1 = empty slot), prior_x (R, A, 4), prior_P (R, A, 4, 4),
    prior_logw (R, A); targets (R, B) int64 (-1 = none); z (R, 2); noise (1 or R, 2, 2);
    detected (R,) bool; tpm (M, M); F, Q (1 or M, 4, 4); offsets (M, 4); H (2, 4).
    ``structured``: F is the constant-velocity transition of step ``dt`` shared by all models, H
    picks the positions, Q and every P are symmetric (``cv_structure``): the cycle is written out
    on the upper triangles with F's and H's zeros and ones left out (``_cv_cycle``); otherwise
    the general 4 x 4 products (``_predict_update``).
    Returns the ModeSet fields on the targets' slots: index, x, P, log_predicted,
    log_likelihood, log_weight, x_predicted, P_predicted.
    """
    R, A = prior_index.shape
    B = targets.shape[1]
    out_index = np.empty((R, B), np.int64)
    out_x = np.empty((R, B, 4))
    out_P = np.empty((R, B, 4, 4))
    out_lp = np.empty((R, B))
    out_ll = np.empty((R, B))
    out_lw = np.empty((R, B))
    out_xp = np.empty((R, B, 4))
    out_Pp = np.empty((R, B, 4, 4))
    slots = np.empty(A, np.int64)
    mu = np.empty(A)
    tslot = np.empty(B, np.int64)
    tmodel = np.empty(B, np.int64)
    prep = np.empty((A, 20))                 # per prior slot: dx (4), P + dx dx' (16, _COL)
    W = np.empty((A, B))                     # mixing weights, prior slot x target
    pred = np.empty(B)
    acc = np.empty((20, B))                  # mixing sums, entry x target
    ne = 14 if structured else 20            # the upper triangle suffices when P is symmetric
    xm = np.empty(4)
    Pm = np.empty(16)
    xp = np.empty(4)
    Pp = np.empty(16)
    xo = np.empty(4)
    Po = np.empty(16)
    T = np.empty(16)
    G = np.empty(8)
    for r in range(R):
        nb = 0
        for b in range(B):
            m = targets[r, b]
            out_index[r, b] = m
            if m < 0:                        # an empty slot: what the numpy cycle leaves there
                out_lp[r, b] = -np.inf
                out_ll[r, b] = -np.inf
                out_lw[r, b] = -np.inf
                out_x[r, b] = 0.0
                out_P[r, b] = 0.0
                out_xp[r, b] = 0.0
                out_Pp[r, b] = 0.0
            else:
                tslot[nb] = b
                tmodel[nb] = m
                nb += 1
        if nb == 0:
            continue
        na = 0
        for a in range(A):
            if prior_index[r, a] >= 0:
                slots[na] = a
                na += 1
        _probabilities(prior_logw[r], slots, na, mu)
        ref = slots[0]
        for i in range(na):                  # centred on the first running slot (eq 6 exact)
            a = slots[i]
            for u in range(4):
                prep[i, u] = prior_x[r, a, u] - prior_x[r, ref, u]
            for u in range(4):
                for v in range(4):
                    prep[i, _COL[u, v]] = prior_P[r, a, u, v] + prep[i, u] * prep[i, v]
        # eqs 1, 3, 5: predicted probabilities and mixing weights, all targets at once (the loops
        # over targets vectorise; each target's sums still add slot after slot)
        for b in range(nb):
            pred[b] = 0.0
        for i in range(na):
            row = tpm[prior_index[r, slots[i]]]
            c = mu[i]
            for b in range(nb):
                j = row[tmodel[b]] * c
                W[i, b] = j
                pred[b] += j
        for i in range(na):
            c = mu[i]
            for b in range(nb):
                p = pred[b]
                W[i, b] = W[i, b] / p if p > 0 else c    # unreachable: the posterior weights
        for e in range(ne):
            for b in range(nb):
                acc[e, b] = 0.0
        for i in range(na):
            for e in range(ne):
                v = prep[i, e]
                for b in range(nb):
                    acc[e, b] += W[i, b] * v
        Rn = noise[r if noise.shape[0] > 1 else 0]
        seen = detected[r]
        rx = prior_x[r, ref]
        for b in range(nb):
            m = tmodel[b]
            t = tslot[b]
            if structured:
                ll = _cv_cycle(acc, b, rx, dt, Q[m if Q.shape[0] > 1 else 0], offsets[m], z[r], Rn, seen,
                               out_xp[r, t], out_Pp[r, t], out_x[r, t], out_P[r, t])
            else:
                for u in range(4):           # eq 6, centred: sum w (P + dx dx') - dx_mix dx_mix'
                    for v in range(4):
                        Pm[4 * u + v] = acc[_COL[u, v], b] - acc[u, b] * acc[v, b]
                for u in range(4):
                    xm[u] = acc[u, b] + rx[u]
                ll = _predict_update(xm, Pm, F[m if F.shape[0] > 1 else 0], Q[m if Q.shape[0] > 1 else 0],
                                     offsets[m], H, z[r], Rn, seen, xp, Pp, xo, Po, T, G)
                for u in range(4):
                    out_x[r, t, u] = xo[u]
                    out_xp[r, t, u] = xp[u]
                    for v in range(4):
                        out_P[r, t, u, v] = Po[4 * u + v]
                        out_Pp[r, t, u, v] = Pp[4 * u + v]
            lp = np.log(pred[b])
            out_lp[r, t] = lp
            out_ll[r, t] = ll
            out_lw[r, t] = lp + ll
    return out_index, out_x, out_P, out_lp, out_ll, out_lw, out_xp, out_Pp


@njit(forceinline=True, **_JIT)
def _moments(weights, slots, na, x, P, mean, cov):
    """mean = sum w x, cov = sum w (P + d d'), d = x - mean, over slots[:na] in order (``combine``),
    the sums in scalars (kept in registers: ~30 % faster than accumulating into ``cov``)."""
    m0 = m1 = m2 = m3 = 0.0
    for i in range(na):
        a = slots[i]
        c = weights[i]
        m0 += c * x[a, 0]
        m1 += c * x[a, 1]
        m2 += c * x[a, 2]
        m3 += c * x[a, 3]
    c00 = c01 = c02 = c03 = c10 = c11 = c12 = c13 = c20 = c21 = c22 = c23 = c30 = c31 = c32 = c33 = 0.0
    for i in range(na):
        a = slots[i]
        c = weights[i]
        d0 = x[a, 0] - m0
        d1 = x[a, 1] - m1
        d2 = x[a, 2] - m2
        d3 = x[a, 3] - m3
        c00 += c * (P[a, 0, 0] + d0 * d0)
        c01 += c * (P[a, 0, 1] + d0 * d1)
        c02 += c * (P[a, 0, 2] + d0 * d2)
        c03 += c * (P[a, 0, 3] + d0 * d3)
        c10 += c * (P[a, 1, 0] + d1 * d0)
        c11 += c * (P[a, 1, 1] + d1 * d1)
        c12 += c * (P[a, 1, 2] + d1 * d2)
        c13 += c * (P[a, 1, 3] + d1 * d3)
        c20 += c * (P[a, 2, 0] + d2 * d0)
        c21 += c * (P[a, 2, 1] + d2 * d1)
        c22 += c * (P[a, 2, 2] + d2 * d2)
        c23 += c * (P[a, 2, 3] + d2 * d3)
        c30 += c * (P[a, 3, 0] + d3 * d0)
        c31 += c * (P[a, 3, 1] + d3 * d1)
        c32 += c * (P[a, 3, 2] + d3 * d2)
        c33 += c * (P[a, 3, 3] + d3 * d3)
    mean[0] = m0
    mean[1] = m1
    mean[2] = m2
    mean[3] = m3
    cov[0, 0] = c00
    cov[0, 1] = c01
    cov[0, 2] = c02
    cov[0, 3] = c03
    cov[1, 0] = c10
    cov[1, 1] = c11
    cov[1, 2] = c12
    cov[1, 3] = c13
    cov[2, 0] = c20
    cov[2, 1] = c21
    cov[2, 2] = c22
    cov[2, 3] = c23
    cov[3, 0] = c30
    cov[3, 1] = c31
    cov[3, 2] = c32
    cov[3, 3] = c33


@njit(**_JIT)
def summary(index, x, P, log_predicted, log_weight, x_predicted, P_predicted, z, noise, detected, H, k,
            with_nis, state_out, cov_out, mode_out, nis_out):
    """What ``_IMMBase.run`` records at scan k, for every run: the combined estimate and covariance
    (``combine``) into state_out[:, k] (R, K, 4) and cov_out[:, k]; the mode probabilities of
    every model into mode_out[:, k] (R, K, M), 0 for the models not running; with ``with_nis``
    the NIS of the combined prediction (``combined_prediction_nis``) into nis_out[:, k], NaN where
    the scan has no detection. z (R, 2), noise (1 or R, 2, 2), detected (R,) are scan k's."""
    R, A = index.shape
    M = mode_out.shape[2]
    slots = np.empty(A, np.int64)
    mu = np.empty(A)
    mean = np.empty(4)
    cov = np.empty((4, 4))
    for r in range(R):
        na = 0
        for a in range(A):
            if index[r, a] >= 0:
                slots[na] = a
                na += 1
        _probabilities(log_weight[r], slots, na, mu)
        _moments(mu, slots, na, x[r], P[r], mean, cov)
        for u in range(4):
            state_out[r, k, u] = mean[u]
            for v in range(4):
                cov_out[r, k, u, v] = cov[u, v]
        for m in range(M):
            mode_out[r, k, m] = 0.0
        for i in range(na):
            mode_out[r, k, index[r, slots[i]]] = mu[i]
        if not with_nis:
            continue
        if not detected[r]:
            nis_out[r, k] = np.nan
            continue
        _probabilities(log_predicted[r], slots, na, mu)
        _moments(mu, slots, na, x_predicted[r], P_predicted[r], mean, cov)
        Rn = noise[r if noise.shape[0] > 1 else 0]
        nu0 = z[r, 0] - (mean[0] * H[0, 0] + mean[1] * H[0, 1] + mean[2] * H[0, 2] + mean[3] * H[0, 3])
        nu1 = z[r, 1] - (mean[0] * H[1, 0] + mean[1] * H[1, 1] + mean[2] * H[1, 2] + mean[3] * H[1, 3])
        s00 = 0.0                            # S = H (P H') + R
        s01 = 0.0
        s10 = 0.0
        s11 = 0.0
        for u in range(4):
            t0 = 0.0
            t1 = 0.0
            for v in range(4):
                t0 += cov[u, v] * H[0, v]
                t1 += cov[u, v] * H[1, v]
            s00 += H[0, u] * t0
            s01 += H[0, u] * t1
            s10 += H[1, u] * t0
            s11 += H[1, u] * t1
        s00 += Rn[0, 0]
        s01 += Rn[0, 1]
        s10 += Rn[1, 0]
        s11 += Rn[1, 1]
        det = s00 * s11 - s01 * s10
        nis_out[r, k] = (nu0 * (s11 * nu0 - s01 * nu1) + nu1 * (s00 * nu1 - s10 * nu0)) / det


@njit(forceinline=True, **_JIT)
def _slot_probability(logw, a):
    """mu of slot a: ``ModeSet.probabilities`` over all of the run's slots (padding -inf adds 0)."""
    top = -np.inf
    for i in range(logw.shape[0]):
        v = logw[i]
        if v > top or v != v:
            top = v
    if not math.isfinite(top):
        top = 0.0
    total = 0.0
    for i in range(logw.shape[0]):
        total += np.exp(logw[i] - top)
    return np.exp(logw[a] - top) / total


@njit(**_JIT)
def activation(index, log_likelihood, log_weight, centre_group, current, eligible, threshold):
    """``_IMMBase._activation`` (seed sec 4.1): per run, the group whose centre is the
    max-likelihood model (numpy's argmax: the first maximum, a NaN counting as one) when that
    model's probability exceeds ``threshold``, the run is eligible and the group is not
    ``current``; else -1."""
    R, A = index.shape
    out = np.full(R, -1, np.int64)
    for r in range(R):
        best = 0
        top = log_likelihood[r, 0]
        if top == top:
            for a in range(1, A):
                v = log_likelihood[r, a]
                if v != v:
                    best = a
                    break
                if v > top:
                    top = v
                    best = a
        m = index[r, best]
        target = centre_group[m] if m >= 0 else -1
        if eligible[r] and target >= 0 and target != current[r]:
            if _slot_probability(log_weight[r], best) > threshold:
                out[r] = target
    return out


@njit(forceinline=True, **_JIT)
def _masked_logsumexp(values, index, membership, g):
    """``_logsumexp`` over the run's slots whose model is in group g (the others count as -inf)."""
    top = -np.inf
    for a in range(values.shape[0]):
        if index[a] >= 0 and membership[g, index[a]]:
            v = values[a]
            if v > top or v != v:
                top = v
    if not math.isfinite(top):
        top = 0.0
    total = 0.0
    for a in range(values.shape[0]):
        if index[a] >= 0 and membership[g, index[a]]:
            total += np.exp(values[a] - top)
    return np.log(total) + top


@njit(**_JIT)
def group_ratios(index, log_weight, log_predicted, membership, old, new, in_union, new_over_old):
    """The termination statistics of ``VSIMM._terminate`` (eq 8, notes 4.5) for the runs whose
    union runs: log t^mu = log mu(M_o) - log mu(M_a) and this scan's log likelihood ratio
    log L(M_o) - log L(M_a) (new over old when ``new_over_old``), group probability the sum of its
    members' mu, group likelihood sum mu_{k|k-1} L / sum mu_{k|k-1}; 0 for the other runs."""
    R, A = index.shape
    log_t_mu = np.zeros(R)
    step = np.zeros(R)
    for r in range(R):
        if not in_union[r]:
            continue
        top = -np.inf
        for a in range(A):
            v = log_weight[r, a]
            if v > top or v != v:
                top = v
        if not math.isfinite(top):
            top = 0.0
        total = 0.0
        for a in range(A):
            total += np.exp(log_weight[r, a] - top)
        mu_old = 0.0
        mu_new = 0.0
        for a in range(A):
            m = index[r, a]
            if m >= 0:
                mu = np.exp(log_weight[r, a] - top) / total
                if membership[old[r], m]:
                    mu_old += mu
                if membership[new[r], m]:
                    mu_new += mu
        L_old = (_masked_logsumexp(log_weight[r], index[r], membership, old[r])
                 - _masked_logsumexp(log_predicted[r], index[r], membership, old[r]))
        L_new = (_masked_logsumexp(log_weight[r], index[r], membership, new[r])
                 - _masked_logsumexp(log_predicted[r], index[r], membership, new[r]))
        if new_over_old:
            log_t_mu[r] = np.log(mu_new) - np.log(mu_old)
            step[r] = L_new - L_old
        else:
            log_t_mu[r] = np.log(mu_old) - np.log(mu_new)
            step[r] = L_old - L_new
    return log_t_mu, step


_warm = False


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) every function of the kernel for the argument
    types ``filters.imm`` passes, on a one-run, one-model problem. ``_IMMBase.run`` calls it before
    its clock starts, so that the first estimator of a process does not carry numba's start-up
    (~0.8 s, numba's own, any cached function pays it) or the compilation in its compute time."""
    global _warm
    if _warm:
        return
    index = np.zeros((1, 1), np.int64)
    x = np.zeros((1, 1, 4))
    P = np.zeros((1, 1, 4, 4))
    P[0, 0] = np.eye(4)
    w = np.zeros((1, 1))
    z = np.zeros((1, 2))
    noise = np.eye(2)[None]
    seen = np.ones(1, dtype=bool)
    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    out = cycle(index, x, P, w, index, z, noise, seen, np.ones((1, 1)), np.eye(4)[None], np.eye(4)[None],
                np.zeros((1, 4)), H, True, 1.0)
    summary(*out[:2], out[2], out[3], out[5], out[6], out[7], z, noise, seen, H, 1, True,
            np.zeros((1, 2, 4)), np.zeros((1, 2, 4, 4)), np.zeros((1, 2, 1)), np.zeros((1, 2)))
    yes = np.ones(1, dtype=bool)
    activation(index, w, w, np.zeros(2, np.int64), np.zeros(1, np.int64), yes, 0.5)
    group_ratios(index, w, w, np.ones((1, 2), dtype=bool), np.zeros(1, np.int64), np.zeros(1, np.int64), yes, True)
    _warm = True
