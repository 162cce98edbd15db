"""In-memory stage outputs: small frozen dataclasses of numpy arrays batched over runs.

Shapes: R runs, K scans, T targets, D detection slots per scan, n state size, m measurement size.
These are what stages pass to each other; ``pipeline.storage.schemas`` turns them into Parquet tables
(one row per run x step x object) and back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np


@dataclass(frozen=True)
class Truth:
    """time (K,); state (R, K, T, n); labels: name -> (R, K, T, ...) e.g. the true acceleration."""

    time: np.ndarray
    state: np.ndarray
    state_names: tuple[str, ...]
    labels: Mapping[str, np.ndarray] = field(default_factory=dict)

    @property
    def runs(self) -> int:
        return self.state.shape[0]


@dataclass(frozen=True)
class Detections:
    """Measurements of every scan, with their origin.

    time (K,), sensor (K,) which sensor scans at k; z (R, K, D, m) NaN where nothing was
    detected; noise_covariance (R, K, D, m, m) what the sensor reports as its noise;
    target (R, K, D) the true origin (-1 clutter); detected (R, K, D) False for a miss;
    measurement_units one unit per measurement name (empty: not stated, e.g. all metres).
    """

    time: np.ndarray
    sensor: np.ndarray
    z: np.ndarray
    noise_covariance: np.ndarray
    target: np.ndarray
    detected: np.ndarray
    measurement_names: tuple[str, ...]
    measurement_units: tuple[str, ...] = ()

    @property
    def runs(self) -> int:
        return self.z.shape[0]
