"""Many planar constant-velocity targets started on a grid (study 002, spec 002 "Scenario").

State per target, in this order: x, y [m], vx, vy [m/s] (seed 002 eq 5: H = [I2 0]).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.bias import STATE_NAMES, dcwna_process_noise  # seed 002 eqs 5, 43, shared with the filters
from pipeline.data import Truth
from pipeline.run.seeding import run_generators


class ConstantVelocityGrid:
    """T targets, one at every (x, y) of ``x_positions`` x ``y_positions``, all with ``velocity``;
    x_k = Phi(dt) x_{k-1} + w_k, w_k ~ N(0, Q(dt)) (seed 002 eqs 42-43), k = 1..K-1.

    Targets are numbered (their order along the target axis T) by distance from
    ``numbering_origin`` ascending, ties (to 1 micrometre) broken by the azimuth
    atan2(dy, dx) from ``numbering_origin`` ascending: with the origin at sensor 1, target 0
    is the nearest to sensor 1 and target T-1 the farthest (spec 002: "target 1 nearest
    sensor 1, target 32 farthest"). ``initial_states`` (T, 4) holds the starts in that order.

    The state at k = 0 is exactly the initial state (no noise). w_k is drawn exactly,
    w_k = L n_k with L L' = Q(dt) and n_k standard normal, from one generator per run
    (``run_generators(seed, "scenario", runs)``, shape (K-1, T, 4) per run), so run r depends
    only on (seed, r). ``process_noise_density`` = 0 gives straight lines and draws nothing.

    Parameters
    ----------
    x_positions, y_positions : grid of start positions [m]
    velocity : (vx, vy) of every target [m/s]
    duration : last scan time [s]; scans at t = 0, dt, ..., duration (duration / dt + 1 scans)
    dt : truth sampling period [s]
    process_noise_density : q of eq 43 [m^2/s^3]
    numbering_origin : (x, y) the targets are numbered from [m] (sensor 1's position)
    """

    def __init__(self, x_positions: Sequence[float], y_positions: Sequence[float],
                 velocity: Sequence[float] = (20.0, 20.0), duration: float = 200.0, dt: float = 0.5,
                 process_noise_density: float = 6.0, numbering_origin: Sequence[float] = (0.0, 0.0)) -> None:
        for key, grid in (("x_positions", x_positions), ("y_positions", y_positions)):
            values = np.asarray(grid, dtype=float)
            if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
                raise ValueError(f"{key}: {list(np.atleast_1d(grid))} must be a non-empty list of finite "
                                 f"positions in m")
        for key, value, unit in (("velocity", velocity, "[vx, vy] in m/s"),
                                 ("numbering_origin", numbering_origin, "[x, y] in m")):
            if len(value) != 2 or not np.all(np.isfinite(np.asarray(value, dtype=float))):
                raise ValueError(f"{key}: {list(value)} must be a finite {unit}")
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: {dt} must be > 0 s")
        if not (np.isfinite(duration) and duration >= dt):
            raise ValueError(f"duration: {duration} must be >= dt = {dt} s")
        steps = float(duration) / float(dt)
        if not abs(steps - round(steps)) <= 1e-9 * steps:
            raise ValueError(f"duration: {duration} s must be a whole number of scan periods dt = {dt} s")
        if not (np.isfinite(process_noise_density) and process_noise_density >= 0):
            raise ValueError(f"process_noise_density: {process_noise_density} must be >= 0 m^2/s^3")
        self.dt = float(dt)
        self.steps = int(round(steps))
        self.duration = self.steps * self.dt
        self.process_noise_density = float(process_noise_density)
        self.velocity = np.asarray(velocity, dtype=float)
        self.numbering_origin = np.asarray(numbering_origin, dtype=float)

        gx, gy = np.meshgrid(np.asarray(x_positions, dtype=float), np.asarray(y_positions, dtype=float),
                             indexing="ij")
        positions = np.stack([gx.ravel(), gy.ravel()], axis=-1)
        delta = positions - self.numbering_origin
        distance = np.round(np.hypot(delta[:, 0], delta[:, 1]), 6)      # ties to 1 micrometre
        azimuth = np.arctan2(delta[:, 1], delta[:, 0])
        order = np.lexsort((azimuth, distance))
        self.initial_states = np.concatenate(
            [positions[order], np.broadcast_to(self.velocity, (len(order), 2))], axis=-1)

    @property
    def targets(self) -> int:
        return self.initial_states.shape[0]

    def generate(self, runs: int, seed: int) -> Truth:
        K, T, dt = self.steps + 1, self.targets, self.dt
        x = np.empty((runs, K, T, 4))
        x[:, 0] = self.initial_states                                      # k = 0: exact, no noise
        if self.process_noise_density > 0:
            L = np.linalg.cholesky(dcwna_process_noise(dt, self.process_noise_density))   # exact, eq 43
            n = np.stack([g.standard_normal((K - 1, T, 4)) for g in run_generators(seed, "scenario", runs)])
            w = n @ L.T                                                    # (R, K-1, T, 4)
        else:
            w = np.zeros((runs, K - 1, T, 4))
        # x_k = Phi x_{k-1} + w_k (eq 42, Phi = cv_transition(dt)) as running sums over k (each sum adds the same terms in the
        # same order as the recursion): v_k = v_{k-1} + w^v_k, p_k = p_{k-1} + (dt v_{k-1} + w^p_k)
        x[:, 1:, :, 2:] = w[..., 2:]
        np.cumsum(x[..., 2:], axis=1, out=x[..., 2:])
        x[:, 1:, :, :2] = dt * x[:, :-1, :, 2:] + w[..., :2]
        np.cumsum(x[..., :2], axis=1, out=x[..., :2])
        time = np.arange(K) * dt
        return Truth(time, x, STATE_NAMES)
