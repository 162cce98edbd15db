"""Study 000's PCRLBs (filters.bounds): the 3-D radar tracking the truth's own process
(``position_bound``) and a target of the filters' Singer model (``position_bound_model``).

Study 000's truth is a deterministic profile, so the expectation over the true state in the
information term is exact (the mean over the runs is of identical values).
"""

from __future__ import annotations

import warnings

import numpy as np

from filters.bounds import SingularBoundWarning, posterior_crlb
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

    A converted covariance R_I that is singular in double precision (condition number >= 1/eps: a
    noise std of 0, the sensor's noise-free channel, or near it, ``sensors.range_std=1e-9`` against
    ~10^2 m cross-range) has no information matrix to work with: the bound is NaN from the first
    such scan on, with one SingularBoundWarning (logged by the runner), as filters.bounds does for a
    singular recursion (it used to end the job with ``LinAlgError: Singular matrix``).
    """

    def __init__(self, tau: float, sigma_m: float, truth_process_noise_std: float = 0.0) -> None:
        self.tau = positive_parameter("bound.tau", tau)
        self.sigma_m = positive_parameter("bound.sigma_m", sigma_m)
        self.truth_process_noise_std = float(truth_process_noise_std)
        if not (np.isfinite(self.truth_process_noise_std) and self.truth_process_noise_std >= 0):
            raise ValueError(f"bound.truth_process_noise_std: {truth_process_noise_std} must be a finite number >= 0")

    def information(self, truth: Truth, sensor) -> np.ndarray:
        """(K, 3, 3) E[H' R_p^-1 H] of the position over the runs, in (x, y, z): R_I^-1, NaN at a scan
        where R_I is singular in double precision (cond(R_I) >= 1/eps) in any run."""
        names = truth.state_names
        position = truth.state[:, :, 0, [names.index(a) for a in ("x", "y", "z")]] - np.asarray(sensor.position)
        r, phi, theta = line_of_sight_angles(position)
        polar_var = np.diag(sensor.noise_covariance)                                    # R_p = diag(range, az, el)
        converted = converted_covariance(np.stack([r, phi, theta], -1), polar_var)      # (R, K, 3, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            singular = ~(np.linalg.cond(converted) < 1.0 / np.finfo(float).eps)      # (R, K); NaN/inf too
        inverse = np.linalg.inv(np.where(singular[..., None, None], np.eye(3), converted))
        inverse[singular] = np.nan
        return inverse.mean(axis=0)

    def _bound(self, truth: Truth, sensor, F: np.ndarray, Q: np.ndarray, pos: list[int], kinematics: int,
               acceleration_variance: float) -> np.ndarray:
        """(K,) sqrt(trace) of the position block (state indices ``pos``) of the PCRLB of x(k+1) = F x(k)
        + w, w ~ N(0, Q), from filter A's two-point start (scans 0 and 1) [m]; NaN from a scan whose
        information is singular (``information``) on, said once."""
        K = truth.time.size
        position_info = self.information(truth, sensor)
        out = np.full(K, np.nan)
        regular = np.isfinite(position_info).all(axis=(1, 2))
        if not regular[:2].all():
            first = int(np.argmin(regular))
            warnings.warn(f"RadarSingerBound: the PCRLB is singular at scan {first} (the radar's converted covariance "
                          f"cannot be inverted in double precision: a noise std of 0 or near it, range/azimuth/"
                          f"elevation std {np.sqrt(np.diag(sensor.noise_covariance)).tolist()}); scans 0..{K - 1} are NaN",
                          SingularBoundWarning, stacklevel=3)
            return out
        n = F.shape[0]
        information = np.zeros((K, n, n))
        information[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]] = position_info      # NaN past a singular scan
        R0, R1 = np.linalg.inv(position_info[0]), np.linalg.inv(position_info[1])
        _, initial = two_point_start(np.zeros(3), np.zeros(3), R0, R1, scan_interval(truth), kinematics,
                                     acceleration_variance)                          # filter A's start
        bounds = posterior_crlb(F, Q, initial, information[1:])                     # scans 1..K-1
        out[1:] = np.sqrt(np.trace(bounds[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]], axis1=1, axis2=2))
        return out

    def position_bound(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) sqrt(trace) of the PCRLB position block of the truth's own process [m]."""
        dt = scan_interval(truth)
        F = np.kron(np.eye(3), np.array([[1.0, dt], [0.0, 1.0]]))                   # (x, vx, y, vy, z, vz)
        gain = np.array([[dt**2 / 2], [dt]])
        Q = self.truth_process_noise_std**2 * np.kron(np.eye(3), gain @ gain.T)
        return self._bound(truth, sensor, F, Q, [0, 2, 4], 2, 0.0)                  # no acceleration

    def position_bound_model(self, truth: Truth, sensor) -> np.ndarray:
        """(K,) the same for a target of the filters' Singer model [m]."""
        dt = scan_interval(truth)
        F = np.kron(np.eye(3), singer_transition(dt, self.tau))                     # (x, vx, ax, y, ...)
        Q = np.kron(np.eye(3), singer_process_noise(dt, self.tau, self.sigma_m))
        return self._bound(truth, sensor, F, Q, [0, 3, 6], 3, self.sigma_m**2)
