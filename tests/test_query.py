"""Tests for ``pipeline.results.query`` (the ``mtt-query`` CLI and its Python API) on a fake artifacts tree.

The tree follows the writer conventions: ``runs/<exp>/<ts>/`` and ``multirun/<ts>/<job>/``
with ``status.json``, ``summary.parquet`` and ``metrics.parquet``; hidden temp files
(``.summary.parquet.<random>.tmp``), ``*.rejected`` and ``cache/`` must never be read.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import polars as pl
import pytest

from pipeline.results import query as q
from pipeline.results.query import QueryError, QueryWarning, load_tables, main, query
from tests.helpers.artifacts_tree import (
    EXAMPLE, RUN_AO, RUN_CV, RUN_TRUNC, SWEEP, TRACEBACK, make_tree, write_status, write_summary,
)
from tests.helpers.processes import run_module


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
        write_status(root, d, "exp", started=f"2026-01-0{i + 1}T00:00:00+00:00")
        write_summary(root, d, "exp", cfg, {("KF", "position_rmse", "all"): i})
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
    write_status(root, d, "cv_turn", started="2026-11-23T00:00:00+00:00")
    write_summary(root, d, "cv_turn", {"mc.runs": 20},
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
    ok = run_module("pipeline.query", "sql", EXAMPLE, "--root", str(root), "--sweep", SWEEP, timeout=None)
    assert ok.returncode == 0 and "AO-VSIMM" in ok.stdout and "filters.vsimm.t1_mu" in ok.stdout
    bad = run_module("pipeline.query", "sql", "SELECT nope FROM runs", "--root", str(root), timeout=None)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "nope" in bad.stderr
