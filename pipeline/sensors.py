"""Sensors that more than one study uses. A 3-D radar: range, azimuth and elevation with white Gaussian noise
(seed 000, spec 000; the ADS-B study's radar too).

Angles in radians. Azimuth phi = atan2(dy, dx) from +x toward +y, wrapped into (-pi, pi];
elevation theta = atan2(dz, hypot(dx, dy)) from the x-y plane, where (dx, dy, dz) is the target
position relative to the radar.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.data import Detections, Truth
from pipeline.run.seeding import run_generators

MEASUREMENT_NAMES = ("range", "azimuth", "elevation")
MEASUREMENT_UNITS = ("m", "rad", "rad")


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap into (-pi, pi]."""
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi          # [-pi, pi)
    return np.where(w == -np.pi, np.pi, w)


def spherical(relative: np.ndarray) -> np.ndarray:
    """(..., 3) Cartesian position relative to the radar -> (..., 3) (range, azimuth, elevation)."""
    dx, dy, dz = relative[..., 0], relative[..., 1], relative[..., 2]
    horizontal = np.hypot(dx, dy)
    return np.stack([np.sqrt(horizontal**2 + dz**2), np.arctan2(dy, dx), np.arctan2(dz, horizontal)], axis=-1)


def cartesian(rae: np.ndarray) -> np.ndarray:
    """(..., 3) (range, azimuth, elevation) -> (..., 3) Cartesian position relative to the radar."""
    r, phi, theta = rae[..., 0], rae[..., 1], rae[..., 2]
    return np.stack([r * np.cos(theta) * np.cos(phi), r * np.cos(theta) * np.sin(phi), r * np.sin(theta)], axis=-1)


def conversion_jacobian(rae: np.ndarray) -> np.ndarray:
    """(..., 3) (r, phi, theta) -> (..., 3, 3) d(x, y, z)/d(r, phi, theta) (literature notes 2.1)."""
    r, phi, theta = rae[..., 0], rae[..., 1], rae[..., 2]
    cp, sp, ct, st = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
    zero = np.zeros_like(r)
    return np.stack([
        np.stack([ct * cp, -r * ct * sp, -r * st * cp], axis=-1),
        np.stack([ct * sp, r * ct * cp, -r * st * sp], axis=-1),
        np.stack([st, zero, r * ct], axis=-1),
    ], axis=-2)


class Radar3D:
    """z_k = (r, phi, theta)(p_k - position) + v_k, v_k ~ N(0, R_p), R_p = diag(range_std^2,
    azimuth_std^2, elevation_std^2); every scan, every target, no misses, no clutter.

    The noise is given as standard deviations: range_std [m], azimuth_std and elevation_std [rad]
    (seed 000: R_p = diag(100 m^2, 4.9e-5 rad^2, 3.6e-5 rad^2), i.e. 10 m, 7 mrad, 6 mrad). The
    measured azimuth is wrapped into (-pi, pi]; the measured elevation is left unwrapped (a
    target near the zenith is outside what this sensor models). Each detection reports
    ``noise_covariance`` = R_p. A std of 0 gives a noise-free channel (for tests; R_p is then
    singular, which a filter may refuse).

    Parameters
    ----------
    position : radar position [m] in the truth's inertial frame
    range_std, azimuth_std, elevation_std : noise standard deviations [m, rad, rad]
    sensor_id : the value of ``Detections.sensor`` at every scan
    max_range : the farthest range it sees [m]; None: no limit. This sensor never misses, so a
        target beyond it is a wrong geometry (a radar on another continent), refused by ``check_range``
        and by ``measure``, not a miss
    """

    produces = "range_azimuth_elevation"          # filters.base.MEASUREMENT_KINDS

    def __init__(self, position: Sequence[float] = (0.0, 0.0, 0.0), range_std: float = 10.0,
                 azimuth_std: float = float(np.sqrt(4.9e-5)), elevation_std: float = float(np.sqrt(3.6e-5)),
                 sensor_id: int = 0, max_range: float | None = None) -> None:
        if len(position) != 3 or not np.all(np.isfinite(np.asarray(position, dtype=float))):
            raise ValueError(f"position: {list(position)} must be a finite [x, y, z] in m")
        if max_range is not None and (isinstance(max_range, bool) or not np.isfinite(max_range) or max_range <= 0):
            raise ValueError(f"max_range: {max_range!r} must be a range > 0 m, or null (no limit)")
        self.max_range = None if max_range is None else float(max_range)
        for key, value, unit in (("range_std", range_std, "m"), ("azimuth_std", azimuth_std, "rad"),
                                 ("elevation_std", elevation_std, "rad")):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{key}: {value} must be a finite standard deviation >= 0 {unit}")
        self.position = np.asarray(position, dtype=float)
        self.std = np.array([range_std, azimuth_std, elevation_std], dtype=float)
        self.noise_covariance = np.diag(self.std**2)
        self.sensor_id = int(sensor_id)

    def check_range(self, xyz: np.ndarray, time: np.ndarray | None = None) -> None:
        """ValueError naming the farthest scan when a target position ``xyz`` ((K, 3), or (R, K, T, 3) runs x
        scans x targets) is beyond max_range."""
        if self.max_range is None:
            return
        distance = np.linalg.norm(np.asarray(xyz, dtype=float) - self.position, axis=-1)
        if np.nanmax(distance) > self.max_range:
            far = np.unravel_index(int(np.nanargmax(distance)), distance.shape)
            scan = int(far[0]) if distance.ndim == 1 else int(far[1])
            when = f"scan {scan}" + (f" (t = {float(time[scan]):g} s)" if time is not None else "")
            raise ValueError(f"max_range: the target is {float(distance[far]) / 1000:.1f} km from the radar at "
                             f"{when}, beyond its range of {self.max_range / 1000:g} km")

    def measure(self, truth: Truth, seed: int) -> Detections:
        R, K, T, _ = truth.state.shape
        index = [truth.state_names.index(n) for n in ("x", "y", "z")] if "z" in truth.state_names else None
        if index is None:
            raise ValueError(f"truth state_names {list(truth.state_names)} lack 'z'; Radar3D needs a 3-D target "
                             f"(x, y, z)")
        self.check_range(truth.state[..., index], truth.time)
        noise = np.stack([g.standard_normal((K, T, 3)) for g in run_generators(seed, "measure", R)])
        z = spherical(truth.state[..., index] - self.position) + self.std * noise
        z[..., 1] = wrap_angle(z[..., 1])
        cov = np.broadcast_to(self.noise_covariance, (R, K, T, 3, 3)).copy()
        return Detections(
            time=truth.time, sensor=np.full(K, self.sensor_id), z=z, noise_covariance=cov,
            target=np.broadcast_to(np.arange(T), (R, K, T)).copy(), detected=np.ones((R, K, T), dtype=bool),
            measurement_names=MEASUREMENT_NAMES, measurement_units=MEASUREMENT_UNITS,
        )

    def to_cartesian(self, detections: Detections) -> Detections:
        """The same detections as inertial Cartesian positions (x, y, z) with the first-order converted
        covariance J R_p J' (J at the measured values), for analyses that want positions."""
        z = detections.z
        converted = cartesian(z) + self.position
        J = conversion_jacobian(z)
        cov = J @ detections.noise_covariance @ np.swapaxes(J, -1, -2)
        return Detections(detections.time, detections.sensor, converted, cov, detections.target,
                          detections.detected, ("x", "y", "z"), ("m", "m", "m"))
