"""Study 003 filter math: the relative-motion model, the modifiable g-rows (bearing, and range by
the seed's theorem 1), the MGEKF / EKF / converted-KF updates, the hand-over, convergence."""

from __future__ import annotations

import numpy as np
import pytest

from filters.mgekf import (
    KFPlusMGEKF, OnlyMGEKF, PlainEKF, SonarReports, bearing_g_row, bearing_range, converted_update,
    jacobian_rows, nonlinear_update, pad_acceleration, range_g_row, relative_motion_model, wrap,
)
from filters.models import singer_process_noise, singer_transition
from pipeline.studies.sonar.scenario import SonarEncounter
from tests.helpers.filter_inputs import sonar_reports


def _random_pairs(n=500, seed=0):
    """True and estimated relative positions [m], the estimate within ~40 deg and 30 % of the truth."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(500, 50_000, n)
    beta = rng.uniform(-np.pi, np.pi, n)
    r_hat = r * rng.uniform(0.7, 1.3, n)
    beta_hat = beta + rng.uniform(-0.7, 0.7, n)
    true = np.stack([r * np.sin(beta), r * np.cos(beta)], -1)
    estimate = np.stack([r_hat * np.sin(beta_hat), r_hat * np.cos(beta_hat)], -1)
    return true, estimate


def test_bearing_convention_is_from_north_clockwise():
    beta, r = bearing_range(np.array([[1000.0, 0.0], [0.0, 1000.0], [-1000.0, 0.0], [0.0, -1000.0]]))
    np.testing.assert_allclose(beta, [np.pi / 2, 0.0, -np.pi / 2, np.pi])
    np.testing.assert_allclose(r, 1000.0)


def test_modifiable_identity_for_bearing_and_range():
    """h(x) - h(x_hat) = g(z, x_hat) (x - x_hat) with the noise-free measurement z = h(x): exact for
    the range row (theorem 1) and the arctan-exact bearing row; the tan row is exact for tan(beta - beta_hat)."""
    true, estimate = _random_pairs()
    beta, r = bearing_range(true)
    beta_hat, r_hat = bearing_range(estimate)
    step = true - estimate
    g_exact = bearing_g_row(estimate, beta, form="exact")
    np.testing.assert_allclose(np.sum(g_exact * step, -1), wrap(beta - beta_hat), atol=1e-12)
    g_tan = bearing_g_row(estimate, beta, form="tan", clamp=1e-6)
    np.testing.assert_allclose(np.sum(g_tan * step, -1), np.tan(wrap(beta - beta_hat)), rtol=1e-9, atol=1e-12)
    g_range = range_g_row(estimate, beta)
    np.testing.assert_allclose(np.sum(g_range * step, -1), r - r_hat, rtol=1e-10, atol=1e-7)


def test_g_rows_reduce_to_the_ekf_jacobian_at_the_prediction():
    _, estimate = _random_pairs(50, seed=1)
    beta_hat, _ = bearing_range(estimate)
    d_beta, d_r = jacobian_rows(estimate)
    np.testing.assert_allclose(bearing_g_row(estimate, beta_hat), d_beta, rtol=1e-12)
    np.testing.assert_allclose(bearing_g_row(estimate, beta_hat, form="exact"), d_beta, rtol=1e-9)
    np.testing.assert_allclose(range_g_row(estimate, beta_hat), d_r, rtol=1e-12)


def test_jacobian_rows_match_finite_differences():
    _, estimate = _random_pairs(20, seed=2)
    d_beta, d_r = jacobian_rows(estimate)
    for axis in (0, 1):
        step = np.zeros(2)
        step[axis] = 1e-3
        b1, r1 = bearing_range(estimate + step)
        b0, r0 = bearing_range(estimate - step)
        np.testing.assert_allclose(wrap(b1 - b0) / 2e-3, d_beta[:, axis], rtol=1e-5)
        np.testing.assert_allclose((r1 - r0) / 2e-3, d_r[:, axis], rtol=1e-5)


def test_bearing_row_denominator_is_clamped_near_ninety_degrees():
    estimate = np.array([[0.0, 1000.0]])                       # due north, r_hat = 1000
    g = bearing_g_row(estimate, np.array([np.pi / 2 - 1e-9]), clamp=0.1)
    assert np.all(np.isfinite(g)) and np.abs(g).max() <= 1.0 / (0.1 * 1000.0) + 1e-12


def test_relative_motion_model_blocks():
    dt, tau, sigma = 1.0, 60.0, 0.01
    Phi, Gamma, Q = relative_motion_model(dt, tau, sigma)
    F, Qs = singer_transition(dt, tau), singer_process_noise(dt, tau, sigma)
    for axis in (0, 1):
        index = [axis, axis + 2, axis + 4]
        np.testing.assert_allclose(Phi[np.ix_(index, index)], F)
        np.testing.assert_allclose(Q[np.ix_(index, index)], Qs)
    np.testing.assert_allclose(Gamma, -np.vstack([0.5 * np.eye(2), np.eye(2), np.zeros((2, 2))]))


def test_truth_follows_the_model_exactly_for_a_straight_target():
    """The scenario's discrete own-ship input makes x(k+1) = Phi x(k) + Gamma u(k) exact (case 1)."""
    truth = SonarEncounter(duration=1200.0).generate(1, 0)
    x = truth.state[0, :, 0]
    u = truth.labels["ownship_acceleration"][0, :, 0]
    Phi, Gamma, _ = relative_motion_model(1.0, 60.0, 0.003)
    predicted = x[:-1] @ Phi.T + u[:-1] @ Gamma.T
    np.testing.assert_allclose(predicted, x[1:], atol=1e-6)


@pytest.mark.parametrize("tracker", [OnlyMGEKF(sigma_m=1e-4), PlainEKF(sigma_m=1e-4),
                                     KFPlusMGEKF(sigma_m=1e-4, handover_acceleration_variance="consistent")])
def test_noise_free_straight_target_converges_with_a_zig_zag_own_ship(tracker):
    """One exact range + bearing at t = 0, bearings only afterwards: the start's velocity error
    (the target's 7 m/s) grows the error to ~230 m, the own-ship's legs make it observable, and
    the estimate converges to the truth."""
    truth, reports = sonar_reports()
    est = tracker.run(reports)
    error = np.linalg.norm(est.state[..., :2] - truth.state[:, :, 0, :2], axis=-1)
    assert error[:, 49].min() > 100.0
    assert error[:, 1000:].max() < 1.0
    assert error[:, -1].max() < 0.1


def test_mgekf_update_equals_the_ekf_update_when_the_measurement_is_predicted_exactly():
    rng = np.random.default_rng(3)
    x = np.array([[3000.0, 8000.0, -4.0, -6.0, 0.0, 0.0], [-2000.0, 5000.0, 1.0, -3.0, 0.01, 0.0]])
    A = rng.standard_normal((2, 6, 6))
    P = A @ np.swapaxes(A, -1, -2) + np.diag([1e4, 1e4, 10, 10, 1e-4, 1e-4])
    beta, r = bearing_range(x[:, :2])
    z = np.stack([beta, r], -1)
    for active in (False, True):
        mg = nonlinear_update(x, P, z, active, 0.0175, 10.0, modified=True)
        ekf = nonlinear_update(x, P, z, active, 0.0175, 10.0, modified=False)
        np.testing.assert_allclose(mg[0], ekf[0], rtol=1e-12)
        np.testing.assert_allclose(mg[1], ekf[1], rtol=1e-9, atol=1e-9)


def test_passive_scalar_update_equals_the_general_form():
    """The bearing-only update (scalar algebra) equals the matrix Joseph form."""
    rng = np.random.default_rng(4)
    x = np.array([[3000.0, 8000.0, -4.0, -6.0, 0.0, 0.0]])
    A = rng.standard_normal((1, 6, 6))
    P = A @ np.swapaxes(A, -1, -2) + np.diag([1e4, 1e4, 10, 10, 1e-4, 1e-4])
    z = np.array([[bearing_range(x[:, :2])[0][0] + 0.02, np.nan]])
    x_new, P_new = nonlinear_update(x, P, z, False, 0.0175, 10.0)
    h = np.zeros((1, 6))
    h[0, :2] = jacobian_rows(x[:, :2])[0][0]
    g = np.zeros((1, 6))
    g[0, :2] = bearing_g_row(x[:, :2], z[:, 0])[0]
    S = h @ P[0] @ h.T + 0.0175**2
    K = P[0] @ h.T / S
    Ag = np.eye(6) - K @ g
    expected = Ag @ P[0] @ Ag.T + K @ K.T * 0.0175**2
    np.testing.assert_allclose(P_new[0], expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(x_new[0], x[0] + K[:, 0] * wrap(z[0, 0] - bearing_range(x[:, :2])[0][0]), rtol=1e-12)


def test_converted_update_uses_the_converted_position_and_covariance():
    x = np.array([[1000.0, 1000.0, 0.0, 0.0]])
    P = np.diag([1e8, 1e8, 1.0, 1.0])[None]                    # a broad prior: the update returns ~ the measurement
    z = np.array([[np.pi / 4, 2000.0]])
    x_new, P_new = converted_update(x, P, z, 0.01, 10.0)
    np.testing.assert_allclose(x_new[0, :2], 2000.0 * np.array([np.sin(np.pi / 4), np.cos(np.pi / 4)]), rtol=1e-5)
    J = np.array([[2000 * np.cos(np.pi / 4), np.sin(np.pi / 4)], [-2000 * np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    np.testing.assert_allclose(P_new[0, :2, :2], J @ np.diag([1e-4, 100.0]) @ J.T, rtol=1e-4)


def test_hand_over_pads_and_the_variance_is_checked():
    x, P = pad_acceleration(np.ones((3, 4)), np.broadcast_to(np.eye(4), (3, 4, 4)), 0.1)
    assert x.shape == (3, 6) and np.all(x[:, 4:] == 0)
    np.testing.assert_allclose(P[:, 4:, 4:], np.broadcast_to(0.1 * np.eye(2), (3, 2, 2)))
    assert not P[:, :4, 4:].any()
    assert KFPlusMGEKF(sigma_m=0.01, handover_acceleration_variance="consistent").handover_acceleration_variance == \
        pytest.approx(1e-4)
    for bad in (1.0, 5.0, 0.0, -1.0, "broad"):
        with pytest.raises(ValueError, match="handover_acceleration_variance"):
            KFPlusMGEKF(handover_acceleration_variance=bad)


def test_kf_architecture_has_no_acceleration_while_active():
    truth, reports = sonar_reports(duration=700.0, active=((0.0, 300.0), (500.0, 600.0)), bearing_std_deg=1.0,
                              range_std=10.0, filter_bearing_std=np.radians(1.0), filter_range_std=10.0)
    est = KFPlusMGEKF(sigma_m=0.01).run(reports)
    active = reports.active
    assert np.isnan(est.state[:, active, 4:]).all() and np.isfinite(est.state[:, ~active, 4:]).all()
    assert np.isfinite(est.state[..., :4]).all()
    np.testing.assert_array_equal(est.extras["active"][0], active.astype(np.int8))


def test_batched_runs_equal_single_runs():
    _, reports = sonar_reports(duration=600.0, active=((0.0, 200.0),), bearing_std_deg=1.0, range_std=10.0, runs=3,
                          filter_bearing_std=np.radians(1.0), filter_range_std=10.0)
    single = SonarReports(reports.time, reports.z[1:2], reports.active, reports.ownship_acceleration[1:2],
                          reports.ownship_velocity0[1:2], reports.bearing_std, reports.range_std)
    for tracker in (OnlyMGEKF(), KFPlusMGEKF()):
        batched, alone = tracker.run(reports), tracker.run(single)
        np.testing.assert_allclose(batched.state[1], alone.state[0], rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("kwargs, key", [({"tau": 0}, "tau"), ({"sigma_m": -1}, "sigma_m"),
                                         ({"bearing_row": "sin"}, "bearing_row"), ({"clamp": 1.5}, "clamp"),
                                         ({"initial_velocity_std": float("nan")}, "initial_velocity_std")])
def test_bad_parameters_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        OnlyMGEKF(**kwargs)


def test_reports_must_start_active():
    _, reports = sonar_reports(duration=20.0)
    with pytest.raises(ValueError, match="active"):
        SonarReports(reports.time, reports.z, np.zeros_like(reports.active), reports.ownship_acceleration,
                     reports.ownship_velocity0, 0.01, 10.0)
