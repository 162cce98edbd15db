"""One Rerun recording per sweep (``<sweep_dir>/sweep.rrd``): every job's per-step metric curves
side by side, each job named by its swept values.

Layout of the entity tree (``j`` = a job's label, ``t1_mu=0.8, runs=20``, escaped as one entity
path part; ``v`` = a variant key)::

    /metrics/{series}/{j}/{v}     the job's Monte Carlo average per step (its metrics.parquet)
    /sweep                        markdown: the jobs with their swept values and status

The stored blueprint has one time-series view per metric (``DEFAULT_SERIES`` that the jobs have,
or all of them when they have few) with every job's and variant's line, and the jobs table beside.
A variant keeps its colour and line width from the run recordings (pipeline.views.colours, in the
sweep's variant order); its jobs are shades of it, the first job the full colour and later ones
lighter, so a line's hue says the variant and its shade the job. The χ² bands (``*_lower`` /
``*_upper``) stay in the run recordings: with jobs of different run counts one view would hold
several bands per variant.

Timelines ``time`` (duration, s) and ``step`` (sequence), as the run recordings; one
``send_columns`` call per line. Encoded in memory and written atomically (temp + rename) like the
run recordings (pipeline.views.recording.atomic_recording).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.results.sweep import Sweep, format_value, variant_order

log = logging.getLogger("pipeline.views.sweep_recording")

SWEEP_RECORDING = "sweep.rrd"
# the metrics a sweep is usually compared on, in view order; a sweep whose jobs have at most
# MAX_ALL_SERIES (non-band) series gets a view for each instead
DEFAULT_SERIES = ("position_rmse", "velocity_rmse", "acceleration_rmse", "acceleration_rmse_x", "acceleration_rmse_y",
                  "nees", "nis")
MAX_ALL_SERIES = 6
LIGHTEST_SHADE = 0.6            # the last job's line: this far from the variant's colour towards white


# what a line needs of a job's metrics table; the names as categories: a paper-size sweep's tables,
# read whole, held ~500 MB at once (study 003's 600 060 rows each, mostly provenance strings)
LINE_COLUMNS = {"series": pl.Categorical, "variant_key": pl.Categorical, "variant": pl.Categorical,
                "step": None, "time": None, "value": None}


def job_metrics(sweep: Sweep) -> dict[str, pl.DataFrame]:
    """Job label -> the columns of its metrics.parquet that a line draws (``LINE_COLUMNS``; the table
    checksum verified whole), for the finished jobs; a job whose table is missing or damaged is left
    out with a warning, as in the sweep summary."""
    from pipeline.storage.store import read_table

    out = {}
    for job in sweep.jobs:
        path = job.folder / "metrics.parquet"
        if job.status.get("status") != "ok" or not path.is_file():
            continue
        try:
            frame = read_table(path)[0]
        except Exception as exc:  # noqa: BLE001 - damaged (checksum) or unreadable: this job's lines are left out, named
            log.warning("skipped %s: %s", path, exc)
            continue
        out[job.label] = frame.select([pl.col(name) if dtype is None else pl.col(name).cast(dtype)
                                       for name, dtype in LINE_COLUMNS.items() if name in frame.columns])
        del frame
    return out


def is_band(series: str, names: set[str]) -> bool:
    base, _, side = series.rpartition("_")
    return side in ("lower", "upper") and base in names


def chosen_series(metrics: dict[str, pl.DataFrame]) -> list[str]:
    """The series that get a view: all the jobs' (non-band) series when there are few, else those of
    DEFAULT_SERIES the jobs have, else the first MAX_ALL_SERIES in the jobs' order."""
    names: list[str] = []
    for frame in metrics.values():
        names += [s for s in frame["series"].unique(maintain_order=True).to_list() if s not in names]
    present = set(names)
    names = [s for s in names if not is_band(s, present)]
    if len(names) <= MAX_ALL_SERIES:
        return names
    preferred = [s for s in DEFAULT_SERIES if s in present]
    return preferred or names[:MAX_ALL_SERIES]


def sweep_lines(sweep: Sweep, metrics: dict[str, pl.DataFrame], series: list[str]) -> list[dict]:
    """One line per (series, job, variant) with finite values: entity path, display name, colour,
    steps, time, values; in view order, then job order, then variant order."""
    import rerun as rr
    from pipeline.views.colours import lighter as lighter_colour, rerun_widths, variant_colour

    order = variant_order(sweep.summary)       # as the sweep's figures colour them
    for frame in metrics.values():
        order += [k for k in frame["variant_key"].unique(maintain_order=True).to_list() if k not in order]
    colours = {key: variant_colour(i) for i, key in enumerate(order)}
    widths = rerun_widths(order)              # as in the run recordings: coinciding lines stay visible
    labels = [j.label for j in sweep.jobs if j.label in metrics]
    lines = []
    for name in series:
        for n, label in enumerate(labels):
            shade = LIGHTEST_SHADE * n / (len(labels) - 1) if len(labels) > 1 else 0.0
            part = metrics[label].filter(pl.col("series") == name)
            for key in order:
                rows = part.filter(pl.col("variant_key") == key).sort("step")
                values = rows["value"].cast(pl.Float64).to_numpy()
                keep = np.isfinite(values)
                if not keep.any():
                    continue
                variant = rows["variant"][0] if "variant" in rows.columns else key
                entity = "/".join(["/metrics", *map(rr.escape_entity_path_part, (name, label, key))])
                lines.append({"entity": entity,
                              "series": name, "job": label, "variant_key": key, "name": f"{label} · {variant}",
                              "colour": lighter_colour(colours[key], shade), "width": widths[key],
                              "steps": rows["step"].to_numpy().astype(np.int64)[keep],
                              "time": rows["time"].cast(pl.Float64).to_numpy()[keep], "values": values[keep]})
    return lines


def jobs_markdown(sweep: Sweep) -> str:
    header = ["job"] + list(sweep.swept) + ["status", "folder"]
    lines = [f"### Jobs of sweep {sweep.folder.name}", "",
             "Each line is one job (named by its swept values) and variant: the variant's colour as in the run "
             "recordings, the job's shade from full (first job) to light (last).", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    errors = []
    for job in sweep.jobs:
        status = job.status.get("status") or "unknown"
        cells = [str(job.num)] + [format_value(job.values[k]) for k in sweep.swept] + [status, job.folder.name]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
        if status != "ok" and job.status.get("error"):   # below the table: a cell would cut it off
            errors.append(f"- job {job.num}: {' '.join(str(job.status['error']).split())}")
    return "\n".join(lines + ([""] + errors if errors else [])) + "\n"


def write_sweep_recording(sweep: Sweep, path: Path | None = None, series: list[str] | None = None) -> Path | None:
    """Write ``<sweep>/sweep.rrd`` (or ``path``); None (nothing written) when no job has metrics."""
    started = time.perf_counter()
    metrics = job_metrics(sweep)
    if not metrics:
        return None
    series = series if series is not None else chosen_series(metrics)

    import rerun as rr                 # lazily: ~0.6 s
    import rerun.blueprint as rrb
    from pipeline.evaluation.metrics import axis_unit_of
    from pipeline.views.recording import atomic_recording, time_columns

    lines = sweep_lines(sweep, metrics, series)
    whole_run = rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                      end=rrb.TimeRangeBoundary.infinite()))
    drawn = [s for s in series if any(line["series"] == s for line in lines)]
    views = []
    for name in drawn:
        try:
            unit = axis_unit_of(name)
        except Exception:              # noqa: BLE001 - a study's metric its package registers on import
            unit = ""
        views.append(rrb.TimeSeriesView(origin=f"/metrics/{rr.escape_entity_path_part(name)}",
                                        name=f"{name} [{unit}]" if unit else name, axis_x=whole_run,
                                        plot_legend=rrb.PlotLegend(corner="RightTop")))
    # one metric per tab, each view the whole height: a legend of jobs x variants entries in a grid of
    # small views covered half of each (screenshot of a 2-job sweep with six views)
    plots = rrb.Tabs(*views, active_tab=0) if views else rrb.Vertical()
    blueprint = rrb.Blueprint(
        rrb.Horizontal(plots, rrb.TextDocumentView(origin="/sweep", name="Jobs"), column_shares=[3.0, 1.0]),
        rrb.TimePanel(state="collapsed", timeline="time"),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
    path = Path(path) if path is not None else sweep.folder / SWEEP_RECORDING
    with atomic_recording(rr, path, f"sweep_{sweep.folder.name}", blueprint,
                          skip_hint="the sweep's tables were written before it") as rec:
        times = time_columns(rr)
        for line in lines:
            rec.log(line["entity"], rr.SeriesLines(names=line["name"], colors=line["colour"], widths=line["width"]),
                    static=True)
            rec.send_columns(line["entity"], indexes=times(line["time"], line["steps"]),
                             columns=rr.Scalars.columns(scalars=line["values"]))
        rec.log("/sweep", rr.TextDocument(jobs_markdown(sweep), media_type=rr.MediaType.MARKDOWN), static=True)
    log.info("sweep recording %s: %d lines (%d metrics x %d jobs), %.0f kB, %.2f s", path, len(lines), len(drawn),
             len(metrics), path.stat().st_size / 1e3, time.perf_counter() - started)
    return path
