"""Active/passive sonar tracking with the modified gain EKF (seed 003; Song & Speyer 1985).

The seed lost almost all of its equations; they are restated here from Song & Speyer's MGEKF
(IEEE TAC 30(10), 1985), Song & Um's relative-motion model (IEEE T-AES 32(1), 1996) and the
seed's words, following the literature notes, section 3. Equation numbers in brackets are the
seed's, where its text says which equation a piece is.

Model (seed eqs 1-3, 6-7). Relative state x = (rx, ry, vx, vy, ax, ay): target minus own-ship
position and velocity, and the target's acceleration, a first-order Markov process with time
constant tau (lambda = 1/tau "assumed constant"). Own-ship acceleration u is a known input::

    x(k+1) = Phi x(k) + Gamma_u u(k) + w(k),  Phi = kron(F_Singer(dt, tau), I2),
    Gamma_u = -[dt^2/2 I2; dt I2; 0],  Q = kron(Q_Singer(dt, tau, sigma_m), I2)

(per-axis Singer blocks in the order position, velocity, acceleration; ``relative_motion_model``).

Measurements (seed eqs 4-5, 15), bearing from north clockwise, x east, y north::

    beta = atan2(rx, ry) + v_beta          (passive and active)
    r    = hypot(rx, ry) + v_r             (active only)

MGEKF (seed eqs 18-22 for the active case; Song & Speyer for bearings). The function h is
*modifiable* (seed eq 13, theorem 1): h(x) - h(x_hat) = g(z, x_hat) (x - x_hat), with g depending
on the true state only through the measurement. The gain is the EKF's; only the covariance update
uses g evaluated with the measured bearing::

    K = P H' (H P H' + R)^-1,  H = dh/dx at x_hat(k|k-1)
    x_hat(k|k) = x_hat(k|k-1) + K [z - h(x_hat(k|k-1))]        (bearing residual wrapped)
    P(k|k) = (I - K g) P(k|k-1) (I - K g)' + K R K'

g-rows (position columns; zeros for velocity and acceleration), with delta = wrap(beta_m - beta_hat):

- bearing, Song & Speyer's "tan" form: g = [cos beta_m, -sin beta_m] / (x_hat sin beta_m + y_hat cos beta_m),
  exact for tan(beta - beta_hat); the denominator equals r_hat cos(delta) and is clamped at
  ``clamp`` r_hat in magnitude (spec 003) so the filter stays finite near own-ship.
  ``bearing_row="exact"``: (delta / (r_hat sin delta)) [cos beta_m, -sin beta_m], exact for beta - beta_hat.
- range, theorem 1 (the seed's A = BC factorisation): r - r_hat = [sin beta_bar, cos beta_bar] (p - p_hat) / cos(delta/2),
  beta_bar = (beta_m + beta_hat)/2, exact when beta_m is the true bearing.

The KF + MGEKF architecture runs, while the sonar is active, a linear Kalman filter on the
relative position and velocity only (4 states, white-acceleration noise of PSD 2 sigma_m^2 tau)
with converted measurements z_c = r_m [sin beta_m, cos beta_m], R_c = J diag(s_beta^2, s_r^2) J'
at the measured values (notes 3.3), and the MGEKF while it is passive. At an active -> passive
switch the KF's estimate is padded with the acceleration states: zero mean, variance
``handover_acceleration_variance`` per axis, no cross-covariance (the KF never estimated them);
at passive -> active the acceleration states are dropped. That structural mismatch is what the
seed blames for its fluctuations; the spec found the effect hangs on the padding variance.

Assumed where the seed is silent (spec 003): the filter starts at the first scan (active) with
the converted position and its covariance, relative velocity = -own-ship velocity (target
velocity unknown, zero mean) with ``initial_velocity_std`` per axis, and target acceleration
zero with variance sigma_m^2.

Engines: ``engine="numba"`` (the default) runs each run's scans in one compiled loop
(filters/mgekf/kernel.py): 0.37-0.48 s against 1.9-2.6 s for the numpy scans per tracker on case 2's
100 runs x 10 001 scans (benchmarks/bench_study003.py), of which ~0.28 s is the loop and the rest
filling the (R, K, 6, 6) output. ``engine="numpy"`` is the vectorised scan loop below, the reference. They agree to rounding (~1e-11 of each state's RMS over
a 10 001-scan run; tests/test_mgekf_kernel.py), a run's numbers do not depend on its batch in either.

Consistency (beyond the paper): ``run`` exports each scan's normalised innovation squared
nu' S^-1 nu as ``extras["nis"]`` (R, K), with ``extras["nis_dof"]`` its dof, from the innovation
the update itself used: the wrapped bearing residual with s = h P h' + sigma_beta^2 (1 dof,
passive); bearing and range with S = H P H' + R (2 dof, active MGEKF / EKF); the converted-
measurement KF's Cartesian z_c - (x, y) with S = P_xy + R_c (2 dof). S is the EKF's for MGEKF too:
the modified row g changes only P(k|k). NaN at the first scan (it starts the filter).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, replace

import numpy as np

from filters.base import TrackEstimate, checked_engine
from filters.compiling import compiling
from filters.kalman import einsum, rows_times, shared_times, times_shared
from filters.models import singer_process_noise, singer_transition
from filters.progress import counted, current

STATE_NAMES = ("x", "y", "vx", "vy", "ax", "ay")


# --------------------------------------------------------------------------------------------
# Model (seed eqs 1-3, 6-7)
# --------------------------------------------------------------------------------------------

def relative_motion_model(dt: float, tau: float, sigma_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phi (6, 6), Gamma_u (6, 2), Q (6, 6) of the relative state (rx, ry, vx, vy, ax, ay)."""
    I2 = np.eye(2)
    Phi = np.kron(singer_transition(dt, tau), I2)
    Q = np.kron(singer_process_noise(dt, tau, sigma_m), I2)
    Gamma = -np.vstack([dt * dt / 2.0 * I2, dt * I2, np.zeros((2, 2))])
    return Phi, Gamma, Q


def cv_relative_model(dt: float, density: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 4-state KF's model (rx, ry, vx, vy): CV with white acceleration of PSD ``density``."""
    I2 = np.eye(2)
    Phi = np.kron(np.array([[1.0, dt], [0.0, 1.0]]), I2)
    Q = density * np.kron(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]), I2)
    Gamma = -np.vstack([dt * dt / 2.0 * I2, dt * I2])
    return Phi, Gamma, Q


def wrap(angle: np.ndarray) -> np.ndarray:
    """Into (-pi, pi]."""
    w = np.mod(angle + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def bearing_range(position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) relative (east, north) -> bearing from north clockwise, range."""
    return np.arctan2(position[..., 0], position[..., 1]), np.hypot(position[..., 0], position[..., 1])


# --------------------------------------------------------------------------------------------
# Jacobians and modifiable g-rows (seed eqs 13-17, 23-24)
# --------------------------------------------------------------------------------------------

def jacobian_rows(position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """EKF rows over (x, y): d beta = [y, -x]/r^2, d r = [x, y]/r; each (..., 2)."""
    x, y = position[..., 0], position[..., 1]
    r2 = x * x + y * y
    r = np.sqrt(r2)
    return np.stack([y / r2, -x / r2], -1), np.stack([x / r, y / r], -1)


def bearing_g_row(position: np.ndarray, measured_bearing: np.ndarray, form: str = "tan",
                  clamp: float = 0.1) -> np.ndarray:
    """The bearing's modifiable row over (x, y) (Song & Speyer), with the measured bearing."""
    s, c = np.sin(measured_bearing), np.cos(measured_bearing)
    direction = np.stack([c, -s], -1)
    r_hat = np.hypot(position[..., 0], position[..., 1])
    if form == "tan":
        denominator = position[..., 0] * s + position[..., 1] * c          # = r_hat cos(delta)
        floor = clamp * r_hat
        denominator = np.where(np.abs(denominator) < floor, np.where(denominator < 0, -floor, floor), denominator)
        return direction / denominator[..., None]
    delta = wrap(measured_bearing - bearing_range(position)[0])
    ratio = np.where(np.abs(delta) < 1e-8, 1.0, delta / np.where(delta == 0, 1.0, np.sin(delta)))
    return direction * (ratio / r_hat)[..., None]


def range_g_row(position: np.ndarray, measured_bearing: np.ndarray) -> np.ndarray:
    """Theorem 1's row: r - r_hat = [sin b, cos b] (p - p_hat) / cos(delta/2), b = (beta_m + beta_hat)/2."""
    beta_hat = bearing_range(position)[0]
    delta = wrap(measured_bearing - beta_hat)
    mean = beta_hat + 0.5 * delta
    return np.stack([np.sin(mean), np.cos(mean)], -1) / np.cos(0.5 * delta)[..., None]


# --------------------------------------------------------------------------------------------
# Updates, batched over the leading axes
# --------------------------------------------------------------------------------------------

def _pad(rows: np.ndarray, n: int) -> np.ndarray:
    """(..., m, 2) rows over (x, y) -> (..., m, n) over the whole state."""
    out = np.zeros(rows.shape[:-1] + (n,))
    out[..., :2] = rows
    return out


def nonlinear_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, active: bool, bearing_std: float,
                     range_std: float, modified: bool = True, bearing_form: str = "tan", clamp: float = 0.1,
                     return_nis: bool = False) -> tuple[np.ndarray, ...]:
    """One MGEKF (``modified``) or EKF update with bearing (and range when ``active``).

    x (R, n), P (R, n, n), z (R, 2) = (bearing, range). The gain uses the EKF Jacobian at the
    prediction; the MGEKF's covariance update uses the g-rows with the measured bearing.
    ``return_nis``: also return (R,) nu' S^-1 nu of the innovation the gain used (bearing wrapped;
    S = H P H' + R with the EKF Jacobian, the same for MGEKF and EKF: g enters only P(k|k)).
    """
    if not active:                                   # bearing only: scalar algebra, no matrix solves
        return _bearing_only_update(x, P, z[..., 0], bearing_std**2, modified, bearing_form, clamp, return_nis)
    n = x.shape[-1]
    position = x[..., :2]
    beta_hat, r_hat = bearing_range(position)
    d_beta, d_r = jacobian_rows(position)                      # active: bearing and range (eqs 20-24)
    H = _pad(np.stack([d_beta, d_r], -2), n)
    residual = np.stack([wrap(z[..., 0] - beta_hat), z[..., 1] - r_hat], -1)
    R = np.diag([bearing_std**2, range_std**2])
    PHt = P @ np.swapaxes(H, -1, -2)
    S = H @ PHt + R
    gain = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
    x_new = x + einsum("rij,rj->ri", gain, residual)
    if modified:
        G = _pad(np.stack([bearing_g_row(position, z[..., 0], bearing_form, clamp),
                           range_g_row(position, z[..., 0])], -2), n)
    else:
        G = H
    A = np.broadcast_to(np.eye(n), P.shape) - gain @ G
    P_new = A @ P @ np.swapaxes(A, -1, -2) + gain @ R @ np.swapaxes(gain, -1, -2)   # Joseph form
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    if return_nis:
        return x_new, P_new, innovation_nis(residual, S)
    return x_new, P_new


def innovation_nis(innovation: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(R, m) innovations nu and (R, m, m) covariances S -> (R,) nu' S^-1 nu (chi-square, m dof, for a
    consistent filter)."""
    return einsum("ri,ri->r", innovation, np.linalg.solve(S, innovation[..., None])[..., 0])


def _bearing_only_update(x: np.ndarray, P: np.ndarray, bearing: np.ndarray, variance: float, modified: bool,
                         form: str, clamp: float, return_nis: bool = False) -> tuple[np.ndarray, ...]:
    """The passive (bearing-only) MGEKF / EKF update written out for one scalar measurement whose
    Jacobian h and modifiable row g touch only (x, y): K = P h' / s, and the Joseph form
    (I - K g) P (I - K g)' + K r K' expanded into outer products. The same algebra as the matrix
    form of ``nonlinear_update`` (tested equal), in a handful of vector operations per scan: the
    trackers spend ~85 % of their scans here. ``return_nis``: also the (R,) residual^2 / s, the
    scalar NIS of the wrapped bearing residual (1 dof)."""
    px, py = x[:, 0], x[:, 1]
    r2 = px * px + py * py
    h0, h1 = py / r2, -px / r2                                            # d beta / d(x, y)
    if not modified:
        g0, g1 = h0, h1
    elif form == "tan":
        s, c = np.sin(bearing), np.cos(bearing)
        denominator = px * s + py * c                                      # r_hat cos(delta)
        floor = clamp * np.sqrt(r2)
        denominator = np.where(np.abs(denominator) < floor, np.where(denominator < 0, -floor, floor), denominator)
        g0, g1 = c / denominator, -s / denominator
    else:
        g0, g1 = np.moveaxis(bearing_g_row(x[:, :2], bearing, form, clamp), -1, 0)
    residual = wrap(bearing - np.arctan2(px, py))
    PHt = P[:, :, 0] * h0[:, None] + P[:, :, 1] * h1[:, None]
    innovation_variance = PHt[:, 0] * h0 + PHt[:, 1] * h1 + variance        # s = h P h' + r
    gain = PHt / innovation_variance[:, None]
    x_new = x + gain * residual[:, None]
    gP = g0[:, None] * P[:, 0, :] + g1[:, None] * P[:, 1, :]
    gPg = gP[:, 0] * g0 + gP[:, 1] * g1
    cross = gain[:, :, None] * gP[:, None, :]
    P_new = P - cross - np.swapaxes(cross, -1, -2) + ((gPg + variance)[:, None] * gain)[:, :, None] * gain[:, None, :]
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    if return_nis:
        return x_new, P_new, residual * residual / innovation_variance
    return x_new, P_new


def converted_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, bearing_std: float, range_std: float,
                     return_nis: bool = False) -> tuple[np.ndarray, ...]:
    """Linear KF update on the converted active measurement r [sin beta, cos beta] (notes 3.3).

    ``return_nis``: also the (R,) NIS of the KF's own 2-D Cartesian innovation z_c - (x, y) with
    S = P_xy + R_c (R_c at the measured values, as the gain uses it)."""
    n = x.shape[-1]
    beta, r = z[..., 0], z[..., 1]
    converted = np.stack([r * np.sin(beta), r * np.cos(beta)], -1)
    J = np.stack([np.stack([r * np.cos(beta), np.sin(beta)], -1),
                  np.stack([-r * np.sin(beta), np.cos(beta)], -1)], -2)          # d(x, y)/d(beta, r)
    R = J @ np.diag([bearing_std**2, range_std**2]) @ np.swapaxes(J, -1, -2)
    H = np.zeros((2, n))
    H[:, :2] = np.eye(2)
    PHt = P[..., :, :2]
    S = P[..., :2, :2] + R
    gain = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
    innovation = converted - x[..., :2]
    x_new = x + einsum("rij,rj->ri", gain, innovation)
    A = np.broadcast_to(np.eye(n), P.shape) - gain @ H
    P_new = A @ P @ np.swapaxes(A, -1, -2) + gain @ R @ np.swapaxes(gain, -1, -2)
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    if return_nis:
        return x_new, P_new, innovation_nis(innovation, S)
    return x_new, P_new


# --------------------------------------------------------------------------------------------
# Inputs and the architectures
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SonarReports:
    """What the sonar trackers consume, batched over R runs and K scans (one per dt).

    time (K,); z (R, K, 2) measured (bearing [rad], range [m]; range NaN when passive);
    active (K,) bool; ownship_acceleration (R, K, 2) the known own-ship input u(k), held over
    [t_k, t_k+1); ownship_velocity0 (R, 2) own-ship velocity at the first scan; bearing_std [rad],
    range_std [m].
    """

    time: np.ndarray
    z: np.ndarray
    active: np.ndarray
    ownship_acceleration: np.ndarray
    ownship_velocity0: np.ndarray
    bearing_std: float
    range_std: float

    def __post_init__(self) -> None:
        K = self.time.shape[0]
        R = self.z.shape[0]
        if self.z.shape != (R, K, 2) or self.active.shape != (K,) or self.ownship_acceleration.shape != (R, K, 2):
            raise ValueError(f"SonarReports: z {self.z.shape}, active {self.active.shape} and ownship_acceleration "
                             f"{self.ownship_acceleration.shape} must be (R, K, 2), (K,), (R, K, 2)")
        if K < 2 or not bool(self.active[0]):
            raise ValueError("SonarReports: the trackers start from an active (range + bearing) first scan")
        if np.any(np.diff(self.time) <= 0):
            raise ValueError("SonarReports: scan times must increase")

    @property
    def runs(self) -> int:
        return self.z.shape[0]

    def select(self, runs) -> "SonarReports":
        """The same scans for a subset of runs (a chunk of the Monte Carlo)."""
        index = np.asarray(runs, dtype=int)
        return replace(self, z=self.z[index], ownship_acceleration=self.ownship_acceleration[index],
                       ownship_velocity0=self.ownship_velocity0[index])


def sonar_start(reports: SonarReports, n: int, initial_velocity_std: float, sigma_m: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """State (R, n) and covariance after the first (active) scan of the relative state (n = 4 or 6):
    the converted position with J diag(sigma_b^2, sigma_r^2) J', the relative velocity minus the
    own-ship's (the target's own unknown: zero mean, ``initial_velocity_std``), acceleration 0 with
    variance ``sigma_m``^2."""
    R = reports.z.shape[0]
    beta, r = reports.z[:, 0, 0], reports.z[:, 0, 1]
    x = np.zeros((R, n))
    x[:, 0], x[:, 1] = r * np.sin(beta), r * np.cos(beta)
    x[:, 2:4] = -reports.ownship_velocity0                 # target velocity unknown: zero mean
    J = np.stack([np.stack([r * np.cos(beta), np.sin(beta)], -1),
                  np.stack([-r * np.sin(beta), np.cos(beta)], -1)], -2)
    P = np.zeros((R, n, n))
    P[:, :2, :2] = J @ np.diag([reports.bearing_std**2, reports.range_std**2]) @ np.swapaxes(J, -1, -2)
    P[:, 2:4, 2:4] = initial_velocity_std**2 * np.eye(2)
    if n == 6:
        P[:, 4:, 4:] = sigma_m**2 * np.eye(2)
    return x, P


class _SonarTracker:
    """Shared set-up of the architectures; see the module docstring for the model."""

    accepts = frozenset({"sonar_bearing_range"})

    def __init__(self, name: str, tau: float = 60.0, sigma_m: float = 0.01, initial_velocity_std: float = 15.0,
                 bearing_row: str = "tan", clamp: float = 0.1, engine: str = "numba") -> None:
        for key, value in (("tau", tau), ("sigma_m", sigma_m), ("initial_velocity_std", initial_velocity_std)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{key}: {value} must be a finite number > 0")
        if bearing_row not in ("tan", "exact"):
            raise ValueError(f"bearing_row: {bearing_row!r} is not allowed; use 'tan' (Song & Speyer) or 'exact'")
        if not (0 < clamp < 1):
            raise ValueError(f"clamp: {clamp} must be in (0, 1): the bearing row's denominator floor as a "
                             f"fraction of the range")
        checked_engine(engine, "the compiled scan loop, filters/mgekf/kernel.py")
        self.engine = engine
        self.name = name
        self.tau = float(tau)
        self.sigma_m = float(sigma_m)
        self.initial_velocity_std = float(initial_velocity_std)
        self.bearing_row = bearing_row
        self.clamp = float(clamp)

    def _start(self, reports: SonarReports, n: int) -> tuple[np.ndarray, np.ndarray]:
        return sonar_start(reports, n, self.initial_velocity_std, self.sigma_m)

    def _models(self, dt: float):
        return relative_motion_model(dt, self.tau, self.sigma_m), cv_relative_model(
            dt, 2.0 * self.sigma_m**2 * self.tau)

    def run(self, reports: SonarReports) -> TrackEstimate:
        if self.engine == "numba":
            return self._run_compiled(reports)
        started = _time.perf_counter()
        K = reports.time.shape[0]
        states, covariances, nis = self._outputs(reports)
        x, P = self._first(reports)
        self._store(states, covariances, 0, x, P)
        steps = np.diff(reports.time)
        models = {}
        for k in counted(range(1, K), "scan", self.name):
            dt = float(steps[k - 1])
            if dt not in models:
                models[dt] = self._models(dt)
            x, P, nis[:, k] = self._step(x, P, reports, k, models[dt])
            self._store(states, covariances, k, x, P)
        return self._estimate(reports, states, covariances, nis, started)

    @staticmethod
    def _outputs(reports: SonarReports) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """States (R, K, 6), covariances (R, K, 6, 6) and the NIS of each scan's update (R, K)
        (evaluate.nis_metrics), NaN until a scan fills them: the KF's 4-state scans leave the
        acceleration entries NaN, and the first scan, which starts the filter, has no innovation."""
        R, K, _ = reports.z.shape
        return np.full((R, K, 6), np.nan), np.full((R, K, 6, 6), np.nan), np.full((R, K), np.nan)

    @staticmethod
    def _estimate(reports: SonarReports, states, covariances, nis, started: float) -> TrackEstimate:
        """The estimate with its extras: the NIS's dof is 2 (bearing + range, or the converted x, y)
        when active, 1 (bearing) when passive, NaN at the first scan."""
        R, K, _ = reports.z.shape
        nis_dof = np.where(reports.active, 2.0, 1.0)
        nis_dof[0] = np.nan
        extras = {"active": np.broadcast_to(reports.active.astype(np.int8), (R, K)).copy(),
                  "nis": nis, "nis_dof": np.broadcast_to(nis_dof, (R, K)).copy()}
        return TrackEstimate(reports.time.copy(), states, covariances, extras, _time.perf_counter() - started)

    # the compiled loop's architecture code, whether its 6-state updates use the g-rows (set by each class)
    _architecture: int = 0
    modified: bool = True
    SCANS_PER_CALL = 500          # progress is told between calls (~1000 calls of the numpy loop's scans)

    def _run_compiled(self, reports: SonarReports) -> TrackEstimate:
        """``run`` through filters.mgekf.kernel.track_block: the same model and updates, each run's scans
        in one compiled loop (see that module for what differs from the numpy scans: rounding)."""
        from filters.mgekf import kernel as mgekf_kernel

        with compiling("filters.mgekf.kernel"):     # says so when numba compiles (the first job of an install)
            mgekf_kernel.warm_up()                  # numba's start before the clock: compute_seconds is the filtering's
        started = _time.perf_counter()
        R, K, _ = reports.z.shape
        states, covariances, nis = self._outputs(reports)
        x0, P0 = self._first(reports)
        n = x0.shape[-1]
        self._store(states, covariances, 0, x0, P0)
        x, P = np.zeros((R, 6)), np.zeros((R, 6, 6))
        x[:, :n], P[:, :n, :n] = x0, P0
        # the models of each distinct dt, as the numpy loop builds them, and which one each scan uses
        steps = np.diff(reports.time)
        distinct: dict[float, int] = {}
        model_of_step = np.array([distinct.setdefault(float(dt), len(distinct)) for dt in steps], dtype=np.int64)
        built = [self._models(dt) for dt in distinct]
        six = [np.ascontiguousarray(np.stack([m[0][i] for m in built])) for i in range(3)]
        four = [np.ascontiguousarray(np.stack([m[1][i] for m in built])) for i in range(3)]
        z, u, active = (mgekf_kernel.read_only(a, dtype) for a, dtype in (
            (reports.z, float), (reports.ownship_acceleration, float), (reports.active, np.bool_)))
        form = mgekf_kernel.TAN if self.bearing_row == "tan" else mgekf_kernel.EXACT
        handover = float(getattr(self, "handover_acceleration_variance", 0.0))
        progress = current()
        progress.start(K - 1, "scan", self.name)
        for first in range(1, K, self.SCANS_PER_CALL):
            stop = min(K, first + self.SCANS_PER_CALL)
            mgekf_kernel.track_block(first, stop, n, self._architecture, self.modified, form, self.clamp,
                                     reports.bearing_std**2, reports.range_std**2, handover, z, active, u,
                                     model_of_step, *six, *four, x, P, states, covariances, nis)
            if self._architecture == mgekf_kernel.KF_PLUS_MGEKF:
                n = 4 if active[stop - 1] else 6
            progress.advance(stop - first)
        return self._estimate(reports, states, covariances, nis, started)

    @staticmethod
    def _store(states, covariances, k, x, P) -> None:
        n = x.shape[-1]
        states[:, k, :n] = x
        covariances[:, k, :n, :n] = P

    @staticmethod
    def _predict(x, P, u, model):
        Phi, Gamma, Q = model
        return rows_times(x, Phi.T) + rows_times(u, Gamma.T), shared_times(Phi, times_shared(P, Phi.T)) + Q


class OnlyMGEKF(_SonarTracker):
    """The seed's proposal: one 6-state MGEKF throughout, range + bearing when active (theorem 1),
    bearing when passive. ``modified=False`` is the plain EKF on the same model (beyond the paper)."""

    modified = True

    def __init__(self, name: str = "only MGEKF", **kwargs) -> None:
        super().__init__(name, **kwargs)

    def _first(self, reports):
        return self._start(reports, 6)

    def _step(self, x, P, reports, k, models):
        x, P = self._predict(x, P, reports.ownship_acceleration[:, k - 1], models[0])
        return nonlinear_update(x, P, reports.z[:, k], bool(reports.active[k]), reports.bearing_std,
                                reports.range_std, self.modified, self.bearing_row, self.clamp, return_nis=True)


class PlainEKF(OnlyMGEKF):
    """A plain EKF on the 6-state model with the same measurements (reference, beyond the paper)."""

    modified = False

    def __init__(self, name: str = "EKF", **kwargs) -> None:
        super().__init__(name, **kwargs)


class KFPlusMGEKF(_SonarTracker):
    """The seed's baseline: a 4-state converted-measurement KF while active, the 6-state MGEKF while
    passive, handing (x, P) over at each switch.

    ``handover_acceleration_variance``: the variance [(m/s^2)^2] given to each padded acceleration
    state at an active -> passive switch; "consistent" uses the model's sigma_m^2. Spec 003's two
    reported settings are 0.1 (paper-like: "unknown, broad") and "consistent"; 1 or more makes runs
    diverge and is refused.
    """

    _architecture = 1             # filters.mgekf.kernel.KF_PLUS_MGEKF

    def __init__(self, name: str = "KF + MGEKF", handover_acceleration_variance: float | str = 0.1, **kwargs) -> None:
        super().__init__(name, **kwargs)
        if handover_acceleration_variance == "consistent":
            variance = self.sigma_m**2
        else:
            try:
                variance = float(handover_acceleration_variance)
            except (TypeError, ValueError):
                variance = float("nan")
            if not (np.isfinite(variance) and 0 < variance < 1.0):
                raise ValueError(f"handover_acceleration_variance: {handover_acceleration_variance!r} must be "
                                 f"'consistent' (sigma_m^2) or a variance in (0, 1) (m/s^2)^2; 1 or more makes the "
                                 f"MGEKF diverge after the hand-over (spec 003)")
        self.handover_acceleration_variance = variance

    def _first(self, reports):
        return self._start(reports, 4)

    def _step(self, x, P, reports, k, models):
        six, four = models
        active, was_active = bool(reports.active[k]), bool(reports.active[k - 1])
        if was_active and not active:                    # KF -> MGEKF: pad the acceleration states
            x, P = pad_acceleration(x, P, self.handover_acceleration_variance)
        elif active and not was_active:                  # MGEKF -> KF: drop them
            x, P = x[:, :4].copy(), P[:, :4, :4].copy()
        if active:
            x, P = self._predict(x, P, reports.ownship_acceleration[:, k - 1], four)
            return converted_update(x, P, reports.z[:, k], reports.bearing_std, reports.range_std, return_nis=True)
        x, P = self._predict(x, P, reports.ownship_acceleration[:, k - 1], six)
        return nonlinear_update(x, P, reports.z[:, k], False, reports.bearing_std, reports.range_std, True,
                                self.bearing_row, self.clamp, return_nis=True)


def pad_acceleration(x: np.ndarray, P: np.ndarray, variance: float) -> tuple[np.ndarray, np.ndarray]:
    """(x4, P4) -> (x6, P6): acceleration zero mean, ``variance`` per axis, no cross-covariance."""
    R = x.shape[0]
    x6 = np.zeros((R, 6))
    x6[:, :4] = x
    P6 = np.zeros((R, 6, 6))
    P6[:, :4, :4] = P
    P6[:, 4:, 4:] = variance * np.eye(2)
    return x6, P6
