"""The objective of a parameter search (conf/config.yaml ``objective``, pipeline.launch.objective): checked
before any stage, returned by the task function, and the sweep's best job written beside the sweep.
Needs no extra: any multirun whose jobs name an objective gets best_config.yaml (tests/test_tune.py
runs the Optuna sweeper itself)."""

from __future__ import annotations

import json
import math

import polars as pl
import pytest
import yaml

from pipeline.errors import ConfigError
from pipeline.launch.objective import BEST_CONFIG, objective_value, trial_result
from pipeline.run.runner import prepare
from tests.helpers.config import composed_config
from tests.helpers.processes import run_pipeline

OBJECTIVE = "objective={variant: vsimm, series: acceleration_rmse_x, window: after_switch, direction: minimize}"


@pytest.mark.parametrize("override, key, allowed", [
    ("objective=5", "objective:", "null (no objective) or a mapping"),
    ("+objective.weight=2", "objective:", "variant, series, window and direction"),
    ("objective.variant=kf", "objective.variant: 'kf'", "one of ['fsimm', 'vsimm', 'ao_vsimm']"),
    ("objective.series=acc_rmse", "objective.series: 'acc_rmse'", "'acceleration_rmse_x'"),
    ("objective.window=after", "objective.window: 'after'", "['all', 'after_switch', 'M3 by step 80']"),
    ("objective.direction=lower", "objective.direction: 'lower'", "['minimize', 'maximize']"),
])
def test_a_bad_objective_is_refused_before_any_stage_in_one_paragraph(override, key, allowed):
    cfg = composed_config("experiment=ao_vsimm_s2", OBJECTIVE, override, "paths.artifacts=/nonexistent-artifacts")
    with pytest.raises(ConfigError) as info:
        prepare(cfg)
    message = str(info.value)
    assert message.startswith(key) and allowed in message and "\n" not in message, message


def test_an_objective_of_a_variant_left_out_by_variants_is_refused():
    cfg = composed_config("experiment=ao_vsimm_s2", OBJECTIVE, "variants=[fsimm]", "paths.artifacts=/nonexistent-artifacts")
    with pytest.raises(ConfigError, match=r"objective.variant: 'vsimm' .* one of \['fsimm'\] .*variants=\['fsimm'\]"):
        prepare(cfg)


def test_the_value_is_the_summary_row_and_nan_is_no_trial_value():
    summary = pl.DataFrame({"variant_key": ["vsimm", "vsimm", "vsimm"], "series": ["nees", "nees", "compute_seconds"],
                            "window": ["all", "after_switch", None], "value": [3.0, None, 0.5]})
    objective = {"variant": "vsimm", "series": "nees", "window": "all", "direction": "minimize"}
    assert objective_value(summary, objective) == 3.0
    assert objective_value(summary, {**objective, "series": "compute_seconds", "window": None}) == 0.5
    assert math.isnan(objective_value(summary, {**objective, "window": "after_switch"}))   # no value: NaN ...
    assert trial_result(math.nan) is None and trial_result(3.0) == 3.0                    # ... a failed trial
    assert objective_value(summary, None) is None
    with pytest.raises(ConfigError, match=r"over the windows \['all', 'after_switch'\]"):
        objective_value(summary, {**objective, "window": "M3 by step 80"})


@pytest.mark.full
def test_a_multirun_with_an_objective_writes_the_best_jobs_config_beside_the_sweep(tmp_path):
    # the basic sweeper: best_config.yaml comes from this project's callback, whatever the sweeper
    proc = run_pipeline("-m", "experiment=ao_vsimm_s2", OBJECTIVE, "variants=[vsimm]", "mc.runs=2",
                        "record.enabled=false", "filters.vsimm.t1_mu=0.6,0.85", "filters.vsimm.t2_mu=1.5", artifacts=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (sweep,) = (tmp_path / "multirun").iterdir()
    values = {}
    for job in ("0", "1"):
        summary = pl.read_parquet(sweep / job / "summary.parquet")
        row = summary.filter((pl.col("variant_key") == "vsimm") & (pl.col("series") == "acceleration_rmse_x")
                             & (pl.col("window") == "after_switch"))
        values[job] = row["value"].item()
    assert values["0"] != values["1"]                       # the swept threshold changed the result
    best_job = min(values, key=values.get)
    best = yaml.safe_load((sweep / BEST_CONFIG).read_text())
    assert best["best_trial"]["objective"]["value"] == values[best_job]
    assert best["best_trial"]["job_num"] == int(best_job)
    assert best["config"] == yaml.safe_load((sweep / best_job / "config.yaml").read_text())
    assert best["best_trial"]["overrides"] == json.loads((sweep / best_job / "status.json").read_text())["overrides"]
    assert f"best job {best_job} of 2: acceleration_rmse_x = {values[best_job]:.6g}" in proc.stderr


def test_a_job_config_reads_back_as_pyyaml_reads_it(tmp_path):
    """pipeline.storage.store.read_yaml (libyaml's parser, what a sweep's aggregation reads every job's
    config.yaml with) gives the objects PyYAML's pure-Python safe loader gives, for a whole
    composed config as a job writes it and for the scalars YAML 1.1 resolves by their look."""
    from omegaconf import OmegaConf

    from pipeline.storage.store import read_yaml

    cfg = composed_config("experiment=sonobuoy_case2", OBJECTIVE, "paths.artifacts=/tmp/x")
    written = OmegaConf.to_yaml(cfg) + ("tricky: {small: 1.0e-06, text_number: '1e-3', yes_text: 'yes', on: true, "
                                        "none: null, date_like: '2026-12-02', octal_like: '010', inf: .inf}\n")
    path = tmp_path / "config.yaml"
    path.write_text(written)
    assert read_yaml(path) == yaml.safe_load(written)
    assert read_yaml(path)["tricky"]["text_number"] == "1e-3" and read_yaml(path)["tricky"]["small"] == 1e-06
