"""Compiled loops (numba) of the evaluate and store paths, where numpy's temporaries or its
advanced indexing over small trailing axes dominate. Imported only where used: a median metric,
a table with a packed covariance (study 003's estimates).

``resampled_medians``: the resampled medians of ``pipeline.uncertainty.SortedItems``. For each resample b and step c, the items of step c (every run's values, sorted, NaN and infinities
carrying no weight) are weighed by how often their run is drawn, ``counts[b, run]``; the median is
the mean of the values at the two middle ranks, read where the cumulative weight first reaches
them: the numbers ``SortedItems.median`` computes with numpy, bit for bit (the same sums of whole
draw counts, the same two values averaged). numpy built a (resamples x items x steps) weight array,
its cumulative sum and two searches of it: ~24 s of a 50-run particle-filter job's evaluation; this
walks each step's sorted items once per resample, with nothing in memory but the answer.

``pack_upper`` / ``unpack_upper``: a covariance's upper triangle in float32 (the ``P_upper``
column of ``pipeline.schemas``) and back: numpy's ``P[..., i, j]`` gather and scatter with index
arrays took 0.5 s and 1.7 s for a 100-run, 10 001-step, 6-state estimate; a row at a time here.

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
