"""Track: what the filters see of the detections.

Each variant is an estimator built from its config node (``_target_``) with
``run(MeasurementSeries) -> TrackEstimate``; every variant gets the same series.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator

import numpy as np
import polars as pl

from filters.base import MeasurementSeries
from pipeline.contract import RecordingInputs, Study
from pipeline.data import Detections
from pipeline.evaluation.faults import FaultChecks


def measurement_series(det: Detections, slot: int = 0, sensor_position=None,
                       state_names: tuple[str, ...] | None = None) -> MeasurementSeries:
    """The filters' view of one detection slot (single-target, single-sensor studies).

    ``sensor_position`` is the static sensor's position (e.g. ``Radar3D.position``) for sensors
    that measure relative to themselves.
    """
    cov = det.noise_covariance[:, :, slot]
    constant = np.allclose(cov, cov[:1, :1])
    position = None if sensor_position is None else np.asarray(sensor_position, dtype=float)
    return MeasurementSeries(det.time, det.z[:, :, slot], cov[0, 0] if constant else cov,
                             det.detected[:, :, slot], det.sensor, position, state_names)


class SingleTargetStudy(Study):
    """The default study (studies 001 and 000): one target, one stream of scans, TrackEstimates.

    Every experiment runs through a ``pipeline.contract.Study``; the bias, sonar and sonobuoy
    studies name theirs with a ``study`` node, the others get this one. ``model_names`` /
    ``group_names`` label the IMMs' modes in the recording (a filter with a ``mode_names``
    attribute is labelled by its own); ``bound`` (the config's ``bound`` node)
    adds the PCRLB metrics ``position_bound`` and ``position_rmse_over_bound``.
    """

    def __init__(self, model_names: list[str] | None = None, group_names: list[str] | None = None,
                 bound=None) -> None:
        self.model_names = model_names
        self.group_names = group_names
        self.bound = bound

    def track_input(self, truth, detections: Detections, sensor, seed: int) -> MeasurementSeries:
        return measurement_series(detections, sensor_position=getattr(sensor, "position", None),
                                  state_names=tuple(truth.state_names))

    def estimate_to_frame(self, estimate, truth):
        from pipeline.storage import schemas
        return schemas.estimate_to_frame(estimate, truth.state_names)

    def fault_flags(self, estimate, truth, checks: FaultChecks) -> np.ndarray:
        """pipeline.evaluation.faults masks, with the NEES and scale tests against target 0's truth."""
        from pipeline.evaluation.faults import fault_flags, truth_scale
        return fault_flags(estimate.state, estimate.covariance, checks, estimate.state - truth.state[:, :, 0, :],
                           estimate.extras.get("weights_underflow"), truth_scale(truth.state[:, :, 0, :]))

    def per_step_metrics(self, truth, estimate, sensor) -> dict[str, np.ndarray]:
        from pipeline.evaluation.bounds import bound_metrics
        from pipeline.evaluation.evaluate import per_step_metrics
        out = per_step_metrics(truth, estimate)
        return out | bound_metrics(self.bound, truth, sensor, out["position_rmse"])

    def record(self, path, inputs: RecordingInputs) -> None:
        from pipeline.views.single_target import write_recording
        # a sensor with a position (e.g. the 3-D radar: polar detections relative to it) tells the
        # recording where it sits
        where = getattr(inputs.sensor, "position", None)
        located = {} if where is None else {"sensor_position": [float(v) for v in where]}
        # a filter that names its own modes (filters.turn.CVCTIMM: CV, CT) is labelled by them; the
        # study's model set labels the IMMs built on it
        names = {key: getattr(inputs.estimators.get(key), "mode_names", None) or self.model_names
                 for key in inputs.estimates}
        write_recording(path, model_names=names, group_names=self.group_names, **inputs.common(), **located)


# ---- the track stage's compute and codec (part of its cache key: pipeline.storage.fingerprint) ------------
def filter_chunks(estimator: Any, track_input: Any, chunk_runs: int) -> Iterator[tuple[int, Any]]:
    """(first run, the estimate of the next ``chunk_runs`` runs), chunk after chunk, so that only one
    chunk's estimate is in memory at a time (the track stage streams each to its table). Each chunk's
    ``compute_seconds`` is the running total: the last one's is the whole stage's."""
    runs, total = _runs_of(track_input), 0.0
    for first in range(0, runs, chunk_runs):
        part = estimator.run(track_input.select(range(first, min(first + chunk_runs, runs))))
        total += float(part.compute_seconds)
        yield first, dataclasses.replace(part, compute_seconds=total)


def truth_runs(truth: Any, first: int, stop: int) -> Any:
    """The truth of runs first..stop-1 (what a chunk's estimate is checked against)."""
    return dataclasses.replace(truth, state=truth.state[first:stop],
                               labels={name: values[first:stop] for name, values in truth.labels.items()})


def _runs_of(track_input: Any) -> int:
    runs = getattr(track_input, "runs", None)
    return int(runs) if runs is not None else int(track_input.z.shape[0])


def with_fault_flags(study: Study, estimate: Any, truth: Any, checks: FaultChecks) -> tuple[pl.DataFrame, dict]:
    """The study's estimate table plus ``fault``: the bit mask of pipeline.evaluation.faults per run x step
    (each row of a run and step gets it, e.g. every target's row)."""
    df, meta = study.estimate_to_frame(estimate, truth)
    flags = study.fault_flags(estimate, truth, checks)
    run = df["run"].to_numpy()
    step = df["step"].to_numpy()
    return df.with_columns(pl.Series("fault", flags[run, step], dtype=pl.UInt8)), meta


def flags_from_table(table: pl.DataFrame, runs: int, steps: int) -> np.ndarray:
    """(R, K) fault bit masks back from an estimate table (0 where the table has no fault column)."""
    flags = np.zeros((runs, steps), dtype=np.uint8)
    if "fault" in table.columns:
        np.bitwise_or.at(flags, (table["run"].to_numpy(), table["step"].to_numpy()), table["fault"].to_numpy())
    return flags
