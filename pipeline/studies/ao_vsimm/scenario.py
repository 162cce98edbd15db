"""A planar target driven by a piecewise-constant acceleration profile (seed 001 eq 12)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.models import acceleration_input_gain, constant_velocity_transition
from pipeline.run.checks import non_negative
from pipeline.data import Truth
from pipeline.run.seeding import run_generators


class PiecewiseAccelerationScenario:
    """x_k = F x_{k-1} + Gamma (a_k + w_k), k = 1..steps, with a_k from ``segments``.

    Parameters
    ----------
    initial_state : (x, vx, y, vy) at k = 0 [m, m/s]
    segments : list of [first_step, last_step, ax, ay]; steps not covered have a = 0; the
        profile is cut at ``steps``
    steps : last scan index (the scenario has steps + 1 scans, k = 0..steps)
    dt : scan period [s]
    process_noise_std : std of w_k [m/s^2]; 0 gives the deterministic profile of the paper
    """

    def __init__(self, initial_state: Sequence[float], segments: Sequence[Sequence[float]], steps: int = 200,
                 dt: float = 1.0, process_noise_std: float = 0.0) -> None:
        if len(initial_state) != 4:
            raise ValueError(f"initial_state: {list(initial_state)} must be [x, vx, y, vy]")
        if int(steps) < 2:
            raise ValueError(f"steps: {steps} must be >= 2 (two-point initialisation needs scans 0 and 1)")
        if not dt > 0:
            raise ValueError(f"dt: {dt} must be > 0 s")
        non_negative("process_noise_std", process_noise_std, "m/s^2")
        self.initial_state = np.asarray(initial_state, dtype=float)
        self.steps = int(steps)
        self.dt = float(dt)
        self.process_noise_std = float(process_noise_std)
        self.acceleration = np.zeros((self.steps + 1, 2))
        for i, seg in enumerate(segments):
            if len(seg) != 4:
                raise ValueError(f"segments[{i}]: {list(seg)} must be [first_step, last_step, ax, ay]")
            k0, k1 = int(seg[0]), int(seg[1])
            if not 1 <= k0 <= k1:
                raise ValueError(f"segments[{i}]: steps {k0}..{k1} must satisfy 1 <= first_step <= last_step")
            # a profile longer than the horizon is cut at `steps` (so steps=40 gives a quick run)
            self.acceleration[k0:min(k1, self.steps) + 1] = [float(seg[2]), float(seg[3])]

    def generate(self, runs: int, seed: int) -> Truth:
        F = constant_velocity_transition(self.dt)
        G = acceleration_input_gain(self.dt)
        K = self.steps + 1
        accel = np.broadcast_to(self.acceleration, (runs, K, 2)).copy()
        if self.process_noise_std > 0:
            noise = np.stack([g.standard_normal((K, 2)) for g in run_generators(seed, "scenario", runs)])
            accel_driven = accel + self.process_noise_std * noise
        else:
            accel_driven = accel
        x = np.empty((runs, K, 4))
        x[:, 0] = self.initial_state
        for k in range(1, K):
            x[:, k] = x[:, k - 1] @ F.T + accel_driven[:, k] @ G.T
        time = np.arange(K) * self.dt
        return Truth(time, x[:, :, None, :], ("x", "vx", "y", "vy"), {"acceleration": accel[:, :, None, :]})
