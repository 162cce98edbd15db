"""Study 003 through the runner: the experiments compose, the tables (compact covariance), the
Table 1 summary rows, the cache, and bad input rejected before any stage (a 1200 s horizon)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pipeline.storage import schemas
from pipeline.errors import ConfigError
from pipeline.results.recompute import MEASURED    # timed in each job: not equal between two jobs
from pipeline.run.runner import RunContext, run_experiment
from pipeline.storage.store import read_table
from tests.helpers.config import CONF

SHORT = ["scenario.duration=1200", "mc.runs=2", "sensors.active_intervals=[[0,300],[600,700]]"]


def run_study(tmp_path: Path, name: str, *overrides: str, experiment: str = "sonar_case2"):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment={experiment}", f"paths.artifacts={tmp_path}",
                                           "record.enabled=false", *overrides])
    ctx = RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))
    return run_experiment(cfg, ctx), ctx


def test_experiments_compose_with_the_case_values():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        one = compose("config", overrides=["experiment=sonar_case1"])
        two = compose("config", overrides=["experiment=sonar_case2"])
    assert list(two.filters) == ["kf_mgekf", "kf_mgekf_consistent", "only_mgekf", "ekf"]
    assert one.filters.only_mgekf.sigma_m == 0.003 and two.filters.only_mgekf.sigma_m == 0.01
    assert two.filters.kf_mgekf.handover_acceleration_variance == 0.1
    assert two.filters.kf_mgekf_consistent.handover_acceleration_variance == "consistent"
    assert two.filters.kf_mgekf_consistent._target_ == "filters.mgekf.KFPlusMGEKF"
    assert [list(t) for t in two.scenario.target_turns] == [[3000.0, -45.0], [5100.0, 45.0]]
    assert one.scenario.target_turns == []
    for cfg in (one, two):
        for table in cfg.report.tables.values():
            assert instantiate(table, _convert_="all").rows


@pytest.fixture(scope="module")
def study_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sonar")
    out, ctx = run_study(tmp, "first", *SHORT)
    return tmp, out, ctx


def test_the_run_writes_the_tables_with_a_compact_covariance(study_run):
    _, out, ctx = study_run
    df, meta = read_table(ctx.run_dir / "estimates" / "only_mgekf.parquet")
    assert df.height == 2 * 1201 and "P_upper" in df.columns and df.schema["P_upper"] == pl.Array(pl.Float32, 21)
    estimate = schemas.estimate_from_frame(df, meta)
    P = estimate.covariance
    assert P.shape == (2, 1201, 6, 6) and np.allclose(P, np.swapaxes(P, -1, -2))
    kf = schemas.estimate_from_frame(*read_table(ctx.run_dir / "estimates" / "kf_mgekf.parquet"))
    active = kf.extras["active"][0].astype(bool)
    assert active[:300].all() and not active[300:600].any() and active[600:700].all()
    assert np.isnan(kf.state[:, active, 4:]).all() and np.isfinite(kf.state[:, ~active, 4:]).all()


def test_summary_has_the_table1_rows_and_the_switch_peaks(study_run):
    _, out, ctx = study_run
    s = out.summary
    for metric in ("rmse_x", "rmse_y", "median_run_rmse_x", "paired_ratio_y"):
        assert s.filter((pl.col("series") == metric) & (pl.col("variant_key") == "ekf")).height == 1, metric
    ratio = s.filter((pl.col("series") == "paired_ratio_x") & (pl.col("variant_key") == "only_mgekf"))["value"][0]
    assert ratio == pytest.approx(1.0)
    windows = set(s.filter(pl.col("series") == "peak_position_rmse")["window"])
    assert windows == {"after 300 s", "after 700 s"}
    metrics = pl.read_parquet(ctx.run_dir / "metrics.parquet")
    assert {"position_rmse_x", "position_rmse_y", "position_rmse", "nees"} <= set(metrics["series"])
    report = (ctx.run_dir / "report.txt").read_text()
    assert "Table 1 (seed 003, case 2)" in report and "KF+MGEKF 1631, only MGEKF 686" in report


def test_cached_estimates_give_the_same_summary(study_run, caplog):
    tmp, first, _ = study_run
    caplog.set_level("INFO", logger="pipeline")
    again, _ = run_study(tmp, "again", *SHORT)
    assert caplog.text.count("[track] reused") == 4
    key = ["variant_key", "metric", "window"]
    a = first.summary.filter(~pl.col("series").is_in(MEASURED)).sort(key).select(*key, "value")
    b = again.summary.filter(~pl.col("series").is_in(MEASURED)).sort(key).select(*key, "value")
    assert a["value"].to_numpy() == pytest.approx(b["value"].to_numpy(), rel=1e-5, nan_ok=True)  # P stored float32


@pytest.mark.parametrize("overrides, message", [
    (["filters.kf_mgekf.handover_acceleration_variance=1.0"], "filters.kf_mgekf: handover_acceleration_variance: 1.0"),
    (["sensors.active_intervals=[[10,300]]"], "sensors.active_intervals: [[10.0, 300.0]] must start active at t = 0"),
    (["filters.kf_mgekf.tau=0"], "filters.kf_mgekf: tau: 0 must be a finite number > 0"),
    (["target_model.tau=0"], "study: bound_tau: 0 must be > 0"),
    (["study.bump_window=-1"], "study: bump_window: -1"),
])
def test_bad_config_is_rejected_before_any_stage(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_study(tmp_path, "bad", *SHORT, *overrides)
    assert message in str(info.value)
    assert not (tmp_path / "cache").exists()
