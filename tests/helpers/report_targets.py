"""Report targets judged on resampled values (pipeline.results.report, issue 18): a run's tables
built from given values and their joint resamples, and the three kinds of target the report and
report-cost tests judge (a threshold, a paired ratio, a self-joining cross target)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from pipeline.results.report import TargetSpec

# the small run both report test files make: 3 runs of 60 steps
SMALL = ("mc.runs=3", "scenario.steps=60")


def tables_with_resamples(a: np.ndarray, b: np.ndarray | None = None, runs: int = 100):
    """Summary values a[0] (and b[0]) of variants a (and b) with joint resamples a[1:] (b[1:]): the
    same resampled runs in both."""
    from pipeline.results.report import RunTables, pivot_summary, resampled_wide
    columns = [("a", a)] + ([("b", b)] if b is not None else [])
    summary = pl.DataFrame({"variant_key": [k for k, _ in columns], "series": ["position_rmse"] * len(columns),
                            "window": ["all"] * len(columns), "value": [v[0] for _, v in columns]})
    count = a.size - 1
    resamples = pl.DataFrame({"variant_key": np.repeat([k for k, _ in columns], count),
                              "series": ["position_rmse"] * len(columns) * count,
                              "window": ["all"] * len(columns) * count,
                              "resample": np.tile(np.arange(count), len(columns)).astype(np.int16),
                              "value": np.concatenate([v[1:] for _, v in columns])})
    wide = pivot_summary(summary)
    return RunTables(Path("."), "x", {}, {"runs": runs}, summary, pl.DataFrame(), wide, None,
                     resampled_wide(wide, resamples))


THRESHOLD = TargetSpec("t", "below 10", "p", """SELECT CAST("a:position_rmse" AS VARCHAR) AS measured,
                                                    "a:position_rmse" < 10 AS pass FROM wide WHERE "window" = 'all'""")


def around(value: float, spread: float, seed: int = 0) -> np.ndarray:
    """The value, then 400 resamples around it with standard deviation ``spread``."""
    return np.concatenate([[value], value + spread * np.random.default_rng(seed).standard_normal(400)])


RATIO = TargetSpec("r", "a within 2 % of b", "p", """SELECT CAST("a:position_rmse" / "b:position_rmse" AS VARCHAR) AS measured,
    ABS("a:position_rmse" / "b:position_rmse" - 1) < 0.02 AS pass FROM wide WHERE "window" = 'all'""")


CROSS = TargetSpec("x", "a below b", "p", """WITH ref AS (SELECT "b:position_rmse" AS m FROM wide WHERE "window" = 'all')
    SELECT CAST("a:position_rmse" AS VARCHAR) AS measured, "a:position_rmse" < ref.m AS pass
    FROM wide CROSS JOIN ref WHERE "window" = 'all'""")
