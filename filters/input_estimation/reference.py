"""Modified input estimation (MIE) with pseudo-residuals on a Singer-type tracking filter (seed 000).

Two base filters, both batched over Monte Carlo runs:

- ``InertialMIE`` (filters A and A-full): a coupled 9-state Kalman filter in inertial Cartesian
  coordinates on converted measurements with their full covariance R_I = J R_p J' (notes 2.1);
  the MIE works with full 3x3 matrices.
- ``LOSMIE`` (filters B and C): the decoupled tracking filter in line-of-sight coordinates
  (eqs 3-16): three independent per-axis 3-state filters, the frame re-pointed at the predicted
  position every scan; the MIE is computed per axis with scalars (eq 23's decoupling), which is
  where the saving is.

State layout inside: (R, axis, kinematic) with kinematic = (p, v, a); outputs are inertial,
ordered (x, y, z, vx, vy, vz, ax, ay, az). The filters work in radar-centred coordinates (the LOS
frame points from the radar) and add ``measurements.sensor_position`` back to the output positions.

MIE per scan k (notes 2.4, A-H): l onset hypotheses n in [max(k - l - N_id + 1, k_c), k - N_id]
over the data window k - l - N_id + 2..k (spec 000: l = 5 candidate onset times); innovations score the samples i <= n, pseudo-residuals (eq 26) the samples i > n;
the input estimate (eq 28) is the new absolute level, L(n) (eq 29) picks n_hat, the test (eq 31)
compares the level change with its covariance (eq 32, sandwich form with eq 33's correlations),
and a detection compensates state (eq 34), covariance (eq 37, with M Cov M', the printed inverse
is a typo), level (eq 38) and, in the LOS filter, re-points the frame (eqs 39-44).

Closed-loop stability (spec 000, designed here): implemented literally, the detect-compensate
loop re-detects a sign-flipped correction every N_id steps and runs away (669 detections in
t = 75-100 at 100 runs; spec: ~750). Three changes make it stable:

1. the test re-arms only after ``rearm_after`` scans of new data since the last compensation k_c
   (default: the full data window, l + N_id - 1), and hypotheses never reach back before k_c;
2. the old level is not exact in eq 31. A compensation sets it from an estimate with covariance
   Sigma_old, and its error eps also biases the compensated velocity by J_v eps (J, the state's
   sensitivity to a level error, is tracked through every scan), hence the new estimate by
   -c T J_v eps with c = sum N/S / sum N^2/S. So Delta = u_hat - u_old has error xi - G eps with
   G = I + c T J_v, and the test uses Cov(Delta) = Sigma_u + G Sigma_old G' (eq 32's cross
   terms between the old level and the compensated velocity). A new level's covariance keeps the
   old error's share, (G - I) Sigma_old (G - I)';
3. because a wrong level would then be shielded from correction, a quiet test still learns from
   Delta: once per window of new data the MMSE estimate of eps given Delta is removed from the
   level (and through J from the state), and Sigma_old shrinks to its posterior ("soft update",
   on with level_uncertainty and level_correlation; per LOS axis in B and C, full 3x3 in A).

Engines: ``engine="numba"`` (the default) runs each run's scans in one compiled loop
(filters/input_estimation/kernel.py; LOSMIE's GLS variant, ``pseudo_residual_covariance="full"``, excepted);
``engine="numpy"`` is the vectorised scan loop below, the reference. They agree to rounding with the
same detections (tests/test_mie_kernel.py); compiled, B costs ~half of A as the spec says of the
work, where numpy's per-scan overhead had hidden it (benchmarks/bench_study000.py).

Without 3, wrong levels persist: B's position RMSE over t = 61-100 was 55.5 m against 39.6 m with
compensation off; with it 43.0 m, and B detects 0.13 times per run after t = 75.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np

from filters.base import MeasurementSeries, TrackEstimate, checked_engine
from filters.compiling import compiling
from filters.coordinates import (converted_covariance, line_of_sight_angles, los_noise_variances, los_rotation,
                                 polar_to_cartesian)
from filters.kalman import einsum, rows_times
from filters.models import singer_input_gain, singer_process_noise, singer_transition
from filters.progress import counted, counted_runs

# (axis, kinematic) -> inertial output order (x, y, z, vx, vy, vz, ax, ay, az)
_KIN_MAJOR = [a * 3 + kin for kin in range(3) for a in range(3)]


def _nis_extras(nis: np.ndarray, dof: int) -> dict[str, np.ndarray]:
    """The filter's own innovation at each scan from 2 on (the update's residual, eqs 8-11, with its covariance,
    before any compensation): NaN at the two-point start (scans 0, 1)."""
    nis = np.array(nis, dtype=float)
    nis[:, :2] = np.nan
    return {"nis": nis, "nis_dof": np.where(np.isfinite(nis), float(dof), 0.0)}


class _MIEBase:
    accepts = frozenset({"range_azimuth_elevation"})   # converted in the filter (notes 2.1)
    name: str
    TESTS: tuple[str, ...] = ()
    RUNS_PER_CALL = 8             # progress is told between calls of the compiled loop

    def __init__(self, name: str, tau: float, sigma_m: float, window: int, min_samples: int, threshold: float,
                 test: str, rearm_after: int | None, level_uncertainty: bool, compensate: bool,
                 level_correlation: bool, engine: str = "numba") -> None:
        checked_engine(engine, "the compiled loop, filters/input_estimation/kernel.py")
        if test not in self.TESTS:
            raise ValueError(f"test: {test!r} is not one of {list(self.TESTS)}")
        if not (np.isfinite(tau) and tau > 0):
            raise ValueError(f"tau: {tau} must be a finite number > 0 s")
        if not (np.isfinite(sigma_m) and sigma_m > 0):
            raise ValueError(f"sigma_m: {sigma_m} must be a finite number > 0 m/s^2")
        if not (isinstance(window, int) and isinstance(min_samples, int) and 1 <= min_samples <= window):
            raise ValueError(f"window, min_samples: need integers with 1 <= min_samples <= window, "
                             f"got window={window}, min_samples={min_samples}")
        if not threshold > 0:
            raise ValueError(f"threshold: {threshold} must be > 0 (a chi-square quantile)")
        rearm = window + min_samples - 1 if rearm_after is None else rearm_after
        if not (isinstance(rearm, int) and rearm >= min_samples):
            raise ValueError(f"rearm_after: {rearm_after} must be an integer >= min_samples ({min_samples})")
        self.name = name
        self.tau, self.sigma_m = float(tau), float(sigma_m)
        self.window, self.min_samples = window, min_samples
        self.threshold = float(threshold)
        self.rearm_after = rearm
        self.level_uncertainty = bool(level_uncertainty)
        self.compensate = bool(compensate)
        self.level_correlation = bool(level_correlation)
        self.test = test
        self.engine = engine

    def _run_compiled(self, measurements: MeasurementSeries) -> TrackEstimate:
        """``run`` through the filter's loop in filters.input_estimation.kernel (``_compiled_loop``): each run's scans
        in one compiled loop, a block of runs per call (what differs from the numpy scans: rounding,
        see that module)."""
        from filters.input_estimation import kernel as mie_kernel

        with compiling("filters.input_estimation.kernel"):     # says so when numba compiles (the first job of an install)
            mie_kernel.warm_up()                    # numba's start before the clock: compute_seconds is the filtering's
        started = time.perf_counter()
        z, polar_var, dt = self._checked(measurements)
        self._model(dt)
        R, K, _ = z.shape
        outputs = _outputs(R, K)
        nis = np.full((R, K), np.nan)
        loop = self._compiled_loop(mie_kernel, z, polar_var, float(dt), outputs, nis)
        for first, stop in counted_runs(R, max(K - 2, 0), self.name, self.RUNS_PER_CALL):
            loop(first, stop)
        out_x, out_P, level_out, detected_out, axis_out, stat_out, onset_out = outputs
        extras = {"input_level": level_out, "maneuver_detected": detected_out, "test_statistic": stat_out,
                  "onset_step": onset_out, **_nis_extras(nis, 3)}
        if self.test == "per_axis":
            extras["maneuver_detected_axis"] = axis_out
        out_x += self._radar_offset(measurements)
        return TrackEstimate(measurements.time, out_x, out_P, extras, time.perf_counter() - started)

    def _compiled_loop(self, kernel, z: np.ndarray, polar_var: np.ndarray, dt: float, outputs: tuple, nis: np.ndarray):
        """``loop(first, stop)``: the kernel's pass over runs first..stop-1, writing ``outputs`` (``_outputs``)
        and ``nis``."""
        raise NotImplementedError

    def _kernel_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One axis's Singer F, Q (3, 3) and G (3,) as the kernels take them."""
        return tuple(np.ascontiguousarray(a, dtype=float) for a in (self.F, self.Q, self.G))

    def _model(self, dt: float) -> None:
        self.F = singer_transition(dt, self.tau)
        self.Q = singer_process_noise(dt, self.tau, self.sigma_m)
        self.G = singer_input_gain(dt, self.tau)
        self.dt = dt

    @staticmethod
    def _radar_offset(measurements: MeasurementSeries) -> np.ndarray:
        """(9,) added to the radar-centred outputs: the radar's position in the position slots."""
        offset = np.zeros(9)
        if measurements.sensor_position is not None:
            position = np.asarray(measurements.sensor_position, dtype=float)
            if position.shape != (3,):
                raise ValueError(f"measurements.sensor_position: shape {position.shape}; expected (3,) [x, y, z]")
            offset[:3] = position
        return offset

    @staticmethod
    def _checked(measurements: MeasurementSeries) -> tuple[np.ndarray, np.ndarray, float]:
        z = measurements.z
        if z.ndim != 3 or z.shape[-1] != 3:
            raise ValueError(f"measurements.z: shape {z.shape}; expected (runs, scans, 3) range/azimuth/elevation")
        if z.shape[1] < 2:
            raise ValueError("measurements: two-point initialisation needs at least 2 scans")
        if not measurements.detected.all():
            raise ValueError("measurements: missed detections are not supported by the MIE filters")
        dts = np.diff(measurements.time)
        if not np.allclose(dts, dts[0]):
            raise ValueError("measurements.time: the MIE filters need a constant scan period")
        noise = np.asarray(measurements.noise_covariance)
        if noise.ndim != 2:
            noise = noise.reshape(-1, 3, 3)[0]
        return z, np.diag(noise).copy(), float(dts[0])

    @property
    def _span(self) -> int:
        """Scans in the data window: the earliest of the l onset hypotheses sees all of them as pseudo-residuals."""
        return self.window + self.min_samples - 1

    def _hypotheses(self, k: int) -> list[int]:
        """Onset offsets d = k - n: the l = ``window`` candidate onset times n in [k - l - N_id + 1, k - N_id]
        (spec 000: "window l = 5 candidate onset times, N_id = 3 minimum samples"). Every hypothesis
        scores the same data window k - d_max + 1..k (innovations up to n, pseudo-residuals after),
        so the scores compare. k_c is applied per run."""
        return [d for d in range(self._span, self.min_samples - 1, -1) if k - d >= 1]


def _outputs(R: int, K: int) -> tuple[np.ndarray, ...]:
    """Every filter's per-scan outputs before any scan: state (R, K, 9) and covariance (R, K, 9, 9)
    NaN until a scan fills them, input level (R, K, 3) zero, detections (R, K) and per-axis
    detections (R, K, 3) none, test statistic NaN, onset -1."""
    return (np.full((R, K, 9), np.nan), np.full((R, K, 9, 9), np.nan), np.zeros((R, K, 3)),
            np.zeros((R, K), dtype=np.int8), np.zeros((R, K, 3), dtype=np.int8), np.full((R, K), np.nan),
            np.full((R, K), -1, dtype=np.int64))


class LOSMIE(_MIEBase):
    """Filters B and C: LOS decoupled tracking filter + per-axis modified input estimation.

    ``test``: ``pooled`` (B) sums the three per-axis statistics against chi2(3) with one onset
    time n_hat for all axes; ``per_axis`` (C) tests, picks n_hat, and compensates each LOS axis on
    its own against chi2(1), with a per-axis k_c.
    """

    TESTS = ("pooled", "per_axis")

    def __init__(self, name: str = "B", tau: float = 10.0, sigma_m: float = 5.0, window: int = 5,
                 min_samples: int = 3, threshold: float = 16.27, test: Literal["pooled", "per_axis"] = "pooled",
                 rearm_after: int | None = None, level_uncertainty: bool = True, compensate: bool = True,
                 level_correlation: bool = True,
                 pseudo_residual_covariance: Literal["diagonal", "full"] = "diagonal", engine: str = "numba") -> None:
        super().__init__(name, tau, sigma_m, window, min_samples, threshold, test, rearm_after, level_uncertainty,
                         compensate, level_correlation, engine)
        if pseudo_residual_covariance not in ("diagonal", "full"):
            raise ValueError(f"pseudo_residual_covariance: {pseudo_residual_covariance!r} is not one of "
                             f"['diagonal', 'full']")
        self.pseudo_residual_covariance = pseudo_residual_covariance

    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        # the compiled loop has the paper's diagonal pseudo-residual covariance; "full" (GLS) runs numpy
        if self.engine == "numba" and self.pseudo_residual_covariance == "diagonal":
            return self._run_compiled(measurements)
        started = time.perf_counter()
        z, polar_var, dt = self._checked(measurements)
        self._model(dt)
        F, Q, G = self.F, self.Q, self.G
        R, K, _ = z.shape
        zI = polar_to_cartesian(z)                                          # converted, inertial (R, K, 3)
        # history, indexed by scan
        frames = np.zeros((R, K, 3, 3))
        x_hist = np.zeros((R, K, 3, 3))
        pvv_hist = np.zeros((R, K, 3))
        nu_hist = np.zeros((R, K, 3))
        s_hist = np.ones((R, K, 3))
        r_hist = np.zeros((R, K, 3))
        gain_hist = np.zeros((R, K, 3, 3))
        out_x, out_P, level_out, detected_out, axis_out, stat_out, onset_out = _outputs(R, K)

        # ---- k = 1: two-point start in the LOS frame of z_I(1) (P's 3x3 blocks diagonal, eq 16 note)
        rng1, phi1, th1 = line_of_sight_angles(zI[:, 1])
        T = los_rotation(phi1, th1)
        x = np.zeros((R, 3, 3))
        x[:, :, 0] = einsum("rab,rb->ra", T, zI[:, 1])
        x[:, :, 1] = einsum("rab,rb->ra", T, zI[:, 1] - zI[:, 0]) / dt
        Rd = los_noise_variances(rng1, th1, polar_var)
        P = np.zeros((R, 3, 3, 3))
        P[:, :, 0, 0], P[:, :, 0, 1] = Rd, Rd / dt
        P[:, :, 1, 0], P[:, :, 1, 1] = Rd / dt, 2 * Rd / dt**2
        P[:, :, 2, 2] = self.sigma_m**2
        u = np.zeros((R, 3))                       # input level in the current frame
        level_cov = np.zeros((R, 3, 3))            # its covariance, current frame
        k_c = np.ones((R, 3), dtype=np.int64)      # last compensation (track start) per axis
        sens = np.zeros((R, 3, 3, 3))              # d x / d (level error), current frame (axis, kin, input)
        sens_v_hist = np.zeros((R, K, 3, 3))       # its velocity rows (axis, input) per scan
        frames[:, 1], x_hist[:, 1], pvv_hist[:, 1], r_hist[:, 1] = T, x, P[:, :, 1, 1], Rd
        self._output(out_x, out_P, level_out, 1, x, P, T, u)

        for k in counted(range(2, K), "scan", self.name):
            # eqs 3-4 (+ G u, as in eq 17): propagate in frame k-1, each axis on its own
            x = x @ F.T + u[:, :, None] * G
            P = F @ P @ F.T + Q
            # eqs 5-7, twist-free (notes 2.3): T(k) from the inertial angles of the prediction
            p_inertial = einsum("rab,ra->rb", T, x[:, :, 0])
            rng, phi, th = line_of_sight_angles(p_inertial)
            T_new = los_rotation(phi, th)
            dT = T_new @ np.swapaxes(T, 1, 2)
            x = einsum("rab,rbk->rak", dT, x)
            u = einsum("rab,rb->ra", dT, u)
            level_cov = dT @ level_cov @ np.swapaxes(dT, 1, 2)
            T = T_new
            # eqs 8-11, 15: per-axis scalar update with the diagonal LOS noise
            zL = einsum("rab,rb->ra", T, zI[:, k])
            Rd = los_noise_variances(rng, th, polar_var)
            S = P[:, :, 0, 0] + Rd
            gain = P[:, :, :, 0] / S[:, :, None]
            nu = zL - x[:, :, 0]
            x = x + gain * nu[:, :, None]
            P = P - gain[:, :, :, None] * gain[:, :, None, :] * S[:, :, None, None]
            # the state's sensitivity to an error in the level follows the filter's linear response
            sens = self._respond(sens, dT, gain)
            frames[:, k], x_hist[:, k], pvv_hist[:, k] = T, x, P[:, :, 1, 1]
            nu_hist[:, k], s_hist[:, k], r_hist[:, k], gain_hist[:, k] = nu, S, Rd, gain
            sens_v_hist[:, k] = sens[:, :, 1, :]

            hyps = self._hypotheses(k)
            armed = (k - k_c) >= self.rearm_after                                 # (R, 3)
            if hyps and armed.any():
                x, P, u, level_cov, T, k_c, sens, det_axes, stat, onset = self._mie(
                    k, hyps, armed, x, P, u, level_cov, T, k_c, sens, zI, frames, x_hist, pvv_hist, nu_hist,
                    s_hist, r_hist, gain_hist, sens_v_hist)
                detected_out[:, k] = det_axes.any(axis=1)
                axis_out[:, k] = det_axes
                stat_out[:, k] = stat
                onset_out[:, k] = onset
                frames[:, k], x_hist[:, k], pvv_hist[:, k] = T, x, P[:, :, 1, 1]
                sens_v_hist[:, k] = sens[:, :, 1, :]
            self._output(out_x, out_P, level_out, k, x, P, T, u)

        extras = {"input_level": level_out, "maneuver_detected": detected_out, "test_statistic": stat_out,
                  "onset_step": onset_out, **_nis_extras(np.sum(nu_hist**2 / s_hist, axis=-1), 3)}
        if self.test == "per_axis":
            extras["maneuver_detected_axis"] = axis_out
        out_x += self._radar_offset(measurements)
        return TrackEstimate(measurements.time, out_x, out_P, extras, time.perf_counter() - started)

    def _compiled_loop(self, kernel, z, polar_var, dt, outputs, nis):
        zI = np.ascontiguousarray(polar_to_cartesian(z), dtype=float)
        F, Q, G = self._kernel_model()
        polar_var = np.ascontiguousarray(polar_var, dtype=float)
        return lambda first, stop: kernel.los_mie(
            first, stop, zI, polar_var, F, Q, G, dt, self.sigma_m, self._span, self.min_samples, self.rearm_after,
            self.threshold, self.test == "per_axis", self.level_uncertainty, self.compensate, self.level_correlation,
            *outputs, nis)

    @staticmethod
    def _output(out_x, out_P, level_out, k, x, P, T, u) -> None:
        """LOS frame -> inertial: x_I = T' x, P_I = T9' blkdiag(P_a) T9, in kin-major order."""
        R = x.shape[0]
        out_x[:, k] = einsum("rab,rak->rkb", T, x).reshape(R, 9)
        out_P[:, k] = einsum("rac,rakl,rad->rkcld", T, P, T).reshape(R, 9, 9)
        level_out[:, k] = einsum("rab,ra->rb", T, u)

    def _respond(self, sens: np.ndarray, dT: np.ndarray, gain: np.ndarray) -> np.ndarray:
        """One scan of d x / d eps for a level error eps held in the (rotating) LOS frame:
        x^k = (I - K H) dT9 [F x^{k-1} + G u^{k-1}] and eps^{k-1} = dT' eps^k."""
        Y = einsum("kl,ralj->rakj", self.F, sens) + self.G[None, None, :, None] * np.eye(3)[None, :, None, :]
        Y = einsum("rab,rbkj->rakj", dT, Y)
        Y = einsum("rakm,rjm->rakj", Y, dT)
        return Y - gain[:, :, :, None] * Y[:, :, 0:1, :]

    def _mie(self, k, hyps, armed, x, P, u, level_cov, T, k_c, sens, zI, frames, x_hist, pvv_hist, nu_hist, s_hist,
             r_hist, gain_hist, sens_v_hist):
        """Scores, inputs and covariances of every onset hypothesis at once, per axis (scalars)."""
        dt = self.dt
        R = x.shape[0]
        rows = np.arange(R)
        D = self._span
        window = np.arange(k - D + 1, k + 1)                                   # scans i of the data window
        onsets = k - np.asarray(hyps)                                          # (H,)
        pseudo = window[None, :] > onsets[:, None]                             # (H, D): i > n
        innov_mask = (~pseudo) & (window[None, :] >= 2)
        # innovations of the samples i <= n (eq 24, first sum)
        q = nu_hist[:, window] ** 2 / s_hist[:, window]                        # (R, D, 3)
        innov = einsum("hd,rda->hra", innov_mask, q)
        # pseudo-residuals in frame n (eq 26) and their decoupled covariance (eq 23)
        Tn = frames[:, onsets]                                                 # (R, H, 3, 3)
        v_n = x_hist[:, onsets][:, :, :, 1]                                    # (R, H, 3)
        tpvv = dt * dt * pvv_hist[:, onsets]                                   # (R, H, 3)
        dz = zI[:, window] - zI[:, window - 1]                                 # (R, D, 3)
        e = einsum("rhab,rdb->rhda", Tn, dz) - dt * v_n[:, :, None, :]      # (R, H, D, 3)
        S = tpvv[:, :, None, :] + r_hist[:, window][:, None] + r_hist[:, window - 1][:, None]
        N = np.where(pseudo, (window[None, :] - onsets[:, None] - 0.5) * dt * dt, 0.0)   # eq 25 (notes 2.4)
        if self.pseudo_residual_covariance == "diagonal":
            Wt = N[None, :, :, None] / S                                       # N_i / S_i, zero for i <= n
            A = (N[None, :, :, None] * Wt).sum(axis=2)                         # (R, H, 3)
            b = (Wt * e).sum(axis=2)
            quad = (pseudo[None, :, :, None] * e * e / S).sum(axis=2)
            u_hat = b / A                                                      # eq 28, per axis
            # eq 32 with eq 33: sum_{i<j} 2 W_i C_ij W_j, C_ij = T^2 P_vv(n) - R(i) [j = i + 1]
            w_sum = Wt.sum(axis=2)
            adjacent = (Wt[:, :, :-1] * Wt[:, :, 1:] * r_hist[:, window[:-1]][:, None]).sum(axis=2)
            cross = tpvv * (w_sum * w_sum - (Wt * Wt).sum(axis=2)) - 2.0 * adjacent
            sigma_u = 1.0 / A + cross / (A * A)
        else:
            A, u_hat, quad, w_sum, sigma_u = self._gls(e, N, pseudo, tpvv, window, onsets, r_hist, gain_hist)
        L = -0.5 * np.moveaxis(innov, 0, 1) - 0.5 * quad + 0.5 * u_hat * u_hat * A     # eqs 29-30
        # the old level and its covariance seen in frame n
        rot = Tn @ np.swapaxes(T, 1, 2)[:, None]                               # (R, H, 3, 3)
        u_old = einsum("rhab,rb->rha", rot, u)
        cov_n = rot @ level_cov[:, None] @ np.swapaxes(rot, 2, 3)
        if self.level_correlation:
            # Delta's error = xi - (I + c T J_v(n)) eps: the compensated velocity v_hat(n) carries
            # J_v(n) eps and biases u_hat by -c T J_v(n) eps (c = sum N/S / sum N^2/S)
            gain_eps = np.eye(3) + (w_sum / A)[..., None] * dt * sens_v_hist[:, onsets]
            old_var = einsum("rhab,rhbc,rhac->rha", gain_eps, cov_n, gain_eps)
        else:
            gain_eps = np.broadcast_to(np.eye(3), cov_n.shape)
            old_var = np.diagonal(cov_n, axis1=2, axis2=3)
        valid = armed[:, None, :] & (onsets[None, :, None] >= k_c[:, None, :])
        # (H, R, 3) for the selection below
        scores, inputs, variances = (np.moveaxis(a, 1, 0) for a in (L, u_hat, sigma_u))
        valid, olds, old_vars = (np.moveaxis(a, 1, 0) for a in (valid, u_old, old_var))
        test_var = variances + (old_vars if self.level_uncertainty else 0.0)
        if self.test == "pooled":
            total = np.where(valid.all(axis=2), scores.sum(axis=2), -np.inf)                   # (H, R)
            best = np.argmax(total, axis=0)                                                    # (R,)
            ok = np.isfinite(total[best, rows])
            best_axes = np.broadcast_to(best[:, None], (R, 3))
            delta = inputs[best, rows] - olds[best, rows]
            stat = (delta * delta / test_var[best, rows]).sum(axis=1)
            det = ok & (stat > self.threshold)
            det_axes = np.broadcast_to(det[:, None], (R, 3)).copy()
            stat = np.where(ok, stat, np.nan)
            quiet = np.broadcast_to((ok & ~det)[:, None], (R, 3))
        else:
            masked = np.where(valid, scores, -np.inf)
            best_axes = np.argmax(masked, axis=0)                                              # (R, 3)
            ok = np.isfinite(self._pick(masked, best_axes))
            delta = self._pick(inputs, best_axes) - self._pick(olds, best_axes)
            stat_axes = delta * delta / self._pick(test_var, best_axes)
            det_axes = ok & (stat_axes > self.threshold)
            stat = np.where(ok.any(axis=1), np.where(ok, stat_axes, -np.inf).max(axis=1), np.nan)
            quiet = ok & ~det_axes
        axis_onsets = k - np.asarray(hyps)[best_axes]                           # (R, 3) n_hat per axis
        onset = np.where(det_axes, axis_onsets, np.iinfo(np.int64).max).min(axis=1)   # earliest detecting axis
        onset = np.where(det_axes.any(axis=1), onset, -1)
        if self.compensate and self.level_uncertainty and self.level_correlation:
            # The test treats the old level's error eps as noise, so an error below ~4 sigma_old is never
            # corrected by a detection. Delta = xi - G eps carries information on eps: when the test does
            # not fire, take the MMSE estimate of eps (once per window of new data), remove it from the level
            # and, through the tracked sensitivity J, from the state, and shrink the level's covariance.
            soft = quiet & ((k - k_c) % self.rearm_after == 0)
            if soft.any():
                g = self._pick(np.moveaxis(np.diagonal(gain_eps, axis1=2, axis2=3), 1, 0), best_axes)
                s_old = self._pick(np.moveaxis(np.diagonal(cov_n, axis1=2, axis2=3), 1, 0), best_axes)
                s_new = self._pick(variances, best_axes)
                denom = g * g * s_old + s_new
                eps_n = np.where(soft, -g * s_old * delta / np.where(denom > 0, denom, 1.0), 0.0)
                post = s_old - (g * s_old) ** 2 / np.where(denom > 0, denom, 1.0)
                eps_k = np.zeros_like(u)
                for h, d in enumerate(hyps):
                    on_h = soft & (best_axes == h)
                    if on_h.any():
                        eps_k += einsum("rab,rb->ra", T @ np.swapaxes(frames[:, k - d], 1, 2), eps_n * on_h)
                u = u - eps_k
                x = x - einsum("rakj,rj->rak", sens, eps_k)
                # the update is per axis, i.e. treats the axes' level errors as independent: keep the level
                # covariance diagonal for these runs (the diagonal of a PSD matrix is PSD; writing only the
                # diagonal beside stale off-diagonal terms can make it indefinite)
                diag = np.diagonal(level_cov, axis1=1, axis2=2)
                touched = soft.any(axis=1)
                new_diag = np.where(soft, np.maximum(post, 0.0), diag)
                level_cov = np.where(touched[:, None, None], einsum("ra,ab->rab", new_diag, np.eye(3)), level_cov)
        if not (self.compensate and det_axes.any()):
            return x, P, u, level_cov, T, k_c, sens, det_axes, stat, onset

        # ---- compensation (eqs 34-44) for the detected (run, axis) pairs --------------------------
        delta = np.where(det_axes, delta, 0.0)
        sigma = np.where(det_axes, self._pick(variances, best_axes), 0.0)
        if self.level_uncertainty and self.level_correlation:
            # the new level's error is xi - (G - I) eps: keep (G - I) Sigma_old (G - I)' in its covariance
            Kc = gain_eps - np.eye(3)
            sigma_level = sigma + np.where(det_axes, self._pick(np.moveaxis(
                einsum("rhab,rhbc,rhac->rha", Kc, cov_n, Kc), 1, 0), best_axes), 0.0)
        else:
            sigma_level = sigma
        dx = np.zeros_like(x)
        dP = np.zeros_like(P)
        du = np.zeros_like(u)
        new_cov = np.zeros((R, 3))
        for h, d in enumerate(hyps):
            use = det_axes & (best_axes == h)                                                   # (R, 3) inputs
            if not use.any():
                continue
            n = k - d
            hit = np.flatnonzero(use.any(axis=1))                       # only the runs that compensate
            M = np.zeros((R, 3, 3, 3))
            M[hit] = self._gain_matrix(n, k, frames[hit], gain_hist[hit])                      # (R, a, kin, j)
            M = M * use[:, None, None, :]
            # the new level's error enters the state through M (in frame n): re-express it in frame k
            sens = np.where(use[:, None, None, :], 0.0, sens) + einsum(
                "rakm,rjm->rakj", M, T @ np.swapaxes(frames[:, n], 1, 2))
            dx += einsum("rakj,rj->rak", M, delta)
            dP += einsum("rakj,rj,ralj->rakl", M, sigma, M)                                  # eq 37, per-axis blocks
            du += einsum("rab,rb->ra", T @ np.swapaxes(frames[:, n], 1, 2), delta * use)     # eq 38
            new_cov += np.where(use, sigma_level, 0.0)
        x, P, u = x + dx, P + dP, u + du
        # the level's covariance: the detected axes' estimates replace the old ones
        keep = ~det_axes
        level_cov = level_cov * (keep[:, :, None] & keep[:, None, :]) + einsum("ra,ab->rab", new_cov, np.eye(3))
        # eqs 39-44: re-point the frame at the compensated position (P is not rotated)
        moved = det_axes.any(axis=1)
        _, dphi, dth = line_of_sight_angles(x[:, :, 0])
        dTu = np.where(moved[:, None, None], los_rotation(dphi, dth), np.eye(3))
        x = einsum("rab,rbk->rak", dTu, x)
        u = einsum("rab,rb->ra", dTu, u)
        level_cov = dTu @ level_cov @ np.swapaxes(dTu, 1, 2)
        sens = einsum("rab,rbkm,rjm->rakj", dTu, sens, dTu)
        T = dTu @ T
        k_c = np.where(det_axes if self.test == "per_axis" else moved[:, None], k, k_c)
        return x, P, u, level_cov, T, k_c, sens, det_axes, stat, onset

    @staticmethod
    def _pick(per_hypothesis: np.ndarray, best_axes: np.ndarray) -> np.ndarray:
        """(H, R, 3) -> (R, 3): each (run, axis) at its chosen onset hypothesis."""
        return np.take_along_axis(per_hypothesis, best_axes[None], axis=0)[0]

    def _gls(self, e, N, pseudo, tpvv, window, onsets, r_hist, gain_hist):
        """Generalised least squares over each hypothesis' correlated pseudo-residuals (per axis, D x D).

        Eqs 28-30 weight the pseudo-residuals by their variances alone, i.e. as if independent; they
        are not (eq 33: adjacent ones share z(i), all share v_hat(n)), and z(n) also enters both
        v_hat(n), through the velocity gain K_v(n), and e(n+1), which eq 33 drops:
        C_ii = T^2 P_vv(n) + R(i) + R(i-1), C_i,i+1 = T^2 P_vv(n) - R(i), C_ij = T^2 P_vv(n), plus
        T K_v(n) R(n) on row and column n+1. With C, u_hat = N'C^-1 e / N'C^-1 N has variance
        exactly 1 / N'C^-1 N, and the score compares hypotheses without favouring short ones.
        Costs batched D x D solves; off by default (the paper's reading)."""
        dt = self.dt
        D = window.size
        first = (window[None, :] == onsets[:, None] + 1).astype(float)              # (H, D): i = n + 1
        tkr = dt * gain_hist[:, onsets][:, :, :, 1] * r_hist[:, onsets]             # (R, H, 3)
        r_i = np.moveaxis(r_hist[:, window], 2, 1)[:, None]                         # (R, 1, 3, D)
        r_im1 = np.moveaxis(r_hist[:, window - 1], 2, 1)[:, None]
        C = np.broadcast_to(tpvv[..., None, None], tpvv.shape + (D, D)).copy()    # (R, H, 3, D, D)
        C += np.eye(D) * (r_i + r_im1)[..., None, :]
        C -= np.eye(D, k=1) * r_i[..., :, None] + np.eye(D, k=-1) * r_i[..., None, :]
        C += tkr[..., None, None] * (first[None, :, None, :, None] + first[None, :, None, None, :])
        both = pseudo[:, :, None] & pseudo[:, None, :]
        C = np.where(both[None, :, None], C, np.eye(D))                             # unit rows for i <= n
        Nv = np.broadcast_to(N[None, :, None, :], C.shape[:-1])
        ev = np.where(pseudo[None, :, None, :], np.moveaxis(e, 3, 2), 0.0)
        sol = np.linalg.solve(C, np.stack([Nv, ev], axis=-1))
        CiN, Cie = sol[..., 0], sol[..., 1]
        A = einsum("rhad,rhad->rha", Nv, CiN)
        u_hat = einsum("rhad,rhad->rha", CiN, ev) / A
        quad = einsum("rhad,rhad->rha", ev, Cie)
        return A, u_hat, quad, CiN.sum(axis=3), 1.0 / A

    def _gain_matrix(self, n: int, k: int, frames: np.ndarray, gain_hist: np.ndarray) -> np.ndarray:
        """M_n(k) (R, axis, kin, input) by the exact recursion of notes 2.4 H (eq 19 with the rotations):
        M <- B; for i = n+1..k: M <- (I - K(i) H) dT9(i/i-1) [F M + G dT3(i-1/n)]."""
        R = frames.shape[0]
        M = np.zeros((R, 3, 3, 3))
        M[:, [0, 1, 2], 2, [0, 1, 2]] = 1.0
        Tn_t = np.swapaxes(frames[:, n], 1, 2)
        for i in range(n + 1, k + 1):
            Y = einsum("kl,ralj->rakj", self.F, M) + self.G[None, None, :, None] * (frames[:, i - 1] @ Tn_t)[:, :, None, :]
            dT = frames[:, i] @ np.swapaxes(frames[:, i - 1], 1, 2)
            Y = einsum("rab,rbkj->rakj", dT, Y)
            M = Y - gain_hist[:, i][:, :, :, None] * Y[:, :, 0:1, :]
        return M


class InertialMIE(_MIEBase):
    """Filters A and A-full: coupled inertial 9-state KF on converted measurements + MIE with
    full 3x3 matrices (the frame is the identity: T3 = I, dT3 = I).

    ``test``: ``per_axis_sum`` (A, the paper's reading) sums the per-axis normalised squares
    Delta_a^2 / Cov_aa against chi2(3), as if the axes were independent; ``full`` (A-full) uses
    Delta' Cov^-1 Delta.
    """

    TESTS = ("per_axis_sum", "full")

    def __init__(self, name: str = "A", tau: float = 10.0, sigma_m: float = 5.0, window: int = 5,
                 min_samples: int = 3, threshold: float = 16.27,
                 test: Literal["per_axis_sum", "full"] = "per_axis_sum", rearm_after: int | None = None,
                 level_uncertainty: bool = True, compensate: bool = True, level_correlation: bool = True,
                 engine: str = "numba") -> None:
        super().__init__(name, tau, sigma_m, window, min_samples, threshold, test, rearm_after, level_uncertainty,
                         compensate, level_correlation, engine)

    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        if self.engine == "numba":
            return self._run_compiled(measurements)
        started = time.perf_counter()
        z, polar_var, dt = self._checked(measurements)
        self._model(dt)
        F9 = np.kron(np.eye(3), self.F)
        Q9 = np.kron(np.eye(3), self.Q)
        G9 = np.kron(np.eye(3), self.G[:, None])                         # (9, 3): level -> state
        pos, vel = [0, 3, 6], [1, 4, 7]
        R, K, _ = z.shape
        zI = polar_to_cartesian(z)
        RI = converted_covariance(z, polar_var)                          # at the measured (r, phi, theta)
        x_hist = np.zeros((R, K, 9))
        pvv_hist = np.zeros((R, K, 3, 3))
        nu_hist = np.zeros((R, K, 3))
        sinv_hist = np.zeros((R, K, 3, 3))
        gain_hist = np.zeros((R, K, 9, 3))
        out_x, out_P, level_out, detected_out, _, stat_out, onset_out = _outputs(R, K)

        x = np.zeros((R, 9))
        x[:, pos] = zI[:, 1]
        x[:, vel] = (zI[:, 1] - zI[:, 0]) / dt
        P = np.zeros((R, 9, 9))
        P[:, np.ix_(pos, pos)[0], np.ix_(pos, pos)[1]] = RI[:, 1]
        P[:, np.ix_(pos, vel)[0], np.ix_(pos, vel)[1]] = RI[:, 1] / dt
        P[:, np.ix_(vel, pos)[0], np.ix_(vel, pos)[1]] = RI[:, 1] / dt
        P[:, np.ix_(vel, vel)[0], np.ix_(vel, vel)[1]] = (RI[:, 1] + RI[:, 0]) / dt**2
        P[:, [2, 5, 8], [2, 5, 8]] = self.sigma_m**2
        u = np.zeros((R, 3))
        level_cov = np.zeros((R, 3, 3))
        k_c = np.ones(R, dtype=np.int64)
        sens = np.zeros((R, 9, 3))                 # d x / d (level error)
        sens_v_hist = np.zeros((R, K, 3, 3))
        x_hist[:, 1], pvv_hist[:, 1] = x, P[:, vel][:, :, vel]
        self._output(out_x, out_P, level_out, 1, x, P, u)
        for k in counted(range(2, K), "scan", self.name):
            x = rows_times(x, F9.T) + rows_times(u, G9.T)
            P = F9 @ P @ F9.T + Q9
            S = P[:, pos][:, :, pos] + RI[:, k]
            S_inv = np.linalg.inv(S)
            gain = P[:, :, pos] @ S_inv
            nu = zI[:, k] - x[:, pos]
            x = x + einsum("rij,rj->ri", gain, nu)
            P = P - gain @ S @ np.swapaxes(gain, 1, 2)
            P = 0.5 * (P + np.swapaxes(P, 1, 2))
            Y = F9 @ sens + G9                                          # the filter's response to a level error
            sens = Y - gain @ Y[:, pos]
            x_hist[:, k], pvv_hist[:, k] = x, P[:, vel][:, :, vel]
            nu_hist[:, k], sinv_hist[:, k], gain_hist[:, k] = nu, S_inv, gain
            sens_v_hist[:, k] = sens[:, vel]
            hyps = self._hypotheses(k)
            armed = (k - k_c) >= self.rearm_after
            if hyps and armed.any():
                x, P, u, level_cov, k_c, sens, det, stat, onset = self._mie(
                    k, hyps, armed, x, P, u, level_cov, k_c, sens, zI, RI, x_hist, pvv_hist, nu_hist, sinv_hist,
                    gain_hist, sens_v_hist, F9, G9)
                detected_out[:, k], stat_out[:, k], onset_out[:, k] = det, stat, onset
                x_hist[:, k], pvv_hist[:, k] = x, P[:, vel][:, :, vel]
                sens_v_hist[:, k] = sens[:, vel]
            self._output(out_x, out_P, level_out, k, x, P, u)
        extras = {"input_level": level_out, "maneuver_detected": detected_out, "test_statistic": stat_out,
                  "onset_step": onset_out, **_nis_extras(einsum("rki,rkij,rkj->rk", nu_hist, sinv_hist, nu_hist), 3)}
        out_x += self._radar_offset(measurements)
        return TrackEstimate(measurements.time, out_x, out_P, extras, time.perf_counter() - started)

    def _compiled_loop(self, kernel, z, polar_var, dt, outputs, nis):
        zI = np.ascontiguousarray(polar_to_cartesian(z), dtype=float)
        RI = np.ascontiguousarray(converted_covariance(z, polar_var), dtype=float)   # at the measured values
        F, Q, G = self._kernel_model()
        out_x, out_P, level_out, detected_out, _, stat_out, onset_out = outputs        # A has no per-axis test
        return lambda first, stop: kernel.inertial_mie(
            first, stop, zI, RI, F, Q, G, dt, self.sigma_m, self._span, self.min_samples, self.rearm_after,
            self.threshold, self.test == "full", self.level_uncertainty, self.compensate, self.level_correlation,
            out_x, out_P, level_out, detected_out, stat_out, onset_out, nis)

    @staticmethod
    def _output(out_x, out_P, level_out, k, x, P, u) -> None:
        out_x[:, k] = x[:, _KIN_MAJOR]
        out_P[:, k] = P[:, _KIN_MAJOR][:, :, _KIN_MAJOR]
        level_out[:, k] = u

    def _mie(self, k, hyps, armed, x, P, u, level_cov, k_c, sens, zI, RI, x_hist, pvv_hist, nu_hist, sinv_hist,
             gain_hist, sens_v_hist, F9, G9):
        dt = self.dt
        R = x.shape[0]
        rows = np.arange(R)
        first = k - self._span + 1
        vel = [1, 4, 7]
        scores, inputs, covs, old_covs, gains = [], [], [], [], []
        for d in hyps:
            n = k - d
            innov = np.zeros(R)
            for i in range(max(first, 2), n + 1):
                innov += einsum("ri,rij,rj->r", nu_hist[:, i], sinv_hist[:, i], nu_hist[:, i])
            v_n = x_hist[:, n, vel]
            tpvv = dt * dt * pvv_hist[:, n]
            A = np.zeros((R, 3, 3))
            b = np.zeros((R, 3))
            quad = np.zeros(R)
            W = np.zeros((R, 3, 3))                                # sum N_i S_i^-1
            weighted = []                                          # N_i S_i^-1
            for i in range(n + 1, k + 1):
                e = zI[:, i] - zI[:, i - 1] - dt * v_n              # eq 26 with T3 = I
                S_inv = np.linalg.inv(tpvv + RI[:, i] + RI[:, i - 1])
                N_i = (i - n - 0.5) * dt * dt
                A += N_i * N_i * S_inv
                b += N_i * einsum("rij,rj->ri", S_inv, e)
                quad += einsum("ri,rij,rj->r", e, S_inv, e)
                weighted.append((N_i * S_inv, RI[:, i]))
                W += N_i * S_inv
            A_inv = np.linalg.inv(A)
            if self.level_correlation:      # see LOSMIE: Delta's error = xi - (I + A^-1 W T J_v(n)) eps
                gain_eps = np.eye(3) + A_inv @ W @ (dt * sens_v_hist[:, n])
                old_covs.append(gain_eps @ level_cov @ np.swapaxes(gain_eps, 1, 2))
            else:
                gain_eps = np.broadcast_to(np.eye(3), level_cov.shape)
                old_covs.append(level_cov)
            gains.append(gain_eps)
            u_hat = einsum("rij,rj->ri", A_inv, b)
            L = -0.5 * innov - 0.5 * quad + 0.5 * einsum("ri,rij,rj->r", u_hat, A, u_hat)
            cross = np.zeros((R, 3, 3))
            m = len(weighted)
            for a_i in range(m):
                for a_j in range(a_i + 1, m):
                    C = tpvv - (weighted[a_i][1] if a_j == a_i + 1 else 0.0)
                    term = weighted[a_i][0] @ C @ weighted[a_j][0]
                    cross += term + np.swapaxes(term, 1, 2)
            scores.append(np.where(armed & (n >= k_c), L, -np.inf))
            inputs.append(u_hat)
            covs.append(A_inv + A_inv @ cross @ A_inv)
        scores, inputs, covs = np.stack(scores), np.stack(inputs), np.stack(covs)
        best = np.argmax(scores, axis=0)
        ok = np.isfinite(scores[best, rows])
        delta = inputs[best, rows] - u
        sigma_u = covs[best, rows]
        V = sigma_u + (np.stack(old_covs)[best, rows] if self.level_uncertainty else 0.0)
        if self.test == "full":
            stat = einsum("ri,rij,rj->r", delta, np.linalg.inv(V), delta)
        else:
            stat = (delta * delta / np.diagonal(V, axis1=1, axis2=2)).sum(axis=1)
        det = ok & (stat > self.threshold)
        stat = np.where(ok, stat, np.nan)
        onset = np.where(det, k - np.asarray(hyps)[best], -1)
        G = np.stack(gains)[best, rows]                                          # (R, 3, 3)
        if self.compensate and self.level_uncertainty and self.level_correlation:
            # see LOSMIE: MMSE estimate of the old level's error from Delta = xi - G eps when the test is quiet
            soft = ok & ~det & ((k - k_c) % self.rearm_after == 0)
            if soft.any():
                SG = level_cov @ np.swapaxes(G, 1, 2)
                gain = SG @ np.linalg.inv(sigma_u + G @ SG)
                eps = -einsum("rij,rj->ri", gain, delta) * soft[:, None]
                u = u - eps
                x = x - einsum("rij,rj->ri", sens, eps)
                level_cov = np.where(soft[:, None, None], level_cov - gain @ np.swapaxes(SG, 1, 2), level_cov)
        if not (self.compensate and det.any()):
            return x, P, u, level_cov, k_c, sens, det, stat, onset
        delta = np.where(det[:, None], delta, 0.0)
        H = np.zeros((3, 9))
        H[[0, 1, 2], [0, 3, 6]] = 1.0
        M = np.zeros((R, 9, 3))
        for h, d in enumerate(hyps):
            use = det & (best == h)
            if not use.any():
                continue
            n = k - d
            hit = np.flatnonzero(use)                                   # only the runs that compensate
            Mh = np.broadcast_to(np.kron(np.eye(3), np.array([[0.0], [0.0], [1.0]])), (hit.size, 9, 3)).copy()  # B
            for i in range(n + 1, k + 1):
                Y = F9 @ Mh + G9
                Mh = Y - gain_hist[hit, i] @ (H @ Y)
            M[hit] = Mh
        x = x + einsum("rij,rj->ri", M, delta)                                # eq 34
        P = P + M @ np.where(det[:, None, None], sigma_u, 0.0) @ np.swapaxes(M, 1, 2)   # eq 37
        u = u + delta                                                            # eq 38
        Kc = G - np.eye(3)                               # the new level's error is xi - (G - I) eps
        carried = self.level_uncertainty and self.level_correlation
        new_level_cov = sigma_u + (Kc @ level_cov @ np.swapaxes(Kc, 1, 2) if carried else 0.0)
        level_cov = np.where(det[:, None, None], new_level_cov, level_cov)
        sens = np.where(det[:, None, None], M, sens)
        k_c = np.where(det, k, k_c)
        return x, P, u, level_cov, k_c, sens, det, stat, onset
