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
from pipeline.metrics import is_count, nees, unit_of

AXES = ("x", "y", "z")
@dataclass(frozen=True)
class Window:
    name: str
    first_step: int
    last_step: int


def _rmse(err: np.ndarray) -> np.ndarray:
    """err (R, K, d) -> (K,) sqrt(mean over runs of |err|^2), ignoring runs without an estimate."""
    return np.sqrt(np.nanmean(np.sum(err**2, axis=-1), axis=0))


def per_step_metrics(truth: Truth, estimate: TrackEstimate) -> dict[str, np.ndarray]:
    """Per-step Monte Carlo metrics (K,) of one variant against target 0's truth.

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
    out: dict[str, np.ndarray] = {}
    with np.errstate(invalid="ignore"), quiet_nanmean():
        out["position_rmse"] = _rmse(err[..., pos])
        if vel:
            out["velocity_rmse"] = _rmse(err[..., vel])
        if acc:
            out["acceleration_rmse"] = _rmse(err[..., acc])
        if "acceleration" in extras and "acceleration" in truth.labels:
            acc_err = extras["acceleration"] - truth.labels["acceleration"][:, :, 0, :]
            for i in range(min(acc_err.shape[-1], len(AXES))):
                out[f"acceleration_rmse_{AXES[i]}"] = _rmse(acc_err[..., i:i + 1])
        started = np.isfinite(estimate.state).all(axis=-1)
        # the run average with its 95 % chi-square band (n dof per valid run)
        out.update(consistency_metrics("nees", nees(err, estimate.covariance), err.shape[-1]))
        out.update(nis_metrics(extras))
        if "models_evaluated" in extras:
            evaluated = extras["models_evaluated"].astype(float)
            out["models_evaluated"] = np.where(started.any(axis=0), evaluated.mean(axis=0), np.nan)
        if "input_level" in extras:
            level = np.asarray(extras["input_level"], dtype=float)
            for i in range(min(level.shape[-1], len(AXES))):
                out[f"input_level_{AXES[i]}"] = np.nanmean(level[..., i], axis=0)
        if "maneuver_detected" in extras:
            out["detections"] = _count(extras["maneuver_detected"])
        if "maneuver_detected_axis" in extras:
            per_axis = np.asarray(extras["maneuver_detected_axis"])
            for i in range(min(per_axis.shape[-1], len(AXES))):
                out[f"detections_axis_{AXES[i]}"] = _count(per_axis[..., i])
    return out


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
    probability 1 - a. NaN where no run has a value.
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
    return {name: mean, f"{name}_lower": lower, f"{name}_upper": upper}


def nis_metrics(extras: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``nis``, ``nis_lower``, ``nis_upper`` from an estimator's extras (empty when it exports none).

    The filter convention: ``extras["nis"]`` (R, K) is each run's normalised innovation squared
    nu' S^-1 nu at each scan, from the innovation the filter itself used (an IMM's combined
    moment-matched prediction, a particle filter's predicted cloud), NaN where the run had no
    measurement or had not started; ``extras["nis_dof"]`` (R, K) the measurement dimension of that
    innovation (chi-square dof for a consistent filter).
    """
    if "nis" not in extras:
        return {}
    values = np.asarray(extras["nis"], dtype=float)
    dof = np.asarray(extras.get("nis_dof", np.nan), dtype=float)
    if not np.all(np.isfinite(np.broadcast_to(dof, values.shape)[np.isfinite(values)])):
        raise ValueError("extras['nis']: a NIS value without its dof: export extras['nis_dof'] (R, K) beside it")
    return consistency_metrics("nis", values, dof)


def _count(flags: np.ndarray) -> np.ndarray:
    """(R, K) 0/1 flags (NaN counts as 0) -> (K,) number of runs flagged at each step."""
    values = np.asarray(flags, dtype=float)
    return np.sum((values != 0) & np.isfinite(values), axis=0).astype(float)


@contextlib.contextmanager
def quiet_nanmean() -> Iterator[None]:
    """All-NaN columns (steps before the first estimate) are expected: silence numpy's warnings about
    them, and only those (a SingularBoundWarning raised meanwhile still reaches the runner)."""
    with warnings.catch_warnings():
        for message in ("Mean of empty slice", "All-NaN slice encountered", "Degrees of freedom <= 0",
                        "invalid value encountered", "divide by zero encountered"):
            warnings.filterwarnings("ignore", message=message, category=RuntimeWarning)
        yield


def metrics_frame(time: np.ndarray, variants: Mapping[str, tuple[str, dict[str, np.ndarray]]], runs: int
                  ) -> pl.DataFrame:
    """Long table: variant, variant_key, metric, step, time, value, n_runs."""
    parts = []
    K = time.size
    for key, (display, metrics) in variants.items():
        for metric, values in metrics.items():
            parts.append(pl.DataFrame({
                "variant": [display] * K, "variant_key": [key] * K, "series": [metric] * K,
                "step": np.arange(K, dtype=np.int32), "time": time.astype(float), "value": values.astype(float),
                "n_runs": np.full(K, runs, dtype=np.int32),
            }))
    return pl.concat(parts)


def group_reached(estimate: TrackEstimate, group: int, by_step: int) -> float | None:
    """Fraction of runs whose running set included ``group`` at some step <= by_step."""
    if "active_group" not in estimate.extras:
        return None
    active = estimate.extras["active_group"][:, : by_step + 1]
    if (active < 0).all():
        return None
    candidate = estimate.extras.get("candidate_group", np.full_like(active, -1))[:, : by_step + 1]
    return float(((active == group) | (candidate == group)).any(axis=1).mean())


def window_value(metric: str, values: np.ndarray, w: Window) -> float:
    """A per-step metric over a window: the sum for a count metric, else the mean (NaN steps ignored);
    NaN when the window holds no step (or, for a mean, no finite value)."""
    segment = values[w.first_step: w.last_step + 1]
    if not segment.size:
        return float("nan")
    if is_count(metric):
        return float(np.nansum(segment))
    with quiet_nanmean():
        return float(np.nanmean(segment))


def summary_rows(variants: Mapping[str, tuple[str, dict[str, np.ndarray]]], estimates: Mapping[str, TrackEstimate],
                 windows: Sequence[Window], reference_key: str | None, runs: int,
                 reached: tuple[str, int, int] | None = None, count_windows: Sequence[Window] = ()
                 ) -> pl.DataFrame:
    """Per variant: each per-step metric over each window (averaged; counts summed: the registry's
    aggregation, pipeline.metrics), the count metrics also over each of ``count_windows``, compute
    time, models per step (and both as % of the reference variant), and optionally the fraction of
    runs reaching a group. Units come from the metric registry."""
    rows: list[dict] = []

    def add(key, display, metric, window, value):
        rows.append({"variant": display, "variant_key": key, "series": metric, "window": window,
                     "value": None if value is None else float(value), "unit": unit_of(metric),
                     "n_runs": runs})

    for key, (display, metrics) in variants.items():
        for w in windows:
            for metric, values in metrics.items():
                add(key, display, metric, w.name, window_value(metric, values, w))
        for w in count_windows:
            for metric, values in metrics.items():
                if is_count(metric):
                    add(key, display, metric, w.name, window_value(metric, values, w))
        add(key, display, "compute_seconds", None, estimates[key].compute_seconds)
        if reached is not None:
            name, group, by_step = reached
            fraction = group_reached(estimates[key], group, by_step)
            if fraction is not None:
                add(key, display, "group_reached_fraction", f"{name} by step {by_step}", fraction)
    if reference_key is not None and reference_key in variants:
        ref_time = estimates[reference_key].compute_seconds
        ref_models = {w.name: _models_per_step(variants[reference_key][1], w) for w in windows}
        for key, (display, metrics) in variants.items():
            add(key, display, "compute_pct_of_reference", None, 100.0 * estimates[key].compute_seconds / ref_time)
            for w in windows:
                mine = _models_per_step(metrics, w)
                ref = ref_models[w.name]
                if mine is not None and ref is not None and np.isfinite(mine) and np.isfinite(ref) and ref:
                    add(key, display, "models_pct_of_reference", w.name, 100.0 * mine / ref)
    return pl.DataFrame(rows, schema={"variant": pl.String, "variant_key": pl.String, "series": pl.String,
                                      "window": pl.String, "value": pl.Float64, "unit": pl.String,
                                      "n_runs": pl.Int32})


def _models_per_step(metrics: Mapping[str, np.ndarray], w: Window) -> float | None:
    values = metrics.get("models_evaluated")
    return None if values is None else window_value("models_evaluated", values, w)
