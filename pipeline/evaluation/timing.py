"""Compute time with its uncertainty: each variant's filtering pass timed several times in the job's
own process, its median with the order-statistic interval, and the ratios of variants timed in one
process.

One timed pass is one sample of a noisy quantity (another process on the machine, the CPU's clock,
the first pass's cold caches): six identical default jobs gave AO-VSIMM 84.6-268.5 % of FSIMM's
compute. So a job times each variant's filtering pass up to ``timing.passes`` times (the track
stage's own pass counts when it ran in this job), starting another only while the passes so far
and one more fit in ``timing.budget_s`` seconds; the variants' passes take turns, so a slow spell
of the machine falls on all of them. A cached estimate's stored time is the one pass of the process
that computed it: it is re-timed here when a pass fits the budget, and otherwise kept, marked
``compute_cached``; a ratio with such a time may mix two processes and is marked ``mixes_processes``.

The interval of the median of n passes is [min, max] of the passes: for any continuous distribution
of pass times it holds the median with probability 1 - 2 * 0.5**n (75 % for 3 passes, 94 % for 5;
the order-statistic interval, David & Nagaraja, "Order Statistics", 2003, 7.1). A ratio's interval is
[min_a / max_b, max_a / min_b], which holds the ratio of the medians whenever both intervals hold
theirs. The count of models a filter evaluates (``models_pct_of_reference``, where a study has one)
is exact and the same on every machine: the cost measure to compare, compute time its noisy echo.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

PASSES = 5              # timing.passes by default: the most timed passes per variant
BUDGET_S = 3.0          # timing.budget_s by default: no further pass once the passes would exceed it


@dataclass(frozen=True)
class Timing:
    """A variant's filtering time: the seconds of each timed pass (``passes``), and whether they are
    the one stored time of the process that computed a cached estimate (``cached``)."""

    passes: tuple[float, ...]
    cached: bool = False

    @property
    def count(self) -> int:
        return len(self.passes)

    def median(self) -> float:
        return float(np.median(self.passes)) if self.passes else float("nan")

    def interval(self) -> tuple[float | None, float | None]:
        """[min, max] of the passes: the order-statistic interval of the median (None for one pass)."""
        if self.count < 2:
            return None, None
        return float(min(self.passes)), float(max(self.passes))

    def coverage(self) -> float | None:
        """The probability that [min, max] of ``count`` passes holds the median: 1 - 2 * 0.5**n."""
        return None if self.count < 2 else 1.0 - 2.0 * 0.5 ** self.count

    def method(self) -> str:
        """The summary's ``interval`` column for this time."""
        if self.cached:
            return "one pass, cached: timed by the process that computed the estimate"
        if self.count < 2:
            return "one pass: one sample, no interval"
        return f"min-max of {self.count} timed passes ({100 * self.coverage():.0f} % for the median)"


def compute_row_fields(timing: Timing) -> dict:
    """The summary columns of a variant's ``compute_seconds`` row from its timing."""
    low, high = timing.interval()
    return {"value": timing.median(), "ci_low": low, "ci_high": high, "interval": timing.method(),
            "compute_passes": timing.count, "compute_cached": timing.cached}


def ratio_fields(mine: Timing, reference: Timing, same_variant: bool) -> dict:
    """The summary columns of a ``compute_pct_of_reference`` row: 100 x the ratio of the medians, its
    interval from the passes' ranges, and whether its two times come from different processes."""
    if same_variant:
        return {"value": 100.0, "ci_low": 100.0, "ci_high": 100.0, "interval": "constant",
                "compute_passes": mine.count, "compute_cached": mine.cached, "mixes_processes": False}
    ref = reference.median()
    value = 100.0 * mine.median() / ref if ref else float("nan")
    (a_low, a_high), (b_low, b_high) = mine.interval(), reference.interval()
    low = high = None
    method = "one pass each: one sample, no interval"
    if None not in (a_low, a_high, b_low, b_high) and b_low > 0:
        low, high = 100.0 * a_low / b_high, 100.0 * a_high / b_low
        method = "from the passes' ranges: min / max to max / min"
    mixed = mine.cached or reference.cached     # two cached times need not come from one process either
    if mixed:
        method = "mixes processes (a cached time: another process's pass): not a comparison"
    return {"value": value, "ci_low": low, "ci_high": high, "interval": method,
            "compute_passes": min(mine.count, reference.count), "compute_cached": mine.cached or reference.cached,
            "mixes_processes": mixed}


def time_passes(run_pass: Mapping[str, Callable[[], float]], first: Mapping[str, float | None],
                stored: Mapping[str, float], passes: int = PASSES, budget_s: float = BUDGET_S,
                clock: Callable[[], float] = time.perf_counter) -> dict[str, Timing]:
    """Each variant's ``Timing``: ``first[v]`` (its track stage's pass when it ran in this job, else
    None) and further passes ``run_pass[v]()`` (returning the filtering seconds it measured), the
    variants taking turns, up to ``passes`` in all per variant while the passes so far plus the
    expected next one (their median, or the stored time of a cached variant) fit in ``budget_s``.
    A cached variant (``first[v]`` None) that gets no pass keeps ``stored[v]``, marked cached."""
    samples = {v: [float(first[v])] if first.get(v) is not None and math.isfinite(first[v]) else []
               for v in run_pass}
    spent = {v: sum(samples[v]) for v in run_pass}
    open_ = [v for v in run_pass]
    while open_:
        for v in list(open_):
            expected = float(np.median(samples[v])) if samples[v] else float(stored.get(v, float("nan")))
            if len(samples[v]) >= passes or not math.isfinite(expected) or spent[v] + expected > budget_s:
                open_.remove(v)
                continue
            started = clock()
            seconds = run_pass[v]()
            wall = clock() - started
            seconds = seconds if seconds is not None and math.isfinite(seconds) else wall
            samples[v].append(float(seconds))
            spent[v] += wall
    return {v: Timing(tuple(samples[v])) if samples[v] else Timing((float(stored.get(v, float("nan"))),), cached=True)
            for v in run_pass}

