"""The multi-target study's Rerun recording: per recorded run the truth, the detections (target-originated
and clutter apart) and every variant's reported tracks, coloured by track id with their 2-sigma
ellipses; births and deaths on the timeline; GOSPA and its split per variant side by side; the
reported number of targets against the truth.

Entity tree (``r`` a recorded run, ``v`` a variant key)::

    /world/run{r}/truth/future            static: every target's whole trajectory, faint
    /world/run{r}/truth/targets           the targets that exist at the scan (their ids as hidden labels)
    /world/run{r}/detections/target       the scan's detections of targets (grey)
    /world/run{r}/detections/clutter      the scan's clutter (red): the origin is known to the recording only
    /world/run{r}/{v}/tracks              the reported tracks at the scan, coloured by track id, labelled
    /world/run{r}/{v}/ellipses            their 2-sigma position ellipses, same colours
    /world/run{r}/{v}/trails              each reported track's last ``TRAIL`` scans
    /events/run{r}/truth                  text log: "target 3 born", "target 0 dies" at its scan
    /events/run{r}/{v}                    text log: a track id first / last reported
    /metrics/{metric}/{v}                 Monte Carlo mean per scan (gospa, its parts, cardinality...)
    /metrics/cardinality/truth            the true number of targets
    /config                               description and config

Every time-varying entity is one ``send_columns`` call (ragged sets: partitioned columns); the
timelines are ``time`` (s) and ``step``.
"""

from __future__ import annotations

import colorsys
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from pipeline.studies.multitarget.scenario import POSITION_INDEX, alive, births_and_deaths
from pipeline.views.blueprints import key_view, no_legend
from pipeline.views.colours import TRUTH_COLOUR, variant_colour
from pipeline.views.recording import (CLUTTER_COLOUR, FUTURE_ALPHA, MEASUREMENT_COLOUR, NORTH_UP_FRAME, VARIANT_KEY,
                                      atomic_recording, checked_record_runs, covariance_ellipses, log_config,
                                      log_keys, log_metric_series, log_north_up, metric_time_series, time_columns)

TRAIL = 15                        # scans of a track's recent path drawn behind it
METRIC_VIEWS = (("gospa", "GOSPA [m]"), ("gospa_localisation", "GOSPA localisation [m^p]"),
                ("gospa_missed", "GOSPA missed [m^p]"), ("gospa_false", "GOSPA false [m^p]"))


def track_colour(track_id: int) -> tuple[int, int, int]:
    """A colour per track id (golden-ratio hues: neighbouring ids differ)."""
    hue = (0.13 + 0.61803398875 * int(track_id)) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(255 * r), int(255 * g), int(255 * b)


def _ragged(rr, rec, times, entity: str, t: np.ndarray, steps: np.ndarray, lengths: Sequence[int], kind: str,
            **columns) -> None:
    """One partitioned send_columns of a per-scan set (points or strips) of ``lengths[k]`` items at scan k."""
    archetype = rr.Points2D if kind == "points" else rr.LineStrips2D
    rec.send_columns(entity, indexes=times(t, steps), columns=archetype.columns(**columns).partition(lengths))


def write_multitarget_recording(path: Path, *, experiment: str, truth, detections, estimates: Mapping,
                                display_names: Mapping[str, str], metrics, record_runs: Sequence[int],
                                config_text: str = "", description: str = "", gospa_c: float = 100.0,
                                gospa_p: float = 2.0) -> None:
    import rerun as rr
    import rerun.blueprint as rrb

    runs = checked_record_runs(record_runs, truth.runs)
    keys = list(estimates)
    colours = {k: variant_colour(i) for i, k in enumerate(keys)}
    index = list(POSITION_INDEX)
    time = np.asarray(truth.time, dtype=float)
    K = time.size
    steps = np.arange(K)
    times = time_columns(rr)
    blueprint = _blueprint(rrb, runs, keys, display_names, truth, gospa_c, gospa_p)
    with atomic_recording(rr, path, experiment, blueprint) as rec:
        log_north_up(rr, rec)
        log_config(rr, rec, experiment, description, config_text, runs, truth.runs)
        log_keys(rr, rec, keys, display_names, colours, extra=[("truth", TRUTH_COLOUR), ("clutter", CLUTTER_COLOUR)])
        exists = alive(truth)
        for r in runs:
            base = f"/world/run{r}"
            position = truth.state[r][..., index]                                  # (K, T, 2)
            strips = [position[exists[r, :, t], t] for t in range(position.shape[1]) if exists[r, :, t].any()]
            rec.log(f"{base}/truth/future", rr.LineStrips2D(strips, colors=[(*TRUTH_COLOUR, FUTURE_ALPHA)], radii=1.5),
                    static=True)
            counts = exists[r].sum(axis=1)
            ids = np.concatenate([np.nonzero(exists[r, k])[0] for k in range(K)]).astype(int)
            _ragged(rr, rec, times, f"{base}/truth/targets", time, steps, counts, "points",
                    positions=position[exists[r]], colors=np.tile(TRUTH_COLOUR, (ids.size, 1)),
                    radii=np.full(ids.size, 5.0), labels=[f"target {i}" for i in ids],
                    show_labels=np.zeros(ids.size, dtype=bool))
            filled = np.asarray(detections.detected[r], dtype=bool)
            origin = np.asarray(detections.target[r])
            for name, mask, colour in (("target", filled & (origin >= 0), MEASUREMENT_COLOUR),
                                       ("clutter", filled & (origin < 0), CLUTTER_COLOUR)):
                z = detections.z[r][mask]
                _ragged(rr, rec, times, f"{base}/detections/{name}", time, steps, mask.sum(axis=1), "points",
                        positions=z, colors=np.tile(colour, (len(z), 1)), radii=np.full(len(z), 4.0))
            events = births_and_deaths(truth, r)
            if events:
                k_ev = np.array([e[0] for e in events])
                rec.send_columns(f"/events/run{r}/truth", indexes=times(time[k_ev], k_ev),
                                 columns=rr.TextLog.columns(text=[f"target {t} {'born' if kind == 'birth' else 'dies'}"
                                                                  for _, t, kind in events],
                                                            level=["INFO"] * len(events)))
            for key in keys:
                _log_tracks(rr, rec, times, f"{base}/{key}", f"/events/run{r}/{key}", estimates[key], r, time, index)
        series = metric_time_series(metrics, experiment, keys, display_names, colours)
        if series:
            log_metric_series(rr, rec, times, series)
            truth_count = exists.sum(axis=-1).mean(axis=0).astype(float)
            rec.log("/metrics/cardinality/truth", rr.SeriesLines(names="truth", colors=TRUTH_COLOUR, widths=3.0),
                    static=True)
            rec.send_columns("/metrics/cardinality/truth", indexes=times(time, steps),
                             columns=rr.Scalars.columns(scalars=truth_count))


def _log_tracks(rr, rec, times, base: str, events: str, tracks, r: int, time: np.ndarray, index: list[int]) -> None:
    """A variant's reported tracks of run ``r``: points, ellipses, trails and the ids' first/last scans."""
    K = time.size
    steps = np.arange(K)
    track_id = np.asarray(tracks.track_id[r])
    reported = np.asarray(tracks.confirmed[r], dtype=bool) & (track_id >= 0)
    state = np.asarray(tracks.state[r], dtype=float)
    reported &= np.all(np.isfinite(state[..., index]), axis=-1)
    cov = np.asarray(tracks.covariance[r], dtype=float)
    mean = state[..., index][reported]
    ids = track_id[reported]
    counts = reported.sum(axis=1)
    colours = np.array([track_colour(i) for i in ids]).reshape(-1, 3)
    _ragged(rr, rec, times, f"{base}/tracks", time, steps, counts, "points", positions=mean, colors=colours,
            radii=np.full(len(ids), 7.0), labels=[str(i) for i in ids], show_labels=np.ones(len(ids), dtype=bool))
    P = cov[..., index, :][..., index][reported]
    P = np.where(np.all(np.isfinite(P), axis=(-1, -2))[:, None, None], P, 0.0)
    _ragged(rr, rec, times, f"{base}/ellipses", time, steps, counts, "strips",
            strips=list(covariance_ellipses(mean, P)) if len(ids) else [], colors=colours,
            radii=np.full(len(ids), 1.0))
    # trails: each reported track's positions over its last TRAIL scans
    where = {}
    for k in range(K):
        for slot in np.nonzero(reported[k])[0]:
            where.setdefault(int(track_id[k, slot]), []).append((k, state[k, slot, index]))
    trails, trail_colours, trail_counts = [], [], np.zeros(K, dtype=int)
    for k in range(K):
        for slot in np.nonzero(reported[k])[0]:
            i = int(track_id[k, slot])
            path = np.array([p for kk, p in where[i] if k - TRAIL < kk <= k])
            trails.append(path)
            trail_colours.append(track_colour(i))
            trail_counts[k] += 1
    _ragged(rr, rec, times, f"{base}/trails", time, steps, trail_counts, "strips", strips=trails,
            colors=np.array(trail_colours).reshape(-1, 3), radii=np.full(len(trails), 1.0))
    lines = []
    for i, visits in where.items():
        first, last = visits[0][0], visits[-1][0]
        lines.append((first, f"track {i} reported"))
        if last + 1 < K:
            lines.append((last + 1, f"track {i} no longer reported"))
    if lines:
        lines.sort()
        k_ev = np.array([k for k, _ in lines])
        rec.send_columns(events, indexes=times(time[k_ev], k_ev),
                         columns=rr.TextLog.columns(text=[text for _, text in lines], level=["INFO"] * len(lines)))


def _blueprint(rrb, runs: Sequence[int], keys: Sequence[str], display: Mapping[str, str], truth, gospa_c: float,
               gospa_p: float):
    """One 2-D view per variant (truth, detections, its tracks) on the left; GOSPA, its parts and the
    cardinality side by side on the right; the events below."""
    r0 = runs[0]
    base = f"/world/run{r0}"
    position = truth.state[r0][..., list(POSITION_INDEX)]
    finite = position[np.all(np.isfinite(position), axis=-1)]
    low, high = (finite.min(axis=0), finite.max(axis=0)) if finite.size else (np.array([-1e3, -1e3]), np.array([1e3, 1e3]))
    pad = 0.08 * np.max(high - low) + 50.0
    bounds = rrb.VisualBounds2D(x_range=[float(low[0] - pad), float(high[0] + pad)],
                                y_range=[float(-high[1] - pad), float(-low[1] + pad)])
    spatial = [rrb.Spatial2DView(origin="/world", name=f"{display.get(k, k)} (run {r0})",
                                 contents=[f"{base}/truth/**", f"{base}/detections/**", f"{base}/{k}/**"],
                                 spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME),
                                 visual_bounds=bounds) for k in keys]
    metric_views = [rrb.TimeSeriesView(origin=f"/metrics/{m}", name=name + (f" (c = {gospa_c:g} m, p = {gospa_p:g})"
                                                                             if m == "gospa" else ""),
                                       plot_legend=no_legend(rrb)) for m, name in METRIC_VIEWS]
    metric_views.append(rrb.TimeSeriesView(origin="/metrics/cardinality", name="targets reported (thick: truth)",
                                           plot_legend=no_legend(rrb)))
    metric_views.append(rrb.TextLogView(origin=f"/events/run{r0}", name=f"births, deaths, tracks (run {r0})"))
    labels = [display.get(k, k) for k in keys] + ["truth", "clutter"]
    right = rrb.Vertical(rrb.Grid(*metric_views, grid_columns=2), key_view(rrb, VARIANT_KEY, labels),
                         row_shares=[12, 1])
    left = rrb.Grid(*spatial, grid_columns=2 if len(spatial) <= 4 else 3)
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[3, 2]),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
