"""Study 002's local-track NIS: each local update's nu' S^-1 nu (converted measurement, 2 dof),
its sum over a radar's tracked targets in the BiasRegistrationResult, the per-radar metrics
``nis_s<n>`` with their 95 % chi-square band, the table round trip and the recording's NIS tab."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from filters.bias import (
    BiasRegistrationResult, EXXRegistration, LocalTracking, LocalTracks, PseudoBiasRegistration, RadarReports,
    TrackStart, bias_jacobian, converted_covariance, converted_measurement, cv_transition, dcwna_process_noise,
    nis_over_targets, polar, predict_local, update_local,
)
from pipeline.data import Detections, Truth
from pipeline.studies.async_bias.adapter import BiasRegistrationStudy, bias_metric_units, bias_study_metrics, target_mean_nis
from pipeline.studies.async_bias import codec as bias_codec
from pipeline.evaluation.evaluate import resolved

POSITIONS = np.array([[0.0, 0.0], [10_000.0, 0.0]])
NOISE_STD = np.array([[10.0, 1e-3], [10.0, 1e-3]])
BETA = np.array([20.0, 2e-3, 3e-5, 2e-4])
P0 = np.diag([100.0, 100.0, 25.0, 25.0])
VARIANTS = (LocalTracking, PseudoBiasRegistration, EXXRegistration)


def simulate(runs: int, targets: int, reports: int, bias=np.zeros(4), q: float = 6.0, seed: int = 0):
    """Truth (dt 0.5 s) of CV targets with the filters' DCWNA noise q, seen by two alternating radars
    (radar 2 at 0.5, 1.5, ... s, radar 1 at 1, 2, ... s) with ``bias`` each; the tracks start at
    truth + N(0, P0), as the study's start does, so a zero-bias local filter is consistent."""
    rng = np.random.default_rng(seed)
    dt = 0.5
    start = np.concatenate([rng.uniform([5e3, 5e3], [40e3, 20e3], (targets, 2)), np.full((targets, 2), 20.0)], 1)
    F, L = cv_transition(dt), np.linalg.cholesky(dcwna_process_noise(dt, q))
    X = np.empty((runs, reports + 1, targets, 4))
    X[:, 0] = start
    for k in range(1, reports + 1):
        X[:, k] = X[:, k - 1] @ F.T + rng.standard_normal((runs, targets, 4)) @ L.T
    sensor = np.arange(1, reports + 1) % 2
    r, theta = polar(X[:, 1:, :, :2] - POSITIONS[sensor][None, :, None])
    std = NOISE_STD[sensor][None, :, None]
    z = np.stack([(1 + bias[2]) * r + bias[0] + std[..., 0] * rng.standard_normal(r.shape),
                  (1 + bias[3]) * theta + bias[1] + std[..., 1] * rng.standard_normal(r.shape)], axis=-1)
    start_state = X[:, 0][:, None] + rng.standard_normal((runs, 2, targets, 4)) * np.sqrt(np.diag(P0))
    time = np.arange(1, reports + 1) * dt
    return X, RadarReports(time, sensor, z, POSITIONS, NOISE_STD, TrackStart(0.0, start_state, P0))


# ---- (a) one local update's NIS -----------------------------------------------------------------

def test_local_update_nis_hand_worked():
    """S = H P H' + R^m = diag(5, 12) + diag(4, 4) = diag(9, 16), nu = (3, 4): NIS = 9/9 + 16/16 = 2."""
    P = np.diag([5.0, 12.0, 1.0, 1.0])
    predicted = LocalTracks(np.zeros((1, 1, 4)), P[None, None], np.zeros((1, 1, 4, 4)))
    z = np.array([[[3.0, 4.0]]])
    updated = update_local(predicted, z, 4.0 * np.eye(2)[None, None], np.zeros((1, 1, 2, 4)))
    assert updated.nis.shape == (1, 1)
    assert updated.nis[0, 0] == pytest.approx(2.0, rel=1e-12)


def test_local_update_nis_equals_the_direct_quadratic_form():
    """Batched over runs and targets, any P and R^m: nu' (H P H' + R^m)^-1 nu by a linear solve."""
    rng = np.random.default_rng(4)
    R, T = 3, 5
    A = rng.standard_normal((R, T, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(4)
    B = rng.standard_normal((R, T, 2, 2))
    noise = B @ np.swapaxes(B, -1, -2) + 0.5 * np.eye(2)
    predicted = LocalTracks(rng.standard_normal((R, T, 4)), P, rng.standard_normal((R, T, 4, 4)))
    z = rng.standard_normal((R, T, 2))
    updated = update_local(predicted, z, noise, rng.standard_normal((R, T, 2, 4)))
    nu = z - predicted.state[..., :2]
    S = P[..., :2, :2] + noise
    direct = np.einsum("rti,rti->rt", nu, np.linalg.solve(S, nu[..., None])[..., 0])
    np.testing.assert_allclose(updated.nis, direct, rtol=1e-10)
    total, dof = nis_over_targets(np.where(np.arange(T) == 2, np.nan, updated.nis))   # one target without
    np.testing.assert_allclose(total, direct.sum(-1) - direct[:, 2], rtol=1e-12)
    np.testing.assert_array_equal(dof, np.full(R, 2.0 * (T - 1)))


def test_the_result_carries_each_report_s_nis_summed_over_all_targets():
    """Report 0 (radar 2 at 0.5 s), by hand from the start: predict, B C and R^m at the prediction
    (spec 002), nu' S^-1 nu of every target (not only the kept ones), summed: chi2 of 2T dof."""
    _, reports = simulate(runs=3, targets=4, reports=6, bias=BETA)
    result = LocalTracking(output_targets=[2]).run(reports)
    i = int(reports.sensor[0])
    start = LocalTracks(reports.start.state[:, i], np.broadcast_to(P0, (3, 4, 4, 4)).copy(), np.zeros((3, 4, 4, 4)))
    predicted = predict_local(start, reports.time[0] - reports.start.time, 6.0)
    B, _ = bias_jacobian(*polar(predicted.state[..., :2] - POSITIONS[i]))
    S = predicted.covariance[..., :2, :2] + converted_covariance(B, NOISE_STD[i])
    nu = converted_measurement(reports.z[:, 0], POSITIONS[i]) - predicted.state[..., :2]
    direct = np.einsum("rti,rti->rt", nu, np.linalg.solve(S, nu[..., None])[..., 0]).sum(-1)
    np.testing.assert_allclose(result.nis[:, 0], direct, rtol=1e-10)
    assert result.nis.shape == (3, 6) and np.isfinite(result.nis).all()
    np.testing.assert_array_equal(result.nis_dof, 8.0)


def test_two_point_start_reports_have_no_nis():
    _, reports = simulate(runs=2, targets=3, reports=8)
    result = LocalTracking(start="two_point", output_targets=[1]).run(reports)
    assert np.isnan(result.nis[:, :4]).all() and (result.nis_dof[:, :4] == 0).all()    # each radar's 2 first
    assert np.isfinite(result.nis[:, 4:]).all() and (result.nis_dof[:, 4:] == 6).all()


def test_nis_is_the_same_in_every_variant_and_leaves_the_estimates_alone():
    """The local tracks do not depend on the bias estimate, so neither does their NIS."""
    _, reports = simulate(runs=2, targets=3, reports=12, bias=BETA)
    results = [cls(output_targets=[1, 3]).run(reports) for cls in VARIANTS]
    for other in results[1:]:
        np.testing.assert_array_equal(other.nis, results[0].nis)
        np.testing.assert_array_equal(other.nis_dof, results[0].nis_dof)
        np.testing.assert_array_equal(other.track_state, results[0].track_state)


# ---- the band of the per-target mean ------------------------------------------------------------

def test_target_mean_band_is_the_chi2_band_of_all_runs_and_targets():
    """N runs x T targets of chi2(2): the mean has the band chi2.ppf(., 2 N T) / (N T)."""
    N, T = 40, 6
    rng = np.random.default_rng(1)
    sums = rng.chisquare(2 * T, size=(N, 3))
    band = target_mean_nis("nis_s1", sums, np.full((N, 3), 2.0 * T))
    np.testing.assert_allclose(band["nis_s1"], sums.mean(0) / T)
    np.testing.assert_allclose(band["nis_s1_lower"], chi2.ppf(0.025, 2 * N * T) / (N * T))
    np.testing.assert_allclose(band["nis_s1_upper"], chi2.ppf(0.975, 2 * N * T) / (N * T))
    sums[:, 1] = np.nan                                              # a step no run has a value at
    assert np.isnan(target_mean_nis("n", sums, np.where(np.isnan(sums), 0.0, 2.0 * T))["n_upper"][1])


# ---- (b) a zero-bias local filter is consistent ---------------------------------------------------

IN_BAND_RATE = 0.85          # measured 0.95 (seed 0; 0.92-0.99 over 20 seeds) for the nominal 0.95


def test_zero_bias_nis_lies_in_its_band_at_most_reports():
    """No bias: the local filter's model (CV, q, R^m) matches the truth, so the NIS averaged over 8
    targets and 100 runs lies in its 95 % band at about 95 % of each radar's 80 reports."""
    X, reports = simulate(runs=100, targets=8, reports=160, seed=0)
    result = LocalTracking(output_targets=[1]).run(reports)
    truth = Truth(np.arange(161) * 0.5, X, ("x", "y", "vx", "vy"))
    metrics = resolved(bias_study_metrics(truth, result, np.zeros(8)))
    rates = []
    for n in (1, 2):
        steps = np.nonzero(np.isfinite(metrics[f"nis_s{n}"]))[0]
        assert steps.size == 80
        value, lower, upper = (metrics[f"nis_s{n}{part}"][steps] for part in ("", "_lower", "_upper"))
        np.testing.assert_allclose(lower, chi2.ppf(0.025, 1600) / 800)
        rates.append(np.mean((lower <= value) & (value <= upper)))
        assert np.mean(value) == pytest.approx(2.0, abs=0.05)
    assert min(rates) >= IN_BAND_RATE, rates


# ---- metrics, table round trip, chunks ---------------------------------------------------------------

def _study_case(runs=3, targets=4, reports=20):
    X, reports_ = simulate(runs=runs, targets=targets, reports=reports, bias=BETA, seed=2)
    truth = Truth(np.arange(reports + 1) * 0.5, X, ("x", "y", "vx", "vy"))
    return truth, reports_


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda c: c.__name__)
def test_every_variant_has_per_radar_nis_metrics_with_units(variant):
    truth, reports = _study_case()
    metrics = resolved(bias_study_metrics(truth, variant(output_targets=[1, 4]).run(reports), np.tile(BETA, 2)))
    for n in (1, 2):
        mine = np.nonzero(reports.sensor == n - 1)[0] + 1                 # truth steps of radar n's reports
        for part in ("", "_lower", "_upper"):
            values = metrics[f"nis_s{n}{part}"]
            assert np.isfinite(values[mine]).all() and np.isnan(np.delete(values, mine)).all()
    units = bias_metric_units(metrics)
    assert "expected 2" in units["nis_s1"] and "band" in units["nis_s2_upper"]


def test_nis_round_trips_through_the_estimate_table_and_chunks():
    truth, reports = _study_case()
    estimator = PseudoBiasRegistration(output_targets=[1, 4])
    whole = estimator.run(reports)
    chunks = BiasRegistrationResult.concat_runs([estimator.run(reports.select([0, 1])),
                                                 estimator.run(reports.select([2]))])
    df, meta = BiasRegistrationStudy().estimate_to_frame(whole, truth)
    back = bias_codec.bias_estimates_from_frame(df, {k: str(v) for k, v in meta.items()})
    for got in (chunks, back):
        for name in ("nis", "nis_dof", "bias", "track_state", "compensated_covariance"):
            np.testing.assert_array_equal(getattr(got, name), getattr(whole, name), err_msg=name)
    assert df.filter(df["target"] >= 0)["nis"].null_count() == df.filter(df["target"] >= 0).height
    old = bias_codec.bias_estimates_from_frame(df.drop("nis", "nis_dof"), meta)   # a table from before
    assert old.nis is None and "nis_s1" not in bias_study_metrics(truth, old, np.tile(BETA, 2))


# ---- recording: the NIS tab -----------------------------------------------------------------------------

def test_recording_has_a_nis_tab_with_each_variant_and_its_band(tmp_path: Path):
    from rerun.chunk import RrdReader

    from pipeline.studies.async_bias.recording import write_bias_recording
    from pipeline.evaluation.evaluate import metrics_frame
    from tests.helpers.rrd_reading import entity_index, read_chunks, temporal

    truth, reports = _study_case(runs=2, targets=3, reports=10)
    keys = ("local", "proposed", "exx")
    estimates = {key: cls(output_targets=[1]).run(reports) for key, cls in zip(keys, VARIANTS)}
    network = SimpleNamespace(names=("radar1", "radar2"), positions=POSITIONS, noise_std=NOISE_STD,
                              biases=np.tile(BETA, (2, 1)), true_bias_vector=lambda: np.tile(BETA, 2))
    metrics = metrics_frame(truth.time, {k: (k, bias_study_metrics(truth, est, np.tile(BETA, 2)))
                                         for k, est in estimates.items()}, 2)
    K, T = reports.z.shape[1:3]
    detections = Detections(reports.time, reports.sensor, reports.z, np.zeros((2, K, T, 2, 2)),
                            np.broadcast_to(np.arange(T), (2, K, T)).copy(), np.ones((2, K, T), dtype=bool),
                            ("range", "azimuth"), ("m", "rad"))
    path = tmp_path / "nis.rrd"
    write_bias_recording(path, experiment="nis", truth=truth, detections=detections, estimates=estimates,
                         display_names={k: k for k in keys}, metrics=metrics, record_runs=[0], sensor=network)
    entities = entity_index(read_chunks(path))
    for key in keys:
        for n in (1, 2):
            temporal(entities, f"/metrics/nis_s{n}/{key}", "Scalars:scalars")
            for side in ("lower", "upper"):
                temporal(entities, f"/metrics/nis_s{n}/{key}_chi2_{side}", "Scalars:scalars")
    reader = RrdReader(path)
    names, origins = set(), set()
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        for column, into in (("ContainerBlueprint:display_name", names), ("ViewBlueprint:display_name", names),
                             ("ViewBlueprint:space_origin", origins)):
            if column in batch.schema.names:
                into.update(str(v[0]) for v in batch.column(column).to_pylist() if v)
    assert "local-track NIS" in names
    assert {"/metrics/nis_s1", "/metrics/nis_s2"} <= origins


# ---- (c) through the runner ---------------------------------------------------------------------------

def test_a_tiny_async_bias_run_has_nis_metrics_for_every_variant(tmp_path: Path):
    from tests.helpers.runs import run_study

    out, _ = run_study(tmp_path, "nis", "scenario.duration=10", "mc.runs=2", experiment="async_bias")
    metrics = out.metrics
    for key in ("local", "proposed", "exx"):
        have = set(metrics.filter(metrics["variant_key"] == key)["series"].to_list())
        assert {"nis_s1", "nis_s1_lower", "nis_s1_upper", "nis_s2", "nis_s2_lower", "nis_s2_upper"} <= have, key
