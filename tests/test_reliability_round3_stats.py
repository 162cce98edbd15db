"""Issue 37 (reliability, round 3), items 15, 16 and 18: statistics out of range refused up front, an
impossible NEES null with its flag, and statistics (and the memory estimate) linear in the runs."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.errors import ConfigError


def _job(tmp_path, name, *overrides):
    from tests.helpers.runs import job
    return job(tmp_path, name, "mc.runs=2", "scenario.steps=20", *overrides)


# ---- item 15: a confidence in (0, 1), at least 100 resamples -----------------------------------------

@pytest.mark.parametrize("value", ["0", "1.0", "1.5", "-0.5", "true", "'high'"])
def test_a_confidence_outside_zero_to_one_is_refused_before_any_stage(tmp_path, value):
    """Before: 0 marked every difference resolved (an interval excluding its own estimate), 1.0 gave
    infinite intervals, 1.5 was accepted: each ran every stage."""
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError) as refused:
        run_experiment(*_job(tmp_path, "bad", f"uncertainty.confidence={value}"))
    message = str(refused.value)
    assert message.startswith("uncertainty.confidence: ") and "is not allowed" in message
    assert "strictly between 0 and 1" in message and "\n" not in message
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("value", ["0", "-3", "99", "2.5", "'many'"])
def test_too_few_bootstrap_resamples_are_refused_before_any_stage(tmp_path, value):
    """Before: bootstrap_resamples=0 failed with a traceback in the bootstrap, after the track stages."""
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError) as refused:
        run_experiment(*_job(tmp_path, "bad", f"uncertainty.bootstrap_resamples={value}"))
    message = str(refused.value)
    assert message.startswith("uncertainty.bootstrap_resamples: ") and "an integer >= 100" in message
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()


def test_the_allowed_ends_of_confidence_and_resamples_pass():
    from pipeline.run.config import check_uncertainty
    from tests.helpers.config import composed_config
    for overrides in (["uncertainty.confidence=0.5", "uncertainty.bootstrap_resamples=100"],
                      ["uncertainty.confidence=0.999"], []):
        check_uncertainty(composed_config(*overrides))


# ---- item 16: a NEES below zero is null with its flag, never a number -----------------------------

def _nees_rows(values: np.ndarray):
    from pipeline.evaluation.evaluate import Window, consistency, summary_rows
    metrics = consistency("nees", values, 6)
    windows = [Window("all", 0, values.shape[1] - 1), Window("early", 0, 1)]
    return metrics, summary_rows({"a": ("A", metrics), "b": ("B", consistency("nees", np.abs(values), 6))},
                                 {"a": 1.0, "b": 1.0}, windows, "b", values.shape[0])


def test_a_negative_nees_is_null_per_step_in_the_summary_and_its_interval():
    """Before: -207,239 (study 003, bearing_std_deg=179) and -2.65e17 (study 000, range_std=1e-6) were
    served as the NEES, per step and in the summary (flagged not-positive-definite, but printed)."""
    from pipeline.evaluation.evaluate import metrics_frame, resolved, summary_table
    from pipeline.views.tables import format_summary
    rng = np.random.default_rng(0)
    values = rng.chisquare(6, size=(20, 5))
    values[3, 3] = -2.65e17                          # run 3, step 3: a covariance that is not positive definite
    metrics, rows = _nees_rows(values)
    per_step = resolved(metrics)["nees"]
    assert np.isnan(per_step[3]) and np.isfinite(per_step[[0, 1, 2, 4]]).all()
    assert np.allclose(per_step[[0, 1, 2, 4]], values[:, [0, 1, 2, 4]].mean(axis=0))
    frame = metrics_frame(np.arange(5.0), {"a": ("A", metrics)}, 20).filter(pl.col("series") == "nees")
    assert frame["value"][3] is None and frame["value"].null_count() == 1
    summary, comparisons, per_run, _ = summary_table(rows, "b", seed=1, resamples=200)
    nees = summary.filter((pl.col("series") == "nees") & (pl.col("variant_key") == "a"))
    whole = nees.filter(pl.col("window") == "all").row(0, named=True)
    assert whole["value"] is None and whole["interval"] == "impossible"
    assert whole["ci_low"] is None and whole["ci_high"] is None and whole["standard_error"] is None
    early = nees.filter(pl.col("window") == "early").row(0, named=True)     # steps 0-1: every value possible
    assert early["value"] == pytest.approx(values[:, :2].mean()) and early["interval"] == "t"
    paired = comparisons.filter((pl.col("series") == "nees") & (pl.col("window") == "all")).row(0, named=True)
    assert paired["difference"] is None and not paired["resolved"]
    run3 = per_run.filter((pl.col("series") == "nees") & (pl.col("variant_key") == "a")
                          & (pl.col("window") == "all") & (pl.col("run") == 3))
    assert run3["value"][0] is None
    printed = format_summary(summary, "x", 20)
    block = printed.split("window: all")[1].split("window:")[0]
    assert "n/a (flagged)" in block and "e+17" not in printed and "-265" not in printed


def test_a_negative_nees_median_is_null_too():
    from pipeline.evaluation.uncertainty import WindowStatistic, normalised_squared
    values = np.random.default_rng(1).chisquare(2, size=(10, 4))
    values[0, 2] = -5.0
    median = normalised_squared(values, "median")
    assert np.isnan(median.per_step()[2]) and np.isfinite(median.per_step()[[0, 1, 3]]).all()
    assert np.isnan(WindowStatistic(median, np.arange(4)).value())
    assert np.isfinite(WindowStatistic(median, np.arange(2)).value())
