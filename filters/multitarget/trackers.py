"""Association trackers: GNN and JPDA with M-of-N track management, each with a CV Kalman track
filter or the project's CV/CT IMM (IMM-GNN, IMM-JPDA), batched over Monte Carlo runs.

Per scan k (time step T = t_k - t_{k-1}), over every run's track slots at once:

1. predict every track (``motion.predict``; filters.multitarget.motion);
2. gate every (run, track, detection) pair (filters.multitarget.association.gate);
3. associate: GNN, one 2-D assignment per run (association.gnn_assign); JPDA, the exact marginals
   per cluster with the Murty fallback (association.jpda_weights);
4. update every track with its association weights (the PDA form; GNN's are one-hot);
5. manage tracks (``TrackManagement``): a track is *hit* at a scan when a detection is assigned to
   it (GNN) or when it is more likely detected than not, beta_0 < 1/2 (JPDA: "some detection in the
   gate" would keep a coasting track alive on the clutter its growing gate collects); detections not assigned (GNN) / in no track's gate (JPDA)
   start tentative tracks (single-point initiation, ``motion.start``);
6. report the confirmed tracks (and the tentative ones with ``report_tentative``).

Only step 3 loops over runs, on the runs whose gates hold a contested detection.

Track management (M-of-N; Blackman & Popoli 1999, 6.3): a tentative track is confirmed once
``confirm_hits`` of its first ``confirm_window`` scans (the starting one counted as a hit) were
hits; it is deleted as soon as that can no longer happen (after ``confirm_window`` scans at the
latest). A confirmed track is deleted after ``delete_misses`` consecutive scans without a hit.
Track ids count from 0 per run in order of initiation; a deleted track's id is never reused.

The defaults (4 of 5, delete after 3, initial velocity std 15 m/s: three quarters of the fastest
Vo-Vo target's 20 m/s per axis, the 0.999 gate then spans some 55 m/s) suit light clutter (about 10
points a scan on the Vo-Vo region [-1000, 1000]^2; 30 m/s gave a worse GOSPA there for every
tracker, JPDA 57.8 against 44.9 on 10 runs). At 50 a scan single-point starts collect clutter in
their first wide gates and 4 of 5 confirms many of them (5 runs of benchmarks/multitarget.py,
2026-12-04, mean GOSPA: GNN 146 with 4 of 5, 80 with 6 of 8; JPDA 245 and 174): use a longer M of N
in dense clutter.

Output (TrackSets): state/covariance in DetectionSets.state_names (components the motion lacks
are NaN); ``existence`` NaN (these trackers carry no existence probability); extras:
``tracks_tentative`` (R, K) tentative tracks alive after the scan; JPDA adds ``events`` (joint
events enumerated) and ``approximated_clusters`` (clusters given to Murty) per (run, scan); the
IMM variants ``mode_probabilities`` (R, K, M, 2) of (CV, CT).
"""

from __future__ import annotations

import time as clock

import numpy as np
from scipy.stats import chi2

from filters.multitarget.association import gate, gnn_assign, jpda_weights, likelihood_ratios
from filters.multitarget.base import POSITION_SETS, DetectionSets, MultiTargetTracker, TrackSets
from filters.multitarget.motion import ConstantVelocity, InteractingCVTurn
from filters.progress import counted


def _probability(value: object, key: str, open_top: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value <= 1
    if not ok or (open_top and value >= 1):
        raise ValueError(f"{key}: {value!r} must be a probability in (0, {'1)' if open_top else '1]'}")
    return float(value)


def _count(value: object, key: str, least: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise ValueError(f"{key}: {value!r} must be a whole number >= {least}")
    return int(value)


class TrackManagement:
    """M-of-N confirmation and deletion (module docstring), on (R, M) arrays of hit bits and counts."""

    def __init__(self, confirm_hits: int = 4, confirm_window: int = 5, delete_misses: int = 3) -> None:
        self.confirm_hits = _count(confirm_hits, "confirm_hits")
        self.confirm_window = _count(confirm_window, "confirm_window")
        self.delete_misses = _count(delete_misses, "delete_misses")
        if self.confirm_hits > self.confirm_window:
            raise ValueError(f"confirm_hits: {confirm_hits} must be <= confirm_window ({confirm_window}): "
                             f"M of N needs M <= N")

    def step(self, hit, alive, confirmed, hits, age, misses):
        """One scan's bookkeeping of the tracks alive before it: returns (alive, confirmed, hits, age, misses)."""
        hits = np.where(alive, hits + hit, hits)
        age = np.where(alive, age + 1, age)
        misses = np.where(alive & ~hit, misses + 1, 0)
        tentative = alive & ~confirmed
        confirmed = confirmed | (tentative & (hits >= self.confirm_hits))
        hopeless = tentative & ~confirmed & (hits + (self.confirm_window - age) < self.confirm_hits)
        lost = confirmed & (misses >= self.delete_misses)
        return alive & ~hopeless & ~lost, confirmed & alive & ~lost, hits, age, misses


class _AssociationTracker(MultiTargetTracker):
    accepts = frozenset({POSITION_SETS})
    association = "gnn"

    def __init__(self, name: str, motion: object, detection_probability: float = 0.98,
                 gate_probability: float = 0.999, clutter_density: float = 12.5e-6, confirm_hits: int = 4,
                 confirm_window: int = 5, delete_misses: int = 3, report_tentative: bool = False,
                 max_events: float = 100000.0, k_best: int = 50) -> None:
        self.name = name
        self.motion = motion
        self.detection_probability = _probability(detection_probability, "detection_probability")
        self.gate_probability = _probability(gate_probability, "gate_probability", open_top=True)
        if not (isinstance(clutter_density, (int, float)) and np.isfinite(clutter_density) and clutter_density > 0):
            raise ValueError(f"clutter_density: {clutter_density!r} must be a finite density > 0 [1/m^2] "
                             f"(clutter rate / surveillance area)")
        self.clutter_density = float(clutter_density)
        self.management = TrackManagement(confirm_hits, confirm_window, delete_misses)
        self.report_tentative = bool(report_tentative)
        if not (isinstance(max_events, (int, float)) and max_events >= 1):
            raise ValueError(f"max_events: {max_events!r} must be a number >= 1 (joint events per cluster "
                             f"enumerated exactly; wider clusters use Murty's k best)")
        self.max_events = float(max_events)
        self.k_best = _count(k_best, "k_best")
        self.threshold = float(chi2.ppf(self.gate_probability, 2))

    def run(self, detections: DetectionSets) -> TrackSets:
        if not isinstance(detections, DetectionSets):
            raise TypeError(f"{self.name}: takes {sorted(self.accepts)} (a DetectionSets), "
                            f"not {type(detections).__name__}")
        if detections.z.shape[-1] != 2:
            raise ValueError(f"{self.name}: detections must be 2-D positions (m = 2), not m = {detections.z.shape[-1]}")
        missing = [name for name in ("x", "y") if name not in tuple(detections.state_names)]
        if missing:
            raise ValueError(f"{self.name}: detections.state_names {tuple(detections.state_names)} lack {missing}; "
                             f"these trackers estimate (x, vx, y, vy) from (x, y) position detections")
        if self.association == "jpda":
            from filters.multitarget import kernel
            kernel.warm_up()                      # numba's start before the clock
        started = clock.perf_counter()
        times = np.asarray(detections.time, dtype=float)
        z = np.asarray(detections.z, dtype=float)
        R, K, D, _ = z.shape
        valid = np.arange(D)[None, None, :] < np.asarray(detections.count)[..., None]
        noise = np.asarray(detections.noise_covariance, dtype=float)
        motion, manage = self.motion, self.management
        M = 4
        state = motion.empty(R, M)
        alive = np.zeros((R, M), bool)
        confirmed = np.zeros((R, M), bool)
        hits = np.zeros((R, M), np.int64)
        age = np.zeros((R, M), np.int64)
        misses = np.zeros((R, M), np.int64)
        ids = np.full((R, M), -1, np.int64)
        next_id = np.zeros(R, np.int64)
        miss_weight = 1.0 - self.detection_probability * self.gate_probability
        out = []
        tentative_count = np.zeros((R, K), np.int64)
        events = np.zeros((R, K))
        approximated = np.zeros((R, K), np.int64)
        for k in counted(range(K), "scan", self.name):
            zk, vk = z[:, k], valid[:, k]
            if k > 0 and alive.any():
                state = motion.predict(state, float(times[k] - times[k - 1]))
                zhat, S = motion.predicted_measurement(state, noise)
                d2, gated, logdet = gate(zhat, S, zk, vk, alive, self.threshold)
                if self.association == "gnn":
                    assigned = gnn_assign(d2 + logdet[..., None], gated)
                    hit = assigned >= 0
                    candidates = zk[np.arange(R)[:, None], np.maximum(assigned, 0)][:, :, None]   # (R, M, 1, 2)
                    beta = hit[..., None].astype(float)
                    beta0 = 1.0 - beta[..., 0]
                    used = np.zeros((R, D), bool)
                    rr, tt = np.nonzero(hit)
                    used[rr, assigned[rr, tt]] = True
                    weight0, weights = beta0, beta
                else:
                    g = likelihood_ratios(d2, logdet, gated, self.detection_probability, self.clutter_density)
                    beta, beta0, counts = jpda_weights(g, miss_weight, self.max_events, self.k_best)
                    events[:, k], approximated[:, k] = counts["events"], counts["approximated_clusters"]
                    hit = beta0 < 0.5                  # more likely detected than not
                    used = gated.any(axis=1)
                    weight0 = np.full((R, alive.shape[1]), miss_weight)
                    weights = np.where(gated, self.detection_probability / self.clutter_density, 0.0)
                    # each track's gated detections only (the rest have beta 0): (R, M, widest gate)
                    width = max(int(gated.sum(axis=2).max()), 1)
                    pick = np.argsort(~gated, axis=2, kind="stable")[:, :, :width]
                    candidates = zk[np.arange(R)[:, None, None], pick]
                    beta, weights = (np.take_along_axis(a, pick, axis=2) for a in (beta, weights))
                state = motion.update(state, candidates, noise, beta, beta0, weight0, weights)
                alive, confirmed, hits, age, misses = manage.step(hit, alive, confirmed, hits, age, misses)
            else:
                used = np.zeros((R, D), bool)
            # births: one tentative track per unused detection
            start = vk & ~used
            need = start.sum(axis=1)
            free = (~alive).sum(axis=1)
            if (need > free).any():
                grow = int((need - free).max())
                alive, confirmed = (np.pad(a, ((0, 0), (0, grow))) for a in (alive, confirmed))
                hits, age, misses = (np.pad(a, ((0, 0), (0, grow))) for a in (hits, age, misses))
                ids = np.pad(ids, ((0, 0), (0, grow)), constant_values=-1)
                extra = motion.empty(R, grow)
                state = {key: np.concatenate([state[key], extra[key]], axis=1) for key in state}
            if need.any():
                runs, cols = np.nonzero(start)
                rank = np.arange(runs.size) - np.searchsorted(runs, runs)
                slots = np.argsort(alive, axis=1, kind="stable")[runs, rank]
                fresh = motion.start(zk[runs, cols], noise)
                for key in state:
                    state[key][runs, slots] = fresh[key]
                alive[runs, slots] = True
                confirmed[runs, slots] = manage.confirm_hits <= 1
                hits[runs, slots], age[runs, slots], misses[runs, slots] = 1, 1, 0
                ids[runs, slots] = next_id[runs] + rank
                next_id += need
            tentative_count[:, k] = (alive & ~confirmed).sum(axis=1)
            report = alive & (confirmed | self.report_tentative)
            out.append(self._snapshot(state, report, ids, confirmed))
        extras = {"tracks_tentative": tentative_count}
        if self.association == "jpda":
            extras.update(events=events, approximated_clusters=approximated)
        return self._stack(times, out, detections.state_names, extras, clock.perf_counter() - started)

    def _snapshot(self, state, report, ids, confirmed):
        width = int(report.sum(axis=1).max()) if report.size else 0
        order = np.argsort(~report, axis=1, kind="stable")[:, :width]
        rows = np.arange(report.shape[0])[:, None]
        x, P, names, extra = self.motion.estimate({key: value[rows, order] for key, value in state.items()})
        keep = report[rows, order]
        return keep, x, P, names, ids[rows, order], confirmed[rows, order], extra

    def _stack(self, times, out, wanted, extras, seconds) -> TrackSets:
        from filters.tracker import to_layout

        R, K = out[0][0].shape[0], len(out)
        M = max([o[0].shape[1] for o in out] + [1])
        n = len(wanted)
        state = np.full((R, K, M, n), np.nan)
        covariance = np.full((R, K, M, n, n), np.nan)
        track_id = np.full((R, K, M), -1, np.int64)
        confirmed = np.zeros((R, K, M), bool)
        modes = None
        for k, (keep, x, P, names, ids, conf, extra) in enumerate(out):
            w = keep.shape[1]
            if w == 0:
                continue
            xo, Po = to_layout(x, P, names, tuple(wanted))
            state[:, k, :w] = np.where(keep[..., None], xo, np.nan)
            covariance[:, k, :w] = np.where(keep[..., None, None], Po, np.nan)
            track_id[:, k, :w] = np.where(keep, ids, -1)
            confirmed[:, k, :w] = keep & conf
            if "mode_probabilities" in extra:
                if modes is None:
                    modes = np.full((R, K, M, 2), np.nan)
                modes[:, k, :w] = np.where(keep[..., None], extra["mode_probabilities"], np.nan)
        if isinstance(self.motion, InteractingCVTurn):
            extras["mode_probabilities"] = modes if modes is not None else np.full((R, K, M, 2), np.nan)
        return TrackSets(np.asarray(times).copy(), state, covariance, track_id, confirmed,
                         np.full((R, K, M), np.nan), extras, seconds)


class GNN(_AssociationTracker):
    """Global nearest neighbour tracker with a CV Kalman filter per track (module docstring).
    ``acceleration_std`` sigma_v [m/s^2] of the CV model, ``initial_velocity_std`` [m/s] of a new
    track; the other keywords are the association's and the track management's."""

    association = "gnn"

    def __init__(self, name: str = "GNN", acceleration_std: float = 5.0, initial_velocity_std: float = 15.0,
                 **options) -> None:
        super().__init__(name, ConstantVelocity(acceleration_std, initial_velocity_std), **options)


class JPDA(_AssociationTracker):
    """Joint probabilistic data association tracker with a CV Kalman filter per track: exact
    marginals per cluster up to ``max_events`` joint events, Murty's ``k_best`` beyond."""

    association = "jpda"

    def __init__(self, name: str = "JPDA", acceleration_std: float = 5.0, initial_velocity_std: float = 15.0,
                 **options) -> None:
        super().__init__(name, ConstantVelocity(acceleration_std, initial_velocity_std), **options)


_IMM_KEYS = ("cv_acceleration_density", "ct_acceleration_density", "turn_rate_density", "sojourn_times",
             "initial_mode_probabilities", "turn_rate_std")


def _imm_motion(initial_velocity_std, options):
    imm = {key: options.pop(key) for key in _IMM_KEYS if key in options}
    return InteractingCVTurn(initial_velocity_std, **imm)


class IMMGNN(_AssociationTracker):
    """GNN with the project's CV/CT IMM per track (filters.turn.CVCTIMM's keywords)."""

    association = "gnn"

    def __init__(self, name: str = "IMM-GNN", initial_velocity_std: float = 15.0, **options) -> None:
        super().__init__(name, _imm_motion(initial_velocity_std, options), **options)


class IMMJPDA(_AssociationTracker):
    """JPDA with the project's CV/CT IMM per track (IMM-PDA mode likelihoods, motion module docstring)."""

    association = "jpda"

    def __init__(self, name: str = "IMM-JPDA", initial_velocity_std: float = 15.0, **options) -> None:
        super().__init__(name, _imm_motion(initial_velocity_std, options), **options)
