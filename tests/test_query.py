"""Tests for ``pipeline.results.query`` (the ``mtt-query`` CLI and its Python API) on a fake artifacts tree.

The tree follows the writer conventions: ``runs/<exp>/<ts>/`` and ``multirun/<ts>/<job>/``
with ``status.json``, ``summary.parquet`` and ``metrics.parquet``; hidden temp files
(``.summary.parquet.<random>.tmp``), ``*.rejected`` and ``cache/`` must never be read.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest

from pipeline.results import query as q
from pipeline.results.query import QueryError, QueryWarning, load_tables, main, query
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
def _write(df: pl.DataFrame, path: Path, table: str) -> None:
    """As the runner writes a table: its name and content checksum in the metadata (a run folder's table
    without them is refused: pipeline.storage.run_tables)."""
    atomic_write_parquet(df, path, table_metadata(table, {}, {}))


def _config_hash(run_dir: Path) -> str:
    """The config hash the folder's status.json records (every table of the run carries the same)."""
    path = run_dir / "status.json"
    return json.loads(path.read_text())["config_hash"] if path.is_file() else "cfg0"


def _status(root: Path, run_dir: Path, experiment: str, *, status: str = "ok", error=None,
            started: str, overrides=(), sweep=None, job_num=None, runs: int = 20) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "status.json").write_text(json.dumps({
        "run_id": run_dir.relative_to(root).as_posix(), "experiment": experiment, "status": status,
        "error": error, "started_at": started,
        "finished_at": None if status == "running" else started.replace(":00+", ":30+"),
        "overrides": list(overrides), "config_hash": f"h{abs(hash(str(run_dir))) % 10**8:08d}",
        "sweep": sweep, "job_num": job_num, "runs": runs}))


def _summary(root: Path, run_dir: Path, experiment: str, config: dict, values: dict, *,
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
        pl.lit(n_runs, dtype=pl.Int32).alias("n_runs"), pl.lit(_config_hash(run_dir)).alias("config_hash"),
        pl.lit(" ".join(overrides)).alias("overrides"),
        pl.lit(sweep, dtype=pl.String).alias("sweep"), pl.lit(job_num, dtype=pl.Int32).alias("job_num"),
        *[pl.lit(v).alias(k) for k, v in config.items()])
    _write(df, run_dir / "summary.parquet", "summary")
    return df


def _metrics(root: Path, run_dir: Path, experiment: str, variants, steps: int = 5) -> None:
    rid = run_dir.relative_to(root).as_posix()
    rows = [{"run_id": rid, "experiment": experiment, "variant": v,
             "variant_key": v.lower().replace("-", "_"), "series": "position_rmse", "step": k,
             "time": 0.5 * k, "value": 1.0 + 0.1 * k, "n_runs": 20}
            for v in variants for k in range(steps)]
    _write(pl.DataFrame(rows, schema=q.METRICS_COLUMNS), run_dir / "metrics.parquet", "metrics")


def _vsimm_values(t1: float) -> dict:
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
    _status(root, d, "cv_turn", started="2026-11-20T09:00:00+00:00", overrides=["filter=kf"])
    _summary(root, d, "cv_turn", {"mc.runs": 20, "mc.seed": 0, "scenario.steps": 100,
                                  "filters.kf.q": 0.1, "scenario.turn_rates": "[0.0, 0.1]"},
             {("KF", "position_rmse", "all"): 3.0, ("KF", "compute_seconds", None): 0.2})
    _metrics(root, d, "cv_turn", ["KF"])
    # single run 2: ao_vsimm_s1, other config columns
    d = root / RUN_AO
    _status(root, d, "ao_vsimm_s1", started="2026-11-20T10:00:00+00:00",
            overrides=["experiment=ao_vsimm_s1", "mc.runs=50"], runs=50)
    _summary(root, d, "ao_vsimm_s1", {"mc.runs": 50, "mc.seed": 1, "filters.vsimm.t1_mu": 0.25,
                                      "models.set": '["cv", "ca13"]'}, _vsimm_values(0.25), n_runs=50)
    _metrics(root, d, "ao_vsimm_s1", ["AO-VSIMM", "VSIMM"])
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
            _status(root, d, "ao_vsimm_sweep", started=f"2026-11-21T08:0{job}:00+00:00",
                    overrides=ov, sweep=SWEEP, job_num=job)
            _summary(root, d, "ao_vsimm_sweep", cfg, _vsimm_values(t1), overrides=ov, sweep=SWEEP,
                     job_num=job)
            _metrics(root, d, "ao_vsimm_sweep", ["AO-VSIMM", "VSIMM"])
        else:   # failed job: status.json + one-row summary with Null-typed metric/value/variant
            _status(root, d, "ao_vsimm_sweep", status="failed", error=TRACEBACK,
                    started="2026-11-21T08:02:00+00:00", overrides=ov, sweep=SWEEP, job_num=job)
            _write(pl.DataFrame({"run_id": [f"{SWEEP}/2"], "experiment": ["ao_vsimm_sweep"],
                          "status": ["failed"], "error": [TRACEBACK], "variant": [None],
                          "variant_key": [None], "series": [None], "window": [None],
                          "value": [None], "unit": [None], "n_runs": [20],
                          "config_hash": [_config_hash(d)], "overrides": [" ".join(ov)], "sweep": [SWEEP],
                          "job_num": [2], **{k: [v] for k, v in cfg.items()}}
                         ), d / "summary.parquet", "summary")
    # a writer's partial temp file next to job 1's summary, and a hidden .hydra dir
    (sweep / "1" / ".summary.parquet.k3j2x9.tmp").write_bytes(b"PAR1\x15\x04")
    (sweep / "1" / ".hydra").mkdir()
    (sweep / "1" / ".hydra" / "summary.parquet").write_bytes(b"PAR1")
    # a run whose summary.parquet is truncated
    d = root / RUN_TRUNC
    _status(root, d, "cv_turn", started="2026-11-22T12:00:00+00:00")
    good = (root / RUN_CV / "summary.parquet").read_bytes()
    (d / "summary.parquet").write_bytes(good[: len(good) // 2])
    # cache and rejected files: never read
    (root / "cache" / "summary").mkdir(parents=True)
    (root / "cache" / "summary" / "summary.parquet").write_bytes(b"garbage")
    (root / RUN_CV / "summary.parquet.20261120-090000.rejected").write_bytes(b"garbage")
    return root


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    return make_tree(tmp_path / "artifacts")


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# ---- list -----------------------------------------------------------------------------------
def test_list_shows_all_runs_including_failed(root, capsys):
    code, out, err = run_cli(capsys, "list", "--root", str(root), "--format", "csv")
    assert code == 0
    df = pl.read_csv(io.StringIO(out))
    assert df.columns == q.LIST_COLUMNS
    assert df["run_id"].to_list() == [RUN_CV, RUN_AO, f"{SWEEP}/0", f"{SWEEP}/1", f"{SWEEP}/2",
                                      RUN_TRUNC]                          # by started_at
    assert df["kind"].to_list() == ["run", "run", "multirun", "multirun", "multirun", "run"]
    failed = df.row(by_predicate=pl.col("status") == "failed", named=True)
    assert failed["run_id"] == f"{SWEEP}/2" and failed["job_num"] == 2 and failed["sweep"] == SWEEP
    assert failed["error"] == "numpy.linalg.LinAlgError: Matrix is not positive definite"
    assert failed["overrides"] == "experiment=ao_vsimm_sweep filters.vsimm.t1_mu=2"
    assert df.filter(pl.col("status") == "ok").height == 5
    assert "Traceback" not in out


def test_list_table_format_and_experiment_filter(root, capsys):
    code, out, _ = run_cli(capsys, "list", "--root", str(root), "--experiment", "ao_vsimm_sweep")
    assert code == 0
    assert out.count("multirun/2026-11-21_08-00-00_000000/") >= 3 and RUN_CV not in out
    assert "numpy.linalg.LinAlgError: Matrix is not positive definite" in out   # not truncated
    assert "experiment=ao_vsimm_sweep filters.vsimm.t1_mu=0.5" in out

    code, _, err = run_cli(capsys, "list", "--root", str(root), "--experiment", "nope")
    assert code == 2
    assert "nope" in err and "ao_vsimm_s1" in err and "cv_turn" in err


# ---- tables / schema drift --------------------------------------------------------------------
def test_load_tables_unifies_drifting_schemas(root):
    with pytest.warns(QueryWarning, match="truncated"):
        tables = load_tables(root)
    assert set(tables) == {"summary", "metrics", "runs", "per_run", "comparisons"}   # the stage tables when named
    assert all(isinstance(lf, pl.LazyFrame) for lf in tables.values())
    schema = tables["summary"].collect_schema()
    assert list(schema)[:len(q.SUMMARY_COLUMNS)] == list(q.SUMMARY_COLUMNS)
    # int in job 0, float in job 1 and the single run -> Float64; columns of both experiments
    assert schema["filters.vsimm.t1_mu"] == pl.Float64
    assert schema["filters.kf.q"] == pl.Float64 and schema["mc.runs"] == pl.Int64   # i32 + i64
    assert schema["models.set"] == pl.String and schema["value"] == pl.Float64
    df = tables["summary"].collect()
    assert df.height == 2 + 8 + 8 + 8 + 1          # cv, ao single, job 0, job 1, failed job 2
    assert df.filter(pl.col("run_id") == f"{SWEEP}/0")["filters.vsimm.t1_mu"].unique().to_list() == [1.0]
    assert df.filter(pl.col("experiment") == "cv_turn")["filters.vsimm.t1_mu"].null_count() == 2
    assert df.filter(pl.col("status") == "failed")["error"].to_list() == [TRACEBACK]
    assert tables["metrics"].collect().height == 5 * (1 + 2 + 2 + 2)
    assert tables["runs"].collect().height == 6


def test_casts_the_scanner_cannot_do(tmp_path, capsys):
    """str vs int -> String; a real list vs a JSON string -> JSON text; list vs float: skipped."""
    root = tmp_path / "a"
    cfgs = [{"scenario.label": "fast", "models.set": '["cv", "ca"]', "x": 1.0},
            {"scenario.label": 3, "models.set": ["cv", "ct"], "x": 2.0},
            {"scenario.label": "slow", "models.set": "[]", "x": [1.0]}]
    for i, cfg in enumerate(cfgs):
        d = root / "runs" / "exp" / f"2026-01-0{i + 1}_00-00-00"
        _status(root, d, "exp", started=f"2026-01-0{i + 1}T00:00:00+00:00")
        _summary(root, d, "exp", cfg, {("KF", "position_rmse", "all"): i})
    code, out, err = run_cli(capsys, "sql", 'SELECT "scenario.label", "models.set", x FROM summary '
                             "ORDER BY value", "--root", str(root), "--format", "csv")
    assert code == 0
    df = pl.read_csv(io.StringIO(out))
    assert df["scenario.label"].to_list() == ["fast", "3"]
    assert df["models.set"].to_list() == ['["cv", "ca"]', '["cv","ct"]']
    assert "2026-01-03_00-00-00/summary.parquet" in err and "clash" in err


def test_tables_command(root, capsys):
    # the config columns only with --config (issue 19: tests/test_query_overview.py checks without it)
    code, out, err = run_cli(capsys, "tables", "--root", str(root), "--format", "csv", "--config")
    assert code == 0
    df = pl.read_csv(io.StringIO(out))
    assert set(df["table"]) == {"summary", "metrics", "runs", "per_run", "comparisons"}
    row = df.filter((pl.col("table") == "summary") & (pl.col("column") == "filters.vsimm.t1_mu"))
    assert row["dtype"].to_list() == ["Float64"]
    assert "truncated" in err and RUN_TRUNC in err


# ---- sql ------------------------------------------------------------------------------------
def test_sql_example_one_row_per_variant_and_swept_value(root):
    df = query(EXAMPLE, root=root, sweep=Path(SWEEP))     # the truncated file is not in it
    assert df.columns == ["variant", "filters.vsimm.t1_mu", "value"]
    assert df.rows() == [("AO-VSIMM", 0.5, 1.5), ("AO-VSIMM", 1.0, 2.0),
                         ("VSIMM", 0.5, 2.5), ("VSIMM", 1.0, 3.0)]     # the failed job adds none
    # without --sweep the single ao_vsimm_s1 run joins in (t1_mu 0.25)
    with pytest.warns(QueryWarning):
        df = query(EXAMPLE, root=root)
    assert df.height == 6 and sorted(set(df["filters.vsimm.t1_mu"])) == [0.25, 0.5, 1.0]


def test_sql_cli_sweep_run_and_stdin(root, capsys, monkeypatch):
    code, out, err = run_cli(capsys, "sql", EXAMPLE, "--root", str(root), "--sweep",
                             str(root / SWEEP), "--format", "csv")
    assert code == 0 and err == ""           # the truncated file is outside the sweep
    assert pl.read_csv(io.StringIO(out)).height == 4
    code, out, _ = run_cli(capsys, "sql", "SELECT DISTINCT run_id FROM summary", "--root",
                           str(root), "--run", f"{SWEEP}/1", "--format", "csv")
    assert code == 0 and out.split() == ["run_id", f"{SWEEP}/1"]
    monkeypatch.setattr(sys, "stdin", io.StringIO("SELECT COUNT(*) AS n FROM runs WHERE status = 'failed'"))
    code, out, _ = run_cli(capsys, "sql", "-", "--root", str(root), "--format", "csv")
    assert code == 0 and out.split() == ["n", "1"]
    code, _, err = run_cli(capsys, "sql", "SELECT 1", "--root", str(root), "--sweep", "multirun/nope")
    assert code == 2 and "--sweep" in err and "no such directory" in err


def test_sql_join_runs_and_metrics(root, capsys):
    sql = ("SELECT r.status, COUNT(*) AS n FROM metrics m JOIN runs r ON m.run_id = r.run_id "
           "GROUP BY ALL ORDER BY ALL")
    code, out, _ = run_cli(capsys, "sql", sql, "--root", str(root), "--format", "csv")
    assert code == 0 and out.split() == ["status,n", "ok,35"]


# ---- output formats -------------------------------------------------------------------------
def test_csv_format(root, capsys):
    code, out, _ = run_cli(capsys, "sql", EXAMPLE, "--root", str(root), "--format", "csv")
    assert code == 0
    assert out.splitlines()[0] == "variant,filters.vsimm.t1_mu,value"
    assert pl.read_csv(io.StringIO(out)).height == 6


def test_markdown_format(root, capsys):
    code, out, _ = run_cli(capsys, "sql", EXAMPLE + "", "--root", str(root), "--sweep", SWEEP,
                           "--format", "markdown")
    assert code == 0
    lines = out.splitlines()
    assert len(lines) == 2 + 4 and all(ln.startswith("| ") and ln.endswith(" |") for ln in lines)
    assert [c.strip() for c in lines[0].strip("| ").split(" | ")] == ["variant", "filters.vsimm.t1_mu", "value"]
    assert lines[1].replace(" ", "").startswith("|---") and lines[1].rstrip(" |").endswith(":")
    assert [c.strip() for c in lines[2].strip("| ").split(" | ")] == ["AO-VSIMM", "0.5", "1.5"]


def test_markdown_escapes_pipes_newlines_and_nulls():
    df = pl.DataFrame({"a": ["x|y", "l1\nl2", None], "b": [1.0, None, 1 / 3]})
    md = q.to_markdown(df).splitlines()
    assert md[2].startswith("| x\\|y") and "l1<br>l2" in md[3] and "0.333333" in md[4]
    assert md[3].split("|")[-2].strip() == ""            # null -> empty cell


def test_table_format_does_not_truncate(root, capsys):
    long = "x" * 300
    code, out, _ = run_cli(capsys, "sql", f"SELECT '{long}' AS long_text, * FROM summary LIMIT 2",
                           "--root", str(root), "--run", RUN_CV)
    assert code == 0
    assert long in out and "filters.kf.q" in out and "scenario.turn_rates" in out
    assert "…" not in out.splitlines()[1]                 # no elided column headers


# ---- corrupt / hidden files ----------------------------------------------------------------------
def test_truncated_summary_skipped_with_warning(root, capsys):
    code, out, err = run_cli(capsys, "sql", "SELECT COUNT(*) AS n FROM summary", "--root",
                             str(root), "--format", "csv")
    assert code == 0 and out.split() == ["n", "27"]
    assert "warning" in err and str(root / RUN_TRUNC / "summary.parquet") in err
    # hidden temp files, hidden dirs, cache/ and *.rejected are never named, never read
    for never in (".tmp", ".hydra", ".submitit", "cache", "rejected"):
        assert never not in err


def test_damaged_data_pages_skipped_with_warning(root, capsys):
    """A file whose footer reads fine but whose data pages are damaged fails only when read."""
    pq = pytest.importorskip("pyarrow.parquet")
    d = root / "runs" / "cv_turn" / "2026-11-23_00-00-00"
    _status(root, d, "cv_turn", started="2026-11-23T00:00:00+00:00")
    _summary(root, d, "cv_turn", {"mc.runs": 20},
             {("KF", f"metric_{i}", "all"): float(i) for i in range(20_000)})
    path = d / "summary.parquet"
    rg = pq.ParquetFile(path).metadata.row_group(0)
    chunk = next(rg.column(i) for i in range(rg.num_columns) if rg.column(i).path_in_schema == "series")
    raw = bytearray(path.read_bytes())
    start = chunk.data_page_offset                   # damage the page header (compressed data
    raw[start:start + 16] = bytes(b ^ 0xFF for b in raw[start:start + 16])  # has no checksum)
    path.write_bytes(bytes(raw))
    # COUNT(*)/COUNT(col) are answered from footer statistics; reading the values hits the damage
    code, out, err = run_cli(capsys, "sql", "SELECT series FROM summary WHERE series IS NOT NULL",
                             "--root", str(root), "--format", "csv")
    assert code == 0 and len(out.split()) == 1 + 26
    assert f"skipping corrupt or truncated {path}" in err     # found when the file is read and checked


# ---- bad input ------------------------------------------------------------------------------
@pytest.mark.parametrize("sql, expect", [
    ("SELEC variant FROM summary", ["SQL syntax error", "summary, metrics, runs"]),
    ("SELECT nope FROM summary", ["nope", "Columns:", '"filters.vsimm.t1_mu"', "double quotes"]),
    ("SELECT filters.vsimm.t1_mu FROM summary", ["double-quoted", '"filters.vsimm.t1_mu"']),
    ("SELECT * FROM nope", ["nope", "summary, metrics, runs"]),
    ("SELECT variant FROM summary WHERE value = 'x'", ["query failed", "compare"]),
    ("   ", ["empty SQL query"]),
])
def test_bad_sql_exit_2_with_message(root, capsys, sql, expect):
    code, out, err = run_cli(capsys, "sql", sql, "--root", str(root))
    assert code == 2 and out == ""
    assert "Traceback" not in err
    errors = [ln for ln in err.splitlines() if not ln.startswith("mtt-query: warning:")]
    assert len(errors) == 1 and errors[0].startswith("mtt-query: error:")   # one paragraph
    for e in expect:
        assert e in errors[0]


def test_missing_and_empty_root_exit_2(tmp_path, capsys):
    code, out, err = run_cli(capsys, "list", "--root", str(tmp_path / "nope"))
    assert code == 2 and out == "" and "does not exist" in err and "--root" in err
    (tmp_path / "empty" / "cache").mkdir(parents=True)
    code, _, err = run_cli(capsys, "sql", EXAMPLE, "--root", str(tmp_path / "empty"))
    assert code == 2 and "no runs found" in err and "cache" in err
    with pytest.raises(QueryError, match="does not exist"):
        load_tables(tmp_path / "nope")


def test_module_entry_point_subprocess(root):
    repo = Path(__file__).resolve().parents[1]
    ok = subprocess.run([sys.executable, "-m", "pipeline.query", "sql", EXAMPLE, "--root",
                         str(root), "--sweep", SWEEP], cwd=repo, capture_output=True, text=True)
    assert ok.returncode == 0 and "AO-VSIMM" in ok.stdout and "filters.vsimm.t1_mu" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "pipeline.query", "sql", "SELECT nope FROM runs",
                          "--root", str(root)], cwd=repo, capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "nope" in bad.stderr
