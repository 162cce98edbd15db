"""What every estimator consumes and returns: plain numpy arrays batched over Monte Carlo runs.

The leading axis of every array is the run axis ``R``; the second is the scan axis ``K``.
Nothing here knows about Hydra, Parquet or Rerun, so a filter can be driven from a
notebook with arrays built by hand.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from abc import ABC, abstractmethod
from typing import ClassVar, Mapping, Protocol, Sequence

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
    state_names : tuple of str or None
        The state layout the study evaluates (its truth's), for a filter that can write its estimate
        in any order (filters.tracker); None leaves the layout to the filter.
    run_ids : (R,) int or None
        Each run's index in the whole Monte Carlo (``select`` keeps them), for a filter that draws
        random numbers per run (a particle filter): run r's draws then do not depend on how the runs
        are chunked. None means 0..R-1.
    """

    time: np.ndarray
    z: np.ndarray
    noise_covariance: np.ndarray
    detected: np.ndarray
    sensor: np.ndarray
    sensor_position: np.ndarray | None = None
    state_names: tuple[str, ...] | None = None
    run_ids: np.ndarray | None = None

    @property
    def runs(self) -> int:
        return self.z.shape[0]

    @property
    def scans(self) -> int:
        return self.z.shape[1]

    def ids(self) -> np.ndarray:
        """(R,) each run's index in the whole Monte Carlo."""
        return np.arange(self.runs) if self.run_ids is None else np.asarray(self.run_ids, dtype=int)

    def select(self, runs: Sequence[int]) -> "MeasurementSeries":
        """The same scans for a subset of runs (a chunk of the Monte Carlo)."""
        index = np.asarray(runs, dtype=int)
        cov = self.noise_covariance
        return replace(self, z=self.z[index], detected=self.detected[index],
                       noise_covariance=cov[index] if cov.ndim == 4 else cov, run_ids=self.ids()[index])


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


# What a sensor produces and a filter takes. A sensor class declares ``produces`` (one kind), a filter
# class ``accepts`` (a set); the runner refuses a variant whose filter does not take what the
# experiment's sensor produces, before any stage. Add a kind here when a new sensor needs one.
MEASUREMENT_KINDS: dict[str, str] = {
    "position_xy": "Cartesian position (x, y) [m] with its noise covariance (a MeasurementSeries, m = 2)",
    "range_azimuth_elevation": "a static radar's range [m], azimuth and elevation [rad] relative to its "
                               "sensor_position (a MeasurementSeries, m = 3)",
    "biased_radar_reports": "several radars' range/azimuth reports of many targets with unknown sensor biases "
                            "(filters.bias.RadarReports)",
    "sonar_bearing_range": "a moving own-ship sonar's bearings, with range while active (filters.mgekf.SonarReports)",
    "sonobuoy_bearings": "drifting sonobuoys' bearings in clutter and an observer's bearings to the buoys "
                         "(filters.particle.BuoyReports)",
    "position_xy_sets": "unlabelled Cartesian position detections of an unknown number of targets in clutter, "
                        "padded over runs and scans (filters.multitarget.DetectionSets)",
}
# kinds carried by a MeasurementSeries: what a filter that declares nothing (the Estimator protocol) takes
SERIES_KINDS = frozenset({"position_xy", "range_azimuth_elevation"})


def accepted_kinds(filter_class: object, config: Mapping | None = None) -> frozenset[str]:
    """The measurement kinds a filter class takes: its ``accepts``, or, when it declares none, every
    kind a MeasurementSeries carries (the Estimator protocol's ``run(MeasurementSeries)``).

    A class whose kinds follow from its configuration (pipeline.stonesoup.StoneSoupFilter: from its
    measurement model's type) also answers ``accepts_config(config)`` for its variant's config node;
    given ``config``, that answer counts (None from it: the class's ``accepts``)."""
    hook = getattr(filter_class, "accepts_config", None)
    if config is not None and callable(hook):
        answer = hook(config)
        if answer is not None:
            return frozenset(answer)
    declared = getattr(filter_class, "accepts", None)
    return SERIES_KINDS if declared is None or not isinstance(declared, (set, frozenset, list, tuple)) \
        else frozenset(declared)


def produced_kind(sensor_class: object, config: Mapping | None = None) -> str | None:
    """The measurement kind a sensor class produces: its ``produces``, or, for a class whose kind follows
    from its configuration (pipeline.stonesoup.StoneSoupSensor: its measurement model), the answer of
    ``produces_config(config)`` for its config node. None: the sensor declares nothing."""
    hook = getattr(sensor_class, "produces_config", None)
    if config is not None and callable(hook):
        answer = hook(config)
        if answer is not None:
            return str(answer)
    declared = getattr(sensor_class, "produces", None)
    return declared if isinstance(declared, str) else None


class Estimator(Protocol):
    """A configured filter variant. Built from a config node with ``_target_``.

    ``accepts`` names the measurement kinds (MEASUREMENT_KINDS) its ``run`` takes; a class without
    it is taken to accept any MeasurementSeries kind.
    """

    name: str
    accepts: ClassVar[frozenset[str]]

    def run(self, measurements: MeasurementSeries) -> TrackEstimate: ...


class SingleTargetFilter(ABC):
    """The base of a filter of one target from one stream of scans (a ``MeasurementSeries``): subclass
    it, set ``name`` and ``accepts``, write ``run``. A walk-through with a complete example in a package
    of your own: docs/your-own-filter.md.

    The layout contract of the ``TrackEstimate`` that ``run`` returns (R runs, K scans; the pipeline
    checks it when the track stage ends and names the variant and the expected shape if it breaks):

    - ``time``: (K,), the measurements' ``time``.
    - ``state``: (R, K, n) with n = ``len(measurements.state_names)``, the components in that order
      (the study's truth's: study 001 ``x, vx, y, vy``; study 000 ``x, y, z, vx, vy, vz, ax, ay, az``),
      NaN for a component the filter does not estimate (a CV filter's accelerations) and at scans
      before it has an estimate. ``empty_estimate`` gives both arrays all NaN in that layout.
    - ``covariance``: (R, K, n, n), NaN in the rows and columns of the components it does not estimate.
    - ``extras``: name -> (R, K, ...) arrays, columns of the estimates table; ``nis`` (R, K) the
      normalised innovation squared nu' S^-1 nu with ``nis_dof`` (R, K) its degrees of freedom (the
      measurement size; NaN nis and 0 dof at a scan without a measurement) give the NIS metrics.
    - ``compute_seconds``: the wall time of the filtering itself (``time.perf_counter`` around it).

    Work on all runs at once (arrays with the run axis first); a loop over scans is fine, a loop over
    runs inside a scan is not (a compiled per-run loop is)."""

    name: str = "my filter"
    accepts: ClassVar[frozenset[str]] = SERIES_KINDS

    @abstractmethod
    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        """Filter every run of ``measurements``; the estimate in the layout above."""

    @staticmethod
    def empty_estimate(measurements: MeasurementSeries, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(state (R, K, n), covariance (R, K, n, n)), all NaN: n = ``len(measurements.state_names)``
        (or ``n`` where the series names no layout); fill the components the filter estimates."""
        names = measurements.state_names
        size = len(names) if names is not None else n
        if size is None:
            raise ValueError("empty_estimate: the measurements name no state layout (state_names is None); pass n")
        R, K = measurements.runs, measurements.scans
        return np.full((R, K, size), np.nan), np.full((R, K, size, size), np.nan)


def layout_problems(estimate: TrackEstimate, runs: int, scans: int, state_names: Sequence[str]) -> list[str]:
    """What breaks ``SingleTargetFilter``'s layout contract in ``estimate`` for ``runs`` x ``scans`` and
    the state ``state_names``: one sentence per array of the wrong shape ([] when it holds)."""
    n = len(state_names)
    expected = {"time": (scans,), "state": (runs, scans, n), "covariance": (runs, scans, n, n)}
    problems = []
    for name, shape in expected.items():
        got = np.shape(getattr(estimate, name))
        if tuple(got) != shape:
            problems.append(f"its {name} has shape {tuple(got)}, expected {shape}")
    for name, values in dict(estimate.extras).items():
        got = np.shape(values)
        if tuple(got[:2]) != (runs, scans):
            problems.append(f"its extras[{name!r}] has shape {tuple(got)}, expected ({runs}, {scans}, ...)")
    return problems


def usable_processors() -> int:
    """The processors this process may run on: its affinity mask where the system has one (Linux:
    a job pinned by ``taskset`` or a batch system's cgroup gets its share, not the machine's count),
    else the machine's count (macOS and Windows have no ``os.sched_getaffinity``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


ENGINES = ("numba", "numpy")     # a filter with a compiled loop: numba (the default) or its numpy reference


def checked_engine(engine: str, compiled: str) -> str:
    """``engine`` when it is one of ``ENGINES``; else a ValueError naming the value, what is allowed
    and what the compiled engine runs (``compiled``, e.g. "the compiled scan loop, filters/mgekf/kernel.py")."""
    if engine not in ENGINES:
        raise ValueError(f"engine: {engine!r} must be one of {list(ENGINES)} (numba: {compiled}; numpy: the "
                         f"vectorised reference)")
    return engine
