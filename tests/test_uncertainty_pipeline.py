"""Issue 18 through a real run: the summary's intervals, the per-run and comparisons tables, null
(not NaN) where a per-step metric is undefined, and the tables pipeline.results.query serves."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
import pytest

from pipeline.results.query import query
from pipeline.storage.store import read_table
from tests.helpers.runs import run_in_process


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("uncertainty")
    out, ctx = run_in_process(root, "ao_vsimm_s1/run", "mc.runs=12", "scenario.steps=60")
    return root, out, ctx


def test_every_value_estimated_from_runs_has_its_interval(run):
    _, out, _ = run
    summary = out.summary
    estimated = summary.filter(pl.col("series").is_in(["position_rmse", "velocity_rmse", "nees", "models_evaluated"]))
    assert estimated.height and estimated["n_valid_runs"].to_list() == [12] * estimated.height
    spread = estimated.filter(pl.col("series") != "models_evaluated")      # FSIMM's 13 models: constant
    assert (spread["ci_low"] < spread["value"]).all() and (spread["value"] < spread["ci_high"]).all()
    assert set(spread["interval"]) <= {"t", "bootstrap BCa", "bootstrap normal"}
    # timed, not estimated from runs: no run count; its interval is of the timed passes (issue 38)
    timing = summary.filter(pl.col("series") == "compute_seconds")
    assert timing["n_valid_runs"].null_count() == timing.height
    assert all("pass" in method for method in timing["interval"].to_list())


def test_a_plain_mean_is_the_mean_of_the_per_run_table(run):
    _, out, ctx = run
    per_run = read_table(ctx.run_dir / "per_run.parquet")[0]
    for variant in ("fsimm", "ao_vsimm"):
        own = per_run.filter((pl.col("variant_key") == variant) & (pl.col("series") == "nees")
                             & (pl.col("window") == "all"))
        assert own["run"].to_list() == list(range(12))
        value = out.summary.filter((pl.col("variant_key") == variant) & (pl.col("series") == "nees")
                                   & (pl.col("window") == "all"))["value"][0]
        assert own["value"].mean() == pytest.approx(value, rel=1e-12)
    # an RMSE's per-run value is the run's own RMS error over the window
    rmse = per_run.filter((pl.col("variant_key") == "fsimm") & (pl.col("series") == "position_rmse")
                          & (pl.col("window") == "all"))["value"]
    assert rmse.len() == 12 and (rmse > 0).all()


def test_comparisons_pair_every_variant_with_the_reference(run):
    _, out, ctx = run
    comparisons = read_table(ctx.run_dir / "comparisons.parquet")[0]
    assert set(comparisons["variant_key"]) == {"vsimm", "ao_vsimm"} and set(comparisons["reference_key"]) == {"fsimm"}
    row = comparisons.filter((pl.col("variant_key") == "vsimm") & (pl.col("series") == "position_rmse")
                             & (pl.col("window") == "all")).row(0, named=True)
    summary = out.summary.filter((pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
    values = dict(zip(summary["variant_key"], summary["value"]))
    assert row["difference"] == pytest.approx(values["vsimm"] - values["fsimm"])
    assert row["ratio"] == pytest.approx(values["vsimm"] / values["fsimm"])
    assert row["difference_low"] <= row["difference"] <= row["difference_high"]
    assert 0 <= row["wilcoxon_p"] <= 1 and row["n_paired_runs"] == 12
    assert "paired with FSIMM" in out.table


def test_undefined_steps_are_null_so_sql_averages_work(run):
    root, out, ctx = run
    metrics = read_table(ctx.run_dir / "metrics.parquet")[0]
    assert metrics["value"].is_nan().sum() == 0
    nees = metrics.filter((pl.col("variant_key") == "fsimm") & (pl.col("series") == "nees")).sort("step")
    assert nees["value"][0] is None                                      # no estimate at step 0
    average = query("SELECT AVG(value) AS mean FROM metrics WHERE series = 'nees'", root=root)["mean"][0]
    assert average is not None and math.isfinite(average)


def test_per_run_truth_and_estimates_are_queryable(run):
    root, _, _ = run
    better = query("""
        SELECT SUM(CASE WHEN a.value < f.value THEN 1 ELSE 0 END) AS better, COUNT(*) AS runs
        FROM per_run a JOIN per_run f ON a.run_id = f.run_id AND a.run = f.run AND a.series = f.series
                                      AND a."window" = f."window"
        WHERE a.variant_key = 'ao_vsimm' AND f.variant_key = 'fsimm' AND a.series = 'position_rmse'
              AND a."window" = 'all'""", root=root)
    assert better["runs"][0] == 12 and 0 <= better["better"][0] <= 12
    estimates = query("SELECT variant_key, COUNT(DISTINCT run) AS runs FROM estimates GROUP BY ALL ORDER BY ALL",
                      root=root)
    assert estimates["variant_key"].to_list() == ["ao_vsimm", "fsimm", "vsimm"] and set(estimates["runs"]) == {12}
    truth = query("SELECT experiment, COUNT(DISTINCT run) AS runs, MAX(step) AS last FROM truth GROUP BY ALL", root=root)
    assert truth.row(0) == ("ao_vsimm_s1", 12, 60)
    assert np.isfinite(query("SELECT AVG(difference) AS d FROM comparisons", root=root)["d"][0])
