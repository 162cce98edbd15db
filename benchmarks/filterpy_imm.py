"""The same FSIMM job with FilterPy's ``IMMEstimator`` over 13 ``KalmanFilter``s, one run at a time.

How the models map onto FilterPy 2.0 (``filterpy/kalman/IMM.py``, ``kalman_filter.py``):

- one ``KalmanFilter(dim_x=4, dim_z=2, dim_u=1)`` per model, sharing F, Q = Gamma (q^2 I2) Gamma',
  H, R; the model's mean acceleration is the control term: B = Gamma a_m as a (4, 1) matrix and
  ``imm.predict(u=[[1.0]])``. ``u`` must be a scalar or (1, 1): a 1-D ``u`` of shape (1,) makes
  ``dot(B, u)`` a (4,) vector, which broadcasts against the (4, 1) state into a (4, 4) "state".
- the transition matrix is passed as is. FilterPy's docstring says ``M[i, j]`` is the
  probability of switching *from j to i*, but the code computes ``cbar = mu @ M`` and
  ``omega[i, j] = M[i, j] mu[i] / cbar[j]``, i.e. it uses row i = P(m_k = j | m_{k-1} = i),
  which is our convention. (Our matrix is not symmetric, so the comparison would catch a
  transposition.)
- every filter starts from the two-point (x, P) at k = 1; each later scan is
  ``imm.predict(u); imm.update(z_k)``; the acceleration estimate is ``imm.mu @ accelerations``.

The zero-probability start. Our FSIMM starts from mu_0 = e_{m1}; then m6..m13 have predicted
probability c_j = 0 at k = 2 (nothing in m1's row leads to them). The spec mixes such a model
with the posterior weights and keeps its probability at 0. FilterPy 2.0 cannot do that: it
computes ``omega[i, j] = M[i, j] mu[i] / cbar[j]`` with no guard, so 0/0 gives NaN mixing
weights (a RuntimeWarning only), the mixed (x, P) of m6..m13 are NaN, and the first
``imm.update`` then fails inside the likelihood: ``KalmanFilter.log_likelihood`` calls
``scipy.stats.multivariate_normal.logpdf`` on a NaN S, which raises
``ValueError: array must not contain infs or NaNs``. (``exact_start_is_finite`` runs one cycle
and returns False on FilterPy 2.0.0.) FilterPy has no hook to mix an unreachable model with
the posterior weights short of re-implementing ``_compute_mixing_probabilities``, which would
no longer be "FilterPy's IMMEstimator". So the FilterPy comparison uses a floored start,
``floored_initial_probabilities``: mu_0 = (1 - eps) e_{m1} + eps/(M - 1) on the others, eps = 1e-6,
and the reference loop (``benchmarks/reference_imm.py``) is run with the *same* floored start
for the FilterPy equality check. The equality check between the reference loop and our batched
FSIMM uses the exact e_{m1} start. The floor moves the estimates by a negligible amount (the
benchmark prints how much), but it is a different filter, which is why each comparison keeps
one start for all its members.

Other FilterPy differences that do not matter here but are worth knowing: the covariance
update is the Joseph form ``(I-KH) P (I-KH)' + K R K'`` (ours: ``P - K S K'``, symmetrised);
the likelihood is ``exp(logpdf)`` floored at ``sys.float_info.min`` rather than exactly 0; mode
probabilities are normalised in the linear domain.
"""

from __future__ import annotations

import numpy as np

from benchmarks.reference_imm import acceleration_gain, cv_transition, position_measurement, two_point_start

FLOOR = 1e-6


def floored_initial_probabilities(models, eps: float = FLOOR, initial_model: str = "m1") -> np.ndarray:
    """(1 - eps) on the initial model, eps spread evenly over the others (sums to 1)."""
    M = models.n_models
    mu = np.full(M, eps / (M - 1))
    mu[models.model_index(initial_model)] = 1.0 - eps
    return mu


def build_imm(models, x0: np.ndarray, P0: np.ndarray, R: np.ndarray, dt: float,
              initial_probabilities: np.ndarray):
    """An ``IMMEstimator`` over one ``KalmanFilter`` per model, every filter at (x0, P0)."""
    from filterpy.kalman import IMMEstimator, KalmanFilter

    F = cv_transition(dt)
    G = acceleration_gain(dt)
    H = position_measurement()
    Q = G @ (models.process_noise_std**2 * np.eye(2)) @ G.T
    filters = []
    for a in np.asarray(models.accelerations, dtype=float):
        kf = KalmanFilter(dim_x=4, dim_z=2, dim_u=1)
        kf.F = F.copy()
        kf.Q = Q.copy()
        kf.H = H.copy()
        kf.R = np.array(R, dtype=float)
        kf.B = (G @ a).reshape(4, 1)
        kf.x = x0.reshape(4, 1).copy()
        kf.P = P0.copy()
        filters.append(kf)
    return IMMEstimator(filters, np.asarray(initial_probabilities, dtype=float),
                        np.asarray(models.transition_matrix, dtype=float))


def filterpy_fsimm(models, z: np.ndarray, R: np.ndarray, dt: float,
                   initial_probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Filter one run with FilterPy's IMMEstimator. Same inputs/outputs as ``reference_fsimm``.

    ``initial_probabilities`` is required: with a zero entry FilterPy returns NaN (see module doc).
    """
    K = len(z)
    accelerations = np.asarray(models.accelerations, dtype=float)
    x0, P0 = two_point_start(z[0], z[1], R, dt)
    imm = build_imm(models, x0, P0, R, dt, initial_probabilities)
    u = np.array([[1.0]])
    states = np.full((K, 4), np.nan)
    acceleration = np.full((K, 2), np.nan)
    states[1] = imm.x.ravel()
    acceleration[1] = imm.mu @ accelerations
    for k in range(2, K):
        imm.predict(u)
        imm.update(z[k])
        states[k] = imm.x.ravel()
        acceleration[k] = imm.mu @ accelerations
    return states, acceleration


def exact_start_is_finite(models, z: np.ndarray, R: np.ndarray, dt: float) -> bool:
    """Does FilterPy survive mu_0 = e_{m1} (zero predicted probabilities at k = 2)? False on 2.0.0."""
    mu0 = np.zeros(models.n_models)
    mu0[models.model_index("m1")] = 1.0
    try:
        with np.errstate(all="ignore"):
            states, acceleration = filterpy_fsimm(models, z[:3], R, dt, mu0)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return False
    return bool(np.isfinite(states[2]).all() and np.isfinite(acceleration[2]).all())
