"""Compiled loops (numba) of the evaluate and store paths, where numpy's temporaries or its
advanced indexing over small trailing axes dominate. Imported only where used: a median metric,
a table with a packed covariance (study 003's estimates).

``resampled_medians``: the resampled medians of ``pipeline.evaluation.uncertainty.SortedItems``. For each resample b and step c, the items of step c (every run's values, sorted, NaN and infinities
carrying no weight) are weighed by how often their run is drawn, ``counts[b, run]``; the median is
the mean of the values at the two middle ranks, read where the cumulative weight first reaches
them: the numbers ``SortedItems.median`` computes with numpy, bit for bit (the same sums of whole
draw counts, the same two values averaged). numpy built a (resamples x items x steps) weight array,
its cumulative sum and two searches of it: ~24 s of a 50-run particle-filter job's evaluation; this
walks each step's sorted items once per resample, with nothing in memory but the answer.

``pack_upper`` / ``unpack_upper``: a covariance's upper triangle in float32 (the ``P_upper``
column of ``pipeline.storage.schemas``) and back: numpy's ``P[..., i, j]`` gather and scatter with index
arrays took 0.5 s and 1.7 s for a 100-run, 10 001-step, 6-state estimate; a row at a time here.

``covariance_checks``: the per-matrix checks of ``pipeline.evaluation.faults`` (finite, reduced estimate,
asymmetry, Cholesky) in one pass per matrix, without numpy's full-size temporaries.

``solve_quadratic``: e' P^-1 e per matrix (``pipeline.evaluation.metrics.nees``), by LU with partial pivoting,
without numpy's per-matrix LAPACK calls and its full-size temporaries.

Compiled on first use with ``cache=True`` (machine code beside this file, keyed by its content).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)
def resampled_medians(values: np.ndarray, runs: np.ndarray, valid: np.ndarray, counts: np.ndarray,
                      out: np.ndarray) -> None:
    """``out[b, c]``: the median at step c of resample b; NaN where no drawn value is finite.

    values, runs, valid : (C, I) each step's items in ascending order, their runs, whether finite
    counts : (B, R) draws of each run (whole numbers as floats)
    """
    C, I = values.shape
    B = counts.shape[0]
    for c in range(C):
        for b in range(B):
            n = 0.0
            for i in range(I):
                if valid[c, i]:
                    n += counts[b, runs[c, i]]
            if n <= 0.0:
                out[b, c] = np.nan
                continue
            lower_rank = (n - 1.0) // 2.0 + 1.0          # 1-based middle ranks, as SortedItems.median
            upper_rank = n // 2.0 + 1.0
            cumulative = 0.0
            lower = -1
            upper = -1
            for i in range(I):
                if valid[c, i]:
                    cumulative += counts[b, runs[c, i]]
                if lower < 0 and cumulative >= lower_rank:
                    lower = i
                if cumulative >= upper_rank:
                    upper = i
                    break
            out[b, c] = 0.5 * (values[c, lower] + values[c, upper])


@njit(cache=True, nogil=True, boundscheck=False)
def pack_upper(covariance: np.ndarray, rows: np.ndarray, cols: np.ndarray, out: np.ndarray) -> None:
    """``out[r, k] = float32(covariance[r, rows[k], cols[k]])`` for (N, n, n) ``covariance``."""
    for r in range(covariance.shape[0]):
        for k in range(rows.shape[0]):
            out[r, k] = np.float32(covariance[r, rows[k], cols[k]])


@njit(cache=True, nogil=True, boundscheck=False)
def unpack_upper(packed: np.ndarray, rows: np.ndarray, cols: np.ndarray, out: np.ndarray) -> None:
    """The symmetric (N, n, n) float64 ``out`` from its float32 upper triangle ``packed`` (N, m)."""
    for r in range(packed.shape[0]):
        for k in range(rows.shape[0]):
            value = np.float64(packed[r, k])
            out[r, rows[k], cols[k]] = value
            out[r, cols[k], rows[k]] = value


@njit(cache=True, nogil=True, boundscheck=False)
def covariance_checks(state: np.ndarray, covariance: np.ndarray, tolerance: float, finite_state: np.ndarray,
                      finite: np.ndarray, asymmetric: np.ndarray, not_positive_definite: np.ndarray) -> None:
    """``pipeline.evaluation.faults._matrix_checks`` for (N, n) states and (N, n, n) covariances, a matrix at a
    time: the same decisions, with the positive-definite test a Cholesky factorisation of
    (P + P')/2 here (a pivot that is not > 0 fails it), as LAPACK's is there; the two can differ only
    for a matrix within rounding of singular."""
    N, n = state.shape
    estimated = np.empty(n, dtype=np.bool_)
    P = np.empty((n, n))
    L = np.zeros((n, n))
    for r in range(N):
        any_estimated, all_estimated = False, True
        for i in range(n):
            estimated[i] = np.isfinite(state[r, i])
            any_estimated |= estimated[i]
            all_estimated &= estimated[i]
        block_finite, outside_nan = True, True
        for i in range(n):
            for j in range(n):
                value = covariance[r, i, j]
                if estimated[i] and estimated[j]:
                    block_finite &= np.isfinite(value)
                else:
                    outside_nan &= np.isnan(value)
        reduced = any_estimated and not all_estimated and block_finite and outside_nan
        finite_state[r] = all_estimated or reduced
        finite[r] = finite_state[r] and block_finite
        scale, asymmetry = 0.0, 0.0
        for i in range(n):
            for j in range(n):
                if finite[r] and estimated[i] and estimated[j]:
                    P[i, j] = covariance[r, i, j]
                else:
                    P[i, j] = 1.0 if i == j else 0.0
        for i in range(n):
            for j in range(n):
                scale = max(scale, abs(P[i, j]))
                asymmetry = max(asymmetry, abs(P[i, j] - P[j, i]))
        asymmetric[r] = finite[r] and asymmetry > tolerance * scale
        factored = True
        for j in range(n):                       # Cholesky of (P + P')/2, column by column
            pivot = 0.5 * (P[j, j] + P[j, j])
            for k in range(j):
                pivot -= L[j, k] * L[j, k]
            if not pivot > 0.0:
                factored = False
                break
            L[j, j] = np.sqrt(pivot)
            for i in range(j + 1, n):
                value = 0.5 * (P[i, j] + P[j, i])
                for k in range(j):
                    value -= L[i, k] * L[j, k]
                L[i, j] = value / L[j, j]
        not_positive_definite[r] = finite[r] and not factored


@njit(cache=True, nogil=True, boundscheck=False)
def solve_quadratic(error: np.ndarray, covariance: np.ndarray, index: np.ndarray, out: np.ndarray,
                    singular: np.ndarray) -> None:
    """``out[r] = e' P^-1 e`` for (N, n) errors and covariances given as (N, m) entries with P[i, j] =
    ``covariance[r, index[i, j]]`` (m = n * n with index = arange for full matrices, m = n(n+1)/2 for
    float32 upper triangles: a PackedCovariance is solved without unpacking it); NaN where either is
    not finite; ``singular[r]`` where P has an exactly zero pivot (the caller uses the pseudo-inverse
    there). Gaussian elimination with partial pivoting on a copy of P and e, then back substitution."""
    N, n = error.shape
    A = np.empty((n, n))
    b = np.empty(n)
    for r in range(N):
        ok = True
        for i in range(n):
            ok &= np.isfinite(error[r, i])
        for k in range(covariance.shape[1]):
            ok &= np.isfinite(covariance[r, k])
        singular[r] = False
        if not ok:
            out[r] = np.nan
            continue
        for i in range(n):
            b[i] = error[r, i]
            for j in range(n):
                A[i, j] = np.float64(covariance[r, index[i, j]])
        for j in range(n):
            pivot_row = j
            for i in range(j + 1, n):
                if abs(A[i, j]) > abs(A[pivot_row, j]):
                    pivot_row = i
            if A[pivot_row, j] == 0.0:
                singular[r] = True
                break
            if pivot_row != j:
                for k in range(n):
                    A[j, k], A[pivot_row, k] = A[pivot_row, k], A[j, k]
                b[j], b[pivot_row] = b[pivot_row], b[j]
            for i in range(j + 1, n):
                factor = A[i, j] / A[j, j]
                for k in range(j + 1, n):
                    A[i, k] -= factor * A[j, k]
                b[i] -= factor * b[j]
        if singular[r]:
            out[r] = np.nan
            continue
        for i in range(n - 1, -1, -1):
            value = b[i]
            for k in range(i + 1, n):
                value -= A[i, k] * b[k]
            b[i] = value / A[i, i]
        total = 0.0
        for i in range(n):
            total += error[r, i] * b[i]
        out[r] = total
