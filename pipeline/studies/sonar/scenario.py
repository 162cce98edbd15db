"""Own-ship zig-zag and a (possibly turning) target for active/passive sonar tracking (study 003,
spec 003 "Scenarios"; literature notes section 3.3).

Frame: x = east, y = north [m]; headings (courses) in degrees from north, clockwise, so a ship on
course psi moves along (sin psi, cos psi). The state is the RELATIVE state of the seed-003 model,
target minus own-ship: (rx, ry, vx, vy, ax, ay) with (ax, ay) the target's acceleration.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.run.checks import finite, positive, whole_steps
from pipeline.data import Truth

STATE_NAMES = ("x", "y", "vx", "vy", "ax", "ay")


def _discrete_track(start: np.ndarray, speed: float, course_deg: np.ndarray, dt: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position (K, 2), velocity (K, 2) and discrete acceleration (K, 2) of a ship on the course
    profile ``course_deg`` (K,) at constant ``speed``.

    v(k) = speed (sin psi_k, cos psi_k); u(k) = (v(k+1) - v(k)) / dt, 0 on the last step;
    p(k+1) = p(k) + dt v(k) + dt^2/2 u(k) (u held constant over [k, k+1)), summed sequentially so
    each position is its predecessor plus the step, as in the recursion.
    """
    psi = np.radians(course_deg)
    velocity = speed * np.stack([np.sin(psi), np.cos(psi)], axis=-1)
    acceleration = np.zeros_like(velocity)
    acceleration[:-1] = (velocity[1:] - velocity[:-1]) / dt
    steps = dt * velocity[:-1] + (dt * dt / 2.0) * acceleration[:-1]
    position = np.cumsum(np.concatenate([start[None], steps]), axis=0)
    return position, velocity, acceleration


class SonarEncounter:
    """A zig-zagging own-ship and a target at constant speed, both deterministic (the paper's truth,
    no process noise), sampled at t = 0, dt, ..., duration.

    Own-ship: starts at the origin on course +``ownship_leg_heading`` at ``ownship_speed``; at every
    t = n ``ownship_leg`` (n >= 1) the commanded course flips sign (+h <-> -h) and the ship turns
    toward it at ``ownship_turn_rate`` (a 90 deg turn takes 30 s at 3 deg/s), so bearings-only
    tracking is observable (spec 003; seed 003 Fig. 1). A turn not finished when the next flip
    comes is turned back from where it got to.

    Target: starts at ``target_offset`` (east, north) from the own-ship's start on course
    ``target_heading`` at ``target_speed``; each [start_time, change] of ``target_turns`` is a
    coordinated turn at ``target_turn_rate`` beginning at start_time, change > 0 to the right
    (clockwise), < 0 to the left, lasting |change| / target_turn_rate (spec 003 case 2: 45 deg at
    0.5 deg/s, 90 s). Turns must be in time order and must not overlap; a turn beyond
    ``duration`` is cut there.

    Discretisation: the course profile is exact on the dt grid; v(k) = speed (sin psi_k, cos psi_k),
    the discrete acceleration u(k) = (v(k+1) - v(k)) / dt is held constant over [k, k+1) and
    p(k+1) = p(k) + dt v(k) + dt^2/2 u(k), for both ships. With the own-ship's u(k) as the known
    input, x(k+1) = Phi x(k) + Gamma_u u(k) with Gamma_u = -[dt^2/2 I2; dt I2; 0] (literature notes
    3.3) is then exact for the own-ship part; only the target's acceleration is left to the model.

    ``generate`` returns ``Truth`` with state (R, K, 1, 6) = (rx, ry, vx, vy, ax, ay): relative
    position and velocity (target minus own-ship) and the target's u(k) (0 on the last step),
    identical for every run, and labels
      "ownship" (R, K, 1, 4): own-ship (x, y, vx, vy) in the world frame;
      "ownship_acceleration" (R, K, 1, 2): own-ship u(k) (0 on the last step);
      "target_world" (R, K, 1, 4): target (x, y, vx, vy) in the world frame. (Not "target": the
      truth table already has a "target" column, the object index; see pipeline.storage.schemas.)

    Parameters
    ----------
    duration : last scan time [s]; scans at t = 0, dt, ..., duration (duration / dt + 1 scans)
    dt : sampling period [s]
    ownship_speed : [m/s]
    ownship_leg : time between course flips [s]
    ownship_leg_heading : h, the legs' courses are +h and -h [deg], 0 <= h < 90; the first is +h
    ownship_turn_rate : [deg/s]
    target_offset : target start minus own-ship start (east, north) [m]
    target_speed : [m/s]
    target_heading : the target's initial course [deg from north, clockwise]
    target_turns : list of [start_time (s, >= 0), course change (deg, != 0, > 0 right)]
    target_turn_rate : [deg/s]
    """

    def __init__(self, duration: float = 10000.0, dt: float = 1.0, ownship_speed: float = 5.0,
                 ownship_leg: float = 500.0, ownship_leg_heading: float = 45.0, ownship_turn_rate: float = 3.0,
                 target_offset: Sequence[float] = (5000.0, 10000.0), target_speed: float = 7.0,
                 target_heading: float = 225.0, target_turns: Sequence[Sequence[float]] = (),
                 target_turn_rate: float = 0.5) -> None:
        self.dt = positive("dt", dt, "s")
        duration = positive("duration", duration, "s")
        self.steps = whole_steps(duration, self.dt)
        self.duration = self.steps * self.dt
        self.ownship_speed = positive("ownship_speed", ownship_speed, "m/s")
        self.ownship_leg = positive("ownship_leg", ownship_leg, "s")
        self.ownship_turn_rate = positive("ownship_turn_rate", ownship_turn_rate, "deg/s")
        self.ownship_leg_heading = finite("ownship_leg_heading", ownship_leg_heading, "deg")
        if not 0 <= self.ownship_leg_heading < 90:
            raise ValueError(f"ownship_leg_heading: {ownship_leg_heading!r} must be in [0, 90) deg "
                             f"(the legs are +h and -h about north)")
        try:
            offset = np.asarray(target_offset, dtype=float)
        except (TypeError, ValueError):
            offset = np.array([np.nan])
        if offset.shape != (2,) or not np.all(np.isfinite(offset)):
            raise ValueError(f"target_offset: {target_offset!r} must be a finite [east, north] in m")
        self.target_offset = offset
        self.target_speed = positive("target_speed", target_speed, "m/s")
        self.target_heading = finite("target_heading", target_heading, "deg")
        self.target_turn_rate = positive("target_turn_rate", target_turn_rate, "deg/s")
        turns = []
        for i, turn in enumerate(target_turns):
            key = f"target_turns[{i}]"
            try:
                start, change = (float(v) for v in turn)
            except (TypeError, ValueError):
                raise ValueError(f"{key}: {turn!r} must be [start_time (s), course change (deg)]") from None
            if not (np.isfinite(start) and start >= 0):
                raise ValueError(f"{key}: start time {start!r} must be a finite number >= 0 s")
            if not (np.isfinite(change) and change != 0):
                raise ValueError(f"{key}: course change {change!r} must be a finite non-zero number of deg "
                                 f"(> 0 right, < 0 left)")
            if turns:
                previous_end = turns[-1][0] + abs(turns[-1][1]) / self.target_turn_rate
                if start < previous_end:
                    raise ValueError(f"{key}: start time {start:g} s must be >= {previous_end:g} s, the end "
                                     f"of target_turns[{i - 1}]; turns must be in time order and not overlap")
            turns.append((start, change))
        self.target_turns = turns

    @property
    def time(self) -> np.ndarray:
        return np.arange(self.steps + 1) * self.dt

    def ownship_course(self, time: np.ndarray) -> np.ndarray:
        """The own-ship's course [deg] at ``time`` [s] (exact, continuous, piecewise linear)."""
        t = np.asarray(time, dtype=float)
        h, leg, rate = self.ownship_leg_heading, self.ownship_leg, self.ownship_turn_rate
        segment = np.maximum(np.floor(t / leg), 0).astype(int)
        legs = int(segment.max(initial=0)) + 1
        start = np.empty(legs)                      # course at the start of each leg
        start[0] = h
        command = np.where(np.arange(legs) % 2 == 0, h, -h)
        for n in range(1, legs):
            gap = command[n - 1] - start[n - 1]
            start[n] = start[n - 1] + np.sign(gap) * min(rate * leg, abs(gap))
        gap = command[segment] - start[segment]
        return start[segment] + np.sign(gap) * np.minimum(rate * (t - segment * leg), np.abs(gap))

    def target_course(self, time: np.ndarray) -> np.ndarray:
        """The target's course [deg] at ``time`` [s] (exact, continuous, piecewise linear; not wrapped)."""
        t = np.asarray(time, dtype=float)
        course = np.full(t.shape, self.target_heading)
        for start, change in self.target_turns:
            course = course + np.sign(change) * np.clip(self.target_turn_rate * (t - start), 0.0, abs(change))
        return course

    def generate(self, runs: int, seed: int) -> Truth:
        """The deterministic encounter, copied for each of ``runs`` runs (``seed`` is not used)."""
        if int(runs) < 1:
            raise ValueError(f"runs: {runs!r} must be >= 1")
        R, time, dt = int(runs), self.time, self.dt
        own_p, own_v, own_u = _discrete_track(np.zeros(2), self.ownship_speed, self.ownship_course(time), dt)
        tgt_p, tgt_v, tgt_u = _discrete_track(self.target_offset, self.target_speed, self.target_course(time), dt)
        state = np.concatenate([tgt_p - own_p, tgt_v - own_v, tgt_u], axis=-1)        # (K, 6)

        def runs_copy(values: np.ndarray) -> np.ndarray:
            return np.broadcast_to(values[None, :, None, :], (R, *values.shape[:1], 1, values.shape[1])).copy()

        labels = {"ownship": runs_copy(np.concatenate([own_p, own_v], axis=-1)),
                  "ownship_acceleration": runs_copy(own_u),
                  "target_world": runs_copy(np.concatenate([tgt_p, tgt_v], axis=-1))}
        return Truth(time, runs_copy(state), STATE_NAMES, labels)
