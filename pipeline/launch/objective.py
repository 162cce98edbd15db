"""A parameter search's objective: one value of a job's summary, and the sweep's best job.

``objective: {variant, series, window, direction}`` (conf/config.yaml; checked before any stage by
pipeline.run.config.check_objective) names one row of summary.parquet. The task function returns that
row's value, so Hydra's Optuna sweeper (``tune=<file in conf/tune>``) optimises it; after any
multirun whose jobs set an objective, SweepSummary writes ``<sweep_dir>/best_config.yaml``: the
best job's config with its objective value, found from the jobs' own summaries by this module's
one function, the one the task function used.

What the task function returns for a job without a value: ``None``. hydra-optuna-sweeper 1.3.0
marks such a trial FAIL ("Return value must be float-castable") and goes on, and Optuna's samplers
leave failed trials out. A NaN must never reach it: with optuna 2.10.1, ``study.tell`` refuses NaN
and the sweeper's own failure path then passes the NaN again, which raises out of the whole sweep.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shlex
from pathlib import Path
from typing import Any, Mapping

import polars as pl
import yaml

from pipeline.errors import ConfigError
from pipeline.storage.run_tables import read_run_table
from pipeline.storage.store import atomic_write_text, read_yaml

log = logging.getLogger("pipeline.launch.objective")

BEST_CONFIG = "best_config.yaml"


def objective_value(summary: pl.DataFrame, objective: Mapping[str, Any] | None) -> float | None:
    """The summary's value for ``objective`` (NaN where the run left it undefined), or None when
    there is no objective. A summary without that row raises ConfigError naming what it holds."""
    if objective is None:
        return None
    variant, series, window = objective["variant"], objective["series"], objective.get("window")
    rows = summary.filter((pl.col("variant_key") == variant) & (pl.col("series") == series)
                          & (pl.col("window").is_null() if window is None else pl.col("window") == window))
    if rows.height != 1:
        held = summary.filter((pl.col("variant_key") == variant) & (pl.col("series") == series))["window"]
        found = (f"it holds that series over the windows {held.to_list()}" if held.len()
                 else f"its series for that variant are {sorted(summary.filter(pl.col('variant_key') == variant)['series'].unique().to_list())}")
        raise ConfigError(f"objective: the summary has {rows.height} rows for variant {variant!r}, series {series!r}, "
                          f"window {window!r}, not one, so there is no objective value; {found}. Set objective.series "
                          f"and objective.window to one of those.")
    value = rows["value"][0]
    return math.nan if value is None else float(value)


def trial_result(value: float | None) -> float | None:
    """What the task function returns for an objective value: the value, or None for NaN (see the
    module docstring: a NaN would abort an Optuna sweep; None fails only its trial)."""
    if value is None or math.isnan(value):
        return None
    return value


@dataclasses.dataclass(frozen=True)
class JobObjective:
    """One job folder of a sweep: its status.json, its config.yaml (None where it wrote none) and the
    objective that config names (None without one)."""
    job_dir: Path
    status: dict[str, Any]
    config: dict[str, Any] | None
    objective: dict[str, Any] | None


def job_objectives(sweep_dir: Path) -> list[JobObjective]:
    """Every job folder of the sweep (a status.json), each config.yaml read once."""
    jobs = []
    for status_path in sorted(Path(sweep_dir).glob("*/status.json")):
        config_path = status_path.parent / "config.yaml"
        config = read_yaml(config_path) if config_path.is_file() else None
        objective = config.get("objective") if isinstance(config, dict) else None
        jobs.append(JobObjective(status_path.parent, json.loads(status_path.read_text()), config, objective))
    return jobs


def best_job(sweep_dir: Path, jobs: list[JobObjective] | None = None) -> dict[str, Any] | None:
    """The sweep's best ok job by the objective its config names, or None when no job has a finite
    objective value. Every job must name the same objective (values of different objectives do not
    compare); a sweep that varies it gets ConfigError. ``jobs``: job_objectives(sweep_dir) when the
    caller has read them already."""
    candidates, objectives = [], {}
    for job in job_objectives(sweep_dir) if jobs is None else jobs:
        if job.status.get("status") != "ok" or job.config is None or job.objective is None:
            continue
        objectives[job.job_dir.name] = job.objective
        try:
            # checked against the job folder too: a summary rewritten or copied in is not this job's
            value = objective_value(read_run_table(job.job_dir, "summary.parquet", job.status)[0], job.objective)
        except Exception as exc:       # a damaged, refused or missing summary: this job cannot be compared
            log.warning("job %s left out of the best job: %s", job.job_dir.name, exc)
            continue
        if value is not None and not math.isnan(value):
            candidates.append((value, job.job_dir, job.status, job.config))
    if len({json.dumps(o, sort_keys=True) for o in objectives.values()}) > 1:
        raise ConfigError(f"objective: the jobs of {sweep_dir} name different objectives ({objectives}); their values "
                          f"do not compare, so the sweep has no best job. Sweep the parameters, not the objective.")
    if not candidates:
        return None
    objective = next(iter(objectives.values()))
    pick = min if objective["direction"] == "minimize" else max
    value, job_dir, status, config = pick(candidates, key=lambda c: c[0])
    return {"job_dir": job_dir, "job_num": status.get("job_num"), "overrides": status.get("overrides", []),
            "objective": {**objective, "value": value}, "compared": len(candidates), "config": config}


def write_best_config(sweep_dir: Path, jobs: list[JobObjective] | None = None) -> dict[str, Any] | None:
    """Write ``<sweep_dir>/best_config.yaml`` (best_trial: job, overrides, objective with its value;
    config: the job's resolved config.yaml) and return the best job, or None (nothing written)."""
    best = best_job(sweep_dir, jobs)
    if best is None:
        return None
    objective = best["objective"]
    window = "no window" if objective.get("window") is None else f"window {objective['window']}"
    header = (f"# The best job of the sweep in this folder by its objective: {objective['series']} of variant "
              f"{objective['variant']} over {window}, {objective['direction']}d over {best['compared']} jobs.\n"
              f"# config: the job's own config.yaml (resolved). Run it again alone:\n"
              f"#   python -m pipeline {' '.join(shlex.quote(o) for o in best['overrides'])}\n")
    document = {"best_trial": {"job_num": best["job_num"], "job_dir": str(Path(best["job_dir"]).resolve()),
                               "overrides": best["overrides"], "objective": objective},
                "config": best["config"]}
    atomic_write_text(header + yaml.safe_dump(document, sort_keys=False, allow_unicode=True),
                      Path(sweep_dir) / BEST_CONFIG)
    return best
