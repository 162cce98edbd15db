"""Sonobuoy bearings: each of four buoys measures the target's bearing and a fixed observer
measures each buoy's bearing, with missed components and clutter (study 004, spec 004 "Model"
and "Clutter and missed detections"; seed 004 eqs 7-10 and section 3; literature notes 6.2).

Bearings from north, clockwise, with x = east: the bearing of (dx, dy) is atan2(dx, dy), wrapped
into (-pi, pi].
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.particle import BUOYS, STATE_NAMES, bearings  # eqs 8-9, shared with the filters
from pipeline.run.checks import non_negative
from pipeline.data import Detections, Truth
from pipeline.run.seeding import run_generators
from pipeline.sensors import wrap_angle

MEASUREMENT_NAMES = ("bearing",)
MEASUREMENT_UNITS = ("rad",)
COMPONENTS = 2 * BUOYS          # theta_1..4 (target from buoy i), then phi_1..4 (buoy i from the observer)
CLUTTER = -1                    # Detections.target of a clutter return


def _probability(key: str, value: object) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: {value!r} must be a probability in [0, 1]") from None
    if not (np.isfinite(number) and 0.0 <= number <= 1.0):
        raise ValueError(f"{key}: {value!r} must be a probability in [0, 1]")
    return number


class SonobuoyBearings:
    """At every scan k >= 1 of a ``SonobuoyField`` truth, 8 bearing components (seed eqs 7-10):
    slots 0-3 theta_i, the target's bearing from buoy i = 1..4, and slots 4-7 phi_i, buoy i's
    bearing from the observer fixed at ``observer_position`` (spec 004: (0, -8 km)). Scan 0 (the
    start) has no measurement: z NaN and detected False in all 8 slots (spec 004: first
    measurement at 5 s).

    Each component independently (seed section 3; literature notes 6.2): missing with
    ``miss_probability``; otherwise a clutter return with ``clutter_probability``, the true bearing
    plus N(0, clutter std^2) (15 deg target bearings, 5 deg buoy bearings in spec 004); otherwise
    nominal, the true bearing plus N(0, std^2) (7 deg, 1.5 deg); wrapped into (-pi, pi]. The draws
    are ``run_generators(seed, "measure", R)``, per run uniform (K, 8, 2) (miss, clutter) and then
    standard normal (K, 8) (the noise, scaled by the nominal or the clutter std), taken at every
    scan whatever the probabilities, so the draws do not depend on the settings and run r depends
    only on (seed, r): with the same seed a clean and a cluttered sensor share their nominal noise.

    ``Detections``: time = truth.time; sensor (K,) zeros; z (R, K, 8, 1) the bearing per slot, NaN
    where missed (and at scan 0); noise_covariance (R, K, 8, 1, 1) the slot's NOMINAL variance at
    every scan (what the sensor states; the filters know ``clutter_std`` and the probabilities from
    the attributes); target (R, K, 8) the object the slot measures: 0 (the target) in slots 0-3,
    i = 1..4 (buoy i) in slots 4-7, and -1 (``CLUTTER``) for a clutter return; detected (R, K, 8)
    False for a missed component (the slot's target then stays the object index);
    measurement_names ("bearing",), units ("rad",).

    Attributes for the filters: ``observer_position`` (2,) [m], ``nominal_std`` (8,) and
    ``clutter_std`` (8,) [rad] per slot, ``miss_probability``, ``clutter_probability``.

    Parameters
    ----------
    observer_position : the fixed observer (east, north) [m]
    target_bearing_std_deg : nominal std of theta_i [deg] (>= 0)
    buoy_bearing_std_deg : nominal std of phi_i [deg] (>= 0)
    miss_probability : probability a component is missing, in [0, 1]
    clutter_probability : probability a received component is clutter, in [0, 1]
    clutter_target_bearing_std_deg : clutter std of theta_i [deg] (>= 0)
    clutter_buoy_bearing_std_deg : clutter std of phi_i [deg] (>= 0)
    """

    produces = "sonobuoy_bearings"          # filters.base.MEASUREMENT_KINDS

    def __init__(self, observer_position: Sequence[float] = (0.0, -8000.0), target_bearing_std_deg: float = 7.0,
                 buoy_bearing_std_deg: float = 1.5, miss_probability: float = 0.0, clutter_probability: float = 0.0,
                 clutter_target_bearing_std_deg: float = 15.0, clutter_buoy_bearing_std_deg: float = 5.0) -> None:
        try:
            observer = np.asarray(observer_position, dtype=float)
        except (TypeError, ValueError):
            observer = np.array([np.nan])
        if observer.shape != (2,) or not np.all(np.isfinite(observer)):
            raise ValueError(f"observer_position: {observer_position!r} must be a finite [east, north] in m")
        self.observer_position = observer
        target_std = np.radians(non_negative("target_bearing_std_deg", target_bearing_std_deg, "deg"))
        buoy_std = np.radians(non_negative("buoy_bearing_std_deg", buoy_bearing_std_deg, "deg"))
        clutter_target = np.radians(non_negative("clutter_target_bearing_std_deg",
                                                  clutter_target_bearing_std_deg, "deg"))
        clutter_buoy = np.radians(non_negative("clutter_buoy_bearing_std_deg", clutter_buoy_bearing_std_deg, "deg"))
        self.nominal_std = np.repeat([target_std, buoy_std], BUOYS)
        self.clutter_std = np.repeat([clutter_target, clutter_buoy], BUOYS)
        self.miss_probability = _probability("miss_probability", miss_probability)
        self.clutter_probability = _probability("clutter_probability", clutter_probability)

    def measure(self, truth: Truth, seed: int) -> Detections:
        """The 8 bearings of every scan k >= 1 of ``truth`` (state names ``STATE_NAMES``, one object)."""
        if tuple(truth.state_names) != STATE_NAMES:
            raise ValueError(f"truth state_names: {list(truth.state_names)} must be the SonobuoyField state "
                             f"{list(STATE_NAMES)} for SonobuoyBearings")
        R, K, T, _ = truth.state.shape
        if T != 1:
            raise ValueError(f"truth state: {T} objects per scan must be 1 (the augmented target and buoy state)")
        time = np.asarray(truth.time, dtype=float)
        draws = [(g.random((K, COMPONENTS, 2)), g.standard_normal((K, COMPONENTS)))
                 for g in run_generators(seed, "measure", R)]
        uniform = np.stack([u for u, _ in draws])                                   # (R, K, 8, 2)
        normal = np.stack([n for _, n in draws])                                    # (R, K, 8)
        missed = uniform[..., 0] < self.miss_probability
        clutter = ~missed & (uniform[..., 1] < self.clutter_probability)
        missed[:, 0] = True                                                         # no measurement at the start
        clutter[:, 0] = False
        std = np.where(clutter, self.clutter_std, self.nominal_std)
        z = wrap_angle(bearings(truth.state[:, :, 0], self.observer_position) + std * normal)
        z = np.where(missed, np.nan, z)
        obj = np.concatenate([np.zeros(BUOYS, dtype=np.int64), np.arange(1, BUOYS + 1)])
        target = np.where(clutter, CLUTTER, obj)
        return Detections(
            time=time.copy(), sensor=np.zeros(K, dtype=int), z=z[..., None],
            noise_covariance=np.broadcast_to((self.nominal_std ** 2)[:, None, None], (R, K, COMPONENTS, 1, 1)).copy(),
            target=target, detected=~missed, measurement_names=MEASUREMENT_NAMES,
            measurement_units=MEASUREMENT_UNITS,
        )
