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

import numpy as np


def posterior_crlb(F: np.ndarray, Q: np.ndarray, initial: np.ndarray, information: np.ndarray) -> np.ndarray:
    """Bounds B (K, n, n) for scans 0..K-1.

    F, Q (n, n) the dynamics (the same every step); initial (n, n) the prior covariance at scan 0
    after its own measurement (B(0)); information (K, n, n) the expected measurement information
    E[H' R^-1 H] at each scan (scan 0's is not used: ``initial`` already holds it).
    """
    K, n = information.shape[0], F.shape[0]
    bounds = np.empty((K, n, n))
    B = np.asarray(initial, dtype=float)
    bounds[0] = B
    for k in range(1, K):
        predicted = F @ B @ F.T + Q
        B = np.linalg.inv(np.linalg.inv(predicted) + information[k])
        B = 0.5 * (B + B.T)
        bounds[k] = B
    return bounds
