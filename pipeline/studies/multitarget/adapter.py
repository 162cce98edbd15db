"""The multi-target study: unlabelled detections in clutter, trackers of an unknown number of targets,
scored with GOSPA (filters.multitarget.metrics) against the truth.

The trackers get ``filters.multitarget.DetectionSets`` (the detections' positions and count per
scan; the true origin stays in the detections table for scoring) and return ``TrackSets``. What is
scored is the set of tracks each tracker reports as targets (``confirmed``: a GNN/JPDA's confirmed
tracks, a GM-PHD's extracted components), by their positions, against the positions of the targets
that exist at that scan.

Per-step metrics (every one kept per run, mean over the runs):

- ``gospa`` [m]: GOSPA (alpha = 2, cut-off ``gospa_c``, order ``gospa_p``; Rahmathullah et al. 2017),
  and its exact split ``gospa_localisation``, ``gospa_missed``, ``gospa_false`` (d^p units: their
  sum is gospa^p); ``ospa`` [m] with the same c and p;
- ``cardinality`` (tracks reported), ``true_cardinality``, ``cardinality_error`` (reported - true),
  ``phd_cardinality`` (a PHD filter's expected number of targets, its ``cardinality`` extra);
- ``missed_targets`` / ``false_targets``: truths / reported tracks left unpaired at a scan;
- ``track_switches`` and ``track_breaks`` (counts: summed over a window's steps, per run).
- ``position_rmse`` [m]: the position RMSE of the tracked targets, over the pairs GOSPA's assignment
  made at d < c (``paired_position_rmse``): one query finds it beside every single-target study's.

The summary adds, per variant, the track-level measures of the whole run (``false_tracks``,
``track_purity``, ``confirmation_delay``, ``tracks_reported``), and the largest deviation of the
mean cardinality from the truth after the births and deaths have settled (``cardinality_excess_settled``,
``cardinality_shortfall_settled``: the max over the settled scans of the run-mean of reported - true
and of true - reported; the settled scans are those at least ``settle_scans`` after any change of
the true number). Across variants, ``gospa_paired_difference``: for each pair of ``paired``
(variant: the variant it is compared with), the run-mean GOSPA of the first minus the second,
averaged over the scans, with its t interval over the runs (the runs are the same, so the
difference is paired).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import numpy as np

from filters.multitarget import DetectionSets, TrackSets
from filters.multitarget.metrics import set_distances, track_measures
from pipeline.contract import JobInputs, RecordingInputs, Study, VariantInputs
from pipeline.data import Detections, Truth
from pipeline.errors import ConfigError
from pipeline.evaluation.evaluate import quiet_nanmean, summary_row
from pipeline.evaluation.metrics import Metric, register
from pipeline.evaluation.uncertainty import RunValues, WindowStatistic
from pipeline.studies.multitarget import codec
from pipeline.studies.multitarget.scenario import POSITION_INDEX, STATE_NAMES, alive

PARTS_UNIT = "m^p (d^p units of the GOSPA order p: gospa^p is the sum of the three parts)"
PER_RUN_COUNT = "count per run (summed over the window's steps)"

register(
    Metric("gospa", "m", label="GOSPA"),
    Metric("gospa_localisation", PARTS_UNIT, "m^p", quantity="gospa_part", component="localisation"),
    Metric("gospa_missed", PARTS_UNIT, "m^p", quantity="gospa_part", component="missed"),
    Metric("gospa_false", PARTS_UNIT, "m^p", quantity="gospa_part", component="false"),
    Metric("ospa", "m", label="OSPA"),
    Metric("cardinality", "targets (tracks reported)", "targets", label="card"),
    Metric("true_cardinality", "targets", "targets"),
    Metric("cardinality_error", "targets (reported - true)", "targets", label="card err"),
    Metric("phd_cardinality", "targets (expected number, PHD)", "targets"),
    Metric("missed_targets", "targets (unpaired truths)", "targets"),
    Metric("false_targets", "targets (unpaired tracks)", "targets"),
    Metric("track_switches", PER_RUN_COUNT, "count", aggregation="sum", label="switches"),
    Metric("track_breaks", PER_RUN_COUNT, "count", aggregation="sum"),
    Metric("false_tracks", "tracks per run (never paired with a truth)", "tracks"),
    Metric("tracks_reported", "track ids per run", "tracks"),
    Metric("track_purity", "fraction (mean over a run's tracks of the share of scans on its main truth)", "-"),
    Metric("confirmation_delay", "s (a truth's first scan to its first tracked scan, mean over truths)", "s"),
    Metric("cardinality_excess_settled", "targets (max over settled scans of mean reported - true)", "targets"),
    Metric("cardinality_shortfall_settled", "targets (max over settled scans of mean true - reported)", "targets"),
    Metric("gospa_paired_difference", "m (run-mean GOSPA of the variant minus its pair's, mean over the scans)", "m"),
)


class MultiTargetStudy(Study):
    """Adapter of the multi-target study (module docstring).

    Parameters
    ----------
    gospa_c : the GOSPA / OSPA cut-off c [m] (> 0)
    gospa_p : their order p (>= 1)
    settle_scans : scans after a change of the true number of targets that the settled cardinality
        rows leave out (>= 0)
    paired : variant key -> the variant key it is compared with (``gospa_paired_difference``); a pair one
        of whose variants does not run (``variants=[...]``) gives no row
    """

    estimate_table = "tracks"

    def __init__(self, gospa_c: float = 100.0, gospa_p: float = 2.0, settle_scans: int = 10,
                 paired: Mapping[str, str] | None = None) -> None:
        if not (np.isfinite(gospa_c) and gospa_c > 0):
            raise ValueError(f"gospa_c: {gospa_c!r} must be a cut-off distance > 0 m")
        if not (np.isfinite(gospa_p) and gospa_p >= 1):
            raise ValueError(f"gospa_p: {gospa_p!r} must be an order >= 1")
        if int(settle_scans) != settle_scans or settle_scans < 0:
            raise ValueError(f"settle_scans: {settle_scans!r} must be a whole number of scans >= 0")
        self.gospa_c, self.gospa_p, self.settle_scans = float(gospa_c), float(gospa_p), int(settle_scans)
        self.paired = {str(k): str(v) for k, v in (paired or {}).items()}
        self._gospa_per_run: dict[str, np.ndarray] = {}

    # ---- checks before any stage runs ---------------------------------------------------------------
    def check(self, scenario: Any, sensor: Any, estimators: Mapping[str, Any]) -> None:
        # study.paired is not checked here: this sees the running variants only (variants=[...] may leave one of a
        # pair out, which then gives no row)
        if not hasattr(sensor, "noise_covariance") or not hasattr(sensor, "clutter_rate"):
            raise ConfigError(f"sensors: {type(sensor).__name__} is not a multi-target position sensor; the "
                              f"multi-target study needs one (e.g. sensors=multitarget_vo_vo).")

    # ---- tables ---------------------------------------------------------------------------------------
    def truth_to_frame(self, truth: Truth):
        return codec.truth_to_frame(truth)

    def truth_from_frame(self, df, metadata) -> Truth:
        return codec.truth_from_frame(df, metadata)

    def detections_to_frame(self, detections: Detections):
        return codec.detections_to_frame(detections)

    def detections_from_frame(self, df, metadata) -> Detections:
        return codec.detections_from_frame(df, metadata)

    def estimate_to_frame(self, estimate: TrackSets, truth: Truth):
        return codec.tracks_to_frame(estimate, tuple(truth.state_names))

    def estimate_from_frame(self, df, metadata) -> TrackSets:
        return codec.tracks_from_frame(df, metadata)

    # ---- track input ----------------------------------------------------------------------------------
    def track_input(self, truth: Truth, detections: Detections, sensor: Any, seed: int) -> DetectionSets:
        """The trackers' view: positions and counts only (the origin is not passed on)."""
        return detection_sets(detections, np.asarray(sensor.noise_covariance, dtype=float))

    def fault_flags(self, estimate: TrackSets, truth: Truth, checks) -> np.ndarray:
        """(R, K) masks of pipeline.evaluation.faults over the filled track slots of each scan (an empty
        slot is not a fault; a run without any track is not flagged either)."""
        from pipeline.evaluation.faults import fault_flags
        filled = np.asarray(estimate.track_id) >= 0
        n = estimate.state.shape[-1]
        state = np.where(filled[..., None], estimate.state, 0.0)
        cov = np.where(filled[..., None, None], estimate.covariance, np.eye(n))
        return fault_flags(state, cov, checks)

    # ---- evaluate ---------------------------------------------------------------------------------------
    def scored(self, truth: Truth, estimate: TrackSets):
        """(estimated positions (R, K, M, 2), their valid mask, true positions (R, K, T, 2), theirs)."""
        index = list(POSITION_INDEX)
        reported = np.asarray(estimate.confirmed, dtype=bool) & (np.asarray(estimate.track_id) >= 0)
        estimated = np.asarray(estimate.state, dtype=float)[..., index]
        reported &= np.all(np.isfinite(estimated), axis=-1)
        return estimated, reported, truth.state[..., index], alive(truth)

    def per_step_metrics(self, truth: Truth, estimate: TrackSets, sensor: Any) -> dict[str, Any]:
        if estimate.state.shape[:2] != truth.state.shape[:2]:
            raise ValueError(f"tracks: {estimate.state.shape[:2]} runs x scans, the truth has {truth.state.shape[:2]}")
        estimated, reported, true, exists = self.scored(truth, estimate)
        d = set_distances(estimated, true, self.gospa_c, self.gospa_p, estimate_valid=reported, truth_valid=exists)
        truth_id = np.where(exists, np.arange(exists.shape[-1]), -1)
        track_id = np.where(reported, estimate.track_id, -1)
        measures = track_measures(truth.time, true, truth_id, estimated, track_id, self.gospa_c, self.gospa_p,
                                  distances=d)
        count = reported.sum(axis=-1).astype(float)
        true_count = exists.sum(axis=-1).astype(float)
        out: dict[str, Any] = {
            "gospa": RunValues(d.gospa, "mean"), "gospa_localisation": RunValues(d.localisation, "mean"),
            "gospa_missed": RunValues(d.missed, "mean"), "gospa_false": RunValues(d.false, "mean"),
            "ospa": RunValues(d.ospa, "mean"), "cardinality": RunValues(count, "mean"),
            "true_cardinality": RunValues(true_count, "mean"),
            "cardinality_error": RunValues(count - true_count, "mean"),
            "missed_targets": RunValues(d.missed_count.astype(float), "mean"),
            "false_targets": RunValues(d.false_count.astype(float), "mean"),
            "track_switches": RunValues(measures.switches.astype(float), "mean"),
            "track_breaks": RunValues(measures.breaks.astype(float), "mean"),
        }
        out["position_rmse"] = paired_position_rmse(estimated, true, d.pairing)
        if "cardinality" in estimate.extras:
            out["phd_cardinality"] = RunValues(np.asarray(estimate.extras["cardinality"], dtype=float), "mean")
        self._measures = (id(estimate), measures)
        return out

    def settled_steps(self, truth: Truth) -> np.ndarray:
        """Scans at least ``settle_scans`` after every change of the true number of targets (in any run),
        the first scan counting as a change (the targets born there)."""
        count = alive(truth).sum(axis=-1)                                  # (R, K)
        K = count.shape[1]
        change = np.zeros(K, dtype=bool)
        change[0] = True
        change[1:] = np.any(count[:, 1:] != count[:, :-1], axis=0)
        unsettled = np.zeros(K, dtype=bool)
        for k in np.nonzero(change)[0]:
            unsettled[k:k + self.settle_scans] = True
        return np.nonzero(~unsettled)[0]

    def variant_summary(self, inputs: VariantInputs) -> list[dict]:
        truth, key, display, estimate = inputs.truth, inputs.key, inputs.display, inputs.estimate
        runs, sensor, metrics = inputs.runs, inputs.sensor, inputs.metrics
        rows = []
        # per_step_metrics of this same estimate ran just before (the runner's order); else run it again
        if getattr(self, "_measures", (None,))[0] != id(estimate):
            self.per_step_metrics(truth, estimate, sensor)
        measures = self._measures[1]
        self._measures = (None, None)

        def add(series: str, window: str, values: np.ndarray, steps, over: str = "mean", across: str = "mean"):
            rows.append(summary_row(key, display, series, window, None, runs,
                                    WindowStatistic(RunValues(values, across), steps, over)))

        whole = [0]
        add("false_tracks", "run", measures.false_tracks.astype(float)[:, None], whole)
        add("tracks_reported", "run", measures.tracks.astype(float)[:, None], whole)
        add("track_purity", "run", measures.purity[:, None], whole)
        add("confirmation_delay", "run", measures.mean_confirmation_delay[:, None], whole)
        settled = self.settled_steps(truth)
        error = metrics["cardinality_error"].values
        if settled.size:
            window = f"settled ({self.settle_scans} scans after each change)"
            add("cardinality_excess_settled", window, error, settled, "max")
            add("cardinality_shortfall_settled", window, -error, settled, "max")
        self._gospa_per_run[key] = np.asarray(metrics["gospa"].values, dtype=float)
        return rows

    def extra_summary(self, inputs: JobInputs) -> list[dict]:
        truth, display, runs = inputs.truth, inputs.display, inputs.runs
        rows = []
        steps = np.arange(truth.time.size)
        for key, other in self.paired.items():
            if key in self._gospa_per_run and other in self._gospa_per_run:
                difference = self._gospa_per_run[key] - self._gospa_per_run[other]
                with quiet_nanmean():
                    rows.append(summary_row(key, display[key], "gospa_paired_difference", f"minus {other}", None, runs,
                                            WindowStatistic(RunValues(difference, "mean"), steps, "mean")))
        return rows

    # ---- record ----------------------------------------------------------------------------------------
    def record(self, path, inputs: RecordingInputs) -> None:
        from pipeline.studies.multitarget.recording import write_multitarget_recording
        write_multitarget_recording(path, gospa_c=self.gospa_c, gospa_p=self.gospa_p, **inputs.common())


def paired_position_rmse(estimated: np.ndarray, true: np.ndarray, pairing: np.ndarray) -> RunValues:
    """Position RMSE of the tracked targets: over the (track, truth) pairs the GOSPA assignment made at
    d < c, sqrt(sum of squared position errors / number of pairs), pooled over the runs at each scan
    (``RunValues`` rms with the pair count as the weight); a run with no pair at a scan has no value
    there. The same quantity as a single-target study's ``position_rmse``, for the targets a tracker
    holds: what it misses or invents is GOSPA's missed and false parts, not this."""
    pairs = pairing >= 0                                                    # (R, K, N)
    partner = np.take_along_axis(estimated, np.maximum(pairing, 0)[..., None], axis=2)
    squared = np.where(pairs, np.sum((partner - np.nan_to_num(true)) ** 2, axis=-1), 0.0).sum(axis=-1)
    count = pairs.sum(axis=-1)
    return RunValues(np.where(count > 0, squared, np.nan), "rms", weights=count.astype(float))


@dataclass(frozen=True)
class StudyDetectionSets(DetectionSets):
    """The study's ``DetectionSets``, which a chunked track stage (``mc.chunk_runs``) can cut into runs."""

    def select(self, runs: Sequence[int]) -> "StudyDetectionSets":
        index = np.asarray(list(runs), dtype=int)
        return replace(self, z=self.z[index], count=self.count[index])


def detection_sets(detections: Detections, noise_covariance: np.ndarray) -> StudyDetectionSets:
    """``DetectionSets`` of the detections: filled slots first (as the sensor writes them), their count."""
    filled = np.asarray(detections.detected, dtype=bool)
    count = filled.sum(axis=-1)
    if np.any(np.cumsum(~filled, axis=-1)[filled] > 0):
        raise ValueError("detections: filled slots must come first in every scan (filters.multitarget.DetectionSets)")
    return StudyDetectionSets(np.asarray(detections.time, dtype=float), np.where(filled[..., None], detections.z, np.nan),
                         count.astype(np.int64), noise_covariance, STATE_NAMES, POSITION_INDEX)
