"""A fake artifacts tree as the writers lay it out (``runs/<exp>/<ts>/`` and ``multirun/<ts>/<job>/``
with ``status.json``, ``summary.parquet`` and ``metrics.parquet``), with what a reader must skip:
hidden temp files, ``*.rejected``, ``cache/``, a truncated summary, a failed job. The query tests
(pipeline.results.query) read it."""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl

from pipeline.results import query as q
from pipeline.storage.schemas import table_metadata
from pipeline.storage.store import atomic_write_parquet

SWEEP = "multirun/2026-11-21_08-00-00_000000"
RUN_CV = "runs/cv_turn/2026-11-20_09-00-00"
RUN_AO = "runs/ao_vsimm_s1/2026-11-20_10-00-00"
RUN_TRUNC = "runs/cv_turn/2026-11-22_12-00-00"
TRACEBACK = ("Traceback (most recent call last):\n  File \"pipeline/run.py\", line 12, in main\n"
             "    run(cfg)\nnumpy.linalg.LinAlgError: Matrix is not positive definite")
EXAMPLE = q.EXAMPLE_SQL


# ---- writing a fake tree ------------------------------------------------------------------------
def write_table(df: pl.DataFrame, path: Path, table: str) -> None:
    """As the runner writes a table: its name and content checksum in the metadata (a run folder's table
    without them is refused: pipeline.storage.run_tables)."""
    atomic_write_parquet(df, path, table_metadata(table, {}, {}))


def config_hash(run_dir: Path) -> str:
    """The config hash the folder's status.json records (every table of the run carries the same)."""
    path = run_dir / "status.json"
    return json.loads(path.read_text())["config_hash"] if path.is_file() else "cfg0"


def write_status(root: Path, run_dir: Path, experiment: str, *, status: str = "ok", error=None,
            started: str, overrides=(), sweep=None, job_num=None, runs: int = 20) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "status.json").write_text(json.dumps({
        "run_id": run_dir.relative_to(root).as_posix(), "experiment": experiment, "status": status,
        "error": error, "started_at": started,
        "finished_at": None if status == "running" else started.replace(":00+", ":30+"),
        "overrides": list(overrides), "config_hash": f"h{abs(hash(str(run_dir))) % 10**8:08d}",
        "sweep": sweep, "job_num": job_num, "runs": runs}))


def write_summary(root: Path, run_dir: Path, experiment: str, config: dict, values: dict, *,
             n_runs: int = 20, overrides=(), sweep=None, job_num=None) -> pl.DataFrame:
    """values: {(variant, metric, window): value}. config: {dotted key: python value}."""
    rid = run_dir.relative_to(root).as_posix()
    rows = []
    for (variant, metric, window), v in values.items():
        rows.append({"run_id": rid, "experiment": experiment, "status": "ok", "error": None,
                     "variant": variant, "variant_key": variant.lower().replace("-", "_"),
                     "series": metric, "window": window, "value": float(v),
                     "unit": "m/s^2" if metric.startswith("acc") else "m"})
    df = pl.DataFrame(rows, schema={"run_id": pl.String, "experiment": pl.String,
                                    "status": pl.String, "error": pl.String,
                                    "variant": pl.String, "variant_key": pl.String,
                                    "series": pl.String, "window": pl.String,
                                    "value": pl.Float64, "unit": pl.String})
    df = df.with_columns(
        pl.lit(n_runs, dtype=pl.Int32).alias("n_runs"), pl.lit(config_hash(run_dir)).alias("config_hash"),
        pl.lit(" ".join(overrides)).alias("overrides"),
        pl.lit(sweep, dtype=pl.String).alias("sweep"), pl.lit(job_num, dtype=pl.Int32).alias("job_num"),
        *[pl.lit(v).alias(k) for k, v in config.items()])
    write_table(df, run_dir / "summary.parquet", "summary")
    return df


def write_metrics(root: Path, run_dir: Path, experiment: str, variants, steps: int = 5) -> None:
    rid = run_dir.relative_to(root).as_posix()
    rows = [{"run_id": rid, "experiment": experiment, "variant": v,
             "variant_key": v.lower().replace("-", "_"), "series": "position_rmse", "step": k,
             "time": 0.5 * k, "value": 1.0 + 0.1 * k, "n_runs": 20}
            for v in variants for k in range(steps)]
    write_table(pl.DataFrame(rows, schema=q.METRICS_COLUMNS), run_dir / "metrics.parquet", "metrics")


def vsimm_values(t1: float) -> dict:
    out = {}
    for variant, base in (("AO-VSIMM", 1.0), ("VSIMM", 2.0)):
        out[(variant, "acceleration_rmse_x", "all")] = base + t1
        out[(variant, "acceleration_rmse_x", "after_switch")] = 10 * base + t1
        out[(variant, "position_rmse", "all")] = 100 + base
        out[(variant, "models_evaluated", None)] = 13.0 if variant == "VSIMM" else 7.0
    return out


def make_tree(root: Path) -> Path:
    """Two single runs of different experiments (different config columns), a truncated run,
    and a 3-job sweep (job 0: t1_mu int 1, job 1: float 0.5, job 2 failed)."""
    # single run 1: cv_turn, its own config columns
    d = root / RUN_CV
    write_status(root, d, "cv_turn", started="2026-11-20T09:00:00+00:00", overrides=["filter=kf"])
    write_summary(root, d, "cv_turn", {"mc.runs": 20, "mc.seed": 0, "scenario.steps": 100,
                                  "filters.kf.q": 0.1, "scenario.turn_rates": "[0.0, 0.1]"},
             {("KF", "position_rmse", "all"): 3.0, ("KF", "compute_seconds", None): 0.2})
    write_metrics(root, d, "cv_turn", ["KF"])
    # single run 2: ao_vsimm_s1, other config columns
    d = root / RUN_AO
    write_status(root, d, "ao_vsimm_s1", started="2026-11-20T10:00:00+00:00",
            overrides=["experiment=ao_vsimm_s1", "mc.runs=50"], runs=50)
    write_summary(root, d, "ao_vsimm_s1", {"mc.runs": 50, "mc.seed": 1, "filters.vsimm.t1_mu": 0.25,
                                      "models.set": '["cv", "ca13"]'}, vsimm_values(0.25), n_runs=50)
    write_metrics(root, d, "ao_vsimm_s1", ["AO-VSIMM", "VSIMM"])
    # the sweep
    sweep = root / SWEEP
    sweep.mkdir(parents=True)
    (sweep / "multirun.yaml").write_text("hydra: {}\n")
    (sweep / ".submitit").mkdir()
    (sweep / ".submitit" / "summary.parquet").write_bytes(b"not parquet")   # hidden dir
    for job, t1 in enumerate((1, 0.5, 2)):
        d = sweep / str(job)
        ov = ["experiment=ao_vsimm_sweep", f"filters.vsimm.t1_mu={t1}"]
        cfg = {"mc.runs": 20, "mc.seed": 0, "filters.vsimm.t1_mu": t1, "scenario.steps": 100}
        if job < 2:
            write_status(root, d, "ao_vsimm_sweep", started=f"2026-11-21T08:0{job}:00+00:00",
                    overrides=ov, sweep=SWEEP, job_num=job)
            write_summary(root, d, "ao_vsimm_sweep", cfg, vsimm_values(t1), overrides=ov, sweep=SWEEP,
                     job_num=job)
            write_metrics(root, d, "ao_vsimm_sweep", ["AO-VSIMM", "VSIMM"])
        else:   # failed job: status.json + one-row summary with Null-typed metric/value/variant
            write_status(root, d, "ao_vsimm_sweep", status="failed", error=TRACEBACK,
                    started="2026-11-21T08:02:00+00:00", overrides=ov, sweep=SWEEP, job_num=job)
            write_table(pl.DataFrame({"run_id": [f"{SWEEP}/2"], "experiment": ["ao_vsimm_sweep"],
                          "status": ["failed"], "error": [TRACEBACK], "variant": [None],
                          "variant_key": [None], "series": [None], "window": [None],
                          "value": [None], "unit": [None], "n_runs": [20],
                          "config_hash": [config_hash(d)], "overrides": [" ".join(ov)], "sweep": [SWEEP],
                          "job_num": [2], **{k: [v] for k, v in cfg.items()}}
                         ), d / "summary.parquet", "summary")
    # a writer's partial temp file next to job 1's summary, and a hidden .hydra dir
    (sweep / "1" / ".summary.parquet.k3j2x9.tmp").write_bytes(b"PAR1\x15\x04")
    (sweep / "1" / ".hydra").mkdir()
    (sweep / "1" / ".hydra" / "summary.parquet").write_bytes(b"PAR1")
    # a run whose summary.parquet is truncated
    d = root / RUN_TRUNC
    write_status(root, d, "cv_turn", started="2026-11-22T12:00:00+00:00")
    good = (root / RUN_CV / "summary.parquet").read_bytes()
    (d / "summary.parquet").write_bytes(good[: len(good) // 2])
    # cache and rejected files: never read
    (root / "cache" / "summary").mkdir(parents=True)
    (root / "cache" / "summary" / "summary.parquet").write_bytes(b"garbage")
    (root / RUN_CV / "summary.parquet.20261120-090000.rejected").write_bytes(b"garbage")
    return root
