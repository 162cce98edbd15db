"""Load: a 50-job sweep through the joblib launcher completes, every job is queryable, and the
workers' memory stays bounded (no growth from job to job in the pooled processes)."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest

from tests.helpers.processes import run_pipeline

# full tier (tests/helpers/tiers.py): a fifty-job sweep's memory
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]
JOBS = 50


@pytest.mark.slow
def test_fifty_job_joblib_sweep_completes_with_bounded_memory(tmp_path):
    proc = run_pipeline("-m", f"mc.seed=range({JOBS})", "mc.runs=2", "scenario.steps=30", "record.enabled=false",
                        "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", artifacts=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]

    from pipeline.results.query import query
    jobs = query("""SELECT job_num, COUNT(*) AS rows, MIN(status) AS status, MIN("mc.seed") AS seed
                    FROM summary GROUP BY job_num ORDER BY job_num""", root=tmp_path)
    assert jobs["job_num"].to_list() == list(range(JOBS))
    assert set(jobs["status"]) == {"ok"} and jobs["seed"].to_list() == list(range(JOBS))
    assert jobs["rows"].min() == jobs["rows"].max() > 0          # every job wrote its whole summary

    (sweep,) = (tmp_path / "multirun").iterdir()
    status = [json.loads((sweep / str(j) / "status.json").read_text()) for j in range(JOBS)]
    peaks = [s["peak_rss_mb"] for s in status]
    # each job reports its process's high-water mark; pooled workers run many jobs, so a leak shows
    # as the late jobs' marks climbing above the early ones'
    early, late = statistics.median(peaks[:10]), statistics.median(peaks[-10:])
    print(f"\npeak RSS per job: min {min(peaks):.0f} MB, max {max(peaks):.0f} MB; median of the first 10 "
          f"{early:.0f} MB, of the last 10 {late:.0f} MB")
    assert max(peaks) < 1024, peaks
    assert late - early < 64, (early, late)
