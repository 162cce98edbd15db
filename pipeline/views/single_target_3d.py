"""The default study's 3-D recording (study 000's radar, the ADS-B flights): truth, detections
converted to Cartesian, estimates with their 2-sigma ellipsoids, maneuver detections, the LOS axes,
a map view where the truth has geodetic coordinates. The entity tree is in pipeline.views.recording's
docstring."""


from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from filters.base import TrackEstimate
from pipeline.evaluation.metrics import axis_unit_of
from pipeline.views.blueprints import (fit_title, fit_titles, key_view, log_path, no_legend,
    path_overrides, path_segments, whole_run as whole_run_axis)
from pipeline.views.colours import TRUTH_COLOUR, lighter as lighter_colour
from pipeline.data import Detections, Truth

if TYPE_CHECKING:  # pragma: no cover
    pass

from pipeline.views.recording import (ELLIPSE_SIGMA, FRAMES_PATH, FUTURE_ALPHA, MEASUREMENT_COLOUR, MEASUREMENT_FAINT, CLUTTER_COLOUR, CLUTTER_FAINT, VARIANT_KEY, atomic_recording, limit_views, log_config, log_keys, log_metric_series, metric_time_series, target_frame, time_columns, track_radius)


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


def write_recording_3d(path: Path, *, experiment: str, truth: Truth, detections: Detections,
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
                                 colors=np.where(clutter[seen][:, None], CLUTTER_COLOUR,
                                                 MEASUREMENT_COLOUR).astype(np.uint8),
                             ).partition(seen[steps].sum(-1)))
            # every scan's detections up to now, faint
            rec.log(f"{world}/measurements/all", rr.Points3D.from_fields(radii=ui(1.5)), static=True)
            rec.send_columns(f"{world}/measurements/all", indexes=times(detections.time[steps], steps),
                             columns=rr.Points3D.columns(
                                 positions=z[seen], colors=np.where(clutter[seen][:, None], CLUTTER_FAINT,
                                                                    MEASUREMENT_FAINT).astype(np.uint8),
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
    tabs += limit_views(rrb, present, whole_run)
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
