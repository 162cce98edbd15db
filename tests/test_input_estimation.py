"""Study 000 math: Singer model, radar geometry, LOS frame, and the MIE on noise-free data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from filters.base import MeasurementSeries
from filters.coordinates import (converted_covariance, line_of_sight_angles, los_noise_variances, los_rotation,
                                 polar_to_cartesian)
from filters.input_estimation import InertialMIE, LOSMIE
from filters.models import singer_input_gain, singer_process_noise, singer_transition

R_P = np.diag([100.0, 4.9e-5, 3.6e-5])


def test_singer_matrices_match_van_loan_and_the_reference_numbers():
    tau, dt, sigma = 10.0, 1.0, 5.0
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1 / tau]])
    np.testing.assert_allclose(singer_transition(dt, tau), expm(A * dt), atol=1e-12)
    # literature notes 1.2: Q1 for T = 1, tau = 10, sigma_m = 5
    np.testing.assert_allclose(singer_process_noise(dt, tau, sigma), [[0.236594, 0.585015, 0.754408],
                                                                      [0.585015, 1.547298, 2.263979],
                                                                      [0.754408, 2.263979, 4.531731]], atol=2e-6)
    # G: a constant level u held from a = u keeps a = u and moves like constant acceleration (eq 2, notes 1.3)
    x = np.array([0.0, 0.0, 3.0])
    np.testing.assert_allclose(singer_transition(dt, tau) @ x + singer_input_gain(dt, tau) * 3.0, [1.5, 3.0, 3.0])
    # the small alpha*T branch (Van Loan, alpha*T = 5e-4) against Q = integral of e^{As} L q L' e^{A's} ds
    from scipy.integrate import quad_vec
    tau_long = 2000.0
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1 / tau_long]])
    q = 2 * sigma**2 / tau_long
    L = np.array([[0.0], [0.0], [1.0]])
    expected = quad_vec(lambda s: expm(A * s) @ L @ L.T @ expm(A * s).T * q, 0.0, dt)[0]
    np.testing.assert_allclose(singer_process_noise(dt, tau_long, sigma), expected, rtol=1e-8)


def test_los_rotation_is_orthonormal_points_at_the_target_and_round_trips():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3)) * [9000, 5000, 2000]
    r, phi, theta = line_of_sight_angles(p)
    T = los_rotation(phi, theta)
    np.testing.assert_allclose(T @ np.swapaxes(T, 1, 2), np.broadcast_to(np.eye(3), T.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(T), 1.0)
    np.testing.assert_allclose(np.einsum("rab,rb->ra", T, p), np.c_[r, np.zeros(50), np.zeros(50)], atol=1e-8)
    np.testing.assert_allclose(polar_to_cartesian(np.c_[r, phi, theta]), p, atol=1e-8)


def test_converted_covariance_is_the_jacobian_sandwich():
    polar = np.array([9000.0, 0.4, 0.2])
    eps = 1e-6 * np.array([1.0, 1e-4, 1e-4])
    J = np.stack([(polar_to_cartesian(polar + e) - polar_to_cartesian(polar - e)) / (2 * h)
                  for e, h in zip(np.diag(eps), eps)], axis=1)
    np.testing.assert_allclose(converted_covariance(polar, np.diag(R_P)), J @ R_P @ J.T, rtol=2e-5)
    d = los_noise_variances(np.array(9000.0), np.array(0.2), np.diag(R_P))
    np.testing.assert_allclose(d, [100.0, (9000 * np.cos(0.2)) ** 2 * 4.9e-5, 9000**2 * 3.6e-5])


def straight_then_maneuver(maneuver=(15.0, -10.0, -5.0), start=40, stop=60, K=101):
    x = np.zeros((K, 9))
    x[0, :3], x[0, 3:6] = [8000, 4000, 2000], [-150, 50, 50]
    for k in range(1, K):
        a = np.array(maneuver) if start <= k - 1 < stop else np.zeros(3)
        x[k, :3] = x[k - 1, :3] + x[k - 1, 3:6] + 0.5 * a
        x[k, 3:6] = x[k - 1, 3:6] + a
        x[k, 6:] = a
    return x


def radar(x, runs=1, seed=None):
    p = x[:, :3]
    polar = np.stack(line_of_sight_angles(p), -1)[None].repeat(runs, 0)
    if seed is not None:
        polar = polar + np.random.default_rng(seed).standard_normal(polar.shape) * np.sqrt(np.diag(R_P))
    K = x.shape[0]
    return MeasurementSeries(np.arange(K, dtype=float), polar, R_P, np.ones((runs, K), bool), np.zeros(K, int))


@pytest.mark.parametrize("make", [lambda: InertialMIE("A", test="full"), lambda: LOSMIE("B"),
                                  lambda: LOSMIE("B", pseudo_residual_covariance="full")],
                         ids=["A-full", "B", "B-gls"])
def test_mie_recovers_a_constant_input_from_noise_free_data(make):
    """Noise-free radar, a (15, -10, -5) m/s^2 input from t = 40 s: the first detection finds the
    onset n = 40 and the level exactly, and the compensated state is the truth (eqs 28, 34, 38)."""
    truth = straight_then_maneuver()
    est = make().run(radar(truth))
    k = int(np.flatnonzero(est.extras["maneuver_detected"][0])[0])
    assert 43 <= k <= 47 and est.extras["onset_step"][0, k] == 40
    np.testing.assert_allclose(est.extras["input_level"][0, k], [15.0, -10.0, -5.0], atol=1e-6)
    np.testing.assert_allclose(est.state[0, k], truth[k], atol=1e-4)


def test_without_maneuver_and_compensation_the_los_filter_matches_the_coupled_one():
    truth = straight_then_maneuver(maneuver=(0.0, 0.0, 0.0))
    meas = radar(truth, runs=60, seed=3)
    rmse = {}
    for name, f in (("A", InertialMIE("A", compensate=False)), ("B", LOSMIE("B", compensate=False))):
        err = f.run(meas).state[:, 5:, :3] - truth[None, 5:, :3]
        rmse[name] = np.sqrt((err**2).sum(-1).mean())
    assert abs(rmse["B"] / rmse["A"] - 1) < 0.05, rmse


def test_los_output_covariance_is_the_rotated_block_diagonal():
    truth = straight_then_maneuver()
    est = LOSMIE("B").run(radar(truth, runs=2, seed=1))
    P = est.covariance[:, 30]
    np.testing.assert_allclose(P, np.swapaxes(P, 1, 2), atol=1e-9)
    assert (np.linalg.eigvalsh(P) > 0).all()


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="test: 'sum'"):
        LOSMIE(test="sum")
    with pytest.raises(ValueError, match="min_samples <= window"):
        InertialMIE(window=2, min_samples=3)
    with pytest.raises(ValueError, match="rearm_after"):
        LOSMIE(rearm_after=1)


def test_a_radar_away_from_the_origin_gives_the_same_errors():
    """The filters work radar-centred and add the radar position back: moving radar and target
    together by the same offset changes nothing but the output positions."""
    truth = straight_then_maneuver()
    offset = np.array([2500.0, -1200.0, 300.0])
    base = radar(truth, runs=3, seed=4)
    moved = MeasurementSeries(base.time, base.z, base.noise_covariance, base.detected, base.sensor, offset)
    for f in (InertialMIE("A"), LOSMIE("B")):
        a, b = f.run(base), f.run(moved)
        np.testing.assert_allclose(b.state[:, 1:, :3] - offset, a.state[:, 1:, :3], atol=1e-6)
        np.testing.assert_allclose(b.state[:, 1:, 3:], a.state[:, 1:, 3:], atol=1e-9)
