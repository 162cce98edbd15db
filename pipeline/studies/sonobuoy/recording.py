"""Write study 004's Rerun recording (``.rrd``): the observer, the drifting sonobuoys and the target
in the world frame, every scan's bearing lines (clutter coloured apart), and per filter side by
side the estimated target and buoys with their 2-sigma ellipses and, for particle filters that
kept one, the particle cloud coloured by mode; below, the Monte Carlo RMSE / median error / buoy
RMSE / NEES, the mode probabilities and the effective sample size, with a blueprint in the file.

Particle cloud (optional): the filters report moments only. A particle filter may add the extras
``"particles"`` float (R', K, P, 20) and ``"particle_modes"`` int (R', K, P) (mode 0 CV, 1 left /
Omega > 0, 2 right / Omega < 0; -1 and NaN rows where not kept), R' = R (indexed by run) or
R' = len(record_runs) (the recorded runs, in ``record_runs`` order); e.g.
``MultipleModelParticleFilter(snapshot_particles=200)``. At most ``max_particles`` of the P are
drawn (evenly spaced). Without them, or for a run they do not cover, no cloud is drawn and a line
in ``/notes`` says so.

Layout of the entity tree (``r`` = a recorded Monte Carlo run, ``v`` = a variant key,
``i`` = buoy 1..4)::

    /world/observer                         static: the observer (fixed)
    /world/run{r}/truth                     static LineStrips2D of the target track (faint) + current position
    /world/run{r}/truth/path                a segment per step, shown up to the time cursor
    /world/run{r}/buoys/{i}                 static LineStrips2D of buoy i's true track (faint) + current position
    /world/run{r}/buoys/{i}/path            a segment per step, shown up to the time cursor
    /world/run{r}/bearings/target/nominal   per scan: a line from each TRUE buoy position along the
    /world/run{r}/bearings/target/clutter   target bearing it measured, BEARING_LINE_SCALE x the true
                                            buoy-target range long; nominal and clutter returns
                                            (Detections.target == -1) apart; none where missed
    /world/run{r}/bearings/buoys/nominal    per scan: a line from the observer along each buoy bearing,
    /world/run{r}/bearings/buoys/clutter    BEARING_LINE_SCALE x the true observer-buoy range long
    /world/run{r}/{v}/track                 estimated target track, a segment per step (up to the cursor)
    /world/run{r}/{v}/estimate              current estimated target position
    /world/run{r}/{v}/covariance            2-sigma ellipse (polyline) of the target position block
    /world/run{r}/{v}/buoys                 current estimated buoy positions (4 points)
    /world/run{r}/{v}/buoys/covariance      2-sigma ellipses of each buoy's position block
    /world/run{r}/{v}/buoys/track           estimated buoy tracks (faint), segments (up to the cursor)
    /world/run{r}/{v}/particles             the cloud's target positions, coloured by mode (if kept)
    /world/run{r}/{v}/particles/buoys       the cloud's buoy positions, faint (if kept)
    /variants/{v}/run{r}/mode_probability/{cv,ccw,cw}   the filter's mode probabilities, run r
    /variants/{v}/run{r}/ess                the effective sample size, run r
    /truth/run{r}/turning                   1 while the true target turns, else 0
    /metrics/{metric}/{v}                   Monte Carlo per-step metrics (position_rmse,
                                            position_median_error, buoy_position_rmse, nees_position,
                                            ess, mode_probability_{cv,ccw,cw}: the latter in mode colours)
    /reference/nees_position/{lower,upper}  95 % band of the mean NEES of R runs: chi2(2R) / R
    /notes                                  TextLog (step 0): what is not drawn and why (no cloud, ...)
    /key/variants                           colour key: variants, truth, bearings, clutter, modes
    /config                                 markdown: description, sensor, legend, config yaml
    /world/frames/north_up                  the frame the 2-D views look from (y = north up)

Every time-varying entity has the timelines ``time`` (duration, s) and ``step`` (sequence) and is
written with one ``send_columns`` call; only static things use ``log``. Rerun is imported lazily.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from filters.particle import MODE_NAMES
from pipeline.data import Detections, Truth
from pipeline.views.blueprints import (fit_titles, key_view, log_path, no_legend, path_overrides,
    whole_run as whole_run_axis)
from pipeline.views.colours import MODE_COLOURS
from pipeline.views.recording import (log_north_up, atomic_recording, checked_record_runs, covariance_ellipses,
    FUTURE_ALPHA, log_config, log_keys, log_metric_series, metric_time_series, NORTH_UP_FRAME, path_part, PATH_SAFE,
    time_columns, track_radius, VARIANT_KEY, xy_index)
from pipeline.views.colours import lighter as lighter_colour, TRUTH_COLOUR, variant_colour
from pipeline.evaluation.metrics import axis_unit_of

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

BUOYS = 4
SLOTS = 2 * BUOYS                  # bearing slots 0-3: the target from buoy i; 4-7: buoy i from the observer
CLUTTER = -1                       # Detections.target of a clutter return
BEARING_LINE_SCALE = 1.3           # a bearing line is 1.3 x the true range long
MAX_PARTICLES = 200                # at most this many particles of a kept cloud are drawn per scan
MODE_LABELS = {"cv": "CV", "ccw": "left turn (Ω > 0)", "cw": "right turn (Ω < 0)"}
# the modes' colours are pipeline.views.colours.MODE_COLOURS (the report's mode figure uses them too)
PLOTTED_METRICS = ("position_rmse", "position_median_error", "buoy_position_rmse", "nees_position")
_NOMINAL_COLOUR = (160, 160, 160, 120)
_CLUTTER_COLOUR = (235, 70, 70, 150)
_OBSERVER_COLOUR = (255, 255, 255)
_BUOY_COLOUR = (200, 200, 200)
_BAND_COLOUR = (130, 130, 130)


def _check_inputs(truth: Truth, detections: Detections, estimates: Mapping[str, TrackEstimate],
                  record_runs: Sequence[int], sensor) -> list[int]:
    R = truth.runs
    runs = checked_record_runs(record_runs, R)
    observer = np.asarray(getattr(sensor, "observer_position", np.full(1, np.nan)), dtype=np.float64)
    if observer.shape != (2,) or not np.isfinite(observer).all():
        raise ValueError(f"sensor: {type(sensor).__name__} has no finite observer_position (east, north); the sonobuoy "
                         f"recording draws the buoy bearings from it (use pipeline.studies.sonobuoy.sensor.SonobuoyBearings)")
    K = np.asarray(truth.time).shape[0]
    n = len(truth.state_names)
    if truth.state.shape != (R, K, 1, n):
        raise ValueError(f"truth: state shape {truth.state.shape} must be (R, K, 1, {n}) (one augmented object)")
    if detections.runs != R:
        raise ValueError(f"detections have {detections.runs} runs but the truth has {R}")
    if detections.z.shape[:3] != (R, K, SLOTS) or np.shape(detections.target) != (R, K, SLOTS) \
            or np.shape(detections.detected) != (R, K, SLOTS):
        raise ValueError(f"detections: z {detections.z.shape}, target {np.shape(detections.target)} and detected "
                         f"{np.shape(detections.detected)} must be (R, K, 8[, 1]) = ({R}, {K}, {SLOTS}): the 8 "
                         f"bearing slots of SonobuoyBearings on the truth's {K} steps")
    for key, est in estimates.items():
        if not PATH_SAFE.match(key):
            raise ValueError(f"variant key {key!r} is not path-safe (allowed: letters, digits, '_', '-', '.')")
        if est.state.shape != (R, K, n):
            raise ValueError(f"estimate {key!r}: state shape {est.state.shape}, expected {(R, K, n)} (R runs, the "
                             f"truth's K steps, its state {list(truth.state_names)} in that order)")
        if est.covariance.shape != (R, K, n, n):
            raise ValueError(f"estimate {key!r}: covariance shape {est.covariance.shape}, expected {(R, K, n, n)}")
        has = ("particles" in est.extras, "particle_modes" in est.extras)
        if any(has) and not all(has):
            raise ValueError(f"estimate {key!r}: extras carry {'particles' if has[0] else 'particle_modes'} without "
                             f"{'particle_modes' if has[0] else 'particles'}; a particle cloud needs both")
        if all(has):
            shape, modes = np.shape(est.extras["particles"]), np.shape(est.extras["particle_modes"])
            if len(shape) != 4 or shape[0] not in (R, len(runs)) or shape[1] != K or shape[3] != n \
                    or modes != shape[:3]:
                raise ValueError(f"estimate {key!r}: extras particles {shape} and particle_modes {modes} must be "
                                 f"(R', K, P, {n}) and (R', K, P) with K = {K} and R' = {R} (every run) or "
                                 f"{len(runs)} (the recorded runs {runs}, in that order)")
    return runs


def _buoy_index(names: Sequence[str]) -> np.ndarray:
    """(4, 2) state indices of buoy i's (x, y), buoys 1..4 (``b{i}_x``, ``b{i}_y``)."""
    names = list(names)
    wanted = [(f"b{i}_x", f"b{i}_y") for i in range(1, BUOYS + 1)]
    missing = [c for pair in wanted for c in pair if c not in names]
    if missing:
        raise ValueError(f"truth: state_names {names} lack {missing}; the sonobuoy recording draws four buoys")
    return np.array([[names.index(a), names.index(b)] for a, b in wanted])


def particle_cloud(est: TrackEstimate, run: int, record_runs: Sequence[int], runs: int,
                   max_particles: int = MAX_PARTICLES) -> tuple[np.ndarray, np.ndarray] | None:
    """Run ``run``'s kept particles (K, P', n) and modes (K, P') (-1 where none), P' <= max_particles
    evenly spaced of the P kept; None when the estimate keeps no cloud or none for that run."""
    if "particles" not in est.extras or "particle_modes" not in est.extras:
        return None
    cloud, modes = est.extras["particles"], est.extras["particle_modes"]
    row = run if np.shape(cloud)[0] == runs else list(record_runs).index(run)
    X = np.asarray(cloud[row], dtype=np.float64)                                     # (K, P, n)
    m = np.asarray(modes[row]).astype(np.int64)                                       # (K, P)
    P = X.shape[1]
    if P > max_particles:
        keep = np.linspace(0, P - 1, max_particles).round().astype(np.int64)
        X, m = X[:, keep], m[:, keep]
    m = np.where((m >= 0) & (m < len(MODE_NAMES)) & np.isfinite(X).all(-1), m, -1)
    return (X, m) if (m >= 0).any() else None


def write_sonobuoy_recording(path: Path, *, experiment: str, truth: Truth, detections: Detections,
                             estimates: Mapping[str, TrackEstimate], display_names: Mapping[str, str],
                             metrics: "pl.DataFrame | None", record_runs: Sequence[int], sensor,
                             config_text: str = "", description: str = "",
                             max_particles: int = MAX_PARTICLES) -> None:
    """Write ``path`` (an ``.rrd`` with its default blueprint) for the runs in ``record_runs``.

    ``truth``: time (K,), state (R, K, 1, 20) (target x, y, vx, vy, then buoys 1..4; x east,
    y north), label "turn_mode" (R, K, 1) (1 CV, 2 left, 3 right; optional); ``detections``: z
    (R, K, 8, 1) bearings from north clockwise [rad], NaN where missed, slots 0-3 the target from
    buoy i, 4-7 buoy i from the observer, target (R, K, 8) -1 for clutter; ``estimates``: variant
    key (path-safe) -> :class:`TrackEstimate` (R, K, 20), in display order, with optional extras
    "mode_probabilities" (R, K, 3), "ess" (R, K) and a particle cloud (module docstring);
    ``metrics``: the long metrics frame (variant_key, metric, step, time, value, ...) or None;
    ``sensor``: the ``SonobuoyBearings`` (``observer_position`` is drawn, the noise described).
    ``max_particles``: at most that many particles of a cloud drawn per scan. The file is written
    to a temporary name beside ``path`` and moved onto it only once complete.
    """
    path = Path(path)
    record_runs = _check_inputs(truth, detections, estimates, record_runs, sensor)
    if int(max_particles) < 1:
        raise ValueError(f"max_particles: {max_particles} must be >= 1")
    R = truth.runs
    xy = xy_index(truth.state_names, "truth")
    buoy_xy = _buoy_index(truth.state_names)
    variant_keys = list(estimates)
    colours = {key: variant_colour(i) for i, key in enumerate(variant_keys)}
    display = {key: str(display_names.get(key, key)) for key in variant_keys}
    metric_series = _mode_styled(metric_time_series(metrics, experiment, variant_keys, display, colours), R)
    time = np.asarray(truth.time, dtype=np.float64)
    observer = np.asarray(sensor.observer_position, dtype=np.float64)
    state = np.asarray(truth.state, dtype=np.float64)[:, :, 0]                          # (R, K, n)

    clouds, notes = {}, []
    for key, est in estimates.items():
        for r in record_runs:
            cloud = particle_cloud(est, r, record_runs, R, int(max_particles))
            if cloud is not None:
                clouds[key, r] = cloud
            elif "particles" in est.extras:
                notes.append(f"{display[key]}: no particle cloud for run {r} (the filter kept none for it).")
        if "particles" not in est.extras:
            if "mode_probabilities" in est.extras or "ess" in est.extras:
                notes.append(f"{display[key]}: no particle cloud drawn (the estimate has no 'particles' / "
                             f"'particle_modes' extras; MultipleModelParticleFilter(snapshot_particles=P) keeps one).")
            else:
                notes.append(f"{display[key]}: no particle cloud (not a particle filter).")

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    blueprint = _sonobuoy_blueprint(rrb, record_runs, variant_keys, display, estimates, metric_series,
                                    state[record_runs], xy, buoy_xy, observer)
    doc = (f"{description.strip()}\n\n" if description else "") + _sensor_doc(sensor, notes)

    with atomic_recording(rr, path, experiment, blueprint) as rec:
        times = time_columns(rr)
        ui = rr.Radius.ui_points
        log_north_up(rr, rec)
        rec.log("/world/observer", rr.Points2D([observer], colors=_OBSERVER_COLOUR, radii=ui(7.0), labels="observer",
                                               show_labels=True, draw_order=50.0), static=True)
        for r in record_runs:
            _log_run(rr, rec, times, ui, r, time, state[r], truth, detections, observer, estimates, xy, buoy_xy,
                     colours, display, clouds)

        if any(m == "nees_position" for m, _ in metric_series):
            _log_nees_band(rr, rec, times, time, R)
        # the mean mode probabilities bold in every variant's view (its run's thin beside them)
        log_metric_series(rr, rec, times, metric_series, {f"mode_probability_{m}": 2.5 for m in MODE_NAMES})
        log_keys(rr, rec, variant_keys, display, colours, extra=KEY_EXTRA)
        if notes:
            zero = np.zeros(len(notes))
            rec.send_columns("/notes", indexes=times(zero, zero.astype(np.int64)),
                             columns=rr.TextLog.columns(text=notes, level=["INFO"] * len(notes)))
        log_config(rr, rec, experiment, doc, config_text, record_runs, R)


def _mode_styled(metric_series: dict, runs: int) -> dict:
    """The Monte Carlo mean mode probabilities in their mode's colour (one view per filter)."""
    out = {}
    for (metric, key), (steps, t, values, name, colour) in metric_series.items():
        mode = str(metric).removeprefix("mode_probability_")
        if str(metric).startswith("mode_probability_") and mode in MODE_COLOURS:
            name, colour = f"{MODE_LABELS[mode]} · mean of {runs} runs", MODE_COLOURS[mode]
        out[(metric, key)] = (steps, t, values, name, colour)
    return out


def _log_run(rr, rec, times, ui, r: int, time: np.ndarray, true: np.ndarray, truth: Truth, detections: Detections,
             observer: np.ndarray, estimates: Mapping[str, TrackEstimate], xy: list[int], buoy_xy: np.ndarray,
             colours: dict, display: dict, clouds: dict) -> None:
    world = f"/world/run{r}"
    K = time.size
    steps_all = np.arange(K, dtype=np.int64)

    # ---- truth: target and buoys, whole tracks (static) + current positions ---------------------
    target = true[:, xy]                                                                  # (K, 2)
    buoys = true[:, buoy_xy]                                                              # (K, 4, 2)
    tracks = [("truth", target, TRUTH_COLOUR, None)] + [
        (f"buoys/{i + 1}", buoys[:, i], _BUOY_COLOUR, f"B{i + 1}") for i in range(BUOYS)]
    for name, track, colour, label in tracks:
        ok = np.isfinite(track).all(-1)
        steps = np.nonzero(ok)[0]
        # the whole track faint (where it goes), the path up to now (time-ranged in the views)
        rec.log(f"{world}/{name}", rr.LineStrips2D([track[ok]], colors=(*colour, FUTURE_ALPHA), radii=ui(0.5),
                                                   draw_order=12.0), static=True)
        log_path(rr, rec, times, f"{world}/{name}/path", time, steps_all, track, ok, colour=colour, radius=0.9,
                 draw_order=16.0)
        rec.log(f"{world}/{name}", rr.Points2D.from_fields(colors=colour, radii=ui(4.0 if label else 5.0),
                                                           draw_order=30.0, labels=label or "target",
                                                           show_labels=label is not None), static=True)
        rec.send_columns(f"{world}/{name}", indexes=times(time[steps], steps),
                         columns=rr.Points2D.columns(positions=track[ok]))
    if "turn_mode" in truth.labels:
        mode = np.asarray(truth.labels["turn_mode"][r]).reshape(K, -1)[:, 0]
        right = (mode == 3).any()
        rec.log(f"/truth/run{r}/turning", rr.SeriesLines(
            names=f"truth: turning{' right' if right else ''} (1) / straight (0)", colors=TRUTH_COLOUR, widths=1.0),
            static=True)
        rec.send_columns(f"/truth/run{r}/turning", indexes=times(time, steps_all),
                         columns=rr.Scalars.columns(scalars=(mode != 1).astype(np.float64)))

    # ---- bearing lines: target from each true buoy, buoys from the observer; clutter apart --------
    z = np.asarray(detections.z[r], dtype=np.float64)[..., 0]                             # (K, 8)
    direction = np.stack([np.sin(z), np.cos(z)], axis=-1)                                # (K, 8, 2) east, north
    origin = np.concatenate([buoys, np.broadcast_to(observer, (K, BUOYS, 2))], axis=1)   # (K, 8, 2)
    seen = np.concatenate([np.broadcast_to(target[:, None], (K, BUOYS, 2)), buoys], axis=1)
    length = BEARING_LINE_SCALE * np.linalg.norm(seen - origin, axis=-1)                  # (K, 8)
    lines = np.stack([origin, origin + length[..., None] * direction], axis=2)           # (K, 8, 2, 2)
    valid = np.asarray(detections.detected[r], dtype=bool) & np.isfinite(lines).all((-1, -2))
    clutter = np.asarray(detections.target[r]) == CLUTTER
    for family, slots in (("target", slice(0, BUOYS)), ("buoys", slice(BUOYS, SLOTS))):
        for kind, mask, colour in (("nominal", valid & ~clutter, _NOMINAL_COLOUR),
                                   ("clutter", valid & clutter, _CLUTTER_COLOUR)):
            entity = f"{world}/bearings/{family}/{kind}"
            m = mask[:, slots]                                                            # (K, 4)
            rec.log(entity, rr.LineStrips2D.from_fields(colors=colour, radii=ui(0.75 if kind == "nominal" else 1.0),
                                                        draw_order=10.0 if kind == "nominal" else 11.0), static=True)
            # a row at every scan: a scan without returns of this kind clears the previous lines
            rec.send_columns(entity, indexes=times(time, steps_all),
                             columns=rr.LineStrips2D.columns(strips=lines[:, slots][m]).partition(m.sum(-1)))

    # ---- per variant: target and buoy estimates with 2-sigma ellipses, the particle cloud --------
    track_radii = track_radius(list(estimates))
    for key, est in estimates.items():
        colour = colours[key]
        base = f"{world}/{key}"
        X = np.asarray(est.state[r], dtype=np.float64)                                    # (K, n)
        C = np.asarray(est.covariance[r], dtype=np.float64)                               # (K, n, n)
        pos, P = X[:, xy], C[:, xy][:, :, xy]
        good = np.isfinite(pos).all(-1)
        steps = np.nonzero(good)[0]
        log_path(rr, rec, times, f"{base}/track", time, steps_all, pos, good, colour=(*colour, 170),
                 radius=track_radii[key], draw_order=15.0)
        rec.log(f"{base}/estimate", rr.Points2D.from_fields(colors=colour, radii=ui(5.0), draw_order=40.0),
                static=True)
        rec.send_columns(f"{base}/estimate", indexes=times(time[steps], steps),
                         columns=rr.Points2D.columns(positions=pos[good]))
        rec.log(f"{base}/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(1.5), draw_order=35.0),
                static=True)
        shown = good & np.isfinite(P).all((-1, -2))
        steps = np.nonzero(shown)[0]
        if steps.size:
            rec.send_columns(f"{base}/covariance", indexes=times(time[steps], steps),
                             columns=rr.LineStrips2D.columns(strips=covariance_ellipses(pos[shown], P[shown])))

        bpos = X[:, buoy_xy]                                                              # (K, 4, 2)
        bcov = C[:, buoy_xy[:, :, None], buoy_xy[:, None, :]]                             # (K, 4, 2, 2)
        bok = np.isfinite(bpos).all(-1)                                                   # (K, 4)
        log_path(rr, rec, times, f"{base}/buoys/track", time, steps_all, bpos, bok, colour=(*colour, 110),
                 radius=0.75, draw_order=14.0)
        rec.log(f"{base}/buoys", rr.Points2D.from_fields(colors=colour, radii=ui(3.5), draw_order=40.0), static=True)
        rec.send_columns(f"{base}/buoys", indexes=times(time, steps_all),
                         columns=rr.Points2D.columns(positions=bpos[bok]).partition(bok.sum(-1)))
        cok = bok & np.isfinite(bcov).all((-1, -2))
        rec.log(f"{base}/buoys/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(1.0),
                                                                        draw_order=35.0), static=True)
        if cok.any():
            rec.send_columns(f"{base}/buoys/covariance", indexes=times(time, steps_all),
                             columns=rr.LineStrips2D.columns(strips=covariance_ellipses(bpos[cok], bcov[cok]))
                             .partition(cok.sum(-1)))

        if (key, r) in clouds:
            particles, modes = clouds[key, r]                                              # (K, P, n), (K, P)
            kept = modes >= 0
            palette = np.array([MODE_COLOURS[m] for m in MODE_NAMES], dtype=np.uint8)
            rec.log(f"{base}/particles", rr.Points2D.from_fields(radii=ui(1.75), draw_order=25.0), static=True)
            rec.send_columns(f"{base}/particles", indexes=times(time, steps_all), columns=rr.Points2D.columns(
                positions=particles[..., xy][kept], colors=palette[modes[kept]]).partition(kept.sum(-1)))
            cloud_buoys = particles[:, :, buoy_xy][kept].reshape(-1, 2)                   # 4 per particle
            rec.log(f"{base}/particles/buoys", rr.Points2D.from_fields(colors=(*lighter_colour(colour), 90), radii=ui(1.0),
                                                                       draw_order=24.0), static=True)
            rec.send_columns(f"{base}/particles/buoys", indexes=times(time, steps_all),
                             columns=rr.Points2D.columns(positions=cloud_buoys).partition(BUOYS * kept.sum(-1)))

        # ---- time series of the recorded run: mode probabilities, effective sample size --------
        series = f"/variants/{key}/run{r}"
        if "mode_probabilities" in est.extras:
            mu = np.asarray(est.extras["mode_probabilities"][r], dtype=np.float64)      # (K, 3)
            for i, mode in enumerate(MODE_NAMES[: mu.shape[-1]]):
                entity = f"{series}/mode_probability/{mode}"
                steps = np.nonzero(np.isfinite(mu[:, i]))[0]
                rec.log(entity, rr.SeriesLines(names=f"{MODE_LABELS[mode]} · run {r}",
                                               colors=lighter_colour(MODE_COLOURS[mode], 0.35), widths=1.0), static=True)
                rec.send_columns(entity, indexes=times(time[steps], steps),
                                 columns=rr.Scalars.columns(scalars=mu[steps, i]))
        if "ess" in est.extras:
            ess = np.asarray(est.extras["ess"][r], dtype=np.float64)
            steps = np.nonzero(np.isfinite(ess))[0]
            rec.log(f"{series}/ess", rr.SeriesLines(names=f"{display[key]} · run {r}", colors=lighter_colour(colour),
                                                    widths=1.0), static=True)
            rec.send_columns(f"{series}/ess", indexes=times(time[steps], steps),
                             columns=rr.Scalars.columns(scalars=ess[steps]))


def nees_band(runs: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided ``probability`` interval of the mean over ``runs`` runs of a consistent filter's
    2-dof NEES: runs x mean ~ chi2(2 runs), i.e. runs x mean / 2 ~ Gamma(runs, 1) (Erlang), whose
    CDF 1 - exp(-y) sum_{j < runs} y^j / j! is inverted by bisection (scipy.stats costs ~0.8 s to import)."""
    from math import lgamma

    R = int(runs)
    if R < 1:
        raise ValueError(f"runs: {runs} must be >= 1")
    j = np.arange(R)
    log_factorial = np.array([lgamma(i + 1.0) for i in range(R)])

    def cdf(y: float) -> float:
        if y <= 0.0:
            return 0.0
        log_terms = j * np.log(y) - log_factorial - y
        top = log_terms.max()
        return 1.0 - float(np.exp(top) * np.exp(log_terms - top).sum())

    def quantile(q: float) -> float:
        lo, hi = 0.0, R + 40.0 * np.sqrt(R) + 40.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if cdf(mid) < q else (lo, mid)
        return 0.5 * (lo + hi)

    tail = (1.0 - probability) / 2.0
    return float(2.0 * quantile(tail) / R), float(2.0 * quantile(1.0 - tail) / R)


def _log_nees_band(rr, rec, times, time: np.ndarray, runs: int) -> None:
    steps = np.arange(time.size, dtype=np.int64)
    for name, value in zip(("lower", "upper"), nees_band(runs)):
        entity = f"/reference/nees_position/{name}"
        rec.log(entity, rr.SeriesLines(names=f"95 % band, χ²(2·{runs})/{runs}: {value:.3g}", colors=_BAND_COLOUR,
                                       widths=1.0), static=True)
        rec.send_columns(entity, indexes=times(time, steps),
                         columns=rr.Scalars.columns(scalars=np.full(time.size, value)))


def _sensor_doc(sensor, notes: list[str]) -> str:
    parts = []
    o = np.asarray(sensor.observer_position, dtype=float)
    parts.append(f"Observer fixed at ({o[0] / 1000:g} km east, {o[1] / 1000:g} km north).")
    nominal, clutter = getattr(sensor, "nominal_std", None), getattr(sensor, "clutter_std", None)
    if nominal is not None:
        s = np.degrees(np.asarray(nominal, dtype=float))
        text = f"Bearing noise σ: target {s[0]:.3g} deg, buoys {s[BUOYS]:.3g} deg"
        if clutter is not None:
            c = np.degrees(np.asarray(clutter, dtype=float))
            text += f"; clutter {c[0]:.3g} deg / {c[BUOYS]:.3g} deg"
        parts.append(text + ".")
    p_miss, p_clutter = getattr(sensor, "miss_probability", None), getattr(sensor, "clutter_probability", None)
    if p_miss is not None and p_clutter is not None:
        parts.append(f"Each component missed with probability {float(p_miss):g}; a received one is clutter with "
                     f"probability {float(p_clutter):g}.")
    parts.append(f"Grey lines: nominal bearings, red: clutter returns; target bearings start at the true buoy "
                 f"positions, buoy bearings at the observer, each {BEARING_LINE_SCALE:g} x the true range long. "
                 f"Per filter: estimated target and buoys with 2σ ellipses of their position blocks; particles "
                 f"(at most {MAX_PARTICLES} per scan) by mode: cyan CV, magenta left (Ω > 0), amber right (Ω < 0); "
                 f"faint: the particles' buoys. Tracks and true paths are drawn up to the time cursor (the true "
                 f"tracks' future faint).")
    parts.append("Tabs: RMSE / sqrt(PCRLB) with the clairvoyant bound and with the bound of the filters' own noise "
                 "(clutter ignored); RMSE and the two sqrt(PCRLB) in metres.")
    if notes:
        parts.append("Not drawn:\n\n" + "\n".join(f"- {n}" for n in notes))
    return "\n\n".join(parts) + "\n"


KEY_EXTRA = (("target (truth)", TRUTH_COLOUR), ("buoys (truth)", _BUOY_COLOUR), ("bearing", _NOMINAL_COLOUR[:3]),
             ("clutter", _CLUTTER_COLOUR[:3]), ("P(CV)", MODE_COLOURS["cv"]), ("P(left)", MODE_COLOURS["ccw"]),
             ("P(right)", MODE_COLOURS["cw"]))


def _sonobuoy_blueprint(rrb, record_runs: list[int], variant_keys: list[str], display: Mapping[str, str],
                        estimates: Mapping[str, TrackEstimate], metric_series: dict, states: np.ndarray,
                        xy: list[int], buoy_xy: np.ndarray, observer: np.ndarray):
    """Top: per variant, a north-up view of the field (observer, buoys, target, bearings, that
    variant's estimates and cloud; paths up to the time cursor). Then the colour key (variants,
    truth, bearings, modes), position RMSE, median error, buoy RMSE and NEES with its band; bottom:
    per particle filter the mode probabilities (run r0 and the Monte Carlo mean) side by side, and
    tabs with the effective sample size, the notes and the config. No legends: the key."""
    r0 = record_runs[0] if record_runs else None
    whole_run = whole_run_axis(rrb)
    legend = no_legend(rrb)
    rows, shares = [], []
    if r0 is not None:
        pts = np.concatenate([states[..., xy].reshape(-1, 2), states[..., buoy_xy].reshape(-1, 2), observer[None]])
        pts = pts[np.isfinite(pts).all(-1)]
        lo, hi = pts.min(0), pts.max(0)
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1000.0) * 1.08
        bounds = rrb.VisualBounds2D(x_range=[centre[0] - half[0], centre[0] + half[0]],
                                    y_range=[-centre[1] - half[1], -centre[1] + half[1]])   # north_up: y negated
        runs = f"runs {', '.join(map(str, record_runs))}" if len(record_runs) > 1 else f"run {r0}"
        titles = fit_titles(1600.0 / max(len(variant_keys), 1),
                            [[f"{display[k]} · {runs} (north up)", display[k]] for k in variant_keys])
        columns = []
        for key, title in zip(variant_keys, titles):
            contents, paths = ["/world/observer"], []
            for r in record_runs:
                world = f"/world/run{r}"
                contents += [f"{world}/truth/**", f"{world}/buoys/**", f"{world}/bearings/**", f"{world}/{key}/**"]
                paths += [f"{world}/truth/path"] + [f"{world}/buoys/{i + 1}/path" for i in range(BUOYS)] + \
                    [f"{world}/{key}/track", f"{world}/{key}/buoys/track"]
            columns.append(rrb.Spatial2DView(origin="/world", name=title, contents=contents, visual_bounds=bounds,
                                             overrides=path_overrides(rrb, paths),
                                             spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME)))
        rows.append(rrb.Horizontal(*columns))
        shares.append(6.0)
    rows.append(key_view(rrb, VARIANT_KEY, [display[k] for k in variant_keys] + [label for label, _ in KEY_EXTRA]))
    shares.append(0.5)

    present = {m for m, _ in metric_series}
    plots = []
    for m in PLOTTED_METRICS:
        if m not in present:
            continue
        if m == "nees_position":
            plots.append(rrb.TimeSeriesView(origin="/", contents=["/metrics/nees_position/**",
                                                                  "/reference/nees_position/**"],
                                            name="position NEES (2 dof, mean; grey: 95 % band)", axis_x=whole_run,
                                            plot_legend=legend))
        else:
            plots.append(rrb.TimeSeriesView(origin=f"/metrics/{path_part(m)}", axis_x=whole_run, plot_legend=legend,
                                            name=f"{m} [{axis_unit_of(m)}]"))
    if plots:
        rows.append(rrb.Horizontal(*plots))
        shares.append(2.4)

    bottom = []
    with_modes = []
    for key in variant_keys:
        est = estimates[key]
        modes = [f"/metrics/mode_probability_{m}/{key}" for m in MODE_NAMES if (f"mode_probability_{m}", key)
                 in metric_series]
        if r0 is None and not modes:
            continue
        if "mode_probabilities" not in est.extras and not modes:
            continue
        with_modes.append((key, modes))
    titles = fit_titles(1600.0 / (len(with_modes) + 1), [
        [f"{display[k]}: P(mode), bold: mean" + (f", thin: run {r0}, white: truth turning" if r0 is not None else ""),
         f"{display[k]}: P(mode), bold mean" + (f", thin run {r0}" if r0 is not None else ""),
         f"{display[k]}: P(mode)"] for k, _ in with_modes])
    for (key, modes), title in zip(with_modes, titles):
        contents = modes + ([f"/variants/{key}/run{r0}/mode_probability/**", f"/truth/run{r0}/turning"]
                            if r0 is not None else [])
        bottom.append(rrb.TimeSeriesView(origin="/", contents=contents, axis_x=whole_run,
                                         axis_y=rrb.ScalarAxis(range=(0.0, 1.0)), plot_legend=legend, name=title))
    tabs = []
    ess = ["/metrics/ess/**"] + ([f"/variants/{k}/run{r0}/ess" for k in variant_keys if "ess" in estimates[k].extras]
                                if r0 is not None else [])
    if "ess" in present or len(ess) > 1:
        tabs.append(rrb.TimeSeriesView(origin="/", contents=ess, axis_x=whole_run, plot_legend=legend,
                                       name="ESS [particles] (mean bold" + (f", run {r0} thin)" if r0 is not None else ")")))
    if "nis" in present:
        tabs.append(rrb.TimeSeriesView(origin="/metrics/nis", axis_x=whole_run, plot_legend=legend,
                                       name="NIS (mean; thin: 95 % band)"))
    if "position_rmse_over_bound" in present:
        tabs.append(rrb.TimeSeriesView(origin="/metrics", contents=["/metrics/position_rmse_over_bound/**",
                                                                    "/metrics/position_rmse_over_bound_model/**"],
                                       axis_x=whole_run, plot_legend=legend, name="RMSE / sqrt(PCRLB)"))
        tabs.append(rrb.TimeSeriesView(origin="/metrics", contents=["/metrics/position_rmse/**",
                                                                    "/metrics/position_bound/**",
                                                                    "/metrics/position_bound_model/**"],
                                       axis_x=whole_run, plot_legend=legend, name="RMSE and sqrt(PCRLB) [m]"))
    be = rrb.encodings
    tabs.append(rrb.TextLogView(origin="/notes", name="Notes", columns=rrb.TextLogColumns(
        timeline_columns=[be.TimelineColumn("step", visible=False), be.TimelineColumn("time", visible=False)],
        text_log_columns=[be.TextLogColumn("Body"), be.TextLogColumn("EntityPath", visible=False),
                          be.TextLogColumn("LogLevel", visible=False)])))
    tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    bottom.append(rrb.Tabs(*tabs, active_tab=0))
    rows.append(rrb.Horizontal(*bottom))
    shares.append(2.6)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
