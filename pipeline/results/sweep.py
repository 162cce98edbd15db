"""Sweeps at a glance: which job ran which swept values, and how a summary metric moves with them.

``python -m pipeline.sweep <sweep_dir> --metric position_rmse [--window all] [--x KEY] [--out DIR]``
draws, for each swept parameter (or only ``--x``), the metric's value against that parameter: one
line per variant (the run recordings' variant colours), the 95 % interval across Monte Carlo runs
as error bars where the summary has ``ci_low`` / ``ci_high``, and one panel per combination of the
other swept parameters' values (so every point is one job and nothing is averaged away).

A separate module rather than a subcommand: ``pipeline.launch.aggregate`` is the Hydra callback whose CLI
rebuilds the sweep's files (one argument, no options), ``pipeline.results.report`` draws the figures an
experiment declares in its YAML for one run, and ``pipeline.results.query`` answers SQL over a whole
artifacts folder; a figure against the swept values needs a sweep's jobs and their swept keys,
which this module works out (the aggregate callback uses it for the sweep's tables too).

The swept keys are the override keys (``status.json`` ``overrides``, else ``.hydra/overrides.yaml``)
whose value differs between the sweep's jobs, in command-line order. A job's value of a swept key
is the resolved config value its summary recorded (``mc.runs=${paper_runs}`` -> 100) where the
summary has that column, else the override's value as Hydra parses it. A job is named by its swept
values (``t1_mu=0.8, runs=20``: each key shortened to its shortest dotted suffix that no other
swept key shares).

Everything here reads the job folders themselves (summaries checked against their checksums), so
it works on a sweep that was interrupted or was written before ``sweep_index.parquet`` existed.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import polars as pl

log = logging.getLogger("pipeline.results.sweep")

SWEEP_INDEX = "sweep_index.parquet"
SWEEP_SUMMARY = "sweep_summary.parquet"
# the jobs table's own columns; one column per swept key follows them
JOB_COLUMNS = {"job_num": pl.Int32, "job": pl.String, "status": pl.String, "experiment": pl.String,
               "error": pl.String, "run_dir": pl.String}
META_SWEPT = "mtt.swept_keys"        # the swept keys in order, JSON, in both sweep tables' metadata
NO_WINDOW = "-"                      # how a window-free value (compute_seconds) is named, as in report's `wide`


class SweepError(ValueError):
    """A sweep folder, metric, window or key that cannot be used; the message says what exists."""


@dataclass
class Job:
    """One job folder of a sweep: its status.json, overrides and summary (None when unreadable)."""
    folder: Path
    status: dict
    overrides: list[str]
    summary: pl.DataFrame | None = None
    values: dict[str, Any] = field(default_factory=dict)     # swept key -> this job's value (set by collect)
    label: str = ""
    skipped: str | None = None       # why its summary was left out (damaged, refused, unreadable), if it was

    @property
    def state(self) -> str:
        """Its status.json status, or ``skipped`` where its summary was left out of the sweep's tables."""
        return "skipped" if self.skipped else (self.status.get("status") or "unknown")

    @property
    def error(self) -> str | None:
        return self.skipped or (self.status.get("error") if self.status else
                                "no status.json: the job did not start its task, or its process died first")

    @property
    def num(self) -> int | None:
        num = self.status.get("job_num")
        if num is None and self.folder.name.isdigit():
            num = int(self.folder.name)
        return None if num is None else int(num)


@dataclass
class Sweep:
    folder: Path
    jobs: list[Job]
    swept: list[str]                  # swept keys, command-line order
    short: dict[str, str]             # swept key -> its short name in job labels
    summary: pl.DataFrame             # every job's summary, with ``job`` and the swept keys first
    index: pl.DataFrame               # one row per job: JOB_COLUMNS + the swept keys

    @property
    def failures(self) -> list[dict]:
        """The status of every job that did not end ok, or whose summary was skipped (``status``
        ``skipped``, ``error`` why)."""
        return [{**j.status, "status": j.state, "error": j.error} if j.skipped else j.status
                for j in self.jobs if (j.status and j.status.get("status") != "ok") or j.skipped]


# ---- the jobs and their swept values ------------------------------------------------------------
def _job_order(folder: Path) -> tuple:
    return (0, int(folder.name), "") if folder.name.isdigit() else (1, 0, folder.name)   # 2 before 10


def read_job(folder: Path) -> Job:
    """A run or job folder's status.json, overrides (status.json's, else .hydra/overrides.yaml) and
    summary; a summary that is damaged, unreadable or not this job's (pipeline.storage.run_tables: no
    checksum, another run's) is left out with a warning, and the job is ``skipped`` with the reason."""
    from pipeline.storage.run_tables import read_run_table

    status_path = folder / "status.json"
    status = json.loads(status_path.read_text()) if status_path.is_file() else {}
    overrides = status.get("overrides")
    if overrides is None and (folder / ".hydra" / "overrides.yaml").is_file():
        from pipeline.storage.store import read_yaml
        overrides = read_yaml(folder / ".hydra" / "overrides.yaml") or []
    job = Job(folder, status, [str(o) for o in overrides or []])
    summary = folder / "summary.parquet"
    if summary.exists():
        try:
            job.summary = read_run_table(folder, "summary.parquet", status)[0]
        except Exception as exc:  # noqa: BLE001 - damaged, refused or unreadable: this job's rows are left out, named
            reason = (str(exc).splitlines()[0] if str(exc) else type(exc).__name__).replace(str(summary), summary.name)
            job.skipped = reason if reason.startswith(summary.name) else f"{summary.name}: {reason}"
            log.warning("skipped job folder %s: %s", folder, job.skipped)
    return job


def read_jobs(sweep_dir: Path) -> list[Job]:
    """The job folders directly under ``sweep_dir`` (a status.json or Hydra's .hydra/overrides.yaml),
    in job-number order."""
    sweep_dir = Path(sweep_dir)
    folders = {p.parent for p in sweep_dir.glob("*/status.json")} | \
              {p.parent.parent for p in sweep_dir.glob("*/.hydra/overrides.yaml")}
    return [read_job(folder) for folder in sorted(folders, key=_job_order)]


def parse_overrides(overrides: Sequence[str]) -> dict[str, tuple[Any, str]]:
    """key -> (value as Hydra parses it, the override's value text). The key drops Hydra's ``+`` /
    ``++`` (add / force-add: the same key either way) and keeps ``group@package``."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    out: dict[str, tuple[Any, str]] = {}
    for text in overrides:
        try:
            (override,) = parser.parse_overrides([text])
            key = override.key_or_group + (f"@{override.package}" if override.package else "")
            value = None if override.is_delete() else override.value()
        except Exception:            # noqa: BLE001 - never fail a sweep's summary over one odd override
            key, _, value = text.lstrip("+~").partition("=")
        out[key] = (value, text.partition("=")[2])
    return out


def swept_keys(jobs: Sequence[Job]) -> list[str]:
    """The override keys whose value text differs between jobs (or that only some jobs set)."""
    parsed = [parse_overrides(j.overrides) for j in jobs]
    keys: list[str] = []
    for p in parsed:
        keys += [k for k in p if k not in keys]
    return [k for k in keys if len({p[k][1] if k in p else None for p in parsed}) > 1]


def short_names(keys: Sequence[str]) -> dict[str, str]:
    """Each key's shortest dotted suffix that no other key ends with (``filters.vsimm.t1_mu`` ->
    ``t1_mu``, unless ``filters.fsimm.t1_mu`` is swept too: then ``vsimm.t1_mu``). A group override
    (``filter@filters.a``, ``hydra/launcher``) keeps its whole key."""
    out = {}
    for key in keys:
        parts = key.split(".") if "@" not in key and "/" not in key else [key]
        for n in range(1, len(parts) + 1):
            suffix = ".".join(parts[-n:])
            if not any(other != key and (other == suffix or other.endswith("." + suffix)) for other in keys):
                break
        out[key] = suffix
    return out


def _scalar(value: Any) -> Any:
    """A config value fit for one table cell: lists and mappings as JSON text (as the summary's
    flattened config columns hold them)."""
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value)
    return value


def _job_value(job: Job, key: str, parsed: dict[str, tuple[Any, str]]) -> Any:
    """The resolved value the job's summary recorded under ``key``, else the parsed override value."""
    if job.summary is not None and key in job.summary.columns and job.summary.height:
        value = job.summary[key].drop_nulls()
        if value.len():
            return _scalar(value[0])
    return _scalar(parsed[key][0]) if key in parsed else None


def typed_column(name: str, values: Sequence[Any]) -> pl.Series:
    """Booleans, integers, numbers (integers and floats together) or, failing those, text."""
    present = [v for v in values if v is not None]
    if present and all(isinstance(v, bool) for v in present):
        dtype = pl.Boolean
    elif present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        dtype = pl.Int64
    elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
        dtype = pl.Float64
        values = [None if v is None else float(v) for v in values]
    else:
        dtype = pl.String
        values = [None if v is None else v if isinstance(v, str) else json.dumps(v) for v in values]
    return pl.Series(name, values, dtype=dtype)


def format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return "null" if value is None else str(value)


def job_label(values: dict[str, Any], short: dict[str, str], num: int | None) -> str:
    if not values:
        return f"job {num}"
    return ", ".join(f"{short[k]}={format_value(v)}" for k, v in values.items())


def label_jobs(jobs: Sequence[Job]) -> tuple[list[str], dict[str, str]]:
    """Work out the swept keys (and their short names) of ``jobs`` and set each job's values and
    label; two jobs with the same swept values (a folder holding several sweeps) get their job
    number in the label too."""
    swept = swept_keys(jobs)
    short = short_names(swept)
    for job in jobs:
        parsed = parse_overrides(job.overrides)
        job.values = {k: _job_value(job, k, parsed) for k in swept}
        job.label = job_label(job.values, short, job.num)
    seen: dict[str, int] = {}
    for job in jobs:
        seen[job.label] = seen.get(job.label, 0) + 1
    for job in jobs:
        if seen[job.label] > 1:
            job.label = f"{job.label} (job {job.num})"
    return swept, short


def collect(sweep_dir: Path) -> Sweep:
    """The sweep's jobs, swept keys, jobs table and combined summary, read from its job folders
    (nothing is written: ``pipeline.launch.aggregate`` writes them)."""
    sweep_dir = Path(sweep_dir)
    jobs = read_jobs(sweep_dir)
    swept, short = label_jobs(jobs)
    index = jobs_table(jobs, swept)
    frames = [_with_job_columns(j.summary, j, index, swept) for j in jobs if j.summary is not None]
    summary = pl.concat(frames, how="diagonal_relaxed") if frames else pl.DataFrame()
    if frames:
        first = ["job"] + [k for k in swept if k in summary.columns]
        summary = summary.select(first + [c for c in summary.columns if c not in first])
    return Sweep(sweep_dir, jobs, swept, short, summary, index)


def jobs_table(jobs: Sequence[Job], swept: Sequence[str]) -> pl.DataFrame:
    """One row per job: job_num, job (its label), status, experiment, error, run_dir (the job folder
    relative to the sweep folder, so the table stays right when the sweep is moved), and one column
    per swept key. A swept ``experiment`` is the experiment column itself."""
    columns = [
        pl.Series("job_num", [j.num for j in jobs], dtype=pl.Int32),
        pl.Series("job", [j.label for j in jobs], dtype=pl.String),
        pl.Series("status", [j.state for j in jobs], dtype=pl.String),
        pl.Series("experiment", [_experiment(j) for j in jobs], dtype=pl.String),
        pl.Series("error", [j.error for j in jobs], dtype=pl.String),
        pl.Series("run_dir", [j.folder.name for j in jobs], dtype=pl.String),
    ]
    columns += [typed_column(k, [j.values[k] for j in jobs]) for k in swept if k not in JOB_COLUMNS]
    return pl.DataFrame(columns)


def _experiment(job: Job) -> str | None:
    """The experiment the job ran (status.json), else the one its overrides chose."""
    chosen = job.values.get("experiment", parse_overrides(job.overrides).get("experiment", (None, ""))[0])
    return job.status.get("experiment") or (None if chosen is None else str(chosen))


def _with_job_columns(summary: pl.DataFrame, job: Job, index: pl.DataFrame, swept: Sequence[str]) -> pl.DataFrame:
    """The job's summary with its label and the swept keys it lacks as columns (a group override
    such as ``scenario=...`` has no config column of that name), typed as in the jobs table."""
    row = index.filter(pl.col("run_dir") == job.folder.name)
    added = [pl.lit(job.label, dtype=pl.String).alias("job")]
    for key in swept:
        if key not in summary.columns and key in index.columns:
            added.append(pl.lit(row[key][0], dtype=index.schema[key]).alias(key))
    return summary.with_columns(added)


def swept_of(metadata: dict[str, str]) -> list[str]:
    """The swept keys a sweep table's metadata records."""
    return json.loads(metadata.get(META_SWEPT, "[]"))


def format_glance(sweep: Sweep, width: int = 60) -> str:
    """The jobs at a glance: one row per job with its swept values and status (a failed job's error,
    cut to ``width``, after it)."""
    header = ["job"] + [sweep.short[k] for k in sweep.swept] + ["status"]
    rows = [header]
    for job in sweep.jobs:
        status = job.state
        if status != "ok" and job.error:
            error = " ".join(str(job.error).split())
            status += ": " + (error if len(error) <= width else error[: width - 1] + "…")
        rows.append([str(job.num)] + [format_value(job.values[k]) for k in sweep.swept] + [status])
    widths = [max(len(r[i]) for r in rows) for i in range(len(header) - 1)]
    lines = []
    for i, r in enumerate(rows):
        lines.append("  ".join([c.ljust(w) for c, w in zip(r[:-1], widths)] + [r[-1]]).rstrip())
        if i == 0:
            lines.append("  ".join(["-" * w for w in widths] + ["-" * len(header[-1])]))
    return "\n".join(lines)


# ---- a metric against the swept values ----------------------------------------------------------
def variant_order(frame: pl.DataFrame) -> list[str]:
    """Variant keys in the order the jobs list them (job order, then each job's own order): the
    order that gives each variant its colour (pipeline.views.colours.variant_colour), as the run
    recordings do when every job runs the same variants."""
    if frame.height == 0 or "variant_key" not in frame.columns:
        return []
    keys = frame.filter(pl.col("variant_key").is_not_null())
    if "job_num" in keys.columns:
        keys = keys.with_row_index("_row").sort("job_num", "_row", nulls_last=True)
    return keys["variant_key"].unique(maintain_order=True).to_list()


def _listing(values: Sequence[str]) -> str:
    return ", ".join(values) if values else "(none)"


def select_metric(summary: pl.DataFrame, metric: str, window: str | None) -> tuple[pl.DataFrame, str, str | None]:
    """(rows, series, window) of one metric: ``metric`` is a ``series`` name or a ``metric`` name
    that is not broken down (no component / sensor / target); ``window`` a summary window, ``-``
    for a window-free value, or None: ``all`` where the metric has it, else its only window."""
    ok = summary.filter(pl.col("status") == "ok") if "status" in summary.columns else summary
    if ok.height == 0 or "series" not in ok.columns:
        raise SweepError("the sweep has no finished job with a summary, so there is no metric to draw; "
                         "see its jobs' status.json (python -m pipeline.aggregate <sweep_dir> lists them)")
    series_names = sorted(ok["series"].drop_nulls().unique().to_list())
    if metric in series_names:
        rows = ok.filter(pl.col("series") == metric)
    elif "metric" in ok.columns and metric in ok["metric"].to_list():
        breakdown = [c for c in ("component", "sensor", "target") if c in ok.columns]
        rows = ok.filter((pl.col("metric") == metric) & pl.all_horizontal([pl.col(c).is_null() for c in breakdown]))
        if rows.height == 0:
            parts = sorted(ok.filter(pl.col("metric") == metric)["series"].unique().to_list())
            raise SweepError(f"metric {metric!r} is broken down (by component, sensor or target) into the series "
                             f"{_listing(parts)}; pass one of them with --metric")
        rows = rows.filter(pl.col("series") == rows["series"][0])
    else:
        raise SweepError(f"no metric {metric!r} in the sweep's summaries (window {window or 'all'}). The "
                         f"metrics (series) there are: {_listing(series_names)}. Pass one with --metric.")
    series = rows["series"][0]
    windows = rows["window"].unique(maintain_order=True).to_list()
    names = [NO_WINDOW if w is None else w for w in windows]
    if window is None:
        window = "all" if "all" in names else names[0] if len(names) == 1 else None
        if window is None:
            raise SweepError(f"metric {series!r} has the windows {_listing(names)}; choose one with --window")
    if window not in names:
        raise SweepError(f"metric {series!r} has no window {window!r}; its windows are {_listing(names)}"
                         + (f" ({NO_WINDOW!r}: a value over the whole run, without a window)" if NO_WINDOW in names
                            else "") + ". Pass one with --window.")
    chosen = None if window == NO_WINDOW else window
    rows = rows.filter(pl.col("window").is_null() if chosen is None else pl.col("window") == chosen)
    return rows, series, chosen


def metric_against(sweep: Sweep, metric: str, window: str | None, x: str) -> tuple[pl.DataFrame, str, str | None]:
    """The data of one figure: one row per job and variant with ``x`` (the job's value of swept key
    ``x``), ``panel`` (the other swept keys' values, "" when there are none), variant_key, variant,
    value, ci_low and ci_high (null where the summary has no interval), job_num and job. Rows come
    in panel order (the jobs' order), then the variants' order, then ``x``."""
    if x not in sweep.swept:
        raise SweepError(f"{x!r} is not a swept key of this sweep; its swept keys (the overrides that differ "
                         f"between its jobs) are {_listing(sweep.swept)}. Pass one with --x.")
    rows, series, chosen = select_metric(sweep.summary, metric, window)
    others = [k for k in sweep.swept if k != x]
    panel = (pl.concat_str([pl.lit(f"{sweep.short[k]}=") + pl.col(k).cast(pl.String).fill_null("null")
                            for k in others], separator=", ") if others else pl.lit(""))
    for bound in ("ci_low", "ci_high"):
        if bound not in rows.columns:            # the summaries before the interval columns
            rows = rows.with_columns(pl.lit(None, dtype=pl.Float64).alias(bound))
    order = {key: i for i, key in enumerate(variant_order(sweep.summary))}
    data = (rows.with_columns(panel.alias("panel"))
            .select(pl.col(x).alias("x"), "panel", "variant_key", "variant",
                    pl.col("value").cast(pl.Float64).fill_nan(None), pl.col("ci_low").cast(pl.Float64),
                    pl.col("ci_high").cast(pl.Float64), "job_num", "job",
                    *(["interval"] if "interval" in rows.columns else []))
            .with_columns(pl.col("variant_key").replace_strict(order, default=len(order)).alias("_variant")))
    first_job = data.group_by("panel").agg(pl.col("job_num").min().alias("_panel"))
    # numbers along their axis; categories (experiment names) in the jobs' order
    along = "x" if is_numeric(data.schema["x"]) else "job_num"
    data = data.join(first_job, on="panel").sort("_panel", "_variant", along, nulls_last=True)
    return data.drop("_panel", "_variant"), series, chosen


def is_numeric(dtype: pl.DataType) -> bool:
    return dtype.is_numeric() and dtype != pl.Boolean


def draw_metric_figure(data: pl.DataFrame, *, x: str, series: str, window: str | None, unit: str,
                       path: Path, colours: dict[str, tuple[int, int, int]], left_out: Sequence[str] = ()) -> None:
    """One panel per ``panel`` value, one line per variant (its recording colour, and the dash, marker
    and width of pipeline.views.colours.variant_styles, so coinciding lines stay apart), error bars from
    ci_low / ci_high where present; numeric ``x`` on a numeric axis, anything else as categories.
    ``left_out``: the labels of jobs without a result (failed, unfinished), named under the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = data["panel"].unique(maintain_order=True).to_list()
    ncols = min(len(panels), 3)
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.8 * ncols + 1.2, 3.6 * nrows + 0.8), dpi=110,
                             sharey=True, squeeze=False)
    numeric = is_numeric(data.schema["x"])
    categories = [format_value(v) for v in data.sort("job_num")["x"].unique(maintain_order=True).to_list()]
    ticks = sorted(data["x"].drop_nulls().unique().to_list()) if numeric else []
    span = (ticks[-1] - ticks[0]) or 1.0 if ticks else 1.0
    variants = data["variant_key"].unique(maintain_order=True).to_list()
    from pipeline.views.colours import variant_styles
    styles = variant_styles(list(colours) + [k for k in variants if k not in colours])
    with_interval = data.filter(pl.col("ci_low").is_not_null() & pl.col("ci_high").is_not_null()).height > 0
    for ax, name in zip(axes.flat, panels):
        part = data.filter(pl.col("panel") == name)
        for i, key in enumerate(variants):
            rows = part.filter((pl.col("variant_key") == key) & pl.col("value").is_not_null() & pl.col("x").is_not_null())
            if rows.height == 0:
                continue
            colour = tuple(c / 255 for c in colours[key])
            if numeric:              # with bars, variants a little apart so that their bars do not hide each other
                shift = (i - (len(variants) - 1) / 2) * 0.012 * span if with_interval else 0.0
                xs = [v + shift for v in rows["x"].cast(pl.Float64).to_list()]
            else:                    # categories side by side: a small offset per variant keeps bars apart
                offset = (i - (len(variants) - 1) / 2) * 0.08
                xs = [categories.index(format_value(v)) + offset for v in rows["x"].to_list()]
            ys = rows["value"].to_list()
            style = styles[key]
            ax.plot(xs, ys, marker=style.marker, markersize=5, linewidth=style.width, color=colour,
                    linestyle=style.dash if numeric else "none", zorder=style.zorder, label=str(rows["variant"][0]))
            bars = [(xv, y, lo, hi) for xv, y, lo, hi in zip(xs, ys, rows["ci_low"].to_list(), rows["ci_high"].to_list())
                    if lo is not None and hi is not None]
            if bars:
                ax.errorbar([b[0] for b in bars], [b[1] for b in bars],
                            yerr=[[max(b[1] - b[2], 0.0) for b in bars], [max(b[3] - b[1], 0.0) for b in bars]],
                            fmt="none", ecolor=colour, elinewidth=1.2, capsize=3)
        if not numeric:
            ax.set_xticks(range(len(categories)), categories, rotation=20 if len(categories) > 3 else 0,
                          ha="right" if len(categories) > 3 else "center")
        elif len(ticks) <= 12:           # the swept values themselves (seeds 1, 2; not 1.2, 1.4, ...)
            ax.set_xticks(ticks, [format_value(v) for v in ticks])
        if name:
            ax.set_title(name, fontsize=9)
        ax.set_xlabel(x)
        ax.grid(True, alpha=0.3)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel(f"{series} [{unit}]" if unit else series)
    axes.flat[0].legend(fontsize=8)
    method = data["interval"].drop_nulls().unique().to_list() if "interval" in data.columns else []
    note = (f"bars: 95 % interval across Monte Carlo runs{' (' + ', '.join(map(str, method)) + ')' if method else ''}"
            if with_interval else "no interval in these summaries (no ci_low / ci_high)")
    if left_out:
        missing = "; ".join(left_out)
        note += f"\nnot drawn (no result): {missing if len(missing) <= 110 else missing[:109] + '…'}"
    fig.suptitle(f"{series}, window {window or NO_WINDOW + ' (whole run)'}, against {x}\n{note}", fontsize=10)
    from pipeline.views.figures import save_figure
    save_figure(fig, path)


def _unit(rows: pl.DataFrame, series: str) -> str:
    from pipeline.evaluation.metrics import axis_unit_of
    try:
        unit = axis_unit_of(series)
    except Exception:                # noqa: BLE001 - a study's metric its package registers on import
        unit = ""
    if not unit and "unit" in rows.columns and rows["unit"].drop_nulls().len():
        unit = rows["unit"].drop_nulls()[0]
    return unit


def draw_figures(sweep: Sweep, metric: str, window: str | None = None, x: str | None = None,
                 out: Path | None = None) -> list[Path]:
    """One PNG per swept key (or only ``x``) under ``out`` (default ``<sweep>/figures``):
    ``<series>_<window>_vs_<key>.png``."""
    from pipeline.views.colours import variant_colour
    from pipeline.views.recording import path_part

    if not sweep.swept:
        raise SweepError(f"the jobs of {sweep.folder} share all their overrides, so nothing was swept to plot "
                         f"against (a sweep's jobs differ in at least one override: -m key=a,b)")
    keys = [x] if x is not None else list(sweep.swept)
    select_metric(sweep.summary, metric, window)          # an unknown metric or window: one error, before any figure
    colours = {key: variant_colour(i) for i, key in enumerate(variant_order(sweep.summary))}
    out = Path(out) if out is not None else sweep.folder / "figures"
    finished = set(sweep.summary.filter(pl.col("status") == "ok")["job"].to_list()) if "status" in sweep.summary.columns else set()
    left_out = [job.label for job in sweep.jobs if job.label not in finished]
    paths = []
    for key in keys:
        data, series, chosen = metric_against(sweep, metric, window, key)
        path = out / f"{path_part(series)}_{path_part(chosen or 'whole_run')}_vs_{path_part(key)}.png"
        draw_metric_figure(data, x=key, series=series, window=chosen, unit=_unit(sweep.summary.filter(
            pl.col("series") == series), series), path=path, colours=colours, left_out=left_out)
        paths.append(path)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.sweep",
                                     description="Figures of a summary metric against each swept parameter of a sweep.")
    parser.add_argument("sweep_dir", type=Path, help="a sweep folder (artifacts/multirun/<time>)")
    parser.add_argument("--metric", required=True, help="a summary series (position_rmse, acceleration_rmse_x, nees, ...)")
    parser.add_argument("--window", help=f"a summary window (default: all, or the metric's only one; "
                                         f"{NO_WINDOW!r}: a window-free value such as compute_seconds)")
    parser.add_argument("--x", help="only this swept key (default: one figure per swept key)")
    parser.add_argument("--out", type=Path, help="folder for the PNGs (default: <sweep_dir>/figures)")
    args = parser.parse_args(argv)
    try:
        if not args.sweep_dir.is_dir():
            raise SweepError(f"{args.sweep_dir}: no such folder; pass a sweep folder (artifacts/multirun/<time>)")
        sweep = collect(args.sweep_dir)
        if not sweep.jobs:
            raise SweepError(f"{args.sweep_dir}: no job folder (<job>/status.json) under it; pass a sweep folder "
                             f"(artifacts/multirun/<time>)")
        paths = draw_figures(sweep, args.metric, args.window, args.x, args.out)
    except SweepError as exc:
        print(f"sweep: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
