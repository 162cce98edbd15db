"""The metric registry: one entry per metric name, read by the summary, the printed tables and the recordings.

Each metric says its ``unit`` (the text of the summary's unit column), its ``axis_unit`` (short,
for plot axes), how a summary window aggregates its per-step values (``mean`` over the window's
steps, or ``sum`` for counts), a short ``label`` for the printed table (metrics without one are in
the tables but not in the printed summary), how many significant ``digits`` to print (0.0023 m/s^2
prints as 0.0023, never 0.00), and, for NEES / NIS, the chi-square degrees of freedom ``dof``.

Shared metrics are registered here; a study registers its own in its package (at import, i.e.
when its study node is built). A family of names (``bias_rmse_range_offset_s2``) is registered
by a pattern. ``nees`` is the one normalised estimation error squared of the project.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Literal

import numpy as np

if TYPE_CHECKING:
    import polars as pl

BAND = "1 (95 % chi2 band of the run average)"
COUNT = "count: sum over runs (and, in the summary, over the window's steps)"


@dataclass(frozen=True)
class Metric:
    name: str
    unit: str
    axis_unit: str = ""
    aggregation: Literal["mean", "sum"] = "mean"
    label: str | None = None          # column label of the printed summary; None: not printed there
    digits: int = 3                   # significant digits when printed (at least two decimals above 1)
    dof: int | str | None = None      # chi-square degrees of freedom (NEES / NIS), or how they are made
    decimals: int | None = None       # fixed decimals instead of significant digits (percentages)
    quantity: str | None = None       # the quantity it is a breakdown of (None: the name itself)
    component: str | None = None      # the axis, bias element or mode it is of that quantity


# The tidy columns of the metrics and summary tables: ``metric`` (the quantity: position_rmse in every
# study) with its breakdown ``component`` (axis, bias element, mode), ``sensor`` (radar number) and
# ``target``; ``series`` is the unique name of the series (position_rmse_s2_t32), which the report's
# queries, the recordings and the printed tables address. A family's pattern names its groups
# 'component', 'sensor' and 'target'.
BREAKDOWN_COLUMNS = ("metric", "component", "sensor", "target")


_REGISTRY: dict[str, Metric] = {}
_FAMILIES: list[tuple[re.Pattern[str], Callable[[re.Match[str]], Metric]]] = []
_ORDER: list[str] = []                # registration order: the printed summary's column order


def register(*metrics: Metric) -> None:
    """Add metrics. A name has one definition in every study: registering it again with another
    definition is refused (the summary's units must not depend on which study was imported first)."""
    for metric in metrics:
        known = _REGISTRY.get(metric.name)
        if known is not None and known != metric:
            raise ValueError(f"metric {metric.name!r} is already registered as {known}; one name, one meaning: "
                             f"pick another name for {metric}")
        if known is None:
            _ORDER.append(metric.name)
        _REGISTRY[metric.name] = metric


def register_family(pattern: str, make: Callable[[re.Match[str]], Metric]) -> None:
    """Names matching ``pattern`` (a full match) get ``make(match)``."""
    _FAMILIES.append((re.compile(pattern), make))


def lookup(name: str) -> Metric | None:
    if name in _REGISTRY:
        return _REGISTRY[name]
    for pattern, make in _FAMILIES:
        match = pattern.fullmatch(name)
        if match:
            return replace(make(match), name=name)
    return None


def registered() -> tuple[list[str], list[str]]:
    """(the registered names in registration order, the families' patterns): what a summary's
    ``series`` may be, for messages that list the allowed names."""
    return list(_ORDER), [pattern.pattern for pattern, _ in _FAMILIES]


def breakdown(name: str) -> tuple[str, str | None, int | None, int | None]:
    """(metric, component, sensor, target) of a series name: position_rmse_s2_t32 -> (position_rmse,
    None, 2, 32), acceleration_rmse_x -> (acceleration_rmse, x, None, None); a name the registry does
    not break down is its own metric."""
    if name in _REGISTRY:
        metric = _REGISTRY[name]
        return metric.quantity or name, metric.component, None, None
    for pattern, make in _FAMILIES:
        match = pattern.fullmatch(name)
        if match:
            metric, groups = make(match), match.groupdict()
            sensor, target = groups.get("sensor"), groups.get("target")
            return (metric.quantity or name, groups.get("component") or metric.component,
                    None if sensor is None else int(sensor), None if target is None else int(target))
    return name, None, None, None


def with_breakdown(table: "pl.DataFrame") -> "pl.DataFrame":
    """``table`` (with a ``series`` column of series names) with the tidy columns metric, component,
    sensor, target before it: "the position RMSE of every study" is ``metric = 'position_rmse'``,
    whatever the study's breakdown by axis, radar or target."""
    import polars as pl

    names = table["series"].unique(maintain_order=True).to_list()
    parts = [breakdown(n) for n in names]
    lookup_frame = pl.DataFrame({"series": names, "metric": [p[0] for p in parts],
                                 "component": [p[1] for p in parts], "sensor": [p[2] for p in parts],
                                 "target": [p[3] for p in parts]},
                                schema={"series": pl.String, "metric": pl.String, "component": pl.String,
                                        "sensor": pl.Int32, "target": pl.Int32})
    joined = table.join(lookup_frame, on="series", how="left", maintain_order="left")
    position = table.columns.index("series")
    order = table.columns[:position] + list(BREAKDOWN_COLUMNS) + table.columns[position:]
    return joined.select(order)


def unit_of(name: str) -> str:
    metric = lookup(name)
    return "" if metric is None else metric.unit


def axis_unit_of(name: str) -> str:
    metric = lookup(name)
    return "" if metric is None else (metric.axis_unit or metric.unit)


def is_count(name: str) -> bool:
    metric = lookup(name)
    return metric is not None and metric.aggregation == "sum"


def printed_columns(names: set[str] | list[str]) -> list[tuple[str, str]]:
    """(name, label) of the printed summary's columns among ``names``, in registration order."""
    present = set(names)
    return [(n, _REGISTRY[n].label) for n in _ORDER if n in present and _REGISTRY[n].label]


def format_value(name: str, value: float | None) -> str:
    """The printed form of a summary value: counts as integers, fixed decimals where the metric says,
    else ``digits`` significant digits (and at least two decimals for values of 1 and above)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    metric = lookup(name)
    if metric is not None and metric.aggregation == "sum":
        return f"{value:.0f}"
    if metric is not None and metric.decimals is not None:
        return f"{value:.{metric.decimals}f}"
    digits = 3 if metric is None else metric.digits
    if value == 0 or not math.isfinite(value):
        return f"{value:.2f}"
    if abs(value) >= 1:
        return f"{value:.2f}"
    exponent = math.floor(math.log10(abs(value)))
    return f"{value:.{max(digits - 1 - exponent, 2)}f}"


def nees(error: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared e' P^-1 e of (..., n) errors with their (..., n, n)
    covariances; NaN where either is not finite (no estimate yet). A singular covariance falls back
    to the pseudo-inverse (such steps are flagged not_positive_definite by pipeline.evaluation.faults).

    Large inputs (``COMPILED_ENTRIES`` covariance entries or more: a 100-run, 10 001-step estimate)
    are solved by a compiled loop (``pipeline.evaluation.kernels.solve_quadratic``, the pseudo-inverse only for
    its singular matrices): numpy's batched solve took ~2.7 s and ~1 GB of temporaries there. The
    two agree to rounding (~1e-15 relative)."""
    error = np.asarray(error, dtype=float)
    n = error.shape[-1]
    packed = getattr(covariance, "packed", None)          # a PackedCovariance (pipeline.storage.schemas): read as it is
    if packed is not None or np.size(covariance) >= COMPILED_ENTRIES:
        from pipeline.evaluation.kernels import solve_quadratic      # numba: only large estimates pay its start
        if packed is not None:
            upper = np.triu_indices(n)
            index = np.empty((n, n), dtype=np.intp)
            index[upper] = index[upper[1], upper[0]] = np.arange(upper[0].size)
            entries = np.ascontiguousarray(packed).reshape(-1, upper[0].size)
        else:
            index = np.arange(n * n).reshape(n, n)
            entries = np.ascontiguousarray(covariance, dtype=float).reshape(-1, n * n)
        flat_error = np.ascontiguousarray(error).reshape(-1, n)
        value = np.empty(flat_error.shape[0])
        singular = np.zeros(flat_error.shape[0], dtype=np.bool_)
        solve_quadratic(flat_error, entries, index, value, singular)
        if singular.any():
            e = flat_error[singular]
            P = entries[singular][:, index].astype(float)
            value[singular] = np.einsum("...i,...i->...", e, (np.linalg.pinv(P) @ e[..., None])[..., 0])
        return value.reshape(error.shape[:-1])
    covariance = np.asarray(covariance, dtype=float)
    ok = np.isfinite(error).all(-1) & np.isfinite(covariance).all((-1, -2))
    P = np.where(ok[..., None, None], covariance, np.eye(error.shape[-1]))
    e = np.where(ok[..., None], error, 0.0)
    try:
        solved = np.linalg.solve(P, e[..., None])[..., 0]
    except np.linalg.LinAlgError:
        solved = (np.linalg.pinv(P) @ e[..., None])[..., 0]
    value = np.einsum("...i,...i->...", e, solved)
    return np.where(ok, value, np.nan)


# Above this many covariance entries nees() runs compiled (numba's import and first call, ~1 s, are
# not worth it for small jobs).
COMPILED_ENTRIES = 4_000_000


# ---- the shared metrics (every study's tracks, the filters' extras, the runner's summary rows) -------
register(
    Metric("acceleration_rmse_x", "m/s^2", "m/s²", label="acc RMSE X", quantity="acceleration_rmse", component="x"),
    Metric("acceleration_rmse_y", "m/s^2", "m/s²", label="acc RMSE Y", quantity="acceleration_rmse", component="y"),
    Metric("acceleration_rmse_z", "m/s^2", "m/s²", label="acc RMSE Z", quantity="acceleration_rmse", component="z"),
    Metric("acceleration_rmse", "m/s^2", "m/s²", label="acc RMSE"),
    Metric("position_rmse", "m", label="pos RMSE"),
    Metric("velocity_rmse", "m/s", label="vel RMSE"),
    Metric("nees", "1 (chi2 dof = n)", "-", label="NEES", dof="state size"),
    Metric("models_evaluated", "models/step", label="models/step"),
    Metric("models_pct_of_reference", "%", label="models %", decimals=1),
    Metric("group_reached_fraction", "fraction of runs", label="reached"),
    Metric("detections", COUNT, "count", aggregation="sum", label="detections"),
    Metric("detections_axis_x", COUNT, "count", aggregation="sum", label="det x", quantity="detections", component="x"),
    Metric("detections_axis_y", COUNT, "count", aggregation="sum", label="det y", quantity="detections", component="y"),
    Metric("detections_axis_z", COUNT, "count", aggregation="sum", label="det z", quantity="detections", component="z"),
    Metric("compute_seconds", "s", label="compute s"),
    Metric("compute_pct_of_reference", "%", label="compute %", decimals=1),
    Metric("nees_lower", BAND, "-"), Metric("nees_upper", BAND, "-"),
    Metric("nis", "1 (chi2 dof = measurement size)", "-", dof="measurement size"),
    Metric("nis_lower", BAND, "-"), Metric("nis_upper", BAND, "-"),
    Metric("input_level_x", "m/s^2", "m/s²", quantity="input_level", component="x"),
    Metric("input_level_y", "m/s^2", "m/s²", quantity="input_level", component="y"),
    Metric("input_level_z", "m/s^2", "m/s²", quantity="input_level", component="z"),
    # one meaning per name in every study (issue 22): position_bound is the PCRLB of the process that
    # generated the truth, a bound for any unbiased estimator of it (a ratio below 1 beyond Monte Carlo
    # error is a bug); position_bound_model the PCRLB under the filters' assumed motion model, which a
    # truth that does not follow that model (a deterministic profile) lets a filter undercut
    Metric("position_bound", "m (sqrt trace of the PCRLB position block of the process that generated the truth)", "m"),
    Metric("position_rmse_over_bound", "ratio (position RMSE / sqrt(PCRLB of the truth's process); below 1 beyond "
           "Monte Carlo error is a bug)", "ratio"),
    Metric("position_bound_model", "m (sqrt trace of the PCRLB position block under the filters' own motion model)",
           "m"),
    Metric("position_rmse_over_bound_model", "ratio (position RMSE / sqrt(PCRLB of the filters' own model); below 1: "
           "the truth does not follow that model)", "ratio"),
)
