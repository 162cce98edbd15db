"""Filters compose by measurement kind: a variant whose filter does not take what the sensor
produces is refused before any stage, with the filters that would fit (filters.base.MEASUREMENT_KINDS).

Reported: +filter@filters.x=mie_a in study 001, a user's CV Kalman filter in sonar_case1 and
+filter@filters.x=fsimm in async_bias ran the scenario and measurement stages, then died with a
traceback ('SonarReports' object has no attribute 'noise_covariance', InterpolationKeyError: 'models').
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra.utils import get_object
from omegaconf import OmegaConf

from filters.base import MEASUREMENT_KINDS, SERIES_KINDS, accepted_kinds, produced_kind
from pipeline.run.config import filter_classes_in_conf, filter_nodes_in_conf
from pipeline.errors import ConfigError
from tests.helpers.processes import run_pipeline
from tests.helpers.runs import run_in_process

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_sensor_and_filter_declares_documented_kinds():
    for path in sorted((ROOT / "conf" / "sensors").glob("*.yaml")):
        node = OmegaConf.load(path)
        sensor = get_object(node["_target_"])
        # a class whose kind follows from its node (pipeline.stonesoup's sensor: its measurement model)
        assert produced_kind(sensor, node) in MEASUREMENT_KINDS, path.name
    classes = filter_classes_in_conf()
    assert len(classes) == len(list((ROOT / "conf" / "filter").glob("*.yaml")))
    for name, cls in classes.items():
        assert getattr(cls, "accepts", None), f"{name}: {cls.__name__} declares no accepts"
        assert set(cls.accepts) <= set(MEASUREMENT_KINDS), name
    for name, (cls, node) in filter_nodes_in_conf().items():
        assert accepted_kinds(cls, node) <= set(cls.accepts), name


def test_a_kind_read_off_the_config_node_counts_before_the_class():
    """pipeline.stonesoup's variant takes the kind of its measurement model's type, known by name (no
    Stone Soup object built, and no Stone Soup needed to tell it)."""
    from pipeline.stonesoup.variant import StoneSoupFilter
    nodes = filter_nodes_in_conf()
    assert accepted_kinds(StoneSoupFilter, nodes["stonesoup_kf_cv"][1]) == {"position_xy"}
    assert accepted_kinds(StoneSoupFilter, nodes["stonesoup_ekf_cv"][1]) == {"range_azimuth_elevation"}
    assert accepted_kinds(StoneSoupFilter, OmegaConf.create({"_target_": "x"})) == StoneSoupFilter.accepts


def test_a_filter_that_declares_nothing_takes_a_measurement_series():
    class Plain:
        def run(self, measurements): ...
    assert accepted_kinds(Plain) == SERIES_KINDS


@pytest.mark.parametrize("overrides, message", [
    (["experiment=ao_vsimm_s1", "+filter@filters.x=mie_a"],
     "filters.x: filters.input_estimation.InertialMIE declares ['range_azimuth_elevation'] measurements, but this "
     "experiment's sensor (pipeline.studies.ao_vsimm.sensor.PositionSensor) produces 'position_xy'"),
    (["experiment=async_bias", "+filter@filters.x=fsimm"],
     "Filters in conf/filter/ that take 'biased_radar_reports': ['bias_exx', 'bias_local', 'bias_proposed']"),
    (["experiment=sonar_case1", "+filters.x={_target_: tests.test_composition.UserCV, name: CV}",
      "plugins.packages=[tests]"],
     "tests.test_composition.UserCV declares no 'accepts', so it is taken to take a MeasurementSeries: "
     "['position_xy', 'range_azimuth_elevation'] measurements, but this experiment's sensor "
     "(pipeline.studies.sonar.sensor.ActivePassiveSonar) produces 'sonar_bearing_range'"),
    (["experiment=mie_los", "+filter@filters.x=ammpf"],
     "Filters in conf/filter/ that take 'range_azimuth_elevation': ['imm_cv_ct', 'kalman_ca', 'kalman_cv', 'kalman_singer', "
     "'kalman_sonar', 'mie_a', 'mie_a_full', 'mie_b', 'mie_b_nocomp', 'mie_c', 'stonesoup_ekf_cv', 'stonesoup_ukf_cv']"),
    # a Stone Soup variant takes its measurement model's kind (LinearGaussian: positions)
    (["experiment=mie_los", "+filter@filters.x=stonesoup_kf_cv"],
     "filters.x: pipeline.stonesoup.variant.StoneSoupFilter declares ['position_xy'] measurements, but this "
     "experiment's sensor (pipeline.sensors.Radar3D) produces 'range_azimuth_elevation'"),
    (["experiment=ao_vsimm_s1", "+filter@filters.x=stonesoup_ekf_cv"],
     "Filters in conf/filter/ that take 'position_xy': ['ao_vsimm', 'fsimm', 'imm_cv_ct', 'kalman_ca', 'kalman_cv', "
     "'kalman_singer', 'kalman_sonar', 'stonesoup_kf_cv', 'stonesoup_pf_cv', 'vsimm', 'vsimm_new_old']"),
    (["experiment=ao_vsimm_s1", "filters.fsimm.models=${nothing}"],
     "filters.fsimm.models: '${nothing}' cannot be resolved (Interpolation key 'nothing' not found)"),
])
def test_an_incompatible_variant_is_refused_before_any_stage(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_in_process(tmp_path, "bad", "mc.runs=2", *overrides)
    assert message in str(info.value)
    assert not list(tmp_path.rglob("*.parquet"))


class UserCV:
    """A user's filter that declares no measurement kinds (the Estimator protocol's default)."""

    def __init__(self, name: str = "CV") -> None:
        self.name = name

    def run(self, measurements):
        raise AssertionError("never reached: refused before any stage")


def test_on_the_command_line_the_refusal_is_one_paragraph(tmp_path):
    proc = run_pipeline("experiment=async_bias", "+filter@filters.x=fsimm", "mc.runs=2", artifacts=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.startswith("error: filters.x:")
    assert proc.stderr.strip().count("\n") == 0
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()   # nothing ran, nothing written


def test_the_shipped_filters_run_in_every_experiment_of_their_kind():
    """A filter that takes a kind runs with every sensor of that kind (composition is by kind, not by study)."""
    from pipeline.run.config import check_measurement_kinds
    from tests.helpers.config import composed, EXPERIMENTS
    classes = filter_classes_in_conf()
    for experiment in EXPERIMENTS:
        cfg = composed(experiment)
        produced = produced_kind(get_object(cfg.sensors._target_), cfg.sensors)
        fitting = [name for name, cls in classes.items() if produced in cls.accepts]
        assert fitting, experiment
        check_measurement_kinds(cfg, list(cfg.filters.keys()))     # the shipped variants fit


if __name__ == "__main__":
    sys.exit(pytest.main([__file__]))
