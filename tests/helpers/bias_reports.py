"""Study 002's radar reports simulated without the pipeline (filters.bias): CV targets seen by two
alternating radars with a known bias."""

from __future__ import annotations

import numpy as np

from filters.bias import RadarReports, TrackStart, cv_transition, dcwna_process_noise, polar

POSITIONS = np.array([[0.0, 0.0], [10_000.0, 0.0]])
NOISE_STD = np.array([[10.0, 1e-3], [10.0, 1e-3]])
BETA = np.array([20.0, 2e-3, 3e-5, 2e-4])
# start positions [km], a spread subset of the spec's 4 x 8 grid
SPREAD = np.array([[5, 5], [40, 20], [20, 10], [30, 5], [10, 20], [35, 15], [15, 15], [25, 20]], dtype=float)


def simulate(runs=4, targets=3, reports=60, bias=BETA, noise_scale=1.0, q=0.0, seed=0, positions=POSITIONS,
             noise_std=NOISE_STD, noise=None):
    """CV targets seen by alternating radars (sensor 1 at 0.5, 1.5, ...; sensor 0 at 1, 2, ...)."""
    rng = np.random.default_rng(seed)
    S = positions.shape[0]
    spread = SPREAD[:targets] * 1000.0           # km -> m: targets seen at many aspects (observability)
    starts = np.concatenate([spread, np.full((targets, 2), 20.0)], axis=1)
    dt = 0.5
    K = reports + 1
    F, Q = cv_transition(dt), dcwna_process_noise(dt, q)
    L = np.linalg.cholesky(Q + 1e-12 * np.eye(4)) if q > 0 else np.zeros((4, 4))
    X = np.empty((runs, K, targets, 4))
    X[:, 0] = starts
    for k in range(1, K):
        X[:, k] = X[:, k - 1] @ F.T + rng.standard_normal((runs, targets, 4)) @ L.T
    time = np.arange(1, K) * dt
    sensor = (np.arange(reports) + 1) % S if S == 2 else np.arange(reports) % S
    bias = np.broadcast_to(bias, (S, 4))
    w = rng.standard_normal((runs, reports, targets, 2)) if noise is None else noise
    z = np.empty((runs, reports, targets, 2))
    for k in range(reports):
        s = sensor[k]
        r, theta = polar(X[:, k + 1, :, :2] - positions[s])
        z[:, k, :, 0] = (1 + bias[s, 2]) * r + bias[s, 0] + noise_scale * noise_std[s, 0] * w[:, k, :, 0]
        z[:, k, :, 1] = (1 + bias[s, 3]) * theta + bias[s, 1] + noise_scale * noise_std[s, 1] * w[:, k, :, 1]
    P0 = np.diag([100.0, 100.0, 25.0, 25.0])
    start_state = np.broadcast_to(X[:, 0][:, None], (runs, S, targets, 4)).copy()
    start = TrackStart(0.0, start_state, P0)
    return X, RadarReports(time, sensor, z, positions, noise_std, start), w
