"""Batched Kalman filter primitives.

Every function works on stacks of small matrices: ``x`` is (..., n), ``P`` is (..., n, n).
The leading axes are whatever the caller batches over (runs, models, targets).
"""

from __future__ import annotations

import numpy as np

LOG_2PI = float(np.log(2.0 * np.pi))


def times_shared(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """A @ M for a stack A (..., p, q) and one shared M (q, r), one product per matrix.

    Folding the stack into the rows of one (N*p, q) BLAS product was faster for the smallest
    matrices, but BLAS picks its kernel (and so its rounding) by the row count: a run's result
    then depended on how many runs were filtered with it. Stacked matmul computes each matrix on
    its own, so chunking the Monte Carlo runs (mc.chunk_runs) gives bit-identical results.
    """
    return A @ M


def shared_times(M: np.ndarray, A: np.ndarray) -> np.ndarray:
    """M @ A for one shared M (r, p) and a stack A (..., p, q), one product per matrix."""
    return M @ A


def einsum(subscripts: str, *operands: np.ndarray) -> np.ndarray:
    """np.einsum on C-contiguous copies of its operands.

    einsum picks its loop order and vectorised sums from the operands' strides: on a transposed
    or moved-axis view, a run's result can differ in the last bit depending on how many runs
    share the batch. Contiguous operands keep each run's arithmetic the same for any batch size
    (mc.chunk_runs is bit-identical, tested); the copy is skipped when already contiguous.
    """
    return np.einsum(subscripts, *(np.ascontiguousarray(o) for o in operands))


def rows_times(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """x @ M for vectors x (..., q) and a matrix M (q, r), one product per vector.

    A 2-D ``x @ M`` with the runs as rows is one BLAS call whose rounding depends on the number
    of rows; this keeps each run's result independent of the batch (see times_shared).
    """
    return (x[..., None, :] @ M)[..., 0, :]


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray,
            offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """x' = F x + offset, P' = F P F' + Q.

    ``offset`` carries a known input (e.g. Gamma a for a model with mean acceleration a).
    F and Q may be shared (n, n) or stacked like P.
    """
    if F.ndim > 2:
        x_pred = einsum("...ij,...j->...i", F, x)
        P_pred = F @ P @ np.swapaxes(F, -1, -2) + Q
    else:
        x_pred = rows_times(x, F.T)
        P_pred = shared_times(F, times_shared(P, F.T)) + Q
    if offset is not None:
        x_pred = x_pred + offset
    return x_pred, P_pred


def inverse_2x2(S: np.ndarray, det: np.ndarray | None = None) -> np.ndarray:
    """Closed-form inverse of a stack of 2x2 matrices (one division per entry, no LAPACK call)."""
    a, b, c, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 0], S[..., 1, 1]
    if det is None:
        det = a * d - b * c
    inv = np.empty_like(S)
    inv[..., 0, 0] = d / det
    inv[..., 0, 1] = -b / det
    inv[..., 1, 0] = -c / det
    inv[..., 1, 1] = a / det
    return inv


def inverse_and_logdet(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse and log-determinant of a stack of SPD matrices; closed form for m <= 2."""
    m = S.shape[-1]
    if m == 1:
        return 1.0 / S, np.log(S[..., 0, 0])
    if m == 2:
        det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
        return inverse_2x2(S, det), np.log(det)
    L = np.linalg.cholesky(S)
    eye = np.broadcast_to(np.eye(m), S.shape)
    L_inv = np.linalg.solve(L, eye)
    return np.swapaxes(L_inv, -1, -2) @ L_inv, 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kalman measurement update.

    Returns the posterior mean and covariance and the log-likelihood
    log N(z; H x, H P H' + R) of the measurement under this prior.
    """
    innovation = z - rows_times(x, H.T)
    PHt = times_shared(P, H.T)
    S = shared_times(H, PHt) + R
    S_inv, logdet = inverse_and_logdet(S)
    gain = PHt @ S_inv
    x_post = x + einsum("...ij,...j->...i", gain, innovation)
    P_post = P - gain @ np.swapaxes(PHt, -1, -2)
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    mahalanobis = einsum("...i,...ij,...j->...", innovation, S_inv, innovation)
    log_likelihood = -0.5 * (mahalanobis + logdet + H.shape[0] * LOG_2PI)
    return x_post, P_post, log_likelihood


def kalman_filter(z: np.ndarray, x0: np.ndarray, P0: np.ndarray, F: np.ndarray, Q: np.ndarray,
                  H: np.ndarray, R: np.ndarray, offset: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Run predict/update over scans. z is (..., K, m); returns states (..., K, n) and covariances.

    The first scan is updated from the prior (x0, P0) without a prediction.
    """
    K = z.shape[-2]
    x, P = x0, P0
    states = np.empty(z.shape[:-2] + (K, x0.shape[-1]))
    covariances = np.empty(z.shape[:-2] + (K, x0.shape[-1], x0.shape[-1]))
    for k in range(K):
        if k > 0:
            x, P = predict(x, P, F, Q, offset)
        x, P, _ = update(x, P, z[..., k, :], H, R)
        states[..., k, :] = x
        covariances[..., k, :, :] = P
    return states, covariances
