"""Interacting multiple model estimators: fixed structure (FSIMM), variable structure with
model-group switching (VSIMM) and the activation-only VSIMM (AO-VSIMM) of seed 001.

Representation
--------------
All Monte Carlo runs are filtered together. Each run carries its own set of running models
on a padded *slot* axis: ``model_index`` (R, A) names the model in each slot (-1 = empty),
and ``x`` (R, A, n), ``P`` (R, A, n, n) hold that model's estimate. Slots are kept compact
(valid slots first, axis trimmed to the largest set), and the Kalman predict/update runs only
on the valid (run, slot) pairs, so a variable-structure estimator that runs 5 of 13 models
really does ~5/13 of the per-model work.

Weights are kept in the log domain and unnormalised: ``log_weight`` = log mu_{k|k-1} + log L_k
(numerator of eq 1). Normalising over whatever set is running gives mu_k, which is exactly
the seed's "common models need no recomputation, only renormalisation" (eqs 2-6).

Engines
-------
``engine="numba"`` (the default) runs each scan's cycle (mixing, predict, update, likelihood) and
what is recorded of it (combination, mode probabilities, NIS) as one compiled pass over the runs
and their models each (``filters.imm.kernel``, 4-state models and 2-D measurements); a run is
computed from its own running models only, so its numbers do not depend on the batch.
``engine="numpy"`` is the vectorised numpy cycle below, the reference; the two agree to rounding
(tests/test_imm_kernel.py; timings in benchmarks/imm_limits.md). The variable-structure logic
(activation, termination, the slot bookkeeping) is numpy in both.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from filters.base import MeasurementSeries, TrackEstimate, checked_engine
from filters.compiling import compiling
from filters.kalman import einsum, predict, rows_times, shared_times, times_shared, update
from filters.models import AccelerationModelSet, two_point_initialisation, two_point_start
from filters.progress import counted


@dataclass(frozen=True)
class ModeSet:
    """Per-model estimates of every run on a padded slot axis.

    model_index : (R, A) int, -1 marks an empty slot
    x : (R, A, n); P : (R, A, n, n)
    log_predicted : (R, A) log mu_{k|k-1} (eq 1, 3); -inf for empty slots
    log_likelihood : (R, A) log L_k (eq 1); -inf for empty slots
    log_weight : (R, A) log_predicted + log_likelihood, the unnormalised posterior weight
    x_predicted : (R, A, n); P_predicted : (R, A, n, n) each model's one-step prediction before the
        update (the NIS of the combined prediction is formed from them)
    """

    model_index: np.ndarray
    x: np.ndarray
    P: np.ndarray
    log_predicted: np.ndarray
    log_likelihood: np.ndarray
    log_weight: np.ndarray
    x_predicted: np.ndarray
    P_predicted: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.model_index >= 0

    def probabilities(self) -> np.ndarray:
        """mu_k (R, A): the weights normalised over each run's running set (eq 1)."""
        top = np.max(self.log_weight, axis=1, keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        w = np.exp(self.log_weight - top)
        return w / _slot_sum(w, axis=1)[:, None]


_FIELDS = ("model_index", "x", "P", "log_predicted", "log_likelihood", "log_weight", "x_predicted", "P_predicted")


def _take_slots(s: ModeSet, order: np.ndarray) -> ModeSet:
    # index the two leading axes only, so each slot's (n,) / (n, n) block is copied whole
    rows = np.arange(order.shape[0])[:, None]
    return ModeSet(*(getattr(s, f)[rows, order] for f in _FIELDS))


def compact(s: ModeSet) -> ModeSet:
    """Move valid slots first (stable) and trim the slot axis to the largest running set."""
    valid = s.valid
    width = max(int(valid.sum(axis=1).max()), 1)
    if valid[:, :width].all() and width == valid.shape[1]:
        return s
    order = np.argsort(~valid, axis=1, kind="stable")[:, :width]
    return _take_slots(s, order)


def drop_slots(s: ModeSet, keep: np.ndarray) -> ModeSet:
    """Empty the slots where ``keep`` is False (terminated or discarded models), then compact."""
    gone = ~keep
    return compact(replace(
        s,
        model_index=np.where(keep, s.model_index, -1),
        log_predicted=np.where(gone, -np.inf, s.log_predicted),
        log_likelihood=np.where(gone, -np.inf, s.log_likelihood),
        log_weight=np.where(gone, -np.inf, s.log_weight),
    ))


def concat(a: ModeSet, b: ModeSet) -> ModeSet:
    return ModeSet(*(np.concatenate([getattr(a, f), getattr(b, f)], axis=1) for f in _FIELDS))


def combine(s: ModeSet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMM output combination: x = sum mu x^j, P = sum mu (P^j + d d')."""
    mu = s.probabilities()
    # sums over the slot axis in slot order (a reduction over a non-innermost axis adds slot by
    # slot): the padding slots a batch carries (mu = 0) then add exact zeros, so a run's result
    # does not depend on which runs share its batch (einsum's vectorised sums did)
    x = (mu[:, :, None] * s.x).sum(axis=1)
    d = s.x - x[:, None, :]
    P = (mu[:, :, None, None] * (s.P + d[..., :, None] * d[..., None, :])).sum(axis=1)
    return x, P, mu


@dataclass(frozen=True)
class GroupState:
    """Which model groups each run is running (variable-structure IMMs).

    old : (R,) the current group M_o (-1 for a fixed-structure IMM)
    new : (R,) the activated group M_a while the union M_o U M_a runs, else -1
    log_lr : (R,) log of the sequential likelihood ratio t^L accumulated since activation (eq 8)
    """

    old: np.ndarray
    new: np.ndarray
    log_lr: np.ndarray

    @classmethod
    def start(cls, runs: int, group: int) -> "GroupState":
        return cls(np.full(runs, group), np.full(runs, -1), np.zeros(runs))


@dataclass(frozen=True)
class LinearModelBank:
    """What the IMM cycle needs of the models: x' = F x + offset_m, noise Q, measurement H.

    F, Q are shared (n, n) or per model (M, n, n); offsets (M, n); tpm (M, M).
    """

    transition: np.ndarray
    process_noise: np.ndarray
    offsets: np.ndarray
    tpm: np.ndarray
    measurement_matrix: np.ndarray

    @property
    def n_models(self) -> int:
        return self.tpm.shape[0]

    @functools.cached_property
    def kernel_arguments(self) -> tuple:
        """The bank as ``filters.imm.kernel.cycle`` takes it (tpm, F, Q, offsets, H, structured, dt),
        worked out once per bank."""
        from filters.imm import kernel as imm_kernel

        dt = imm_kernel.cv_structure(self.transition, self.process_noise, self.measurement_matrix)
        c = _kernel_array
        return (c(self.tpm, dtype=float), _stack3(self.transition), _stack3(self.process_noise),
                c(self.offsets, dtype=float), c(self.measurement_matrix, dtype=float), dt is not None,
                0.0 if dt is None else dt)

    @classmethod
    def from_model_set(cls, models: AccelerationModelSet) -> "LinearModelBank":
        return cls(models.transition, models.process_noise, models.offsets, models.transition_matrix,
                   models.measurement_matrix)




def compiled_shapes(bank: LinearModelBank) -> bool:
    """Whether the compiled cycle covers this bank: 4-state models, 2-D measurements."""
    return bank.transition.shape[-1] == 4 and bank.measurement_matrix.shape == (2, 4)


def imm_cycle(prior: ModeSet, targets: np.ndarray, z: np.ndarray, noise_covariance: np.ndarray,
              bank: LinearModelBank, detected: np.ndarray | None = None, engine: str = "numpy") -> ModeSet:
    """One IMM cycle VSIMM[M_k, M_{k-1}] (seed 001 eqs 1-6; literature notes 4.3).

    ``prior`` holds the k-1 posteriors of the models that ran at k-1; ``targets`` (R, B) names
    the models to run at k (-1 = none). Only valid (run, target) pairs reach the Kalman filter.

    Runs whose sets differ in size (a VSIMM union of 8 models beside groups of 5) are filtered in
    buckets of equal (prior size, target size), so no run mixes or filters padding.
    ``engine="numba"``: the compiled cycle (``filters.imm.kernel.cycle``), each run over its own
    running slots, no buckets; banks of other shapes than 4-state / 2-D take the numpy cycle.
    """
    if engine == "numba" and compiled_shapes(bank):
        return _compiled_cycle(prior, targets, z, noise_covariance, bank, detected)
    valid = targets >= 0
    if valid.all() and prior.valid.all():                      # FSIMM, AO-VSIMM: one dense bucket
        return _dense_cycle(prior, targets, z, noise_covariance, bank, detected)
    counts = valid.sum(axis=1)
    prior_counts = prior.valid.sum(axis=1)
    width = targets.shape[1] + 1
    codes = np.unique(prior_counts * width + counts)          # (prior size, target size) pairs
    R, B = targets.shape
    n = prior.x.shape[-1]
    out = ModeSet(np.full((R, B), -1), np.zeros((R, B, n)), np.zeros((R, B, n, n)), np.full((R, B), -np.inf),
                  np.full((R, B), -np.inf), np.full((R, B), -np.inf), np.zeros((R, B, n)), np.zeros((R, B, n, n)))
    prior_order = np.argsort(~prior.valid, axis=1, kind="stable")
    target_order = np.argsort(~valid, axis=1, kind="stable")
    for prior_count, count in zip(codes // width, codes % width):
        if count == 0:
            continue
        rows = np.flatnonzero((prior_counts == prior_count) & (counts == count))
        sub_prior = _take_slots(_take_runs(prior, rows), prior_order[rows, :prior_count])
        slots = target_order[rows, :count]
        sub = _dense_cycle(sub_prior, targets[rows[:, None], slots], z[rows], _runs_of(noise_covariance, rows),
                           bank, None if detected is None else detected[rows])
        for field in _FIELDS:
            getattr(out, field)[rows[:, None], slots] = getattr(sub, field)
    return out


def _kernel_array(a, dtype=float) -> np.ndarray:
    """``a`` as the kernels take it: C-contiguous and writable (a read-only array, e.g. a table's
    column read back from the stage cache, is another argument type to numba: a second compilation)."""
    return np.require(a, dtype=dtype, requirements=["C_CONTIGUOUS", "WRITEABLE"])


def _stack3(a: np.ndarray) -> np.ndarray:
    """(n, n) or (M, n, n) -> a C-contiguous, writable float (1 or M, n, n) stack."""
    return _kernel_array(a).reshape((-1,) + a.shape[-2:])


def _compiled_cycle(prior: ModeSet, targets: np.ndarray, z: np.ndarray, noise_covariance: np.ndarray,
                    bank: LinearModelBank, detected: np.ndarray | None) -> ModeSet:
    from filters.imm import kernel as imm_kernel

    seen = np.ones(targets.shape[0], dtype=bool) if detected is None else _kernel_array(detected, dtype=bool)
    c = _kernel_array
    out = imm_kernel.cycle(c(prior.model_index, dtype=np.int64), c(prior.x, dtype=float), c(prior.P, dtype=float),
                           c(prior.log_weight, dtype=float), c(targets, dtype=np.int64), c(z, dtype=float),
                           _stack3(noise_covariance), seen, *bank.kernel_arguments)
    return ModeSet(*out)


def _take_runs(s: ModeSet, rows: np.ndarray) -> ModeSet:
    return ModeSet(*(getattr(s, f)[rows] for f in _FIELDS))


def _runs_of(noise_covariance: np.ndarray, rows: np.ndarray) -> np.ndarray:
    return noise_covariance[rows] if noise_covariance.ndim == 3 else noise_covariance


def _dense_cycle(prior: ModeSet, targets: np.ndarray, z: np.ndarray, noise_covariance: np.ndarray,
                 bank: LinearModelBank, detected: np.ndarray | None) -> ModeSet:
    """The IMM cycle where every prior slot and every target is a running model (no padding)."""
    R, A = prior.model_index.shape
    n = prior.x.shape[-1]
    B = targets.shape[1]
    mu = prior.probabilities()
    joint = bank.tpm[prior.model_index[:, :, None], targets[:, None, :]] * mu[:, :, None]   # pi_ij mu^i, (R, A, B)
    predicted = joint.sum(axis=1)                                                     # eqs 1, 3
    reachable = predicted > 0
    # eq 5; a model no running model can switch to keeps mu = 0 and mixes with the posteriors
    weights = np.where(reachable[:, None, :], joint / np.where(reachable, predicted, 1.0)[:, None, :],
                       mu[:, :, None])
    wT = np.swapaxes(weights, 1, 2)                                                   # (R, B, A)
    reference = prior.x[:, :1, :]                                                     # centring keeps eq 6 exact
    dx = prior.x - reference
    x_mix = wT @ dx                                                                   # eq 5, centred
    second = (prior.P + dx[..., :, None] * dx[..., None, :]).reshape(R, A, n * n)
    P_mix = (wT @ second).reshape(R, B, n, n) - x_mix[..., :, None] * x_mix[..., None, :]   # eq 6
    x_mix = x_mix + reference

    model = targets.reshape(-1)
    run_of = np.repeat(np.arange(R), B)
    F = bank.transition[model] if bank.transition.ndim == 3 else bank.transition
    Q = bank.process_noise[model] if bank.process_noise.ndim == 3 else bank.process_noise
    x_pred, P_pred = predict(x_mix.reshape(R * B, n), P_mix.reshape(R * B, n, n), F, Q, bank.offsets[model])
    Rm = noise_covariance[run_of] if noise_covariance.ndim == 3 else noise_covariance
    x_post, P_post, loglik = update(x_pred, P_pred, z[run_of], bank.measurement_matrix, Rm)
    if detected is not None and not detected.all():
        seen = detected[run_of]
        x_post = np.where(seen[:, None], x_post, x_pred)
        P_post = np.where(seen[:, None, None], P_post, P_pred)
        loglik = np.where(seen, loglik, 0.0)
    with np.errstate(divide="ignore"):
        log_pred = np.log(predicted)
    loglik = loglik.reshape(R, B)
    return ModeSet(targets, x_post.reshape(R, B, n), P_post.reshape(R, B, n, n), log_pred, loglik, log_pred + loglik,
                   x_pred.reshape(R, B, n), P_pred.reshape(R, B, n, n))


def combined_prediction_nis(s: ModeSet, z: np.ndarray, noise_covariance: np.ndarray, H: np.ndarray,
                            detected: np.ndarray | None = None) -> np.ndarray:
    """(R,) NIS of scan k's measurement against the IMM's combined prediction.

    The models' predictions are moment-matched with the predicted mode probabilities mu_{k|k-1}
    (eqs 1, 3; normalised over the running slots, since a VSIMM union holds two groups' cycles):
    x = sum c_j x_j, P = sum c_j (P_j + d d'), then nu = z - H x, S = H P H' + R. This is the
    innovation a single Gaussian summary of the IMM's prediction sees, so for a consistent IMM its
    run average sits near dim(z) (chi-square; Bar-Shalom, Li & Kirubarajan 2001, 11.6.6). NaN
    where the scan has no detection.
    """
    top = np.max(s.log_predicted, axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    c = np.exp(s.log_predicted - top)
    c = c / _slot_sum(c, axis=1)[:, None]
    x = (c[:, :, None] * s.x_predicted).sum(axis=1)
    d = s.x_predicted - x[:, None, :]
    P = (c[:, :, None, None] * (s.P_predicted + d[..., :, None] * d[..., None, :])).sum(axis=1)
    nu = z - rows_times(x, H.T)                        # per-run products: batch-size independent
    S = shared_times(H, times_shared(P, H.T)) + noise_covariance
    nis = einsum("ri,ri->r", nu, np.linalg.solve(S, nu[..., None])[..., 0])
    return nis if detected is None else np.where(detected, nis, np.nan)


def _slot_sum(a: np.ndarray, axis: int) -> np.ndarray:
    """Sum over the model-slot axis, strictly in slot order.

    A batch's slot axis is as wide as its largest running set, so a run carries padding slots
    (weight 0) that depend on which runs share its batch. np.sum over a contiguous axis adds in
    vectorised partial sums whose grouping depends on that width; a running sum adds slot after
    slot, so the padding adds exact zeros and a run's result does not depend on its batch.
    """
    return np.take(np.cumsum(a, axis=axis), -1, axis=axis)


def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    top = np.max(a, axis=axis, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(_slot_sum(np.exp(a - top), axis=axis)) + np.squeeze(top, axis=axis)


class _IMMBase:
    accepts = frozenset({"position_xy"})       # 2-D position (seed 001 eq 7)
    """Shared run loop: two-point start at k = 1, one cycle per scan after that."""

    name: str

    def __init__(self, models: AccelerationModelSet, name: str, initial_model: str = "m1",
                 engine: str = "numba") -> None:
        checked_engine(engine, "the compiled IMM cycle, filters/imm/kernel.py")
        self.models = models
        self.name = name
        self.bank = LinearModelBank.from_model_set(models)
        # "numba": the compiled cycle and summary (filters.imm.kernel); "numpy": the reference
        self.engine = engine if compiled_shapes(self.bank) else "numpy"
        self.initial_model = models.model_index(initial_model)
        M = models.n_models
        G = len(models.group_names)
        # membership[g, m]: model m belongs to group g; the extra column M stands for "empty slot"
        self.membership = np.zeros((G, M + 1), dtype=bool)
        for g in range(G):
            self.membership[g, models.groups[g][models.groups[g] >= 0]] = True
        # centre_group[m]: the group whose centre (first member) is model m, else -1 (activation, sec 4.1)
        self.centre_group = np.full(M + 1, -1)
        for g in range(G):
            self.centre_group[models.groups[g][0]] = g

    # ---- hooks -------------------------------------------------------------------------
    def _initial_models(self) -> np.ndarray:
        raise NotImplementedError

    def _initial_groups(self) -> int:
        return -1

    def _step(self, prior: ModeSet, groups: GroupState, z: np.ndarray, noise: np.ndarray, detected
              ) -> tuple[ModeSet, GroupState, np.ndarray]:
        """One scan: returns the posteriors, the group state and the models evaluated per run."""
        raise NotImplementedError

    # ---- driver ------------------------------------------------------------------------
    def _start(self, measurements: MeasurementSeries) -> ModeSet:
        z = measurements.z
        R = z.shape[0]
        noise = measurements.noise_covariance
        dt = float(np.diff(measurements.time[:2])[0])
        if noise.ndim == 4:       # each run's own scan 0 and 1 covariances (converted radar plots)
            x0, P0 = two_point_start(z[:, 0], z[:, 1], noise[:, 0], noise[:, 1], dt)
        else:
            x0, P0 = two_point_initialisation(z[:, 0], z[:, 1], dt, noise)
        members = self._initial_models()
        A = members.size
        if self.initial_model not in members:
            raise ValueError(f"initial_model {self.models.names[self.initial_model]!r} is not among the "
                             f"models running at the start: {[self.models.names[m] for m in members]}")
        log_w = np.where(members == self.initial_model, 0.0, -np.inf)
        return ModeSet(
            np.broadcast_to(members, (R, A)).copy(),
            np.broadcast_to(x0[:, None, :], (R, A, x0.shape[-1])).copy(),
            np.broadcast_to(P0[:, None], (R, A) + P0.shape[1:]).copy(),
            np.broadcast_to(log_w, (R, A)).copy(),
            np.zeros((R, A)),
            np.broadcast_to(log_w, (R, A)).copy(),
            np.broadcast_to(x0[:, None, :], (R, A, x0.shape[-1])).copy(),
            np.broadcast_to(P0[:, None], (R, A) + P0.shape[1:]).copy(),
        )

    def run(self, measurements: MeasurementSeries) -> TrackEstimate:
        """Filter every run. Estimates start at scan 1 (two-point differencing of scans 0 and 1).

        The compiled engine's kernel is loaded (once per process; compiled once per machine) before
        the clock starts: the estimate's compute time is the filtering's, whichever estimator of a
        process comes first."""
        if self.engine == "numba":
            from filters.imm import kernel as imm_kernel
            with compiling("filters.imm.kernel"):     # says so when numba compiles (the first job of an install)
                imm_kernel.warm_up()
        started = time.perf_counter()
        z = measurements.z
        R, K, _ = z.shape
        if K < 2:
            raise ValueError(f"{self.name}: needs at least 2 scans for two-point initialisation, got {K}")
        M = self.models.n_models
        n = self.bank.transition.shape[-1]
        state_out = np.full((R, K, n), np.nan)
        cov_out = np.full((R, K, n, n), np.nan)
        mode_prob = np.full((R, K, M), np.nan)
        evaluated = np.zeros((R, K), dtype=np.int16)
        active = np.full((R, K), -1, dtype=np.int16)
        candidate = np.full((R, K), -1, dtype=np.int16)
        nis = np.full((R, K), np.nan)
        noise = measurements.noise_covariance
        detected = measurements.detected

        s = self._start(measurements)
        groups = GroupState.start(R, self._initial_groups())
        rows = np.arange(R)[:, None]
        compiled = self.engine == "numba"
        if compiled:
            from filters.imm import kernel as imm_kernel
            H = self.bank.kernel_arguments[4]
            c = _kernel_array
        for k in counted(range(1, K), "scan", self.name):
            noise_k = noise[:, k] if noise.ndim == 4 else noise
            if k > 1:
                s, groups, evaluated[:, k] = self._step(s, groups, z[:, k], noise_k, detected[:, k])
            if compiled:            # writes scan k of state_out, cov_out, mode_prob and (k > 1) nis
                imm_kernel.summary(c(s.model_index, dtype=np.int64), c(s.x), c(s.P), c(s.log_predicted),
                                   c(s.log_weight), c(s.x_predicted), c(s.P_predicted), c(z[:, k], dtype=float),
                                   _stack3(noise_k), c(detected[:, k], dtype=bool), H, k, k > 1,
                                   state_out, cov_out, mode_prob, nis)
            else:
                if k > 1:
                    nis[:, k] = combined_prediction_nis(s, z[:, k], noise_k, self.bank.measurement_matrix,
                                                        detected[:, k])
                x, P, mu = combine(s)
                state_out[:, k], cov_out[:, k] = x, P
                full = np.zeros((R, M + 1))
                full[rows, np.where(s.valid, s.model_index, M)] = mu
                mode_prob[:, k] = full[:, :M]
            active[:, k], candidate[:, k] = groups.old, groups.new
        elapsed = time.perf_counter() - started
        extras = {
            "mode_probabilities": mode_prob,
            "acceleration": mode_prob @ self.models.accelerations,  # a_hat = sum mu_m a^(m) (spec 001)
            "models_evaluated": evaluated,
            "active_group": active,
            "candidate_group": candidate,
            "nis": nis,
            "nis_dof": np.where(np.isfinite(nis), float(z.shape[-1]), 0.0),
        }
        return TrackEstimate(measurements.time, state_out, cov_out, extras, elapsed)

    # ---- shared pieces of the variable-structure logic ---------------------------------
    def _activation(self, result: ModeSet, current: np.ndarray, eligible: np.ndarray) -> np.ndarray:
        """Activation logic (seed sec 4.1, notes 4.4): the max-likelihood model of M_o is the centre
        of another group and its probability exceeds t_a -> that group. Returns (R,) group or -1."""
        if self.engine == "numba":
            from filters.imm import kernel as imm_kernel
            c = _kernel_array
            return imm_kernel.activation(c(result.model_index, dtype=np.int64), c(result.log_likelihood),
                                         c(result.log_weight), self.centre_group, c(current, dtype=np.int64),
                                         c(eligible, dtype=bool), self.activation_threshold)
        mu = result.probabilities()
        best = np.argmax(result.log_likelihood, axis=1)
        rows = np.arange(best.size)
        best_model = result.model_index[rows, best]
        target = self.centre_group[np.where(best_model >= 0, best_model, -1)]
        fire = eligible & (target >= 0) & (target != current) & (mu[rows, best] > self.activation_threshold)
        return np.where(fire, target, -1)

    def _activate(self, prior: ModeSet, result: ModeSet, z, noise, detected, target: np.ndarray
                  ) -> tuple[ModeSet, np.ndarray]:
        """Initialise M_n = M_a minus M_o from the k-1 posteriors (eqs 2-6) and filter it with z_k;
        append it to the running set. Returns the union and the number of new models per run."""
        fire = target >= 0
        members = self.models.groups[np.where(fire, target, 0)]                       # (R, S)
        already = (members[:, :, None] == result.model_index[:, None, :]).any(-1)
        new_targets = np.where(fire[:, None] & ~already & (members >= 0), members, -1)
        new = imm_cycle(prior, new_targets, z, noise, self.bank, detected, self.engine)
        return compact(concat(result, new)), (new_targets >= 0).sum(axis=1)

    def _in_group(self, s: ModeSet, group: np.ndarray) -> np.ndarray:
        idx = np.where(s.valid, s.model_index, self.models.n_models)
        return self.membership[np.where(group >= 0, group, 0)[:, None], idx] & (group >= 0)[:, None]


class FSIMM(_IMMBase):
    """Standard IMM (Blom & Bar-Shalom 1988) over every model of the set, every scan."""

    def __init__(self, models: AccelerationModelSet, name: str = "FSIMM", initial_model: str = "m1",
                 initial_mode_probabilities: list[float] | None = None, engine: str = "numba") -> None:
        """``initial_mode_probabilities`` (M,) replaces the default mu_0 = e_{initial_model}; ``engine``:
        "numba" (compiled cycle, default) or "numpy" (the reference), see the module's docstring."""
        super().__init__(models, name, initial_model, engine)
        self.initial_mode_probabilities = None
        if initial_mode_probabilities is not None:
            mu0 = np.asarray(initial_mode_probabilities, dtype=float)
            if mu0.shape != (models.n_models,) or (mu0 < 0).any() or abs(mu0.sum() - 1) > 1e-9:
                raise ValueError(f"initial_mode_probabilities: {list(initial_mode_probabilities)} must be "
                                 f"{models.n_models} non-negative numbers summing to 1")
            self.initial_mode_probabilities = mu0

    def _initial_models(self) -> np.ndarray:
        return np.arange(self.models.n_models)

    def _start(self, measurements: MeasurementSeries) -> ModeSet:
        s = super()._start(measurements)
        if self.initial_mode_probabilities is None:
            return s
        with np.errstate(divide="ignore"):
            log_mu = np.log(self.initial_mode_probabilities)[s.model_index]
        return replace(s, log_predicted=log_mu, log_weight=log_mu)

    def _step(self, prior, groups, z, noise, detected):
        s = imm_cycle(prior, prior.model_index, z, noise, self.bank, detected, self.engine)
        return s, groups, s.valid.sum(axis=1)


class AOVSIMM(_IMMBase):
    """Activation-only VSIMM (seed 001 sec 3, notes 4.6).

    Runs one group. When the activation logic fires, the new group's extra models are
    initialised from the current group's k-1 estimates (eqs 2-6), the common models keep
    their weights, the old group's other models are discarded at once, and only M_a runs on.
    """

    def __init__(self, models: AccelerationModelSet, name: str = "AO-VSIMM", initial_group: str = "M1",
                 initial_model: str = "m1", activation_threshold: float = 0.4, engine: str = "numba") -> None:
        super().__init__(models, name, initial_model, engine)
        self.initial_group = models.group_index(initial_group)
        if not 0.0 <= activation_threshold <= 1.0:
            raise ValueError(f"activation_threshold: {activation_threshold} must be a probability in [0, 1]")
        self.activation_threshold = float(activation_threshold)

    def _initial_models(self) -> np.ndarray:
        g = self.models.groups[self.initial_group]
        return g[g >= 0]

    def _initial_groups(self) -> int:
        return self.initial_group

    def _step(self, prior, groups, z, noise, detected):
        result = imm_cycle(prior, prior.model_index, z, noise, self.bank, detected, self.engine)
        evaluated = result.valid.sum(axis=1)
        target = self._activation(result, groups.old, np.ones(len(groups.old), dtype=bool))
        if (target < 0).all():
            return result, groups, evaluated
        union, added = self._activate(prior, result, z, noise, detected, target)
        fire = target >= 0
        keep = np.where(fire[:, None], self._in_group(union, target), union.valid)   # discard M_o \ M_a
        groups = replace(groups, old=np.where(fire, target, groups.old))
        return drop_slots(union, keep), groups, evaluated + added


class VSIMM(_IMMBase):
    """VSIMM with model-group switching (Li, Zhi & Zhang 1999 Part III; seed 001 sec 2, eq 8).

    After activation the union M_u = M_o U M_a runs until the termination logic ends one group.
    Ratios (t^mu, t^L) and rules follow ``ratio``:

    - ``printed``: t^mu = mu(M_o)/mu(M_a), t^L = prod L(M_o)/L(M_a) (eq 8 as printed); both below
      t1 -> end M_a, both above t2 -> end M_o. Reproduces the paper's S2 failure (spec 001).
    - ``new_old``: the same rules on new/old ratios (notes 4.5's recommended reading).
    - ``old_new``: old/new ratios with the rules flipped (below t1 -> end M_o).

    Group probability mu(M) = sum of member mu; group likelihood
    L(M) = sum mu_{k|k-1} L / sum mu_{k|k-1} over members (notes 4.5). Termination is tested
    from the activation step on; no new activation while the union runs.
    """

    RATIOS = ("printed", "new_old", "old_new")

    def __init__(self, models: AccelerationModelSet, name: str = "VSIMM", initial_group: str = "M1",
                 initial_model: str = "m1", activation_threshold: float = 0.4,
                 t1_mu: float = 0.85, t2_mu: float = 0.93, t1_L: float = 0.9, t2_L: float = 1.0,
                 ratio: Literal["printed", "new_old", "old_new"] = "printed", engine: str = "numba") -> None:
        super().__init__(models, name, initial_model, engine)
        if ratio not in self.RATIOS:
            raise ValueError(f"ratio: {ratio!r} is not one of {list(self.RATIOS)}")
        for key, value in (("activation_threshold", activation_threshold),):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{key}: {value} must be a probability in [0, 1]")
        for key, value in (("t1_mu", t1_mu), ("t2_mu", t2_mu), ("t1_L", t1_L), ("t2_L", t2_L)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{key}: {value} must be a finite positive ratio threshold")
        if t1_mu > t2_mu or t1_L > t2_L:
            raise ValueError(f"thresholds: need t1_mu <= t2_mu and t1_L <= t2_L, got t1_mu={t1_mu}, "
                             f"t2_mu={t2_mu}, t1_L={t1_L}, t2_L={t2_L}")
        self.initial_group = models.group_index(initial_group)
        self.activation_threshold = float(activation_threshold)
        self.log_t1_mu, self.log_t2_mu = np.log(t1_mu), np.log(t2_mu)
        self.log_t1_L, self.log_t2_L = np.log(t1_L), np.log(t2_L)
        self.ratio = ratio

    def _initial_models(self) -> np.ndarray:
        g = self.models.groups[self.initial_group]
        return g[g >= 0]

    def _initial_groups(self) -> int:
        return self.initial_group

    def _step(self, prior, groups, z, noise, detected):
        result = imm_cycle(prior, prior.model_index, z, noise, self.bank, detected, self.engine)
        evaluated = result.valid.sum(axis=1)
        in_union = groups.new >= 0
        target = self._activation(result, groups.old, ~in_union)
        fire = target >= 0
        if fire.any():
            result, added = self._activate(prior, result, z, noise, detected, target)
            evaluated = evaluated + added
            groups = replace(groups, new=np.where(fire, target, groups.new),
                             log_lr=np.where(fire, 0.0, groups.log_lr))
            in_union = in_union | fire
        if not in_union.any():
            return result, groups, evaluated
        result, groups = self._terminate(result, groups, in_union)
        return result, groups, evaluated

    def _terminate(self, s: ModeSet, groups: GroupState, in_union: np.ndarray) -> tuple[ModeSet, GroupState]:
        """Termination logic (eq 8, notes 4.5) for the runs whose union is running."""
        if self.engine == "numba":
            from filters.imm import kernel as imm_kernel
            c = _kernel_array
            log_t_mu, step_lr = imm_kernel.group_ratios(
                c(s.model_index, dtype=np.int64), c(s.log_weight), c(s.log_predicted), self.membership,
                c(groups.old, dtype=np.int64), c(groups.new, dtype=np.int64), c(in_union, dtype=bool),
                self.ratio == "new_old")
        else:
            in_old = self._in_group(s, groups.old)
            in_new = self._in_group(s, groups.new)
            mu = s.probabilities()
            with np.errstate(divide="ignore", invalid="ignore"):
                log_mu_old = np.log(_slot_sum(mu * in_old, axis=1))
                log_mu_new = np.log(_slot_sum(mu * in_new, axis=1))
                neg = -np.inf
                log_L_old = (_logsumexp(np.where(in_old, s.log_weight, neg), 1)
                             - _logsumexp(np.where(in_old, s.log_predicted, neg), 1))
                log_L_new = (_logsumexp(np.where(in_new, s.log_weight, neg), 1)
                             - _logsumexp(np.where(in_new, s.log_predicted, neg), 1))
            if self.ratio == "new_old":
                log_t_mu, step_lr = log_mu_new - log_mu_old, log_L_new - log_L_old
            else:
                log_t_mu, step_lr = log_mu_old - log_mu_new, log_L_old - log_L_new
        log_lr = np.where(in_union, groups.log_lr + step_lr, groups.log_lr)
        low = in_union & (log_t_mu < self.log_t1_mu) & (log_lr < self.log_t1_L)
        high = in_union & (log_t_mu > self.log_t2_mu) & (log_lr > self.log_t2_L)
        if self.ratio == "old_new":
            end_old, end_new = low, high
        else:
            end_new, end_old = low, high
        ended = end_old | end_new
        groups_before = groups
        groups = GroupState(old=np.where(end_old, groups.new, groups.old), new=np.where(ended, -1, groups.new),
                            log_lr=np.where(ended, 0.0, log_lr))
        if not ended.any():
            return s, groups
        in_old, in_new = self._in_group(s, groups_before.old), self._in_group(s, groups_before.new)
        keep = np.where(end_new[:, None], in_old, np.where(end_old[:, None], in_new, s.valid))
        return drop_slots(s, keep), groups
