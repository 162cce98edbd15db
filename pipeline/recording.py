"""Write one experiment's Rerun recording (``.rrd``): trajectories, estimates, mode probabilities,
model-group switching and the Monte Carlo metrics, with a side-by-side blueprint in the same file.

Layout of the entity tree (``r`` = a recorded Monte Carlo run, ``v`` = a variant key)::

    /world/run{r}/truth                   static trajectory + current true position
    /world/run{r}/measurements            detections of the current scan (clutter coloured apart)
    /world/run{r}/measurements/all        every scan's detections, static and faint
    /world/run{r}/{v}/track               static estimated trajectory
    /world/run{r}/{v}/estimate            current estimate
    /world/run{r}/{v}/covariance          current 2-sigma position ellipse (polyline)
    /variants/{v}/run{r}/mode_probability/{model}
    /variants/{v}/run{r}/active_group     1-based group number (M1 = 1)
    /variants/{v}/run{r}/candidate_group  1-based, 0 while no union runs
    /variants/{v}/run{r}/events           text log of group-set changes
    /metrics/{metric}/{v}                 Monte Carlo average per step
    /config                               markdown: description + config yaml
    /world/frames/...                     named frames the 2-D views look from: "north_up" (y up;
                                          Rerun draws 2-D y downwards) and "target_run{r}" (that
                                          run's true target position, y up) for the zoomed views

Every time-varying entity has the timelines ``time`` (duration, s) and ``step`` (sequence) and is
written with one ``send_columns`` call; only static things use ``log``. Rerun is imported lazily.
"""

from __future__ import annotations

import colorsys
import os
import re
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from pipeline.data import Detections, Truth

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

APPLICATION_ID = "mtt"
ELLIPSE_POINTS = 48
ELLIPSE_SIGMA = 2.0
SPATIAL_METRICS = ("acceleration_rmse_x", "acceleration_rmse_y", "position_rmse")
_UNITS = {"acceleration_rmse_x": "m/s²", "acceleration_rmse_y": "m/s²", "position_rmse": "m",
          "velocity_rmse": "m/s", "nees": "-", "models_evaluated": "models/step"}

# One colour per variant, in display order, used in every view (tracks, estimates, metric lines).
_VARIANT_COLOURS = [(31, 119, 255), (255, 127, 14), (44, 200, 80), (214, 39, 40), (160, 103, 219),
                    (23, 190, 207), (227, 119, 194), (188, 189, 34), (140, 86, 75), (127, 127, 127)]
_TRUTH_COLOUR = (235, 235, 235)
_MEASUREMENT_COLOUR = (170, 170, 170)
_CLUTTER_COLOUR = (220, 70, 70)
_MEASUREMENT_FAINT = (95, 95, 95)
_CLUTTER_FAINT = (120, 50, 50)
_FRAMES = "/world/frames"
NORTH_UP_FRAME = "north_up"
_PATH_SAFE = re.compile(r"^[A-Za-z0-9_.-]+$")


def recording_id(experiment: str) -> str:
    """The experiment name reduced to ``[A-Za-z0-9_-]`` (Rerun's catalog dislikes anything else)."""
    rid = re.sub(r"[^A-Za-z0-9_-]+", "_", experiment).strip("_")
    return rid or "experiment"


def target_frame(run: int) -> str:
    """Named transform frame centred on run ``run``'s true target position, y (north) up."""
    return f"target_run{run}"


def variant_colour(i: int) -> tuple[int, int, int]:
    if i < len(_VARIANT_COLOURS):
        return _VARIANT_COLOURS[i]
    r, g, b = colorsys.hsv_to_rgb((i * 0.61803398875) % 1.0, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def _model_colour(i: int, n: int) -> tuple[int, int, int]:
    r, g, b = colorsys.hsv_to_rgb(i / max(n, 1), 0.7, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def _xy_index(names: Sequence[str], what: str) -> list[int]:
    missing = [c for c in ("x", "y") if c not in names]
    if missing:
        raise ValueError(f"{what}: state_names {list(names)} lack {missing}; the recording plots (x, y)")
    return [list(names).index("x"), list(names).index("y")]


def _ellipses(mean: np.ndarray, cov: np.ndarray, n_sigma: float = ELLIPSE_SIGMA,
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
                    model_names: Sequence[str] | None = None, group_names: Sequence[str] | None = None,
                    config_text: str = "", description: str = "") -> None:
    """Write ``path`` (an ``.rrd`` with its default blueprint) for the runs in ``record_runs``.

    ``estimates`` maps variant key (path-safe) -> estimate, in display order; ``metrics`` is the
    long metrics frame (variant, variant_key, metric, step, time, value, ...) or None. The file is
    written to a temporary name beside ``path`` and moved onto it only once complete.
    """
    path = Path(path)
    R = truth.runs
    record_runs = [int(r) for r in record_runs]
    bad = [r for r in record_runs if not 0 <= r < R]
    if bad:
        raise ValueError(f"record.runs: {bad} out of range; the experiment has {R} runs, "
                         f"so each recorded run must be in 0..{R - 1}")
    if len(set(record_runs)) != len(record_runs):
        raise ValueError(f"record.runs: {record_runs} lists a run twice")
    for key in estimates:
        if not _PATH_SAFE.match(key):
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
    truth_xy = _xy_index(truth.state_names, "truth")
    meas_xy = _xy_index(detections.measurement_names, "detections")
    variant_keys = list(estimates)
    colours = {key: variant_colour(i) for i, key in enumerate(variant_keys)}
    display = {key: str(display_names.get(key, key)) for key in variant_keys}

    metric_series = _metric_series(metrics, experiment, variant_keys, display, colours)

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    blueprint = _blueprint(rrb, truth, truth_xy, record_runs, variant_keys, display, metric_series,
                           estimates, has_config=True,
                           noise_sigma=_noise_sigma(detections, meas_xy, record_runs[0] if record_runs else 0))

    path.parent.mkdir(parents=True, exist_ok=True)
    # Rerun creates the file itself (normal permissions); a hidden unique name beside the target
    # keeps os.replace atomic and never leaves a partial .rrd under the final name.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(experiment))
    try:
        rec.set_log_time_enabled(False)
        rec.save(tmp, default_blueprint=blueprint)

        def times(t: np.ndarray, steps: np.ndarray) -> list:
            return [rr.TimeColumn("time", duration=np.asarray(t, dtype=np.float64)),
                    rr.TimeColumn("step", sequence=np.asarray(steps, dtype=np.int64))]

        ui = rr.Radius.ui_points
        # Rerun's 2-D views draw y downwards (image convention). The views look at the data from
        # named frames whose y axis is flipped, so north is up: "north_up" for the whole scene and,
        # per recorded run, "target_run{r}" centred on the true target position at each step.
        flip = np.array([1.0, -1.0, 1.0])
        rec.log(f"{_FRAMES}/north_up", rr.Transform3D(scale=flip, parent_frame="tf#/world",
                                                      child_frame=NORTH_UP_FRAME), static=True)
        for r in record_runs:
            world = f"/world/run{r}"
            # ---- truth: whole trajectory (static) + current position --------------------------
            xy = truth.state[r][..., truth_xy]                                   # (K, T, 2)
            K, T = xy.shape[:2]
            strips = [xy[:, t][np.isfinite(xy[:, t]).all(-1)] for t in range(T)]
            rec.log(f"{world}/truth", rr.LineStrips2D(strips, colors=_TRUTH_COLOUR, radii=ui(0.75),
                                                      draw_order=16.0), static=True)
            rec.log(f"{world}/truth", rr.Points2D.from_fields(colors=_TRUTH_COLOUR, radii=ui(5.0),
                                                              draw_order=30.0), static=True)
            ok = np.isfinite(xy).all(-1)                                          # (K, T)
            steps = np.nonzero(ok.any(-1))[0]
            rec.send_columns(f"{world}/truth", indexes=times(truth.time[steps], steps),
                             columns=rr.Points2D.columns(positions=xy[ok]).partition(ok[steps].sum(-1)))
            first = ok[:, 0]                                                      # follow target 0
            steps = np.nonzero(first)[0]
            if steps.size:
                rec.send_columns(
                    f"{_FRAMES}/target_run{r}", indexes=times(truth.time[steps], steps),
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
            # every scan's detections at once, faint: the noise cloud around the tracks when zoomed in
            rec.log(f"{world}/measurements/all", rr.Points2D(
                z[seen], radii=ui(1.5), draw_order=5.0,
                colors=np.where(clutter[seen][:, None], _CLUTTER_FAINT, _MEASUREMENT_FAINT).astype(np.uint8)),
                static=True)

            # ---- per variant: track, estimate, covariance ellipse ------------------------------
            for key, est in estimates.items():
                colour = colours[key]
                base = f"{world}/{key}"
                pos = est.state[r][:, truth_xy]                                    # (K, 2)
                P = est.covariance[r][:, truth_xy][:, :, truth_xy]                 # (K, 2, 2)
                good = np.isfinite(pos).all(-1) & np.isfinite(P).all((-1, -2))
                steps = np.nonzero(good)[0]
                rec.log(f"{base}/track", rr.LineStrips2D([pos[good]], colors=colour, radii=ui(1.25),
                                                         draw_order=15.0), static=True)
                rec.log(f"{base}/estimate", rr.Points2D.from_fields(colors=colour, radii=ui(3.5),
                                                                    draw_order=40.0), static=True)
                rec.send_columns(f"{base}/estimate", indexes=times(est.time[steps], steps),
                                 columns=rr.Points2D.columns(positions=pos[good]))
                rec.log(f"{base}/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(1.0),
                                                                          draw_order=35.0), static=True)
                if steps.size:
                    rec.send_columns(f"{base}/covariance", indexes=times(est.time[steps], steps),
                                     columns=rr.LineStrips2D.columns(strips=_ellipses(pos[good], P[good])))

                _log_variant_run(rr, rec, times, key, r, est, model_names, group_names)

        for (metric, key), series in metric_series.items():
            steps, t, values, name, colour = series
            entity = f"/metrics/{_path_part(metric)}/{key}"
            rec.log(entity, rr.SeriesLines(names=name, colors=colour, widths=2.0), static=True)
            rec.send_columns(entity, indexes=times(t, steps), columns=rr.Scalars.columns(scalars=values))

        doc = f"# {experiment}\n\n"
        if description:
            doc += f"{description.strip()}\n\n"
        doc += f"Recorded runs: {', '.join(map(str, record_runs))} of {R}.\n\n"
        if config_text:
            doc += f"```yaml\n{config_text.rstrip()}\n```\n"
        rec.log("/config", rr.TextDocument(doc, media_type=rr.MediaType.MARKDOWN), static=True)

        rec.flush()
        rec.disconnect()
        os.replace(tmp, path)
    except BaseException:
        try:
            rec.disconnect()
        finally:
            tmp.unlink(missing_ok=True)
        raise


def _noise_sigma(detections: Detections, meas_xy: list[int], run: int) -> float:
    """Typical position-measurement standard deviation [m] of a run (median over its detections)."""
    cov = np.asarray(detections.noise_covariance)
    if cov.ndim != 5 or cov.shape[0] <= run:
        return float("nan")
    block = cov[run][..., meas_xy, :][..., meas_xy]                      # (K, D, 2, 2)
    var = 0.5 * (block[..., 0, 0] + block[..., 1, 1])
    var = var[detections.detected[run] & np.isfinite(var)]
    return float(np.sqrt(np.median(var))) if var.size else float("nan")


def _path_part(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(name))


def _metric_series(metrics, experiment: str, variant_keys: list[str], display: Mapping[str, str],
                   colours: dict) -> dict:
    """(metric, variant_key) -> (steps, time, values, display name, colour), finite values only, in
    metric order of appearance and display order of variants (variants only in the frame come last)."""
    if metrics is None or metrics.height == 0:
        return {}
    import polars as pl

    required = {"variant_key", "metric", "step", "time", "value"}
    missing = required - set(metrics.columns)
    if missing:
        raise ValueError(f"metrics frame lacks columns {sorted(missing)}; it has {metrics.columns}")
    if "experiment" in metrics.columns and metrics["experiment"].n_unique() > 1:
        metrics = metrics.filter(pl.col("experiment") == experiment)
    dupes = metrics.group_by("variant_key", "metric", "step").len().filter(pl.col("len") > 1)
    if dupes.height:
        raise ValueError(f"metrics frame has {dupes.height} duplicate (variant_key, metric, step) rows, "
                         f"e.g. {dupes.row(0, named=True)}; pass one experiment's Monte Carlo averages")
    keys = list(variant_keys) + [k for k in metrics["variant_key"].unique(maintain_order=True).to_list()
                                 if k not in variant_keys]
    for i, key in enumerate(keys):
        colours.setdefault(key, variant_colour(i))
    out: dict = {}
    for metric in metrics["metric"].unique(maintain_order=True).to_list():
        part = metrics.filter(pl.col("metric") == metric)
        for key in keys:
            rows = part.filter(pl.col("variant_key") == key).sort("step")
            if rows.height == 0:
                continue
            if not _PATH_SAFE.match(str(key)):
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
            entity = f"{base}/mode_probability/{_path_part(name)}"
            steps = np.nonzero(np.isfinite(mu[:, i]))[0]
            rec.log(entity, rr.SeriesLines(names=str(name), colors=_model_colour(i, M), widths=1.5), static=True)
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
               has_config: bool, noise_sigma: float = float("nan")):
    """Top: per variant, a target-centred 2-D view over a whole-trajectory one (truth + measurements +
    that variant). Middle: the RMSE plots of all variants. Bottom: tabs with each variant's mode
    probabilities and groups, and the config."""
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

    columns = []
    for key in variant_keys:
        everything = []
        for r in record_runs:
            everything += [f"/world/run{r}/truth", f"/world/run{r}/measurements/**", f"/world/run{r}/{key}/**"]
        views = []
        if r0 is not None:
            views.append(rrb.Spatial2DView(
                origin="/world", name=f"{display[key]} · run {r0}, centred on the target",
                contents=[f"/world/run{r0}/truth", f"/world/run{r0}/measurements/**", f"/world/run{r0}/{key}/**"],
                spatial_information=rrb.SpatialInformation(target_frame=target_frame(r0)),
                visual_bounds=follow_bounds))
        views.append(rrb.Spatial2DView(
            origin="/world", contents=everything,
            name=f"{display[key]} · {'runs ' + ', '.join(map(str, record_runs)) + ', ' if len(record_runs) > 1 else ''}"
                 f"whole trajectory",
            spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME), visual_bounds=overview_bounds))
        columns.append(rrb.Vertical(*views, row_shares=[3.0, 2.0][: len(views)], name=display[key]))
    rows = [rrb.Horizontal(*columns)]
    shares = [6.0]

    whole_run = rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                      end=rrb.TimeRangeBoundary.infinite()))
    present = [m for m in SPATIAL_METRICS if any(mk == m for mk, _ in metric_series)]
    if present:
        rows.append(rrb.Horizontal(*[
            rrb.TimeSeriesView(origin=f"/metrics/{_path_part(m)}", name=f"{m} [{_UNITS.get(m, '')}]",
                               axis_x=whole_run, plot_legend=rrb.PlotLegend(corner="RightTop"))
            for m in present]))
        shares.append(2.5)

    be = rrb.encodings
    event_columns = rrb.TextLogColumns(
        timeline_columns=[be.TimelineColumn("step"), be.TimelineColumn("time", visible=False)],
        text_log_columns=[be.TextLogColumn("Body"), be.TextLogColumn("EntityPath", visible=False),
                          be.TextLogColumn("LogLevel", visible=False)])
    tabs, richest = [], None
    if r0 is not None:
        for key in variant_keys:
            est = estimates[key]
            base = f"/variants/{key}/run{r0}"
            parts = []
            if "mode_probabilities" in est.extras:
                parts.append(rrb.TimeSeriesView(origin=f"{base}/mode_probability",
                                                name=f"{display[key]}: mode probabilities (run {r0})",
                                                axis_x=whole_run, axis_y=rrb.ScalarAxis(range=(0.0, 1.0)),
                                                plot_legend=rrb.PlotLegend(corner="RightTop")))
            if _group_series(est, r0) is not None:
                parts.append(rrb.TimeSeriesView(origin=base, contents=[f"{base}/active_group",
                                                                       f"{base}/candidate_group"],
                                                name=f"{display[key]}: model group (run {r0})", axis_x=whole_run,
                                                plot_legend=rrb.PlotLegend(corner="LeftTop")))
                parts.append(rrb.TextLogView(origin=f"{base}/events", name=f"{display[key]}: group switches",
                                             columns=event_columns))
            if parts:
                if richest is None and len(parts) > 1:
                    richest = len(tabs)   # open on the first variant with groups: probabilities + groups + events
                tabs.append(rrb.Horizontal(*parts, column_shares=[3.0, 1.6, 1.8][: len(parts)], name=display[key]))
    if has_config:
        tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    if tabs:
        rows.append(rrb.Tabs(*tabs, active_tab=richest or 0))
        shares.append(2.5)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
