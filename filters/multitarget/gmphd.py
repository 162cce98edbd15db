"""The Gaussian-mixture PHD filter (Vo & Ma, "The Gaussian Mixture Probability Hypothesis Density
Filter", IEEE TSP 54(11), 2006), batched over Monte Carlo runs.

The PHD (intensity) v_k(x) = sum_j w_j N(x; m_j, P_j) of every run is a padded mixture (R, J).
Linear Gaussian models (the paper's A.4-A.5): CV dynamics F, Q = sigma_v^2 G G' (filters.models),
positions z = H x + w, w ~ N(0, R); survival P_S and detection P_D constant; Poisson clutter of
intensity kappa(z) = ``clutter_density`` [1/m^2] (lambda_c / area); births a Gaussian mixture
gamma_k(x) = sum_b w_b N(x; m_b, P_b) (no spawning).

Prediction (Proposition 1)::

    v_{k|k-1}(x) = P_S sum_j w_j N(x; F m_j, F P_j F' + Q) + gamma_k(x)

Update (Proposition 2), with q_j(z) = N(z; H m_j, S_j), S_j = H P_j H' + R, K_j = P_j H' S_j^-1::

    v_k(x) = (1 - P_D) v_{k|k-1}(x) + sum_{z in Z_k} sum_j w_j(z) N(x; m_j + K_j (z - H m_j), (I - K_j H) P_j)
    w_j(z) = P_D w_j q_j(z) / (kappa(z) + P_D sum_l w_l q_l(z))

Pruning and merging (Table II): components of weight < ``prune_below`` (T) are dropped; from the
heaviest left, every component within Mahalanobis distance (m_i - m_j)' P_i^-1 (m_i - m_j) <=
``merge_within`` (U) is merged (moment-matched); the ``max_components`` (J_max) heaviest are kept
(filters.multitarget.kernel.merge_components, compiled, all runs in one call).

State extraction (Table III): each component with w > ``extract_above`` (0.5) gives round(w)
estimates at its mean. The expected number of targets is sum_j w_j (extra ``cardinality``).

Identity: the PHD has none; each component carries a label (births get fresh ones; an updated
component keeps its parent's; a merged one its heaviest member's), and an extracted estimate
reports its component's label as ``track_id`` (a second estimate of one label in a scan gets a new
label, kept by its component from then on). Labels count from 0 per run and are never reused.

Defaults are those of the four-birth linear scenario of the RFS literature's released code (the
"Vo-Vo" scenario of issue 41): four birth components of weight 0.03 at (0, 0), (400, -600),
(-800, -200), (-200, 800) m with zero velocity and P_b = diag(10, 10, 10, 10)^2 in (x, vx, y, vy);
P_S = 0.99, P_D = 0.98, sigma_v = 5 m/s^2; kappa = 12.5e-6 m^-2 (Vo & Ma 2006 Sec. IV: 50 clutter points
a scan on [-1000, 1000]^2; set it to lambda_c / area of the scenario run); T = 1e-5, U = 4, J_max = 100.

Output (TrackSets): the extracted estimates as confirmed tracks, existence = their component
weight; extras ``cardinality`` (R, K) sum of weights and ``components`` (R, K) after pruning/merging.
"""

from __future__ import annotations

import time as clock
from typing import Sequence

import numpy as np

from filters.kalman import LOG_2PI, inverse_and_logdet
from filters.models import acceleration_input_gain, constant_velocity_transition
from filters.multitarget.base import POSITION_SETS, DetectionSets, MultiTargetTracker, TrackSets
from filters.progress import counted

STATE_NAMES = ("x", "vx", "y", "vy")
VO_MA_BIRTHS = ((0.0, 0.0, 0.0, 0.0), (400.0, 0.0, -600.0, 0.0), (-800.0, 0.0, -200.0, 0.0), (-200.0, 0.0, 800.0, 0.0))


def ordered_sum(values: np.ndarray, axis: int) -> np.ndarray:
    """Sum over the component axis in index order. numpy's pairwise sum groups terms by the
    axis' length, and a batch pads every run to its widest, so ``ndarray.sum`` gave a run's
    weights a different rounding in a batch of 14 runs than of 13 (last-bit differences in
    the cardinality and every table after it). Zeros appended after the last term leave a
    running sum unchanged, whatever the padding."""
    return np.cumsum(values, axis=axis).take(-1, axis=axis) if values.shape[axis] else \
        np.zeros(values.shape[:axis] + values.shape[axis + 1:])


def _number(value: object, key: str, low: float = 0.0, high: float = np.inf, closed_low: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value) \
        and (value >= low if closed_low else value > low) and value <= high
    if not ok:
        bound = f"{'>=' if closed_low else '>'} {low:g}" + (f" and <= {high:g}" if np.isfinite(high) else "")
        raise ValueError(f"{key}: {value!r} must be a finite number {bound}")
    return float(value)


class GMPHD(MultiTargetTracker):
    """GM-PHD filter (module docstring), all runs at once."""

    accepts = frozenset({POSITION_SETS})

    def __init__(self, name: str = "GM-PHD", birth_means: Sequence[Sequence[float]] = VO_MA_BIRTHS,
                 birth_std: Sequence[float] = (10.0, 10.0, 10.0, 10.0), birth_weight: float = 0.03,
                 survival_probability: float = 0.99, detection_probability: float = 0.98,
                 acceleration_std: float = 5.0, clutter_density: float = 12.5e-6,
                 prune_below: float = 1e-5, merge_within: float = 4.0, max_components: int = 100,
                 extract_above: float = 0.5) -> None:
        self.name = name
        means = np.asarray(birth_means, dtype=float)
        if means.ndim != 2 or means.shape[1] != 4 or not np.isfinite(means).all():
            raise ValueError(f"birth_means: {birth_means!r} must be a list of (x, vx, y, vy) means")
        std = np.asarray(birth_std, dtype=float)
        if std.shape != (4,) or not (std > 0).all():
            raise ValueError(f"birth_std: {birth_std!r} must be four standard deviations > 0 of (x, vx, y, vy)")
        self.birth_means = means
        self.birth_covariance = np.diag(std**2)
        self.birth_weight = _number(birth_weight, "birth_weight")
        self.survival_probability = _number(survival_probability, "survival_probability", high=1.0)
        self.detection_probability = _number(detection_probability, "detection_probability", high=1.0)
        self.acceleration_std = _number(acceleration_std, "acceleration_std")
        self.clutter_density = _number(clutter_density, "clutter_density")
        self.prune_below = _number(prune_below, "prune_below", closed_low=True)
        self.merge_within = _number(merge_within, "merge_within", closed_low=True)
        if isinstance(max_components, bool) or not isinstance(max_components, (int, np.integer)) or max_components < 1:
            raise ValueError(f"max_components: {max_components!r} must be a whole number >= 1")
        self.max_components = int(max_components)
        self.extract_above = _number(extract_above, "extract_above", closed_low=True)

    def run(self, detections: DetectionSets) -> TrackSets:
        from filters.multitarget import kernel
        from filters.tracker import to_layout

        if not isinstance(detections, DetectionSets):
            raise TypeError(f"{self.name}: takes {sorted(self.accepts)} (a DetectionSets), "
                            f"not {type(detections).__name__}")
        missing = [name for name in ("x", "y") if name not in tuple(detections.state_names)]
        if missing:
            raise ValueError(f"{self.name}: detections.state_names {tuple(detections.state_names)} lack {missing}; "
                             f"these trackers estimate (x, vx, y, vy) from (x, y) position detections")
        kernel.warm_up()                                  # numba's start before the clock
        started = clock.perf_counter()
        times = np.asarray(detections.time, dtype=float)
        z = np.asarray(detections.z, dtype=float)
        R, K, D, _ = z.shape
        valid = np.arange(D)[None, None, :] < np.asarray(detections.count)[..., None]
        noise = np.asarray(detections.noise_covariance, dtype=float)
        H = np.zeros((2, 4))
        H[[0, 1], [0, 2]] = 1.0
        B = len(self.birth_means)
        Jmax = self.max_components
        w = np.zeros((R, 0))
        m = np.zeros((R, 0, 4))
        P = np.zeros((R, 0, 4, 4))
        label = np.zeros((R, 0), np.int64)
        next_label = np.zeros(R, np.int64)
        pd = self.detection_probability
        estimates = []
        cardinality = np.zeros((R, K))
        components = np.zeros((R, K), np.int64)
        for k in counted(range(K), "scan", self.name):
            # prediction (Proposition 1) and births
            if k > 0:
                dt = float(times[k] - times[k - 1])
                F = constant_velocity_transition(dt)
                G = acceleration_input_gain(dt)
                Q = self.acceleration_std**2 * G @ G.T
                w = self.survival_probability * w
                m = m @ F.T
                P = F @ P @ F.T + Q
            w = np.concatenate([w, np.full((R, B), self.birth_weight)], axis=1)
            m = np.concatenate([m, np.broadcast_to(self.birth_means, (R, B, 4))], axis=1)
            P = np.concatenate([P, np.broadcast_to(self.birth_covariance, (R, B, 4, 4))], axis=1)
            label = np.concatenate([label, next_label[:, None] + np.arange(B)], axis=1)
            next_label += B
            J = w.shape[1]
            # update (Proposition 2)
            zhat = m[..., [0, 2]]
            PHt = P[..., :, [0, 2]]
            S = PHt[..., [0, 2], :] + noise
            S_inv, logdet = inverse_and_logdet(S)
            gain = PHt @ S_inv                                                  # K_j (R, J, 4, 2)
            P_updated = P - gain @ np.swapaxes(PHt, -1, -2)
            P_updated = 0.5 * (P_updated + np.swapaxes(P_updated, -1, -2))
            nu = np.nan_to_num(z[:, k, None, :, :] - zhat[:, :, None, :])       # (R, J, D, 2)
            d2 = np.einsum("rjdm,rjmk,rjdk->rjd", nu, S_inv, nu)
            q = np.exp(-0.5 * (d2 + logdet[..., None] + 2 * LOG_2PI))
            numerator = np.where(valid[:, k, None, :], pd * w[..., None] * q, 0.0)
            w_z = numerator / (self.clutter_density + ordered_sum(numerator, axis=1)[:, None])
            # candidates: slot 0 the missed-detection copy, slots 1..D the updates
            cand_w = np.concatenate([(1.0 - pd) * w[..., None], w_z], axis=2).reshape(R, J * (D + 1))
            keep = cand_w >= self.prune_below
            count = keep.sum(axis=1)
            width = max(int(count.max()), 1)
            order = np.argsort(~keep, axis=1, kind="stable")[:, :width]
            rows = np.arange(R)[:, None]
            parent, which = order // (D + 1), order % (D + 1)
            detection = np.maximum(which - 1, 0)
            cand_m = m[rows, parent] + np.where(
                (which > 0)[..., None], np.einsum("rcnm,rcm->rcn", gain[rows, parent], nu[rows, parent, detection]), 0.0)
            cand_P = np.where((which > 0)[..., None, None], P_updated[rows, parent], P[rows, parent])
            cand_label = label[rows, parent]
            cand_w = cand_w[rows, order]
            # prune, merge, cap (Table II)
            out_w, out_m = np.zeros((R, Jmax)), np.zeros((R, Jmax, 4))
            out_P, out_label = np.zeros((R, Jmax, 4, 4)), np.zeros((R, Jmax), np.int64)
            kept = kernel.merge_components(np.ascontiguousarray(cand_w), np.ascontiguousarray(cand_m),
                                           np.ascontiguousarray(cand_P), np.ascontiguousarray(cand_label),
                                           count.astype(np.int64), self.prune_below, self.merge_within, Jmax,
                                           out_w, out_m, out_P, out_label)
            width = max(int(kept.max()), 0)
            w, m, P, label = out_w[:, :width], out_m[:, :width], out_P[:, :width], out_label[:, :width]
            filled = np.arange(width)[None, :] < kept[:, None]
            P = np.where(filled[..., None, None], P, np.eye(4))               # empty slots: harmless values
            cardinality[:, k] = ordered_sum(w, axis=1)
            components[:, k] = kept
            # state extraction (Table III) with labels
            extracted = filled & (w > self.extract_above)
            label = self._unique_labels(extracted, w, label, next_label)
            estimates.append((extracted, np.rint(w).astype(np.int64), w.copy(), m.copy(), P.copy(), label.copy()))
        state, covariance, track_id, existence = self._stack(estimates, R, K, next_label)
        state, covariance = to_layout(state, covariance, STATE_NAMES, tuple(detections.state_names))
        extras = {"cardinality": cardinality, "components": components}
        return TrackSets(times.copy(), state, covariance, track_id, track_id >= 0, existence, extras,
                         clock.perf_counter() - started)

    @staticmethod
    def _unique_labels(extracted, w, label, next_label):
        """Give every extracted component of a run a label no other extracted one has (the heaviest
        of a shared label keeps it); new labels from next_label (updated in place)."""
        r, j = np.nonzero(extracted)
        if r.size < 2:
            return label
        order = np.lexsort((-w[r, j], label[r, j], r))
        r, j = r[order], j[order]
        lab = label[r, j]
        repeat = np.zeros(r.size, bool)
        repeat[1:] = (r[1:] == r[:-1]) & (lab[1:] == lab[:-1])
        if repeat.any():
            label = label.copy()
            rr, jj = r[repeat], j[repeat]
            rank = np.arange(rr.size) - np.searchsorted(rr, rr)
            label[rr, jj] = next_label[rr] + rank
            np.add.at(next_label, rr, 1)
        return label

    @staticmethod
    def _stack(estimates, R, K, next_label):
        """Table III's round(w) copies of each extracted mean as (R, K, M, ...) arrays; a copy beyond the
        first gets a fresh label of its own."""
        widths = [int(np.where(ext, np.maximum(c, 1), 0).sum(axis=1).max()) if ext.size else 0
                  for ext, c, *_ in estimates]
        M = max(widths + [1])
        state = np.full((R, K, M, 4), np.nan)
        covariance = np.full((R, K, M, 4, 4), np.nan)
        track_id = np.full((R, K, M), -1, np.int64)
        existence = np.full((R, K, M), np.nan)
        for k, (ext, copies, w, m, P, label) in enumerate(estimates):
            r, j = np.nonzero(ext)
            if r.size == 0:
                continue
            n = np.maximum(copies[r, j], 1)
            r, j = np.repeat(r, n), np.repeat(j, n)
            first = np.ones(r.size, bool)
            first[1:] = ~((r[1:] == r[:-1]) & (j[1:] == j[:-1]))
            slot = np.arange(r.size) - np.searchsorted(r, r)
            ids = label[r, j].copy()
            extra = ~first
            if extra.any():
                rank = np.arange(extra.sum()) - np.searchsorted(r[extra], r[extra])
                ids[extra] = next_label[r[extra]] + rank
                np.add.at(next_label, r[extra], 1)
            state[r, k, slot], covariance[r, k, slot] = m[r, j], P[r, j]
            track_id[r, k, slot], existence[r, k, slot] = ids, w[r, j]
        return state, covariance, track_id, existence
