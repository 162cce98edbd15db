"""Argument checks shared by the scenarios and sensors: each returns the value as a float or
raises one ValueError sentence naming the key, the value and what is allowed."""

from __future__ import annotations

import numpy as np


def _number(key: str, value: object, allowed: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: {value!r} must be {allowed}") from None
    return number


def positive(key: str, value: object, unit: str) -> float:
    number = _number(key, value, f"a number > 0 {unit}")
    if not (np.isfinite(number) and number > 0):
        raise ValueError(f"{key}: {value!r} must be > 0 {unit}")
    return number


def non_negative(key: str, value: object, unit: str) -> float:
    number = _number(key, value, f"a number >= 0 {unit}")
    if not (np.isfinite(number) and number >= 0):
        raise ValueError(f"{key}: {value!r} must be >= 0 {unit}")
    return number


def finite(key: str, value: object, unit: str) -> float:
    number = _number(key, value, f"a finite number in {unit}")
    if not np.isfinite(number):
        raise ValueError(f"{key}: {value!r} must be a finite number in {unit}")
    return number


def whole_steps(duration: float, dt: float) -> int:
    """How many steps of ``dt`` make ``duration`` (which must be a whole number >= 1 of them)."""
    steps = duration / dt
    if not (steps >= 1 - 1e-9 and abs(steps - round(steps)) <= 1e-9 * steps):
        raise ValueError(f"duration: {duration:g} s must be a whole number (>= 1) of scan periods dt = {dt:g} s")
    return int(round(steps))
