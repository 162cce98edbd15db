"""Study 001's clairvoyant PCRLBs (filters.bounds) along the truth: the acceleration profile known.

Study 001's truth is a deterministic profile, so the expectation over the true state in the
information term is exact. ``position_bound`` is the bound of the process that made the truth;
``position_bound_model`` the bound of the IMMs' model, which a deterministic truth lets a filter
come below (ratio < 1).
"""

from __future__ import annotations

import numpy as np

from filters.bounds import posterior_crlb
from filters.models import (acceleration_input_gain, constant_velocity_transition, position_measurement_matrix,
                            two_point_initialisation)
from pipeline.evaluation.bounds import positive_parameter, scan_interval
from pipeline.data import Truth


class KnownInputBound:
    """Study 001's bounds, with the true mode sequence (the acceleration profile) known.

    Every model of the set is x(k+1) = F x(k) + Gamma (a_m + w(k)), w ~ N(0, q^2 I) (seed 001
    eqs 7, 9-11): the modes differ only in the known input a_m, so with the mode sequence known the
    model is linear-Gaussian with a known input, and its PCRLB is the covariance of the mode-matched
    Kalman filter with process noise q, started like the IMMs by two-point differencing of scans 0
    and 1 (so the bound starts at scan 1). A known input moves the mean only, so the bound is the
    same for every mode sequence. Two bounds, one meaning per name (issue 22):

    - ``position_bound``: q = ``truth_process_noise_std``, the process that generated the truth (the
      scenario's, 0 for the paper's deterministic profile: the bound of estimating that truth from
      the measurements with its dynamics known; finite, and shrinking as scans accumulate). No
      unbiased estimator's RMSE is below it: a ratio below 1 beyond Monte Carlo error is a bug.
    - ``position_bound_model``: q = ``model_process_noise_std``, the IMMs' own model. A truth that
      does not use that process noise lets a filter come below it (ratio < 1): not a bug.

    Missed detections (a sensor with ``detection_probability`` < 1) scale the measurement
    information by that probability, the information-reduction factor of a clutter-free sensor.
    """

    def __init__(self, truth_process_noise_std: float, model_process_noise_std: float) -> None:
        self.truth_process_noise_std = float(truth_process_noise_std)
        if not (np.isfinite(self.truth_process_noise_std) and self.truth_process_noise_std >= 0):
            raise ValueError(f"bound.truth_process_noise_std: {truth_process_noise_std} must be a finite number >= 0")
        self.model_process_noise_std = positive_parameter("bound.model_process_noise_std", model_process_noise_std)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) sqrt(trace) of the PCRLB position block of the truth's own process [m]."""
        return self.bound(truth, sensor, self.truth_process_noise_std)

    def position_bound_model(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) the same with the IMMs' process noise [m]."""
        return self.bound(truth, sensor, self.model_process_noise_std)

    @staticmethod
    def bound(truth: Truth, sensor, process_noise_std: float) -> np.ndarray:
        dt = scan_interval(truth)
        K = truth.time.size
        F = constant_velocity_transition(dt)
        G = acceleration_input_gain(dt)
        Q = process_noise_std**2 * G @ G.T
        H = position_measurement_matrix()
        R = float(sensor.noise_std) ** 2 * np.eye(2)
        detection = float(getattr(sensor, "detection_probability", 1.0))
        information = np.broadcast_to(detection * H.T @ np.linalg.inv(R) @ H, (K - 1, 4, 4))
        _, initial = two_point_initialisation(np.zeros(2), np.zeros(2), dt, R)
        bounds = posterior_crlb(F, Q, initial, information)                           # scans 1..K-1
        position = [0, 2]                                                             # (x, vx, y, vy)
        out = np.full(K, np.nan)
        out[1:] = np.sqrt(bounds[:, position[0], position[0]] + bounds[:, position[1], position[1]])
        return out
