"""The multi-target contract: sets of detections in, sets of tracks out, batched over Monte Carlo runs.

Every array is padded to the largest set in the batch, so one array holds every run's ragged sets:

- R runs, K scans, D detection slots per scan, m measurement size;
- M track slots per scan, n state size.

A slot beyond a scan's count holds NaN (floats), -1 (ids) or False (flags). The true origin of a
detection is kept by the study for scoring and never given to a tracker.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar, Mapping

import numpy as np

#: the measurement kind a multi-target tracker takes (see ``filters.base.MEASUREMENT_KINDS``)
POSITION_SETS = "position_xy_sets"


@dataclass(frozen=True)
class DetectionSets:
    """Unlabelled detections of every run and scan.

    time (K,) [s]; z (R, K, D, m) NaN in empty slots; count (R, K) the number of filled slots of
    each scan (filled slots come first); noise_covariance (m, m) the sensor's measurement noise R;
    state_names the names of the state the trackers estimate (e.g. ("x", "vx", "y", "vy")),
    position_index the indices of the measured position in that state.
    """

    time: np.ndarray
    z: np.ndarray
    count: np.ndarray
    noise_covariance: np.ndarray
    state_names: tuple[str, ...]
    position_index: tuple[int, ...]

    @property
    def runs(self) -> int:
        return self.z.shape[0]

    @property
    def steps(self) -> int:
        return self.z.shape[1]


@dataclass(frozen=True)
class TrackSets:
    """What a multi-target tracker reports at every run and scan.

    state (R, K, M, n) and covariance (R, K, M, n, n), NaN in empty slots; track_id (R, K, M) int64,
    -1 in empty slots, unique within a run and never reused; confirmed (R, K, M) bool, the tracks
    the tracker reports as targets (a GM-PHD's extracted components); existence (R, K, M) the
    probability of existence or the component weight where the tracker has one, NaN otherwise;
    extras: per-scan arrays (R, K, ...) such as ``cardinality`` (a PHD's expected count) or
    ``hypotheses`` (association cost); compute_seconds the filtering time of the whole batch.
    """

    time: np.ndarray
    state: np.ndarray
    covariance: np.ndarray
    track_id: np.ndarray
    confirmed: np.ndarray
    existence: np.ndarray
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    compute_seconds: float = float("nan")

    @property
    def runs(self) -> int:
        return self.state.shape[0]


class MultiTargetTracker(ABC):
    """A tracker of an unknown number of targets from unlabelled detections (association, track
    management or a random-finite-set filter), run over every Monte Carlo run at once."""

    accepts: ClassVar[frozenset[str]] = frozenset({POSITION_SETS})
    name: str = "tracker"

    @abstractmethod
    def run(self, detections: DetectionSets) -> TrackSets:
        """Track every run of ``detections``; the result has the same R and K."""
