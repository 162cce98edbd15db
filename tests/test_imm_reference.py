"""Our batched FSIMM against the one-run-at-a-time reference loop (benchmarks/reference_imm.py),
and FilterPy's IMMEstimator against the same loop from a floored start (FilterPy 2.0 cannot start
from mu_0 = e_m1: its mixing divides by a zero predicted probability; see benchmarks/filterpy_imm.py).
3 runs x 40 steps of an S1-like profile."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf  # noqa: E402
from hydra.utils import instantiate  # noqa: E402

from benchmarks.reference_imm import reference_fsimm  # noqa: E402
from filters.base import MeasurementSeries  # noqa: E402
from filters.imm import FSIMM  # noqa: E402
from pipeline.studies.ao_vsimm.scenario import PiecewiseAccelerationScenario  # noqa: E402
from pipeline.studies.ao_vsimm.sensor import PositionSensor  # noqa: E402

RUNS, SEED = 3, 7
RTOL = 1e-8


@pytest.fixture(scope="module")
def setup():
    models = instantiate(OmegaConf.load(ROOT / "conf/models/acceleration13.yaml"))
    scenario = PiecewiseAccelerationScenario(initial_state=[20000, 340, 20000, 340],
                                             segments=[[1, 10, 0, 0], [11, 25, 18, 3], [26, 40, -20, 5]], steps=40)
    truth = scenario.generate(RUNS, SEED)
    det = PositionSensor(20.0).measure(truth, SEED)
    meas = MeasurementSeries(det.time, det.z[:, :, 0], 400.0 * np.eye(2), det.detected[:, :, 0], det.sensor)
    return models, meas


def _reference(models, meas, initial_probabilities=None):
    out = [reference_fsimm(models, meas.z[r], meas.noise_covariance, 1.0, initial_probabilities)
           for r in range(meas.runs)]
    return np.stack([s for s, _ in out]), np.stack([a for _, a in out])


def _assert_close(actual, expected, what):
    assert np.isnan(actual[:, 0]).all() and np.isnan(expected[:, 0]).all(), f"{what}: k = 0 has no estimate"
    a, e = actual[:, 1:], expected[:, 1:]
    assert np.isfinite(a).all() and np.isfinite(e).all(), f"{what}: non-finite estimates"
    worst = np.abs(a - e).max()
    scale = np.abs(e).max()
    assert worst <= RTOL * scale, f"{what}: max |difference| {worst:.3e} > {RTOL:g} x {scale:.3e}"


def test_batched_fsimm_equals_reference_loop(setup):
    models, meas = setup
    estimate = FSIMM(models).run(meas)
    states, acceleration = _reference(models, meas)
    _assert_close(estimate.state, states, "states")
    _assert_close(estimate.extras["acceleration"], acceleration, "acceleration")
    # the zero-probability convention matters here: m6..m13 are unreachable from e_m1 at k = 2
    assert np.all(estimate.extras["mode_probabilities"][:, 2, 5:] == 0.0)


def test_filterpy_imm_equals_reference_loop_with_floored_start(setup):
    pytest.importorskip("filterpy")
    from benchmarks.filterpy_imm import filterpy_fsimm, floored_initial_probabilities

    models, meas = setup
    mu0 = floored_initial_probabilities(models)
    ref_states, ref_acc = _reference(models, meas, mu0)
    fp = [filterpy_fsimm(models, meas.z[r], meas.noise_covariance, 1.0, mu0) for r in range(meas.runs)]
    _assert_close(np.stack([s for s, _ in fp]), ref_states, "FilterPy states")
    _assert_close(np.stack([a for _, a in fp]), ref_acc, "FilterPy acceleration")
