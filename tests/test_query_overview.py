"""Issue 19: ``mtt-query tables`` lists each experiment's variants, metrics and windows first and the
tables' columns without the config columns (``--config`` adds them); a string literal compared with a
name column that matches none of its values is warned about with the close names; an unknown column's
error names the close columns only. On a tiny artifacts tree written as the runner writes it."""

from __future__ import annotations

import io
import json
from pathlib import Path

import polars as pl
import pytest

from pipeline.storage.schemas import table_metadata
from pipeline.storage.store import atomic_write_parquet
from pipeline.results.query import QueryWarning, compared_literals, main, query, tables_overview

RUN_AO = "runs/ao_vsimm_s1/2026-11-20_10-00-00"
RUN_AO_20 = "runs/ao_vsimm_s1/2026-11-21_10-00-00"
RUN_MIE = "runs/mie_los/2026-11-20_11-00-00"
CONFIG = {"mc.runs": 5, "mc.seed": 1, "filters.vsimm.t1_mu": 0.25, "metrics.reference_variant": "fsimm",
          "experiment_name": "x"}


def _run(root: Path, rel: str, experiment: str, n_runs: int, variants: dict, series: dict, config: dict) -> None:
    """series: {series: (metric, [windows], per_step)}; a window None is a window-free value."""
    d = root / rel
    d.mkdir(parents=True)
    (d / "status.json").write_text(json.dumps({"status": "ok", "experiment": experiment, "runs": n_runs,
                                               "started_at": rel.rsplit("/", 1)[1]}))
    rows, steps = [], []
    for key, display in variants.items():
        for name, (metric, windows, per_step) in series.items():
            rows += [{"variant": display, "variant_key": key, "metric": metric, "series": name, "window": w,
                      "value": 1.0, "unit": "m", "n_runs": n_runs} for w in windows]
            if per_step:
                steps += [{"variant": display, "variant_key": key, "metric": metric, "series": name, "step": k,
                           "time": float(k), "value": 1.0, "n_runs": n_runs} for k in range(3)]
    provenance = [pl.lit(rel).alias("run_id"), pl.lit(experiment).alias("experiment"), pl.lit("ok").alias("status")]
    # as the runner writes them: the table's name and content checksum in its metadata
    atomic_write_parquet(pl.DataFrame(rows).with_columns(pl.col("n_runs").cast(pl.Int32), *provenance,
                                                         *[pl.lit(v).alias(k) for k, v in config.items()]),
                         d / "summary.parquet", table_metadata("summary", {}, {}))
    atomic_write_parquet(pl.DataFrame(steps).with_columns(pl.col("n_runs").cast(pl.Int32), *provenance),
                         d / "metrics.parquet", table_metadata("metrics", {}, {}))


AO_SERIES = {"acceleration_rmse_x": ("acceleration_rmse", ["all", "after_switch"], True),
             "acceleration_rmse_y": ("acceleration_rmse", ["all", "after_switch"], True),
             "position_rmse": ("position_rmse", ["all", "after_switch"], True),
             "nees": ("nees", ["all", "after_switch"], True), "nees_lower": ("nees_lower", ["all", "after_switch"], True),
             "nees_upper": ("nees_upper", ["all", "after_switch"], True),
             "compute_seconds": ("compute_seconds", [None], False),
             **{f"fault_runs_{k}": (f"fault_runs_{k}", [None], False) for k in ("a", "b", "c", "d")}}
MIE_SERIES = {"position_rmse": ("position_rmse", ["all", "maneuver"], True),
              "detections": ("detections", ["all", "maneuver", "t1-40"], True),
              "detections_axis_x": ("detections", ["all", "maneuver", "t1-40"], True),
              "compute_seconds": ("compute_seconds", [None], False)}


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    root = tmp_path / "artifacts"
    ao = {"fsimm": "FSIMM", "vsimm": "VSIMM", "ao_vsimm": "AO-VSIMM"}
    _run(root, RUN_AO, "ao_vsimm_s1", 5, ao, AO_SERIES, CONFIG)
    _run(root, RUN_AO_20, "ao_vsimm_s1", 20, ao, AO_SERIES, CONFIG | {"mc.runs": 20})
    _run(root, RUN_MIE, "mie_los", 5, {"a": "A", "b": "B"}, MIE_SERIES,
         {"mc.runs": 5, "filters.a.window": 5, "metrics.windows.maneuver": "[41, 60]"})
    return root


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# ---- tables: the overview first, no config columns unless asked ------------------------------------
def test_tables_lists_each_experiments_metrics_and_windows_first(root, capsys):
    code, out, err = cli(capsys, "tables", "--root", str(root))
    assert code == 0 and err == ""
    overview, columns = out.split("\nColumns (")
    lines = overview.replace("\n    (", " (").splitlines()            # a wrapped header line, joined
    ao = lines.index("ao_vsimm_s1: 2 run folders (n_runs 5, 20); variants FSIMM (fsimm), VSIMM (vsimm), "
                     "AO-VSIMM (ao_vsimm)")
    mie = lines.index("mie_los: 1 run folder (n_runs 5); variants A (a), B (b)")
    assert ao < mie
    block = "\n".join(lines[ao:mie])
    # metrics grouped by their windows; the breakdown's series, the band folded, a family shortened
    assert "  \"window\" 'all', 'after_switch'; per step in metrics too:\n" in block
    flat = " ".join(block.split())                                     # the lists are wrapped at 100 columns
    assert ("acceleration_rmse (series acceleration_rmse_x, acceleration_rmse_y), nees (+_lower,_upper), "
            "position_rmse") in flat
    assert "  \"window\" IS NULL:\n      compute_seconds, fault_runs_* (4)" in block
    mie_block = " ".join("\n".join(lines[mie:]).split())
    assert "detections (series detections, detections_axis_x)" in mie_block
    assert "'all', 'maneuver', 't1-40'" in mie_block
    # then the columns, without the config columns: how many were left out and how to list them
    assert columns.startswith("7 config columns of summary left out")
    assert "`mtt-query tables --config`" in columns
    assert "filters.vsimm.t1_mu" not in out and "mc.runs" not in columns.split("\n", 1)[1]
    for fixed in ("run_id", "ci_low", "reference_key", "wilcoxon_p", "step"):
        assert fixed in columns
    assert len(out.splitlines()) < 140


def test_tables_config_markdown_and_csv(root, capsys):
    code, out, _ = cli(capsys, "tables", "--root", str(root), "--format", "csv")
    df = pl.read_csv(io.StringIO(out))                          # csv: the columns only, parseable
    assert code == 0 and df.columns == ["table", "column", "dtype"]
    assert not any("." in c for c in df["column"]) and "experiment_name" not in df["column"].to_list()
    assert "interval" in df.filter(pl.col("table") == "summary")["column"].to_list()   # not a config column
    code, out, _ = cli(capsys, "tables", "--root", str(root), "--format", "csv", "--config")
    df = pl.read_csv(io.StringIO(out)).filter(pl.col("table") == "summary")
    assert {"filters.vsimm.t1_mu", "mc.runs", "experiment_name", "filters.a.window"} <= set(df["column"])
    code, out, _ = cli(capsys, "tables", "--root", str(root), "--format", "markdown")
    assert code == 0 and "### mie_los: 1 run folder (n_runs 5); variants A (a), B (b)" in out
    assert "- \"window\" IS NULL: `compute_seconds`" in out and "## Columns (" in out and "| table" in out
    # the Python API
    frames = tables_overview(root)
    m = frames["metrics"].filter(pl.col("experiment") == "mie_los")
    assert m["metric"].to_list() == ["compute_seconds", "detections", "position_rmse"]
    assert m.filter(pl.col("metric") == "detections")["windows"].to_list() == [["all", "maneuver", "t1-40"]]
    assert m["per_step"].to_list() == [False, True, True]


def test_an_old_summary_without_the_metric_column_lists_its_series(tmp_path, capsys):
    from tests.helpers.artifacts_tree import make_tree
    root = make_tree(tmp_path / "artifacts")
    with pytest.warns(QueryWarning):                                 # the tree's truncated file
        frames = tables_overview(root)
    vsimm = frames["metrics"].filter(pl.col("experiment") == "ao_vsimm_sweep")
    assert set(vsimm["metric"]) == {"acceleration_rmse_x", "position_rmse", "models_evaluated"}


# ---- literals that name nothing --------------------------------------------------------------------
def test_the_literals_compared_with_name_columns():
    sql = ("SELECT 'metric = ''x''' AS t, \"filters.a.variant\" FROM summary s WHERE s.metric = 'pos' "
           "AND 'all' = \"window\" AND variant IN ('A', 'B''s') AND series NOT LIKE 'det%' "
           "AND s.\"window\" <> 'w' AND value = 'v' AND \"filters.a.variant\" = 'cfg'")
    found = [(c.column, c.op, c.literal) for c in compared_literals(sql)]
    assert found == [("metric", "=", "pos"), ("window", "=", "all"), ("variant", "IN", "A"),
                     ("variant", "IN", "B's"), ("series", "NOT LIKE", "det%"), ("window", "<>", "w")]


def test_a_literal_that_is_no_metric_warns_with_the_close_names(root, capsys):
    code, out, err = cli(capsys, "sql", "SELECT * FROM summary WHERE metric = 'pos_rmse'", "--root", str(root),
                         "--format", "csv")
    assert code == 0 and pl.read_csv(io.StringIO(out)).height == 0     # no row, as before ...
    warning = [ln for ln in err.splitlines() if ln.startswith("mtt-query: warning:")]
    assert len(warning) == 1                                          # ... but said, once, on stderr
    assert "'pos_rmse' is no metric in summary" in warning[0] and "'position_rmse'" in warning[0]
    assert "matches no row" in warning[0] and "mtt-query tables" in warning[0]
    # series, variant (case), window, IN lists, LIKE, the per-step table; each literal once
    sql = ("SELECT COUNT(*) AS n FROM metrics m JOIN summary s ON m.run_id = s.run_id WHERE m.series IN "
           "('position_rmse', 'acc_rmse_x') AND s.variant = 'Fsimm' AND s.\"window\" = 'after-switch' "
           "AND s.experiment LIKE 'mie_lo' AND s.variant <> 'Fsimm'")
    code, _, err = cli(capsys, "sql", sql, "--root", str(root), "--format", "csv")
    lines = err.splitlines()
    assert code == 0 and len(lines) == 4, err
    assert "'acc_rmse_x' is no series in summary, metrics" in lines[0] and "'acceleration_rmse_x'" in lines[0]
    assert "'Fsimm' is no variant" in lines[1] and "close: 'FSIMM'" in lines[1]
    assert "'after-switch' is no window" in lines[2] and "'after_switch'" in lines[2]
    assert "no experiment matches LIKE 'mie_lo'" in lines[3] and "'mie_los'" in lines[3]
    code, _, err = cli(capsys, "sql", "SELECT * FROM summary WHERE series <> 'posit'", "--root", str(root))
    assert "excluding it excludes nothing" in err and "'position_rmse'" in err


def test_literals_that_exist_warn_nothing(root, capsys):
    sql = ("SELECT variant, AVG(value) AS v FROM summary WHERE metric = 'acceleration_rmse' AND \"window\" = 'all' "
           "AND variant IN ('FSIMM', 'AO-VSIMM') AND series LIKE 'acceleration_rmse_%' AND experiment = 'ao_vsimm_s1' "
           "AND 'x = ''nope''' <> 'y' GROUP BY ALL ORDER BY ALL")
    code, out, err = cli(capsys, "sql", sql, "--root", str(root), "--format", "csv")
    assert code == 0 and err == "" and pl.read_csv(io.StringIO(out)).height == 2
    with pytest.warns(QueryWarning, match="'pos_rmse' is no metric"):       # the Python API: a QueryWarning
        assert query("SELECT * FROM summary WHERE metric = 'pos_rmse'", root=root).height == 0


# ---- an unknown column: the close ones only --------------------------------------------------------
@pytest.mark.parametrize("sql, close", [
    ("SELECT variantt FROM summary", ["variant (summary)", "variant_key (summary)"]),
    ("SELECT s.metrc FROM summary s", ["metric (summary)"]),
    ("SELECT t1_mu FROM summary", ['"filters.vsimm.t1_mu" (summary)']),
    ("SELECT filters.vsim.t1_mu FROM summary", ['"filters.vsimm.t1_mu" (summary)', "double-quoted"]),
    ('SELECT "filters.vsim.t1_mu" FROM summary', ['"filters.vsimm.t1_mu" (summary)']),
    ("SELECT serie FROM metrics", ["series (metrics)"]),
])
def test_a_column_typo_names_the_close_columns_only(root, capsys, sql, close):
    code, out, err = cli(capsys, "sql", sql, "--root", str(root))
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and "Close column names:" in err
    for name in close:
        assert name in err
    assert "`mtt-query tables` lists every table's columns (`--config` with the config columns)" in err
    assert "mc.seed" not in err and len(err) < 1200                       # not every column (was ~9 KB)


def test_a_column_with_no_close_name_lists_the_columns_without_the_config_ones(root, capsys):
    code, _, err = cli(capsys, "sql", "SELECT zzz FROM summary", "--root", str(root))
    assert code == 2 and "No column is named like it" in err
    assert "summary: run_id, experiment" in err and "ci_low" in err
    assert "and 7 config columns" in err and "filters.a.window" not in err
