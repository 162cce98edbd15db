"""The tables: in-memory stage outputs <-> tidy Parquet frames (one row per run x step x object).

One function pair per table, used by the writer and the reader alike. Vectors and matrices are
fixed-size ``pl.Array`` columns (matrices flattened row-major). Every file carries in its
key-value metadata the table name, the schema version, the units, and the provenance the
runner adds (experiment, config hash, cache key, package versions).
"""

from __future__ import annotations

import json
from typing import Mapping

import numpy as np
import polars as pl

from filters.base import TrackEstimate
from pipeline.data import Detections, Truth

SCHEMA_VERSION = "4"          # 2: estimates tables carry the fault column; 3: and the filters' NIS; 4: every table a content checksum
META_TABLE = "mtt.table"
META_VERSION = "mtt.schema_version"
META_UNITS = "mtt.units"
META_NAMES = "mtt.names"


class TableError(ValueError):
    """A Parquet file that is not the table it claims to be."""


def run_step_grid(R: int, K: int, T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    run = np.repeat(np.arange(R, dtype=np.int32), K * T)
    step = np.tile(np.repeat(np.arange(K, dtype=np.int32), T), R)
    obj = np.tile(np.arange(T, dtype=np.int32), R * K)
    return run, step, obj


def array_column(name: str, values: np.ndarray, rows: int) -> pl.Series:
    """(rows, ...) -> scalar column if no trailing dims, else a flattened fixed-size Array column."""
    flat = values.reshape(rows, -1) if values.ndim > 1 else values.reshape(rows)
    if flat.ndim == 1:
        return pl.Series(name, flat)
    inner = pl.Float64 if np.issubdtype(flat.dtype, np.floating) else pl.Int64
    return pl.Series(name, flat.astype(np.float64 if inner == pl.Float64 else np.int64), dtype=pl.Array(inner, flat.shape[1]))


def _column_array(df: pl.DataFrame, name: str, shape: tuple[int, ...]) -> np.ndarray:
    return df[name].to_numpy().reshape(shape)


def table_metadata(table: str, names: Mapping[str, object], units: Mapping[str, str]) -> dict[str, str]:
    return {META_TABLE: table, META_VERSION: SCHEMA_VERSION, META_NAMES: json.dumps(names),
            META_UNITS: json.dumps(units)}


# ---- truth -------------------------------------------------------------------------------
def truth_to_frame(truth: Truth) -> tuple[pl.DataFrame, dict[str, str]]:
    R, K, T, n = truth.state.shape
    run, step, target = run_step_grid(R, K, T)
    rows = R * K * T
    cols = [pl.Series("run", run), pl.Series("step", step), pl.Series("time", truth.time[step]),
            pl.Series("target", target), array_column("x", truth.state, rows)]
    label_shapes = {}
    for name, values in truth.labels.items():
        cols.append(array_column(name, values, rows))
        label_shapes[name] = list(values.shape[3:])
    meta = table_metadata("truth", {"state": list(truth.state_names), "labels": label_shapes},
                          {"time": "s", "x": "m, m/s (m/s^2 for ax, ay, az) per state_names", "acceleration": "m/s^2"})
    return pl.DataFrame(cols), meta


def truth_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> Truth:
    names = json.loads(meta[META_NAMES])
    R, K, T = _extent(df, "target")
    n = len(names["state"])
    time = df.filter((pl.col("run") == 0) & (pl.col("target") == 0))["time"].to_numpy()
    labels = {k: _column_array(df, k, (R, K, T, *shape)) for k, shape in names["labels"].items()}
    return Truth(time, _column_array(df, "x", (R, K, T, n)), tuple(names["state"]), labels)


# ---- detections ----------------------------------------------------------------------------
def detections_to_frame(d: Detections) -> tuple[pl.DataFrame, dict[str, str]]:
    R, K, D, m = d.z.shape
    run, step, slot = run_step_grid(R, K, D)
    rows = R * K * D
    target = d.target.reshape(rows)
    detected = d.detected.reshape(rows)
    df = pl.DataFrame([
        pl.Series("run", run), pl.Series("step", step), pl.Series("time", d.time[step]),
        pl.Series("sensor", d.sensor[step].astype(np.int32)), pl.Series("detection", slot),
        pl.Series("target", target.astype(np.int32)), array_column("z", d.z, rows),
        array_column("R", d.noise_covariance, rows), pl.Series("detected", detected),
        pl.Series("clutter", detected & (target < 0)),
    ])
    names: dict[str, object] = {"measurement": list(d.measurement_names)}
    units = {"time": "s", "z": "m per measurement names", "R": "m^2, row-major m x m"}
    if d.measurement_units:
        names["measurement_units"] = list(d.measurement_units)
        units["z"] = ", ".join(f"{n}: {u}" for n, u in zip(d.measurement_names, d.measurement_units))
        units["R"] = "row-major m x m, products of the z units"
    meta = table_metadata("detections", names, units)
    return df, meta


def detections_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> Detections:
    stated = json.loads(meta[META_NAMES])
    names = stated["measurement"]
    R, K, D = _extent(df, "detection")
    m = len(names)
    first = df.filter((pl.col("run") == 0) & (pl.col("detection") == 0))
    return Detections(
        time=first["time"].to_numpy(), sensor=first["sensor"].to_numpy(),
        z=_column_array(df, "z", (R, K, D, m)), noise_covariance=_column_array(df, "R", (R, K, D, m, m)),
        target=_column_array(df, "target", (R, K, D)), detected=_column_array(df, "detected", (R, K, D)),
        measurement_names=tuple(names), measurement_units=tuple(stated.get("measurement_units", ())),
    )


# ---- estimates -----------------------------------------------------------------------------
def estimate_to_frame(est: TrackEstimate, state_names: tuple[str, ...], compact_covariance: bool = False
                      ) -> tuple[pl.DataFrame, dict[str, str]]:
    """One row per run x step. ``compact_covariance`` stores P as its upper triangle in float32
    (column ``P_upper``, row-major i <= j): 3.4x smaller for a 6-state filter, for long runs
    (study 003: 100 runs x 10 001 steps) where the full float64 P would be ~200 MB per variant."""
    R, K, n = est.state.shape
    run, step, target = run_step_grid(R, K, 1)
    rows = R * K
    if compact_covariance:
        from pipeline.evaluation.kernels import pack_upper          # numba: only a packed covariance needs it
        upper = np.triu_indices(n)
        packed = np.empty((rows, upper[0].size), dtype=np.float32)
        pack_upper(np.ascontiguousarray(est.covariance).reshape(rows, n, n), upper[0], upper[1], packed)
        covariance = pl.Series("P_upper", packed, dtype=pl.Array(pl.Float32, upper[0].size))
    else:
        covariance = array_column("P", est.covariance, rows)
    cols = [pl.Series("run", run), pl.Series("step", step), pl.Series("time", est.time[step]),
            pl.Series("target", target), array_column("x", est.state, rows), covariance]
    extra_shapes = {}
    for name, values in est.extras.items():
        cols.append(array_column(name, values, rows))
        extra_shapes[name] = {"shape": list(values.shape[2:]), "dtype": str(values.dtype)}
    meta = table_metadata("estimates", {"state": list(state_names), "extras": extra_shapes},
                          {"time": "s", "x": "per state names",
                           "P": "row-major n x n" if not compact_covariance else "P_upper: upper triangle, float32",
                           "compute_seconds": str(est.compute_seconds)})
    return pl.DataFrame(cols), meta


def estimate_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> TrackEstimate:
    names = json.loads(meta[META_NAMES])
    R, K, _ = _extent(df, "target")
    n = len(names["state"])
    time = df.filter(pl.col("run") == 0)["time"].to_numpy()
    extras = {k: _column_array(df, k, (R, K, *v["shape"])).astype(v["dtype"]) for k, v in names["extras"].items()}
    seconds = float(json.loads(meta[META_UNITS]).get("compute_seconds", "nan"))
    if "P_upper" in df.columns:
        covariance = PackedCovariance(_column_array(df, "P_upper", (R, K, n * (n + 1) // 2)), n)
    else:
        covariance = _column_array(df, "P", (R, K, n, n))
    return TrackEstimate(time, _column_array(df, "x", (R, K, n)), covariance, extras, seconds)


class PackedCovariance:
    """(R, K, n, n) float64 covariances held as their float32 upper triangles (R, K, n(n+1)/2), as a
    compact estimate table stores them, and unpacked where used: whole by ``np.asarray`` (the
    symmetric float64 matrices, the same numbers as the table's every time), or a run at a time by
    ``covariance[r]`` / ``covariance[runs, ...]`` (a recording's run). A 100-run, 10 001-step,
    6-state variant holds 84 MB instead of 288 MB, so a job with four of them stays within ~1.5 GB;
    a metric that reads all of them unpacks them for as long as it needs them (0.1 s)."""

    def __init__(self, packed: np.ndarray, n: int) -> None:
        if packed.shape[-1] != n * (n + 1) // 2:
            raise ValueError(f"PackedCovariance: {packed.shape[-1]} entries per matrix, expected {n * (n + 1) // 2} "
                             f"for n = {n}")
        self.packed, self.n = packed, n
        self.shape = (*packed.shape[:-1], n, n)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(np.float64)
        self.size = int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _unpacked(self, packed: np.ndarray) -> np.ndarray:
        from pipeline.evaluation.kernels import unpack_upper        # numba: only a packed covariance needs it
        upper = np.triu_indices(self.n)
        out = np.empty((*packed.shape[:-1], self.n, self.n))
        unpack_upper(np.ascontiguousarray(packed).reshape(-1, packed.shape[-1]), upper[0], upper[1],
                     out.reshape(-1, self.n, self.n))
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self._unpacked(self.packed)
        return out if dtype is None else out.astype(dtype, copy=False)

    def __getitem__(self, key):
        """A leading run index or slice unpacks only the runs it selects; any other index unpacks all first."""
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) and key else (key, ())
        if isinstance(first, (int, np.integer)):
            selected = self._unpacked(self.packed[first])
            return selected[rest] if rest else selected
        if isinstance(first, slice) and not any(isinstance(k, (list, np.ndarray)) for k in rest):
            selected = self._unpacked(self.packed[first])
            return selected[(slice(None), *rest)] if rest else selected
        return np.asarray(self)[key]

    def __repr__(self) -> str:
        return f"PackedCovariance(shape={self.shape}, float32 upper triangles)"


def _extent(df: pl.DataFrame, object_column: str) -> tuple[int, int, int]:
    if df.height == 0:
        raise TableError("the table has no rows")
    R = int(df["run"].max()) + 1
    K = int(df["step"].max()) + 1
    T = int(df[object_column].max()) + 1
    if df.height != R * K * T:
        raise TableError(f"{df.height} rows do not fill the run x step x {object_column} grid {R}x{K}x{T}")
    return R, K, T
