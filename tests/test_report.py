"""The reproduction report (python -m pipeline.report): built from a small run's stored tables,
with every declared target's measured value and verdict, the figures, the limits section; a sweep
gets an index; a bad report definition is refused before any stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.errors import ConfigError
from pipeline.results.report import ReportError, ReportSpec, TargetSpec, evaluate_target, load_run, main, write_reports
from tests.helpers.report_targets import CROSS, RATIO, SMALL, THRESHOLD, around, tables_with_resamples
from tests.helpers.runs import run_in_process
from tests.helpers.processes import run_module



@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    _, ctx = run_in_process(root, "s2", "experiment=ao_vsimm_s2_ratios", *SMALL)
    return ctx.run_dir


def test_the_report_shows_every_target_with_its_measured_value_and_the_figures(small_run, tmp_path):
    (report,), index = write_reports(small_run, tmp_path / "out")
    assert index is None and report.path == tmp_path / "out" / "report.md"
    text = report.path.read_text()
    spec = ReportSpec.from_config(load_run(small_run).config["report"])
    ids = {t.id for t in spec.targets}
    assert ids == {"models_per_step", "s2_vsimm_fails", "s2_m3_not_reached", "s2_ao_vsimm_close", "s2_new_old_close"}
    assert {t.spec.id for t in report.targets} == ids
    for target in report.targets:
        assert target.verdict in ("PASS", "FAIL", "INCONCLUSIVE"), (target.spec.id, target.measured)   # no query error
        row = next(line for line in text.splitlines() if line.startswith(f"| {target.spec.id} |"))
        assert target.measured in row and target.verdict in row
    # the declared figures and the limits figures, each a PNG beside the report and linked from it
    names = {p.name for p in report.figures}
    assert {"acceleration_rmse_x.png", "acceleration_rmse_y.png", "models_per_step.png", "limit_nees.png",
            "limit_nis.png", "limit_rmse_over_bound.png"} <= names
    for path in report.figures:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"]({path.name})" in text
    assert "## How far from the limit" in text and "share_in_band" in text and "| FSIMM | nis |" in text
    assert "query <code>s2_vsimm_fails</code>" in text                     # each number's query is shown


def test_a_query_that_fails_or_returns_no_row_is_an_error_not_a_pass(small_run):
    tables = load_run(small_run)
    broken = evaluate_target(tables, TargetSpec("x", "t", "p", "SELECT nothing FROM nowhere"))
    empty = evaluate_target(tables, TargetSpec("y", "t", "p", "SELECT 'a' AS measured, true AS pass FROM wide WHERE 1 = 0"))
    assert broken.verdict == "ERROR" and "query failed" in broken.measured
    assert empty.verdict == "ERROR" and "0 row(s)" in empty.measured


@pytest.mark.full
def test_a_sweep_gets_one_report_per_run_and_an_index(tmp_path):
    sweep = tmp_path / "multirun" / "2026-01-01"          # the layout of a Hydra sweep: <sweep>/<job_num>/
    sweep.mkdir(parents=True)
    for job, overrides in (("0", ["experiment=ao_vsimm_s1", "scenario.steps=40"]), ("1", ["experiment=mie_los"])):
        run_in_process(tmp_path, job, "mc.runs=2", *overrides)
        (tmp_path / "runs" / job).rename(sweep / job)
    assert main([str(sweep)]) == 0
    index = (sweep / "index.md").read_text()
    assert "ao_vsimm_s1" in index and "mie_los" in index and "(0/report/report.md)" in index
    assert (sweep / "1" / "report" / "report.md").read_text().count("| detection_peaks |") == 1
    assert main(["--latest", "--artifacts", str(tmp_path)]) == 0


def test_latest_is_the_newest_of_single_runs_and_sweeps(tmp_path, capsys):
    """python -m pipeline ... then python -m pipeline.report --latest: a single run counts (it used to
    look under multirun/ only and refuse)."""
    assert main(["--latest", "--artifacts", str(tmp_path)]) == 2
    assert "no run under" in capsys.readouterr().err
    older_sweep = tmp_path / "multirun" / "2026-01-01_10-00-00_000000"
    older_sweep.mkdir(parents=True)
    run_in_process(tmp_path, "job", "experiment=mie_los", "mc.runs=2")
    newest = tmp_path / "runs" / "mie_los" / "2026-01-02_10-00-00_000000"
    newest.parent.mkdir(parents=True)
    (tmp_path / "runs" / "job").rename(newest)
    assert main(["--latest", "--artifacts", str(tmp_path)]) == 0
    assert "mie_los:" in capsys.readouterr().out and (newest / "report" / "report.md").is_file()


def test_check_fails_the_command_when_a_target_fails(small_run, tmp_path):
    """--check: exit 1 when any target is FAIL or ERROR (at 3 runs of 60 steps some S2 targets fail)."""
    proc = run_module("pipeline.report", str(small_run), "--out", str(tmp_path), "--check", timeout=120)
    results = load_run(small_run)
    verdicts = [evaluate_target(results, t).verdict for t in ReportSpec.from_config(results.config["report"]).targets]
    assert proc.returncode == (1 if set(verdicts) & {"FAIL", "ERROR"} else 0), proc.stdout + proc.stderr
    assert "targets pass" in proc.stdout


def test_a_missing_folder_or_an_unfinished_run_is_a_clear_error(tmp_path, capsys):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.parquet").write_bytes(b"")
    assert main([str(tmp_path / "run")]) == 2
    assert "not a finished run folder" in capsys.readouterr().err


@pytest.mark.parametrize("override, message", [
    ("+report.targets.bad={target: t, paper: p}", "report.targets.bad: keys"),
    ("+report.targets.bad={target: t, paper: p, query: 'SELECT 1', timed: sometimes}", "report.targets.bad.timed: 'sometimes'"),
    ("+report.findings.bad={finding: f, query: 'SELECT 1'}", "report.findings.bad: keys"),
    ("+report.figures.bad={query: acceleration_rmse_by_step, x: time}", "report.figures.bad: missing ['y']"),
    ("+report.figures.bad={query: 'not sql', x: a, y: b}", "neither SQL nor a name"),
    ("+report.figures.bad={query: acceleration_rmse_by_step, x: time, y: value, kind: pie}", "kind: 'pie'"),
])
def test_a_bad_report_definition_is_refused_before_any_stage(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        run_in_process(tmp_path, "bad", "experiment=ao_vsimm_s1", "mc.runs=2", override)
    assert not (tmp_path / "runs" / "bad" / "summary.parquet").exists()


def test_report_spec_rejects_a_target_list():
    with pytest.raises(ReportError, match="must map an id"):
        ReportSpec.from_config({"targets": [{"target": "t", "paper": "p", "query": "SELECT 1"}]})


def test_every_experiment_declares_targets_that_parse():
    from omegaconf import OmegaConf

    from tests.helpers.config import composed, EXPERIMENTS
    for name in EXPERIMENTS:
        cfg = composed(name)
        spec = ReportSpec.from_config(OmegaConf.to_container(cfg.report, resolve=True))
        assert spec.targets, f"{name} declares no reproduction targets"
        assert int(cfg.paper_runs) >= 50, name


def test_current_rechecks_a_stored_run_against_the_definitions_in_conf(small_run, tmp_path):
    """--current: the run's tables, today's report definition (here the same: the same targets)."""
    from pipeline.results.report import write_run_report
    recorded = write_run_report(small_run, tmp_path / "recorded")
    current = write_run_report(small_run, tmp_path / "current", current=True)
    assert [(t.spec.id, t.measured, t.verdict) for t in current.targets] == \
        [(t.spec.id, t.measured, t.verdict) for t in recorded.targets]


# ---- targets judged with the values' uncertainty (issue 18) ---------------------------------------
def test_a_target_is_pass_fail_or_inconclusive_by_the_share_of_passing_resamples():
    assert evaluate_target(tables_with_resamples(around(9.0, 0.2)), THRESHOLD).verdict == "PASS"
    assert evaluate_target(tables_with_resamples(around(11.0, 0.2)), THRESHOLD).verdict == "FAIL"
    straddling = evaluate_target(tables_with_resamples(around(9.8, 0.2)), THRESHOLD)
    assert straddling.verdict == "INCONCLUSIVE" and straddling.point_pass
    # margin 0.2 over a standard error of 0.2: z ~ 1, so about (1.96 / 1)^2 x 100 runs
    assert 300 <= int(straddling.runs_to_decide.split()[1]) <= 500
    # the values pass but most resamples fail: no number of runs would make the values' verdict hold
    leaning = around(10.3, 0.2)
    leaning[0] = 9.99
    assert "lean against" in evaluate_target(tables_with_resamples(leaning), THRESHOLD).runs_to_decide


def test_a_target_over_a_window_free_value_is_judged_on_its_value():
    spec = TargetSpec("c", "t", "p", """SELECT 'x' AS measured, COUNT(*) = 1 AS pass FROM summary""")
    result = evaluate_target(tables_with_resamples(around(9.8, 0.2)), spec)
    assert result.verdict == "PASS" and "reads no summary interval" in result.interval_note


def test_a_run_without_stored_resamples_is_judged_on_its_values_and_says_so():
    from pipeline.results.report import RunTables, pivot_summary
    summary = pl.DataFrame({"variant_key": ["a"], "series": ["position_rmse"], "window": ["all"], "value": [9.8]})
    result = evaluate_target(RunTables(Path("."), "x", {}, {"runs": 100}, summary, pl.DataFrame(),
                                       pivot_summary(summary)), THRESHOLD)
    assert result.verdict == "PASS" and "stored no resamples" in result.interval_note


def test_a_paired_target_is_judged_on_joint_resamples():
    rng = np.random.default_rng(1)
    common = 20.0 + rng.normal(0, 1.0, 401)                 # the runs' spread (5 %), shared by both variants
    a, b = common * 1.001, common.copy()                     # a differs by 0.1 %, whatever the runs
    result = evaluate_target(tables_with_resamples(a, b), RATIO)
    assert result.verdict == "PASS" and "100.0 % of 400" in result.interval_note
    # the same spreads resampled independently: the ratio's spread is the runs' (~7 %), undecided
    unpaired = evaluate_target(tables_with_resamples(a, np.concatenate([b[:1], rng.permutation(b[1:])])), RATIO)
    assert unpaired.verdict == "INCONCLUSIVE"


def test_an_inconclusive_paired_target_names_the_runs_that_would_decide_it():
    rng = np.random.default_rng(2)
    common = 20.0 + rng.normal(0, 1.0, 401)
    a = common * (1.015 + rng.normal(0, 0.005, 401))         # 1.5 % +- 0.5 %: z = 1 against the 2 % margin
    a[0] = common[0] * 1.015
    result = evaluate_target(tables_with_resamples(a, common), RATIO)
    assert result.verdict == "INCONCLUSIVE" and result.point_pass
    runs = int(result.runs_to_decide.split()[1])
    assert 250 <= runs <= 600                                 # (1.96 / ~1)^2 x 100 runs


def test_a_target_that_joins_the_wide_table_to_itself_is_judged_resample_by_resample():
    """On the stacked resamples the self-join pairs every resample with every other (400 x 400 rows),
    so each resample is queried on its own; the share counts each resample's own verdict."""
    b = np.full(401, 20.0)
    a = np.concatenate([[19.0], np.full(389, 19.0), np.full(11, 21.0)])     # 389 of 400 resamples pass
    result = evaluate_target(tables_with_resamples(a, b), CROSS)
    assert result.verdict == "INCONCLUSIVE" and "97.2 % of 400" in result.interval_note
    a[-1] = 19.0                                                             # 390 of 400: 97.5 %, the bar
    result = evaluate_target(tables_with_resamples(a, b), CROSS)
    assert result.verdict == "PASS" and "97.5 % of 400" in result.interval_note


def test_the_resample_queries_run_where_the_system_has_no_affinity_mask(monkeypatch):
    """macOS and Windows have no os.sched_getaffinity: the report used it unguarded (AttributeError
    out of the report) to size its threads."""
    import os
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    b = np.full(401, 20.0)
    a = np.concatenate([[19.0], np.full(395, 19.0), np.full(5, 21.0)])
    result = evaluate_target(tables_with_resamples(a, b), CROSS)
    assert result.verdict == "PASS" and "98.8 % of 400" in result.interval_note
