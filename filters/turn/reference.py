"""The air-traffic baseline: an IMM of a constant-velocity (CV) and a coordinated-turn (CT) model
with unknown turn rate (Bar-Shalom, Li & Kirubarajan 2001, "Estimation with Applications to
Tracking and Navigation", 11.7; IMM 11.6.6), in 3-D with a CV vertical channel.

State (both modes, so that they mix): ``(x, vx, y, vy, z, vz, omega)`` from range/azimuth/elevation,
``(x, vx, y, vy, omega)`` from 2-D positions; omega [rad/s] is the horizontal turn rate, > 0
counter-clockwise (from +x toward +y).

CT model (11.7.1 with omega a state, 11.7.2), over a scan of length T, with a = sin(wT)/w and
b = (1 - cos wT)/w::

    x'  = x + a vx - b vy          vx' = cos(wT) vx - sin(wT) vy
    y'  = y + b vx + a vy          vy' = sin(wT) vx + cos(wT) vy
    z'  = z + T vz                 vz' = vz                        w' = w

a point moves along the exact circle of radius |v|/|w|. Its EKF Jacobian is the CT transition
F_CT(w) with the omega column (da = d a/dw, db = d b/dw)::

    d x'/dw = da vx - db vy        d vx'/dw = -T (sin(wT) vx + cos(wT) vy)
    d y'/dw = db vx + da vy        d vy'/dw =  T (cos(wT) vx - sin(wT) vy)

As w -> 0: a -> T, b -> 0, da -> 0, db -> T^2/2, so f is the CV transition and the omega column
tends to (-T^2/2 vy, -T vy, T^2/2 vx, T vx) (11.7.2). Below |wT| = 1e-2 the four coefficients
come from their Taylor series (``turn_coefficients``), where the closed forms would cancel.

CV model: F = blockdiag([[1, T], [0, 1]] per axis, 0 for omega). The CV mode does not model the
turn rate; it carries omega ~ N(0, ``turn_rate_std``^2) (predicted to 0 with that variance and,
being uncorrelated with its kinematics, never updated). That is its belief "no turn, but an
unknown turn rate if one starts", and what it gives the CT mode in the mixing: when a turn begins,
the CT mode mixes in that wide prior and can lock onto the new rate within a few scans, rather than
being pulled toward omega = 0 with a variance of 0.

Process noise: continuous white acceleration of power spectral density q [m^2/s^3] per axis,
Q = q [[T^3/3, T^2/2], [T^2/2, T]] (6.2.2; the KalmanTracker's ``cv``), with q the mode's
``cv_acceleration_density`` or ``ct_acceleration_density`` on x and y and
``vertical_acceleration_density`` on z in both modes; the CT mode's turn rate a random walk of PSD
``turn_rate_density`` [rad^2/s^3], Q_ww = q_w T. (The book drives its CT model with discrete
noise through a gain Gamma; the continuous form keeps q meaning the same at any scan period, as
ADS-B periods vary, and gives the CT mode at omega = 0 the CV mode's kinematic Q for the same q.)

Mode transitions: each mode's sojourn is exponential with mean ``sojourn_times`` [s], so over a
scan of T seconds p_ii = exp(-T / tau_i) (~ 1 - T/tau_i, the usual choice for T << tau; this stays
a probability for any T and follows a varying scan period). An infinite sojourn never leaves.

IMM cycle per scan (11.6.6): 1. mixing probabilities mu_{i|j} = p_ij mu_i / c_j,
c_j = sum_i p_ij mu_i; 2. mixed initial conditions x0_j = sum_i mu_{i|j} x_i,
P0_j = sum_i mu_{i|j} (P_i + (x_i - x0_j)(.)'); 3. mode-matched filtering (the CV Kalman filter,
the CT EKF) with likelihoods L_j = N(nu_j; 0, S_j); 4. mu_j = c_j L_j / sum; 5. combination
x = sum mu_j x_j, P = sum mu_j (P_j + (x_j - x)(.)'). Measurements: Cartesian positions, radar
polar ones converted (filters.tracker.cartesian_measurements: z_c with R_c = J R_p J'), so H is
linear and only the CT dynamics need the EKF. A missed scan keeps the predictions and c_j.

Start: two-point differencing on scans 0 and 1 (filters.models.two_point_start, 5.5.3), both
modes at that state, omega = 0 with variance ``turn_rate_std``^2, mode probabilities
``initial_mode_probabilities``; estimates from scan 1 on, NaN before.

Output: the state in the order ``MeasurementSeries.state_names`` asks (the study's truth layout;
acceleration components are NaN with their covariance rows, a reduced estimate like the
KalmanTracker's CV; omega where the layout names it or none is given). Extras:
``mode_probabilities`` (R, K, 2) in the order of ``MODES``; ``turn_rate`` (R, K) the combined
estimate sum mu_j omega_j [rad/s], which reads mu_CV omega_CT short of the CT mode's own in a turn
(the CV mode's omega is 0); ``nis`` / ``nis_dof`` of each scan's measurement against the
moment-matched prediction (filters.imm.combined_prediction_nis).

Determinism: every product is per run (stacked matmul, contiguous einsum, sums over the two modes
in mode order), so a run's estimate does not depend on which runs share its batch (bit for bit).

Engines: ``numba`` (the default) runs each run's scans in one compiled loop
(``filters.tracker.kernel.cv_ct_imm``); ``numpy`` runs the vectorised cycle below over all runs at once and is
the reference. They agree to rounding (that module says where they differ).
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np

from filters.base import MeasurementSeries, TrackEstimate, checked_engine
from filters.compiling import compiling
from filters.imm import ModeSet, combine, combined_prediction_nis
from filters.kalman import einsum, update
from filters.models import two_point_start
from filters.progress import counted, counted_runs
from filters.tracker import cartesian_measurements, to_layout

MODES = ("CV", "CT")
STATE_NAMES_3D = ("x", "vx", "y", "vy", "z", "vz", "omega")
STATE_NAMES_2D = ("x", "vx", "y", "vy", "omega")
SERIES_BELOW = 1e-2     # |omega T| under which turn_coefficients uses its Taylor series


def turn_coefficients(omega: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """a = sin(wT)/w, b = (1 - cos wT)/w and their derivatives da/dw, db/dw (11.7.1-11.7.2).

    With u = wT: a = T sin(u)/u, b = T (1 - cos u)/u, da = T^2 (u cos u - sin u)/u^2,
    db = T^2 (u sin u - (1 - cos u))/u^2. For |u| < SERIES_BELOW their Taylor series to u^7
    (truncation < 1e-20 relative there), exact at w = 0: a = T, b = 0, da = 0, db = T^2/2.
    """
    u = omega * dt
    small = np.abs(u) < SERIES_BELOW
    w = np.where(small, 1.0, omega)                 # a safe divisor; the series branch ignores it
    s, c = np.sin(w * dt), np.cos(w * dt)
    a, b = s / w, (1.0 - c) / w
    da, db = (dt * c - a) / w, (dt * s - b) / w
    u2 = u * u
    a_series = dt * (1.0 - u2 / 6.0 * (1.0 - u2 / 20.0 * (1.0 - u2 / 42.0)))
    b_series = dt * u * (0.5 - u2 / 24.0 * (1.0 - u2 / 30.0 * (1.0 - u2 / 56.0)))
    da_series = dt * dt * u * (-1.0 / 3.0 + u2 / 30.0 * (1.0 - u2 / 28.0 * (1.0 - u2 / 54.0)))
    db_series = dt * dt * (0.5 - u2 / 8.0 * (1.0 - u2 / 18.0 * (1.0 - u2 / 40.0)))
    return (np.where(small, a_series, a), np.where(small, b_series, b),
            np.where(small, da_series, da), np.where(small, db_series, db))


def coordinated_turn(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """f(x) and its Jacobian df/dx (..., n, n) for states (..., n) laid out as STATE_NAMES_3D
    (n = 7) or STATE_NAMES_2D (n = 5): the CT model with unknown turn rate (module docstring)."""
    vx, vy, w = x[..., 1], x[..., 3], x[..., -1]
    a, b, da, db = turn_coefficients(w, dt)
    s, c = np.sin(w * dt), np.cos(w * dt)
    f = x.copy()
    f[..., 0] = x[..., 0] + a * vx - b * vy
    f[..., 1] = c * vx - s * vy
    f[..., 2] = x[..., 2] + b * vx + a * vy
    f[..., 3] = s * vx + c * vy
    n = x.shape[-1]
    F = np.zeros(x.shape + (n,))
    F[..., np.arange(n), np.arange(n)] = 1.0
    F[..., 0, 1], F[..., 0, 3], F[..., 2, 1], F[..., 2, 3] = a, -b, b, a
    F[..., 1, 1], F[..., 1, 3], F[..., 3, 1], F[..., 3, 3] = c, -s, s, c
    F[..., 0, -1] = da * vx - db * vy                   # the omega column (11.7.2)
    F[..., 1, -1] = -dt * (s * vx + c * vy)
    F[..., 2, -1] = db * vx + da * vy
    F[..., 3, -1] = dt * (c * vx - s * vy)
    if n == 7:                                          # vertical CV channel
        f[..., 4] = x[..., 4] + dt * x[..., 5]
        F[..., 4, 5] = dt
    return f, F


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers(values: object) -> np.ndarray:
    """A config list as floats (NaN for what is not a number), for the range checks."""
    items = list(values) if isinstance(values, (list, tuple, np.ndarray, Sequence)) else [values]
    return np.array([float(v) if _is_number(v) else math.nan for v in items])


def white_acceleration_noise(dt: float, density: float) -> np.ndarray:
    """Q of one axis of a CV model driven by continuous white acceleration of PSD ``density`` (6.2.2)."""
    return density * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


class CVCTIMM:
    """IMM of a CV and a coordinated-turn (EKF, unknown turn rate) model; see the module docstring.

    Defaults are conf/filter/imm_cv_ct.yaml's air-traffic tuning (its comments say why).
    """

    accepts = frozenset({"position_xy", "range_azimuth_elevation"})
    mode_names = MODES          # labels of mode_probabilities (the recording's)

    def __init__(self, name: str = "IMM-CV/CT", cv_acceleration_density: float = 1.0,
                 ct_acceleration_density: float = 4.0, turn_rate_density: float = 1e-5,
                 vertical_acceleration_density: float = 2.0, sojourn_times: Sequence[float] = (120.0, 30.0),
                 initial_mode_probabilities: Sequence[float] = (0.9, 0.1), turn_rate_std: float = 0.05,
                 engine: str = "numba") -> None:
        for key, value in (("cv_acceleration_density", cv_acceleration_density),
                           ("ct_acceleration_density", ct_acceleration_density),
                           ("turn_rate_density", turn_rate_density),
                           ("vertical_acceleration_density", vertical_acceleration_density),
                           ("turn_rate_std", turn_rate_std)):
            if not (_is_number(value) and math.isfinite(value) and value > 0):
                raise ValueError(f"{key}: {value!r} must be a finite number > 0")
        tau = _numbers(sojourn_times)
        if tau.shape != (2,) or not (tau > 0).all():     # inf allowed: a mode never left
            raise ValueError(f"sojourn_times: {sojourn_times!r} must be two mean sojourn times > 0 [s] "
                             f"for {list(MODES)} (inf: never left)")
        mu0 = _numbers(initial_mode_probabilities)
        if mu0.shape != (2,) or not np.isfinite(mu0).all() or (mu0 < 0).any() or abs(mu0.sum() - 1.0) > 1e-9:
            raise ValueError(f"initial_mode_probabilities: {initial_mode_probabilities!r} must be two "
                             f"probabilities for {list(MODES)} summing to 1")
        checked_engine(engine, "the compiled scan loop, filters/tracker/kernel.py")
        self.name = name
        self.engine = engine
        self.cv_acceleration_density = float(cv_acceleration_density)
        self.ct_acceleration_density = float(ct_acceleration_density)
        self.turn_rate_density = float(turn_rate_density)
        self.vertical_acceleration_density = float(vertical_acceleration_density)
        self.sojourn_times = tuple(float(v) for v in tau)
        self.initial_mode_probabilities = mu0
        self.turn_rate_std = float(turn_rate_std)

    # ---- models ---------------------------------------------------------------------------------
    def transition_probabilities(self, dt: float) -> np.ndarray:
        """(2, 2) row i: P(mode_k = j | mode_{k-1} = i) over a scan of ``dt`` s: p_ii = exp(-dt/tau_i)."""
        stay = np.exp(-dt / np.array(self.sojourn_times))
        return np.array([[stay[0], 1.0 - stay[0]], [1.0 - stay[1], stay[1]]])

    def cv_model(self, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """F, Q of the CV mode in the common state: omega predicted to 0 with variance turn_rate_std^2."""
        F = np.zeros((n, n))
        for p in range(0, n - 1, 2):
            F[p:p + 2, p:p + 2] = [[1.0, dt], [0.0, 1.0]]
        Q = self._kinematic_noise(dt, n, self.cv_acceleration_density)
        Q[-1, -1] = self.turn_rate_std**2
        return F, Q

    def ct_noise(self, dt: float, n: int) -> np.ndarray:
        """Q of the CT mode: white acceleration on x, y (and z), a random-walk turn rate."""
        Q = self._kinematic_noise(dt, n, self.ct_acceleration_density)
        Q[-1, -1] = self.turn_rate_density * dt
        return Q

    def _kinematic_noise(self, dt: float, n: int, horizontal_density: float) -> np.ndarray:
        """(n, n) white-acceleration Q on (x, vx), (y, vy) and (z, vz); zero on omega."""
        Q = np.zeros((n, n))
        for p in range(0, n - 1, 2):
            density = horizontal_density if p < 4 else self.vertical_acceleration_density
            Q[p:p + 2, p:p + 2] = white_acceleration_noise(dt, density)
        return Q

    # ---- one IMM cycle ---------------------------------------------------------------------------
    def mix(self, x: np.ndarray, P: np.ndarray, mu: np.ndarray, dt: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Steps 1-2 of 11.6.6: the mixed (x0_j, P0_j) (R, 2, n[, n]) and c_j (R, 2)."""
        joint = self.transition_probabilities(dt)[None] * mu[:, :, None]     # p_ij mu_i, (R, i, j)
        predicted = joint[:, 0] + joint[:, 1]                                  # c_j
        reachable = predicted > 0           # a mode no mode can switch to keeps mu = 0; mix it with mu
        weights = np.where(reachable[:, None, :], joint / np.where(reachable, predicted, 1.0)[:, None, :],
                           mu[:, :, None])                                     # mu_{i|j}
        reference = x[:, :1]                # centred on the CV mode: exact when mu_{CV|j} = 1
        dx = x - reference
        x_mix = (weights[..., None] * dx[:, :, None, :]).sum(axis=1)           # sums over i in mode order
        spread = P + dx[..., :, None] * dx[..., None, :]
        P_mix = (weights[..., None, None] * spread[:, :, None]).sum(axis=1) - x_mix[..., :, None] * x_mix[..., None, :]
        return x_mix + reference, P_mix, predicted

    def predict(self, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Step 3's prediction: the CV Kalman filter and the CT EKF, (R, 2, n[, n])."""
        n = x.shape[-1]
        F_cv, Q_cv = self.cv_model(dt, n)
        x_ct, F_ct = coordinated_turn(x[:, 1], dt)
        x_pred = np.stack([einsum("ij,rj->ri", F_cv, x[:, 0]), x_ct], axis=1)
        F = np.stack([np.broadcast_to(F_cv, F_ct.shape), F_ct], axis=1)
        P_pred = F @ P @ np.swapaxes(F, -1, -2) + np.stack([Q_cv, self.ct_noise(dt, n)])
        return x_pred, 0.5 * (P_pred + np.swapaxes(P_pred, -1, -2))

    # ---- run ------------------------------------------------------------------------------------
    RUNS_PER_CALL = 8       # of the compiled loop; progress is told between calls

    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        if self.engine == "numba":
            from filters.tracker import kernel as kalman_kernel
            with compiling("filters.tracker.kernel"):     # says so when numba compiles (the first job of an install)
                kalman_kernel.warm_up()         # numba's start before the clock: compute_seconds is the filtering's
        started = time.perf_counter()
        if not isinstance(measurements, MeasurementSeries):
            raise TypeError(f"{self.name}: takes {sorted(self.accepts)} measurements, "
                            f"not {type(measurements).__name__}")
        times = np.asarray(measurements.time, dtype=float)
        if times.size < 3:
            raise ValueError("measurements: the two-point start needs at least 3 scans")
        dts = np.diff(times)
        if not (dts > 0).all():
            raise ValueError("measurements.time: scan times must increase")
        z, noise, detected = cartesian_measurements(measurements)
        R, K, d = z.shape
        names = STATE_NAMES_3D if d == 3 else STATE_NAMES_2D
        n = len(names)
        positions = np.arange(d) * 2
        H = np.zeros((d, n))
        H[np.arange(d), positions] = 1.0

        state = np.full((R, K, n), np.nan)
        covariance = np.full((R, K, n, n), np.nan)
        mode_probabilities = np.full((R, K, 2), np.nan)
        nis = np.full((R, K), np.nan)
        x0, P0 = two_point_start(z[:, 0], z[:, 1], noise[:, 0], noise[:, 1], float(dts[0]))
        x = np.zeros((R, 2, n))
        P = np.zeros((R, 2, n, n))
        x[..., :-1] = x0[:, None]
        P[..., :-1, :-1] = P0[:, None]
        P[..., -1, -1] = self.turn_rate_std**2
        mu = np.broadcast_to(self.initial_mode_probabilities, (R, 2)).copy()
        state[:, 1], covariance[:, 1], mode_probabilities[:, 1] = x[:, 0], P[:, 0], mu
        if self.engine == "numba":
            self._run_compiled(z, noise, detected, dts, x, P, mu, state, covariance, mode_probabilities, nis)
        else:
            self._run_numpy(z, noise, detected, dts, H, x, P, mu, state, covariance, mode_probabilities, nis)
        turn_rate = state[..., -1].copy()
        state, covariance = to_layout(state, covariance, names, tuple(measurements.state_names or names))
        extras = {"mode_probabilities": mode_probabilities, "turn_rate": turn_rate, "nis": nis,
                  "nis_dof": np.where(np.isfinite(nis), float(d), 0.0)}
        return TrackEstimate(times.copy(), state, covariance, extras, time.perf_counter() - started)

    def _run_compiled(self, z, noise, detected, dts, x, P, mu, state, covariance, mode_probabilities, nis) -> None:
        """Scans 2.. through filters.tracker.kernel.cv_ct_imm, a block of runs per call; the per-scan matrices
        from ``cv_model``, ``ct_noise`` and ``transition_probabilities`` (once per distinct period)."""
        from filters.tracker import kernel as kalman_kernel

        R, K, _ = z.shape
        n = x.shape[-1]
        F_cv, Q_cv, Q_ct = (np.empty((K - 1, n, n)) for _ in range(3))
        transition = np.empty((K - 1, 2, 2))
        for dt in np.unique(dts):
            at = dts == dt
            F_cv[at], Q_cv[at] = self.cv_model(float(dt), n)
            Q_ct[at] = self.ct_noise(float(dt), n)
            transition[at] = self.transition_probabilities(float(dt))
        # C-contiguous and writeable, as warm_up compiled it: a read-only array (measurements read
        # from the stage cache) is another numba type, which would compile inside the filter's clock
        inputs = [np.require(a, requirements=("C", "W")) for a in (z, noise, detected, dts, F_cv, Q_cv, Q_ct, transition)]
        start = [np.require(a, requirements=("C", "W")) for a in (x, P, mu)]
        for first, stop in counted_runs(R, max(K - 2, 0), self.name, self.RUNS_PER_CALL):
            kalman_kernel.cv_ct_imm(first, stop, *inputs, SERIES_BELOW, *start, state, covariance, mode_probabilities, nis)

    def _run_numpy(self, z, noise, detected, dts, H, x, P, mu, state, covariance, mode_probabilities, nis) -> None:
        """Scans 2.., all runs at once: the reference."""
        R, K, _ = z.shape
        modes = np.broadcast_to(np.arange(2), (R, 2))
        for k in counted(range(2, K), "scan", self.name):
            dt = float(dts[k - 1])
            x_mix, P_mix, predicted = self.mix(x, P, mu, dt)                  # steps 1-2
            x_pred, P_pred = self.predict(x_mix, P_mix, dt)                   # step 3
            x, P, log_likelihood = update(x_pred, P_pred, z[:, k, None], H, noise[:, k, None])
            seen = detected[:, k]
            x = np.where(seen[:, None, None], x, x_pred)
            P = np.where(seen[:, None, None, None], P, P_pred)
            log_likelihood = np.where(seen[:, None], log_likelihood, 0.0)
            with np.errstate(divide="ignore"):
                log_predicted = np.log(predicted)
            cycle = ModeSet(modes, x, P, log_predicted, log_likelihood, log_predicted + log_likelihood,
                            x_pred, P_pred)
            state[:, k], covariance[:, k], mu = combine(cycle)                 # steps 4-5
            mode_probabilities[:, k] = mu
            nis[:, k] = combined_prediction_nis(cycle, z[:, k], noise[:, k], H, seen)
