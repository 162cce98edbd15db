"""Evaluate: Monte Carlo metrics per step, and their windowed summary per variant.

Pure functions of arrays; the runner adds provenance columns and writes the tables.
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np
import polars as pl

from filters.base import TrackEstimate
from pipeline.data import Truth
from pipeline.evaluation.metrics import is_count, nees, unit_of
from pipeline.evaluation.timing import Timing, compute_row_fields, ratio_fields
from pipeline.evaluation.uncertainty import (CONFIDENCE, RESAMPLES, Estimated, Interval, RunValues, WindowStatistic,
                                  comparisons_schema, counts_as_flags, normalised_squared, summarize)

AXES = ("x", "y", "z")
@dataclass(frozen=True)
class Window:
    name: str
    first_step: int
    last_step: int


def _squared(err: np.ndarray) -> np.ndarray:
    """err (R, K, d) -> (R, K) |err|^2 (NaN where the run has no estimate)."""
    return np.sum(err**2, axis=-1)


def per_step_metrics(truth: Truth, estimate: TrackEstimate) -> dict[str, RunValues | np.ndarray]:
    """Monte Carlo metrics of one variant against target 0's truth, kept per run (``RunValues``: the
    per-step value over the runs, and the summary's intervals, come from them); fixed (K,) arrays
    for the consistency bands.

    Errors are taken in the truth's state order (``truth.state_names``; estimates use the same):

    - ``position_rmse`` over x, y (and z when the state has it), ``velocity_rmse`` over vx, vy (vz);
    - ``acceleration_rmse``: 3-D (or 2-D) norm over the state's ax, ay, az, when the state has them;
    - ``acceleration_rmse_x/_y(/_z)``: per axis, from the estimator's ``acceleration`` extra against
      the truth's ``acceleration`` label, when both exist (study 001);
    - ``nees``: over the full state (chi-square with n = state size dof for a consistent filter), and
      ``nees_lower`` / ``nees_upper``: the 95 % band of its run average (``consistency_metrics``);
    - ``nis`` / ``nis_lower`` / ``nis_upper``: the run-averaged normalised innovation squared with
      its band, from the estimator's ``nis`` / ``nis_dof`` extras (``nis_metrics``);
    - ``models_evaluated``: mean over runs of the extra of that name;
    - ``input_level_x/_y/_z``: mean over runs of ``extras["input_level"]`` (R, K, 3) [m/s^2];
    - ``detections``: SUM over runs of ``extras["maneuver_detected"]`` (R, K) at each step (a count);
    - ``detections_axis_x/_y/_z``: the same for ``extras["maneuver_detected_axis"]`` (R, K, 3), in the
      estimator's own axis order (filter C of study 000: its LOS axes, as in the paper's Table 1).
    """
    names = truth.state_names
    x_true = truth.state[:, :, 0, :]
    err = estimate.state - x_true
    pos = [names.index(n) for n in ("x", "y", "z") if n in names]
    vel = [names.index(n) for n in ("vx", "vy", "vz") if n in names]
    acc = [names.index(n) for n in ("ax", "ay", "az") if n in names]
    extras = estimate.extras
    out: dict[str, RunValues | np.ndarray] = {}
    with np.errstate(invalid="ignore"), quiet_nanmean():
        out["position_rmse"] = RunValues(_squared(err[..., pos]), "rms")
        if vel:
            out["velocity_rmse"] = RunValues(_squared(err[..., vel]), "rms")
        if acc:
            out["acceleration_rmse"] = RunValues(_squared(err[..., acc]), "rms")
        if "acceleration" in extras and "acceleration" in truth.labels:
            acc_err = extras["acceleration"] - truth.labels["acceleration"][:, :, 0, :]
            for i in range(min(acc_err.shape[-1], len(AXES))):
                out[f"acceleration_rmse_{AXES[i]}"] = RunValues(_squared(acc_err[..., i:i + 1]), "rms")
        started = np.isfinite(estimate.state).all(axis=-1)
        # the run average with its 95 % chi-square band (n dof per valid run)
        out.update(consistency("nees", nees(err, estimate.covariance), err.shape[-1]))
        out.update(nis_metrics(extras, per_run=True))
        if "models_evaluated" in extras:
            evaluated = extras["models_evaluated"].astype(float)
            # every run counts at a step where any has started (a run not yet started evaluates none)
            out["models_evaluated"] = RunValues(np.where(started.any(axis=0)[None, :], evaluated, np.nan), "mean")
        if "input_level" in extras:
            level = np.asarray(extras["input_level"], dtype=float)
            for i in range(min(level.shape[-1], len(AXES))):
                out[f"input_level_{AXES[i]}"] = RunValues(level[..., i], "mean")
        if "maneuver_detected" in extras:
            out["detections"] = RunValues(counts_as_flags(extras["maneuver_detected"]), "sum")
        if "maneuver_detected_axis" in extras:
            per_axis = np.asarray(extras["maneuver_detected_axis"])
            for i in range(min(per_axis.shape[-1], len(AXES))):
                out[f"detections_axis_{AXES[i]}"] = RunValues(counts_as_flags(per_axis[..., i]), "sum")
    return out


def resolved(metrics: Mapping[str, RunValues | np.ndarray]) -> dict[str, np.ndarray]:
    """metric name -> (K,) per-step values: a RunValues' value over the runs, a fixed array as it is."""
    return {name: m.per_step() if isinstance(m, RunValues) else np.asarray(m, dtype=float)
            for name, m in metrics.items()}


def consistency(name: str, values: np.ndarray, dof: np.ndarray | int,
                probability: float | None = None) -> dict[str, RunValues | np.ndarray]:
    """``consistency_metrics`` with the run average kept per run (its interval: a mean over runs)."""
    band = consistency_metrics(name, values, dof, CONSISTENCY_PROBABILITY if probability is None else probability)
    band[name] = normalised_squared(values)
    return band


CONSISTENCY_PROBABILITY = 0.95


def consistency_metrics(name: str, values: np.ndarray, dof: np.ndarray | int,
                        probability: float = CONSISTENCY_PROBABILITY) -> dict[str, np.ndarray]:
    """Run-averaged NEES or NIS with its two-sided chi-square acceptance band, per step.

    ``values`` (R, K): each run's normalised squared error at each step (NaN where the run has
    none: not started, no measurement, diverged); ``dof`` (R, K) or a scalar: its chi-square
    degrees of freedom (the state or measurement dimension, which may change per step).

    Returns ``{name}`` (K,) the mean over the runs that have a value, and ``{name}_lower`` /
    ``{name}_upper`` the ``probability`` band of that mean for a consistent filter (Bar-Shalom,
    Li & Kirubarajan 2001, 5.4.2): with N valid runs whose dofs sum to D, the sum of the N values
    is chi-square(D), so the mean lies in [chi2.ppf(a/2, D), chi2.ppf(1 - a/2, D)] / N with
    probability 1 - a. NaN where no run has a value, and where a run's value is below zero (impossible
    for e' P^-1 e with P positive definite: ``normalised_squared``).
    """
    from scipy.stats import chi2

    values = np.asarray(values, dtype=float)
    valid = np.isfinite(values)
    dofs = np.broadcast_to(np.asarray(dof, dtype=float), values.shape)
    counts = valid.sum(axis=0)
    total_dof = np.where(valid, dofs, 0.0).sum(axis=0)
    tail = 0.5 * (1.0 - probability)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, np.where(valid, values, 0.0).sum(axis=0) / np.maximum(counts, 1), np.nan)
        lower = np.where(counts > 0, chi2.ppf(tail, np.maximum(total_dof, 1e-12)) / np.maximum(counts, 1), np.nan)
        upper = np.where(counts > 0, chi2.ppf(1.0 - tail, np.maximum(total_dof, 1e-12)) / np.maximum(counts, 1), np.nan)
        mean = np.where((values < 0).any(axis=0), np.nan, mean)      # an impossible value: no mean (normalised_squared)
    return {name: mean, f"{name}_lower": lower, f"{name}_upper": upper}


def nis_metrics(extras: Mapping[str, np.ndarray], per_run: bool = False) -> dict[str, np.ndarray | RunValues]:
    """``nis``, ``nis_lower``, ``nis_upper`` from an estimator's extras (empty when it exports none).

    The filter convention: ``extras["nis"]`` (R, K) is each run's normalised innovation squared
    nu' S^-1 nu at each scan, from the innovation the filter itself used (an IMM's combined
    moment-matched prediction, a particle filter's predicted cloud), NaN where the run had no
    measurement or had not started; ``extras["nis_dof"]`` (R, K) the measurement dimension of that
    innovation (chi-square dof for a consistent filter). ``per_run``: ``nis`` as a RunValues.
    """
    if "nis" not in extras:
        return {}
    values = np.asarray(extras["nis"], dtype=float)
    dof = np.asarray(extras.get("nis_dof", np.nan), dtype=float)
    if not np.all(np.isfinite(np.broadcast_to(dof, values.shape)[np.isfinite(values)])):
        raise ValueError("extras['nis']: a NIS value without its dof: export extras['nis_dof'] (R, K) beside it")
    return consistency("nis", values, dof) if per_run else consistency_metrics("nis", values, dof)


@contextlib.contextmanager
def quiet_nanmean() -> Iterator[None]:
    """All-NaN columns (steps before the first estimate) are expected: silence numpy's warnings about
    them, and only those (a SingularBoundWarning raised meanwhile still reaches the runner)."""
    with warnings.catch_warnings():
        for message in ("Mean of empty slice", "All-NaN slice encountered", "Degrees of freedom <= 0",
                        "invalid value encountered", "divide by zero encountered"):
            warnings.filterwarnings("ignore", message=message, category=RuntimeWarning)
        yield


def metrics_frame(time: np.ndarray, variants: Mapping[str, tuple[str, Mapping[str, RunValues | np.ndarray]]],
                  runs: int) -> pl.DataFrame:
    """Long table: variant, variant_key, metric, step, time, value, n_runs. A step where a metric is
    undefined (before the first estimate, the NIS before the first innovation) is null, not NaN, so
    SQL aggregates skip it."""
    parts = []
    K = time.size
    for key, (display, metrics) in variants.items():
        for metric, values in resolved(metrics).items():
            parts.append(pl.DataFrame({
                "variant": [display] * K, "variant_key": [key] * K, "series": [metric] * K,
                "step": np.arange(K, dtype=np.int32), "time": time.astype(float), "value": values.astype(float),
                "n_runs": np.full(K, runs, dtype=np.int32),
            }))
    return pl.concat(parts).with_columns(pl.col("value").fill_nan(None))


def group_reached(estimate: TrackEstimate, group: int, by_step: int) -> np.ndarray | None:
    """(R,) 1.0 for a run whose running set included ``group`` at some step <= by_step, else 0.0 (the
    summary's fraction of runs is their mean)."""
    if "active_group" not in estimate.extras:
        return None
    active = estimate.extras["active_group"][:, : by_step + 1]
    if (active < 0).all():
        return None
    candidate = estimate.extras.get("candidate_group", np.full_like(active, -1))[:, : by_step + 1]
    return ((active == group) | (candidate == group)).any(axis=1).astype(float)


def window_statistic(metric: str, values: RunValues, w: Window) -> WindowStatistic:
    """A per-step metric over a window: the sum for a count metric (the registry's aggregation), else
    the mean of the per-step values (NaN steps ignored)."""
    steps = np.arange(w.first_step, min(w.last_step, values.values.shape[1] - 1) + 1)
    return WindowStatistic(values, steps, "sum" if is_count(metric) else "mean")


def window_value(metric: str, values: np.ndarray, w: Window) -> float:
    """A fixed per-step array over a window, as ``window_statistic`` reduces it; NaN when the window
    holds no step (or, for a mean, no finite value)."""
    segment = values[w.first_step: w.last_step + 1]
    if not segment.size:
        return float("nan")
    if is_count(metric):
        return float(np.nansum(segment))
    with quiet_nanmean():
        return float(np.nanmean(segment))


SUMMARY_SCHEMA = {"variant": pl.String, "variant_key": pl.String, "series": pl.String, "window": pl.String,
                  "value": pl.Float64, "unit": pl.String, "n_runs": pl.Int32}
INTERVAL_SCHEMA = {"n_valid_runs": pl.Int32, "standard_error": pl.Float64, "ci_low": pl.Float64,
                   "ci_high": pl.Float64, "interval": pl.String}
# the compute rows' timing (pipeline.evaluation.timing): passes timed, a cached time, a ratio of two processes
TIMING_SCHEMA = {"compute_passes": pl.Int32, "compute_cached": pl.Boolean, "mixes_processes": pl.Boolean}


def summary_row(key: str, display: str, series: str, window: str | None, value: float | None, runs: int,
                statistic: WindowStatistic | None = None) -> dict:
    """One summary row; with ``statistic`` (how the value comes from the runs) it gets an interval, and
    its value is the statistic's."""
    if statistic is not None:
        value = statistic.value()
    return {"variant": display, "variant_key": key, "series": series, "window": window,
            "value": None if value is None else float(value), "unit": unit_of(series), "n_runs": runs,
            "statistic": statistic}


SAME_AS_REFERENCE = "same as reference_key"


def summary_rows(variants: Mapping[str, tuple[str, Mapping[str, RunValues | np.ndarray]]],
                 compute_seconds: Mapping[str, float], windows: Sequence[Window], reference_key: str | None,
                 runs: int, reached: tuple[str, int, int] | None = None, count_windows: Sequence[Window] = (),
                 compute_reference: str | None = SAME_AS_REFERENCE,
                 reached_fractions: Mapping[str, np.ndarray | None] | None = None) -> list[dict]:
    """Per variant: each per-step metric over each window (averaged; counts summed: the registry's
    aggregation, pipeline.evaluation.metrics), the count metrics also over each of ``count_windows``, compute
    time (and as % of ``compute_reference``, by default the reference variant; none when it is None:
    a study whose variants have no sensible common yardstick prints seconds only), models per step
    (and as % of the reference variant), and optionally the fraction of runs reaching a group
    (``reached`` names it, ``reached_fractions`` holds each variant's ``group_reached``).
    ``compute_seconds``: each variant's filtering time. Units come from the metric registry; a
    percentage's unit names its reference ("% of FSIMM"), which the printed table's header shows.
    Rows of metrics kept per run carry their ``statistic`` (``summary_table`` turns them into
    intervals). The rows of ``variant_rows`` for each variant, then those of ``reference_rows``."""
    rows: list[dict] = []
    for key, (display, metrics) in variants.items():
        rows += variant_rows(key, display, metrics, compute_seconds[key], windows, runs, reached, count_windows,
                             (reached_fractions or {}).get(key))
    models = {key: models_per_step(metrics, windows) for key, (_, metrics) in variants.items()}
    return rows + reference_rows({key: display for key, (display, _) in variants.items()}, compute_seconds, models,
                                 windows, reference_key, runs, compute_reference)


def _row(key: str, display: str, metric: str, window: str | None, values, runs: int, w: Window | None = None) -> dict:
    if isinstance(values, RunValues):
        return summary_row(key, display, metric, window, None, runs, window_statistic(metric, values, w))
    value = window_value(metric, values, w) if w is not None else values
    return summary_row(key, display, metric, window, value, runs)


def variant_rows(key: str, display: str, metrics: Mapping[str, RunValues | np.ndarray], compute_seconds: float | Timing,
                 windows: Sequence[Window], runs: int, reached: tuple[str, int, int] | None = None,
                 count_windows: Sequence[Window] = (), reached_fraction: np.ndarray | None = None) -> list[dict]:
    """One variant's rows of ``summary_rows``: its metrics over the windows (counts also over the
    count windows), its compute time, the fraction of its runs reaching ``reached``'s group."""
    rows = [_row(key, display, metric, w.name, values, runs, w) for w in windows for metric, values in metrics.items()]
    rows += [_row(key, display, metric, w.name, values, runs, w) for w in count_windows
             for metric, values in metrics.items() if is_count(metric)]
    rows.append(compute_row(key, display, compute_seconds, runs))
    if reached is not None and reached_fraction is not None:
        name, _, by_step = reached
        rows.append(_row(key, display, "group_reached_fraction", f"{name} by step {by_step}",
                         RunValues(reached_fraction[:, None], "mean"), runs, Window("", 0, 0)))
    return rows


def compute_row(key: str, display: str, compute_seconds: float | Timing, runs: int) -> dict:
    """A variant's ``compute_seconds`` row: a float is one pass; a ``Timing`` gives the median of its
    passes with their range, how many, and whether it is a cached time (pipeline.evaluation.timing)."""
    timing = compute_seconds if isinstance(compute_seconds, Timing) else Timing((float(compute_seconds),))
    return _row(key, display, "compute_seconds", None, timing.median(), runs) | compute_row_fields(timing)


def models_per_step(metrics: Mapping[str, RunValues | np.ndarray], windows: Sequence[Window]) -> dict[str, float | None]:
    """window name -> a variant's mean models evaluated per step (None without that metric)."""
    return {w.name: _models_per_step(metrics, w) for w in windows}


def reference_rows(display: Mapping[str, str], compute_seconds: Mapping[str, float | Timing],
                   models: Mapping[str, Mapping[str, float | None]], windows: Sequence[Window],
                   reference_key: str | None, runs: int, compute_reference: str | None = SAME_AS_REFERENCE
                   ) -> list[dict]:
    """The rows of ``summary_rows`` across variants: compute time as % of ``compute_reference``'s (the
    ratio of the medians of the passes, its interval from their ranges, flagged where one of the two
    times is cached and the other not: pipeline.evaluation.timing), and
    models per step (``models``: each variant's ``models_per_step``) as % of the reference variant's."""
    if compute_reference == SAME_AS_REFERENCE:
        compute_reference = reference_key
    rows: list[dict] = []
    if compute_reference is not None and compute_reference in display:
        timings = {key: t if isinstance(t, Timing) else Timing((float(t),)) for key, t in compute_seconds.items()}
        ref_time = timings[compute_reference]
        for key, name in display.items():
            fields = ratio_fields(timings[key], ref_time, key == compute_reference)
            rows.append(_row(key, name, "compute_pct_of_reference", None, fields["value"], runs) | fields
                        | {"unit": f"% of {display[compute_reference]}"})
    if reference_key is not None and reference_key in display:
        ref_models = models[reference_key]
        for key, name in display.items():
            for w in windows:
                mine, ref = models[key][w.name], ref_models[w.name]
                if mine is not None and ref is not None and np.isfinite(mine) and np.isfinite(ref) and ref:
                    rows.append(_row(key, name, "models_pct_of_reference", w.name, 100.0 * mine / ref, runs)
                                | {"unit": f"% of {display[reference_key]}"})
    return rows


def _models_per_step(metrics: Mapping[str, RunValues | np.ndarray], w: Window) -> float | None:
    values = metrics.get("models_evaluated")
    if values is None:
        return None
    if isinstance(values, RunValues):
        return window_statistic("models_evaluated", values, w).value()
    return window_value("models_evaluated", values, w)


def summary_table(rows: Sequence[dict], reference_key: str | None, seed: int, confidence: float = CONFIDENCE,
                  resamples: int = RESAMPLES) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(summary, comparisons, per-run, resamples) tables from summary rows (``summary_row``).

    summary: each row with ``n_valid_runs``, ``standard_error``, ``ci_low``, ``ci_high`` and the
    ``interval`` method (pipeline.evaluation.uncertainty); null for a value not estimated from runs (compute
    time, a bound, a study's value without per-run data). ``models_pct_of_reference`` gets the
    interval of the paired ratio of models per step (x 100).
    comparisons: each variant against ``reference_key`` per series and window (pipeline.evaluation.uncertainty).
    per-run: run x variant x series x window, each run's own value (``WindowStatistic.per_run``).
    """
    estimated = [Estimated(r["variant_key"], r["series"], r["window"], r["statistic"])
                 for r in rows if r.get("statistic") is not None]
    kept: dict = {}
    intervals, comparisons = summarize(estimated, reference_key, seed, confidence, resamples, kept)
    by_row: dict[int, Interval] = {}
    j = 0
    for i, r in enumerate(rows):
        if r.get("statistic") is not None:
            by_row[i] = intervals[j]
            j += 1
    ratio = {(c["variant_key"], c["window"]): c for c in comparisons if c["series"] == "models_evaluated"}
    records = []
    for i, r in enumerate(rows):
        record = {k: v for k, v in r.items() if k != "statistic"}
        interval = by_row.get(i)
        if interval is not None:
            record |= {"n_valid_runs": interval.n_valid_runs, "standard_error": interval.standard_error,
                       "ci_low": interval.low, "ci_high": interval.high, "interval": interval.method}
        elif r["series"] == "models_pct_of_reference" and (r["variant_key"], r["window"]) in ratio:
            c = ratio[(r["variant_key"], r["window"])]
            record |= {"n_valid_runs": c["n_paired_runs"], "standard_error": None,
                       "ci_low": 100 * c["ratio_low"], "ci_high": 100 * c["ratio_high"],
                       "interval": "bootstrap BCa (paired ratio)"}
        elif r["series"] == "models_pct_of_reference" and r["variant_key"] == reference_key:
            record |= {"n_valid_runs": None, "standard_error": 0.0, "ci_low": r["value"], "ci_high": r["value"],
                       "interval": "constant"}
        records.append(record)
    summary = pl.DataFrame(records, schema=SUMMARY_SCHEMA | INTERVAL_SCHEMA | TIMING_SCHEMA)
    summary = summary.with_columns(pl.col(c).fill_nan(None) for c in ("value", "standard_error", "ci_low", "ci_high"))
    compared = pl.DataFrame(comparisons, schema=comparisons_schema()).with_columns(
        pl.col(pl.Float64).fill_nan(None))
    per_run = per_run_table(rows)
    return summary, compared, per_run, resamples_table(estimated, kept.get("values"))


def resamples_table(estimated: Sequence[Estimated], values: np.ndarray | None) -> pl.DataFrame:
    """variant_key x series x window x resample: the first joint bootstrap resamples of every summary
    statistic (the same resampled runs in every row), on which the report judges compound targets."""
    schema = {"variant_key": pl.String, "series": pl.String, "window": pl.String, "resample": pl.Int16,
              "value": pl.Float64}
    if values is None or not len(estimated):
        return pl.DataFrame(schema=schema)
    count = values.shape[1]
    return pl.DataFrame({
        "variant_key": np.repeat([e.variant for e in estimated], count),
        "series": np.repeat([e.series for e in estimated], count),
        "window": pl.Series(np.repeat(np.array([e.window for e in estimated], dtype=object), count), dtype=pl.String),
        "resample": np.tile(np.arange(count, dtype=np.int16), len(estimated)),
        "value": values.reshape(-1).astype(float)}, schema=schema).with_columns(pl.col("value").fill_nan(None))


def per_run_table(rows: Sequence[dict]) -> pl.DataFrame:
    """run x variant x series x window: each run's own value of every summary statistic (one frame
    built from the stacked values, not one per statistic)."""
    estimated = [r for r in rows if r.get("statistic") is not None]
    values = [r["statistic"].per_run().astype(float) for r in estimated]
    counts = [v.size for v in values]

    def repeated(key: str) -> pl.Series:
        return pl.Series(key, np.repeat(np.array([r[key] for r in estimated], dtype=object), counts), dtype=pl.String)

    return pl.DataFrame({
        "run": np.concatenate([np.arange(n, dtype=np.int32) for n in counts]) if counts else np.zeros(0, np.int32),
        "variant": repeated("variant"), "variant_key": repeated("variant_key"), "series": repeated("series"),
        "window": repeated("window"),
        "value": np.concatenate(values) if values else np.zeros(0)}).with_columns(pl.col("value").fill_nan(None))
