"""Bit-for-bit comparison of every experiment's tables between a base commit and the working tree.

    python tools/compare_runs.py --base 9997773 [--head REV] [--runs 5] [--experiments mie_los sonar_case1]
                                 [--rename-metric old=new ...] [--keep DIR]

For each experiment (default: every file in conf/experiment/) it runs
``python -m pipeline experiment=NAME mc.runs=N record.enabled=false cache.enabled=false`` once in
a git worktree of ``--base`` and once in this tree (or in a worktree of ``--head``), then compares truth, detections, every
variant's estimates and the per-step metrics: the same rows (sorted by their key columns), the
same columns, and every value equal bit for bit (NaN equal to NaN). Provenance columns (run id,
config hash, overrides, ...) are left out. ``--rename-metric old=new`` maps a metric renamed
since the base (in the metric column and in estimate column names). Prints one line per table
and exits 1 when any differs. A refactor that must not change a number is checked with it.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import polars as pl

ROOT = Path(__file__).resolve().parents[1]
PROVENANCE = {"run_id", "experiment", "status", "error", "config_hash", "overrides", "sweep", "job_num"}
KEYS = {"truth": ["run", "step", "target"], "detections": ["run", "step", "sensor", "detection"],
        "metrics": ["variant_key", "metric", "step"]}


def run_pipeline(tree: Path, artifacts: Path, experiment: str, runs: int) -> Path:
    env = {**os.environ, "PYTHONPATH": str(tree), "HYDRA_FULL_ERROR": "1"}
    proc = subprocess.run([sys.executable, "-m", "pipeline", f"experiment={experiment}", f"mc.runs={runs}",
                           "record.enabled=false", "cache.enabled=false", f"paths.artifacts={artifacts}"],
                          cwd=tree, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{experiment} failed in {tree}:\n{proc.stderr[-3000:]}")
    (run_dir,) = (artifacts / "runs" / experiment).iterdir()
    return run_dir


def tables_of(run_dir: Path) -> dict[str, Path]:
    found = {name: run_dir / f"{name}.parquet" for name in ("truth", "detections", "metrics")
             if (run_dir / f"{name}.parquet").is_file()}
    found |= {f"estimates/{p.stem}": p for p in sorted((run_dir / "estimates").glob("*.parquet"))}
    return found


def _renamed(df: pl.DataFrame, renames: dict[str, str]) -> pl.DataFrame:
    if not renames:
        return df
    df = df.rename({c: renames[c] for c in df.columns if c in renames})
    if "metric" in df.columns:
        df = df.with_columns(pl.col("series").replace(renames))
    return df


def _values_equal(a: pl.Series, b: pl.Series) -> bool:
    if a.dtype != b.dtype:
        return False
    if a.dtype.is_numeric() or isinstance(a.dtype, (pl.Array, pl.List)):
        try:
            x, y = a.to_numpy(), b.to_numpy()
        except Exception:  # noqa: BLE001 - ragged lists: fall back to polars equality
            return a.equals(b)
        if x.dtype == object:
            return a.equals(b)
        return x.shape == y.shape and bool(np.array_equal(x, y, equal_nan=np.issubdtype(x.dtype, np.floating)))
    return a.equals(b)


def compare(name: str, base: Path, head: Path, renames: dict[str, str]) -> str | None:
    """None when equal, else what differs."""
    a, b = _renamed(pl.read_parquet(base), renames), pl.read_parquet(head)
    if "series" in b.columns and "series" not in a.columns and "metric" in a.columns:
        a = a.rename({"metric": "series"})      # the series' name moved to 'series'; 'metric' is now its quantity
    a, b = a.drop([c for c in a.columns if c in PROVENANCE]), b.drop([c for c in b.columns if c in PROVENANCE])
    missing = sorted(set(a.columns) - set(b.columns))
    if missing:
        return f"columns of the base missing here: {missing}"
    b = b.select(a.columns)                 # columns added since the base (e.g. tidy breakdowns) are not compared
    if a.height != b.height:
        return f"{a.height} rows in base, {b.height} here"
    keys = KEYS.get(name, [c for c in ("run", "step", "target") if c in a.columns])
    keys = [("series" if k == "metric" and "series" in a.columns else k) for k in keys]
    a, b = a.sort(keys), b.sort(keys)
    differing = [c for c in a.columns if not _values_equal(a[c], b[c])]
    return f"values differ in {differing}" if differing else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="the commit to compare against")
    parser.add_argument("--head", help="compare this commit instead of the working tree")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--experiments", nargs="*", help="default: every conf/experiment/*.yaml")
    parser.add_argument("--rename-metric", action="append", default=[], metavar="OLD=NEW")
    parser.add_argument("--keep", type=Path, help="keep both trees' outputs here (default: a temp folder)")
    args = parser.parse_args(argv)
    renames = dict(item.split("=", 1) for item in args.rename_metric)
    experiments = args.experiments or sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
    work = args.keep or Path(tempfile.mkdtemp(prefix="compare-runs-"))
    work.mkdir(parents=True, exist_ok=True)
    trees = {"base": (work / "base-tree", args.base)} | ({"head": (work / "head-tree", args.head)} if args.head else {})
    for tree, rev in trees.values():
        if not tree.exists():
            subprocess.run(["git", "worktree", "add", "--detach", str(tree), rev], cwd=ROOT, check=True,
                           capture_output=True)
    base_tree = trees["base"][0]
    head_tree = trees["head"][0] if args.head else ROOT
    different = 0
    try:
        for experiment in experiments:
            base_run = run_pipeline(base_tree, work / "base" / experiment, experiment, args.runs)
            head_run = run_pipeline(head_tree, work / "head" / experiment, experiment, args.runs)
            base_tables, head_tables = tables_of(base_run), tables_of(head_run)
            for name in sorted(set(base_tables) | set(head_tables)):
                if name not in base_tables or name not in head_tables:
                    problem = f"only in {'base' if name in base_tables else 'this tree'}"
                else:
                    problem = compare(name.split("/")[0], base_tables[name], head_tables[name], renames)
                different += problem is not None
                print(f"{experiment:32s} {name:28s} {'equal' if problem is None else 'DIFFERENT: ' + problem}")
    finally:
        for tree, _ in trees.values():
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
    print(f"{different} table(s) differ (base {args.base}, {args.runs} runs, {len(experiments)} experiments)")
    return 1 if different else 0


if __name__ == "__main__":
    sys.exit(main())
