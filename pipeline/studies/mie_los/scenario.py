"""A 3-D target driven by a piecewise-constant inertial acceleration profile (seed 000, spec 000).

State per scan, in this order: x, y, z [m], vx, vy, vz [m/s], ax, ay, az [m/s^2] (inertial axes).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.run.checks import non_negative
from pipeline.data import Truth
from pipeline.run.seeding import run_generators

STATE_NAMES = ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")


class PiecewiseAcceleration3D:
    """Constant-acceleration kinematics over each scan interval, the acceleration piecewise constant in time.

    The acceleration *in force at time t* is that of the segment with ``t_start <= t < t_end``
    (zero where no segment covers t). Over the interval (k-1, k] the target moves with the
    acceleration in force at time k-1, exactly::

        p_k = p_{k-1} + v_{k-1} dt + a_{k-1} dt^2 / 2,    v_k = v_{k-1} + a_{k-1} dt

    so with the study-000 segment [40, 60, 15, -10, -5] the target accelerates during [40, 60):
    the first scan that shows it is k = 41 and the velocity is constant again from k = 60 on.

    The state's ax, ay, az at scan k and the label ``acceleration`` (R, K, 1, 3) are, with the
    default ``acceleration_at_scan="in_force"``, the acceleration in force at time k, i.e. the one
    applied over (k, k+1] (so scan 40 already carries the maneuver, scan 60 no longer does). No
    causal filter can know it at scan 40: that step's acceleration error is unavoidable. With
    ``"last_interval"`` they are instead the acceleration applied over (k-1, k], the one the data
    up to scan k reflect (scans 41..60 carry the maneuver; scan 0 takes the in-force value). With
    ``process_noise_std`` > 0, a white Gaussian acceleration w_k ~ N(0, std^2 I3), drawn per run
    and per interval and held over (k, k+1], is added to the profile; the state and the label
    then hold the acceleration actually applied (profile + w_k). The default 0 gives the
    deterministic truth of the paper.

    Parameters
    ----------
    initial_position : (x, y, z) at t = 0 [m]
    initial_velocity : (vx, vy, vz) at t = 0 [m/s]
    segments : list of [t_start, t_end, ax, ay, az] [s, s, m/s^2 x3]; half-open [t_start, t_end),
        must not overlap
    duration : last scan time [s]; scans at t = 0, dt, ..., duration (duration / dt + 1 scans)
    dt : scan period [s]
    process_noise_std : std of w_k per axis [m/s^2]
    acceleration_at_scan : in_force | last_interval: which acceleration the state and the label
        give at each scan (above); the kinematics are the same
    """

    def __init__(self, initial_position: Sequence[float], initial_velocity: Sequence[float],
                 segments: Sequence[Sequence[float]] = (), duration: float = 100.0, dt: float = 1.0,
                 process_noise_std: float = 0.0, acceleration_at_scan: str = "in_force") -> None:
        if len(initial_position) != 3:
            raise ValueError(f"initial_position: {list(initial_position)} must be [x, y, z] in m")
        if len(initial_velocity) != 3:
            raise ValueError(f"initial_velocity: {list(initial_velocity)} must be [vx, vy, vz] in m/s")
        if not np.all(np.isfinite(np.asarray(initial_position, dtype=float))):
            raise ValueError(f"initial_position: {list(initial_position)} must be finite")
        if not np.all(np.isfinite(np.asarray(initial_velocity, dtype=float))):
            raise ValueError(f"initial_velocity: {list(initial_velocity)} must be finite")
        if not dt > 0:
            raise ValueError(f"dt: {dt} must be > 0 s")
        steps = float(duration) / float(dt)
        if not abs(steps - round(steps)) < 1e-9 * max(1.0, steps):
            raise ValueError(f"duration: {duration} s is not a whole number of scan periods dt = {dt} s")
        if round(steps) < 2:
            raise ValueError(f"duration: {duration} s must be >= 2 dt = {2 * dt} s (two-point initialisation "
                             f"needs scans 0 and 1, and one more to filter)")
        non_negative("process_noise_std", process_noise_std, "m/s^2")
        if acceleration_at_scan not in ("in_force", "last_interval"):
            raise ValueError(f"acceleration_at_scan: {acceleration_at_scan!r} is not one of ['in_force', "
                             f"'last_interval']")
        self.acceleration_at_scan = acceleration_at_scan
        self.initial_position = np.asarray(initial_position, dtype=float)
        self.initial_velocity = np.asarray(initial_velocity, dtype=float)
        self.dt = float(dt)
        self.steps = int(round(steps))
        self.duration = self.steps * self.dt
        self.process_noise_std = float(process_noise_std)
        self.time = np.arange(self.steps + 1) * self.dt
        self.segments = [self._segment(i, seg) for i, seg in enumerate(segments)]
        order = sorted(range(len(self.segments)), key=lambda i: self.segments[i][0])
        for i, j in zip(order, order[1:]):
            if self.segments[j][0] < self.segments[i][1]:
                raise ValueError(f"segments[{i}] and segments[{j}]: [{self.segments[i][0]}, {self.segments[i][1]}) "
                                 f"and [{self.segments[j][0]}, {self.segments[j][1]}) overlap; give each time "
                                 f"one acceleration")
        # the profile at each scan time; a tolerance of 1e-9 dt keeps k * dt on the right side of
        # a boundary that is a whole number of periods (e.g. 40 with dt = 0.1)
        eps = 1e-9 * self.dt
        self.acceleration = np.zeros((self.steps + 1, 3))
        for t0, t1, a in self.segments:
            inside = (self.time >= t0 - eps) & (self.time < t1 - eps)
            self.acceleration[inside] = a

    @staticmethod
    def _segment(i: int, seg: Sequence[float]) -> tuple[float, float, np.ndarray]:
        if len(seg) != 5:
            raise ValueError(f"segments[{i}]: {list(seg)} must be [t_start, t_end, ax, ay, az]")
        t0, t1 = float(seg[0]), float(seg[1])
        values = np.asarray(seg[2:], dtype=float)
        if not (np.isfinite(t0) and np.isfinite(t1) and 0 <= t0 < t1):
            raise ValueError(f"segments[{i}]: times {seg[0]}..{seg[1]} must satisfy 0 <= t_start < t_end")
        if not np.all(np.isfinite(values)):
            raise ValueError(f"segments[{i}]: acceleration {list(seg[2:])} must be finite")
        return t0, t1, values

    def generate(self, runs: int, seed: int) -> Truth:
        K = self.steps + 1
        dt = self.dt
        accel = np.broadcast_to(self.acceleration, (runs, K, 3)).copy()
        if self.process_noise_std > 0:
            noise = np.stack([g.standard_normal((K, 3)) for g in run_generators(seed, "scenario", runs)])
            accel = accel + self.process_noise_std * noise
        pos = np.empty((runs, K, 3))
        vel = np.empty((runs, K, 3))
        pos[:, 0] = self.initial_position
        vel[:, 0] = self.initial_velocity
        for k in range(1, K):
            a = accel[:, k - 1]
            pos[:, k] = pos[:, k - 1] + vel[:, k - 1] * dt + 0.5 * a * dt**2
            vel[:, k] = vel[:, k - 1] + a * dt
        shown = accel
        if self.acceleration_at_scan == "last_interval":     # scan k shows the interval (k-1, k]; scan 0 (k, k+1]
            shown = np.concatenate([accel[:, :1], accel[:, :-1]], axis=1)
        state = np.concatenate([pos, vel, shown], axis=-1)
        return Truth(self.time.copy(), state[:, :, None, :], STATE_NAMES, {"acceleration": shown[:, :, None, :].copy()})
