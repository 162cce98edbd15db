"""Determinism: for a given seed the tables are bit-identical whatever the launcher (basic, isolated,
joblib), whether a stage was computed or read back from the cache, and however the runs are
chunked."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.run.runner import RunContext, run_experiment
from tests.helpers.assertions import assert_same_tables
from tests.helpers.config import composed_config, smoke_experiments
from tests.helpers.processes import run_pipeline

ROOT = Path(__file__).resolve().parents[1]
def in_process(artifacts: Path, name: str, *overrides: str) -> Path:
    cfg = composed_config(f"paths.artifacts={artifacts}", "record.enabled=false", *overrides)
    ctx = RunContext(artifacts / "runs" / name, artifacts, list(overrides))
    run_experiment(cfg, ctx)
    return ctx.run_dir


def sweep(artifacts: Path, *args: str) -> list[Path]:
    artifacts.mkdir(parents=True, exist_ok=True)
    proc = run_pipeline("-m", *args, artifacts=artifacts, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (where,) = (artifacts / "multirun").iterdir()
    return sorted((p for p in where.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


@pytest.mark.full
@pytest.mark.parametrize("experiment, smoke", smoke_experiments())
def test_a_cached_stage_gives_the_same_tables_as_a_recomputed_one(tmp_path, smoke_runs, experiment, smoke):
    """The session's smoke run (conftest.SmokeRuns: its stages computed and cached), the same job again
    in its artifacts root (every stage read from the cache) and with the cache off."""
    overrides = ["mc.runs=2", *smoke]
    fresh = smoke_runs(experiment)[1].run_dir
    again = in_process(smoke_runs.root, f"{experiment}/again", f"experiment={experiment}", *overrides)  # every stage cached
    uncached = in_process(tmp_path / "b", "uncached", f"experiment={experiment}", "cache.enabled=false", *overrides)
    assert_same_tables(fresh, again)
    assert_same_tables(fresh, uncached)


@pytest.mark.full
def test_the_launcher_does_not_change_the_tables(tmp_path):
    args = ["experiment=ao_vsimm_s1", "mc.seed=1,2", "mc.runs=3", "scenario.steps=40", "record.enabled=false"]
    basic = sweep(tmp_path / "basic", *args)
    joblib = sweep(tmp_path / "joblib", *args, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    isolated = sweep(tmp_path / "isolated", *args, "hydra/launcher=isolated", "hydra.launcher.n_jobs=2")
    assert len(basic) == len(joblib) == len(isolated) == 2
    for a, b, c in zip(basic, joblib, isolated):
        assert_same_tables(a, b)
        assert_same_tables(a, c)



@pytest.mark.full
@pytest.mark.parametrize("experiment, smoke", smoke_experiments())
def test_chunks_of_runs_give_the_same_tables_as_all_runs_at_once(tmp_path, experiment, smoke):
    """14 runs whole, as 13 + 1 and as 9 + 5: batches above and below 8 lanes, the last chunk shorter,
    and a run filtered alone (run 13: local index 0 of its chunk, global index 13, which is what a
    per-run random stream or a batch-dependent sum gets wrong). Chunks of one run each were the same
    check 14 times over, and a filter whose scans cost the same for 1 run as for 14 (studies 000,
    003) paid 14 scan loops for it. 14, not 9 or 13: from 3 to 13 runs the summary's Wilcoxon tests
    of tied differences (scipy, method auto) enumerate all 2^n sign flips, at 9 runs three quarters
    of study 000's job; above 13 they are asymptotic."""
    overrides = ["mc.runs=14", *smoke]
    whole = in_process(tmp_path / "whole", "whole", f"experiment={experiment}", *overrides)
    for chunk in (13, 9):
        chunked = in_process(tmp_path / f"chunk{chunk}", "chunked", f"experiment={experiment}",
                             f"mc.chunk_runs={chunk}", *overrides)
        assert_same_tables(whole, chunked)
