"""Spec 000 reproduction targets at the paper's size (100 runs), through the pipeline.

The thresholds are not written here: the tests evaluate the study's report targets
(``conf/report/mie_los.yaml``, the same definitions ``python -m pipeline.report --check`` uses) on a
run of their own. Study 000 costs about 4.5 s at 100 runs, so the tests run at the paper's size
and need no margins: at 100 runs every target holds for seeds 1-6 with room (during the maneuver B
is 0.93-0.97x its no-compensation control, after the end is detected 1.05-1.07x; README). The one
target judged on wall time (``timed: true``) is left to the report and the benchmark.
"""

from __future__ import annotations

import polars as pl
import pytest

from pipeline.results.report import ReportSpec, evaluate_finding, evaluate_target, load_run
from tests.helpers.runs import run_in_process

RUNS = 100          # the paper's size
NO_RUNAWAY = ("no_runaway_detections", "compensation_helps_during_maneuver", "within_10pct_after_end_detected")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("s000")
    out, ctx = run_in_process(root, "main", "experiment=mie_los", f"mc.runs={RUNS}")
    literal, _ = run_in_process(root, "literal", "experiment=mie_los", f"mc.runs={RUNS}", "variants=[b]",
                                "filters.b.rearm_after=3", "filters.b.level_uncertainty=false")
    tables = load_run(ctx.run_dir)
    return out, literal, tables, ReportSpec.from_config(tables.config["report"])


def window(out, variant: str, metric: str, name: str) -> float:
    rows = out.summary.filter((pl.col("variant_key") == variant) & (pl.col("series") == metric)
                              & (pl.col("window") == name))
    return float(rows["value"][0])


def failed(tables, targets) -> list[str]:
    results = [evaluate_target(tables, t) for t in targets]
    # the values must pass; an interval straddling a threshold (INCONCLUSIVE) is reported, not failed
    return [f"{r.spec.id}: {r.verdict}, measured {r.measured} (target: {r.spec.target})"
            for r in results if r.verdict not in ("PASS", "INCONCLUSIVE") or not r.point_pass]


@pytest.mark.slow
def test_the_restated_no_runaway_target_holds(study):
    """Spec 000 (restated 2026-12): after t = 75 B fires fewer than once per run; during the maneuver
    (t = 41-60) B's RMS position error is below its no-compensation control's; over t = 71-100 it is
    within 10 % of it. (The old target, not above the control over all of t = 61-100, was met by no
    design: B holds the old level until it detects the end.)"""
    _, _, tables, spec = study
    targets = [t for t in spec.targets if t.id in NO_RUNAWAY]
    assert {t.id for t in targets} == set(NO_RUNAWAY)
    assert not failed(tables, targets)


@pytest.mark.slow
def test_every_other_untimed_target_of_the_spec_holds(study):
    _, _, tables, spec = study
    targets = [t for t in spec.targets if not t.timed and t.id not in NO_RUNAWAY]
    assert len(targets) >= 5
    assert not failed(tables, targets)


@pytest.mark.slow
def test_the_end_lag_is_reported_as_a_finding_beside_the_control(study):
    """t = 61-70 is reported, not judged: B pays for holding the level until it detects the end."""
    out, _, tables, spec = study
    (finding,) = [f for f in spec.findings if f.id == "end_lag_vs_control"]
    measured = evaluate_finding(tables, finding)
    b, control = window(out, "b", "position_rmse", "end_lag"), window(out, "b_nocomp", "position_rmse", "end_lag")
    assert measured.startswith(f"B {round(b, 2)} m vs B-nocomp {round(control, 2)} m")
    assert b > control          # the finding the spec predicts: a few metres above the control


@pytest.mark.slow
def test_no_track_diverges(study):
    """Every variant stays near the measurement-noise level overall (a divergent run would dominate)."""
    out, _, _, _ = study
    for variant in ("a", "a_full", "b", "c", "b_nocomp"):
        assert window(out, variant, "position_rmse", "all") < 60.0, variant


@pytest.mark.slow
def test_the_literal_detect_compensate_loop_runs_away(study):
    """Literal loop (re-test N_id scans after a compensation, old level exact): several detections per
    run after t = 75 (spec: ~7.5 per run), where the designed loop stays under one."""
    out, literal, _, _ = study
    assert window(literal, "b", "detections", "t75-100") / RUNS > 4.0
    assert window(out, "b", "detections", "t75-100") / RUNS < 1.0
