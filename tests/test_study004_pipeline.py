"""Study 004 through the runner: the four experiments compose, the tables and summary rows, the
recording with a re-filtered particle cloud, and bad input rejected before any stage."""

from __future__ import annotations

from pathlib import Path

import polars as pl
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pipeline.errors import ConfigError
from pipeline.storage.store import read_table
from tests.helpers import runs
from tests.helpers.config import CONF
from tests.helpers.runs import SONOBUOY_SHORT

def run_study(tmp_path: Path, name: str, *overrides: str, experiment: str = "sonobuoy_case2b", record=False):
    return runs.run_study(tmp_path, name, *overrides, experiment=experiment, record=record)


def test_experiments_compose_with_the_case_values():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfgs = {c: compose("config", overrides=[f"experiment=sonobuoy_{c}"]) for c in ("case1", "case1b", "case2", "case2b")}
    assert list(cfgs["case1"].filters) == ["ammpf", "ammpf_nolw", "ekf"]
    assert cfgs["case1"].filters.ammpf_nolw.lw_h == 0.0 and cfgs["case1"].filters.ammpf.lw_h == 0.3
    assert cfgs["case1b"].filters.ammpf.particles == 3000 and cfgs["case1b"].study.target_prior == "field"
    assert cfgs["case2"].filters.ammpf.target_sigma == 0.05 and cfgs["case2b"].filters.ammpf.target_sigma == 0.005
    assert cfgs["case2b"].filters.ammpf.tpm[0][0] == 0.99 and cfgs["case2"].filters.sir_mm.auxiliary is False
    assert cfgs["case2"].sensors.miss_probability == 0.2 and cfgs["case1"].sensors.miss_probability == 0.0
    for cfg in cfgs.values():
        for table in cfg.report.tables.values():
            assert instantiate(table, _convert_="all").rows


def test_a_short_run_writes_tables_summary_and_a_recording_with_the_cloud(tmp_path):
    out, ctx = run_study(tmp_path, "first", *SONOBUOY_SHORT, record=True)
    df, meta = read_table(ctx.run_dir / "estimates" / "ammpf.parquet")
    assert df.height == 2 * 21 and df.schema["P_upper"] == pl.Array(pl.Float32, 210)
    assert "particles" not in df.columns and df.schema["mode_probabilities"] == pl.Array(pl.Float64, 3)
    s = out.summary
    for metric, window in (("track_loss_rate", "final error > 2000 m"), ("final_position_rmse", "final"),
                           ("peak_median_error", "t300-600")):
        assert s.filter((pl.col("series") == metric) & (pl.col("window") == window)).height == 3, metric
    assert s.filter((pl.col("series") == "mode_probability_cw") & (pl.col("variant_key") == "ekf")).height == 0
    assert (ctx.run_dir / "recording.rrd").stat().st_size > 100_000
    assert "Case 2B (mode switch)" in (ctx.run_dir / "report.txt").read_text()


@pytest.mark.parametrize("overrides, message", [
    (["target_model.tpm=[[1,0],[0,1]]"], "filters.ammpf: tpm: [[1, 0], [0, 1]] must be a 3 x 3 matrix"),
    (["target_model.particles=5"], "filters.ammpf: particles: 5 must be an integer >= 10"),
    (["study.target_prior=somewhere"], "study: target_prior: 'somewhere' is not allowed"),
    (["filters.ammpf.lw_h=1.5"], "filters.ammpf: lw_h: 1.5 must be in [0, 1)"),
    # refused by measurement kind (pipeline.run.config.check_measurement_kinds) before the study's own check
    (["sensors=sonar_case1"], "filters.ammpf: filters.particle.MultipleModelParticleFilter declares "
                              "['sonobuoy_bearings'] measurements, but this experiment's sensor "
                              "(pipeline.studies.sonar.sensor.ActivePassiveSonar) produces 'sonar_bearing_range'"),
])
def test_bad_config_is_rejected_before_any_stage(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_study(tmp_path, "bad", *SONOBUOY_SHORT, *overrides)
    assert message in str(info.value)
    assert not (tmp_path / "cache").exists()
