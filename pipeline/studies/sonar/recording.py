"""Write study 003's Rerun recording (``.rrd``): own-ship and target tracks in the world frame, the
sonar's passive bearings (lines) and active fixes (points), each architecture's estimated target
position with its 2-sigma ellipse side by side, the X / Y errors, the Monte Carlo RMSE and the
sonar mode (active / passive) on the timeline, with a blueprint in the same file.

The trackers estimate the RELATIVE state (target minus own-ship); the recording draws the estimated
target in the world frame: own-ship world position (known to the own-ship, the truth's "ownship"
label) + estimated relative position, and the ellipse of the relative position covariance centred
there (the own-ship position adds no uncertainty).

Layout of the entity tree (``r`` = a recorded Monte Carlo run, ``v`` = a variant key)::

    /world/run{r}/ownship                 static LineStrips2D of the own-ship track (faint) + current position
    /world/run{r}/ownship/path            a segment per step, shown up to the time cursor
    /world/run{r}/target                  static LineStrips2D of the true target track (faint) + current position
    /world/run{r}/target/path             a segment per step, shown up to the time cursor
    /world/run{r}/measurements/bearing    passive scans: a line from the own-ship along the measured
                                          bearing, BEARING_LINE_SCALE x the true range long; an empty
                                          row at the first active scan after a passive one (clears it)
    /world/run{r}/measurements/fix        active scans: the point own-ship + r (sin beta, cos beta); an
                                          empty row at the first passive scan after an active one
    /world/run{r}/{v}/track               estimated target track (own-ship + relative estimate): a
                                          segment per step, shown up to the time cursor
    /world/run{r}/{v}/estimate            current estimated target position
    /world/run{r}/{v}/covariance          2-sigma ellipse (polyline) of the relative position
                                          covariance, centred on the estimate: every
                                          ``ellipse_stride``-th step and at every mode switch only
    /errors/run{r}/{x,y}/{v}              estimate minus truth, east (x) and north (y) [m]
    /key/variants                         colour key: the variants, own-ship, target, fixes, bearings
    /sensor/mode                          StateChange "active" / "passive" at each switch (+ the first
                                          scan), shown by a StateTimelineView (Rerun 0.41, unstable)
    /sensor/active                        the same as a scalar step series, 1 = active, 0 = passive
    /sensor/events                        TextLog line at each switch
    /metrics/{metric}/{v}                 Monte Carlo averages per step (position_rmse[_x, _y], ...)
    /metrics/{nees,nis}/{v}_chi2_{lower,upper}   the 95 % chi-square band of the run-averaged NEES /
                                          NIS (the metrics' nees_lower / _upper, nis_lower / _upper),
                                          thin lines in the variant's lighter colour beside its line
    /config                               markdown: description, sonar schedule and noise, config yaml
    /world/frames/north_up, /world/frames/target_run{r}   frames the 2-D views look from (y = north
                                          up; the latter centred on run r's true target position)

Decimation: a 10 000 s case has 10 001 steps. Everything is logged at every step except the
covariance ellipses (48-point polylines, 4 variants: ~15 MB per run at every step), which are
logged every ``ellipse_stride`` (default 10) steps and at each mode switch; an ellipse stays on
screen until the next one. Tracks are a two-point segment per step (~1.7 MB more than static
strips for 4 variants x 10 001 steps); bearing lines and fixes are at every scan (a two-point strip
or one point each, small).

Every time-varying entity has the timelines ``time`` (duration, s) and ``step`` (sequence) and is
written with one ``send_columns`` call; only static things use ``log``. Rerun is imported lazily.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from pipeline.evaluation.metrics import axis_unit_of
from pipeline.data import Detections, Truth
from pipeline.views.blueprints import (fit_title, fit_titles, key_view, log_path, no_legend, path_overrides,
    whole_run as whole_run_axis)
from pipeline.views.recording import (log_north_up, atomic_recording, checked_record_runs, covariance_ellipses,
    FRAMES_PATH, FUTURE_ALPHA, log_config, log_keys, log_metric_series, metric_time_series, NORTH_UP_FRAME,
    path_part, PATH_SAFE, target_frame, time_columns, track_radius, VARIANT_KEY, xy_index)
from pipeline.views.colours import TRUTH_COLOUR, variant_colour

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

ACTIVE, PASSIVE = "active", "passive"
MODE_LABELS = {ACTIVE: "active (bearing + range)", PASSIVE: "passive (bearing only)"}
STATE_LABELS = {ACTIVE: "active", PASSIVE: "passive"}      # short: they fit the timeline's bands
ELLIPSE_STRIDE = 10               # covariance ellipses every 10th step (+ at each mode switch)
BEARING_LINE_SCALE = 1.2          # a passive bearing line is 1.2 x the true range long
TIME_SERIES_METRICS = ("position_rmse", "position_rmse_x", "position_rmse_y", "velocity_rmse", "nees", "nis",
                       "position_rmse_over_bound", "position_rmse_over_bound_model")
# Titles (tab names) of the metric views, short enough for a tab: each variant's run average with its
# 95 % band (thin, lighter); the config document says more (NEES: 6 dof, NaN while KF + MGEKF runs
# its 4-state KF; NIS: 2 dof active, 1 dof passive)
_VIEW_TITLES = {
    "nees": "NEES (thin: 95 % band)",
    "nis": "NIS (thin: 95 % band)",
    "position_rmse_over_bound": "RMSE / sqrt(PCRLB)",
    "position_rmse_over_bound_model": "RMSE / sqrt(model PCRLB)",
}
_OWNSHIP_COLOUR = (255, 215, 0)
_FIX_COLOUR = (255, 110, 220)
KEY_EXTRA = (("own-ship", _OWNSHIP_COLOUR), ("target", TRUTH_COLOUR), ("active fix", _FIX_COLOUR),
             ("passive bearing", (150, 150, 150)))


def key_extra(zoom: float) -> list:
    """The key's entries beside the variants, with the target-centred views' half width."""
    return list(KEY_EXTRA) + [(f"target-centred: ±{zoom / 1000:.2g} km", (110, 110, 110))]
_BEARING_COLOUR = (150, 150, 150, 110)
_MODE_COLOURS = {ACTIVE: 0xFF6EDCFF, PASSIVE: 0x5A6E8CFF}


def sonar_mode(detections: Detections) -> np.ndarray:
    """(K,) bool: True at active scans (``Detections.sensor`` == 1, bearing + range)."""
    return np.asarray(detections.sensor) == 1


def mode_switches(active: np.ndarray) -> np.ndarray:
    """Steps where the mode changes, with step 0 first (the starting mode)."""
    active = np.asarray(active, dtype=bool)
    if not active.size:
        return np.empty(0, dtype=np.int64)
    return np.r_[0, np.nonzero(active[1:] != active[:-1])[0] + 1].astype(np.int64)


def _check_inputs(truth: Truth, detections: Detections, estimates: Mapping[str, TrackEstimate],
                  record_runs: Sequence[int]) -> list[int]:
    R = truth.runs
    runs = checked_record_runs(record_runs, R)
    K = np.asarray(truth.time).shape[0]
    if "ownship" not in truth.labels:
        raise ValueError("truth: no 'ownship' label (own-ship x, y, vx, vy in the world frame); the sonar "
                         "recording draws the world frame from it (use pipeline.studies.sonar.scenario.SonarEncounter)")
    own = np.shape(truth.labels["ownship"])
    if own[:2] != (R, K) or own[-1] < 2:
        raise ValueError(f"truth.labels['ownship']: shape {own} must be (R, K, 1, 4) = ({R}, {K}, 1, 4)")
    if detections.runs != R:
        raise ValueError(f"detections have {detections.runs} runs but the truth has {R}")
    if detections.z.shape[1] != K or np.shape(detections.sensor) != (K,) or detections.z.shape[-1] != 2:
        raise ValueError(f"detections: z {detections.z.shape} and sensor {np.shape(detections.sensor)} must be "
                         f"(R, K, 1, 2) (bearing, range) and (K,) on the truth's {K} steps")
    for key, est in estimates.items():
        if not PATH_SAFE.match(key):
            raise ValueError(f"variant key {key!r} is not path-safe (allowed: letters, digits, '_', '-', '.')")
        n = len(truth.state_names)
        if est.state.shape != (R, K, n):
            raise ValueError(f"estimate {key!r}: state shape {est.state.shape}, expected {(R, K, n)} (R runs, "
                             f"the truth's K steps, its state {list(truth.state_names)})")
        if est.covariance.shape != (R, K, n, n):
            raise ValueError(f"estimate {key!r}: covariance shape {est.covariance.shape}, expected {(R, K, n, n)}")
    return runs


def _zoom_half(truth_rel: np.ndarray, estimates: Mapping[str, TrackEstimate], xy: list[int], r: int) -> float:
    """Half width [m] of the target-centred views: 4 x the median over variants of each one's median
    position error in the recorded run, in [500, 20000] m. At that scale the active phases' 2-sigma
    ellipses (tens to a few hundred metres) are rings of several pixels; the passive phases' ones
    are needles along the bearing (range unobserved: 1-30 km long, tens to hundreds of metres wide)
    that cross the view. (1.5 x the 90th percentile, the scale before, drew the active ellipses as
    2-7 px dots.)"""
    q = []
    for est in estimates.values():
        e = np.linalg.norm(est.state[r][:, xy] - truth_rel, axis=-1)
        e = e[np.isfinite(e)]
        if e.size:
            q.append(np.median(e))
    return float(np.clip(4.0 * np.median(q), 500.0, 20000.0)) if q else 3000.0


def write_sonar_recording(path: Path, *, experiment: str, truth: Truth, detections: Detections,
                          estimates: Mapping[str, TrackEstimate], display_names: Mapping[str, str],
                          metrics: "pl.DataFrame | None", record_runs: Sequence[int], sensor,
                          config_text: str = "", description: str = "",
                          ellipse_stride: int = ELLIPSE_STRIDE) -> None:
    """Write ``path`` (an ``.rrd`` with its default blueprint) for the runs in ``record_runs``.

    ``truth``: time (K,), state (R, K, 1, 6) relative (rx, ry, vx, vy, ax, ay), labels "ownship"
    (R, K, 1, 4) own-ship world (x, y, vx, vy) and optionally "target_world" (R, K, 1, 4) (else
    own-ship + relative); ``detections``: sensor (K,) 1 = active, 0 = passive, z (R, K, 1, 2)
    (bearing from north clockwise [rad], range [m], NaN when passive); ``estimates``: variant key
    (path-safe) -> relative :class:`TrackEstimate` (R, K, 6), in display order (NaN acceleration
    while KF + MGEKF runs its 4-state KF is fine: only the position is drawn); ``metrics``: the long
    metrics frame (variant_key, metric, step, time, value, ...) or None; ``sensor``: the sonar
    (``active_intervals``, ``bearing_std`` [rad], ``range_std`` [m]; only described in /config, the
    mode drawn is the detections'). ``ellipse_stride``: covariance ellipses every that many steps
    (and at each mode switch). The file is written to a temporary name beside ``path`` and moved
    onto it only once complete. See the module docstring for the entity tree.
    """
    path = Path(path)
    record_runs = _check_inputs(truth, detections, estimates, record_runs)
    if int(ellipse_stride) < 1:
        raise ValueError(f"ellipse_stride: {ellipse_stride} must be >= 1")
    ellipse_stride = int(ellipse_stride)
    R = truth.runs
    xy = xy_index(truth.state_names, "truth")
    variant_keys = list(estimates)
    colours = {key: variant_colour(i) for i, key in enumerate(variant_keys)}
    display = {key: str(display_names.get(key, key)) for key in variant_keys}
    metric_series = metric_time_series(metrics, experiment, variant_keys, display, colours)

    time = np.asarray(truth.time, dtype=np.float64)
    K = time.size
    active = sonar_mode(detections)
    switches = mode_switches(active)
    ownship = np.asarray(truth.labels["ownship"], dtype=np.float64)[:, :, 0, :2]             # (R, K, 2)
    relative = np.asarray(truth.state, dtype=np.float64)[:, :, 0][..., xy]                   # (R, K, 2)
    if "target_world" in truth.labels:
        target = np.asarray(truth.labels["target_world"], dtype=np.float64)[:, :, 0, :2]
    else:
        target = ownship + relative
    zoom = _zoom_half(relative[record_runs[0]], estimates, xy, record_runs[0]) if record_runs else 3000.0

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    blueprint = _sonar_blueprint(rrb, record_runs, variant_keys, display, metric_series, ownship, target, zoom)
    doc = (f"{description.strip()}\n\n" if description else "") + _sensor_doc(sensor, active, time, ellipse_stride)

    with atomic_recording(rr, path, experiment, blueprint) as rec:
        times = time_columns(rr)
        ui = rr.Radius.ui_points
        flip = np.array([1.0, -1.0, 1.0])
        log_north_up(rr, rec)
        steps_all = np.arange(K, dtype=np.int64)
        for r in record_runs:
            _log_run(rr, rec, times, ui, r, time, ownship[r], target[r], relative[r], detections, active,
                     switches, estimates, xy, colours, display, ellipse_stride, flip)

        # ---- sensor mode: state timeline, scalar step series, switch log ------------------------
        labels = [ACTIVE if active[k] else PASSIVE for k in switches.tolist()]
        rec.log("/sensor/mode", rr.StateConfiguration(values=[ACTIVE, PASSIVE],
                                                      labels=[STATE_LABELS[ACTIVE], STATE_LABELS[PASSIVE]],
                                                      colors=[_MODE_COLOURS[ACTIVE], _MODE_COLOURS[PASSIVE]]),
                static=True)
        if switches.size:
            rec.send_columns("/sensor/mode", indexes=times(time[switches], switches),
                             columns=rr.StateChange.columns(state=labels))
            rec.send_columns("/sensor/events", indexes=times(time[switches], switches),
                             columns=rr.TextLog.columns(text=[MODE_LABELS[m] for m in labels],
                                                        level=["INFO"] * switches.size))
        rec.log("/sensor/active", rr.SeriesLines(names="sonar active (1) / passive (0)", colors=_FIX_COLOUR,
                                                 widths=1.5), static=True)
        rec.send_columns("/sensor/active", indexes=times(time, steps_all),
                         columns=rr.Scalars.columns(scalars=active.astype(np.float64)))

        log_metric_series(rr, rec, times, metric_series)
        log_keys(rr, rec, variant_keys, display, colours, extra=key_extra(zoom))
        log_config(rr, rec, experiment, doc, config_text, record_runs, R)


def _log_run(rr, rec, times, ui, r: int, time: np.ndarray, own: np.ndarray, target: np.ndarray,
             relative: np.ndarray, detections: Detections, active: np.ndarray, switches: np.ndarray,
             estimates: Mapping[str, TrackEstimate], xy: list[int], colours: dict, display: dict,
             ellipse_stride: int, flip: np.ndarray) -> None:
    world = f"/world/run{r}"
    K = time.size

    # ---- own-ship and target: path up to now, the whole track faint, current positions; frame --
    steps_all = np.arange(K, dtype=np.int64)
    for name, track, colour in (("ownship", own, _OWNSHIP_COLOUR), ("target", target, TRUTH_COLOUR)):
        ok = np.isfinite(track).all(-1)
        steps = np.nonzero(ok)[0]
        rec.log(f"{world}/{name}", rr.LineStrips2D([track[ok]], colors=(*colour, FUTURE_ALPHA), radii=ui(0.5),
                                                   draw_order=12.0, labels=name, show_labels=False), static=True)
        log_path(rr, rec, times, f"{world}/{name}/path", time, steps_all, track, ok, colour=colour, radius=0.9,
                 draw_order=16.0)
        rec.log(f"{world}/{name}", rr.Points2D.from_fields(colors=colour, radii=ui(5.0), draw_order=30.0),
                static=True)
        rec.send_columns(f"{world}/{name}", indexes=times(time[steps], steps),
                         columns=rr.Points2D.columns(positions=track[ok]))
    steps = np.nonzero(np.isfinite(target).all(-1))[0]
    if steps.size:
        rec.send_columns(f"{FRAMES_PATH}/{target_frame(r)}", indexes=times(time[steps], steps),
                         columns=rr.Transform3D.columns(
                             translation=np.c_[target[steps], np.zeros(steps.size)],
                             scale=np.tile(flip, (steps.size, 1)), parent_frame=["tf#/world"] * steps.size,
                             child_frame=[target_frame(r)] * steps.size))

    # ---- measurements: passive bearing lines, active fixes; each cleared when the mode changes --
    z = np.asarray(detections.z[r], dtype=np.float64)[:, 0]                                 # (K, 2)
    direction = np.stack([np.sin(z[:, 0]), np.cos(z[:, 0])], axis=-1)                      # (K, 2) east, north
    true_range = np.hypot(relative[:, 0], relative[:, 1])
    own_ok = np.isfinite(own).all(-1)
    bearing_ok = ~active & own_ok & np.isfinite(z[:, 0]) & np.isfinite(true_range)
    fix_ok = active & own_ok & np.isfinite(z).all(-1)
    lines = np.stack([own, own + (BEARING_LINE_SCALE * true_range)[:, None] * direction], axis=1)   # (K, 2, 2)
    fixes = own + z[:, 1:2] * direction
    first_active = switches[active[switches]]
    first_passive = switches[~active[switches]]
    for entity, ok, clear, cols, style in (
            ("bearing", bearing_ok, first_active, lambda m: rr.LineStrips2D.columns(strips=lines[m]),
             rr.LineStrips2D.from_fields(colors=_BEARING_COLOUR, radii=ui(0.5), draw_order=10.0)),
            ("fix", fix_ok, first_passive, lambda m: rr.Points2D.columns(positions=fixes[m]),
             rr.Points2D.from_fields(colors=_FIX_COLOUR, radii=ui(3.5), draw_order=20.0))):
        rec.log(f"{world}/measurements/{entity}", style, static=True)
        # rows with data, and empty rows where the other mode starts (rows[ok[rows]] carry data)
        rows = np.union1d(np.nonzero(ok)[0], clear[clear > 0]).astype(np.int64)
        if rows.size:
            rec.send_columns(f"{world}/measurements/{entity}", indexes=times(time[rows], rows),
                             columns=cols(rows[ok[rows]]).partition(ok[rows].astype(np.int64)))

    # ---- per variant: estimated target world position, track, 2-sigma ellipse, errors ---------
    track_radii = track_radius(list(estimates))
    decimated = np.zeros(K, dtype=bool)
    decimated[::ellipse_stride] = True
    decimated[switches] = True
    decimated[-1] = True
    for key, est in estimates.items():
        colour = colours[key]
        base = f"{world}/{key}"
        rel = np.asarray(est.state[r], dtype=np.float64)[:, xy]                             # (K, 2)
        P = np.asarray(est.covariance[r], dtype=np.float64)[:, xy][:, :, xy]                # (K, 2, 2)
        pos = own + rel
        good = np.isfinite(pos).all(-1)
        steps = np.nonzero(good)[0]
        # the track up to now, thin and a little transparent, so the estimate and its ellipse stand out
        log_path(rr, rec, times, f"{base}/track", time, steps_all, pos, good, colour=(*colour, 170),
                 radius=track_radii[key], draw_order=15.0)
        rec.log(f"{base}/estimate", rr.Points2D.from_fields(colors=colour, radii=ui(5.0), draw_order=40.0),
                static=True)
        rec.send_columns(f"{base}/estimate", indexes=times(time[steps], steps),
                         columns=rr.Points2D.columns(positions=pos[good]))
        # the ellipse bold and above the bearing lines and tracks: in passive phases it is a needle
        # along the bearing (the range is unobserved) and would hide under them
        rec.log(f"{base}/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(2.0), draw_order=45.0),
                static=True)
        shown = good & decimated & np.isfinite(P).all((-1, -2))
        steps = np.nonzero(shown)[0]
        if steps.size:
            rec.send_columns(f"{base}/covariance", indexes=times(time[steps], steps),
                             columns=rr.LineStrips2D.columns(strips=covariance_ellipses(pos[shown], P[shown])))
        err = rel - relative                                                                 # (K, 2)
        for i, axis in enumerate(("x", "y")):
            entity = f"/errors/run{r}/{axis}/{key}"
            steps = np.nonzero(np.isfinite(err[:, i]))[0]
            rec.log(entity, rr.SeriesLines(names=display[key], colors=colour, widths=1.5), static=True)
            rec.send_columns(entity, indexes=times(time[steps], steps),
                             columns=rr.Scalars.columns(scalars=err[steps, i]))


def _sensor_doc(sensor, active: np.ndarray, time: np.ndarray, ellipse_stride: int) -> str:
    intervals = getattr(sensor, "active_intervals", None)
    parts = []
    if intervals is not None:
        parts.append("Active sonar (bearing + range) in " + (", ".join(f"[{a:g}, {b:g}) s" for a, b in intervals)
                                                             or "no interval") + "; passive (bearing only) otherwise.")
    noise = []
    if getattr(sensor, "bearing_std", None) is not None:
        noise.append(f"σ_β = {np.degrees(float(sensor.bearing_std)):g} deg")
    if getattr(sensor, "range_std", None) is not None:
        noise.append(f"σ_r = {float(sensor.range_std):g} m")
    if noise:
        parts.append("Noise: " + ", ".join(noise) + ".")
    parts.append(f"{int(active.sum())} active and {int((~active).sum())} passive scans of {time.size}.")
    parts.append("Tabs: NEES is the run average (χ² 6 dof; NaN while KF + MGEKF runs its 4-state KF), NIS the run "
                 "average (χ² 2 dof active, 1 dof passive), each with its 95 % band as thin lighter lines.")
    parts.append(f"Grey lines: passive bearings ({BEARING_LINE_SCALE:g} x the true range long); pink points: active "
                 f"fixes. Estimated target = own-ship + relative estimate; ellipses: 2σ of the relative position "
                 f"covariance, every {ellipse_stride} steps and at each mode switch.")
    return "\n\n".join(parts) + "\n"


def _sonar_blueprint(rrb, record_runs: list[int], variant_keys: list[str], display: Mapping[str, str],
                     metric_series: dict, ownship: np.ndarray, target: np.ndarray, zoom: float):
    """Top: per variant a target-centred view (own-ship, target, bearings, fixes, that variant; the
    zoom says its half width), and one world view (north up) of the scene with every variant; tracks
    up to the time cursor. Then the colour key, the sonar mode as a
    state timeline, the recorded run's X and Y errors and the Monte Carlo position RMSE; bottom tabs:
    X / Y RMSE, velocity RMSE, NEES and NIS (each variant with its 95 % chi-square band as thin
    lighter lines), the mode as a scalar with the switch log, the config. No legends: the key."""
    r0 = record_runs[0] if record_runs else None
    whole_run = whole_run_axis(rrb)
    legend = no_legend(rrb)
    rows, shares = [], []
    if record_runs:
        pts = np.concatenate([ownship[record_runs].reshape(-1, 2), target[record_runs].reshape(-1, 2)])
        pts = pts[np.isfinite(pts).all(-1)]
        lo, hi = (pts.min(0), pts.max(0)) if pts.size else (np.zeros(2), np.zeros(2))
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1000.0) * 1.08
        overview = rrb.VisualBounds2D(x_range=[centre[0] - half[0], centre[0] + half[0]],
                                      y_range=[-centre[1] - half[1], -centre[1] + half[1]])   # north_up: y negated
        follow = rrb.VisualBounds2D(x_range=[-zoom, zoom], y_range=[-zoom, zoom])
        width = 1600.0 / (len(variant_keys) + 1)
        runs = f"runs {', '.join(map(str, record_runs))}" if len(record_runs) > 1 else f"run {r0}"
        near = fit_titles(width, [[f"{display[k]} · run {r0}, target-centred", f"{display[k]} · target-centred",
                                   display[k]] for k in variant_keys])
        columns = []
        world = f"/world/run{r0}"
        for key, title in zip(variant_keys, near):
            columns.append(rrb.Spatial2DView(
                origin="/world", name=title,
                contents=[f"{world}/ownship/**", f"{world}/target/**", f"{world}/measurements/**", f"{world}/{key}/**"],
                overrides=path_overrides(rrb, [f"{world}/ownship/path", f"{world}/target/path", f"{world}/{key}/track"]),
                spatial_information=rrb.SpatialInformation(target_frame=target_frame(r0)), visual_bounds=follow))
        # one view of the whole scene with every variant: at that scale their estimates coincide
        everything, paths = [], []
        for r in record_runs:
            world = f"/world/run{r}"
            everything += [f"{world}/ownship/**", f"{world}/target/**", f"{world}/measurements/**"] + \
                [f"{world}/{k}/**" for k in variant_keys]
            paths += [f"{world}/ownship/path", f"{world}/target/path"] + [f"{world}/{k}/track" for k in variant_keys]
        columns.append(rrb.Spatial2DView(
            origin="/world", name=fit_title(width, f"{runs}: world (north up), every variant", "world, north up", "world"),
            contents=everything, overrides=path_overrides(rrb, paths),
            spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME), visual_bounds=overview))
        rows.append(rrb.Horizontal(*columns))
        shares.append(5.0)
    rows.append(key_view(rrb, VARIANT_KEY, [display[k] for k in variant_keys] + [label for label, _ in key_extra(zoom)]))
    shares.append(0.5)

    rows.append(rrb.StateTimelineView(origin="/sensor/mode", name="sonar mode: active (bearing + range) / passive "
                                      "(bearing only)", time_view=whole_run))
    shares.append(1.5)

    plots = []
    if r0 is not None:
        for axis, word in (("x", "east"), ("y", "north")):
            plots.append(rrb.TimeSeriesView(origin=f"/errors/run{r0}/{axis}", axis_x=whole_run, plot_legend=legend,
                                            name=f"run {r0}: {axis} ({word}) error, estimate − truth [m]"))
    present = {m for m, _ in metric_series}
    if "position_rmse" in present:
        plots.append(rrb.TimeSeriesView(origin="/metrics/position_rmse", axis_x=whole_run, plot_legend=legend,
                                        name="position RMSE [m] (all runs)"))
    if plots:
        rows.append(rrb.Horizontal(*plots))
        shares.append(2.6)

    tabs = []
    for m in TIME_SERIES_METRICS[1:]:
        if m in present:
            title = _VIEW_TITLES.get(m, f"{m} [{axis_unit_of(m)}]")
            tabs.append(rrb.TimeSeriesView(origin=f"/metrics/{path_part(m)}", axis_x=whole_run, plot_legend=legend,
                                           name=title))
    be = rrb.encodings
    log_columns = rrb.TextLogColumns(
        timeline_columns=[be.TimelineColumn("time"), be.TimelineColumn("step", visible=False)],
        text_log_columns=[be.TextLogColumn("Body"), be.TextLogColumn("EntityPath", visible=False),
                          be.TextLogColumn("LogLevel", visible=False)])
    tabs.append(rrb.Horizontal(
        rrb.TimeSeriesView(origin="/sensor/active", axis_x=whole_run, axis_y=rrb.ScalarAxis(range=(-0.1, 1.1)),
                           plot_legend=legend, name="sonar active (1) / passive (0)"),
        rrb.TextLogView(origin="/sensor/events", name="mode switches", columns=log_columns),
        column_shares=[3.0, 1.5], name="sonar mode"))
    tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    rows.append(rrb.Tabs(*tabs, active_tab=0))
    shares.append(2.2)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
