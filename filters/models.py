"""Motion models and their process noise.

State layout for planar models: (x, vx, y, vy), the order of seed 001 eq (7).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Mapping, Sequence

import numpy as np


def constant_velocity_transition(dt: float, axes: int = 2) -> np.ndarray:
    """F of a constant-velocity model, (p, v) per axis, axes stacked block-diagonally (eq 7)."""
    block = np.array([[1.0, dt], [0.0, 1.0]])
    return np.kron(np.eye(axes), block)


def acceleration_input_gain(dt: float, axes: int = 2) -> np.ndarray:
    """Gamma of eq (7): how a piecewise-constant acceleration enters (p, v) per axis."""
    return np.kron(np.eye(axes), np.array([[dt * dt / 2.0], [dt]]))


def position_measurement_matrix(axes: int = 2) -> np.ndarray:
    """H picking the positions out of (p, v) per axis."""
    return np.kron(np.eye(axes), np.array([[1.0, 0.0]]))


def two_point_initialisation(z0: np.ndarray, z1: np.ndarray, dt: float, noise_covariance: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Two-point differencing with one noise covariance R for both scans (two_point_start): per axis
    pair (i, j) [[R_ij, R_ij/dt], [R_ij/dt, 2 R_ij/dt^2]], which keeps the cross-axis terms of a
    correlated R; the state is (p, v) per axis."""
    R = np.asarray(noise_covariance, dtype=float)
    return two_point_start(z0, z1, R, R, dt)


def two_point_start(z0: np.ndarray, z1: np.ndarray, R0: np.ndarray, R1: np.ndarray, dt: float,
                    kinematics: int = 2, acceleration_variance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Two-point differencing with each scan's own noise covariance (converted measurements):
    p = z1, v = (z1 - z0)/dt, cov(p) = R1, cov(p, v) = R1/dt, cov(v) = (R1 + R0)/dt^2 (Bar-Shalom,
    Li & Kirubarajan 5.5.3); with ``kinematics`` 3 an acceleration 0 of variance
    ``acceleration_variance`` per axis. z (..., d), R (..., d, d); state axis-major, (p, v[, a]) per
    axis: x (..., d * kinematics), P (..., n, n)."""
    d = z1.shape[-1]
    n = d * kinematics
    pos = np.arange(d) * kinematics
    vel = pos + 1
    x = np.zeros(z1.shape[:-1] + (n,))
    x[..., pos], x[..., vel] = z1, (z1 - z0) / dt
    P = np.zeros(np.broadcast_shapes(z1.shape[:-1], R0.shape[:-2], R1.shape[:-2]) + (n, n))
    P[..., pos[:, None], pos[None, :]] = R1
    P[..., pos[:, None], vel[None, :]] = R1 / dt
    P[..., vel[:, None], pos[None, :]] = R1 / dt
    P[..., vel[:, None], vel[None, :]] = (R1 + R0) / dt**2
    if kinematics == 3:
        P[..., pos + 2, pos + 2] = acceleration_variance
    return x, P


def _parse_probability(value: object, where: str) -> float:
    if isinstance(value, str):
        try:
            return float(Fraction(value.replace(" ", "")))
        except (ValueError, ZeroDivisionError):
            raise ValueError(f"{where}: '{value}' is not a number or a fraction like '29/30'") from None
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} is not a number or a fraction like '29/30'") from None


@dataclass(frozen=True)
class AccelerationModelSet:
    """Models that differ only in a known mean acceleration (seed 001 eqs 7, 9-11).

    Model m: x_{k+1} = F x_k + Gamma (a_m + w_k), w_k ~ N(0, q^2 I). Models are grouped for
    variable-structure IMM; each group lists its centre model first (eq 10), which is what
    the activation logic keys on.

    Attributes
    ----------
    names : model names, e.g. ("m1", ..., "m13")
    accelerations : (M, 2) mean accelerations [m/s^2]
    group_names : e.g. ("M1", ..., "M5")
    groups : (G, S) int model indices per group, centre first
    transition_matrix : (M, M), row i = P(m_k = j | m_{k-1} = i)
    """

    names: tuple[str, ...]
    accelerations: np.ndarray
    group_names: tuple[str, ...]
    groups: np.ndarray
    transition_matrix: np.ndarray
    process_noise_std: float
    dt: float

    @classmethod
    def from_config(cls, accelerations: Mapping[str, Sequence[float]], transition_matrix: Sequence[Sequence],
                    groups: Mapping[str, Sequence[str]] | None = None, process_noise_std: float = 10.0,
                    dt: float = 1.0, row_tolerance: float = 1e-9) -> "AccelerationModelSet":
        """Build and validate from config-shaped values (names -> accelerations, names -> members).

        Raises ValueError naming the offending argument, value and what is allowed.
        """
        names = tuple(str(n) for n in accelerations)
        if not names:
            raise ValueError("accelerations: no models given; give at least one name: [ax, ay]")
        acc = []
        for name in names:
            value = list(accelerations[name])
            if len(value) != 2:
                raise ValueError(f"accelerations.{name}: {value} must be a pair [ax, ay] in m/s^2")
            acc.append([float(v) for v in value])
        M = len(names)
        rows = list(transition_matrix)
        if len(rows) != M or any(len(list(r)) != M for r in rows):
            shape = f"{len(rows)}x{'/'.join(sorted({str(len(list(r))) for r in rows})) or 0}"
            raise ValueError(
                f"transition_matrix: shape {shape} does not match the {M} models {list(names)}; "
                f"it must be {M}x{M}, row i holding P(m_k = j | m_(k-1) = i)")
        tpm = np.array([[_parse_probability(v, f"transition_matrix[{i}][{j}]") for j, v in enumerate(r)]
                        for i, r in enumerate(rows)])
        if (tpm < 0).any() or (tpm > 1).any():
            i, j = np.argwhere((tpm < 0) | (tpm > 1))[0]
            raise ValueError(f"transition_matrix[{i}][{j}] = {tpm[i, j]} is not a probability in [0, 1]")
        sums = tpm.sum(axis=1)
        bad = np.flatnonzero(np.abs(sums - 1.0) > row_tolerance)
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"transition_matrix: row {i} ({names[i]}) sums to {sums[i]:.12g}; every row must sum to 1 "
                f"(within {row_tolerance:g}). Rows not summing to 1: {[names[b] for b in bad]}")
        if groups is None:
            groups = {"all": list(names)}
        group_names = tuple(str(g) for g in groups)
        index = {n: i for i, n in enumerate(names)}
        members = []
        for g in group_names:
            listed = [str(m) for m in groups[g]]
            unknown = [m for m in listed if m not in index]
            if unknown:
                raise ValueError(f"groups.{g}: unknown models {unknown}; known models are {list(names)}")
            if len(set(listed)) != len(listed) or not listed:
                raise ValueError(f"groups.{g}: {listed} must list distinct models, centre first")
            members.append([index[m] for m in listed])
        size = max(len(m) for m in members)
        group_array = np.full((len(members), size), -1, dtype=np.int64)
        for gi, m in enumerate(members):
            group_array[gi, : len(m)] = m
        if not (np.isfinite(float(process_noise_std)) and float(process_noise_std) >= 0):
            raise ValueError(f"process_noise_std: {process_noise_std} must be a finite number >= 0 (m/s^2)")
        if not float(dt) > 0:
            raise ValueError(f"dt: {dt} must be > 0 (s)")
        return cls(names, np.array(acc), group_names, group_array, tpm, float(process_noise_std), float(dt))

    @property
    def n_models(self) -> int:
        return len(self.names)

    @property
    def transition(self) -> np.ndarray:
        return constant_velocity_transition(self.dt)

    @property
    def input_gain(self) -> np.ndarray:
        return acceleration_input_gain(self.dt)

    @property
    def process_noise(self) -> np.ndarray:
        G = self.input_gain
        return self.process_noise_std**2 * G @ G.T

    @property
    def offsets(self) -> np.ndarray:
        """(M, 4): Gamma a_m, the known-input term of each model's prediction."""
        return self.accelerations @ self.input_gain.T

    @property
    def measurement_matrix(self) -> np.ndarray:
        return position_measurement_matrix()

    def model_index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"model {name!r} is not one of {list(self.names)}")
        return self.names.index(name)

    def group_index(self, name: str) -> int:
        if name not in self.group_names:
            raise ValueError(f"group {name!r} is not one of {list(self.group_names)}")
        return self.group_names.index(name)


# ---- Singer (1970) model with an input level (seed 000 eqs 1-2; literature notes 1.2-1.3) -------
def singer_transition(dt: float, tau: float) -> np.ndarray:
    """Per-axis F for (p, v, a): exact discretisation of a_dot = -a/tau + w (seed 000 eq 2)."""
    e = np.exp(-dt / tau)
    return np.array([[1.0, dt, tau * tau * (-1.0 + dt / tau + e)],
                     [0.0, 1.0, tau * (1.0 - e)],
                     [0.0, 0.0, e]])


def singer_input_gain(dt: float, tau: float) -> np.ndarray:
    """Per-axis G of eq 2: how a constant input level u drives (p, v, a) over one step.

    a_dot = -(a - u)/tau + w, so G = integral of e^{As} [0, 0, 1/tau]' ds = g_CA - F B with
    g_CA = (dt^2/2, dt, 1) (notes 1.3): under a constant level the motion is constant acceleration.
    """
    F = singer_transition(dt, tau)
    return np.array([dt * dt / 2.0, dt, 1.0]) - F[:, 2]


def singer_process_noise(dt: float, tau: float, sigma_m: float) -> np.ndarray:
    """Per-axis Q of the Singer model, q = 2 sigma_m^2 / tau (Singer 1970; notes 1.2).

    For alpha*dt < 1e-3 the closed form cancels catastrophically; a Van Loan matrix exponential
    is used there instead.
    """
    a = 1.0 / tau
    aT = a * dt
    q = 2.0 * a * sigma_m**2
    if aT < 1e-3:
        from scipy.linalg import expm
        A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -a]])
        L = np.array([[0.0], [0.0], [1.0]])
        M = np.block([[-A, q * L @ L.T], [np.zeros((3, 3)), A.T]]) * dt
        E = expm(M)
        F = E[3:, 3:].T
        return F @ E[:3, 3:]
    e1, e2 = np.exp(-aT), np.exp(-2.0 * aT)
    q11 = (1 - e2 + 2 * aT + 2 * aT**3 / 3 - 2 * aT**2 - 4 * aT * e1) / (2 * a**5)
    q12 = (e2 + 1 - 2 * e1 + 2 * aT * e1 - 2 * aT + aT**2) / (2 * a**4)
    q13 = (1 - e2 - 2 * aT * e1) / (2 * a**3)
    q22 = (4 * e1 - 3 - e2 + 2 * aT) / (2 * a**3)
    q23 = (e2 + 1 - 2 * e1) / (2 * a**2)
    q33 = (1 - e2) / (2 * a)
    return q * np.array([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]])
