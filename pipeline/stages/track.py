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
