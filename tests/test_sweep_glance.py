"""Sweeps at a glance (issue 18): the jobs table with each job's swept values (sweep_index.parquet),
the swept columns first in sweep_summary.parquet, the table printed at the end of a multirun, the
report index's swept columns, figures of a summary metric against each swept key (with the 95 %
intervals where the summary has them) and the sweep's recording with one line per job and variant."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import polars as pl
import pytest

from pipeline.results import sweep as sweep_module
from pipeline.views.colours import variant_colour
from pipeline.storage.store import read_table
from pipeline.results.sweep import NO_WINDOW, SweepError, collect, draw_metric_figure, metric_against, select_metric
from pipeline.views.sweep_recording import DEFAULT_SERIES
from tests.helpers.rrd_reading import read_chunks
from tests.helpers.processes import run_pipeline

T1_MU, SEED = "filters.vsimm.t1_mu", "mc.seed"
VARIANTS = ["fsimm", "vsimm", "ao_vsimm"]


@pytest.fixture(scope="module")
def real_sweep(tmp_path_factory):
    """Four jobs: two swept keys, one float (t1_mu), one integer (mc.seed)."""
    root = tmp_path_factory.mktemp("glance")
    proc = run_pipeline("-m", f"{T1_MU}=0.8,0.9", f"{SEED}=1,2", "mc.runs=3", "scenario.steps=40", "record.enabled=false", artifacts=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (folder,) = (root / "multirun").iterdir()
    return folder, proc.stderr


def _overrides(job_dir: Path) -> dict[str, str]:
    return dict(o.split("=", 1) for o in json.loads((job_dir / "status.json").read_text())["overrides"])


def test_the_sweep_index_lists_each_job_with_its_swept_values(real_sweep):
    folder, _ = real_sweep
    index, meta = read_table(folder / "sweep_index.parquet")
    assert index.columns == ["job_num", "job", "status", "experiment", "error", "run_dir", T1_MU, SEED]
    assert index.schema[T1_MU] == pl.Float64 and index.schema[SEED] == pl.Int64 and index.schema["job_num"] == pl.Int32
    assert json.loads(meta["mtt.swept_keys"]) == [T1_MU, SEED]
    assert index["job_num"].to_list() == [0, 1, 2, 3] and set(index["status"]) == {"ok"}
    assert set(index["experiment"]) == {"ao_vsimm_s1"} and index["error"].null_count() == 4
    for row in index.iter_rows(named=True):
        given = _overrides(folder / row["run_dir"])          # what the job was launched with
        assert row[T1_MU] == float(given[T1_MU]) and row[SEED] == int(given[SEED])
        assert row["job"] == f"t1_mu={given[T1_MU]}, seed={given[SEED]}"
    assert sorted(zip(index[T1_MU], index[SEED])) == [(0.8, 1), (0.8, 2), (0.9, 1), (0.9, 2)]


def test_the_sweep_summary_puts_the_job_and_its_swept_values_first(real_sweep):
    folder, _ = real_sweep
    summary, meta = read_table(folder / "sweep_summary.parquet")
    index = pl.read_parquet(folder / "sweep_index.parquet")
    assert summary.columns[:3] == ["job", T1_MU, SEED] and json.loads(meta["mtt.swept_keys"]) == [T1_MU, SEED]
    per_job = summary.select("job_num", "job", T1_MU, SEED).unique().sort("job_num")
    assert per_job.equals(index.select("job_num", "job", T1_MU, SEED))


def test_the_end_of_a_multirun_prints_the_jobs_at_a_glance(real_sweep):
    _, stderr = real_sweep
    table = stderr[stderr.index("job  t1_mu"):].splitlines()
    assert table[0].split() == ["job", "t1_mu", "seed", "status"]
    assert [line.split() for line in table[2:6]] == [
        [str(job), *_swept_text(real_sweep[0] / str(job)), "ok"] for job in range(4)]


def _swept_text(job_dir: Path) -> list[str]:
    given = _overrides(job_dir)
    return [given[T1_MU], given[SEED]]


def test_the_figure_data_is_the_summary_per_job_variant_and_panel(real_sweep, tmp_path):
    folder, _ = real_sweep
    sweep = collect(folder)
    data, series, window = metric_against(sweep, "position_rmse", None, T1_MU)
    assert (series, window) == ("position_rmse", "all")
    assert data.schema["x"] == pl.Float64
    assert data["panel"].unique(maintain_order=True).to_list() == ["seed=1", "seed=2"]   # the other swept key
    assert data.height == 4 * 3 and data["ci_low"].null_count() == 0                  # every point with its interval
    assert (data["ci_low"] <= data["value"]).all() and (data["value"] <= data["ci_high"]).all()
    first = data.filter(pl.col("panel") == "seed=1")
    assert first["variant_key"].to_list() == ["fsimm", "fsimm", "vsimm", "vsimm", "ao_vsimm", "ao_vsimm"]
    assert first["x"].to_list() == [0.8, 0.9] * 3
    summary = pl.read_parquet(folder / "sweep_summary.parquet")
    for row in data.iter_rows(named=True):
        stored = summary.filter((pl.col("job_num") == row["job_num"]) & (pl.col("variant_key") == row["variant_key"])
                                & (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
        assert stored["value"].to_list() == [row["value"]] and stored[T1_MU][0] == row["x"]

    assert sweep_module.main([str(folder), "--metric", "position_rmse", "--out", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["position_rmse_all_vs_filters.vsimm.t1_mu.png",
                                                              "position_rmse_all_vs_mc.seed.png"]
    assert (tmp_path / "position_rmse_all_vs_mc.seed.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_intervals_are_used_where_the_summary_has_them(real_sweep, tmp_path):
    """The uncertainty columns (n_valid_runs, standard_error, ci_low, ci_high, interval) as another
    change adds them; a row with a null interval gets no bar."""
    sweep = collect(real_sweep[0])
    value = pl.col("value")
    sweep.summary = sweep.summary.with_columns(
        pl.col("n_runs").cast(pl.Int32).alias("n_valid_runs"), (0.05 * value).alias("standard_error"),
        pl.when(pl.col("variant_key") != "ao_vsimm").then(value * 0.9).alias("ci_low"),
        pl.when(pl.col("variant_key") != "ao_vsimm").then(value * 1.1).alias("ci_high"),
        pl.lit("t").alias("interval"))
    data, _, _ = metric_against(sweep, "position_rmse", "all", SEED)
    with_bars = data.filter(pl.col("variant_key") != "ao_vsimm")
    assert (with_bars["ci_low"] - with_bars["value"] * 0.9).abs().max() < 1e-12
    assert (with_bars["ci_high"] - with_bars["value"] * 1.1).abs().max() < 1e-12
    assert data.filter(pl.col("variant_key") == "ao_vsimm")["ci_low"].null_count() == 4
    assert data["x"].to_list()[:2] == [1, 2] and data["panel"].unique(maintain_order=True).to_list() == [
        "t1_mu=0.8", "t1_mu=0.9"]
    path = tmp_path / "with_ci.png"
    draw_metric_figure(data, x=SEED, series="position_rmse", window="all", unit="m", path=path,
                       colours={k: variant_colour(i) for i, k in enumerate(VARIANTS)})
    assert path.stat().st_size > 10_000


def test_categorical_swept_values_are_categories_in_job_order(tmp_path):
    """A swept experiment: text on a category axis, in the jobs' order (not alphabetical)."""
    rows = []
    for job, (experiment, runs) in enumerate([("s2", 10), ("s1", 10), ("s2", 20), ("s1", 20)]):
        for i, key in enumerate(VARIANTS):
            rows.append({"job_num": job, "job": f"experiment={experiment}, runs={runs}", "experiment": experiment,
                         "mc.runs": runs, "variant_key": key, "variant": key.upper(), "series": "nees",
                         "metric": "nees", "window": "all", "value": 1.0 + job + i / 10, "unit": "1",
                         "status": "ok"})
    summary = pl.DataFrame(rows)
    sweep = sweep_module.Sweep(tmp_path, [], ["experiment", "mc.runs"], {"experiment": "experiment", "mc.runs": "runs"},
                               summary, pl.DataFrame())
    data, _, _ = metric_against(sweep, "nees", None, "experiment")
    assert data.schema["x"] == pl.String and data.schema["ci_high"] == pl.Float64
    assert data.filter(pl.col("panel") == "runs=10")["x"].to_list() == ["s2", "s1"] * 3
    draw_metric_figure(data, x="experiment", series="nees", window="all", unit="", path=tmp_path / "c.png",
                       colours={k: variant_colour(i) for i, k in enumerate(VARIANTS)})
    assert (tmp_path / "c.png").is_file()


@pytest.mark.parametrize("args, says", [
    (["--metric", "positon_rmse"], ["no metric 'positon_rmse'", "position_rmse, position_rmse_over_bound"]),
    (["--metric", "acceleration_rmse"], ["broken down", "acceleration_rmse_x, acceleration_rmse_y"]),
    (["--metric", "nees", "--window", "last"], ["no window 'last'", "its windows are all."]),
    (["--metric", "nees", "--x", "mc.runs"], ["'mc.runs' is not a swept key", f"are {T1_MU}, {SEED}."]),
])
def test_an_unknown_metric_window_or_key_is_one_paragraph_naming_what_exists(real_sweep, capsys, args, says):
    assert sweep_module.main([str(real_sweep[0]), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sweep: ") and err.count("\n") == 1 and "Traceback" not in err
    for text in says:
        assert text in err, err


def test_a_window_free_metric_is_chosen_by_its_own_name(real_sweep):
    sweep = collect(real_sweep[0])
    rows, series, window = select_metric(sweep.summary, "compute_seconds", None)
    assert (series, window) == ("compute_seconds", None) and rows.height == 4 * 3
    assert select_metric(sweep.summary, "compute_seconds", NO_WINDOW)[2] is None
    with pytest.raises(SweepError, match="has no window 'all'; its windows are -"):
        select_metric(sweep.summary, "compute_seconds", "all")


def test_the_sweep_recording_has_one_line_per_job_and_variant(real_sweep):
    import rerun as rr
    from rerun.chunk import RrdReader

    folder, _ = real_sweep
    path = folder / "sweep.rrd"
    reader = RrdReader(path)
    assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("mtt", f"sweep_{folder.name}")]
    assert reader.blueprints(), "no blueprint stored in the .rrd"
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".sweep.rrd")], "temporary file left behind"
    index = pl.read_parquet(folder / "sweep_index.parquet")
    labels = index["job"].to_list()
    series = ["position_rmse", "velocity_rmse", "acceleration_rmse_x", "acceleration_rmse_y", "nees", "nis"]
    assert set(series) <= set(DEFAULT_SERIES)            # the study has more series: the default set is drawn
    expected = {f"/metrics/{s}/{rr.escape_entity_path_part(label)}/{v}" for s in series for label in labels
                for v in VARIANTS}
    chunks = read_chunks(path)
    temporal = {p for p, static, _, _ in chunks if not static}
    assert temporal == expected
    for label, run_dir in zip(labels, index["run_dir"]):      # each line: its job's finite values, on both timelines
        metrics = pl.read_parquet(folder / run_dir / "metrics.parquet").filter(pl.col("value").is_finite())
        for s in series:
            for v in VARIANTS:
                entity = f"/metrics/{s}/{rr.escape_entity_path_part(label)}/{v}"
                want = metrics.filter((pl.col("series") == s) & (pl.col("variant_key") == v)).sort("step")
                got = pl.concat([df for p, static, timelines, df in chunks if p == entity and not static
                                 and timelines == {"time", "step"}]).sort("step")
                assert got["step"].to_list() == want["step"].to_list()
                assert got["Scalars:scalars"].list.first().to_list() == want["value"].to_list()
    names, colours = {}, {}
    for p, static, _, df in chunks:
        if static and "SeriesLines:names" in df.columns:
            names[p] = df["SeriesLines:names"][0][0]
            colours[p] = df["SeriesLines:colors"][0][0]
    first = rr.escape_entity_path_part(labels[0])
    for i, v in enumerate(VARIANTS):          # the first job in the run recordings' colour of the variant
        entity = f"/metrics/position_rmse/{first}/{v}"
        assert names[entity] == f"{labels[0]} · {v.upper().replace('AO_', 'AO-')}"
        r, g, b = variant_colour(i)
        assert colours[entity] == (r << 24) | (g << 16) | (b << 8) | 0xFF
    assert any("Jobs of sweep" in str(df.row(0)) for p, s, _, df in chunks if p == "/sweep")


def test_the_aggregate_cli_rebuilds_the_sweep_files(real_sweep, tmp_path):
    from pipeline.launch.aggregate import main

    copy = tmp_path / "copy"
    shutil.copytree(real_sweep[0], copy)
    for name in ("sweep_index.parquet", "sweep_summary.parquet", "sweep.rrd"):
        (copy / name).unlink()
    assert main([str(copy)]) == 0
    assert read_table(copy / "sweep_index.parquet")[0].equals(read_table(real_sweep[0] / "sweep_index.parquet")[0])
    assert (copy / "sweep.rrd").stat().st_size > 0 and (copy / "sweep_summary.parquet").is_file()


@pytest.mark.full
def test_a_failed_job_is_in_the_index_with_its_error_and_the_report_index_has_the_swept_column(tmp_path):
    from pipeline.results.report import swept_columns

    proc = run_pipeline("-m", "mc.runs=2,0", "scenario.steps=20", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 1
    (folder,) = (tmp_path / "multirun").iterdir()
    index = pl.read_parquet(folder / "sweep_index.parquet")
    assert index.select("job", "status", "mc.runs").rows() == [("runs=2", "ok", 2), ("runs=0", "failed", 0)]
    assert "mc.runs: 0 is not allowed" in index["error"][1]
    assert "1    0     failed: mc.runs: 0 is not allowed" in proc.stderr
    assert swept_columns([folder / "0", folder / "1"]) == {"mc.runs": {folder / "0": "2", folder / "1": "0"}}
    # the figure draws the finished job and names the other under its title
    data, _, _ = metric_against(collect(folder), "position_rmse", None, "mc.runs")
    assert data["job"].unique().to_list() == ["runs=2"]
    assert sweep_module.main([str(folder), "--metric", "position_rmse", "--out", str(tmp_path / "fig")]) == 0
    # the recording holds the finished job only
    chunks = read_chunks(folder / "sweep.rrd")
    assert {p.split("/")[3] for p, static, _, _ in chunks if p.startswith("/metrics/") and not static} == {"runs\\=2"}
