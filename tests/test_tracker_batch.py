"""KalmanTracker gives each run the same bits in any batch (mc.chunk_runs, launchers): a 9-state 3-D
Singer filter on study 000's radar used to differ, since a 2-D x @ F' over the runs is one BLAS call
whose rounding depends on the number of rows (found by the ADS-B study's chunking test)."""

from __future__ import annotations

import numpy as np
import pytest

from filters.tracker import KalmanTracker
from tests.helpers.config import composed_config


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.parametrize("motion", ["singer", "cv"])
def test_a_run_filtered_alone_equals_the_same_run_in_a_batch(motion, engine):
    from pipeline.run.runner import prepare
    prepared = prepare(composed_config("experiment=mie_los", "scenario.duration=40"))
    truth = prepared.scenario.generate(7, 3)
    view = prepared.study.track_input(truth, prepared.sensor.measure(truth, 3), prepared.sensor, 3)
    tracker = KalmanTracker(motion=motion, engine=engine)
    whole = tracker.run(view)
    for r in range(7):
        alone = tracker.run(view.select([r]))
        assert np.array_equal(whole.state[r], alone.state[0], equal_nan=True), r
        assert np.array_equal(whole.covariance[r], alone.covariance[0], equal_nan=True), r
