"""A job holds one variant's estimate at a time (pipeline.storage.estimates): the evaluation measures each
variant after its track stage and lets it go, a study's own summary reads the tables again one at a
time, and the recording gets only the recorded runs' rows."""

from __future__ import annotations

import weakref

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from filters.base import TrackEstimate
from filters.bias import BiasRegistrationResult
from pipeline.run import runner as runner_module
from pipeline.storage.estimates import RecordedRuns, StoredEstimates, recorded_runs
from pipeline.run.runner import RunContext, run_experiment
from pipeline.storage.schemas import PackedCovariance, estimate_from_frame, estimate_to_frame
from pipeline.storage.store import atomic_write_parquet
from tests.helpers.config import CONF


def _estimate(runs: int = 5, steps: int = 4, n: int = 2, seed: int = 0) -> TrackEstimate:
    rng = np.random.default_rng(seed)
    state = rng.normal(size=(runs, steps, n))
    roots = rng.normal(size=(runs, steps, n, n))
    covariance = roots @ np.swapaxes(roots, -1, -2)
    return TrackEstimate(np.arange(steps, dtype=float), state, covariance,
                         {"mode_probabilities": rng.random((runs, steps, 3))}, 0.25)


def test_recorded_runs_give_the_recorded_rows_and_refuse_every_other_run():
    est = _estimate()
    kept = recorded_runs(est, [3, 1], est.state.shape[0])
    assert isinstance(kept.state, RecordedRuns) and kept.state.shape == est.state.shape and len(kept.state) == 5
    assert kept.state.ndim == 3 and np.shape(kept.covariance) == est.covariance.shape
    np.testing.assert_array_equal(kept.state[3], est.state[3])
    np.testing.assert_array_equal(kept.state[1][:, 1], est.state[1][:, 1])
    np.testing.assert_array_equal(kept.covariance[1, 2], est.covariance[1, 2])
    np.testing.assert_array_equal(kept.state[[3, 1]], est.state[[3, 1]])
    np.testing.assert_array_equal(kept.state[-2], est.state[3])                  # run -2 of 5 is run 3
    np.testing.assert_array_equal(kept.extras["mode_probabilities"][1], est.extras["mode_probabilities"][1])
    np.testing.assert_array_equal(kept.time, est.time)                            # (K,): kept whole
    assert kept.compute_seconds == 0.25
    with pytest.raises(IndexError, match=r"run 0 is not among the recorded runs \[1, 3\]"):
        kept.state[0]
    with pytest.raises(IndexError, match="leading index"):
        kept.state[:, 0]
    with pytest.raises(TypeError, match="only the recorded runs"):
        np.asarray(kept.state)
    with pytest.raises(TypeError, match="instead of iterating"):   # not a silent stop at run 0
        list(kept.state)


def test_a_packed_covariance_keeps_its_recorded_runs_unpacked():
    est = _estimate(n=3)
    upper = np.triu_indices(3)
    packed = PackedCovariance(est.covariance[..., upper[0], upper[1]].astype(np.float32), 3)
    kept = recorded_runs(TrackEstimate(est.time, est.state, packed), [2], 5)
    np.testing.assert_array_equal(kept.covariance[2], packed[2])
    assert kept.covariance.shape == (5, 4, 3, 3)


def test_a_bias_registration_result_keeps_its_sensor_and_targets_whole():
    R, K, T = 4, 6, 2
    rng = np.random.default_rng(1)
    result = BiasRegistrationResult(
        time=np.arange(K, dtype=float), sensor=np.arange(K) % 2, bias=rng.normal(size=(R, K, 8)),
        bias_covariance=rng.normal(size=(R, K, 8, 8)), targets=np.array([0, 3]),
        track_state=rng.normal(size=(R, K, T, 4)), track_covariance=rng.normal(size=(R, K, T, 4, 4)),
        compensated_state=rng.normal(size=(R, K, T, 4)), compensated_covariance=rng.normal(size=(R, K, T, 4, 4)),
        nis=rng.normal(size=(R, K)), nis_dof=np.full((R, K), 4))
    kept = recorded_runs(result, [0], R)
    np.testing.assert_array_equal(kept.sensor, result.sensor)
    np.testing.assert_array_equal(kept.targets, result.targets)
    np.testing.assert_array_equal(kept.bias[0, :, 2], result.bias[0, :, 2])
    with pytest.raises(IndexError):
        kept.track_state[1]


def test_stored_estimates_read_a_table_when_asked_and_keep_only_the_last(tmp_path):
    paths = {}
    for i, key in enumerate(("a", "b")):
        df, meta = estimate_to_frame(_estimate(seed=i), ("x", "y"))
        paths[key] = tmp_path / f"{key}.parquet"
        atomic_write_parquet(df, paths[key], meta)
    reads = []

    def from_frame(df, meta):
        reads.append(df.height)
        return estimate_from_frame(df, meta)

    stored = StoredEstimates(paths, from_frame)
    assert list(stored) == ["a", "b"] and len(stored) == 2 and not reads
    a = stored["a"]
    np.testing.assert_array_equal(a.state, _estimate(seed=0).state)
    assert stored["a"] is a and len(reads) == 1                # the last one read is kept
    alive = weakref.ref(a)
    del a
    np.testing.assert_array_equal(stored["b"].state, _estimate(seed=1).state)
    assert alive() is None                                     # ... and only that one
    with pytest.raises(KeyError):
        stored["c"]


def test_a_job_holds_one_variants_estimate_at_a_time_and_records_the_recorded_runs(tmp_path, monkeypatch):
    """Before: every variant's estimate stayed in memory from its track stage to the recording (an
    ADS-B job with seven variants peaked at 1.0 GB, 0.66 GB since). The async-bias recording, given
    only the recorded runs, must still draw (it read every run's biases to see if a variant has any)."""
    alive: list[weakref.ref] = []
    held_at_track_start: list[int] = []
    original = runner_module._Stages.run

    def run(self, stage, key, table, *args, **kwargs):
        if stage == "track":
            held_at_track_start.append(sum(ref() is not None for ref in alive))
        value, hit, df = original(self, stage, key, table, *args, **kwargs)
        if stage == "track":
            alive.append(weakref.ref(value))
        return value, hit, df

    monkeypatch.setattr(runner_module._Stages, "run", run)
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=async_bias", f"paths.artifacts={tmp_path}",
                                           "scenario.duration=20", "mc.runs=3", "record.runs=[2]"])
    assert cfg.record.enabled and len(cfg.filters) >= 3
    ctx = RunContext(tmp_path / "runs" / "one", tmp_path, [])
    outcome = run_experiment(cfg, ctx)
    assert held_at_track_start == [0] * len(cfg.filters)
    assert (ctx.run_dir / "recording.rrd").stat().st_size > 0
    assert outcome.summary.height > 0


@pytest.mark.parametrize("experiment, overrides", [
    ("sonar_case2", ["++scenario.duration=600"]),
    ("adsb_jet", ["++scenario.duration=60"]),
    ("sonobuoy_case2", ["++scenario.duration=100", "++target_model.particles=100"]),
])
def test_the_shipped_studies_summaries_read_no_estimate_table_again(tmp_path, monkeypatch, experiment, overrides):
    """Their own rows come from variant_summary while each estimate is in memory; extra_summary (rows
    across variants) works from what it kept. Before, each variant's 147 MB study 003 table was read
    again (0.5-0.7 s each) at the evaluation's peak."""
    reads: list[str] = []
    original = StoredEstimates.__getitem__

    def getitem(self, key):
        reads.append(key)
        return original(self, key)

    monkeypatch.setattr(StoredEstimates, "__getitem__", getitem)
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment={experiment}", f"paths.artifacts={tmp_path}", "mc.runs=2",
                                           "record.enabled=false", *overrides])
    outcome = run_experiment(cfg, RunContext(tmp_path / "runs" / "one", tmp_path, []))
    assert reads == []
    own = {"sonar_case2": "paired_ratio_x", "adsb_jet": "position_rmse_straight",
           "sonobuoy_case2": "track_loss_rate"}[experiment]
    assert outcome.summary.filter(outcome.summary["series"] == own).height == len(cfg.filters)


@pytest.mark.parametrize("experiment", ["mie_los", "sonar_case2"])
def test_the_evaluation_lets_a_measured_variants_per_run_values_go(tmp_path, monkeypatch, experiment):
    """Its summary statistics are resampled when it is added (pipeline.evaluation.uncertainty.resample), so
    nothing holds its (runs x steps) metric arrays afterwards. Before, every variant's stayed until the
    summary: ~90 MB per 100-run study 003 variant, 1288 MB -> 1107 MB at that job's peak."""
    from pipeline.evaluation.uncertainty import RunValues

    original_add = runner_module.Evaluation.add
    alive_after_add: list[int] = []

    def add(self, key, display, estimate):
        measure = type(self.study).per_step_metrics
        arrays: list[weakref.ref] = []

        def per_step_metrics(study, truth, est, sensor):
            out = measure(study, truth, est, sensor)
            # the estimate's own arrays (its NIS extra) live as long as the estimate, which the runner drops
            own = {id(a) for a in (est.state, *getattr(est, "extras", {}).values())}
            arrays.extend(weakref.ref(v.values) for v in out.values()
                          if isinstance(v, RunValues) and id(v.values) not in own)
            return out

        monkeypatch.setattr(type(self.study), "per_step_metrics", per_step_metrics)
        original_add(self, key, display, estimate)
        monkeypatch.setattr(type(self.study), "per_step_metrics", measure)
        assert arrays
        alive_after_add.append(sum(ref() is not None for ref in arrays))

    monkeypatch.setattr(runner_module.Evaluation, "add", add)
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment={experiment}", f"paths.artifacts={tmp_path}", "mc.runs=3",
                                           "record.enabled=false", "++scenario.duration=600"])
    outcome = run_experiment(cfg, RunContext(tmp_path / "runs" / "one", tmp_path, []))
    assert alive_after_add == [0] * len(cfg.filters)
    assert outcome.summary["ci_low"].is_not_null().sum() > 0


def test_recomputing_a_run_reads_one_variants_estimate_at_a_time(tmp_path, monkeypatch):
    """pipeline.results.recompute evaluates the stored tables through StoredEstimates; its loop kept the
    previous estimate while the next one was read (two in memory)."""
    from pipeline.results.recompute import recompute
    from tests.helpers.runs import run_in_process

    _, ctx = run_in_process(tmp_path, "run", "experiment=mie_los", "mc.runs=2")
    returned: list[weakref.ref] = []
    alive_at_read: list[int] = []
    original_init = StoredEstimates.__init__

    def init(self, tables, from_frame):
        def counted(df, meta):                 # called once the previous estimate was let go
            alive_at_read.append(sum(ref() is not None for ref in returned))
            value = from_frame(df, meta)
            returned.append(weakref.ref(value))
            return value
        original_init(self, tables, counted)

    monkeypatch.setattr(StoredEstimates, "__init__", init)
    recompute(ctx.run_dir)
    assert len(alive_at_read) >= 5 and set(alive_at_read) == {0}, alive_at_read
