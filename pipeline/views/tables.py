"""Report: the variant x metric table printed at the end of a run, and study-specific tables.

``format_summary`` prints the summary (variant x metric, one block per window) for every
experiment. An experiment can add its own tables under ``report.tables`` (a mapping name ->
config node with ``_target_``): the runner builds each node before any stage runs and, after the
summary, prints ``table.render(ReportContext)`` for each, in order. A table is any object with
``render(ctx: ReportContext) -> str``; if it has ``variant_keys`` (the variants it reads), the
runner checks them against the experiment's ``filters``. ``BinnedTable`` is the generic one:
per-step metrics summed (or averaged) over step bins, ours beside reference values (a paper's
table) kept in the experiment's YAML.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol, Sequence

import numpy as np
import polars as pl

from pipeline.evaluation.metrics import format_value, printed_columns

IMPOSSIBLE = "impossible"           # the interval method of a value that cannot be (pipeline.evaluation.uncertainty)
IMPOSSIBLE_TEXT = "n/a (flagged)"   # printed in its place: a run's value is impossible (a fault_runs_* count says which)


def format_summary(summary: pl.DataFrame, experiment: str, runs: int,
                   comparisons: pl.DataFrame | None = None) -> str:
    """Variant x metric table, one block per window (window-free metrics shown in every block). A value
    with an interval (the summary's ci_low / ci_high) prints as ``value ± half its width``; with
    ``comparisons`` (pipeline.evaluation.uncertainty), the paired differences with the reference variant follow.
    A value that is impossible (a NEES below zero: interval ``impossible``, value null) prints as
    ``n/a (flagged)``."""
    shown = {m for m, _ in printed_columns(set(summary["series"].unique().to_list()))}
    windows = [w for w in summary.filter(pl.col("series").is_in(shown))["window"].unique(maintain_order=True).to_list()
               if w is not None and " by step " not in w]
    variants = summary["variant"].unique(maintain_order=True).to_list()
    with_intervals = {"ci_low", "ci_high"} <= set(summary.columns)
    lines = [f"{experiment}: {runs} Monte Carlo runs"]
    if with_intervals:
        lines.append("value ± half its 95 % interval over the runs (summary.parquet: ci_low, ci_high)")
    for window in windows or [None]:
        in_window = pl.lit(False) if window is None else pl.col("window") == window
        rows = summary.filter(pl.col("window").is_null() | in_window | pl.col("window").str.contains(" by step "))
        cols = printed_columns(rows["series"].to_list())       # the registry's labels, in its order
        header = ["variant"] + [_with_reference(label, rows, m) for m, label in cols]
        table = [header]
        for v in variants:
            row = [v]
            for m, _ in cols:
                hit = rows.filter((pl.col("variant") == v) & (pl.col("series") == m))
                if hit.height == 0 or hit["value"][0] is None:
                    impossible = "interval" in hit.columns and hit.height and hit["interval"][0] == IMPOSSIBLE
                    row.append(IMPOSSIBLE_TEXT if impossible else "")
                    continue
                text = format_value(m, hit["value"][0])
                if with_intervals and hit["ci_low"][0] is not None and hit["ci_high"][0] is not None:
                    text += f" ± {_like(text, (hit['ci_high'][0] - hit['ci_low'][0]) / 2)}"
                text += _timing_mark(hit)
                row.append(text)
            table.append(row)
        lines += _block(table, f"window: {window}" if window else "")
    lines += timing_note(summary)
    if comparisons is not None and comparisons.height:
        lines += format_comparisons(comparisons, summary)
    return "\n".join(lines)


def _timing_mark(hit: pl.DataFrame) -> str:
    """`` (cached)`` after a compute value timed by another process, `` (mixed)`` after a ratio of two
    processes' times (pipeline.evaluation.timing); nothing for the other values or an older summary."""
    if "mixes_processes" in hit.columns and hit["mixes_processes"][0]:
        return " (mixed)"
    if "compute_cached" in hit.columns and hit["compute_cached"][0] and hit["series"][0] == "compute_seconds":
        return " (cached)"
    return ""


def timing_note(summary: pl.DataFrame) -> list[str]:
    """What the compute columns are (the median of the passes timed in this job, ± half their range)
    and, where the study counts the models its filters evaluate, that this count is the cost to compare."""
    if "compute_passes" not in summary.columns:
        return []
    rows = summary.filter(pl.col("series") == "compute_seconds")
    if not rows.height:
        return []
    passes = sorted({int(n) for n in rows["compute_passes"].drop_nulls().to_list()})
    count = f"{passes[0]}" if len(passes) == 1 else f"{passes[0]}-{passes[-1]}"
    lines = ["", f"compute: the median of {count} filtering pass(es) timed in this job, ± half their range "
                 f"(timing.passes, timing.budget_s; summary.parquet: compute_passes, ci_low, ci_high)"]
    cached = rows.filter(pl.col("compute_cached").fill_null(False))["variant"].to_list()
    if cached:
        lines.append(f"(cached): {', '.join(cached)} kept the one pass of the process that computed the estimate; "
                     f"a ratio with it mixes processes (mixed): not a comparison. Raise timing.budget_s to re-time it.")
    if summary.filter(pl.col("series") == "models_pct_of_reference").height:
        lines.append("cost: `models %` counts the models evaluated per step, exact and the same on every machine; "
                     "compare costs by it, compute time is its noisy echo")
    return lines


def _with_reference(label: str, rows: pl.DataFrame, series: str) -> str:
    """A percentage's label with the variant it is relative to, from its unit ("% of SIR-MM"):
    "compute % of SIR-MM"; the label alone where the unit names none (or there is no unit column)."""
    if "unit" not in rows.columns:
        return label
    units = rows.filter(pl.col("series") == series)["unit"].drop_nulls().unique(maintain_order=True).to_list()
    if len(units) == 1 and units[0].startswith("% of ") and label.endswith("%"):
        return f"{label} {units[0][2:]}"
    return label


def format_comparisons(comparisons: pl.DataFrame, summary: pl.DataFrame) -> list[str]:
    """Each variant minus the reference on the printed metrics, per window, paired over the runs."""
    names = dict(zip(summary["variant_key"].to_list(), summary["variant"].to_list()))
    reference = names.get(comparisons["reference_key"][0], comparisons["reference_key"][0])
    lines = ["", f"paired with {reference} over the same runs: difference [its 95 % interval]; "
                 f"* = resolved (the interval excludes 0)"]
    shown = dict(printed_columns(set(comparisons["series"].to_list())))
    for window in comparisons["window"].unique(maintain_order=True).to_list():
        if window is None or " by step " in window:
            continue
        part = comparisons.filter(pl.col("window") == window)
        cols = [(m, label) for m, label in shown.items() if m in set(part["series"].to_list())]
        if not cols:
            continue
        table = [["variant"] + [label for _, label in cols]]
        for key in part["variant_key"].unique(maintain_order=True).to_list():
            row = [names.get(key, key)]
            for m, _ in cols:
                hit = part.filter((pl.col("variant_key") == key) & (pl.col("series") == m))
                if hit.height == 0 or hit["difference"][0] is None:
                    row.append("")
                    continue
                text = "+" + format_value(m, hit["difference"][0]) if hit["difference"][0] >= 0 \
                    else format_value(m, hit["difference"][0])
                low, high = hit["difference_low"][0], hit["difference_high"][0]
                if low is not None and high is not None:    # bootstrap intervals are asymmetric: both ends
                    text += f" [{_like(text, low)}, {_like(text, high)}]" + (" *" if hit["resolved"][0] else "  ")
                row.append(text)
            table.append(row)
        lines += _block(table, f"window: {window}")
    return lines


def _block(table: list[list[str]], title: str) -> list[str]:
    header = table[0]
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines = ["", title]
    for i, r in enumerate(table):
        lines.append("  ".join(c.ljust(widths[j]) if j == 0 else c.rjust(widths[j]) for j, c in enumerate(r)))
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    return lines


def _like(printed: str, value: float) -> str:
    """``value`` with as many decimals as ``printed`` (a half-width beside its value)."""
    number = printed.split()[0].lstrip("+")
    decimals = len(number.split(".")[1]) if "." in number else 0
    return f"{value:.{decimals}f}"


# ---- study-specific tables ---------------------------------------------------------------------
@dataclass(frozen=True)
class ReportContext:
    """What a report table may read: the run's tables as the runner wrote them.

    ``variants`` maps variant key -> display name, in run order (only the variants that ran);
    ``metrics`` is the long per-step frame (variant_key, metric, step, time, value, ...);
    ``summary`` the summary frame.
    """

    experiment: str
    runs: int
    variants: Mapping[str, str]
    metrics: pl.DataFrame
    summary: pl.DataFrame
    extra: Mapping[str, Any] = field(default_factory=dict)


class ReportTable(Protocol):
    def render(self, ctx: ReportContext) -> str: ...


@dataclass(frozen=True)
class _Column:
    label: str
    variant: str
    metrics: tuple[str, ...]
    parts: tuple[str, ...]


@dataclass(frozen=True)
class _Row:
    first: int
    last: int
    reference: tuple[float | None, ...]

    @property
    def label(self) -> str:
        return str(self.first) if self.first == self.last else f"{self.first}-{self.last}"


class BinnedTable:
    """Per-step metrics of some variants, summed (or averaged) over step bins, each beside a
    reference value (a paper's table).

    Parameters
    ----------
    title : first line printed
    columns : list of {label, variant, metrics, parts}: one column pair "ours LABEL" / "REF LABEL"
        per entry; ``variant`` is a variant key (``filters.<key>``); ``metrics`` one or more
        per-step metric names from metrics.parquet (several print in one cell joined by "/", e.g.
        the per-axis counts of one filter, with ``parts`` naming them: [x, y, z])
    rows : list of {steps, reference}: ``steps`` an inclusive step range [first, last] or one step;
        ``reference`` the reference values, one per metric over all columns in order (null: none)
    aggregate : sum (counts, e.g. detections) | mean
    reference_label : the reference columns' name, e.g. "paper"
    reference_runs : the reference's number of Monte Carlo runs (printed beside ours; counts scale
        with it)
    row_header : the first column's header
    total_row : also print the sum over all rows (aggregate = sum only)
    note : a line printed under the title
    """

    def __init__(self, title: str, columns: Sequence[Mapping[str, Any]], rows: Sequence[Mapping[str, Any]],
                 aggregate: str = "sum", reference_label: str = "paper", reference_runs: int | None = None,
                 row_header: str = "step", total_row: bool = True, note: str = "") -> None:
        if aggregate not in ("sum", "mean"):
            raise ValueError(f"aggregate: {aggregate!r} is not one of ['sum', 'mean']")
        if not columns:
            raise ValueError("columns: at least one column is needed")
        cols = []
        for i, c in enumerate(columns):
            c = dict(c)
            unknown = set(c) - {"label", "variant", "metrics", "parts"}
            if unknown or "variant" not in c or "metrics" not in c:
                raise ValueError(f"columns[{i}]: {c} must be {{label, variant, metrics[, parts]}}"
                                 + (f"; unknown key(s) {sorted(unknown)}" if unknown else ""))
            metrics = (c["metrics"],) if isinstance(c["metrics"], str) else tuple(str(m) for m in c["metrics"])
            if not metrics:
                raise ValueError(f"columns[{i}].metrics: name at least one per-step metric")
            parts = tuple(str(p) for p in c.get("parts") or ())
            if parts and len(parts) != len(metrics):
                raise ValueError(f"columns[{i}].parts: {list(parts)} names {len(parts)} parts for "
                                 f"{len(metrics)} metrics {list(metrics)}")
            cols.append(_Column(str(c.get("label", c["variant"])), str(c["variant"]), metrics, parts))
        width = sum(len(c.metrics) for c in cols)
        parsed = []
        for i, r in enumerate(rows):
            r = dict(r)
            unknown = set(r) - {"steps", "reference"}
            if unknown or "steps" not in r:
                raise ValueError(f"rows[{i}]: {r} must be {{steps, reference}}"
                                 + (f"; unknown key(s) {sorted(unknown)}" if unknown else ""))
            steps = r["steps"]
            if isinstance(steps, int):
                first, last = steps, steps
            elif isinstance(steps, (list, tuple)) and len(steps) == 2:
                first, last = steps
            else:
                first = last = None
            if not (isinstance(first, int) and isinstance(last, int) and 0 <= first <= last):
                raise ValueError(f"rows[{i}].steps: {steps!r} must be a step >= 0 or [first, last] with "
                                 f"0 <= first <= last")
            ref = r.get("reference")
            ref = [None] * width if ref is None else list(ref)
            if len(ref) != width:
                raise ValueError(f"rows[{i}].reference: {ref} holds {len(ref)} values; the columns "
                                 f"{[c.label for c in cols]} have {width} metrics, one value each")
            parsed.append(_Row(first, last, tuple(None if v is None else float(v) for v in ref)))
        self.title = str(title)
        self.columns = cols
        self.rows = parsed
        self.aggregate = aggregate
        self.reference_label = str(reference_label)
        self.reference_runs = None if reference_runs is None else int(reference_runs)
        self.row_header = str(row_header)
        self.total_row = bool(total_row) and aggregate == "sum"
        self.note = str(note)

    @property
    def variant_keys(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(c.variant for c in self.columns))

    def values(self, ctx: ReportContext) -> list[list[list[float | None]]]:
        """ours[row][column][metric]; None where the variant did not run or has no such metric."""
        series: dict[tuple[str, str], np.ndarray] = {}
        if ctx.metrics.height:
            for (variant, metric), part in ctx.metrics.group_by(["variant_key", "series"]):
                part = part.sort("step")
                values = np.full(int(part["step"].max()) + 1, np.nan)
                values[part["step"].to_numpy()] = part["value"].to_numpy()
                series[(variant, metric)] = values
        out = []
        for row in self.rows:
            cells = []
            for c in self.columns:
                cell = []
                for m in c.metrics:
                    values = series.get((c.variant, m)) if c.variant in ctx.variants else None
                    segment = None if values is None else values[row.first: row.last + 1]
                    if segment is None or segment.size == 0 or np.isnan(segment).all():
                        cell.append(None)
                    else:
                        cell.append(float(np.nansum(segment) if self.aggregate == "sum" else np.nanmean(segment)))
                cells.append(cell)
            out.append(cells)
        return out

    def render(self, ctx: ReportContext) -> str:
        ours = self.values(ctx)
        header = [self.row_header]
        for c in self.columns:
            suffix = f" {'/'.join(c.parts)}" if c.parts else ""
            header += [f"ours {c.label}{suffix}", f"{self.reference_label} {c.label}{suffix}"]
        table = [header]
        for row, cells in zip(self.rows, ours):
            line, i = [row.label], 0
            for c, cell in zip(self.columns, cells):
                ref = row.reference[i: i + len(c.metrics)]
                i += len(c.metrics)
                line += [self._cell(cell), self._cell(ref)]
            table.append(line)
        if self.total_row and self.rows:
            line, i = ["total"], 0
            for j, c in enumerate(self.columns):
                n = len(c.metrics)
                mine = [_sum([cells[j][k] for cells in ours]) for k in range(n)]
                ref = [_sum([row.reference[i + k] for row in self.rows]) for k in range(n)]
                i += n
                line += [self._cell(mine), self._cell(ref)]
            table.append(line)
        widths = [max(len(r[i]) for r in table) for i in range(len(header))]
        lines = [self.title]
        runs = f"ours: {ctx.runs} Monte Carlo runs"
        if self.reference_runs is not None:
            runs += f"; {self.reference_label}: {self.reference_runs} runs"
        missing = [v for v in self.variant_keys if v not in ctx.variants]
        if missing:
            runs += f"; not run here: {', '.join(missing)} (shown as -)"
        lines.append(runs)
        if self.note:
            lines.append(self.note)
        lines.append("")
        sep = "  ".join("-" * w for w in widths)
        for n, r in enumerate(table):
            if n == len(table) - 1 and self.total_row and self.rows:
                lines.append(sep)
            lines.append("  ".join(cell.ljust(widths[j]) if j == 0 else cell.rjust(widths[j])
                                   for j, cell in enumerate(r)))
            if n == 0:
                lines.append(sep)
        return "\n".join(lines)

    def _cell(self, values: Sequence[float | None]) -> str:
        if all(v is None for v in values) and len(values) > 1:
            return "-"
        return "/".join("-" if v is None else _number(v) for v in values)


def _sum(values: Sequence[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return float(sum(present)) if present else None


def _number(value: float) -> str:
    if math.isnan(value):
        return "-"
    return f"{value:.0f}" if float(value).is_integer() else f"{value:.2f}"


@dataclass(frozen=True)
class _SummaryRow:
    label: str
    metric: str
    window: str
    scale: float
    reference: str


class SummaryTable:
    """Chosen summary values (metric over a window) of some variants side by side, with an optional
    ratio of two variants and a reference column (free text: a paper's or a spec's value).

    Parameters
    ----------
    title : first line printed
    variants : variant keys, one column each
    rows : list of {label, metric, window[, scale][, reference]}: ``metric`` and ``window`` pick a
        summary row (see metrics.windows); ``scale`` multiplies the value for display (e.g. 1000
        to print rad as mrad; say so in the label); ``reference`` is printed as given
    ratio : optional [numerator, denominator] variant keys: adds a column numerator / denominator
    reference_label : the reference column's header
    note : a line printed under the title
    """

    def __init__(self, title: str, variants: Sequence[str], rows: Sequence[Mapping[str, Any]],
                 ratio: Sequence[str] | None = None, reference_label: str = "reference", note: str = "") -> None:
        if not variants:
            raise ValueError("variants: name at least one variant key")
        if ratio is not None and (len(ratio) != 2 or any(r not in variants for r in ratio)):
            raise ValueError(f"ratio: {ratio!r} must be [numerator, denominator], two of the table's variants "
                             f"{list(variants)}")
        parsed = []
        for i, r in enumerate(rows):
            r = dict(r)
            unknown = set(r) - {"label", "metric", "window", "scale", "reference"}
            if unknown or "metric" not in r or "window" not in r:
                raise ValueError(f"rows[{i}]: {r} must be {{label, metric, window[, scale][, reference]}}"
                                 + (f"; unknown key(s) {sorted(unknown)}" if unknown else ""))
            scale = float(r.get("scale", 1.0))
            if not math.isfinite(scale) or scale == 0:
                raise ValueError(f"rows[{i}].scale: {r.get('scale')!r} must be a finite non-zero factor")
            parsed.append(_SummaryRow(str(r.get("label", r["metric"])), str(r["metric"]), str(r["window"]), scale,
                                      "" if r.get("reference") is None else str(r["reference"])))
        self.title = str(title)
        self.variants = [str(v) for v in variants]
        self.rows = parsed
        self.ratio = None if ratio is None else (str(ratio[0]), str(ratio[1]))
        self.reference_label = str(reference_label)
        self.note = str(note)

    @property
    def variant_keys(self) -> tuple[str, ...]:
        return tuple(self.variants)

    def value(self, ctx: ReportContext, variant: str, row: _SummaryRow) -> float | None:
        hit = ctx.summary.filter((pl.col("variant_key") == variant) & (pl.col("series") == row.metric)
                                 & (pl.col("window") == row.window))["value"]
        if hit.len() == 0 or hit[0] is None or math.isnan(hit[0]):
            return None
        return float(hit[0])

    def render(self, ctx: ReportContext) -> str:
        shown = [v for v in self.variants]
        header = ["", *[ctx.variants.get(v, v) for v in shown]]
        if self.ratio:
            header.append(f"{ctx.variants.get(self.ratio[0], self.ratio[0])} / "
                          f"{ctx.variants.get(self.ratio[1], self.ratio[1])}")
        if any(r.reference for r in self.rows):
            header.append(self.reference_label)
        table = [header]
        for row in self.rows:
            values = {v: self.value(ctx, v, row) for v in shown}
            line = [row.label] + ["-" if values[v] is None else _significant(values[v] * row.scale) for v in shown]
            if self.ratio:
                a, b = values[self.ratio[0]], values[self.ratio[1]]
                line.append("-" if a is None or b is None or b == 0 else f"{a / b:.2f}")
            if len(header) > len(line):
                line.append(row.reference)
            table.append(line)
        widths = [max(len(r[i]) for r in table) for i in range(len(header))]
        lines = [self.title, f"ours: {ctx.runs} Monte Carlo runs"]
        if self.note:
            lines.append(self.note)
        lines.append("")
        text_columns = {0} | ({len(header) - 1} if header[-1] == self.reference_label else set())
        for n, r in enumerate(table):
            lines.append("  ".join(cell.ljust(widths[j]) if j in text_columns else cell.rjust(widths[j])
                                   for j, cell in enumerate(r)).rstrip())
            if n == 0:
                lines.append("  ".join("-" * w for w in widths))
        return "\n".join(lines)


def _significant(value: float) -> str:
    """Three significant digits, plain notation where that reads well."""
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    magnitude = abs(value)
    if 1e-3 <= magnitude < 1e5:
        digits = max(0, 2 - int(math.floor(math.log10(magnitude))))
        return f"{value:.{digits}f}"
    return f"{value:.2e}"
