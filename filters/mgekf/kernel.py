"""The compiled scan loop of study 003's sonar trackers (``filters.mgekf``): one numba pass over a
block of scans for every run, each run's state held in local arrays from scan to scan.

``track_block`` runs scans k0..k1-1 of every run: the prediction (seed eqs 1-3, 6-7; Phi, Gamma_u,
Q of the scan's dt), then

- bearing only (passive): the scalar MGEKF / EKF update of ``filters.mgekf.reference._bearing_only_update``
  (K = P h' / s, Joseph form with the g-row);
- bearing and range (active) in the 6-state filters: ``filters.mgekf.nonlinear_update`` (EKF gain
  at the prediction, Joseph form with the g-rows of the measured bearing (seed eqs 18-22) or with H
  for the plain EKF);
- bearing and range in the KF of KF + MGEKF: ``filters.mgekf.converted_update`` (4 states, the
  converted measurement r [sin b, cos b] with R_c = J diag(s_b^2, s_r^2) J' at the measured values),
  with the hand-over at each switch (``pad_acceleration`` / dropping the acceleration states);

and stores the state, the covariance and the update's NIS. The numpy trackers (``engine="numpy"``)
stay as the reference; the maths is theirs, written out in scalars:

- the 2 x 2 innovation covariances are inverted in closed form (numpy: LAPACK's solve);
- the products skip the columns that are zero by construction: H and the g-rows touch only the
  position (x, y), the KF's H picks it, so A = I - K G acts on two columns
  (A P A' = P - K (G P) - ((A P) G') K');
- the predictions are the full 6 x 6 (4 x 4) products in index order.

So the engines agree to rounding, not bit for bit (tests/test_mgekf_kernel.py: ~1e-12 relative over
a case-2 scenario's first scans). Each run is computed on its own, in a fixed order: a run's numbers
do not depend on the other runs of the batch or their number (mc.chunk_runs stays bit-identical).

Compiled with ``cache=True`` and without ``fastmath`` (IEEE arithmetic in the written order), like
filters/imm/kernel.py: the first process on a machine compiles, the next ones load the machine code
from ``__pycache__``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)
SINGLE, KF_PLUS_MGEKF = 0, 1          # architectures: one 6-state filter throughout; the KF / MGEKF pair
TAN, EXACT = 0, 1                     # the bearing g-row (filters.mgekf.bearing_g_row)


@njit(forceinline=True, **_JIT)
def _wrap(angle):
    """``filters.mgekf.wrap``: into (-pi, pi], numpy's floating mod (fmod, then the divisor's sign)."""
    period = 2.0 * math.pi
    w = np.fmod(angle + math.pi, period)
    if w != 0.0 and w < 0.0:
        w += period
    w -= math.pi
    return math.pi if w == -math.pi else w


@njit(forceinline=True, **_JIT)
def _predict(x, P, n, u0, u1, Phi, Gamma, Q, xp, T):
    """x = Phi x + Gamma u, P = Phi (P Phi') + Q on the leading n states (in place; xp, T scratch)."""
    for i in range(n):
        value = 0.0
        for j in range(n):
            value += x[j] * Phi[i, j]
        xp[i] = value + (u0 * Gamma[i, 0] + u1 * Gamma[i, 1])
    for i in range(n):
        x[i] = xp[i]
    for i in range(n):
        for j in range(n):
            value = 0.0
            for m in range(n):
                value += P[i, m] * Phi[j, m]
            T[i, j] = value
    for i in range(n):
        for j in range(n):
            value = 0.0
            for m in range(n):
                value += Phi[i, m] * T[m, j]
            P[i, j] = value + Q[i, j]


@njit(forceinline=True, **_JIT)
def _bearing_row(px, py, bearing, form, clamp, r_hat):
    """The bearing's modifiable row (g0, g1) over (x, y) with the measured bearing; ``r_hat`` is the
    range the caller's numpy counterpart floors the tan form with."""
    s, c = math.sin(bearing), math.cos(bearing)
    if form == TAN:
        denominator = px * s + py * c                                  # r_hat cos(delta)
        floor = clamp * r_hat
        if abs(denominator) < floor:
            denominator = -floor if denominator < 0 else floor
        return c / denominator, -s / denominator
    delta = _wrap(bearing - math.atan2(px, py))
    ratio = 1.0 if abs(delta) < 1e-8 else delta / (1.0 if delta == 0 else math.sin(delta))
    scale = ratio / math.hypot(px, py)
    return c * scale, -s * scale


@njit(forceinline=True, **_JIT)
def _symmetrised(P, n):
    for i in range(n):
        for j in range(i + 1, n):
            value = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = value
            P[j, i] = value


@njit(forceinline=True, **_JIT)
def _bearing_only(x, P, n, bearing, variance, modified, form, clamp, gain, gP):
    """``_bearing_only_update``: returns the NIS residual^2 / s."""
    px, py = x[0], x[1]
    r2 = px * px + py * py
    h0, h1 = py / r2, -px / r2
    if not modified:
        g0, g1 = h0, h1
    else:
        g0, g1 = _bearing_row(px, py, bearing, form, clamp, math.sqrt(r2))
    residual = _wrap(bearing - math.atan2(px, py))
    for i in range(n):
        gain[i] = P[i, 0] * h0 + P[i, 1] * h1                        # P h'
    s = gain[0] * h0 + gain[1] * h1 + variance
    for i in range(n):
        gain[i] = gain[i] / s
        x[i] = x[i] + gain[i] * residual
    for j in range(n):
        gP[j] = g0 * P[0, j] + g1 * P[1, j]
    gPg = gP[0] * g0 + gP[1] * g1
    for i in range(n):
        for j in range(n):
            P[i, j] = P[i, j] - gain[i] * gP[j] - gain[j] * gP[i] + ((gPg + variance) * gain[i]) * gain[j]
    _symmetrised(P, n)
    return residual * residual / s


@njit(forceinline=True, **_JIT)
def _two_row_update(x, P, n, r0, r1, H, S, G, R00, R01, R11, K, GP, AP, APG):
    """The Kalman update with a 2-D residual (r0, r1), rows H (2, n) over the position (columns 0, 1),
    innovation covariance S (2, 2) (filled by the caller), the Joseph form with rows G (2, n) and
    measurement noise R: x += K r, P = (I - K G) P (I - K G)' + K R K'. Returns r' S^-1 r."""
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    i00, i01, i10, i11 = S[1, 1] / det, -S[0, 1] / det, -S[1, 0] / det, S[0, 0] / det
    for i in range(n):
        a = P[i, 0] * H[0, 0] + P[i, 1] * H[0, 1]                    # (P H')[i, 0]
        b = P[i, 0] * H[1, 0] + P[i, 1] * H[1, 1]
        K[i, 0] = a * i00 + b * i10
        K[i, 1] = a * i01 + b * i11
        x[i] = x[i] + (K[i, 0] * r0 + K[i, 1] * r1)
    for a in range(2):
        for j in range(n):
            GP[a, j] = G[a, 0] * P[0, j] + G[a, 1] * P[1, j]
    for i in range(n):
        for j in range(n):
            AP[i, j] = P[i, j] - (K[i, 0] * GP[0, j] + K[i, 1] * GP[1, j])
    for i in range(n):
        APG[i, 0] = AP[i, 0] * G[0, 0] + AP[i, 1] * G[0, 1]
        APG[i, 1] = AP[i, 0] * G[1, 0] + AP[i, 1] * G[1, 1]
    for i in range(n):
        KR0 = K[i, 0] * R00 + K[i, 1] * R01
        KR1 = K[i, 0] * R01 + K[i, 1] * R11
        for j in range(n):
            P[i, j] = AP[i, j] - (APG[i, 0] * K[j, 0] + APG[i, 1] * K[j, 1]) + (KR0 * K[j, 0] + KR1 * K[j, 1])
    _symmetrised(P, n)
    return r0 * (i00 * r0 + i01 * r1) + r1 * (i10 * r0 + i11 * r1)


@njit(forceinline=True, **_JIT)
def _active(x, P, n, bearing, rng, bearing_var, range_var, modified, form, clamp, H, S, G, K, GP, AP, APG):
    """``nonlinear_update`` with bearing and range (seed eqs 18-24)."""
    px, py = x[0], x[1]
    r2 = px * px + py * py
    r = math.sqrt(r2)
    beta_hat, r_hat = math.atan2(px, py), math.hypot(px, py)
    H[0, 0], H[0, 1] = py / r2, -px / r2
    H[1, 0], H[1, 1] = px / r, py / r
    r0, r1 = _wrap(bearing - beta_hat), rng - r_hat
    for a in range(2):
        for b in range(2):
            value = 0.0
            for i in range(2):
                value += H[a, i] * (P[i, 0] * H[b, 0] + P[i, 1] * H[b, 1])
            S[a, b] = value
    S[0, 0] += bearing_var
    S[1, 1] += range_var
    if modified:
        G[0, 0], G[0, 1] = _bearing_row(px, py, bearing, form, clamp, r_hat)
        delta = _wrap(bearing - beta_hat)
        mean = beta_hat + 0.5 * delta
        scale = math.cos(0.5 * delta)
        G[1, 0], G[1, 1] = math.sin(mean) / scale, math.cos(mean) / scale   # theorem 1's range row
    else:
        for a in range(2):
            G[a, 0], G[a, 1] = H[a, 0], H[a, 1]
    return _two_row_update(x, P, n, r0, r1, H, S, G, bearing_var, 0.0, range_var, K, GP, AP, APG)


@njit(forceinline=True, **_JIT)
def _converted(x, P, n, bearing, rng, bearing_var, range_var, H, S, K, GP, AP, APG):
    """``converted_update``: the linear KF on r [sin b, cos b] with R_c at the measured values."""
    sb, cb = math.sin(bearing), math.cos(bearing)
    j00, j01, j10, j11 = rng * cb, sb, -rng * sb, cb                   # d(x, y) / d(beta, r)
    R00 = j00 * bearing_var * j00 + j01 * range_var * j01
    R01 = j00 * bearing_var * j10 + j01 * range_var * j11
    R11 = j10 * bearing_var * j10 + j11 * range_var * j11
    H[0, 0], H[0, 1], H[1, 0], H[1, 1] = 1.0, 0.0, 0.0, 1.0
    S[0, 0], S[0, 1], S[1, 0], S[1, 1] = P[0, 0] + R00, P[0, 1] + R01, P[1, 0] + R01, P[1, 1] + R11
    r0, r1 = rng * sb - x[0], rng * cb - x[1]
    return _two_row_update(x, P, n, r0, r1, H, S, H, R00, R01, R11, K, GP, AP, APG)


@njit(**_JIT)
def track_block(k0, k1, n0, architecture, modified, form, clamp, bearing_var, range_var, handover_var,
                z, active, u, model_of_step, Phi6, Gamma6, Q6, Phi4, Gamma4, Q4, x, P, states, covariances, nis):
    """Scans k0..k1-1 of every run. ``n0``: the state's size before scan k0 (4: the KF of KF + MGEKF
    while active; 6 otherwise); x (R, 6) and P (R, 6, 6) carry each run's state in their leading n
    entries into and out of the block. z (R, K, 2) bearing and range, active (K,), u (R, K, 2) the
    own-ship input; ``model_of_step[k - 1]`` indexes the models of scan k's dt. Writes states
    (R, K, 6), covariances (R, K, 6, 6) (the leading n entries; the rest as the caller filled them)
    and nis (R, K)."""
    R = z.shape[0]
    xr = np.empty(6)
    Pr = np.empty((6, 6))
    xp = np.empty(6)
    T = np.empty((6, 6))
    gain = np.empty(6)
    gP = np.empty(6)
    H = np.zeros((2, 6))
    S = np.empty((2, 2))
    G = np.zeros((2, 6))
    K = np.empty((6, 2))
    GP = np.empty((2, 6))
    AP = np.empty((6, 6))
    APG = np.empty((6, 2))
    for r in range(R):
        n = n0
        for i in range(6):
            xr[i] = x[r, i]
            for j in range(6):
                Pr[i, j] = P[r, i, j]
        for k in range(k0, k1):
            m = model_of_step[k - 1]
            u0, u1 = u[r, k - 1, 0], u[r, k - 1, 1]
            bearing, rng = z[r, k, 0], z[r, k, 1]
            if architecture == KF_PLUS_MGEKF:
                if active[k - 1] and not active[k]:                 # KF -> MGEKF: pad the accelerations
                    xr[4] = 0.0
                    xr[5] = 0.0
                    for i in range(6):
                        for j in range(4, 6):
                            Pr[i, j] = 0.0
                            Pr[j, i] = 0.0
                    Pr[4, 4] = handover_var
                    Pr[5, 5] = handover_var
                    n = 6
                elif active[k] and not active[k - 1]:               # MGEKF -> KF: drop them
                    n = 4
                if active[k]:
                    _predict(xr, Pr, 4, u0, u1, Phi4[m], Gamma4[m], Q4[m], xp, T)
                    value = _converted(xr, Pr, 4, bearing, rng, bearing_var, range_var, H, S, K, GP, AP, APG)
                else:
                    _predict(xr, Pr, 6, u0, u1, Phi6[m], Gamma6[m], Q6[m], xp, T)
                    value = _bearing_only(xr, Pr, 6, bearing, bearing_var, True, form, clamp, gain, gP)
            else:
                _predict(xr, Pr, 6, u0, u1, Phi6[m], Gamma6[m], Q6[m], xp, T)
                if active[k]:
                    value = _active(xr, Pr, 6, bearing, rng, bearing_var, range_var, modified, form, clamp,
                                    H, S, G, K, GP, AP, APG)
                else:
                    value = _bearing_only(xr, Pr, 6, bearing, bearing_var, modified, form, clamp, gain, gP)
            nis[r, k] = value
            for i in range(n):
                states[r, k, i] = xr[i]
                for j in range(n):
                    covariances[r, k, i, j] = Pr[i, j]
        for i in range(6):
            x[r, i] = xr[i]
            for j in range(6):
                P[r, i, j] = Pr[i, j]


_warm = False


def read_only(a, dtype) -> np.ndarray:
    """``a`` as the kernel takes its inputs: C-contiguous, ``dtype``, and read-only (a table's columns
    reach the trackers read-only; one array type for every caller is one compiled specialisation,
    the one ``warm_up`` loads)."""
    view = np.ascontiguousarray(a, dtype=dtype).view()
    view.flags.writeable = False
    return view


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) ``track_block`` for the argument types
    ``filters.mgekf`` passes, on a one-run problem without scans. The trackers call it before their
    clock starts, so that the first tracker of a process does not carry numba's start-up (~0.5 s)
    in its compute time (the job's compute-seconds column compares the variants)."""
    global _warm
    if _warm:
        return
    models = np.zeros((1, 6, 6)), np.zeros((1, 6, 2)), np.zeros((1, 6, 6))
    small = np.zeros((1, 4, 4)), np.zeros((1, 4, 2)), np.zeros((1, 4, 4))
    track_block(1, 1, 6, SINGLE, True, TAN, 0.1, 1.0, 1.0, 0.0, read_only(np.zeros((1, 2, 2)), float),
                read_only(np.ones(2), np.bool_), read_only(np.zeros((1, 2, 2)), float), np.zeros(1, dtype=np.int64),
                *models, *small, np.zeros((1, 6)),
                np.zeros((1, 6, 6)), np.zeros((1, 2, 6)), np.zeros((1, 2, 6, 6)), np.zeros((1, 2)))
    _warm = True
