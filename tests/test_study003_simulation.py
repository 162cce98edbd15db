"""Study 003 simulation (spec 003 "Model" and "Scenarios"; literature notes 3.3): the own-ship
zig-zag / target encounter and the active/passive sonar, built from their Hydra configs."""

from __future__ import annotations

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from pipeline.data import Truth
from pipeline.studies.sonar.scenario import SonarEncounter
from pipeline.storage.schemas import detections_from_frame, detections_to_frame, truth_from_frame, truth_to_frame
from pipeline.studies.sonar.sensor import ActivePassiveSonar
from tests.helpers.config import CONF


def load(group: str, name: str, **overrides):
    node = OmegaConf.load(CONF / group / f"{name}.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


@pytest.fixture(scope="module")
def case1() -> Truth:
    return load("scenario", "sonar_case1").generate(1, seed=0)


@pytest.fixture(scope="module")
def case2() -> Truth:
    return load("scenario", "sonar_case2").generate(1, seed=0)


def course_deg(velocity: np.ndarray) -> np.ndarray:
    """Course from north, clockwise [deg] in [0, 360) of velocities (..., 2) = (east, north)."""
    return np.mod(np.degrees(np.arctan2(velocity[..., 0], velocity[..., 1])), 360.0)


def relative_position(points) -> Truth:
    state = np.zeros((1, len(points), 1, 6))
    state[0, :, 0, :2] = points
    return Truth(np.arange(len(points), dtype=float), state, ("x", "y", "vx", "vy", "ax", "ay"))


# ---------------------------------------------------------------- configs

def test_configs_build_with_the_spec_values():
    s1, s2 = load("scenario", "sonar_case1"), load("scenario", "sonar_case2")
    for s in (s1, s2):
        assert (s.duration, s.dt, s.steps) == (10000.0, 1.0, 10000)
        assert (s.ownship_speed, s.ownship_leg, s.ownship_leg_heading, s.ownship_turn_rate) == (5.0, 500.0, 45.0, 3.0)
        np.testing.assert_array_equal(s.target_offset, [5000.0, 10000.0])
        assert (s.target_speed, s.target_heading, s.target_turn_rate) == (7.0, 225.0, 0.5)
    assert s1.target_turns == [] and s2.target_turns == [(3000.0, -45.0), (5100.0, 45.0)]
    a1, a2 = load("sensors", "sonar_case1"), load("sensors", "sonar_case2")
    assert a1.active_intervals == [(0.0, 500.0)]
    assert a2.active_intervals == [(0.0, 500.0), (2500.0, 3000.0), (5000.0, 5500.0)]
    for a in (a1, a2):
        assert a.bearing_std == pytest.approx(np.radians(1.0)) and a.range_std == 10.0


def test_truth_layout(case1):
    assert case1.state_names == ("x", "y", "vx", "vy", "ax", "ay")
    assert case1.state.shape == (1, 10001, 1, 6)
    np.testing.assert_array_equal(case1.time, np.arange(10001.0))
    assert {k: v.shape for k, v in case1.labels.items()} == {
        "ownship": (1, 10001, 1, 4), "ownship_acceleration": (1, 10001, 1, 2), "target_world": (1, 10001, 1, 4)}
    truth = SonarEncounter(duration=50.0).generate(3, seed=7)
    for values in (truth.state, *truth.labels.values()):
        np.testing.assert_array_equal(values[0], values[2])                  # every run the same
    np.testing.assert_array_equal(truth.state, SonarEncounter(duration=50.0).generate(3, seed=8).state)


# ---------------------------------------------------------------- own-ship and target motion

def test_ownship_zigzag_course_legs_turn_rate_and_speed(case1):
    own = case1.labels["ownship"][0, :, 0]
    np.testing.assert_array_equal(own[0], [0.0, 0.0, 5.0 * np.sin(np.pi / 4), 5.0 * np.cos(np.pi / 4)])
    t = case1.time
    # first leg +45; at t = 500 + s the course is 45 - 3 s until -45 (s = 30); at 1000 + s it is -45 + 3 s
    s500, s1000 = np.mod(t - 500.0, 1000.0), np.mod(t, 1000.0)
    expected = np.where(t < 500, 45.0, np.where(s500 < 500, np.maximum(45.0 - 3.0 * s500, -45.0),
                                                np.minimum(-45.0 + 3.0 * s1000, 45.0)))
    got = course_deg(own[:, 2:])
    got = np.where(got > 180, got - 360, got)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    np.testing.assert_allclose(got[[500, 515, 530, 1000, 1015, 1030]], [45, 0, -45, -45, 0, 45], atol=1e-9)
    np.testing.assert_allclose(load("scenario", "sonar_case1").ownship_course(t), expected, atol=1e-12)
    np.testing.assert_allclose(np.hypot(own[:, 2], own[:, 3]), 5.0, rtol=1e-12)          # speed kept
    # a turn longer than the leg is turned back from where it got to: 90 deg at 3 deg/s on 20 s legs
    short = SonarEncounter(duration=60.0, ownship_leg=20.0)
    np.testing.assert_allclose(short.ownship_course([0, 10, 20, 30, 40, 50, 60]), [45, 45, 45, 15, -15, 15, 45])


def test_discrete_kinematics_are_exact(case2):
    dt = 1.0
    own, own_u = case2.labels["ownship"][0, :, 0], case2.labels["ownship_acceleration"][0, :, 0]
    tgt, tgt_u = case2.labels["target_world"][0, :, 0], case2.state[0, :, 0, 4:]
    for track, u in ((own, own_u), (tgt, tgt_u)):
        p, v = track[:, :2], track[:, 2:]
        np.testing.assert_array_equal(u[-1], [0.0, 0.0])
        np.testing.assert_allclose(p[1:], p[:-1] + dt * v[:-1] + dt ** 2 / 2 * u[:-1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(v[1:], v[:-1] + dt * u[:-1], rtol=0, atol=1e-12)
    # the relative-motion model of literature notes 3.3 with the own-ship's u as the known input
    # (Gamma_u = -[dt^2/2 I2; dt I2]) and the target's discrete acceleration is exact
    x = case2.state[0, :, 0]
    predicted_p = x[:-1, :2] + dt * x[:-1, 2:4] + dt ** 2 / 2 * (x[:-1, 4:] - own_u[:-1])
    predicted_v = x[:-1, 2:4] + dt * (x[:-1, 4:] - own_u[:-1])
    np.testing.assert_allclose(x[1:, :2], predicted_p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(x[1:, 2:4], predicted_v, rtol=0, atol=1e-12)


def test_relative_state_is_target_minus_ownship(case2):
    own, tgt = case2.labels["ownship"][0, :, 0], case2.labels["target_world"][0, :, 0]
    np.testing.assert_array_equal(case2.state[0, :, 0, :4], tgt - own)
    np.testing.assert_array_equal(tgt[0, :2], [5000.0, 10000.0])
    np.testing.assert_allclose(tgt[0, 2:], [-7.0 / np.sqrt(2), -7.0 / np.sqrt(2)], atol=1e-12)


def test_target_turns_by_the_requested_amount_at_the_requested_rate(case1, case2):
    t = case2.time
    tgt = case2.labels["target_world"][0, :, 0]
    expected = (225.0 - np.clip(0.5 * (t - 3000.0), 0.0, 45.0) + np.clip(0.5 * (t - 5100.0), 0.0, 45.0))
    np.testing.assert_allclose(course_deg(tgt[:, 2:]), expected, atol=1e-9)
    np.testing.assert_allclose(course_deg(tgt[[2999, 3045, 3090, 5099, 5145, 5190], 2:]),
                               [225, 202.5, 180, 180, 202.5, 225], atol=1e-9)
    np.testing.assert_allclose(np.hypot(tgt[:, 2], tgt[:, 3]), 7.0, rtol=1e-12)
    accel = np.hypot(case2.state[0, :, 0, 4], case2.state[0, :, 0, 5])
    turning = ((t >= 3000) & (t < 3090)) | ((t >= 5100) & (t < 5190))
    # chord of the velocity circle: |dv| / dt = 2 v sin(dpsi / 2) for dpsi = 0.5 deg per step
    np.testing.assert_allclose(accel[turning], 2 * 7.0 * np.sin(np.radians(0.25)), rtol=1e-9)
    np.testing.assert_array_equal(accel[~turning], 0.0)
    np.testing.assert_array_equal(case1.state[0, :, 0, 4:], 0.0)                     # straight target
    np.testing.assert_allclose(course_deg(case1.labels["target_world"][0, :, 0, 2:]), 225.0, atol=1e-9)
    # a right turn of 30 deg at 1 deg/s from course 0
    right = SonarEncounter(duration=100.0, target_heading=0.0, target_turns=[[10, 30]], target_turn_rate=1.0)
    np.testing.assert_allclose(right.target_course([0, 10, 25, 40, 100]), [0, 0, 15, 30, 30])


def test_closest_approach_and_final_range_as_the_spec_says(case1, case2):
    for truth in (case1, case2):
        r = np.hypot(truth.state[0, :, 0, 0], truth.state[0, :, 0, 1])
        k = int(np.argmin(r))
        assert 900.0 < r[k] < 1100.0 and 1060.0 <= truth.time[k] <= 1120.0        # ~1 km near 1090 s
        assert 85e3 < r[-1] < 90e3                                                   # ~88 km at 10 000 s
        assert r[0] == pytest.approx(np.hypot(5000.0, 10000.0))


# ---------------------------------------------------------------- sonar

def test_bearing_convention_from_north_clockwise():
    points = [(1000.0, 0.0), (0.0, 1000.0), (-1000.0, 0.0), (0.0, -1000.0), (1000.0, 1000.0), (-1.0, -1000.0)]
    det = ActivePassiveSonar(active_intervals=[[0, 100]], bearing_std_deg=0.0, range_std=0.0).measure(
        relative_position(points), seed=1)
    np.testing.assert_allclose(det.z[0, :, 0, 0], [np.pi / 2, 0.0, -np.pi / 2, np.pi, np.pi / 4,
                                                  -np.pi + np.arctan(1e-3)], atol=1e-12)
    assert det.z[0, 3, 0, 0] == np.pi                                                # wrapped into (-pi, pi]
    np.testing.assert_allclose(det.z[0, :, 0, 1], [1000, 1000, 1000, 1000, np.hypot(1e3, 1e3), np.hypot(1, 1e3)])
    # noise across +-pi wraps: a target due south stays in (-pi, pi]
    south = relative_position([(0.0, -1000.0)] * 2000)
    z = ActivePassiveSonar(bearing_std_deg=5.0).measure(south, seed=2).z[0, :, 0, 0]
    assert np.all((z > -np.pi) & (z <= np.pi)) and np.any(z > 3.0) and np.any(z < -3.0)


def test_active_passive_schedule_and_interval_edges(case2):
    sonar = load("sensors", "sonar_case2")
    t = np.array([0, 499, 500, 2499, 2500, 2999, 3000, 4999, 5000, 5499, 5500, 10000], dtype=float)
    np.testing.assert_array_equal(sonar.is_active(t), [1, 1, 0, 0, 1, 1, 0, 0, 1, 1, 0, 0])
    det = sonar.measure(case2, seed=3)
    active = sonar.is_active(case2.time)
    assert active.sum() == 1500
    np.testing.assert_array_equal(det.time, case2.time)
    np.testing.assert_array_equal(det.sensor, active.astype(int))
    assert det.sensor.dtype.kind == "i"
    assert det.z.shape == (1, 10001, 1, 2) and det.noise_covariance.shape == (1, 10001, 1, 2, 2)
    np.testing.assert_array_equal(np.isnan(det.z[0, :, 0, 1]), ~active)
    assert not np.any(np.isnan(det.z[..., 0]))
    stated = np.diag([np.radians(1.0) ** 2, 100.0])
    np.testing.assert_allclose(det.noise_covariance[0, :, 0], np.broadcast_to(stated, (10001, 2, 2)))
    np.testing.assert_array_equal(det.target, 0)
    assert det.detected.all()
    assert det.measurement_names == ("bearing", "range") and det.measurement_units == ("rad", "m")
    # scan times of a 0.1 s grid sit within 1e-9 s of the edges: 500.00000000000006 is passive
    fine = np.arange(6001) * 0.1
    edge = load("sensors", "sonar_case1").is_active(fine)
    assert edge[4999] and not edge[5000] and edge.sum() == 5000
    assert not ActivePassiveSonar(active_intervals=[]).is_active(fine).any()
    adjacent = ActivePassiveSonar(active_intervals=[[0, 10], [10, 20]])
    np.testing.assert_array_equal(adjacent.is_active([9, 10, 19, 20]), [1, 1, 1, 0])


def test_noise_statistics():
    truth = SonarEncounter(duration=5000.0).generate(40, seed=0)
    sonar = ActivePassiveSonar(active_intervals=[[0, 5001]], bearing_std_deg=1.0, range_std=10.0)
    det = sonar.measure(truth, seed=11)
    rx, ry = truth.state[..., 0], truth.state[..., 1]
    bearing_error = np.angle(np.exp(1j * (det.z[..., 0] - np.arctan2(rx, ry)))).ravel()
    range_error = (det.z[..., 1] - np.hypot(rx, ry)).ravel()
    n = bearing_error.size
    assert abs(bearing_error.mean()) < 4 * np.radians(1.0) / np.sqrt(n)
    assert abs(range_error.mean()) < 4 * 10.0 / np.sqrt(n)
    assert bearing_error.std() == pytest.approx(np.radians(1.0), rel=0.01)
    assert range_error.std() == pytest.approx(10.0, rel=0.01)
    assert abs(np.corrcoef(bearing_error, range_error)[0, 1]) < 4 / np.sqrt(n)


def test_determinism_run_independence_and_schedule_independent_noise():
    sonar1, sonar2 = load("sensors", "sonar_case1"), load("sensors", "sonar_case2")
    truth5 = SonarEncounter(duration=3000.0).generate(5, seed=0)
    truth2 = SonarEncounter(duration=3000.0).generate(2, seed=0)
    a, b = sonar2.measure(truth5, seed=4), sonar2.measure(truth5, seed=4)
    np.testing.assert_array_equal(a.z, b.z)
    assert not np.allclose(a.z[..., 0], sonar2.measure(truth5, seed=5).z[..., 0])
    np.testing.assert_array_equal(sonar2.measure(truth2, seed=4).z, a.z[:2])          # run r independent of R
    assert not np.allclose(a.z[0, :, :, 0], a.z[1, :, :, 0])                           # runs differ
    c = sonar1.measure(truth5, seed=4)                                                  # another schedule
    np.testing.assert_array_equal(c.z[..., 0], a.z[..., 0])
    both = sonar1.is_active(truth5.time) & sonar2.is_active(truth5.time)
    np.testing.assert_array_equal(c.z[:, both, :, 1], a.z[:, both, :, 1])


def test_stage_outputs_round_trip_through_the_tables():
    truth = SonarEncounter(duration=20.0, target_turns=[[5, 10]], target_turn_rate=2.0).generate(2, seed=0)
    back = truth_from_frame(*truth_to_frame(truth))
    assert back.state_names == truth.state_names and set(back.labels) == set(truth.labels)
    np.testing.assert_array_equal(back.state, truth.state)
    for key, values in truth.labels.items():
        np.testing.assert_array_equal(back.labels[key], values)
    det = ActivePassiveSonar(active_intervals=[[0, 10]]).measure(truth, seed=1)
    again = detections_from_frame(*detections_to_frame(det))
    np.testing.assert_array_equal(again.z, det.z)
    np.testing.assert_array_equal(again.sensor, det.sensor)
    np.testing.assert_array_equal(again.noise_covariance, det.noise_covariance)
    assert again.measurement_units == ("rad", "m")


# ---------------------------------------------------------------- bad arguments

@pytest.mark.parametrize("overrides, key", [
    ({"duration": -1.0}, "duration"),
    ({"duration": 10.5}, "duration"),
    ({"dt": 0.0}, "dt"),
    ({"ownship_speed": 0.0}, "ownship_speed"),
    ({"ownship_leg": -500.0}, "ownship_leg"),
    ({"ownship_turn_rate": 0.0}, "ownship_turn_rate"),
    ({"ownship_leg_heading": 90.0}, "ownship_leg_heading"),
    ({"ownship_leg_heading": -10.0}, "ownship_leg_heading"),
    ({"target_offset": [1.0]}, "target_offset"),
    ({"target_offset": [1.0, float("nan")]}, "target_offset"),
    ({"target_speed": -7.0}, "target_speed"),
    ({"target_heading": float("inf")}, "target_heading"),
    ({"target_turn_rate": 0.0}, "target_turn_rate"),
    ({"target_turns": [[-1.0, 45.0]]}, "target_turns[0]"),
    ({"target_turns": [[100.0, 0.0]]}, "target_turns[0]"),
    ({"target_turns": [[100.0]]}, "target_turns[0]"),
    ({"target_turns": [[100.0, 45.0], [150.0, 45.0]]}, "target_turns[1]"),       # first ends at 190 s
])
def test_scenario_rejects_bad_arguments_naming_the_key(overrides, key):
    with pytest.raises(ValueError, match=r"^" + key.replace("[", r"\[").replace("]", r"\]") + ":"):
        SonarEncounter(**overrides)


@pytest.mark.parametrize("overrides, key", [
    ({"active_intervals": [[5.0, 5.0]]}, "active_intervals[0]"),
    ({"active_intervals": [[0.0]]}, "active_intervals[0]"),
    ({"active_intervals": [[0.0, 500.0], [400.0, 600.0]]}, "active_intervals[1]"),
    ({"active_intervals": [[500.0, 600.0], [0.0, 100.0]]}, "active_intervals[1]"),
    ({"bearing_std_deg": -1.0}, "bearing_std_deg"),
    ({"range_std": float("nan")}, "range_std"),
])
def test_sonar_rejects_bad_arguments_naming_the_key(overrides, key):
    with pytest.raises(ValueError, match=r"^" + key.replace("[", r"\[").replace("]", r"\]") + ":"):
        ActivePassiveSonar(**overrides)


def test_sonar_needs_a_relative_position_truth():
    truth = Truth(np.arange(3.0), np.zeros((1, 3, 1, 2)), ("range", "bearing"))
    with pytest.raises(ValueError, match=r"state_names.*\('x', 'y'\)"):
        ActivePassiveSonar().measure(truth, seed=0)
