"""Study 002's estimate table: the stacked bias estimate and every kept target's local tracks.

The table codec of ``BiasRegistrationStudy`` (``estimate_to_frame`` / ``estimate_from_frame``),
built on the shared helpers of ``pipeline.storage.schemas``.
"""

from __future__ import annotations

import json
from typing import Mapping

import numpy as np
import polars as pl

from filters.bias import BIAS_NAMES, STATE_NAMES as BIAS_STUDY_STATE, BiasRegistrationResult
from pipeline.storage.schemas import META_NAMES, META_UNITS, TableError, array_column, run_step_grid, table_metadata


def bias_estimates_to_frame(res: BiasRegistrationResult) -> tuple[pl.DataFrame, dict[str, str]]:
    """Rows (run, step, time, sensor, target): target -1 is the stacked bias estimate (columns
    bias, bias_P; the others null), target >= 0 a kept target's local track of the reporting radar
    (x, P biased; x_compensated, P_compensated; bias columns null)."""
    R, K, Tsel, _ = res.track_state.shape
    objects = np.concatenate([[-1], res.targets]).astype(np.int32)
    run, step, slot = run_step_grid(R, K, Tsel + 1)
    rows = run.size
    is_bias = slot == 0

    def per_object(bias_part: np.ndarray | None, track_part: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
        full = np.full((R, K, Tsel + 1) + shape, np.nan)
        if bias_part is not None:
            full[:, :, 0] = bias_part
        if track_part is not None:
            full[:, :, 1:] = track_part
        return full

    n = res.bias.shape[-1]
    cols = [pl.Series("run", run), pl.Series("step", step), pl.Series("time", res.time[step]),
            pl.Series("sensor", res.sensor[step].astype(np.int32)), pl.Series("target", objects[slot])]
    for name, bias_part, track_part, shape in (
            ("x", None, res.track_state, (4,)), ("P", None, res.track_covariance, (4, 4)),
            ("x_compensated", None, res.compensated_state, (4,)),
            ("P_compensated", None, res.compensated_covariance, (4, 4)),
            ("bias", res.bias, None, (n,)), ("bias_P", res.bias_covariance, None, (n, n))):
        column = array_column(name, per_object(bias_part, track_part, shape), rows)
        keep = is_bias if track_part is None else ~is_bias
        cols.append(pl.select(pl.when(pl.Series(keep)).then(column)).to_series().alias(name))
    units = {"time": "s", "x": "m, m/s (x, y, vx, vy)", "P": "row-major 4 x 4", "bias": "per radar: m, rad, 1, 1",
             "bias_P": f"row-major {n} x {n}", "compute_seconds": str(res.compute_seconds)}
    if res.nis is not None and res.nis_dof is not None:
        # the reporting radar's local-track NIS, one value per report: on the bias rows
        for name, values in (("nis", res.nis), ("nis_dof", res.nis_dof)):
            full = np.full((R, K, Tsel + 1), np.nan)
            full[:, :, 0] = values
            cols.append(pl.select(pl.when(pl.Series(is_bias)).then(pl.Series(name, full.reshape(-1))))
                        .to_series().alias(name))
        units.update(nis="1 (sum over the reporting radar's tracked targets of nu' S^-1 nu)",
                     nis_dof="chi2 dof of nis (2 per target, summed)")
    meta = table_metadata("bias_estimates", {"state": list(BIAS_STUDY_STATE), "bias": list(BIAS_NAMES),
                                             "targets": res.targets.tolist()}, units)
    return pl.DataFrame(cols), meta


def bias_estimates_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> BiasRegistrationResult:
    names = json.loads(meta[META_NAMES])
    targets = np.asarray(names["targets"], dtype=int)
    df = df.sort("run", "step", "target")
    R = int(df["run"].max()) + 1
    K = int(df["step"].max()) + 1
    Tsel = targets.size
    if df.height != R * K * (Tsel + 1):
        raise TableError(f"{df.height} rows do not fill the run x step x (bias + {Tsel} targets) grid")
    bias_rows = df.filter(pl.col("target") < 0)
    track_rows = df.filter(pl.col("target") >= 0)
    n = bias_rows["bias"].dtype.size
    first = bias_rows.filter(pl.col("run") == 0)
    seconds = float(json.loads(meta[META_UNITS]).get("compute_seconds", "nan"))

    def arr(frame: pl.DataFrame, name: str, shape: tuple[int, ...]) -> np.ndarray:
        return frame[name].to_numpy().reshape(shape).astype(float)

    return BiasRegistrationResult(
        first["time"].to_numpy(), first["sensor"].to_numpy().astype(int), arr(bias_rows, "bias", (R, K, n)),
        arr(bias_rows, "bias_P", (R, K, n, n)), targets, arr(track_rows, "x", (R, K, Tsel, 4)),
        arr(track_rows, "P", (R, K, Tsel, 4, 4)), arr(track_rows, "x_compensated", (R, K, Tsel, 4)),
        arr(track_rows, "P_compensated", (R, K, Tsel, 4, 4)), seconds,
        *((arr(bias_rows, "nis", (R, K)), arr(bias_rows, "nis_dof", (R, K))) if "nis" in df.columns else ()))
