"""Asynchronous 2-D radars with offset and scale biases in range and azimuth (study 002, seed 002 eq 1).

Each radar s reports every target at its own times first_report_s + n period_s (n >= 0):

    r^p = (1 + eps_r) r + b_r + w_r,    theta^p = (1 + eps_theta) theta + b_theta + w_theta   (eq 1)

with w ~ N(0, diag(range_std^2, azimuth_std^2)) and the bias vector
beta_s = (b_r [m], b_theta [rad], eps_r [-], eps_theta [-]). r and theta are the true range and
azimuth of the target relative to the radar, theta = atan2(dy, dx) from +x toward +y in (-pi, pi].
The measured azimuth is not re-wrapped (the scale bias multiplies the wrapped true angle).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from pipeline.data import Detections, Truth
from pipeline.run.seeding import run_generators

MEASUREMENT_NAMES = ("range", "azimuth")
MEASUREMENT_UNITS = ("m", "rad")
RADAR_KEYS = ("name", "position", "period", "first_report", "range_std", "azimuth_std", "bias")
TIME_TOLERANCE = 1e-9          # [s] a report time matches a truth time this close


def _finite_vector(where: str, value: object, size: int, what: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} must be {what}") from None
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{where}: {value!r} must be {what}")
    return array


def _number(where: str, value: object, lowest: float, strict: bool, unit: str) -> float:
    bound = f"> {lowest:g}" if strict else f">= {lowest:g}"
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} must be a number {bound} {unit}") from None
    if not (np.isfinite(number) and (number > lowest if strict else number >= lowest)):
        raise ValueError(f"{where}: {value!r} must be {bound} {unit}")
    return number


class BiasedRadarNetwork:
    """S radars measuring range and azimuth of every target with the biases of seed 002 eq 1.

    Every radar reports all T targets at each of its report times (no misses, no clutter); the
    reports of all radars are merged into one time-ordered sequence of scans (``report_times``).
    Each detection reports ``noise_covariance`` = diag(range_std^2, azimuth_std^2) of its radar:
    what the radar knows; the biases are unknown to it (``true_bias_vector`` gives them for
    evaluation). A std of 0 gives a noise-free channel (for tests).

    Parameters
    ----------
    radars : one mapping per radar, with exactly the keys
        name (str), position [x, y] [m], period [s] (> 0), first_report [s] (> 0: the time of
        its first report), range_std [m] (>= 0), azimuth_std [rad] (>= 0),
        bias [b_r (m), b_theta (rad), eps_r (-), eps_theta (-)]
        The radar's index in this list is its sensor index in ``Detections.sensor``.
    """

    produces = "biased_radar_reports"          # filters.base.MEASUREMENT_KINDS

    def __init__(self, radars: Sequence[Mapping]) -> None:
        if isinstance(radars, (str, bytes, Mapping)) or len(radars) == 0:
            raise ValueError(f"radars: {radars!r} must be a non-empty list of radar mappings")
        names, positions, noise_std, biases, periods, first_reports = [], [], [], [], [], []
        for i, radar in enumerate(radars):
            where = f"radars[{i}]"
            if not isinstance(radar, Mapping):
                raise ValueError(f"{where}: {radar!r} must be a mapping with keys {list(RADAR_KEYS)}")
            unknown = [key for key in radar if key not in RADAR_KEYS]
            if unknown:
                raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {list(RADAR_KEYS)}")
            missing = [key for key in RADAR_KEYS if key not in radar]
            if missing:
                raise ValueError(f"{where}: missing key(s) {missing}; required: {list(RADAR_KEYS)}")
            name = radar["name"]
            if not isinstance(name, str) or not name:
                raise ValueError(f"{where}.name: {name!r} must be a non-empty string")
            if name in names:
                raise ValueError(f"{where}.name: {name!r} is already the name of radars[{names.index(name)}]; "
                                 f"names must be unique")
            names.append(name)
            positions.append(_finite_vector(f"{where}.position", radar["position"], 2, "a finite [x, y] in m"))
            periods.append(_number(f"{where}.period", radar["period"], 0.0, True, "s"))
            first_reports.append(_number(f"{where}.first_report", radar["first_report"], 0.0, True, "s"))
            noise_std.append([_number(f"{where}.range_std", radar["range_std"], 0.0, False, "m"),
                              _number(f"{where}.azimuth_std", radar["azimuth_std"], 0.0, False, "rad")])
            biases.append(_finite_vector(f"{where}.bias", radar["bias"], 4,
                                         "a finite [b_r (m), b_theta (rad), eps_r, eps_theta]"))
        self.names = tuple(names)
        self.positions = np.array(positions)                # (S, 2)
        self.noise_std = np.array(noise_std)                # (S, 2) range_std, azimuth_std
        self.biases = np.array(biases)                      # (S, 4) b_r, b_theta, eps_r, eps_theta
        self.periods = np.array(periods)                    # (S,)
        self.first_reports = np.array(first_reports)        # (S,)

    @property
    def sensors(self) -> int:
        return len(self.names)

    def true_bias_vector(self) -> np.ndarray:
        """(4S,) the stacked bias vectors [beta_1; ...; beta_S], beta_s = (b_r, b_theta, eps_r, eps_theta)."""
        return self.biases.reshape(-1).copy()

    def report_times(self, duration: float) -> tuple[np.ndarray, np.ndarray]:
        """All reports up to ``duration`` [s]: time (K,) and sensor (K,) int, sorted by time, ties in
        radar order. Radar s reports at first_report_s + n period_s for every n >= 0 with
        time <= duration (to 1e-9 s)."""
        duration = _number("duration", duration, 0.0, False, "s")
        times, sensors = [], []
        for s in range(self.sensors):
            count = int(np.floor((duration + TIME_TOLERANCE - self.first_reports[s]) / self.periods[s])) + 1
            t = self.first_reports[s] + np.arange(max(count, 0)) * self.periods[s]
            times.append(t)
            sensors.append(np.full(t.size, s))
        time, sensor = np.concatenate(times), np.concatenate(sensors)
        order = np.lexsort((sensor, np.round(time / TIME_TOLERANCE)))      # equal to 1e-9 s: radar order
        return time[order], sensor[order]

    def measure(self, truth: Truth, seed: int) -> Detections:
        """One scan per report of ``report_times(truth.time[-1])``: z (R, K, T, 2) the biased, noisy
        (range, azimuth) of every target relative to the reporting radar (eq 1). Every report time
        must lie on ``truth.time``; ``Detections.time`` takes the truth's value of it."""
        if tuple(truth.state_names[:2]) != ("x", "y"):
            raise ValueError(f"truth state_names: {list(truth.state_names)} must start with ('x', 'y') "
                             f"for BiasedRadarNetwork")
        R, _, T, _ = truth.state.shape
        truth_time = np.asarray(truth.time, dtype=float)
        time, sensor = self.report_times(truth_time[-1])
        index = np.minimum(np.searchsorted(truth_time, time - TIME_TOLERANCE), truth_time.size - 1)
        off = np.abs(truth_time[index] - time) > TIME_TOLERANCE
        if np.any(off):
            first = int(np.argmax(off))
            step = f"{np.diff(truth_time)[0]:g} s" if truth_time.size > 1 else "none (a single scan)"
            raise ValueError(f"report time {time[first]:g} s of radar {self.names[sensor[first]]!r} is not on "
                             f"the truth's time grid (time step {step}); every report time must be a truth time")
        K = time.size
        relative = truth.state[:, index, :, :2] - self.positions[sensor][None, :, None, :]    # (R, K, T, 2)
        r = np.hypot(relative[..., 0], relative[..., 1])
        theta = np.arctan2(relative[..., 1], relative[..., 0])
        theta = np.where(theta == -np.pi, np.pi, theta)                                        # (-pi, pi]
        b_r, b_theta, eps_r, eps_theta = (self.biases[sensor, j][None, :, None] for j in range(4))
        std = self.noise_std[sensor][None, :, None, :]                                        # (1, K, 1, 2)
        noise = np.stack([g.standard_normal((K, T, 2)) for g in run_generators(seed, "measure", R)])
        z = np.stack([(1.0 + eps_r) * r + b_r, (1.0 + eps_theta) * theta + b_theta], axis=-1) + std * noise
        variance = self.noise_std[sensor] ** 2                                                # (K, 2)
        cov = np.zeros((K, 2, 2))
        cov[:, 0, 0], cov[:, 1, 1] = variance[:, 0], variance[:, 1]
        return Detections(
            time=truth_time[index], sensor=sensor.astype(int), z=z,
            noise_covariance=np.broadcast_to(cov[None, :, None], (R, K, T, 2, 2)).copy(),
            target=np.broadcast_to(np.arange(T), (R, K, T)).copy(), detected=np.ones((R, K, T), dtype=bool),
            measurement_names=MEASUREMENT_NAMES, measurement_units=MEASUREMENT_UNITS,
        )
