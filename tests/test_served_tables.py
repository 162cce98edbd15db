"""What the query, the report and a sweep's aggregation serve from a run folder (issue 37, items
9-13). Each test is the case that went wrong, on a copy of the session's smoke run
(tests/conftest.py), in-process."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import polars as pl
import pytest

from pipeline.results.query import QueryError, query
from pipeline.results.report import ReportError, load_run

EXPERIMENT = "ao_vsimm_s1"


@pytest.fixture()
def artifacts(tmp_path: Path, smoke_runs) -> Path:
    """An artifacts root holding a copy of the smoke run of study 001 (the session's stays as it is)."""
    _, ctx = smoke_runs(EXPERIMENT)
    root = tmp_path / "artifacts"
    shutil.copytree(ctx.run_dir, root / "runs" / EXPERIMENT / "run")
    return root


def _run(root: Path) -> Path:
    return root / "runs" / EXPERIMENT / "run"


def _collect(messages: list[str]):
    return messages.append


def _rewritten_by_another_tool(path: Path, factor: float = 1.5) -> None:
    """What pandas, DuckDB or a polars one-liner leaves: the rows changed, the project's metadata gone."""
    df = pl.read_parquet(path)
    df.with_columns(pl.col("value") * factor).write_parquet(path)


# ---- item 10: a table without the project's metadata ------------------------------------------
def test_a_table_without_a_checksum_is_not_served(artifacts):
    """A summary x1.5 rewritten by another tool was served as FSIMM 19.5 models/step, without a word."""
    run = _run(artifacts)
    _rewritten_by_another_tool(run / "summary.parquet")
    said: list[str] = []
    served = query("SELECT variant, value FROM summary WHERE series = 'models_evaluated'", artifacts, warn=said.append)
    assert served.height == 0
    assert any("summary.parquet" in m and "carries no content checksum" in m for m in said), said
    with pytest.raises(ReportError, match="carries no content checksum"):
        load_run(run)


# ---- item 11: two variants' estimates swapped -------------------------------------------------
def test_swapped_estimates_are_not_served_under_each_others_names(artifacts):
    run = _run(artifacts)
    fsimm, vsimm = run / "estimates" / "fsimm.parquet", run / "estimates" / "vsimm.parquet"
    held = fsimm.read_bytes()
    fsimm.write_bytes(vsimm.read_bytes())
    vsimm.write_bytes(held)
    said: list[str] = []
    served = query("SELECT DISTINCT variant_key FROM estimates ORDER BY ALL", artifacts, warn=said.append)
    assert served["variant_key"].to_list() == ["ao_vsimm"]
    assert any("estimates/fsimm.parquet" in m and "stored as estimates/vsimm.parquet" in m for m in said), said
    assert any("estimates/vsimm.parquet" in m and "stored as estimates/fsimm.parquet" in m for m in said), said


def test_an_estimates_table_the_run_never_wrote_is_not_served(artifacts):
    run = _run(artifacts)
    shutil.copy(run / "estimates" / "fsimm.parquet", run / "estimates" / "extra.parquet")
    said: list[str] = []
    served = query("SELECT DISTINCT variant_key FROM estimates ORDER BY ALL", artifacts, warn=said.append)
    assert served["variant_key"].to_list() == ["ao_vsimm", "fsimm", "vsimm"]
    assert any("estimates/extra.parquet" in m and "wrote no table under that name" in m for m in said), said


# ---- item 13: a table copied from another run -------------------------------------------------
@pytest.fixture()
def other_seed(artifacts, smoke_runs) -> Path:
    """The same experiment at seed 2, beside the copy of the smoke run (seed 1 there)."""
    from tests.helpers.config import smoke_experiments
    from tests.helpers.runs import run_in_process

    overrides = dict(smoke_experiments())[EXPERIMENT]
    _, ctx = run_in_process(artifacts, f"{EXPERIMENT}/seed2", f"experiment={EXPERIMENT}", "mc.runs=2", "mc.seed=2",
                            *overrides)
    return ctx.run_dir


def test_a_summary_copied_from_another_run_is_not_served(artifacts, other_seed):
    run = _run(artifacts)
    shutil.copy(other_seed / "summary.parquet", run / "summary.parquet")
    shutil.copy(other_seed / "truth.parquet", run / "truth.parquet")
    said: list[str] = []
    served = query("SELECT DISTINCT run_id FROM summary ORDER BY ALL", artifacts, warn=said.append)
    assert served["run_id"].to_list() == [f"runs/{EXPERIMENT}/seed2"]     # seed 2's own folder still serves it
    assert any("run/summary.parquet" in m and "copied from another run folder" in m for m in said), said
    truth = query("SELECT DISTINCT run_id FROM truth ORDER BY ALL", artifacts, warn=said.append)
    assert truth["run_id"].to_list() == [f"runs/{EXPERIMENT}/seed2"]
    assert any("run/truth.parquet" in m and "not the table this run computed" in m for m in said), said
    with pytest.raises(ReportError, match="copied from another run folder"):
        load_run(run)


def test_a_summary_of_another_config_under_this_runs_id_is_not_served(artifacts):
    """The config hash too: a status.json and a summary that disagree on it are not one run's."""
    run = _run(artifacts)
    status = json.loads((run / "status.json").read_text())
    (run / "status.json").write_text(json.dumps({**status, "run_id": f"runs/{EXPERIMENT}/run", "config_hash": "0" * 16}))
    said: list[str] = []
    assert query("SELECT * FROM metrics", artifacts, warn=said.append).height == 0
    assert any("metrics.parquet" in m and "status.json records 0000000000000000" in m for m in said), said


# ---- item 12: a sweep's aggregation -----------------------------------------------------------
def test_aggregate_leaves_out_a_rewritten_job_summary_and_says_skipped(artifacts, capsys):
    from pipeline.launch.aggregate import main
    from pipeline.results.sweep import collect, format_glance

    sweep = artifacts / "multirun" / "2026-12-04_10-00-00"
    for job in ("0", "1"):
        shutil.copytree(_run(artifacts), sweep / job)
        status = json.loads((sweep / job / "status.json").read_text())
        (sweep / job / "status.json").write_text(json.dumps({**status, "job_num": int(job),
                                                             "overrides": [f"mc.seed={job}"]}))
    _rewritten_by_another_tool(sweep / "1" / "summary.parquet")
    collected = collect(sweep)
    assert set(collected.summary["job"].unique().to_list()) == {collected.jobs[0].label}
    glance = format_glance(collected).splitlines()
    assert glance[2].endswith("ok") and " skipped: " in glance[3] and "no content checksum" in glance[3], glance
    assert collected.index["status"].to_list() == ["ok", "skipped"]
    assert main([str(sweep)]) == 1
    err = capsys.readouterr().err
    assert "0 failed, 1 skipped" in err and "job 1 skipped:" in err
    written = pl.read_parquet(sweep / "sweep_summary.parquet")
    assert written["job"].unique().to_list() == [collected.jobs[0].label]
