"""Multi-sensor bearings-only tracking in clutter with an auxiliary multiple-model particle filter
(seed 004: Kim, Song, Oh), a bootstrap multiple-model SIR for comparison, and an EKF baseline.

Model (seed eqs 1-10, literature notes 6.1-6.2). Augmented state of 20: the target (x, y, vx, vy)
and four drifting sonobuoys (x, y, vx, vy each); x east, y north. The target's mode r in
{1: CV, 2, 3: coordinated turns} is a Markov chain (transition matrix ``tpm``); the turn rate is
Omega_j = (-1)^j a_m / max(|v|, 0.5) (eq 5, from each particle's own target velocity), so r = 2
turns counter-clockwise (Omega > 0) and r = 3 clockwise, whatever the seed's labels say. The
coordinated-turn transition is eq 4 (CV in the limit Omega -> 0); buoys move CV (eq 2).
Process noise enters through Gamma = [[g, 0], [0, g], [T, 0], [0, T]] per object with
g = T^2/2 (``noise_gain="standard"``, the literature notes' correction) or T/2 (``"paper"``,
eq 6 as printed), target sigma and buoy sigma separate.

Measurements (eqs 7-10): the bearing of the target from each buoy and of each buoy from the
known observer, atan2(dx, dy) from north; residuals are always wrapped. A missed component (NaN)
contributes nothing. Clutter (spec 004): each received component's likelihood is the two-
component mixture (1 - p_c) N(e; 0, s^2) + p_c N(e; 0, s_c^2), evaluated in the log domain.

AMMPF (Ristic, Arulampalam & Gordon, "Beyond the Kalman Filter"; seed eqs 11-17), per scan:
1. first stage: for every particle i and mode m, the noise-free predicted mean mu(i, m) and
   lambda(i, m) = w_i pi(r_i -> m) p(z | mu(i, m)) (eq 16), normalised over the 3N pairs;
2. systematic resampling of N (parent, mode) pairs from lambda;
3. propagation of each parent under its drawn mode with process noise (eq 15);
4. second-stage weights p(z | x) / p(z | mu(parent, mode)) (eq 17), normalised;
5. output: weighted mean and covariance, mode probabilities, effective sample size;
6. systematic resampling (every scan, as the seed), then
7. Liu-West regularisation [spec 004, resolved]: X <- a X + (1 - a) mean + h chol(cov) eps with
   a = sqrt(1 - h^2) on all 20 states (``lw_h``; 0 is the paper-faithful ablation). Without it the
   cloud collapses in the 20-state space (16 nearly static buoy states) while the ESS stays near N.

SIR-MM: the bootstrap multiple-model filter (mode drawn from the transition matrix, weights from
the likelihood), the same resampling and regularisation. EKF: one CV model on the same 20 states,
Joseph update on the received components, moment-matched variances in clutter (notes 6.4).

Engines: by default (``engine="numba"``) each scan of a chunk of runs is one compiled pass over
the particles (``filters.particle.kernel``: the numpy loop's arithmetic fused per particle, ~5x
faster; benchmarks/bench_study004.py, benchmarks/particle_limits.md). ``engine="numpy"`` is the
vectorised loop below, the reference: particles are (runs, particles, state) arrays; there is no
Python loop over runs, particles or modes inside a scan. Systematic resampling is vectorised over
runs by offsetting each run's cumulative weights by its run index and searching all runs at once.
Random numbers come from one generator per run (spawned from the seed), so run r's particles do
not depend on R; both engines draw the same numbers in the same order.
"""

from __future__ import annotations

import functools
import os
import time as _time
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from filters.base import TrackEstimate, checked_engine, usable_processors
from filters.kalman import einsum, rows_times
from filters.progress import SILENT, Progress
from filters.progress import current as current_progress

TARGET_STATES = ("x", "y", "vx", "vy")
BUOYS = 4
MODE_NAMES = ("cv", "ccw", "cw")      # the jump-Markov modes in index order: CV, counter-clockwise, clockwise turn
STATE_NAMES = TARGET_STATES + tuple(f"b{i}_{c}" for i in range(1, BUOYS + 1) for c in ("x", "y", "vx", "vy"))
LOG_2PI = float(np.log(2.0 * np.pi))
TWO_PI = 2.0 * np.pi
MIN_SPEED = 0.5                     # [m/s] floor of |v| in eq 5 (spec 004)


# --------------------------------------------------------------------------------------------
# Model pieces
# --------------------------------------------------------------------------------------------

def wrap(angle: np.ndarray) -> np.ndarray:
    """Into [-pi, pi] (residuals; the end point does not matter for a density). A multiply and a
    rint: cheaper than np.mod on the (runs x particles x modes x bearings) arrays."""
    return angle - angle.dtype.type(TWO_PI) * np.rint(angle * angle.dtype.type(1.0 / TWO_PI))


NOISE_GAINS = ("standard", "paper")


def noise_gain(dt: float, form: str = "standard") -> np.ndarray:
    """Gamma (4, 2) of eq 6: position gain T^2/2 ("standard") or T/2 ("paper", as printed)."""
    if form not in NOISE_GAINS:
        raise ValueError(f"noise_gain: {form!r} must be one of {list(NOISE_GAINS)}")
    g = dt * dt / 2.0 if form == "standard" else dt / 2.0
    return np.array([[g, 0.0], [0.0, g], [dt, 0.0], [0.0, dt]])


def turn_rates(velocity: np.ndarray, max_acceleration: float) -> np.ndarray:
    """(..., 2) target velocity -> (..., 3) Omega per mode: 0 (CV), +a/|v|, -a/|v| (eq 5)."""
    speed = np.maximum(np.hypot(velocity[..., 0], velocity[..., 1]), MIN_SPEED)
    omega = max_acceleration / speed
    return np.stack([np.zeros_like(omega), omega, -omega], axis=-1)


def coordinated_turn(target: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Eq 4 applied to (..., 4) target states with turn rates (...); CV where |Omega| < 1e-9."""
    x, y, vx, vy = target[..., 0], target[..., 1], target[..., 2], target[..., 3]
    wt = omega * dt
    small = np.abs(omega) < 1e-9
    safe = np.where(small, 1.0, omega)
    s, c = np.sin(wt), np.cos(wt)
    a = np.where(small, dt, s / safe)                    # sin(wT)/w
    b = np.where(small, 0.0, (1.0 - c) / safe)           # (1 - cos(wT))/w
    return np.stack([x + a * vx - b * vy, y + b * vx + a * vy, c * vx - s * vy, s * vx + c * vy], axis=-1)


def predicted_positions(target: np.ndarray, speed_floor_rate: float, dt: float) -> np.ndarray:
    """Noise-free predicted target positions (..., 3, 2) under the three modes (eq 4 with eq 5's
    Omega = 0, +a/|v|, -a/|v|). Only positions: the first stage needs nothing else. The two turns
    share sin and cos: sin(wT)/w is even in w and (1 - cos wT)/w odd."""
    x, y, vx, vy = target[..., 0], target[..., 1], target[..., 2], target[..., 3]
    omega = speed_floor_rate / np.maximum(np.hypot(vx, vy), MIN_SPEED)
    wt = omega * dt
    small = omega < 1e-9
    safe = np.where(small, 1.0, omega)
    a = np.where(small, dt, np.sin(wt) / safe)
    b = np.where(small, 0.0, (1.0 - np.cos(wt)) / safe)
    out = np.empty(target.shape[:-1] + (3, 2))
    out[..., 0, 0], out[..., 0, 1] = x + dt * vx, y + dt * vy
    ax, ay, bx, by = a * vx, a * vy, b * vy, b * vx
    out[..., 1, 0], out[..., 1, 1] = x + ax - bx, y + by + ay
    out[..., 2, 0], out[..., 2, 1] = x + ax + bx, y - by + ay
    return out


def cv_transition(dt: float) -> np.ndarray:
    """F_CV (4, 4) over ``dt`` for (x, y, vx, vy) (eq 3)."""
    return np.array([[1.0, 0.0, dt, 0.0], [0.0, 1.0, 0.0, dt], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def ct_transition(omega: float, dt: float) -> np.ndarray:
    """F_CT(Omega) (4, 4) of eq 4 as a matrix (``coordinated_turn`` applies it to state stacks);
    |Omega| < 1e-9 gives F_CV."""
    if abs(omega) < 1e-9:
        return cv_transition(dt)
    s, c = np.sin(omega * dt), np.cos(omega * dt)
    return np.array([[1.0, 0.0, s / omega, -(1.0 - c) / omega], [0.0, 1.0, (1.0 - c) / omega, s / omega],
                     [0.0, 0.0, c, -s], [0.0, 0.0, s, c]])


def bearings(state: np.ndarray, observer: np.ndarray) -> np.ndarray:
    """(..., 20) -> (..., 8): target from each buoy (4), each buoy from the observer (4) (eq 9)."""
    target = state[..., None, 0:2]
    buoys = state[..., 4:20].reshape(state.shape[:-1] + (BUOYS, 4))[..., 0:2]
    d_target = target - buoys
    d_buoy = buoys - observer
    return np.concatenate([np.arctan2(d_target[..., 0], d_target[..., 1]),
                           np.arctan2(d_buoy[..., 0], d_buoy[..., 1])], axis=-1)


@dataclass(frozen=True)
class BearingLikelihood:
    """log p(z | bearings) per component: the two-component clutter mixture (or the nominal
    Gaussian when p_c = 0), missed components (NaN) contribute 0. std, clutter_std (8,) rad."""

    std: np.ndarray
    clutter_std: np.ndarray
    clutter_probability: float = 0.0

    def log(self, predicted: np.ndarray, z: np.ndarray) -> np.ndarray:
        """predicted (..., C) bearings of the components in z's last axis; z broadcastable, NaN missed.

        The mixture is summed as densities around the clutter term (one exp and a log, cheaper than
        logaddexp); the clutter density is the wider one, so nothing underflows."""
        missed = np.isnan(z)
        e = wrap(np.where(missed, 0.0, z) - predicted)
        e2 = e * e
        if self.clutter_probability > 0:
            # log(a e^{f1 e2} + b e^{f2 e2}) = f2 e2 + log(b + a e^{(f1 - f2) e2}): one exp, exact
            value = e2 * self._clutter_factor + np.log(
                self._clutter_scale + self._nominal_scale * np.exp(e2 * (self._nominal_factor - self._clutter_factor)))
        else:
            value = e2 * self._nominal_factor + self._nominal_log_scale
        return np.where(missed, 0.0, value)

    def __post_init__(self) -> None:
        std, clutter, pc = np.asarray(self.std, dtype=float), np.asarray(self.clutter_std, dtype=float), \
            float(self.clutter_probability)
        # float32 constants: the particle filters evaluate this on float32 bearings (see there)
        f32 = np.float32
        object.__setattr__(self, "_nominal_factor", (-0.5 / std**2).astype(f32))
        object.__setattr__(self, "_clutter_factor", (-0.5 / clutter**2).astype(f32))
        object.__setattr__(self, "_nominal_log_scale", (-np.log(std) - 0.5 * LOG_2PI).astype(f32))
        object.__setattr__(self, "_nominal_scale", ((1.0 - pc) / (np.sqrt(2.0 * np.pi) * std)).astype(f32))
        object.__setattr__(self, "_clutter_scale", (pc / (np.sqrt(2.0 * np.pi) * clutter)).astype(f32))

    @property
    def variance(self) -> np.ndarray:
        """(C,) each component's noise variance: the mixture's (1 - p_c) s^2 + p_c s_c^2."""
        pc = float(self.clutter_probability)
        return (1.0 - pc) * np.asarray(self.std, dtype=float) ** 2 + pc * np.asarray(self.clutter_std, dtype=float) ** 2

    def subset(self, columns: slice) -> "BearingLikelihood":
        return BearingLikelihood(self.std[columns], self.clutter_std[columns], self.clutter_probability)


# --------------------------------------------------------------------------------------------
# Resampling and regularisation, vectorised over runs
# --------------------------------------------------------------------------------------------

def systematic_resample(log_weights: np.ndarray, offsets: np.ndarray, draws: int) -> np.ndarray:
    """Systematic resampling per run. log_weights (R, M) (unnormalised), offsets (R,) uniform [0, 1);
    returns (R, draws) indices into M. Each run's normalised cumulative weights are shifted by its
    run index, so one searchsorted serves every run."""
    R, M = log_weights.shape
    w = np.exp(log_weights - log_weights.max(axis=1, keepdims=True))
    cumulative = np.cumsum(w, axis=1)
    cumulative /= cumulative[:, -1:]
    cumulative[:, -1] = 1.0
    run = np.arange(R)[:, None]
    points = (offsets[:, None] + np.arange(draws)[None, :]) / draws
    flat = np.searchsorted((cumulative + run).ravel(), (points + run).ravel(), side="right")
    return np.minimum(flat.reshape(R, draws) - run * M, M - 1)


def normalise_log(log_weights: np.ndarray) -> np.ndarray:
    """(R, M) log weights -> normalised weights."""
    w = np.exp(log_weights - log_weights.max(axis=1, keepdims=True))
    return w / w.sum(axis=1, keepdims=True)


def weighted_moments(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, N, n), (R, N) -> mean (R, n), covariance (R, n, n)."""
    mean = (weights[:, None, :] @ particles)[:, 0]
    centred = particles - mean[:, None, :]
    covariance = np.swapaxes(centred * weights[..., None], -1, -2) @ centred     # batched BLAS, not einsum
    return mean, 0.5 * (covariance + np.swapaxes(covariance, -1, -2))


def liu_west(particles: np.ndarray, h: float, normals: np.ndarray) -> np.ndarray:
    """Liu-West shrinkage kernel on equally weighted particles: a X + (1 - a) mean + h L eps,
    a = sqrt(1 - h^2), L L' the particles' covariance (jittered to stay positive definite)."""
    N, n = particles.shape[1:]
    mean = particles.mean(axis=1)
    centred = particles - mean[:, None, :]
    covariance = (np.swapaxes(centred, -1, -2) @ centred) / N
    scale = np.maximum(np.diagonal(covariance, axis1=-2, axis2=-1), 1e-12)
    covariance = covariance + np.eye(n) * (1e-9 * scale)[:, None, :]
    L = np.linalg.cholesky(covariance)
    a = np.sqrt(1.0 - h * h)
    # the jitter in the normals' dtype (float32 from the filters: it only perturbs), added once
    jitter = normals @ np.swapaxes(h * L, -1, -2).astype(normals.dtype)
    jitter += ((1.0 - a) * mean)[:, None, :].astype(normals.dtype)
    out = a * particles
    out += jitter
    return out


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BuoyReports:
    """What the trackers consume, batched over R runs and K scans (scan 0 is the start).

    z (R, K, 8) bearings [rad] (NaN where missed); observer (2,); std / clutter_std (8,) nominal and
    clutter standard deviations [rad]; clutter_probability; prior_mean (R, 20) and prior_std (20,):
    the start, identical for every filter; seed: the filters' random numbers (per run).
    """

    time: np.ndarray
    z: np.ndarray
    observer: np.ndarray
    std: np.ndarray
    clutter_std: np.ndarray
    clutter_probability: float
    prior_mean: np.ndarray
    prior_std: np.ndarray
    seed: int = 0
    run_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        R, K = self.z.shape[:2]
        if self.z.shape != (R, K, 8) or self.time.shape != (K,) or self.prior_mean.shape != (R, 20):
            raise ValueError(f"BuoyReports: time {self.time.shape}, z {self.z.shape}, prior_mean {self.prior_mean.shape} "
                             f"must be (K,), (R, K, 8), (R, 20)")
        if self.std.shape != (8,) or self.clutter_std.shape != (8,) or self.prior_std.shape != (20,):
            raise ValueError("BuoyReports: std and clutter_std must be (8,), prior_std (20,)")

    def likelihood(self) -> BearingLikelihood:
        return BearingLikelihood(self.std, self.clutter_std, self.clutter_probability)

    def generators(self, stream: str) -> list[np.random.Generator]:
        """One generator per run, keyed by the run's id (``run_ids``, default 0..R-1): a subset of runs
        filtered again (e.g. run 0 alone for a recording) draws exactly the same numbers."""
        key = zlib.crc32(stream.encode())
        ids = range(self.z.shape[0]) if self.run_ids is None else [int(r) for r in self.run_ids]
        return [np.random.default_rng(np.random.SeedSequence(entropy=self.seed, spawn_key=(key, r))) for r in ids]

    def select(self, runs: Sequence[int]) -> "BuoyReports":
        """The same reports for a subset of runs, keeping their ids (so their random numbers)."""
        index = np.asarray(runs, dtype=int)
        ids = index if self.run_ids is None else np.asarray(self.run_ids)[index]
        return BuoyReports(self.time, self.z[index], self.observer, self.std, self.clutter_std,
                           self.clutter_probability, self.prior_mean[index], self.prior_std, self.seed, ids)


def _stack(generators, draw) -> np.ndarray:
    return np.stack([draw(g) for g in generators])




def available_processors() -> int:
    """Threads for the particle filters: ``NUMBA_NUM_THREADS`` when set, else the processors this
    process may run on (its affinity mask: a job pinned by ``taskset`` or a batch system's cgroup
    gets its share, not the whole machine's count)."""
    env = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    return usable_processors()


_MASK64 = (1 << 64) - 1


def _pcg64_state(g: np.random.Generator) -> np.ndarray:
    """A PCG64 Generator's state as (6,) uint64: state high, low, increment high, low, has_uint32, uinteger."""
    d = g.bit_generator.state
    state, inc = d["state"]["state"], d["state"]["inc"]
    return np.array([state >> 64, state & _MASK64, inc >> 64, inc & _MASK64, d["has_uint32"], d["uinteger"]],
                    dtype=np.uint64)


def _set_pcg64_state(g: np.random.Generator, s: np.ndarray) -> None:
    hi, lo, inc_hi, inc_lo, has, value = (int(v) for v in s)
    g.bit_generator.state = {"bit_generator": "PCG64", "state": {"state": (hi << 64) | lo, "inc": (inc_hi << 64) | inc_lo},
                             "has_uint32": has, "uinteger": value}


@functools.cache
def _inline_draws_match() -> bool:
    """Whether the kernel's inline PCG64 and float32 ziggurat give exactly this numpy's numbers
    (Generator.random, standard_normal(dtype=float32)) and leave the same state: checked once per
    process through the kernel's own scan (no second compiled entry point to load) on one scan of
    3000 particles, AMMPF and SIR-MM order (~180 000 numbers: thousands of the ziggurat's wedge
    and hundreds of its tail cases). If numpy ever changes them, the filters fall back to drawing
    with the Generators (slower, same results as that numpy's)."""
    from filters.particle import kernel

    N, M = 3000, 3
    ok = True
    for seed, auxiliary in ((0, True), (20240517, False)):
        reference = np.random.default_rng(seed)
        rng = _pcg64_state(np.random.default_rng(seed))[None].copy()
        draws = _ScanDraws(1, N, auxiliary, True)
        X = np.zeros((1, 20, N))
        X[0, 2] = 1.0
        tpm = np.full((M, M), 1.0 / M)
        states, covariances = np.zeros((1, 2, 20)), np.zeros((1, 2, 20, 20))
        kernel.scan(X, np.empty_like(X), np.zeros((1, N), dtype=np.int64), np.ones((1, 8)), 5.0, np.log(tpm), tpm,
                    np.ones((6, 8), dtype=np.float32), True, np.array([0.0, -1.0]), 0.01, np.ones(5), np.ones(4), 0.3,
                    auxiliary, draws.first_offsets, draws.uniforms, draws.noise, draws.second_offsets, draws.normals,
                    rng, True, np.ones(8), 1, states, covariances, np.zeros((1, 2, M)), np.zeros((1, 2)),
                    np.zeros((1, 2), dtype=bool), np.zeros((1, 2)), np.zeros((1, 2)))
        if auxiliary:
            ok &= reference.random() == draws.first_offsets[0]
        else:
            ok &= bool(np.array_equal(reference.random(N), draws.uniforms[0]))
        ok &= bool(np.array_equal(reference.standard_normal((N, 10), dtype=np.float32), draws.noise[0]))
        ok &= reference.random() == draws.second_offsets[0]
        ok &= bool(np.array_equal(reference.standard_normal((N, 20), dtype=np.float32), draws.normals[0]))
        ok &= bool(np.array_equal(_pcg64_state(reference), rng[0]))
    if not ok:
        warnings.warn("filters.particle: the compiled kernel's PCG64 draws differ from this numpy's; the particle "
                      "filters draw with numpy's Generators instead (slower, same results)", RuntimeWarning)
    return ok


class _ScanDraws:
    """One scan's random numbers for a chunk of runs, drawn per run by the same Generator calls in
    the same order as ``filter_jump_markov`` (first-stage offset or the SIR-MM's mode uniforms,
    process noise, resampling offset, Liu-West normals), into arrays reused every scan."""

    def __init__(self, runs: int, particles: int, auxiliary: bool, regularised: bool) -> None:
        self.auxiliary, self.regularised = auxiliary, regularised
        self.first_offsets, self.second_offsets = np.zeros(runs), np.zeros(runs)
        self.uniforms = np.zeros((runs, 1 if auxiliary else particles))
        self.noise = np.empty((runs, particles, 10), dtype=np.float32)
        self.normals = np.zeros((runs, particles if regularised else 1, 20), dtype=np.float32)

    def draw(self, gens) -> None:
        for r, g in enumerate(gens):
            if self.auxiliary:
                self.first_offsets[r] = g.random()
            else:
                g.random(out=self.uniforms[r])
            # float32 normals: half the generator time; they only scale small perturbations
            g.standard_normal(dtype=np.float32, out=self.noise[r])
            self.second_offsets[r] = g.random()
            if self.regularised:
                g.standard_normal(dtype=np.float32, out=self.normals[r])


# --------------------------------------------------------------------------------------------
# The filters
# --------------------------------------------------------------------------------------------

class _ModelParameters:
    accepts = frozenset({"sonobuoy_bearings"})

    def __init__(self, name: str, max_acceleration: float, target_sigma: float, buoy_sigma: float,
                 noise_gain: str = "standard") -> None:
        for key, value in (("max_acceleration", max_acceleration), ("target_sigma", target_sigma),
                           ("buoy_sigma", buoy_sigma)):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{key}: {value} must be a finite number >= 0 (m/s^2)")
        if noise_gain not in ("standard", "paper"):
            raise ValueError(f"noise_gain: {noise_gain!r} is not allowed; use 'standard' (T^2/2) or 'paper' "
                             f"(T/2, eq 6 as printed)")
        self.name = name
        self.max_acceleration = float(max_acceleration)
        self.target_sigma = float(target_sigma)
        self.buoy_sigma = float(buoy_sigma)
        self.noise_gain = noise_gain

    def _process_noise(self, dt: float) -> np.ndarray:
        """Q (20, 20) = B blkdiag(sigma_t^2 I2, sigma_s^2 I8) B'."""
        G = noise_gain(dt, self.noise_gain)
        Q = np.zeros((20, 20))
        for block in range(5):
            sigma = self.target_sigma if block == 0 else self.buoy_sigma
            Q[4 * block:4 * block + 4, 4 * block:4 * block + 4] = sigma**2 * (G @ G.T)
        return Q


class MultipleModelParticleFilter(_ModelParameters):
    """AMMPF (``auxiliary=True``, the seed's filter) or bootstrap SIR-MM (``auxiliary=False``).

    Parameters
    ----------
    particles : N per run
    max_acceleration : a_m of eq 5 [m/s^2]
    target_sigma, buoy_sigma : process-noise std of the target and of each buoy [m/s^2]
    tpm : 3 x 3 mode transition matrix, rows = from (1 CV, 2 Omega > 0, 3 Omega < 0)
    lw_h : Liu-West kernel width h (0 = off, the paper-faithful ablation)
    noise_gain : "standard" (T^2/2) or "paper" (T/2)
    auxiliary : True for the AMMPF, False for the bootstrap SIR-MM
    chunk_runs : runs filtered together (memory locality and threads; results do not depend on it);
        None: a whole number of chunks per worker, at most 25 runs each
    workers : threads filtering chunks in parallel (None: one per processor); results do not depend on it
    snapshot_particles : keep this many particles per scan (evenly spaced in the resampled,
        regularised cloud) as extras "particles" (R, K, P, 20) float32 and "particle_modes" int8,
        for a recording of a few runs; 0 (default) keeps none
    engine : "numba" (default): each scan is one compiled pass over the particles
        (``filters.particle.kernel``), about 5x faster; "numpy": the vectorised numpy loop
        (``filter_jump_markov`` with ``SonobuoyModel``), the reference. Same random numbers, same
        filter; results agree to float32 rounding scan by scan (the module's docstring says where
        the arithmetic differs), so whole runs drift apart only as resampling decisions flip
    """

    def __init__(self, name: str = "AMMPF", particles: int = 1000, max_acceleration: float = 0.01,
                 target_sigma: float = 0.05, buoy_sigma: float = 0.0005,
                 tpm: Sequence[Sequence[float]] = ((0.95, 0.025, 0.025), (0.025, 0.95, 0.025), (0.025, 0.025, 0.95)),
                 lw_h: float = 0.3, noise_gain: str = "standard", auxiliary: bool = True, chunk_runs: int | None = None,
                 workers: int | None = None, snapshot_particles: int = 0, engine: str = "numba") -> None:
        super().__init__(name, max_acceleration, target_sigma, buoy_sigma, noise_gain)
        if not (isinstance(particles, int) and not isinstance(particles, bool) and particles >= 10):
            raise ValueError(f"particles: {particles!r} must be an integer >= 10")
        matrix = np.asarray(tpm, dtype=float)
        if matrix.shape != (3, 3) or np.any(matrix < 0) or not np.allclose(matrix.sum(axis=1), 1.0, atol=1e-9):
            raise ValueError(f"tpm: {np.asarray(tpm).tolist()} must be a 3 x 3 matrix of probabilities whose rows sum "
                             f"to 1 (rows: from CV, Omega > 0, Omega < 0)")
        if not (0.0 <= lw_h < 1.0):
            raise ValueError(f"lw_h: {lw_h} must be in [0, 1) (0 = no regularisation)")
        if chunk_runs is not None and not (isinstance(chunk_runs, int) and not isinstance(chunk_runs, bool)
                                           and chunk_runs >= 1):
            raise ValueError(f"chunk_runs: {chunk_runs!r} must be an integer >= 1 or null (automatic)")
        if workers is not None and not (isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1):
            raise ValueError(f"workers: {workers!r} must be an integer >= 1 or null (one per processor)")
        if not (isinstance(snapshot_particles, int) and 0 <= snapshot_particles <= particles):
            raise ValueError(f"snapshot_particles: {snapshot_particles!r} must be an integer in [0, particles]")
        checked_engine(engine, "the compiled particle scan, filters/particle/kernel.py")
        self.engine = engine
        self.snapshot_particles = snapshot_particles
        self.particles = particles
        self.chunk_runs = chunk_runs
        self.workers = workers
        self.tpm = matrix
        self.lw_h = float(lw_h)
        self.auxiliary = bool(auxiliary)

    def run(self, reports: BuoyReports) -> TrackEstimate:
        """All runs, ``chunk_runs`` runs at a time: a chunk's particle arrays (a few MB) stay in the
        processor's cache through a scan; results do not depend on the chunking (per-run random
        streams)."""
        started = _time.perf_counter()
        R, K, _ = reports.z.shape
        progress = current_progress()       # taken here: the worker threads do not inherit the listener
        progress.start(K - 1, "scan", self.name)
        gens = reports.generators(f"particles:{self.name}")
        workers = max(1, min(self.workers or available_processors(), R))
        size = self.chunk_runs
        if size is None and self.engine == "numba":
            # a chunk's particles, random numbers and scratch (~550 B per particle) within the
            # core's 2 MB L2 cache; the chunks are handed to the workers as they free up
            size = max(1, min(R, 1_100_000 // (550 * self.particles)))
        elif size is None:      # a whole number of chunks per worker, each at most 25 runs
            count = workers * -(-R // (workers * 25))
            size = -(-R // count)
        chunks = [slice(r0, min(r0 + size, R)) for r0 in range(0, R, size)]
        workers = min(workers, len(chunks))
        if workers > 1:
            # numpy releases the GIL inside its array loops and its random fills, the compiled scan
            # runs without it: chunks of runs filter in parallel
            with ThreadPoolExecutor(max_workers=workers) as pool:
                parts = list(pool.map(lambda c: self._run_chunk(reports, gens, c, progress), chunks))
        else:
            parts = [self._run_chunk(reports, gens, c, progress) for c in chunks]
        extras = {name: np.concatenate([p[2][name] for p in parts]) for name in parts[0][2]}
        return TrackEstimate(reports.time.copy(), np.concatenate([p[0] for p in parts]),
                             np.concatenate([p[1] for p in parts]), extras, _time.perf_counter() - started)

    def _run_chunk(self, all_reports: BuoyReports, all_gens, runs: slice, progress: Progress = SILENT):
        reports = all_reports.select(range(runs.start, runs.stop))
        # each scan of this chunk is its share of the runs' scan: the scans done over all chunks
        share = (runs.stop - runs.start) / all_reports.z.shape[0]
        on_scan = None if progress is SILENT else (lambda: progress.advance(share))
        if self.engine == "numba":
            return self._compiled_chunk(reports, all_gens[runs], on_scan)
        model = SonobuoyModel(self.max_acceleration, self.target_sigma, self.buoy_sigma, self.noise_gain,
                              reports.likelihood(), np.asarray(reports.observer, dtype=float))
        return filter_jump_markov(model, self.tpm, reports.time, reports.z, reports.prior_mean, reports.prior_std,
                                  all_gens[runs], self.particles, self.auxiliary, self.lw_h, self.snapshot_particles,
                                  on_scan)

    def _compiled_chunk(self, reports: BuoyReports, gens, on_scan=None):
        """``filter_jump_markov`` for ``SonobuoyModel``, a scan at a time through the compiled kernel
        (``filters.particle.kernel.scan``): the same start, random numbers, outputs and extras
        (``on_scan()`` after each scan, as there)."""
        from filters.particle import kernel

        R, K = reports.z.shape[:2]
        N, M, n = self.particles, 3, 20
        X = reports.prior_mean[:, None, :] + reports.prior_std * _stack(gens, lambda g: g.standard_normal((N, n)))
        modes = np.zeros((R, N), dtype=np.int64)                            # every particle starts in mode 0
        states = np.full((R, K, n), np.nan)
        covariances = np.full((R, K, n, n), np.nan)
        mode_probability = np.full((R, K, M), np.nan)
        ess = np.full((R, K), np.nan)
        states[:, 0], covariances[:, 0] = weighted_moments(X, np.full((R, N), 1.0 / N))
        mode_probability[:, 0] = np.eye(M)[0]
        ess[:, 0] = N
        P = self.snapshot_particles
        if P:
            spaced = np.linspace(0, N - 1, P).astype(np.int64)
            cloud = np.full((R, K, P, n), np.nan, dtype=np.float32)
            cloud_modes = np.full((R, K, P), -1, dtype=np.int8)
            cloud[:, 0], cloud_modes[:, 0] = X[:, spaced], 0
        underflow = np.zeros((R, K), dtype=bool)
        nis, nis_dof = np.full((R, K), np.nan), np.zeros((R, K))
        X = np.ascontiguousarray(np.swapaxes(X, 1, 2))        # (R, 20, N): the kernel's component-major layout
        X_out = np.empty_like(X)

        likelihood = reports.likelihood()
        lik = np.stack([likelihood._nominal_factor, likelihood._clutter_factor,
                        likelihood._nominal_factor - likelihood._clutter_factor, likelihood._clutter_scale,
                        likelihood._nominal_scale, likelihood._nominal_log_scale]).astype(np.float32)
        mixture = bool(likelihood.clutter_probability > 0)
        variance = np.ascontiguousarray(likelihood.variance, dtype=float)
        observer = np.ascontiguousarray(reports.observer, dtype=float)
        log_tpm = np.log(np.maximum(self.tpm, 1e-300))
        sigma = np.array([self.target_sigma] + [self.buoy_sigma] * BUOYS)
        draws = _ScanDraws(R, N, self.auxiliary, self.lw_h > 0)
        # each run's numbers in filter_jump_markov's order: drawn inside the kernel from the runs'
        # PCG64 states (the same numbers, checked once per process), else by the Generators here
        inline = _inline_draws_match() and all(type(g.bit_generator).__name__ == "PCG64" for g in gens)
        rng = np.stack([_pcg64_state(g) for g in gens]) if inline else np.zeros((R, 6), dtype=np.uint64)
        for k in range(1, K):
            dt = float(reports.time[k] - reports.time[k - 1])
            G = noise_gain(dt, self.noise_gain)
            if not inline:
                draws.draw(gens)
            kernel.scan(X, X_out, modes, np.ascontiguousarray(reports.z[:, k]), dt, log_tpm, self.tpm, lik, mixture,
                        observer, self.max_acceleration, sigma, np.array([G[0, 0], G[1, 1], G[2, 0], G[3, 1]]),
                        self.lw_h, self.auxiliary, draws.first_offsets, draws.uniforms, draws.noise,
                        draws.second_offsets, draws.normals, rng, inline, variance, k, states, covariances,
                        mode_probability, ess, underflow, nis, nis_dof)
            X, X_out = X_out, X                                # the kernel leaves scan k's cloud in X_out
            if P:
                cloud[:, k], cloud_modes[:, k] = np.swapaxes(X[:, :, spaced], 1, 2), modes[:, spaced]
            if on_scan is not None:
                on_scan()
        if inline:                                             # the Generators end where numpy's calls leave them
            for g, state in zip(gens, rng):
                _set_pcg64_state(g, state)
        extras = {"mode_probabilities": mode_probability, "ess": ess, "weights_underflow": underflow, "nis": nis,
                  "nis_dof": nis_dof}
        if P:
            extras.update(particles=cloud, particle_modes=cloud_modes)
        return states, covariances, extras


class SonobuoyModel:
    """Seed 004's jump-Markov model for ``filter_jump_markov``: 20 states, 3 target modes (CV,
    Omega > 0, Omega < 0), process noise (target 2 + 4 buoys x 2 accelerations) through Gamma, the
    8-bearing likelihood. The likelihoods run in float32 (see ``_target_bearings``)."""

    modes = 3
    state_size = 20
    noise_shape = (5, 2)

    def __init__(self, max_acceleration: float, target_sigma: float, buoy_sigma: float, gain: str,
                 likelihood: BearingLikelihood, observer: np.ndarray) -> None:
        self.max_acceleration = max_acceleration
        self.sigma = np.array([target_sigma] + [buoy_sigma] * BUOYS)[:, None]
        self.gain = gain
        self.target_part, self.buoy_part = likelihood.subset(slice(0, 4)), likelihood.subset(slice(4, 8))
        self.observer = observer

    def first_stage(self, X: np.ndarray, z: np.ndarray, dt: float) -> tuple[np.ndarray, dict]:
        """log p(z | mu(i, m)) (R, N, 3) of the noise-free predicted means (eq 16), and what the
        propagation re-uses (the buoys' predicted states, the turn rates)."""
        R, N = X.shape[:2]
        buoys = X[..., 4:].reshape(R, N, BUOYS, 4)
        buoys_next = np.concatenate([buoys[..., :2] + dt * buoys[..., 2:], buoys[..., 2:]], axis=-1)
        target_mean = predicted_positions(X[..., 0:4], self.max_acceleration, dt)            # (R, N, 3, 2)
        predicted = mode_bearings(target_mean, buoys_next[..., :2])                           # (R, N, 3, 4)
        zz = z[:, None, None, 0:4].astype(np.float32)
        log_likelihood = (self.target_part.log(predicted, zz).sum(axis=-1, dtype=np.float64)
                          + _buoy_log_likelihood(buoys_next[..., :2], z, self.observer, self.buoy_part)[..., None])
        return log_likelihood, {"buoys_next": buoys_next}

    def propagate(self, X: np.ndarray, parent: np.ndarray, mode: np.ndarray, noise: np.ndarray, dt: float,
                  context: dict | None) -> np.ndarray:
        """Eq 15: each parent under its drawn mode, plus process noise (noise (R, N, 5, 2) standard)."""
        R, N = parent.shape
        run_index = np.arange(R)[:, None]
        source = X[run_index, parent]
        omega = np.take_along_axis(turn_rates(source[..., 2:4], self.max_acceleration), mode[..., None], axis=-1)[..., 0]
        increments = (noise * self.sigma) @ noise_gain(dt, self.gain).T                        # (R, N, 5, 4)
        if context is not None:
            buoys_next = context["buoys_next"][run_index, parent]
        else:
            buoys = source[..., 4:].reshape(R, N, BUOYS, 4)
            buoys_next = np.concatenate([buoys[..., :2] + dt * buoys[..., 2:], buoys[..., 2:]], axis=-1)
        X_new = np.empty_like(X)
        X_new[..., 0:4] = coordinated_turn(source[..., 0:4], omega, dt) + increments[..., 0, :]
        X_new[..., 4:] = (buoys_next + increments[..., 1:, :]).reshape(R, N, 16)
        return X_new

    def predicted_measurements(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The particles' (R, N, 20) bearings, float32: target from each buoy (R, N, 4) and each buoy
        from the observer (R, N, 4); computed once per scan for the likelihood and the NIS."""
        R, N = X.shape[:2]
        buoys = X[..., 4:].reshape(R, N, BUOYS, 4)[..., :2]
        return _target_bearings(X[..., :2], buoys), _buoy_bearings(buoys, self.observer)

    def innovation_nis(self, predicted: tuple[np.ndarray, np.ndarray], log_weights: np.ndarray, z: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(R,) NIS of scan k's received bearings against the predicted cloud, and its dof (R,).

        ``predicted`` the propagated particles' bearings (``predicted_measurements``) and
        ``log_weights`` (R, N) their weights as a sample of the prediction p(x_k | z_1..k-1). The
        predicted bearings' mean and covariance are the cloud's (exact moments, no linearisation),
        plus the measurement noise; clutter is taken as noise of the mixture's variance
        (1 - p_c) s^2 + p_c s_c^2 (measurement-origin uncertainty ignored), so the mean NIS of a
        consistent filter is the dof while the chi-square band is only approximate in clutter (the
        mixture's tails are heavier).
        """
        weights = normalise_log(log_weights).astype(np.float32)
        bearing = np.concatenate(predicted, axis=-1)                                      # (R, N, 8)
        reference = bearing[:, :1]
        deviation = wrap(bearing - reference)
        mean = (weights[:, None, :] @ deviation)[:, 0]                                   # (R, 8)
        centred = deviation - mean[:, None, :]
        S = (np.swapaxes(centred * weights[..., None], -1, -2) @ centred).astype(np.float64)
        reference, mean = reference.astype(np.float64), mean.astype(np.float64)
        S = S + np.diag(np.concatenate([self.target_part.variance, self.buoy_part.variance]))
        return _masked_nis(wrap(z - reference[:, 0] - mean), S)

    def log_likelihood(self, X: np.ndarray, z: np.ndarray,
                       predicted: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(R, N) log p(z | X); ``predicted``: X's bearings when already computed."""
        target, buoy = self.predicted_measurements(X) if predicted is None else predicted
        return (_bearings_log_likelihood(target, z[:, 0:4], self.target_part)
                + _bearings_log_likelihood(buoy, z[:, 4:8], self.buoy_part))


def mode_bearings(target_mean: np.ndarray, buoy_xy: np.ndarray) -> np.ndarray:
    """Bearings (float32, (..., 3, 4)) of the three modes' predicted target positions (..., 3, 2)
    from the buoys (..., 4, 2). The turn modes' positions differ from the CV one by at most
    a_m T^2 / 2 (0.125 m for case 2), so their bearings are the CV bearing plus the first-order
    change (d_y Delta_x - d_x Delta_y) / rho^2: off by (Delta / rho)^2 (< 1e-6 rad beyond 125 m
    from a buoy), far below the 7 deg noise, with one atan2 per buoy instead of three."""
    cv = target_mean[..., 0, :].astype(np.float32)
    d = cv[..., None, :] - buoy_xy.astype(np.float32)                                  # (..., 4, 2)
    base = np.arctan2(d[..., 0], d[..., 1])
    rho2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
    shift = (target_mean[..., 1:, :] - target_mean[..., :1, :]).astype(np.float32)      # (..., 2, 2)
    change = (d[..., None, :, 1] * shift[..., :, None, 0] - d[..., None, :, 0] * shift[..., :, None, 1]) / rho2[..., None, :]
    return np.concatenate([base[..., None, :], base[..., None, :] + change], axis=-2)


def _target_bearings(target_xy: np.ndarray, buoy_xy: np.ndarray) -> np.ndarray:
    """float32 bearings (..., 4) of the target (..., 2) from the buoys (..., 4, 2).

    In float32: bearings of differences of ~10 km positions keep ~1e-7 rad, far below the
    1.5-15 deg noise, and numpy's float32 atan2/exp/log run about twice as fast."""
    d = target_xy.astype(np.float32)[..., None, :] - buoy_xy.astype(np.float32)
    return np.arctan2(d[..., 0], d[..., 1])


def _buoy_bearings(buoy_xy: np.ndarray, observer: np.ndarray) -> np.ndarray:
    """float32 bearings (..., 4) of the buoys (..., 4, 2) from the observer."""
    d = buoy_xy.astype(np.float32) - observer.astype(np.float32)
    return np.arctan2(d[..., 0], d[..., 1])


def _bearings_log_likelihood(predicted: np.ndarray, z: np.ndarray, part: BearingLikelihood) -> np.ndarray:
    """Sum over 4 components of log p(z | predicted); predicted (R, ..., 4) float32, z (R, 4)."""
    zz = z.astype(np.float32).reshape((z.shape[0],) + (1,) * (predicted.ndim - 2) + (4,))
    return part.log(predicted, zz).sum(axis=-1, dtype=np.float64)


def _buoy_log_likelihood(buoy_xy: np.ndarray, z: np.ndarray, observer: np.ndarray,
                         part: BearingLikelihood) -> np.ndarray:
    return _bearings_log_likelihood(_buoy_bearings(buoy_xy, observer), z[:, 4:8], part)


def filter_jump_markov(model, tpm: np.ndarray, time: np.ndarray, z: np.ndarray, prior_mean: np.ndarray,
                       prior_std: np.ndarray, gens, particles: int, auxiliary: bool = True, lw_h: float = 0.0,
                       snapshot_particles: int = 0, on_scan: Callable[[], None] | None = None):
    """The multiple-model particle filter over scans 1..K-1, batched over runs (R) and particles.

    ``model`` supplies ``modes``, ``state_size``, ``noise_shape``, ``first_stage(X, z, dt)``,
    ``propagate(X, parent, mode, noise, dt, context)`` and ``log_likelihood(X, z)`` (and for the NIS
    ``predicted_measurements(X)``, ``innovation_nis(predicted, log_weights, z)`` and
    ``log_likelihood(X, z, predicted)``); ``gens`` one
    random generator per run. Auxiliary (AMMPF, seed eqs 15-17): first-stage weights over every
    (particle, mode) pair, joint systematic resampling of (parent, mode), propagation, second-stage
    weights p(z|x)/p(z|mu). Otherwise the bootstrap SIR-MM (mode from the transition matrix).
    Then output moments, resample every scan (seed step 5) and regularise (Liu-West, ``lw_h``).
    Returns states (R, K, n), covariances, extras (mode_probabilities, ess, weights_underflow, nis,
    nis_dof[, particles, particle_modes]); the NIS when the model has ``innovation_nis``.
    ``on_scan()`` is called after each scan (progress; it reads and changes nothing here).
    """
    R, K = z.shape[:2]
    N, M, n = particles, model.modes, model.state_size
    log_tpm = np.log(np.maximum(tpm, 1e-300))
    X = prior_mean[:, None, :] + prior_std * _stack(gens, lambda g: g.standard_normal((N, n)))
    modes = np.zeros((R, N), dtype=np.int64)                                # every particle starts in mode 0
    states = np.full((R, K, n), np.nan)
    covariances = np.full((R, K, n, n), np.nan)
    mode_probability = np.full((R, K, M), np.nan)
    ess = np.full((R, K), np.nan)
    states[:, 0], covariances[:, 0] = weighted_moments(X, np.full((R, N), 1.0 / N))
    mode_probability[:, 0] = np.eye(M)[0]
    ess[:, 0] = N
    P = snapshot_particles
    if P:
        spaced = np.linspace(0, N - 1, P).astype(np.int64)
        cloud = np.full((R, K, P, n), np.nan, dtype=np.float32)
        cloud_modes = np.full((R, K, P), -1, dtype=np.int8)
        cloud[:, 0], cloud_modes[:, 0] = X[:, spaced], 0
    run_index = np.arange(R)[:, None]
    underflow = np.zeros((R, K), dtype=bool)
    nis, nis_dof = np.full((R, K), np.nan), np.zeros((R, K))
    for k in range(1, K):
        dt = float(time[k] - time[k - 1])
        zk = z[:, k]
        if auxiliary:
            first, context = model.first_stage(X, zk, dt)                          # (R, N, M), eq 16
            log_lambda = log_tpm[modes] + first                                     # weights are uniform after resampling
            log_lambda, lost = _restart_if_underflowed(log_lambda.reshape(R, M * N))
            underflow[:, k] |= lost
            log_lambda = log_lambda.reshape(R, N, M)
            pick = systematic_resample(log_lambda.reshape(R, M * N), _stack(gens, lambda g: g.random()), N)
            parent, new_mode = pick // M, pick % M
            first_at_pick = np.take_along_axis(first.reshape(R, M * N), pick, axis=1)
        else:
            parent = np.broadcast_to(np.arange(N), (R, N))
            u = _stack(gens, lambda g: g.random(N))
            new_mode = np.minimum((u[..., None] > np.cumsum(tpm[modes], axis=-1)).sum(axis=-1), M - 1)
            first_at_pick, context = 0.0, None
        # float32 normals: half the generator time; they only scale small perturbations
        noise = _stack(gens, lambda g: g.standard_normal((N,) + tuple(model.noise_shape), dtype=np.float32))
        X_new = model.propagate(X, parent, new_mode, noise, dt, context)              # eq 15
        # the propagated cloud reweighted by 1 / p(z | mu) (auxiliary) is a sample of the prediction
        if hasattr(model, "innovation_nis"):          # the bearings serve the NIS and the likelihood
            predicted = model.predicted_measurements(X_new)
            nis[:, k], nis_dof[:, k] = model.innovation_nis(predicted, np.broadcast_to(-first_at_pick, (R, N)), zk)
            log_likelihood = model.log_likelihood(X_new, zk, predicted)
        else:
            log_likelihood = model.log_likelihood(X_new, zk)
        log_weights, lost = _restart_if_underflowed(log_likelihood - first_at_pick)
        underflow[:, k] |= lost
        weights = normalise_log(log_weights)                                           # eq 17
        states[:, k], covariances[:, k] = weighted_moments(X_new, weights)
        mode_probability[:, k] = np.stack([np.sum(weights * (new_mode == m), axis=1) for m in range(M)], -1)
        ess[:, k] = 1.0 / np.sum(weights**2, axis=1)
        keep = systematic_resample(np.log(np.maximum(weights, 1e-300)), _stack(gens, lambda g: g.random()), N)
        X = X_new[run_index, keep]
        modes = new_mode[run_index, keep]
        if lw_h > 0:
            X = liu_west(X, lw_h, _stack(gens, lambda g: g.standard_normal((N, n), dtype=np.float32)))
        if P:
            cloud[:, k], cloud_modes[:, k] = X[:, spaced], modes[:, spaced]
        if on_scan is not None:
            on_scan()
    extras = {"mode_probabilities": mode_probability, "ess": ess, "weights_underflow": underflow, "nis": nis,
              "nis_dof": nis_dof}
    if P:
        extras.update(particles=cloud, particle_modes=cloud_modes)
    return states, covariances, extras


def _masked_nis(residual: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, C) residuals (NaN: the component was missed) and (R, C, C) innovation covariances ->
    (R,) nu' S^-1 nu over the received components and (R,) their number (NaN NIS where none)."""
    received = np.isfinite(residual)
    both = received[:, :, None] & received[:, None, :]
    eye = np.eye(residual.shape[-1], dtype=bool)
    S = np.where(both, S, np.where(eye, 1.0, 0.0))               # a missed component: decoupled, unit
    nu = np.where(received, residual, 0.0)
    nis = einsum("ri,ri->r", nu, np.linalg.solve(S, nu[..., None])[..., 0])
    dof = received.sum(axis=-1).astype(float)
    return np.where(dof > 0, nis, np.nan), dof


def _restart_if_underflowed(log_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, M) log weights -> the same, with a run whose every weight underflowed (all -inf, or NaN)
    restarted from uniform weights, and (R,) which runs that was. The run goes on (its cloud is
    kept, its estimate flagged ``weights_underflow``) instead of turning into NaN."""
    log_weights = np.where(np.isnan(log_weights), -np.inf, log_weights)
    lost = ~np.isfinite(log_weights.max(axis=1))
    return np.where(lost[:, None], 0.0, log_weights), lost


class BearingsEKF(_ModelParameters):
    """EKF on the same 20 states with one CV target model (notes 6.4): Joseph update on the received
    components; in clutter the moment-matched variance (1 - p_c) s^2 + p_c s_c^2 per component."""

    def __init__(self, name: str = "EKF", target_sigma: float = 0.05, buoy_sigma: float = 0.0005,
                 noise_gain: str = "standard") -> None:
        super().__init__(name, 0.0, target_sigma, buoy_sigma, noise_gain)       # one CV model: no a_m

    def run(self, reports: BuoyReports) -> TrackEstimate:
        started = _time.perf_counter()
        R, K, _ = reports.z.shape
        pc = reports.clutter_probability
        variance = (1.0 - pc) * reports.std**2 + pc * reports.clutter_std**2                # (8,)
        x = reports.prior_mean.copy()
        P = np.broadcast_to(np.diag(reports.prior_std**2), (R, 20, 20)).copy()
        states = np.full((R, K, 20), np.nan)
        covariances = np.full((R, K, 20, 20), np.nan)
        states[:, 0], covariances[:, 0] = x, P
        nis, nis_dof = np.full((R, K), np.nan), np.zeros((R, K))     # its own innovation (moment-matched R)
        observer = np.asarray(reports.observer, dtype=float)
        progress = current_progress()
        progress.start(K - 1, "scan", self.name)
        for k in range(1, K):
            dt = float(reports.time[k] - reports.time[k - 1])
            F = np.kron(np.eye(5), cv_transition(dt))
            x = rows_times(x, F.T)
            P = F @ P @ F.T + self._process_noise(dt)
            z = reports.z[:, k]
            H = bearing_jacobian(x, observer)                                              # (R, 8, 20)
            residual = wrap(z - bearings(x, observer))
            received = ~np.isnan(z)
            # a missed component: zero row and a unit variance, so it changes nothing
            H = np.where(received[..., None], H, 0.0)
            residual = np.where(received, residual, 0.0)
            Rm = np.broadcast_to(np.diag(variance), (R, 8, 8)) * received[:, None, :] * received[:, :, None]
            Rm = Rm + np.eye(8) * (~received)[:, None, :]
            PHt = P @ np.swapaxes(H, -1, -2)
            S = H @ PHt + Rm
            nis[:, k], nis_dof[:, k] = _masked_nis(np.where(received, residual, np.nan), S)
            gain = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
            x = x + einsum("rij,rj->ri", gain, residual)
            A = np.eye(20) - gain @ H
            P = A @ P @ np.swapaxes(A, -1, -2) + gain @ Rm @ np.swapaxes(gain, -1, -2)
            P = 0.5 * (P + np.swapaxes(P, -1, -2))
            states[:, k], covariances[:, k] = x, P
            progress.advance()
        return TrackEstimate(reports.time.copy(), states, covariances, {"nis": nis, "nis_dof": nis_dof},
                             _time.perf_counter() - started)


def bearing_jacobian(state: np.ndarray, observer: np.ndarray) -> np.ndarray:
    """(R, 20) -> (R, 8, 20): d bearing / d state (notes 6.4)."""
    R = state.shape[0]
    H = np.zeros((R, 8, 20))
    target = state[:, 0:2]
    for i in range(BUOYS):
        buoy = state[:, 4 + 4 * i:6 + 4 * i]
        d = target - buoy
        rho2 = d[:, 0] ** 2 + d[:, 1] ** 2
        row = np.stack([d[:, 1] / rho2, -d[:, 0] / rho2], -1)
        H[:, i, 0:2] = row
        H[:, i, 4 + 4 * i:6 + 4 * i] = -row
        d = buoy - observer
        rho2 = d[:, 0] ** 2 + d[:, 1] ** 2
        H[:, 4 + i, 4 + 4 * i:6 + 4 * i] = np.stack([d[:, 1] / rho2, -d[:, 0] / rho2], -1)
    return H
