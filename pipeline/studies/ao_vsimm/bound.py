"""Study 001's clairvoyant PCRLB (filters.bounds) along the truth: the acceleration profile known.

Study 001's truth is a deterministic profile, so the expectation over the true state in the
information term is exact. The bound is of a stated model; a deterministic truth that leaves the
model's process noise unused lets a filter come below it, which the ratio then shows (< 1).
"""

from __future__ import annotations

import numpy as np

from filters.bounds import posterior_crlb
from filters.models import (acceleration_input_gain, constant_velocity_transition, position_measurement_matrix,
                            two_point_initialisation)
from pipeline.bounds import positive_parameter, scan_interval
from pipeline.data import Truth


class KnownInputBound:
    """Study 001's clairvoyant bound: the true mode sequence (the acceleration profile) known.

    Every model of the set is x(k+1) = F x(k) + Gamma (a_m + w(k)), w ~ N(0, q^2 I) (seed 001
    eqs 7, 9-11): the modes differ only in the known input a_m, so with the mode sequence known the
    model is linear-Gaussian with a known input, and its PCRLB is the covariance of the
    mode-matched Kalman filter with the models' process noise q, started like the IMMs by
    two-point differencing of scans 0 and 1 (so the bound starts at scan 1). A known input moves
    the mean only, so the bound is the same for every mode sequence: what an IMM loses to not
    knowing the mode is the RMSE / sqrt(PCRLB) ratio above 1. Missed detections (a sensor with
    ``detection_probability`` < 1) scale the measurement information by that probability, the
    information-reduction factor of a clutter-free sensor.

    Parameters: process_noise_std q [m/s^2] (the models' ``process_noise_std``).
    """

    def __init__(self, process_noise_std: float) -> None:
        self.process_noise_std = positive_parameter("bound.process_noise_std", process_noise_std)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        dt = scan_interval(truth)
        K = truth.time.size
        F = constant_velocity_transition(dt)
        G = acceleration_input_gain(dt)
        Q = self.process_noise_std**2 * G @ G.T
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
