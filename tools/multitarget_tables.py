"""The multi-target study's results tables (docs/studies/multitarget.md) from a run folder's summary.parquet.

    python tools/multitarget_tables.py <run folder> [--window all]

Prints markdown: per variant, mean GOSPA and its split (localisation, missed, false in m^2: their sum is
the mean of GOSPA^2; missed / (c^2 / 2) is the mean number of missed targets a scan, likewise false),
OSPA, the cardinality error, track switches and breaks (summed over the window's scans), the track measures of the whole run, the settled cardinality band, and the
paired GOSPA differences (study.paired), each value with its 95 % interval over the runs. Every number is
read from the summary table; nothing is recomputed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import polars as pl

GOSPA_COLUMNS = (("gospa", "GOSPA [m]"), ("gospa_localisation", "localisation [m^2]"),
                 ("gospa_missed", "missed [m^2]"), ("gospa_false", "false [m^2]"), ("ospa", "OSPA [m]"),
                 ("cardinality_error", "card err"), ("missed_targets", "missed / scan"),
                 ("false_targets", "false / scan"), ("track_switches", "switches / run"),
                 ("track_breaks", "breaks / run"), ("position_rmse", "pos RMSE [m]"))
TRACK_COLUMNS = (("tracks_reported", "track ids"), ("false_tracks", "false tracks"), ("track_purity", "purity"),
                 ("confirmation_delay", "conf. delay [s]"))
SETTLED_COLUMNS = (("cardinality_excess_settled", "max excess"), ("cardinality_shortfall_settled", "max shortfall"))


def _cell(row: dict | None) -> str:
    if row is None or row["value"] is None:
        return ""
    value, low, high = row["value"], row["ci_low"], row["ci_high"]
    digits = 3 if abs(value) < 10 else 1
    text = f"{value:.{digits}f}"
    if low is not None and high is not None and low == low and high == high:
        text += f" [{low:.{digits}f}, {high:.{digits}f}]"
    return text


def _table(summary: pl.DataFrame, columns, window_filter) -> list[str]:
    rows = summary.filter(window_filter)
    variants = rows.unique("variant_key", maintain_order=True).select("variant_key", "variant").rows()
    lines = ["| variant | " + " | ".join(label for _, label in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for key, name in variants:
        cells = []
        for series, _ in columns:
            found = rows.filter((pl.col("variant_key") == key) & (pl.col("series") == series))
            cells.append(_cell(found.row(0, named=True) if found.height else None))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def tables(run: Path, window: str = "all") -> str:
    """The markdown tables of one run folder (module docstring)."""
    path = Path(run) / "summary.parquet"
    if not path.is_file():
        raise FileNotFoundError(f"{run}: no summary.parquet (not a finished run folder)")
    summary = pl.read_parquet(path)
    first = summary.row(0, named=True)
    out = [f"Run `{Path(run).name}` of `{first['experiment_name']}`: {first['n_runs']} runs, seed {first['mc.seed']}, "
           f"config {first['config_hash']}.", "",
           f"GOSPA and its split, window `{window}` (mean over the runs and the window's scans):", ""]
    out += _table(summary, GOSPA_COLUMNS, pl.col("window") == window)
    out += ["", "Track measures (per run, mean over the runs):", ""]
    out += _table(summary, TRACK_COLUMNS, pl.col("window") == "run")
    out += ["", "Settled cardinality (max over the settled scans of the run-mean reported - true, and true - reported):", ""]
    out += _table(summary, SETTLED_COLUMNS, pl.col("window").str.starts_with("settled"))
    paired = summary.filter(pl.col("series") == "gospa_paired_difference")
    if paired.height:
        out += ["", "Paired GOSPA differences (run-mean GOSPA of the variant minus its pair's, mean over the scans):", "",
                "| variant | pair | difference [m] [95 %] |", "|---|---|---:|"]
        for row in paired.iter_rows(named=True):
            out.append(f"| {row['variant']} | {row['window']} | {_cell(row)} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (holding summary.parquet)")
    parser.add_argument("--window", default="all", help="the metrics window of the GOSPA table (default: all)")
    args = parser.parse_args(argv)
    missing = [str(run) for run in args.runs if not (run / "summary.parquet").is_file()]
    if missing:
        print(f"runs: {', '.join(missing)} hold no summary.parquet; give finished run folders "
              f"(runs/<experiment_name>/<time>/).", file=sys.stderr)
        return 2
    for run in args.runs:
        print(tables(run, args.window))
    return 0


if __name__ == "__main__":
    sys.exit(main())
