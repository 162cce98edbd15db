"""Spec 001 reproduction targets at reduced Monte Carlo size (30 runs), through the pipeline.

The full-size (100-run) figures are in README.md; these check the same orderings with margins
that 30 runs support.
"""

from __future__ import annotations

import polars as pl
import pytest

from tests.test_pipeline import run_in_process

RUNS = 30


def values(summary: pl.DataFrame, metric: str, window: str | None = "all") -> dict[str, float]:
    rows = summary.filter(pl.col("metric") == metric)
    if window is not None:
        rows = rows.filter(pl.col("window") == window)
    return dict(zip(rows["variant_key"], rows["value"]))


@pytest.fixture(scope="module")
def s1(tmp_path_factory):
    out, _ = run_in_process(tmp_path_factory.mktemp("s1"), "s1", "experiment=ao_vsimm_s1", f"mc.runs={RUNS}")
    return out.summary


@pytest.fixture(scope="module")
def s2(tmp_path_factory):
    out, _ = run_in_process(tmp_path_factory.mktemp("s2"), "s2", "experiment=ao_vsimm_s2_ratios", f"mc.runs={RUNS}")
    return out.summary


@pytest.mark.slow
def test_s1_the_three_variants_are_close(s1):
    for axis in ("x", "y"):
        acc = values(s1, f"acceleration_rmse_{axis}")
        assert abs(acc["ao_vsimm"] / acc["fsimm"] - 1) < 0.10, acc
        assert abs(acc["vsimm"] / acc["fsimm"] - 1) < 0.25, acc
    acc_x = values(s1, "acceleration_rmse_x")["fsimm"]
    assert 3.5 < acc_x < 4.8          # spec reference 4.1 m/s^2 at 100 runs


@pytest.mark.slow
def test_s2_vsimm_printed_fails_after_the_switch_and_ao_vsimm_does_not(s2):
    for axis in ("x", "y"):
        acc = values(s2, f"acceleration_rmse_{axis}", "after_switch")
        assert acc["vsimm"] > 1.4 * acc["fsimm"] and acc["vsimm"] > 1.4 * acc["ao_vsimm"], acc
        assert abs(acc["ao_vsimm"] / acc["fsimm"] - 1) < 0.10, acc
        assert abs(acc["vsimm_new_old"] / acc["ao_vsimm"] - 1) < 0.05, acc
    reached = values(s2, "group_reached_fraction", None)
    assert reached["vsimm"] < 0.5 and reached["ao_vsimm"] == 1.0      # M3 not reached by k = 80 in most runs


@pytest.mark.slow
def test_models_evaluated_per_step_ao_below_vsimm_below_fsimm(s1, s2):
    for summary in (s1, s2):
        models = values(summary, "models_evaluated")
        assert models["ao_vsimm"] < models["vsimm"] < models["fsimm"] == 13.0
        assert 5.0 < models["ao_vsimm"] < 5.4
