"""Track filters of the association trackers, batched over every (run, track slot) pair at once.

A motion keeps its tracks' state as a dict of arrays whose two leading axes are (runs R, slots M);
the trackers index, grow and fill those arrays without knowing what they hold. Measurements are
positions z = H x + w, w ~ N(0, R) (DetectionSets.position_index picks H).

Both motions update with the probabilistic data association form (Bar-Shalom & Tse 1975; Bar-Shalom,
Willett & Tian 2011, "Tracking and Data Fusion", 3.4), which takes the association weights beta_i
of the scan's detections i and beta_0 of "none of them" (sum 1)::

    nu = sum_i beta_i nu_i,  nu_i = z_i - H x^-               (combined innovation)
    x^+ = x^- + W nu,        W = P^- H' S^-1,  S = H P^- H' + R
    P^+ = beta_0 P^- + (1 - beta_0) (P^- - W S W') + W (sum_i beta_i nu_i nu_i' - nu nu') W'

A GNN assignment is the one-hot case (beta_i = 1 for the assigned detection: the Kalman update;
beta_0 = 1 for a missed track: the prediction), JPDA gives the marginal association probabilities.

``ConstantVelocity``: (x, vx, y, vy), F = blockdiag([[1, T], [0, 1]]), Q = sigma_v^2 G G' with
G = blockdiag([T^2/2, T]') (discrete white acceleration; Vo & Ma 2006 Sec. IV-A's model).
A track starts at one detection z: position z with covariance R, velocity 0 with standard deviation
``initial_velocity_std`` per axis (single-point initiation).

``InteractingCVTurn``: the project's CV/CT IMM (filters.turn.CVCTIMM: its mixing and mode-matched
predictions, Bar-Shalom, Li & Kirubarajan 2001, 11.6.6 and 11.7) run per track, state
(x, vx, y, vy, omega). Gating and association use the moment-matched prediction with the predicted
mode probabilities c_j. Each mode is updated with the same beta (IMM-PDA, Houles & Bar-Shalom 1989)
and its mode likelihood is Lambda_j = lambda_0 + sum_i lambda_i N(z_i; H x_j^-, S_j), with lambda_0 and
lambda_i given by the tracker: for JPDA lambda_0 = 1 - P_D P_G, lambda_i = P_D / kappa over the gated
detections (kappa the clutter density); for GNN lambda_i = 1 on the assigned detection and
lambda_0 = 1 for a missed track (so mu follows the assigned detection's likelihoods, and stays at c_j
on a miss). Then mu_j = c_j Lambda_j / sum, x = sum mu_j x_j, P = sum mu_j (P_j + d d').
"""

from __future__ import annotations

import numpy as np

from filters.kalman import LOG_2PI, inverse_and_logdet
from filters.models import acceleration_input_gain, constant_velocity_transition

CV_NAMES = ("x", "vx", "y", "vy")
CT_NAMES = ("x", "vx", "y", "vy", "omega")


def _positive(value: object, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise ValueError(f"{key}: {value!r} must be a finite number > 0")
    return float(value)


def _pda(x, P, H, R, z, beta, beta0):
    """The PDA update (module docstring) of states x (..., n), P (..., n, n) with each track's
    candidate detections z (..., D, m) (broadcastable: one scan's set for every track, or the one a
    GNN assigned), beta (..., D), beta0 (...); also returns each candidate's log N(z_i; H x, S)
    (..., D)."""
    rows = H_rows(H)
    zhat = x[..., rows]
    PHt = P[..., :, rows]
    S = PHt[..., rows, :] + R
    S_inv, logdet = inverse_and_logdet(S)
    W = PHt @ S_inv
    nu_i = np.nan_to_num(z - zhat[..., None, :])        # (..., D, m); empty slots have beta 0
    b = np.nan_to_num(beta)
    nu = np.einsum("...d,...dm->...m", b, nu_i)
    spread = np.einsum("...d,...dm,...dk->...mk", b, nu_i, nu_i) - nu[..., :, None] * nu[..., None, :]
    x_post = x + np.einsum("...nm,...m->...n", W, nu)
    WSWt = W @ S @ np.swapaxes(W, -1, -2)
    b0 = beta0[..., None, None]
    P_post = P - (1.0 - b0) * WSWt + W @ spread @ np.swapaxes(W, -1, -2)
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    mahalanobis = np.einsum("...dm,...mk,...dk->...d", nu_i, S_inv, nu_i)
    loglik = -0.5 * (mahalanobis + logdet[..., None] + H.shape[0] * LOG_2PI)
    return x_post, P_post, loglik


def H_rows(H: np.ndarray) -> np.ndarray:
    """The state indices a position-picking H (m, n) measures."""
    return np.argmax(H, axis=1)


class ConstantVelocity:
    """Kalman CV track filter (module docstring); ``acceleration_std`` sigma_v [m/s^2]."""

    state_names = CV_NAMES

    def __init__(self, acceleration_std: float = 5.0, initial_velocity_std: float = 15.0) -> None:
        self.acceleration_std = _positive(acceleration_std, "acceleration_std")
        self.initial_velocity_std = _positive(initial_velocity_std, "initial_velocity_std")
        self.H = np.zeros((2, 4))
        self.H[[0, 1], [0, 2]] = 1.0

    def empty(self, R: int, M: int) -> dict[str, np.ndarray]:
        return {"x": np.zeros((R, M, 4)), "P": np.broadcast_to(np.eye(4), (R, M, 4, 4)).copy()}

    def start(self, z: np.ndarray, noise: np.ndarray) -> dict[str, np.ndarray]:
        """Tracks started at detections z (B, 2)."""
        B = z.shape[0]
        x = np.zeros((B, 4))
        x[:, [0, 2]] = z
        P = np.zeros((B, 4, 4))
        P[:, [[0], [2]], [[0, 2]]] = noise
        P[:, [1, 3], [1, 3]] = self.initial_velocity_std**2
        return {"x": x, "P": P}

    def predict(self, state: dict, dt: float) -> dict:
        F = constant_velocity_transition(dt)
        G = acceleration_input_gain(dt)
        Q = self.acceleration_std**2 * G @ G.T
        x = state["x"] @ F.T
        P = F @ state["P"] @ F.T + Q
        return {"x": x, "P": 0.5 * (P + np.swapaxes(P, -1, -2))}

    def predicted_measurement(self, state: dict, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, M, 2) H x^- and (R, M, 2, 2) S = H P^- H' + R."""
        rows = H_rows(self.H)
        return state["x"][..., rows], state["P"][..., rows[:, None], rows[None, :]] + noise

    def update(self, state: dict, z: np.ndarray, noise: np.ndarray, beta: np.ndarray, beta0: np.ndarray,
               weight0: np.ndarray, weights: np.ndarray) -> dict:
        """PDA update with each track's candidates z (R, M or 1, D, 2), beta (R, M, D), beta0 (R, M); the
        mode weights are unused."""
        x, P, _ = _pda(state["x"], state["P"], self.H, noise, z, beta, beta0)
        return {"x": x, "P": P}

    def estimate(self, state: dict) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], dict]:
        return state["x"], state["P"], CV_NAMES, {}


class InteractingCVTurn:
    """IMM of the project's CV and coordinated-turn models per track (module docstring); the
    keywords are filters.turn.CVCTIMM's (its 2-D state), ``initial_velocity_std`` as for CV."""

    state_names = CT_NAMES

    def __init__(self, initial_velocity_std: float = 15.0, cv_acceleration_density: float = 1.0,
                 ct_acceleration_density: float = 4.0, turn_rate_density: float = 1e-4,
                 sojourn_times=(20.0, 10.0), initial_mode_probabilities=(0.8, 0.2),
                 turn_rate_std: float = 0.1) -> None:
        from filters.turn import CVCTIMM

        self.imm = CVCTIMM(cv_acceleration_density=cv_acceleration_density,
                           ct_acceleration_density=ct_acceleration_density, turn_rate_density=turn_rate_density,
                           sojourn_times=sojourn_times, initial_mode_probabilities=initial_mode_probabilities,
                           turn_rate_std=turn_rate_std, engine="numpy")
        self.initial_velocity_std = _positive(initial_velocity_std, "initial_velocity_std")
        self.H = np.zeros((2, 5))
        self.H[[0, 1], [0, 2]] = 1.0

    def empty(self, R: int, M: int) -> dict[str, np.ndarray]:
        return {"x": np.zeros((R, M, 2, 5)), "P": np.broadcast_to(np.eye(5), (R, M, 2, 5, 5)).copy(),
                "mu": np.full((R, M, 2), 0.5)}

    def start(self, z: np.ndarray, noise: np.ndarray) -> dict[str, np.ndarray]:
        B = z.shape[0]
        x = np.zeros((B, 2, 5))
        x[:, :, [0, 2]] = z[:, None]
        P = np.zeros((B, 2, 5, 5))
        P[:, :, [[0], [2]], [[0, 2]]] = noise
        P[:, :, [1, 3], [1, 3]] = self.initial_velocity_std**2
        P[:, :, 4, 4] = self.imm.turn_rate_std**2
        mu = np.broadcast_to(self.imm.initial_mode_probabilities, (B, 2)).copy()
        return {"x": x, "P": P, "mu": mu}

    def predict(self, state: dict, dt: float) -> dict:
        """IMM steps 1-3's prediction (11.6.6) on every (run, slot); mu becomes c_j."""
        R, M = state["mu"].shape[:2]
        x, P, mu = state["x"].reshape(R * M, 2, 5), state["P"].reshape(R * M, 2, 5, 5), state["mu"].reshape(R * M, 2)
        x_mix, P_mix, predicted = self.imm.mix(x, P, mu, dt)
        x_pred, P_pred = self.imm.predict(x_mix, P_mix, dt)
        return {"x": x_pred.reshape(R, M, 2, 5), "P": P_pred.reshape(R, M, 2, 5, 5),
                "mu": predicted.reshape(R, M, 2)}

    @staticmethod
    def _moments(x, P, mu):
        xm = np.einsum("...j,...jn->...n", mu, x)
        d = x - xm[..., None, :]
        Pm = np.einsum("...j,...jnk->...nk", mu, P + d[..., :, None] * d[..., None, :])
        return xm, Pm

    def predicted_measurement(self, state: dict, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xm, Pm = self._moments(state["x"], state["P"], state["mu"])
        rows = H_rows(self.H)
        return xm[..., rows], Pm[..., rows[:, None], rows[None, :]] + noise

    def update(self, state: dict, z: np.ndarray, noise: np.ndarray, beta: np.ndarray, beta0: np.ndarray,
               weight0: np.ndarray, weights: np.ndarray) -> dict:
        """Per-mode PDA update with the shared beta; mu_j = c_j Lambda_j / sum (module docstring)."""
        b = beta[:, :, None]                                  # (R, M, 1, D) shared by both modes
        x, P, loglik = _pda(state["x"], state["P"], self.H, noise, z[:, :, None], b, beta0[:, :, None])
        with np.errstate(divide="ignore"):
            terms = np.where(weights[:, :, None] > 0, np.log(weights)[:, :, None] + loglik, -np.inf)   # (R, M, 2, D)
            terms = np.concatenate([np.broadcast_to(np.log(weight0)[:, :, None, None], terms.shape[:3] + (1,)),
                                    terms], axis=-1)
        top = np.max(terms, axis=(-1, -2), keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        lam = np.exp(terms - top).sum(axis=-1)                # Lambda_j up to one factor shared by the modes
        mu = state["mu"] * lam
        total = mu.sum(axis=-1, keepdims=True)
        mu = np.where(total > 0, mu / np.where(total > 0, total, 1.0), state["mu"])
        return {"x": x, "P": P, "mu": mu}

    def estimate(self, state: dict) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], dict]:
        xm, Pm = self._moments(state["x"], state["P"], state["mu"])
        return xm, Pm, CT_NAMES, {"mode_probabilities": state["mu"]}
