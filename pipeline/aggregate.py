"""Sweep-level summary: every job's summary.parquet in one file at the sweep root.

Hydra calls ``SweepSummary.on_multirun_end`` after a multirun. Jobs never raise out of the task
function (they record their failure instead), so the callback runs even when a job failed; it is
also a CLI for a sweep that was interrupted: ``python -m pipeline.aggregate <sweep_dir>``.

``SweepSummary.on_multirun_start`` runs in the driver before any job is launched and pins the
sweep directory to an absolute path (the driver's working directory + the configured, usually
relative, ``hydra.sweep.dir``). Launchers that run jobs in other processes re-compose each job's
config there and resolve relative paths against that process's working directory: Ray workers of
an existing cluster start in the directory where ``ray start`` ran, so without the pin their job
folders (and Hydra's ``.hydra/``) would land outside the sweep folder this callback aggregates.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from pathlib import Path

import polars as pl
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, open_dict, read_write

from pipeline.store import atomic_write_parquet, read_table

log = logging.getLogger("pipeline.aggregate")


def aggregate(sweep_dir: Path) -> tuple[pl.DataFrame, list[dict]]:
    """Concatenate the jobs' summaries (schemas may differ: swept keys, failed jobs) and list failures."""
    sweep_dir = Path(sweep_dir)
    frames, failures = [], []
    for status_path in sorted(sweep_dir.glob("*/status.json"), key=lambda p: (len(p.parent.name), p.parent.name)):
        status = json.loads(status_path.read_text())
        if status.get("status") != "ok":
            failures.append(status)
        summary = status_path.parent / "summary.parquet"
        if summary.exists():
            try:
                frames.append(read_table(summary)[0])
            except Exception as exc:     # damaged (checksum) or unreadable: this job is left out, named
                log.warning("skipped %s: %s", summary, exc)
    df = pl.concat(frames, how="diagonal_relaxed") if frames else pl.DataFrame()
    if frames:
        atomic_write_parquet(df, sweep_dir / "sweep_summary.parquet", {"mtt.table": "sweep_summary"})
    return df, failures


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
        from pipeline.runner import describe_exception, job_context, record_job_failure
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
        df, failures = aggregate(sweep_dir)
        jobs = len(list(sweep_dir.glob("*/status.json")))
        if jobs == 0:
            print(f"sweep {sweep_dir}: no job wrote its status.json under this folder. If the jobs ran on "
                  f"other machines (hydra/launcher=ray_cluster), the sweep folder must be on storage every "
                  f"node mounts at the same path: pass an absolute paths.artifacts=/shared/... ; the jobs' "
                  f"own logs are in the launcher's output above.", file=sys.stderr)
            sys.exit(1)
        print(f"sweep {sweep_dir}: {jobs} jobs, {jobs - len(failures)} ok, {len(failures)} failed; "
              f"summary of all jobs in {sweep_dir / 'sweep_summary.parquet'}", file=sys.stderr)
        for f in failures:
            print(f"  job {f.get('job_num')} ({' '.join(f.get('overrides', []))}) {f.get('status')}: {f.get('error')}",
                  file=sys.stderr)
        if failures:
            sys.exit(1)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not Path(args[0]).is_dir():
        print("usage: python -m pipeline.aggregate <sweep_dir>  (a directory holding <job>/status.json)", file=sys.stderr)
        return 2
    df, failures = aggregate(Path(args[0]))
    print(f"{df.height} summary rows; {len(failures)} failed jobs", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
