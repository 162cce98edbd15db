"""`mtt-query export-mlflow` round trip (issue 42; the [mlflow] extra, required in CI by .ci/run):
runs written into an MLflow SQLite store read back with ``mlflow.search_runs`` as they are in the
run folders: params, every summary value with its interval, provenance tags, tags and notes."""

from __future__ import annotations

import json
import shutil

import polars as pl
import pytest

from tests.helpers.extras import require_extra

require_extra("mlflow", "mlflow", "sqlalchemy", "alembic")

import mlflow  # noqa: E402

from pipeline.results import mlflow_export, tracking  # noqa: E402
from pipeline.results.cli import main as query_main  # noqa: E402
from tests.helpers.runs import run_in_process  # noqa: E402

RUN = ("experiment=ao_vsimm_s1", "mc.runs=3", "scenario.steps=30", "variants=[fsimm,ao_vsimm]")


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("mlflow_runs")
    _, a = run_in_process(root, "ao_vsimm_s1/a", *RUN)
    _, b = run_in_process(root, "ao_vsimm_s1/b", *RUN, "filters.ao_vsimm.activation_threshold=0.3")
    return root, a.run_dir, b.run_dir


def search(store, experiment="ao_vsimm_s1"):
    mlflow.set_tracking_uri(mlflow_export.store_uri(store))
    return {r.data.tags["mtt.run_id"]: r for r in mlflow.search_runs(experiment_names=[experiment], output_format="list")}


def test_runs_round_trip_through_an_mlflow_sqlite_store(two_runs, tmp_path, capsys):
    root, a, b = two_runs
    assert query_main(["tag", "--root", str(root), str(b), "lower-threshold"]) == 0
    assert query_main(["note", "--root", str(root), str(b), "t_a 0.3 instead of 0.4"]) == 0
    store = tmp_path / "mlflow.db"
    assert query_main(["export-mlflow", "--root", str(root), str(a), str(b), "--store", str(store)]) == 0
    assert "exported 2 runs" in capsys.readouterr().out
    found = search(store)
    assert set(found) == {"runs/ao_vsimm_s1/a", "runs/ao_vsimm_s1/b"}
    for folder in (a, b):
        run = tracking.resolve_run(root, folder)
        got = found[run.run_id]
        assert got.info.status == "FINISHED"
        assert got.data.params == mlflow_export.run_params(run)
        assert got.data.params["filters.ao_vsimm.activation_threshold"] == ("0.3" if folder == b else "0.4")
        assert not any(k.startswith(("paths.", "hydra.")) for k in got.data.params)
        summary = pl.read_parquet(folder / "summary.parquet").filter(
            (pl.col("variant_key") == "ao_vsimm") & (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
        row = summary.row(0, named=True)
        assert got.data.metrics["ao_vsimm.position_rmse.all"] == row["value"]
        assert got.data.metrics["ao_vsimm.position_rmse.all.ci_low"] == row["ci_low"]
        assert got.data.metrics["ao_vsimm.position_rmse.all.ci_high"] == row["ci_high"]
        assert got.data.metrics["ao_vsimm.position_rmse.all.se"] == row["standard_error"]
        status = json.loads((folder / "status.json").read_text())
        assert got.data.tags["mtt.code"] == status["provenance"]["code"]
        assert got.data.tags["mtt.config_hash"] == status["config_hash"]
        assert got.data.tags["mtt.run_dir"] == folder.as_uri()
    assert found["runs/ao_vsimm_s1/b"].data.tags["mtt.tag.lower-threshold"] == "true"
    assert found["runs/ao_vsimm_s1/b"].data.tags["mlflow.note.content"] == "t_a 0.3 instead of 0.4"
    # exporting again replaces, never duplicates
    assert query_main(["export-mlflow", "--root", str(root), str(b), "--store", str(store)]) == 0
    assert len(search(store)) == 2


def test_a_sweep_folder_becomes_a_parent_run_with_its_jobs_as_children(two_runs, tmp_path):
    root, a, b = two_runs
    sweep = root / "multirun" / "2026-12-04_00-00-00_000000"
    for job, source in (("0", a), ("1", b)):
        shutil.copytree(source, sweep / job)
    store = tmp_path / "sweep.db"
    written = mlflow_export.export(root, [str(sweep)], store)
    assert len(written) == 2
    found = search(store)
    parent = found["multirun/2026-12-04_00-00-00_000000"]
    children = [r for k, r in found.items() if k.startswith("multirun/2026-12-04_00-00-00_000000/")]
    assert len(children) == 2 and all(c.data.tags["mlflow.parentRunId"] == parent.info.run_id for c in children)
