"""Estimation math against hand-worked cases and textbook invariants."""

from __future__ import annotations

import numpy as np
import pytest

from filters.base import MeasurementSeries
from filters.imm import AOVSIMM, FSIMM, VSIMM, ModeSet, compact, drop_slots
from filters.kalman import inverse_and_logdet, kalman_filter, predict, update
from filters.models import AccelerationModelSet, constant_velocity_transition, two_point_initialisation
from tests.helpers.filter_inputs import measurements, scenario


def test_predict_matches_hand_computed():
    F = constant_velocity_transition(2.0)
    P = np.diag([4.0, 1.0, 9.0, 2.0])
    Q = np.eye(4) * 0.5
    x, P1 = predict(np.array([1.0, 2.0, 3.0, -1.0]), P, F, Q)
    np.testing.assert_allclose(x, [5.0, 2.0, 1.0, -1.0])
    np.testing.assert_allclose(P1, F @ P @ F.T + Q, atol=1e-14)


def test_scalar_update_matches_textbook():
    # prior N(0, 4), z = 2 with R = 1: gain 0.8, posterior mean 1.6, variance 0.8
    x, P, ll = update(np.array([0.0]), np.array([[4.0]]), np.array([2.0]), np.array([[1.0]]), np.array([[1.0]]))
    np.testing.assert_allclose(x, [1.6])
    np.testing.assert_allclose(P, [[0.8]])
    np.testing.assert_allclose(ll, -0.5 * (4.0 / 5.0 + np.log(5.0) + np.log(2 * np.pi)))


@pytest.mark.parametrize("m", [1, 2, 3])
def test_closed_form_inverse(m):
    rng = np.random.default_rng(m)
    A = rng.standard_normal((7, m, m))
    S = A @ np.swapaxes(A, -1, -2) + m * np.eye(m)
    inv, logdet = inverse_and_logdet(S)
    np.testing.assert_allclose(inv, np.linalg.inv(S), rtol=1e-10)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(S)[1], rtol=1e-10)


def single_model_set(acceleration=(0.0, 0.0)):
    return AccelerationModelSet.from_config({"m1": list(acceleration)}, [[1]], process_noise_std=10.0)


def test_imm_with_one_model_equals_the_kalman_filter():
    truth = scenario("ao_vsimm_s1", steps=60).generate(4, 3)
    meas = measurements(truth, 3)
    ms = single_model_set()
    est = FSIMM(ms).run(meas)
    x0, P0 = two_point_initialisation(meas.z[:, 0], meas.z[:, 1], 1.0, meas.noise_covariance)
    # the KF starts at scan 1 from (x0, P0) and predicts+updates from scan 2
    xs, Ps = [], []
    x, P = x0, P0
    for k in range(2, meas.scans):
        x, P = predict(x, P, ms.transition, ms.process_noise, ms.offsets[0])
        x, P, _ = update(x, P, meas.z[:, k], ms.measurement_matrix, meas.noise_covariance)
        xs.append(x)
        Ps.append(P)
    np.testing.assert_allclose(est.state[:, 2:], np.stack(xs, 1), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(est.covariance[:, 2:], np.stack(Ps, 1), rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(est.extras["mode_probabilities"][:, 2:], 1.0)


@pytest.mark.parametrize("cls", [FSIMM, VSIMM, AOVSIMM])
def test_batched_over_runs_equals_one_run_at_a_time(cls, models13):
    truth = scenario("ao_vsimm_s2", steps=90).generate(5, 11)
    meas = measurements(truth, 11)
    batched = cls(models13).run(meas)
    for r in range(meas.runs):
        one = MeasurementSeries(meas.time, meas.z[r:r + 1], meas.noise_covariance, meas.detected[r:r + 1], meas.sensor)
        single = cls(models13).run(one)
        np.testing.assert_allclose(batched.state[r:r + 1], single.state, rtol=1e-10, atol=1e-8)
        for name in ("mode_probabilities", "active_group", "candidate_group", "models_evaluated"):
            np.testing.assert_allclose(batched.extras[name][r:r + 1], single.extras[name], atol=1e-10)


def test_linear_gaussian_kf_nees_averages_its_dimension():
    """A KF matched to the simulated model is consistent: mean NEES ~ n (chi-square, 4 dof)."""
    rng = np.random.default_rng(7)
    ms = single_model_set()
    F, Q, H = ms.transition, ms.process_noise, ms.measurement_matrix
    R_meas = 25.0 * np.eye(2)
    runs, K = 400, 60
    x = np.zeros((runs, 4))
    x0_cov = np.diag([100.0, 25.0, 100.0, 25.0])
    x = rng.multivariate_normal(np.zeros(4), x0_cov, size=runs)
    truth = np.empty((runs, K, 4))
    for k in range(K):
        if k:
            x = x @ F.T + rng.multivariate_normal(np.zeros(4), Q, size=runs)
        truth[:, k] = x
    z = truth @ H.T + rng.multivariate_normal(np.zeros(2), R_meas, size=(runs, K))
    states, covs = kalman_filter(z, np.zeros((runs, 4)), np.broadcast_to(x0_cov, (runs, 4, 4)), F, Q, H, R_meas)
    e = states - truth
    nees = np.einsum("rki,rki->rk", e, np.linalg.solve(covs, e[..., None])[..., 0])
    mean = nees[:, 10:].mean()
    # mean of 400*50 (correlated) chi2(4) draws: well within +-0.2 of 4
    assert abs(mean - 4.0) < 0.2, mean


def test_transition_matrix_validation_names_the_problem():
    acc = {"a": [0, 0], "b": [1, 0]}
    with pytest.raises(ValueError, match=r"row 1 \(b\) sums to 0.9"):
        AccelerationModelSet.from_config(acc, [[0.5, 0.5], [0.4, 0.5]])
    with pytest.raises(ValueError, match=r"shape 3x2 does not match the 2 models"):
        AccelerationModelSet.from_config(acc, [[1, 0], [0, 1], [0, 1]])
    with pytest.raises(ValueError, match="not a probability"):
        AccelerationModelSet.from_config(acc, [[1.5, -0.5], [0, 1]])
    with pytest.raises(ValueError, match="unknown models"):
        AccelerationModelSet.from_config(acc, [[1, 0], [0, 1]], groups={"G": ["a", "zz"]})
    ok = AccelerationModelSet.from_config(acc, [["1/3", "2/3"], [0, 1]])
    assert ok.transition_matrix[0, 0] == pytest.approx(1 / 3)


def test_study001_transition_matrix_rows_stay_in_the_central_group(models13):
    tpm = models13.transition_matrix
    np.testing.assert_allclose(tpm.sum(axis=1), 1.0, atol=1e-12)
    for g in models13.groups:
        centre = g[0]
        assert set(np.flatnonzero(tpm[centre])) <= set(g.tolist())


def test_compact_and_drop_keep_estimates_with_their_models():
    R, A = 2, 4
    idx = np.array([[3, -1, 5, 7], [-1, -1, 2, -1]])
    x = np.arange(R * A * 1, dtype=float).reshape(R, A, 1)
    s = ModeSet(idx, x, np.ones((R, A, 1, 1)), np.where(idx >= 0, 0.0, -np.inf), np.zeros((R, A)),
                np.where(idx >= 0, 0.0, -np.inf), x, np.ones((R, A, 1, 1)))
    c = compact(s)
    np.testing.assert_array_equal(c.model_index, [[3, 5, 7], [2, -1, -1]])
    np.testing.assert_array_equal(c.x[..., 0], [[0, 2, 3], [6, 4, 5]])
    d = drop_slots(c, np.array([[True, False, True], [True, False, False]]))
    np.testing.assert_array_equal(d.model_index, [[3, 7], [2, -1]])
    np.testing.assert_allclose(d.probabilities(), [[0.5, 0.5], [1.0, 0.0]])


def test_ao_vsimm_runs_five_models_and_switches_groups(models13):
    truth = scenario("ao_vsimm_s2").generate(6, 5)
    est = AOVSIMM(models13).run(measurements(truth, 5))
    evaluated = est.extras["models_evaluated"][:, 2:]
    assert set(np.unique(evaluated)) <= {5, 8}           # 5 per step, 8 on an activation step
    assert (est.extras["candidate_group"] == -1).all()    # never a union
    # S2 goes M1 -> M2 (k 31-45) -> M1 -> M3 (k 56-80): every run must have visited M2 and M3
    groups = est.extras["active_group"]
    assert ((groups == 1).any(axis=1)).all() and ((groups == 2).any(axis=1)).all()
    np.testing.assert_allclose(np.nansum(est.extras["mode_probabilities"][:, 2:], axis=-1), 1.0, atol=1e-12)


def test_vsimm_new_old_reading_equals_ao_vsimm(models13):
    """With new/old ratios the union terminates the old group at once: the same estimates as AO-VSIMM."""
    truth = scenario("ao_vsimm_s2").generate(4, 9)
    meas = measurements(truth, 9)
    a = VSIMM(models13, ratio="new_old").run(meas)
    b = AOVSIMM(models13).run(meas)
    np.testing.assert_allclose(a.state[:, 1:], b.state[:, 1:], rtol=1e-9)


def test_vsimm_rejects_bad_settings(models13):
    with pytest.raises(ValueError, match="ratio"):
        VSIMM(models13, ratio="sideways")
    with pytest.raises(ValueError, match="t1_mu <= t2_mu"):
        VSIMM(models13, t1_mu=0.95, t2_mu=0.9)
    with pytest.raises(ValueError, match="group 'M9'"):
        AOVSIMM(models13, initial_group="M9")


def test_termination_readings_on_a_hand_worked_union(models13):
    """Union M1 (old) + M2 (new), all evidence on m10 (only in M2): mu(M1) ~ 0.005, mu(M2) ~ 0.997,
    L(M1) = 1e-3, L(M2) ~ 0.2. 'printed' (old/new, printed rules) ends the better group M2 -- the
    paper's S2 failure mode; 'new_old' and 'old_new' end M1. Evidence split evenly keeps the union."""
    from filters.imm import GroupState

    union = np.array([[0, 1, 2, 3, 4, 9, 5, 8]])            # M1 = m1..m5, plus m10, m6, m9 of M2
    A = union.shape[1]
    log_pred = np.full((1, A), np.log(1 / A))
    log_lik = np.where(union == 9, 0.0, np.log(1e-3))
    s = ModeSet(union, np.zeros((1, A, 4)), np.broadcast_to(np.eye(4), (1, A, 4, 4)).copy(), log_pred, log_lik,
                log_pred + log_lik, np.zeros((1, A, 4)), np.broadcast_to(np.eye(4), (1, A, 4, 4)).copy())
    start = GroupState(old=np.array([0]), new=np.array([1]), log_lr=np.zeros(1))
    for ratio, survivor in (("printed", 0), ("new_old", 1), ("old_new", 1)):
        kept, groups = VSIMM(models13, ratio=ratio)._terminate(s, start, np.array([True]))
        assert groups.old[0] == survivor and groups.new[0] == -1, ratio
        assert set(kept.model_index[0][kept.valid[0]]) == set(models13.groups[survivor]), ratio

    even = ModeSet(union, s.x, s.P, log_pred, np.zeros((1, A)), log_pred, s.x, s.P)
    kept, groups = VSIMM(models13)._terminate(even, start, np.array([True]))
    assert groups.new[0] == 1 and kept.valid.sum() == A     # t^L = 1 is not above t2^L = 1: keep the union
