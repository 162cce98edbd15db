"""filters.tracker.kernel: the KalmanTracker's compiled scan loop against its numpy scans (the
reference) for every motion model and both Cartesian measurement kinds, with missed scans;
read-only measurements running the signature warm_up compiled. Batch independence, for both
engines: tests/test_tracker_batch.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from filters.tracker import kernel as kalman_kernel
from filters.tracker import KalmanTracker
from tests.helpers.filter_inputs import radar_series
from tests.helpers.assertions import assert_same_to_rounding
from tests.helpers.filter_inputs import turning_positions


def series(kind: str):
    if kind == "range_azimuth_elevation":
        return radar_series(np.random.default_rng(4), R=10, K=80)          # 10 % missed
    return turning_positions(np.random.default_rng(2), R=6, K=100)          # 2-D, turns, 10 % missed


@pytest.mark.parametrize("kind", ["range_azimuth_elevation", "position_xy"])
@pytest.mark.parametrize("motion", ["cv", "ca", "singer"])
def test_the_compiled_loop_is_the_numpy_scans(motion, kind):
    m = series(kind)
    # measured: <= 3e-16 (state), 3e-15 (covariance), 3e-13 (NIS) of the largest entry
    assert_same_to_rounding(KalmanTracker(motion=motion, engine="numba").run(m),
                            KalmanTracker(motion=motion, engine="numpy").run(m))


def test_read_only_measurements_run_the_warmed_up_signature():
    kalman_kernel.warm_up()
    signatures = len(kalman_kernel.kalman_cartesian.signatures)
    m = series("position_xy")
    z, detected = m.z.copy(), m.detected.copy()
    z.flags.writeable = detected.flags.writeable = False
    KalmanTracker(motion="cv", engine="numba").run(replace(m, z=z, detected=detected))
    assert len(kalman_kernel.kalman_cartesian.signatures) == signatures


def test_an_unknown_engine_is_refused_with_the_choices():
    with pytest.raises(ValueError, match=r"^engine: 'gpu' must be one of \['numba', 'numpy'\]"):
        KalmanTracker(engine="gpu")


@pytest.mark.parametrize("filter_class", ["kf", "imm"])
def test_an_innovation_covariance_that_is_not_positive_definite_spoils_only_its_own_run(filter_class):
    """A run whose S is not positive definite (a negative noise variance reported at one scan) gets NaN
    from that scan on, which the fault flags report as nonfinite; the other runs are the runs
    filtered without it. (numpy's Cholesky, the IMM's in 3-D, raised for the whole batch; the KF's
    LU solve and the 2 x 2 closed forms went on with numbers.)"""
    from filters.turn import CVCTIMM
    m = series("position_xy")
    noise = np.broadcast_to(np.asarray(m.noise_covariance, float), m.z.shape + (2,)).copy()
    k = 10 + int(np.argmax(m.detected[0, 10:]))     # a detected scan of run 0
    noise[0, k] = -1e9 * np.eye(2)                   # negative definite: its determinant is > 0
    bad = replace(m, noise_covariance=noise)
    make = (lambda: KalmanTracker(motion="cv")) if filter_class == "kf" else (lambda: CVCTIMM())
    estimate = make().run(bad)
    assert np.isfinite(estimate.state[0, 1:k, 0]).all() and np.isnan(estimate.state[0, k:]).all()
    rest = make().run(m.select(list(range(1, m.runs))))
    np.testing.assert_array_equal(estimate.state[1:], rest.state)
