"""Recompute a stored run's metrics from its files alone: ``python -m pipeline.recompute <run> [--out DIR]``.

Reads the run's ``config.yaml`` (the resolved config it ran with), builds its study, scenario,
sensor and filters from it (no stage runs: nothing is simulated or filtered), reads
``truth.parquet`` and ``estimates/<variant>.parquet`` through the study's codecs, and runs the
evaluate stage (``pipeline.run.runner.evaluate_stage``) on them. The recomputed per-step metrics and
summary are compared with the stored ``metrics.parquet`` and ``summary.parquet``, value for value
(bit for bit, NaN equal to NaN); exit 0 when they agree, 1 when they differ, 2 when the folder is
not a finished run. ``--out DIR`` also writes the recomputed tables there (e.g. after a change of
the metric code, to compare old and new readings of the same estimates).

First the config: ``config.yaml``'s hash must be the one the run recorded (``status.json``'s
``config_hash``, else the summary's ``mtt.config_hash``), or the folder is refused (exit 2): a
config edited after the run would have its metrics "recomputed" with values the run never ran with,
and a match would certify nothing. Moved class names (pipeline.run.stored) are the same config.

What the metrics need from the sensor (true biases, active periods, noise levels) are its
configured values, rebuilt from ``config.yaml``; the random parts of a run are all in the tables.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import polars as pl

SUMMARY_KEY = ["variant_key", "metric", "window"]
METRICS_KEY = ["variant_key", "metric", "step"]


MEASURED = ("compute_seconds", "compute_pct_of_reference")     # timed by the run, not recomputable from its files


class RecomputeError(Exception):
    """A folder that is not a finished run."""


def config_hash_check(run_dir: Path, status: dict, cfg) -> str:
    """One line saying that ``run_dir/config.yaml`` is the config the run recorded (its hash, as
    ``pipeline.run.runner`` computes it, equals ``status.json``'s ``config_hash``, or the summary's
    ``mtt.config_hash`` where status.json has none), or that no hash was recorded; RecomputeError when
    it differs (the file was edited after the run). ``cfg`` is the file with moved class names mapped
    (pipeline.run.stored): a stored run of before the moves matches as written, the same file mapped
    matches too."""
    from omegaconf import OmegaConf

    from pipeline.storage.run_tables import META_CONFIG_HASH
    from pipeline.storage.store import stable_hash
    path = run_dir / "config.yaml"
    recorded, where = str(status.get("config_hash") or ""), "status.json's config_hash"
    if not recorded:
        try:
            meta = pl.read_parquet_metadata(run_dir / "summary.parquet")
        except (OSError, pl.exceptions.PolarsError):
            meta = {}
        recorded, where = str(meta.get(META_CONFIG_HASH) or ""), f"summary.parquet's {META_CONFIG_HASH}"
    if not recorded:
        return (f"config.yaml: the run recorded no config hash (status.json config_hash), so whether the file "
                f"was edited since cannot be told; the comparison below is with the config as it is now")
    written = stable_hash(OmegaConf.to_container(OmegaConf.load(path), resolve=False))
    mapped = stable_hash(OmegaConf.to_container(cfg, resolve=False))
    if recorded not in (written, mapped):
        raise RecomputeError(
            f"{path}: edited after the run: its config hash is {written}, but the run recorded {recorded} "
            f"({where}). The stored tables were computed with another config, so recomputing them from this "
            f"one would certify nothing; nothing was recomputed. Restore the config.yaml the run wrote, or run "
            f"the edited config as a new run (python -m pipeline.rerun {run_dir}).")
    return f"config.yaml: config hash {recorded}, the one the run recorded ({where}): not edited since"


def recompute(run_dir: Path, plugins: Sequence[str] = (), said: list[str] | None = None
              ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(metrics, summary) of the stored run, recomputed from its files; ``plugins`` the packages its
    ``plugins.packages`` may list (a stored folder is input: pipeline.run.stored.check_stored_packages).
    First its config.yaml is held to the hash the run recorded (``config_hash_check``; its line is
    appended to ``said``)."""
    from pipeline.storage.estimates import StoredEstimates
    from pipeline.run.runner import evaluate_stage, prepare
    from pipeline.run.stored import check_stored_packages, stored_config
    from pipeline.evaluation.faults import fault_summary
    from pipeline.storage.store import read_table
    from pipeline.studies.single_target import flags_from_table

    run_dir = Path(run_dir)
    status_path = run_dir / "status.json"
    if not (run_dir / "config.yaml").is_file() or not status_path.is_file():
        raise RecomputeError(f"{run_dir}: not a run folder (no config.yaml / status.json)")
    status = json.loads(status_path.read_text())
    if status.get("status") != "ok":
        raise RecomputeError(f"{run_dir}: the run's status is {status.get('status')!r}, not 'ok'; nothing to recompute")
    cfg = stored_config(run_dir)
    line = config_hash_check(run_dir, status, cfg)       # before anything is built from it
    if said is not None:
        said.append(line)
    check_stored_packages(cfg, run_dir, plugins, f"python -m pipeline.recompute {run_dir} --plugins {{packages}}")
    prepared = prepare(cfg)
    truth = prepared.study.truth_from_frame(*read_table(run_dir / "truth.parquet"))
    runs, steps = truth.runs, truth.time.size
    tables = {v: run_dir / "estimates" / f"{v}.parquet" for v in prepared.variants}
    display, faults = {}, {}
    for v, path in tables.items():
        # the fault column alone; the whole table is read and its checksum verified once, below
        columns = [c for c in ("run", "step", "fault") if c in pl.read_parquet_schema(path)]
        display[v] = str(getattr(prepared.estimators[v], "name", v))
        faults[v] = fault_summary(flags_from_table(pl.read_parquet(path, columns=columns), runs, steps))
    # one variant at a time, as the run held them (pipeline.storage.estimates)
    estimates = StoredEstimates(tables, prepared.study.estimate_from_frame)
    evaluated = evaluate_stage(cfg, prepared.study, prepared.sensor, truth, estimates, display, faults, runs)
    return evaluated.metrics, evaluated.summary


def differences(stored: pl.DataFrame, recomputed: pl.DataFrame, key: list[str], columns: list[str]) -> list[str]:
    """What differs between two tables on ``columns``, matched on ``key`` ([] when equal bit for bit)."""
    a = stored.select(key + columns).sort(key, nulls_last=True)
    b = recomputed.select(key + columns).sort(key, nulls_last=True)
    if a.height != b.height:
        return [f"{a.height} rows stored, {b.height} recomputed"]
    problems = []
    for column in key + columns:
        x, y = a[column], b[column]
        if x.dtype.is_numeric():
            same = np.array_equal(x.to_numpy().astype(float), y.to_numpy().astype(float), equal_nan=True)
        else:
            same = x.equals(y)
        if not same:
            problems.append(f"column {column!r} differs")
    return problems


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.recompute", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder (artifacts/runs/<experiment>/<time>, or a sweep job's folder)")
    parser.add_argument("--out", help="write the recomputed metrics.parquet and summary.parquet here")
    parser.add_argument("--plugins", nargs="+", default=[], metavar="PACKAGE",
                        help="packages the run's plugins.packages lists that you trust to be imported and built "
                             "(a stored folder's own list is not taken on its word)")
    args = parser.parse_args(argv)
    from pipeline.errors import PipelineError
    from pipeline.storage.store import TableDamaged
    said: list[str] = []
    try:
        metrics, summary = recompute(Path(args.run), args.plugins, said)
    except (RecomputeError, PipelineError, FileNotFoundError, TableDamaged) as exc:
        print(f"recompute: {exc}", file=sys.stderr)
        return 2
    for line in said:
        print(line)
    # the stored tables as written: a damaged one shows here as rows that differ from the recomputed
    stored_metrics = pl.read_parquet(Path(args.run) / "metrics.parquet")
    stored_summary = pl.read_parquet(Path(args.run) / "summary.parquet")
    # compute time is measured, not recomputed: the run timed its filtering passes (pipeline.evaluation.timing),
    # the files keep only the track stage's pass; its rows are left out of the comparison
    timed = pl.col("series").is_in(list(MEASURED))
    stored_recomputable, recomputable = stored_summary.filter(~timed), summary.filter(~timed)
    report = {"metrics.parquet": differences(stored_metrics, metrics, METRICS_KEY, ["variant", "time", "value", "n_runs"]),
              "summary.parquet": differences(stored_recomputable, recomputable, SUMMARY_KEY, ["variant", "value", "unit", "n_runs", "n_valid_runs",
                                                                                   "standard_error", "ci_low", "ci_high", "interval"])}
    for name, problems in report.items():
        rows = (metrics if name.startswith("metrics") else recomputable).height
        print(f"{name}: {rows} rows recomputed, " + ("equal to the stored table bit for bit" if not problems
                                                     else "DIFFERENT: " + "; ".join(problems)))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        metrics.write_parquet(out / "metrics.parquet")
        summary.write_parquet(out / "summary.parquet")
        print(f"written to {out}")
    return 1 if any(report.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
