"""The "obvious way" pseudo-bias-measurement registration (seed 002, the paper's proposal): one run,
one report, one target at a time, plain numpy. The executable specification.

``filters/bias/reference.py`` runs every Monte Carlo run and every target at once and keeps the bias least
squares in a prior-normalised information form. This module writes the same estimator the way
the paper's equations read, so that the batched code can be checked against it and timed against
it. It shares nothing with ``filters/bias/reference.py`` except the input dataclass ``RadarReports``.

Conventions (spec 002, literature notes section 5):

- State X = (x, y, vx, vy), H = [I2 0]. CV transition Phi(T) (eq 42) and DCWNA process noise
  Q(T) = q [[T^3/3 I2, T^2/2 I2], [T^2/2 I2, T I2]] (eq 43), q = 6 m^2/s^3.
- Radar s at position o_s; bias beta_s = (b_r [m], b_theta [rad], eps_r, eps_theta). At a
  point (r, theta) relative to the radar: B = [[cos th, -r sin th], [sin th, r cos th]] (eq 4),
  C = [[1, 0, r, 0], [0, 1, 0, th]] (eq 3), R^m = B diag(sigma_r^2, sigma_th^2) B' (eq 6).
  B, C and R^m are evaluated at the reporting radar's *predicted* biased track position of that
  target, before the update (spec 002, "Evaluation point of the Jacobians").
- Converted measurement z^m = o_i + r^p (cos theta^p, sin theta^p) (eq 2).
- Local tracks: every radar tracks every target from RadarReports.start (truth + N(0, P0),
  P = P0, bias matrix G = 0) at the start time.
- Stacked bias b = [beta_1; beta_2; ...], b_hat = 0, Sigma = blkdiag(diag(100^2, 0.2^2,
  0.01^2, 0.1^2), ...) unless another prior is given.

Report k of radar i at time t, for each target in turn:

  1. prediction of radar i's track: X^- = Phi X, P^- = Phi P Phi' + Q, G^- = Phi G
     (T = t - t_i, t_i the time of radar i's last update);
     B_i, C_i, R^m_i at the predicted position X^-[:2] - o_i.
  2. for every other radar j (its latest track of the target, last updated at t_j, T_j = t - t_j):
         z^b   = z^m_i - H Phi(T_j) X^b_j                                         (eq 22)
         H^b   = [B_i C_i in radar i's 4 columns, -H Phi(T_j) G_j in radar j's]   (eq 25)
         R^b   = H (Phi P_j Phi' + Q(T_j)) H' + R^m_i                             (eq 27)
     stacked over j (eq 28; with S > 2 the blocks share w_i, so R^m_i goes off the diagonal,
     literature notes 5.2 - with the study's two radars there is one block and no choice);
     covariance-form recursive least squares (eqs 33-35):
         K = Sigma H^b' (H^b Sigma H^b' + R^b)^-1
         b_hat += K (z^b - H^b b_hat)
         Sigma -= K H^b Sigma
  3. radar i's Kalman update of that target with z^m_i:
         S = H P^- H' + R^m_i,  K_i = P^- H' S^-1,
         X = X^- + K_i (z^m_i - H X^-),  P = (I - K_i H) P^-,
         G = (I - K_i H) G^- + K_i B_i C_i      (eq 20 with the printed "(I - K) H" read as (I - K H))

Step 2 for all targets of the report comes before step 3 for any of them (the pseudo measurements
use the other radars' tracks only, so this order is immaterial for them; it matters only in that
radar i's own track is the one before its update, used only through B_i C_i, R^m_i).

After report k: the bias estimate b_hat and Sigma, and for every target radar i's biased track
X^b and its compensated version X^b - G beta_hat_i (eq 38), beta_hat_i = radar i's block of b_hat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

PRIOR_STD = (100.0, 0.2, 0.01, 0.1)


def transition(T: float) -> np.ndarray:
    """Phi(T) of eq 42 for (x, y, vx, vy)."""
    return np.array([[1.0, 0.0, T, 0.0],
                     [0.0, 1.0, 0.0, T],
                     [0.0, 0.0, 1.0, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


def process_noise(T: float, q: float) -> np.ndarray:
    """Q(T) of eq 43."""
    a, b, c = T**3 / 3.0, T**2 / 2.0, T
    return q * np.array([[a, 0.0, b, 0.0],
                         [0.0, a, 0.0, b],
                         [b, 0.0, c, 0.0],
                         [0.0, b, 0.0, c]])


H_POS = np.array([[1.0, 0.0, 0.0, 0.0],
                  [0.0, 1.0, 0.0, 0.0]])


def bias_model(position: np.ndarray, radar: np.ndarray, sigma_r: float, sigma_theta: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """B C (2 x 4) and R^m (2 x 2) at ``position`` (x, y), seen from ``radar``: eqs 3, 4, 6."""
    dx, dy = position[0] - radar[0], position[1] - radar[1]
    r = math.sqrt(dx * dx + dy * dy)
    th = math.atan2(dy, dx)
    B = np.array([[math.cos(th), -r * math.sin(th)],
                  [math.sin(th), r * math.cos(th)]])
    C = np.array([[1.0, 0.0, r, 0.0],
                  [0.0, 1.0, 0.0, th]])
    Rm = B @ np.diag([sigma_r**2, sigma_theta**2]) @ B.T
    return B @ C, Rm


def converted(z_polar: np.ndarray, radar: np.ndarray) -> np.ndarray:
    """z^m = o + r^p (cos theta^p, sin theta^p) (eq 2)."""
    r, th = z_polar[0], z_polar[1]
    return np.array([radar[0] + r * math.cos(th), radar[1] + r * math.sin(th)])


@dataclass
class ReferenceResult:
    """bias (R, K, 4S) and bias_covariance (R, K, 4S, 4S) after each report; track_state and
    compensated_state (R, K, T, 4): the reporting radar's biased track of every target after the
    report, and the same with beta_hat_i removed."""

    bias: np.ndarray
    bias_covariance: np.ndarray
    track_state: np.ndarray
    compensated_state: np.ndarray


def reference_pseudo_bias_run(time: np.ndarray, sensor: np.ndarray, z: np.ndarray, sensor_position: np.ndarray,
                              noise_std: np.ndarray, start_time: float, start_state: np.ndarray,
                              start_covariance: np.ndarray, q: float = 6.0,
                              prior_std: Sequence[float] = PRIOR_STD
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One Monte Carlo run. z (K, T, 2) polar reports; start_state (S, T, 4).

    Returns bias (K, 4S), bias covariance (K, 4S, 4S), track state (K, T, 4) and compensated
    track state (K, T, 4).
    """
    K, T, _ = z.shape
    S = sensor_position.shape[0]
    n = 4 * S
    I4 = np.eye(4)

    # local tracks [radar][target] = [X, P, G], and each radar's last update time
    tracks = [[[start_state[s, t].astype(float).copy(), np.array(start_covariance, dtype=float), np.zeros((4, 4))]
               for t in range(T)] for s in range(S)]
    last = [float(start_time)] * S

    b = np.zeros(n)
    Sigma = np.diag(np.tile(np.asarray(prior_std, dtype=float), S) ** 2)

    out_b = np.zeros((K, n))
    out_Sigma = np.zeros((K, n, n))
    out_x = np.zeros((K, T, 4))
    out_xc = np.zeros((K, T, 4))

    for k in range(K):
        i, t_now = int(sensor[k]), float(time[k])
        o_i = sensor_position[i]
        sigma_r, sigma_th = noise_std[i]
        Ti = t_now - last[i]
        Phi_i, Q_i = transition(Ti), process_noise(Ti, q)

        # 1. predict radar i's tracks; B C and R^m at the predicted positions
        predicted = []
        for t in range(T):
            X, P, G = tracks[i][t]
            Xp = Phi_i @ X
            Pp = Phi_i @ P @ Phi_i.T + Q_i
            Gp = Phi_i @ G
            BC, Rm = bias_model(Xp[:2], o_i, sigma_r, sigma_th)
            zm = converted(z[k, t], o_i)
            predicted.append((Xp, Pp, Gp, BC, Rm, zm))

        # 2. pseudo bias measurements, bias update target by target (eqs 22-35)
        others = [j for j in range(S) if j != i]
        for t in range(T):
            _, _, _, BC, Rm, zm = predicted[t]
            m = 2 * len(others)
            zb = np.zeros(m)
            Hb = np.zeros((m, n))
            Rb = np.zeros((m, m))
            for row, j in enumerate(others):
                Xj, Pj, Gj = tracks[j][t]
                Tj = t_now - last[j]
                Phi_j = transition(Tj)
                rows = slice(2 * row, 2 * row + 2)
                zb[rows] = zm - H_POS @ Phi_j @ Xj                                       # eq 22
                Hb[rows, 4 * i:4 * i + 4] = BC                                            # eq 25
                Hb[rows, 4 * j:4 * j + 4] = -H_POS @ Phi_j @ Gj
                Pj_pred = Phi_j @ Pj @ Phi_j.T + process_noise(Tj, q)
                for col in range(len(others)):                                            # eq 27 (+ shared w_i)
                    Rb[rows, 2 * col:2 * col + 2] = Rm
                Rb[rows, rows] = H_POS @ Pj_pred @ H_POS.T + Rm
            gain = Sigma @ Hb.T @ np.linalg.inv(Hb @ Sigma @ Hb.T + Rb)                    # eq 33
            b = b + gain @ (zb - Hb @ b)                                                  # eq 34
            Sigma = Sigma - gain @ Hb @ Sigma                                             # eq 35

        # 3. radar i's local Kalman updates (eqs 16-21)
        beta_i = b[4 * i:4 * i + 4]
        for t in range(T):
            Xp, Pp, Gp, BC, Rm, zm = predicted[t]
            Sk = H_POS @ Pp @ H_POS.T + Rm
            Kk = Pp @ H_POS.T @ np.linalg.inv(Sk)
            X = Xp + Kk @ (zm - H_POS @ Xp)
            P = (I4 - Kk @ H_POS) @ Pp
            G = (I4 - Kk @ H_POS) @ Gp + Kk @ BC
            tracks[i][t] = [X, P, G]
            out_x[k, t] = X
            out_xc[k, t] = X - G @ beta_i                                                 # eq 38
        last[i] = t_now
        out_b[k] = b
        out_Sigma[k] = Sigma
    return out_b, out_Sigma, out_x, out_xc


def reference_pseudo_bias(reports, runs: Sequence[int] | None = None, q: float = 6.0,
                          prior_std: Sequence[float] = PRIOR_STD) -> ReferenceResult:
    """Every run of ``reports`` (a filters.bias.RadarReports with a truth start), one at a time,
    or only the runs listed in ``runs`` (in that order)."""
    if reports.start is None:
        raise ValueError("the reference implements the bias-free (truth) start only; RadarReports.start is None")
    chosen = list(range(reports.z.shape[0])) if runs is None else list(runs)
    results = [reference_pseudo_bias_run(reports.time, reports.sensor, reports.z[r], reports.sensor_position,
                                         reports.noise_std, reports.start.time, reports.start.state[r],
                                         reports.start.covariance, q, prior_std) for r in chosen]
    return ReferenceResult(*(np.stack([res[c] for res in results]) for c in range(4)))
