"""Single runs in this process (pipeline.run.runner.run_experiment on a composed config), as
``python -m pipeline`` makes them but without its process: cheaper wherever the claim is not about
the command line (tests.helpers.processes starts that)."""

from __future__ import annotations

from pathlib import Path

from tests.helpers.config import composed_config

# study 004 shortened: 100 s of the sonobuoy field, 2 runs of 100 particles
SONOBUOY_SHORT = ["scenario.duration=100", "mc.runs=2", "target_model.particles=100"]


def job(tmp_path: Path, name: str, *overrides: str):
    """(cfg, ctx) of a single run ``runs/<name>`` under ``tmp_path`` (the recording off), not run."""
    from pipeline.run.runner import RunContext
    cfg = composed_config(f"paths.artifacts={tmp_path}", "record.enabled=false", *overrides)
    return cfg, RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))


def run_in_process(tmp_path: Path, name: str, *overrides: str):
    """(RunOutcome, RunContext) of the single run ``runs/<name>`` (the recording off)."""
    from pipeline.run.runner import run_experiment
    cfg, ctx = job(tmp_path, name, *overrides)
    return run_experiment(cfg, ctx), ctx


def run_study(tmp_path: Path, name: str, *overrides: str, experiment: str, record: bool = False):
    """(RunOutcome, RunContext) of ``experiment`` as the run ``runs/<name>``, the recording off
    unless ``record``; the context lists ``overrides`` only (the experiment is the caller's)."""
    from pipeline.run.runner import RunContext, run_experiment
    cfg = composed_config(f"experiment={experiment}", f"paths.artifacts={tmp_path}",
                          f"record.enabled={str(record).lower()}", *overrides)
    ctx = RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))
    return run_experiment(cfg, ctx), ctx
