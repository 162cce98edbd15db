"""Study 004's estimation limits: the NIS of the EKF and the particle filters, and the PCRLB of
the 20-state sonobuoy model (true mode sequence known, measurement origin ignored)."""

from __future__ import annotations

import numpy as np
import polars as pl
from hydra import compose, initialize_config_dir

from filters.particle.reference import BearingLikelihood, SonobuoyModel, _masked_nis, bearings
from pipeline.run.config import build
from tests.helpers.config import CONF
from tests.helpers.runs import SONOBUOY_SHORT, run_study


def test_masked_nis_skips_missed_components_as_worked_by_hand():
    residual = np.array([[0.2, np.nan, -0.1]])
    S = np.array([[[0.04, 0.5, 0.0], [0.5, 9.0, 0.5], [0.0, 0.5, 0.01]]])      # the NaN row's entries are ignored
    nis, dof = _masked_nis(residual, S)
    np.testing.assert_allclose(nis, [0.2**2 / 0.04 + 0.1**2 / 0.01])
    np.testing.assert_array_equal(dof, [2.0])
    nis, dof = _masked_nis(np.full((1, 3), np.nan), S)
    assert np.isnan(nis[0]) and dof[0] == 0


def test_particle_nis_of_a_point_cloud_is_the_residual_over_the_noise_variance():
    """All particles at one state: the predicted bearings have no spread, so S is the noise alone
    (the clutter mixture's variance)."""
    state = np.concatenate([[-6000.0, 3000.0, 5.0, -1.0], np.tile([2000.0, 2000.0, 0.2, 0.1], 4)])
    state[[4, 5, 8, 9, 12, 13, 16, 17]] = [-2000, -2000, 2000, -2000, 2000, 2000, -2000, 2000]
    X = np.broadcast_to(state, (1, 50, 20)).copy()
    std, clutter_std, pc = np.full(8, 0.1), np.full(8, 0.3), 0.25
    model = SonobuoyModel(0.001, 0.005, 0.0005, "standard", BearingLikelihood(std, clutter_std, pc),
                          np.array([0.0, -8000.0]))
    offset = np.array([0.05, -0.1, 0.0, 0.2, 0.01, 0.0, np.nan, -0.03])
    z = bearings(state, np.array([0.0, -8000.0]))[None] + offset
    nis, dof = model.innovation_nis(model.predicted_measurements(X), np.zeros((1, 50)), z)
    variance = (1 - pc) * 0.1**2 + pc * 0.3**2
    np.testing.assert_allclose(nis, [np.nansum(offset**2) / variance], rtol=1e-5)
    assert dof[0] == 7


def bound_study(experiment: str):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment={experiment}"])
    return build(cfg.study, "study"), build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors")


def test_the_bound_follows_the_true_turn_and_shrinks_with_information():
    study, scenario, sensor = bound_study("sonobuoy_case2")
    truth = scenario.generate(3, 1)
    clairvoyant = study.position_bound(truth, sensor, 0.0)
    model = study.position_bound(truth, sensor, study.bound_model_target_sigma)
    assert clairvoyant.shape == truth.time.shape and np.all(np.isfinite(clairvoyant)) and np.all(clairvoyant > 0)
    np.testing.assert_allclose(clairvoyant[0], np.hypot(*study.target_std[:2]))          # the prior at scan 0
    assert clairvoyant[-1] < 0.1 * clairvoyant[0]                                       # bearings pin it down
    assert np.all(model >= clairvoyant - 1e-9)                                          # more noise, higher bound
    # the bound's target transition is the truth's: a turn it did not know would not bound this truth
    from filters.particle import ct_transition
    target = truth.state[0, :, 0, :4]
    heading = np.arctan2(target[:, 2], target[:, 3])
    dt = float(truth.time[1] - truth.time[0])
    omega = -np.angle(np.exp(1j * np.diff(heading))) / dt
    assert np.any(np.abs(omega) > 1e-6)                                                 # case 2 turns right
    predicted = np.stack([ct_transition(w, dt) @ x for w, x in zip(omega, target[:-1])])
    straddle = np.abs(np.linalg.norm(predicted - target[1:], axis=-1)) > 1e-6
    assert straddle.sum() <= 1                                                          # only the step the turn starts in
    np.testing.assert_allclose(predicted[~straddle], target[1:][~straddle], atol=1e-6)


def test_every_variant_reports_nis_and_rmse_over_the_bound(tmp_path):
    from tests.helpers.rrd_reading import entity_index, read_chunks

    out, ctx = run_study(tmp_path, "limits", *SONOBUOY_SHORT, experiment="sonobuoy_case2b", record=True)
    metrics = out.metrics
    entities = set(entity_index(read_chunks(ctx.run_dir / "recording.rrd")))
    for key in ("ammpf", "sir_mm", "ekf"):
        mine = metrics.filter(pl.col("variant_key") == key)
        have = set(mine["series"])
        assert {"nis", "nis_lower", "nis_upper", "position_bound", "position_bound_model",
                "position_rmse_over_bound"} <= have, (key, sorted(have))
        nis = mine.filter((pl.col("series") == "nis") & (pl.col("step") >= 1))["value"]
        assert nis.is_finite().all() and (nis > 0).all()
        assert {f"/metrics/nis/{key}", f"/metrics/nis/{key}_chi2_upper", f"/metrics/position_rmse_over_bound/{key}",
                f"/metrics/nees_position/{key}_chi2_lower"} <= entities, key
    assert metrics["variant_key"].n_unique() >= 2


def test_the_bound_is_computed_once_per_truth_not_once_per_variant(monkeypatch):
    study, scenario, sensor = bound_study("sonobuoy_case1")
    truth = scenario.generate(2, 1)
    calls = []
    original = type(study)._compute_bound
    monkeypatch.setattr(type(study), "_compute_bound", lambda self, *a: calls.append(a[2]) or original(self, *a))
    first = study.position_bound(truth, sensor, 0.0)
    assert study.position_bound(truth, sensor, 0.0) is first and calls == [0.0]
    study.position_bound(truth, sensor, 0.005)
    other = scenario.generate(2, 2)                       # another truth: computed again, and for it alone
    study.position_bound(other, sensor, 0.0)
    assert calls == [0.0, 0.005, 0.0]
