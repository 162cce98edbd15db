"""The default study's recording (pipeline.studies.single_target.SingleTargetStudy.record): a 2-D
truth and its estimates, or, for a truth with a ``z`` state, the 3-D recording of
pipeline.views.single_target_3d. The entity tree and what the viewer shows are described in
pipeline.views.recording, whose shared parts both use."""


from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from pipeline.evaluation.metrics import axis_unit_of
from pipeline.views.blueprints import (fit_title, fit_titles, key_view, legend_in_quiet_corner, log_path, no_legend,
    path_overrides, whole_run)
from pipeline.views.colours import TRUTH_COLOUR, model_colour, variant_colour
from pipeline.data import Detections, Truth

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

from pipeline.views.recording import (FRAMES_PATH, FUTURE_ALPHA, LEGEND_MAX, MEASUREMENT_COLOUR, MEASUREMENT_FAINT,
    CLUTTER_COLOUR, CLUTTER_FAINT, MODEL_KEY, NORTH_UP_FRAME, PATH_SAFE, SPATIAL_METRICS, VARIANT_KEY,
    atomic_recording, checked_record_runs, covariance_ellipses, limit_views, log_config, log_keys, log_metric_series,
    log_north_up, metric_time_series, path_part, target_frame, time_columns, track_radius, xy_index)
from pipeline.views.single_target_3d import is_3d, write_recording_3d


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
        write_recording_3d(path, experiment=experiment, truth=truth, detections=detections, estimates=estimates,
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
                colors=np.where(clutter[seen][:, None], CLUTTER_COLOUR, MEASUREMENT_COLOUR).astype(np.uint8),
            ).partition(seen[steps].sum(-1))
            rec.log(f"{world}/measurements", rr.Points2D.from_fields(radii=ui(3.0), draw_order=20.0), static=True)
            rec.send_columns(f"{world}/measurements", indexes=times(detections.time[steps], steps), columns=cols)
            # every scan's detections up to now, faint: the noise cloud around the tracks when zoomed in
            rec.log(f"{world}/measurements/all", rr.Points2D.from_fields(radii=ui(1.5), draw_order=5.0), static=True)
            rec.send_columns(f"{world}/measurements/all", indexes=times(detections.time[steps], steps),
                             columns=rr.Points2D.columns(
                                 positions=z[seen], colors=np.where(clutter[seen][:, None], CLUTTER_FAINT,
                                                                    MEASUREMENT_FAINT).astype(np.uint8),
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


def _noise_sigma(detections: Detections, meas_xy: list[int], run: int) -> float:
    """Typical position-measurement standard deviation [m] of a run (median over its detections)."""
    cov = np.asarray(detections.noise_covariance)
    if cov.ndim != 5 or cov.shape[0] <= run:
        return float("nan")
    block = cov[run][..., meas_xy, :][..., meas_xy]                      # (K, D, 2, 2)
    var = 0.5 * (block[..., 0, 0] + block[..., 1, 1])
    var = var[detections.detected[run] & np.isfinite(var)]
    return float(np.sqrt(np.median(var))) if var.size else float("nan")


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
    tabs += limit_views(rrb, {m for m, _ in metric_series}, axis)
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

