"""A filter variant made of Stone Soup components: ``pipeline.stonesoup.variant.StoneSoupFilter``.

The variant's YAML names Stone Soup classes with ``_target_`` (they are allowed without listing:
pipeline.run.config.COMPONENT_PACKAGES): a transition model, a measurement model, a predictor and an
updater given as ``_partial_: true`` (this class hands them their models), optionally an initiator or
a prior. The measurement model's type says which measurements the variant takes
(``LinearGaussian``: position_xy; ``CartesianToElevationBearingRange``: range_azimuth_elevation),
and the framework refuses it before any stage in an experiment whose sensor produces another kind.

Run: one Monte Carlo run at a time (Stone Soup filters one object at a time), the runs spread over
``workers`` processes. Run r's result depends only on run r: each worker filters whole runs with
the same code, and anything random (a particle filter's draws) is seeded per run from ``seed`` and
the run's index in the whole Monte Carlo (``MeasurementSeries.run_ids``), so the estimates are the
same bit for bit whatever the number of workers or the chunking of runs. Each detection is a Stone
Soup ``Detection`` carrying its measurement model: the configured one with the detection's reported
noise covariance (``noise_from_detections``) and, for a radar, the sensor's position as its
translation offset; a missed scan is predicted, not updated.

Start: by default the project's two-point start (filters.models.two_point_start on the first two
scans, converted to Cartesian positions for a radar, as filters.tracker.KalmanTracker does): the
estimate starts at scan 1, and a Stone Soup Kalman filter with the model of KalmanTracker gives
its estimates to rounding. ``prior`` (a Stone Soup state in the filter's layout) starts at scan 0
instead; ``initiator`` (a Stone Soup initiator, e.g. ``SimpleMeasurementInitiator``) at the first
detected scan. A particle predictor gets ``particles`` draws from a Gaussian start.

Output: the TrackEstimate our filters return, in the truth's state order
(``MeasurementSeries.state_names``; a component the filter lacks is NaN), NaN before the start,
with the ``nis`` / ``nis_dof`` extras of each update's innovation where the update has a Gaussian
measurement prediction.
"""

from __future__ import annotations

import functools
import pickle
import time
import zlib
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from filters.base import MeasurementSeries, TrackEstimate, usable_processors
from pipeline.stonesoup import require_stonesoup

# the kinds a StoneSoupFilter may take (a variant takes the one of its measurement model)
SUPPORTED_KINDS = frozenset({"position_xy", "range_azimuth_elevation"})
RANDOM_STREAM = zlib.crc32(b"stonesoup-filter")      # the spawn key of a run's draws
# by default (workers: null) a job of fewer run-scans is filtered in this process: about 7 s of Stone
# Soup's Kalman filter (0.4-0.5 ms a run-scan), about what the worker processes' start-up costs (5-7 s
# on the first call: fresh interpreters importing numpy, scipy and Stone Soup; benchmarks/bench_stonesoup.py)
SERIAL_BELOW = 15000


class StoneSoupFilter:
    """A Stone Soup predictor and updater as a filter variant (see the module docstring).

    Parameters
    ----------
    predictor : a Stone Soup predictor, or a partial of one (``_partial_: true``) that takes
        ``transition_model``
    updater : a Stone Soup updater, or a partial of one that takes ``measurement_model``
    transition_model : Stone Soup transition model (needed when ``predictor`` is a partial)
    measurement_model : Stone Soup measurement model; its type decides the measurement kind; its
        mapping must pick the positions of the filter's state. Default: the updater's
    state_names : the filter's state layout (its state vector's components by name: x, vx, y, vy...);
        default: told from a transition model that stacks one kinematic model per axis
        (pipeline.stonesoup.convert.infer_state_names)
    initiator : a Stone Soup initiator started on the first detected scan (instead of the two-point start)
    prior : a Stone Soup state at the first scan (instead of the two-point start); its timestamp is set
    noise_from_detections : each detection's measurement model takes the noise covariance the sensor
        reported with it (as our filters do); false keeps the configured model's
    start_acceleration_std : the two-point start's standard deviation of any acceleration component [m/s^2]
    particles : draws from a Gaussian start for a particle predictor
    workers : worker processes; null: the machine's CPUs; 1: in this process. Never more than the runs
    seed : the seed of anything random in the filter (per run, with the run's index)
    """

    accepts = SUPPORTED_KINDS          # the class's; an instance takes its measurement model's kind

    def __init__(self, predictor: Any, updater: Any, transition_model: Any = None, measurement_model: Any = None,
                 name: str = "Stone Soup", state_names: Sequence[str] | None = None, initiator: Any = None,
                 prior: Any = None, noise_from_detections: bool = True, start_acceleration_std: float = 5.0,
                 particles: int = 1000, workers: int | None = None, seed: int = 0) -> None:
        require_stonesoup()
        from stonesoup.predictor.base import Predictor
        from stonesoup.updater.base import Updater

        from pipeline.stonesoup.convert import infer_state_names, kind_of_model
        if initiator is not None and prior is not None:
            raise ValueError("initiator: give an initiator or a prior, not both (neither: the two-point start)")
        if isinstance(predictor, functools.partial):
            if transition_model is None:
                raise ValueError("transition_model: a predictor given as a partial (_partial_: true) needs the "
                                 "transition model to build it with")
            predictor = predictor(transition_model=transition_model)
        if not isinstance(predictor, Predictor):
            raise ValueError(f"predictor: {type(predictor).__name__} is not a Stone Soup predictor")
        transition_model = predictor.transition_model if transition_model is None else transition_model
        if measurement_model is None:
            measurement_model = getattr(updater, "measurement_model", None)
        if measurement_model is None:
            raise ValueError("measurement_model: none given (and the updater has none); name a Stone Soup "
                             "measurement model, e.g. stonesoup.models.measurement.linear.LinearGaussian")
        if isinstance(updater, functools.partial):
            updater = updater(measurement_model=measurement_model)
        if not isinstance(updater, Updater):
            raise ValueError(f"updater: {type(updater).__name__} is not a Stone Soup updater")
        kind = kind_of_model(measurement_model)
        if kind not in SUPPORTED_KINDS:
            raise ValueError(f"measurement_model: {type(measurement_model).__name__} takes no measurement kind of "
                             f"this project; a LinearGaussian takes position_xy, a CartesianToElevationBearingRange "
                             f"range_azimuth_elevation")
        names = tuple(state_names) if state_names is not None else infer_state_names(transition_model)
        if names is None:
            raise ValueError(f"state_names: the layout of {type(transition_model).__name__}'s state cannot be told; "
                             f"name its components, e.g. state_names: [x, vx, y, vy]")
        if len(set(names)) != len(names) or len(names) != int(transition_model.ndim_state):
            raise ValueError(f"state_names: {list(names)} must name each of the transition model's "
                             f"{transition_model.ndim_state} state components once")
        if not (np.isfinite(start_acceleration_std) and start_acceleration_std >= 0):
            raise ValueError(f"start_acceleration_std: {start_acceleration_std} must be a finite number >= 0 m/s^2")
        if int(particles) < 1:
            raise ValueError(f"particles: {particles} must be an integer >= 1")
        if workers is not None and int(workers) < 1:
            raise ValueError(f"workers: {workers} must be an integer >= 1, or null for the machine's CPUs")
        if int(seed) < 0:
            raise ValueError(f"seed: {seed} must be an integer >= 0")
        self.name = name
        self.predictor, self.updater = predictor, updater
        self.transition_model, self.measurement_model = transition_model, measurement_model
        self.kind = kind
        self.accepts = frozenset({kind})
        self.state_names = names
        self.initiator, self.prior = initiator, prior
        self.noise_from_detections = bool(noise_from_detections)
        self.start_acceleration_std = float(start_acceleration_std)
        self.particles = int(particles)
        self.workers = None if workers is None else int(workers)
        self.seed = int(seed)

    @classmethod
    def accepts_config(cls, config: Mapping) -> frozenset[str] | None:
        """The kind a variant node takes, from its measurement model's ``_target_`` (no Stone Soup object is
        built; the kinds of Stone Soup's own models are known by name, so this works without the extra)."""
        from pipeline.stonesoup.kinds import kind_of_model, model_target
        target = model_target(config, ("measurement_model",), ("updater", "measurement_model"))
        kind = None if target is None else kind_of_model(target)
        return None if kind is None else frozenset({kind})

    # ---- run ----------------------------------------------------------------------------------------
    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        started = time.perf_counter()
        if not isinstance(measurements, MeasurementSeries):
            raise TypeError(f"{self.name}: takes {sorted(self.accepts)} measurements, "
                            f"not {type(measurements).__name__}")
        job, per_run = self._prepare(measurements)
        workers = self.workers_for(measurements.runs, measurements.scans)
        if workers <= 1:
            results = [_filter_runs(job, per_run[r:r + 1])[0] for r in range(len(per_run))]
        else:
            results = _in_processes(job, per_run, workers)
        state = np.stack([r[0] for r in results])
        covariance = np.stack([r[1] for r in results])
        from filters.tracker import to_layout
        wanted = tuple(measurements.state_names or self.state_names)
        state, covariance = to_layout(state, covariance, self.state_names, wanted)
        nis = np.stack([r[2] for r in results])
        dof = np.stack([r[3] for r in results])
        return TrackEstimate(np.asarray(measurements.time, dtype=float).copy(), state, covariance,
                             {"nis": nis, "nis_dof": dof}, time.perf_counter() - started)

    def workers_for(self, runs: int, scans: int) -> int:
        """The processes that filter ``runs`` runs of ``scans`` scans: ``workers`` if set; by default the
        processors this process may run on (``filters.base.usable_processors``), or none (this process) for a job under SERIAL_BELOW run-scans, which the workers'
        start-up would outlast. Never more than the runs."""
        if self.workers is not None:
            return max(1, min(self.workers, runs))
        if runs * scans < SERIAL_BELOW:
            return 1
        return max(1, min(usable_processors(), runs))   # the affinity mask: a pinned job gets its share

    def _prepare(self, m: MeasurementSeries) -> tuple["_Job", list["_Run"]]:
        """What every run shares (the job) and each run's arrays."""
        from pipeline.stonesoup.convert import KIND_MEASUREMENTS
        names = KIND_MEASUREMENTS[self.kind]
        R, K, d = m.z.shape
        if d != len(names):
            raise ValueError(f"{self.name}: measurements have {d} values per scan; its measurement model "
                             f"({type(self.measurement_model).__name__}) takes {len(names)} ({', '.join(names)})")
        noise = np.asarray(m.noise_covariance, dtype=float)
        starts: list[tuple[np.ndarray, np.ndarray] | None] = [None] * R
        if self.prior is None and self.initiator is None:
            starts = self._two_point(m)
        ids = m.ids()
        job = _Job(self.predictor, self.updater, self.measurement_model, names, self.state_names,
                   None if m.sensor_position is None else np.asarray(m.sensor_position, dtype=float),
                   np.asarray(m.time, dtype=float), self.noise_from_detections, self.initiator, self.prior,
                   self.particles, self.seed)
        per_run = [_Run(int(ids[r]), m.z[r], noise[r] if noise.ndim == 4 else noise, m.detected[r], starts[r])
                   for r in range(R)]
        return job, per_run

    def _two_point(self, m: MeasurementSeries) -> list[tuple[np.ndarray, np.ndarray]]:
        """The two-point start at scan 1 of every run, in the filter's layout (filters.models.two_point_start
        on the Cartesian positions of scans 0 and 1, each with its own covariance)."""
        from filters.models import two_point_start
        from filters.tracker import cartesian_measurements
        if m.scans < 2:
            raise ValueError(f"{self.name}: the two-point start needs at least 2 scans")
        positions, noise, _ = cartesian_measurements(m)          # refuses runs missing scan 0 or 1
        d = positions.shape[-1]
        x, P = two_point_start(positions[:, 0], positions[:, 1], noise[:, 0], noise[:, 1],
                               float(m.time[1] - m.time[0]), 3, self.start_acceleration_std**2)
        ours = tuple(f"{k}{a}" for a in ("x", "y", "z")[:d] for k in ("", "v", "a"))
        unknown = [n for n in self.state_names if n not in ours]
        if unknown or not all(f"{k}{a}" in self.state_names for a in ("x", "y", "z")[:d] for k in ("", "v")):
            raise ValueError(f"{self.name}: the two-point start fills positions, velocities and accelerations "
                             f"({list(ours)}); the state {list(self.state_names)} needs a prior or an initiator")
        index = [ours.index(n) for n in self.state_names]
        return [(x[r, index], P[r][np.ix_(index, index)]) for r in range(m.runs)]


@dataclass
class _Job:
    predictor: Any
    updater: Any
    measurement_model: Any
    measurement_names: tuple[str, ...]
    state_names: tuple[str, ...]
    sensor_position: np.ndarray | None
    time: np.ndarray
    noise_from_detections: bool
    initiator: Any
    prior: Any
    particles: int
    seed: int


@dataclass
class _Run:
    id: int
    z: np.ndarray                    # (K, m)
    noise: np.ndarray                # (K, m, m) or (m, m)
    detected: np.ndarray             # (K,)
    start: tuple[np.ndarray, np.ndarray] | None


def _filter_runs(job: _Job, runs: Sequence[_Run]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(state (K, n), covariance (K, n, n), nis (K,), nis dof (K,)) of each run, one after the other."""
    return [_filter_one(job, run) for run in runs]


def _filter_one(job: _Job, run: _Run) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState

    from pipeline.stonesoup.convert import (global_seed, measurement_model, moments, reseed, timestamp,
                                            to_stonesoup_vector)
    K, n = job.time.size, len(job.state_names)
    states, covariances = np.full((K, n), np.nan), np.full((K, n, n), np.nan)
    nis, dof = np.full(K, np.nan), np.zeros(K)
    sequence = np.random.SeedSequence(entropy=job.seed, spawn_key=(RANDOM_STREAM, run.id))
    components, global_draws = sequence.spawn(2)
    reseed([job.predictor, job.updater, job.initiator], components)
    models: dict[bytes, Any] = {}

    def model_at(k: int) -> Any:
        if not job.noise_from_detections:
            noise = None
        else:
            noise = run.noise[k] if run.noise.ndim == 3 else run.noise
        key = b"" if noise is None else np.ascontiguousarray(noise).tobytes()
        if key not in models:
            if noise is None:
                models[key] = measurement_model(job.measurement_names, _noise_of(job), job.state_names,
                                                job.sensor_position, job.measurement_model)
            else:
                models[key] = measurement_model(job.measurement_names, noise, job.state_names, job.sensor_position,
                                                job.measurement_model)
        return models[key]

    state = None
    with global_seed(global_draws):
        for k in range(K):
            when = timestamp(job.time[k])
            detection = (Detection(to_stonesoup_vector(job.measurement_names, run.z[k]), timestamp=when,
                                   measurement_model=model_at(k)) if run.detected[k] else None)
            if state is None:
                if run.start is not None:                 # the two-point start, at scan 1
                    if k == 1:
                        state = _particles_if_needed(job, GaussianState(run.start[0].reshape(-1, 1), run.start[1],
                                                                        timestamp=when))
                        states[k], covariances[k] = moments(state)
                    continue
                if job.initiator is not None:
                    if detection is None:
                        continue
                    tracks = job.initiator.initiate({detection}, when)
                    if len(tracks) != 1:
                        raise ValueError(f"initiator: {type(job.initiator).__name__} started {len(tracks)} tracks "
                                         f"on one detection; a variant needs one")
                    state = _particles_if_needed(job, next(iter(tracks)).state)
                    states[k], covariances[k] = moments(state)
                    continue
                state = _particles_if_needed(job, _with_time(job.prior, when))
            state = job.predictor.predict(state, timestamp=when)
            if detection is not None:
                hypothesis = SingleHypothesis(state, detection)
                state = job.updater.update(hypothesis)
                nis[k], dof[k] = _nis(hypothesis, detection)
            states[k], covariances[k] = moments(state)
    return states, covariances, nis, dof


def _noise_of(job: _Job) -> np.ndarray:
    """The configured measurement model's noise, in our measurement order."""
    from pipeline.stonesoup.convert import from_stonesoup_covariance
    return from_stonesoup_covariance(job.measurement_names, job.measurement_model.covar())


def _with_time(state: Any, when: Any) -> Any:
    import copy
    duplicate = copy.copy(state)
    duplicate.timestamp = when
    return duplicate


def _particles_if_needed(job: _Job, state: Any) -> Any:
    """A Gaussian start as ``job.particles`` draws (numpy's global generator, seeded per run) when the
    predictor is a particle predictor; any other state as it is."""
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.types.array import StateVectors
    from stonesoup.types.state import ParticleState
    if not isinstance(job.predictor, ParticlePredictor) or isinstance(state, ParticleState):
        return state
    mean = np.asarray(state.state_vector, dtype=float).ravel()
    draws = np.random.multivariate_normal(mean, np.asarray(state.covar, dtype=float), size=job.particles)
    return ParticleState(StateVectors(draws.T), log_weight=np.full(job.particles, -np.log(job.particles)),
                         timestamp=state.timestamp)


def _nis(hypothesis: Any, detection: Any) -> tuple[float, float]:
    """The update's normalised innovation squared and its dof (NaN, 0 without a Gaussian measurement prediction)."""
    prediction = getattr(hypothesis, "measurement_prediction", None)
    S = getattr(prediction, "covar", None)
    if prediction is None or S is None:
        return float("nan"), 0.0
    nu = np.asarray(detection.state_vector - prediction.state_vector, dtype=float).ravel()
    try:
        value = float(nu @ np.linalg.solve(np.asarray(S, dtype=float), nu))
    except np.linalg.LinAlgError:
        return float("nan"), 0.0
    return value, float(nu.size)


# ---- worker processes -----------------------------------------------------------------------------
def _worker(payload: bytes, runs: list["_Run"]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    return _filter_runs(pickle.loads(payload), runs)


def _in_processes(job: _Job, runs: list[_Run], workers: int) -> list[tuple[np.ndarray, ...]]:
    """Every run filtered in ``workers`` processes: contiguous batches, results in run order.

    joblib's loky processes (joblib comes with Hydra's joblib launcher): started fresh (not forked from
    this process and its threads), without re-running the caller's main module, and kept for the next
    call for a few minutes, so a second variant or chunk pays no start-up (a worker's start, mostly
    importing Stone Soup, takes seconds)."""
    from joblib import Parallel, delayed
    payload = pickle.dumps(job)
    batches = [b for b in np.array_split(np.arange(len(runs)), min(len(runs), workers * 4)) if b.size]
    parts = Parallel(n_jobs=workers, backend="loky")(delayed(_worker)(payload, [runs[i] for i in batch])
                                                     for batch in batches)
    return [result for part in parts for result in part]
