"""filters.tracker.KalmanTracker: one Kalman-type filter for three measurement kinds (studies 001, 000, 003)."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from filters.base import MeasurementSeries
from filters.kalman import kalman_filter
from filters.tracker import KalmanTracker, to_layout
from tests.helpers.runs import run_in_process


def _cv_truth(R: int, K: int, dt: float, d: int, rng) -> np.ndarray:
    """(R, K, d) positions of constant-velocity targets."""
    p0 = rng.uniform(-5000, 5000, (R, 1, d))
    v = rng.uniform(-200, 200, (R, 1, d))
    return p0 + v * (np.arange(K) * dt)[None, :, None]


def test_on_positions_it_is_the_textbook_kalman_filter():
    """After the two-point start, scans 2.. equal filters.kalman.kalman_filter started from the same state."""
    rng = np.random.default_rng(1)
    R, K, dt, sigma = 4, 30, 1.0, 20.0
    z = _cv_truth(R, K, dt, 2, rng) + sigma * rng.standard_normal((R, K, 2))
    tracker = KalmanTracker(motion="cv", acceleration_density=3.0)
    est = tracker.run(MeasurementSeries(np.arange(K) * dt, z, sigma**2 * np.eye(2), np.ones((R, K), bool),
                                        np.zeros(K, int)))
    assert np.isnan(est.state[:, 0]).all() and np.isfinite(est.state[:, 1:]).all()
    F1, Q1 = tracker.axis_model(dt)
    F, Q = np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    x1, P1 = est.state[:, 1], est.covariance[:, 1]
    x_pred, P_pred = x1 @ F.T, F @ P1 @ F.T + Q
    # kalman_filter updates its first scan from the prior: give it the prediction to scan 2
    states, covariances = kalman_filter(z[:, 2:], x_pred, P_pred, F, Q, H, sigma**2 * np.eye(2))
    np.testing.assert_allclose(est.state[:, 2:], states, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(est.covariance[:, 2:], covariances, rtol=1e-9, atol=1e-6)


def test_noise_free_polar_measurements_of_a_cv_target_are_tracked_exactly():
    rng = np.random.default_rng(2)
    R, K, dt = 3, 20, 1.0
    truth = _cv_truth(R, K, dt, 3, rng) + np.array([0.0, 0.0, 20000.0])
    radar = np.array([100.0, -50.0, 10.0])
    rel = truth - radar
    polar = np.stack([np.linalg.norm(rel, axis=-1), np.arctan2(rel[..., 1], rel[..., 0]),
                      np.arcsin(rel[..., 2] / np.linalg.norm(rel, axis=-1))], -1)
    series = MeasurementSeries(np.arange(K) * dt, polar, np.diag([1e-6, 1e-12, 1e-12]), np.ones((R, K), bool),
                               np.zeros(K, int), radar, ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az"))
    from filters.coordinates import polar_to_cartesian
    np.testing.assert_allclose(polar_to_cartesian(polar) + radar, truth, atol=1e-6)   # the geometry agrees
    est = KalmanTracker(motion="singer", tau=10.0, sigma_m=1.0).run(series)
    np.testing.assert_allclose(est.state[:, 1:, :3], truth[:, 1:], atol=1e-2)
    assert est.state.shape == (R, K, 9)


def test_a_layout_without_some_components_leaves_them_nan():
    state = np.arange(4.0).reshape(1, 1, 4)
    cov = np.eye(4).reshape(1, 1, 4, 4) * np.arange(1.0, 5.0)
    x, P = to_layout(state, cov, ("x", "vx", "y", "vy"), ("x", "y", "vx", "vy", "ax", "ay"))
    np.testing.assert_array_equal(x[0, 0, :4], [0.0, 2.0, 1.0, 3.0])
    assert np.isnan(x[0, 0, 4:]).all() and np.isnan(P[0, 0, 4]).all() and P[0, 0, 1, 1] == 3.0


@pytest.mark.parametrize("experiment, kf, extra, reference, tolerance", [
    # study 001 (2-D positions): the CV filter next to the IMMs on the maneuvering target
    ("ao_vsimm_s1", "kalman_cv", [], "fsimm", 1.5),
    # study 000 (range/azimuth/elevation): the Singer filter next to the MIE filters
    ("mie_los", "kalman_singer", [], "b_nocomp", 1.25),
    # study 003 (sonar bearings, range while active): the Singer EKF next to the study's plain EKF
    ("sonar_case1", "kalman_sonar", ["scenario.duration=2000"], "ekf", 1.25),
])
def test_one_filter_runs_unchanged_in_three_studies(tmp_path, experiment, kf, extra, reference, tolerance):
    # the tracker and the variant it is compared with, on the runs they would have among all the
    # variants (a run's noise depends on the seed, the stage and the run alone); the others'
    # paired comparisons with the study's reference were half a minute of study 000's job
    out, _ = run_in_process(tmp_path, "run", f"experiment={experiment}", "mc.runs=10", f"+filter@filters.kf={kf}",
                            f"variants=[kf,{reference}]", *extra)
    rmse = out.summary.filter((pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
    values = dict(zip(rmse["variant_key"], rmse["value"]))
    assert np.isfinite(values["kf"]) and values["kf"] < tolerance * values[reference], values
    faults = out.summary.filter((pl.col("series") == "diverged_runs") & (pl.col("variant_key") == "kf"))
    assert faults["value"][0] == 0


def test_on_sonar_reports_it_is_the_studys_plain_ekf():
    """With study 003's model, the tracker's sonar path is the study's plain EKF (another product order)."""
    from hydra import compose, initialize_config_dir

    from filters.mgekf import PlainEKF
    from pipeline.run.config import build
    from tests.helpers.config import CONF
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=sonar_case1", "scenario.duration=2000"])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(3, 1)
    reports = study.track_input(truth, sensor.measure(truth, 1), sensor, 1)
    ours = KalmanTracker(tau=60.0, sigma_m=0.003).run(reports)
    theirs = PlainEKF(tau=60.0, sigma_m=0.003).run(reports)
    np.testing.assert_allclose(ours.state, theirs.state, rtol=0, atol=1e-8)
    np.testing.assert_allclose(ours.covariance, theirs.covariance, rtol=1e-9, atol=1e-8)


def test_the_ca_model_is_the_white_jerk_model_and_tracks_a_constant_acceleration_exactly():
    """motion='ca' (Bar-Shalom et al. 6.2.3): F and Q by hand at T = 2 s; noise-free constant
    acceleration is predicted exactly once the acceleration is estimated."""
    from filters.base import MeasurementSeries
    tracker = KalmanTracker(motion="ca", jerk_density=0.5)
    F, Q = tracker.axis_model(2.0)
    np.testing.assert_allclose(F, [[1, 2, 2], [0, 1, 2], [0, 0, 1]])
    np.testing.assert_allclose(Q, 0.5 * np.array([[32 / 20, 16 / 8, 8 / 6], [16 / 8, 8 / 3, 2], [8 / 6, 2, 2]]))
    t = np.arange(40.0)
    z = np.stack([3.0 * t + 0.5 * 0.8 * t**2, -2.0 * t], axis=-1)[None]          # ax = 0.8, ay = 0 m/s^2
    series = MeasurementSeries(t, z, 1e-6 * np.eye(2), np.ones((1, 40), bool), np.zeros(40, int),
                               state_names=("x", "vx", "ax", "y", "vy", "ay"))
    estimate = tracker.run(series)
    np.testing.assert_allclose(estimate.state[0, -1], [z[0, -1, 0], 3.0 + 0.8 * 39, 0.8, z[0, -1, 1], -2.0, 0.0],
                               atol=1e-3)
    with pytest.raises(ValueError, match="motion: 'cj' is not one of"):
        KalmanTracker(motion="cj")
