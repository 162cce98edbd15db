"""Assertions several test files share: two run folders' tables equal bit for bit (their provenance
and timings aside), and two engines' estimates equal to rounding."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from polars.testing import assert_frame_equal

# columns that say where and when a table was made, not what it holds
PROVENANCE = ("run_id", "config_hash", "overrides", "sweep", "job_num", "estimates_from_cache", "paths.artifacts", "cache.enabled",
              "hydra/launcher", "mc.chunk_runs")
TIMINGS = ("compute_seconds", "compute_pct_of_reference")


def content(run_dir: Path) -> dict[str, pl.DataFrame]:
    """Every table of a run directory, without provenance columns and wall-clock rows."""
    tables = {}
    for path in sorted(run_dir.rglob("*.parquet")):
        df = pl.read_parquet(path)
        df = df.drop([c for c in df.columns if c in PROVENANCE or c.startswith(("hydra", "record."))])
        if "metric" in df.columns:
            df = df.filter(~pl.col("series").is_in(TIMINGS))
        tables[path.relative_to(run_dir).as_posix()] = df
    return tables


def assert_same_tables(a: Path, b: Path) -> None:
    left, right = content(a), content(b)
    assert sorted(left) == sorted(right)
    for name in left:
        try:
            assert_frame_equal(left[name], right[name], check_exact=True)
        except AssertionError as exc:
            raise AssertionError(f"{name} differs between {a} and {b}: {exc}") from None


def assert_same_to_rounding(compiled, reference):
    """Two engines' estimates (state, covariance, every extra): the same NaN, and within 1e-11 of
    each output's largest entry (measured: ~1e-14 to 1e-12; the closed-form inverse of S and
    index-order sums against LAPACK and BLAS are the only differences)."""
    pairs = [("state", compiled.state, reference.state), ("covariance", compiled.covariance, reference.covariance),
             *((name, compiled.extras[name], reference.extras[name]) for name in reference.extras)]
    for name, ours, theirs in pairs:
        np.testing.assert_array_equal(np.isnan(ours), np.isnan(theirs), err_msg=name)
        scale = max(float(np.nanmax(np.abs(theirs))), 1.0)
        assert np.nanmax(np.abs(ours - theirs)) <= 1e-11 * scale, (name, np.nanmax(np.abs(ours - theirs)) / scale)
