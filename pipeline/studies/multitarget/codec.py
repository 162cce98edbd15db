"""The multi-target study's long tables: only what exists gets a row.

- ``truth``: one row per run x step x target that exists (column ``target``: its id, 0-based);
- ``detections``: one row per detection (``detection``: its slot in the scan, ``target``: the true
  origin, -1 for clutter; ``clutter``), so a scan has as many rows as it has detections;
- ``tracks`` (the estimate table): one row per run x step x track slot that holds a track
  (``track_id``, ``x``, ``P``, ``confirmed``, ``existence``), plus one scan row per run x step
  (``slot`` -1, ``track_id`` -1, track columns null) that carries the tracker's per-scan extras
  (e.g. a PHD's ``cardinality``) and keeps every scan present when it has no track.

Each table's metadata carries what a reader needs beyond its rows (runs, scans, times, slots), so
the padded arrays of pipeline.data / filters.multitarget come back exactly.
"""

from __future__ import annotations

import json
from typing import Mapping

import numpy as np
import polars as pl

from filters.multitarget import TrackSets
from pipeline.data import Detections, Truth
from pipeline.storage.schemas import META_NAMES, META_UNITS, TableError, array_column, table_metadata

SCAN_ROW = -1                     # the slot of a tracks table's per-scan row


def _names(meta: Mapping[str, str]) -> dict:
    return json.loads(meta[META_NAMES])


# ---- truth -------------------------------------------------------------------------------------
def truth_to_frame(truth: Truth) -> tuple[pl.DataFrame, dict[str, str]]:
    """Rows (run, step, time, target, x, labels...) where the target exists (finite state)."""
    R, K, T, n = truth.state.shape
    run, step, target = np.nonzero(np.all(np.isfinite(truth.state), axis=-1))
    rows = run.size
    cols = [pl.Series("run", run.astype(np.int32)), pl.Series("step", step.astype(np.int32)),
            pl.Series("time", np.asarray(truth.time, dtype=float)[step]), pl.Series("target", target.astype(np.int32)),
            array_column("x", truth.state[run, step, target], rows)]
    label_shapes = {}
    for name, values in truth.labels.items():
        cols.append(array_column(name, np.asarray(values)[run, step, target], rows))
        label_shapes[name] = list(np.shape(values)[3:])
    names = {"state": list(truth.state_names), "labels": label_shapes, "runs": R, "targets": T,
             "time": np.asarray(truth.time, dtype=float).tolist()}
    meta = table_metadata("truth", names, {"time": "s", "x": "m, m/s per state names", "turn_rate": "rad/s"})
    return pl.DataFrame(cols, schema_overrides={"x": pl.Array(pl.Float64, n)} if rows == 0 else None), meta


def truth_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> Truth:
    names = _names(meta)
    R, T, time = int(names["runs"]), int(names["targets"]), np.asarray(names["time"], dtype=float)
    K, n = time.size, len(names["state"])
    run, step, target = (df[c].to_numpy().astype(int) for c in ("run", "step", "target"))
    state = np.full((R, K, T, n), np.nan)
    state[run, step, target] = df["x"].to_numpy().reshape(-1, n)
    labels = {}
    for name, shape in names["labels"].items():
        values = np.full((R, K, T, *shape), np.nan)
        values[run, step, target] = df[name].to_numpy().reshape((-1, *shape))
        labels[name] = values
    return Truth(time, state, tuple(names["state"]), labels)


# ---- detections --------------------------------------------------------------------------------
def detections_to_frame(d: Detections) -> tuple[pl.DataFrame, dict[str, str]]:
    """Rows (run, step, time, detection, target, z, clutter) of the filled slots; the sensor's noise
    covariance (the same for every detection) is in the metadata."""
    R, K, D, m = d.z.shape
    run, step, slot = np.nonzero(d.detected)
    target = d.target[run, step, slot]
    cov = np.asarray(d.noise_covariance)
    constant = cov.reshape(-1, m, m)[:1] if cov.size else np.zeros((1, m, m))
    if cov.size and not np.allclose(cov.reshape(-1, m, m), constant):
        raise TableError("detections: the multi-target table stores one noise covariance for every detection; "
                         "these detections carry several")
    df = pl.DataFrame([
        pl.Series("run", run.astype(np.int32)), pl.Series("step", step.astype(np.int32)),
        pl.Series("time", d.time[step]), pl.Series("detection", slot.astype(np.int32)),
        pl.Series("target", target.astype(np.int32)),
        pl.Series("z", d.z[run, step, slot].astype(np.float64), dtype=pl.Array(pl.Float64, m)),
        pl.Series("clutter", target < 0)])
    names = {"measurement": list(d.measurement_names), "measurement_units": list(d.measurement_units),
             "runs": R, "slots": D, "time": np.asarray(d.time, dtype=float).tolist(),
             "sensor": np.asarray(d.sensor).astype(int).tolist(), "noise_covariance": constant[0].tolist()}
    meta = table_metadata("detections", names, {"time": "s", "z": "m per measurement names",
                                                "target": "true origin (-1: clutter)"})
    return df, meta


def detections_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> Detections:
    names = _names(meta)
    R, D, time = int(names["runs"]), int(names["slots"]), np.asarray(names["time"], dtype=float)
    K, m = time.size, len(names["measurement"])
    run, step, slot = (df[c].to_numpy().astype(int) for c in ("run", "step", "detection"))
    z = np.full((R, K, D, m), np.nan)
    z[run, step, slot] = df["z"].to_numpy().reshape(-1, m)
    target = np.full((R, K, D), -1, dtype=np.int64)
    target[run, step, slot] = df["target"].to_numpy()
    detected = np.zeros((R, K, D), dtype=bool)
    detected[run, step, slot] = True
    cov = np.broadcast_to(np.asarray(names["noise_covariance"], dtype=float), (R, K, D, m, m))
    return Detections(time, np.asarray(names["sensor"], dtype=int), z, cov, target, detected,
                      tuple(names["measurement"]), tuple(names.get("measurement_units", ())))


# ---- tracks ------------------------------------------------------------------------------------
def tracks_to_frame(tracks: TrackSets, state_names: tuple[str, ...]) -> tuple[pl.DataFrame, dict[str, str]]:
    """Rows of the filled track slots (track_id >= 0) and one scan row per run x step (module docstring)."""
    R, K, M, n = tracks.state.shape
    run, step, slot = np.nonzero(np.asarray(tracks.track_id) >= 0)
    scan_run, scan_step = (a.ravel() for a in np.meshgrid(np.arange(R), np.arange(K), indexing="ij"))
    rows, scans = run.size, scan_run.size
    total = rows + scans
    time = np.asarray(tracks.time, dtype=float)

    def stacked(track_values: np.ndarray, scan_fill) -> np.ndarray:
        scan_part = np.full((scans,) + track_values.shape[1:], scan_fill, dtype=track_values.dtype)
        return np.concatenate([track_values, scan_part])

    state = stacked(np.asarray(tracks.state, dtype=float)[run, step, slot], np.nan)
    cov = stacked(np.asarray(tracks.covariance, dtype=float)[run, step, slot], np.nan)
    cols = [pl.Series("run", np.r_[run, scan_run].astype(np.int32)),
            pl.Series("step", np.r_[step, scan_step].astype(np.int32)),
            pl.Series("time", time[np.r_[step, scan_step]]),
            pl.Series("slot", np.r_[slot, np.full(scans, SCAN_ROW)].astype(np.int32)),
            pl.Series("track_id", np.r_[np.asarray(tracks.track_id)[run, step, slot], np.full(scans, -1)].astype(np.int64)),
            array_column("x", state, total), array_column("P", cov, total),
            pl.Series("confirmed", np.r_[np.asarray(tracks.confirmed)[run, step, slot], np.zeros(scans, bool)]),
            pl.Series("existence", np.r_[np.asarray(tracks.existence, dtype=float)[run, step, slot], np.full(scans, np.nan)])]
    extras = {}
    for name, values in tracks.extras.items():
        values = np.asarray(values)
        per_scan = values[scan_run, scan_step]
        fill = np.zeros if values.dtype == bool else (lambda shape, dtype: np.full(shape, np.nan if np.issubdtype(
            dtype, np.floating) else -1, dtype=dtype))
        full = np.concatenate([fill((rows,) + values.shape[2:], values.dtype), per_scan])
        cols.append(array_column(name, full, total))
        extras[name] = {"shape": list(values.shape[2:]), "dtype": str(values.dtype)}
    # rows by run, step, slot (the scan row first): a table written in chunks of runs is the same table
    df = pl.DataFrame(cols).sort("run", "step", "slot", maintain_order=True)
    # the track columns are null on the scan rows (NaN in memory)
    df = df.with_columns([pl.when(pl.col("slot") >= 0).then(pl.col(c)).otherwise(None).alias(c)
                          for c in ("x", "P", "confirmed", "existence")])
    names = {"state": list(state_names), "runs": R, "slots": M, "time": time.tolist(), "extras": extras}
    meta = table_metadata("tracks", names, {"time": "s", "x": "per state names", "P": "row-major n x n",
                                            "existence": "probability of existence or component weight",
                                            "compute_seconds": str(tracks.compute_seconds)})
    return df, meta


def tracks_from_frame(df: pl.DataFrame, meta: Mapping[str, str]) -> TrackSets:
    names = _names(meta)
    # a table written in chunks of runs (mc.chunk_runs) carries one chunk's metadata: runs and slots come from
    # the rows (every run has its scan rows)
    time = np.asarray(names["time"], dtype=float)
    K, n = time.size, len(names["state"])
    R = int(df["run"].max()) + 1 if df.height else 0
    track = df.filter(pl.col("slot") >= 0)
    M = max(int(track["slot"].max()) + 1 if track.height else 0, int(names["slots"]), 1)
    scan = df.filter(pl.col("slot") == SCAN_ROW).sort("run", "step")
    if scan.height != R * K:
        raise TableError(f"tracks: {scan.height} scan rows do not fill the {R} runs x {K} scans")
    run, step, slot = (track[c].to_numpy().astype(int) for c in ("run", "step", "slot"))
    state = np.full((R, K, M, n), np.nan)
    cov = np.full((R, K, M, n, n), np.nan)
    track_id = np.full((R, K, M), -1, dtype=np.int64)
    confirmed = np.zeros((R, K, M), dtype=bool)
    existence = np.full((R, K, M), np.nan)
    if track.height:
        state[run, step, slot] = track["x"].to_numpy().reshape(-1, n)
        cov[run, step, slot] = track["P"].to_numpy().reshape(-1, n, n)
        track_id[run, step, slot] = track["track_id"].to_numpy()
        confirmed[run, step, slot] = track["confirmed"].to_numpy()
        existence[run, step, slot] = track["existence"].to_numpy().astype(float)
    extras = {name: scan[name].to_numpy().reshape((R, K, *spec["shape"])).astype(spec["dtype"])
              for name, spec in names["extras"].items()}
    seconds = float(json.loads(meta[META_UNITS]).get("compute_seconds", "nan"))
    return TrackSets(time, state, cov, track_id, confirmed, existence, extras, seconds)
