"""Filter inputs the unit tests build without the pipeline: a scenario's truth from its config and
its position measurements (study 001), coordinated-turn tracks and radar series (filters.turn),
the sonar encounter's reports (study 003, filters.mgekf) and the sonobuoy field's (study 004,
filters.particle)."""

from __future__ import annotations

import numpy as np
from hydra.utils import instantiate
from omegaconf import OmegaConf

from filters.base import MeasurementSeries
from filters.mgekf import SonarReports
from filters.particle import BuoyReports
from pipeline.studies.sonar.scenario import SonarEncounter
from pipeline.studies.sonar.sensor import ActivePassiveSonar
from pipeline.studies.sonobuoy.scenario import SonobuoyField
from pipeline.studies.sonobuoy.sensor import SonobuoyBearings
from tests.helpers.config import CONF


def scenario(name: str, **overrides):
    node = OmegaConf.load(CONF / "scenario" / f"{name}.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


def measurements(truth, seed: int, noise_std: float = 20.0) -> MeasurementSeries:
    from pipeline.studies.ao_vsimm.sensor import PositionSensor
    det = PositionSensor(noise_std).measure(truth, seed)
    return MeasurementSeries(det.time, det.z[:, :, 0], noise_std**2 * np.eye(2), det.detected[:, :, 0], det.sensor)


STUDY_000_LAYOUT = ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")


def rotation(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def circle(p0: np.ndarray, v0: np.ndarray, omega: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed form of a coordinated turn: p(t) = c + Rot(w t)(p0 - c), c = p0 + (-v0y, v0x)/w."""
    centre = p0 + np.array([-v0[1], v0[0]]) / omega
    turn = rotation(omega * t)
    return centre + turn @ (p0 - centre), turn @ v0


def positions_series(p: np.ndarray, t: np.ndarray, sigma: float, detected: np.ndarray | None = None,
                     ) -> MeasurementSeries:
    R, K, _ = p.shape
    seen = np.ones((R, K), bool) if detected is None else detected
    return MeasurementSeries(t, np.where(seen[..., None], p, np.nan), sigma**2 * np.eye(2), seen, np.zeros(K, int))


def radar_series(rng: np.random.Generator, R: int = 6, K: int = 40, misses: float = 0.1) -> MeasurementSeries:
    """Noisy range/azimuth/elevation of straight 3-D tracks from a radar at (100, -50, 10), some missed."""
    t = np.arange(K) * 2.0
    truth = (np.array([30e3, 10e3, 8e3]) + rng.uniform(-5e3, 5e3, (R, 1, 3))
             + rng.uniform(-200, 200, (R, 1, 3)) * np.array([1, 1, 0.05]) * t[None, :, None])
    radar = np.array([100.0, -50.0, 10.0])
    rel = truth - radar
    r = np.linalg.norm(rel, axis=-1)
    std = np.array([10.0, 0.002, 0.002])
    polar = np.stack([r, np.arctan2(rel[..., 1], rel[..., 0]), np.arcsin(rel[..., 2] / r)], -1)
    polar = polar + std * rng.standard_normal(polar.shape)
    detected = rng.random((R, K)) > misses
    detected[:, :2] = True
    return MeasurementSeries(t, np.where(detected[..., None], polar, np.nan), np.diag(std**2), detected,
                             np.zeros(K, int), radar, STUDY_000_LAYOUT)


def turning_positions(rng: np.random.Generator, R: int = 8, K: int = 120, varying: bool = False):
    """2-D positions, noise 25 m: a straight leg, a turn of +-2..4 deg/s, a straight leg; ~10 % missed."""
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(1.0, 5.0, K - 1))]) if varying else np.arange(K) * 2.0
    tracks = []
    for _ in range(R):
        p0, v0 = rng.uniform(-1e4, 1e4, 2), rng.uniform(-200.0, 200.0, 2)
        omega = rng.choice([-1.0, 1.0]) * rng.uniform(0.035, 0.07)
        start, stop = t[K // 3], t[2 * K // 3]
        straight = p0 + v0 * np.minimum(t, start)[:, None]
        turned, v1 = circle(straight[K // 3], v0, omega, np.clip(t - start, 0.0, stop - start))
        track = np.where((t < start)[:, None], straight, turned)
        after = t > stop
        track[after] = turned[after][0] + v1[-1] * (t[after] - stop)[:, None] - v1[-1] * (t[after][0] - stop)
        tracks.append(track)
    p = np.stack(tracks) + 25.0 * rng.standard_normal((R, K, 2))
    detected = rng.random((R, K)) > 0.1
    detected[:, :2] = True
    return positions_series(p, t, 25.0, detected)


def sonar_reports(duration=3000.0, active=((0.0, 1.0),), bearing_std_deg=0.0, range_std=0.0, runs=2, turns=(),
             filter_bearing_std=1e-3, filter_range_std=1.0, seed=0):
    scenario = SonarEncounter(duration=duration, target_turns=[list(t) for t in turns])
    truth = scenario.generate(runs, seed)
    detections = ActivePassiveSonar(active_intervals=[list(a) for a in active], bearing_std_deg=bearing_std_deg,
                                    range_std=range_std).measure(truth, seed)
    reports = SonarReports(detections.time, detections.z[:, :, 0], detections.sensor == 1,
                           truth.labels["ownship_acceleration"][:, :, 0], truth.labels["ownship"][:, 0, 0, 2:4],
                           filter_bearing_std, filter_range_std)
    return truth, reports


def buoy_reports(runs=4, duration=300.0, clutter=False, seed=0):
    truth = SonobuoyField(duration=duration).generate(runs, seed)
    sensor = SonobuoyBearings(miss_probability=0.2 if clutter else 0.0, clutter_probability=0.5 if clutter else 0.0)
    detections = sensor.measure(truth, seed)
    prior_std = np.array([1000.0, 1000.0, 2.0, 2.0] + [100.0, 100.0, 0.05, 0.05] * 4)
    prior_mean = truth.state[:, 0, 0] + np.random.default_rng(seed).standard_normal((runs, 20)) * prior_std
    return truth, BuoyReports(detections.time, detections.z[..., 0], np.asarray(sensor.observer_position),
                              np.asarray(sensor.nominal_std), np.asarray(sensor.clutter_std),
                              float(sensor.clutter_probability), prior_mean, prior_std, seed)
