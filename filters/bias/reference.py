"""Multisensor bias registration for asynchronous 2-D radars (seed 002: Kim, Kim, Park, Song,
"Multisensor Bias Estimation with Pseudo Measurement for Asynchronous Sensors").

Every radar s measures range and azimuth with offset and scale biases (eq 1),
``beta_s = (b_r, b_theta, eps_r, eps_theta)``. Each radar runs a *biased local filter* per target
on its converted measurements; its estimate splits into the target part and a bias part,
``X^b = X + G beta_s`` (eqs 9, 13, 16), with the bias matrix G carried along (eq 20). Three
ways to live with the biases, all batched over Monte Carlo runs and targets:

- :class:`LocalTracking`: the biased local tracks alone (no bias handling; the floor).
- :class:`PseudoBiasRegistration` (the paper's proposal): at each report of radar i, every
  other radar j's latest track, predicted to the report time, gives a pseudo bias measurement
  ``z^b = z^m_i - H Phi X^b_j = [B_i C_i, -H Phi G_j] b + w^b`` (eqs 22-32) of the stacked bias
  ``b = [beta_1; ...; beta_S]``; a recursive least-squares update over all targets of the report
  (eqs 33-36) refines ``b``; the local tracks are compensated, ``X^b - G beta_hat`` with
  covariance ``P + G Sigma G'`` (eqs 37-41).
- :class:`EXXRegistration` (the baseline: Lin, Bar-Shalom & Kirubarajan 2005): state-independent
  pseudo measurements from three measurements of one target in a "proper time slot" (two of one
  radar, one of another), whose CV-dynamics combination cancels position and velocity exactly;
  least squares with the same prior. The 2005 paper was not available: this implements the
  reconstruction in the literature notes, section 5.4 (alternating 3-report slots, process-noise
  term of the interpolation/extrapolation), and says so here.

Conventions (spec 002): state ``X = (x, y, vx, vy)`` (eq 5); CV dynamics and DCWNA process noise
(eqs 42-43); angles in radians with the azimuth from +x counter-clockwise; scale biases are
dimensionless. B, C and R^m are evaluated at the radar's own *predicted* biased track position
before the update, for both methods and for the G recursion (``jacobian_at="prediction"``; the
spec found that the measured range/azimuth leaks measurement noise into the scale-bias columns,
available as ``jacobian_at="measurement"`` to show it). Eq 20 as printed, ``(I - K) H Phi G``,
is dimensionally impossible; the derivation of eq 16 gives ``(I - K H) Phi G``, used here.

The bias estimators keep the information form of the least squares in prior-normalised units
(``b / prior_std``): the information added by all targets of a report is summed in one batched
product, which equals the seed's target-by-target recursion (eqs 33-36) because no pseudo
measurement depends on the bias estimate; the normalisation keeps the 10^-4..10^8 spread of the
raw information matrix out of the solves.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from filters.base import checked_engine
from filters.compiling import compiling
from filters.kalman import einsum, inverse_2x2, rows_times, shared_times, times_shared
from filters.progress import counted

STATE_NAMES = ("x", "y", "vx", "vy")
BIAS_NAMES = ("range_offset", "azimuth_offset", "range_scale", "azimuth_scale")
BIAS_UNITS = ("m", "rad", "1", "1")
# Spec 002: Sigma_1 = Sigma_2 = diag(100^2, 0.2^2, 0.01^2, 0.1^2) (SI)
DEFAULT_PRIOR_STD = (100.0, 0.2, 0.01, 0.1)


# --------------------------------------------------------------------------------------------
# Model pieces (eqs 2-6, 42-43)
# --------------------------------------------------------------------------------------------

def cv_transition(dt: np.ndarray | float) -> np.ndarray:
    """Phi(dt) of eq 42 for state (x, y, vx, vy); dt of any shape (...) gives (..., 4, 4)."""
    dt = np.asarray(dt, dtype=float)
    F = np.broadcast_to(np.eye(4), dt.shape + (4, 4)).copy()
    F[..., 0, 2] = dt
    F[..., 1, 3] = dt
    return F


def dcwna_process_noise(dt: np.ndarray | float, density: float) -> np.ndarray:
    """Q(dt) of eq 43 (discretised continuous white-noise acceleration), density q [m^2/s^3]."""
    dt = np.asarray(dt, dtype=float)
    Q = np.zeros(dt.shape + (4, 4))
    for axis in (0, 1):
        Q[..., axis, axis] = dt**3 / 3.0
        Q[..., axis, axis + 2] = Q[..., axis + 2, axis] = dt**2 / 2.0
        Q[..., axis + 2, axis + 2] = dt
    return density * Q


def polar(relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) position relative to the radar -> range, azimuth (from +x, counter-clockwise)."""
    return np.hypot(relative[..., 0], relative[..., 1]), np.arctan2(relative[..., 1], relative[..., 0])


def bias_jacobian(range_: np.ndarray, azimuth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B (eq 4) and B C (eqs 3-4) at (range, azimuth): (..., 2, 2) and (..., 2, 4).

    B = d(x, y)/d(r, theta); C maps beta = (b_r, b_theta, eps_r, eps_theta) to the polar error
    (b_r + eps_r r, b_theta + eps_theta theta), so the converted measurement carries B C beta.
    """
    c, s = np.cos(azimuth), np.sin(azimuth)
    B = np.stack([np.stack([c, -range_ * s], -1), np.stack([s, range_ * c], -1)], -2)
    BC = np.concatenate([B, B * np.stack([range_, azimuth], -1)[..., None, :]], axis=-1)
    return B, BC


def converted_measurement(z_polar: np.ndarray, sensor_position: np.ndarray) -> np.ndarray:
    """z^m of eq 2: the measured (range, azimuth) as a position in the common frame."""
    r, theta = z_polar[..., 0], z_polar[..., 1]
    return sensor_position + np.stack([r * np.cos(theta), r * np.sin(theta)], axis=-1)


def converted_covariance(B: np.ndarray, noise_std: np.ndarray) -> np.ndarray:
    """R^m = B diag(sigma_r^2, sigma_theta^2) B' (eq 6)."""
    scaled = B * np.asarray(noise_std, dtype=float)
    return _times_2(scaled, np.swapaxes(scaled, -1, -2))


# --------------------------------------------------------------------------------------------
# Inputs and outputs
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TrackStart:
    """Bias-free start of every radar's local tracks (the seed's simulation set-up).

    time : start time [s]; state : (R, S, T, 4) start estimates; covariance : (4, 4) P0.
    """

    time: float
    state: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class RadarReports:
    """Asynchronous reports of S radars on T targets, batched over R Monte Carlo runs.

    time (K,) report times, non-decreasing; sensor (K,) which radar reports (0..S-1);
    z (R, K, T, 2) measured (range, azimuth) of every target; sensor_position (S, 2);
    noise_std (S, 2) (sigma_r, sigma_theta) each radar states; start: the bias-free track start,
    or None (then only a two-point-differencing start is possible).
    """

    time: np.ndarray
    sensor: np.ndarray
    z: np.ndarray
    sensor_position: np.ndarray
    noise_std: np.ndarray
    start: TrackStart | None = None

    def __post_init__(self) -> None:
        K = self.time.shape[0]
        if self.sensor.shape != (K,) or self.z.ndim != 4 or self.z.shape[1] != K or self.z.shape[-1] != 2:
            raise ValueError(f"RadarReports: time {self.time.shape}, sensor {self.sensor.shape} and z {self.z.shape} "
                             f"must be (K,), (K,) and (R, K, T, 2)")
        S = self.sensor_position.shape[0]
        if self.sensor_position.shape != (S, 2) or self.noise_std.shape != (S, 2):
            raise ValueError(f"RadarReports: sensor_position {self.sensor_position.shape} and noise_std "
                             f"{self.noise_std.shape} must both be (S, 2)")
        if K and (self.sensor.min() < 0 or self.sensor.max() >= S):
            raise ValueError(f"RadarReports: sensor indices must be 0..{S - 1}, got {np.unique(self.sensor).tolist()}")
        if np.any(np.diff(self.time) < 0):
            raise ValueError("RadarReports: report times must be non-decreasing")
        if self.start is not None:
            R, _, T, _ = self.z.shape
            if self.start.state.shape != (R, S, T, 4) or np.shape(self.start.covariance) != (4, 4):
                raise ValueError(f"TrackStart: state {self.start.state.shape} must be (R, S, T, 4) = {(R, S, T, 4)} "
                                 f"and covariance {np.shape(self.start.covariance)} (4, 4)")
            if K and self.start.time > self.time[0]:
                raise ValueError(f"TrackStart: time {self.start.time} is after the first report at {self.time[0]}")

    @property
    def runs(self) -> int:
        return self.z.shape[0]

    def select(self, runs: Sequence[int]) -> "RadarReports":
        """The same reports for a subset of runs (a chunk of the Monte Carlo)."""
        index = np.asarray(runs, dtype=int)
        start = None if self.start is None else replace(self.start, state=self.start.state[index])
        return replace(self, z=self.z[index], start=start)

    @property
    def sensors(self) -> int:
        return self.sensor_position.shape[0]

    @property
    def targets(self) -> int:
        return self.z.shape[2]


@dataclass(frozen=True)
class BiasRegistrationResult:
    """What a bias-registration variant returns, one entry per report k.

    bias (R, K, 4S) and bias_covariance (R, K, 4S, 4S): the stacked bias estimate after report k
    (NaN for a variant without bias estimation). targets (Tsel,): the target indices whose tracks
    are kept. track_state (R, K, Tsel, 4) / track_covariance: the reporting radar's biased local
    track after report k (NaN before it has one); compensated_state / compensated_covariance:
    the same track with the radar's bias estimate removed (eqs 38, 41).

    nis (R, K): the normalised innovation squared nu' S^-1 nu of the reporting radar's local
    update at report k (converted measurement, S = H P H' + R^m, eq 19), SUMMED over all its
    tracked targets (not only the kept ones), so that it is chi-square with nis_dof (R, K) = 2 x the
    number of targets summed degrees of freedom for a consistent local filter (the targets'
    innovations are independent); NaN with dof 0 where the radar had no track to update (a
    two-point start's first two reports). None for a result read from a table without them.
    """

    time: np.ndarray
    sensor: np.ndarray
    bias: np.ndarray
    bias_covariance: np.ndarray
    targets: np.ndarray
    track_state: np.ndarray
    track_covariance: np.ndarray
    compensated_state: np.ndarray
    compensated_covariance: np.ndarray
    compute_seconds: float = float("nan")
    nis: np.ndarray | None = None
    nis_dof: np.ndarray | None = None

    @classmethod
    def concat_runs(cls, parts: Sequence["BiasRegistrationResult"]) -> "BiasRegistrationResult":
        """Chunks of runs (in run order) as one result; compute time is the sum of the chunks'."""
        first = parts[0]
        names = ["bias", "bias_covariance", "track_state", "track_covariance", "compensated_state",
                 "compensated_covariance"]
        if all(p.nis is not None and p.nis_dof is not None for p in parts):
            names += ["nis", "nis_dof"]
        stacked = {name: np.concatenate([getattr(p, name) for p in parts]) for name in names}
        return cls(first.time, first.sensor, targets=first.targets, compute_seconds=float(sum(p.compute_seconds for p in parts)),
                   **stacked)


# --------------------------------------------------------------------------------------------
# Biased local filter (eqs 7-21)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LocalTracks:
    """One radar's biased local tracks: state (..., T, 4), covariance (..., T, 4, 4),
    bias matrix G (..., T, 4, 4) with X^b = X + G beta (eq 16); nis (..., T): the normalised
    innovation squared of the update that gave these tracks (None for predicted or started ones)."""

    state: np.ndarray
    covariance: np.ndarray
    bias_matrix: np.ndarray
    nis: np.ndarray | None = None




def _cv_move(state: np.ndarray, covariance: np.ndarray, bias_matrix: np.ndarray | None, dt: float,
             density: float, engine: str = "numpy") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Phi X, Phi P Phi' + Q, Phi G with the one shared Phi, one product per track
    (kalman.times_shared: each run's result does not depend on the batch)."""
    F = cv_transition(dt)
    Q = dcwna_process_noise(dt, density)
    if engine == "numba":
        from filters.bias import kernel as bias_kernel
        x, P, G = _flat(state, 4), _flat(covariance, 4, 4), _flat(bias_matrix, 4, 4)
        out = np.empty_like(x), np.empty_like(P), np.empty_like(G)
        bias_kernel.cv_move(x, P, G, F, Q, *out)
        return (out[0].reshape(state.shape), out[1].reshape(covariance.shape),
                None if bias_matrix is None else out[2].reshape(bias_matrix.shape))
    moved = rows_times(state, F.T)
    P = shared_times(F, times_shared(covariance, F.T)) + Q
    G = None if bias_matrix is None else shared_times(F, bias_matrix)
    return moved, P, G


def _flat(a: np.ndarray | None, *trailing: int) -> np.ndarray:
    """A stack (..., *trailing) as C-contiguous float64 (N, *trailing); None as (0, *trailing)."""
    if a is None:
        return np.empty((0,) + trailing)
    return np.ascontiguousarray(a, dtype=float).reshape((-1,) + trailing)


def predict_local(tracks: LocalTracks, dt: float, density: float, engine: str = "numpy") -> LocalTracks:
    """Eqs 13-14: X^b and G move with Phi; P gains Q and does not depend on the bias."""
    return LocalTracks(*_cv_move(tracks.state, tracks.covariance, tracks.bias_matrix, dt, density, engine))


def _times_2(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B for stacks A (..., p, 2) and B (..., 2, q) as two broadcast products: for these tiny
    matrices that beats numpy's one-product-per-matrix stacked matmul several-fold."""
    return A[..., :, 0:1] * B[..., 0:1, :] + A[..., :, 1:2] * B[..., 1:2, :]


def update_local(predicted: LocalTracks, z_converted: np.ndarray, noise: np.ndarray, bias_columns: np.ndarray,
                 engine: str = "numpy") -> LocalTracks:
    """Eqs 16-21 with the converted measurement z^m, its covariance R^m and B C.

    G' = (I - K H) Phi G + K B C (eq 20 corrected), P' = (I - K H) P (eq 21, as P - K S K').
    The updated tracks carry each target's NIS nu' S^-1 nu of this update (chi-square, 2 dof, for
    a consistent filter). ``engine="numba"``: the same operations per track, compiled
    (filters/bias/kernel.py), bit for bit these.
    """
    if engine == "numba":
        return _update_local_compiled(predicted, z_converted, noise, bias_columns)
    P = predicted.covariance
    PHt = P[..., :, :2]
    S = P[..., :2, :2] + noise                                       # eq 19
    S_inv = inverse_2x2(S)
    gain = _times_2(PHt, S_inv)                                     # eq 18
    innovation = z_converted - predicted.state[..., :2]
    nis = np.sum(innovation * _times_2(S_inv, innovation[..., None])[..., 0], axis=-1)
    state = predicted.state + gain[..., 0] * innovation[..., 0:1] + gain[..., 1] * innovation[..., 1:2]
    covariance = P - _times_2(gain, np.swapaxes(PHt, -1, -2))
    covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
    G = predicted.bias_matrix
    bias_matrix = G + _times_2(gain, bias_columns - G[..., :2, :])   # eq 20: (I - K H) Phi G + K B C
    return LocalTracks(state, covariance, bias_matrix, nis)


def _update_local_compiled(predicted: LocalTracks, z_converted: np.ndarray, noise: np.ndarray,
                           bias_columns: np.ndarray) -> LocalTracks:
    from filters.bias import kernel as bias_kernel
    lead = predicted.state.shape[:-1]
    x, P, G = _flat(predicted.state, 4), _flat(predicted.covariance, 4, 4), _flat(predicted.bias_matrix, 4, 4)
    out_x, out_P, out_G, nis = np.empty_like(x), np.empty_like(P), np.empty_like(G), np.empty(x.shape[0])
    bias_kernel.update_local(x, P, G, _flat(np.broadcast_to(z_converted, lead + (2,)), 2),
                             _flat(np.broadcast_to(noise, lead + (2, 2)), 2, 2),
                             _flat(np.broadcast_to(bias_columns, lead + (2, 4)), 2, 4), out_x, out_P, out_G, nis)
    return LocalTracks(out_x.reshape(lead + (4,)), out_P.reshape(lead + (4, 4)), out_G.reshape(lead + (4, 4)),
                       nis.reshape(lead))


def two_point_start(z0: np.ndarray, z1: np.ndarray, noise0: np.ndarray, noise1: np.ndarray,
                    bias_columns0: np.ndarray, bias_columns1: np.ndarray, dt: float) -> LocalTracks:
    """Eqs 8-11: X^b = (z1, (z1 - z0)/T), G = (B1 C1, (B1 C1 - B0 C0)/T), P from R^m."""
    state = np.concatenate([z1, (z1 - z0) / dt], axis=-1)
    P = np.zeros(z1.shape[:-1] + (4, 4))
    P[..., :2, :2] = noise1
    P[..., :2, 2:] = P[..., 2:, :2] = noise1 / dt
    P[..., 2:, 2:] = (noise1 + noise0) / dt**2
    G = np.concatenate([bias_columns1, (bias_columns1 - bias_columns0) / dt], axis=-2)
    return LocalTracks(state, P, G)


def nis_over_targets(nis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-target NIS (..., T) -> their sum over the targets (...) and its chi-square dof (...):
    2 per target with a finite NIS (independent 2-D innovations); NaN with dof 0 where none is."""
    counted = np.isfinite(nis)
    count = counted.sum(axis=-1)
    total = np.where(counted, nis, 0.0).sum(axis=-1)
    return np.where(count > 0, total, np.nan), 2.0 * count


def compensate(tracks: LocalTracks, bias: np.ndarray, bias_covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 38 and 41: X^b - G beta_hat and P + G Sigma G' (beta_hat (..., 4), Sigma (..., 4, 4)
    broadcast over the target axis)."""
    G = tracks.bias_matrix
    state = tracks.state - einsum("...tij,...j->...ti", G, bias)
    covariance = tracks.covariance + G @ bias_covariance[..., None, :, :] @ np.swapaxes(G, -1, -2)
    return state, covariance


# --------------------------------------------------------------------------------------------
# Least squares with a prior, information form (eqs 33-36)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BiasInformation:
    """Information form of the stacked-bias estimate in prior-normalised units b / prior_std:
    information (R, n, n) and information_vector (R, n); prior_std (n,)."""

    information: np.ndarray
    information_vector: np.ndarray
    prior_std: np.ndarray

    @classmethod
    def prior(cls, runs: int, prior_std: np.ndarray) -> "BiasInformation":
        n = prior_std.size
        return cls(np.broadcast_to(np.eye(n), (runs, n, n)).copy(), np.zeros((runs, n)), prior_std)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The bias estimate (R, n) and its covariance (R, n, n) in SI units."""
        n = self.prior_std.size
        covariance = np.linalg.solve(self.information, np.broadcast_to(np.eye(n), self.information.shape))
        covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
        mean = einsum("rij,rj->ri", covariance, self.information_vector)
        scale = self.prior_std
        return mean * scale, covariance * scale[:, None] * scale[None, :]


def add_pseudo_measurements(info: BiasInformation, z: np.ndarray, H: np.ndarray, noise: np.ndarray,
                            valid: np.ndarray | None = None) -> BiasInformation:
    """Fold pseudo measurements z = H b + w, w ~ N(0, noise), of every target into the estimate.

    z (R, T, m), H (R, T, m, n), noise (R, T, m, m); ``valid`` (R, T) masks targets out. One
    batched sum over targets equals the target-by-target recursion of eqs 33-35.
    """
    H_scaled = H * info.prior_std
    if noise.shape[-1] == 2:
        weighted = _times_2(inverse_2x2(noise), H_scaled)            # R_b^-1 H (per target)
    else:
        weighted = np.linalg.solve(noise, H_scaled)
    if valid is not None:
        weighted = np.where(valid[..., None, None], weighted, 0.0)
    R, n = H.shape[0], H.shape[-1]
    stacked_H = H_scaled.reshape(R, -1, n)                            # all targets' rows of a run
    stacked_W = weighted.reshape(R, -1, n)
    information = info.information + np.swapaxes(stacked_H, -1, -2) @ stacked_W
    vector = info.information_vector + (np.swapaxes(stacked_W, -1, -2) @ np.nan_to_num(z).reshape(R, -1, 1))[..., 0]
    return BiasInformation(information, vector, info.prior_std)


@dataclass(frozen=True)
class BiasState:
    """A bias estimator's state between reports: the least-squares information, the reports
    gathered towards an EXX time slot (radar, time, z^m, R^m, B C each), the number of radars."""

    information: BiasInformation
    slot: tuple
    sensors: int


# --------------------------------------------------------------------------------------------
# The variants
# --------------------------------------------------------------------------------------------

class LocalTracking:
    """Biased local tracks of every radar, with no bias handling (the floor).

    Parameters
    ----------
    name : display name
    process_noise_density : q of the filters' DCWNA model [m^2/s^3] (eq 43)
    start : "truth" (the bias-free start the reports carry, G = 0; the seed's set-up) or
        "two_point" (eqs 8-11 from each radar's first two reports)
    prior_std : the 4 standard deviations of each radar's bias prior (b_r m, b_theta rad,
        eps_r, eps_theta); the prior mean is 0
    output_targets : target numbers (1-based, the paper's numbering) whose tracks are returned;
        None returns every target
    jacobian_at : "prediction" (B, C, R^m at the radar's predicted track position; spec 002) or
        "measurement" (at the measured range and azimuth; the ablation)
    engine : "numba" (default): each local filter's move and update is one compiled pass over the
        tracks (filters/bias/kernel.py); "numpy": the broadcast steps of this module, the reference.
        The updates are the same bit for bit; a move's products may round differently in the last
        bit (numpy's matmul), so the two agree to rounding (identical on the paper-size async_bias
        job; see filters/bias/kernel.py).
    """

    accepts = frozenset({"biased_radar_reports"})

    estimates_bias = False

    def __init__(self, name: str = "local", process_noise_density: float = 6.0, start: str = "truth",
                 prior_std: Sequence[float] = DEFAULT_PRIOR_STD, output_targets: Sequence[int] | None = (1, 32),
                 jacobian_at: str = "prediction", engine: str = "numba") -> None:
        if not (np.isfinite(process_noise_density) and process_noise_density >= 0):
            raise ValueError(f"process_noise_density: {process_noise_density} must be a finite q >= 0 m^2/s^3")
        if start not in ("truth", "two_point"):
            raise ValueError(f"start: {start!r} is not allowed; use 'truth' (bias-free start, the seed's set-up) or "
                             f"'two_point' (eqs 8-11)")
        prior = np.asarray(prior_std, dtype=float)
        if prior.shape != (4,) or not np.all(np.isfinite(prior) & (prior > 0)):
            raise ValueError(f"prior_std: {list(prior_std)} must be 4 finite standard deviations > 0 "
                             f"(b_r m, b_theta rad, eps_r, eps_theta)")
        if output_targets is not None:
            numbers = list(output_targets)
            if not numbers or not all(isinstance(t, (int, np.integer)) and not isinstance(t, bool) and t >= 1
                                      for t in numbers):
                raise ValueError(f"output_targets: {numbers} must be target numbers >= 1 (1 = the target nearest "
                                 f"radar 1) or null for all targets")
        if jacobian_at not in ("prediction", "measurement"):
            raise ValueError(f"jacobian_at: {jacobian_at!r} is not allowed; use 'prediction' (spec 002) or "
                             f"'measurement'")
        checked_engine(engine, "the compiled local filter steps, filters/bias/kernel.py")
        self.name = name
        self.engine = engine
        self.process_noise_density = float(process_noise_density)
        self.start = start
        self.prior_std = prior
        self.output_targets = None if output_targets is None else [int(t) for t in output_targets]
        self.jacobian_at = jacobian_at

    # hooks of the bias estimators: the estimate travels as an explicit BiasState through run() --
    def _begin(self, reports: RadarReports) -> "BiasState":
        return BiasState(BiasInformation.prior(reports.runs, np.tile(self.prior_std, reports.sensors)), (),
                         reports.sensors)

    def _bias_step(self, state: "BiasState", i: int, t: float, z_converted: np.ndarray, noise: np.ndarray,
                   bias_columns: np.ndarray, tracks: list[LocalTracks | None], last_time: np.ndarray
                   ) -> tuple["BiasState", bool]:
        """The state after report k of radar i (before its local update), and whether the bias
        estimate changed."""
        return state, False

    # -------------------------------------------------------------------------------------------
    def _selected(self, T: int) -> np.ndarray:
        if self.output_targets is None:
            return np.arange(T)
        bad = [t for t in self.output_targets if t > T]
        if bad:
            raise ValueError(f"output_targets: {self.output_targets} names target(s) {bad} but the scenario has "
                             f"{T} targets (numbered 1..{T})")
        return np.asarray(self.output_targets) - 1

    def run(self, reports: RadarReports) -> BiasRegistrationResult:
        if self.engine == "numba":
            from filters.bias import kernel as bias_kernel
            with compiling("filters.bias.kernel"):     # says so when numba compiles (the first job of an install)
                bias_kernel.warm_up()               # numba's start before the clock: compute_seconds is the filtering's
        started = _time.perf_counter()
        R, K, T, _ = reports.z.shape
        S = reports.sensors
        selected = self._selected(T)
        if self.start == "truth" and reports.start is None:
            raise ValueError("start: 'truth' needs the bias-free track start in RadarReports.start; use "
                             "start='two_point' for reports without one")
        tracks: list[LocalTracks | None] = [None] * S
        last_time = np.full(S, np.nan)
        first_report: list[tuple[np.ndarray, np.ndarray, np.ndarray, float] | None] = [None] * S
        if self.start == "truth":
            P0 = np.broadcast_to(np.asarray(reports.start.covariance, dtype=float), (R, T, 4, 4))
            for s in range(S):
                tracks[s] = LocalTracks(reports.start.state[:, s].astype(float), P0.copy(), np.zeros((R, T, 4, 4)))
            last_time[:] = reports.start.time
        state = self._begin(reports)
        n = 4 * S
        bias = np.zeros((R, n))
        bias_cov = np.broadcast_to(np.diag(np.tile(self.prior_std, S) ** 2), (R, n, n)).copy()
        out_bias = np.full((R, K, n), np.nan if not self.estimates_bias else 0.0)
        out_bias_cov = np.full((R, K, n, n), np.nan)
        Tsel = selected.size
        out_x = np.full((R, K, Tsel, 4), np.nan)
        out_P = np.full((R, K, Tsel, 4, 4), np.nan)
        out_xc = np.full((R, K, Tsel, 4), np.nan)
        out_Pc = np.full((R, K, Tsel, 4, 4), np.nan)
        out_nis = np.full((R, K), np.nan)
        out_nis_dof = np.zeros((R, K))
        for k in counted(range(K), "scan", self.name):
            i, t = int(reports.sensor[k]), float(reports.time[k])
            position = reports.sensor_position[i]
            z_polar = reports.z[:, k]
            z_converted = converted_measurement(z_polar, position)
            predicted = None
            if tracks[i] is not None:
                predicted = predict_local(tracks[i], t - last_time[i], self.process_noise_density, self.engine)
            if predicted is not None and self.jacobian_at == "prediction":
                where = polar(predicted.state[..., :2] - position)       # spec 002: the predicted position
            else:
                where = (z_polar[..., 0], z_polar[..., 1])
            B, BC = bias_jacobian(*where)
            noise = converted_covariance(B, reports.noise_std[i])       # eq 6
            if self.estimates_bias:
                state, changed = self._bias_step(state, i, t, z_converted, noise, BC, tracks, last_time)
                if changed:
                    bias, bias_cov = state.information.estimate()
                out_bias[:, k] = bias
                out_bias_cov[:, k] = bias_cov
            if predicted is not None:
                tracks[i] = update_local(predicted, z_converted, noise, BC, self.engine)
                last_time[i] = t
                # all T targets, not only the kept ones: the radar's whole local filter, chi2(2T)
                out_nis[:, k], out_nis_dof[:, k] = nis_over_targets(tracks[i].nis)
            elif first_report[i] is None:
                first_report[i] = (z_converted, noise, BC, t)
            else:                                                       # eqs 8-11 from the first two reports
                z0, noise0, BC0, t0 = first_report[i]
                tracks[i] = two_point_start(z0, z_converted, noise0, noise, BC0, BC, t - t0)
                last_time[i] = t
            if tracks[i] is not None and last_time[i] == t:
                chosen = LocalTracks(tracks[i].state[:, selected], tracks[i].covariance[:, selected],
                                     tracks[i].bias_matrix[:, selected])
                out_x[:, k], out_P[:, k] = chosen.state, chosen.covariance
                if self.estimates_bias:
                    block = slice(4 * i, 4 * i + 4)
                    out_xc[:, k], out_Pc[:, k] = compensate(chosen, bias[:, block], bias_cov[:, block, block])
                else:
                    out_xc[:, k], out_Pc[:, k] = chosen.state, chosen.covariance
        return BiasRegistrationResult(
            reports.time.copy(), reports.sensor.copy(), out_bias, out_bias_cov, selected, out_x, out_P, out_xc,
            out_Pc, _time.perf_counter() - started, out_nis, out_nis_dof)


class PseudoBiasRegistration(LocalTracking):
    """The paper's proposal: pseudo bias measurements from the other radars' biased local tracks
    (eqs 22-32), least squares over the stacked bias (eqs 33-36), compensation (eqs 37-41).

    Extra parameter ``correlated_pseudo_noise``: with S > 2 radars the S-1 pseudo measurements of
    one report share the reporting radar's noise w_i, so their exact joint covariance has R^m_i
    off the diagonal (literature notes 5.2); False treats them as independent, as the seed
    does. With S = 2 there is one pseudo measurement per target and the switch changes nothing.
    """

    estimates_bias = True

    def __init__(self, name: str = "proposed", correlated_pseudo_noise: bool = True, **kwargs) -> None:
        super().__init__(name=name, **kwargs)
        self.correlated_pseudo_noise = bool(correlated_pseudo_noise)

    def _bias_step(self, state, i, t, z_converted, noise, bias_columns, tracks, last_time):
        if tracks[i] is None and self.start == "two_point":
            return state, False                  # the reporting radar has no track yet
        others = [j for j in range(len(tracks)) if j != i and tracks[j] is not None]
        if not others:
            return state, False
        z, H, Rb = pseudo_bias_measurements(i, z_converted, noise, bias_columns, [tracks[j] for j in others],
                                            others, t - last_time[others], self.process_noise_density,
                                            len(tracks), self.correlated_pseudo_noise, self.engine)
        return replace(state, information=add_pseudo_measurements(state.information, z, H, Rb)), True


def pseudo_bias_measurements(i: int, z_converted: np.ndarray, noise: np.ndarray, bias_columns: np.ndarray,
                             other_tracks: Sequence[LocalTracks], others: Sequence[int], elapsed: np.ndarray,
                             density: float, sensors: int, correlated: bool = True, engine: str = "numpy"
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stacked pseudo bias measurements of radar i's report (eqs 22-32).

    For each other radar j (track ``other_tracks``, last updated ``elapsed`` seconds ago):
    z^b = z^m_i - H Phi X^b_j (eq 22), H^b = [.. B_i C_i (block i) .. -H Phi G_j (block j) ..]
    (eqs 25, 31), R^b = H P_j(t_k|t_j) H' + R^m_i (eq 27). Returns z (R, T, 2J), H (R, T, 2J, 4S),
    noise (R, T, 2J, 2J) for J = len(others); ``correlated`` puts R^m_i in the off-diagonal blocks.
    """
    J = len(others)
    R, T = z_converted.shape[:2]
    z = np.empty((R, T, 2 * J))
    H = np.zeros((R, T, 2 * J, 4 * sensors))
    Rb = np.zeros((R, T, 2 * J, 2 * J))
    for row, (j, track, dt) in enumerate(zip(others, other_tracks, elapsed)):
        rows = slice(2 * row, 2 * row + 2)
        predicted_state, predicted_cov, predicted_G = _cv_move(track.state, track.covariance, track.bias_matrix,
                                                                float(dt), density, engine)
        z[..., rows] = z_converted - predicted_state[..., :2]                    # eq 22
        H[..., rows, 4 * i:4 * i + 4] = bias_columns                             # eq 25, block i
        H[..., rows, 4 * j:4 * j + 4] = -predicted_G[..., :2, :]                 # eq 25, block j: -H Phi G_j
        Rb[..., rows, rows] = predicted_cov[..., :2, :2] + noise                 # eq 27
        if correlated:
            for col in range(J):
                if col != row:
                    Rb[..., rows, 2 * col:2 * col + 2] = noise
    return z, H, Rb


class EXXRegistration(LocalTracking):
    """EXX (Lin, Bar-Shalom & Kirubarajan 2005) as reconstructed in the literature notes 5.4.

    Reports are gathered into proper time slots of three consecutive reports holding two reports
    of one radar A (t1 < t2) and one of another radar B (t_b); each measurement is used in one
    slot only, so slots give white pseudo measurements. With a1 = (t2 - t_b)/(t2 - t1) and
    a2 = (t_b - t1)/(t2 - t1), the CV state cancels exactly from
    zeta = z^m_B - a1 z^m_A(t1) - a2 z^m_A(t2) = B_B C_B beta_B - (a1 B_A C_A(t1) + a2 B_A C_A(t2)) beta_A + e,
    Cov(e) = R^m_B + a1^2 R^m_A(t1) + a2^2 R^m_A(t2) + V I2, with the process-noise term
    V = q d1^2 d2^2 / (3 (d1 + d2)) for interpolation (d1 = t_b - t1, d2 = t2 - t_b) and
    V = q E^2 (D + E) / 3 for extrapolation by E beyond an end of D = t2 - t1. The bias estimate
    is the least squares with the same prior as the proposed method, updated when a slot
    completes (between slots it waits: the latency the seed criticises). For the seed's two
    1 Hz radars offset by 0.5 s this gives the notes' alternating slots
    {B(0.5), A(1), B(1.5)}, {A(2), B(2.5), A(3)}, ... with V = q/48. B, C and R^m of each
    measurement are those of its radar's predicted local track at that report (spec 002);
    the local tracks serve only that and the compensation.
    """

    estimates_bias = True

    def __init__(self, name: str = "exx", **kwargs) -> None:
        super().__init__(name=name, **kwargs)

    def _bias_step(self, state, i, t, z_converted, noise, bias_columns, tracks, last_time):
        slot = state.slot + ((i, t, z_converted, noise, bias_columns),)
        if len(slot) < 3:
            return replace(state, slot=slot), False
        pseudo = exx_pseudo_measurement(slot, self.process_noise_density, state.sensors)
        if pseudo is None:
            return replace(state, slot=slot[1:]), False   # not a proper slot: slide by one report
        return replace(state, information=add_pseudo_measurements(state.information, *pseudo), slot=()), True


def exx_process_noise(t1: float, t2: float, t_b: float, density: float) -> float:
    """Per-axis variance of the CV process noise left in p(t_b) - a1 p(t1) - a2 p(t2) (notes 5.4)."""
    D = t2 - t1
    if t1 <= t_b <= t2:
        d1, d2 = t_b - t1, t2 - t_b
        return density * d1**2 * d2**2 / (3.0 * D)
    E = t_b - t2 if t_b > t2 else t1 - t_b
    return density * E**2 * (D + E) / 3.0


def exx_pseudo_measurement(slot, density: float, sensors: int):
    """zeta, H_zeta, R_zeta (each batched (R, T, ...)) of a 3-report slot, or None when the slot
    does not hold two distinct-time reports of one radar and one report of another."""
    ids = [entry[0] for entry in slot]
    for a in set(ids):
        if ids.count(a) == 2 and len(set(ids)) == 2:
            (_, t1, z1, n1, bc1), (_, t2, z2, n2, bc2) = [entry for entry in slot if entry[0] == a]
            (b, t_b, z_b, n_b, bc_b), = [entry for entry in slot if entry[0] != a]
            if t2 == t1:
                return None
            a1, a2 = (t2 - t_b) / (t2 - t1), (t_b - t1) / (t2 - t1)
            zeta = z_b - a1 * z1 - a2 * z2
            R, T = zeta.shape[:2]
            H = np.zeros((R, T, 2, 4 * sensors))
            H[..., 4 * a:4 * a + 4] = -(a1 * bc1 + a2 * bc2)
            H[..., 4 * b:4 * b + 4] = bc_b
            noise = n_b + a1**2 * n1 + a2**2 * n2 + exx_process_noise(t1, t2, t_b, density) * np.eye(2)
            return zeta, H, noise
    return None
