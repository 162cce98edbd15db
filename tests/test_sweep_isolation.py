"""A sweep job whose process is killed (SIGKILL, as the out-of-memory killer ends one) fails that job
only: with hydra/launcher=isolated the other jobs run and the sweep summary lists the killed one as
failed, naming the signal. (hydra/launcher=joblib fails this test: the dead loky worker raises
TerminatedWorkerError out of the whole sweep, the later jobs never run, the running ones stay
``running`` and no sweep_summary.parquet is written. Issue 16, item 8.)"""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pytest

from tests.helpers.processes import run_pipeline

# full tier (tests/helpers/tiers.py): sweeps across processes, killed jobs
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]
LAUNCHER = "isolated"
KILLED_JOB = 1            # the one job of three whose filter SIGKILLs its own process


@pytest.mark.smoke          # the isolated launcher sends each job with cloudpickle: what joblib 1.6 moved
def test_a_killed_job_fails_alone_and_the_sweep_summary_lists_it(tmp_path):
    proc = run_pipeline(
        "-m", "mc.runs=2", "scenario.steps=20",
        "record.enabled=false", "variants=[fsimm]", "filters.fsimm._target_=tests.faulty_filters.SelfKillingFSIMM", "plugins.packages=[tests]",
        "+filters.fsimm.sigkill=false,true,false", f"hydra/launcher={LAUNCHER}", "hydra.launcher.n_jobs=2",
        artifacts=tmp_path, timeout=120)
    assert proc.returncode == 1, proc.stderr[-3000:]      # the sweep returns, reporting its one failed job
    assert "3 jobs, 2 ok, 1 failed" in proc.stderr, proc.stderr[-3000:]

    (sweep,) = (tmp_path / "multirun").iterdir()
    status = {int(p.parent.name): json.loads(p.read_text()) for p in sweep.glob("*/status.json")}
    assert {job: s["status"] for job, s in status.items()} == {0: "ok", 1: "failed", 2: "ok"}
    killed = status[KILLED_JOB]
    assert "killed by signal 9 (SIGKILL" in killed["error"] and killed["job_num"] == KILLED_JOB
    assert "+filters.fsimm.sigkill=True" in killed["overrides"]

    summary = pl.read_parquet(sweep / "sweep_summary.parquet")
    by_job = summary.group_by("job_num").agg(pl.col("status").unique(), pl.col("error").first(),
                                             pl.col("filters.fsimm.sigkill").first()).sort("job_num")
    assert by_job["job_num"].to_list() == [0, 1, 2]
    assert by_job["status"].to_list() == [["ok"], ["failed"], ["ok"]]
    assert by_job["filters.fsimm.sigkill"].to_list() == [False, True, False]
    assert "SIGKILL" in by_job["error"][KILLED_JOB]
