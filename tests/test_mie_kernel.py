"""The compiled loops of study 000's filters (filters/input_estimation/kernel.py, ``engine="numba"``: A and A-full,
B and C) against the numpy scans (``engine="numpy"``, the reference): the same states, covariances,
input levels, test statistics and NIS to rounding, and the same detections (per axis for C) and
onsets, for each test (A's per-axis sum, A-full's quadratic form, B's pooled, C's per-axis) and each
switch of the MIE, on study 000's scenario and an ADS-B flight; and a run's numbers independent of
its batch, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from filters.input_estimation import LOSMIE, InertialMIE
from pipeline.run.runner import prepare
from tests.helpers.config import composed


def _inputs(experiment: str, runs: int, *overrides: str):
    prepared = prepare(composed(experiment, f"mc.runs={runs}", "paths.artifacts=/nonexistent-artifacts", *overrides))
    truth = prepared.scenario.generate(runs, 1)
    detections = prepared.sensor.measure(truth, 2)
    return prepared.study.track_input(truth, detections, prepared.sensor, 3)


@pytest.fixture(scope="module")
def study000():
    return _inputs("mie_los", 12)


def _scaled_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| over each trailing column's RMS; NaN where both are NaN, which must coincide."""
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    columns = a.reshape(a.shape[0] * a.shape[1], -1)
    scale = np.sqrt(np.nanmean(columns**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    return float(np.nanmax(np.abs(columns - b.reshape(columns.shape)) / scale))


def _assert_engines_agree(make, series) -> None:
    reference, compiled = make("numpy").run(series), make("numba").run(series)
    assert reference.extras["maneuver_detected"].sum() > 0                     # the MIE acted
    assert set(reference.extras) == set(compiled.extras)
    for name in ("maneuver_detected", "maneuver_detected_axis", "onset_step"):
        if name in reference.extras:
            np.testing.assert_array_equal(reference.extras[name], compiled.extras[name], err_msg=name)
    for name, a, b in (("state", reference.state, compiled.state), ("covariance", reference.covariance, compiled.covariance),
                       *((k, reference.extras[k], compiled.extras[k]) for k in ("input_level", "test_statistic", "nis"))):
        assert _scaled_difference(a, b) < 1e-9, name
    np.testing.assert_array_equal(reference.extras["nis_dof"], compiled.extras["nis_dof"])


@pytest.mark.parametrize("kwargs", [
    {}, {"test": "full"}, {"level_correlation": False}, {"level_uncertainty": False}, {"compensate": False},
    {"rearm_after": 3, "test": "full"}, {"window": 3, "min_samples": 2},
], ids=lambda k: ",".join(f"{a}={b}" for a, b in k.items()) or "A")
def test_the_compiled_loop_equals_the_numpy_scans_on_study_000(study000, kwargs):
    _assert_engines_agree(lambda engine: InertialMIE(engine=engine, **kwargs), study000)


@pytest.mark.parametrize("kwargs", [
    {}, {"test": "per_axis"}, {"compensate": False}, {"level_correlation": False},
    {"level_uncertainty": False, "test": "per_axis"}, {"rearm_after": 4, "test": "per_axis"},
    {"window": 3, "min_samples": 2},
], ids=lambda k: ",".join(f"{a}={b}" for a, b in k.items()) or "B")
def test_the_los_filters_compiled_loop_equals_the_numpy_scans_on_study_000(study000, kwargs):
    _assert_engines_agree(lambda engine: LOSMIE(engine=engine, **kwargs), study000)


@pytest.mark.parametrize("make", [InertialMIE, LOSMIE, lambda **kw: LOSMIE(test="per_axis", **kw)], ids=["A", "B", "C"])
def test_the_compiled_loops_equal_the_numpy_scans_on_a_recorded_flight(make):
    series = _inputs("adsb_jet", 4, "++scenario.duration=600")      # C detects once in these 4 runs
    _assert_engines_agree(lambda engine: make(engine=engine), series)


def test_the_gls_variant_runs_the_numpy_scans():
    """pseudo_residual_covariance: full (generalised least squares) has no compiled loop: the numpy
    scans run whatever the engine says."""
    filter_ = LOSMIE(pseudo_residual_covariance="full")
    assert filter_.engine == "numba"
    import filters.input_estimation.kernel as kernel

    calls = []
    original = kernel.los_mie
    kernel.los_mie = lambda *a: calls.append(a)
    try:
        estimate = filter_.run(_inputs("mie_los", 2))
    finally:
        kernel.los_mie = original
    assert not calls and np.isfinite(estimate.state[:, 2:]).all()


@pytest.mark.parametrize("make", [InertialMIE, lambda: LOSMIE(test="per_axis")], ids=["A", "C"])
def test_a_run_alone_equals_it_in_the_batch_bit_for_bit(study000, make):
    import dataclasses

    batched = make().run(study000)
    for run in (0, 7):
        alone = make().run(dataclasses.replace(study000, z=study000.z[run:run + 1],
                                               detected=study000.detected[run:run + 1]))
        np.testing.assert_array_equal(batched.state[run], alone.state[0])
        np.testing.assert_array_equal(batched.covariance[run], alone.covariance[0])
        for name in batched.extras:
            np.testing.assert_array_equal(batched.extras[name][run], alone.extras[name][0])


@pytest.mark.parametrize("filter_class", [InertialMIE, LOSMIE])
def test_an_unknown_engine_is_refused_naming_the_key(filter_class):
    with pytest.raises(ValueError, match=r"engine: 'gpu' must be one of \['numba', 'numpy'\]"):
        filter_class(engine="gpu")
