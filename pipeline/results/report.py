"""Reproduction report: ``python -m pipeline.report <run dir | sweep dir | --latest> [--out DIR] [--check]``.

For each run (a folder with ``summary.parquet``, ``metrics.parquet``, ``config.yaml`` and
``status.json``, as the runner writes it) a Markdown report with PNG figures (matplotlib, Agg),
made from the stored tables alone:

- **Reproduction targets**: each of the spec's targets with the paper's / spec's value, the value
  measured in this run and PASS / FAIL / INCONCLUSIVE judged with the values' 95 % intervals over the
  runs (ERROR when its query fails or returns no row);
- **Figures**: the experiment's figures, each drawn from a named SQL query (shown with it);
- **How far from the limit**: NEES / NIS run averages with the share of steps inside their 95 %
  chi-square band, RMSE / sqrt(PCRLB) per window, and their figures over time;
- the summary table and the study's own tables (as printed at the end of the run).

Experiments declare their part in their YAML under ``report`` (next to ``report.tables``):

``report.queries``  name -> SQL over this run's tables ``summary`` and ``metrics`` (the Parquet
    files; NaN read as NULL so AVG skips it) and ``wide`` (the summary pivoted: one row per window,
    '-' for window-free values, one column per "<variant_key>:<series>");
``report.figures``  name -> {title, query (a query name or SQL), x, y, series, lower, upper, kind
    (line | step | bar), xlabel, ylabel, logy, reference: [{label, x: [...], y: [...]}]}: one line
    per value of ``series`` (the paper's points drawn as markers from ``reference``);
``report.targets``  id -> {target, paper, query, timed (optional)}: the query returns one row with
    a text column ``measured`` and a boolean ``pass``; ``timed: true`` marks a target judged on wall
    time (the report checks it; the reproduction tests, which read the same definitions, do not);
``report.findings`` id -> {finding, paper, query}: a number the spec asks to report beside a
    reference without a threshold; the query returns one row with ``measured``.

A sweep folder (``multirun/<time>``, or any folder holding runs below it) gets one report per run and
an ``index.md`` with each run's swept values (a column per override that differs between the runs)
and targets passed; a job that failed (or is unfinished, or whose tables
fail their checksum) gets a line saying why, and the others their reports. ``--check`` exits 1 when
any target is FAIL or ERROR, or a job has no report (INCONCLUSIVE does not fail it). Reports go to ``<run>/report/`` unless ``--out`` is given. The targets and figures are the
ones the run recorded in its config.yaml; ``--current`` checks a stored run against the
definitions conf/ holds now (e.g. a target added after the run).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import polars as pl

from pipeline.run.stored import stored_config
from pipeline.storage.run_tables import read_run_table
from pipeline.storage.store import TableDamaged

FIGURE_KEYS = {"title", "query", "x", "y", "series", "lower", "upper", "kind", "xlabel", "ylabel", "logy",
               "reference"}
TARGET_KEYS = {"target", "paper", "query"}
OPTIONAL_TARGET_KEYS = {"timed"}      # timed: true = judged on wall time, which the tests do not judge
FINDING_KEYS = {"finding", "paper", "query"}
KINDS = ("line", "step", "bar")

# Built-in named queries: the limits section of every report. ``{series}`` is filled per figure.
BUILTIN_QUERIES = {
    "consistency": """
WITH v AS (SELECT variant, series, step, value FROM metrics),
lo AS (SELECT variant, REPLACE(series, '_lower', '') AS series, step, value AS lower
       FROM metrics WHERE ENDS_WITH(series, '_lower')),
up AS (SELECT variant, REPLACE(series, '_upper', '') AS series, step, value AS upper
       FROM metrics WHERE ENDS_WITH(series, '_upper'))
SELECT v.variant, v.series, AVG(v.value) AS mean, AVG(lo.lower) AS band_lower, AVG(up.upper) AS band_upper,
       AVG(CASE WHEN v.value BETWEEN lo.lower AND up.upper THEN 1.0 ELSE 0.0 END) AS share_in_band,
       COUNT(*) AS steps
FROM v JOIN lo ON v.variant = lo.variant AND v.series = lo.series AND v.step = lo.step
JOIN up ON v.variant = up.variant AND v.series = up.series AND v.step = up.step
WHERE v.value IS NOT NULL AND lo.lower IS NOT NULL
GROUP BY v.variant, v.series ORDER BY v.series, v.variant""",
    "consistency_by_step": """
WITH v AS (SELECT variant, series, step, time, value FROM metrics WHERE series = '{series}'),
lo AS (SELECT variant, step, value AS lower FROM metrics WHERE series = '{series}_lower'),
up AS (SELECT variant, step, value AS upper FROM metrics WHERE series = '{series}_upper')
SELECT v.variant, v.time, v.value, lo.lower, up.upper
FROM v JOIN lo ON v.variant = lo.variant AND v.step = lo.step
JOIN up ON v.variant = up.variant AND v.step = up.step
ORDER BY v.variant, v.time""",
    "bound_ratio_by_window": """
SELECT variant, REPLACE(series, 'position_rmse_over_', '') AS bound, "window", value AS rmse_over_bound FROM summary
WHERE series LIKE 'position_rmse_over_bound%' AND "window" IS NOT NULL ORDER BY bound, "window", variant""",
    "bound_ratio_by_step": """
SELECT variant || CASE WHEN series = 'position_rmse_over_bound' THEN '' ELSE ' (' || REPLACE(series, 'position_rmse_over_', '') || ')' END
       AS line, time, value
FROM metrics WHERE series LIKE 'position_rmse_over_bound%' ORDER BY line, time""",
    "compute": """
SELECT variant, value AS compute_seconds FROM summary WHERE series = 'compute_seconds' ORDER BY variant""",
}


class ReportError(ValueError):
    """A report definition or a run folder that cannot be reported; the message names the key."""


@dataclass(frozen=True)
class FigureSpec:
    name: str
    title: str
    query: str
    x: str
    y: str
    series: str | None = None
    lower: str | None = None
    upper: str | None = None
    kind: str = "line"
    xlabel: str = ""
    ylabel: str = ""
    logy: bool = False
    reference: tuple[Mapping[str, Any], ...] = ()


@dataclass(frozen=True)
class TargetSpec:
    id: str
    target: str
    paper: str
    query: str
    timed: bool = False        # judged on wall time (machine-dependent): the report checks it, tests do not


@dataclass(frozen=True)
class FindingSpec:
    """A number the spec asks to report beside a reference, without a pass/fail threshold."""
    id: str
    finding: str
    paper: str
    query: str


@dataclass(frozen=True)
class ReportSpec:
    queries: Mapping[str, str]
    figures: tuple[FigureSpec, ...]
    targets: tuple[TargetSpec, ...]
    findings: tuple[FindingSpec, ...] = ()

    @classmethod
    def from_config(cls, node: Mapping[str, Any] | None) -> "ReportSpec":
        """Validate ``report.queries / figures / targets / findings`` (a plain mapping: the run's config.yaml)."""
        node = dict(node or {})
        queries = dict(node.get("queries") or {})
        for name, sql in queries.items():
            if not isinstance(sql, str) or not sql.strip():
                raise ReportError(f"report.queries.{name}: {sql!r} must be an SQL string over summary / metrics")
        clash = set(queries) & set(BUILTIN_QUERIES)
        if clash:
            raise ReportError(f"report.queries: {sorted(clash)} are built-in query names; pick other names")
        figures = []
        for name, fig in (node.get("figures") or {}).items():
            fig = dict(fig or {})
            unknown = set(fig) - FIGURE_KEYS
            missing = {"query", "x", "y"} - set(fig)
            if unknown or missing:
                raise ReportError(f"report.figures.{name}: " + (f"unknown key(s) {sorted(unknown)}; " if unknown else "")
                                  + (f"missing {sorted(missing)}; " if missing else "")
                                  + f"allowed keys are {sorted(FIGURE_KEYS)}")
            kind = str(fig.get("kind", "line"))
            if kind not in KINDS:
                raise ReportError(f"report.figures.{name}.kind: {kind!r} is not one of {list(KINDS)}")
            reference = tuple(dict(r) for r in fig.get("reference") or ())
            for i, r in enumerate(reference):
                if set(r) != {"label", "x", "y"} or len(list(r["x"])) != len(list(r["y"])):
                    raise ReportError(f"report.figures.{name}.reference[{i}]: {r} must be {{label, x: [...], y: [...]}} "
                                      f"with as many x as y")
            figures.append(FigureSpec(str(name), str(fig.get("title", name)), _resolve(fig["query"], queries, name),
                                      str(fig["x"]), str(fig["y"]), _opt(fig.get("series")), _opt(fig.get("lower")),
                                      _opt(fig.get("upper")), kind, str(fig.get("xlabel", fig["x"])),
                                      str(fig.get("ylabel", fig["y"])), bool(fig.get("logy", False)), reference))
        targets = []
        raw = node.get("targets") or {}
        if not isinstance(raw, Mapping):
            raise ReportError(f"report.targets: must map an id to {{target, paper, query}} (a mapping, so an "
                              f"experiment that extends another adds targets to it); got {type(raw).__name__}")
        for key, target in raw.items():
            target = dict(target or {})
            if not TARGET_KEYS <= set(target) <= TARGET_KEYS | OPTIONAL_TARGET_KEYS:
                raise ReportError(f"report.targets.{key}: keys {sorted(target)} must be {sorted(TARGET_KEYS)}, "
                                  f"optionally with {sorted(OPTIONAL_TARGET_KEYS)}")
            timed = target.get("timed", False)
            if not isinstance(timed, bool):
                raise ReportError(f"report.targets.{key}.timed: {timed!r} must be true or false")
            targets.append(TargetSpec(str(key), str(target["target"]).strip(), str(target["paper"]).strip(),
                                      _resolve(target["query"], queries, f"targets.{key}"), timed))
        findings = []
        raw = node.get("findings") or {}
        if not isinstance(raw, Mapping):
            raise ReportError(f"report.findings: must map an id to {{finding, paper, query}}; got {type(raw).__name__}")
        for key, finding in raw.items():
            finding = dict(finding or {})
            if set(finding) != FINDING_KEYS:
                raise ReportError(f"report.findings.{key}: keys {sorted(finding)} must be exactly {sorted(FINDING_KEYS)}")
            findings.append(FindingSpec(str(key), str(finding["finding"]).strip(), str(finding["paper"]).strip(),
                                        _resolve(finding["query"], queries, f"findings.{key}")))
        return cls(queries, tuple(figures), tuple(targets), tuple(findings))


def _opt(value: Any) -> str | None:
    return None if value is None else str(value)


def _resolve(query: str, queries: Mapping[str, str], where: str) -> str:
    """A query name (from report.queries or the built-ins) or the SQL itself."""
    query = str(query)
    if query in queries:
        return queries[query]
    if query in BUILTIN_QUERIES:
        return BUILTIN_QUERIES[query]
    if not any(word in query.upper() for word in ("SELECT", "WITH")):
        raise ReportError(f"report.{where}: query {query!r} is neither SQL nor a name in report.queries "
                          f"({sorted(queries)}) or the built-ins ({sorted(BUILTIN_QUERIES)})")
    return query


# ---- a run's tables ----------------------------------------------------------------------------
@dataclass(frozen=True)
class RunTables:
    run_dir: Path
    experiment: str
    config: Mapping[str, Any]
    status: Mapping[str, Any]
    summary: pl.DataFrame
    metrics: pl.DataFrame
    wide: pl.DataFrame          # the summary pivoted: one row per window, one column per "<variant_key>:<series>"
    comparisons: pl.DataFrame | None = None
    wide_resamples: pl.DataFrame | None = None   # the wide table once per joint bootstrap resample (column resample)

    def query(self, sql: str, wide: pl.DataFrame | None = None) -> pl.DataFrame:
        """``sql`` over this run's tables; ``wide`` replaces the wide table (the resampled one)."""
        from pipeline.results.query import check_tables_only
        check_tables_only(sql)                     # the run's tables only, no file-reading functions
        frames = {"summary": self.summary, "metrics": self.metrics, "wide": self.wide if wide is None else wide}
        if self.comparisons is not None:
            frames["comparisons"] = self.comparisons
        return pl.SQLContext(frames, eager=True).execute(sql)


def load_run(run_dir: Path) -> RunTables:
    from omegaconf import OmegaConf

    run_dir = Path(run_dir)
    missing = [n for n in ("summary.parquet", "metrics.parquet", "config.yaml", "status.json")
               if not (run_dir / n).is_file()]
    if missing:
        raise ReportError(f"{run_dir}: not a finished run folder: {missing} missing (a run writes summary.parquet, "
                          f"metrics.parquet, config.yaml and status.json)")
    status = json.loads((run_dir / "status.json").read_text())
    config = OmegaConf.to_container(stored_config(run_dir), resolve=False)

    def read(name: str) -> pl.DataFrame:
        try:
            # checksum verified, and the table this folder's run wrote under this name: a checksum it has, this
            # run's id and config hash (pipeline.storage.run_tables)
            df = read_run_table(run_dir, name, status)[0]
        except TableDamaged as exc:
            raise ReportError(f"{exc}; re-run the job (or `python -m pipeline.recompute {run_dir}` to see what "
                              f"differs) before reporting on it") from None
        floats = [c for c, t in df.schema.items() if t in (pl.Float32, pl.Float64)]
        return df.with_columns(pl.col(c).fill_nan(None) for c in floats)

    summary = read("summary.parquet")
    comparisons = read("comparisons.parquet") if (run_dir / "comparisons.parquet").is_file() else None
    wide = pivot_summary(summary)
    resampled = None
    if (run_dir / "resamples.parquet").is_file():
        resampled = resampled_wide(wide, read("resamples.parquet"))
    return RunTables(run_dir, str(status.get("experiment") or config.get("experiment_name")), config, status,
                     summary, read("metrics.parquet"), wide, comparisons, resampled)


def resampled_wide(wide: pl.DataFrame, resamples: pl.DataFrame) -> pl.DataFrame | None:
    """The wide table once per stored joint resample (a ``resample`` column): each resampled value
    from that resample of the runs, every other value (compute time, bounds) as it is."""
    if resamples.height == 0 or wide.height == 0:
        return None
    resampled = (resamples.with_columns(pl.col("window").fill_null("-"),
                                        (pl.col("variant_key") + ":" + pl.col("series")).alias("column"))
                 .pivot(on="column", index=["window", "resample"], values="value", aggregate_function="first"))
    ids = resamples.select(pl.col("resample").unique().sort())
    grid = wide.join(ids, how="cross")
    joined = grid.join(resampled, on=["window", "resample"], how="left", suffix="__resampled")
    replaced = [pl.coalesce(f"{c}__resampled", c).alias(c) for c in wide.columns
                if c != "window" and f"{c}__resampled" in joined.columns]
    return joined.with_columns(replaced).select(wide.columns + ["resample"])


def pivot_summary(summary: pl.DataFrame) -> pl.DataFrame:
    """The summary one row per window ('-' for window-free values such as compute_seconds), one
    column per "<variant_key>:<series>": targets compare variants without self-joins."""
    if summary.height == 0:
        return pl.DataFrame(schema={"window": pl.String})
    return (summary.with_columns(pl.col("window").fill_null("-"),
                                 (pl.col("variant_key") + ":" + pl.col("series")).alias("column"))
            .pivot(on="column", index="window", values="value", aggregate_function="first"))


# ---- targets and figures -----------------------------------------------------------------------
@dataclass(frozen=True)
class TargetResult:
    spec: TargetSpec
    measured: str
    verdict: str               # PASS | FAIL | INCONCLUSIVE | ERROR
    point_pass: bool | None = None      # the verdict of the values alone, without their intervals
    runs_to_decide: str = ""            # for INCONCLUSIVE: how many runs would likely decide it
    interval_note: str = ""             # what the verdict's intervals were (or why there were none)


VERDICTS = ("PASS", "FAIL", "INCONCLUSIVE", "ERROR")


def evaluate_target(tables: RunTables, spec: TargetSpec) -> TargetResult:
    """The target's query on the values, then on the run's stored joint bootstrap resamples
    (``_judged_on_resamples``: paired, the way the runs were drawn). A query that reads no resampled
    value (the summary or metrics tables directly, window-free values such as compute time), and a
    run stored without resamples, are judged on their values, and the result says so."""
    try:
        df = tables.query(spec.query)
    except Exception as exc:  # noqa: BLE001 - a broken query is reported, not raised
        return TargetResult(spec, f"query failed: {type(exc).__name__}: {str(exc).splitlines()[0]}", "ERROR")
    if df.height != 1 or not {"measured", "pass"} <= set(df.columns):
        return TargetResult(spec, f"query returned {df.height} row(s) with columns {df.columns}; expected one row "
                                  f"with 'measured' and 'pass'", "ERROR")
    row = df.row(0, named=True)
    if row["measured"] is None or row["pass"] is None:
        return TargetResult(spec, "no value: an input of the query is NULL (an empty window, a variant or "
                                  "metric this run does not have)", "ERROR")
    point = bool(row["pass"])
    if tables.wide_resamples is None:
        return TargetResult(spec, str(row["measured"]), "PASS" if point else "FAIL", point,
                            interval_note="judged on the values: the run stored no resamples (written before "
                                          "resamples.parquet)")
    return _judged_on_resamples(tables, spec, str(row["measured"]), point)


def _judged_on_resamples(tables: RunTables, spec: TargetSpec, measured: str, point: bool) -> TargetResult:
    """The target's query on each stored joint resample of the runs (every value of the wide table from
    the same resampled runs, so a comparison of two variants is a paired one): PASS when the values
    pass and at least 97.5 % of the resamples do (the one-sided 95 % percentile interval of whatever
    the target measures lies on the passing side), FAIL when the values fail and at most 2.5 % pass,
    INCONCLUSIVE otherwise. The runs that would likely decide it: the share of passing resamples is
    Phi(z) with z = margin / standard error, which grows as sqrt(runs), so n' = n (1.96 / z)^2."""
    import re

    from scipy.special import ndtri

    wide = tables.wide_resamples
    named = [c for c in dict.fromkeys(re.findall(r'"([^"]+)"', spec.query)) if c in wide.columns and c != "window"]
    varying = [c for c in named if wide[c].drop_nulls().n_unique() > 1]
    if not re.search(r"\bwide\b", spec.query) or not varying:
        return TargetResult(spec, measured, "PASS" if point else "FAIL", point,
                            interval_note="judged on the values: the query reads no summary interval")
    count = int(wide["resample"].n_unique())
    together = _all_resamples_at_once(tables, spec.query, wide, count)
    if together is not None and together.height == count and "pass" in together.columns:
        outcomes = together["pass"].to_list()
    else:                     # a query that does not keep one row per resample: one resample at a time
        outcomes = _each_resample(tables, spec.query, wide, count)
    judged = [bool(o) for o in outcomes if o is not None]
    if len(judged) < 0.9 * count:
        return TargetResult(spec, measured, "PASS" if point else "FAIL", point,
                            interval_note="judged on the values: the resamples gave no verdict")
    share = sum(judged) / len(judged)
    note = f"passes on {100 * share:.1f} % of {len(judged)} joint resamples of the runs"
    if (point and share >= 0.975) or (not point and share <= 0.025):
        return TargetResult(spec, measured, "PASS" if point else "FAIL", point, interval_note=note)
    runs = int(tables.status.get("runs") or 0)
    z = float(ndtri(min(max(share, 0.5 / len(judged)), 1 - 0.5 / len(judged))))
    if (z > 0) != point or z == 0:
        needed = "no number of runs (the resamples lean against the values)"
    else:
        factor = (1.96 / z) ** 2
        needed = f"about {math.ceil(runs * factor)} runs" if runs else f"about {factor:.2g}x the runs"
    return TargetResult(spec, measured, "INCONCLUSIVE", point, needed, note)


PROBE_RESAMPLES = 2


def _all_resamples_at_once(tables: RunTables, query: str, wide: pl.DataFrame, count: int) -> pl.DataFrame | None:
    """The query on every resample's rows of the wide table at once, where it keeps one row per resample;
    None where it does not (or fails). Whether it does is probed first on the rows of two resamples:
    a query that joins the wide table with itself (``a CROSS JOIN b CROSS JOIN c``, one window each)
    pairs every resample with every other, 400^3 = 64 million rows on the whole table: 95 s of a
    sonar_case2 report spent on a result that was then thrown away for the one-at-a-time evaluation
    (8 rows on the probe's 2 resamples, a few ms)."""
    if count > PROBE_RESAMPLES:
        probe = wide.filter(pl.col("resample").is_in(wide["resample"].unique().sort().head(PROBE_RESAMPLES).to_list()))
        try:
            probed = tables.query(query, probe)
        except Exception:  # noqa: BLE001 - judged one resample at a time, as a failing query on all of them
            return None
        if probed.height != PROBE_RESAMPLES or "pass" not in probed.columns:
            return None
    try:
        return tables.query(query, wide)
    except Exception:  # noqa: BLE001
        return None


def _each_resample(tables: RunTables, query: str, wide: pl.DataFrame, count: int) -> list[Any]:
    """The query's ``pass`` on resample 0, 1, ..., count - 1 of the wide table alone (None where it
    fails or does not give one row). The table is split once, and the queries run on a thread per
    core: polars plans and runs each one outside the GIL, so two threads took a 400-resample ADS-B
    target from 1.8 s to 0.75 s (one resample filtered out per query, one after another, before)."""
    from concurrent.futures import ThreadPoolExecutor

    from filters.base import usable_processors

    parts = wide.partition_by("resample", as_dict=True, include_key=False, maintain_order=True)
    empty = wide.head(0).drop("resample")

    def passes(r: int) -> Any:
        try:
            df = tables.query(query, parts.get((r,), empty))
        except Exception:  # noqa: BLE001 - a resample the query cannot judge gives no verdict
            return None
        return df["pass"][0] if df.height == 1 and "pass" in df.columns else None

    with ThreadPoolExecutor(max_workers=max(1, min(count, usable_processors()))) as pool:
        return list(pool.map(passes, range(count)))


def evaluate_finding(tables: RunTables, spec: FindingSpec) -> str:
    """The finding's measured text, or why there is none (a broken query is reported, not raised)."""
    try:
        df = tables.query(spec.query)
    except Exception as exc:  # noqa: BLE001
        return f"query failed: {type(exc).__name__}: {str(exc).splitlines()[0]}"
    if df.height != 1 or "measured" not in df.columns:
        return f"query returned {df.height} row(s) with columns {df.columns}; expected one row with 'measured'"
    measured = df.row(0, named=True)["measured"]
    return "no value: an input of the query is NULL" if measured is None else str(measured)


def run_variants(tables: RunTables) -> list[tuple[str, str]]:
    """(variant key, display name) of the run's variants in the experiment's order (summary.parquet
    keeps it): the order that gives each its colour in the recording (pipeline.views.colours)."""
    frame = tables.summary if tables.summary.height else tables.metrics
    if frame.height == 0 or not {"variant_key", "variant"} <= set(frame.columns):
        return []
    pairs = frame.select("variant_key", "variant").filter(pl.col("variant_key").is_not_null()).unique(
        subset="variant_key", maintain_order=True)
    return [(str(k), str(v)) for k, v in pairs.iter_rows()]


def draw_figure(df: pl.DataFrame, spec: FigureSpec, path: Path, variants: Sequence[tuple[str, str]] = ()) -> None:
    """One line (or bar group) per ``spec.series`` value, each in its style from pipeline.views.colours:
    a series naming a variant of ``variants`` ((key, display name), the run's order) in that
    variant's colour, width and dash, as in the recording; a mode in the mode's colour; the rest grey.
    Lines are drawn widest first, so where curves coincide each stays visible."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    needed = [c for c in (spec.x, spec.y, spec.series, spec.lower, spec.upper) if c]
    absent = [c for c in needed if c not in df.columns]
    if absent:
        raise ReportError(f"report.figures.{spec.name}: the query's columns {df.columns} lack {absent}")
    from pipeline.views.colours import figure_styles, mpl, variant_styles
    from pipeline.views.figures import save_figure

    fig, ax = plt.subplots(figsize=(8.0, 4.2), dpi=110)
    groups = [(None, df)] if spec.series is None else [
        (key[0], part) for key, part in df.group_by(spec.series, maintain_order=True)]
    styles = figure_styles([str(label) for label, _ in groups if label is not None], variants)
    single = next(iter(variant_styles(["_"]).values()))          # a figure without series: the first style
    width = 0.8 / max(len(groups), 1)
    for i, (label, part) in enumerate(groups):
        x, y = part[spec.x].to_numpy(), part[spec.y].to_numpy().astype(float)
        name = None if label is None else str(label)
        style = single if name is None else styles[name]
        if spec.kind == "bar":
            positions = range(len(x))
            ax.bar([p + i * width for p in positions], y, width=width, label=name, color=mpl(style.colour),
                   edgecolor="black", linewidth=0.5, hatch=None if style.variant else "//" * (i % 2))
            ax.set_xticks([p + 0.4 - width / 2 for p in positions], [str(v) for v in x], rotation=30, ha="right")
            continue
        plot = ax.step if spec.kind == "step" else ax.plot
        plot(x, y, label=name, **style.plot_kwargs(len(x)), **({"where": "mid"} if spec.kind == "step" else {}))
        if spec.lower and spec.upper:
            ax.fill_between(x, part[spec.lower].to_numpy().astype(float), part[spec.upper].to_numpy().astype(float),
                            color=mpl(style.colour), alpha=0.12, linewidth=0, zorder=1)
    for ref, marker in zip(spec.reference, "osD^vPX*" * 4):      # one hollow marker shape per reference
        ax.plot(list(ref["x"]), list(ref["y"]), linestyle="none", marker=marker, markersize=6, markerfacecolor="none",
                color="black", label=str(ref["label"]))
    ax.set_title(spec.title, fontsize=10)
    ax.set_xlabel(spec.xlabel)
    ax.set_ylabel(spec.ylabel)
    if spec.logy:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    if groups[0][0] is not None or spec.reference:
        ax.legend(fontsize=8)
    save_figure(fig, path)


def limit_figures(tables: RunTables) -> list[FigureSpec]:
    """One figure per consistency metric (X with X_lower / X_upper) and one of RMSE / sqrt(PCRLB)."""
    names = set(tables.metrics["series"].unique().to_list()) if tables.metrics.height else set()
    out = []
    for metric in sorted(m for m in names if f"{m}_lower" in names and f"{m}_upper" in names):
        out.append(FigureSpec(f"limit_{metric}", f"{metric}: run average per step, shaded: its χ² 95 % band",
                              BUILTIN_QUERIES["consistency_by_step"].replace("{series}", metric), "time", "value",
                              "variant", "lower", "upper", "line", "time [s]", metric, metric.startswith(("nees", "nis"))
                              and _spread(tables, metric) > 30))
    if "position_rmse_over_bound" in names:
        out.append(FigureSpec("limit_rmse_over_bound", "position RMSE / sqrt(PCRLB) (1 = at the bound)",
                              BUILTIN_QUERIES["bound_ratio_by_step"], "time", "value", "line", kind="line",
                              xlabel="time [s]", ylabel="RMSE / sqrt(PCRLB)",
                              logy="position_rmse_over_bound_model" in names))
    return out


def _spread(tables: RunTables, metric: str) -> float:
    values = tables.metrics.filter(pl.col("series") == metric)["value"].drop_nulls()
    if values.len() == 0 or values.min() is None or values.min() <= 0:
        return 1.0
    return float(values.max() / values.min())


# ---- the Markdown ------------------------------------------------------------------------------
@dataclass
class RunReport:
    run_dir: Path
    path: Path
    experiment: str
    targets: list[TargetResult] = field(default_factory=list)
    findings: list[tuple[FindingSpec, str]] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)

    @property
    def counts(self) -> dict[str, int]:
        return {v: sum(t.verdict == v for t in self.targets) for v in VERDICTS}


def _md_table(df: pl.DataFrame, digits: int = 3) -> str:
    def cell(v: Any) -> str:
        if v is None:
            return ""
        if isinstance(v, float):
            return "nan" if math.isnan(v) else f"{v:.{digits}g}" if abs(v) < 1e4 else f"{v:.0f}"
        return str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.iter_rows()]
    return "\n".join(lines)


def _sql_block(name: str, sql: str) -> str:
    return f"<details><summary>query <code>{name}</code></summary>\n\n```sql\n{sql.strip()}\n```\n</details>\n"


def current_definition(experiment: str) -> Mapping[str, Any]:
    """The ``report`` node of ``experiment`` as conf/ defines it now (to re-check stored runs
    against targets written after them; the run's tables are not touched)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(version_base="1.3", config_dir=str(conf)):
        cfg = compose("config", overrides=[f"experiment={experiment}"])
    return OmegaConf.to_container(cfg.get("report") or {}, resolve=True)


def write_run_report(run_dir: Path, out_dir: Path | None = None, current: bool = False) -> RunReport:
    tables = load_run(run_dir)
    spec = ReportSpec.from_config(current_definition(tables.experiment) if current else tables.config.get("report"))
    out_dir = Path(out_dir) if out_dir is not None else tables.run_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    report = RunReport(tables.run_dir, out_dir / "report.md", tables.experiment)
    status, config = tables.status, tables.config
    lines = [f"# {tables.experiment}: reproduction report", ""]
    if config.get("description"):
        lines += [str(config["description"]).strip(), ""]
    if status.get("scenario"):         # what ran (a recorded flight's file), not the experiment's default
        lines += [f"Scenario: {status['scenario']}", ""]
    lines += [f"- run: `{tables.run_dir}` ({status.get('status')}, {status.get('runs')} Monte Carlo runs, seed "
              f"{(config.get('mc') or {}).get('seed')}, config {status.get('config_hash')}, finished "
              f"{status.get('finished_at')})",
              f"- overrides: `{' '.join(status.get('overrides') or []) or '(none)'}`",
              "- every number and figure below is computed from this run's `summary.parquet` and "
              "`metrics.parquet` by the query shown with it (`python -m pipeline.report` rebuilds it)", ""]

    report.targets = [evaluate_target(tables, t) for t in spec.targets]
    lines += ["## Reproduction targets", ""]
    if report.targets:
        c = report.counts
        lines += [f"**{c['PASS']} of {len(report.targets)} pass**" + (f", {c['FAIL']} fail" if c["FAIL"] else "")
                  + (f", {c['INCONCLUSIVE']} inconclusive" if c["INCONCLUSIVE"] else "")
                  + (f", {c['ERROR']} error" if c["ERROR"] else "") + f" (at {status.get('runs')} runs; the spec's "
                  f"references are at the paper's size).", "",
                  "Each target's query is also run on 400 joint bootstrap resamples of the runs (every value from "
                  "the same resampled runs, so comparisons between variants are paired): PASS when the values pass "
                  "and at least 97.5 % of the resamples do, FAIL when the values fail and at most 2.5 % pass, "
                  "INCONCLUSIVE in between, with the runs that would likely decide it (the margin over its "
                  "standard error grows as sqrt(runs)). A target that reads no interval is judged on its values.", "",
                  "| id | target | paper / spec | measured here | result |", "|---|---|---|---|---|"]
        for t in report.targets:
            mark = {"PASS": "PASS", "FAIL": "**FAIL**", "ERROR": "**ERROR**",
                    "INCONCLUSIVE": f"INCONCLUSIVE (values {'pass' if t.point_pass else 'fail'}; "
                                    f"{t.runs_to_decide} would likely decide)"}[t.verdict]
            if t.interval_note:
                mark += f"<br><sub>{_cell(t.interval_note)}</sub>"
            lines.append(f"| {t.spec.id} | {_cell(t.spec.target)} | {_cell(t.spec.paper)} | {_cell(t.measured)} | {mark} |")
        lines += [""] + [_sql_block(t.spec.id, t.spec.query) for t in report.targets] + [""]
    else:
        lines += ["This experiment declares no reproduction targets (`report.targets`).", ""]
    if spec.findings:
        lines += ["## Findings", "", "Figures the spec asks to report beside a reference, with no pass/fail threshold.",
                  "", "| id | finding | paper / spec | measured here |", "|---|---|---|---|"]
        report.findings = [(f, evaluate_finding(tables, f)) for f in spec.findings]
        for f, measured in report.findings:
            lines.append(f"| {f.id} | {_cell(f.finding)} | {_cell(f.paper)} | {_cell(measured)} |")
        lines += [""] + [_sql_block(f.id, f.query) for f in spec.findings] + [""]

    lines += _comparisons_section(tables)
    if spec.figures:
        lines += ["## Figures", ""]
        for fig in spec.figures:
            lines += _figure_section(tables, fig, out_dir, report)

    lines += ["## How far from the limit", "",
              "NEES / NIS: the run average per step against the two-sided 95 % chi-square band of that average "
              "for a consistent filter; a share of steps in the band near 0.95 means consistent, a mean below "
              "the band pessimistic, above it optimistic.", ""]
    consistency = tables.query(BUILTIN_QUERIES["consistency"])
    if consistency.height:
        lines += [_md_table(consistency), "", _sql_block("consistency", BUILTIN_QUERIES["consistency"]), ""]
    else:
        lines += ["(no NEES / NIS bands in this run's metrics)", ""]
    ratio = tables.query(BUILTIN_QUERIES["bound_ratio_by_window"])
    if ratio.height:
        lines += ["Position RMSE / sqrt(PCRLB) averaged over each summary window (1 = at the bound). `bound`: the "
                  "PCRLB of the process that generated the truth, a bound for any unbiased estimator of this "
                  "truth: a ratio below 1 beyond Monte Carlo error would be a bug. `bound_model`, beside it: the "
                  "PCRLB under the filters' own motion model, which a truth that does not follow that model (a "
                  "deterministic profile) lets a filter undercut (ratio below 1):", "",
                  _md_table(ratio.pivot(on="window", index=["variant", "bound"], values="rmse_over_bound")), "",
                  _sql_block("bound_ratio_by_window", BUILTIN_QUERIES["bound_ratio_by_window"]), ""]
    for fig in limit_figures(tables):
        lines += _figure_section(tables, fig, out_dir, report, heading="###")

    compute = tables.query(BUILTIN_QUERIES["compute"])
    if compute.height:
        lines += ["## Compute", "", _md_table(compute), "", _sql_block("compute", BUILTIN_QUERIES["compute"]), ""]
    printed = tables.run_dir / "report.txt"
    if printed.is_file():
        lines += ["## Tables printed by the run", "", "```", printed.read_text().rstrip(), "```", ""]
    tmp = report.path.with_name(f".{report.path.name}.tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(report.path)
    return report


def _comparisons_section(tables: RunTables) -> list[str]:
    """Which differences from the reference variant the runs resolve (comparisons.parquet), for the
    metrics the printed summary shows."""
    from pipeline.evaluation.metrics import format_value, printed_columns

    c = tables.comparisons
    if c is None or c.height == 0:
        return []
    labels = dict(printed_columns(set(c["series"].to_list())))
    c = c.filter(pl.col("series").is_in(list(labels)) & pl.col("window").is_not_null())
    if c.height == 0:
        return []
    names = dict(zip(tables.summary["variant_key"].to_list(), tables.summary["variant"].to_list()))
    reference = names.get(c["reference_key"][0], c["reference_key"][0])
    lines = ["## Paired comparisons with " + reference, "",
             f"Each variant minus {reference} on the same runs and noise (comparisons.parquet): the difference "
             "and the ratio with their 95 % bootstrap intervals over the runs (the same resamples for both "
             "variants), and the Wilcoxon signed-rank p-value of the runs' own values. **Resolved**: the "
             "difference's interval excludes 0; otherwise these runs cannot tell the two apart.", "",
             "| variant | metric | window | difference [95 %] | ratio [95 %] | Wilcoxon p | resolved |",
             "|---|---|---|---|---|---|---|"]
    for row in c.iter_rows(named=True):
        def interval(value, low, high, series=row["series"]):
            if value is None:
                return ""
            text = format_value(series, value)
            return text if low is None or high is None else \
                f"{text} [{format_value(series, low)}, {format_value(series, high)}]"
        ratio = "" if row["ratio"] is None else f"{row['ratio']:.3f}" + (
            "" if row["ratio_low"] is None else f" [{row['ratio_low']:.3f}, {row['ratio_high']:.3f}]")
        p = "" if row["wilcoxon_p"] is None else f"{row['wilcoxon_p']:.2g}"
        lines.append(f"| {names.get(row['variant_key'], row['variant_key'])} | {labels[row['series']]} | "
                     f"{row['window']} | {interval(row['difference'], row['difference_low'], row['difference_high'])} | "
                     f"{ratio} | {p} | {'**yes**' if row['resolved'] else 'no'} |")
    return lines + [""]


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _figure_section(tables: RunTables, fig: FigureSpec, out_dir: Path, report: RunReport,
                    heading: str = "###") -> list[str]:
    path = out_dir / f"{fig.name}.png"
    try:
        df = tables.query(fig.query)
        if df.height == 0:
            raise ReportError("the query returned no rows")
        draw_figure(df, fig, path, run_variants(tables))
    except Exception as exc:  # noqa: BLE001 - one broken figure must not lose the report
        return [f"{heading} {fig.title}", "", f"**figure not drawn**: {type(exc).__name__}: {exc}", "",
                _sql_block(fig.name, fig.query), ""]
    report.figures.append(path)
    return [f"{heading} {fig.title}", "", f"![{fig.name}]({path.name})", "", _sql_block(fig.name, fig.query), ""]


# ---- many runs ---------------------------------------------------------------------------------
def find_runs(path: Path) -> list[Path]:
    path = Path(path)
    if (path / "summary.parquet").is_file():
        return [path]
    def natural(p: Path) -> tuple:                # sweep jobs in their number order: 2 before 10
        return (len(p.parts),) + tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in p.parts)
    return sorted({p.parent for p in path.rglob("summary.parquet") if "cache" not in p.parts and "report" not in p.parts},
                  key=natural)


def latest_result(artifacts: Path) -> Path:
    """The newest sweep (``multirun/<time>``) or single run (``runs/<experiment>/<time>``), whichever
    started last: both folder names are the start time, so they compare as text."""
    artifacts = Path(artifacts)
    sweeps = [p for p in (artifacts / "multirun").glob("*") if p.is_dir()]
    runs = [p for p in (artifacts / "runs").glob("*/*") if (p / "summary.parquet").is_file()]
    if not sweeps and not runs:
        raise ReportError(f"--latest: no run under {artifacts / 'runs'} and no sweep under {artifacts / 'multirun'}; "
                          f"run one with python -m pipeline [-m] ...")
    return max(sweeps + runs, key=lambda p: p.name)


def write_reports(path: Path, out: Path | None = None, current: bool = False) -> tuple[list[RunReport], Path | None]:
    runs = find_runs(path)
    if not runs:
        raise ReportError(f"{path}: no run below it (no summary.parquet); pass a run folder or a sweep folder")
    if len(runs) == 1 and runs[0] == Path(path):
        return [write_run_report(runs[0], out, current)], None
    index = (Path(out) if out is not None else Path(path)) / "index.md"
    swept = swept_columns(runs)
    shown = [k for k in swept if k != "experiment"]        # a swept experiment is the experiment column
    lines = [f"# Reproduction reports: {path}", "",
             "| " + " | ".join(["run", *map(_cell, shown), "experiment", "runs", "targets passed", "report"]) + " |",
             "|" + "---|" * (len(shown) + 5)]
    reports: list[RunReport | NotReported] = []
    for run_dir in runs:
        name = run_dir.relative_to(path) if run_dir != Path(path) else "."
        name = " | ".join([str(name), *(_cell(swept[k][run_dir]) for k in shown)])     # the run and its swept values
        try:
            status = json.loads((run_dir / "status.json").read_text())
        except (OSError, ValueError):
            status = {}
        try:
            if status.get("status") != "ok":   # a failed or unfinished job: its line says why, the others go on
                raise ReportError(f"the job is {status.get('status') or 'of unknown status'}"
                                  + (f": {_one_line(status['error'])}" if status.get("error") else ""))
            rep = write_run_report(run_dir, None if out is None else Path(out) / run_dir.relative_to(path), current)
        except ReportError as exc:
            skipped = NotReported(run_dir, str(status.get("experiment") or "?"), str(exc))
            reports.append(skipped)
            lines.append(f"| {name} | {skipped.experiment} | {status.get('runs')} | not reported | "
                         f"{_cell(skipped.reason)} |")
            continue
        reports.append(rep)
        c = rep.counts
        total = sum(c.values())
        verdict = f"{c['PASS']} / {total}" + (f" ({c['FAIL']} FAIL)" if c["FAIL"] else "") + \
            (f" ({c['INCONCLUSIVE']} INCONCLUSIVE)" if c["INCONCLUSIVE"] else "") + \
            (f" ({c['ERROR']} ERROR)" if c["ERROR"] else "") if total else "none declared"
        lines.append(f"| {name} | {rep.experiment} | {status.get('runs')} | {verdict} | "
                     f"[{rep.path.name}]({rep.path.relative_to(index.parent)}) |")
    index.parent.mkdir(parents=True, exist_ok=True)
    index.write_text("\n".join(lines) + "\n")
    return reports, index


def swept_columns(runs: Sequence[Path]) -> dict[str, dict[Path, str]]:
    """Swept key -> run folder -> its value as text, for the overrides that differ between the runs
    (pipeline.results.sweep: the values the runs' summaries recorded, else the overrides')."""
    from pipeline.results.sweep import format_value, label_jobs, read_job

    jobs = [read_job(run_dir) for run_dir in runs]
    swept, _ = label_jobs(jobs)
    return {key: {job.folder: format_value(job.values[key]) for job in jobs} for key in swept}


@dataclass
class NotReported:
    """A job of a sweep with no report (it failed, is unfinished, or its tables are damaged): why."""

    run_dir: Path
    experiment: str
    reason: str


def _one_line(text: object, width: int = 300) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= width else line[: width - 1] + "…"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("path", nargs="?", help="a run folder, or a sweep / artifacts folder holding runs")
    parser.add_argument("--latest", action="store_true", help="report the newest run or sweep under --artifacts (runs/ or multirun/)")
    parser.add_argument("--artifacts", default="artifacts", help="the artifacts root for --latest (default: artifacts)")
    parser.add_argument("--out", help="write the reports here instead of <run>/report/")
    parser.add_argument("--check", action="store_true", help="exit 1 when any reproduction target is FAIL or ERROR, "
                        "or a job has no report (INCONCLUSIVE does not fail)")
    parser.add_argument("--current", action="store_true",
                        help="check the targets and figures as conf/ defines them now, not as the run recorded them")
    args = parser.parse_args(argv)
    try:
        if args.latest == bool(args.path):
            raise ReportError("give a run or sweep folder, or --latest (not both)")
        path = latest_result(Path(args.artifacts)) if args.latest else Path(args.path)
        if not path.exists():
            raise ReportError(f"{path}: no such folder")
        reports, index = write_reports(path, None if args.out is None else Path(args.out), args.current)
    except ReportError as exc:
        print(f"report: {exc}", file=sys.stderr)
        return 2
    failed = 0
    for rep in reports:
        if isinstance(rep, NotReported):
            print(f"{rep.experiment}: not reported ({rep.run_dir}): {rep.reason}")
            failed += 1
            continue
        c = rep.counts
        print(f"{rep.experiment}: {c['PASS']}/{sum(c.values())} targets pass"
              + (f", {c['FAIL']} FAIL" if c["FAIL"] else "")
              + (f", {c['INCONCLUSIVE']} INCONCLUSIVE" if c["INCONCLUSIVE"] else "")
              + (f", {c['ERROR']} ERROR" if c["ERROR"] else "")
              + f", {len(rep.figures)} figures -> {rep.path}")
        for t in rep.targets:
            if t.verdict != "PASS":
                decide = f" ({t.runs_to_decide} would likely decide)" if t.runs_to_decide else ""
                print(f"  {t.verdict} {t.spec.id}: {t.measured}{decide}")
        failed += c["FAIL"] + c["ERROR"]
    if index is not None:
        print(f"index: {index}")
    return 1 if args.check and failed else 0


if __name__ == "__main__":
    sys.exit(main())
