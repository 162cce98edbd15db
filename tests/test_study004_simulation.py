"""Study 004 simulation (spec 004 "Model", "Clutter and missed detections" and "Scenarios";
literature notes 6.1-6.2): the target and drifting sonobuoys and their bearings, built from their
Hydra configs."""

from __future__ import annotations

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from filters.particle import STATE_NAMES, ct_transition
from pipeline.data import Truth
from pipeline.studies.sonobuoy.scenario import SonobuoyField
from pipeline.storage.schemas import detections_from_frame, detections_to_frame, truth_from_frame, truth_to_frame
from pipeline.run.seeding import run_generators
from pipeline.studies.sonobuoy.sensor import SonobuoyBearings
from tests.helpers.config import CONF

SQUARE_4KM = [[-2000.0, -2000.0], [2000.0, -2000.0], [2000.0, 2000.0], [-2000.0, 2000.0]]


def load(group: str, name: str, **overrides):
    node = OmegaConf.load(CONF / group / f"{name}.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


@pytest.fixture(scope="module")
def case2() -> Truth:
    return load("scenario", "sonobuoy_case2").generate(2, seed=0)


def heading(velocity: np.ndarray) -> np.ndarray:
    """Heading from north, clockwise [rad], unwrapped along the time axis of velocities (K, 2)."""
    return np.unwrap(np.arctan2(velocity[..., 0], velocity[..., 1]))


def residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * (a - b)))


def true_bearings(x: np.ndarray, observer=(0.0, -8000.0)) -> np.ndarray:
    """(..., 8) theta_i = atan2(x_t - x_bi, y_t - y_bi), phi_i = atan2(x_bi - x_o, y_bi - y_o) of states (..., 20)."""
    theta = [np.arctan2(x[..., 0] - x[..., 4 + 4 * i], x[..., 1] - x[..., 5 + 4 * i]) for i in range(4)]
    phi = [np.arctan2(x[..., 4 + 4 * i] - observer[0], x[..., 5 + 4 * i] - observer[1]) for i in range(4)]
    return np.stack(theta + phi, axis=-1)


def one_scan_truth(target, buoys) -> Truth:
    """Two scans (0 and 1) holding the same state: target (x, y) and four buoy (x, y), at rest."""
    state = np.zeros((1, 2, 1, 20))
    state[..., :2] = target
    for i, b in enumerate(buoys):
        state[..., 4 + 4 * i: 6 + 4 * i] = b
    return Truth(np.array([0.0, 5.0]), state, STATE_NAMES)


# ---------------------------------------------------------------- configs and layout

def test_configs_build_with_the_spec_values():
    cases = {name: load("scenario", f"sonobuoy_{name}") for name in ("case1", "case1b", "case2")}
    for s in cases.values():
        assert isinstance(s, SonobuoyField)
        assert (s.duration, s.dt, s.steps, s.buoy_sigma, s.noise_gain) == (1800.0, 5.0, 360, 0.0005, "standard")
        np.testing.assert_array_equal(s.target_start, [-6000.0, 3000.0])
        np.testing.assert_array_equal(s.target_velocity, [5.0, -1.0])
        np.testing.assert_array_equal(s.buoy_drift, [0.2, 0.1])
    np.testing.assert_array_equal(cases["case1"].buoy_positions, SQUARE_4KM)
    np.testing.assert_array_equal(cases["case2"].buoy_positions, SQUARE_4KM)
    np.testing.assert_array_equal(cases["case1b"].buoy_positions, np.array(SQUARE_4KM) / 4)
    assert cases["case1"].target_turn_start is None and cases["case1b"].target_turn_start is None
    c2 = cases["case2"]
    assert (c2.target_turn_start, c2.target_turn_acceleration, c2.turn_direction) == (800.0, 0.005, "right")
    clean, clutter = load("sensors", "sonobuoy_clean"), load("sensors", "sonobuoy_clutter")
    for sensor in (clean, clutter):
        np.testing.assert_array_equal(sensor.observer_position, [0.0, -8000.0])
        np.testing.assert_allclose(np.degrees(sensor.nominal_std), [7] * 4 + [1.5] * 4)
        np.testing.assert_allclose(np.degrees(sensor.clutter_std), [15] * 4 + [5] * 4)
    assert (clean.miss_probability, clean.clutter_probability) == (0.0, 0.0)
    assert (clutter.miss_probability, clutter.clutter_probability) == (0.2, 0.5)


def test_truth_layout(case2):
    assert case2.state.shape == (2, 361, 1, 20) and case2.state_names == STATE_NAMES
    assert STATE_NAMES[:6] == ("x", "y", "vx", "vy", "b1_x", "b1_y") and STATE_NAMES[-1] == "b4_vy"
    np.testing.assert_array_equal(case2.time, np.arange(361) * 5.0)
    assert set(case2.labels) == {"turn_mode"} and case2.labels["turn_mode"].shape == (2, 361, 1)
    assert case2.labels["turn_mode"].dtype.kind == "i"
    np.testing.assert_array_equal(case2.state[0, :, :, :4], case2.state[1, :, :, :4])     # one target track
    assert not np.allclose(case2.state[0, 1:, 0, 4:], case2.state[1, 1:, 0, 4:])           # buoy noise per run
    np.testing.assert_array_equal(case2.state[:, 0, 0, :4], [[-6000.0, 3000.0, 5.0, -1.0]] * 2)
    np.testing.assert_array_equal(case2.state[0, 0, 0, 4:].reshape(4, 4),
                                  np.hstack([SQUARE_4KM, np.tile([0.2, 0.1], (4, 1))]))


# ---------------------------------------------------------------- target

def test_straight_target_without_process_noise():
    truth = load("scenario", "sonobuoy_case1").generate(3, seed=5)
    t = truth.time[:, None]
    target = truth.state[:, :, 0, :4]
    line = np.array([-6000.0, 3000.0]) + t * [5.0, -1.0]
    np.testing.assert_allclose(target[..., :2], np.broadcast_to(line, target[..., :2].shape), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(target[..., 2:], np.broadcast_to([5.0, -1.0], target[..., 2:].shape))
    np.testing.assert_array_equal(truth.labels["turn_mode"], 1)


@pytest.mark.parametrize("direction, sign, mode", [("right", 1.0, 3), ("left", -1.0, 2)])
def test_coordinated_turn_rate_sense_and_mode_label(direction, sign, mode):
    scenario = SonobuoyField(target_turn_start=800.0, turn_direction=direction)
    truth = scenario.generate(1, seed=0)
    t, target = truth.time, truth.state[0, :, 0, :4]
    speed = np.hypot(5.0, 1.0)
    rate = 0.005 / speed                                                   # accel / speed [rad/s]
    assert scenario.turn_rate == pytest.approx(-sign * rate)               # Omega < 0 is clockwise
    np.testing.assert_allclose(np.hypot(target[:, 2], target[:, 3]), speed, rtol=1e-12)
    psi = heading(target[:, 2:])
    expected = np.arctan2(5.0, -1.0) + sign * rate * np.clip(t - 800.0, 0.0, None)   # right: heading increases
    np.testing.assert_allclose(psi, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.diff(psi)[t[1:] > 800.0], sign * rate * 5.0, rtol=1e-9)
    # positions on the circle: p(t) = p_s + (speed / w) (cos psi_s - cos psi, sin psi - sin psi_s) for
    # heading psi = psi_s + w (t - t_s), w = sign * rate
    k_s = 160
    assert t[k_s] == 800.0
    np.testing.assert_allclose(target[: k_s + 1, :2], np.array([-6000.0, 3000.0]) + t[: k_s + 1, None] * [5.0, -1.0],
                               atol=1e-9)
    w, psi_s = sign * rate, expected[k_s]
    arc = target[k_s, :2] + speed / w * np.stack([np.cos(psi_s) - np.cos(expected),
                                                  np.sin(expected) - np.sin(psi_s)], axis=-1)
    np.testing.assert_allclose(target[k_s:, :2], arc[k_s:], rtol=0, atol=1e-6)
    labels = truth.labels["turn_mode"][0, :, 0]
    np.testing.assert_array_equal(labels, np.where(t > 800.0, mode, 1))     # mode of the step (k-1, k]
    # centripetal acceleration: |v(k+1) - v(k)| / T = 2 speed sin(rate T / 2) / T ~ 0.005 m/s^2
    dv = np.hypot(*np.diff(target[:, 2:], axis=0).T)[t[1:] > 800.0] / 5.0
    np.testing.assert_allclose(dv, 0.005, rtol=1e-4)


def test_turn_start_between_scans_splits_the_step():
    on_grid = SonobuoyField(duration=100.0, target_turn_start=40.0, target_turn_acceleration=0.5)
    off_grid = SonobuoyField(duration=100.0, target_turn_start=42.0, target_turn_acceleration=0.5)
    a, b = on_grid.target_track()[0], off_grid.target_track()[0]
    omega = on_grid.turn_rate
    # t = 45: straight for 2 s from t = 40, then turning for 3 s; the same as turning from 42 exactly
    straight = a[8] + [2.0 * 5.0, -2.0, 0.0, 0.0]                          # the target at t = 42
    np.testing.assert_allclose(b[9], ct_transition(omega, 3.0) @ straight, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(off_grid.target_track()[1][8:11], [1, 3, 3])
    np.testing.assert_allclose(np.hypot(b[:, 2], b[:, 3]), np.hypot(5.0, 1.0), rtol=1e-12)
    assert SonobuoyField(duration=100.0, target_turn_start=500.0).target_track()[1].max() == 1   # after the end


# ---------------------------------------------------------------- buoys

@pytest.mark.parametrize("gain, g", [("standard", 12.5), ("paper", 2.5)])
def test_buoys_follow_the_cv_model_with_the_stated_noise(gain, g):
    R, sigma, T = 200, 0.0005, 5.0
    scenario = SonobuoyField(duration=200.0, buoy_sigma=sigma, noise_gain=gain)
    truth = scenario.generate(R, seed=3)
    K = truth.time.size
    b = truth.state[:, :, 0, 4:].reshape(R, K, 4, 4)
    p, v = b[..., :2], b[..., 2:]
    w = (v[:, 1:] - v[:, :-1]) / T                                          # recovered accelerations
    np.testing.assert_allclose(p[:, 1:] - p[:, :-1] - T * v[:, :-1], g * w, rtol=0, atol=1e-9)
    expected = sigma * np.stack([gen.standard_normal((K - 1, 4, 2)) for gen in run_generators(3, "scenario", R)])
    np.testing.assert_allclose(w, expected, rtol=1e-9, atol=1e-15)        # the documented stream
    # statistics: mean drift and the N(0, sigma^2 I2) process noise (loose)
    n = (w / sigma).reshape(-1, 2)
    assert abs(n.mean()) < 4 / np.sqrt(n.size)
    np.testing.assert_allclose(np.cov(n.T), np.eye(2), atol=0.05)
    mean_p = p.mean(axis=0)                                                 # (K, 4, 2)
    drift = np.array(SQUARE_4KM)[None] + truth.time[:, None, None] * [0.2, 0.1]
    # p(K-1) = p0 + (K-1) T v0 + sum_j (g + T^2 (K-2-j)) w(j): the final position's std per axis
    final_std = sigma * np.sqrt(np.sum((g + T * T * (K - 2 - np.arange(K - 1))) ** 2))
    assert np.all(np.abs(mean_p - drift) < 5 * final_std / np.sqrt(R))
    assert np.std(p[:, -1], axis=0) == pytest.approx(np.full((4, 2), final_std), rel=0.25)
    quiet = SonobuoyField(duration=200.0, buoy_sigma=0.0).generate(2, seed=3).state[:, :, 0, 4:].reshape(2, K, 4, 4)
    np.testing.assert_allclose(quiet[..., :2], np.broadcast_to(drift, quiet[..., :2].shape), rtol=0, atol=1e-9)


# ---------------------------------------------------------------- bearings

def test_bearing_convention_and_wrap():
    clean = SonobuoyBearings(target_bearing_std_deg=0.0, buoy_bearing_std_deg=0.0)
    # target at the origin; buoy 1 due west (target due east of it), buoy 2 due north (target due
    # south: +pi, not -pi), buoy 3 due east, buoy 4 south-west; observer at (0, -8 km)
    buoys = [(-1000.0, 0.0), (0.0, 1000.0), (1000.0, 0.0), (-1000.0, -1000.0)]
    det = clean.measure(one_scan_truth((0.0, 0.0), buoys), seed=0)
    z = det.z[0, 1, :, 0]
    np.testing.assert_allclose(z[:4], [np.pi / 2, np.pi, -np.pi / 2, np.pi / 4], rtol=0, atol=1e-15)
    assert z[1] == np.pi
    np.testing.assert_allclose(z[4:], [np.arctan2(-1000, 8000), np.arctan2(0, 9000), np.arctan2(1000, 8000),
                                       np.arctan2(-1000, 7000)], rtol=0, atol=1e-15)
    # a buoy due south of the observer, -0.0 east of it: atan2(-0.0, -1) = -pi is wrapped to +pi
    south = SonobuoyBearings(observer_position=(0.0, 5000.0), target_bearing_std_deg=0.0, buoy_bearing_std_deg=0.0)
    assert south.measure(one_scan_truth((0.0, 0.0), [(-0.0, 0.0)] * 4), seed=0).z[0, 1, 4, 0] == np.pi
    # noise across +-pi stays in (-pi, pi]
    noisy = SonobuoyBearings(target_bearing_std_deg=7.0).measure(
        Truth(np.arange(2000.0), np.repeat(one_scan_truth((0.0, 0.0), buoys).state[:, :1], 2000, axis=1),
              STATE_NAMES), seed=1).z[0, 1:, 1, 0]
    assert np.all((noisy > -np.pi) & (noisy <= np.pi)) and np.any(noisy > 3.0) and np.any(noisy < -3.0)


def test_noise_free_sensor_reproduces_the_geometry(case2):
    sensor = load("sensors", "sonobuoy_clean", target_bearing_std_deg=0.0, buoy_bearing_std_deg=0.0)
    det = sensor.measure(case2, seed=0)
    np.testing.assert_allclose(det.z[:, 1:, :, 0], true_bearings(case2.state[:, 1:, 0]), rtol=0, atol=1e-15)


def test_detections_layout_and_start_scan(case2):
    det = load("sensors", "sonobuoy_clutter").measure(case2, seed=1)
    assert det.z.shape == (2, 361, 8, 1) and det.noise_covariance.shape == (2, 361, 8, 1, 1)
    assert det.target.shape == det.detected.shape == (2, 361, 8)
    np.testing.assert_array_equal(det.time, case2.time)
    np.testing.assert_array_equal(det.sensor, 0)
    assert np.all(np.isnan(det.z[:, 0])) and not det.detected[:, 0].any()       # nothing at the start
    assert det.measurement_names == ("bearing",) and det.measurement_units == ("rad",)
    np.testing.assert_allclose(det.noise_covariance[..., 0, 0],
                               np.broadcast_to(np.radians([7.0] * 4 + [1.5] * 4) ** 2, (2, 361, 8)))
    np.testing.assert_array_equal(np.isnan(det.z[..., 0]), ~det.detected)
    obj = np.array([0, 0, 0, 0, 1, 2, 3, 4])
    assert np.all((det.target == -1) | (det.target == obj))
    assert not np.any((det.target == -1) & ~det.detected)
    clean = load("sensors", "sonobuoy_clean").measure(case2, seed=1)
    assert clean.detected[:, 1:].all() and np.all(clean.target == obj)


def test_miss_and_clutter_fractions_labels_and_spread():
    truth = load("scenario", "sonobuoy_case2").generate(20, seed=2)
    sensor = load("sensors", "sonobuoy_clutter")
    det = sensor.measure(truth, seed=7)
    d, z, target = det.detected[:, 1:], det.z[:, 1:, :, 0], det.target[:, 1:]
    n = d.size
    assert (~d).mean() == pytest.approx(0.2, abs=4 * np.sqrt(0.16 / n))
    clutter = target == -1
    assert clutter[d].mean() == pytest.approx(0.5, abs=4 * np.sqrt(0.25 / d.sum()))
    error = residual(z, true_bearings(truth.state[:, 1:, 0]))
    for slots, nominal, inflated in ((slice(0, 4), 7.0, 15.0), (slice(4, 8), 1.5, 5.0)):
        e, c, ok = error[..., slots], clutter[..., slots], d[..., slots]
        assert np.degrees(e[ok & ~c].std()) == pytest.approx(nominal, rel=0.05)
        assert np.degrees(e[ok & c].std()) == pytest.approx(inflated, rel=0.05)


def test_determinism_run_independence_and_setting_independent_draws():
    scenario = load("scenario", "sonobuoy_case2")
    truth5, truth2 = scenario.generate(5, seed=0), scenario.generate(2, seed=0)
    np.testing.assert_array_equal(truth2.state, truth5.state[:2])                 # truth run r independent of R
    np.testing.assert_array_equal(scenario.generate(5, seed=0).state, truth5.state)
    sensor = load("sensors", "sonobuoy_clutter")
    a, b = sensor.measure(truth5, seed=4), sensor.measure(truth5, seed=4)
    np.testing.assert_array_equal(a.z, b.z)
    np.testing.assert_array_equal(a.target, b.target)
    np.testing.assert_array_equal(sensor.measure(truth2, seed=4).z, a.z[:2])        # run r independent of R
    assert not np.array_equal(a.detected, sensor.measure(truth5, seed=5).detected)
    # the clean sensor draws the same numbers: where the cluttered one gave a nominal return, they agree
    c = load("sensors", "sonobuoy_clean").measure(truth5, seed=4)
    nominal = a.detected & (a.target >= 0)
    np.testing.assert_array_equal(c.z[nominal], a.z[nominal])


def test_stage_outputs_round_trip_through_the_tables():
    truth = SonobuoyField(duration=30.0, target_turn_start=10.0, turn_direction="left").generate(2, seed=0)
    back = truth_from_frame(*truth_to_frame(truth))
    assert back.state_names == truth.state_names and set(back.labels) == {"turn_mode"}
    np.testing.assert_array_equal(back.state, truth.state)
    np.testing.assert_array_equal(back.time, truth.time)
    np.testing.assert_array_equal(back.labels["turn_mode"], truth.labels["turn_mode"])
    det = SonobuoyBearings(miss_probability=0.3, clutter_probability=0.5).measure(truth, seed=1)
    df, meta = detections_to_frame(det)
    again = detections_from_frame(df, meta)
    for name in ("time", "sensor", "z", "noise_covariance", "target", "detected"):
        np.testing.assert_array_equal(getattr(again, name), getattr(det, name))
    assert again.measurement_names == ("bearing",) and again.measurement_units == ("rad",)
    assert df["clutter"].sum() == int((det.target == -1).sum())


# ---------------------------------------------------------------- bad arguments

def _key_pattern(key: str) -> str:
    return r"^" + key.replace("[", r"\[").replace("]", r"\]") + ":"


@pytest.mark.parametrize("overrides, key", [
    ({"duration": 0.0}, "duration"),
    ({"duration": 12.0}, "duration"),
    ({"dt": -5.0}, "dt"),
    ({"target_start": [1.0]}, "target_start"),
    ({"target_start": [1.0, float("nan")]}, "target_start"),
    ({"target_velocity": "fast"}, "target_velocity"),
    ({"target_velocity": [0.0, 0.0], "target_turn_start": 10.0}, "target_velocity"),
    ({"buoy_positions": [[0.0, 0.0]] * 3}, "buoy_positions"),
    ({"buoy_positions": [[0.0, 0.0]] * 3 + [[0.0, float("inf")]]}, "buoy_positions"),
    ({"buoy_drift": [0.2]}, "buoy_drift"),
    ({"buoy_sigma": -0.001}, "buoy_sigma"),
    ({"buoy_sigma": "x"}, "buoy_sigma"),
    ({"target_turn_start": -1.0}, "target_turn_start"),
    ({"target_turn_acceleration": 0.0}, "target_turn_acceleration"),
    ({"turn_direction": "clockwise"}, "turn_direction"),
    ({"turn_direction": ["right"]}, "turn_direction"),
    ({"noise_gain": "T/2"}, "noise_gain"),
])
def test_scenario_rejects_bad_arguments_naming_the_key(overrides, key):
    with pytest.raises(ValueError, match=_key_pattern(key)):
        SonobuoyField(**overrides)
    with pytest.raises(ValueError, match=r"^runs:"):
        SonobuoyField().generate(0, seed=0)


@pytest.mark.parametrize("overrides, key", [
    ({"observer_position": [0.0]}, "observer_position"),
    ({"observer_position": [0.0, float("nan")]}, "observer_position"),
    ({"target_bearing_std_deg": -7.0}, "target_bearing_std_deg"),
    ({"buoy_bearing_std_deg": float("inf")}, "buoy_bearing_std_deg"),
    ({"miss_probability": 1.2}, "miss_probability"),
    ({"clutter_probability": -0.1}, "clutter_probability"),
    ({"clutter_probability": None}, "clutter_probability"),
    ({"clutter_target_bearing_std_deg": -1.0}, "clutter_target_bearing_std_deg"),
    ({"clutter_buoy_bearing_std_deg": "wide"}, "clutter_buoy_bearing_std_deg"),
])
def test_sensor_rejects_bad_arguments_naming_the_key(overrides, key):
    with pytest.raises(ValueError, match=_key_pattern(key)):
        SonobuoyBearings(**overrides)


def test_sensor_needs_a_sonobuoy_truth():
    truth = Truth(np.arange(3.0), np.zeros((1, 3, 1, 6)), ("x", "y", "vx", "vy", "ax", "ay"))
    with pytest.raises(ValueError, match=r"^truth state_names:"):
        SonobuoyBearings().measure(truth, seed=0)
