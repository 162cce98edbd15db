"""Truths of the multi-target study: targets born and dying at given scans, moving at constant
velocity or in coordinated turns, every Monte Carlo run at once.

State per target, in this order: x, vx, y, vy [m, m/s] (Vo & Ma 2006's layout). A truth is
``pipeline.data.Truth`` with state (R, K, T, 4), NaN at the scans where target T does not exist,
and the labels ``turn_rate`` (R, K, T) [rad/s] (the rate over the step that led to scan k; NaN
where the target does not exist).

Motion over one scan period T, per target (an exact discretisation for a constant turn rate w
over the period; Bar-Shalom, Li & Kirubarajan 2001, eq 11.7.1-4)::

    x_{k+1} = F(w_k, T) x_k + G w_k^a,   G = kron(I_2, [T^2/2, T]'),   w^a ~ N(0, sigma_v^2 I_2)

    F(w, T) = [[1, sin(wT)/w,      0, -(1 - cos(wT))/w],
               [0, cos(wT),        0, -sin(wT)        ],
               [0, (1 - cos(wT))/w, 1, sin(wT)/w       ],
               [0, sin(wT),        0, cos(wT)         ]]

with F(0, T) = kron(I_2, [[1, T], [0, 1]]) the constant-velocity transition (Vo & Ma 2006,
Section V-A). F(w, -T) = F(w, T)^-1, so a trajectory can also be run backwards from a point it
must pass (``CrossingTurns``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.data import Truth
from pipeline.run.checks import non_negative, positive
from pipeline.run.seeding import run_generators

STATE_NAMES = ("x", "vx", "y", "vy")
POSITION_INDEX = (0, 2)


def turn_transition(omega: np.ndarray, dt: float) -> np.ndarray:
    """(..., 4, 4) F(omega, dt) of the module docstring for every turn rate in ``omega`` (...) [rad/s];
    the constant-velocity limit where |omega dt| < 1e-9."""
    omega = np.asarray(omega, dtype=float)
    a = omega * dt
    small = np.abs(a) < 1e-9
    safe = np.where(small, 1.0, omega)
    s = np.where(small, dt, np.sin(a) / safe)                 # sin(wT)/w -> T
    c = np.where(small, 0.0, (1.0 - np.cos(a)) / safe)        # (1 - cos wT)/w -> 0
    cos, sin = np.cos(a), np.sin(a)
    F = np.zeros(omega.shape + (4, 4))
    F[..., 0, 0] = F[..., 2, 2] = 1.0
    F[..., 0, 1], F[..., 0, 3] = s, -c
    F[..., 1, 1], F[..., 1, 3] = cos, -sin
    F[..., 2, 1], F[..., 2, 3] = c, s
    F[..., 3, 1], F[..., 3, 3] = sin, cos
    return F


def acceleration_gain(dt: float) -> np.ndarray:
    """G (4, 2) of the module docstring: a piecewise-constant acceleration on (x, vx) and (y, vy)."""
    return np.kron(np.eye(2), np.array([[dt * dt / 2.0], [dt]]))


def _simulate(first: np.ndarray, birth: np.ndarray, death: np.ndarray, omega: np.ndarray, dt: float,
              sigma_v: float, runs: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, K, T, 4) states and (R, K, T) turn rates of T targets over K scans.

    first (T, 4): each target's state at its birth scan; birth, death (T,) 0-based scans, the target
    exists at scans birth..death (inclusive); omega (K, T) the turn rate applied from scan k-1 to k.
    Every run draws its acceleration noise (K, T, 2) from ``run_generators(seed, "scenario", R)``
    whatever the targets' lives (so run r depends only on (seed, r)); none is drawn for sigma_v = 0.
    The recursion runs over the scans, every run and target at once."""
    K, T = omega.shape
    if sigma_v > 0:
        noise = np.stack([g.standard_normal((K, T, 2)) for g in run_generators(seed, "scenario", runs)]) * sigma_v
    else:
        noise = np.zeros((runs, K, T, 2))
    G = acceleration_gain(dt)
    F = turn_transition(omega, dt)                                       # (K, T, 4, 4)
    state = np.full((runs, K, T, 4), np.nan)
    current = np.broadcast_to(first, (runs, T, 4)).copy()
    for k in range(K):
        if k > 0:
            current = np.einsum("tij,rtj->rti", F[k], current) + noise[:, k] @ G.T
        born = k == birth
        current[:, born] = first[born]                                  # exactly the given state at birth
        alive = (birth <= k) & (k <= death)
        state[:, k, alive] = current[:, alive]
    rate = np.where(((birth <= np.arange(K)[:, None]) & (np.arange(K)[:, None] <= death))[None],
                    np.broadcast_to(omega, (runs, K, T)), np.nan)
    return state, rate


def _targets_table(key: str, rows: Sequence[Sequence[float]], width: int, what: str) -> np.ndarray:
    try:
        table = np.asarray(rows, dtype=float)
    except (TypeError, ValueError):
        table = np.empty((0,))
    if table.ndim != 2 or table.shape[1] != width or table.shape[0] == 0 or not np.all(np.isfinite(table)):
        raise ValueError(f"{key}: {rows!r} must be a non-empty list of [{what}] rows of {width} finite numbers")
    return table


class LinearBirthDeath:
    """The linear RFS scenario of Vo & Ma (IEEE TSP 54(11), 2006, Section V-A) as the RFS
    literature's released code generates it (Vo's gmphd ``gen_truth``): T = 1 s, K = 100 scans at
    t = 1..100 s, 12 targets in [-1000, 1000]^2 m, born at k = 1, 1, 1, 20, 20, 20, 40, 40, 60, 60,
    80, 80, targets 1 and 3 dying after k = 70, several crossing.

    ``targets`` rows: [x, vx, y, vy, birth, death] with birth/death the 1-based scans of the first
    and last scan the target exists (death > scans: it lives to the end; a target born after the
    last scan never appears, so ``scans`` may cut the scenario short). As in the released code,
    the state at the birth scan is F [x, vx, y, vy]' (its generator propagates the start once
    before recording it), and the targets move noiselessly (``sigma_v_truth`` = 0); sigma_v_truth
    > 0 adds the CV model's acceleration noise N(0, sigma_v^2) per axis and scan (Vo & Ma: 5 m/s^2).

    ``birth_means`` (4 rows x, vx, y, vy) and ``birth_std`` are the paper's four Gaussian birth
    locations, stated here for the trackers' configs to read (``${scenario.birth_means}``); the
    truth does not use them.
    """

    def __init__(self, targets: Sequence[Sequence[float]], scans: int = 100, dt: float = 1.0,
                 sigma_v_truth: float = 0.0, region: Sequence[Sequence[float]] = ((-1000.0, 1000.0), (-1000.0, 1000.0)),
                 birth_means: Sequence[Sequence[float]] = (), birth_std: Sequence[float] = (10.0, 10.0, 10.0, 10.0),
                 birth_weight: float = 0.03) -> None:
        table = _targets_table("targets", targets, 6, "x, vx, y, vy, birth, death")
        self.scans = int(positive("scans", scans, "scans"))
        if self.scans != scans:
            raise ValueError(f"scans: {scans!r} must be a whole number of scans >= 1")
        self.dt = positive("dt", dt, "s")
        self.sigma_v_truth = non_negative("sigma_v_truth", sigma_v_truth, "m/s^2")
        birth, death = table[:, 4], table[:, 5]
        if np.any(birth != np.round(birth)) or np.any(birth < 1) or np.any(death < birth):
            raise ValueError(f"targets: birth scans {birth.tolist()} must be whole scans >= 1 and each last scan >= "
                             f"its birth scan (last scans {death.tolist()})")
        self.start = table[:, :4]
        self.birth = birth.astype(int) - 1                                  # 0-based
        self.death = np.minimum(death, self.scans).astype(int) - 1
        self.region = _region(region)
        self.birth_means = np.asarray(birth_means, dtype=float).reshape(-1, 4) if len(birth_means) else np.zeros((0, 4))
        self.birth_std = np.asarray(birth_std, dtype=float)
        self.birth_weight = float(birth_weight)

    @property
    def targets(self) -> int:
        return self.start.shape[0]

    def generate(self, runs: int, seed: int) -> Truth:
        K, T = self.scans, self.targets
        first = turn_transition(np.zeros(T), self.dt) @ self.start[..., None]
        state, rate = _simulate(first[..., 0], self.birth, self.death, np.zeros((K, T)), self.dt, self.sigma_v_truth,
                                runs, seed)
        return Truth(np.arange(1, K + 1) * self.dt, state, STATE_NAMES, {"turn_rate": rate})


class CrossingTurns:
    """Two to five targets that cross close together in time and space while making coordinated turns
    (the maneuvering scenario: an IMM of CV and CT models should matter).

    Each target is given by where it crosses: ``targets`` rows [x, y, speed, heading_deg,
    crossing_time, birth_time, death_time] place it at (x, y) [m] with ``speed`` [m/s] and heading
    [deg, from the x axis, counter-clockwise] at ``crossing_time`` [s]; it exists from birth_time to
    death_time [s] (both on the scan grid t = dt, 2 dt, ..., scans dt). ``turns`` rows [target,
    t_start, t_end, rate_deg_s] make target ``target`` (0-based) turn at rate_deg_s [deg/s,
    counter-clockwise positive] over the scans with t_start < t <= t_end; elsewhere it flies
    straight. The trajectory is run forwards and backwards from the crossing state with the exact
    transition F(w, +-dt) (module docstring), so the crossing happens where and when stated
    whatever the turns; ``sigma_v_truth`` > 0 adds white acceleration noise on the way forwards
    from the birth scan (the states then pass near, not exactly through, the crossing point).
    ``birth_means``, ``birth_std``, ``birth_weight``: a GM-PHD's birth intensity, stated for the trackers'
    configs as in ``LinearBirthDeath``.
    """

    def __init__(self, targets: Sequence[Sequence[float]], turns: Sequence[Sequence[float]] = (),
                 scans: int = 100, dt: float = 1.0, sigma_v_truth: float = 0.0,
                 region: Sequence[Sequence[float]] = ((-2000.0, 2000.0), (-2000.0, 2000.0)),
                 birth_means: Sequence[Sequence[float]] = (), birth_std: Sequence[float] = (20.0, 30.0, 20.0, 30.0),
                 birth_weight: float = 0.03) -> None:
        self.birth_means = np.asarray(birth_means, dtype=float).reshape(-1, 4) if len(birth_means) else np.zeros((0, 4))
        self.birth_std, self.birth_weight = np.asarray(birth_std, dtype=float), float(birth_weight)
        table = _targets_table("targets", targets, 7, "x, y, speed, heading_deg, crossing_time, birth_time, death_time")
        if not 1 <= table.shape[0] <= 5:
            raise ValueError(f"targets: {table.shape[0]} targets given; the crossing scenario takes 2 to 5")
        self.scans = int(positive("scans", scans, "scans"))
        self.dt = positive("dt", dt, "s")
        self.sigma_v_truth = non_negative("sigma_v_truth", sigma_v_truth, "m/s^2")
        self.region = _region(region)
        time = np.arange(1, self.scans + 1) * self.dt

        def scan_of(key: str, t: float) -> int:
            hit = np.nonzero(np.isclose(time, t, atol=1e-9 * max(1.0, abs(t))))[0]
            if not hit.size:
                raise ValueError(f"{key}: {t:g} s is not a scan time (dt = {self.dt:g} s, scans at "
                                 f"{time[0]:g}..{time[-1]:g} s)")
            return int(hit[0])

        T = table.shape[0]
        self.crossing = np.array([scan_of(f"targets[{i}] crossing_time", row[4]) for i, row in enumerate(table)])
        self.birth = np.array([scan_of(f"targets[{i}] birth_time", row[5]) for i, row in enumerate(table)])
        self.death = np.array([scan_of(f"targets[{i}] death_time", row[6]) for i, row in enumerate(table)])
        bad = np.nonzero((self.birth > self.crossing) | (self.crossing > self.death))[0]
        if bad.size:
            raise ValueError(f"targets[{int(bad[0])}]: birth_time <= crossing_time <= death_time must hold "
                             f"({table[bad[0], 5]:g}, {table[bad[0], 4]:g}, {table[bad[0], 6]:g} s)")
        heading = np.radians(table[:, 3])
        self.crossing_state = np.stack([table[:, 0], table[:, 2] * np.cos(heading),
                                        table[:, 1], table[:, 2] * np.sin(heading)], axis=-1)
        self.omega = np.zeros((self.scans, T))
        for i, row in enumerate(turns):
            values = np.asarray(row, dtype=float)
            if values.shape != (4,) or not np.all(np.isfinite(values)) or not (0 <= values[0] < T) \
                    or values[0] != int(values[0]) or not values[1] < values[2]:
                raise ValueError(f"turns[{i}]: {list(row)!r} must be [target 0..{T - 1}, t_start, t_end > t_start, "
                                 f"rate_deg_s]")
            inside = (time > values[1] + 1e-9) & (time <= values[2] + 1e-9)
            self.omega[inside, int(values[0])] = np.radians(values[3])

    @property
    def targets(self) -> int:
        return self.crossing_state.shape[0]

    def birth_states(self) -> np.ndarray:
        """(T, 4) each target's state at its birth scan: the crossing state run backwards."""
        out = self.crossing_state.copy()
        for t in range(self.targets):
            for k in range(self.crossing[t], self.birth[t], -1):
                out[t] = turn_transition(self.omega[k, t], -self.dt) @ out[t]   # F(w, -T) = F(w, T)^-1
        return out

    def generate(self, runs: int, seed: int) -> Truth:
        state, rate = _simulate(self.birth_states(), self.birth, self.death, self.omega, self.dt,
                                self.sigma_v_truth, runs, seed)
        return Truth(np.arange(1, self.scans + 1) * self.dt, state, STATE_NAMES, {"turn_rate": rate})


def _region(region: Sequence[Sequence[float]]) -> np.ndarray:
    try:
        box = np.asarray(region, dtype=float)
    except (TypeError, ValueError):
        box = np.empty(0)
    if box.shape != (2, 2) or not np.all(np.isfinite(box)) or not np.all(box[:, 0] < box[:, 1]):
        raise ValueError(f"region: {region!r} must be [[x_min, x_max], [y_min, y_max]] in m with min < max")
    return box


def alive(truth: Truth) -> np.ndarray:
    """(R, K, T) True where the target exists (its state is finite)."""
    return np.all(np.isfinite(truth.state), axis=-1)


def births_and_deaths(truth: Truth, run: int = 0) -> list[tuple[int, int, str]]:
    """(step, target, "birth" | "death") events of one run: a birth at the first scan a target exists,
    a death at the first scan after its last (none for a target alive at the end)."""
    exists = alive(truth)[run]
    events = []
    for t in range(exists.shape[1]):
        steps = np.nonzero(exists[:, t])[0]
        if steps.size:
            events.append((int(steps[0]), t, "birth"))
            if steps[-1] + 1 < exists.shape[0]:
                events.append((int(steps[-1]) + 1, t, "death"))
    return sorted(events)


__all__ = ["STATE_NAMES", "POSITION_INDEX", "LinearBirthDeath", "CrossingTurns", "turn_transition",
           "acceleration_gain", "alive", "births_and_deaths"]
