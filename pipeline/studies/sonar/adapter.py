"""Track and evaluate stages of the active/passive sonar study (spec 003, seed 003).

The trackers need what the sonar reports (bearing, and range when active, per scan), the sensor
schedule, and the own-ship's own motion (the known input u of the relative-motion model, and its
velocity at the start). The truth carries the own-ship as labels; this adapter hands the
trackers only the own-ship part of it.

Per-step metrics are the generic ones (position/velocity RMSE, NEES over the finite states)
plus ``position_rmse_x`` / ``position_rmse_y``. The summary adds the seed's Table 1 reading,
RMS over all runs and steps (``rmse_x``, ``rmse_y``, window "all"), the median of the per-run
RMSEs (``median_run_rmse_x``/``_y``), the median over runs of the per-run ratio to the reference
variant (``paired_ratio_x``/``_y``), and the peak of the per-step position RMSE within
``bump_window`` seconds after each active -> passive switch (``peak_position_rmse``, window
"after <t> s").
"""

from __future__ import annotations

import numpy as np

from filters.bounds import posterior_crlb
from filters.mgekf import STATE_NAMES, SonarReports, jacobian_rows, relative_motion_model
from pipeline.storage import schemas
from pipeline.contract import JobInputs, RecordingInputs, Study, VariantInputs
from pipeline.evaluation.metrics import Metric, register
from pipeline.data import Detections, Truth
from pipeline.errors import ConfigError
from pipeline.evaluation.bounds import PerTruth
from pipeline.evaluation.evaluate import per_step_metrics, quiet_nanmean, summary_row
from pipeline.evaluation.uncertainty import RunValues, WindowStatistic

register(
    Metric("position_rmse_x", "m", quantity="position_rmse", component="x"),
    Metric("position_rmse_y", "m", quantity="position_rmse", component="y"),
    # the seed's Table 1 reading: RMS over all runs and steps, per axis
    Metric("rmse_x", "m", quantity="position_rmse_all_steps", component="x"),
    Metric("rmse_y", "m", quantity="position_rmse_all_steps", component="y"),
    Metric("median_run_rmse_x", "m", quantity="median_run_position_rmse", component="x"),
    Metric("median_run_rmse_y", "m", quantity="median_run_position_rmse", component="y"),
    Metric("paired_ratio_x", "ratio to the reference variant, median over runs", "ratio",
           quantity="paired_position_rmse_ratio", component="x"),
    Metric("paired_ratio_y", "ratio to the reference variant, median over runs", "ratio",
           quantity="paired_position_rmse_ratio", component="y"),
    Metric("peak_position_rmse", "m"),
)


class SonarStudy(Study):
    """Adapter of study 003.

    Parameters
    ----------
    bump_window : seconds after each active -> passive switch in which the peak position RMSE
        is reported (spec 003: KF + MGEKF's error rises within 300 s of each switch)
    bound_tau, bound_sigma_m, bound_velocity_std : the model whose posterior Cramer-Rao bound is
        reported (``position_bound``, ``position_rmse_over_bound``): the trackers' 6-state model
        (tau [s], sigma_m [m/s^2]) and start (velocity std [m/s]); None leaves the bound out
    """

    estimate_table = "estimates"

    def __init__(self, bump_window: float = 300.0, bound_tau: float | None = None,
                 bound_sigma_m: float | None = None, bound_velocity_std: float = 15.0) -> None:
        if not (np.isfinite(bump_window) and bump_window > 0):
            raise ValueError(f"bump_window: {bump_window} must be > 0 s")
        for key, value in (("bound_tau", bound_tau), ("bound_sigma_m", bound_sigma_m),
                           ("bound_velocity_std", bound_velocity_std)):
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"{key}: {value} must be > 0 (or null to leave the bound out)")
        self.bump_window = float(bump_window)
        self.bound_model = None if bound_tau is None or bound_sigma_m is None else (
            float(bound_tau), float(bound_sigma_m), float(bound_velocity_std))
        self._bounds = PerTruth()
        # what variant_summary keeps of each variant for extra_summary: (R, 2) per-run RMSEs, (R, K)
        # squared position errors
        self._per_run: dict[str, np.ndarray] = {}
        self._squared: dict[str, RunValues] = {}

    def check(self, scenario, sensor, estimators: dict) -> None:
        if not hasattr(sensor, "is_active"):
            raise ConfigError(f"sensors: {type(sensor).__name__} is not an active/passive sonar; the sonar study "
                              f"needs one (e.g. sensors=sonar_case2).")
        if not bool(np.asarray(sensor.is_active(np.array([0.0])))[0]):
            intervals = [[float(a), float(b)] for a, b in sensor.active_intervals]
            raise ConfigError(f"sensors.active_intervals: {intervals} must start active at t = 0: the "
                              f"trackers start from a range + bearing measurement.")

    def track_input(self, truth: Truth, detections: Detections, sensor, seed: int) -> SonarReports:
        for label in ("ownship", "ownship_acceleration"):
            if label not in truth.labels:
                raise ValueError(f"scenario: the truth has no '{label}' label; the sonar trackers need the own-ship's "
                                 f"motion (use pipeline.studies.sonar.scenario.SonarEncounter)")
        return SonarReports(detections.time, detections.z[:, :, 0], detections.sensor == 1,
                            truth.labels["ownship_acceleration"][:, :, 0], truth.labels["ownship"][:, 0, 0, 2:4],
                            float(sensor.bearing_std), float(sensor.range_std))

    @staticmethod
    def estimate_to_frame(estimate, truth=None):
        # 100 runs x 10 001 steps: the full float64 covariance would be ~200 MB per variant
        return schemas.estimate_to_frame(estimate, STATE_NAMES, compact_covariance=True)

    def per_step_metrics(self, truth: Truth, estimate, sensor) -> dict[str, np.ndarray]:
        out = per_step_metrics(truth, estimate)
        err = estimate.state[..., :2] - truth.state[:, :, 0, :2]
        out["position_rmse_x"] = RunValues(err[..., 0] ** 2, "rms")
        out["position_rmse_y"] = RunValues(err[..., 1] ** 2, "rms")
        if self.bound_model is not None:
            bound = self.position_bound(truth, sensor)
            out["position_bound"] = bound
            out["position_rmse_over_bound"] = out["position_rmse"].over(bound)
            out["position_bound_model"] = self.position_bound(truth, sensor, "model")
            out["position_rmse_over_bound_model"] = out["position_rmse"].over(out["position_bound_model"])
        return out

    def position_bound(self, truth: Truth, sensor, model: str = "clairvoyant") -> np.ndarray:
        """sqrt(trace) of the position block of the PCRLB (filters.bounds) along the true trajectory
        with the sonar's schedule; (K,) [m]. "clairvoyant": the truth's own dynamics, deterministic
        (no process noise; own-ship and target accelerations known), a bound for any estimator of
        this truth; "model": the trackers' 6-state Singer model (random target acceleration), which
        a deterministic truth lets a tracker undercut. Computed once per truth and sensor."""
        return self._bounds.get(truth, sensor, model, lambda: self._compute_bound(truth, sensor, model))

    def _compute_bound(self, truth: Truth, sensor, model: str) -> np.ndarray:
        tau, sigma_m, velocity_std = self.bound_model
        dt = float(truth.time[1] - truth.time[0])
        if model == "model":
            F, _, Q = relative_motion_model(dt, tau, sigma_m)
        else:                                   # known inputs move the mean only: CV, Q = 0
            F, Q = np.kron(np.array([[1.0, dt], [0.0, 1.0]]), np.eye(2)), np.zeros((4, 4))
        n = F.shape[0]
        position = truth.state[:, :, 0, :2]                                                  # (R, K, 2)
        d_beta, d_r = jacobian_rows(position)
        active = np.asarray(sensor.is_active(truth.time), dtype=float)                      # (K,)
        rows = (d_beta[..., :, None] * d_beta[..., None, :] / sensor.bearing_std**2
                + active[None, :, None, None] * d_r[..., :, None] * d_r[..., None, :] / sensor.range_std**2)
        information = np.zeros(rows.shape[1:2] + (n, n))
        information[:, :2, :2] = rows.mean(axis=0)                                          # E over the runs
        # the trackers' start: the converted first (active) measurement, velocity and acceleration priors
        beta, r = np.arctan2(position[:, 0, 0], position[:, 0, 1]), np.hypot(position[:, 0, 0], position[:, 0, 1])
        J = np.stack([np.stack([r * np.cos(beta), np.sin(beta)], -1), np.stack([-r * np.sin(beta), np.cos(beta)], -1)], -2)
        initial = np.zeros((n, n))
        initial[:2, :2] = (J @ np.diag([sensor.bearing_std**2, sensor.range_std**2]) @ np.swapaxes(J, -1, -2)).mean(0)
        initial[2:4, 2:4] = velocity_std**2 * np.eye(2)
        if n == 6:
            initial[4:, 4:] = sigma_m**2 * np.eye(2)
        bounds = posterior_crlb(F, Q, initial, information)
        return np.sqrt(bounds[:, 0, 0] + bounds[:, 1, 1])

    def record(self, path, inputs: RecordingInputs) -> None:
        from pipeline.studies.sonar.recording import write_sonar_recording
        write_sonar_recording(path, sensor=inputs.sensor, **inputs.common(), **inputs.options)

    def variant_summary(self, inputs: VariantInputs) -> list[dict]:
        """Table 1's readings of one variant (see the module docstring); keeps its per-run RMSEs and
        squared position errors for ``extra_summary``'s ratios and post-switch peaks."""
        truth, key, display, estimate = inputs.truth, inputs.key, inputs.display, inputs.estimate
        runs = inputs.runs
        rows: list[dict] = []
        every_step = np.arange(truth.time.size)
        err = estimate.state[..., :2] - truth.state[:, :, 0, :2]
        self._squared[key] = RunValues(np.sum(err**2, axis=-1), "rms")
        for axis, name in enumerate("xy"):
            # pooled over the runs and the steps: the paper's Table 1 reading
            rows.append(summary_row(key, display, f"rmse_{name}", "all", None, runs,
                                    WindowStatistic(RunValues(err[..., axis] ** 2, "rms"), every_step, "pool")))
        with quiet_nanmean():
            self._per_run[key] = np.sqrt(np.nanmean(err**2, axis=1))            # (R, 2)
        for axis, name in enumerate("xy"):
            rows.append(summary_row(key, display, f"median_run_rmse_{name}", "all", None, runs,
                                    WindowStatistic(RunValues(self._per_run[key][:, axis:axis + 1], "median"), [0],
                                                    "mean")))
        return rows

    def extra_summary(self, inputs: JobInputs) -> list[dict]:
        """The paired ratios to the reference and the post-switch peaks, from what ``variant_summary``
        kept of each variant (the estimates are not read again)."""
        truth, display, runs = inputs.truth, inputs.display, inputs.runs
        reference, sensor, per_variant = inputs.reference, inputs.sensor, inputs.per_variant
        rows: list[dict] = []

        def add(key, metric, window, statistic: WindowStatistic):
            rows.append(summary_row(key, display[key], metric, window, None, runs, statistic))

        # what variant_summary kept, let go with these rows (the recording follows)
        per_run, squared = self._per_run, self._squared
        self._per_run, self._squared = {}, {}
        if reference in per_run:
            for key in per_variant:
                with np.errstate(invalid="ignore", divide="ignore"):
                    ratio = per_run[key] / per_run[reference]
                for axis, name in enumerate("xy"):
                    add(key, f"paired_ratio_{name}", "all",
                        WindowStatistic(RunValues(ratio[:, axis:axis + 1], "median"), [0], "mean"))
        time = truth.time
        active = np.asarray(sensor.is_active(time), dtype=bool)
        switches = np.nonzero(active[:-1] & ~active[1:])[0] + 1               # first passive scan
        for key in per_variant:
            for k in switches:
                inside = np.nonzero((time >= time[k]) & (time < time[k] + self.bump_window))[0]
                add(key, "peak_position_rmse", f"after {time[k]:g} s", WindowStatistic(squared[key], inside, "max"))
        return rows
