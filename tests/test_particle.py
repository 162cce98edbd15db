"""Study 004 filter math: the particle machinery (systematic resampling, moments, Liu-West), the
jump-Markov loop against a Kalman filter on a linear-Gaussian problem, the turn model, the
bearing likelihood at +-pi, the EKF's Jacobian, and the filters' contracts."""

from __future__ import annotations

import numpy as np
import pytest

from filters.kalman import kalman_filter
from filters.particle import (
    BearingLikelihood, BearingsEKF, MultipleModelParticleFilter, bearing_jacobian, bearings,
    coordinated_turn, filter_jump_markov, liu_west, mode_bearings, predicted_positions, systematic_resample, turn_rates,
    weighted_moments, wrap,
)
from tests.helpers.filter_inputs import buoy_reports


def test_systematic_resampling_keeps_the_weights_expectation():
    """Over many uniform offsets, each index is drawn N w_i times on average, and never more than
    ceil(N w_i) nor fewer than floor(N w_i) times in one draw (the systematic property)."""
    rng = np.random.default_rng(0)
    R, M, N = 4000, 7, 50
    w = rng.dirichlet(np.ones(M), size=1)[0]
    log_w = np.broadcast_to(np.log(w), (R, M)).copy()
    idx = systematic_resample(log_w, rng.random(R), N)
    counts = np.stack([(idx == m).sum(axis=1) for m in range(M)], axis=1)            # (R, M)
    np.testing.assert_allclose(counts.mean(axis=0), N * w, atol=0.05 * N * w.max())
    assert np.all(counts >= np.floor(N * w) - 1e-9) and np.all(counts <= np.ceil(N * w) + 1e-9)


def test_systematic_resampling_is_per_run():
    """Each run resamples its own weights: a run with all weight on index 2 draws only 2."""
    log_w = np.log(np.array([[1e-300, 1e-300, 1.0, 1e-300], [0.25, 0.25, 0.25, 0.25]]))
    idx = systematic_resample(log_w, np.array([0.3, 0.5]), 8)
    assert set(idx[0]) == {2}
    np.testing.assert_array_equal(np.bincount(idx[1], minlength=4), [2, 2, 2, 2])


def test_weighted_moments_and_liu_west_keep_mean_and_covariance():
    rng = np.random.default_rng(1)
    X = rng.standard_normal((3, 20000, 4)) @ np.diag([1.0, 2.0, 0.5, 3.0]) + np.array([1.0, -2.0, 0.0, 5.0])
    w = np.full((3, 20000), 1.0 / 20000)
    mean, cov = weighted_moments(X, w)
    Y = liu_west(X, 0.3, rng.standard_normal(X.shape))
    mean2, cov2 = weighted_moments(Y, w)
    np.testing.assert_allclose(mean2, mean, atol=0.05)
    np.testing.assert_allclose(cov2, cov, atol=0.12, rtol=0.05)     # a^2 + h^2 = 1: the kernel keeps the covariance


class _LinearGaussian:
    """A 1-D constant-velocity target observed in position, as a 2-mode jump-Markov model whose
    modes are identical: the multiple-model filter must then equal the Kalman filter."""

    modes = 2
    state_size = 2
    noise_shape = (1,)

    def __init__(self, q: float, r: float) -> None:
        self.F = np.array([[1.0, 1.0], [0.0, 1.0]])
        self.G = np.array([[0.5], [1.0]]) * np.sqrt(q)
        self.r = r

    def first_stage(self, X, z, dt):
        mean = X @ self.F.T
        ll = -0.5 * (z[:, None, 0] - mean[..., 0]) ** 2 / self.r
        return np.repeat(ll[..., None], 2, axis=-1), None

    def propagate(self, X, parent, mode, noise, dt, context):
        source = X[np.arange(X.shape[0])[:, None], parent]
        return source @ self.F.T + noise.astype(float) @ self.G.T

    def log_likelihood(self, X, z):
        return -0.5 * (z[:, None, 0] - X[..., 0]) ** 2 / self.r


@pytest.mark.parametrize("auxiliary", [True, False])
def test_particle_mean_approaches_the_kalman_filter_as_particles_grow(auxiliary):
    rng = np.random.default_rng(2)
    R, K, q, r = 20, 25, 0.5, 4.0
    model = _LinearGaussian(q, r)
    x = np.zeros((R, K, 2))
    x[:, 0] = [0.0, 1.0]
    for k in range(1, K):
        x[:, k] = x[:, k - 1] @ model.F.T + rng.standard_normal((R, 1)) @ model.G.T
    z = x[..., :1] + np.sqrt(r) * rng.standard_normal((R, K, 1))
    prior_mean, prior_std = np.tile([0.0, 1.0], (R, 1)), np.array([3.0, 1.0])
    Q = model.G @ model.G.T
    # the Kalman filter from the same prior, predicted to scan 1 (the particle loop starts there)
    x0, P0 = prior_mean @ model.F.T, model.F @ np.diag(prior_std**2) @ model.F.T + Q
    kf, _ = kalman_filter(z[:, 1:], x0, np.broadcast_to(P0, (R, 2, 2)), model.F, Q, np.array([[1.0, 0.0]]),
                          np.array([[r]]))
    errors = []
    for N in (100, 3000):
        gens = [np.random.default_rng(np.random.SeedSequence(entropy=5, spawn_key=(r_,))) for r_ in range(R)]
        states, _, extras = filter_jump_markov(model, np.array([[0.9, 0.1], [0.1, 0.9]]), np.arange(K, dtype=float),
                                               z, prior_mean, prior_std, gens, N, auxiliary=auxiliary)
        errors.append(np.sqrt(np.mean((states[:, 1:] - kf) ** 2)))
        assert np.allclose(extras["mode_probabilities"].sum(-1)[:, 1:], 1.0)
    assert errors[1] < 0.45 * errors[0], errors          # Monte Carlo error ~ 1/sqrt(N)
    assert errors[1] < 0.1


def test_turn_with_vanishing_rate_equals_cv_and_a_turn_keeps_the_speed():
    state = np.array([[100.0, -50.0, 4.0, -3.0]])
    cv = coordinated_turn(state, np.array([0.0]), 5.0)
    tiny = coordinated_turn(state, np.array([1e-7]), 5.0)
    np.testing.assert_allclose(tiny, cv, atol=1e-5)
    np.testing.assert_allclose(cv[0], [120.0, -65.0, 4.0, -3.0])
    turned = coordinated_turn(state, np.array([0.01]), 5.0)
    assert np.hypot(*turned[0, 2:]) == pytest.approx(5.0)
    heading_change = np.arctan2(turned[0, 3], turned[0, 2]) - np.arctan2(-3.0, 4.0)
    assert heading_change == pytest.approx(0.05)                  # Omega > 0 turns counter-clockwise


def test_first_stage_positions_equal_the_full_turn_for_each_mode():
    rng = np.random.default_rng(3)
    target = np.concatenate([rng.normal(0, 5000, (6, 2)), rng.normal(0, 4, (6, 2))], axis=1)
    positions = predicted_positions(target, 0.01, 5.0)
    omega = turn_rates(target[:, 2:4], 0.01)
    for m in range(3):
        np.testing.assert_allclose(positions[:, m], coordinated_turn(target, omega[:, m], 5.0)[:, :2], rtol=1e-12)


def test_bearing_likelihood_wraps_around_pi_and_skips_misses():
    lik = BearingLikelihood(np.full(2, np.radians(7.0)), np.full(2, np.radians(15.0)), 0.5)
    near_pi = np.array([np.pi - 0.01, -np.pi + 0.02])
    across = lik.log(near_pi.astype(np.float32), np.array([-np.pi + 0.01, np.pi - 0.02], dtype=np.float32))
    same = lik.log(np.array([0.0, 0.0], dtype=np.float32), np.array([0.02, -0.04], dtype=np.float32))
    np.testing.assert_allclose(across, same, rtol=1e-4)          # 0.02 rad apart across the +-pi cut
    missed = lik.log(np.array([0.3, 0.3], dtype=np.float32), np.array([np.nan, 0.3], dtype=np.float32))
    assert missed[0] == 0.0 and missed[1] != 0.0
    np.testing.assert_allclose(wrap(np.array([3 * np.pi / 2, -3 * np.pi / 2])), [-np.pi / 2, np.pi / 2])


def test_mixture_likelihood_matches_the_density():
    s, sc, pc = np.radians(7.0), np.radians(15.0), 0.5
    lik = BearingLikelihood(np.array([s]), np.array([sc]), pc)
    e = np.linspace(-1.0, 1.0, 11)
    expected = np.log((1 - pc) * np.exp(-0.5 * e**2 / s**2) / (np.sqrt(2 * np.pi) * s)
                      + pc * np.exp(-0.5 * e**2 / sc**2) / (np.sqrt(2 * np.pi) * sc))
    got = lik.log(np.zeros((11, 1), dtype=np.float32), e[:, None].astype(np.float32))[:, 0]
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)      # float32 evaluation


def test_bearing_jacobian_matches_finite_differences():
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.normal(0, 4000, (3, 2)), rng.normal(0, 3, (3, 2))], axis=1)
    buoys = np.array([[-2000, -2000, 0.2, 0.1], [2000, -2000, 0.2, 0.1], [2000, 2000, 0.2, 0.1],
                      [-2000, 2000, 0.2, 0.1]], dtype=float).ravel()
    state = np.concatenate([x, np.tile(buoys, (3, 1))], axis=1)
    observer = np.array([0.0, -8000.0])
    H = bearing_jacobian(state, observer)
    for j in range(20):
        step = np.zeros(20)
        step[j] = 1e-3
        diff = wrap(bearings(state + step, observer) - bearings(state - step, observer)) / 2e-3
        np.testing.assert_allclose(H[:, :, j], diff, atol=1e-9, rtol=1e-5)


def test_filters_run_and_are_invariant_to_chunking_threads_and_batch():
    truth, reports = buoy_reports(runs=3, duration=100.0, clutter=True)
    base = MultipleModelParticleFilter(particles=200).run(reports)
    chunked = MultipleModelParticleFilter(particles=200, chunk_runs=1, workers=2).run(reports)
    np.testing.assert_array_equal(base.state, chunked.state)
    alone = MultipleModelParticleFilter(particles=200).run(reports.select([2]))
    np.testing.assert_array_equal(alone.state[0], base.state[2])
    assert base.extras["mode_probabilities"].shape == (3, 21, 3) and np.isfinite(base.state).all()
    np.testing.assert_allclose(base.extras["mode_probabilities"][:, 1:].sum(-1), 1.0)
    assert (base.extras["ess"][:, 1:] <= 200 + 1e-9).all()
    snap = MultipleModelParticleFilter(particles=200, snapshot_particles=20).run(reports)
    np.testing.assert_array_equal(snap.state, base.state)       # snapshots change nothing
    assert snap.extras["particles"].shape == (3, 21, 20, 20) and snap.extras["particle_modes"].dtype == np.int8
    ekf = BearingsEKF().run(reports)
    assert np.isfinite(ekf.state).all() and np.allclose(ekf.covariance, np.swapaxes(ekf.covariance, -1, -2))


class _Heard:
    """A filters.progress listener that keeps what it hears (thread-safe: the chunks' threads report)."""

    def __init__(self) -> None:
        import threading
        self.lock, self.starts, self.done = threading.Lock(), [], 0.0

    def start(self, total, unit="step", label=None):
        with self.lock:
            self.starts.append((total, unit, label))
            self.done = 0.0

    def advance(self, amount=1.0):
        with self.lock:
            self.done += amount


@pytest.mark.parametrize("chunk_runs, workers", [(None, 1), (1, 2), (2, 2)])
def test_the_filters_report_their_scans_and_reporting_changes_nothing(chunk_runs, workers):
    """Heard through filters.progress, the particle filter's chunks of runs add up to its scans (each
    scan of a chunk counts its share of the runs), whatever the chunking and threads; the EKF counts
    its scans. The estimates are bit-identical with and without a listener."""
    from filters.progress import listening
    _, reports = buoy_reports(runs=3, duration=100.0, clutter=True)
    K = reports.time.size
    for make in (lambda: MultipleModelParticleFilter(particles=100, chunk_runs=chunk_runs, workers=workers),
                 lambda: BearingsEKF()):
        quiet = make().run(reports)
        heard = _Heard()
        with listening(heard):
            loud = make().run(reports)
        assert heard.starts == [(K - 1, "scan", make().name)]
        assert heard.done == pytest.approx(K - 1)
        np.testing.assert_array_equal(loud.state, quiet.state)
        np.testing.assert_array_equal(loud.covariance, quiet.covariance)
        for name in quiet.extras:
            np.testing.assert_array_equal(loud.extras[name], quiet.extras[name])


def test_filters_follow_the_target_on_a_short_clean_run():
    truth, reports = buoy_reports(runs=4, duration=600.0)
    for estimator in (MultipleModelParticleFilter(particles=500, max_acceleration=0.001, target_sigma=0.005),
                      BearingsEKF(target_sigma=0.005)):
        est = estimator.run(reports)
        start = np.linalg.norm(est.state[:, 0, :2] - truth.state[:, 0, 0, :2], axis=-1)
        end = np.linalg.norm(est.state[:, -1, :2] - truth.state[:, -1, 0, :2], axis=-1)
        assert np.median(end) < 0.5 * np.median(start), (estimator.name, start, end)


@pytest.mark.parametrize("kwargs, key", [({"particles": 5}, "particles"), ({"tpm": [[1, 0], [0, 1]]}, "tpm"),
                                         ({"lw_h": 1.0}, "lw_h"), ({"noise_gain": "half"}, "noise_gain"),
                                         ({"target_sigma": -1}, "target_sigma"), ({"chunk_runs": 0}, "chunk_runs"),
                                         ({"workers": 0}, "workers"), ({"snapshot_particles": 5000}, "snapshot_particles")])
def test_bad_parameters_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        MultipleModelParticleFilter(**kwargs)


def test_mode_bearings_match_the_exact_bearings_of_each_modes_position():
    """The first stage's turn-mode bearings (CV bearing + first-order change) equal atan2 of each
    mode's predicted position to < 1e-5 rad (the noise is 7 deg = 0.12 rad)."""
    rng = np.random.default_rng(5)
    target = np.concatenate([rng.normal(0, 6000, (5000, 2)), rng.normal(0, 5, (5000, 2))], axis=1)
    buoys = rng.normal(0, 3000, (5000, 4, 2))
    positions = predicted_positions(target, 0.01, 5.0)
    d = positions[:, :, None, :] - buoys[:, None]
    exact = np.arctan2(d[..., 0], d[..., 1])
    assert np.abs(wrap(mode_bearings(positions, buoys).astype(float) - exact)).max() < 1e-5
