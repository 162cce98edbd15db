"""Study 003 reproduction at reduced size (spec 003 "Reproduction targets"; full size: 100 runs,
python -m pipeline experiment=sonar_case2 mc.runs=100, figures in README.md).

Driven through the experiment's own scenario, sonar, study adapter and filter nodes at 8 runs.
"""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from pipeline.config import build
from tests.conftest import CONF

RUNS = 8


def _run(case: int, variants):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment=sonar_case{case}", f"mc.runs={RUNS}"])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(RUNS, 1)
    reports = study.track_input(truth, sensor.measure(truth, 1), sensor, 1)
    out = {}
    for key in variants:
        estimate = build(cfg.filters[key], f"filters.{key}").run(reports)
        err = estimate.state[..., :2] - truth.state[:, :, 0, :2]
        out[key] = {"rmse": np.sqrt(np.mean(err**2, axis=(0, 1))),                  # (x, y): Table 1's reading
                    "per_run": np.sqrt(np.mean(err**2, axis=1)),                     # (R, 2)
                    "per_step": np.sqrt(np.mean(np.sum(err**2, -1), axis=0))}        # (K,)
    return out


@pytest.fixture(scope="module")
def case2():
    return _run(2, ("kf_mgekf", "kf_mgekf_consistent", "only_mgekf"))


def test_case2_paper_like_hand_over_costs_only_mgekf_2_to_3x(case2):
    """Reference 1631 / 4035 m vs 686 / 1598 m (ratio 2.4 / 2.5); measured at 100 runs in README."""
    ratio = case2["kf_mgekf"]["rmse"] / case2["only_mgekf"]["rmse"]
    assert np.all((ratio > 1.8) & (ratio < 3.5)), ratio
    paired = np.median(case2["kf_mgekf"]["per_run"] / case2["only_mgekf"]["per_run"], axis=0)
    assert np.all(paired > 1.5), paired


def test_case2_consistent_hand_over_equals_only_mgekf(case2):
    ratio = case2["kf_mgekf_consistent"]["rmse"] / case2["only_mgekf"]["rmse"]
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio


def test_case2_error_bumps_after_each_active_to_passive_switch_only_with_the_paper_like_prior(case2):
    for switch in (500, 3000, 5500):
        window = slice(switch, switch + 300)
        kf = case2["kf_mgekf"]["per_step"][window].max()
        only = case2["only_mgekf"]["per_step"][window].max()
        assert kf > 500.0 and kf > 3.0 * only, (switch, kf, only)      # reference: 0.6-3 km, no bump in only MGEKF


def test_case1_architectures_close_and_the_ekf_not_better():
    out = _run(1, ("kf_mgekf", "only_mgekf", "ekf"))
    ratio = out["kf_mgekf"]["rmse"] / out["only_mgekf"]["rmse"]
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio
    middle = slice(1000, 7000)
    ekf, mgekf = out["ekf"]["per_step"][middle].mean(), out["only_mgekf"]["per_step"][middle].mean()
    assert ekf > mgekf, (ekf, mgekf)
