"""The Hydra app: ``python -m pipeline [experiment=NAME] [key=value ...]`` and ``-m`` for sweeps.

A failed job prints one paragraph and exits non-zero in a single run; in a multirun it records
its error (status.json + a failed summary row) and lets the other jobs go on.

With ``objective`` set (a parameter search, conf/tune/), the task function returns that summary
value for the sweeper; a job without one (failed, or NaN) returns None (pipeline.launch.objective says why).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig

from pipeline.errors import PipelineError
from pipeline.run.memory import exempt_survivors_from_collection, release_freed_memory
from pipeline.launch.objective import objective_value, trial_result
from pipeline.run.runner import RunContext, describe_exception, job_context, record_job_failure, run_experiment

log = logging.getLogger("pipeline")


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    ctx = job_context(cfg, hc)
    try:
        return _run(cfg, hc, multirun, ctx)
    finally:
        if multirun:          # the next job of a one-process sweep starts from what this one freed
            release_freed_memory()
            exempt_survivors_from_collection()     # later jobs' collections skip what lives on


def _run(cfg: DictConfig, hc: DictConfig, multirun: bool, ctx: RunContext) -> float | None:
    try:
        outcome = run_experiment(cfg, ctx)
        objective = objective_value(outcome.summary, cfg.get("objective"))   # a missing row fails the job
    except PipelineError as exc:
        if multirun or ctx.started:
            _fail(ctx, cfg, str(exc), None)               # the sweep lists the job; a started run says why
        else:
            _remove_unused_run_folder(ctx.run_dir, ctx.artifacts)   # refused before any work: nothing is written
        # a sweep's jobs share the terminal: say which job (as its log lines do)
        print(f"{f'[job {hc.job.num}] ' if multirun else ''}error: {exc}", file=sys.stderr)
        if not multirun:
            sys.exit(2)
        return None
    except Exception as exc:  # a bug or a numerical failure: keep the sweep alive, keep the evidence
        message, detail = describe_exception(exc)
        if multirun or ctx.started or not _folder_was_there(ctx.run_dir):   # never over another run's files
            _fail(ctx, cfg, message, detail)
        if not multirun:
            raise
        log.error("job %s failed: %s (traceback in %s)", hc.job.num, message, ctx.run_dir / "status.json")
        return None
    print(outcome.table)
    if objective is None:
        return None
    log.info("objective: %s of %s over window %s = %s", cfg.objective.series, cfg.objective.variant,
             cfg.objective.window, objective)
    result = trial_result(objective)
    if result is None:
        log.warning("objective is NaN: returned as None, a failed trial for the sweeper (a NaN aborts an Optuna sweep)")
    return result


def _remove_unused_run_folder(run_dir: Path, artifacts: Path) -> None:
    """Remove what a single run refused before any stage made: Hydra's own files (.hydra/ with the
    composed config, the job's log) and the folders it created for them while they are empty; a
    folder that was there before keeps every file it held (pipeline.launch.folders)."""
    from pipeline.launch import folders
    folders.remove_what_the_job_made(run_dir, artifacts, folders.BEFORE)


def _folder_was_there(run_dir: Path) -> bool:
    """Whether a single run's folder existed before this job (its files are not this job's to replace)."""
    from pipeline.launch import folders
    before = folders.BEFORE
    return before is None or before.made_from is None


def _fail(ctx: RunContext, cfg: DictConfig, message: str, detail: str | None) -> None:
    try:
        record_job_failure(ctx, cfg, message, detail)
    except Exception as exc:  # e.g. the disk that failed the job is still full: report the job's error, not this one
        log.error("could not record the failure in %s: %s", ctx.run_dir, describe_exception(exc)[0])


SWEEP_FLAGS = ("-m", "--multirun")


def is_sweep(argv: list[str]) -> bool:
    """Whether this command line asks Hydra for a multirun (``-m``, ``--multirun`` or
    ``hydra.mode=MULTIRUN``): only a sweep instantiates a launcher."""
    return any(a in SWEEP_FLAGS or a.replace("+", "", 1) in ("hydra.mode=MULTIRUN", "hydra.mode=multirun")
               for a in argv)


def register_isolated_launcher() -> None:
    """Make ``hydra/launcher=isolated`` (hydra_plugins/isolated_launcher) work however the package is
    installed. Hydra 1.3 finds plugins by walking the ``hydra_plugins`` namespace, and a setuptools>=64
    editable install (``pip install -e .``) serves it through an import hook that cannot be walked
    (hydra issue #2359): the module imports, but Hydra never sees the launcher or its config node.

    The config node (a dataclass, nothing imported) is registered for every command, so a config that
    names the launcher composes; the launcher itself only for a sweep, so a single job never depends
    on what only sweeps use."""
    from hydra_plugins.isolated_launcher import config  # noqa: F401  (registers the node hydra/launcher/isolated)
    if not is_sweep(sys.argv[1:]):
        return
    from hydra.core.plugins import Plugins
    plugins = Plugins.instance()          # scans first: a launcher it found is the class registered below
    from hydra_plugins.isolated_launcher import launcher
    plugins.register(launcher.IsolatedLauncher)


def entry() -> None:
    """``python -m pipeline``: Hydra's app, with one exit code (2) for every input error. Hydra exits
    1 when it refuses the command line or the config (an unknown key, a missing experiment) before
    any callback ran; our own refusals exit 2; a bug keeps Python's 1 with its traceback. What the
    config names for Hydra itself to build is checked first (pipeline.launch.hydra_targets)."""
    from pipeline.launch import folders
    from pipeline.launch.hydra_targets import check_command
    register_isolated_launcher()
    try:      # what the config names for Hydra to build (callbacks, launcher, sweeper), before Hydra builds it
        check_command(sys.argv[1:])
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    # Hydra prints its own text for a command line it refuses (an unknown key, a missing option);
    # asked to raise instead, its refusal becomes our paragraph with the close names
    # (pipeline.launch.refusals). HYDRA_FULL_ERROR=1 set by the user keeps Hydra's full traceback.
    explained = os.environ.get("HYDRA_FULL_ERROR") != "1"
    before = os.environ.get("HYDRA_FULL_ERROR")
    if explained:
        os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        main()
    except SystemExit as exc:
        if exc.code == 1 and not folders.COMPOSED:
            sys.exit(2)
        raise
    except HydraException as exc:
        if not explained or folders.COMPOSED:
            raise
        from pipeline.launch.refusals import explain
        print(f"error: {explain(exc, sys.argv[1:])}", file=sys.stderr)
        sys.exit(2)
    finally:
        if explained:
            if before is None:
                os.environ.pop("HYDRA_FULL_ERROR", None)
            else:
                os.environ["HYDRA_FULL_ERROR"] = before


if __name__ == "__main__":
    entry()
