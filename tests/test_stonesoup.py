"""Stone Soup inside the pipeline (issue 21; pipeline/stonesoup, the [stonesoup] extra).

- its Kalman filter equals ours with the same model (study 001's positions, 1e-9 relative), and its
  EKF and UKF on study 000's radar give the position RMSE of our converted-measurement Kalman
  filter within Monte Carlo error (the summary's 95 % intervals);
- the variant's results do not depend on the number of worker processes or the chunking of runs
  (a particle filter too);
- its simulators are the scenario and measure stages, cached like any stage;
- a stored run loads as Stone Soup objects, on which its OSPA and GOSPA run (study 002);
- the framework's compatibility check reads a variant's kind off its measurement model's type.

Skipped without the extra, failed in CI (.ci/run sets MTT_REQUIRE_STONESOUP=1).
"""

from __future__ import annotations

import dataclasses
import functools
import logging

import numpy as np
import polars as pl
import pytest

from tests.helpers.extras import require_extra

require_extra("stonesoup", "stonesoup")

from pipeline.errors import ConfigError  # noqa: E402
from pipeline.results.report import ReportSpec, evaluate_target, load_run as load_tables  # noqa: E402
from pipeline.storage.store import read_table  # noqa: E402
from tests.helpers.runs import run_in_process  # noqa: E402


def _estimates(run_dir, key):
    from pipeline.storage import schemas
    return schemas.estimate_from_frame(*read_table(run_dir / "estimates" / f"{key}.parquet"))


def _targets(run_dir):
    tables = load_tables(run_dir)
    return {t.id: evaluate_target(tables, t) for t in ReportSpec.from_config(tables.config["report"]).targets}


def test_stonesoup_kalman_filter_equals_ours_on_study_001(tmp_path):
    """The same CV model (q = 100 m^2/s^3) and two-point start: the same estimates to 1e-9 relative."""
    _, ctx = run_in_process(tmp_path, "kf", "experiment=stonesoup_kf", "mc.runs=4", "scenario.steps=60")
    ours, theirs = _estimates(ctx.run_dir, "kf"), _estimates(ctx.run_dir, "ss_kf")
    assert np.array_equal(np.isnan(ours.state), np.isnan(theirs.state))      # NaN before the start (scan 0)
    assert np.isnan(theirs.state[:, 0]).all() and np.isfinite(theirs.state[:, 1:]).all()
    started = np.isfinite(ours.state)
    scale = np.abs(ours.state[started]).max()
    relative = np.abs(theirs.state[started] - ours.state[started]).max() / scale
    P_ours, P_theirs = ours.covariance[:, 1:], theirs.covariance[:, 1:]
    relative_P = np.abs(P_theirs - P_ours).max() / np.abs(P_ours).max()
    print(f"Stone Soup KF vs ours: state {relative:.1e}, covariance {relative_P:.1e} relative")
    assert relative < 1e-9 and relative_P < 1e-9
    np.testing.assert_allclose(theirs.extras["nis"], ours.extras["nis"], rtol=1e-9, atol=1e-12)
    results = _targets(ctx.run_dir)
    assert {k: r.verdict for k, r in results.items()} == {"same_position_rmse": "PASS", "same_nees": "PASS"}


def test_stonesoup_ekf_and_ukf_agree_with_our_converted_kalman_filter_on_study_000(tmp_path):
    """CartesianToElevationBearingRange with an EKF and a UKF against converted measurements, the same CV
    model: each position RMSE lies inside the others' 95 % intervals over the runs."""
    _, ctx = run_in_process(tmp_path, "radar", "experiment=stonesoup_radar", "mc.runs=8")
    summary = pl.read_parquet(ctx.run_dir / "summary.parquet").filter(
        (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
    rows = {r["variant_key"]: r for r in summary.iter_rows(named=True)}
    kf = rows["kf"]
    for key in ("ss_ekf", "ss_ukf"):
        row = rows[key]
        print(f"{key}: position RMSE {row['value']:.3f} [{row['ci_low']:.3f}, {row['ci_high']:.3f}] m; "
              f"KF {kf['value']:.3f} [{kf['ci_low']:.3f}, {kf['ci_high']:.3f}] m")
        assert kf["ci_low"] <= row["value"] <= kf["ci_high"]
        assert row["ci_low"] <= kf["value"] <= row["ci_high"]
    comparisons = pl.read_parquet(ctx.run_dir / "comparisons.parquet").filter(
        (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
    for row in comparisons.iter_rows(named=True):
        print(f"{row['variant_key']} - kf paired: {row['difference']:+.4f} [{row['difference_low']:+.4f}, "
              f"{row['difference_high']:+.4f}] m")
        # the paired difference is far inside the spread of either filter's RMSE over the runs
        assert abs(row["difference"]) < (kf["ci_high"] - kf["ci_low"]) / 2
    results = _targets(ctx.run_dir)
    assert {k: r.verdict for k, r in results.items()} == {"ekf_as_converted_kf": "PASS", "ukf_as_converted_kf": "PASS"}
    # the estimate is in the truth's 9-state order, accelerations NaN (a CV filter has none)
    estimate = _estimates(ctx.run_dir, "ss_ekf")
    assert estimate.state.shape[-1] == 9 and np.isnan(estimate.state[:, 1:, 6:]).all()
    assert np.isfinite(estimate.state[:, 1:, :6]).all()


def _variant(kind: str, workers: int, seed: int = 0):
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.resampler.particle import SystematicResampler
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.particle import ParticleUpdater

    from pipeline.stonesoup.variant import StoneSoupFilter
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(100.0), ConstantVelocity(100.0)])
    measurement = LinearGaussian(4, (0, 2), np.eye(2))
    if kind == "kf":
        return StoneSoupFilter(functools.partial(KalmanPredictor), functools.partial(KalmanUpdater), transition,
                               measurement, workers=workers)
    return StoneSoupFilter(functools.partial(ParticlePredictor),
                           functools.partial(ParticleUpdater, resampler=SystematicResampler()), transition,
                           measurement, workers=workers, particles=200, seed=seed)


def test_the_default_workers_are_the_processors_this_job_may_run_on(monkeypatch):
    """A job pinned to one core (taskset, a batch system's cgroup) filters in this process: the
    default pool counted the machine's CPUs (os.cpu_count), so it started 8 workers on one core."""
    monkeypatch.setattr("os.cpu_count", lambda: 8)
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0}, raising=False)
    variant = _variant("kf", workers=None)
    assert variant.workers_for(runs=100, scans=1000) == 1
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    assert variant.workers_for(runs=100, scans=1000) == 3
    assert variant.workers_for(runs=2, scans=100_000) == 2          # never more than the runs


def test_the_estimates_do_not_depend_on_the_workers_or_the_chunks():
    """Run r's result depends on run r alone: 1 or 2 worker processes, all runs or a chunk of them; a particle
    filter's draws are seeded per run (its index in the whole Monte Carlo), so it too."""
    from tests.helpers.filter_inputs import measurements, scenario
    truth = scenario("ao_vsimm_s1", steps=12).generate(4, 1)
    series = dataclasses.replace(measurements(truth, 1), state_names=("x", "vx", "y", "vy"))
    for kind in ("kf", "pf"):
        alone = _variant(kind, workers=1).run(series)
        shared = _variant(kind, workers=2).run(series)
        chunk = _variant(kind, workers=1).run(series.select([2, 3]))
        assert np.array_equal(alone.state, shared.state, equal_nan=True), kind
        assert np.array_equal(alone.covariance, shared.covariance, equal_nan=True), kind
        assert np.array_equal(alone.state[2:], chunk.state, equal_nan=True), kind
    other_seed = _variant("pf", workers=1, seed=1).run(series)
    assert not np.array_equal(alone.state, other_seed.state, equal_nan=True)
    # the particle filter (200 particles) follows the Kalman filter's estimate within its sampling error
    kf = _variant("kf", workers=1).run(series)
    gap = np.abs(alone.state - kf.state)[:, 1:][..., [0, 2]]
    assert np.median(gap) < 5.0 and gap.max() < 50.0


def test_stonesoup_simulators_are_cached_stages(tmp_path, caplog):
    """A Stone Soup ground-truth and detection simulator write our truth and detections tables; a second
    run re-uses them from the cache; run r depends only on (seed, r)."""
    args = ("experiment=stonesoup_simulated", "scenario.steps=30", "filters.ss_kf.workers=1")
    with caplog.at_level(logging.INFO, logger="pipeline"):
        _, first = run_in_process(tmp_path, "first", "mc.runs=3", *args)
        caplog.clear()
        _, again = run_in_process(tmp_path, "again", "mc.runs=3", *args)
    assert "[scenario] reused cached" in caplog.text and "[measure] reused cached" in caplog.text
    truth = pl.read_parquet(first.run_dir / "truth.parquet")
    assert truth.height == 3 * 31 and truth.schema["x"] == pl.Array(pl.Float64, 4)
    assert pl.read_parquet(again.run_dir / "truth.parquet").equals(truth)
    x = np.asarray(truth.filter(pl.col("run") == 0)["x"].to_list())
    assert np.allclose(x[0], [20000.0, 340.0, 20000.0, 340.0])
    assert np.allclose(np.diff(x[:, 0]), (x[1:, 1] + x[:-1, 1]) / 2, atol=1.0)      # nearly constant velocity
    detections = pl.read_parquet(first.run_dir / "detections.parquet")
    target = detections.filter(pl.col("target") == 0)
    assert target["detected"].all() and target.height == 3 * 31
    assert detections.filter(pl.col("clutter")).height > 0                           # 0.5 clutter per scan
    z = np.asarray(target.filter(pl.col("run") == 0).sort("step")["z"].to_list())
    assert np.abs(z - x[:, [0, 2]]).max() < 5 * 20.0
    # a bigger job's first runs are the same runs
    _, bigger = run_in_process(tmp_path, "bigger", "mc.runs=4", *args)
    assert pl.read_parquet(bigger.run_dir / "truth.parquet").filter(pl.col("run") < 3).equals(truth)
    assert np.array_equal(_estimates(bigger.run_dir, "ss_kf").state[:3], _estimates(first.run_dir, "ss_kf").state,
                          equal_nan=True)


def test_a_stored_study_002_run_loads_as_stonesoup_objects_for_ospa_and_gospa(tmp_path):
    """load_run: ground-truth paths, detections with their measurement models, tracks; Stone Soup's OSPA
    and GOSPA on them equal the distances computed from our tables."""
    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
    from stonesoup.types.detection import TrueDetection

    from pipeline.stonesoup.convert import seconds
    from pipeline.stonesoup.load import load_run
    _, ctx = run_in_process(tmp_path, "bias", "experiment=async_bias", "mc.runs=2", "scenario.duration=10")
    loaded = load_run(ctx.run_dir, run=1, state_column="x_compensated")
    assert loaded.state_names == ("x", "y", "vx", "vy") and loaded.measurement_names == ("range", "azimuth")
    assert len(loaded.truths) == 32 and set(loaded.tracks) == {"exx", "local", "proposed"}
    assert loaded.names["local"] == "local (no bias handling)"
    detections = pl.read_parquet(ctx.run_dir / "detections.parquet").filter((pl.col("run") == 1) & pl.col("detected"))
    assert len(loaded.detections) == detections.height and len(loaded.scans) == detections["step"].n_unique()
    # each detection's measurement model predicts its (biased, noisy) measurement from its target's truth
    for detection in list(loaded.detections)[:50]:
        assert isinstance(detection, TrueDetection)
        truth_state = next(s for s in detection.groundtruth_path if s.timestamp == detection.timestamp)
        predicted = detection.measurement_model.function(truth_state)
        residual = np.asarray(detection.state_vector - predicted, dtype=float).ravel()   # (bearing, range)
        assert abs(residual[0]) < 0.05 and abs(residual[1]) < 200.0
    sensor = {d.metadata["sensor"]: d.measurement_model.translation_offset.ravel() for d in loaded.detections}
    assert np.allclose(sensor[0], [0.0, 0.0]) and np.allclose(sensor[1], [10000.0, 0.0])

    # OSPA (p = 2) and GOSPA (alpha = 2, p = 2) with a cut-off beyond every error: the RMS and the root of
    # the summed squared position errors over the tracked targets at each report time
    tracked = {int(t.id.rsplit(" ", 1)[1]) for t in loaded.tracks["proposed"]}
    truths = {p for p in loaded.truths if p[0].metadata["target"] in tracked}
    mapping = Euclidean(mapping=loaded.position_mapping)
    ospa = OSPAMetric(c=1e6, p=2, measure=mapping)
    gospa = GOSPAMetric(c=1e6, p=2, measure=mapping)
    tracks = loaded.tracks["proposed"]
    ospa_values = ospa.compute_over_time(*ospa.extract_states(tracks, True), *ospa.extract_states(truths, True))
    gospa_values = gospa.compute_over_time(*gospa.extract_states(tracks, True), *gospa.extract_states(truths, True))
    estimates = pl.read_parquet(ctx.run_dir / "estimates" / "proposed.parquet").filter(
        (pl.col("run") == 1) & (pl.col("target") >= 0))
    truth = pl.read_parquet(ctx.run_dir / "truth.parquet").filter(pl.col("run") == 1)
    checked = 0
    for ospa_at, gospa_at in zip(ospa_values.value, gospa_values.value):
        when = seconds(ospa_at.timestamp)
        rows = estimates.filter(pl.col("time") == when).sort("target")
        if rows.height == 0:
            continue                                          # t = 0: the truth only, no report
        truth_rows = truth.filter((pl.col("time") == when) & pl.col("target").is_in(rows["target"].to_list())).sort("target")
        error = np.asarray(rows["x_compensated"].to_list())[:, :2] - np.asarray(truth_rows["x"].to_list())[:, :2]
        squared = (error**2).sum(axis=1)
        assert ospa_at.value == pytest.approx(np.sqrt(squared.mean()), rel=1e-9)
        assert gospa_at.value["distance"] == pytest.approx(np.sqrt(squared.sum()), rel=1e-9)
        checked += 1
    assert checked == 20                                       # 10 s of reports, two radars at 1 Hz


def test_a_stonesoup_variant_runs_where_its_measurement_model_fits(tmp_path):
    """The framework's check reads the kind off the measurement model's type: an EKF with
    CartesianToElevationBearingRange is refused on positions, a LinearGaussian KF on the radar."""
    with pytest.raises(ConfigError, match=r"filters.x: pipeline.stonesoup.variant.StoneSoupFilter declares "
                                          r"\['range_azimuth_elevation'\] measurements.*produces 'position_xy'"):
        run_in_process(tmp_path, "bad", "mc.runs=2", "experiment=stonesoup_kf", "+filter@filters.x=stonesoup_ekf_cv")
    assert not list(tmp_path.rglob("*.parquet"))


def test_stonesoup_classes_outside_its_component_packages_need_listing(tmp_path):
    """Stone Soup's models, predictors, updaters, simulators... are allowed without listing; a writer (it
    opens its file when built) is not, unless plugins.packages lists it."""
    victim = tmp_path / "victim.yaml"
    node = f"{{_target_:stonesoup.writer.yaml.YAMLWriter,path:{victim}}}"
    with pytest.raises(ConfigError, match=r"'stonesoup.writer.yaml.YAMLWriter' is not allowed \(nothing was imported\)"):
        run_in_process(tmp_path, "bad", "mc.runs=2", f"+filters.evil={node}")
    assert not victim.exists()
    from omegaconf import OmegaConf

    from pipeline.run.config import check_targets
    check_targets(OmegaConf.create({"plugins": {"packages": ["stonesoup.writer"]},
                                    "x": {"_target_": "stonesoup.writer.yaml.YAMLWriter"}}))   # listed: allowed
    with pytest.raises(ConfigError, match="plugins.packages"):
        check_targets(OmegaConf.create({"plugins": {"packages": ["stonesoup..writer"]}}))
