"""Study 004 reproduction at reduced size (spec 004 "Reproduction targets"; full size: 100 runs,
python -m pipeline experiment=sonobuoy_case2b mc.runs=100 etc., figures in README.md).

Driven through each experiment's own scenario, sensors, study adapter and filter nodes, with fewer
runs and particles (and case 1B's horizon cut to 600 s, where its target lies).
"""

from __future__ import annotations

import numpy as np
from hydra import compose, initialize_config_dir

from pipeline.run.config import build
from tests.helpers.config import CONF
from pipeline.evaluation.evaluate import resolved


def _run(experiment: str, runs: int, variants, *overrides: str):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"experiment={experiment}", f"mc.runs={runs}", *overrides])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(runs, 1)
    reports = study.track_input(truth, sensor.measure(truth, 1), sensor, 1)
    return truth, _metrics(cfg, study, truth, reports, sensor, variants)


def _metrics(cfg, study, truth, reports, sensor, variants):
    out = {}
    for key in variants:
        estimate = build(cfg.filters[key], f"filters.{key}").run(reports)
        metrics = resolved(study.per_step_metrics(truth, estimate, sensor))
        metrics["final_error"] = np.linalg.norm(estimate.state[:, -1, :2] - truth.state[:, -1, 0, :2], axis=-1)
        out[key] = metrics
    return out


def test_case1b_the_ammpf_finds_the_target_where_the_ekf_wanders():
    """Spec: EKF median error > 5 km somewhere in 300-600 s; AMMPF median < 1.5 km by 300 s. The
    spec's 3000 particles at 4 runs, cut at 600 s (measured at 100 runs: 978 m at 300 s, EKF peak 7761 m)."""
    _, m = _run("sonobuoy_case1b", 4, ("ammpf", "ekf"), "scenario.duration=600")
    ammpf, ekf = m["ammpf"]["position_median_error"], m["ekf"]["position_median_error"]
    assert ammpf[60] < 1500.0, ammpf[60]
    assert ekf[60:121].max() > 3000.0 and ekf[60:121].max() > 3 * ammpf[60:121].max(), (ekf[60:121].max(),
                                                                                         ammpf[60:121].max())


def test_case2b_the_right_turn_mode_becomes_the_most_probable():
    _, m = _run("sonobuoy_case2b", 4, ("ammpf", "ekf"))
    ammpf = m["ammpf"]
    late = slice(240, 361)
    right, cv, left = (np.mean(ammpf[f"mode_probability_{n}"][late]) for n in ("cw", "cv", "ccw"))
    assert right > cv and right > 0.35 and left < 0.3, (right, cv, left)
    assert np.mean(ammpf["mode_probability_cw"][:181]) < 0.3
    assert np.all(ammpf["final_error"] < 2000.0)
    assert np.sqrt(np.mean(m["ekf"]["final_error"] ** 2)) > 1.5 * np.sqrt(np.mean(ammpf["final_error"] ** 2))


def test_case1_without_regularisation_the_track_is_lost_far_more_often():
    _, m = _run("sonobuoy_case1", 10, ("ammpf", "ammpf_nolw"), "target_model.particles=400")
    lost = {key: int(np.sum(m[key]["final_error"] > 2000.0)) for key in m}
    assert lost["ammpf"] == 0 and lost["ammpf_nolw"] >= 2, lost
