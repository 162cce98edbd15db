"""Report: the variant x metric table printed at the end of a run."""

from __future__ import annotations

import polars as pl

SHOWN = [("acceleration_rmse_x", "acc RMSE X"), ("acceleration_rmse_y", "acc RMSE Y"), ("position_rmse", "pos RMSE"),
         ("velocity_rmse", "vel RMSE"), ("nees", "NEES"), ("models_evaluated", "models/step"),
         ("models_pct_of_reference", "models %"), ("group_reached_fraction", "reached"),
         ("compute_seconds", "compute s"), ("compute_pct_of_reference", "compute %")]


def format_summary(summary: pl.DataFrame, experiment: str, runs: int) -> str:
    """Variant x metric table, one block per window (window-free metrics shown in every block)."""
    windows = [w for w in summary["window"].unique(maintain_order=True).to_list()
               if w is not None and " by step " not in w]
    variants = summary["variant"].unique(maintain_order=True).to_list()
    lines = [f"{experiment}: {runs} Monte Carlo runs"]
    for window in windows or [None]:
        rows = summary.filter(pl.col("window").is_null() | (pl.col("window") == window)
                              | pl.col("window").str.contains(" by step "))
        cols = [(m, label) for m, label in SHOWN if m in rows["metric"].to_list()]
        header = ["variant"] + [label for _, label in cols]
        table = [header]
        for v in variants:
            row = [v]
            for m, _ in cols:
                hit = rows.filter((pl.col("variant") == v) & (pl.col("metric") == m))["value"]
                row.append("" if hit.len() == 0 or hit[0] is None else _fmt(m, hit[0]))
            table.append(row)
        widths = [max(len(r[i]) for r in table) for i in range(len(header))]
        lines.append("")
        lines.append(f"window: {window}" if window else "")
        for i, r in enumerate(table):
            lines.append("  ".join(c.ljust(widths[j]) if j == 0 else c.rjust(widths[j]) for j, c in enumerate(r)))
            if i == 0:
                lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(metric: str, value: float) -> str:
    if metric.endswith("pct_of_reference"):
        return f"{value:.1f}"
    if metric == "compute_seconds":
        return f"{value:.3f}"
    if metric == "group_reached_fraction":
        return f"{value:.2f}"
    return f"{value:.2f}"
