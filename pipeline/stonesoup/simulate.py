"""Stone Soup's simulators as our scenario and measure stages.

``StoneSoupScenario`` runs a Stone Soup ground-truth simulator (``SingleTargetGroundTruthSimulator``,
``MultiTargetGroundTruthSimulator``, ... configured in YAML with its transition model and initial
state) once per Monte Carlo run and writes our truth table; ``StoneSoupSensor`` runs a Stone Soup
detection simulator (``SimpleDetectionSimulator``, given as ``_partial_: true`` with its measurement
model: it reads our truth, from any scenario, through pipeline.stonesoup.convert.ArrayGroundTruthReader)
and writes our detections table. Both are plain scenario and sensor nodes, so their stages are cached
like any other (the key holds their config and Stone Soup's version).

Randomness: run r's simulator is a copy whose every random state (the simulator's, its models') is
seeded from (mc.seed, stage, r) (pipeline.stonesoup.convert.reseed), and numpy's global generator too
for the run, so run r's truth and detections depend only on the seed and r.
"""

from __future__ import annotations

import copy
import zlib
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.data import Detections, Truth
from pipeline.stonesoup import require_stonesoup


def _run_sequence(seed: int, stage: str, run: int) -> np.random.SeedSequence:
    """Run r's seed sequence of a stage (pipeline.run.seeding.run_generators draws from the same)."""
    return np.random.SeedSequence(entropy=seed, spawn_key=(zlib.crc32(stage.encode()), run))


class StoneSoupScenario:
    """Our truth from a Stone Soup ground-truth simulator, one Monte Carlo run at a time.

    Parameters
    ----------
    simulator : a Stone Soup ground-truth simulator with its transition model and initial state (the
        initial state's timestamp, the simulator's ``timestep`` and ``number_steps`` are set from
        ``dt`` and ``steps``)
    state_names : the names of the simulated state's components, in its order (x, vx, y, vy, ...): the
        truth's ``state_names``, which the filters and metrics read (x, y[, z] positions, vx... velocities)
    steps : last scan index (scans k = 0..steps at t = k dt)
    dt : scan period [s]

    Targets: the paths in the order they appear (at one scan, by their state); a target that does not
    exist at a scan has a NaN state there. The single-target studies evaluate target 0.
    """

    def __init__(self, simulator: Any, state_names: Sequence[str], steps: int = 100, dt: float = 1.0) -> None:
        require_stonesoup()
        from stonesoup.simulator.base import GroundTruthSimulator
        if not isinstance(simulator, GroundTruthSimulator):
            raise ValueError(f"simulator: {type(simulator).__name__} is not a Stone Soup ground-truth simulator "
                             f"(e.g. stonesoup.simulator.simple.SingleTargetGroundTruthSimulator)")
        if isinstance(steps, bool) or int(steps) < 1:
            raise ValueError(f"steps: {steps} must be an integer >= 1 (scans k = 0..steps)")
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: {dt} must be a finite scan period > 0 s")
        names = tuple(str(n) for n in state_names)
        if not names or len(set(names)) != len(names):
            raise ValueError(f"state_names: {list(state_names)} must name each state component once")
        size = int(np.asarray(simulator.initial_state.state_vector).size)
        if size != len(names):
            raise ValueError(f"state_names: {list(names)} names {len(names)} components; the simulator's initial "
                             f"state has {size}")
        self.simulator, self.state_names = simulator, names
        self.steps, self.dt = int(steps), float(dt)

    def generate(self, runs: int, seed: int) -> Truth:
        from pipeline.stonesoup.convert import global_seed, reseed
        per_run = []
        for r in range(runs):
            components, global_draws = _run_sequence(seed, "scenario", r).spawn(2)
            simulator = self._configured()
            reseed(simulator, components)
            with global_seed(global_draws):
                per_run.append(self._simulate(simulator))
        T = max(1, max(states.shape[1] for states in per_run))
        K, n = self.steps + 1, len(self.state_names)
        state = np.full((runs, K, T, n), np.nan)
        for r, states in enumerate(per_run):
            state[r, :, :states.shape[1]] = states
        return Truth(np.arange(K) * self.dt, state, self.state_names)

    def _configured(self) -> Any:
        import datetime

        from pipeline.stonesoup.convert import EPOCH, rebuilt
        simulator = copy.deepcopy(self.simulator)
        initial = copy.copy(simulator.initial_state)
        initial.timestamp = EPOCH
        return rebuilt(simulator, initial_state=initial, timestep=datetime.timedelta(seconds=self.dt),
                       number_steps=self.steps + 1)

    def _simulate(self, simulator: Any) -> np.ndarray:
        """(K, T, n) one run's states, targets in the order they appear."""
        from pipeline.stonesoup.convert import seconds
        K, n = self.steps + 1, len(self.state_names)
        order: dict[int, int] = {}
        rows: list[np.ndarray] = []
        for when, paths in simulator:
            k = int(round(seconds(when) / self.dt))
            if not 0 <= k < K:
                continue
            new = sorted((p for p in paths if id(p) not in order),
                         key=lambda p: tuple(np.asarray(p[-1].state_vector, dtype=float).ravel()))
            for path in new:
                order[id(path)] = len(order)
                rows.append(np.full((K, n), np.nan))
            for path in paths:
                rows[order[id(path)]][k] = np.asarray(path[-1].state_vector, dtype=float).ravel()
        return np.stack(rows, axis=1) if rows else np.full((K, 0, n), np.nan)


class StoneSoupSensor:
    """Our detections from a Stone Soup detection simulator reading our truth, one Monte Carlo run at a time.

    Parameters
    ----------
    simulator : a partial (``_partial_: true``) of a Stone Soup detection simulator that takes
        ``groundtruth`` (e.g. ``SimpleDetectionSimulator`` with its measurement model, detection
        probability, clutter rate and measurement range); its measurement model's type decides the
        measurement kind (LinearGaussian: position_xy; CartesianToElevationBearingRange:
        range_azimuth_elevation, relative to its translation offset, the sensor's ``position``)
    sensor_id : the value of ``Detections.sensor`` at every scan

    Detection slots per scan: slot t holds target t's detection (``detected`` False when missed), the
    slots after them the clutter (target -1), ordered by value; NaN where empty. Each detection
    reports the measurement model's noise covariance.
    """

    def __init__(self, simulator: Any, sensor_id: int = 0) -> None:
        require_stonesoup()
        import functools

        from pipeline.stonesoup.kinds import kind_of_model
        if not isinstance(simulator, functools.partial):
            raise ValueError("simulator: give the detection simulator as a partial (_partial_: true): it is built "
                             "per Monte Carlo run with that run's ground truth")
        for key, low, high in (("detection_probability", 0.0, 1.0), ("clutter_rate", 0.0, np.inf)):
            value = simulator.keywords.get(key)
            if value is not None and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                          and low <= value <= high):
                raise ValueError(f"simulator.{key}: {value!r} must be a number in [{low:g}, {high:g}]")
        model = simulator.keywords.get("measurement_model")
        kind = kind_of_model(model) if model is not None else None
        if kind is None:
            raise ValueError("simulator.measurement_model: a LinearGaussian (positions) or a "
                             "CartesianToElevationBearingRange (a 3-D radar) is needed to give our detections a kind")
        self.simulator, self.measurement_model, self.sensor_id = simulator, model, int(sensor_id)
        self._kind = kind

    @property
    def produces(self) -> str:
        """The measurement kind (filters.base.MEASUREMENT_KINDS) of the measurement model's type."""
        return self._kind

    @classmethod
    def produces_config(cls, config: Mapping) -> str | None:
        """The kind of a sensor node, from its simulator's measurement model's ``_target_`` (nothing built)."""
        from pipeline.stonesoup.kinds import kind_of_model, model_target
        target = model_target(config, ("simulator", "measurement_model"))
        return None if target is None else kind_of_model(target)

    @property
    def position(self) -> np.ndarray | None:
        """A radar's position (its measurement model's translation offset); None for positions."""
        offset = getattr(self.measurement_model, "translation_offset", None)
        return None if offset is None else np.asarray(offset, dtype=float).ravel()

    def measure(self, truth: Truth, seed: int) -> Detections:
        from stonesoup.types.detection import TrueDetection

        from pipeline.stonesoup.convert import (KIND_MEASUREMENTS, MEASUREMENT_UNITS, ArrayGroundTruthReader,
                                                from_stonesoup_covariance, from_stonesoup_vector, global_seed,
                                                reseed, seconds)
        names = KIND_MEASUREMENTS[self._kind]
        self._check_layout(truth)
        R, K, T, _ = truth.state.shape
        noise = from_stonesoup_covariance(names, self.measurement_model.covar())
        scans: list[list[list[tuple[int, np.ndarray]]]] = []       # run -> step -> [(target, z)]
        for r in range(R):
            components, global_draws = _run_sequence(seed, "measure", r).spawn(2)
            reader = ArrayGroundTruthReader(time=np.asarray(truth.time, dtype=float), states=truth.state[r])
            simulator = copy.deepcopy(self.simulator)(groundtruth=reader)
            reseed(simulator, components)
            steps: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(K)]
            with global_seed(global_draws):
                for when, detections in simulator:
                    k = int(np.argmin(np.abs(truth.time - seconds(when))))
                    for detection in detections:
                        target = (reader.target_of(detection.groundtruth_path)
                                  if isinstance(detection, TrueDetection) else -1)
                        steps[k].append((target, from_stonesoup_vector(names, detection.state_vector)))
            scans.append(steps)
        clutter = max((sum(1 for t, _ in step if t < 0) for steps in scans for step in steps), default=0)
        D, m = T + clutter, len(names)
        z = np.full((R, K, D, m), np.nan)
        target = np.full((R, K, D), -1, dtype=int)
        target[:, :, :T] = np.arange(T)
        detected = np.zeros((R, K, D), dtype=bool)
        for r, steps in enumerate(scans):
            for k, step in enumerate(steps):
                spurious = sorted((tuple(value) for t, value in step if t < 0))
                for t, value in step:
                    if t >= 0:
                        z[r, k, t], detected[r, k, t] = value, True
                for i, value in enumerate(spurious):
                    z[r, k, T + i], detected[r, k, T + i] = value, True
        cov = np.broadcast_to(noise, (R, K, D, m, m)).copy()
        return Detections(time=np.asarray(truth.time, dtype=float), sensor=np.full(K, self.sensor_id), z=z,
                          noise_covariance=cov, target=target, detected=detected, measurement_names=names,
                          measurement_units=tuple(MEASUREMENT_UNITS[n] for n in names))

    def _check_layout(self, truth: Truth) -> None:
        """The measurement model must read the truth's positions (its mapping, in the truth's layout)."""
        positions = ("x", "y", "z") if self._kind == "range_azimuth_elevation" else ("x", "y")
        names = tuple(truth.state_names)
        if any(p not in names for p in positions):
            raise ValueError(f"sensors: the truth's state {list(names)} lacks {list(positions)}")
        wanted = [names.index(p) for p in positions]
        model = self.measurement_model
        if int(model.ndim_state) != len(names) or [int(i) for i in model.mapping] != wanted:
            raise ValueError(f"sensors.simulator.measurement_model: ndim_state {model.ndim_state} and mapping "
                             f"{list(model.mapping)} must pick {list(positions)} of the truth's state {list(names)}: "
                             f"ndim_state {len(names)}, mapping {wanted}")
