"""Study 002 through the runner: configs compose, the study adapter's tables, the cache, the report
tables and bad input rejected before any stage runs (a 20 s horizon keeps it fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pipeline.errors import ConfigError
from pipeline.run.runner import RunContext, run_experiment
from pipeline.storage.store import read_table
from pipeline.studies.async_bias import codec as bias_codec
from tests.helpers.config import CONF

SHORT = ["scenario.duration=20", "mc.runs=3"]


def compose_study(tmp_path: Path, *overrides: str, experiment: str = "async_bias"):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose("config", overrides=[f"experiment={experiment}", f"paths.artifacts={tmp_path}",
                                           "record.enabled=false", *overrides])


def run_study(tmp_path: Path, name: str, *overrides: str, experiment: str = "async_bias"):
    cfg = compose_study(tmp_path, *overrides, experiment=experiment)
    ctx = RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))
    return run_experiment(cfg, ctx), ctx


def test_experiments_compose_with_their_variants_and_tables():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=async_bias"])
        ablation = compose("config", overrides=["experiment=async_bias_two_point"])
        measured = compose("config", overrides=["experiment=async_bias_measured_jacobians"])
    assert list(cfg.filters) == ["local", "proposed", "exx"]
    assert cfg.filters.proposed._target_ == "filters.bias.PseudoBiasRegistration"
    assert cfg.filters.exx._target_ == "filters.bias.EXXRegistration"
    assert {cfg.filters[v].start for v in cfg.filters} == {"truth"}
    assert {ablation.filters[v].start for v in ablation.filters} == {"two_point"}
    assert {measured.filters[v].jacobian_at for v in measured.filters} == {"measurement"}
    assert cfg.study._target_ == "pipeline.studies.async_bias.adapter.BiasRegistrationStudy"
    for name in ("bias_rmse", "compensation", "consistency"):
        table = instantiate(cfg.report.tables[name], _convert_="all")
        assert table.rows
    assert "TRUTH-start" in ablation.report.tables.bias_rmse.note


@pytest.fixture(scope="module")
def study_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("async_bias")
    out, ctx = run_study(tmp, "first", *SHORT)
    return tmp, out, ctx


def test_the_run_writes_the_study_tables(study_run):
    tmp, out, ctx = study_run
    for name in ("truth.parquet", "detections.parquet", "estimates/local.parquet", "estimates/proposed.parquet",
                 "estimates/exx.parquet", "metrics.parquet", "summary.parquet", "report.txt", "status.json"):
        assert (ctx.run_dir / name).is_file(), name
    truth = pl.read_parquet(ctx.run_dir / "truth.parquet")
    assert truth.height == 3 * 41 * 32                                   # runs x 0.5 s steps x targets
    detections = pl.read_parquet(ctx.run_dir / "detections.parquet")
    assert detections.height == 3 * 40 * 32 and set(detections["sensor"].unique()) == {0, 1}
    df, meta = read_table(ctx.run_dir / "estimates" / "proposed.parquet")
    assert df.height == 3 * 40 * 3                                       # runs x reports x (bias + 2 targets)
    bias_rows = df.filter(pl.col("target") == -1)
    assert bias_rows["x"].null_count() == bias_rows.height and bias_rows["bias"].null_count() == 0
    assert sorted(df.filter(pl.col("target") >= 0)["target"].unique().to_list()) == [0, 31]
    result = bias_codec.bias_estimates_from_frame(df, meta)
    assert result.bias.shape == (3, 40, 8) and result.track_state.shape == (3, 40, 2, 4)
    local = bias_codec.bias_estimates_from_frame(*read_table(ctx.run_dir / "estimates" / "local.parquet"))
    assert np.isnan(local.bias).all()
    np.testing.assert_allclose(local.track_state, result.track_state)   # the biased tracks are shared
    status = json.loads((ctx.run_dir / "status.json").read_text())
    assert status["status"] == "ok"


def test_summary_and_report_carry_the_bias_metrics(study_run):
    _, out, ctx = study_run
    summary = out.summary
    row = summary.filter((pl.col("variant_key") == "proposed") & (pl.col("series") == "bias_rmse_range_offset_s1")
                         & (pl.col("window") == "t10"))
    assert row.height == 1 and row["unit"][0] == "m" and 0 < row["value"][0] < 20
    assert summary.filter((pl.col("variant_key") == "local") & pl.col("series").str.starts_with("bias_")).height == 0
    assert set(summary.filter(pl.col("series") == "position_rmse_s1_t32_compensated")["variant_key"]) == \
        {"local", "proposed", "exx"}
    report = (ctx.run_dir / "report.txt").read_text()
    assert "Figs 3-6 (seed 002)" in report and "Figs 8-11 (seed 002)" in report and "EXX / proposed" in report
    assert "proposed ~19 (optimistic), EXX 7.2-8.8" in report


def test_a_filter_change_reuses_scenario_measurements_and_other_variants(study_run, caplog):
    tmp, _, _ = study_run
    caplog.set_level("INFO", logger="pipeline")
    out, _ = run_study(tmp, "second", *SHORT, "filters.exx.process_noise_density=3.0")
    text = caplog.text
    assert "[scenario] reused" in text and "[measure] reused" in text
    cached = dict(out.summary.select("variant_key", "estimates_from_cache").unique().iter_rows())
    assert cached == {"local": True, "proposed": True, "exx": False}


@pytest.mark.parametrize("overrides, message", [
    (["study.start_std=[1,2]"], "study: start_std: [1, 2] must be 4 standard deviations"),
    (["study.start_time=0.25"], "study.start_time: 0.25 s is not a time of the scenario's grid"),
    (["filters.proposed.output_targets=[1,40]"], "filters.proposed.output_targets: [1, 40] names target(s) [40]"),
    (["filters.exx.start=first"], "filters.exx: start: 'first' is not allowed"),
    (["sensors.radars.1.first_report=0.7"], "sensors.radars[1]: reports at 0.7 s, which is not on the scenario's"),
    (["sensors.radars.0.period=0"], "sensors: radars[0].period: 0"),
])
def test_bad_config_is_rejected_before_any_stage(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_study(tmp_path, "bad", *SHORT, *overrides)
    assert message in str(info.value)
    assert not (tmp_path / "cache").exists()
