"""Our arrays <-> Stone Soup's objects: times, measurement vectors and models, state layouts, seeding.

Imported only where Stone Soup is used (it imports Stone Soup at the top).

- **Time**: our times are seconds from 0; Stone Soup's are datetimes. Time t is ``EPOCH + t s``
  (a datetime holds microseconds, so times are taken to the microsecond).
- **Measurements**: ours are in the order of the detections' ``measurement_names``; Stone Soup's
  models have their own order. Positions (x, y[, z]) are ``LinearGaussian``'s order; a radar's
  (range, azimuth, elevation) is ``CartesianToElevationBearingRange``'s (elevation, bearing, range)
  and a 2-D radar's (range, azimuth) is ``CartesianToBearingRange``'s (bearing, range). The angle
  conventions are the same (azimuth atan2(dy, dx) from +x toward +y, elevation from the x-y plane:
  pipeline/sensors.py), so only the order and the angle types differ.
- **Kinds**: the measurement kind (filters.base.MEASUREMENT_KINDS) a Stone Soup measurement model
  takes follows from its type (``kind_of_model``).
- **Randomness**: ``reseed`` gives every random state of a Stone Soup object graph (its models'
  ``random_state``, a simulator's) a generator of its own from one SeedSequence, so run r's draws
  depend only on the run, not on the worker that computes it.
"""

from __future__ import annotations

import contextlib
import copy
import datetime
from typing import Any, Iterator, Sequence

import numpy as np
from stonesoup.base import Base, Property
from stonesoup.buffered_generator import BufferedGenerator
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToBearingRange, CartesianToElevationBearingRange
from stonesoup.reader.base import GroundTruthReader
from stonesoup.types.angle import Bearing, Elevation
from stonesoup.types.array import CovarianceMatrix, StateVector
from stonesoup.types.groundtruth import GroundTruthPath, GroundTruthState

from pipeline.stonesoup.kinds import KIND_MEASUREMENTS, MODEL_KINDS, kind_of_model  # noqa: F401 - re-exported

EPOCH = datetime.datetime(2000, 1, 1)

MEASUREMENT_UNITS = {"x": "m", "y": "m", "z": "m", "range": "m", "azimuth": "rad", "elevation": "rad"}
# our measurement names -> (the Stone Soup model class, our indices in Stone Soup's order, position names)
LAYOUTS = {
    ("x", "y"): (LinearGaussian, (0, 1), ("x", "y")),
    ("x", "y", "z"): (LinearGaussian, (0, 1, 2), ("x", "y", "z")),
    ("range", "azimuth", "elevation"): (CartesianToElevationBearingRange, (2, 1, 0), ("x", "y", "z")),
    ("range", "azimuth"): (CartesianToBearingRange, (1, 0), ("x", "y")),
}
ANGLE_TYPES = {"azimuth": Bearing, "elevation": Elevation}


def timestamp(seconds: float) -> datetime.datetime:
    return EPOCH + datetime.timedelta(seconds=float(seconds))


def seconds(when: datetime.datetime) -> float:
    return (when - EPOCH).total_seconds()


def layout(names: Sequence[str]) -> tuple[type, tuple[int, ...], tuple[str, ...]]:
    try:
        return LAYOUTS[tuple(names)]
    except KeyError:
        raise ValueError(f"measurements named {list(names)} have no Stone Soup measurement model here; known: "
                         f"{[list(k) for k in LAYOUTS]}") from None


def to_stonesoup_vector(names: Sequence[str], z: np.ndarray) -> StateVector:
    """Our measurement (in ``names`` order) as Stone Soup's measurement vector, angles typed."""
    _, order, _ = layout(names)
    values = []
    for i in order:
        angle = ANGLE_TYPES.get(names[i])
        values.append(angle(float(z[i])) if angle else float(z[i]))
    return StateVector(values)


def from_stonesoup_vector(names: Sequence[str], vector: Any) -> np.ndarray:
    """Stone Soup's measurement vector back in ``names`` order (angles as plain radians)."""
    _, order, _ = layout(names)
    flat = np.asarray(vector, dtype=float).ravel()
    out = np.empty(len(order))
    out[list(order)] = flat
    return out


def to_stonesoup_covariance(names: Sequence[str], R: np.ndarray) -> CovarianceMatrix:
    _, order, _ = layout(names)
    index = list(order)
    return CovarianceMatrix(np.asarray(R, dtype=float)[np.ix_(index, index)])


def from_stonesoup_covariance(names: Sequence[str], R: Any) -> np.ndarray:
    _, order, _ = layout(names)
    back = np.argsort(order)
    return np.asarray(R, dtype=float)[np.ix_(back, back)]


def rebuilt(model: Base, **changes: Any) -> Base:
    """A Stone Soup component of the same type with some properties replaced (the others as they are)."""
    values = {name: getattr(model, name) for name in type(model).properties}
    return type(model)(**{**values, **changes})


def measurement_model(names: Sequence[str], noise: np.ndarray, state_names: Sequence[str],
                      position: np.ndarray | None = None, template: Base | None = None) -> Base:
    """The Stone Soup measurement model of our measurements ``names`` with noise covariance ``noise``
    (ours, in ``names`` order) of a target whose state is laid out as ``state_names``, for a sensor at
    ``position`` (its translation offset; a radar's). With ``template`` (a configured model of the same
    type), its other properties are kept; its mapping must pick the state's positions."""
    cls, _, positions = layout(names)
    missing = [p for p in positions if p not in state_names]
    if missing:
        raise ValueError(f"the state {list(state_names)} lacks {missing}, which measurements {list(names)} need")
    mapping = tuple(list(state_names).index(p) for p in positions)
    changes: dict[str, Any] = {"ndim_state": len(state_names), "mapping": mapping,
                               "noise_covar": to_stonesoup_covariance(names, noise)}
    if cls is not LinearGaussian:
        offset = np.zeros(len(positions)) if position is None else np.asarray(position, dtype=float)[:len(positions)]
        changes["translation_offset"] = StateVector(offset)
    if template is None:
        return cls(**changes)
    if not isinstance(template, cls):
        raise ValueError(f"measurement_model: a {type(template).__name__} cannot take measurements {list(names)}; "
                         f"they need a {cls.__name__}")
    if tuple(template.mapping) != mapping or template.ndim_state != len(state_names):
        raise ValueError(f"measurement_model: mapping {list(template.mapping)} of a {template.ndim_state}-dimensional "
                         f"state does not pick {list(positions)} of the filter's state {list(state_names)}; it must "
                         f"be mapping {list(mapping)} with ndim_state {len(state_names)}")
    return rebuilt(template, **changes)


# ---- state layouts ---------------------------------------------------------------------------------
AXES = ("x", "y", "z")
DERIVATIVES = ("", "v", "a")


def infer_state_names(transition_model: Any) -> tuple[str, ...] | None:
    """The layout of a Stone Soup state whose transition model stacks one 1-D kinematic model per axis
    (``CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])``: x, vx, y, vy;
    with ``ConstantAcceleration`` or ``Singer``: x, vx, ax, ...); None when it cannot be told."""
    parts = getattr(transition_model, "model_list", None)
    parts = list(parts) if parts is not None else [transition_model]
    if not 1 <= len(parts) <= len(AXES):
        return None
    names: list[str] = []
    for axis, part in zip(AXES, parts):
        if getattr(part, "model_list", None) is not None:
            return None
        try:
            size = int(part.ndim_state)
        except Exception:  # noqa: BLE001 - a model without a fixed dimension
            return None
        if not 1 <= size <= len(DERIVATIVES):
            return None
        names += [f"{d}{axis}" for d in DERIVATIVES[:size]]
    return tuple(names)


def moments(state: Any) -> tuple[np.ndarray, np.ndarray]:
    """(mean (n,), covariance (n, n)) of a Stone Soup state: a Gaussian's own, a particle state's weighted."""
    if hasattr(state, "covar") and not hasattr(state, "particle_list"):
        return np.asarray(state.state_vector, dtype=float).ravel(), np.asarray(state.covar, dtype=float)
    return np.asarray(state.mean, dtype=float).ravel(), np.asarray(state.covar, dtype=float)


# ---- randomness -----------------------------------------------------------------------------------
def _components(root: Any) -> list[Base]:
    """Every Stone Soup object reachable from ``root`` through properties, lists, tuples and dicts, in a
    fixed order (depth first, each once)."""
    found: list[Base] = []
    seen: set[int] = set()

    def walk(obj: Any) -> None:
        if isinstance(obj, (list, tuple)):
            for item in obj:
                walk(item)
        elif isinstance(obj, dict):
            for item in obj.values():
                walk(item)
        elif isinstance(obj, Base) and id(obj) not in seen:
            seen.add(id(obj))
            found.append(obj)
            for name in type(obj).properties:
                try:
                    walk(getattr(obj, name))
                except Exception:  # noqa: BLE001 - a property that cannot be read here is not a component
                    continue
    walk(root)
    return found


def reseed(root: Any, sequence: np.random.SeedSequence) -> None:
    """Give every object of ``root``'s graph that draws random numbers (a ``random_state`` attribute: Stone
    Soup's models, simulators, resamplers) its own generator spawned from ``sequence``, in place."""
    holders = [obj for obj in _components(root) if hasattr(obj, "random_state")]
    for obj, child in zip(holders, sequence.spawn(len(holders))):
        obj.random_state = np.random.RandomState(np.random.MT19937(child))


@contextlib.contextmanager
def global_seed(sequence: np.random.SeedSequence) -> Iterator[None]:
    """numpy's global generator seeded from ``sequence`` for the block, then restored (Stone Soup's
    components without a random_state of their own, e.g. resamplers, draw from it)."""
    saved = np.random.get_state()
    np.random.seed(sequence.generate_state(1, dtype=np.uint32)[0])
    try:
        yield
    finally:
        np.random.set_state(saved)


def seeded_copy(root: Any, sequence: np.random.SeedSequence) -> Any:
    duplicate = copy.deepcopy(root)
    reseed(duplicate, sequence)
    return duplicate


# ---- our truth as a Stone Soup ground-truth reader --------------------------------------------------

class ArrayGroundTruthReader(GroundTruthReader):
    """One Monte Carlo run of our truth as a Stone Soup ground-truth reader (what a detection simulator
    reads): at each scan, the paths of the targets that exist (a finite state), grown to that scan.
    Path t's id is ``target t``; its states' metadata hold the target and the step."""

    time: np.ndarray = Property(doc="(K,) scan times [s]")
    states: np.ndarray = Property(doc="(K, T, n) the targets' states, NaN where a target does not exist")

    @BufferedGenerator.generator_method
    def groundtruth_paths_gen(self):
        K, T, _ = self.states.shape
        paths = [GroundTruthPath(id=f"target {t}") for t in range(T)]
        for k in range(K):
            when = timestamp(self.time[k])
            present = set()
            for t in range(T):
                if np.all(np.isfinite(self.states[k, t])):
                    paths[t].append(GroundTruthState(StateVector(self.states[k, t]), timestamp=when,
                                                     metadata={"target": t, "step": k}))
                    present.add(paths[t])
            yield when, present

    def target_of(self, path: GroundTruthPath) -> int:
        return int(path.id.split(" ")[1])
