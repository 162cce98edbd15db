"""The "obvious way" FSIMM: one run, one model at a time, plain numpy. The executable specification.

Nothing here is batched or clever. ``filters/imm/reference.py`` filters every Monte Carlo run at once on a
padded model-slot axis with log-domain weights; this module writes the same estimator the way
a textbook listing reads (Bar-Shalom, Li & Kirubarajan 2001, sec 11.6.6), so that the batched
code can be checked against it and timed against it.

Conventions (seed 001, "Conventions [resolved]"):

- State (x, vx, y, vy). Model m: x_k = F x_{k-1} + Gamma (a_m + w), w ~ N(0, q^2 I2), q = 10 m/s^2.
  Measurement z_k = H x_k + v, v ~ N(0, R), R = 20^2 I2.
- The first estimate is at k = 1, by two-point differencing of z_0 and z_1: position z_1,
  velocity (z_1 - z_0)/T, per-axis covariance [[R, R/T], [R/T, 2R/T^2]]. Every model starts
  from that same (x, P).
- Mode probabilities at k = 1: mu = e_{m1} (all mass on m1) unless ``initial_probabilities``
  is given (the FilterPy comparison needs a floored start, see ``benchmarks/filterpy_imm.py``).
- From k = 2 on, one IMM cycle per scan:
    1. predicted mode probability  c_j = sum_i pi_ij mu_i     (pi row i = P(m_k = j | m_{k-1} = i))
       mixing weights              w_ij = pi_ij mu_i / c_j,
       except when c_j = 0: that model is mixed with the posterior weights w_ij = mu_i
       (and, below, keeps probability 0);
       mixed estimate              x0_j = sum_i w_ij x_i,
                                   P0_j = sum_i w_ij (P_i + (x_i - x0_j)(x_i - x0_j)')
    2. Kalman filter of model j:   x' = F x0_j + Gamma a_j,  P' = F P0_j F' + Gamma Q Gamma'
                                   S = H P' H' + R,  K = P' H' S^-1,
                                   x_j = x' + K (z - H x'),  P_j = (I - K H) P'
                                   likelihood L_j = N(z - H x'; 0, S)
    3. mu_j proportional to c_j L_j (normalised over the models)
    4. combined estimate           x = sum_j mu_j x_j
- Acceleration estimate a_hat = sum_j mu_j a_j.

Likelihoods are handled as logs and scaled by the largest one before exponentiating (so that
no ratio underflows); that changes nothing mathematically.
"""

from __future__ import annotations

import numpy as np


def cv_transition(dt: float) -> np.ndarray:
    """F for (x, vx, y, vy)."""
    return np.array([[1.0, dt, 0.0, 0.0],
                     [0.0, 1.0, 0.0, 0.0],
                     [0.0, 0.0, 1.0, dt],
                     [0.0, 0.0, 0.0, 1.0]])


def acceleration_gain(dt: float) -> np.ndarray:
    """Gamma (4, 2): how an acceleration (ax, ay) held over one period enters the state."""
    return np.array([[dt * dt / 2.0, 0.0],
                     [dt, 0.0],
                     [0.0, dt * dt / 2.0],
                     [0.0, dt]])


def position_measurement() -> np.ndarray:
    """H (2, 4): picks (x, y)."""
    return np.array([[1.0, 0.0, 0.0, 0.0],
                     [0.0, 0.0, 1.0, 0.0]])


def two_point_start(z0: np.ndarray, z1: np.ndarray, R: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """x = (z1x, (z1x - z0x)/T, z1y, (z1y - z0y)/T); P per axis pair [[R, R/T], [R/T, 2R/T^2]]."""
    x = np.array([z1[0], (z1[0] - z0[0]) / dt, z1[1], (z1[1] - z0[1]) / dt])
    P = np.zeros((4, 4))
    for a in range(2):          # rows: axis a
        for b in range(2):      # columns: axis b (keeps cross terms of a correlated R)
            r = R[a, b]
            P[2 * a, 2 * b] = r
            P[2 * a, 2 * b + 1] = r / dt
            P[2 * a + 1, 2 * b] = r / dt
            P[2 * a + 1, 2 * b + 1] = 2.0 * r / dt**2
    return x, P


def reference_fsimm(models, z: np.ndarray, R: np.ndarray, dt: float,
                    initial_probabilities: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Filter one run with the fixed-structure IMM over every model of ``models``.

    models : filters.models.AccelerationModelSet (only its accelerations, transition matrix and
        process-noise std are used; F, Gamma, H are written out above)
    z : (K, 2) position measurements z_0 .. z_{K-1}
    R : (2, 2) measurement noise covariance
    dt : scan period
    initial_probabilities : (M,) mode probabilities at k = 1; default e_{m1}

    Returns states (K, 4) and acceleration estimates (K, 2); row 0 is NaN (no estimate yet).
    """
    accelerations = np.asarray(models.accelerations, dtype=float)      # (M, 2)
    tpm = np.asarray(models.transition_matrix, dtype=float)            # (M, M)
    M = len(accelerations)
    K = len(z)
    F = cv_transition(dt)
    G = acceleration_gain(dt)
    H = position_measurement()
    Q = models.process_noise_std**2 * np.eye(2)
    GQG = G @ Q @ G.T
    I4 = np.eye(4)

    if initial_probabilities is None:
        mu = np.zeros(M)
        mu[models.model_index("m1")] = 1.0
    else:
        mu = np.array(initial_probabilities, dtype=float)
        mu = mu / mu.sum()

    states = np.full((K, 4), np.nan)
    acceleration = np.full((K, 2), np.nan)

    # k = 1: two-point start, the same (x, P) for every model
    x0, P0 = two_point_start(z[0], z[1], R, dt)
    xs = [x0.copy() for _ in range(M)]
    Ps = [P0.copy() for _ in range(M)]
    states[1] = sum(mu[j] * xs[j] for j in range(M))
    acceleration[1] = sum(mu[j] * accelerations[j] for j in range(M))

    for k in range(2, K):
        # 1. mixing
        c = np.zeros(M)
        for j in range(M):
            for i in range(M):
                c[j] += tpm[i, j] * mu[i]
        mixed_x, mixed_P = [], []
        for j in range(M):
            if c[j] > 0:
                w = [tpm[i, j] * mu[i] / c[j] for i in range(M)]
            else:
                w = [mu[i] for i in range(M)]       # unreachable model: mix with the posteriors
            xm = np.zeros(4)
            for i in range(M):
                xm += w[i] * xs[i]
            Pm = np.zeros((4, 4))
            for i in range(M):
                d = xs[i] - xm
                Pm += w[i] * (Ps[i] + np.outer(d, d))
            mixed_x.append(xm)
            mixed_P.append(Pm)

        # 2. one Kalman filter per model
        log_likelihood = np.zeros(M)
        for j in range(M):
            x_pred = F @ mixed_x[j] + G @ accelerations[j]
            P_pred = F @ mixed_P[j] @ F.T + GQG
            nu = z[k] - H @ x_pred
            S = H @ P_pred @ H.T + R
            S_inv = np.linalg.inv(S)
            gain = P_pred @ H.T @ S_inv
            xs[j] = x_pred + gain @ nu
            Ps[j] = (I4 - gain @ H) @ P_pred
            log_likelihood[j] = -0.5 * (nu @ S_inv @ nu + np.log(np.linalg.det(2.0 * np.pi * S)))

        # 3. mode probabilities: mu_j proportional to c_j L_j (a model with c_j = 0 stays at 0)
        scale = log_likelihood.max()
        for j in range(M):
            mu[j] = c[j] * np.exp(log_likelihood[j] - scale)
        mu = mu / mu.sum()

        # 4. combination
        states[k] = sum(mu[j] * xs[j] for j in range(M))
        acceleration[k] = sum(mu[j] * accelerations[j] for j in range(M))
    return states, acceleration
