"""The thin runner: owns paths, the stage cache, provenance and atomic writes.

scenario (truth) -> measure (detections) -> track (one estimate per variant) -> evaluate
(metrics, summary) -> record (.rrd). Each stage is a pure function of its inputs; the runner
keys each output by the stage's resolved config and its inputs' keys, so a sweep over a filter
parameter re-uses the scenario and the measurements, and every variant sees identical inputs.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import math
import os
import sys
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import polars as pl
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from pipeline.storage import fingerprint, schemas
from pipeline.contract import JobInputs, RecordingInputs, Study, VariantInputs
from pipeline.run.config import build, check_added_keys, check_objective, compute_reference, flatten, selected_variants, validate
from pipeline.run import provenance as provenance_of_run
from pipeline.run.environment import environment, table_metadata as environment_metadata
from pipeline.errors import ConfigError, StorageError
from pipeline.storage.estimates import StoredEstimates, recorded_runs
from pipeline.evaluation.evaluate import (Window, compute_row, group_reached, metrics_frame, models_per_step, reference_rows,
                               summary_row, summary_table, variant_rows)
from pipeline.evaluation.timing import BUDGET_S, PASSES, Timing, time_passes
from pipeline.evaluation.evaluate import resolved as per_step_values
from pipeline.evaluation.uncertainty import CONFIDENCE, RESAMPLES, resample
from pipeline.evaluation.faults import FaultChecks, fault_summary
from pipeline.run.memory import check as check_memory
from pipeline.run.memory import own_peak_rss_mb
from pipeline.evaluation.metrics import with_breakdown
from pipeline.run.process import identity as process_identity
from pipeline.run.progress import Reporter, choose_mode
from pipeline.views.tables import ReportContext, format_summary
from pipeline.run.stages import declare as declare_stages
from pipeline.studies.single_target import SingleTargetStudy, filter_chunks, flags_from_table
from pipeline.storage.run_tables import STAGE_KEYS
from pipeline.storage.store import (StageCache, atomic_write_parquet, atomic_write_text, inside, package_version, publish,
                            read_table, stable_hash)
from pipeline.storage.keys import stage_key

log = logging.getLogger("pipeline")


@dataclass
class RunContext:
    """Where a run writes and how it identifies itself in every table."""

    run_dir: Path
    artifacts: Path
    overrides: list[str]
    sweep: str | None = None
    job_num: int | None = None
    started: bool = False          # set once this job has written its status.json (run_experiment)
    tables_written: bool = False   # set once it has written its summary and the other computed tables

    @property
    def run_id(self) -> str:
        try:
            return self.run_dir.resolve().relative_to(self.artifacts.resolve()).as_posix()
        except ValueError:
            return self.run_dir.as_posix()


@dataclass
class RunOutcome:
    summary: pl.DataFrame
    metrics: pl.DataFrame
    table: str
    comparisons: pl.DataFrame | None = None


def _now() -> str:
    return dt.datetime.now().isoformat(timespec="seconds")


def write_status(ctx: RunContext, experiment: str, status: str, *, config_hash: str = "", runs: int | None = None,
                 error: str | None = None, started_at: str | None = None, detail: str | None = None,
                 peak_rss_mb: float | None = None, provenance: dict | None = None,
                 stage_keys: Mapping[str, str] | None = None, scenario: str | None = None) -> None:
    """``peak_rss_mb``: the job's process's peak memory when another process writes its status (the
    launcher, for a job whose process died); by default this process's. ``stage_keys``: the cache key of
    each stage table the run folder holds, by its name there (``estimates/fsimm.parquet``), for readers
    to check each table against its name (pipeline.storage.run_tables), ``mtt-query diff`` to pair runs
    by and ``mtt-query gc`` to keep; written as the stages finish. ``provenance``
    (pipeline.run.provenance): which code made the run. ``scenario``: what the scenario that ran says it is
    (its ``describe()``: a recorded flight's file, window and radar site), for the report's header. All
    three are kept from the previous status when not given."""
    path = ctx.run_dir / "status.json"
    previous = json.loads(path.read_text()) if path.exists() else {}
    record = {
        "run_id": ctx.run_id, "experiment": experiment, "status": status, "error": error,
        "started_at": started_at or previous.get("started_at") or _now(),
        "finished_at": None if status == "running" else _now(), "overrides": ctx.overrides,
        "config_hash": config_hash or previous.get("config_hash", ""), "sweep": ctx.sweep, "job_num": ctx.job_num,
        "runs": runs if runs is not None else previous.get("runs"), "package_version": package_version(),
        # the process's high-water mark so far (a pooled sweep worker's covers its earlier jobs too)
        "peak_rss_mb": round(peak_rss_mb if peak_rss_mb is not None else own_peak_rss_mb(), 1),
        # who runs it: a reader tells a job still running from one whose process was killed (pipeline.run.process)
        "process": process_identity(),
        # the software it ran with: the lock's hash, the direct dependencies' versions and any that differ
        "environment": environment(),
        # which code made it (git commit, dirty diff, user packages) and how it was called
        "provenance": provenance if provenance is not None else previous.get("provenance"),
        STAGE_KEYS: dict(stage_keys) if stage_keys is not None else previous.get(STAGE_KEYS, {}),
    }
    described = scenario if scenario is not None else previous.get("scenario")
    if described:
        record["scenario"] = described
    if detail:
        record["traceback"] = detail
    try:
        atomic_write_text(json.dumps(record, indent=2), path)
    except StorageError:
        # a full disk has no room for a new file, but this job's own status.json has its bytes: a job
        # that ends must not stay 'running' there (issue 37)
        if status == "running" or not path.exists() or not _overwrite_in_place(path, record):
            raise


def _overwrite_in_place(path: Path, record: dict) -> bool:
    """Write ``record`` over the bytes ``path`` already has (the file's size unchanged, padded with
    spaces, so no new block is needed): the whole record, else without its traceback and environment.
    False if neither fits or the write fails."""
    size = path.stat().st_size
    compact = {k: v for k, v in record.items() if k not in ("traceback", "environment")}
    for candidate in (record, compact | {"note": "written over the running status in place: the disk was full"}):
        data = json.dumps(candidate, indent=2).encode()
        if len(data) + 1 > size:
            continue
        try:
            with open(path, "r+b") as f:
                f.write(data + b" " * (size - len(data) - 1) + b"\n")
                f.flush()
                os.fsync(f.fileno())
        except OSError:
            return False
        return True
    return False


def _provenance(df: pl.DataFrame, ctx: RunContext, experiment: str, config_hash: str, status: str = "ok",
                error: str | None = None) -> pl.DataFrame:
    return df.with_columns(
        pl.lit(ctx.run_id).alias("run_id"), pl.lit(experiment).alias("experiment"), pl.lit(status).alias("status"),
        pl.lit(error, dtype=pl.String).alias("error"), pl.lit(config_hash).alias("config_hash"),
        pl.lit(" ".join(ctx.overrides)).alias("overrides"), pl.lit(ctx.sweep, dtype=pl.String).alias("sweep"),
        pl.lit(ctx.job_num, dtype=pl.Int32).alias("job_num"),
    )


def _config_columns(resolved: dict) -> dict[str, Any]:
    # filters.<v>.models repeats the top-level models node (interpolated): keep it once; the report
    # node holds reference tables (a paper's numbers), the objective what a search reads: neither is
    # a parameter of the experiment
    return {f"{k}": v for k, v in flatten(resolved, skip=("filters.*.models", "description", "report", "smoke",
                                                          "objective")).items()}


def _windows(cfg: DictConfig, key: str, K: int, warn: bool = False) -> list[Window]:
    """The summary windows over steps 0..K-1. ``all`` means all: it ends at the last step whatever its
    configured end. A window that starts after the last step is left out (it was a row of NaN), one
    that ends after it is clipped; with ``warn`` each is logged by name."""
    windows = []
    for name, bounds in (cfg.metrics.get(key) or {}).items():
        first, last = int(bounds[0]), int(bounds[1])
        if last < first:
            raise ConfigError(f"metrics.{key}.{name}: [{first}, {last}] ends before it starts; give [first, last] "
                              f"steps with first <= last.")
        if first > K - 1:                 # a short run of a long study: say so, do not write NaN rows
            if warn:
                log.warning("metrics.%s.%s: [%d, %d] starts after the scenario's last step %d; left out of the "
                            "summary", key, name, first, last, K - 1)
            continue
        if name == "all":
            last = K - 1
        elif last > K - 1:
            if warn:
                log.warning("metrics.%s.%s: [%d, %d] ends after the scenario's last step %d; summarised over "
                            "steps %d..%d", key, name, first, last, K - 1, first, K - 1)
            last = K - 1
        windows.append(Window(name, first, last))
    return windows


def build_report_tables(cfg: DictConfig) -> dict[str, Any]:
    """report.tables: name -> table object (see pipeline.views.tables), built and checked up front."""
    report = cfg.get("report")
    nodes = report.get("tables") if isinstance(report, DictConfig) else None
    if report is not None and not isinstance(report, DictConfig):
        raise ConfigError(f"report: {report!r} must be a mapping with a 'tables' mapping (name -> table node).")
    if report is not None:
        from pipeline.results.report import ReportError, ReportSpec
        try:      # the reproduction report's queries, figures and targets: checked now, used by pipeline.results.report
            ReportSpec.from_config(OmegaConf.to_container(report, resolve=True))
        except ReportError as exc:
            raise ConfigError(str(exc)) from None
    if not nodes:
        return {}
    if not isinstance(nodes, DictConfig):
        raise ConfigError(f"report.tables: must be a mapping name -> table node with a _target_, not "
                          f"{type(nodes).__name__}; e.g. report.tables.table1: {{_target_: "
                          f"pipeline.views.tables.BinnedTable, ...}}.")
    tables = {}
    for name, node in nodes.items():
        if node is None:
            continue          # a table switched off with report.tables.NAME=null
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise ConfigError(f"report.tables.{name}: {node!r} is not a table node; it needs a _target_ naming a "
                              f"class with render(ReportContext) -> str (e.g. pipeline.views.tables.BinnedTable).")
        table = build(node, f"report.tables.{name}")
        if not callable(getattr(table, "render", None)):
            raise ConfigError(f"report.tables.{name}: {node._target_} has no render(ReportContext) method.")
        unknown = [v for v in getattr(table, "variant_keys", ()) if v not in cfg.filters]
        if unknown:
            raise ConfigError(f"report.tables.{name}: names variant(s) {unknown} that experiment "
                              f"'{cfg.get('experiment_name')}' does not define; its variants are "
                              f"{list(cfg.filters.keys())}.")
        tables[str(name)] = table
    return tables


def failure_summary(ctx: RunContext, experiment: str, error: str, resolved: dict | None) -> pl.DataFrame:
    base = pl.DataFrame({"variant": [None], "variant_key": [None], "series": [None], "window": [None],
                         "value": [None], "unit": [None], "n_runs": [None]},
                        schema={"variant": pl.String, "variant_key": pl.String, "series": pl.String,
                                "window": pl.String, "value": pl.Float64, "unit": pl.String, "n_runs": pl.Int32})
    df = _provenance(base, ctx, experiment, stable_hash(resolved) if resolved else "", "failed", error)
    if resolved:
        df = df.with_columns(*[pl.lit(v).alias(k) for k, v in _config_columns(resolved).items()])
    return df


def record_failure(ctx: RunContext, experiment: str, error: str, resolved: dict | None, detail: str | None,
                   peak_rss_mb: float | None = None) -> None:
    """A failed job leaves status.json and a one-row summary saying why, so sweeps stay queryable. A job
    that failed after writing its tables (in the record stage) keeps them: its summary is not replaced."""
    ctx.run_dir.mkdir(parents=True, exist_ok=True)
    write_status(ctx, experiment, "failed", error=error, detail=detail, peak_rss_mb=peak_rss_mb)
    if ctx.tables_written:
        return
    atomic_write_parquet(failure_summary(ctx, experiment, error, resolved), ctx.run_dir / "summary.parquet",
                         schemas.table_metadata("summary", {}, {}))


def record_job_failure(ctx: RunContext, cfg: DictConfig, error: str, detail: str | None,
                       peak_rss_mb: float | None = None) -> None:
    """record_failure for a job's config, resolved where it resolves (a bad interpolation may be the error)."""
    try:
        resolved = OmegaConf.to_container(cfg, resolve=True)
    except Exception:
        resolved = None
    record_failure(ctx, str(cfg.get("experiment_name")), error, resolved, detail, peak_rss_mb)


def job_context(cfg: DictConfig, hydra_cfg: DictConfig) -> RunContext:
    """The RunContext of the Hydra job with config ``cfg`` and Hydra node ``hydra_cfg`` (HydraConfig.get()
    in the job; ``config.hydra`` in a callback): the task function and SweepSummary.on_job_end, which
    records a job whose process died, must name the same folder, sweep and job."""
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    # relative to where the run or sweep was started (hydra.runtime.cwd is recorded there), not to
    # this process's working directory: a Ray worker of an existing cluster starts elsewhere
    artifacts = Path(str(hydra_cfg.runtime.cwd)) / str(cfg.paths.artifacts)
    sweep = None
    if multirun:
        try:
            sweep = Path(hydra_cfg.sweep.dir).resolve().relative_to(artifacts.resolve()).as_posix()
        except ValueError:
            sweep = str(hydra_cfg.sweep.dir)
    overrides = list(OmegaConf.to_container(hydra_cfg.overrides.task, resolve=False))
    return RunContext(Path(hydra_cfg.runtime.output_dir), artifacts, overrides, sweep,
                      hydra_cfg.job.num if multirun else None)


class _Stages:
    def __init__(self, cache: StageCache, ctx: RunContext, provenance: dict[str, str], link: bool = False,
                 progress: Reporter | None = None) -> None:
        self.cache = cache
        self.link = link              # cache.publish=link: hard links into the cache instead of copies
        self.ctx = ctx
        self.provenance = provenance
        self.progress = progress or Reporter("off")

    def run(self, stage: str, key: str, table: str, compute: Callable[[], Any],
            to_frame: Callable[[Any], tuple[pl.DataFrame, dict]], publish_as: Path, describe: str,
            from_frame: Callable[[pl.DataFrame, dict[str, str]], Any],
            chunks: Callable[[], Any] | None = None, label: str | None = None,
            units: int = 1) -> tuple[Any, bool, pl.DataFrame]:
        """(the stage's value as the table holds it, whether it came from the cache, the table).
        With ``chunks`` (an iterator of (frame, metadata) per chunk of runs, ``units`` of them), a
        computed table is streamed to the cache one chunk at a time, then read back whole. A computed
        stage shows its progress as ``label`` (pipeline.run.progress)."""
        started = time.perf_counter()
        label = label or f"[{stage}] {describe}"
        destination = inside(self.ctx.run_dir, publish_as)
        hit = self.cache.load(stage, key, table, publish_to=None if self.link else destination)
        if hit is not None:
            df = hit[0]
            value = from_frame(*hit)
            path = self.cache.path(stage, key)
            log.info("[%s] reused cached %s (key %s) %s, %.2f s", stage, path.name, key, describe, time.perf_counter() - started)
        elif chunks is not None:
            stream = self.cache.stream(stage, key)
            try:
                meta: dict = {}
                with self.progress.task(label, units, "chunk") as task:
                    for part, meta in chunks():
                        stream.write(part)
                        del part                       # one chunk in memory at a time
                        task.unit_done()
                path = stream.finish({**meta, **self.provenance})
            except BaseException:
                stream.abort()
                raise
            computed = time.perf_counter() - started
            df, stored = read_table(path)
            value = from_frame(df, stored)
            log.info("[%s] computed %s in chunks of runs, %.2f s (written as it went)", stage, describe, computed)
        else:
            with self.progress.task(label) as task:
                value = compute()
                computed = time.perf_counter() - started
                task.set_note("writing its table")
                df, meta = to_frame(value)
                value = None                           # the table holds it now: one copy in memory, not two
                path = self.cache.store(stage, key, df, {**meta, **self.provenance})
                # later stages see exactly what the table holds (e.g. the float32 compact covariance),
                # so a recomputed stage and a cached one give bit-identical metrics
                value = from_frame(df, {k: str(v) for k, v in meta.items()})
            log.info("[%s] computed %s, %.2f s (+%.2f s to write the cache)", stage, describe, computed,
                     time.perf_counter() - started - computed)
        if hit is None or self.link:
            publish(path, destination, link=self.link)
        return value, hit is not None, df


@dataclass(frozen=True)
class Prepared:
    """Everything an experiment needs, built and cross-checked from its config before any stage."""

    study: Any
    scenario: Any
    sensor: Any
    estimators: dict[str, Any]
    variants: list[str]
    report_tables: dict[str, Any]


def prepare(cfg: DictConfig) -> Prepared:
    """Check the config and build every node (raising ConfigError naming the key): nothing is read
    or written, so a bad value costs nothing and leaves every file as it was."""
    validate(cfg)
    report_tables = build_report_tables(cfg)
    build_fault_checks(cfg)
    variants = selected_variants(cfg)
    study = build(cfg.study, "study") if cfg.get("study") is not None else _default_study(cfg)
    if not isinstance(study, Study):
        raise ConfigError(f"study: {cfg.study.get('_target_')} is not a pipeline.contract.Study; a study subclasses "
                          f"it and provides the hooks it lists (track_input, estimate_to_frame, per_step_metrics, "
                          f"record, ...).")
    check_objective(cfg, variants)     # after the study: building it registers its metric names
    scenario = build(cfg.scenario, "scenario")
    sensor = build(cfg.sensors, "sensors")
    estimators = {v: build(cfg.filters[v], f"filters.{v}") for v in variants}
    check_display_names(estimators)
    study.check(scenario, sensor, estimators)
    return Prepared(study, scenario, sensor, estimators, variants, report_tables)


def check_display_names(estimators: dict[str, Any]) -> None:
    """A variant's display name heads its row of the printed tables and its column of the recording,
    and names it in summary.parquet: two variants with one name would collapse into one row."""
    by_name: dict[str, list[str]] = {}
    for key, estimator in estimators.items():
        by_name.setdefault(str(getattr(estimator, "name", key)), []).append(key)
    clashes = {name: keys for name, keys in by_name.items() if len(keys) > 1}
    if clashes:
        name, keys = next(iter(clashes.items()))
        raise ConfigError(
            f"filters.{keys[1]}.name: {name!r} is also the display name of " + ", ".join(f"filters.{k}" for k in keys[:1] + keys[2:])
            + f". Each variant's name must be unique within an experiment (it heads the variant's row of the "
            f"printed table and its column of the recording, and the variant column of summary.parquet); "
            f"give one of them its own, e.g. filters.{keys[1]}.name={name}-{keys[1]}.")


def run_experiment(cfg: DictConfig, ctx: RunContext) -> RunOutcome:
    """Run every stage of one experiment job; write its tables, recording and status."""
    total_started = time.perf_counter()
    experiment = str(cfg.get("experiment_name"))
    check_added_keys(cfg, ctx.overrides)      # a '+' key nothing reads (+mc.rnus=5): refused, not ignored
    prepared = prepare(cfg)
    report_tables = prepared.report_tables
    resolved = OmegaConf.to_container(cfg, resolve=True)
    config_hash = stable_hash(resolved)
    runs, seed = int(cfg.mc.runs), int(cfg.mc.seed)
    memory = check_memory(cfg, prepared.scenario, prepared.sensor, len(prepared.variants))   # before any work
    ctx.run_dir.mkdir(parents=True, exist_ok=True)
    # what the scenario says it is (a recorded flight: the file that runs, not the experiment's default)
    scenario_text = str(prepared.scenario.describe()) if callable(getattr(prepared.scenario, "describe", None)) else None
    write_status(ctx, experiment, "running", config_hash=config_hash, runs=runs, provenance={}, stage_keys={},
                 scenario=scenario_text)
    ctx.started = True             # from here on a failure is this job's to record in its folder
    run_provenance = provenance_of_run.record(ctx.run_dir, resolved, ctx.overrides,
                                              fingerprint.producers(resolved, "pipeline.run.runner"))
    write_status(ctx, experiment, "running", config_hash=config_hash, runs=runs, provenance=run_provenance)
    atomic_write_text(OmegaConf.to_yaml(cfg, resolve=True), ctx.run_dir / "config.yaml")
    variants = prepared.variants
    log.info("experiment %s: %d Monte Carlo runs, seed %d, variants %s -> %s", experiment, runs, seed, variants, ctx.run_dir)
    log.info("memory: about %.2f GB at the peak (estimated; pipeline.run.memory)", memory.peak / 2**30)
    study, sensor, estimators = prepared.study, prepared.sensor, prepared.estimators
    cache = StageCache(ctx.artifacts / "cache", enabled=bool(cfg.cache.enabled))
    provenance = {"mtt.experiment": experiment, "mtt.config_hash": config_hash, "mtt.package_version": package_version(),
                  **environment_metadata(), **provenance_of_run.table_metadata(run_provenance)}
    # a bar on a terminal, plain lines in a pipe or a sweep, nothing for a stage under 2 s
    progress = Reporter(choose_mode(sys.stderr, multirun=ctx.job_num is not None))
    stages = _Stages(cache, ctx, provenance, link=cfg.cache.get("publish", "copy") == "link", progress=progress)

    # the declared stages (pipeline.run.stages), run in order through the cache: each key covers its
    # config subtree, its inputs' keys and the import closure of the code that makes its table
    outputs: dict[str, Any] = {}
    keys: dict[str, str] = {}
    stage_keys: dict[str, str] = {}        # each published stage table's key, by its name in the run folder
    faults: dict[str, dict[str, int]] = {}
    cached: dict[str, bool] = {}
    display = {v: str(getattr(estimators[v], "name", v)) for v in variants}
    tables: dict[str, Path] = {}           # each variant's track table, read again only where asked
    recorded: dict[str, Any] = {}          # each variant's recorded runs (pipeline.storage.estimates)
    record_runs = ([cfg.record.runs] if isinstance(cfg.record.runs, int) else list(cfg.record.runs)) \
        if cfg.record.enabled else []
    evaluation: Evaluation | None = None
    stored_seconds: dict[str, float] = {}  # each variant's track stage time (a cached one's: another process's)
    declared, track_input = declare_stages(cfg, resolved, prepared, build_fault_checks(cfg))
    read_later = {name for stage in declared for name in stage.inputs}
    chunk_runs = cfg.mc.get("chunk_runs")
    for stage in declared:
        inputs = {name: outputs[name] for name in stage.inputs}
        key = stage_key(stage.cache, stage.config, tuple(keys[name] for name in stage.inputs), stage.producers)
        outputs[stage.output], cached[stage.output], table = stages.run(
            stage.cache, key, stage.table, lambda s=stage, i=inputs: s.compute(**i),
            lambda value, s=stage, i=inputs: s.to_frame(value, i), stage.publish_as, stage.describe(inputs),
            stage.from_frame, None if stage.chunks is None else lambda s=stage, i=inputs: s.chunks(**i),
            _progress_label(stage, inputs, prepared),
            math.ceil(runs / chunk_runs) if stage.chunks is not None else 1)
        keys[stage.output] = key
        stage_keys[Path(stage.publish_as).as_posix()] = key
        write_status(ctx, experiment, "running", config_hash=config_hash, runs=runs, stage_keys=stage_keys)
        del inputs
        if stage.output == "truth":       # the windows must fit the scenario before any filtering
            for which in ("windows", "count_windows"):
                _windows(cfg, which, outputs["truth"].time.size, warn=True)
        if stage.cache == "track" and stage.output.startswith("estimates/") \
                and stage.output[len("estimates/"):] in estimators:
            # measured now and let go: a job holds one variant's estimate at a time (pipeline.storage.estimates)
            v = stage.output[len("estimates/"):]
            estimate = outputs[stage.output] if stage.output in read_later else outputs.pop(stage.output)
            truth = outputs["truth"]
            faults[v] = _track_done(v, display[v], estimate, table, cached[stage.output], runs, truth.time.size)
            stored_seconds[v] = float(estimate.compute_seconds)
            if evaluation is None:
                evaluation = Evaluation(cfg, study, sensor, truth, runs)
            with progress.task(f"[evaluate] {display[v]}"):      # the bootstrap reports its metrics
                evaluation.add(v, display[v], estimate)
            if record_runs:
                recorded[v] = recorded_runs(estimate, record_runs, runs)
            tables[v] = inside(ctx.run_dir, stage.publish_as)
            del estimate
        del table
    truth = outputs["truth"]
    detections = outputs["detections"]
    K = truth.time.size
    if evaluation is None:
        evaluation = Evaluation(cfg, study, sensor, truth, runs)
    # compute time: every variant timed in this process, several passes taking turns (pipeline.evaluation.timing)
    for v, timing in time_variants(cfg, estimators, variants, lambda: track_input(truth, detections), stored_seconds,
                                   {v: not cached[f"estimates/{v}"] for v in variants}, display, progress).items():
        evaluation.set_timing(v, timing)
    estimates = StoredEstimates(tables, study.estimate_from_frame)
    started = time.perf_counter()
    with progress.task(f"[evaluate] {len(variants)} variants x {K} steps"):   # the bootstrap reports its metrics
        evaluated = evaluation.finish(estimates, faults)
    estimates.release()
    metrics, summary = evaluated.metrics, evaluated.summary
    summary = summary.with_columns(pl.col("variant_key").replace_strict(
        {v: cached[f"estimates/{v}"] for v in variants}, return_dtype=pl.Boolean).alias("estimates_from_cache"))
    metrics = _provenance(metrics, ctx, experiment, config_hash)
    summary = _provenance(summary, ctx, experiment, config_hash)
    summary = summary.with_columns(*[pl.lit(v).alias(k) for k, v in _config_columns(resolved).items()])
    atomic_write_parquet(metrics, ctx.run_dir / "metrics.parquet",
                         {**schemas.table_metadata("metrics", {}, {"value": "see summary units"}), **provenance})
    atomic_write_parquet(summary, ctx.run_dir / "summary.parquet",
                         {**schemas.table_metadata("summary", {}, {}), **provenance})
    atomic_write_parquet(_provenance(evaluated.comparisons, ctx, experiment, config_hash),
                         ctx.run_dir / "comparisons.parquet",
                         {**schemas.table_metadata("comparisons", {}, {}), **provenance})
    atomic_write_parquet(_provenance(evaluated.per_run, ctx, experiment, config_hash),
                         ctx.run_dir / "per_run.parquet", {**schemas.table_metadata("per_run", {}, {}), **provenance})
    atomic_write_parquet(evaluated.resamples, ctx.run_dir / "resamples.parquet",
                         {**schemas.table_metadata("resamples", {}, {}), **provenance})
    # the evaluate stage's time: each variant measured after its track stage, then the summary
    log.info("[evaluate] metrics for %d variants x %d steps, %.2f s", len(variants), K,
             evaluation.measuring_seconds + time.perf_counter() - started)

    text = format_summary(summary, experiment, runs, evaluated.comparisons)
    if scenario_text:
        first, newline, rest = text.partition("\n")
        text = f"{first}\nscenario: {scenario_text}{newline}{rest}"
    text = job_header(text, ctx)
    if report_tables:
        report_ctx = ReportContext(experiment, runs, display, metrics, summary)
        text += "".join(f"\n\n{table.render(report_ctx)}" for table in report_tables.values())
    atomic_write_text(text + "\n", ctx.run_dir / "report.txt")
    ctx.tables_written = True      # a failure from here on (the recording) keeps them (record_failure)

    if cfg.record.enabled:
        started = time.perf_counter()
        # no count measures a recording: it shows its time so far (and a filter re-run for it, its scans)
        with progress.task("[record] recording.rrd", units=None):
            study.record(ctx.run_dir / "recording.rrd", RecordingInputs(
                experiment=experiment, truth=truth, detections=detections, estimates=recorded, display_names=display,
                metrics=metrics, record_runs=record_runs, sensor=sensor, estimators=estimators,
                track_input=track_input(truth, detections),     # the filters' view (made once), for re-runs
                seed=seed, config_text=OmegaConf.to_yaml(cfg, resolve=True),
                description=str(cfg.get("description", ""))))
        log.info("[record] recording.rrd (runs %s), %.2f s", record_runs, time.perf_counter() - started)
    write_status(ctx, experiment, "ok", config_hash=config_hash, runs=runs, stage_keys=stage_keys)
    log.info("done in %.2f s", time.perf_counter() - total_started)
    return RunOutcome(summary, metrics, text, evaluated.comparisons)


def _track_done(key: str, display: str, estimate: Any, table: pl.DataFrame, hit: bool, runs: int, steps: int
                ) -> dict[str, int]:
    """A variant's track stage done: its filtering time and fault counts logged; the fault counts."""
    if not hit:
        per_step = getattr(estimate, "extras", {}).get("models_evaluated")
        models = f", {per_step[:, 2:].mean():.2f} models/step" if per_step is not None and steps > 2 else ""
        log.info("[track] %s filtered in %.3f s%s", display, estimate.compute_seconds, models)
    faults = fault_summary(flags_from_table(table, runs, steps))
    if faults["diverged_runs"]:
        log.warning("[track] %s: %d of %d runs hit a numerical fault (%s); their rows are flagged in "
                    "estimates/%s.parquet (column fault)", display, faults["diverged_runs"], runs,
                    ", ".join(f"{name[len('fault_runs_'):]}: {count}" for name, count in faults.items()
                              if name.startswith("fault_runs_") and count), key)
    return faults


def time_variants(cfg: DictConfig, estimators: Mapping[str, Any], variants: list[str], view: Callable[[], Any],
                  stored_seconds: Mapping[str, float], timed_here: Mapping[str, bool], display: Mapping[str, str],
                  progress: Reporter) -> dict[str, Timing]:
    """Each variant's ``Timing`` in this process: its track stage's pass where it ran here (``timed_here``)
    and further filtering passes on the same input (``view()``, the filters' view of the detections),
    up to ``timing.passes`` per variant within ``timing.budget_s`` seconds each (pipeline.evaluation.timing).
    A pass's estimate is dropped as soon as it is timed; with ``mc.chunk_runs`` a pass goes chunk by
    chunk, as the track stage did."""
    node = cfg.get("timing") or {}
    passes, budget = int(node.get("passes", PASSES)), float(node.get("budget_s", BUDGET_S))
    chunk_runs = cfg.mc.get("chunk_runs")
    runs = int(cfg.mc.runs)

    def one_pass(v: str) -> float:
        with progress.task(f"[timing] {display[v]}"):
            if chunk_runs and chunk_runs < runs:
                seconds = float("nan")
                for _, part in filter_chunks(estimators[v], view(), chunk_runs):
                    seconds = float(part.compute_seconds)      # the running total of the chunks'
                    del part
                return seconds
            return float(estimators[v].run(view()).compute_seconds)

    timings = time_passes({v: (lambda v=v: one_pass(v)) for v in variants},
                          {v: stored_seconds[v] if timed_here[v] else None for v in variants}, stored_seconds,
                          passes, budget)
    for v, t in timings.items():
        low, high = t.interval()
        log.info("[timing] %s: %.4g s, %s%s", display[v], t.median(), t.method(),
                 f" [{low:.4g}, {high:.4g}] s" if low is not None else "")
    return timings


def job_header(text: str, ctx: RunContext) -> str:
    """A sweep job's printed summary headed by its job number and overrides (``[job 3] ao_vsimm_s1: 5
    Monte Carlo runs; overrides: ...``): the jobs' tables reach one terminal, each must say whose it
    is. A single run's is left as it is."""
    if ctx.job_num is None:
        return text
    first, newline, rest = text.partition("\n")
    return f"[job {ctx.job_num}] {first}; overrides: {' '.join(ctx.overrides) or '(none)'}{newline}{rest}"


@dataclass(frozen=True)
class Evaluated:
    """The evaluate stage's tables (pipeline.evaluation.evaluate): per-step ``metrics``, the ``summary`` with its
    intervals, the paired ``comparisons`` with the reference variant, and each run's own values
    (``per_run``)."""
    metrics: pl.DataFrame
    summary: pl.DataFrame
    comparisons: pl.DataFrame
    per_run: pl.DataFrame
    resamples: pl.DataFrame | None = None


class Evaluation:
    """The evaluate stage, fed one variant at a time (``add``, as soon as its estimate exists, which
    can then be let go: pipeline.storage.estimates) and finished once every variant is in (``finish``).
    ``add`` measures the variant (``Study.per_step_metrics``, its summary rows and the study's
    ``variant_summary`` rows) and resamples its rows' statistics on the job's bootstrap resamples
    (``pipeline.evaluation.uncertainty.resample``: the same resampled runs for every variant, so the comparisons
    stay paired), then lets its per-run, per-step values go: what is kept of a variant is its per-step
    values over the runs, its rows' resamples and per-run values, its compute time. A bound that
    cannot be inverted (``filters.bounds.SingularBoundWarning``) is logged once, at the end."""

    def __init__(self, cfg: DictConfig, study: Study, sensor: Any, truth: Any, runs: int) -> None:
        self.cfg, self.study, self.sensor, self.truth, self.runs = cfg, study, sensor, truth, runs
        K = truth.time.size
        self.windows, self.count_windows = _windows(cfg, "windows", K), _windows(cfg, "count_windows", K)
        uncertainty = cfg.get("uncertainty") or {}
        self.seed = int(cfg.mc.seed)
        self.confidence = float(uncertainty.get("confidence", CONFIDENCE))
        self.resamples = int(uncertainty.get("bootstrap_resamples", RESAMPLES))
        self.reached = None
        gr = cfg.metrics.get("group_reached")            # checked by validate()
        if gr:
            self.reached = (str(gr.group), list(cfg.models.groups.keys()).index(gr.group), int(gr.by_step))
        # per variant, in the order added
        self.display: dict[str, str] = {}
        self.per_step: dict[str, tuple[str, dict[str, Any]]] = {}    # (K,) values over the runs, per metric
        self.rows: dict[str, list[dict]] = {}            # its summary rows (pipeline.evaluation.evaluate.variant_rows)
        self.study_rows: dict[str, list[dict]] = {}      # its Study.variant_summary rows
        self.models: dict[str, dict[str, float | None]] = {}
        self.compute_seconds: dict[str, float | Timing] = {}
        self._warnings: list[warnings.WarningMessage] = []
        self._reissued: set[tuple] = set()
        self.measuring_seconds = 0.0                     # spent in ``add``, between the track stages

    @contextlib.contextmanager
    def _catching(self):
        from filters.bounds import SingularBoundWarning
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", SingularBoundWarning)
            yield
        self._warnings += [w for w in caught if issubclass(w.category, SingularBoundWarning)]
        for w in caught:
            key = (str(w.message), w.category, w.filename, w.lineno)
            if not issubclass(w.category, SingularBoundWarning) and key not in self._reissued:
                self._reissued.add(key)           # once per job, not once per variant
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

    def add(self, key: str, display: str, estimate: Any) -> None:
        """Measure one variant's estimate (against the truth, with the study's metrics)."""
        started = time.perf_counter()
        with self._catching():
            metrics = self.study.per_step_metrics(self.truth, estimate, self.sensor)
            fraction = group_reached(estimate, self.reached[1], self.reached[2]) if self.reached else None
            own = variant_rows(key, display, metrics, float(estimate.compute_seconds), self.windows, self.runs,
                               self.reached, self.count_windows, fraction)
            studied = [row if "statistic" in row else row | {"statistic": None} for row in
                       self.study.variant_summary(VariantInputs(self.truth, key, display, estimate, self.runs,
                                                                self.sensor, metrics))]
            estimated = [row for row in own + studied if row.get("statistic") is not None]
            for row, reduced in zip(estimated, resample([row["statistic"] for row in estimated], self.seed,
                                                        self.resamples)):
                row["statistic"] = reduced               # its per-run, per-step values can go now
            self.display[key] = display
            self.rows[key], self.study_rows[key] = own, studied
            self.per_step[key] = (display, per_step_values(metrics))
            self.models[key] = models_per_step(metrics, self.windows)
            self.compute_seconds[key] = float(estimate.compute_seconds)
        self.measuring_seconds += time.perf_counter() - started

    def set_timing(self, key: str, timing: Timing) -> None:
        """A variant's compute time as this job timed it (pipeline.evaluation.timing): its compute row,
        and the ratios ``finish`` makes, get the median of the passes and their range."""
        self.compute_seconds[key] = timing
        self.rows[key] = [compute_row(key, self.display[key], timing, self.runs) if row["series"] == "compute_seconds"
                          else row for row in self.rows[key]]

    def finish(self, estimates: Mapping[str, Any], faults: dict[str, dict[str, int]]) -> Evaluated:
        """The tables, once every variant is in; ``estimates`` (variant key -> estimate, e.g. a
        ``pipeline.storage.estimates.StoredEstimates``) serves the study's rows across variants."""
        cfg, runs, display = self.cfg, self.runs, self.display
        variants = list(display)
        with self._catching():
            ref = cfg.metrics.get("reference_variant")
            ref = ref if ref in variants else None
            rows = [row for v in variants for row in self.rows[v]]
            rows += reference_rows(display, self.compute_seconds, self.models, self.windows, ref, runs,
                                   compute_reference(cfg))      # compute time as % of it (pipeline.run.config)
            # the study's rows across variants read the per-step values (over the runs)
            rows += [row for v in variants for row in self.study_rows[v]]
            rows += [row if "statistic" in row else row | {"statistic": None} for row in
                     self.study.extra_summary(JobInputs(self.truth, estimates, display, runs, ref, self.sensor,
                                                        self.per_step))]
            rows += [summary_row(v, display[v], name, None, float(count), runs) for v in variants
                     for name, count in faults[v].items()]
            summary, comparisons, per_run, resamples = summary_table(rows, ref, self.seed, self.confidence,
                                                                     self.resamples)
            metrics = metrics_frame(self.truth.time, self.per_step, runs)
        # a bound that cannot be inverted is NaN from that scan (filters.bounds): said once, in the log
        for message in dict.fromkeys(str(w.message) for w in self._warnings):
            log.warning("[evaluate] %s: position_bound and its ratios are NaN there; the metrics go on", message)
        self._warnings = []
        # the tidy columns metric (the quantity), component, sensor, target (pipeline.evaluation.metrics.breakdown)
        return Evaluated(with_breakdown(metrics), with_breakdown(summary), with_breakdown(comparisons),
                         with_breakdown(per_run), resamples)


def evaluate_stage(cfg: DictConfig, study: Study, sensor: Any, truth: Any, estimates: Mapping[str, Any],
                   display: dict[str, str], faults: dict[str, dict[str, int]], runs: int) -> Evaluated:
    """The evaluate stage's tables of every variant, from the truth, the estimates as their tables hold
    them (a dict, or a ``pipeline.storage.estimates.StoredEstimates`` that reads them one at a time), the fault
    counts of their tables, and the built sensor and study: ``python -m pipeline.recompute``
    recomputes a stored run's from its files alone (a run measures each variant as its track stage
    ends: ``Evaluation``)."""
    evaluation = Evaluation(cfg, study, sensor, truth, runs)
    for v in list(estimates):        # no loop variable keeps the previous estimate while the next is read
        evaluation.add(v, display[v], estimates[v])
    if isinstance(estimates, StoredEstimates):
        estimates.release()
    evaluated = evaluation.finish(estimates, faults)
    if isinstance(estimates, StoredEstimates):
        estimates.release()
    return evaluated


def _progress_label(stage: Any, inputs: dict[str, Any], prepared: Prepared) -> str:
    """What a stage's progress says it is: ``[track] AMMPF, variant 1/3``, ``[scenario] 100 runs``."""
    if stage.cache == "track" and stage.output.startswith("estimates/"):
        key = stage.output[len("estimates/"):]
        if key in prepared.variants:
            name = getattr(prepared.estimators[key], "name", key)
            return f"[track] {name}, variant {prepared.variants.index(key) + 1}/{len(prepared.variants)}"
    return f"[{stage.cache}] {stage.describe(inputs)}"


def build_fault_checks(cfg: DictConfig) -> FaultChecks:
    node = cfg.get("faults")
    if node is None:
        return FaultChecks()
    if not isinstance(node, DictConfig):
        raise ConfigError(f"faults: {node!r} must be a mapping with symmetry_tolerance, nees_bound and "
                          f"divergence_factor.")
    unknown = sorted(set(node.keys()) - {"symmetry_tolerance", "nees_bound", "divergence_factor"})
    if unknown:
        raise ConfigError(f"faults: unknown key(s) {unknown}; allowed are symmetry_tolerance (a number >= 0), "
                          f"nees_bound (a number > 0 or null) and divergence_factor (a number > 0 or null).")
    try:
        return FaultChecks(**OmegaConf.to_container(node, resolve=True))
    except (TypeError, ValueError) as exc:
        raise ConfigError(str(exc)) from None


def _default_study(cfg: DictConfig) -> SingleTargetStudy:
    models = cfg.get("models")
    return SingleTargetStudy(
        model_names=list(models.accelerations.keys()) if models and "accelerations" in models else None,
        group_names=list(models.groups.keys()) if models and "groups" in models else None,
        bound=build(cfg.bound, "bound") if cfg.get("bound") is not None else None)


def describe_exception(exc: BaseException) -> tuple[str, str]:
    return f"{type(exc).__name__}: {exc}", "".join(traceback.format_exception(exc))
