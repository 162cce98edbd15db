"""A Kalman-type tracker for every study whose sensor gives positions, radar polar measurements or sonar bearings.

Motion model, per Cartesian axis (Bar-Shalom, Li & Kirubarajan 2001, 6.2 and 8.2):

- ``cv``: (p, v), white acceleration noise of power spectral density ``acceleration_density``
  [m^2/s^3]: F = [[1, T], [0, 1]], Q = q [[T^3/3, T^2/2], [T^2/2, T]];
- ``singer``: (p, v, a), acceleration a first-order Markov process with time constant ``tau`` [s]
  and standard deviation ``sigma_m`` [m/s^2] (filters.models.singer_*);
- ``ca``: (p, v, a), nearly constant acceleration, white jerk of power spectral density
  ``jerk_density`` [m^2/s^5] (Bar-Shalom et al. 6.2.3, the Wiener-process acceleration model):
  F = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]], Q = q [[T^5/20, T^4/8, T^3/6], [T^4/8, T^3/3, T^2/2],
  [T^3/6, T^2/2, T]]; its acceleration starts at 0 with standard deviation ``sigma_m``.

Measurements, by kind (filters.base.MEASUREMENT_KINDS), all batched over the Monte Carlo runs:

- ``position_xy``: a linear Kalman filter, H picks the positions; missed scans are not updated.
- ``range_azimuth_elevation``: converted measurements z_c = polar_to_cartesian(z) + the sensor's
  position with R_c = J R_p J' at the measured point (filters.coordinates, notes 2.1 of study 000),
  then the same linear filter.
- ``sonar_bearing_range``: an EKF on the target's position and velocity relative to the own-ship,
  whose known acceleration enters as an input (filters.mgekf.relative_motion_model); the bearing
  atan2(x, y), and the range while the sonar is active, with the EKF Jacobian at the prediction
  (filters.mgekf.nonlinear_update with modified=False).

Start: two-point differencing on the first two (Cartesian) scans, p = z1, v = (z1 - z0)/T with
cov(p) = R1, cov(p, v) = R1/T, cov(v) = (R0 + R1)/T^2 (Bar-Shalom et al. 5.5.3; a Singer
acceleration starts at 0 with variance sigma_m^2); the sonar: the first (active) scan converted,
relative velocity minus the own-ship's with ``initial_velocity_std``. The estimate is NaN before.

Engines (Cartesian measurements): ``numba`` (the default) runs each run's scans in one compiled
loop (``filters.tracker.kernel.kalman_cartesian``); ``numpy`` filters all runs at once and is the
reference. They agree to rounding (that module says where they differ). The sonar EKF runs numpy.
Output: the state in the order the input names (``MeasurementSeries.state_names``: the layout of
the truth the study evaluates; for the sonar, filters.mgekf.STATE_NAMES), a component the motion
model lacks NaN with its covariance row and column (a reduced estimate); ``nis`` / ``nis_dof``
extras from each update's own innovation.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np

from filters.base import MeasurementSeries, TrackEstimate, checked_engine
from filters.compiling import compiling
from filters.kalman import einsum as kalman_einsum
from filters.kalman import predict, rows_times
from filters.coordinates import converted_covariance, polar_to_cartesian
from filters.mgekf import STATE_NAMES as SONAR_STATE_NAMES
from filters.mgekf import SonarReports, cv_relative_model, nonlinear_update, relative_motion_model, sonar_start
from filters.models import singer_process_noise, singer_transition, two_point_start
from filters.progress import counted, counted_runs

AXES = ("x", "y", "z")


class KalmanTracker:
    """A CV, Singer or CA Kalman filter (converted measurements) / EKF (sonar bearings); see the module docstring."""

    accepts = frozenset({"position_xy", "range_azimuth_elevation", "sonar_bearing_range"})

    def __init__(self, name: str = "KF", motion: Literal["cv", "singer", "ca"] = "singer", tau: float = 10.0,
                 sigma_m: float = 5.0, acceleration_density: float = 10.0, initial_velocity_std: float = 15.0,
                 jerk_density: float = 1.0, engine: str = "numba") -> None:
        if motion not in ("cv", "singer", "ca"):
            raise ValueError(f"motion: {motion!r} is not one of ['cv', 'singer', 'ca']")
        for key, value in (("tau", tau), ("sigma_m", sigma_m), ("acceleration_density", acceleration_density),
                           ("initial_velocity_std", initial_velocity_std), ("jerk_density", jerk_density)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{key}: {value} must be a finite number > 0")
        checked_engine(engine, "the compiled scan loop, filters/tracker/kernel.py")
        self.name = name
        self.engine = engine
        self.motion = motion
        self.tau, self.sigma_m = float(tau), float(sigma_m)
        self.acceleration_density = float(acceleration_density)
        self.initial_velocity_std = float(initial_velocity_std)
        self.jerk_density = float(jerk_density)

    # ---- model ----------------------------------------------------------------------------------
    @property
    def kinematics(self) -> int:
        return 2 if self.motion == "cv" else 3

    def axis_model(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F, Q of one Cartesian axis."""
        if self.motion == "cv":
            q = self.acceleration_density
            return (np.array([[1.0, dt], [0.0, 1.0]]),
                    q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]))
        if self.motion == "ca":
            q = self.jerk_density
            return (np.array([[1.0, dt, dt**2 / 2.0], [0.0, 1.0, dt], [0.0, 0.0, 1.0]]),
                    q * np.array([[dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
                                  [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
                                  [dt**3 / 6.0, dt**2 / 2.0, dt]]))
        return singer_transition(dt, self.tau), singer_process_noise(dt, self.tau, self.sigma_m)

    def state_names(self, axes: int) -> tuple[str, ...]:
        """Internal order: axis-major, (p, v[, a]) per axis."""
        kin = ("", "v", "a")[: self.kinematics]
        return tuple(f"{k}{a}" for a in AXES[:axes] for k in kin)

    # ---- run ------------------------------------------------------------------------------------
    RUNS_PER_CALL = 8       # of the compiled loop; progress is told between calls

    def run(self, measurements) -> TrackEstimate:
        if self.engine == "numba" and isinstance(measurements, MeasurementSeries):
            from filters.tracker import kernel as kalman_kernel
            with compiling("filters.tracker.kernel"):     # says so when numba compiles (the first job of an install)
                kalman_kernel.warm_up()         # numba's start before the clock: compute_seconds is the filtering's
        started = time.perf_counter()
        if isinstance(measurements, SonarReports):
            state, covariance, names, extras = self._run_sonar(measurements)
            wanted = SONAR_STATE_NAMES
        elif isinstance(measurements, MeasurementSeries):
            positions, noise, detected, dt = self._cartesian(measurements)
            state, covariance, extras = self._run_cartesian(positions, noise, detected, dt)
            names = self.state_names(positions.shape[-1])
            wanted = measurements.state_names or names
        else:
            raise TypeError(f"{self.name}: takes {sorted(self.accepts)} measurements, not {type(measurements).__name__}")
        state, covariance = to_layout(state, covariance, names, tuple(wanted))
        return TrackEstimate(np.asarray(measurements.time, dtype=float).copy(), state, covariance, extras,
                             time.perf_counter() - started)

    @staticmethod
    def _cartesian(m: MeasurementSeries) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(positions (R, K, d), their noise covariance (R, K, d, d), detected (R, K), scan period)."""
        if m.z.shape[1] < 3:
            raise ValueError("measurements: the two-point start needs at least 3 scans")
        dts = np.diff(m.time)
        if not np.allclose(dts, dts[0]):
            raise ValueError("measurements.time: the KalmanTracker needs a constant scan period")
        return (*cartesian_measurements(m), float(dts[0]))

    def _run_cartesian(self, z, noise, detected, dt):
        R, K, d = z.shape
        nk = self.kinematics
        n = d * nk
        F1, Q1 = self.axis_model(dt)
        F, Q = np.kron(np.eye(d), F1), np.kron(np.eye(d), Q1)
        pos = np.arange(d) * nk                                                   # p of each axis
        states = np.full((R, K, n), np.nan)
        covariances = np.full((R, K, n, n), np.nan)
        nis = np.full((R, K), np.nan)
        # two-point start at scan 1, with the two scans' own covariances
        x, P = two_point_start(z[:, 0], z[:, 1], noise[:, 0], noise[:, 1], dt, nk, self.sigma_m**2)
        states[:, 1], covariances[:, 1] = x, P
        if self.engine == "numba":
            from filters.tracker import kernel as kalman_kernel
            # C-contiguous and writeable, as warm_up compiled it (read-only measurements are another numba type)
            inputs = [np.require(a, requirements=("C", "W")) for a in (z, noise, detected, F, Q)]
            start = [np.require(a, requirements=("C", "W")) for a in (x, P)]
            for first, stop in counted_runs(R, max(K - 2, 0), self.name, self.RUNS_PER_CALL):
                kalman_kernel.kalman_cartesian(first, stop, *inputs, nk, *start, states, covariances, nis)
            return states, covariances, {"nis": nis, "nis_dof": np.where(np.isfinite(nis), float(d), 0.0)}
        for k in counted(range(2, K), "scan", self.name):
            # per-run products only (filters.kalman): a 2-D x @ F' over the runs is one BLAS call whose
            # rounding depends on how many runs share it, and einsum's on its operands' strides
            x, P = predict(x, P, F, Q)
            PHt = P[:, :, pos]                                                    # (R, n, d)
            S = PHt[:, pos, :] + noise[:, k]
            nu = np.where(detected[:, k, None], z[:, k] - x[:, pos], 0.0)
            # one solve for the gain K = P H' S^-1 and for S^-1 nu (the NIS)
            solved = np.linalg.solve(S, np.concatenate([np.swapaxes(PHt, 1, 2), nu[..., None]], axis=-1))
            gain, s_nu = np.swapaxes(solved[..., :n], 1, 2), solved[..., n]
            seen = detected[:, k]
            x = x + kalman_einsum("rij,rj->ri", gain, nu)
            updated = P - gain @ np.swapaxes(PHt, 1, 2)
            P = np.where(seen[:, None, None], 0.5 * (updated + np.swapaxes(updated, 1, 2)), P)
            nis[:, k] = np.where(seen, kalman_einsum("ri,ri->r", nu, s_nu), np.nan)
            states[:, k], covariances[:, k] = x, P
        return states, covariances, {"nis": nis, "nis_dof": np.where(np.isfinite(nis), float(d), 0.0)}

    def _run_sonar(self, reports: SonarReports):
        if self.motion == "ca":
            raise ValueError("motion: 'ca' takes positions or radar measurements; the sonar EKF takes 'cv' or 'singer'")
        R, K, _ = reports.z.shape
        n = 4 if self.motion == "cv" else 6
        names = SONAR_STATE_NAMES[:n]
        x, P = sonar_start(reports, n, self.initial_velocity_std, self.sigma_m)
        states = np.full((R, K, n), np.nan)
        covariances = np.full((R, K, n, n), np.nan)
        nis = np.full((R, K), np.nan)
        states[:, 0], covariances[:, 0] = x, P
        models = {}
        for k in counted(range(1, K), "scan", self.name):
            dt = float(reports.time[k] - reports.time[k - 1])
            if dt not in models:
                models[dt] = (cv_relative_model(dt, self.acceleration_density) if n == 4
                              else relative_motion_model(dt, self.tau, self.sigma_m))
            Phi, Gamma, Q = models[dt]
            x, P = predict(x, P, Phi, Q, offset=rows_times(reports.ownship_acceleration[:, k - 1], Gamma.T))
            x, P, nis[:, k] = nonlinear_update(x, P, reports.z[:, k], bool(reports.active[k]), reports.bearing_std,
                                               reports.range_std, modified=False, return_nis=True)
            states[:, k], covariances[:, k] = x, P
        dof = np.where(reports.active, 2.0, 1.0)[None, :] * np.isfinite(nis)
        return states, covariances, names, {"nis": nis, "nis_dof": dof}


def cartesian_measurements(m: MeasurementSeries) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A series' detections as Cartesian positions (R, K, d) [m] with their noise covariance
    (R, K, d, d) and ``detected`` (R, K): x, y as given; range, azimuth, elevation converted,
    z_c = polar_to_cartesian(z) + the sensor's position with R_c = J R_p J' at the measured point
    (filters.coordinates, notes 2.1 of study 000). NaN positions where not detected. Refuses a series
    whose first two scans are not all detected (the two-point start needs them)."""
    z = np.asarray(m.z, dtype=float)
    R, K, d = z.shape
    noise = np.asarray(m.noise_covariance, dtype=float)
    noise = np.broadcast_to(noise, (R, K, d, d)) if noise.ndim == 2 else noise
    detected = np.asarray(m.detected, dtype=bool)
    if not detected[:, :2].all():
        raise ValueError("measurements: the two-point start needs detections at the first two scans of every run")
    if d == 3:
        variances = np.diagonal(noise, axis1=-2, axis2=-1)
        converted = polar_to_cartesian(np.where(detected[..., None], z, 1.0))
        offset = np.zeros(3) if m.sensor_position is None else np.asarray(m.sensor_position, dtype=float)
        positions = np.where(detected[..., None], converted + offset, np.nan)
        noise = converted_covariance(np.where(detected[..., None], z, 1.0), variances)
        return positions, noise, detected
    if d != 2:
        raise ValueError(f"measurements.z: {d} values per scan; a Cartesian tracker takes 2 (x, y) or 3 "
                         f"(range, azimuth, elevation)")
    return z, noise, detected


def to_layout(state: np.ndarray, covariance: np.ndarray, names: tuple[str, ...], wanted: tuple[str, ...]
              ) -> tuple[np.ndarray, np.ndarray]:
    """The estimate in the order ``wanted``; a wanted component not in ``names`` is NaN, with NaN
    covariance row and column (a reduced estimate)."""
    if tuple(names) == tuple(wanted):
        return state, covariance
    index = np.array([names.index(w) if w in names else -1 for w in wanted])
    have = index >= 0
    safe = np.where(have, index, 0)
    out_x = np.where(have, state[..., safe], np.nan)
    out_P = covariance[..., safe[:, None], safe[None, :]]
    out_P = np.where(have[:, None] & have[None, :], out_P, np.nan)
    return out_x, out_P
