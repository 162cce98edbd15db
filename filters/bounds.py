"""Estimation limits: the posterior Cramer-Rao lower bound (PCRLB).

Tichavsky, Muravchik & Nehorai, "Posterior Cramer-Rao bounds for discrete-time nonlinear
filtering", IEEE TSP 46(5), 1998. For linear dynamics x(k+1) = F x(k) + u(k) + w(k), w ~ N(0, Q),
and measurements z(k) = h(x(k)) + v(k), v ~ N(0, R), the Fisher information J(k) of x(k) obeys

    J(k+1) = (Q + F J(k)^-1 F')^-1 + E[H(k+1)' R^-1 H(k+1)],   H = dh/dx at the true state,

written here in covariance form, so a singular Q is fine:

    B(k+1|k) = F B(k) F' + Q,   B(k+1) = (B(k+1|k)^-1 + I(k+1))^-1,   B = J^-1.

Any unbiased estimator's error covariance is at least B(k). The expectation over the true state
is the mean over the Monte Carlo runs of H' R^-1 H evaluated at each run's true state (exact when
the truth is deterministic). For a linear-Gaussian model the bound is the Kalman filter's covariance.
"""

from __future__ import annotations

import warnings

import numpy as np


class SingularBoundWarning(RuntimeWarning):
    """The PCRLB recursion met a matrix it cannot invert; the bound is NaN from that scan on."""


def posterior_crlb(F: np.ndarray, Q: np.ndarray, initial: np.ndarray, information: np.ndarray) -> np.ndarray:
    """Bounds B (K, n, n) for scans 0..K-1.

    F, Q the dynamics from scan k-1 to k: (n, n) the same every step, or (K, n, n) per step (entry
    k moves scan k-1 to k; entry 0 is not used), e.g. a known (clairvoyant) mode sequence or an
    uneven scan interval; initial (n, n) the prior covariance at scan 0 after its own measurement
    (B(0)); information (K, n, n) the expected measurement information E[H' R^-1 H] at each scan
    (scan 0's is not used: ``initial`` already holds it).
    """
    K = information.shape[0]
    F = np.asarray(F, dtype=float)
    Q = np.asarray(Q, dtype=float)
    n = F.shape[-1]
    for name, value in (("F", F), ("Q", Q)):
        if value.shape not in ((n, n), (K, n, n)):
            raise ValueError(f"posterior_crlb: {name} has shape {value.shape}; expected ({n}, {n}) or ({K}, {n}, {n}).")
    F_at = (lambda k: F[k]) if F.ndim == 3 else (lambda k: F)
    Q_at = (lambda k: Q[k]) if Q.ndim == 3 else (lambda k: Q)
    bounds = np.full((K, n, n), np.nan)
    B = np.asarray(initial, dtype=float)
    bounds[0] = B
    for k in range(1, K):
        predicted = F_at(k) @ B @ F_at(k).T + Q_at(k)
        try:
            B = np.linalg.inv(np.linalg.inv(predicted) + information[k])
        except np.linalg.LinAlgError:
            B = np.full((n, n), np.nan)
        if not np.isfinite(B).all():
            # an exactly singular matrix in double precision (noise levels 1e-12 against 1e12, say):
            # the bound is undefined from here on; NaN, and the caller says so, rather than a crash
            warnings.warn(f"posterior_crlb: the bound is singular at scan {k} (its covariance or information "
                          f"cannot be inverted in double precision); scans {k}..{K - 1} are NaN",
                          SingularBoundWarning, stacklevel=2)
            break
        B = 0.5 * (B + B.T)
        bounds[k] = B
    return bounds
