"""Re-run a stored run with its own config into the artifacts tree: ``python -m pipeline.rerun <run> [key=value ...]``.

The run's ``config.yaml`` (resolved, every value as it ran; moved class names mapped by
pipeline.run.stored) is the config, the overrides change values of it (``mc.runs=100``; ``+key=value``
adds one), and the new run goes where ``python -m pipeline`` puts one: ``<artifacts>/runs/<experiment>/<time>/``
of the artifacts tree the stored run is in (``paths.artifacts=DIR`` for another), so
``python -m pipeline.query`` lists it beside the stored one. Hydra's own way,
``python -m pipeline --config-path <run>/.hydra``, composes without this project's Hydra settings
and writes to ``outputs/``, where no query looks. The stages are cached as for any run: a re-run
with nothing changed reuses every stage's table.

A config group choice (``experiment=``, ``scenario=s2``, ``+filter@filters.x=...``) composes a new
config rather than changing this one: that is ``python -m pipeline``'s job, and is refused here.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import sys
from pathlib import Path
from typing import Sequence

from omegaconf import DictConfig, OmegaConf

from pipeline.errors import ConfigError, PipelineError


class RerunError(PipelineError):
    """A folder that is not a stored run, or an override rerun cannot apply."""


def artifacts_of(run_dir: Path, status: dict) -> Path:
    """The artifacts tree a stored run is in: its folder less its ``run_id`` (runs/<experiment>/<time>,
    or multirun/<time>/<job>); its parent's parent's parent where the run_id does not fit."""
    resolved = run_dir.resolve()
    run_id = Path(str(status.get("run_id") or ""))
    parts = run_id.parts
    if parts and not run_id.is_absolute() and resolved.parts[-len(parts):] == parts:
        return Path(*resolved.parts[:-len(parts)])
    return resolved.parents[2]


def apply_overrides(cfg: DictConfig, overrides: Sequence[str]) -> None:
    """Set each ``key=value`` (``+key=value``: a new key) on ``cfg``, in place; a value is read as
    YAML (Hydra's overrides read the same: ``3`` an int, ``[a,b]`` a list, ``{k: v}`` a mapping)."""
    from pipeline.launch.refusals import close_names
    for override in overrides:
        add = override.startswith("+")
        key, eq, text = override.lstrip("+").partition("=")
        if not eq or not key or key.startswith("~"):
            raise RerunError(f"{override}: an override of a stored run is key=value (or +key=value for a new key), "
                             f"e.g. mc.runs=100.")
        if "@" in key or key.startswith("hydra"):
            raise RerunError(f"{override}: a config group choice composes a new config; rerun changes values of the "
                             f"stored one. Compose it with python -m pipeline {override} (and the stored run's "
                             f"overrides, status.json 'overrides').")
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        exists = isinstance(node, DictConfig) and leaf in node
        if not exists and not add:
            keys = [str(k) for k in node.keys()] if isinstance(node, DictConfig) else []
            close = close_names(leaf, keys)
            raise RerunError(f"{override}: the stored config has no key {key!r}"
                             + (f"; did you mean {' or '.join(repr(f'{parent}.{c}' if parent else c) for c in close)}?"
                                if close else ".")
                             + f" To add a new key, write +{key}={text}.")
        current = OmegaConf.select(cfg, key) if exists else None
        value = OmegaConf.create(f"v: {text}").v if text else None
        if isinstance(current, DictConfig) and not isinstance(value, DictConfig):
            raise RerunError(f"{override}: {key!r} is a config node ({current.get('_target_', 'a mapping')}); choosing "
                             f"another file of a config group composes a new config: python -m pipeline {override}. "
                             f"rerun sets values, e.g. {key}.<field>=...")
        OmegaConf.update(cfg, key, value, merge=False, force_add=True)


def rerun(run_dir: Path, overrides: Sequence[str], now: dt.datetime | None = None):
    """Run the stored run's config with ``overrides`` into its artifacts tree; (the outcome, its RunContext)."""
    from pipeline.run.runner import RunContext, record_job_failure, run_experiment
    from pipeline.run.stored import stored_config

    run_dir = Path(run_dir)
    status_path = run_dir / "status.json"
    if not (run_dir / "config.yaml").is_file() or not status_path.is_file():
        raise RerunError(f"{run_dir}: not a run folder (no config.yaml / status.json); give a folder under "
                         f"<artifacts>/runs/<experiment>/ (python -m pipeline.query list shows them).")
    status = json.loads(status_path.read_text())
    cfg = stored_config(run_dir)
    if not any(o.lstrip("+~").startswith("plugins.packages") for o in overrides):   # an override is the user's word
        from pipeline.run.stored import check_stored_packages
        check_stored_packages(cfg, run_dir, (), f"python -m pipeline.rerun {run_dir} plugins.packages=[{{packages}}]")
    artifacts = artifacts_of(run_dir, status)
    cfg.paths.artifacts = str(artifacts)
    apply_overrides(cfg, overrides)
    artifacts = Path(str(cfg.paths.artifacts)).resolve()
    experiment = str(cfg.get("experiment_name"))
    stamp = (now or dt.datetime.now()).strftime("%Y-%m-%d_%H-%M-%S_%f")
    from pipeline.launch.folders import check_writable
    check_writable(artifacts / "runs" / experiment, "paths.artifacts", cfg.paths.artifacts)
    stored_overrides = [str(o) for o in status.get("overrides") or []]
    ctx = RunContext(artifacts / "runs" / experiment / stamp, artifacts,
                     [*stored_overrides, *overrides])
    logging.getLogger("pipeline").info("rerun of %s with its config.yaml%s", status.get("run_id") or run_dir,
                                       f" and {' '.join(overrides)}" if overrides else "")
    try:
        return run_experiment(cfg, ctx), ctx
    except Exception as exc:
        if ctx.started:         # its folder exists: it says why, as a job of python -m pipeline does
            from pipeline.run.runner import describe_exception
            message, detail = (str(exc), None) if isinstance(exc, PipelineError) else describe_exception(exc)
            record_job_failure(ctx, cfg, message, detail)
        raise


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.rerun", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a stored run's folder (artifacts/runs/<experiment>/<time>, or a sweep job's)")
    parser.add_argument("overrides", nargs="*", help="key=value changes of its config (+key=value adds one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s] %(message)s", datefmt="%H:%M:%S", stream=sys.stderr)
    try:
        outcome, ctx = rerun(Path(args.run), args.overrides)
    except (PipelineError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(outcome.table)
    print(f"written to {ctx.run_dir}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
