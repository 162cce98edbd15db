"""filters.kalman_kernel: the KalmanTracker's compiled scan loop against its numpy scans (the
reference) for every motion model and both Cartesian measurement kinds, with missed scans;
read-only measurements running the signature warm_up compiled. Batch independence, for both
engines: tests/test_tracker_batch.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from filters import kalman_kernel
from filters.tracker import KalmanTracker
from tests.test_turn import radar_series
from tests.test_turn_kernel import turning_positions


def series(kind: str):
    if kind == "range_azimuth_elevation":
        return radar_series(np.random.default_rng(4), R=10, K=80)          # 10 % missed
    return turning_positions(np.random.default_rng(2), R=6, K=100)          # 2-D, turns, 10 % missed


@pytest.mark.parametrize("kind", ["range_azimuth_elevation", "position_xy"])
@pytest.mark.parametrize("motion", ["cv", "ca", "singer"])
def test_the_compiled_loop_is_the_numpy_scans(motion, kind):
    m = series(kind)
    ours = KalmanTracker(motion=motion, engine="numba").run(m)
    theirs = KalmanTracker(motion=motion, engine="numpy").run(m)
    for name, a, b in (("state", ours.state, theirs.state), ("covariance", ours.covariance, theirs.covariance),
                       *((key, ours.extras[key], theirs.extras[key]) for key in theirs.extras)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        scale = max(float(np.nanmax(np.abs(b))), 1.0)
        # measured: <= 3e-16 (state), 3e-15 (covariance), 3e-13 (NIS) of the largest entry; the
        # Cholesky inverse of S against LAPACK's LU and index-order sums are the only differences
        assert np.nanmax(np.abs(a - b)) <= 1e-11 * scale, (name, np.nanmax(np.abs(a - b)) / scale)


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
