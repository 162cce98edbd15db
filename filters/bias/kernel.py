"""Compiled (numba) local-filter steps of study 002's bias registration (``filters/bias/reference.py``).

Every radar's local filter moves and updates a (runs x targets) stack of 4-state tracks, each with
its 4x4 bias matrix G, at every report: 1200 updates and 1600 moves over the three variants of a
100-run paper job. numpy did an update as ~40 broadcast operations over the stack and a move as ~6,
each a pass through memory with its own temporary: 6.7 s of the job's 11.6 s of filtering (timed on
2026-12-03). Here each track is one pass of scalar arithmetic.

``cv_move``: X' = Phi X, P' = Phi P Phi' + Q, G' = Phi G (eqs 13-14), Phi and Q shared. The
products sum their four terms in index order, one product per track, so a run's result does not
depend on the batch; numpy's matmul may round the same sums differently in the last bit (it calls
BLAS), so the moves agree with the numpy steps to rounding, not necessarily bit for bit
(tests/test_bias_kernel.py holds them to 1e-13 of each array's largest entry; at study 002's 1 s
and 0.5 s steps they were identical).

``update_local``: eqs 16-21 (see ``filters.bias.update_local``), the same operations in the same
order as the numpy step, so the results are bit for bit those of numpy.

Both work on the stack flattened to (N, ...), C-contiguous float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, boundscheck=False)
def cv_move(state: np.ndarray, covariance: np.ndarray, bias_matrix: np.ndarray, F: np.ndarray, Q: np.ndarray,
            out_state: np.ndarray, out_covariance: np.ndarray, out_bias_matrix: np.ndarray) -> None:
    """state (N, 4), covariance (N, 4, 4), bias_matrix (N, 4, 4) or (0, 4, 4) for none; F, Q (4, 4)."""
    moved_bias = bias_matrix.shape[0] > 0
    PFt = np.empty((4, 4))
    for n in range(state.shape[0]):
        for i in range(4):                       # x' = x F' (rows_times: the state as a row)
            s = 0.0
            for k in range(4):
                s += state[n, k] * F[i, k]
            out_state[n, i] = s
        for i in range(4):                       # P F'
            for j in range(4):
                s = 0.0
                for k in range(4):
                    s += covariance[n, i, k] * F[j, k]
                PFt[i, j] = s
        for i in range(4):                       # F (P F') + Q
            for j in range(4):
                s = 0.0
                for k in range(4):
                    s += F[i, k] * PFt[k, j]
                out_covariance[n, i, j] = s + Q[i, j]
        if moved_bias:
            for i in range(4):                   # F G
                for j in range(4):
                    s = 0.0
                    for k in range(4):
                        s += F[i, k] * bias_matrix[n, k, j]
                    out_bias_matrix[n, i, j] = s


@njit(cache=True, nogil=True, boundscheck=False)
def update_local(state: np.ndarray, covariance: np.ndarray, bias_matrix: np.ndarray, z: np.ndarray,
                 noise: np.ndarray, bias_columns: np.ndarray, out_state: np.ndarray, out_covariance: np.ndarray,
                 out_bias_matrix: np.ndarray, out_nis: np.ndarray) -> None:
    """state (N, 4), covariance (N, 4, 4), bias_matrix (N, 4, 4), z (N, 2), noise (N, 2, 2),
    bias_columns (N, 2, 4): the predicted tracks, the converted measurement, R^m and B C."""
    gain = np.empty((4, 2))
    C = np.empty((4, 4))
    for n in range(state.shape[0]):
        a = covariance[n, 0, 0] + noise[n, 0, 0]                  # S = H P H' + R^m (eq 19)
        b = covariance[n, 0, 1] + noise[n, 0, 1]
        c = covariance[n, 1, 0] + noise[n, 1, 0]
        d = covariance[n, 1, 1] + noise[n, 1, 1]
        det = a * d - b * c                                       # kalman.inverse_2x2
        s00 = d / det
        s01 = -b / det
        s10 = -c / det
        s11 = a / det
        for i in range(4):                                        # K = P H' S^-1 (eq 18)
            gain[i, 0] = covariance[n, i, 0] * s00 + covariance[n, i, 1] * s10
            gain[i, 1] = covariance[n, i, 0] * s01 + covariance[n, i, 1] * s11
        nu0 = z[n, 0] - state[n, 0]
        nu1 = z[n, 1] - state[n, 1]
        out_nis[n] = nu0 * (s00 * nu0 + s01 * nu1) + nu1 * (s10 * nu0 + s11 * nu1)
        for i in range(4):
            out_state[n, i] = state[n, i] + gain[i, 0] * nu0 + gain[i, 1] * nu1
        for i in range(4):                                        # P - K (P H')' (eq 21)
            for j in range(4):
                C[i, j] = covariance[n, i, j] - (gain[i, 0] * covariance[n, j, 0] + gain[i, 1] * covariance[n, j, 1])
        for i in range(4):
            for j in range(4):
                out_covariance[n, i, j] = 0.5 * (C[i, j] + C[j, i])
        for i in range(4):                                        # G + K (B C - H G) (eq 20)
            for j in range(4):
                out_bias_matrix[n, i, j] = bias_matrix[n, i, j] + (
                    gain[i, 0] * (bias_columns[n, 0, j] - bias_matrix[n, 0, j])
                    + gain[i, 1] * (bias_columns[n, 1, j] - bias_matrix[n, 1, j]))


_warm = False


def warm_up() -> None:
    """Load (or compile, the first time on a machine) both steps for the argument types the filters
    pass, on one track, before a filter's clock starts (the job's compute-seconds column compares
    the variants; the first one would otherwise carry numba's start)."""
    global _warm
    if _warm:
        return
    x, P, G, F = np.zeros((1, 4)), np.broadcast_to(np.eye(4), (1, 4, 4)).copy(), np.zeros((1, 4, 4)), np.eye(4)
    cv_move(x, P, G, F, F, np.empty_like(x), np.empty_like(P), np.empty_like(G))
    cv_move(x, P, np.empty((0, 4, 4)), F, F, np.empty_like(x), np.empty_like(P), np.empty((0, 4, 4)))
    update_local(x, P, G, np.zeros((1, 2)), np.broadcast_to(np.eye(2), (1, 2, 2)).copy(), np.zeros((1, 2, 4)),
                 np.empty_like(x), np.empty_like(P), np.empty_like(G), np.empty(1))
    _warm = True
