"""filters.turn: the CV/CT IMM (Bar-Shalom, Li & Kirubarajan 2001, 11.7) against hand-worked cases
and invariants: the CT model's limits and exact circles, mode selection and turn-rate convergence on
noise-free turns, batch independence, the CV-only reduction to the KalmanTracker, and its NIS."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from filters.tracker import KalmanTracker
from filters.turn import CVCTIMM, SERIES_BELOW, coordinated_turn, turn_coefficients
from pipeline.evaluation.evaluate import nis_metrics
from tests.helpers.filter_inputs import circle, positions_series, radar_series

# ---- (a) the CT model ------------------------------------------------------------------------------
def test_at_zero_turn_rate_the_ct_transition_is_cv_and_its_jacobian_takes_the_books_limit():
    T = 4.0
    x = np.array([100.0, 200.0, -50.0, -30.0, 9000.0, 5.0, 0.0])
    f, F = coordinated_turn(x, T)
    cv = np.kron(np.eye(3), [[1.0, T], [0.0, 1.0]])
    np.testing.assert_array_equal(f[:6], cv @ x[:6])
    np.testing.assert_array_equal(F[:6, :6], cv)
    vx, vy = x[1], x[3]
    # 11.7.2: d(x, vx, y, vy)'/d omega -> (-T^2/2 vy, -T vy, T^2/2 vx, T vx), nothing else on omega
    np.testing.assert_array_equal(F[:, -1], [-T * T / 2 * vy, -T * vy, T * T / 2 * vx, T * vx, 0.0, 0.0, 1.0])
    # just off zero (the Taylor branch) f moves by the omega column to first order, F barely
    f_near, F_near = coordinated_turn(x + np.eye(7)[-1] * 1e-9, T)
    np.testing.assert_allclose(f_near - f, F[:, -1] * 1e-9, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(F_near, F, rtol=1e-7, atol=1e-8)


def taylor(u: float, T: float) -> tuple[float, float, float, float]:
    """sin(u)/u, (1 - cos u)/u and their u-derivatives by 15 terms of their series, scaled by T, T, T^2, T^2."""
    a = b = da = db = 0.0
    for k in range(15):
        sign = (-1) ** k
        a += sign * u ** (2 * k) / math.factorial(2 * k + 1)
        b += sign * u ** (2 * k + 1) / math.factorial(2 * k + 2)
        da += sign * 2 * k * u ** (2 * k - 1) / math.factorial(2 * k + 1) if k else 0.0
        db += sign * (2 * k + 1) * u ** (2 * k) / math.factorial(2 * k + 2)
    return T * a, T * b, T * T * da, T * T * db


@pytest.mark.parametrize("u", [1e-8, 1e-4, 0.5 * SERIES_BELOW, 0.999 * SERIES_BELOW, SERIES_BELOW, 0.02, 0.3, -0.004,
                               -0.05])
def test_the_turn_coefficients_are_accurate_on_both_sides_of_the_series_switch(u):
    T = 3.0
    got = [float(v) for v in turn_coefficients(np.array(u / T), T)]
    np.testing.assert_allclose(got, taylor(u, T), rtol=1e-10, atol=0.0)


def test_the_jacobian_is_the_derivative_of_the_transition():
    T = 5.0
    x = np.array([1e3, 150.0, -2e3, 80.0, 5e3, -3.0, 0.04])
    _, F = coordinated_turn(x, T)
    h = np.array([1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 1e-4, 1e-7])
    numeric = np.stack([(coordinated_turn(x + h[j] * np.eye(7)[j], T)[0]
                         - coordinated_turn(x - h[j] * np.eye(7)[j], T)[0]) / (2 * h[j]) for j in range(7)], -1)
    np.testing.assert_allclose(F, numeric, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("omega", [0.05, -0.02])
def test_a_known_turn_rate_moves_a_point_along_the_exact_circle(omega):
    T, steps = 1.5, 100
    p0, v0 = np.array([1e3, -2e3]), np.array([180.0, 60.0])
    x = np.array([p0[0], v0[0], p0[1], v0[1], 7e3, -4.0, omega])
    for _ in range(steps):
        x, _ = coordinated_turn(x, T)
    p, v = circle(p0, v0, omega, np.array(steps * T))
    np.testing.assert_allclose(x[[0, 2]], p, atol=1e-8)
    np.testing.assert_allclose(x[[1, 3]], v, atol=1e-10)
    np.testing.assert_allclose(x[4:], [7e3 - 4.0 * steps * T, -4.0, omega], atol=1e-8)


# ---- (b) mode selection and the turn rate -----------------------------------------------------------
@pytest.mark.parametrize("omega, period, least, tolerance", [(0.05, "2 s", 0.999, 1e-5), (-0.03, "1-5 s", 0.98, 1e-3)])
def test_on_a_noise_free_turn_the_ct_mode_wins_and_the_turn_rate_converges(omega, period, least, tolerance):
    """A 3 deg/s (and a -1.7 deg/s) turn at 227 m/s, measured exactly, assumed sigma 1 m. Scans of
    1 s tell the modes apart less (CV misses by v w T^2/2 = 3 m) than scans of 2 s (22 m); the
    combined turn rate sum mu_j w_j is short of the CT mode's by mu_CV w (the CV mode's is 0)."""
    rng = np.random.default_rng(5)
    K = 60
    t = np.arange(K) * 2.0 if period == "2 s" else np.concatenate([[0.0], np.cumsum(rng.uniform(1, 5, K - 1))])
    p, _ = circle(np.array([2e3, 5e3]), np.array([-150.0, 170.0]), omega, t)
    est = CVCTIMM().run(positions_series(p[None], t, sigma=1.0))
    mu_ct = est.extras["mode_probabilities"][0, :, 1]
    assert (mu_ct[-20:] > least).all(), mu_ct[-20:]
    np.testing.assert_allclose(est.extras["turn_rate"][0, -10:], omega, atol=tolerance)


def test_on_a_straight_line_the_cv_mode_dominates_and_the_turn_rate_is_zero():
    t = np.arange(60) * 3.0
    p = np.array([1e3, -4e3]) + np.array([120.0, 210.0]) * t[:, None]
    est = CVCTIMM().run(positions_series(p[None], t, sigma=20.0))
    assert (est.extras["mode_probabilities"][0, 10:, 0] > 0.95).all()
    np.testing.assert_allclose(est.extras["turn_rate"][0, 10:], 0.0, atol=1e-6)


# ---- (c) batch independence ------------------------------------------------------------------------
@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_a_run_in_a_batch_gets_the_same_estimate_as_alone_bit_for_bit(engine):
    m = radar_series(np.random.default_rng(7))
    imm = CVCTIMM(engine=engine)
    batch = imm.run(m)
    for r in range(m.runs):
        alone = imm.run(m.select([r]))
        np.testing.assert_array_equal(batch.state[r:r + 1], alone.state)
        np.testing.assert_array_equal(batch.covariance[r:r + 1], alone.covariance)
        for name, value in batch.extras.items():
            np.testing.assert_array_equal(value[r:r + 1], alone.extras[name], err_msg=name)


# ---- (d) the CV mode alone is the KalmanTracker ----------------------------------------------------
@pytest.mark.parametrize("kind", ["range_azimuth_elevation", "position_xy"])
def test_with_the_turn_mode_switched_off_it_is_the_cv_kalman_tracker(kind):
    rng = np.random.default_rng(3)
    if kind == "position_xy":
        t = np.arange(50) * 2.0
        p = rng.uniform(-5e3, 5e3, (4, 1, 2)) + rng.uniform(-200, 200, (4, 1, 2)) * t[None, :, None]
        detected = rng.random((4, 50)) > 0.1
        detected[:, :2] = True
        m = replace(positions_series(p + 20.0 * rng.standard_normal(p.shape), t, 20.0, detected),
                    state_names=("x", "vx", "y", "vy"))
    else:
        m = radar_series(rng)
    q = 7.0
    imm = CVCTIMM(cv_acceleration_density=q, vertical_acceleration_density=q, sojourn_times=(math.inf, math.inf),
                  initial_mode_probabilities=(1.0, 0.0))
    ours, kf = imm.run(m), KalmanTracker(motion="cv", acceleration_density=q).run(m)
    assert ours.state.shape == kf.state.shape
    np.testing.assert_allclose(ours.state, kf.state, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ours.covariance, kf.covariance, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ours.extras["nis"], kf.extras["nis"], rtol=1e-9)
    np.testing.assert_array_equal(ours.extras["nis_dof"], kf.extras["nis_dof"])
    np.testing.assert_array_equal(ours.extras["mode_probabilities"][:, 1:, 1], 0.0)
    np.testing.assert_array_equal(ours.extras["turn_rate"][:, 1:], 0.0)


def test_the_estimate_is_in_the_studys_layout_with_the_accelerations_nan():
    est = CVCTIMM().run(radar_series(np.random.default_rng(1), R=2, K=10))
    assert est.state.shape == (2, 10, 9) and est.covariance.shape == (2, 10, 9, 9)
    assert np.isnan(est.state[:, 0]).all() and np.isfinite(est.state[:, 1:, :6]).all()
    assert np.isnan(est.state[..., 6:]).all() and np.isnan(est.covariance[:, 1:, 6, :]).all()
    mu = est.extras["mode_probabilities"]
    assert mu.shape == (2, 10, 2) and est.extras["turn_rate"].shape == (2, 10)
    np.testing.assert_allclose(mu[:, 1:].sum(-1), 1.0)
    assert np.isnan(est.extras["nis"][:, :2]).all() and np.isfinite(est.compute_seconds)


# ---- (e) parameters --------------------------------------------------------------------------------
@pytest.mark.parametrize("key, value", [
    ("cv_acceleration_density", 0.0), ("ct_acceleration_density", -1.0), ("turn_rate_density", math.nan),
    ("vertical_acceleration_density", math.inf), ("turn_rate_std", "0.05"), ("sojourn_times", [60.0]),
    ("sojourn_times", [60.0, 0.0]), ("initial_mode_probabilities", [0.5, 0.6]),
    ("initial_mode_probabilities", [1.2, -0.2]),
])
def test_a_bad_parameter_is_refused_naming_its_key(key, value):
    with pytest.raises(ValueError, match=f"^{key}: "):
        CVCTIMM(**{key: value})


def test_measurements_it_cannot_filter_are_refused():
    t = np.array([0.0, 1.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="measurements.time"):
        CVCTIMM().run(positions_series(np.zeros((1, 4, 2)), t, 1.0))


# ---- (f) NIS ---------------------------------------------------------------------------------------
def test_on_a_cv_target_the_nis_sits_in_its_chi_square_band():
    """Targets drawn from the CV model the filter assumes (white acceleration of PSD q, exactly
    discretised). With a mode prior that fits them (straight legs of 10 min) the run-averaged NIS of
    the combined prediction lies in its 95 % band at most scans after the start. With the air-traffic
    default (2 min legs) the CT mode keeps ~7 % probability and its wider prediction (the turn
    rate's uncertainty) widens the mixture's: the NIS sits a little low (1.88 against the
    KalmanTracker's 1.99), still inside the band on average."""
    rng = np.random.default_rng(11)
    R, K, T, q, sigma = 300, 60, 2.0, 4.0, 30.0
    F = np.array([[1.0, T], [0.0, 1.0]])
    L = np.linalg.cholesky(q * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]]))
    state = np.stack([rng.uniform(-1e4, 1e4, (R, 2)), rng.uniform(-200, 200, (R, 2))], -1)   # (R, axis, p/v)
    z = np.empty((R, K, 2))
    for k in range(K):
        if k:
            state = state @ F.T + rng.standard_normal((R, 2, 2)) @ L.T
        z[:, k] = state[..., 0] + sigma * rng.standard_normal((R, 2))
    later = slice(10, None)
    for sojourn, least in (((600.0, 30.0), 0.85), ((120.0, 30.0), 0.0)):
        imm = CVCTIMM(cv_acceleration_density=q, sojourn_times=sojourn)
        est = imm.run(positions_series(z, np.arange(K) * T, sigma))
        band = {name: value[later] for name, value in nis_metrics(est.extras).items()}
        inside = (band["nis"] >= band["nis_lower"]) & (band["nis"] <= band["nis_upper"])
        assert inside.mean() >= least, (sojourn, inside.mean())
        assert band["nis_lower"][-1] <= band["nis"].mean() <= band["nis_upper"][-1], (sojourn, band["nis"].mean())


# ---- in the pipeline -------------------------------------------------------------------------------
@pytest.mark.parametrize("experiment", ["mie_los", "ao_vsimm_s1"])
def test_it_runs_in_the_studies_of_both_its_kinds_with_its_modes_labelled_in_the_recording(tmp_path, experiment):
    """Study 000's radar (3-D) and study 001's positions (2-D): both run and record. The 2-D
    recording draws mode probabilities, labelled by the study's 13 models for its IMMs and CV, CT
    for this filter (the 3-D recording draws none)."""
    import polars as pl

    from pipeline.run.runner import RunContext, run_experiment
    from tests.helpers.rrd_reading import entity_index, read_chunks
    from tests.helpers.config import composed_config

    overrides = [f"experiment={experiment}", "mc.runs=2", "+filter@filters.ct=imm_cv_ct"]
    ctx = RunContext(tmp_path / "runs" / "ct", tmp_path, overrides)
    out = run_experiment(composed_config(f"paths.artifacts={tmp_path}", *overrides), ctx)
    rmse = out.summary.filter((pl.col("series") == "position_rmse") & (pl.col("variant_key") == "ct"))
    assert rmse.height > 0 and np.isfinite(rmse["value"].to_numpy()).all()
    entities = set(entity_index(read_chunks(ctx.run_dir / "recording.rrd")))
    if experiment == "ao_vsimm_s1":
        assert {"/variants/ct/run0/mode_probability/CV", "/variants/ct/run0/mode_probability/CT",
                "/variants/fsimm/run0/mode_probability/m13"} <= entities
