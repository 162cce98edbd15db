"""Track and evaluate stages of the bias-registration study (spec 002, seed 002).

The study differs from the single-target ones in what the filters consume (asynchronous reports
of several radars on many targets, plus the bias-free track start of the seed's set-up) and in
what they return (a stacked bias estimate, biased and compensated local tracks), so an
experiment selects this adapter with a ``study`` node; the runner then asks it for the filters'
input, the estimate table and the per-step metrics.

Metrics live on the truth's time grid (step k is truth.time[k]); a report at time t fills the
step at t. Names: ``bias_rmse_<component>_s<n>`` (radar n, 1-based), ``bias_nees`` (all 4S
components), ``bias_nees_s<n>``; for every kept target m and radar n, at that radar's reports:
``position_rmse_s<n>_t<m>`` / ``velocity_rmse_...`` of the biased local track, the same with
``_compensated``, and ``track_nees_s<n>_t<m>_compensated`` (4 dof); for every radar n, at its
reports: ``nis_s<n>`` the normalised innovation squared of its local updates, averaged over all
its tracked targets and the runs (2 dof per target: expected 2), with ``nis_s<n>_lower`` /
``nis_s<n>_upper`` the 95 % chi-square band of that average (``target_mean_nis``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.bias import BIAS_NAMES, BIAS_UNITS, BiasRegistrationResult, RadarReports, TrackStart
from pipeline.contract import RecordingInputs, Study
from pipeline.evaluation.metrics import BAND, Metric, lookup, nees, register, register_family, unit_of
from pipeline.studies.async_bias.codec import bias_estimates_from_frame, bias_estimates_to_frame
from pipeline.data import Detections, Truth
from pipeline.errors import ConfigError
from pipeline.run.seeding import run_generators
from pipeline.evaluation.evaluate import consistency, consistency_metrics, quiet_nanmean
from pipeline.evaluation.uncertainty import RunValues, normalised_squared


class BiasRegistrationStudy(Study):
    """Adapter of study 002.

    Parameters
    ----------
    start_time : when the local tracks start [s] (a truth time before the first report)
    start_std : standard deviations of the start error (x, y, vx, vy) [m, m/s]: every radar's
        track of every target starts at truth + N(0, P0), P0 = diag(start_std^2), G = 0 (the
        seed's bias-free start; each radar draws its own error). P0 is also the filters' initial
        covariance.
    """

    estimate_table = "bias_estimates"

    def __init__(self, start_time: float = 0.0, start_std: Sequence[float] = (10.0, 10.0, 5.0, 5.0)) -> None:
        std = np.asarray(start_std, dtype=float)
        if std.shape != (4,) or not np.all(np.isfinite(std) & (std >= 0)):
            raise ValueError(f"start_std: {list(start_std)} must be 4 standard deviations >= 0 (x, y m; vx, vy m/s)")
        if not np.isfinite(start_time):
            raise ValueError(f"start_time: {start_time} must be a finite time in s")
        self.start_time = float(start_time)
        self.start_std = std

    # ---- checks before any stage runs -------------------------------------------------------
    def check(self, scenario, sensor, estimators: dict) -> None:
        """Cross-node consistency the nodes cannot check alone; raises ConfigError naming the key."""
        positions = getattr(sensor, "positions", None)
        if positions is None or np.ndim(positions) != 2 or np.shape(positions)[1] != 2:
            raise ConfigError(f"sensors: {type(sensor).__name__} is not a network of 2-D radars; the "
                              f"bias-registration study needs one (e.g. sensors=async_bias).")
        dt, duration = getattr(scenario, "dt", None), getattr(scenario, "duration", None)
        targets = getattr(scenario, "targets", None)
        if dt is not None and duration is not None:
            grid = np.arange(int(round(duration / dt)) + 1) * dt
            if not np.isclose(grid, self.start_time, atol=1e-9).any():
                raise ConfigError(f"study.start_time: {self.start_time} s is not a time of the scenario's grid "
                                  f"(0..{duration:g} s in steps of scenario.dt = {dt:g} s).")
            times, radar = sensor.report_times(duration)
            off = np.abs(np.round(times / dt) * dt - times) > 1e-9
            if off.any():
                first = int(np.argmax(off))
                raise ConfigError(
                    f"sensors.radars[{int(radar[first])}]: reports at {times[first]:g} s, which is not on the "
                    f"scenario's time grid (scenario.dt = {dt:g} s); make every first_report and period a "
                    f"multiple of scenario.dt.")
            if times.size and times[0] < self.start_time:
                raise ConfigError(f"study.start_time: {self.start_time} s is after the first report at "
                                  f"{times[0]:g} s; the tracks must start before it.")
        for key, estimator in estimators.items():
            wanted = getattr(estimator, "output_targets", None)
            if targets is not None and wanted is not None and max(wanted) > targets:
                raise ConfigError(f"filters.{key}.output_targets: {wanted} names target(s) "
                                  f"{[t for t in wanted if t > targets]} but the scenario has {targets} targets "
                                  f"(numbered 1..{targets}, 1 = nearest radar 1); choose numbers in that range.")

    # ---- track input -----------------------------------------------------------------------
    def track_input(self, truth: Truth, detections: Detections, sensor, seed: int) -> RadarReports:
        """The filters' view: each radar's polar reports, its stated noise, its position, and the
        bias-free track start drawn here (stage "track_start": same per run whatever R)."""
        positions = np.asarray(getattr(sensor, "positions", None), dtype=float)
        S = positions.shape[0]
        if positions.ndim != 2 or positions.shape[1] != 2:
            raise ValueError(f"study: the bias-registration study needs a radar network with 2-D positions "
                             f"(sensors.radars); {type(sensor).__name__} has none")
        noise_std = np.full((S, 2), np.nan)
        for s in range(S):
            scans = np.nonzero(detections.sensor == s)[0]
            if scans.size:
                cov = detections.noise_covariance[0, scans[0], 0]
                noise_std[s] = np.sqrt(np.diag(cov))
        hit = np.nonzero(np.isclose(truth.time, self.start_time, atol=1e-9))[0]
        if not hit.size:
            raise ValueError(f"study.start_time: {self.start_time} s is not a time of the truth (it runs "
                             f"{truth.time[0]}..{truth.time[-1]} s in steps of {truth.time[1] - truth.time[0]} s)")
        R, _, T, _ = truth.state.shape
        noise = np.stack([g.standard_normal((S, T, 4)) for g in run_generators(seed, "track_start", R)])
        start_state = truth.state[:, hit[0]][:, None] + noise * self.start_std
        start = TrackStart(self.start_time, start_state, np.diag(self.start_std**2))
        return RadarReports(detections.time, detections.sensor.astype(int), detections.z, positions, noise_std, start)

    def estimate_to_frame(self, result: BiasRegistrationResult, truth=None):
        return bias_estimates_to_frame(result)

    def estimate_from_frame(self, df, metadata) -> BiasRegistrationResult:
        return bias_estimates_from_frame(df, metadata)

    @staticmethod
    def fault_flags(result: BiasRegistrationResult, truth: Truth, checks) -> np.ndarray:
        """(R, reports) fault masks of the bias estimate and of every kept track, biased and
        compensated (no NEES test: the bias truth lives in the sensor, the tracks' in the truth)."""
        from pipeline.evaluation.faults import fault_flags
        flags = np.zeros(result.track_state.shape[:2], dtype=np.uint8)
        if np.isfinite(result.bias).any():
            flags |= fault_flags(result.bias, result.bias_covariance, checks)
        flags |= fault_flags(result.track_state, result.track_covariance, checks)
        flags |= fault_flags(result.compensated_state, result.compensated_covariance, checks)
        return flags

    # ---- evaluate --------------------------------------------------------------------------
    @staticmethod
    def per_step_metrics(truth: Truth, result: BiasRegistrationResult, sensor) -> dict[str, np.ndarray]:
        """The metrics against the radars' true biases (``sensor.true_bias_vector()``)."""
        return bias_study_metrics(truth, result, np.asarray(sensor.true_bias_vector(), dtype=float))

    # ---- record ----------------------------------------------------------------------------
    def record(self, path, inputs: RecordingInputs) -> None:
        from pipeline.studies.async_bias.recording import write_bias_recording
        write_bias_recording(path, sensor=inputs.sensor, **inputs.common())


def _steps(truth_time: np.ndarray, times: np.ndarray) -> np.ndarray:
    index = np.searchsorted(truth_time, times - 1e-9)
    index = np.clip(index, 0, truth_time.size - 1)
    if not np.allclose(truth_time[index], times, atol=1e-9):
        raise ValueError("estimate times are not on the truth's time grid")
    return index


def bias_study_metrics(truth: Truth, result: BiasRegistrationResult, true_bias: np.ndarray
                       ) -> dict[str, RunValues | np.ndarray]:
    """Metrics of one variant on the truth's grid (K_truth steps), kept per run; see the module
    docstring for the names."""
    Kt = truth.time.size
    steps = _steps(truth.time, result.time)
    S = true_bias.size // 4
    out: dict[str, RunValues | np.ndarray] = {}

    def on_grid(values: np.ndarray, at: np.ndarray | None = None, prior: float | None = None) -> np.ndarray:
        """(K,) or (R, K) values at the reports -> on the truth's grid (NaN between reports)."""
        grid = np.full(values.shape[:-1] + (Kt,), np.nan)
        grid[..., steps if at is None else steps[at]] = values
        if prior is not None and steps.size and steps[0] > 0:
            grid[..., : steps[0]] = prior
        return grid

    with np.errstate(invalid="ignore"), quiet_nanmean():
        if np.isfinite(result.bias).any():
            err = result.bias - true_bias                                   # (R, K, 4S)
            for s in range(S):
                for c, name in enumerate(BIAS_NAMES):
                    j = 4 * s + c
                    # before the first report the estimate is the prior mean 0
                    out[f"bias_rmse_{name}_s{s + 1}"] = RunValues(on_grid(err[..., j] ** 2, prior=true_bias[j] ** 2), "rms")
            bias_nees = nees(err, result.bias_covariance)
            band = consistency("bias_nees", bias_nees, err.shape[-1])    # 95 % band, 4S dof
            out.update({name: on_grid(values) for name, values in band.items() if not isinstance(values, RunValues)})
            out["bias_nees"] = normalised_squared(on_grid(bias_nees))
            for s in range(S):
                block = slice(4 * s, 4 * s + 4)
                out[f"bias_nees_s{s + 1}"] = normalised_squared(
                    on_grid(nees(err[..., block], result.bias_covariance[..., block, block])))
        truth_at = truth.state[:, steps][:, :, result.targets]              # (R, K, Tsel, 4)
        for s in range(S):
            mine = np.nonzero(result.sensor == s)[0]
            if not mine.size:
                continue
            for col, target in enumerate(result.targets):
                label = f"s{s + 1}_t{target + 1}"
                true_state = truth_at[:, mine, col]
                for kind, state in (("", result.track_state), ("_compensated", result.compensated_state)):
                    e = state[:, mine, col] - true_state
                    out[f"position_rmse_{label}{kind}"] = RunValues(on_grid(np.sum(e[..., :2]**2, -1), mine), "rms")
                    out[f"velocity_rmse_{label}{kind}"] = RunValues(on_grid(np.sum(e[..., 2:]**2, -1), mine), "rms")
                e = result.compensated_state[:, mine, col] - true_state
                out[f"track_nees_{label}_compensated"] = normalised_squared(
                    on_grid(nees(e, result.compensated_covariance[:, mine, col]), mine))
        if result.nis is not None and result.nis_dof is not None:
            for s in range(S):
                mine = np.nonzero(result.sensor == s)[0]
                if mine.size:
                    band = target_mean_nis(f"nis_s{s + 1}", result.nis[:, mine], result.nis_dof[:, mine])
                    out.update({name: on_grid(values, mine) for name, values in band.items()})
                    # the per-target mean kept per run: each run's NIS sum over its targets, weighed by them
                    out[f"nis_s{s + 1}"] = RunValues(on_grid(result.nis[:, mine], mine), "mean",
                                                     weights=on_grid(result.nis_dof[:, mine] / 2.0, mine))
    return out


def target_mean_nis(name: str, nis_sum: np.ndarray, dof: np.ndarray) -> dict[str, np.ndarray]:
    """``{name}``, ``{name}_lower``, ``{name}_upper`` (K,): the NIS averaged over the targets and
    the runs, with its 95 % chi-square band, from each run's NIS summed over its targets ``nis_sum``
    (R, K) (NaN: none) and the sum's dof (R, K) (2 per target).

    Over the N runs with a value, the sums add up to a chi-square of D = their summed dof, so the
    average per target, sum / (D / 2), has expected value 2 and the band chi2.ppf(., D) / (D / 2):
    consistency_metrics' band of the run-averaged sum (chi2.ppf(., D) / N) divided by D / (2 N), the
    targets per run. With the same targets in every run this is the run average of each run's
    per-target mean.
    """
    band = consistency_metrics(name, nis_sum, dof)
    valid = np.isfinite(nis_sum)
    runs = valid.sum(axis=0)
    targets_per_run = np.where(valid, dof, 0.0).sum(axis=0) / np.maximum(2.0 * runs, 1.0)
    ok = (runs > 0) & (targets_per_run > 0)
    return {key: np.where(ok, values / np.where(ok, targets_per_run, 1.0), np.nan) for key, values in band.items()}


# the study's metric families (radar n, target m), pipeline.evaluation.metrics
register(Metric("bias_nees", "1 (chi2 dof = 4 per radar)", "-", dof="4 per radar"),
         Metric("bias_nees_lower", BAND, "-"), Metric("bias_nees_upper", BAND, "-"))
register_family(r"bias_rmse_(?P<component>[a-z_]+)_s(?P<sensor>\d+)",
                lambda m: Metric("", BIAS_UNITS[BIAS_NAMES.index(m["component"])], quantity="bias_rmse"))
register_family(r"bias_nees_s(?P<sensor>\d+)", lambda m: Metric("", "1 (chi2 dof = 4 per radar)", "-", dof=4,
                                                               quantity="bias_nees"))
register_family(r"track_nees_s(?P<sensor>\d+)_t(?P<target>\d+)_compensated",
                lambda m: Metric("", "1 (chi2 dof = 4)", "-", dof=4, quantity="compensated_nees"))
register_family(r"nis_s(?P<sensor>\d+)_(?P<band>lower|upper)",
                lambda m: Metric("", "1 (95 % chi2 band of the run and target average)", "-", quantity=f"nis_{m['band']}"))
register_family(r"nis_s(?P<sensor>\d+)", lambda m: Metric("", "1 (per-target mean of chi2 dof = 2; expected 2)", "-",
                                                         dof=2, quantity="nis"))
register_family(r"(?P<kind>position|velocity)_rmse_s(?P<sensor>\d+)_t(?P<target>\d+)(?P<compensated>_compensated)?",
                lambda m: Metric("", "m" if m["kind"] == "position" else "m/s",
                                 quantity=("compensated_" if m["compensated"] else "") + f"{m['kind']}_rmse"))


def bias_metric_units(names: Sequence[str]) -> dict[str, str]:
    """Units of the study's metric names (from the registry)."""
    return {name: unit_of(name) for name in names if lookup(name) is not None}
