"""How far from the limit: posterior Cramer-Rao bounds (filters.bounds) along a study's truth.

A bound node (config ``bound``, ``_target_`` one of the classes below) gives the single-target
studies (001, 000) ``position_bound(truth, sensor) -> (K,)`` = sqrt(trace) of the position block of
the PCRLB at each scan [m] (NaN before the filters' first estimate); the study adds the metrics
``position_bound`` and ``position_rmse_over_bound`` (RMSE / sqrt(PCRLB): 1 = at the bound).

Both truths here are deterministic profiles, so the expectation over the true state in the
information term is exact (the mean over the runs is of identical values). Each bound is the bound
of a stated *model*; a deterministic truth that leaves the model's process noise unused lets a
filter come below it, which the ratio then shows (< 1).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from filters.bounds import posterior_crlb
from filters.coordinates import converted_covariance, line_of_sight_angles
from filters.models import (acceleration_input_gain, constant_velocity_transition, position_measurement_matrix,
                            singer_process_noise, singer_transition, two_point_initialisation)
from pipeline.data import Truth


def _positive(key: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{key}: {value} must be a finite number > 0")
    return value


def _scan_interval(truth: Truth) -> float:
    steps = np.diff(truth.time)
    if steps.size == 0 or not np.allclose(steps, steps[0]):
        raise ValueError("bound: the PCRLB here needs evenly spaced scans; the truth's times are not")
    return float(steps[0])


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
        self.process_noise_std = _positive("bound.process_noise_std", process_noise_std)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        dt = _scan_interval(truth)
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


class RadarSingerBound:
    """Study 000's bound: the 3-D radar (range, azimuth, elevation with R_p) tracking a target
    of the filters' Singer model (tau, sigma_m per axis, spec 000).

    The information at scan k is E[H' R_p^-1 H] with H = d(r, phi, theta)/d(position) at the true
    position, i.e. the inverse of the converted covariance R_I = J R_p J' there (J = H^-1); the
    start is filter A's two-point start (scans 0 and 1, with R_I at the truth) with the Singer
    acceleration prior sigma_m^2. The truth's acceleration is a deterministic profile, not the
    Singer process: this is the bound of the model the filters assume, which a filter that tracks
    the deterministic profile closely can come below (ratio < 1), most of all while it does not
    maneuver (the Singer noise then over-states the motion's randomness).
    """

    def __init__(self, tau: float, sigma_m: float) -> None:
        self.tau = _positive("bound.tau", tau)
        self.sigma_m = _positive("bound.sigma_m", sigma_m)

    def information(self, truth: Truth, sensor) -> np.ndarray:
        """(K, 3, 3) E[H' R_p^-1 H] of the position over the runs, in (x, y, z)."""
        names = truth.state_names
        position = truth.state[:, :, 0, [names.index(a) for a in ("x", "y", "z")]] - np.asarray(sensor.position)
        r, phi, theta = line_of_sight_angles(position)
        polar_var = np.diag(sensor.noise_covariance)                                    # R_p = diag(range, az, el)
        converted = converted_covariance(np.stack([r, phi, theta], -1), polar_var)      # (R, K, 3, 3)
        return np.linalg.inv(converted).mean(axis=0)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        dt = _scan_interval(truth)
        K = truth.time.size
        F = np.kron(np.eye(3), singer_transition(dt, self.tau))                     # (x, vx, ax, y, ...)
        Q = np.kron(np.eye(3), singer_process_noise(dt, self.tau, self.sigma_m))
        position_info = self.information(truth, sensor)
        pos, vel, acc = [0, 3, 6], [1, 4, 7], [2, 5, 8]
        information = np.zeros((K, 9, 9))
        information[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]] = position_info
        R0, R1 = np.linalg.inv(position_info[0]), np.linalg.inv(position_info[1])
        initial = np.zeros((9, 9))                                                  # filter A's start
        initial[np.ix_(pos, pos)] = R1
        initial[np.ix_(pos, vel)] = R1 / dt
        initial[np.ix_(vel, pos)] = R1 / dt
        initial[np.ix_(vel, vel)] = (R1 + R0) / dt**2
        initial[acc, acc] = self.sigma_m**2
        bounds = posterior_crlb(F, Q, initial, information[1:])                     # scans 1..K-1
        out = np.full(K, np.nan)
        out[1:] = np.sqrt(np.trace(bounds[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]], axis1=1, axis2=2))
        return out


class PerTruth:
    """Values computed from one truth and sensor (a bound along the true trajectory), kept for the
    truth last asked about: the runner evaluates every variant against the same truth, so the
    bound is computed once per (truth, sensor, key), not once per variant. Holds the objects
    themselves, compared by identity (ids could be reused), and only the latest truth's values."""

    def __init__(self) -> None:
        self._entries: list[tuple[Any, Any, Any, Any]] = []

    def get(self, truth: Truth, sensor, key, compute: Callable[[], Any]) -> Any:
        for cached_truth, cached_sensor, cached_key, value in self._entries:
            if cached_truth is truth and cached_sensor is sensor and cached_key == key:
                return value
        value = compute()
        self._entries = [e for e in self._entries if e[0] is truth] + [(truth, sensor, key, value)]
        return value


def bound_metrics(bound, truth: Truth, sensor, position_rmse: np.ndarray) -> dict[str, np.ndarray]:
    """``position_bound`` and ``position_rmse_over_bound`` (K,) for a bound node (None: none)."""
    if bound is None:
        return {}
    limit = bound.position_bound(truth, sensor)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"position_bound": limit, "position_rmse_over_bound": position_rmse / limit}
