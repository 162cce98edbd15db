"""Track and evaluate stages of the sonobuoy study (spec 004, seed 004).

The filters get the bearings (NaN where missed), the observer's position, the nominal and clutter
noise, and a start identical for every filter (spec 004): prior mean = truth + N(0, P0) drawn here
in its own seeded stage ("prior", per run), or for case 1B a fixed target prior centred on the
field. Per-step metrics (step k is t = k T):

- ``position_rmse`` / ``position_median_error``: the target's position error, RMS and median over runs;
- ``buoy_position_rmse`` / ``buoy_position_median_error``: RMS / median over runs and the four buoys;
- ``nees_position`` / ``nees_position_median``: the target position NEES (2 dof), mean and median over runs;
- ``ess`` (particle filters): mean effective sample size; ``mode_probability_cv/_ccw/_cw``: mean
  over runs of the filter's mode probabilities (ccw: Omega > 0, the seed's r = 2; cw: Omega < 0, r = 3).

The summary adds ``track_loss_rate`` (final position error above ``loss_threshold``),
``final_position_rmse``, and ``peak_median_error`` within each of ``peak_windows`` (seconds).
"""

from __future__ import annotations

import copy
from typing import Sequence

import numpy as np

from filters.particle import MODE_NAMES, NOISE_GAINS, STATE_NAMES, BuoyReports, MultipleModelParticleFilter
from pipeline.storage import schemas
from pipeline.contract import RecordingInputs, Study, VariantInputs
from pipeline.evaluation.metrics import BAND, Metric, nees, register
from pipeline.data import Detections, Truth
from pipeline.errors import ConfigError
from pipeline.run.seeding import run_generators
from pipeline.evaluation.bounds import PerTruth
from pipeline.evaluation.evaluate import consistency, nis_metrics, quiet_nanmean, summary_row
from pipeline.evaluation.uncertainty import RunValues, WindowStatistic, normalised_squared

register(
    Metric("position_median_error", "m"), Metric("buoy_position_rmse", "m"), Metric("buoy_position_median_error", "m"),
    # the target's position NEES (2 dof): position_nees in every study's terms
    Metric("nees_position", "1 (chi2 dof = 2)", "-", dof=2, quantity="position_nees"),
    Metric("nees_position_lower", BAND, "-", quantity="position_nees_lower"),
    Metric("nees_position_upper", BAND, "-", quantity="position_nees_upper"),
    Metric("nees_position_median", "1 (chi2 dof = 2: median 1.39)", "-", dof=2, quantity="position_nees_median"),
    Metric("ess", "particles"),
    Metric("mode_probability_cv", "probability", quantity="mode_probability", component="cv"),
    Metric("mode_probability_ccw", "probability", quantity="mode_probability", component="ccw"),
    Metric("mode_probability_cw", "probability", quantity="mode_probability", component="cw"),
    Metric("track_loss_rate", "fraction of runs"), Metric("final_position_rmse", "m"), Metric("peak_median_error", "m"),
)


class SonobuoyStudy(Study):
    """Adapter of study 004.

    Parameters
    ----------
    target_prior : "truth" (mean = truth + N(0, P0), the spec's default) or "field" (mean
        ``field_target_mean``; case 1B: the target prior centred on the field)
    target_std : P0's target standard deviations (x, y, vx, vy) [m, m/s]
    buoy_std : P0's standard deviations of each buoy (x, y, vx, vy)
    field_target_mean : the target prior mean for ``target_prior: field``
    loss_threshold : a run whose final position error exceeds it has lost the track [m]
    peak_windows : name -> [t0, t1] seconds; the summary reports the peak median error in each
    """

    estimate_table = "estimates"

    def __init__(self, target_prior: str = "truth", target_std: Sequence[float] = (1000.0, 1000.0, 2.0, 2.0),
                 buoy_std: Sequence[float] = (100.0, 100.0, 0.05, 0.05),
                 field_target_mean: Sequence[float] = (0.0, 0.0, 0.0, 0.0), loss_threshold: float = 2000.0,
                 peak_windows: dict | None = None, bound_buoy_sigma: float | None = None,
                 bound_noise_gain: str = "standard", bound_model_target_sigma: float | None = None) -> None:
        if target_prior not in ("truth", "field"):
            raise ValueError(f"target_prior: {target_prior!r} is not allowed; use 'truth' (truth + N(0, P0)) or "
                             f"'field' (field_target_mean)")
        for key, value in (("target_std", target_std), ("buoy_std", buoy_std), ("field_target_mean", field_target_mean)):
            array = np.asarray(value, dtype=float)
            if array.shape != (4,) or not np.all(np.isfinite(array)) or (key != "field_target_mean" and np.any(array <= 0)):
                raise ValueError(f"{key}: {list(value)} must be 4 finite values (x, y, vx, vy)"
                                 + ("" if key == "field_target_mean" else " > 0"))
        if not (np.isfinite(loss_threshold) and loss_threshold > 0):
            raise ValueError(f"loss_threshold: {loss_threshold} must be > 0 m")
        self.target_prior = target_prior
        self.target_std = np.asarray(target_std, dtype=float)
        self.buoy_std = np.asarray(buoy_std, dtype=float)
        self.field_target_mean = np.asarray(field_target_mean, dtype=float)
        self.loss_threshold = float(loss_threshold)
        self.peak_windows = {str(k): (float(v[0]), float(v[1])) for k, v in (peak_windows or {}).items()}
        for key, value in (("bound_buoy_sigma", bound_buoy_sigma), ("bound_model_target_sigma", bound_model_target_sigma)):
            if value is not None and not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{key}: {value} must be a finite std >= 0 [m/s^2] (or null: no bound)")
        if bound_noise_gain not in NOISE_GAINS:
            raise ValueError(f"bound_noise_gain: {bound_noise_gain!r} must be one of {list(NOISE_GAINS)}")
        self.bound_buoy_sigma = None if bound_buoy_sigma is None else float(bound_buoy_sigma)
        self.bound_noise_gain = bound_noise_gain
        self.bound_model_target_sigma = None if bound_model_target_sigma is None else float(bound_model_target_sigma)
        self._bounds = PerTruth()
        for name, (t0, t1) in self.peak_windows.items():
            if not t0 <= t1:
                raise ValueError(f"peak_windows.{name}: [{t0}, {t1}] must have t0 <= t1 (seconds)")

    @property
    def prior_std(self) -> np.ndarray:
        return np.concatenate([self.target_std, np.tile(self.buoy_std, 4)])

    def check(self, scenario, sensor, estimators: dict) -> None:
        if not hasattr(sensor, "observer_position"):
            raise ConfigError(f"sensors: {type(sensor).__name__} is not the sonobuoy bearing sensor; the sonobuoy "
                              f"study needs one (e.g. sensors=sonobuoy_clean).")

    def track_input(self, truth: Truth, detections: Detections, sensor, seed: int) -> BuoyReports:
        R = truth.runs
        start = truth.state[:, 0, 0]                                              # (R, 20)
        draws = np.stack([g.standard_normal(20) for g in run_generators(seed, "prior", R)])
        prior_mean = start + draws * self.prior_std
        if self.target_prior == "field":
            prior_mean[:, 0:4] = self.field_target_mean
        return BuoyReports(detections.time, detections.z[..., 0], np.asarray(sensor.observer_position, dtype=float),
                           np.asarray(sensor.nominal_std, dtype=float), np.asarray(sensor.clutter_std, dtype=float),
                           float(sensor.clutter_probability), prior_mean, self.prior_std, int(seed))

    @staticmethod
    def estimate_to_frame(estimate, truth=None):
        return schemas.estimate_to_frame(estimate, STATE_NAMES, compact_covariance=True)

    def per_step_metrics(self, truth: Truth, estimate, sensor) -> dict[str, np.ndarray]:
        true = truth.state[:, :, 0]
        error = np.linalg.norm(estimate.state[..., 0:2] - true[..., 0:2], axis=-1)          # (R, K)
        buoy_error = (estimate.state[..., 4:] - true[..., 4:]).reshape(error.shape + (4, 4))[..., 0:2]
        out = {}
        with np.errstate(invalid="ignore"), quiet_nanmean():
            out["position_rmse"] = RunValues(error**2, "rms")
            out["position_median_error"] = RunValues(error, "median")
            buoy_distance = np.sqrt(np.sum(buoy_error**2, axis=-1))                       # (R, K, 4)
            out["buoy_position_rmse"] = RunValues((buoy_distance**2).mean(axis=-1), "rms")
            out["buoy_position_median_error"] = RunValues(buoy_distance, "median")       # over runs and buoys
            e = estimate.state[..., 0:2] - true[..., 0:2]
            P = estimate.covariance[..., 0:2, 0:2]
            position_nees = nees(e, P)
            # the run average with its 95 % chi-square band (2 dof per valid run)
            out.update(consistency("nees_position", position_nees, 2))
            # the mean is what a consistency check reads, but one collapsed cloud (covariance of
            # centimetres, error of metres) dominates it: the median shows the typical run
            out["nees_position_median"] = normalised_squared(position_nees, "median")
            extras = estimate.extras
            out.update(nis_metrics(extras, per_run=True))
            if "ess" in extras:
                out["ess"] = RunValues(np.asarray(extras["ess"], dtype=float), "mean")
            if "mode_probabilities" in extras:
                for m, name in enumerate(MODE_NAMES):
                    out[f"mode_probability_{name}"] = RunValues(extras["mode_probabilities"][..., m], "mean")
        if self.bound_buoy_sigma is not None:
            bound = self.position_bound(truth, sensor, 0.0)
            out["position_bound"] = bound
            out["position_rmse_over_bound"] = out["position_rmse"].over(bound)
            if self.bound_model_target_sigma is not None:
                out["position_bound_model"] = self.position_bound(truth, sensor, self.bound_model_target_sigma)
                out["position_rmse_over_bound_model"] = out["position_rmse"].over(out["position_bound_model"])
        return out

    def position_bound(self, truth: Truth, sensor, target_sigma: float) -> np.ndarray:
        """Once per truth, sensor and target noise (every variant is evaluated against the same truth);
        see ``_compute_bound``."""
        return self._bounds.get(truth, sensor, target_sigma, lambda: self._compute_bound(truth, sensor, target_sigma))

    def _compute_bound(self, truth: Truth, sensor, target_sigma: float) -> np.ndarray:
        """(K,) sqrt(trace) of the target position block of the PCRLB (filters.bounds) of the 20
        states [m], with the true mode sequence known and measurement-origin uncertainty ignored.

        Dynamics: the target's own transition at each step, the coordinated turn at the truth's turn
        rate (the heading change over the step; CV when straight), with process noise
        ``target_sigma`` (0: the truth's, a bound for any estimator of this truth; the filters'
        value: the bound of their model), the buoys CV with ``bound_buoy_sigma`` through Gamma (seed
        eqs 2-6). Information per scan: E over the runs (the buoys drift differently) of
        (1 - miss probability) sum_i h_i' h_i / s_i^2 over the 8 bearings at the true state, the
        nominal noise s_i: every received bearing is taken as the object's own, so in clutter
        (spec 004 cases 2, 2B: half of them) the bound is optimistic, a floor no tracker reaches.
        Start: the filters' prior P0 at scan 0 (no measurement then); with ``target_prior: field``
        the prior mean is not centred on the truth, so the bound is indicative there.
        """
        from filters.bounds import posterior_crlb
        from filters.particle import bearing_jacobian, ct_transition, cv_transition, noise_gain

        time = truth.time
        K = time.size
        true = truth.state[:, :, 0]                                                      # (R, K, 20)
        heading = np.arctan2(true[0, :, 2], true[0, :, 3])                               # the target is the same in every run
        F = np.zeros((K, 20, 20))
        Q = np.zeros((K, 20, 20))
        for k in range(1, K):
            dt = float(time[k] - time[k - 1])
            omega = -float(np.angle(np.exp(1j * (heading[k] - heading[k - 1])))) / dt   # heading from north: Omega < 0 turns right
            F[k] = 0.0
            F[k, 0:4, 0:4] = ct_transition(omega, dt)
            gamma = noise_gain(dt, self.bound_noise_gain)
            for i in range(5):
                if i:
                    F[k, 4 * i:4 * i + 4, 4 * i:4 * i + 4] = cv_transition(dt)
                sigma = target_sigma if i == 0 else self.bound_buoy_sigma
                Q[k, 4 * i:4 * i + 4, 4 * i:4 * i + 4] = sigma**2 * gamma @ gamma.T
        H = bearing_jacobian(true.reshape(-1, 20), np.asarray(sensor.observer_position, dtype=float))
        H = H.reshape(true.shape[:2] + (8, 20))                                           # (R, K, 8, 20)
        weighted = H / np.asarray(sensor.nominal_std, dtype=float)[:, None]
        information = (1.0 - float(sensor.miss_probability)) * np.mean(np.swapaxes(weighted, -1, -2) @ weighted, axis=0)
        bounds = posterior_crlb(F, Q, np.diag(self.prior_std**2), information)
        return np.sqrt(bounds[:, 0, 0] + bounds[:, 1, 1])

    def variant_summary(self, inputs: VariantInputs) -> list[dict]:
        truth, key, display, estimate = inputs.truth, inputs.key, inputs.display, inputs.estimate
        runs = inputs.runs
        rows = []

        def add(metric, window, statistic: WindowStatistic):
            rows.append(summary_row(key, display, metric, window, None, runs, statistic))

        time = truth.time
        final = np.linalg.norm(estimate.state[:, -1, 0:2] - truth.state[:, -1, 0, 0:2], axis=-1)
        lost = (~(final <= self.loss_threshold)).astype(float)[:, None]          # a run without an estimate is lost
        add("track_loss_rate", f"final error > {self.loss_threshold:g} m", WindowStatistic(RunValues(lost, "mean"), [0]))
        add("final_position_rmse", "final", WindowStatistic(RunValues(final[:, None] ** 2, "rms"), [0]))
        error = np.linalg.norm(estimate.state[..., 0:2] - truth.state[:, :, 0, 0:2], axis=-1)
        for name, (t0, t1) in self.peak_windows.items():
            inside = np.nonzero((time >= t0) & (time <= t1))[0]
            if inside.size:
                add("peak_median_error", name, WindowStatistic(RunValues(error, "median"), inside, "max"))
            else:
                rows.append(summary_row(key, display, "peak_median_error", name, None, runs))
        return rows

    def record(self, path, inputs: RecordingInputs) -> None:
        """The recording, with each particle filter's cloud for the recorded runs: those runs are
        filtered again alone with snapshots on (per-run random streams: the same particles as in the
        Monte Carlo batch, checked), so the estimates tables never carry clouds."""
        from dataclasses import replace

        from pipeline.studies.sonobuoy.recording import write_sonobuoy_recording
        options = dict(inputs.options)
        cloud_particles = int(options.pop("cloud_particles", 200))
        estimates = dict(inputs.estimates)
        runs = list(inputs.record_runs)
        if inputs.track_input is not None:
            reports = inputs.track_input.select(runs)
            for key, estimator in inputs.estimators.items():
                if not isinstance(estimator, MultipleModelParticleFilter) or key not in estimates:
                    continue
                again = copy.copy(estimator)
                again.snapshot_particles = min(cloud_particles, estimator.particles)
                snap = again.run(reports)
                if not np.array_equal(snap.state, estimates[key].state[runs]):
                    raise RuntimeError(f"filters.{key}: re-filtering runs {runs} alone did not reproduce the batch")
                extras = {**estimates[key].extras, "particles": snap.extras["particles"],
                          "particle_modes": snap.extras["particle_modes"]}
                estimates[key] = replace(estimates[key], extras=extras)
        write_sonobuoy_recording(path, sensor=inputs.sensor, **(inputs.common() | {"estimates": estimates}), **options)
