"""Spec 000 reproduction targets at reduced size (30 runs), through the pipeline.

Targets this implementation does not meet are strict xfails with the measured reason, so they
stay visible and a change that meets them shows up as a failure to update (README has the
100-run table).
"""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from tests.test_pipeline import run_in_process

RUNS = 30


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("s000")
    out, _ = run_in_process(root, "main", "experiment=mie_los", f"mc.runs={RUNS}")
    literal, _ = run_in_process(root, "literal", "experiment=mie_los", f"mc.runs={RUNS}", "variants=[b]",
                                "filters.b.rearm_after=3", "filters.b.level_uncertainty=false")
    return out, literal


def per_step(out, variant: str, metric: str) -> np.ndarray:
    rows = out.metrics.filter((pl.col("variant_key") == variant) & (pl.col("metric") == metric)).sort("step")
    return rows["value"].to_numpy()


def window(out, variant: str, metric: str, name: str) -> float:
    rows = out.summary.filter((pl.col("variant_key") == variant) & (pl.col("metric") == metric)
                              & (pl.col("window") == name))
    return float(rows["value"][0])


def false_alarms(out, variant: str) -> float:
    return window(out, variant, "detections", "t1-40") + window(out, variant, "detections", "t75-100")


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["a", "b"])
def test_detections_peak_3_to_7_steps_after_the_maneuver_starts_and_ends(study, variant):
    out, _ = study
    det = per_step(out, variant, "detections")
    assert 43 <= 41 + int(np.argmax(det[41:61])) <= 47
    assert 63 <= 61 + int(np.argmax(det[61:75])) <= 67


@pytest.mark.slow
def test_no_track_diverges(study):
    """Every variant stays near the measurement-noise level overall (a divergent run would dominate)."""
    out, _ = study
    for variant in ("a", "a_full", "b", "c", "b_nocomp"):
        assert window(out, variant, "position_rmse", "all") < 60.0, variant


@pytest.mark.slow
def test_full_covariance_test_has_no_more_false_alarms_than_b(study):
    out, _ = study
    assert false_alarms(out, "a_full") <= false_alarms(out, "b")


@pytest.mark.slow
def test_a_and_b_track_alike_and_c_leaves_the_elevation_axis_mostly_silent(study):
    out, _ = study
    a, b = window(out, "a", "position_rmse", "all"), window(out, "b", "position_rmse", "all")
    assert abs(b / a - 1) < 0.15
    axes = [window(out, "c", f"detections_axis_{x}", "t41-60") + window(out, "c", f"detections_axis_{x}", "t61-74")
            for x in "xyz"]
    assert axes[2] < 0.1 * sum(axes)


@pytest.mark.slow
def test_the_detect_compensate_loop_does_not_run_away(study):
    """Literal loop (re-test N_id scans after a compensation, old level exact): several detections
    per run after t = 75 (spec: ~7.5/run). The designed loop: well under one per run."""
    out, literal = study
    assert window(literal, "b", "detections", "t75-100") / RUNS > 4.0
    assert window(out, "b", "detections", "t75-100") / RUNS < 1.0


@pytest.mark.slow
def test_a_has_more_than_twice_the_false_alarms_of_b(study):
    """The paper's point: A's per-axis-sum test ignores the converted noise's correlation (100 runs: A 33, B 16)."""
    out, _ = study
    assert false_alarms(out, "a") > 2 * false_alarms(out, "b")


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured at 100 runs: B 42.95 m vs B-nocomp 39.62 m over t = 61-100, most "
                                       "of it over t = 61-70 before the end is detected (46.2 vs 38.9 m); the code "
                                       "review's oracle (true onset, 500 runs) still gave 40.8 vs 38.9 m")
def test_closed_loop_is_not_worse_than_no_compensation_after_the_maneuver(study):
    out, _ = study
    assert window(out, "b", "position_rmse", "after") <= window(out, "b_nocomp", "position_rmse", "after")
