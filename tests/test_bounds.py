"""The posterior Cramer-Rao bound (filters.bounds): for a linear-Gaussian model it is the Kalman
filter's covariance; for the sonar study it is finite, shrinks while the sonar is active and grows
with the range while it is passive."""

from __future__ import annotations

import numpy as np
from hydra import compose, initialize_config_dir

from filters.bounds import posterior_crlb
from filters.kalman import kalman_filter
from pipeline.config import build
from tests.conftest import CONF


def test_linear_gaussian_bound_is_the_kalman_covariance():
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.3 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H, R = np.array([[1.0, 0.0]]), np.array([[4.0]])
    P0 = np.diag([9.0, 1.0])
    K = 30
    z = np.zeros((1, K, 1))                                   # the KF covariance does not depend on z
    # the KF's first scan updates the prior with z_0: the bound's initial is that posterior
    _, kf_cov = kalman_filter(z, np.zeros((1, 2)), P0[None], F, Q, H, R)
    information = np.broadcast_to(H.T @ np.linalg.inv(R) @ H, (K, 2, 2))
    bounds = posterior_crlb(F, Q, kf_cov[0, 0], information)
    np.testing.assert_allclose(bounds, kf_cov[0], rtol=1e-10, atol=1e-12)


def test_singular_process_noise_is_fine():
    F = np.eye(2)
    Q = np.diag([0.0, 1.0])
    bounds = posterior_crlb(F, Q, np.eye(2), np.broadcast_to(np.diag([1.0, 0.0]), (5, 2, 2)))
    assert np.all(np.isfinite(bounds)) and bounds[-1, 0, 0] < bounds[0, 0, 0]


def test_sonar_bounds_shrink_when_active_and_the_trackers_sit_above_the_clairvoyant_one():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=sonar_case2", "mc.runs=4", "scenario.duration=3000"])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(4, 1)
    bound = study.position_bound(truth, sensor, "model")           # the trackers' Singer model
    assert bound.shape == (3001,) and np.all(np.isfinite(bound)) and np.all(bound > 0)
    assert bound[499] < bound[0]                     # 500 s of range + bearing
    assert bound[2499] > bound[600]                  # passive, the range opens up
    assert bound[2999] < bound[2499]                 # active again
    clairvoyant = study.position_bound(truth, sensor)               # the deterministic truth's own dynamics
    assert np.all(clairvoyant[1:] <= bound[1:] * (1 + 1e-9))
    reports = study.track_input(truth, sensor.measure(truth, 1), sensor, 1)
    metrics = study.per_step_metrics(truth, build(cfg.filters.only_mgekf, "f").run(reports), sensor)
    ratio = metrics["position_rmse_over_bound"]
    assert np.nanmedian(ratio[1:]) > 1.0, np.nanmedian(ratio[1:])           # no estimator beats it
