"""Monte Carlo uncertainty: every summary value with its number of runs, standard error and interval,
and variants compared pairwise on the runs they share.

A study keeps a metric per run (``RunValues``: each run's contribution at each step, and how the
runs combine into the Monte Carlo value: an RMS, a mean, a count or a median). A summary value is a
``WindowStatistic``: the per-step Monte Carlo values reduced over a window's steps (mean, sum, max,
or pooled over runs and steps). Its uncertainty is the spread over the Monte Carlo runs, the
independent unit: every interval resamples or averages whole runs, never steps (which are
correlated along a run).

The interval of a value (``CONFIDENCE`` = 95 % by default):

- **t** where the value is a plain mean over runs of each run's own value (a mean NEES, models per
  step, a detection count divided by the runs: the same steps valid in every run): mean +- t(n-1)
  s / sqrt(n), with the standard error s / sqrt(n);
- **exact** (Clopper-Pearson, ``scipy.stats.binomtest``) where, in addition, each run's value is 0 or
  1 (a loss rate, a fraction of runs, a count of at most one event per run);
- **bootstrap** otherwise (an RMSE is the square root of a mean; a median; a window mean of per-step
  RMS errors; runs valid at different steps): ``scipy.stats.bootstrap`` over the runs, BCa,
  ``resamples`` resamples from a generator seeded by the job's seed, its standard error the
  bootstrap's. A statistic that every resample leaves unchanged (FSIMM's 13 models per step) has the
  point as its interval.

Paired comparisons (``comparisons``): variants filter the same runs with the same noise, so a
difference is judged on the runs' resamples drawn together: for each variant and each summary
statistic it shares with the reference variant, the difference and the ratio of the two values
with their bootstrap intervals (the same resamples for both), and the Wilcoxon signed-rank test
(``scipy.stats.wilcoxon``) of the runs' own values (``WindowStatistic.per_run``). A difference is
*resolved* when its interval excludes 0.
"""

from __future__ import annotations

import warnings
import zlib
from dataclasses import dataclass
from typing import Literal, Mapping, Sequence

import numpy as np

from filters.progress import SILENT, Progress
from filters.progress import current as current_progress

ACROSS_RUNS = ("rms", "mean", "sum", "median")
OVER_STEPS = ("mean", "sum", "max", "pool")
CONFIDENCE = 0.95
RESAMPLES = 2000
KEPT_RESAMPLES = 400                 # joint resamples stored with a run (resamples.parquet) for its targets
FLOAT32_CELLS = 200_000           # runs x steps above which a metric's resampled sums are float32
_BATCH_CELLS = 4_000_000          # resamples x steps per bootstrap batch: a few such arrays (32 MB each) at a time


@dataclass(frozen=True, eq=False)
class RunValues:
    """One per-step metric kept per Monte Carlo run.

    ``values`` (R, K): run r's contribution at step k, NaN where the run has none (not started, no
    report at that step); (R, K, m) for ``median`` over m members per run (buoys). ``across_runs``
    says how the runs combine at a step:

    - ``rms``: values are squared errors; sqrt(sum of values / sum of weights) over the runs that
      have one (an RMSE, or an RMSE divided by a bound when the values are e^2 / b^2);
    - ``mean``: sum of values / sum of weights (a mean NEES, a probability, models per step);
    - ``sum``: the sum over runs, NaN counting as 0 (a count of detections);
    - ``median``: the median over the runs (and members) that have a value.

    ``weights`` (R, K): the denominators of ``rms`` and ``mean`` (a run's NIS summed over its targets
    with weight = its number of targets makes the per-target mean); default 1 where a value exists.
    ``scale`` (K,): a fixed divisor of the per-step value (an RMSE over a bound: the ratio to the bound).
    ``impossible`` (R, K) bool: the run's value at the step exists but cannot be (a NEES below zero, from a
    covariance that is not positive definite): that value is dropped, and so is every Monte Carlo value
    it would enter: the per-step value at that step, a window statistic over it and its interval (NaN:
    null in the tables, with the run's fault flag), rather than a mean over the other runs.
    """

    values: np.ndarray
    across_runs: Literal["rms", "mean", "sum", "median"]
    weights: np.ndarray | None = None
    scale: np.ndarray | None = None
    impossible: np.ndarray | None = None

    def __post_init__(self) -> None:
        values = np.asarray(self.values, dtype=float)
        if self.across_runs not in ACROSS_RUNS:
            raise ValueError(f"RunValues.across_runs: {self.across_runs!r} is not one of {list(ACROSS_RUNS)}")
        if values.ndim != (3 if values.ndim == 3 and self.across_runs == "median" else 2):
            raise ValueError(f"RunValues.values: shape {values.shape} must be (runs, steps)"
                             + (" or (runs, steps, members)" if self.across_runs == "median" else ""))
        if self.impossible is not None:
            impossible = np.broadcast_to(np.asarray(self.impossible, dtype=bool), values.shape[:2])
            if impossible.any():
                values = np.where(impossible.reshape(impossible.shape + (1,) * (values.ndim - 2)), np.nan, values)
                object.__setattr__(self, "impossible", impossible)
            else:
                object.__setattr__(self, "impossible", None)
        object.__setattr__(self, "values", values)
        if self.weights is not None:
            if self.across_runs not in ("rms", "mean"):
                raise ValueError(f"RunValues.weights: only 'rms' and 'mean' take weights, not {self.across_runs!r}")
            weights = np.broadcast_to(np.asarray(self.weights, dtype=float), values.shape)
            object.__setattr__(self, "weights", np.where(np.isfinite(values), weights, 0.0))
        if self.scale is not None:
            scale = np.asarray(self.scale, dtype=float)
            if scale.shape != values.shape[1:2] or self.across_runs not in ("rms", "mean"):
                raise ValueError(f"RunValues.scale: shape {scale.shape} must be (steps,) = {values.shape[1:2]}, "
                                 f"for an 'rms' or 'mean'")
            object.__setattr__(self, "scale", scale)

    @property
    def runs(self) -> int:
        return self.values.shape[0]

    def over(self, scale: np.ndarray) -> "RunValues":
        """The same metric divided by a fixed (K,) per-step value (an RMSE over a bound: the ratio)."""
        if self.scale is not None:
            raise ValueError("RunValues.over: the metric is already divided by a scale")
        return RunValues(self.values, self.across_runs, self.weights, np.asarray(scale, dtype=float), self.impossible)

    def valid(self) -> np.ndarray:
        """(R, K): the run has a value at the step."""
        finite = np.isfinite(self.values)
        return finite.any(axis=-1) if finite.ndim == 3 else finite

    def per_step(self) -> np.ndarray:
        """(K,) the Monte Carlo value at each step (NaN where no run has one, or one run's is impossible)."""
        per_step = self._per_step()
        if self.impossible is not None:
            per_step = np.where(self.impossible.any(axis=0), np.nan, per_step)
        return per_step

    def _per_step(self) -> np.ndarray:
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            v = self.values
            if self.across_runs == "sum":
                return np.nansum(v, axis=0)
            if self.across_runs == "median":
                return nanmedian_last(_members_as_runs(v).T)
            if self.weights is None:
                mean = np.nanmean(v, axis=0)
            else:
                mean = np.nansum(v, axis=0) / np.where(self.weights.sum(axis=0) > 0, self.weights.sum(axis=0), np.nan)
            return self._scaled(np.sqrt(mean) if self.across_runs == "rms" else mean)

    def _scaled(self, per_step: np.ndarray) -> np.ndarray:
        return per_step if self.scale is None else per_step / self.scale

    def resampled_per_step(self, counts: np.ndarray, columns: np.ndarray, totals: "ResampledTotals") -> np.ndarray:
        """(B, C) the values at steps ``columns`` of B resamples of the runs: ``counts`` (B, R) how often
        each run is drawn; ``totals`` shares the weighted sums between the metrics of one array."""
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            if self.across_runs == "median":
                return totals.sorted_items(self.values, columns).median(counts)
            total = totals.of(self.values, columns, counts)
            if self.across_runs == "sum":
                return total
            if self.weights is None:
                denominator = totals.valid_counts(self.values, columns, counts)
            else:
                denominator = counts @ self.weights[:, columns]
            per_step = total / np.where(denominator > 0, denominator, np.nan)
            if self.across_runs == "rms":
                np.sqrt(per_step, out=per_step)
            if self.scale is not None:
                per_step /= self.scale[columns]
            return per_step

    def per_run_values(self) -> np.ndarray:
        """(R, K[, m]) the values with the scale applied per step (e^2 / b^2 for an ``rms``)."""
        if self.scale is None:
            return self.values
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.values / (self.scale**2 if self.across_runs == "rms" else self.scale)


class ResampledTotals:
    """Within one batch of resamples: sum over the drawn runs of a values array at some steps, computed
    once per array (an RMSE and its ratios to two bounds share one array; their metrics come one after
    the other, so only the current array's sums are kept), and the number of drawn runs with a value
    (the resample size at steps where every run has one: the usual case, no product needed)."""

    def __init__(self, columns_of: Mapping[int, np.ndarray]) -> None:
        self._columns_of = columns_of         # id(values) -> the union of the steps its metrics need
        self._totals: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._valid: dict[int, np.ndarray] = {}
        self._filled: dict[int, tuple[np.ndarray, np.ndarray]] = {}      # one array's values at its steps
        self._batch: int | None = None

    def batch(self, first: int) -> None:
        """A new batch of resamples: the sums are of the previous batch."""
        if first != self._batch:
            self._totals.clear()
            self._valid.clear()
            self._batch = first

    def _prepared(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = id(values)
        if key not in self._filled:
            self._filled.clear()
            part = values[:, self._columns_of[key]]
            finite = np.isfinite(part)
            self._filled[key] = (np.where(finite, part, 0.0).astype(self.dtype(part)), finite)
        return self._filled[key]

    @staticmethod
    def dtype(part: np.ndarray) -> type:
        """float32 for a large product (a 100-run, 10 001-step metric): it halves the product's time and
        memory, and its relative rounding (1e-6 over a run sum) is four orders below an interval's
        width; float64 for small ones, where it costs nothing (and the tests compare with scipy)."""
        return np.float32 if part.size > FLOAT32_CELLS else np.float64

    def sorted_items(self, values: np.ndarray, columns: np.ndarray) -> "SortedItems":
        """A median's values at ``columns`` sorted per step, once per array (kept for the current one)."""
        key = ("sorted", id(values), columns.size)
        cached = self._filled.get(key)
        if cached is None:
            self._filled.clear()
            cached = SortedItems(values[:, columns])
            self._filled[key] = cached
        return cached

    def _pick(self, key: int, table: np.ndarray, columns: np.ndarray, full: np.ndarray) -> np.ndarray:
        if columns is self._columns_of[key]:
            return table
        return table[:, np.searchsorted(full, columns)]

    def of(self, values: np.ndarray, columns: np.ndarray, counts: np.ndarray) -> np.ndarray:
        key = id(values)
        if key not in self._totals:
            self._totals.clear()              # metrics of one array come together: keep one array's sums
            full = self._columns_of[key]
            filled = self._prepared(values)[0]
            self._totals[key] = (counts.astype(filled.dtype, copy=False) @ filled, full)
        table, full = self._totals[key]
        return self._pick(key, table, columns, full)

    def valid_counts(self, values: np.ndarray, columns: np.ndarray, counts: np.ndarray) -> np.ndarray:
        key = id(values)
        full = self._columns_of[key]
        if key not in self._valid:
            self._valid.clear()
            valid = self._prepared(values)[1]
            drawn = counts.sum(axis=1, keepdims=True)
            every = valid.all(axis=0)
            if every.all():                   # every run has a value at every step: the resample size
                table = drawn
            else:
                table = np.broadcast_to(drawn, (counts.shape[0], full.size)).copy()
                table[:, ~every] = counts @ valid[:, ~every].astype(counts.dtype)
            self._valid[key] = table
        table = self._valid[key]
        return table if table.shape[1] == 1 else self._pick(key, table, columns, full)


class SortedItems:
    """The median over resampled runs without drawing them: each step's values (R runs x m members)
    are sorted once; a resample weighs each value by how often its run is drawn, and the median is
    read where the cumulative weight passes the middle rank (the mean of the two middle values for
    an even count), as np.nanmedian of the drawn values gives it. Gathering the drawn values and
    partitioning them cost a 50-run particle-filter job over a minute per variant; the weighing is
    one compiled pass (``pipeline.evaluation.kernels``)."""

    def __init__(self, values: np.ndarray) -> None:
        items = values if values.ndim == 2 else np.moveaxis(values, 2, 1).reshape(-1, values.shape[1])
        runs = values.shape[0]
        members = 1 if values.ndim == 2 else values.shape[2]
        run_of_item = np.repeat(np.arange(runs), members)                      # (I,) item -> its run
        order = np.argsort(np.where(np.isnan(items), np.inf, items), axis=0, kind="stable")   # (I, C)
        # step-major (C, I): each step's items contiguous for the kernel's walk
        self.values = np.ascontiguousarray(np.take_along_axis(items, order, axis=0).T)   # NaN last
        self.runs = np.ascontiguousarray(run_of_item[order].T)
        self.valid = np.isfinite(self.values)

    def median(self, counts: np.ndarray) -> np.ndarray:
        """(B, C) the median of each resample (``counts`` (B, R): draws per run); NaN where none."""
        from pipeline.evaluation.kernels import resampled_medians       # numba: only a median metric needs it
        out = np.empty((counts.shape[0], self.values.shape[0]))
        resampled_medians(self.values, self.runs, self.valid, np.ascontiguousarray(counts, dtype=np.float64), out)
        return out


def nanmedian_last(values: np.ndarray) -> np.ndarray:
    """The median over the last axis of the finite values (NaN where none), as np.nanmedian gives
    it; np.nanmedian falls back to one Python call per column when NaNs are present (minutes over a
    bootstrap of a 50-run particle-filter job), so here NaNs sort last and each column's middle is
    read at its own count of finite values."""
    nan = np.isnan(values)
    if not nan.any():
        return np.median(values, axis=-1)
    ordered = np.sort(np.where(nan, np.inf, values), axis=-1)
    count = (~nan).sum(axis=-1)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    high = np.take_along_axis(ordered, np.maximum(count // 2, 0)[..., None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore"):
        middle = 0.5 * (low + high)
    return np.where(count > 0, middle, np.nan)


def _members_as_runs(values: np.ndarray) -> np.ndarray:
    """(R, K, m) -> (R * m, K): a median over runs and members alike."""
    if values.ndim == 2:
        return values
    return np.moveaxis(values, 2, 1).reshape(-1, values.shape[1])


@dataclass(frozen=True, eq=False)
class WindowStatistic:
    """A summary value: ``values``' per-step Monte Carlo values over ``steps`` (indices), reduced by
    ``over_steps``: ``mean`` (NaN steps skipped), ``sum`` (counts), ``max`` (a peak), or ``pool``
    (the runs' values pooled over the window's steps first: sqrt(sum e^2 / count) over runs x steps)."""

    values: RunValues
    steps: np.ndarray
    over_steps: Literal["mean", "sum", "max", "pool"] = "mean"

    def __post_init__(self) -> None:
        if self.over_steps not in OVER_STEPS:
            raise ValueError(f"WindowStatistic.over_steps: {self.over_steps!r} is not one of {list(OVER_STEPS)}")
        if self.over_steps == "pool" and self.values.across_runs not in ("rms", "mean"):
            raise ValueError("WindowStatistic: over_steps='pool' pools an RMS or a mean, not a "
                             f"{self.values.across_runs!r}")
        object.__setattr__(self, "steps", np.asarray(self.steps, dtype=np.intp).reshape(-1))

    def impossible(self) -> bool:
        """A run's value in the window is impossible (``RunValues.impossible``): so is the statistic."""
        return self.values.impossible is not None and bool(self.values.impossible[:, self.steps].any())

    def value(self) -> float:
        """The Monte Carlo value (NaN when the window holds no value, or an impossible one)."""
        if self.impossible():
            return float("nan")
        if self.over_steps == "pool":
            return float(self._pooled(np.ones((1, self.values.runs)))[0])
        return float(_reduce(self.values.per_step()[self.steps][None, :], self.over_steps)[0])

    def resampled(self, per_step: np.ndarray | None, columns: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """(B,) the value of each resample, from the resamples' values (B, C) at the steps ``columns``
        (sorted, holding this statistic's steps)."""
        if self.over_steps == "pool":
            return self._pooled(counts)
        return _reduce(per_step[:, self._where_in(columns)], self.over_steps)

    def _where_in(self, columns: np.ndarray) -> slice | np.ndarray:
        """The positions of this statistic's steps among ``columns``: a slice where they are contiguous
        there (a window), so that reading them copies nothing."""
        cached = getattr(self, "_where", None)
        if cached is not None and cached[0] is columns:
            return cached[1]
        positions = np.searchsorted(columns, self.steps)
        where: slice | np.ndarray = positions
        if positions.size and positions[-1] - positions[0] + 1 == positions.size:
            where = slice(int(positions[0]), int(positions[-1]) + 1)
        object.__setattr__(self, "_where", (columns, where))
        return where

    def _pooled(self, counts: np.ndarray) -> np.ndarray:
        sums = getattr(self, "_run_sums", None)
        if sums is None:                      # each run's sum and weight over the window, once
            rv = self.values
            window = rv.per_run_values()[:, self.steps]
            weights = np.isfinite(window).astype(float) if rv.weights is None else rv.weights[:, self.steps]
            sums = (np.nansum(window, axis=1), weights.sum(axis=1))
            object.__setattr__(self, "_run_sums", sums)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (counts @ sums[0]) / (counts @ sums[1])
        return np.sqrt(mean) if self.values.across_runs == "rms" else mean

    def valid_runs(self) -> np.ndarray:
        """(R,) the runs that have a value in the window (NaN counts as 0 for a count: every run)."""
        if self.values.across_runs == "sum":
            return np.ones(self.values.runs, dtype=bool)
        return self.values.valid()[:, self.steps].any(axis=1)

    def per_run(self) -> np.ndarray:
        """(R,) each run's own value over the window (NaN for a run without one): the run's RMS error
        over the window's steps (``rms``), its mean (``mean``; for ``median``, of its members too), its
        count (``sum``), or its peak (``max``). The per-run table and the paired test read these. NaN
        for a run with an impossible value in the window."""
        own = self._per_run()
        if self.values.impossible is not None:
            own = np.where(self.values.impossible[:, self.steps].any(axis=1), np.nan, own)
        return own

    def _per_run(self) -> np.ndarray:
        window = self.values.per_run_values()[:, self.steps]
        if window.ndim == 3:
            window = np.nanmean(window, axis=2) if window.shape[2] else window[..., 0]
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            if self.values.across_runs == "sum":
                return np.nanmax(window, axis=1) if self.over_steps == "max" else np.nansum(window, axis=1)
            if self.over_steps == "max":
                peak = np.nanmax(window, axis=1)
                return np.sqrt(peak) if self.values.across_runs == "rms" else peak
            if self.values.weights is not None:
                weights = self.values.weights[:, self.steps].sum(axis=1)
                mean = np.nansum(window, axis=1) / np.where(weights > 0, weights, np.nan)
            else:
                mean = np.nanmean(window, axis=1)
            return np.sqrt(mean) if self.values.across_runs == "rms" else mean

    def plain_mean(self) -> tuple[np.ndarray, float] | None:
        """(each valid run's own value, scale) when the value is exactly scale x the mean of those (so a
        t or exact interval applies), else None. Holds for a mean or a count over runs with a mean or a
        sum over steps, without weights, when every valid run has a value at the same steps."""
        rv = self.values
        if rv.across_runs not in ("mean", "sum") or rv.weights is not None or rv.scale is not None \
                or self.over_steps not in ("mean", "sum") or self.impossible():
            return None
        if rv.values.ndim == 3:
            return None
        window = rv.values[:, self.steps]
        if rv.across_runs == "sum":
            window = np.where(np.isfinite(window), window, 0.0)
            steps_with_value = np.ones(window.shape[1], dtype=bool)
            runs = np.ones(window.shape[0], dtype=bool)
        else:
            valid = np.isfinite(window)
            runs = valid.any(axis=1)
            if not runs.any():
                return None
            steps_with_value = valid[runs][0]
            if not (valid[runs] == steps_with_value).all():      # runs valid at different steps: a ratio of sums
                return None
        inside = window[runs][:, steps_with_value]
        if not inside.shape[1]:
            return None
        own = inside.mean(axis=1) if self.over_steps == "mean" else inside.sum(axis=1)
        scale = float(runs.sum()) if rv.across_runs == "sum" else 1.0
        return own, scale


def _reduce(per_step: np.ndarray, over_steps: str) -> np.ndarray:
    """(B, k) -> (B,) over the window's steps; NaN where none has a value (0 steps: NaN too)."""
    if per_step.shape[1] == 0:
        return np.full(per_step.shape[0], np.nan)
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        if over_steps == "max":
            return np.nanmax(per_step, axis=1)
        total = per_step.sum(axis=1)
        if np.isfinite(total).all():          # no NaN step (the usual case): no masked copy
            return total if over_steps == "sum" else total / per_step.shape[1]
        if over_steps == "sum":
            return np.nansum(per_step, axis=1)
        return np.nanmean(per_step, axis=1)


# ---- intervals --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Interval:
    value: float
    n_valid_runs: int
    standard_error: float
    low: float
    high: float
    method: str                 # t | exact | bootstrap BCa | bootstrap percentile | constant | none | impossible


def plain_interval(own: np.ndarray, scale: float, confidence: float, value: float) -> Interval:
    """scale x mean of the runs' own values: Clopper-Pearson when each is 0 or 1, else Student's t."""
    from scipy import stats

    n = own.size
    if n < 2:
        return Interval(value, n, float("nan"), float("nan"), float("nan"), "none")
    if np.isin(own, (0.0, 1.0)).all():
        successes = int(own.sum())
        ci = stats.binomtest(successes, n).proportion_ci(confidence_level=confidence, method="exact")
        p = successes / n
        return Interval(value, n, scale * float(np.sqrt(p * (1 - p) / n)), scale * float(ci.low),
                        scale * float(ci.high), "exact")
    mean = float(own.mean())
    se = float(own.std(ddof=1) / np.sqrt(n))
    if se == 0.0:
        return Interval(value, n, 0.0, value, value, "constant")
    half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * se
    return Interval(value, n, scale * se, scale * (mean - half), scale * (mean + half), "t")


def bootstrap_values(groups: Sequence[tuple[RunValues, Sequence[WindowStatistic]]], runs: int, combine,
                     outputs: int, seed: Sequence[int], confidence: float, resamples: int):
    """Bootstrap over the runs, BCa: ``combine(values)`` maps the statistics' values on a set of
    resamples (a list of (B,) arrays in the order of ``groups``) to ``outputs`` rows (outputs, B).
    Returns (low, high, standard error, method) arrays over the outputs and the bootstrap
    distribution itself (outputs, resamples).

    The same resamples (``resamples`` x ``runs`` run indices from a generator seeded by ``seed``) serve
    every output, so a difference of two outputs is a paired one. The BCa interval is Efron's, as
    ``scipy.stats.bootstrap(method="BCa")`` computes it (tests/test_uncertainty.py checks that both
    give the same interval on the same resamples); it is computed here, metric by metric, so that
    one metric's values over all steps are read once for all resamples instead of once per batch of
    resamples (a 100-run, 10 001-step job would otherwise spend half a minute here). Where BCa is
    undefined (every resample on one side of the value: a statistic whose bootstrap is biased, such as
    a window mean of per-step RMS errors over many independent steps), the interval is the value +-
    z x the bootstrap standard error ("bootstrap normal"); where every resample agrees, the point
    ("constant"); NaN where more than 1 % of the resamples have no value ("none")."""
    values = _resampled(groups, runs, seed, resamples)
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        distribution, jackknife, point = (np.asarray(combine(v), dtype=float).reshape(outputs, -1) for v in values)
    low, high, se, method = _bca(distribution, jackknife, point[:, 0], confidence)
    return low, high, se, method, distribution


def _resampled(groups: Sequence[tuple[RunValues, Sequence[WindowStatistic]]], runs: int, seed: Sequence[int],
               resamples: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Each statistic's values (in the order of ``groups``) on the bootstrap resamples (B,), with each
    run left out (the jackknife, (runs,)), and on all runs once ((1,): the BCa's reference point)."""
    rng = np.random.default_rng(list(seed))
    drawn = rng.integers(0, runs, size=(resamples, runs))
    counts = np.zeros((resamples, runs))
    np.add.at(counts, (np.repeat(np.arange(resamples), runs), drawn.ravel()), 1.0)
    jack_counts = 1.0 - np.eye(runs)                    # the jackknife: each run left out once
    columns = [np.unique(np.concatenate([s.steps for s in stats_ if s.over_steps != "pool"] or
                                        [np.zeros(0, dtype=np.intp)])) for _, stats_ in groups]
    columns_of: dict[int, np.ndarray] = {}
    for (rv, _), needed in zip(groups, columns):
        key = id(rv.values)
        columns_of[key] = needed if key not in columns_of else np.union1d(columns_of[key], needed)

    sharing: dict[int, list[int]] = {}                 # values array -> the groups (metrics) reading it
    for g, (rv, _) in enumerate(groups):
        sharing.setdefault(id(rv.values), []).append(g)

    def evaluate(all_counts: np.ndarray, progress: Progress = SILENT) -> list[np.ndarray]:
        """Every statistic's value on each resample (rows of counts): array by array, batch by
        batch, the metrics sharing an array reading one product of counts and values; ``progress``
        hears of each array done."""
        progress.start(len(sharing), "bootstrap, metric", None)
        parts: list[list[list[np.ndarray]]] = [[[] for _ in statistics] for _, statistics in groups]
        totals = ResampledTotals(columns_of)
        for key, members in sharing.items():
            needed = columns_of[key]
            # a batch holds a few (B, C) arrays; a median also its (B, runs x members, C) weights
            rv = groups[members[0]][0]
            items = runs * int(np.prod(rv.values.shape[2:])) if rv.across_runs == "median" else 1
            batch = max(1, _BATCH_CELLS // (max(needed.size, 1) * items))
            for first in range(0, all_counts.shape[0], batch):
                counts_b = all_counts[first:first + batch]
                totals.batch(first)
                for g in members:
                    rv, statistics = groups[g]
                    per_step = rv.resampled_per_step(counts_b, needed, totals) if needed.size else None
                    for part, statistic in zip(parts[g], statistics):
                        part.append(statistic.resampled(per_step, needed, counts_b))
            progress.advance()
        return [np.concatenate(part) for group in parts for part in group]

    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        # the resamples are the work (the jackknife's and the point's rows are few): their progress
        results = evaluate(counts, current_progress()), evaluate(jack_counts), evaluate(np.ones((1, runs)))
    impossible = [s.impossible() for _, statistics in groups for s in statistics]
    for values in results:                  # an impossible value in a window: no value on any resample
        for i in np.flatnonzero(impossible):
            values[i] = np.full_like(values[i], np.nan)
    return results


def _bca(distribution: np.ndarray, jackknife: np.ndarray, point: np.ndarray, confidence: float):
    """(low, high, standard error, method) of each output row from its bootstrap ``distribution``
    (outputs, B), ``jackknife`` (outputs, runs) and value on all runs ``point`` (outputs,); see
    ``bootstrap_values``."""
    from scipy.special import ndtr, ndtri

    outputs = distribution.shape[0]
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        finite = np.isfinite(distribution).mean(axis=1) >= 0.99
        se = np.nanstd(distribution, axis=1, ddof=1)
        alpha = (1 - confidence) / 2
        # Efron's BCa: bias correction z0 from the share of resamples below the value, acceleration
        # from the jackknife's skewness
        below = np.nanmean(np.where(np.isfinite(distribution), distribution < point[:, None], np.nan), axis=1)
        z0 = ndtri(below)
        spread = np.nanmean(jackknife, axis=1, keepdims=True) - jackknife
        acceleration = np.nansum(spread**3, axis=1) / (6 * np.nansum(spread**2, axis=1) ** 1.5)
        z = ndtri(np.array([alpha, 1 - alpha]))[:, None]
        levels = ndtr(z0 + (z0 + z) / (1 - acceleration * (z0 + z)))            # (2, outputs)
        low, high = np.full(outputs, np.nan), np.full(outputs, np.nan)
        for o in np.nonzero(finite & np.isfinite(levels).all(axis=0))[0]:
            sample = distribution[o][np.isfinite(distribution[o])]
            low[o], high[o] = np.percentile(sample, 100 * levels[:, o])
    method = np.full(outputs, "bootstrap BCa", dtype=object)
    constant = finite & np.all(distribution == distribution[:, :1], axis=1)
    normal = finite & ~constant & ~(np.isfinite(low) & np.isfinite(high))
    half = ndtri(1 - alpha) * se
    low[normal], high[normal] = point[normal] - half[normal], point[normal] + half[normal]
    method[normal] = "bootstrap normal"
    low[constant], high[constant], se[constant] = point[constant], point[constant], 0.0
    method[constant] = "constant"
    low[~finite], high[~finite], se[~finite] = np.nan, np.nan, np.nan
    method[~finite] = "none"
    return low, high, se, method


def stream_seed(seed: int, *names: str) -> list[int]:
    """A generator seed for (job seed, names): the same resamples wherever the job runs."""
    return [int(seed), *(zlib.crc32(name.encode()) for name in names)]


# ---- a job's summary intervals and comparisons ---------------------------------------------------
@dataclass(frozen=True)
class Estimated:
    """One summary row's statistic: the variant, its series and window, and how it is computed."""
    variant: str
    series: str
    window: str | None
    statistic: "WindowStatistic | Resampled"


@dataclass(frozen=True)
class Resampled:
    """A ``WindowStatistic`` reduced to what its interval, its paired comparisons, the per-run table and
    the resamples table read (``resample``), so that the per-run, per-step values it came from can be
    let go (the evaluation resamples each variant's statistics when the variant is measured:
    pipeline.run.runner.Evaluation). ``summarize`` and ``summary_table`` take it where they take the
    statistic, with the same results bit for bit."""
    point: float                                   # the statistic's value
    valid: np.ndarray                              # (R,) runs with a value in the window
    plain: tuple[np.ndarray, float] | None         # its plain_mean()
    runs_values: np.ndarray                        # (R,) each run's own value (per_run())
    distribution: np.ndarray                       # (B,) its value on each bootstrap resample
    jackknife: np.ndarray                          # (R,) ... with each run left out
    all_runs: np.ndarray                           # (1,) ... on all runs once: the BCa's reference point
    impossible: bool = False                       # WindowStatistic.impossible(): null value and interval
    # (the arrays keep the resampling's dtype: float32 for large counts, ResampledTotals; pairs are
    # formed in it and cast to float64 after, as in bootstrap_values)

    @property
    def runs(self) -> int:
        return int(self.valid.size)

    def value(self) -> float:
        return self.point

    def valid_runs(self) -> np.ndarray:
        return self.valid

    def plain_mean(self) -> tuple[np.ndarray, float] | None:
        return self.plain

    def per_run(self) -> np.ndarray:
        return self.runs_values


def _runs_of(statistic: "WindowStatistic | Resampled") -> int:
    return statistic.runs if isinstance(statistic, Resampled) else statistic.values.runs


def resample(statistics: Sequence[WindowStatistic], seed: int, resamples: int = RESAMPLES) -> list[Resampled]:
    """Each statistic reduced to a ``Resampled`` on the job's bootstrap resamples (those of ``seed``,
    the same for every statistic of the job whenever it is resampled: a comparison stays paired).
    Statistics reading one ``RunValues`` share its resampled per-step values (give them together)."""
    if not statistics:
        return []
    runs = statistics[0].values.runs
    if any(s.values.runs != runs for s in statistics):
        raise ValueError("resample: every statistic of a job must hold the same Monte Carlo runs")
    # group the statistics by their RunValues so each resample computes a metric's per-step values once
    order: dict[int, tuple[RunValues, list[int]]] = {}
    for i, statistic in enumerate(statistics):
        order.setdefault(id(statistic.values), (statistic.values, []))[1].append(i)
    first_of_array: dict[int, int] = {}
    for n, (rv, _) in enumerate(order.values()):
        first_of_array.setdefault(id(rv.values), n)
    order = dict(sorted(order.items(), key=lambda item: first_of_array[id(item[1][0].values)]))
    flat_order = [i for _, members in order.values() for i in members]
    groups = [(rv, [statistics[i] for i in members]) for rv, members in order.values()]
    distribution, jackknife, point = _resampled(groups, runs, stream_seed(seed, "summary"), resamples)
    at = {i: p for p, i in enumerate(flat_order)}
    return [Resampled(s.value(), s.valid_runs(), s.plain_mean(), s.per_run(), distribution[at[i]],
                      jackknife[at[i]], point[at[i]], s.impossible()) for i, s in enumerate(statistics)]


def summarize(rows: Sequence[Estimated], reference: str | None, seed: int, confidence: float = CONFIDENCE,
              resamples: int = RESAMPLES, kept: dict | None = None) -> tuple[dict[int, Interval], list[dict]]:
    """Intervals of every row (by its index in ``rows``) and the paired comparisons of each variant with
    ``reference`` on every (series, window) both have (rows as dicts, see ``comparisons_schema``).
    A row's statistic is a ``WindowStatistic`` (resampled here, with the others) or one already
    ``resample``d on the same ``seed`` and ``resamples``.
    ``kept``: a dict that gets ``"values"``, the first ``KEPT_RESAMPLES`` joint resamples of every row
    (rows x resamples: the same resampled runs for every row), which the report judges targets on."""
    from scipy import stats

    if not rows:
        return {}, []
    runs = _runs_of(rows[0].statistic)
    if any(_runs_of(r.statistic) != runs for r in rows):
        raise ValueError("summarize: every statistic of a job must hold the same Monte Carlo runs")
    fresh = [i for i, r in enumerate(rows) if not isinstance(r.statistic, Resampled)]
    reduced = dict(zip(fresh, resample([rows[i].statistic for i in fresh], seed, resamples)))
    statistics = [reduced.get(i, r.statistic) for i, r in enumerate(rows)]
    if any(s.distribution.size != resamples for s in statistics):
        raise ValueError(f"summarize: a statistic was resampled {resamples} times elsewhere; every one must be "
                         f"resampled the same way")

    by_key = {(r.variant, r.series, r.window): i for i, r in enumerate(rows)}
    pairs = []
    if reference is not None:
        for i, r in enumerate(rows):
            j = by_key.get((reference, r.series, r.window))
            if r.variant != reference and j is not None:
                pairs.append((i, j))

    def combine(own: list[np.ndarray]) -> np.ndarray:
        out = list(own)
        with np.errstate(invalid="ignore", divide="ignore"):
            out += [own[i] - own[j] for i, j in pairs]
            out += [own[i] / own[j] for i, j in pairs]
        return np.stack(out)

    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        distribution = np.asarray(combine([s.distribution for s in statistics]), dtype=float)
        jackknife = np.asarray(combine([s.jackknife for s in statistics]), dtype=float)
        point = np.asarray(combine([s.all_runs for s in statistics]), dtype=float)[:, 0]
    low, high, se, method = _bca(distribution, jackknife, point, confidence)
    if kept is not None:
        kept["values"] = distribution[:len(rows), :KEPT_RESAMPLES]
    intervals: dict[int, Interval] = {}
    points = [s.value() for s in statistics]
    for i, statistic in enumerate(statistics):
        valid = statistic.valid_runs()
        n = int(valid.sum())
        plain = statistic.plain_mean()
        if statistic.impossible:
            intervals[i] = Interval(points[i], n, float("nan"), float("nan"), float("nan"), "impossible")
        elif plain is not None and np.isfinite(points[i]):
            intervals[i] = plain_interval(plain[0], plain[1], confidence, points[i])
        elif not np.isfinite(points[i]) or n < 2:
            intervals[i] = Interval(points[i], n, float("nan"), float("nan"), float("nan"), "none")
        else:
            intervals[i] = Interval(points[i], n, float(se[i]), float(low[i]), float(high[i]), str(method[i]))
    comparisons = []
    for p, (i, j) in enumerate(pairs):
        a, b = rows[i], rows[j]
        d, q = len(rows) + p, len(rows) + len(pairs) + p
        mine, theirs = statistics[i].per_run(), statistics[j].per_run()
        both = np.isfinite(mine) & np.isfinite(theirs)
        differences = (mine - theirs)[both]
        if differences.size and np.all(differences == 0):
            p_value = 1.0
        elif differences.size >= 2:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p_value = float(stats.wilcoxon(differences, zero_method="wilcox").pvalue)
        else:
            p_value = float("nan")
        difference = points[i] - points[j]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = points[i] / points[j] if points[j] != 0 else float("nan")
        resolved = bool(np.isfinite(low[d]) and np.isfinite(high[d]) and (low[d] > 0 or high[d] < 0))
        comparisons.append({
            "variant_key": a.variant, "reference_key": b.variant, "series": a.series, "window": a.window,
            "value": points[i], "reference_value": points[j], "n_paired_runs": int(both.sum()),
            "difference": difference, "difference_low": float(low[d]), "difference_high": float(high[d]),
            "ratio": float(ratio), "ratio_low": float(low[q]), "ratio_high": float(high[q]),
            "wilcoxon_p": p_value, "resolved": resolved,
        })
    return intervals, comparisons


def normalised_squared(values: np.ndarray, across_runs: Literal["mean", "median"] = "mean") -> RunValues:
    """A NEES or NIS kept per run, (R, K): e' P^-1 e is >= 0 for any positive-definite P, so a value
    below zero (a covariance that is not positive definite: the run's fault flag) is impossible, and
    so is every Monte Carlo value it would enter (``RunValues.impossible``): null, never a number."""
    values = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        return RunValues(values, across_runs, impossible=values < 0)


def counts_as_flags(flags: np.ndarray) -> np.ndarray:
    """(R, K) event flags (NaN counts as no event) -> 0/1 floats for a ``sum`` RunValues."""
    values = np.asarray(flags, dtype=float)
    return ((values != 0) & np.isfinite(values)).astype(float)


def comparisons_schema() -> Mapping[str, object]:
    import polars as pl
    return {"variant_key": pl.String, "reference_key": pl.String, "series": pl.String, "window": pl.String,
            "value": pl.Float64, "reference_value": pl.Float64, "n_paired_runs": pl.Int32,
            "difference": pl.Float64, "difference_low": pl.Float64, "difference_high": pl.Float64,
            "ratio": pl.Float64, "ratio_low": pl.Float64, "ratio_high": pl.Float64,
            "wilcoxon_p": pl.Float64, "resolved": pl.Boolean}
