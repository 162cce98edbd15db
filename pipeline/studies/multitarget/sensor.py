"""Unlabelled position detections of many targets in clutter (Vo & Ma 2006, Section V-A: linear
Gaussian observations, P_D, Poisson clutter uniform over the surveillance region).

Each scan: every target that exists is detected with probability ``detection_probability``; a
detection is z = H x + v, H picking (x, y) of (x, vx, y, vy), v ~ N(0, R) with R =
noise_std^2 I_2 (Vo & Ma: 10^2 I m^2); the clutter is a Poisson number of points of mean
``clutter_density`` x the region's area per scan (lambda), uniform over ``region``. The detections of a scan are put in random
order (so a slot says nothing of its origin), filled slots first.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.multitarget import POSITION_SETS
from pipeline.data import Detections, Truth
from pipeline.run.checks import non_negative, positive
from pipeline.run.seeding import run_generators
from pipeline.studies.multitarget.scenario import POSITION_INDEX, STATE_NAMES, _region

MEASUREMENT_NAMES = ("x", "y")
MEASUREMENT_UNITS = ("m", "m")
CLUTTER = -1                    # Detections.target of a clutter point


class ClutteredPositions:
    """Position detections with misses and Poisson clutter (module docstring).

    ``Detections``: z (R, K, D, 2), D the most detections of any scan of any run, NaN beyond a
    scan's count; target (R, K, D) the true origin (the target index, ``CLUTTER`` = -1 for clutter,
    -1 in empty slots too); detected (R, K, D) True in the filled slots; noise_covariance the
    constant R broadcast to (R, K, D, 2, 2) (a read-only view, no copy).

    Draws per run (``run_generators(seed, "measure", R)``), in this order whatever the settings:
    uniform (K, T) detection draws, standard normal (K, T, 2) noise, Poisson (K,) clutter counts,
    uniform (sum of counts, 2) clutter positions, uniform (K, T + max count) sort keys of the
    scan's order. Run r depends only on (seed, r).

    Parameters
    ----------
    detection_probability : P_D in [0, 1] (Vo & Ma: 0.98)
    clutter_density : clutter points per m^2 and scan, >= 0 (Vo & Ma: 12.5e-6, lambda = 50 over the
        region; the literature's lambda = 10 to 66 is 2.5e-6 to 16.5e-6 here); lambda = ``clutter_rate``
    noise_std : the position noise standard deviation per axis [m] (Vo & Ma: 10)
    region : [[x_min, x_max], [y_min, y_max]] of the clutter [m] (Vo & Ma: [-1000, 1000]^2)
    """

    produces = POSITION_SETS          # filters.base.MEASUREMENT_KINDS

    def __init__(self, detection_probability: float = 0.98, clutter_density: float = 2.5e-6, noise_std: float = 10.0,
                 region: Sequence[Sequence[float]] = ((-1000.0, 1000.0), (-1000.0, 1000.0))) -> None:
        p = non_negative("detection_probability", detection_probability, "(a probability)")
        if p > 1:
            raise ValueError(f"detection_probability: {detection_probability!r} must be a probability in [0, 1]")
        self.detection_probability = p
        self.clutter_density = non_negative("clutter_density", clutter_density, "points per m^2 and scan")
        self.noise_std = positive("noise_std", noise_std, "m")
        self.region = _region(region)

    @property
    def noise_covariance(self) -> np.ndarray:
        return self.noise_std**2 * np.eye(2)

    @property
    def clutter_rate(self) -> float:
        """lambda, the mean clutter points per scan: the density times the region's area (Vo & Ma eq 20's kappa
        is the density)."""
        return self.clutter_density * float(np.prod(self.region[:, 1] - self.region[:, 0]))

    def measure(self, truth: Truth, seed: int) -> Detections:
        if tuple(truth.state_names) != STATE_NAMES:
            raise ValueError(f"truth state_names: {list(truth.state_names)} must be {list(STATE_NAMES)} for "
                             f"ClutteredPositions")
        R, K, T, _ = truth.state.shape
        position = truth.state[..., list(POSITION_INDEX)]                          # (R, K, T, 2)
        exists = np.all(np.isfinite(truth.state), axis=-1)
        low, width = self.region[:, 0], self.region[:, 1] - self.region[:, 0]
        per_run = []
        for g in run_generators(seed, "measure", R):
            hit = g.random((K, T))
            noise = g.standard_normal((K, T, 2))
            counts = g.poisson(self.clutter_rate, K)
            clutter = low + width * g.random((int(counts.sum()), 2))
            keys = g.random((K, T + int(counts.max(initial=0))))
            per_run.append((hit, noise, counts, clutter, keys))
        detected = exists & (np.stack([d[0] for d in per_run]) < self.detection_probability)        # (R, K, T)
        z_target = position + self.noise_std * np.stack([d[1] for d in per_run])
        counts = np.stack([d[2] for d in per_run])                                                 # (R, K)
        C = int(counts.max(initial=0))
        # candidate slots: T target slots then C clutter slots per scan; unused ones sort last
        z = np.full((R, K, T + C, 2), np.nan)
        origin = np.full((R, K, T + C), CLUTTER, dtype=np.int64)
        used = np.zeros((R, K, T + C), dtype=bool)
        z[:, :, :T] = np.where(detected[..., None], z_target, np.nan)
        origin[:, :, :T] = np.where(detected, np.arange(T), CLUTTER)
        used[:, :, :T] = detected
        keys = np.ones((R, K, T + C)) * 2.0
        for r, (_, _, n, points, key) in enumerate(per_run):
            slot = np.arange(C) < n[:, None]                                                       # (K, C)
            block = np.full((K, C, 2), np.nan)
            block[slot] = points                    # row-major over (k, slot): scan k's points in order
            z[r, :, T:] = block
            used[r, :, T:] = slot
            keys[r, :, :key.shape[1]] = key
        keys = np.where(used, keys, 2.0 + np.arange(T + C))                                        # unused last, in order
        order = np.argsort(keys, axis=-1, kind="stable")
        z = np.take_along_axis(z, order[..., None], axis=2)
        origin = np.take_along_axis(np.where(used, origin, CLUTTER), order, axis=2)
        used = np.take_along_axis(used, order, axis=2)
        D = max(int(used.sum(axis=-1).max(initial=0)), 1)
        z, origin, used = z[:, :, :D], origin[:, :, :D], used[:, :, :D]
        return Detections(time=np.asarray(truth.time, dtype=float).copy(), sensor=np.zeros(K, dtype=int), z=z,
                          noise_covariance=np.broadcast_to(self.noise_covariance, (R, K, D, 2, 2)),
                          target=origin, detected=used, measurement_names=MEASUREMENT_NAMES,
                          measurement_units=MEASUREMENT_UNITS)
