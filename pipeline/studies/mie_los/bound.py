"""Study 000's PCRLB (filters.bounds): the 3-D radar tracking a target of the filters' Singer model.

Study 000's truth is a deterministic profile, so the expectation over the true state in the
information term is exact (the mean over the runs is of identical values).
"""

from __future__ import annotations

import numpy as np

from filters.bounds import posterior_crlb
from filters.coordinates import converted_covariance, line_of_sight_angles
from filters.models import singer_process_noise, singer_transition, two_point_start
from pipeline.bounds import positive_parameter, scan_interval
from pipeline.data import Truth


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
        self.tau = positive_parameter("bound.tau", tau)
        self.sigma_m = positive_parameter("bound.sigma_m", sigma_m)

    def information(self, truth: Truth, sensor) -> np.ndarray:
        """(K, 3, 3) E[H' R_p^-1 H] of the position over the runs, in (x, y, z)."""
        names = truth.state_names
        position = truth.state[:, :, 0, [names.index(a) for a in ("x", "y", "z")]] - np.asarray(sensor.position)
        r, phi, theta = line_of_sight_angles(position)
        polar_var = np.diag(sensor.noise_covariance)                                    # R_p = diag(range, az, el)
        converted = converted_covariance(np.stack([r, phi, theta], -1), polar_var)      # (R, K, 3, 3)
        return np.linalg.inv(converted).mean(axis=0)

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
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
