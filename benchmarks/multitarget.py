"""The multi-target trackers on the Vo-Vo scenario: our batched trackers and Stone Soup's GNN and
GM-PHD on the same detections, in the same process; where our time goes.

Run from the repository root (Stone Soup from the [stonesoup] extra):

    .venv/bin/python benchmarks/multitarget.py --runs 100 --clutter 10 --stonesoup-runs 3

Scenario (``vo_vo``): the four-birth linear scenario of the RFS literature's released code (issue 41
item 2a): 100 scans at T = 1 s, 12 noiseless CV targets born at k = 1, 1, 1, 20, 20, 20, 40, 40, 60,
60, 80, 80 (1-based; targets 1 and 3 die after k = 70), region [-1000, 1000]^2 m, P_D = 0.98,
R = 10^2 I, Poisson clutter of ``--clutter`` points a scan, uniform on the region. Made here with
numpy (seed ``--seed``); the study package draws its own.

Trackers (filters.multitarget): GNN, JPDA, IMM-GNN, IMM-JPDA (4-of-5 confirmation, deletion after 3
misses) and GM-PHD (the scenario's four births, Vo & Ma's T, U, J_max), with the scenario's
clutter density. Each is run once on 2 runs first (numba's start), then timed on all runs: its
``compute_seconds`` (the run call's filtering). ``--profile`` adds where GNN's and JPDA's time goes
(gating, assignment, the bare linear_sum_assignment calls, prediction, update, the rest).

Stone Soup 1.9.1, on the first ``--stonesoup-runs`` runs of the same detections (it runs one object
graph per run; its time is per run, scaled to ``--runs`` for the ratio):

- GNN: KalmanPredictor/KalmanUpdater on the same CV model (a LinearGaussianTransitionModel subclass
  with F and Q = sigma_v^2 G G' of filters.models), DistanceHypothesiser (Mahalanobis, the same
  gate), GNNWith2DAssignment, MultiMeasurementInitiator (min_points 4, holding tracks deleted
  after 2 scans without update, prior velocity std 15 m/s as ours: single-point initiation),
  UpdateTimeStepsDeleter(3), MultiTargetTracker;
- GM-PHD: the same models, GaussianMixtureHypothesiser over a DistanceHypothesiser with no gate
  (as Vo & Ma), PHDUpdater, GaussianMixtureReducer(T = 1e-5, U = 4, J_max = 100); the four birth
  components (Stone Soup's PointProcessMultiTargetTracker takes one) appended at each scan's time
  and extraction at w > 0.5, in a loop over its components here.

Also reported: mean GOSPA (c = 100 m, p = 2) over the Stone Soup runs for both, as a check that the
two do the same job (not a comparison of accuracy: their initiation and reduction differ in detail).
The results go to benchmarks/results/multitarget.md (and .json; ``--results-dir`` elsewhere) with the
date, commit, machine and load, through benchmarks/results_file.py.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402
from filters.models import acceleration_input_gain, constant_velocity_transition  # noqa: E402
from filters.multitarget import association, motion  # noqa: E402
from filters.multitarget.base import DetectionSets  # noqa: E402
from filters.multitarget.gmphd import GMPHD, VO_MA_BIRTHS  # noqa: E402
from filters.multitarget.metrics import set_distances  # noqa: E402
from filters.multitarget.trackers import GNN, IMMGNN, IMMJPDA, JPDA  # noqa: E402

HALF_WIDTH = 1000.0
NOISE_STD = 10.0
# (x, vx, y, vy), birth and death scan (1-based, inclusive) of the released code's gen_truth
VO_VO_TARGETS = (
    ((0.0, 0.0, 0.0, -10.0), 1, 70), ((400.0, -10.0, -600.0, 5.0), 1, 100), ((-800.0, 20.0, -200.0, -5.0), 1, 70),
    ((400.0, -7.0, -600.0, -4.0), 20, 100), ((400.0, -2.5, -600.0, 10.0), 20, 100), ((0.0, 7.5, 0.0, -5.0), 20, 100),
    ((-800.0, 12.0, -200.0, 7.0), 40, 100), ((-200.0, 15.0, 800.0, -10.0), 40, 100),
    ((-800.0, 3.0, -200.0, 15.0), 60, 100), ((-200.0, -3.0, 800.0, -15.0), 60, 100),
    ((0.0, -20.0, 0.0, -15.0), 80, 100), ((-200.0, 15.0, 800.0, -5.0), 80, 100),
)


def vo_vo(runs: int, clutter: float, seed: int = 1, scans: int = 100, detection_probability: float = 0.98):
    """truth (K, 12, 4) NaN where absent and DetectionSets (R, K, D, 2); the module docstring's scenario."""
    rng = np.random.default_rng(seed)
    F = constant_velocity_transition(1.0)
    truth = np.full((scans, len(VO_VO_TARGETS), 4), np.nan)
    for t, (start, born, dies) in enumerate(VO_VO_TARGETS):
        x = np.array(start)
        for k in range(born - 1, min(dies, scans)):
            truth[k, t] = x
            x = F @ x
    present = np.isfinite(truth[..., 0])
    seen = present[None] & (rng.random((runs, scans, len(VO_VO_TARGETS))) < detection_probability)
    n_clutter = rng.poisson(clutter, (runs, scans))
    D = int((seen.sum(-1) + n_clutter).max())
    z = np.full((runs, scans, D, 2), np.nan)
    count = np.zeros((runs, scans), np.int64)
    for r in range(runs):
        for k in range(scans):
            points = truth[k, seen[r, k]][:, [0, 2]] + rng.normal(0.0, NOISE_STD, (seen[r, k].sum(), 2))
            points = np.concatenate([points, rng.uniform(-HALF_WIDTH, HALF_WIDTH, (n_clutter[r, k], 2))])
            z[r, k, : len(points)] = rng.permutation(points)
            count[r, k] = len(points)
    return truth, DetectionSets(np.arange(scans, dtype=float), z, count, NOISE_STD**2 * np.eye(2),
                                ("x", "vx", "y", "vy"), (0, 2))


def clutter_density(clutter: float) -> float:
    return max(clutter, 0.1) / (2 * HALF_WIDTH) ** 2


def ours(clutter: float) -> dict:
    kappa = clutter_density(clutter)
    births = [(m[0], 0.0, m[2], 0.0) for m in VO_MA_BIRTHS]
    return {"GNN": GNN(clutter_density=kappa), "JPDA": JPDA(clutter_density=kappa),
            "IMM-GNN": IMMGNN(clutter_density=kappa), "IMM-JPDA": IMMJPDA(clutter_density=kappa),
            "GM-PHD": GMPHD(birth_means=births, clutter_density=kappa)}


def subset(detections: DetectionSets, runs: int) -> DetectionSets:
    return DetectionSets(detections.time, detections.z[:runs], detections.count[:runs],
                         detections.noise_covariance, detections.state_names, detections.position_index)


def mean_gospa(estimates: np.ndarray, truth: np.ndarray) -> float:
    """Mean GOSPA (c = 100, p = 2) of (R, K, M, 2) estimates against the (K, T, 4) truth."""
    R = estimates.shape[0]
    truths = np.broadcast_to(truth[None][..., [0, 2]], (R,) + truth.shape[:2] + (2,))
    return float(set_distances(estimates, truths, c=100.0, p=2.0).gospa.mean())


# ---- where the time goes -------------------------------------------------------------------------

class Timers:
    """Wraps module functions with wall-clock accumulators for one call of a tracker."""

    def __init__(self):
        self.spent: dict[str, float] = {}
        self._saved: list[tuple[object, str, object]] = []

    def wrap(self, owner, name, label):
        original = getattr(owner, name)

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.spent[label] = self.spent.get(label, 0.0) + time.perf_counter() - start
        self._saved.append((owner, name, original))
        setattr(owner, name, timed)

    def restore(self):
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)


def profile(tracker, detections) -> dict[str, float]:
    from filters.multitarget import trackers as tracker_module

    timers = Timers()
    timers.wrap(tracker_module, "gate", "gating")
    timers.wrap(tracker_module, "gnn_assign", "association (GNN, per run)")
    timers.wrap(tracker_module, "jpda_weights", "association (JPDA marginals)")
    timers.wrap(association, "linear_sum_assignment", "  of which linear_sum_assignment")
    timers.wrap(type(tracker.motion), "predict", "prediction")
    timers.wrap(type(tracker.motion), "update", "update")
    try:
        result = tracker.run(detections)
    finally:
        timers.restore()
    spent = dict(timers.spent)
    order = ["prediction", "gating", "association (GNN, per run)", "association (JPDA marginals)",
             "  of which linear_sum_assignment", "update"]
    out = {"total": result.compute_seconds}
    out.update({k: spent[k] for k in order if k in spent})
    out["rest (management, births, output)"] = result.compute_seconds - sum(
        v for k, v in spent.items() if not k.startswith(" "))
    return out


# ---- Stone Soup ------------------------------------------------------------------------------------

def stonesoup_parts():
    """The Stone Soup classes used, imported here (Stone Soup is an optional extra)."""
    from stonesoup.base import Property
    from stonesoup.buffered_generator import BufferedGenerator
    from stonesoup.models.transition.linear import LinearGaussianTransitionModel
    from stonesoup.reader.base import DetectionReader
    from stonesoup.types.array import CovarianceMatrix

    class DiscreteWhiteAccelerationCV(LinearGaussianTransitionModel):
        """CV in (x, vx, y, vy) with Q = sigma^2 G G' (filters.models), as our trackers use."""

        sigma: float = Property(doc="acceleration standard deviation [m/s^2]")

        @property
        def ndim_state(self):
            return 4

        def matrix(self, time_interval, **kwargs):
            return constant_velocity_transition(time_interval.total_seconds())

        def covar(self, time_interval, **kwargs):
            G = acceleration_input_gain(time_interval.total_seconds())
            return CovarianceMatrix(self.sigma**2 * G @ G.T)

    class ScanReader(DetectionReader):
        """Prepared (time, set of Detection) scans as a Stone Soup detection reader."""

        scans: list = Property(doc="(timestamp, detections) per scan")

        @BufferedGenerator.generator_method
        def detections_gen(self):
            yield from self.scans

    return DiscreteWhiteAccelerationCV, ScanReader


def stonesoup_scans(detections: DetectionSets, r: int, measurement_model):
    from stonesoup.types.detection import Detection

    start = datetime.datetime(2026, 1, 1)
    scans = []
    for k, t in enumerate(detections.time):
        when = start + datetime.timedelta(seconds=float(t))
        zs = detections.z[r, k, : detections.count[r, k]]
        scans.append((when, {Detection(v.reshape(2, 1), timestamp=when, measurement_model=measurement_model)
                             for v in zs}))
    return scans


def stonesoup_gnn(detections: DetectionSets, r: int, gate: float) -> np.ndarray:
    """Stone Soup's GNN tracker on run r: confirmed track positions (K, M, 2), NaN-padded."""
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.simple import MultiTargetTracker
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import KalmanUpdater

    CV, ScanReader = stonesoup_parts()
    measurement_model = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=detections.noise_covariance)
    predictor = KalmanPredictor(CV(sigma=5.0))
    updater = KalmanUpdater(measurement_model)
    hypothesiser = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=np.sqrt(gate))
    associator = GNNWith2DAssignment(hypothesiser)
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([0.0, 15.0**2, 0.0, 15.0**2])),
        deleter=UpdateTimeStepsDeleter(2), data_associator=associator, updater=updater,
        measurement_model=measurement_model, min_points=4)
    tracker = MultiTargetTracker(initiator=initiator, deleter=UpdateTimeStepsDeleter(3),
                                 detector=ScanReader(stonesoup_scans(detections, r, measurement_model)),
                                 data_associator=associator, updater=updater)
    out = []
    for _, tracks in tracker:
        out.append([np.asarray(track.state_vector, dtype=float)[[0, 2], 0] for track in tracks])
    return _pad(out)


def stonesoup_gmphd(detections: DetectionSets, r: int, kappa: float, births) -> tuple[np.ndarray, np.ndarray]:
    """Stone Soup's GM-PHD components on run r: extracted positions (K, M, 2) and sum of weights (K,)."""
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.gaussianmixture import GaussianMixtureHypothesiser
    from stonesoup.measures import Mahalanobis
    from stonesoup.mixturereducer.gaussianmixture import GaussianMixtureReducer
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.types.state import TaggedWeightedGaussianState
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.pointprocess import PHDUpdater

    CV, _ = stonesoup_parts()
    measurement_model = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=detections.noise_covariance)
    predictor = KalmanPredictor(CV(sigma=5.0))
    updater = KalmanUpdater(measurement_model)
    hypothesiser = GaussianMixtureHypothesiser(
        DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=1e12), order_by_detection=True)
    phd = PHDUpdater(updater, clutter_spatial_density=kappa, prob_detection=0.98, prob_survival=0.99)
    reducer = GaussianMixtureReducer(prune_threshold=1e-5, merge_threshold=4.0, max_number_components=100)
    components: list = []
    out, cardinality = [], []
    for when, dets in stonesoup_scans(detections, r, measurement_model):
        for mean in births:
            components.append(TaggedWeightedGaussianState(np.reshape(mean, (4, 1)), np.diag([100.0] * 4), weight=0.03,
                                                          tag=TaggedWeightedGaussianState.BIRTH, timestamp=when))
        hypotheses = hypothesiser.hypothesise(components, dets, when)
        components = list(reducer.reduce(list(phd.update(hypotheses))))
        cardinality.append(sum(float(c.weight) for c in components))
        out.append([np.asarray(c.state_vector, dtype=float)[[0, 2], 0] for c in components for _ in
                    range(int(np.rint(float(c.weight)))) if float(c.weight) > 0.5])
    return _pad(out), np.array(cardinality)


def _pad(scans: list[list[np.ndarray]]) -> np.ndarray:
    width = max([len(s) for s in scans] + [1])
    out = np.full((len(scans), width, 2), np.nan)
    for k, points in enumerate(scans):
        if points:
            out[k, : len(points)] = points
    return out


# ---- the run -------------------------------------------------------------------------------------

def main(argv=None) -> int:
    context = start("benchmarks/multitarget.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--clutter", type=float, nargs="+", default=[10.0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--stonesoup-runs", type=int, default=3)
    parser.add_argument("--profile", action="store_true")
    add_results_argument(parser)
    args = parser.parse_args(argv)
    columns = [Column("tracker", "tracker"), Column("ours", "ours", "seconds", ".2f"),
               Column("vs_gnn", "vs our GNN", "ratio", ".1f"), Column("gospa", "GOSPA (ours, all runs)", "number", ".1f"),
               Column("theirs_per_run", "Stone Soup per run", "seconds", ".2f"),
               Column("theirs_scaled", f"Stone Soup x {args.runs} runs", "seconds", ".0f"),
               Column("ratio", "Stone Soup / ours", "ratio", ".0f"),
               Column("gospa_pair", "GOSPA on the Stone Soup runs (ours / theirs)")]
    tables, notes = [], [f"Our time: the tracker's compute_seconds (filtering only) on all runs in one call, after one "
                         f"untimed call on 2 runs (numba's start); Stone Soup: per run on its first "
                         f"{args.stonesoup_runs} runs, scaled to {args.runs} runs for the ratio.",
                         "GOSPA: c = 100 m, p = 2, the mean over runs and scans; a check that the two do the same "
                         "job, not a comparison of accuracy."]
    for clutter in args.clutter:
        truth, detections = vo_vo(args.runs, clutter, args.seed)
        kappa = clutter_density(clutter)
        trackers = ours(clutter)
        rows = []
        print(f"clutter {clutter:g} a scan (kappa = {kappa:.3g} m^-2); up to {detections.z.shape[2]} detections a scan")
        for name, tracker in trackers.items():
            tracker.run(subset(detections, 2))                       # numba's start, off the clock
            result = tracker.run(detections)
            estimates = np.where(result.confirmed[..., None], result.state[..., [0, 2]], np.nan)
            row = {"tracker": name, "ours": result.compute_seconds, "gospa": mean_gospa(estimates, truth)}
            if args.stonesoup_runs > 0 and name in ("GNN", "GM-PHD"):
                try:
                    import stonesoup  # noqa: F401
                except ImportError:
                    pass
                else:
                    started = time.perf_counter()
                    if name == "GNN":
                        got = [stonesoup_gnn(detections, r, tracker.threshold) for r in range(args.stonesoup_runs)]
                    else:
                        births = [(m[0], 0.0, m[2], 0.0) for m in VO_MA_BIRTHS]
                        got = [stonesoup_gmphd(detections, r, kappa, births)[0] for r in range(args.stonesoup_runs)]
                    per_run = (time.perf_counter() - started) / args.stonesoup_runs
                    width = max(g.shape[1] for g in got)
                    stacked = np.full((len(got), 100, width, 2), np.nan)
                    for i, g in enumerate(got):
                        stacked[i, :, : g.shape[1]] = g
                    small_ours = estimates[: args.stonesoup_runs]
                    row.update({"theirs_per_run": per_run, "theirs_scaled": per_run * args.runs,
                                "ratio": per_run * args.runs / result.compute_seconds,
                                "gospa_pair": f"{mean_gospa(small_ours, truth):.1f} / {mean_gospa(stacked, truth):.1f}"})
            rows.append(row)
            print(row, flush=True)
        gnn = next(r["ours"] for r in rows if r["tracker"] == "GNN")
        for row in rows:
            row["vs_gnn"] = row["ours"] / gnn
        tables.append(Table(columns, rows, f"Clutter {clutter:g} a scan (kappa = {kappa:.3g} m^-2); up to "
                                           f"{detections.z.shape[2]} detections a scan:"))
        if args.profile:
            for name in ("GNN", "JPDA", "IMM-GNN"):
                spent = profile(ours(clutter)[name], detections)
                total = spent.pop("total")
                parts = ", ".join(f"{k.strip()} {100 * v / total:.0f} %" for k, v in spent.items())
                notes.append(f"clutter {clutter:g}, where {name}'s time goes (one call on all runs, share of its "
                             f"compute_seconds): {parts}")
                print(notes[-1], flush=True)
    write_result("multitarget", f"Multi-target trackers on the Vo-Vo scenario ({args.runs} runs x 100 scans)",
                 tables, notes, context=context,
                 parameters={"runs": args.runs, "scans": 100, "clutter a scan": ", ".join(f"{c:g}" for c in args.clutter),
                             "Stone Soup runs": args.stonesoup_runs, "seed": args.seed},
                 directory=args.results_dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
