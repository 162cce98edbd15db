"""``mtt-query export-mlflow``: stored runs into an MLflow tracking store, for ``mlflow ui``.

Optional (``pip install -c lock/ci.txt -e '.[mlflow]'``: mlflow-skinny with SQLAlchemy and alembic
for its SQLite store). Jobs never log to MLflow live: its file store is deprecated and one SQLite
file written by many cluster jobs at once is what its users report as broken; the run folders stay
the record and this command copies them, after the fact, in one process.

Each run becomes one MLflow run in the experiment of its name (or ``--mlflow-experiment``):

- **params**: the run's resolved config flattened to dotted keys (``filters.vsimm.t1_mu``), where
  it wrote (``paths.*``, ``hydra.*``) left out;
- **metrics**: every summary row as ``<variant_key>.<series>.<window>`` with its interval's
  bounds and standard error beside it (``....ci_low``, ``....ci_high``, ``....se``), so a chart
  in MLflow shows the uncertainty that our tables state;
- **tags**: the provenance (``mtt.commit``, ``mtt.branch``, ``mtt.dirty``, ``mtt.code``,
  ``mtt.environment``, ``mtt.config_hash``, ``mtt.seed``, ``mtt.overrides``, ``mtt.host``), the
  run's tags (``mtt.tag.<name>``) and note (MLflow's ``mlflow.note.content``), and links
  (``mtt.recording``, ``mtt.report``, ``mtt.run_dir``: file URIs of the run folder's files);
- a sweep's jobs are children of one parent run named for the sweep folder.

Exporting a run again replaces its MLflow run (found by the tag ``mtt.run_id``).
"""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path
from typing import Sequence

import polars as pl

from pipeline.results.query import QueryError
from pipeline.results.tracking import LOCATION_KEYS, STATUS, Run, load_runs, provenance_fields, resolve_folder, \
    resolve_run

MAX_PARAM_LENGTH = 6000          # MLflow's limit on a param value (longer: cut, and says so)
BATCH = 100                      # MLflow's limit on params per log_batch call (metrics: 1000)


def store_uri(store: str | Path) -> str:
    text = str(store)
    if text.startswith("sqlite:///"):
        return text
    if "://" in text:
        raise QueryError(f"--store {text!r}: give an SQLite store, a .db file or sqlite:///PATH; MLflow's file "
                         f"store is deprecated and this command writes only SQLite.")
    return f"sqlite:///{Path(text).resolve()}"


def _client(uri: str):
    try:
        from mlflow.entities import Metric, Param, RunTag
        from mlflow.tracking import MlflowClient
    except ImportError as exc:
        raise QueryError(f"export-mlflow needs the optional [mlflow] extra, which is not installed ({exc}): "
                         f"pip install -c lock/ci.txt -e '.[mlflow]'") from None
    logging.getLogger("alembic").setLevel(logging.WARNING)
    return MlflowClient(tracking_uri=uri), Metric, Param, RunTag


def _ms(text: str | None) -> int | None:
    try:
        return int(dt.datetime.fromisoformat(text).timestamp() * 1000) if text else None
    except ValueError:
        return None


def _runs_of(root: Path, given: Sequence[str]) -> list[tuple[Run, str | None]]:
    """(run, sweep folder or None) for every run named, a sweep folder standing for all its jobs."""
    out: list[tuple[Run, str | None]] = []
    for name in given:
        path = resolve_folder(root, name, "RUN_OR_SWEEP")
        if (path / STATUS).is_file():
            out.append((resolve_run(root, name), None))
            continue
        jobs = load_runs(root, path)
        if not jobs:
            raise QueryError(f"export-mlflow: '{name}' is neither a run folder nor a folder of runs.")
        sweep = path.relative_to(Path(root).resolve()).as_posix()
        out += [(job, sweep) for job in jobs]
    return out


def run_tags(run: Run) -> dict[str, str]:
    status, fields = run.status, provenance_fields(run)
    tags = {"mtt.run_id": run.run_id, "mtt.experiment": status.get("experiment"), "mtt.status": status.get("status"),
            "mtt.config_hash": status.get("config_hash"), "mtt.commit": run.git.get("commit") or fields["commit"],
            "mtt.branch": fields["branch"], "mtt.dirty": fields["dirty"], "mtt.code": fields["code"],
            "mtt.diff_sha256": run.git.get("diff_sha256"), "mtt.environment": fields["environment"],
            "mtt.lock": ((status.get("environment") or {}).get("lock") or {}).get("sha256"),
            "mtt.seed": run.provenance.get("seed"), "mtt.host": fields["host"], "mtt.runs": status.get("runs"),
            "mtt.overrides": " ".join(status.get("overrides") or []), "mtt.sweep": status.get("sweep"),
            "mtt.job_num": status.get("job_num"), "mtt.run_dir": run.path.as_uri()}
    for name, file in (("mtt.recording", "recording.rrd"), ("mtt.report", "report.md"), ("mtt.report_text", "report.txt")):
        if (run.path / file).is_file():
            tags[name] = (run.path / file).as_uri()
    for name in run.tags:
        tags[f"mtt.tag.{name}"] = "true"
    if run.annotations.get("note"):
        tags["mlflow.note.content"] = run.annotations["note"]
    return {k: str(v) for k, v in tags.items() if v is not None and v != ""}


def run_params(run: Run) -> dict[str, str]:
    params = {}
    for key, value in run.config().items():
        if key.startswith(LOCATION_KEYS) or value is None:
            continue
        text = str(value)
        params[key[:250]] = text if len(text) <= MAX_PARAM_LENGTH else text[:MAX_PARAM_LENGTH - 12] + " [truncated]"
    return params


def run_metrics(run: Run) -> dict[str, float]:
    path = run.path / "summary.parquet"
    if not path.is_file():
        return {}
    rows = pl.read_parquet(path, columns=["variant_key", "series", "window", "value", "ci_low", "ci_high",
                                          "standard_error"]).filter(pl.col("series").is_not_null())
    metrics: dict[str, float] = {}
    for row in rows.iter_rows(named=True):
        name = f"{row['variant_key']}.{row['series']}.{row['window'] or 'job'}"
        for suffix, column in (("", "value"), (".ci_low", "ci_low"), (".ci_high", "ci_high"), (".se", "standard_error")):
            value = row[column]
            if value is not None:
                metrics[name + suffix] = float(value)
    return metrics


def _experiment_id(client, name: str) -> str:
    found = client.get_experiment_by_name(name)
    return found.experiment_id if found is not None else client.create_experiment(name)


def _replace(client, experiment_id: str, run_id: str) -> None:
    for old in client.search_runs([experiment_id], filter_string=f"tags.`mtt.run_id` = '{run_id}'"):
        client.delete_run(old.info.run_id)


def export(root: Path, given: Sequence[str], store: str | Path, experiment: str | None = None) -> list[str]:
    """Write the runs (or sweeps' jobs) into the MLflow store; their MLflow run ids."""
    runs = _runs_of(Path(root), given)
    uri = store_uri(store)
    client, Metric, Param, RunTag = _client(uri)
    parents: dict[tuple[str, str], str] = {}
    written = []
    for run, sweep in runs:
        experiment_id = _experiment_id(client, experiment or str(run.status.get("experiment") or "mtt"))
        tags = run_tags(run)
        if sweep is not None:
            if (experiment_id, sweep) not in parents:
                _replace(client, experiment_id, sweep)
                parent = client.create_run(experiment_id, run_name=sweep, tags={"mtt.run_id": sweep, "mtt.sweep": sweep})
                client.set_terminated(parent.info.run_id)
                parents[(experiment_id, sweep)] = parent.info.run_id
            tags["mlflow.parentRunId"] = parents[(experiment_id, sweep)]
        _replace(client, experiment_id, run.run_id)
        started = _ms(run.status.get("started_at"))
        created = client.create_run(experiment_id, start_time=started, run_name=run.run_id, tags=tags)
        mlflow_id = created.info.run_id
        params = [Param(k, v) for k, v in run_params(run).items()]
        stamp = _ms(run.status.get("finished_at")) or started or 0
        metrics = [Metric(k, v, stamp, 0) for k, v in run_metrics(run).items()]
        for i in range(0, len(params), BATCH):
            client.log_batch(mlflow_id, params=params[i:i + BATCH])
        for i in range(0, len(metrics), 1000):
            client.log_batch(mlflow_id, metrics=metrics[i:i + 1000])
        state = {"ok": "FINISHED", "failed": "FAILED", "running": "RUNNING"}.get(str(run.status.get("status")), "KILLED")
        if state != "RUNNING":
            client.set_terminated(mlflow_id, status=state, end_time=_ms(run.status.get("finished_at")))
        written.append(mlflow_id)
    return written
