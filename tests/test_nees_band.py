"""The run-averaged NEES and its chi-square band: a correctly tuned Kalman filter stays inside
the 95 % band at about the stated rate, a mistuned one does not; the band reaches the metrics
and the recording."""

from __future__ import annotations

import numpy as np

from filters.bias import cv_transition, dcwna_process_noise
from filters.kalman import predict, update
from pipeline.evaluation.evaluate import consistency_metrics


def nees_of_a_kalman_filter(q_scale: float, runs: int = 200, steps: int = 100, seed: int = 3) -> np.ndarray:
    """(runs, steps) NEES of a 1-D-per-axis CV Kalman filter on data from the same model, with the
    filter's process noise scaled by q_scale (1 = correctly tuned)."""
    rng = np.random.default_rng(seed)
    F, Q = cv_transition(1.0), dcwna_process_noise(1.0, 0.5)
    H, R = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]), 25.0 * np.eye(2)
    L = np.linalg.cholesky(Q)
    x_true = np.zeros((runs, 4))
    x, P = x_true + rng.standard_normal((runs, 4)) * 10.0, np.broadcast_to(100.0 * np.eye(4), (runs, 4, 4)).copy()
    out = np.empty((runs, steps))
    for k in range(steps):
        x_true = x_true @ F.T + rng.standard_normal((runs, 4)) @ L.T
        z = x_true @ H.T + rng.standard_normal((runs, 2)) * 5.0
        x, P = predict(x, P, F, q_scale * Q)
        x, P, _ = update(x, P, z, H, R)
        e = x - x_true
        out[:, k] = np.einsum("ri,ri->r", e, np.linalg.solve(P, e[..., None])[..., 0])
    return out


def inside(band: dict) -> float:
    mean, lower, upper = band["nees"], band["nees_lower"], band["nees_upper"]
    return float(np.mean((mean >= lower) & (mean <= upper)))


def test_a_tuned_kalman_filter_stays_inside_the_band_at_about_the_stated_rate():
    assert 0.88 <= inside(consistency_metrics("nees", nees_of_a_kalman_filter(1.0), 4)) <= 1.0


def test_a_mistuned_kalman_filter_leaves_the_band():
    assert inside(consistency_metrics("nees", nees_of_a_kalman_filter(0.01), 4)) < 0.3


def test_the_band_handles_missing_runs_and_varying_dof_as_worked_by_hand():
    from scipy.stats import chi2
    values = np.array([[1.0, np.nan], [3.0, 2.0], [np.nan, 4.0]])
    dof = np.array([[1, 2], [1, 2], [1, 2]])
    band = consistency_metrics("nis", values, dof)
    np.testing.assert_allclose(band["nis"], [2.0, 3.0])                       # means over valid runs
    np.testing.assert_allclose(band["nis_lower"], [chi2.ppf(0.025, 2) / 2, chi2.ppf(0.025, 4) / 2])
    np.testing.assert_allclose(band["nis_upper"], [chi2.ppf(0.975, 2) / 2, chi2.ppf(0.975, 4) / 2])


def test_the_band_is_in_the_metrics_and_beside_the_nees_in_the_recording(tmp_path):
    from hydra import compose, initialize_config_dir

    from pipeline.run.runner import RunContext, run_experiment
    from tests.helpers.config import CONF
    from tests.helpers.rrd_reading import entity_index, read_chunks

    overrides = ["mc.runs=3", "scenario.steps=20", "variants=[fsimm]"]
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"paths.artifacts={tmp_path}", *overrides])
    ctx = RunContext(tmp_path / "runs" / "band", tmp_path, overrides)
    outcome = run_experiment(cfg, ctx)
    metrics = set(outcome.metrics["series"].unique())
    assert {"nees", "nees_lower", "nees_upper"} <= metrics
    entities = entity_index(read_chunks(ctx.run_dir / "recording.rrd"))
    assert {"/metrics/nees/fsimm", "/metrics/nees/fsimm_chi2_lower", "/metrics/nees/fsimm_chi2_upper"} <= set(entities)
