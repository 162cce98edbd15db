"""Every experiment's reproduction targets, as the report defines them, hold at the size the
experiment names in ``target_test_runs`` (its paper's size, where that costs seconds).

The thresholds live in one place: ``report.targets`` of the experiment's YAML (and its study's
``conf/report/<study>.yaml``), which ``python -m pipeline.report --check`` evaluates too; this test
runs the experiment in process and evaluates the same queries on its tables. Targets judged on
wall time (``timed: true``) are left to the report. An experiment whose paper size costs minutes
sets ``target_test_runs: null`` and its study's own test file checks its claims at reduced size
(study 004: tests/test_reproduction_004.py; study 000's file adds the restated no-runaway checks).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.results.report import ReportSpec, evaluate_target, load_run
from tests.helpers.config import composed, EXPERIMENTS
from tests.helpers.runs import run_in_process


def _experiments() -> list[tuple[str, int]]:
    found = []
    for name in EXPERIMENTS:
        cfg = composed(name)
        runs = cfg.get("target_test_runs")
        if runs is not None and (cfg.get("report") or {}).get("targets"):
            found.append((name, int(runs)))
    return found


# The test fails when a target's values fail (or its query errs); the bootstrap resamples only
# decide between PASS and INCONCLUSIVE, which both count as held, so 200 resamples, not the
# default 2000 (which took two thirds of study 003's 100-run job), give the same outcome.
RESAMPLES = 200


@pytest.mark.full
@pytest.mark.slow
@pytest.mark.parametrize("experiment, runs", _experiments())
def test_every_untimed_target_holds(tmp_path, experiment, runs):
    _, ctx = run_in_process(tmp_path, "run", f"experiment={experiment}", f"mc.runs={runs}",
                            f"uncertainty.bootstrap_resamples={RESAMPLES}")
    tables = load_run(ctx.run_dir)
    targets = [t for t in ReportSpec.from_config(tables.config["report"]).targets if not t.timed]
    results = [evaluate_target(tables, t) for t in targets]
    # the values must pass; an interval straddling a threshold (INCONCLUSIVE) is reported, not failed
    failed = [f"{r.spec.id}: {r.verdict}, measured {r.measured} (target: {r.spec.target})"
              for r in results if r.verdict not in ("PASS", "INCONCLUSIVE") or not r.point_pass]
    assert targets and not failed, "\n".join(failed)


def test_the_experiments_with_targets_are_all_covered():
    """Every experiment with targets is tested here or names the test file that covers it."""
    for name in EXPERIMENTS:
        cfg = composed(name)
        if (cfg.get("report") or {}).get("targets") and cfg.get("target_test_runs") is None:
            assert (Path(__file__).parent / str(cfg.targets_tested_in)).is_file(), name
