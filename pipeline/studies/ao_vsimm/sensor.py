"""A sensor that measures the Cartesian position with white Gaussian noise (seed 001 eq 7)."""

from __future__ import annotations

import numpy as np

from pipeline.run.checks import positive
from pipeline.data import Detections, Truth
from pipeline.run.seeding import run_generators


class PositionSensor:
    """z_k = (x, y) + v_k, v_k ~ N(0, noise_std^2 I2), every scan, every target, no misses."""

    produces = "position_xy"          # filters.base.MEASUREMENT_KINDS

    def __init__(self, noise_std: float = 20.0, sensor_id: int = 0) -> None:
        positive("noise_std", noise_std, "m")
        self.noise_std = float(noise_std)
        self.sensor_id = int(sensor_id)

    def measure(self, truth: Truth, seed: int) -> Detections:
        R, K, T, _ = truth.state.shape
        index = [truth.state_names.index("x"), truth.state_names.index("y")]
        noise = np.stack([g.standard_normal((K, T, 2)) for g in run_generators(seed, "measure", R)])
        z = truth.state[..., index] + self.noise_std * noise
        cov = np.broadcast_to(self.noise_std**2 * np.eye(2), (R, K, T, 2, 2)).copy()
        return Detections(
            time=truth.time, sensor=np.full(K, self.sensor_id), z=z, noise_covariance=cov,
            target=np.broadcast_to(np.arange(T), (R, K, T)).copy(), detected=np.ones((R, K, T), dtype=bool),
            measurement_names=("x", "y"),
        )
