"""Study 002 simulation (spec 002, seed 002 eqs 1-6, 42-43): the 32-target constant-velocity grid
and the asynchronous biased radar pair, built from their Hydra configs."""

from __future__ import annotations

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from pipeline.data import Truth
from filters.bias import cv_transition, dcwna_process_noise
from pipeline.studies.async_bias.scenario import ConstantVelocityGrid
from pipeline.studies.async_bias.sensor import BiasedRadarNetwork
from tests.helpers.config import CONF


def study_scenario(**overrides) -> ConstantVelocityGrid:
    node = OmegaConf.load(CONF / "scenario" / "async_bias.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


def scenario_kwargs(**overrides) -> dict:
    node = OmegaConf.to_container(OmegaConf.load(CONF / "scenario" / "async_bias.yaml"))
    node.pop("_target_")
    return {**node, **overrides}


def study_radars() -> BiasedRadarNetwork:
    return instantiate(OmegaConf.load(CONF / "sensors" / "async_bias.yaml"), _convert_="all")


def radar_config(**overrides) -> list[dict]:
    radars = OmegaConf.to_container(OmegaConf.load(CONF / "sensors" / "async_bias.yaml"))["radars"]
    for radar in radars:
        radar.update(overrides)
    return radars


def short_truth(runs: int = 2, duration: float = 10.0, q: float = 6.0, seed: int = 3) -> Truth:
    return study_scenario(duration=duration, process_noise_density=q).generate(runs, seed)


# ---------------------------------------------------------------- scenario

def test_configs_build_with_the_spec_values():
    scenario, radars = study_scenario(), study_radars()
    assert scenario.initial_states.shape == (32, 4)
    assert scenario.dt == 0.5 and scenario.steps == 400 and scenario.process_noise_density == 6.0
    np.testing.assert_array_equal(scenario.initial_states[:, 2:], np.full((32, 2), 20.0))
    assert radars.names == ("radar1", "radar2")
    np.testing.assert_array_equal(radars.positions, [[0.0, 0.0], [10000.0, 0.0]])
    np.testing.assert_array_equal(radars.noise_std, [[10.0, 0.001], [10.0, 0.001]])
    np.testing.assert_array_equal(radars.periods, [1.0, 1.0])
    np.testing.assert_array_equal(radars.first_reports, [1.0, 0.5])
    np.testing.assert_array_equal(radars.true_bias_vector(), [20.0, 0.002, 3e-5, 2e-4] * 2)


def test_targets_are_numbered_by_distance_then_azimuth():
    starts = study_scenario().initial_states[:, :2]
    grid = {(x, y) for x in range(5000, 40001, 5000) for y in range(5000, 20001, 5000)}
    assert {tuple(p) for p in starts} == grid
    np.testing.assert_array_equal(starts[0], [5000.0, 5000.0])
    np.testing.assert_array_equal(starts[-1], [40000.0, 20000.0])
    distance = np.hypot(starts[:, 0], starts[:, 1])
    assert np.all(np.diff(distance) >= 0)
    # (10 km, 5 km) and (5 km, 10 km) are equally far: the smaller azimuth comes first
    np.testing.assert_array_equal(starts[1], [10000.0, 5000.0])
    np.testing.assert_array_equal(starts[2], [5000.0, 10000.0])


def test_truth_starts_on_the_grid_and_is_a_straight_line_without_process_noise():
    scenario = study_scenario(process_noise_density=0.0)
    truth = scenario.generate(2, seed=1)
    assert truth.state_names == ("x", "y", "vx", "vy")
    assert truth.state.shape == (2, 401, 32, 4)
    np.testing.assert_array_equal(truth.time, np.arange(0.0, 200.25, 0.5))
    np.testing.assert_array_equal(truth.state[:, 0], np.broadcast_to(scenario.initial_states, (2, 32, 4)))
    expected = scenario.initial_states[:, :2] + truth.time[:, None, None] * np.array([20.0, 20.0])
    np.testing.assert_allclose(truth.state[0, ..., :2], expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(truth.state[..., 2:], 20.0)
    noisy = study_scenario().generate(2, seed=1)
    np.testing.assert_array_equal(noisy.state[:, 0], truth.state[:, 0])        # k = 0 has no noise
    assert not np.allclose(noisy.state[:, 1:], truth.state[:, 1:])


def test_one_step_process_noise_matches_dcwna_covariance():
    dt, q = 0.5, 6.0
    truth = study_scenario(duration=2.0, dt=dt, process_noise_density=q).generate(400, seed=5)
    # increment w_k = x_k - Phi x_{k-1}, pooled over runs, steps and targets: 400 x 4 x 32 samples
    w = truth.state[:, 1:] - truth.state[:, :-1] @ cv_transition(dt).T
    w = w.reshape(-1, 4)
    Q = dcwna_process_noise(dt, q)
    np.testing.assert_allclose(w.mean(axis=0), 0.0, atol=0.05 * np.sqrt(np.diag(Q)).max())
    empirical = np.cov(w, rowvar=False)
    scale = np.sqrt(np.outer(np.diag(Q), np.diag(Q)))
    np.testing.assert_allclose(empirical / scale, Q / scale, atol=0.05)       # correlations to 0.05
    np.testing.assert_allclose(np.diag(empirical), np.diag(Q), rtol=0.1)


def test_scenario_rejects_bad_input():
    with pytest.raises(ValueError, match=r"dt: 0 must be > 0"):
        ConstantVelocityGrid(**scenario_kwargs(dt=0))
    with pytest.raises(ValueError, match=r"duration: 10.2 s must be a whole number"):
        ConstantVelocityGrid(**scenario_kwargs(duration=10.2))
    with pytest.raises(ValueError, match=r"duration: 0.1 must be >= dt"):
        ConstantVelocityGrid(**scenario_kwargs(duration=0.1))
    with pytest.raises(ValueError, match=r"process_noise_density: -1"):
        ConstantVelocityGrid(**scenario_kwargs(process_noise_density=-1.0))
    with pytest.raises(ValueError, match=r"x_positions: \[\]"):
        ConstantVelocityGrid(**scenario_kwargs(x_positions=[]))
    with pytest.raises(ValueError, match=r"velocity: \[1.0, 2.0, 3.0\]"):
        ConstantVelocityGrid(**scenario_kwargs(velocity=[1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match=r"numbering_origin: \[0.0\]"):
        ConstantVelocityGrid(**scenario_kwargs(numbering_origin=[0.0]))


# ---------------------------------------------------------------- radars

def test_report_times_alternate_between_the_radars():
    time, sensor = study_radars().report_times(200.0)
    assert time.shape == sensor.shape == (400,)
    np.testing.assert_array_equal(time, np.arange(1, 401) * 0.5)
    np.testing.assert_array_equal(sensor, np.tile([1, 0], 200))
    assert sensor.dtype.kind == "i"
    # same period and offset: ties in radar order
    tied = BiasedRadarNetwork(radar_config(first_report=1.0))
    time, sensor = tied.report_times(3.0)
    np.testing.assert_array_equal(time, [1.0, 1.0, 2.0, 2.0, 3.0, 3.0])
    np.testing.assert_array_equal(sensor, [0, 1, 0, 1, 0, 1])


def test_noise_and_bias_free_measurement_round_trips_to_the_truth():
    truth = short_truth()
    radars = BiasedRadarNetwork(radar_config(range_std=0.0, azimuth_std=0.0, bias=[0.0, 0.0, 0.0, 0.0]))
    det = radars.measure(truth, seed=9)
    assert det.z.shape == (2, 20, 32, 2)
    assert det.measurement_names == ("range", "azimuth") and det.measurement_units == ("m", "rad")
    index = np.rint(det.time / 0.5).astype(int)
    np.testing.assert_array_equal(truth.time[index], det.time)
    origin = radars.positions[det.sensor][None, :, None, :]
    r, theta = det.z[..., 0], det.z[..., 1]
    back = origin + r[..., None] * np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    np.testing.assert_allclose(back, truth.state[:, index, :, :2], rtol=0, atol=1e-8)
    np.testing.assert_array_equal(det.target, np.broadcast_to(np.arange(32), (2, 20, 32)))
    assert det.detected.all()


def test_biased_measurement_is_scale_and_offset_of_the_true_one():
    truth = short_truth()
    bias = np.array([20.0, 0.002, 3e-5, 2e-4])
    clean = BiasedRadarNetwork(radar_config(range_std=0.0, azimuth_std=0.0, bias=[0.0] * 4)).measure(truth, 1)
    biased = BiasedRadarNetwork(radar_config(range_std=0.0, azimuth_std=0.0, bias=bias.tolist())).measure(truth, 1)
    np.testing.assert_array_equal(biased.z[..., 0], (1 + bias[2]) * clean.z[..., 0] + bias[0])
    np.testing.assert_array_equal(biased.z[..., 1], (1 + bias[3]) * clean.z[..., 1] + bias[1])
    # what the radar reports as its noise, not the bias
    np.testing.assert_array_equal(biased.noise_covariance, 0.0)


def test_measurement_noise_has_the_configured_std():
    truth = short_truth(runs=200, duration=5.0)
    radars = study_radars()
    det = radars.measure(truth, seed=11)
    clean = BiasedRadarNetwork(radar_config(range_std=0.0, azimuth_std=0.0)).measure(truth, 11)
    error = (det.z - clean.z).reshape(-1, 2)                # 200 runs x 10 reports x 32 targets
    np.testing.assert_allclose(error.std(axis=0), [10.0, 0.001], rtol=0.03)
    np.testing.assert_allclose(error.mean(axis=0) / [10.0, 0.001], 0.0, atol=0.03)
    np.testing.assert_array_equal(det.noise_covariance[0, 0, 0], np.diag([100.0, 1e-6]))
    assert det.noise_covariance.shape == (200, 10, 32, 2, 2)


def test_runs_are_reproducible_and_independent_of_the_run_count():
    scenario, radars = study_scenario(duration=5.0), study_radars()
    three, five = scenario.generate(3, seed=7), scenario.generate(5, seed=7)
    np.testing.assert_array_equal(three.state[1], five.state[1])
    det3, det5 = radars.measure(three, seed=8), radars.measure(five, seed=8)
    np.testing.assert_array_equal(det3.z[1], det5.z[1])
    np.testing.assert_array_equal(radars.measure(three, seed=8).z, det3.z)
    assert not np.array_equal(radars.measure(three, seed=9).z, det3.z)


def test_radar_network_rejects_bad_input():
    bad = radar_config()
    bad[1]["colour"] = "red"
    with pytest.raises(ValueError, match=r"radars\[1\]: unknown key\(s\) \['colour'\]"):
        BiasedRadarNetwork(bad)
    bad = radar_config()
    del bad[0]["bias"]
    with pytest.raises(ValueError, match=r"radars\[0\]: missing key\(s\) \['bias'\]"):
        BiasedRadarNetwork(bad)
    bad = radar_config()
    bad[1]["period"] = 0
    with pytest.raises(ValueError, match=r"radars\[1\]\.period: 0 must be > 0 s"):
        BiasedRadarNetwork(bad)
    with pytest.raises(ValueError, match=r"radars\[0\]\.bias"):
        BiasedRadarNetwork(radar_config(bias=[1.0, 2.0]))
    with pytest.raises(ValueError, match=r"radars\[0\]\.range_std: -1.0 must be >= 0 m"):
        BiasedRadarNetwork(radar_config(range_std=-1.0))
    with pytest.raises(ValueError, match=r"radars: \[\]"):
        BiasedRadarNetwork([])


def test_measure_rejects_report_times_off_the_truth_grid():
    truth = study_scenario(duration=10.0, dt=1.0).generate(1, seed=1)
    with pytest.raises(ValueError, match=r"report time 0.5 s of radar 'radar2' is not on the truth's time grid "
                                         r"\(time step 1 s\)"):
        study_radars().measure(truth, seed=1)
    planar = Truth(truth.time, truth.state, ("vx", "vy", "x", "y"))
    with pytest.raises(ValueError, match=r"state_names"):
        study_radars().measure(planar, seed=1)
