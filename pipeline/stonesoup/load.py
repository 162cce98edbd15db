"""A stored run as Stone Soup objects: ``load_run(run_dir, run=0)``.

For Stone Soup's metric generators (OSPA, GOSPA, SIAP, ...) and plotters on what our pipeline wrote::

    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.measures import Euclidean
    from pipeline.stonesoup.load import load_run

    loaded = load_run("artifacts/runs/async_bias/<time>", run=0)
    gospa = GOSPAMetric(c=100, p=1, measure=Euclidean(mapping=loaded.position_mapping))
    metric = gospa.compute_over_time(*gospa.extract_states(loaded.tracks["proposed"], True),
                                     *gospa.extract_states(loaded.truths, True))

Times are ``pipeline.stonesoup.convert.EPOCH`` + the run's seconds; every state vector is in the
truth's state order (``state_names``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import polars as pl

from pipeline.stonesoup import require_stonesoup


@dataclass
class StoneSoupRun:
    """One Monte Carlo run of a stored run, as Stone Soup objects.

    Attributes
    ----------
    truths : set of GroundTruthPath, one per target (id ``target <t>``); states' metadata hold target, step
    scans : [(timestamp, set of Detection)] in time order, every scan (an empty set where nothing was
        detected): what a Stone Soup tracker reads. A detection of target t is a TrueDetection whose
        ``groundtruth_path`` is that target's path, clutter a Clutter; each carries its measurement model
        (the sensor's position as its translation offset, the noise covariance it reported) and metadata
        sensor, target, step, slot. None as the model for measurements Stone Soup has no model for here
    tracks : variant key -> set of Track, one per target (and per sensor where the table has one), of
        GaussianStates (the table's state and covariance; a step without an estimate has no state)
    names : variant key -> display name
    state_names : the truth's state order, which every state vector here follows
    """

    run_dir: Path
    run: int
    state_names: tuple[str, ...]
    measurement_names: tuple[str, ...]
    truths: set = field(default_factory=set)
    scans: list = field(default_factory=list)
    tracks: dict = field(default_factory=dict)
    names: dict = field(default_factory=dict)

    @property
    def detections(self) -> set:
        """Every detection of the run."""
        return {d for _, scan in self.scans for d in scan}

    @property
    def position_mapping(self) -> tuple[int, ...]:
        """The positions' indices in the state vectors (x, y[, z]): ``Euclidean(mapping=...)`` for OSPA/GOSPA."""
        return tuple(self.state_names.index(n) for n in ("x", "y", "z") if n in self.state_names)


def load_run(run_dir: str | Path, run: int = 0, variants: Sequence[str] | None = None,
             state_column: str = "x", plugins: Sequence[str] = ()) -> StoneSoupRun:
    """One Monte Carlo run of the stored run in ``run_dir`` as Stone Soup ground-truth paths, detections
    with their measurement models, and each variant's tracks (see ``StoneSoupRun``).

    ``variants``: the variant keys whose estimates become tracks (default: every estimates/*.parquet);
    ``state_column``: the estimate column read as the track's state (study 002's tables also have
    ``x_compensated``, the bias-compensated track, with ``P_compensated``); ``plugins``: the packages
    the run's ``plugins.packages`` lists that you trust (its sensor is rebuilt from config.yaml, and a
    stored folder's own list is not taken on its word: pipeline.run.stored.check_stored_packages).
    """
    require_stonesoup()
    from pipeline.storage.store import read_table
    run_dir = Path(run_dir)
    if not (run_dir / "truth.parquet").is_file():
        raise FileNotFoundError(f"{run_dir}: not a run folder (no truth.parquet)")
    truth_df, truth_meta = read_table(run_dir / "truth.parquet")
    runs = int(truth_df["run"].max()) + 1
    if not 0 <= int(run) < runs:
        raise ValueError(f"run: {run} is not one of the stored run's Monte Carlo runs 0..{runs - 1}")
    state_names = tuple(json.loads(truth_meta["mtt.names"])["state"])
    truths, paths = _truths(truth_df.filter(pl.col("run") == run), state_names)
    det_df, det_meta = read_table(run_dir / "detections.parquet")
    measurement_names = tuple(json.loads(det_meta["mtt.names"])["measurement"])
    positions = _sensor_positions(run_dir, plugins)
    scans = _scans(det_df.filter(pl.col("run") == run), measurement_names, state_names, positions, paths)
    available = sorted(p.stem for p in (run_dir / "estimates").glob("*.parquet"))
    keys = list(variants) if variants is not None else available
    unknown = [v for v in keys if v not in available]
    if unknown:
        raise ValueError(f"variants: {unknown} have no estimates in {run_dir / 'estimates'}; stored: {available}")
    tracks, names = {}, _display_names(run_dir)
    for key in keys:
        df, meta = read_table(run_dir / "estimates" / f"{key}.parquet")
        tracks[key] = _tracks(df.filter(pl.col("run") == run), meta, key, state_column, state_names)
    return StoneSoupRun(run_dir, int(run), state_names, measurement_names, truths, scans, tracks,
                        {k: names.get(k, k) for k in keys})


def _truths(df: pl.DataFrame, state_names: tuple[str, ...]) -> tuple[set, dict[int, Any]]:
    from stonesoup.types.array import StateVector
    from stonesoup.types.groundtruth import GroundTruthPath, GroundTruthState

    from pipeline.stonesoup.convert import timestamp
    df = df.sort("target", "step")
    x = np.asarray(df["x"].to_list(), dtype=float).reshape(df.height, len(state_names))
    paths: dict[int, Any] = {}
    for i, (target, step, time) in enumerate(zip(df["target"].to_list(), df["step"].to_list(), df["time"].to_list())):
        if not np.all(np.isfinite(x[i])):
            continue                                   # the target does not exist at this scan
        path = paths.setdefault(int(target), GroundTruthPath(id=f"target {int(target)}"))
        path.append(GroundTruthState(StateVector(x[i]), timestamp=timestamp(time),
                                     metadata={"target": int(target), "step": int(step)}))
    return set(paths.values()), paths


def _sensor_positions(run_dir: Path, plugins: Sequence[str] = ()) -> Any:
    """sensor id -> position (a radar's), from the run's sensor rebuilt from its config.yaml: a network's
    ``positions`` (S, d), a single sensor's ``position``; None where the sensor has none (positions)."""
    from pipeline.run.config import build, check_targets
    from pipeline.run.stored import check_stored_packages, stored_config
    cfg = stored_config(run_dir)
    check_stored_packages(cfg, run_dir, plugins, "load_run(..., plugins=[{packages}])")
    check_targets(cfg)                                  # a config is data: only allowed classes are built
    sensor = build(cfg.sensors, "sensors")
    many = getattr(sensor, "positions", None)
    if many is not None:
        many = np.asarray(many, dtype=float)
        return lambda s: many[int(s)]
    one = getattr(sensor, "position", None)
    one = None if one is None else np.asarray(one, dtype=float).ravel()
    return lambda s: one


def _scans(df: pl.DataFrame, names: tuple[str, ...], state_names: tuple[str, ...], position_of: Any,
           paths: dict[int, Any]) -> list:
    from stonesoup.types.detection import Clutter, TrueDetection

    from pipeline.stonesoup.convert import LAYOUTS, measurement_model, timestamp, to_stonesoup_vector
    df = df.sort("step", "detection")
    m = len(names)
    modelled = tuple(names) in LAYOUTS
    z = np.asarray(df["z"].to_list(), dtype=float).reshape(df.height, m)
    R = np.asarray(df["R"].to_list(), dtype=float).reshape(df.height, m, m)
    models: dict[tuple, Any] = {}
    scans: dict[int, tuple[Any, set]] = {}
    columns = zip(df["step"].to_list(), df["time"].to_list(), df["sensor"].to_list(), df["detection"].to_list(),
                  df["target"].to_list(), df["detected"].to_list())
    for i, (step, time, sensor, slot, target, detected) in enumerate(columns):
        when = timestamp(time)
        scan = scans.setdefault(int(step), (when, set()))[1]
        if not detected:
            continue
        model = None
        if modelled:
            key = (int(sensor), R[i].tobytes())
            if key not in models:
                models[key] = measurement_model(names, R[i], state_names, position_of(sensor))
            model = models[key]
            vector = to_stonesoup_vector(names, z[i])
        else:
            from stonesoup.types.array import StateVector
            vector = StateVector(z[i])
        metadata = {"sensor": int(sensor), "target": int(target), "step": int(step), "slot": int(slot)}
        if target >= 0 and int(target) in paths:
            scan.add(TrueDetection(vector, timestamp=when, measurement_model=model,
                                   groundtruth_path=paths[int(target)], metadata=metadata))
        else:
            scan.add(Clutter(vector, timestamp=when, measurement_model=model, metadata=metadata))
    return [scans[k] for k in sorted(scans)]


def _display_names(run_dir: Path) -> dict[str, str]:
    """variant key -> display name, from the run's summary (absent: the keys)."""
    path = run_dir / "summary.parquet"
    if not path.is_file():
        return {}
    summary = pl.read_parquet(path, columns=["variant_key", "variant"]).drop_nulls().unique()
    return dict(zip(summary["variant_key"].to_list(), summary["variant"].to_list()))


def _tracks(df: pl.DataFrame, meta: dict, key: str, column: str, state_names: tuple[str, ...]) -> set:
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track

    from filters.tracker import to_layout
    from pipeline.stonesoup.convert import timestamp
    if column not in df.columns:
        arrays = [c for c in df.columns if isinstance(df.schema[c], pl.Array)]
        raise ValueError(f"state_column: {column!r} is not a column of estimates/{key}.parquet; its state "
                         f"columns: {arrays}")
    names = tuple(json.loads(meta["mtt.names"])["state"])
    n = len(names)
    df = df.filter(pl.col(column).is_not_null())
    covariance_column = {"x": "P", "x_compensated": "P_compensated"}.get(column, "P")
    x = np.asarray(df[column].to_list(), dtype=float).reshape(df.height, n)
    if covariance_column in df.columns:
        P = np.asarray(df[covariance_column].to_list(), dtype=float).reshape(df.height, n, n)
    elif "P_upper" in df.columns:
        upper = np.triu_indices(n)
        packed = np.asarray(df["P_upper"].to_list(), dtype=float)
        P = np.zeros((df.height, n, n))
        P[:, upper[0], upper[1]] = packed
        P[:, upper[1], upper[0]] = packed
    else:
        P = np.full((df.height, n, n), np.nan)
    if names != state_names:
        x, P = to_layout(x, P, names, state_names)
    by_sensor = "sensor" in df.columns
    tracks: dict[tuple, Any] = {}
    sensors = df["sensor"].to_list() if by_sensor else [None] * df.height
    for i, (step, time, target, sensor) in enumerate(zip(df["step"].to_list(), df["time"].to_list(),
                                                         df["target"].to_list(), sensors)):
        if not np.all(np.isfinite(x[i])):
            continue                                    # no estimate yet at this step
        ident = (sensor, int(target))
        if ident not in tracks:
            where = "" if sensor is None else f" sensor {int(sensor)}"
            tracks[ident] = Track(id=f"{key}{where} target {int(target)}")
        tracks[ident].append(GaussianState(x[i].reshape(-1, 1), P[i], timestamp=timestamp(time)))
    return set(tracks.values())
