"""How far from the limit: posterior Cramer-Rao bounds (filters.bounds) along a study's truth.

A bound node (config ``bound``, ``_target_`` a study's bound class, e.g.
pipeline.studies.ao_vsimm.bound.KnownInputBound) gives a single-target study
``position_bound(truth, sensor) -> (K,)`` = sqrt(trace) of the position block of the PCRLB of the
process that generated the truth at each scan [m] (NaN before the filters' first estimate), and
optionally ``position_bound_model`` = the same under the filters' assumed model; the study adds
them and the ratios ``position_rmse_over_bound`` / ``position_rmse_over_bound_model`` (RMSE /
sqrt(PCRLB): 1 = at the bound). One meaning per name in every study: below 1 against
``position_bound`` beyond Monte Carlo error is a bug; against ``position_bound_model`` it means
the truth does not follow the filters' model. This module holds what the
studies' bounds share: argument checks, the scan interval, the per-truth memo and the metrics.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from pipeline.data import Truth
from pipeline.evaluation.uncertainty import RunValues


def positive_parameter(key: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{key}: {value} must be a finite number > 0")
    return value


def scan_interval(truth: Truth) -> float:
    steps = np.diff(truth.time)
    if steps.size == 0 or not np.allclose(steps, steps[0]):
        raise ValueError("bound: the PCRLB here needs evenly spaced scans; the truth's times are not")
    return float(steps[0])


class PerTruth:
    """Values computed from one truth and sensor (a bound along the true trajectory), kept for the
    truth last asked about: the runner evaluates every variant against the same truth, so the
    bound is computed once per (truth, sensor, key), not once per variant. Holds the objects
    themselves, compared by identity (ids could be reused), and only the latest truth's values."""

    def __init__(self) -> None:
        self._entries: list[tuple[Any, Any, Any, Any]] = []

    def get(self, truth: Truth, sensor, key, compute: Callable[[], Any]) -> Any:
        for cached_truth, cached_sensor, cached_key, value in self._entries:
            if cached_truth is truth and cached_sensor is sensor and cached_key == key:
                return value
        value = compute()
        self._entries = [e for e in self._entries if e[0] is truth] + [(truth, sensor, key, value)]
        return value


def bound_metrics(bound, truth: Truth, sensor, position_rmse: RunValues) -> dict[str, np.ndarray | RunValues]:
    """For a bound node (None: none): ``position_bound`` (K,), the PCRLB of the process that made the
    truth, and ``position_rmse_over_bound`` (the RMSE kept per run, over it); with a node that also
    has ``position_bound_model`` (the filters' assumed model), that bound and its ratio too."""
    if bound is None:
        return {}
    limit = bound.position_bound(truth, sensor)
    out = {"position_bound": limit, "position_rmse_over_bound": position_rmse.over(limit)}
    if hasattr(bound, "position_bound_model"):
        model = bound.position_bound_model(truth, sensor)
        out |= {"position_bound_model": model, "position_rmse_over_bound_model": position_rmse.over(model)}
    return out
