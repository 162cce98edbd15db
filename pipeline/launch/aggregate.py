"""Sweep-level files at the sweep root: every job's summary.parquet in one table (sweep_summary.parquet),
the jobs with their swept values (sweep_index.parquet) and their metric curves (sweep.rrd), and for a
sweep whose jobs name an ``objective`` (a parameter search) the best job's config in best_config.yaml.

Hydra calls ``SweepSummary.on_multirun_end`` after a multirun. Jobs never raise out of the task
function (they record their failure instead), so the callback runs even when a job failed; it is
also a CLI for a sweep that was interrupted: ``python -m pipeline.aggregate <sweep_dir>``.

A job's summary enters the sweep's tables only where it is the one the job wrote (its checksum, run_id
and config hash: pipeline.storage.run_tables); a job whose summary is left out is listed as
``skipped`` with the reason, in the glance, the jobs table and the exit code (1), never as ok.

``SweepSummary.on_multirun_start`` runs in the driver before any job is launched and pins the
sweep directory to an absolute path (the driver's working directory + the configured, usually
relative, ``hydra.sweep.dir``). Launchers that run jobs in other processes re-compose each job's
config there and resolve relative paths against that process's working directory: Ray workers of
an existing cluster start in the directory where ``ray start`` ran, so without the pin their job
folders (and Hydra's ``.hydra/``) would land outside the sweep folder this callback aggregates.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, open_dict, read_write

from pipeline.errors import PipelineError
from pipeline.launch.objective import BEST_CONFIG, job_objectives, write_best_config
from pipeline.storage.store import atomic_write_parquet, read_yaml
from pipeline.results.sweep import META_SWEPT, SWEEP_INDEX, SWEEP_SUMMARY, Sweep, collect, format_glance


def aggregate(sweep_dir: Path, record: bool = True) -> Sweep:
    """Write the sweep's tables from its job folders: ``sweep_summary.parquet`` (every job's summary,
    schemas may differ: swept keys, failed jobs; the job's label and the swept keys first) and
    ``sweep_index.parquet`` (one row per job with its swept values); then, with ``record``, the
    sweep's recording ``sweep.rrd``. A recording that cannot be written is a warning: the tables
    are the sweep's result, and they are written first."""
    sweep = collect(Path(sweep_dir))
    metadata = {META_SWEPT: json.dumps(sweep.swept)}
    if sweep.summary.height:
        atomic_write_parquet(sweep.summary, sweep.folder / SWEEP_SUMMARY, {"mtt.table": "sweep_summary", **metadata})
    if sweep.jobs:
        atomic_write_parquet(sweep.index, sweep.folder / SWEEP_INDEX, {"mtt.table": "sweep_index", **metadata})
    if record and sweep.jobs:
        from pipeline.views.sweep_recording import write_sweep_recording
        try:
            write_sweep_recording(sweep)
        except Exception as exc:      # noqa: BLE001 - e.g. a full disk: the tables above are written
            print(f"sweep {sweep.folder}: the sweep recording was not written: {exc}", file=sys.stderr)
    return sweep


def _quoted_override_value(text: str) -> str:
    """A Hydra override value that stays one string whatever the path holds (spaces, commas, =).

    Hydra's quoted strings: a quote is escaped as \\', and backslashes need doubling only where
    they precede a quote or the closing quote.
    """
    escaped = re.sub(r"(\\*)('|$)", lambda m: m.group(1) * 2 + ("\\'" if m.group(2) else ""), text)
    return f"'{escaped}'"


class SweepSummary(Callback):
    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))     # resolves ${now:...} once, here (cached)
        if sweep_dir.is_absolute():
            return
        absolute = str(Path(str(config.hydra.runtime.cwd)) / sweep_dir)
        with read_write(config.hydra), open_dict(config.hydra):
            config.hydra.sweep.dir = absolute
            # every job's config is re-composed from these overrides (+ its own), in whatever process
            config.hydra.overrides.hydra.append(f"hydra.sweep.dir={_quoted_override_value(absolute)}")

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs) -> None:
        """A job that ended FAILED without recording its failure gets status.json ``failed`` and the
        failed summary row, so the sweep summary lists it: a job whose process died (the isolated
        launcher calls this from its own process then, with the cause as the error) or whose task
        function raised past its own handler. A job that recorded itself is left as it is."""
        if job_return.status != JobStatus.FAILED or job_return.cfg is None:
            return
        from pipeline.run.runner import describe_exception, job_context, record_job_failure
        ctx = job_context(job_return.cfg, config.hydra)
        status_path = ctx.run_dir / "status.json"
        if status_path.exists() and json.loads(status_path.read_text()).get("status") in ("ok", "failed"):
            return
        error = job_return._return_value     # return_value re-raises it (or, for a dead job, is None)
        if isinstance(error, BaseException) and error.__traceback__ is not None:
            message, detail = describe_exception(error)
        else:                                 # never raised: the launcher's account of a dead process
            message, detail = str(error), None
        # a dead job's own peak memory (the launcher measured it), not this process's
        record_job_failure(ctx, job_return.cfg, message, detail, getattr(error, "peak_rss_mb", None))

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        sweep = aggregate(sweep_dir)
        failures = sweep.failures
        jobs = len(list(sweep_dir.glob("*/status.json")))
        if jobs == 0:
            print(f"sweep {sweep_dir}: no job wrote its status.json under this folder. If the jobs ran on "
                  f"other machines (hydra/launcher=ray_cluster), the sweep folder must be on storage every "
                  f"node mounts at the same path: pass an absolute paths.artifacts=/shared/... ; the jobs' "
                  f"own logs are in the launcher's output above.", file=sys.stderr)
            sys.exit(1)
        skipped = sum(f.get("status") == "skipped" for f in failures)
        print(f"sweep {sweep_dir}: {jobs} jobs, {jobs - len(failures)} ok, {len(failures) - skipped} failed"
              + (f", {skipped} skipped (their summary left out: see below)" if skipped else "") + "; "
              f"summary of all jobs in {sweep_dir / SWEEP_SUMMARY}, the jobs and their swept values in "
              f"{SWEEP_INDEX}" + (", their metric curves in sweep.rrd" if (sweep_dir / "sweep.rrd").is_file() else ""),
              file=sys.stderr)
        print(format_glance(sweep), file=sys.stderr)
        report_best_job(sweep_dir)
        for f in failures:
            print(f"  job {f.get('job_num')} ({' '.join(f.get('overrides', []))}) {f.get('status')}: {f.get('error')}",
                  file=sys.stderr)
        if failures:
            sys.exit(1)


def report_best_job(sweep_dir: Path) -> None:
    """With an objective (a parameter search): write <sweep_dir>/best_config.yaml and say which job won.
    Optuna's own optimization_results.yaml holds the best parameters only; this adds the whole config
    of the job they came from, and checks that both name the same value."""
    jobs = job_objectives(sweep_dir)
    try:
        best = write_best_config(sweep_dir, jobs)
    except PipelineError as exc:
        print(f"  no best job: {exc}", file=sys.stderr)
        return
    if best is None:
        if any(job.objective is not None for job in jobs):
            print("  no best job: no job that ended ok has a finite objective value", file=sys.stderr)
        return
    value = best["objective"]["value"]
    print(f"  best job {best['job_num']} of {best['compared']}: {best['objective']['series']} = {value:.6g}; its "
          f"config in {sweep_dir / BEST_CONFIG}", file=sys.stderr)
    optuna = sweep_dir / "optimization_results.yaml"
    if optuna.is_file():
        reported = read_yaml(optuna).get("best_value")
        if reported is not None and reported != value:   # e.g. a study resumed from storage with older trials
            print(f"  note: Optuna's best_value {reported} (optimization_results.yaml) is not this sweep's best job's "
                  f"{value}: the study holds trials this folder does not", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not Path(args[0]).is_dir():
        print("usage: python -m pipeline.aggregate <sweep_dir>  (a directory holding <job>/status.json)", file=sys.stderr)
        return 2
    sweep = aggregate(Path(args[0]))
    failures = sweep.failures
    skipped = sum(f.get("status") == "skipped" for f in failures)
    print(f"{sweep.summary.height} summary rows; {len(sweep.jobs)} jobs, {len(failures) - skipped} failed"
          + (f", {skipped} skipped (their summary left out)" if skipped else ""), file=sys.stderr)
    for f in failures:
        if f.get("status") == "skipped":
            print(f"  job {f.get('job_num')} skipped: {f.get('error')}", file=sys.stderr)
    print(format_glance(sweep), file=sys.stderr)
    report_best_job(Path(args[0]))
    return 1 if failures else 0

if __name__ == "__main__":
    sys.exit(main())
