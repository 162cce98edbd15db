"""Study 000's PCRLBs (filters.bounds): the 3-D radar tracking the truth's own process
(``position_bound``) and a target of the filters' Singer model (``position_bound_model``).

Study 000's truth is a deterministic profile, so the expectation over the true state in the
information term is exact (the mean over the runs is of identical values).
"""

from __future__ import annotations

import numpy as np

from filters.bounds import posterior_crlb
from filters.coordinates import converted_covariance, line_of_sight_angles
from filters.models import singer_process_noise, singer_transition, two_point_start
from pipeline.evaluation.bounds import positive_parameter, scan_interval
from pipeline.data import Truth


class RadarSingerBound:
    """Study 000's bounds for the 3-D radar (range, azimuth, elevation with R_p).

    ``position_bound`` (issue 22): the process that generated the truth. Its acceleration is a
    known profile plus, with the scenario's ``process_noise_std`` q > 0, white acceleration held over
    each scan (x(k+1) = F x(k) + Gamma (a(k) + w(k)), Gamma = [dt^2/2, dt] per axis): a known input
    moves the mean only, so the bound is that of a CV model with Q = q^2 Gamma Gamma' (Q = 0 for the
    paper's deterministic truth: estimating it from the measurements with its dynamics known,
    finite and shrinking as scans accumulate), started like filter A by two-point differencing of
    scans 0 and 1. No unbiased estimator comes below it.

    ``position_bound_model``: a target of the filters' Singer model (tau, sigma_m per axis, spec 000).

    The information at scan k is E[H' R_p^-1 H] with H = d(r, phi, theta)/d(position) at the true
    position, i.e. the inverse of the converted covariance R_I = J R_p J' there (J = H^-1); the
    start is filter A's two-point start (scans 0 and 1, with R_I at the truth) with the Singer
    acceleration prior sigma_m^2. The truth's acceleration is a deterministic profile, not the
    Singer process: this is the bound of the model the filters assume, which a filter that tracks
    the deterministic profile closely can come below (ratio < 1), most of all while it does not
    maneuver (the Singer noise then over-states the motion's randomness).
    """

    def __init__(self, tau: float, sigma_m: float, truth_process_noise_std: float = 0.0) -> None:
        self.tau = positive_parameter("bound.tau", tau)
        self.sigma_m = positive_parameter("bound.sigma_m", sigma_m)
        self.truth_process_noise_std = float(truth_process_noise_std)
        if not (np.isfinite(self.truth_process_noise_std) and self.truth_process_noise_std >= 0):
            raise ValueError(f"bound.truth_process_noise_std: {truth_process_noise_std} must be a finite number >= 0")

    def information(self, truth: Truth, sensor) -> np.ndarray:
        """(K, 3, 3) E[H' R_p^-1 H] of the position over the runs, in (x, y, z)."""
        names = truth.state_names
        position = truth.state[:, :, 0, [names.index(a) for a in ("x", "y", "z")]] - np.asarray(sensor.position)
        r, phi, theta = line_of_sight_angles(position)
        polar_var = np.diag(sensor.noise_covariance)                                    # R_p = diag(range, az, el)
        converted = converted_covariance(np.stack([r, phi, theta], -1), polar_var)      # (R, K, 3, 3)
        return np.linalg.inv(converted).mean(axis=0)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) sqrt(trace) of the PCRLB position block of the truth's own process [m]."""
        dt = scan_interval(truth)
        K = truth.time.size
        F = np.kron(np.eye(3), np.array([[1.0, dt], [0.0, 1.0]]))                   # (x, vx, y, vy, z, vz)
        gain = np.array([[dt**2 / 2], [dt]])
        Q = self.truth_process_noise_std**2 * np.kron(np.eye(3), gain @ gain.T)
        position_info = self.information(truth, sensor)
        pos = [0, 2, 4]
        information = np.zeros((K, 6, 6))
        information[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]] = position_info
        R0, R1 = np.linalg.inv(position_info[0]), np.linalg.inv(position_info[1])
        _, initial = two_point_start(np.zeros(3), np.zeros(3), R0, R1, dt)          # filter A's start, no acceleration
        bounds = posterior_crlb(F, Q, initial, information[1:])                     # scans 1..K-1
        out = np.full(K, np.nan)
        out[1:] = np.sqrt(np.trace(bounds[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]], axis1=1, axis2=2))
        return out

    def position_bound_model(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) the same for a target of the filters' Singer model [m]."""
        dt = scan_interval(truth)
        K = truth.time.size
        F = np.kron(np.eye(3), singer_transition(dt, self.tau))                     # (x, vx, ax, y, ...)
        Q = np.kron(np.eye(3), singer_process_noise(dt, self.tau, self.sigma_m))
        position_info = self.information(truth, sensor)
        pos = [0, 3, 6]                                                             # (x, vx, ax, y, ...)
        information = np.zeros((K, 9, 9))
        information[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]] = position_info
        R0, R1 = np.linalg.inv(position_info[0]), np.linalg.inv(position_info[1])
        _, initial = two_point_start(np.zeros(3), np.zeros(3), R0, R1, dt, 3, self.sigma_m**2)   # filter A's start
        bounds = posterior_crlb(F, Q, initial, information[1:])                     # scans 1..K-1
        out = np.full(K, np.nan)
        out[1:] = np.sqrt(np.trace(bounds[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]], axis1=1, axis2=2))
        return out
