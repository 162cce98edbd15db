"""Issue 40: the report at a fraction of the run. A target's query on the stacked joint resamples is
run on all of them at once only where it keeps one row per resample (probed on two); a query that
joins the wide table with itself is judged one resample at a time without first building every
combination of resamples (400^3 rows for sonar_case2's three-window targets: 95 s of its report).
The verdicts are those of the evaluation without the probe."""

from __future__ import annotations

import numpy as np
import pytest

import pipeline.results.report as report
from pipeline.results.report import ReportSpec, RunTables, evaluate_target, load_run
from tests.helpers.report_targets import around, CROSS, RATIO, SMALL, tables_with_resamples, THRESHOLD
from tests.helpers.runs import run_in_process


def _largest_result(monkeypatch) -> list[int]:
    heights: list[int] = []
    query = RunTables.query

    def recording(self, sql, wide=None):
        out = query(self, sql, wide)
        heights.append(out.height)
        return out

    monkeypatch.setattr(RunTables, "query", recording)
    return heights


def test_a_self_joining_target_never_builds_every_pair_of_resamples(monkeypatch):
    """Before: the query ran first on all 400 stacked resamples, 400 x 400 = 160 000 rows here (a
    three-way join: 64 million), and the result was discarded for the one-at-a-time evaluation."""
    heights = _largest_result(monkeypatch)
    b = np.full(401, 20.0)
    a = np.concatenate([[19.0], np.full(389, 19.0), np.full(11, 21.0)])
    result = evaluate_target(tables_with_resamples(a, b), CROSS)
    assert result.verdict == "INCONCLUSIVE" and "97.2 % of 400" in result.interval_note
    assert heights and max(heights) <= 400


def _without_probe(monkeypatch):
    monkeypatch.setattr(report, "PROBE_RESAMPLES", 10**9)        # every query on all resamples first, as before


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    _, ctx = run_in_process(tmp_path_factory.mktemp("report_cost"), "s2", "experiment=ao_vsimm_s2_ratios", *SMALL)
    return ctx.run_dir


def test_the_verdicts_are_those_without_the_probe(small_run, monkeypatch):
    tables = load_run(small_run)
    specs = ReportSpec.from_config(tables.config["report"]).targets
    synthetic = [(tables_with_resamples(around(9.8, 0.2)), THRESHOLD),
                 (tables_with_resamples(20.0 + np.random.default_rng(1).normal(0, 1.0, 401) * 1.001,
                                         20.0 + np.random.default_rng(1).normal(0, 1.0, 401)), RATIO),
                 (tables_with_resamples(np.concatenate([[19.0], np.full(389, 19.0), np.full(11, 21.0)]),
                                         np.full(401, 20.0)), CROSS)]
    cases = [(tables, s) for s in specs] + synthetic
    probed = [evaluate_target(t, s) for t, s in cases]
    with monkeypatch.context() as patched:
        _without_probe(patched)
        unprobed = [evaluate_target(t, s) for t, s in cases]
    assert len(specs) >= 3
    assert [(r.verdict, r.measured, r.point_pass, r.runs_to_decide, r.interval_note) for r in probed] == \
           [(r.verdict, r.measured, r.point_pass, r.runs_to_decide, r.interval_note) for r in unprobed]
