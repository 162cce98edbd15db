"""Write one experiment's Rerun recording (``.rrd``): trajectories, estimates, mode probabilities,
model-group switching and the Monte Carlo metrics, with a side-by-side blueprint in the same file.

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
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from pipeline.evaluation.metrics import axis_unit_of
from pipeline.views.blueprints import (fit_title, fit_titles, key_view, legend_in_quiet_corner, log_key, log_path, no_legend,
    path_overrides, path_segments, whole_run, whole_run as whole_run_axis)
from pipeline.views.colours import TRUTH_COLOUR, lighter as lighter_colour, model_colour, rerun_widths, variant_colour
from pipeline.data import Detections, Truth
from pipeline.errors import StorageError
from pipeline.storage.store import atomic_write_bytes

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

APPLICATION_ID = "mtt"
ELLIPSE_POINTS = 48
ELLIPSE_SIGMA = 2.0
SPATIAL_METRICS = ("acceleration_rmse_x", "acceleration_rmse_y", "position_rmse")
# a metric view is titled "<name> [<axis unit>]" from the metric registry (pipeline.evaluation.metrics)

# One colour per variant, in display order, used in every view (tracks, estimates, metric lines) and
# in the report and sweep figures: pipeline.views.colours (variant_colour, TRUTH_COLOUR, lighter_colour and
# model_colour are imported from there).
_MEASUREMENT_COLOUR = (170, 170, 170)
_CLUTTER_COLOUR = (220, 70, 70)
_MEASUREMENT_FAINT = (95, 95, 95)
_CLUTTER_FAINT = (120, 50, 50)
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


def _events(active: np.ndarray, candidate: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """Steps where the running group set changes and a line for each ("M1 -> M1 + M2 (union)")."""
    def label(a: int, c: int) -> str:
        name = lambda g: names[g] if 0 <= g < len(names) else f"G{g + 1}"  # noqa: E731
        return name(a) if c < 0 else f"{name(a)} + {name(c)}"

    steps, lines = [], []
    previous: tuple[int, int] | None = None
    for k, (a, c) in enumerate(zip(active.tolist(), candidate.tolist())):
        if a < 0:
            continue
        now = (a, c)
        if previous is None:
            steps.append(k)
            lines.append(f"start: {label(a, c)}")
        elif now != previous:
            steps.append(k)
            lines.append(f"{label(*previous)} -> {label(a, c)}" + (" (union)" if c >= 0 else ""))
        previous = now
    return np.asarray(steps, dtype=np.int64), lines


def write_recording(path: Path, *, experiment: str, truth: Truth, detections: Detections,
                    estimates: Mapping[str, TrackEstimate], display_names: Mapping[str, str],
                    metrics: "pl.DataFrame | None", record_runs: Sequence[int],
                    model_names: Sequence[str] | Mapping[str, Sequence[str] | None] | None = None,
                    group_names: Sequence[str] | None = None,
                    config_text: str = "", description: str = "",
                    sensor_position: Sequence[float] = (0.0, 0.0, 0.0),
                    maneuver_names: Sequence[str] | None = None,
                    to_geodetic: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
    """Write ``path`` (an ``.rrd`` with its default blueprint) for the runs in ``record_runs``.

    3-D only: ``maneuver_names`` names the codes of a truth label ``maneuver`` (R, K, 1), drawn as a
    timeline (a class per scan and a log line at each change); ``to_geodetic`` maps (N, 3) positions
    of the truth's frame to (N, 2) latitude, longitude [deg], adding a map view of the truth, the
    tracks and the radar.

    ``estimates`` maps variant key (path-safe) -> estimate, in display order; ``metrics`` is the
    long metrics frame (variant, variant_key, metric, step, time, value, ...) or None. The file is
    written to a temporary name beside ``path`` and moved onto it only once complete.

    A truth with a ``z`` state is drawn in 3-D (see the module docstring); ``sensor_position`` is
    then where the radar sits (polar detections are relative to it). 2-D recordings ignore it.
    ``model_names`` labels the mode probabilities: one list for every variant, or a list (None:
    m1, m2, ...) per variant key, for variants whose IMMs run different model sets.
    """
    path = Path(path)
    R = truth.runs
    record_runs = checked_record_runs(record_runs, R)
    for key in estimates:
        if not PATH_SAFE.match(key):
            raise ValueError(f"variant key {key!r} is not path-safe (allowed: letters, digits, '_', '-', '.')")
    if detections.runs != R:
        raise ValueError(f"detections have {detections.runs} runs but the truth has {R}")
    for key, est in estimates.items():
        if est.state.shape[0] != R:
            raise ValueError(f"estimate {key!r} has {est.state.shape[0]} runs but the truth has {R}")
        n = len(truth.state_names)
        if est.state.shape[-1] != n:
            raise ValueError(f"estimate {key!r} has state size {est.state.shape[-1]}; the truth's state is "
                             f"{list(truth.state_names)} and estimates must use the same order")
        if est.covariance.shape != est.state.shape + (n,):
            raise ValueError(f"estimate {key!r}: covariance shape {est.covariance.shape} does not match "
                             f"state shape {est.state.shape} (expected {est.state.shape + (n,)})")
    variant_keys = list(estimates)
    colours = {key: variant_colour(i) for i, key in enumerate(variant_keys)}
    display = {key: str(display_names.get(key, key)) for key in variant_keys}
    if is_3d(truth):
        _write_recording_3d(path, experiment=experiment, truth=truth, detections=detections, estimates=estimates,
                            display=display, colours=colours, metrics=metrics, record_runs=record_runs,
                            config_text=config_text, description=description, sensor_position=sensor_position,
                            maneuver_names=maneuver_names, to_geodetic=to_geodetic)
        return
    truth_xy = xy_index(truth.state_names, "truth")
    meas_xy = xy_index(detections.measurement_names, "detections")

    metric_series = metric_time_series(metrics, experiment, variant_keys, display, colours)

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    blueprint = _blueprint(rrb, truth, truth_xy, record_runs, variant_keys, display, metric_series,
                           estimates, has_config=True,
                           noise_sigma=_noise_sigma(detections, meas_xy, record_runs[0] if record_runs else 0),
                           models=_shared_model_names(estimates, model_names))

    track_radii = track_radius(variant_keys)
    with atomic_recording(rr, path, experiment, blueprint) as rec:
        times = time_columns(rr)

        ui = rr.Radius.ui_points
        # Rerun's 2-D views draw y downwards (image convention). The views look at the data from
        # named frames whose y axis is flipped, so north is up: "north_up" for the whole scene and,
        # per recorded run, "target_run{r}" centred on the true target position at each step.
        flip = np.array([1.0, -1.0, 1.0])
        log_north_up(rr, rec)
        for r in record_runs:
            world = f"/world/run{r}"
            # ---- truth: the path up to now, the whole trajectory faint, the current position -------
            xy = truth.state[r][..., truth_xy]                                   # (K, T, 2)
            K, T = xy.shape[:2]
            strips = [xy[:, t][np.isfinite(xy[:, t]).all(-1)] for t in range(T)]
            rec.log(f"{world}/truth", rr.LineStrips2D(strips, colors=(*TRUTH_COLOUR, FUTURE_ALPHA), radii=ui(0.5),
                                                      draw_order=12.0), static=True)
            rec.log(f"{world}/truth", rr.Points2D.from_fields(colors=TRUTH_COLOUR, radii=ui(5.0),
                                                              draw_order=30.0), static=True)
            ok = np.isfinite(xy).all(-1)                                          # (K, T)
            log_path(rr, rec, times, f"{world}/truth/path", truth.time, np.arange(K), xy, ok,
                     colour=TRUTH_COLOUR, radius=0.9, draw_order=16.0)
            steps = np.nonzero(ok.any(-1))[0]
            rec.send_columns(f"{world}/truth", indexes=times(truth.time[steps], steps),
                             columns=rr.Points2D.columns(positions=xy[ok]).partition(ok[steps].sum(-1)))
            first = ok[:, 0]                                                      # follow target 0
            steps = np.nonzero(first)[0]
            if steps.size:
                rec.send_columns(
                    f"{FRAMES_PATH}/target_run{r}", indexes=times(truth.time[steps], steps),
                    columns=rr.Transform3D.columns(
                        translation=np.c_[xy[steps, 0], np.zeros(steps.size)], scale=np.tile(flip, (steps.size, 1)),
                        parent_frame=["tf#/world"] * steps.size, child_frame=[target_frame(r)] * steps.size))

            # ---- measurements of the current scan ---------------------------------------------
            z = detections.z[r][..., meas_xy]                                     # (K, D, 2)
            seen = detections.detected[r] & np.isfinite(z).all(-1)
            steps = np.nonzero(seen.any(-1))[0]
            clutter = detections.target[r] < 0
            cols = rr.Points2D.columns(
                positions=z[seen],
                colors=np.where(clutter[seen][:, None], _CLUTTER_COLOUR, _MEASUREMENT_COLOUR).astype(np.uint8),
            ).partition(seen[steps].sum(-1))
            rec.log(f"{world}/measurements", rr.Points2D.from_fields(radii=ui(3.0), draw_order=20.0), static=True)
            rec.send_columns(f"{world}/measurements", indexes=times(detections.time[steps], steps), columns=cols)
            # every scan's detections up to now, faint: the noise cloud around the tracks when zoomed in
            rec.log(f"{world}/measurements/all", rr.Points2D.from_fields(radii=ui(1.5), draw_order=5.0), static=True)
            rec.send_columns(f"{world}/measurements/all", indexes=times(detections.time[steps], steps),
                             columns=rr.Points2D.columns(
                                 positions=z[seen], colors=np.where(clutter[seen][:, None], _CLUTTER_FAINT,
                                                                    _MEASUREMENT_FAINT).astype(np.uint8),
                             ).partition(seen[steps].sum(-1)))

            # ---- per variant: track, estimate, covariance ellipse ------------------------------
            for key, est in estimates.items():
                colour = colours[key]
                base = f"{world}/{key}"
                pos = est.state[r][:, truth_xy]                                    # (K, 2)
                P = est.covariance[r][:, truth_xy][:, :, truth_xy]                 # (K, 2, 2)
                good = np.isfinite(pos).all(-1) & np.isfinite(P).all((-1, -2))
                steps = np.nonzero(good)[0]
                log_path(rr, rec, times, f"{base}/track", est.time, np.arange(est.time.size), pos, good,
                         colour=colour, radius=track_radii[key], draw_order=15.0)
                rec.log(f"{base}/estimate", rr.Points2D.from_fields(colors=colour, radii=ui(3.5),
                                                                    draw_order=40.0), static=True)
                rec.send_columns(f"{base}/estimate", indexes=times(est.time[steps], steps),
                                 columns=rr.Points2D.columns(positions=pos[good]))
                rec.log(f"{base}/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(1.0),
                                                                          draw_order=35.0), static=True)
                if steps.size:
                    rec.send_columns(f"{base}/covariance", indexes=times(est.time[steps], steps),
                                     columns=rr.LineStrips2D.columns(strips=covariance_ellipses(pos[good], P[good])))

                names = model_names.get(key) if isinstance(model_names, Mapping) else model_names
                _log_variant_run(rr, rec, times, key, r, est, names, group_names)

        log_metric_series(rr, rec, times, metric_series)
        log_keys(rr, rec, variant_keys, display, colours, _shared_model_names(estimates, model_names))
        log_config(rr, rec, experiment, description, config_text, record_runs, R)


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


def _shared_model_names(estimates: Mapping[str, TrackEstimate], model_names) -> list[str] | None:
    """The model names every variant with mode probabilities shares (their colours are then the same
    in every mode view and one key names them), or None."""
    names = []
    for key, est in estimates.items():
        if "mode_probabilities" not in est.extras:
            continue
        M = np.shape(est.extras["mode_probabilities"])[-1]
        mine = model_names.get(key) if isinstance(model_names, Mapping) else model_names
        names.append(tuple(mine) if mine is not None else tuple(f"m{i + 1}" for i in range(M)))
    return list(names[0]) if names and len(set(names)) == 1 else None


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


def _noise_sigma(detections: Detections, meas_xy: list[int], run: int) -> float:
    """Typical position-measurement standard deviation [m] of a run (median over its detections)."""
    cov = np.asarray(detections.noise_covariance)
    if cov.ndim != 5 or cov.shape[0] <= run:
        return float("nan")
    block = cov[run][..., meas_xy, :][..., meas_xy]                      # (K, D, 2, 2)
    var = 0.5 * (block[..., 0, 0] + block[..., 1, 1])
    var = var[detections.detected[run] & np.isfinite(var)]
    return float(np.sqrt(np.median(var))) if var.size else float("nan")


def path_part(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(name))


# how far from the limit: consistency (NEES, NIS with their chi-square bands) and RMSE over the PCRLB
LIMIT_VIEWS = (("nees", "NEES (line: run average; thin: its χ² 95 % band)"),
               ("nis", "NIS (line: run average; thin: its χ² 95 % band)"),
               ("position_rmse_over_bound", "position RMSE / sqrt(PCRLB) (1 = at the bound)"),
               ("position_bound", "sqrt(PCRLB) of the position [m]"))


def _limit_views(rrb, present: set, whole_run) -> list:
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


def _group_series(est: TrackEstimate, r: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(active, candidate) group indices of run r, or None when the estimator has no groups."""
    if "active_group" not in est.extras:
        return None
    active = np.asarray(est.extras["active_group"][r]).astype(np.int64)
    if (active < 0).all():
        return None   # e.g. FSIMM: all models, no group structure
    cand = est.extras.get("candidate_group")
    candidate = np.full_like(active, -1) if cand is None else np.asarray(cand[r]).astype(np.int64)
    return active, candidate


def _log_variant_run(rr, rec, times, key: str, r: int, est: TrackEstimate,
                     model_names: Sequence[str] | None, group_names: Sequence[str] | None) -> None:
    base = f"/variants/{key}/run{r}"
    t = est.time
    if "mode_probabilities" in est.extras:
        mu = np.asarray(est.extras["mode_probabilities"][r], dtype=np.float64)   # (K, M)
        M = mu.shape[-1]
        names = list(model_names) if model_names is not None else [f"m{i + 1}" for i in range(M)]
        if len(names) != M:
            raise ValueError(f"model_names: {len(names)} names for {M} mode probabilities of {key!r}")
        for i, name in enumerate(names):
            entity = f"{base}/mode_probability/{path_part(name)}"
            steps = np.nonzero(np.isfinite(mu[:, i]))[0]
            rec.log(entity, rr.SeriesLines(names=str(name), colors=model_colour(i, M), widths=1.5), static=True)
            rec.send_columns(entity, indexes=times(t[steps], steps), columns=rr.Scalars.columns(scalars=mu[steps, i]))
    groups = _group_series(est, r)
    if groups is None:
        return
    active, candidate = groups
    steps = np.nonzero(active >= 0)[0]
    rec.log(f"{base}/active_group", rr.SeriesLines(names="active group (M1 = 1)", colors=(240, 200, 40),
                                                   widths=2.5), static=True)
    rec.send_columns(f"{base}/active_group", indexes=times(t[steps], steps),
                     columns=rr.Scalars.columns(scalars=(active[steps] + 1).astype(np.float64)))
    rec.log(f"{base}/candidate_group", rr.SeriesLines(names="candidate group (0 = none)", colors=(90, 200, 250),
                                                      widths=1.5), static=True)
    rec.send_columns(f"{base}/candidate_group", indexes=times(t[steps], steps),
                     columns=rr.Scalars.columns(scalars=np.where(candidate[steps] >= 0, candidate[steps] + 1, 0)
                                                .astype(np.float64)))
    ev_steps, lines = _events(active, candidate, list(group_names) if group_names is not None else [])
    if lines:
        rec.send_columns(f"{base}/events", indexes=times(t[ev_steps], ev_steps),
                         columns=rr.TextLog.columns(text=lines, level=["INFO"] * len(lines)))


def _blueprint(rrb, truth: Truth, truth_xy: list[int], record_runs: list[int], variant_keys: list[str],
               display: Mapping[str, str], metric_series: dict, estimates: Mapping[str, TrackEstimate],
               has_config: bool, noise_sigma: float = float("nan"), models: Sequence[str] | None = None):
    """Top: per variant a target-centred 2-D view (truth, measurements, that variant), and one view of
    the whole trajectories with every variant; tracks and the true path drawn up to the time cursor
    (the rest of the true trajectory faint). Then the colour keys (variants; models when they share
    one set), the RMSE plots, the mode probabilities of every variant side by side, and tabs with
    the model groups (side by side), the limit views and the config. Plots have no legends (they
    covered the lines and were cut): the keys name the colours."""
    r0 = record_runs[0] if record_runs else None
    xy = truth.state[record_runs][..., truth_xy].reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(-1)]
    overview_bounds = None
    if xy.size:
        lo, hi = xy.min(0), xy.max(0)
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 100.0) * 1.1
        # in the north-up frame y is negated
        overview_bounds = rrb.VisualBounds2D(x_range=[centre[0] - half[0], centre[0] + half[0]],
                                             y_range=[-centre[1] - half[1], -centre[1] + half[1]])
    # Target-centred zoom: about ten measurement-noise sigmas either side, so single measurements,
    # the 2-sigma ellipses and the estimation errors are all visible (the track spans tens of km).
    follow_half = 200.0
    if np.isfinite(noise_sigma) and noise_sigma > 0:
        follow_half = float(np.clip(10.0 * noise_sigma, 20.0, 5000.0))
    follow_bounds = rrb.VisualBounds2D(x_range=[-follow_half, follow_half], y_range=[-follow_half, follow_half])
    axis = whole_run(rrb)
    n = len(variant_keys)

    rows, shares = [], []
    columns = []
    width = 1600.0 / (n + 1)
    titles = fit_titles(width, [[f"{display[k]} · run {r0}, target-centred", f"{display[k]} · run {r0}", display[k]]
                                for k in variant_keys])
    if r0 is not None:
        for key, title in zip(variant_keys, titles):
            world = f"/world/run{r0}"
            columns.append(rrb.Spatial2DView(
                origin="/world", name=title,
                contents=[f"{world}/truth/**", f"{world}/measurements/**", f"{world}/{key}/**"],
                overrides=path_overrides(rrb, [f"{world}/truth/path", f"{world}/measurements/all",
                                               f"{world}/{key}/track"]),
                spatial_information=rrb.SpatialInformation(target_frame=target_frame(r0)),
                visual_bounds=follow_bounds))
    everything, paths = [], []
    for r in record_runs:
        world = f"/world/run{r}"
        everything += [f"{world}/truth/**", f"{world}/measurements/**"] + [f"{world}/{k}/**" for k in variant_keys]
        paths += [f"{world}/truth/path", f"{world}/measurements/all"] + [f"{world}/{k}/track" for k in variant_keys]
    runs = f"runs {', '.join(map(str, record_runs))}" if len(record_runs) > 1 else f"run {r0}"
    columns.append(rrb.Spatial2DView(
        origin="/world", contents=everything, overrides=path_overrides(rrb, paths),
        name=fit_title(width, f"{runs}: whole trajectory, every variant", "whole trajectory", "overview"),
        spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME), visual_bounds=overview_bounds))
    rows.append(rrb.Horizontal(*columns))
    shares.append(4.8)

    labels = [display[k] for k in variant_keys]
    keys = [key_view(rrb, VARIANT_KEY, labels, name="variants")]
    key_shares = [sum(len(x) + 5 for x in labels)]
    if models and any("mode_probabilities" in est.extras for est in estimates.values()):
        keys.append(key_view(rrb, MODEL_KEY, list(models), name="models (mode probabilities)"))
        key_shares.append(sum(len(str(x)) + 5 for x in models))
    rows.append(rrb.Horizontal(*keys, column_shares=key_shares) if len(keys) > 1 else keys[0])
    shares.append(0.5)

    present = [m for m in SPATIAL_METRICS if any(mk == m for mk, _ in metric_series)]
    if present:
        rows.append(rrb.Horizontal(*[
            rrb.TimeSeriesView(origin=f"/metrics/{path_part(m)}", name=f"{m} [{axis_unit_of(m)}]",
                               axis_x=axis, plot_legend=no_legend(rrb))
            for m in present]))
        shares.append(2.3)

    modes = []
    if r0 is not None:
        with_modes = [k for k in variant_keys if "mode_probabilities" in estimates[k].extras]
        w = 1600.0 / max(len(with_modes), 1)
        for key in with_modes:
            M = np.shape(estimates[key].extras["mode_probabilities"])[-1]
            base = f"/variants/{key}/run{r0}/mode_probability"
            if models or M > LEGEND_MAX:
                legend = no_legend(rrb)
            else:
                mu = np.asarray(estimates[key].extras["mode_probabilities"][r0], dtype=np.float64)
                t = np.asarray(estimates[key].time, dtype=np.float64)
                legend = legend_in_quiet_corner(rrb, [(t, mu[:, i]) for i in range(M)], M, (0.0, 1.0))
            modes.append(rrb.TimeSeriesView(
                origin=base, axis_x=axis, axis_y=rrb.ScalarAxis(range=(0.0, 1.0)), plot_legend=legend,
                name=fit_title(w, f"{display[key]}: mode probabilities (run {r0})", f"{display[key]}: P(mode), run {r0}",
                               f"{display[key]}: P(mode)")))
    if modes:
        rows.append(rrb.Horizontal(*modes))
        shares.append(2.5)

    be = rrb.encodings
    event_columns = rrb.TextLogColumns(
        timeline_columns=[be.TimelineColumn("step"), be.TimelineColumn("time", visible=False)],
        text_log_columns=[be.TextLogColumn("Body"), be.TextLogColumn("EntityPath", visible=False),
                          be.TextLogColumn("LogLevel", visible=False)])
    tabs = []
    if r0 is not None:
        grouped = [k for k in variant_keys if _group_series(estimates[k], r0) is not None]
        w = 1600.0 / max(len(grouped), 1)
        parts = []
        for key in grouped:
            base = f"/variants/{key}/run{r0}"
            parts.append(rrb.Horizontal(
                rrb.TimeSeriesView(origin=base, contents=[f"{base}/active_group", f"{base}/candidate_group"],
                                   name=fit_title(w * 0.6, f"{display[key]}: group, active yellow, candidate blue",
                                                  f"{display[key]}: active / candidate group",
                                                  f"{display[key]}: groups"),
                                   axis_x=axis, plot_legend=no_legend(rrb)),
                rrb.TextLogView(origin=f"{base}/events", name=fit_title(w * 0.4, f"{display[key]}: group switches",
                                                                        "group switches", "switches"),
                                columns=event_columns),
                column_shares=[3.0, 2.0]))
        if parts:
            tabs.append(rrb.Horizontal(*parts, name="model groups (run %d)" % r0))
    tabs += _limit_views(rrb, {m for m, _ in metric_series}, axis)
    if has_config:
        tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    if tabs:
        rows.append(rrb.Tabs(*tabs, active_tab=0))
        shares.append(2.2)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


# ---------------------------------------------------------------------------------------------------
# 3-D (a truth with a "z" state, e.g. study 000: radar at the origin, polar detections)
# ---------------------------------------------------------------------------------------------------

AXES = ("x", "y", "z")
RMSE_METRICS_3D = ("position_rmse", "velocity_rmse", "acceleration_rmse")
# LOS x, y, z (arrows, per-axis statistics and counts): shades of the variant's own colour, x darkest
# (a variant keeps its one colour; red / green / blue would read as three other variants)
AXIS_SHADES = {"x": 0.0, "y": 0.35, "z": 0.6}
_RADAR_COLOUR = (255, 215, 0)
_DETECTION_COLOUR = (255, 235, 60)
_DETECTION_FAINT = (175, 160, 60)
_POLAR = ("range", "azimuth", "elevation")
_AXIS_METRIC = re.compile(r"^(?P<base>.+)_axis_(?P<axis>[xyz])$")


def is_3d(truth: Truth) -> bool:
    """A truth with a ``z`` state is recorded in 3-D."""
    return "z" in truth.state_names


def _xyz_index(names: Sequence[str], what: str, prefix: str = "") -> list[int]:
    wanted = [f"{prefix}{c}" for c in AXES]
    missing = [c for c in wanted if c not in names]
    if missing:
        raise ValueError(f"{what}: state_names {list(names)} lack {missing}; the 3-D recording plots (x, y, z)")
    return [list(names).index(c) for c in wanted]


def polar_to_cartesian(polar: np.ndarray, origin: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(..., 3) range, azimuth, elevation [m, rad] -> (..., 3) x, y, z; azimuth from +x toward +y,
    elevation from the x-y plane, relative to the sensor at ``origin``."""
    r, az, el = polar[..., 0], polar[..., 1], polar[..., 2]
    c = np.cos(el)
    return np.stack([r * c * np.cos(az), r * c * np.sin(az), r * np.sin(el)], axis=-1) + np.asarray(origin, float)


def _polar_jacobian(polar: np.ndarray) -> np.ndarray:
    """d(x, y, z)/d(range, azimuth, elevation), (..., 3, 3)."""
    r, az, el = polar[..., 0], polar[..., 1], polar[..., 2]
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    zero = np.zeros_like(r)
    return np.stack([np.stack([ce * ca, -r * ce * sa, -r * se * ca], -1),
                     np.stack([ce * sa, r * ce * ca, -r * se * sa], -1),
                     np.stack([se, zero, r * ce], -1)], -2)


def _measurements_xyz(detections: Detections, origin: Sequence[float]) -> tuple[np.ndarray, np.ndarray | None]:
    """Detections as Cartesian positions (R, K, D, 3), and their position covariance (R, K, D, 3, 3)
    where the detections carry one (converted through the Jacobian for polar ones), else None."""
    names = list(detections.measurement_names)
    z = np.asarray(detections.z, dtype=np.float64)
    cov = np.asarray(detections.noise_covariance, dtype=np.float64)
    cov_ok = cov.ndim == 5 and cov.shape[:3] == z.shape[:3]
    if all(c in names for c in AXES):
        idx = [names.index(c) for c in AXES]
        return z[..., idx], (cov[..., idx, :][..., idx] if cov_ok else None)
    if all(c in names for c in _POLAR):
        idx = [names.index(c) for c in _POLAR]
        polar = z[..., idx]
        if not cov_ok:
            return polar_to_cartesian(polar, origin), None
        J = _polar_jacobian(polar)
        Rp = cov[..., idx, :][..., idx]
        return polar_to_cartesian(polar, origin), J @ Rp @ np.swapaxes(J, -1, -2)
    raise ValueError(f"detections: measurement_names {names} are neither (x, y, z) nor (range, azimuth, "
                     f"elevation); the 3-D recording cannot place them")


def _noise_sigma_3d(cov: np.ndarray | None, detected: np.ndarray) -> float:
    """Typical (rms over the three axes) Cartesian measurement standard deviation [m] of one run."""
    if cov is None:
        return float("nan")
    var = np.trace(cov, axis1=-2, axis2=-1) / 3.0                           # (K, D)
    var = var[detected & np.isfinite(var)]
    return float(np.sqrt(np.median(var))) if var.size else float("nan")


def ellipsoids(cov: np.ndarray, n_sigma: float = ELLIPSE_SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) covariances -> (N, 3) half sizes n_sigma*sqrt(eigenvalues) and (N, 4) rotations as
    xyzw quaternions (scipy's order, = rr.Quaternion(xyzw=...)) turning local axis i onto eigenvector i."""
    from scipy.spatial.transform import Rotation

    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    w, V = np.linalg.eigh(sym)
    V = V.copy()
    V[np.linalg.det(V) < 0, :, 0] *= -1.0                                  # proper rotation: det +1
    return n_sigma * np.sqrt(np.clip(w, 0.0, None)), Rotation.from_matrix(V).as_quat()


def _los_axes(position: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N, 3) positions -> (N, 3, 3) rows: unit LOS (range), cross-range (azimuth), elevation axes
    seen from the sensor at ``origin`` (the frame of seed 000, notes 2.2)."""
    d = position - origin
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    zero = np.zeros_like(az)
    return np.stack([np.stack([ca * ce, sa * ce, se], -1), np.stack([-sa, ca, zero], -1),
                     np.stack([-ca * se, -sa * se, ce], -1)], -2)


def _fmt(value: float) -> str:
    return "n/a" if not np.isfinite(value) else f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def _detection_events(est: TrackEstimate, r: int) -> dict | None:
    """Maneuver detections of run r: steps (with a finite estimate), per-axis flags, text lines.
    None when the variant reports no detections at all (no ``maneuver_detected*`` extras)."""
    extras = est.extras
    if "maneuver_detected" not in extras and "maneuver_detected_axis" not in extras:
        return None
    axis = extras.get("maneuver_detected_axis")
    axis = None if axis is None else np.asarray(axis[r]).astype(bool)          # (K, 3)
    if "maneuver_detected" in extras:
        flag = np.asarray(extras["maneuver_detected"][r]).astype(bool)          # (K,)
        if axis is not None:
            flag = flag | axis.any(-1)
    else:
        flag = axis.any(-1)
    flag &= np.isfinite(est.state[r]).all(-1)
    steps = np.nonzero(flag)[0]
    onset = extras.get("onset_step")
    stat = extras.get("test_statistic")
    lines = []
    for k in steps.tolist():
        what = "maneuver detected"
        if axis is not None:
            on = [a for a, hit in zip(AXES, axis[k]) if hit]
            what += f" on LOS {', '.join(on)}" if on else ""
        if onset is not None:
            n = int(np.asarray(onset[r])[k].max()) if np.ndim(onset[r]) > 1 else int(np.asarray(onset[r])[k])
            what += f", onset n = {n}" if n >= 0 else ", onset n = ?"
        if stat is not None:
            s = np.asarray(stat[r], dtype=np.float64)[k]
            what += ", statistic " + (_fmt(float(s)) if np.ndim(s) == 0 else
                                      "(" + ", ".join(f"{a} {_fmt(float(v))}" for a, v in zip(AXES, s)) + ")")
        lines.append(what)
    return {"steps": steps, "axis": axis, "lines": lines}


def _styled_3d_metric_series(metric_series: dict) -> dict:
    """Per-axis counts of one variant (``detections_axis_x`` ...) are drawn in one view: give each
    axis its own name and shade of the variant's colour."""
    out = {}
    for (metric, key), (steps, t, values, name, colour) in metric_series.items():
        m = _AXIS_METRIC.match(str(metric))
        if m:
            shade = AXIS_SHADES[m["axis"]]
            name, colour = f"{name} · LOS {m['axis']}", lighter_colour(colour, shade)
        out[(metric, key)] = (steps, t, values, name, colour)
    return out


def log_maneuvers(rr, rec, times, r: int, t: np.ndarray, codes: np.ndarray, names: Sequence[str]) -> None:
    """A truth's maneuver class per scan on the timeline as a state (/truth/run<r>/maneuver: the
    class's name at each change, drawn by a state-timeline view) and a log line where it changes
    (/truth/run<r>/maneuvers)."""
    codes = np.asarray(codes).astype(np.int64)
    labels = [str(name).replace("_", " / ") for name in names]
    greys = [(70 + int(120 * i / max(len(names) - 1, 1)),) * 3 for i in range(len(names))]
    rec.log(f"/truth/run{r}/maneuver", rr.StateConfiguration(values=labels, labels=labels, colors=greys), static=True)
    changes = np.nonzero(np.diff(codes, prepend=-1))[0]
    rec.send_columns(f"/truth/run{r}/maneuver", indexes=times(t[changes], changes),
                     columns=rr.StateChange.columns(state=[labels[codes[k]] for k in changes]))
    lines = [f"{labels[codes[k]]} from t = {t[k]:.0f} s" for k in changes]
    rec.send_columns(f"/truth/run{r}/maneuvers", indexes=times(t[changes], changes),
                     columns=rr.TextLog.columns(text=lines, level=["INFO"] * len(lines)))


def log_map(rr, rec, times, ui, r: int, t: np.ndarray, truth_xyz: np.ndarray, origin: np.ndarray,
            to_geodetic: Callable[[np.ndarray], np.ndarray], tracks: Mapping[str, np.ndarray],
            colours: Mapping[str, Sequence[int]], display: Mapping[str, str]) -> None:
    """Run r on a map (/map/run<r>/...): the truth and each track as geographic lines (a segment per
    step at ``<name>/path``, shown up to the time cursor) and their current points, the radar as a
    point. ``to_geodetic``: (N, 3) -> (N, 2) latitude, longitude."""
    rec.log("/map/radar", rr.GeoPoints(lat_lon=to_geodetic(origin[None]), radii=ui(6.0), colors=_RADAR_COLOUR),
            static=True)
    for name, xyz, colour in [("truth", truth_xyz, TRUTH_COLOUR)] + \
            [(key, tracks[key], colours[key]) for key in tracks]:
        ok = np.isfinite(xyz).all(-1)
        if not ok.any():
            continue
        lat_lon = to_geodetic(xyz[ok])
        entity = f"/map/run{r}/{name}"
        steps = np.nonzero(ok)[0]
        geo = np.full(xyz.shape[:-1] + (2,), np.nan)
        geo[ok] = lat_lon
        rows, counts, segments = path_segments(geo)
        rec.log(f"{entity}/path", rr.GeoLineStrings.from_fields(radii=ui(1.0), colors=colour), static=True)
        if rows.size:
            rec.send_columns(f"{entity}/path", indexes=times(t[rows], rows),
                             columns=rr.GeoLineStrings.columns(line_strings=segments).partition(counts))
        rec.log(entity, rr.GeoPoints.from_fields(radii=ui(5.0), colors=colour), static=True)
        rec.send_columns(entity, indexes=times(t[steps], steps), columns=rr.GeoPoints.columns(positions=lat_lon))


def _write_recording_3d(path: Path, *, experiment: str, truth: Truth, detections: Detections,
                        estimates: Mapping[str, TrackEstimate], display: dict, colours: dict, metrics,
                        record_runs: list[int], config_text: str, description: str,
                        sensor_position: Sequence[float], maneuver_names: Sequence[str] | None = None,
                        to_geodetic: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
    R = truth.runs
    maneuvers = maneuver_names if maneuver_names is not None and "maneuver" in truth.labels else None
    origin = np.asarray(sensor_position, dtype=np.float64).reshape(3)
    t_xyz = _xyz_index(truth.state_names, "truth")
    z_xyz, z_cov = _measurements_xyz(detections, origin)                       # (R, K, D, 3)
    variant_keys = list(estimates)
    metric_series = _styled_3d_metric_series(metric_time_series(metrics, experiment, variant_keys, display, colours))
    r0 = record_runs[0] if record_runs else 0
    sigma = _noise_sigma_3d(None if z_cov is None else z_cov[r0], np.asarray(detections.detected[r0]))

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    key_extra = _key_extra_3d(sigma)
    blueprint = _blueprint_3d(rrb, truth, t_xyz, origin, record_runs, estimates, display, metric_series, sigma,
                              maneuvers=maneuvers is not None, geographic=to_geodetic is not None,
                              key_extra=key_extra)

    track_radii = track_radius(variant_keys)
    with atomic_recording(rr, path, experiment, blueprint) as rec:
        times = time_columns(rr)
        ui = rr.Radius.ui_points
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("/world/radar", rr.Points3D([origin], colors=_RADAR_COLOUR, radii=ui(7.0), labels="radar",
                                            show_labels=True), static=True)
        for r in record_runs:
            world = f"/world/run{r}"
            # ---- truth: path up to now, whole trajectory faint, current position; target frame ---
            xyz = truth.state[r][..., t_xyz]                                     # (K, T, 3)
            T = xyz.shape[1]
            strips = [xyz[:, t][np.isfinite(xyz[:, t]).all(-1)] for t in range(T)]
            rec.log(f"{world}/truth", rr.LineStrips3D(strips, colors=(*TRUTH_COLOUR, FUTURE_ALPHA), radii=ui(0.6)),
                    static=True)
            rec.log(f"{world}/truth", rr.Points3D.from_fields(colors=TRUTH_COLOUR, radii=ui(6.0)), static=True)
            ok = np.isfinite(xyz).all(-1)                                        # (K, T)
            log_path(rr, rec, times, f"{world}/truth/path", truth.time, np.arange(truth.time.size), xyz, ok,
                     colour=TRUTH_COLOUR, radius=1.0)
            steps = np.nonzero(ok.any(-1))[0]
            rec.send_columns(f"{world}/truth", indexes=times(truth.time[steps], steps),
                             columns=rr.Points3D.columns(positions=xyz[ok]).partition(ok[steps].sum(-1)))
            steps = np.nonzero(ok[:, 0])[0]                                      # follow target 0
            if steps.size:
                rec.send_columns(
                    f"{FRAMES_PATH}/target_run{r}", indexes=times(truth.time[steps], steps),
                    columns=rr.Transform3D.columns(
                        translation=xyz[steps, 0], parent_frame=["tf#/world"] * steps.size,
                        child_frame=[target_frame(r)] * steps.size))

            # ---- measurements (converted to Cartesian) of the current scan + faint static cloud ---
            z = z_xyz[r]                                                         # (K, D, 3)
            seen = np.asarray(detections.detected[r]) & np.isfinite(z).all(-1)
            steps = np.nonzero(seen.any(-1))[0]
            clutter = np.asarray(detections.target[r]) < 0
            rec.log(f"{world}/measurements", rr.Points3D.from_fields(radii=ui(4.0)), static=True)
            rec.send_columns(f"{world}/measurements", indexes=times(detections.time[steps], steps),
                             columns=rr.Points3D.columns(
                                 positions=z[seen],
                                 colors=np.where(clutter[seen][:, None], _CLUTTER_COLOUR,
                                                 _MEASUREMENT_COLOUR).astype(np.uint8),
                             ).partition(seen[steps].sum(-1)))
            # every scan's detections up to now, faint
            rec.log(f"{world}/measurements/all", rr.Points3D.from_fields(radii=ui(1.5)), static=True)
            rec.send_columns(f"{world}/measurements/all", indexes=times(detections.time[steps], steps),
                             columns=rr.Points3D.columns(
                                 positions=z[seen], colors=np.where(clutter[seen][:, None], _CLUTTER_FAINT,
                                                                    _MEASUREMENT_FAINT).astype(np.uint8),
                             ).partition(seen[steps].sum(-1)))

            for key, est in estimates.items():
                _log_variant_3d(rr, rec, times, ui, key, r, est, t_xyz, colours[key], display[key], origin, sigma,
                                track_radii[key])
            if maneuvers is not None:
                log_maneuvers(rr, rec, times, r, truth.time, np.asarray(truth.labels["maneuver"][r])[:, 0], maneuvers)
            if to_geodetic is not None:
                log_map(rr, rec, times, ui, r, truth.time, xyz[:, 0], origin, to_geodetic,
                        {key: est.state[r][..., t_xyz] for key, est in estimates.items()}, colours, display)
            if "acceleration" in truth.labels:
                acc = np.asarray(truth.labels["acceleration"][r], dtype=np.float64)[:, 0]    # (K, 3)
                for i, a in enumerate(AXES):
                    entity = f"/truth/run{r}/acceleration/{a}"
                    steps = np.nonzero(np.isfinite(acc[:, i]))[0]
                    rec.log(entity, rr.SeriesLines(names=f"truth (run {r})", colors=TRUTH_COLOUR, widths=1.5),
                            static=True)
                    rec.send_columns(entity, indexes=times(truth.time[steps], steps),
                                     columns=rr.Scalars.columns(scalars=acc[steps, i]))

        log_metric_series(rr, rec, times, metric_series)
        log_keys(rr, rec, variant_keys, display, colours, extra=key_extra)
        log_config(rr, rec, experiment, description, config_text, record_runs, R)


def _log_variant_3d(rr, rec, times, ui, key: str, r: int, est: TrackEstimate, t_xyz: list[int],
                    colour: tuple[int, int, int], name: str, origin: np.ndarray, sigma: float,
                    track_radius: float = 1.25) -> None:
    base = f"/world/run{r}/{key}"
    t = est.time
    pos = est.state[r][:, t_xyz]                                                  # (K, 3)
    P = est.covariance[r][:, t_xyz][:, :, t_xyz]                                  # (K, 3, 3)
    good = np.isfinite(pos).all(-1) & np.isfinite(P).all((-1, -2))
    steps = np.nonzero(good)[0]
    log_path(rr, rec, times, f"{base}/track", t, np.arange(t.size), pos, good, colour=colour, radius=track_radius)
    rec.log(f"{base}/estimate", rr.Points3D.from_fields(colors=colour, radii=ui(5.0)), static=True)
    rec.send_columns(f"{base}/estimate", indexes=times(t[steps], steps), columns=rr.Points3D.columns(positions=pos[good]))
    rec.log(f"{base}/covariance", rr.Ellipsoids3D.from_fields(colors=colour, line_radii=ui(1.0),
                                                              fill_mode="MajorWireframe"), static=True)
    if steps.size:
        half, quat = ellipsoids(P[good])
        rec.send_columns(f"{base}/covariance", indexes=times(t[steps], steps),
                         columns=rr.Ellipsoids3D.columns(centers=pos[good], half_sizes=half, quaternions=quat))

    # ---- maneuver detections: a log line and a marker at the estimate, shown at that step only ----
    events = _detection_events(est, r)
    if events is not None and events["steps"].size:
        ev, axis = events["steps"], events["axis"]
        rec.send_columns(f"{base}/detections", indexes=times(t[ev], ev),
                         columns=rr.TextLog.columns(text=events["lines"], level=["INFO"] * ev.size))
        # marker at each detection step, cleared at the next step unless that is a detection too
        K = t.size
        clear = np.setdiff1d(ev + 1, ev)
        clear = clear[clear < K]
        mark = np.union1d(ev, clear)
        hit = np.isin(mark, ev)
        labels = ["maneuver" + ("" if axis is None else " " + "+".join(a for a, h in zip(AXES, axis[k]) if h))
                  for k in mark[hit]]
        rec.log(f"{base}/detections", rr.Points3D.from_fields(colors=_DETECTION_COLOUR, radii=ui(9.0),
                                                              show_labels=True), static=True)
        rec.send_columns(f"{base}/detections", indexes=times(t[mark], mark),
                         columns=rr.Points3D.columns(positions=pos[mark[hit]], labels=labels)
                         .partition(hit.astype(np.int64)))
        # every detection of the run up to now (faint): where along the track the test fired
        rec.log(f"{base}/detections/all", rr.Points3D.from_fields(colors=_DETECTION_FAINT, radii=ui(3.0)), static=True)
        rec.send_columns(f"{base}/detections/all", indexes=times(t[ev], ev), columns=rr.Points3D.columns(positions=pos[ev]))
        if axis is not None:
            # per LOS axis (variant C): an arrow from the estimate along the axis that fired
            length = 3.0 * sigma if np.isfinite(sigma) and sigma > 0 else 100.0
            los = _los_axes(pos[mark], origin)                                    # (M, 3, 3)
            for i, a in enumerate(AXES):
                fired = hit & axis[mark, i]
                entity = f"{base}/detections/{a}"
                rec.log(entity, rr.Arrows3D.from_fields(colors=lighter_colour(colour, AXIS_SHADES[a]), radii=ui(2.0),
                                                        show_labels=True), static=True)
                rec.send_columns(entity, indexes=times(t[mark], mark), columns=rr.Arrows3D.columns(
                    origins=pos[mark[fired]], vectors=length * los[fired, i], labels=[f"LOS {a}"] * int(fired.sum()),
                ).partition(fired.astype(np.int64)))

    # ---- time series: estimated input level, test statistic ------------------------------------
    series = f"/variants/{key}/run{r}"
    if "input_level" in est.extras:
        u = np.asarray(est.extras["input_level"][r], dtype=np.float64)          # (K, 3)
        for i, a in enumerate(AXES):
            entity = f"{series}/input_level/{a}"
            steps = np.nonzero(np.isfinite(u[:, i]))[0]
            rec.log(entity, rr.SeriesLines(names=f"{name} (run {r})", colors=lighter_colour(colour), widths=1.0),
                    static=True)
            rec.send_columns(entity, indexes=times(t[steps], steps), columns=rr.Scalars.columns(scalars=u[steps, i]))
    if "test_statistic" in est.extras:
        s = np.asarray(est.extras["test_statistic"][r], dtype=np.float64)
        parts = [(f"{series}/test_statistic", s, name, colour)] if s.ndim == 1 else [
            (f"{series}/test_statistic/{a}", s[:, i], f"{name} LOS {a}", lighter_colour(colour, AXIS_SHADES[a]))
            for i, a in enumerate(AXES)]
        for entity, values, label, c in parts:
            steps = np.nonzero(np.isfinite(values))[0]
            rec.log(entity, rr.SeriesLines(names=label, colors=c, widths=1.5), static=True)
            rec.send_columns(entity, indexes=times(t[steps], steps), columns=rr.Scalars.columns(scalars=values[steps]))


def _follow_half_3d(sigma: float) -> float:
    """Half size [m] of the target-centred 3-D views: about 6 measurement sigmas."""
    return float(np.clip(6.0 * sigma, 20.0, 5000.0)) if np.isfinite(sigma) and sigma > 0 else 300.0


def _key_extra_3d(sigma: float) -> list:
    """Key entries beside the variants: the truth (its path, its acceleration in the input-level
    views) and the spacing of the grid in the target-centred views. Per-axis lines are shades of
    their variant's colour, named in their views' titles."""
    return [("truth", TRUTH_COLOUR), (f"grid {_round_spacing(_follow_half_3d(sigma) / 2.0):g} m", (110, 110, 110))]


def _round_spacing(x: float) -> float:
    """The largest 1, 2 or 5 x 10^n not above x (x > 0)."""
    e = 10.0 ** np.floor(np.log10(x))
    return float(max(m * e for m in (1.0, 2.0, 5.0) if m * e <= x))


def _view_direction(track: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    """Unit vector from the target to the camera: across the plane the trajectory mostly lies in
    (its least-spread principal axis, so a manoeuvre's turn is seen face on), from above, tilted
    towards the sensor and never straight down (the views keep z up)."""
    up = np.array([0.0, 0.0, 1.0])
    p = track[np.isfinite(track).all(-1)]
    normal = np.array([-0.5, -0.7, 0.5])
    if len(p) >= 3:
        w, V = np.linalg.eigh(np.cov((p - p.mean(0)).T))
        if w[-1] > 0:
            if w[1] > 1e-4 * w[-1]:
                normal = V[:, 0]                               # a curved track: its plane's normal
            else:                                              # a straight one: across it, horizontally
                normal = np.cross(V[:, -1], up) if np.linalg.norm(np.cross(V[:, -1], up)) > 1e-6 else V[:, 0]
    normal = normal / np.linalg.norm(normal)
    if normal @ up < 0:
        normal = -normal
    toward_sensor = sensor - (p.mean(0) if len(p) else sensor)
    if np.linalg.norm(toward_sensor) > 0:
        normal = normal + 0.3 * toward_sensor / np.linalg.norm(toward_sensor)
    normal = normal + 0.35 * up                                 # look a little down on the scene
    normal = normal / np.linalg.norm(normal)
    if normal @ up > 0.8:                                       # not straight down: keep a horizon
        horizontal = normal - (normal @ up) * up
        horizontal = horizontal / np.linalg.norm(horizontal) if np.linalg.norm(horizontal) > 1e-9 else \
            np.array([0.0, -1.0, 0.0])
        normal = 0.8 * up + 0.6 * horizontal
    return normal / np.linalg.norm(normal)


def _blueprint_3d(rrb, truth: Truth, t_xyz: list[int], origin: np.ndarray, record_runs: list[int],
                  estimates: Mapping[str, TrackEstimate], display: Mapping[str, str], metric_series: dict,
                  sigma: float, maneuvers: bool = False, geographic: bool = False, key_extra: Sequence = ()):
    """Top: per variant, a target-centred 3-D view (truth + measurements + that variant). Then the RMSE
    curves of all variants and the detections per step; the mean (and run r0's) input level per axis
    beside tabs with each variant's detection log and test statistic, NEES and the config."""
    r0 = record_runs[0] if record_runs else None
    variant_keys = list(estimates)
    # Camera: a fixed offset from the target (the views look from the frame that follows it), so that
    # about +-6 measurement sigmas around it are in view: single detections, the 2-sigma ellipsoids
    # and the estimation errors are visible although the track spans kilometres.
    half = _follow_half_3d(sigma)
    track = truth.state[r0][:, 0][:, t_xyz] if r0 is not None else np.empty((0, 3))
    eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=2.0 * half * _view_direction(track, origin),
                            look_target=[0.0, 0.0, 0.0], eye_up=[0.0, 0.0, 1.0])
    # a faint grid through the target for scale, spacing a round 1, 2 or 5 x 10^n metres
    spacing = _round_spacing(half / 2.0)
    grid = rrb.LineGrid3D(visible=True, spacing=spacing, stroke_width=1.0, color=[90, 90, 90, 110])
    columns = []
    titles = fit_titles(1600.0 / max(len(variant_keys), 1), [
        [f"{display[k]} · run {r0}, target-centred (grid {spacing:g} m)", f"{display[k]} · run {r0} (grid {spacing:g} m)",
         f"{display[k]} (grid {spacing:g} m)", display[k]] for k in variant_keys])
    for key, title in zip(variant_keys, titles):
        if r0 is None:
            break
        world = f"/world/run{r0}"
        columns.append(rrb.Spatial3DView(
            origin="/world", name=title,
            contents=[f"{world}/truth/**", f"{world}/measurements/**", f"{world}/{key}/**", "/world/radar"],
            overrides=path_overrides(rrb, [f"{world}/truth/path", f"{world}/measurements/all", f"{world}/{key}/track",
                                           f"{world}/{key}/detections/all"]),
            spatial_information=rrb.SpatialInformation(target_frame=target_frame(r0)),
            eye_controls=eye, line_grid=grid))
    rows, shares = [], []
    if columns:
        rows.append(rrb.Horizontal(*columns))
        shares.append(5.0)
    rows.append(key_view(rrb, VARIANT_KEY, [display[k] for k in variant_keys] + [label for label, _ in key_extra]))
    shares.append(0.5)

    whole_run = whole_run_axis(rrb)
    legend = no_legend(rrb)           # the key names the variants' colours
    present = {m for m, _ in metric_series}
    plots = [rrb.TimeSeriesView(origin=f"/metrics/{m}", name=f"{m} [{axis_unit_of(m)}]", axis_x=whole_run,
                                plot_legend=legend) for m in RMSE_METRICS_3D if m in present]
    if "detections" in present:
        plots.append(rrb.TimeSeriesView(origin="/metrics/detections", name="maneuver detections per step (all runs)",
                                        axis_x=whole_run, plot_legend=legend))
    if plots:
        rows.append(rrb.Horizontal(*plots))
        shares.append(2.2)

    bottom = []
    for a in AXES:
        contents = [f"/metrics/input_level_{a}/**"]
        if r0 is not None:
            contents += [f"/variants/{k}/run{r0}/input_level/{a}" for k in variant_keys
                         if "input_level" in estimates[k].extras]
            contents.append(f"/truth/run{r0}/acceleration/{a}")
        if f"input_level_{a}" in present or len(contents) > 2:
            # nine lines: no legend (it would cover them); the colours are the variants' everywhere
            bottom.append(rrb.TimeSeriesView(
                origin="/", contents=contents, axis_x=whole_run, plot_legend=rrb.PlotLegend(visible=False),
                name=f"input {a} [m/s²]: mean" + (f", run {r0}, truth" if r0 is not None else "")))
    be = rrb.encodings
    log_columns = rrb.TextLogColumns(
        timeline_columns=[be.TimelineColumn("step"), be.TimelineColumn("time", visible=False)],
        text_log_columns=[be.TextLogColumn("Body"), be.TextLogColumn("EntityPath", visible=False),
                          be.TextLogColumn("LogLevel", visible=False)])
    tabs = []
    tab_width = 1600.0 * 2.8 / (2.0 * len(bottom) + 2.8)
    if r0 is not None:
        for key in variant_keys:
            est = estimates[key]
            parts = []
            axis_counts = [f"/metrics/detections_axis_{a}/{key}" for a in AXES
                           if (f"detections_axis_{a}", key) in metric_series]
            w = tab_width / (("test_statistic" in est.extras) + bool(axis_counts) or 1)
            if "test_statistic" in est.extras:
                per_axis = np.ndim(est.extras["test_statistic"]) == 3
                shades = ", LOS x dark, y, z light" if per_axis else ""
                parts.append(rrb.TimeSeriesView(origin=f"/variants/{key}/run{r0}/test_statistic",
                                                name=fit_title(w, f"{display[key]}: test statistic (run {r0}){shades}",
                                                               f"{display[key]}: test statistic{shades}",
                                                               f"{display[key]}: statistic"),
                                                axis_x=whole_run, plot_legend=legend))
            if axis_counts:
                parts.append(rrb.TimeSeriesView(origin="/metrics", contents=axis_counts, axis_x=whole_run,
                                                plot_legend=legend,
                                                name=fit_title(w, f"{display[key]}: detections per LOS axis (all runs), "
                                                                  f"x dark, y, z light",
                                                               f"{display[key]}: detections per LOS axis, x dark",
                                                               f"{display[key]}: per-axis detections",
                                                               f"{display[key]}: LOS detections")))
            if parts:
                parts = [rrb.Horizontal(*parts)] if len(parts) > 1 else parts
            if _detection_events(est, r0) is not None:
                parts.append(rrb.TextLogView(origin=f"/world/run{r0}/{key}/detections",
                                             name=f"{display[key]}: maneuver detections (run {r0})",
                                             columns=log_columns))
            if parts:
                tabs.append(rrb.Vertical(*parts, name=display[key]))
    if geographic and r0 is not None:
        tabs.insert(0, rrb.MapView(origin="/map", name=f"map: truth, tracks and radar (run {r0})",
                                   contents=["/map/radar", f"/map/run{r0}/**"],
                                   overrides=path_overrides(rrb, [f"/map/run{r0}/{name}/path"
                                                                  for name in ["truth", *variant_keys]])))
    if maneuvers and r0 is not None:
        tabs.insert(0, rrb.Vertical(
            rrb.StateTimelineView(origin=f"/truth/run{r0}/maneuver", name=f"maneuver of the truth (run {r0})",
                                  time_view=whole_run),
            rrb.TextLogView(origin=f"/truth/run{r0}/maneuvers", name="maneuver changes", columns=log_columns),
            name="maneuvers"))
    tabs += _limit_views(rrb, present, whole_run)
    overview = [f"/world/run{r}/truth/**" for r in record_runs] + ["/world/radar"] + \
        [f"/world/run{r}/{k}/track" for r in record_runs for k in variant_keys]
    overview_paths = [f"/world/run{r}/truth/path" for r in record_runs] + \
        [f"/world/run{r}/{k}/track" for r in record_runs for k in variant_keys]
    pts = np.concatenate([truth.state[record_runs][..., t_xyz].reshape(-1, 3), origin[None]])
    pts = pts[np.isfinite(pts).all(-1)]
    lo, hi = pts.min(0), pts.max(0)
    extent = max(float(np.max(hi - lo)), 100.0)
    tabs.append(rrb.Spatial3DView(
        origin="/world", contents=overview, name="trajectories and radar", overrides=path_overrides(rrb, overview_paths),
        eye_controls=rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, look_target=(lo + hi) / 2,
                                       position=(lo + hi) / 2 + 2.0 * extent * _view_direction(track, origin),
                                       eye_up=[0.0, 0.0, 1.0]),
        line_grid=rrb.LineGrid3D(visible=True, spacing=_round_spacing(extent / 5.0), stroke_width=1.0,
                                 color=[90, 90, 90, 110])))
    tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    bottom.append(rrb.Tabs(*tabs, active_tab=0))
    rows.append(rrb.Horizontal(*bottom, column_shares=[2.0] * (len(bottom) - 1) + [2.8]))
    shares.append(2.6)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
