"""Numerical faults of a filter, flagged per run and step.

A sweep that runs for hours must not hand back a table whose numbers silently came from a
broken filter. Each estimate table gets a ``fault`` column (a bit mask per run x step) computed
from the estimate itself before it is stored, and each summary counts the runs that hit each
fault. A faulty run does not stop the others: its rows stay in the table, flagged.

Bits (``FAULTS``):

- ``nonfinite``: the state or covariance holds NaN or inf after the run's first estimate (the NaN
  rows before a track starts are not a fault);
- ``asymmetric``: the covariance is not symmetric: max |P - P'| > tolerance * max |P|;
- ``not_positive_definite``: the covariance has no Cholesky factor (an eigenvalue <= 0);
- ``nees_above_bound``: the NEES against the truth exceeds a configured bound (``faults.nees_bound``;
  a divergence test: a consistent filter's NEES is chi-square with n dof);
- ``weights_underflow``: a particle filter reported that all its weights underflowed at that step
  (``extras["weights_underflow"]``) and had to restart its weights;
- ``never_finite``: the run has no finite estimate at any step (its leading NaN never ends: a
  filter fed NaN, or one that failed at its start); every step of the run is flagged;
- ``beyond_scale``: the estimate is farther from the truth than ``faults.divergence_factor`` (default
  100) times the scenario's scale, the largest norm of the truth's state over every run and step
  (``truth_scale``): a filter lost to numbers, not one tracking badly. Why: the checks above are
  numerical, so a filter whose state runs off to 1e15 m with a large but finite, symmetric,
  positive definite covariance passed them all (MIE A on a 10 000 s ADS-B flight: 8.7e8 m off a
  truth within 3.5e5 m, 0 runs flagged), and the NEES bound is off by default (a consistent filter's
  NEES has no scale-free bound that fits every study). 100 x the scale is far outside any estimate
  a filter still following the target makes, in every study (their errors are below the scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.evaluation.metrics import Metric, nees, register

FAULTS = {"nonfinite": 1, "asymmetric": 2, "not_positive_definite": 4, "nees_above_bound": 8,
          "weights_underflow": 16, "never_finite": 32, "beyond_scale": 64}
DIVERGENCE_FACTOR = 100.0


@dataclass(frozen=True)
class FaultChecks:
    """What counts as a fault (config node ``faults``)."""

    symmetry_tolerance: float = 1e-8
    nees_bound: float | None = None
    divergence_factor: float | None = DIVERGENCE_FACTOR

    def __post_init__(self) -> None:
        if self.divergence_factor is not None and (isinstance(self.divergence_factor, bool) or not (
                np.isfinite(self.divergence_factor) and self.divergence_factor > 0)):
            raise ValueError(f"faults.divergence_factor: {self.divergence_factor!r} must be a number > 0 (an error "
                             f"this many times the truth's scale is flagged beyond_scale) or null (no such test)")
        if not (np.isfinite(self.symmetry_tolerance) and self.symmetry_tolerance >= 0):
            raise ValueError(f"faults.symmetry_tolerance: {self.symmetry_tolerance!r} must be a finite number >= 0 "
                             f"(relative to the largest covariance entry)")
        if self.nees_bound is not None and not (np.isfinite(self.nees_bound) and self.nees_bound > 0):
            raise ValueError(f"faults.nees_bound: {self.nees_bound!r} must be a number > 0 or null (no NEES test)")


def truth_scale(state: np.ndarray) -> float:
    """The scenario's scale for ``beyond_scale``: the largest norm of the truth's state (R, K, [T,] n)
    over its runs, steps and targets (finite components); 0 for an all-NaN truth."""
    state = np.asarray(state, dtype=float)
    norms = np.sqrt(np.nansum(state ** 2, axis=-1)) if state.size else np.zeros(1)
    return float(np.max(norms, initial=0.0))


def fault_flags(state: np.ndarray, covariance: np.ndarray, checks: FaultChecks = FaultChecks(),
                error: np.ndarray | None = None, weights_underflow: np.ndarray | None = None,
                scale: float | None = None) -> np.ndarray:
    """(R, K) uint8 bit mask of FAULTS for states (R, K, n) and covariances (R, K, n, n).

    ``error`` (R, K, n): estimate minus truth, for the NEES bound and, with ``scale`` (``truth_scale``
    of that truth), the ``beyond_scale`` test; ``weights_underflow`` (R, K) bool.
    Extra leading axes (e.g. targets: (R, K, T, n)) are allowed: a step is flagged if any of them is.
    """
    state = np.asarray(state, dtype=float)
    covariance = np.asarray(covariance, dtype=float)
    finite_state, finite, asymmetric, not_positive_definite = _matrix_checks(state, covariance,
                                                                             checks.symmetry_tolerance)
    # a run's rows before its first estimate are NaN by design (no track yet)
    started = np.logical_or.accumulate(finite_state, axis=1)
    flags = np.zeros(finite.shape, dtype=np.uint8)
    flags |= np.where(started & ~finite, FAULTS["nonfinite"], 0).astype(np.uint8)
    flags |= np.where(asymmetric, FAULTS["asymmetric"], 0).astype(np.uint8)
    flags |= np.where(not_positive_definite, FAULTS["not_positive_definite"], 0).astype(np.uint8)

    if checks.nees_bound is not None and error is not None:
        estimated, both = _estimated(state)
        e = np.where(finite[..., None] & estimated, np.asarray(error, dtype=float), 0.0)
        with np.errstate(all="ignore"):
            value = nees(e, _checked_matrices(covariance, finite, both))
        flags |= np.where(finite & ~(value <= checks.nees_bound), FAULTS["nees_above_bound"], 0).astype(np.uint8)
    if checks.divergence_factor is not None and error is not None and scale is not None and scale > 0:
        with np.errstate(all="ignore"):
            distance = np.sqrt(np.nansum(np.asarray(error, dtype=float) ** 2, axis=-1))
        flags |= np.where(finite_state & (distance > checks.divergence_factor * scale),
                          FAULTS["beyond_scale"], 0).astype(np.uint8)
    if weights_underflow is not None:
        flags |= np.where(np.asarray(weights_underflow, dtype=bool), FAULTS["weights_underflow"], 0).astype(np.uint8)
    while flags.ndim > 2:                      # targets etc.: a step is faulty if any of them is
        flags = np.bitwise_or.reduce(flags, axis=-1)
    # "no track yet" that never ends: not one finite estimate in the whole run
    never = ~finite_state.reshape(finite_state.shape[0], -1).any(axis=1)
    flags |= np.where(never[:, None], FAULTS["never_finite"], 0).astype(np.uint8)
    return flags


# Above this many covariance entries the checks run compiled (pipeline.evaluation.kernels.covariance_checks):
# numpy's version makes ~15 passes over full-size temporaries and one LAPACK call per matrix, 7 s
# and ~1.5 GB for a 100-run, 10 001-step, 6-state estimate; below it numpy is quick and a job
# does not pay numba's import and first call (~1 s).
COMPILED_ENTRIES = 4_000_000


def _matrix_checks(state: np.ndarray, covariance: np.ndarray, tolerance: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per matrix (the leading axes): whether the state is estimated (all components, or a reduced
    estimate), whether state and covariance are finite, asymmetric beyond ``tolerance`` x max |P|,
    and not positive definite (no Cholesky factor of (P + P')/2), the last two only where finite.

    A filter that does not estimate some components at a step (study 003's KF + MGEKF runs a
    4-state KF while the sonar is active: no acceleration) leaves exactly those NaN: in the state
    and in their covariance rows and columns, with the rest finite. That is a reduced estimate,
    checked on its finite block; a numerical fault spreads NaN through the whole covariance."""
    if covariance.size >= COMPILED_ENTRIES:
        from pipeline.evaluation.kernels import covariance_checks     # numba: only large estimates pay its start
        n = state.shape[-1]
        flat_state = np.ascontiguousarray(state).reshape(-1, n)
        out = np.empty((4, flat_state.shape[0]), dtype=np.bool_)
        covariance_checks(flat_state, np.ascontiguousarray(covariance).reshape(-1, n, n), float(tolerance),
                          out[0], out[1], out[2], out[3])
        return tuple(row.reshape(state.shape[:-1]) for row in out)
    estimated, both = _estimated(state)
    reduced = (estimated.any(axis=-1) & ~estimated.all(axis=-1)
               & np.where(both, np.isfinite(covariance), True).all(axis=(-1, -2))
               & np.where(both, True, np.isnan(covariance)).all(axis=(-1, -2)))
    finite_state = estimated.all(axis=-1) | reduced
    finite = finite_state & np.where(both, np.isfinite(covariance), True).all(axis=(-1, -2))
    P = _checked_matrices(covariance, finite, both)
    scale = np.abs(P).max(axis=(-1, -2))
    asymmetry = np.abs(P - np.swapaxes(P, -1, -2)).max(axis=(-1, -2))
    asymmetric = finite & (asymmetry > tolerance * scale)
    not_positive_definite = finite & ~_positive_definite(0.5 * (P + np.swapaxes(P, -1, -2)))
    return finite_state, finite, asymmetric, not_positive_definite


def _estimated(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The estimated components (finite state entries) and the covariance entries between two of them."""
    estimated = np.isfinite(state)
    return estimated, estimated[..., :, None] & estimated[..., None, :]


def _checked_matrices(covariance: np.ndarray, finite: np.ndarray, both: np.ndarray) -> np.ndarray:
    """The matrices checked: the estimated block of a finite covariance, the identity elsewhere."""
    eye = np.broadcast_to(np.eye(covariance.shape[-1], dtype=bool), covariance.shape)
    return np.where(finite[..., None, None] & both, covariance, np.where(eye, 1.0, 0.0))


def _positive_definite(P: np.ndarray) -> np.ndarray:
    """Per matrix: has a Cholesky factor. One batched call when all do (the usual case)."""
    try:
        np.linalg.cholesky(P)
        return np.ones(P.shape[:-2], dtype=bool)
    except np.linalg.LinAlgError:
        return np.linalg.eigvalsh(P).min(axis=-1) > 0


def fault_summary(flags: np.ndarray) -> dict[str, int]:
    """Runs with any fault (``diverged_runs``) and runs with each fault (``fault_runs_<name>``)."""
    flags = np.asarray(flags, dtype=np.uint8)
    per_run = np.bitwise_or.reduce(flags, axis=1) if flags.size else np.zeros(flags.shape[0], dtype=np.uint8)
    out = {"diverged_runs": int((per_run != 0).sum())}
    for name, bit in FAULTS.items():
        out[f"fault_runs_{name}"] = int(((per_run & bit) != 0).sum())
    return out


register(Metric("diverged_runs", "runs"), *(Metric(f"fault_runs_{name}", "runs") for name in FAULTS))


def describe(mask: int) -> list[str]:
    """The fault names of one bit mask."""
    return [name for name, bit in FAULTS.items() if mask & bit]
