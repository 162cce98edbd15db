"""A parameter search through Hydra's Optuna sweeper (the ``[tune]`` extra): conf/tune/vsimm_thresholds
on study 001's S2 with a few trials of two Monte Carlo runs each. The task function's return value
is what Optuna saw (optimization_results.yaml), and best_config.yaml beside the sweep is the best
job's own config with that value. A trial that fails (VSIMM refuses t1_mu > t2_mu) fails alone."""

from __future__ import annotations

import json

import polars as pl
import pytest
import yaml

from tests.helpers.extras import require_extra

# .ci/run sets MTT_REQUIRE_TUNE=1: in CI a missing extra fails instead of skipping
require_extra("tune", "hydra_plugins.hydra_optuna_sweeper", "optuna")

from pipeline.launch.objective import BEST_CONFIG  # noqa: E402
from tests.helpers.processes import run_pipeline  # noqa: E402

# full tier (tests/helpers/tiers.py): the Optuna sweeper
pytestmark = [pytest.mark.tune, pytest.mark.full]
TUNE = ["-m", "experiment=ao_vsimm_s2", "tune=vsimm_thresholds", "mc.runs=2"]


def _objective(job_dir) -> float:
    summary = pl.read_parquet(job_dir / "summary.parquet")
    return summary.filter((pl.col("variant_key") == "vsimm") & (pl.col("series") == "acceleration_rmse_x")
                          & (pl.col("window") == "after_switch"))["value"].item()


def test_an_optuna_search_writes_the_best_trials_whole_config_beside_the_sweep(tmp_path):
    proc = run_pipeline(*TUNE, "hydra.sweeper.n_trials=4", "hydra.sweeper.n_jobs=2", artifacts=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Directions: ['minimize']" in proc.stdout          # the sweeper's direction follows objective.direction
    (sweep,) = (tmp_path / "multirun").iterdir()
    jobs = sorted((p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
    assert [p.name for p in jobs] == ["0", "1", "2", "3"]
    values = {int(p.name): _objective(p) for p in jobs}
    assert len(set(values.values())) == 4                     # four different threshold sets, four values
    best_num = min(values, key=values.get)

    optuna = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    best = yaml.safe_load((sweep / BEST_CONFIG).read_text())
    trial = best["best_trial"]
    assert trial["job_num"] == best_num
    assert trial["objective"]["value"] == values[best_num] == optuna["best_value"]
    assert trial["objective"] | {"value": None} == {"variant": "vsimm", "series": "acceleration_rmse_x",
                                                    "window": "after_switch", "direction": "minimize", "value": None}
    assert best["config"] == yaml.safe_load((sweep / str(best_num) / "config.yaml").read_text())
    for key, value in optuna["best_params"].items():          # the config is the one of Optuna's best parameters
        assert f"{key}={value}" in trial["overrides"]
        assert best["config"]["filters"]["vsimm"][key.rsplit(".", 1)[1]] == value
    assert best["config"]["variants"] == ["vsimm"] and best["config"]["mc"]["runs"] == 2


def test_a_failed_trial_fails_alone_and_the_best_config_is_the_best_ok_job(tmp_path):
    # t1_mu=1.5 > t2_mu=1.0 (fixed) is refused by VSIMM (a failed job); sampler seed 1 draws both values
    proc = run_pipeline(*TUNE, "hydra.sweeper.params={filters.vsimm.t1_mu: 'choice(0.85, 1.5)', filters.vsimm.t2_mu: '1.0'}",
                        "hydra.sweeper.n_trials=3", "hydra.sweeper.n_jobs=1", artifacts=tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]           # the sweep ends and reports its failed job
    assert "Return value must be float-castable. Got 'None'" in proc.stdout   # Optuna: a failed trial, not an abort
    assert "t1_mu <= t2_mu" in proc.stderr
    (sweep,) = (tmp_path / "multirun").iterdir()
    status = {p.parent.name: json.loads(p.read_text()) for p in sweep.glob("*/status.json")}
    assert len(status) == 3 and {s["status"] for s in status.values()} == {"ok", "failed"}, status
    ok = {job: _objective(sweep / job) for job, s in status.items() if s["status"] == "ok"}
    best_num = min(ok, key=ok.get)
    best = yaml.safe_load((sweep / BEST_CONFIG).read_text())
    assert best["best_trial"]["job_num"] == int(best_num) and best["config"]["filters"]["vsimm"]["t1_mu"] == 0.85
    assert best["best_trial"]["objective"]["value"] == ok[best_num]
    assert yaml.safe_load((sweep / "optimization_results.yaml").read_text())["best_value"] == ok[best_num]
