"""Track: what the filters see of the detections.

Each variant is an estimator built from its config node (``_target_``) with
``run(MeasurementSeries) -> TrackEstimate``; every variant gets the same series.
"""

from __future__ import annotations

import numpy as np

from filters.base import MeasurementSeries
from pipeline.data import Detections


def measurement_series(det: Detections, slot: int = 0, sensor_position=None) -> MeasurementSeries:
    """The filters' view of one detection slot (single-target, single-sensor studies).

    ``sensor_position`` is the static sensor's position (e.g. ``Radar3D.position``) for sensors
    that measure relative to themselves.
    """
    cov = det.noise_covariance[:, :, slot]
    constant = np.allclose(cov, cov[:1, :1])
    position = None if sensor_position is None else np.asarray(sensor_position, dtype=float)
    return MeasurementSeries(det.time, det.z[:, :, slot], cov[0, 0] if constant else cov,
                             det.detected[:, :, slot], det.sensor, position)


class SingleTargetStudy:
    """The default stage adapter (studies 001 and 000): one target, one stream of scans.

    Every experiment runs through an adapter with the same methods (``check``, ``track_input``,
    ``estimate_table`` / ``estimate_to_frame``, ``per_step_metrics``, ``metric_units``,
    ``record``); the bias, sonar and sonobuoy studies name theirs with a ``study`` node, the
    others get this one. ``model_names`` / ``group_names`` label the IMMs' modes in the recording;
    ``bound`` (the config's ``bound`` node, pipeline.stages.bounds) adds the PCRLB metrics
    ``position_bound`` and ``position_rmse_over_bound``.
    """

    estimate_table = "estimates"

    def __init__(self, model_names: list[str] | None = None, group_names: list[str] | None = None,
                 bound=None) -> None:
        self.model_names = model_names
        self.group_names = group_names
        self.bound = bound

    def check(self, scenario, sensor, estimators: dict) -> None:
        """Nothing to cross-check beyond config.validate."""

    @staticmethod
    def track_input(truth, detections: Detections, sensor, seed: int) -> MeasurementSeries:
        return measurement_series(detections, sensor_position=getattr(sensor, "position", None))

    @staticmethod
    def estimate_to_frame(estimate, truth):
        from pipeline import schemas
        return schemas.estimate_to_frame(estimate, truth.state_names)

    @staticmethod
    def fault_flags(estimate, truth, checks) -> np.ndarray:
        """pipeline.stages.faults masks, with the NEES test against target 0's truth."""
        from pipeline.stages.faults import fault_flags
        return fault_flags(estimate.state, estimate.covariance, checks, estimate.state - truth.state[:, :, 0, :],
                           estimate.extras.get("weights_underflow"))

    def per_step_metrics(self, truth, estimate, sensor) -> dict[str, np.ndarray]:
        from pipeline.stages.bounds import bound_metrics
        from pipeline.stages.evaluate import per_step_metrics
        out = per_step_metrics(truth, estimate)
        return out | bound_metrics(self.bound, truth, sensor, out["position_rmse"])

    @staticmethod
    def metric_units(names) -> dict[str, str]:
        from pipeline.stages.bounds import UNITS
        return {n: UNITS[n] for n in names if n in UNITS}      # evaluate.UNITS knows the generic names

    def record(self, path, context: dict | None = None, **kwargs) -> None:
        from pipeline.recording import write_recording
        # a sensor with a position (e.g. the 3-D radar: polar detections relative to it) tells the
        # recording where it sits
        where = getattr(kwargs.pop("sensor"), "position", None)
        located = {} if where is None else {"sensor_position": [float(v) for v in where]}
        write_recording(path, model_names=self.model_names, group_names=self.group_names, **kwargs, **located)
