"""A target crossing a field of four drifting sonobuoys (study 004, spec 004 "Model" and
"Scenarios"; seed 004 eqs 1-6; literature notes sections 6.1-6.2).

Frame: x = east, y = north [m]; headings and bearings from north, clockwise, so a heading psi
moves along (sin psi, cos psi) and the bearing of (dx, dy) is atan2(dx, dy). The truth is the
seed's augmented state of 20: the target (x, y, vx, vy), then buoys 1..4 (x, y, vx, vy each).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

# eqs 3, 4, 6 and the state layout, shared with the filters
from filters.particle import BUOYS, NOISE_GAINS, STATE_NAMES, ct_transition, cv_transition, noise_gain
from pipeline.run.checks import non_negative, positive, whole_steps
from pipeline.data import Truth
from pipeline.run.seeding import run_generators

CV, COUNTER_CLOCKWISE, CLOCKWISE = 1, 2, 3      # the seed's mode numbers by its FORMULA (see SonobuoyField)
TURN_DIRECTIONS = {"right": -1.0, "left": 1.0}  # sign of Omega (Omega > 0 turns counter-clockwise)


def _finite_array(key: str, value: object, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        array = np.array([np.nan])
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise ValueError(f"{key}: {value!r} must be {what}")
    return array


class SonobuoyField:
    """A target (no process noise) and four buoys drifting with the current (with process noise),
    sampled at t = 0, dt, ..., duration (scan 0 is the start; the sensor measures from scan 1).

    Target: starts at ``target_start`` with ``target_velocity`` and runs straight until
    ``target_turn_start`` (None: never), then makes a coordinated turn with centripetal
    acceleration ``target_turn_acceleration`` until the end: turn rate |Omega| = accel / speed
    (seed eq 5; the speed stays |target_velocity|), Omega < 0 (clockwise: the heading from north
    increases) for ``turn_direction`` "right", Omega > 0 for "left" (spec 004 cases 2 and 2B: right
    from 800 s at 0.005 m/s^2). Each step is the exact transition F_CT(Omega) (``filters.particle.ct_transition``);
    a step that straddles the turn start is F_CT(Omega) over the part after it times F_CV over the
    part before it, so the start need not be on the scan grid. No process noise (spec 004: "target
    without process noise").

    Buoys: buoy i starts at ``buoy_positions[i]`` with velocity ``buoy_drift`` and follows
    b(k+1) = F_CV b(k) + Gamma v_i(k), v_i(k) ~ N(0, buoy_sigma^2 I2) (seed eqs 3, 6) with Gamma
    from ``filters.particle.noise_gain(dt, noise_gain)``. The draws v are ``run_generators(seed, "scenario", R)``,
    standard_normal((K-1, 4, 2)) per run (step, buoy, axis), taken even when buoy_sigma = 0, so
    run r depends only on (seed, r).

    ``generate`` returns ``Truth`` with state (R, K, 1, 20) in ``STATE_NAMES`` order (the target's
    (x, y, vx, vy), then b1_x, b1_y, b1_vx, b1_vy, ..., b4_vy) and the label
      "turn_mode" (R, K, 1) int: the mode r_k of the step (k-1, k] that led to scan k (the seed's
      X_k = A^(r_k) X_{k-1}): 1 for straight (CV), and for a turning step the seed's mode number by
      its FORMULA Omega = (-1)^j a_m / speed (eq 5): 2 for Omega > 0 (counter-clockwise, "left"),
      3 for Omega < 0 (clockwise, "right"). The seed LABELS mode 2 "clockwise"; the label and the
      formula disagree (literature notes 6.1) and spec 004 keeps the formula, so the truth's right
      turn is mode 3 ("the seed's r = 3 formula despite its label"). Scan 0 is 1, and a step that
      straddles the turn start counts as a turn.

    Parameters
    ----------
    duration : last scan time [s]; a whole number (>= 1) of dt; scans at 0, dt, ..., duration
    dt : scan period T [s]
    target_start : the target's initial position (east, north) [m]
    target_velocity : the target's initial velocity (east, north) [m/s]; non-zero if it turns
    buoy_positions : four (east, north) [m], buoys 1..4
    buoy_drift : every buoy's initial velocity (east, north) [m/s] (the current)
    buoy_sigma : buoy process-noise std [m/s^2] (>= 0)
    target_turn_start : time the turn starts [s] (>= 0), or None for no turn
    target_turn_acceleration : centripetal acceleration of the turn [m/s^2] (> 0)
    turn_direction : "right" (clockwise) or "left" (counter-clockwise)
    noise_gain : "standard" (g = T^2/2) or "paper" (g = T/2, seed eq 6 as printed)
    """

    def __init__(self, duration: float = 1800.0, dt: float = 5.0,
                 target_start: Sequence[float] = (-6000.0, 3000.0),
                 target_velocity: Sequence[float] = (5.0, -1.0),
                 buoy_positions: Sequence[Sequence[float]] = ((-2000.0, -2000.0), (2000.0, -2000.0),
                                                              (2000.0, 2000.0), (-2000.0, 2000.0)),
                 buoy_drift: Sequence[float] = (0.2, 0.1), buoy_sigma: float = 0.0005,
                 target_turn_start: float | None = None, target_turn_acceleration: float = 0.005,
                 turn_direction: str = "right", noise_gain: str = "standard") -> None:
        self.dt = positive("dt", dt, "s")
        duration = positive("duration", duration, "s")
        self.steps = whole_steps(duration, self.dt)
        self.duration = self.steps * self.dt
        self.target_start = _finite_array("target_start", target_start, (2,), "a finite [east, north] in m")
        self.target_velocity = _finite_array("target_velocity", target_velocity, (2,),
                                             "a finite [east, north] in m/s")
        self.buoy_positions = _finite_array("buoy_positions", buoy_positions, (BUOYS, 2),
                                            f"{BUOYS} finite [east, north] positions in m")
        self.buoy_drift = _finite_array("buoy_drift", buoy_drift, (2,), "a finite [east, north] in m/s")
        self.buoy_sigma = non_negative("buoy_sigma", buoy_sigma, "m/s^2")
        if target_turn_start is None:
            self.target_turn_start = None
        else:
            self.target_turn_start = non_negative("target_turn_start", target_turn_start, "s (or null: no turn)")
            if not np.hypot(*self.target_velocity) > 0:
                raise ValueError(f"target_velocity: {target_velocity!r} must be non-zero when the target turns "
                                 f"(turn rate = acceleration / speed)")
        self.target_turn_acceleration = positive("target_turn_acceleration", target_turn_acceleration, "m/s^2")
        if not isinstance(turn_direction, str) or turn_direction not in TURN_DIRECTIONS:
            raise ValueError(f"turn_direction: {turn_direction!r} must be one of {list(TURN_DIRECTIONS)}")
        self.turn_direction = turn_direction
        if not isinstance(noise_gain, str) or noise_gain not in NOISE_GAINS:
            raise ValueError(f"noise_gain: {noise_gain!r} must be one of {list(NOISE_GAINS)}")
        self.noise_gain = noise_gain

    @property
    def time(self) -> np.ndarray:
        return np.arange(self.steps + 1) * self.dt

    @property
    def turn_rate(self) -> float:
        """Omega [rad/s] of the turn: -accel / speed for "right", +accel / speed for "left" (0 if no turn)."""
        if self.target_turn_start is None:
            return 0.0
        speed = float(np.hypot(*self.target_velocity))
        return TURN_DIRECTIONS[self.turn_direction] * self.target_turn_acceleration / speed

    @property
    def turn_mode(self) -> int:
        """The seed's mode number of the turn by its formula: 3 for Omega < 0 (right), 2 for Omega > 0."""
        return CLOCKWISE if TURN_DIRECTIONS[self.turn_direction] < 0 else COUNTER_CLOCKWISE

    def target_track(self) -> tuple[np.ndarray, np.ndarray]:
        """The target's (x, y, vx, vy) (K, 4) and mode r_k (K,) (see the class docstring)."""
        time, dt, omega = self.time, self.dt, self.turn_rate
        K = time.size
        state = np.empty((K, 4))
        state[0] = np.concatenate([self.target_start, self.target_velocity])
        mode = np.full(K, CV, dtype=np.int64)
        start = np.inf if self.target_turn_start is None else self.target_turn_start
        F_cv, F_ct = cv_transition(dt), ct_transition(omega, dt)
        for k in range(1, K):
            straight = float(np.clip(start - time[k - 1], 0.0, dt))     # CV part of (t_{k-1}, t_k]
            if straight >= dt:
                F = F_cv
            else:
                mode[k] = self.turn_mode
                F = F_ct if straight <= 0.0 else ct_transition(omega, dt - straight) @ cv_transition(straight)
            state[k] = F @ state[k - 1]
        return state, mode

    def generate(self, runs: int, seed: int) -> Truth:
        """The truth of ``runs`` Monte Carlo runs: one target track for all, buoy noise per run."""
        if int(runs) < 1:
            raise ValueError(f"runs: {runs!r} must be >= 1")
        R, dt = int(runs), self.dt
        K = self.steps + 1
        target, mode = self.target_track()
        noise = np.stack([g.standard_normal((K - 1, BUOYS, 2)) for g in run_generators(seed, "scenario", R)])
        w = self.buoy_sigma * noise                                                # (R, K-1, 4, 2) [m/s^2]
        gamma = noise_gain(dt, self.noise_gain)
        g_pos, g_vel = gamma[0, 0], gamma[2, 0]
        # b(k+1) = F_CV b(k) + Gamma w(k), unrolled: v(k) = v0 + g_vel sum_{j<k} w(j);
        # p(k) = p0 + sum_{j<k} (dt v(j) + g_pos w(j))
        zero = np.zeros((R, 1, BUOYS, 2))
        velocity = self.buoy_drift + np.concatenate([zero, np.cumsum(g_vel * w, axis=1)], axis=1)
        position = self.buoy_positions + np.concatenate(
            [zero, np.cumsum(dt * velocity[:, :-1] + g_pos * w, axis=1)], axis=1)  # (R, K, 4, 2)
        buoys = np.concatenate([position, velocity], axis=-1).reshape(R, K, 4 * BUOYS)
        state = np.concatenate([np.broadcast_to(target, (R, K, 4)), buoys], axis=-1)[:, :, None, :]
        labels = {"turn_mode": np.broadcast_to(mode[None, :, None], (R, K, 1)).copy()}
        return Truth(self.time, np.ascontiguousarray(state), STATE_NAMES, labels)
