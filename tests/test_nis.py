"""NIS of the IMM family (study 001) and the input-estimation filters (study 000): hand-worked
values, the consistency rate of a correctly tuned filter, and the metrics every variant carries."""

from __future__ import annotations

import numpy as np
import pytest

from filters.base import MeasurementSeries
from filters.imm import FSIMM, ModeSet, combined_prediction_nis
from filters.models import AccelerationModelSet
from pipeline.evaluation.evaluate import nis_metrics


def one_slot(x, P, log_predicted=0.0):
    R, n = x.shape
    return ModeSet(np.zeros((R, 1), dtype=int), x[:, None], P[:, None], np.full((R, 1), log_predicted),
                   np.zeros((R, 1)), np.zeros((R, 1)), x[:, None], P[:, None])


def test_the_combined_prediction_nis_of_one_model_is_the_kalman_nis_worked_by_hand():
    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    x = np.array([[10.0, 1.0, -5.0, 0.0]])
    P = np.diag([4.0, 1.0, 9.0, 1.0])[None]
    z = np.array([[13.0, -1.0]])
    # S = diag(4 + 1, 9 + 3), nu = (3, 4): NIS = 9/5 + 16/12
    nis = combined_prediction_nis(one_slot(x, P), z, np.diag([1.0, 3.0]), H)
    np.testing.assert_allclose(nis, [9 / 5 + 16 / 12])


def test_two_models_are_moment_matched_with_the_predicted_probabilities():
    """Two slots at x1, x2 with c = (0.25, 0.75): mean 0.25 x1 + 0.75 x2, spread c1 c2 (x1 - x2)^2."""
    H = np.array([[1.0, 0.0]])
    x1, x2 = np.array([0.0, 0.0]), np.array([4.0, 0.0])
    s = ModeSet(np.array([[0, 1]]), np.zeros((1, 2, 2)), np.zeros((1, 2, 2, 2)), np.log([[0.25, 0.75]]) + 7.0,
                np.zeros((1, 2)), np.zeros((1, 2)), np.stack([x1, x2])[None], np.broadcast_to(np.eye(2), (1, 2, 2, 2)))
    z = np.array([[5.0]])
    mean, spread = 3.0, 0.25 * 0.75 * 16.0
    nis = combined_prediction_nis(s, z, np.array([[2.0]]), H, detected=np.array([True]))
    np.testing.assert_allclose(nis, [(5.0 - mean) ** 2 / (1.0 + spread + 2.0)])
    assert np.isnan(combined_prediction_nis(s, z, np.array([[2.0]]), H, detected=np.array([False])))[0]


def imm_of_identical_models(q: float) -> AccelerationModelSet:
    return AccelerationModelSet.from_config({"a": [0, 0], "b": [0, 0]}, [[0.9, 0.1], [0.1, 0.9]],
                                            process_noise_std=q)


def test_an_imm_whose_models_match_the_truth_has_its_nis_inside_the_band_at_the_stated_rate():
    """Two identical models = one Kalman filter: on data drawn from that model the run-averaged
    NIS lies inside its 95 % band at about 95 % of the scans; with the process noise 10x too
    small it does not."""
    rng = np.random.default_rng(11)
    runs, steps, q, noise = 300, 80, 2.0, 20.0
    models = imm_of_identical_models(q)
    F, G, H = models.transition, models.input_gain, models.measurement_matrix
    x = np.tile([0.0, 30.0, 0.0, -10.0], (runs, 1))
    z = np.empty((runs, steps, 2))
    for k in range(steps):
        if k:
            x = x @ F.T + (rng.standard_normal((runs, 2)) * q) @ G.T
        z[:, k] = x @ H.T + rng.standard_normal((runs, 2)) * noise
    series = MeasurementSeries(np.arange(steps, dtype=float), z, noise**2 * np.eye(2), np.ones((runs, steps), bool),
                               np.zeros(steps, dtype=int))
    rates = {}
    for name, q_filter in (("tuned", q), ("too_small", q / 10)):
        estimate = FSIMM(imm_of_identical_models(q_filter), initial_model="a").run(series)
        assert estimate.extras["nis"].shape == (runs, steps)
        assert np.isnan(estimate.extras["nis"][:, :2]).all()        # the two-point start has no innovation
        band = nis_metrics(estimate.extras)
        later = slice(10, None)                                     # after the two-point start settles
        rates[name] = float(np.mean((band["nis"][later] >= band["nis_lower"][later])
                                    & (band["nis"][later] <= band["nis_upper"][later])))
    assert rates["tuned"] >= 0.85, rates
    assert rates["too_small"] <= 0.3, rates


def test_a_nis_without_its_dof_is_refused():
    with pytest.raises(ValueError, match="nis_dof"):
        nis_metrics({"nis": np.ones((2, 3))})


@pytest.mark.parametrize("experiment", ["ao_vsimm_s1", "mie_los"])
def test_every_variant_of_studies_001_and_000_has_nis_with_its_band_in_the_metrics(tmp_path, experiment):
    import polars as pl
    from hydra import compose, initialize_config_dir

    from pipeline.run.runner import RunContext, run_experiment
    from tests.helpers.config import CONF
    from tests.helpers.rrd_reading import entity_index, read_chunks

    overrides = [f"experiment={experiment}", "mc.runs=4", f"paths.artifacts={tmp_path}"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    ctx = RunContext(tmp_path / "runs" / "nis", tmp_path, overrides)
    run_experiment(cfg, ctx)
    metrics = pl.read_parquet(ctx.run_dir / "metrics.parquet")
    entities = set(entity_index(read_chunks(ctx.run_dir / "recording.rrd")))
    for key in cfg.filters:
        have = set(metrics.filter(pl.col("variant_key") == key)["series"].unique())
        assert {"nis", "nis_lower", "nis_upper"} <= have, (key, sorted(have))
        assert {f"/metrics/nis/{key}", f"/metrics/nis/{key}_chi2_lower", f"/metrics/nis/{key}_chi2_upper"} <= entities
    nis = metrics.filter(pl.col("series") == "nis")
    assert nis.filter(pl.col("step") >= 2)["value"].is_finite().all()
    assert (nis.filter(pl.col("step") >= 2)["value"] > 0).all()
