"""Stone Soup's multi-target trackers as variants on our detection sets: ``pipeline.stonesoup.tracker.StoneSoupTracker``.

Takes ``filters.multitarget.DetectionSets`` (measurement kind ``position_xy_sets``) and returns
``TrackSets``, like the project's trackers, so the same detections are tracked by both and scored
alike. The motion and measurement models are Stone Soup objects named in the YAML (as for
``pipeline.stonesoup.variant.StoneSoupFilter``); the tracker is built from Stone Soup's classes
for each Monte Carlo run afresh:

- ``kind: gnn``: ``stonesoup.tracker.simple.MultiTargetTracker`` with ``GNNWith2DAssignment`` over a
  ``DistanceHypothesiser`` (Mahalanobis distance, ``gate`` as its missed distance), a
  ``MultiMeasurementInitiator`` (``min_points`` associated detections confirm a track, started by a
  ``SimpleMeasurementInitiator`` with a zero-velocity prior of ``initial_velocity_std``) and an
  ``UpdateTimeStepsDeleter`` (``delete_after`` scans without an update) for tracks and tentative
  tracks alike (Stone Soup's tutorial 6 set-up). Every track the tracker holds is reported
  (confirmed); existence is NaN.
- ``kind: gmphd``: the GM-PHD recursion of ``stonesoup.tracker.pointprocess.PointProcessMultiTargetTracker``
  (Vo & Ma 2006) from its own components, ``GaussianMixtureHypothesiser`` over the same distance
  hypothesiser, ``PHDUpdater`` (P_D, P_S, clutter density) and ``GaussianMixtureReducer`` (prune,
  merge, cap), one step at a time as its ``__next__`` does, with one change: the birth intensity is
  the mixture of ``birth_means`` (each ``birth_weight``, covariance diag(``birth_std``^2)) where
  Stone Soup's tracker takes a single birth component. A component's tag is its track id (Stone
  Soup's tracks are made the same way); a component is reported (confirmed) when its weight exceeds
  ``extraction_threshold`` (Stone Soup's ``extracted_target_states``); existence is the weight;
  the extra ``cardinality`` is the mixture's total weight (its ``estimated_number_of_targets``).

Runs are filtered one at a time (Stone Soup holds objects), spread over ``workers`` joblib (loky)
processes; nothing here is random, so a run's tracks depend on that run's detections alone.
"""

from __future__ import annotations

import copy
import functools
import math
import time
from typing import Any, Sequence

import numpy as np

from filters.base import usable_processors
from filters.multitarget import POSITION_SETS, DetectionSets, MultiTargetTracker, TrackSets
from filters.progress import current
from pipeline.stonesoup import require_stonesoup

KINDS = ("gnn", "gmphd")
SERIAL_BELOW = 20           # runs: below this, no worker processes (their start-up takes seconds)


class StoneSoupTracker(MultiTargetTracker):
    """Stone Soup's GNN or GM-PHD tracker as a variant (module docstring).

    Parameters
    ----------
    kind : "gnn" or "gmphd"
    transition_model : Stone Soup transition model on (x, vx, y, vy) (e.g. two ConstantVelocity models)
    measurement_model : Stone Soup LinearGaussian picking (x, y); each detection carries it with the
        detection sets' noise covariance
    gate : the hypothesiser's missed distance (Mahalanobis) [-]
    min_points, delete_after, initial_velocity_std : the GNN's track initiation and deletion (above)
    detection_probability, survival_probability, clutter_density [1/m^2] : the GM-PHD's model
    birth_means (rows x, vx, y, vy), birth_std (4,), birth_weight : its birth intensity
    prune_threshold, merge_threshold (squared Mahalanobis), max_components, extraction_threshold : its reduction and extraction
    workers : processes; null: the usable processors for 20 runs or more, else this process
    """

    accepts = frozenset({POSITION_SETS})

    def __init__(self, kind: str, transition_model: Any, measurement_model: Any, name: str | None = None,
                 gate: float = 3.0, min_points: int = 2, delete_after: int = 3, initial_velocity_std: float = 20.0,
                 detection_probability: float = 0.98, survival_probability: float = 0.99,
                 clutter_density: float = 2.5e-6,
                 birth_means: Sequence[Sequence[float]] = ((0.0, 0.0, 0.0, 0.0),),
                 birth_std: Sequence[float] = (10.0, 10.0, 10.0, 10.0), birth_weight: float = 0.03,
                 prune_threshold: float = 1e-5, merge_threshold: float = 4.0, max_components: int = 100,
                 extraction_threshold: float = 0.5, workers: int | None = None) -> None:
        require_stonesoup()
        if kind not in KINDS:
            raise ValueError(f"kind: {kind!r} is not a Stone Soup tracker here; use one of {list(KINDS)}")
        for key, value, low in (("gate", gate, 0.0), ("initial_velocity_std", initial_velocity_std, 0.0),
                                ("clutter_density", clutter_density, 0.0), ("birth_weight", birth_weight, 0.0),
                                ("merge_threshold", merge_threshold, 0.0)):
            if not (np.isfinite(value) and value > low):
                raise ValueError(f"{key}: {value!r} must be a finite number > {low:g}")
        for key, value in (("detection_probability", detection_probability),
                           ("survival_probability", survival_probability),
                           ("extraction_threshold", extraction_threshold), ("prune_threshold", prune_threshold)):
            if not (np.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{key}: {value!r} must be a probability in [0, 1]")
        for key, value in (("min_points", min_points), ("delete_after", delete_after), ("max_components", max_components)):
            if int(value) != value or value < 1:
                raise ValueError(f"{key}: {value!r} must be a whole number >= 1")
        means = np.asarray(birth_means, dtype=float)
        if means.ndim != 2 or means.shape[1] != 4 or not means.size or not np.all(np.isfinite(means)):
            raise ValueError(f"birth_means: {birth_means!r} must be rows of 4 finite numbers (x, vx, y, vy)")
        std = np.asarray(birth_std, dtype=float)
        if std.shape != (4,) or not np.all(std > 0):
            raise ValueError(f"birth_std: {birth_std!r} must be 4 standard deviations > 0 (x, vx, y, vy)")
        if workers is not None and int(workers) < 1:
            raise ValueError(f"workers: {workers!r} must be a whole number >= 1, or null")
        self.kind = kind
        self.name = name or f"SS-{kind.upper()}"
        self.transition_model, self.measurement_model = transition_model, measurement_model
        self.gate, self.min_points, self.delete_after = float(gate), int(min_points), int(delete_after)
        self.initial_velocity_std = float(initial_velocity_std)
        self.detection_probability, self.survival_probability = float(detection_probability), float(survival_probability)
        self.clutter_density = float(clutter_density)
        self.birth_means, self.birth_std, self.birth_weight = means, std, float(birth_weight)
        self.prune_threshold, self.merge_threshold = float(prune_threshold), float(merge_threshold)
        self.max_components, self.extraction_threshold = int(max_components), float(extraction_threshold)
        self.workers = None if workers is None else int(workers)

    def run(self, detections: DetectionSets) -> TrackSets:
        started = time.perf_counter()
        if not isinstance(detections, DetectionSets):
            raise TypeError(f"{self.name}: takes {POSITION_SETS} (DetectionSets), not {type(detections).__name__}")
        if tuple(detections.state_names) != ("x", "vx", "y", "vy"):
            raise ValueError(f"{self.name}: the Stone Soup models here are on (x, vx, y, vy); the detections' state "
                             f"is {list(detections.state_names)}")
        per_run = [(detections.z[r], detections.count[r]) for r in range(detections.runs)]
        workers = self.workers if self.workers is not None else (
            1 if detections.runs < SERIAL_BELOW else max(1, min(usable_processors(), detections.runs)))
        job = (self, np.asarray(detections.time, dtype=float), np.asarray(detections.noise_covariance, dtype=float))
        progress, scans, runs = current(), detections.time.shape[0], max(detections.runs, 1)
        progress.start(scans, "scan", self.name)          # a run done is its share of the scans
        if workers <= 1:
            results = []
            for z, count in per_run:
                results.append(_track_run(job, z, count))
                progress.advance(scans / runs)
        else:
            from joblib import Parallel, delayed
            batches = [b for b in np.array_split(np.arange(len(per_run)), min(len(per_run), workers * 4)) if b.size]
            parts = []
            for part in Parallel(n_jobs=workers, backend="loky", return_as="generator")(
                    delayed(_track_runs)(job, [per_run[i] for i in batch]) for batch in batches):
                parts.append(part)
                progress.advance(scans * len(part) / runs)
            results = [result for part in parts for result in part]
        return _stacked(results, detections, time.perf_counter() - started)


def _track_runs(job, runs) -> list:
    return [_track_run(job, z, count) for z, count in runs]


@functools.cache
def _slot_detection() -> type:
    """Stone Soup's ``Detection`` hashed by its (scan, slot) instead of its address: Stone Soup keeps
    detections and tracks in sets, and an address-keyed set is iterated in an order that changes from
    one process to the next (the hypotheses, the initiator's order, the mixture's), so a run's tracks
    would not be the same twice."""
    from stonesoup.types.detection import Detection

    class SlotDetection(Detection):
        def __hash__(self) -> int:
            return hash(self.metadata["slot"])

    return SlotDetection


def _detections(tracker: StoneSoupTracker, z: np.ndarray, count: int, when, model, k: int) -> set:
    detection = _slot_detection()
    return {detection(np.asarray(z[i], dtype=float).reshape(-1, 1), timestamp=when, measurement_model=model,
                      metadata={"slot": (k, i)}) for i in range(int(count))}


def _canonical(rows: list) -> list:
    """A scan's reported rows in an order that does not depend on set iteration: by weight (descending),
    then by the state vector."""
    return sorted(rows, key=lambda row: (-row[4] if np.isfinite(row[4]) else 0.0, tuple(np.round(row[1], 9))))


def _models(tracker: StoneSoupTracker, noise: np.ndarray):
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.updater.kalman import KalmanUpdater
    model = LinearGaussian(ndim_state=4, mapping=tuple(int(i) for i in tracker.measurement_model.mapping),
                           noise_covar=np.asarray(noise, dtype=float))
    return model, KalmanPredictor(copy.deepcopy(tracker.transition_model)), KalmanUpdater(model)


def _track_run(job, z: np.ndarray, count: np.ndarray) -> list[list[tuple[str, np.ndarray, np.ndarray, bool, float]]]:
    """Per scan, the reported (tag, mean, covariance, confirmed, existence) of one run, plus the scan's extras."""
    tracker, times, noise = job
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.measures import Mahalanobis

    from pipeline.stonesoup.convert import timestamp
    model, predictor, updater = _models(tracker, noise)
    hypothesiser = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=tracker.gate)
    scans = []
    if tracker.kind == "gnn":
        from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
        from stonesoup.deleter.time import UpdateTimeStepsDeleter
        from stonesoup.initiator.simple import MultiMeasurementInitiator
        from stonesoup.tracker.simple import MultiTargetTracker as SSMultiTargetTracker
        from stonesoup.types.state import GaussianState
        deleter = UpdateTimeStepsDeleter(time_steps_since_update=tracker.delete_after)
        prior = GaussianState(np.zeros((4, 1)), np.diag([0.0, tracker.initial_velocity_std**2,
                                                         0.0, tracker.initial_velocity_std**2]))
        initiator = MultiMeasurementInitiator(
            prior_state=prior, measurement_model=model, deleter=deleter,
            data_associator=GNNWith2DAssignment(DistanceHypothesiser(predictor, updater, measure=Mahalanobis(),
                                                                     missed_distance=tracker.gate)),
            updater=updater, min_points=tracker.min_points)
        feed = [(timestamp(t), _detections(tracker, z[k], count[k], timestamp(t), model, k)) for k, t in enumerate(times)]
        ss = SSMultiTargetTracker(initiator=initiator, deleter=deleter, detector=feed,
                                  data_associator=GNNWith2DAssignment(hypothesiser), updater=updater)
        for when, tracks in ss:
            rows = []
            for track in tracks:
                state = track.state
                if state.timestamp == when:
                    rows.append((str(track.id), np.asarray(state.state_vector, dtype=float).ravel(),
                                 np.asarray(state.covar, dtype=float), True, float("nan")))
            scans.append((_canonical(rows), float("nan")))
        return scans
    from stonesoup.hypothesiser.gaussianmixture import GaussianMixtureHypothesiser
    from stonesoup.mixturereducer.gaussianmixture import GaussianMixtureReducer
    from stonesoup.types.mixture import GaussianMixture
    from stonesoup.types.state import TaggedWeightedGaussianState
    from stonesoup.updater.pointprocess import PHDUpdater
    gm_hypothesiser = GaussianMixtureHypothesiser(hypothesiser=hypothesiser, order_by_detection=True)
    phd = PHDUpdater(updater, clutter_spatial_density=tracker.clutter_density,
                     prob_detection=tracker.detection_probability, prob_survival=tracker.survival_probability)
    # no k-d tree gate: it hands the merge a set of components, whose order (and so the merged sums' rounding)
    # changes from one process to the next
    reducer = GaussianMixtureReducer(prune_threshold=tracker.prune_threshold, merge_threshold=tracker.merge_threshold,
                                     max_number_components=tracker.max_components, kdtree_max_distance=None)
    mixture = GaussianMixture()
    birth_cov = np.diag(tracker.birth_std**2)
    for k, t in enumerate(times):
        when = timestamp(t)
        for mean in tracker.birth_means:
            mixture.append(TaggedWeightedGaussianState(mean.reshape(-1, 1), birth_cov, weight=tracker.birth_weight,
                                                       tag=TaggedWeightedGaussianState.BIRTH, timestamp=when))
        hypotheses = gm_hypothesiser.hypothesise(mixture.components,
                                                 _detections(tracker, z[k], count[k], when, model, k), when)
        mixture = phd.update(hypotheses)
        # the reducer leaves its components in an order that follows their tags' (random) string hashes: sort them,
        # so that the next scan's sums run in one order
        mixture.components = sorted(reducer.reduce(mixture.components),
                                    key=lambda c: (-float(c.weight), tuple(np.asarray(c.state_vector, float).ravel())))
        rows = []
        for component in sorted(mixture.components, key=lambda c: -float(c.weight)):
            if component.tag == component.BIRTH:
                continue
            weight = float(component.weight)
            rows.append((str(component.tag), np.asarray(component.state_vector, dtype=float).ravel(),
                         np.asarray(component.covar, dtype=float), weight > tracker.extraction_threshold, weight))
        # only components above the extraction threshold become tracks in Stone Soup's tracker; the rest are
        # kept out of the table (they are the mixture's, not reported targets)
        scans.append((_canonical([row for row in rows if row[3]]),
                       math.fsum(float(c.weight) for c in mixture.components)))
    return scans


def _stacked(results: list, detections: DetectionSets, seconds: float) -> TrackSets:
    """Per-run lists of per-scan rows -> padded TrackSets; a tag's first appearance in a run gets the next id
    (a second component of a tag already reported at that scan gets an id of its own)."""
    R, K = detections.runs, detections.steps
    M = max([len(rows) for scans in results for rows, _ in scans] + [1])
    state = np.full((R, K, M, 4), np.nan)
    cov = np.full((R, K, M, 4, 4), np.nan)
    track_id = np.full((R, K, M), -1, dtype=np.int64)
    confirmed = np.zeros((R, K, M), dtype=bool)
    existence = np.full((R, K, M), np.nan)
    cardinality = np.full((R, K), np.nan)
    for r, scans in enumerate(results):
        ids: dict[str, int] = {}
        for k, (rows, total) in enumerate(scans):
            cardinality[r, k] = total
            seen = set()
            for m, (tag, x, P, is_confirmed, weight) in enumerate(rows):
                key = tag if tag not in seen else f"{tag}#{k}#{m}"
                seen.add(tag)
                ids.setdefault(key, len(ids))
                state[r, k, m], cov[r, k, m] = x, P
                track_id[r, k, m], confirmed[r, k, m], existence[r, k, m] = ids[key], is_confirmed, weight
    extras = {"cardinality": cardinality} if np.isfinite(cardinality).any() else {}
    return TrackSets(np.asarray(detections.time, dtype=float).copy(), state, cov, track_id, confirmed, existence,
                     extras, seconds)
