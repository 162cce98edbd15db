"""What every estimator consumes and returns: plain numpy arrays batched over Monte Carlo runs.

The leading axis of every array is the run axis ``R``; the second is the scan axis ``K``.
Nothing here knows about Hydra, Parquet or Rerun, so a filter can be driven from a
notebook with arrays built by hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Protocol, Sequence

import numpy as np


@dataclass(frozen=True)
class MeasurementSeries:
    """One stream of scans, batched over runs.

    Attributes
    ----------
    time : (K,) float
        Scan times [s]. Asynchronous sensors interleave their scans on this axis.
    z : (R, K, m) float
        Measured values; NaN where ``detected`` is False.
    noise_covariance : (m, m) or (R, K, m, m) float
        Measurement noise covariance the filter should assume.
    detected : (R, K) bool
        False marks a missed detection (no measurement at that scan).
    sensor : (K,) int
        Which sensor produced each scan.
    sensor_position : (d,) float or None
        Position of a static sensor in the truth's frame, for measurements taken relative to it
        (a radar's range and angles); None means the origin.
    """

    time: np.ndarray
    z: np.ndarray
    noise_covariance: np.ndarray
    detected: np.ndarray
    sensor: np.ndarray
    sensor_position: np.ndarray | None = None

    @property
    def runs(self) -> int:
        return self.z.shape[0]

    @property
    def scans(self) -> int:
        return self.z.shape[1]

    def select(self, runs: Sequence[int]) -> "MeasurementSeries":
        """The same scans for a subset of runs (a chunk of the Monte Carlo)."""
        index = np.asarray(runs, dtype=int)
        cov = self.noise_covariance
        return replace(self, z=self.z[index], detected=self.detected[index],
                       noise_covariance=cov[index] if cov.ndim == 4 else cov)


@dataclass(frozen=True)
class TrackEstimate:
    """A filter's output, one estimate per run and scan.

    Attributes
    ----------
    time : (K,) float
    state : (R, K, n) float; NaN before the filter has an estimate.
    covariance : (R, K, n, n) float
    extras : mapping of name -> (R, K, ...) array
        Algorithm-specific per-step outputs (mode probabilities, active model group,
        models evaluated, input estimates, ...). They become columns of the estimates table.
    compute_seconds : float
        Wall time of the filtering itself (no I/O), measured by the estimator.
    """

    time: np.ndarray
    state: np.ndarray
    covariance: np.ndarray
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    compute_seconds: float = float("nan")

    @classmethod
    def concat_runs(cls, parts: Sequence["TrackEstimate"]) -> "TrackEstimate":
        """Chunks of runs (in run order) as one estimate; compute time is the sum of the chunks'."""
        first = parts[0]
        return cls(first.time, np.concatenate([p.state for p in parts]),
                   np.concatenate([p.covariance for p in parts]),
                   {name: np.concatenate([np.asarray(p.extras[name]) for p in parts]) for name in first.extras},
                   float(sum(p.compute_seconds for p in parts)))


class Estimator(Protocol):
    """A configured filter variant. Built from a config node with ``_target_``."""

    name: str

    def run(self, measurements: MeasurementSeries) -> TrackEstimate: ...
