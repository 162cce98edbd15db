"""Study 002 filter math: the biased local filter and its bias matrix G, the pseudo bias
measurement, the least-squares bias update, EXX's slot pseudo measurements, compensation."""

from __future__ import annotations

import numpy as np
import pytest

from filters.bias import (
    BiasInformation, EXXRegistration, LocalTracking, LocalTracks, PseudoBiasRegistration, RadarReports, TrackStart,
    add_pseudo_measurements, bias_jacobian, converted_covariance, converted_measurement, cv_transition,
    dcwna_process_noise, exx_process_noise, exx_pseudo_measurement, polar, pseudo_bias_measurements,
    two_point_start,
)
from tests.helpers.bias_reports import BETA, NOISE_STD, simulate


def test_bias_jacobian_matches_finite_differences():
    """B C beta is the first-order change of the converted measurement (eqs 2-4)."""
    r, theta = np.array(12_000.0), np.array(0.7)
    _, BC = bias_jacobian(r, theta)
    for j, step in enumerate([1e-2, 1e-7, 1e-8, 1e-8]):
        beta = np.zeros(4)
        beta[j] = step
        perturbed = np.array([(1 + beta[2]) * r + beta[0], (1 + beta[3]) * theta + beta[1]])
        diff = (converted_measurement(perturbed, np.zeros(2)) - converted_measurement(np.array([r, theta]),
                                                                                       np.zeros(2))) / step
        np.testing.assert_allclose(diff, BC[:, j], rtol=1e-4)


def test_converted_covariance_is_b_diag_bt():
    B, _ = bias_jacobian(np.array(5000.0), np.array(1.1))
    expected = B @ np.diag(NOISE_STD[0] ** 2) @ B.T
    np.testing.assert_allclose(converted_covariance(B, NOISE_STD[0]), expected, rtol=1e-12)


def test_bias_matrix_is_exact_for_the_linearised_measurement():
    """Eq 20's recursion: add B C delta (the filter's own B C) to every converted measurement with
    the gains held fixed; the tracks move by exactly G delta."""
    _, reports, _ = simulate(runs=2, targets=2, reports=40, bias=np.zeros(4), seed=3)
    states, G, fixed = _replay(reports)
    for j, step in enumerate([5.0, 1e-3, 1e-4, 1e-4]):
        delta = np.zeros(4)
        delta[j] = step
        moved, _, _ = _replay(reports, fixed=fixed, offset=delta)
        np.testing.assert_allclose(moved - states, G @ delta, rtol=1e-6, atol=1e-9 * np.abs(G @ delta).max())


def test_bias_matrix_matches_finite_difference_of_the_local_filter():
    """G (eq 20) is d X^b / d beta: perturb one bias component of the radars' polar measurements,
    re-run the local filter on the same noise, compare the track change with G delta. G uses
    B C at the predicted position, the data the true one: they differ by ~(track error / range),
    so the match is to ~1 %, whatever the step (checked: halving the steps changes nothing)."""
    steps = [0.05, 5e-6, 2e-7, 5e-7]
    _, base, w = simulate(runs=2, targets=2, reports=40, bias=np.zeros(4), seed=3)
    local = LocalTracking(output_targets=None)
    reference = local.run(base)
    _, G, _ = _replay(base)
    for j, step in enumerate(steps):
        beta = np.zeros(4)
        beta[j] = step
        _, perturbed, _ = simulate(runs=2, targets=2, reports=40, bias=np.broadcast_to(beta, (2, 4)), seed=3, noise=w)
        change = (local.run(perturbed).track_state - reference.track_state) / step     # (R, K, T, 4)
        # both radars carry the same perturbation, so the reporting radar's track moves by its G[:, j]
        predicted = G[..., j]
        scale = np.abs(predicted).max(axis=(0, 1, 2))                      # per state component
        assert np.max(np.abs(change - predicted) / scale) < 1.5e-2, j


def _replay(reports: RadarReports, fixed=None, offset=None):
    """Replay the truth-started local filter; return the reporting radar's track and G after every
    report, and the per-report (B C, R^m) used. ``fixed`` re-uses those; ``offset`` adds B C offset
    to each converted measurement."""
    from filters.bias import predict_local, update_local

    R, K, T, _ = reports.z.shape
    tracks = [LocalTracks(reports.start.state[:, s].copy(),
                          np.broadcast_to(reports.start.covariance, (R, T, 4, 4)).copy(),
                          np.zeros((R, T, 4, 4))) for s in range(2)]
    last = np.zeros(2)
    states, G, used = np.empty((R, K, T, 4)), np.empty((R, K, T, 4, 4)), []
    for k in range(K):
        i = reports.sensor[k]
        predicted = predict_local(tracks[i], reports.time[k] - last[i], 6.0)
        if fixed is None:
            B, BC = bias_jacobian(*polar(predicted.state[..., :2] - reports.sensor_position[i]))
            noise = converted_covariance(B, reports.noise_std[i])
        else:
            BC, noise = fixed[k]
        used.append((BC, noise))
        z = converted_measurement(reports.z[:, k], reports.sensor_position[i])
        if offset is not None:
            z = z + BC @ offset
        tracks[i] = update_local(predicted, z, noise, BC)
        last[i] = reports.time[k]
        states[:, k], G[:, k] = tracks[i].state, tracks[i].bias_matrix
    return states, G, used


def _track(R=2, T=3, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((R, T, 4, 4))
    return LocalTracks(rng.standard_normal((R, T, 4)), A @ np.swapaxes(A, -1, -2) + np.eye(4),
                       rng.standard_normal((R, T, 4, 4)))


@pytest.mark.parametrize("sensors", [2, 3])
def test_stacked_pseudo_measurement_blocks(sensors):
    """H^b (eq 31) has B_i C_i in radar i's columns of every row block and -H Phi G_j in radar j's
    columns of j's row block, zeros elsewhere; R^b (eq 27) has H P_j H' + R^m_i on the diagonal
    and R^m_i off it (the shared w_i)."""
    rng = np.random.default_rng(1)
    R, T, i = 2, 3, 1
    others = [j for j in range(sensors) if j != i]
    tracks = [_track(R, T, seed=j) for j in others]
    elapsed = np.array([0.5 + 0.25 * j for j in others])
    z_m = rng.standard_normal((R, T, 2)) * 1000
    B, BC = bias_jacobian(np.full((R, T), 9000.0), np.full((R, T), 0.6))
    noise = converted_covariance(B, NOISE_STD[0])
    z, H, Rb = pseudo_bias_measurements(i, z_m, noise, BC, tracks, others, elapsed, 6.0, sensors, correlated=True)
    J = len(others)
    assert z.shape == (R, T, 2 * J) and H.shape == (R, T, 2 * J, 4 * sensors) and Rb.shape == (R, T, 2 * J, 2 * J)
    for row, (j, track, dt) in enumerate(zip(others, tracks, elapsed)):
        rows = slice(2 * row, 2 * row + 2)
        F = cv_transition(dt)
        np.testing.assert_allclose(H[..., rows, 4 * i:4 * i + 4], BC)
        np.testing.assert_allclose(H[..., rows, 4 * j:4 * j + 4], -(F @ track.bias_matrix)[..., :2, :])
        for other in range(sensors):
            if other not in (i, j):
                assert not H[..., rows, 4 * other:4 * other + 4].any()
        np.testing.assert_allclose(z[..., rows], z_m - (track.state @ F.T)[..., :2])
        P = F @ track.covariance @ F.T + dcwna_process_noise(dt, 6.0)
        np.testing.assert_allclose(Rb[..., rows, rows], P[..., :2, :2] + noise)
        for col in range(J):
            if col != row:
                np.testing.assert_allclose(Rb[..., rows, 2 * col:2 * col + 2], noise)
    _, _, independent = pseudo_bias_measurements(i, z_m, noise, BC, tracks, others, elapsed, 6.0, sensors,
                                                 correlated=False)
    if J > 1:
        assert not independent[..., 0:2, 2:4].any()


def test_information_update_equals_target_by_target_rls():
    """One information-form update over all targets = the seed's recursion eqs 33-35 target by target."""
    rng = np.random.default_rng(2)
    R, T, m, n = 3, 5, 2, 8
    prior_std = np.tile([100.0, 0.2, 0.01, 0.1], 2)
    H = rng.standard_normal((R, T, m, n)) * np.array([1, 1e4, 1e4, 1e4, 1, 1e4, 1e4, 1e4])
    A = rng.standard_normal((R, T, m, m))
    noise = A @ np.swapaxes(A, -1, -2) + 50 * np.eye(m)
    z = rng.standard_normal((R, T, m)) * 30
    info = add_pseudo_measurements(BiasInformation.prior(R, prior_std), z, H, noise)
    mean, cov = info.estimate()
    b = np.zeros((R, n))
    Sigma = np.broadcast_to(np.diag(prior_std**2), (R, n, n)).copy()
    for t in range(T):
        Ht = H[:, t]
        gain = Sigma @ np.swapaxes(Ht, -1, -2) @ np.linalg.inv(Ht @ Sigma @ np.swapaxes(Ht, -1, -2) + noise[:, t])  # eq 33
        b = b + np.einsum("rij,rj->ri", gain, z[:, t] - np.einsum("rij,rj->ri", Ht, b))                          # eq 34
        Sigma = Sigma - gain @ Ht @ Sigma                                                                         # eq 35
    scale = np.outer(prior_std, prior_std)
    np.testing.assert_allclose(mean / prior_std, b / prior_std, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(cov / scale, Sigma / scale, rtol=1e-6, atol=1e-12)


def test_zero_bias_estimate_stays_near_zero_and_compensation_changes_little():
    prior_std = np.tile([100.0, 0.2, 0.01, 0.1], 2)
    _, clean, _ = simulate(runs=20, targets=8, reports=160, bias=np.zeros(4), seed=4)
    _, biased, _ = simulate(runs=20, targets=8, reports=160, seed=4)
    zero = PseudoBiasRegistration(output_targets=None).run(clean)
    rms = np.sqrt((zero.bias[:, -1] ** 2).mean(axis=0))
    assert np.all(rms < 0.1 * prior_std), rms / prior_std             # measured: <= 0.04 of the prior
    assert rms[0] < 6.0 and rms[4] < 6.0                              # range offsets [m]; the study's are 20 m

    def moved(est):
        return np.nanmean(np.linalg.norm(est.compensated_state[..., :2] - est.track_state[..., :2], axis=-1))

    with_bias = PseudoBiasRegistration(output_targets=None).run(biased)
    assert moved(zero) < 0.2 * moved(with_bias), (moved(zero), moved(with_bias))


def test_offsets_are_recovered_with_truth_start():
    """Measured at this size: range offsets proposed ~4 / 2 m, EXX ~16 / 5 m (prior 100 m);
    azimuth offsets ~0.3-0.4 mrad for both (prior 200 mrad, truth 2 mrad)."""
    _, reports, _ = simulate(runs=10, targets=8, reports=400, seed=5, q=6.0)
    for estimator, range_bound in ((PseudoBiasRegistration(output_targets=None), 8.0),
                                   (EXXRegistration(output_targets=None), 30.0)):
        est = estimator.run(reports)
        err = est.bias[:, -1] - np.tile(BETA, 2)
        rmse = np.sqrt((err**2).mean(axis=0))
        assert rmse[0] < range_bound and rmse[4] < range_bound, (estimator.name, rmse)
        assert rmse[1] < 1e-3 and rmse[5] < 1e-3, (estimator.name, rmse)


def test_compensation_with_the_true_bias_removes_the_bias_part():
    """With beta_hat = beta and Sigma = 0, X^b - G beta equals the filter run on unbiased data
    (to the linearisation of eq 2)."""
    _, biased, w = simulate(runs=2, targets=3, reports=60, seed=6)
    _, clean, _ = simulate(runs=2, targets=3, reports=60, bias=np.zeros(4), seed=6, noise=w)
    local = LocalTracking(output_targets=None)
    _, G, _ = _replay(biased)
    x_biased = local.run(biased).track_state
    x_clean = local.run(clean).track_state
    compensated = x_biased - np.einsum("rktij,j->rkti", G, BETA)
    before = np.abs(x_biased - x_clean)[..., :2].max()
    after = np.abs(compensated - x_clean)[..., :2].max()
    assert before > 20 and after < 0.05 * before


def test_exx_slot_cancels_the_state_and_keeps_the_bias():
    """zeta = z_B - a1 z_A(t1) - a2 z_A(t2) has no CV state in it: noise-free and bias-free it is 0;
    biased it equals H_zeta beta to first order."""
    for bias, expect_zero in ((np.zeros(4), True), (BETA, False)):
        X, reports, _ = simulate(runs=1, targets=2, reports=3, bias=bias, noise_scale=0.0, seed=7)
        slot = []
        for k in range(3):
            i = reports.sensor[k]
            position = reports.sensor_position[i]
            truth_polar = polar(X[:, k + 1, :, :2] - position)
            B, BC = bias_jacobian(*truth_polar)
            slot.append((i, reports.time[k], converted_measurement(reports.z[:, k], position),
                         converted_covariance(B, reports.noise_std[i]), BC))
        zeta, H, noise = exx_pseudo_measurement(slot, 6.0, 2)
        if expect_zero:
            np.testing.assert_allclose(zeta, 0.0, atol=1e-7)
        else:   # second-order terms (b_r b_theta, r b_theta^2 / 2) are a few cm here
            predicted = np.einsum("rtij,j->rti", H, np.tile(bias, 2))
            np.testing.assert_allclose(zeta, predicted, atol=0.1)
        assert np.allclose(noise, np.swapaxes(noise, -1, -2))


@pytest.mark.parametrize("times", [(0.0, 0.5, 1.0), (0.0, 0.3, 1.0), (0.0, 1.0, 1.7), (0.4, 1.0, 0.0)])
def test_exx_process_noise_matches_monte_carlo(times):
    """The process-noise variance left in p(t_b) - a1 p(t1) - a2 p(t2) (notes 5.4), against sampled
    DCWNA trajectories."""
    t1, t2, t_b = times
    q = 6.0
    rng = np.random.default_rng(8)
    grid = np.unique(np.array([0.0, t1, t2, t_b]))
    n = 200_000
    state = np.zeros((n, 4))
    at = {}
    previous = 0.0
    for t in grid:
        dt = t - previous
        if dt > 0:
            L = np.linalg.cholesky(dcwna_process_noise(dt, q))
            state = state @ cv_transition(dt).T + rng.standard_normal((n, 4)) @ L.T
        at[t] = state[:, 0].copy()
        previous = t
    a1, a2 = (t2 - t_b) / (t2 - t1), (t_b - t1) / (t2 - t1)
    combination = at[t_b] - a1 * at[t1] - a2 * at[t2]
    expected = exx_process_noise(t1, t2, t_b, q)
    assert combination.var() == pytest.approx(expected, rel=0.02)


def test_exx_slots_follow_the_alternating_pattern():
    """Two 1 Hz radars offset by 0.5 s: one slot per 3 reports, every report used once."""
    _, reports, _ = simulate(runs=1, targets=1, reports=12, seed=9)
    exx = EXXRegistration(output_targets=None)
    est = exx.run(reports)
    changed = np.nonzero(np.any(np.diff(np.vstack([np.zeros(8), est.bias[0]]), axis=0) != 0, axis=1))[0]
    np.testing.assert_array_equal(changed, [2, 5, 8, 11])


def test_two_point_start_follows_eqs_8_to_11():
    rng = np.random.default_rng(10)
    z0, z1 = rng.standard_normal((2, 3, 2)) * 100
    B0, BC0 = bias_jacobian(np.full(3, 8000.0), np.full(3, 0.5))
    B1, BC1 = bias_jacobian(np.full(3, 8010.0), np.full(3, 0.51))
    R0, R1 = converted_covariance(B0, NOISE_STD[0]), converted_covariance(B1, NOISE_STD[0])
    tracks = two_point_start(z0, z1, R0, R1, BC0, BC1, 1.0)
    np.testing.assert_allclose(tracks.state[..., :2], z1)
    np.testing.assert_allclose(tracks.state[..., 2:], z1 - z0)
    np.testing.assert_allclose(tracks.bias_matrix[..., :2, :], BC1)
    np.testing.assert_allclose(tracks.bias_matrix[..., 2:, :], BC1 - BC0)
    np.testing.assert_allclose(tracks.covariance[..., 2:, 2:], R0 + R1)


def test_two_point_start_runs_and_estimates():
    _, reports, _ = simulate(runs=6, targets=4, reports=120, seed=11)
    est = PseudoBiasRegistration(start="two_point", output_targets=None).run(reports)
    assert np.isnan(est.track_state[:, :2]).all()          # each radar needs two reports first
    assert np.isfinite(est.track_state[:, 4:]).all()
    err = np.abs(est.bias[:, -1, 0] - BETA[0])
    assert err.mean() < 40                                  # prior 100 m


def test_batched_runs_equal_single_runs():
    _, reports, _ = simulate(runs=3, targets=3, reports=30, seed=12)
    batched = PseudoBiasRegistration(output_targets=None).run(reports)
    single = RadarReports(reports.time, reports.sensor, reports.z[1:2], reports.sensor_position, reports.noise_std,
                          TrackStart(0.0, reports.start.state[1:2], reports.start.covariance))
    alone = PseudoBiasRegistration(output_targets=None).run(single)
    np.testing.assert_allclose(batched.bias[1], alone.bias[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(batched.compensated_state[1], alone.compensated_state[0], rtol=1e-9)


@pytest.mark.parametrize("kwargs, key", [({"start": "first"}, "start"), ({"prior_std": [1, 2, 3]}, "prior_std"),
                                         ({"output_targets": [0]}, "output_targets"),
                                         ({"jacobian_at": "truth"}, "jacobian_at"),
                                         ({"process_noise_density": -1}, "process_noise_density")])
def test_bad_parameters_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        PseudoBiasRegistration(**kwargs)


def test_output_target_beyond_the_scenario_is_refused():
    _, reports, _ = simulate(runs=1, targets=3, reports=4)
    with pytest.raises(ValueError, match="output_targets"):
        LocalTracking(output_targets=[1, 32]).run(reports)
