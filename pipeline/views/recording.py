"""The parts every Rerun recording (``.rrd``) shares: the entity tree below, colour keys, frames, ellipses,
the metrics' time series, the config page and an atomic write. The default study's recording is in
pipeline.views.single_target (2-D) and pipeline.views.single_target_3d; the studies' own are in
their packages.

Layout of the entity tree (``r`` = a recorded Monte Carlo run, ``v`` = a variant key)::

    /world/run{r}/truth                   static whole trajectory (faint: the future) + current true position
    /world/run{r}/truth/path              a segment per step (the views show them up to the time cursor)
    /world/run{r}/measurements            detections of the current scan (clutter coloured apart)
    /world/run{r}/measurements/all        every scan's detections, faint (shown up to the cursor)
    /world/run{r}/{v}/track               estimated trajectory: a segment per step (up to the cursor)
    /world/run{r}/{v}/estimate            current estimate
    /world/run{r}/{v}/covariance          current 2-sigma position ellipse (polyline)
    /variants/{v}/run{r}/mode_probability/{model}
    /variants/{v}/run{r}/active_group     1-based group number (M1 = 1)
    /variants/{v}/run{r}/candidate_group  1-based, 0 while no union runs
    /variants/{v}/run{r}/events           text log of group-set changes
    /metrics/{metric}/{v}                 Monte Carlo average per step
    /config                               markdown: description + config yaml
    /key/variants, /key/models            colour keys: labelled points in the variants' (and the
                                          models') colours; the plots have no legends
    /world/frames/...                     named frames the 2-D views look from: "north_up" (y up;
                                          Rerun draws 2-D y downwards) and "target_run{r}" (that
                                          run's true target position, y up) for the zoomed views

A truth with a ``z`` state (study 000: 9 states x, y, z, vx, ..., az; a radar whose detections are
range, azimuth, elevation, or already x, y, z) is recorded in 3-D instead, z up::

    /world/radar                          static marker at the sensor position
    /world/run{r}/truth                   static LineStrips3D (faint) + current Points3D; /path segments
    /world/run{r}/measurements            the scan's detections converted to Cartesian (Points3D)
    /world/run{r}/measurements/all        every scan's detections, faint (shown up to the cursor)
    /world/run{r}/{v}/track               LineStrips3D segment per step (shown up to the cursor)
    /world/run{r}/{v}/estimate            Points3D per step
    /world/run{r}/{v}/covariance          Ellipsoids3D per step: 2-sigma of the position block
    /world/run{r}/{v}/detections          maneuver detections: TextLog line + Points3D marker at the
                                          estimate, at the detection step only (cleared the step after)
    /world/run{r}/{v}/detections/all      every detection's estimate (shown up to the cursor)
    /world/run{r}/{v}/detections/{x,y,z}  per LOS axis (variants with maneuver_detected_axis): an
                                          Arrows3D from the estimate along that LOS axis
    /variants/{v}/run{r}/input_level/{x,y,z}, /variants/{v}/run{r}/test_statistic[/{x,y,z}]
    /truth/run{r}/acceleration/{x,y,z}    the true acceleration, reference for the input level
    /truth/run{r}/maneuver[s]             maneuver class of the truth (state at each change; log lines)
    /metrics/{metric}/{v}, /config, /world/frames/target_run{r} (no flip: 3-D views keep z up)

Every time-varying entity has the timelines ``time`` (duration, s) and ``step`` (sequence) and is
written with one ``send_columns`` call; only static things use ``log``. Rerun is imported lazily.

What the viewer shows (issue 19): paths and tracks up to the time cursor (per-entity visible time
ranges, pipeline.views.blueprints), the rest of the true trajectory faint; one colour per variant
(pipeline.views.colours, shared with the report and sweep figures) and colour keys instead of legends;
titles fitted to their views on a 1600 x 900 window; the mode probabilities of every variant side by
side. The colours, the widths that keep coinciding lines visible and the keys are in pipeline.views.colours
and pipeline.views.blueprints.
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from pipeline.views.blueprints import (log_key, no_legend)
from pipeline.views.colours import lighter as lighter_colour, model_colour, rerun_widths, variant_colour
from pipeline.errors import StorageError
from pipeline.storage.store import atomic_write_bytes

if TYPE_CHECKING:  # pragma: no cover
    pass

APPLICATION_ID = "mtt"
ELLIPSE_POINTS = 48
ELLIPSE_SIGMA = 2.0
SPATIAL_METRICS = ("acceleration_rmse_x", "acceleration_rmse_y", "position_rmse")
# a metric view is titled "<name> [<axis unit>]" from the metric registry (pipeline.evaluation.metrics)

# One colour per variant, in display order, used in every view (tracks, estimates, metric lines) and
# in the report and sweep figures: pipeline.views.colours (variant_colour, TRUTH_COLOUR, lighter_colour and
# model_colour are imported from there).
MEASUREMENT_COLOUR = (170, 170, 170)
CLUTTER_COLOUR = (220, 70, 70)
MEASUREMENT_FAINT = (95, 95, 95)
CLUTTER_FAINT = (120, 50, 50)
FRAMES_PATH = "/world/frames"
NORTH_UP_FRAME = "north_up"
PATH_SAFE = re.compile(r"^[A-Za-z0-9_.-]+$")
FUTURE_ALPHA = 70                 # the whole true trajectory (where the target goes next), faint
VARIANT_KEY = "/key/variants"     # colour keys (pipeline.views.blueprints.log_key)
MODEL_KEY = "/key/models"
LEGEND_MAX = 5                    # a view of more lines than this gets no legend (a key names them)
ENCODE_TIMEOUT_S = 300.0          # backstop for encoding the recording in memory (atomic_recording)


def checked_record_runs(record_runs, runs: int) -> list[int]:
    """record.runs as ints, each in 0..runs-1 and listed once; a ValueError naming the key otherwise."""
    chosen = [int(r) for r in record_runs]
    bad = [r for r in chosen if not 0 <= r < runs]
    if bad:
        raise ValueError(f"record.runs: {bad} out of range; the experiment has {runs} runs, "
                         f"so each recorded run must be in 0..{runs - 1}")
    if len(set(chosen)) != len(chosen):
        raise ValueError(f"record.runs: {chosen} lists a run twice")
    return chosen


def log_north_up(rr, rec) -> None:
    """The "north_up" frame the 2-D views look from: Rerun draws 2-D y downwards (image
    convention), so the frame flips y and north is up."""
    rec.log(f"{FRAMES_PATH}/north_up", rr.Transform3D(scale=np.array([1.0, -1.0, 1.0]), parent_frame="tf#/world",
                                                  child_frame=NORTH_UP_FRAME), static=True)


def recording_id(experiment: str) -> str:
    """The experiment name reduced to ``[A-Za-z0-9_-]`` (Rerun's catalog dislikes anything else)."""
    rid = re.sub(r"[^A-Za-z0-9_-]+", "_", experiment).strip("_")
    return rid or "experiment"


def target_frame(run: int) -> str:
    """Named transform frame centred on run ``run``'s true target position, y (north) up."""
    return f"target_run{run}"


def xy_index(names: Sequence[str], what: str) -> list[int]:
    missing = [c for c in ("x", "y") if c not in names]
    if missing:
        raise ValueError(f"{what}: state_names {list(names)} lack {missing}; the recording plots (x, y)")
    return [list(names).index("x"), list(names).index("y")]


def covariance_ellipses(mean: np.ndarray, cov: np.ndarray, n_sigma: float = ELLIPSE_SIGMA,
              points: int = ELLIPSE_POINTS) -> np.ndarray:
    """(N, 2) means and (N, 2, 2) covariances -> (N, points, 2) closed n-sigma ellipse polylines."""
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    w, V = np.linalg.eigh(sym)
    scale = V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]             # columns: axes of the ellipse
    angle = np.linspace(0.0, 2.0 * np.pi, points)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1)          # (points, 2), first == last
    return mean[:, None, :] + n_sigma * np.einsum("pj,nij->npi", circle, scale)


def track_radius(keys: Sequence[str]) -> dict[str, float]:
    """key -> track line radius [ui points], by path order like the metric lines (pipeline.views.colours):
    where several variants' tracks share a view and coincide, each stays visible."""
    return {key: round(0.3 + 0.4 * w, 3) for key, w in rerun_widths(list(keys)).items()}


def log_keys(rr, rec, variant_keys: Sequence[str], display: Mapping[str, str], colours: Mapping[str, Sequence[int]],
             models: Sequence[str] | None = None, extra: Sequence[tuple[str, Sequence[int]]] = ()) -> None:
    """The colour keys the blueprint shows instead of legends: the variants (+ ``extra`` entries)
    at /key/variants and, when every variant runs the same models, the models at /key/models."""
    log_key(rr, rec, VARIANT_KEY, [(display[k], colours[k]) for k in variant_keys] + list(extra))
    if models:
        log_key(rr, rec, MODEL_KEY, [(str(m), model_colour(i, len(models))) for i, m in enumerate(models)])


def time_columns(rr):
    """times(t, steps) -> the ``time`` (duration, s) and ``step`` (sequence) index columns."""
    def times(t: np.ndarray, steps: np.ndarray) -> list:
        return [rr.TimeColumn("time", duration=np.asarray(t, dtype=np.float64)),
                rr.TimeColumn("step", sequence=np.asarray(steps, dtype=np.int64))]
    return times


@contextmanager
def atomic_recording(rr, path: Path, experiment: str, blueprint,
                     skip_hint: str = "the tables were written before the recording; record.enabled=false skips it"):
    """A recording stream whose encoded bytes are written onto ``path`` atomically when the body ends;
    on any error nothing is left under ``path`` and no temp file stays behind.

    Rerun's file sink (``rec.save``) writes from its own thread, out of Python's sight: when a write
    fails (full disk, ``ulimit -f``), ``flush()`` either blocked forever, raised "File-writer thread
    shut down prematurely" without the OS error, or the job ended ok with a truncated file (issue 16
    item 7). So Rerun only encodes into memory here (``binary_stream``, read once: a ``read`` closes
    the stream with its footer, so several reads would not make one valid file), and Python writes
    the bytes through the tables' atomic writer, where an ``OSError`` surfaces. The price is the
    encoded recording held in memory once (measured 1.4-22 MB per recorded run, sonar_case2 largest).
    """
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(experiment))
    try:
        rec.set_log_time_enabled(False)
        stream = rec.binary_stream()
        rec.send_blueprint(blueprint, make_active=False, make_default=True)   # what save(default_blueprint=) sends
        yield rec
        # encoding only, no disk I/O; the timeout is a backstop so that nothing here can block forever
        data = stream.read(flush=True, flush_timeout_sec=ENCODE_TIMEOUT_S) or b""
    finally:
        rec.disconnect()
    try:
        atomic_write_bytes(data, path)     # an OSError comes back as a StorageError naming the path and the fix
    except StorageError as exc:
        raise StorageError(f"{exc} Nothing was left under that name; {skip_hint}.") from None


def log_metric_series(rr, rec, times, metric_series: dict, metric_widths: Mapping[str, float] | None = None) -> None:
    """Each metric under /metrics/<metric>/<variant>; a consistency band (``<m>_lower`` /
    ``<m>_upper``, evaluate.consistency_metrics) goes beside its metric, /metrics/<m>/<variant>_chi2_lower,
    as a thin line in the variant's lighter colour, so the NEES view shows each variant with its band.
    Each variant's line has its width (pipeline.views.colours.rerun_widths: the first key in path order,
    drawn first, widest), so coinciding curves stay visible; ``metric_widths`` fixes the width of
    some metrics' lines instead (e.g. study 004's mean mode probabilities, one view per variant)."""
    metrics = {m for m, _ in metric_series}
    widths = rerun_widths(list(dict.fromkeys(key for _, key in metric_series)))
    for (metric, key), series in metric_series.items():
        steps, t, values, name, colour = series
        base, _, side = str(metric).rpartition("_")
        if side in ("lower", "upper") and base in metrics:
            entity = f"/metrics/{path_part(base)}/{key}_chi2_{side}"
            style = rr.SeriesLines(names=f"{name}: χ² 95 % {side}", colors=lighter_colour(colour, 0.5), widths=1.0)
        else:
            entity = f"/metrics/{path_part(metric)}/{key}"
            style = rr.SeriesLines(names=name, colors=colour, widths=(metric_widths or {}).get(metric, widths[key]))
        rec.log(entity, style, static=True)
        rec.send_columns(entity, indexes=times(t, steps), columns=rr.Scalars.columns(scalars=values))


def log_config(rr, rec, experiment: str, description: str, config_text: str, record_runs: list[int],
                runs: int) -> None:
    doc = f"# {experiment}\n\n"
    if description:
        doc += f"{description.strip()}\n\n"
    doc += f"Recorded runs: {', '.join(map(str, record_runs))} of {runs}.\n\n"
    if config_text:
        doc += f"```yaml\n{config_text.rstrip()}\n```\n"
    rec.log("/config", rr.TextDocument(doc, media_type=rr.MediaType.MARKDOWN), static=True)


def path_part(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(name))


# how far from the limit: consistency (NEES, NIS with their chi-square bands) and RMSE over the PCRLB
LIMIT_VIEWS = (("nees", "NEES (line: run average; thin: its χ² 95 % band)"),
               ("nis", "NIS (line: run average; thin: its χ² 95 % band)"),
               ("position_rmse_over_bound", "position RMSE / sqrt(PCRLB) (1 = at the bound)"),
               ("position_bound", "sqrt(PCRLB) of the position [m]"))


def limit_views(rrb, present: set, whole_run) -> list:
    """One view per limit metric the run has, each variant's line beside its band (no legend: the
    variants' key names the colours, the title the thin band lines)."""
    return [rrb.TimeSeriesView(origin=f"/metrics/{metric}", name=name, axis_x=whole_run, plot_legend=no_legend(rrb))
            for metric, name in LIMIT_VIEWS if metric in present]


def metric_time_series(metrics, experiment: str, variant_keys: list[str], display: Mapping[str, str],
                   colours: dict) -> dict:
    """(metric, variant_key) -> (steps, time, values, display name, colour), finite values only, in
    metric order of appearance and display order of variants (variants only in the frame come last)."""
    if metrics is None or metrics.height == 0:
        return {}
    import polars as pl

    required = {"variant_key", "series", "step", "time", "value"}
    missing = required - set(metrics.columns)
    if missing:
        raise ValueError(f"metrics frame lacks columns {sorted(missing)}; it has {metrics.columns}")
    if "experiment" in metrics.columns and metrics["experiment"].n_unique() > 1:
        metrics = metrics.filter(pl.col("experiment") == experiment)
    dupes = metrics.group_by("variant_key", "series", "step").len().filter(pl.col("len") > 1)
    if dupes.height:
        raise ValueError(f"metrics frame has {dupes.height} duplicate (variant_key, metric, step) rows, "
                         f"e.g. {dupes.row(0, named=True)}; pass one experiment's Monte Carlo averages")
    keys = list(variant_keys) + [k for k in metrics["variant_key"].unique(maintain_order=True).to_list()
                                 if k not in variant_keys]
    for i, key in enumerate(keys):
        colours.setdefault(key, variant_colour(i))
    out: dict = {}
    for metric in metrics["series"].unique(maintain_order=True).to_list():
        part = metrics.filter(pl.col("series") == metric)
        for key in keys:
            rows = part.filter(pl.col("variant_key") == key).sort("step")
            if rows.height == 0:
                continue
            if not PATH_SAFE.match(str(key)):
                raise ValueError(f"metrics: variant_key {key!r} is not path-safe")
            values = rows["value"].cast(pl.Float64).to_numpy()
            keep = np.isfinite(values)
            if not keep.any():
                continue
            name = display.get(key) or (rows["variant"][0] if "variant" in rows.columns else key)
            out[(metric, key)] = (rows["step"].to_numpy().astype(np.int64)[keep],
                                  rows["time"].cast(pl.Float64).to_numpy()[keep], values[keep], str(name),
                                  colours[key])
    return out


