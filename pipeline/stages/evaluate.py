"""Evaluate: Monte Carlo metrics per step, and their windowed summary per variant.

Pure functions of arrays; the runner adds provenance columns and writes the tables.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from filters.base import TrackEstimate
from pipeline.data import Truth

UNITS = {
    "acceleration_rmse_x": "m/s^2", "acceleration_rmse_y": "m/s^2", "position_rmse": "m",
    "velocity_rmse": "m/s", "nees": "1 (chi2 dof = n)", "models_evaluated": "models/step",
    "compute_seconds": "s", "compute_pct_of_reference": "%", "models_pct_of_reference": "%",
    "group_reached_fraction": "fraction of runs",
}


@dataclass(frozen=True)
class Window:
    name: str
    first_step: int
    last_step: int


def _rmse(err: np.ndarray) -> np.ndarray:
    """err (R, K, d) -> (K,) sqrt(mean over runs of |err|^2), ignoring runs without an estimate."""
    return np.sqrt(np.nanmean(np.sum(err**2, axis=-1), axis=0))


def per_step_metrics(truth: Truth, estimate: TrackEstimate) -> dict[str, np.ndarray]:
    """Per-step Monte Carlo metrics (K,) of one variant against target 0's truth."""
    names = truth.state_names
    x_true = truth.state[:, :, 0, :]
    err = estimate.state - x_true
    pos = [names.index(n) for n in ("x", "y") if n in names]
    vel = [names.index(n) for n in ("vx", "vy") if n in names]
    out: dict[str, np.ndarray] = {}
    with np.errstate(invalid="ignore"), _quiet_nanmean():
        out["position_rmse"] = _rmse(err[..., pos])
        if vel:
            out["velocity_rmse"] = _rmse(err[..., vel])
        if "acceleration" in estimate.extras and "acceleration" in truth.labels:
            acc_err = estimate.extras["acceleration"] - truth.labels["acceleration"][:, :, 0, :]
            out["acceleration_rmse_x"] = _rmse(acc_err[..., :1])
            out["acceleration_rmse_y"] = _rmse(acc_err[..., 1:2])
        started = np.isfinite(estimate.state).all(axis=-1)
        P = np.where(started[..., None, None], estimate.covariance, np.eye(err.shape[-1]))
        e = np.where(started[..., None], err, 0.0)
        nees = np.einsum("rki,rki->rk", e, np.linalg.solve(P, e[..., None])[..., 0])
        out["nees"] = np.nanmean(np.where(started, nees, np.nan), axis=0)
        if "models_evaluated" in estimate.extras:
            evaluated = estimate.extras["models_evaluated"].astype(float)
            out["models_evaluated"] = np.where(started.any(axis=0), evaluated.mean(axis=0), np.nan)
    return out


class _quiet_nanmean:
    """All-NaN columns (steps before the first estimate) are expected: silence their warnings."""

    def __enter__(self):
        import warnings
        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", category=RuntimeWarning)

    def __exit__(self, *exc):
        self._ctx.__exit__(*exc)


def metrics_frame(time: np.ndarray, variants: Mapping[str, tuple[str, dict[str, np.ndarray]]], runs: int
                  ) -> pl.DataFrame:
    """Long table: variant, variant_key, metric, step, time, value, n_runs."""
    parts = []
    K = time.size
    for key, (display, metrics) in variants.items():
        for metric, values in metrics.items():
            parts.append(pl.DataFrame({
                "variant": [display] * K, "variant_key": [key] * K, "metric": [metric] * K,
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


def summary_rows(variants: Mapping[str, tuple[str, dict[str, np.ndarray]]], estimates: Mapping[str, TrackEstimate],
                 windows: Sequence[Window], reference_key: str | None, runs: int,
                 reached: tuple[str, int, int] | None = None) -> pl.DataFrame:
    """Per variant: each per-step metric averaged over each window, compute time, models per step
    (and both as % of the reference variant), and optionally the fraction of runs reaching a group."""
    rows: list[dict] = []

    def add(key, display, metric, window, value):
        rows.append({"variant": display, "variant_key": key, "metric": metric, "window": window,
                     "value": None if value is None else float(value), "unit": UNITS.get(metric, ""),
                     "n_runs": runs})

    for key, (display, metrics) in variants.items():
        for w in windows:
            for metric, values in metrics.items():
                segment = values[w.first_step: w.last_step + 1]
                with _quiet_nanmean():
                    add(key, display, metric, w.name, np.nanmean(segment) if segment.size else np.nan)
        add(key, display, "compute_seconds", None, estimates[key].compute_seconds)
        if reached is not None:
            name, group, by_step = reached
            fraction = group_reached(estimates[key], group, by_step)
            if fraction is not None:
                add(key, display, "group_reached_fraction", f"{name} by step {by_step}", fraction)
    if reference_key is not None and reference_key in variants:
        ref_time = estimates[reference_key].compute_seconds
        ref_models = {w.name: _window_mean(variants[reference_key][1].get("models_evaluated"), w) for w in windows}
        for key, (display, metrics) in variants.items():
            add(key, display, "compute_pct_of_reference", None, 100.0 * estimates[key].compute_seconds / ref_time)
            for w in windows:
                mine = _window_mean(metrics.get("models_evaluated"), w)
                if mine is not None and ref_models[w.name]:
                    add(key, display, "models_pct_of_reference", w.name, 100.0 * mine / ref_models[w.name])
    return pl.DataFrame(rows, schema={"variant": pl.String, "variant_key": pl.String, "metric": pl.String,
                                      "window": pl.String, "value": pl.Float64, "unit": pl.String,
                                      "n_runs": pl.Int32})


def _window_mean(values: np.ndarray | None, w: Window) -> float | None:
    if values is None:
        return None
    segment = values[w.first_step: w.last_step + 1]
    with _quiet_nanmean():
        return float(np.nanmean(segment)) if segment.size else None
