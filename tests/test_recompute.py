"""python -m pipeline.recompute: a stored run's metrics recomputed from its files alone equal the run's."""

from __future__ import annotations

import polars as pl
import pytest

from pipeline.results.recompute import main
from tests.helpers.config import smoke_experiments
from tests.helpers.runs import run_in_process


@pytest.mark.parametrize("experiment, smoke", smoke_experiments())
def test_every_study_recomputes_its_stored_metrics_bit_for_bit(tmp_path, capsys, smoke_runs, experiment, smoke):
    _, ctx = smoke_runs(experiment)                 # the session's smoke run (conftest.SmokeRuns), read only
    assert main([str(ctx.run_dir), "--out", str(tmp_path / "again")]) == 0
    out = capsys.readouterr().out
    assert out.count("equal to the stored table bit for bit") == 2, out
    stored = pl.read_parquet(ctx.run_dir / "summary.parquet")
    again = pl.read_parquet(tmp_path / "again" / "summary.parquet")
    assert again.height == stored.height


def test_a_changed_estimate_or_metric_is_reported_as_a_difference(tmp_path, capsys):
    _, ctx = run_in_process(tmp_path, "run", "experiment=mie_los", "mc.runs=2")
    metrics = pl.read_parquet(ctx.run_dir / "metrics.parquet")
    metrics.with_columns(pl.when(pl.col("step") == 50).then(pl.col("value") + 1.0).otherwise(pl.col("value"))
                         .alias("value")).write_parquet(ctx.run_dir / "metrics.parquet")
    assert main([str(ctx.run_dir)]) == 1
    assert "metrics.parquet: 8888 rows recomputed, DIFFERENT: column 'value' differs" in capsys.readouterr().out


def test_a_folder_that_is_not_a_finished_run_is_a_clear_error(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err
