"""The pipeline end to end: files, cache reuse and invalidation, sweeps, bad input."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import polars as pl
import pytest

from pipeline.errors import ConfigError
from tests.helpers.processes import ROOT, run_pipeline
from tests.helpers.runs import run_in_process


def test_default_job_writes_every_file(tmp_path):
    proc = run_pipeline("mc.runs=4", artifacts=tmp_path)
    assert proc.returncode == 0, proc.stderr
    (run_dir,) = (tmp_path / "runs" / "ao_vsimm_s1").iterdir()
    for name in ("config.yaml", "truth.parquet", "detections.parquet", "estimates/fsimm.parquet",
                 "estimates/vsimm.parquet", "estimates/ao_vsimm.parquet", "metrics.parquet", "summary.parquet",
                 "recording.rrd", "status.json"):
        assert (run_dir / name).is_file(), name
    # summary table on stdout, progress with counts and timings on stderr
    assert "FSIMM" in proc.stdout and "AO-VSIMM" in proc.stdout and "acc RMSE X" in proc.stdout
    assert "[scenario] computed 4 runs" in proc.stderr and "[track] FSIMM filtered in" in proc.stderr
    summary = pl.read_parquet(run_dir / "summary.parquet")
    assert set(summary["variant"]) == {"FSIMM", "VSIMM", "AO-VSIMM"}
    assert summary["mc.runs"].unique().to_list() == [4]            # config values as columns
    assert "filters.vsimm.t1_mu" in summary.columns
    truth = pl.read_parquet(run_dir / "truth.parquet")
    assert truth.height == 4 * 201 and truth.schema["x"] == pl.Array(pl.Float64, 4)
    assert json.loads((run_dir / "status.json").read_text())["status"] == "ok"
    metrics = pl.read_parquet(run_dir / "metrics.parquet")
    assert {"acceleration_rmse_x", "acceleration_rmse_y", "position_rmse", "velocity_rmse", "nees",
            "models_evaluated"} <= set(metrics["series"])


def _mtimes(root: Path) -> dict[str, int]:
    return {p.relative_to(root).as_posix(): p.stat().st_mtime_ns for p in root.rglob("*.parquet")}


def test_cache_reuses_scenario_and_measurements_for_a_filter_change(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="pipeline")
    run_in_process(tmp_path, "a", "mc.runs=3", "scenario.steps=60")
    cache = tmp_path / "cache"
    before = _mtimes(cache)
    assert len([k for k in before if k.startswith("track/")]) == 3
    caplog.clear()
    run_in_process(tmp_path, "b", "mc.runs=3", "scenario.steps=60", "filters.vsimm.t1_mu=0.8")
    after = _mtimes(cache)
    log = caplog.text
    assert "[scenario] reused cached" in log and "[measure] reused cached" in log
    assert "computed VSIMM" in log and "computed FSIMM" not in log          # only the changed variant reruns
    for name, stamp in before.items():
        assert after[name] == stamp, f"{name} was rewritten"
    assert len([k for k in after if k.startswith("track/")]) == 4
    # the run directory's files are copies of the cached bytes, identical inputs for every variant
    assert (tmp_path / "runs/b/truth.parquet").read_bytes() == next((cache / "scenario").glob("*.parquet")).read_bytes()

    caplog.clear()
    run_in_process(tmp_path, "c", "mc.runs=3", "scenario.steps=60", "mc.seed=7")
    log = caplog.text
    assert "[scenario] computed" in log and "[measure] computed" in log and "computed FSIMM" in log
    caplog.clear()
    run_in_process(tmp_path, "d", "mc.runs=3", "scenario.steps=60", "scenario.segments=[[1,60,5,5]]")
    assert "[scenario] computed" in caplog.text and "[measure] computed" in caplog.text


def test_truncated_or_foreign_cache_file_is_rejected_and_recomputed(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    run_in_process(tmp_path, "a", "mc.runs=2", "scenario.steps=30")
    (scenario_file,) = (tmp_path / "cache" / "scenario").glob("*.parquet")
    (measure_file,) = (tmp_path / "cache" / "measure").glob("*.parquet")
    scenario_file.write_bytes(scenario_file.read_bytes()[:100])          # an interrupted write by some other tool
    measure_bytes = measure_file.read_bytes()
    (tmp_path / "cache" / "scenario" / f".{scenario_file.name}.x.tmp").write_bytes(b"PAR1")  # stray temp file
    caplog.clear()
    run_in_process(tmp_path, "b", "mc.runs=2", "scenario.steps=30")
    assert "was not used: it cannot be read" in caplog.text and "[scenario] computed" in caplog.text
    assert list((tmp_path / "cache" / "scenario").glob("*.rejected"))      # kept aside, not deleted
    assert "[measure] reused cached" in caplog.text

    # a foreign file (another table) under the measure key
    scenario_bytes = scenario_file.read_bytes()
    measure_file.write_bytes(scenario_bytes)
    caplog.clear()
    out, _ = run_in_process(tmp_path, "c", "mc.runs=2", "scenario.steps=30")
    assert "it holds table 'truth', expected 'detections'" in caplog.text
    assert measure_file.read_bytes() != scenario_bytes and len(measure_file.read_bytes()) == len(measure_bytes)

    # the same table made under another config (another key in its metadata), e.g. copied by hand
    run_in_process(tmp_path, "other", "mc.runs=2", "scenario.steps=30", "mc.seed=5")
    other = next(f for f in (tmp_path / "cache" / "scenario").glob("*.parquet") if f != scenario_file)
    scenario_file.write_bytes(other.read_bytes())
    caplog.clear()
    out, ctx = run_in_process(tmp_path, "e", "mc.runs=2", "scenario.steps=30")
    assert f"its cache key is '{other.stem}', expected '{scenario_file.stem}'" in caplog.text
    assert "[scenario] computed" in caplog.text
    _, fresh = run_in_process(tmp_path, "f", "mc.runs=2", "scenario.steps=30", "cache.enabled=false")
    assert pl.read_parquet(ctx.run_dir / "truth.parquet").equals(pl.read_parquet(fresh.run_dir / "truth.parquet"))


@pytest.mark.parametrize("overrides, message", [
    (["mc.runs=0"], "mc.runs: 0 is not allowed; the number of Monte Carlo runs must be an integer >= 1"),
    (["mc.runs=3", "record.runs=[0,5]"], "record.runs: [0, 5] holds run index(es) [5] outside the 3 Monte Carlo runs"),
    (["variants=[fsimm,imm9]"], "variants: ['fsimm', 'imm9'] names unknown variant(s) ['imm9']. The variants of "
                                "experiment 'ao_vsimm_s1' are ['fsimm', 'vsimm', 'ao_vsimm']"),
    (["models.transition_matrix.1.1=0.5"], "row 1 (m2) sums to 0.55; every row must sum to 1"),
    (["models.transition_matrix=[[1,0],[0,1]]"], "transition_matrix: shape 2x2 does not match the 13 models"),
    (["filters.vsimm.ratio=sideways"], "filters.vsimm.ratio: 'sideways' is not allowed; it must be one of ['printed', 'new_old', 'old_new']"),
    (["filters.vsimm.t1_mu=high"], "filters.vsimm.t1_mu: 'high' is not allowed; it must be a number"),
    (["scenario.steps=2.5"], "scenario.steps: 2.5 is not allowed; it must be an integer"),
    (["experiment=ao_vsimm_s2", "metrics.group_reached.group=M9"],
     "metrics.group_reached.group: 'M9' is not a model group of this experiment; groups are ['M1', 'M2', 'M3', 'M4', 'M5']"),
    # two variants displayed alike collapsed into one row of the printed table and two identically
    # titled columns of the recording, silently
    (["+filter@filters.v2=vsimm", "filters.v2.t1_mu=0.9"],
     "filters.v2.name: 'VSIMM' is also the display name of filters.vsimm. Each variant's name must be unique"),
])
def test_bad_input_is_rejected_with_the_key_the_value_and_what_is_allowed(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_in_process(tmp_path, "bad", *overrides)
    assert message in str(info.value)
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").rglob("track/*.parquet"))


def test_bad_input_on_the_command_line_gives_one_paragraph_no_traceback(tmp_path):
    proc = run_pipeline("mc.runs=0", artifacts=tmp_path)
    assert proc.returncode == 2
    assert "error: mc.runs: 0 is not allowed" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "runs").exists()          # refused before any work: nothing is written

    proc = run_pipeline("experiment=ao_vsimm_s9", artifacts=tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "Could not find 'experiment/ao_vsimm_s9'" in proc.stderr and "ao_vsimm_s2" in proc.stderr


def _sweep_summaries(root: Path) -> pl.DataFrame:
    return pl.concat([pl.read_parquet(p) for p in sorted(root.glob("multirun/*/*/summary.parquet"))],
                     how="diagonal_relaxed")


@pytest.mark.full
def test_multirun_sweep_yields_one_summary_per_job_with_the_swept_value(tmp_path):
    proc = run_pipeline("-m", "filters.vsimm.t1_mu=0.8,0.85", "mc.runs=3", "scenario.steps=60", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 0, proc.stderr
    from pipeline.results.query import query
    rows = query("""SELECT "filters.vsimm.t1_mu" AS t1_mu, value FROM summary
                    WHERE variant = 'VSIMM' AND series = 'acceleration_rmse_x' AND "window" = 'all'
                    ORDER BY t1_mu""", root=tmp_path)
    assert rows["t1_mu"].to_list() == [0.8, 0.85] and rows["value"].is_finite().all()
    (sweep,) = (tmp_path / "multirun").iterdir()
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]
    assert (sweep / "sweep_summary.parquet").is_file()


@pytest.mark.full
def test_a_failed_job_is_recorded_and_the_others_stay_queryable(tmp_path):
    proc = run_pipeline("-m", "mc.runs=2,0", "scenario.steps=40", "record.enabled=false",
                        "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", artifacts=tmp_path)
    assert proc.returncode == 1                     # the sweep reports its failure ...
    assert "1 ok, 1 failed" in proc.stderr and "mc.runs: 0 is not allowed" in proc.stderr
    df = _sweep_summaries(tmp_path)                 # ... and both jobs are in the tables
    assert set(df["status"]) == {"ok", "failed"}
    failed = df.filter(pl.col("status") == "failed")
    assert failed.height == 1 and "mc.runs: 0" in failed["error"][0] and failed["mc.runs"][0] == 0
    assert df.filter(pl.col("status") == "ok")["mc.runs"].unique().to_list() == [2]


# the long studies run shortened here (their own pipeline tests cover them in depth): 10 000 s of
# sonar, 1000-3000 particles and 900 s of ADS-B flight under seven filters (the MIE filters' scans
# cost milliseconds each) would otherwise take most of this test's time. One sweep for all of them
# (each sweep pays for its process, Hydra's composition of every job and the sweep's summary and
# recording): the overrides suit each of these studies; a key one of them does not use is added
# ("++") and left unread (the sonar filters read target_model's keys one by one), which the other
# studies' scenarios would refuse as not theirs
SHORTENED = ["sonar_*", "sonobuoy_*", "adsb_*"]
SHORT = ["++scenario.duration=100", "++target_model.particles=100"]


@pytest.mark.full
def test_every_experiment_file_runs_end_to_end(tmp_path):
    """Multiruns over glob(*): every experiment in conf/experiment composes, runs and is queryable."""
    listed = ",".join(SHORTENED)
    for sweep in ([f"experiment=glob(*,exclude=[{listed}])"], [f"experiment=glob([{listed}])", *SHORT]):
        proc = run_pipeline("-m", *sweep, "mc.runs=2", "record.enabled=false", timeout=300, artifacts=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
    from pipeline.results.query import query
    experiments = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
    runs = query("SELECT experiment, status FROM runs ORDER BY experiment", root=tmp_path)
    assert runs["experiment"].to_list() == experiments and set(runs["status"]) == {"ok"}
