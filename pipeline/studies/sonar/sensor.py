"""Own-ship sonar: a passive array (bearing only) and an active sonar (bearing and range) switched
on a schedule (study 003, spec 003 "Model" and "Scenarios"; literature notes section 3.3).

Bearing from north, clockwise, with x = east: beta = atan2(rx, ry) of the relative position
r = target minus own-ship (literature notes 3.2), wrapped into (-pi, pi]; range = |r|.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.run.checks import non_negative
from pipeline.data import Detections, Truth
from pipeline.run.seeding import run_generators
from pipeline.sensors import wrap_angle

MEASUREMENT_NAMES = ("bearing", "range")
MEASUREMENT_UNITS = ("rad", "m")
PASSIVE, ACTIVE = 0, 1          # Detections.sensor: the passive array, the active sonar
TIME_TOLERANCE = 1e-9           # [s] a scan time this close to an interval edge counts as on it


class ActivePassiveSonar:
    """One scan per truth time: ACTIVE (bearing and range) at a scan inside an active interval,
    PASSIVE (bearing only) otherwise (spec 003: case 1 active 0-500 s; case 2 active 0-500,
    2500-3000 and 5000-5500 s).

    An active interval [start, end) includes its start and excludes its end (to 1e-9 s).

    z = (atan2(rx, ry) + sigma_beta n_1 wrapped into (-pi, pi], |r| + sigma_r n_2), with
    (n_1, n_2) standard normal from ``run_generators(seed, "measure", R)``, drawn as (K, T, 2) per
    run (the same stream as (K, 2) for the single relative state, T = 1) at every scan whatever the
    schedule, so the noise does not depend on it and run r depends only on (seed, r). At passive
    scans the range is NaN.

    ``Detections``: time = truth.time; sensor (K,) = 1 (active sonar) at active scans, 0 (passive
    array) at passive scans; z (R, K, T, 2) = (bearing, range), one slot per truth object (T = 1
    for ``SonarEncounter``); noise_covariance (R, K, T, 2, 2) = diag(bearing_std^2, range_std^2)
    at EVERY scan (the sensor's stated noise; a missing range
    is marked by z's NaN only, so a filter takes the [0, 0] entry at passive scans); target the
    slot's object index (0); detected True.

    Parameters
    ----------
    active_intervals : list of [start, end] [s], start < end, sorted and not overlapping
        (one may end where the next starts); empty: passive throughout
    bearing_std_deg : bearing noise std [deg] (>= 0; stored as ``bearing_std`` in rad)
    range_std : range noise std [m] (>= 0)
    """

    produces = "sonar_bearing_range"          # filters.base.MEASUREMENT_KINDS

    def __init__(self, active_intervals: Sequence[Sequence[float]] = ((0.0, 500.0),),
                 bearing_std_deg: float = 1.0, range_std: float = 10.0) -> None:
        intervals: list[tuple[float, float]] = []
        for i, interval in enumerate(active_intervals):
            key = f"active_intervals[{i}]"
            try:
                start, end = (float(v) for v in interval)
            except (TypeError, ValueError):
                raise ValueError(f"{key}: {interval!r} must be [start, end] in s") from None
            if not (np.isfinite(start) and np.isfinite(end) and start < end):
                raise ValueError(f"{key}: {interval!r} must be finite [start, end] in s with start < end")
            if intervals and start < intervals[-1][1]:
                raise ValueError(f"{key}: {interval!r} must start at or after {intervals[-1][1]:g} s, the end of "
                                 f"active_intervals[{i - 1}]; intervals must be sorted and not overlap")
            intervals.append((start, end))
        self.active_intervals = intervals
        self.bearing_std = np.radians(non_negative("bearing_std_deg", bearing_std_deg, "deg"))
        self.range_std = non_negative("range_std", range_std, "m")

    def is_active(self, time: np.ndarray) -> np.ndarray:
        """bool array of ``time``'s shape: True where a scan at that time [s] is active."""
        t = np.asarray(time, dtype=float)
        active = np.zeros(t.shape, dtype=bool)
        for start, end in self.active_intervals:
            active |= (t >= start - TIME_TOLERANCE) & (t < end - TIME_TOLERANCE)
        return active

    def measure(self, truth: Truth, seed: int) -> Detections:
        """(bearing, range) of every scan of ``truth`` (state names starting ("x", "y"): the
        relative position target minus own-ship, as ``SonarEncounter`` gives)."""
        if tuple(truth.state_names[:2]) != ("x", "y"):
            raise ValueError(f"truth state_names: {list(truth.state_names)} must start with ('x', 'y') "
                             f"(the relative position) for ActivePassiveSonar")
        R, K, T, _ = truth.state.shape
        time = np.asarray(truth.time, dtype=float)
        active = self.is_active(time)
        rx, ry = truth.state[..., 0], truth.state[..., 1]                                    # (R, K, T)
        noise = np.stack([g.standard_normal((K, T, 2)) for g in run_generators(seed, "measure", R)])
        bearing = wrap_angle(np.arctan2(rx, ry) + self.bearing_std * noise[..., 0])
        distance = np.hypot(rx, ry) + self.range_std * noise[..., 1]
        z = np.stack([bearing, np.where(active[None, :, None], distance, np.nan)], axis=-1)   # (R, K, T, 2)
        cov = np.diag([self.bearing_std ** 2, self.range_std ** 2])
        return Detections(
            time=time.copy(), sensor=np.where(active, ACTIVE, PASSIVE).astype(int), z=z,
            noise_covariance=np.broadcast_to(cov, (R, K, T, 2, 2)).copy(),
            target=np.broadcast_to(np.arange(T), (R, K, T)).copy(), detected=np.ones((R, K, T), dtype=bool),
            measurement_names=MEASUREMENT_NAMES, measurement_units=MEASUREMENT_UNITS,
        )
