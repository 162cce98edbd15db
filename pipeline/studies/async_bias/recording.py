"""Write study 002's Rerun recording (``.rrd``): asynchronous 2-D radars with range/azimuth offset and
scale biases, many constant-velocity targets, biased vs bias-compensated local tracks and the bias
estimates of each variant against the true biases, with a side-by-side blueprint in the same file.

Layout of the entity tree (``r`` = a recorded Monte Carlo run, ``v`` = a variant key, ``n`` = radar
number 1..S as in the metric names ``..._s<n>``, ``m`` = target number 1..T)::

    /world/radars                                 static markers at the radar positions, labelled
    /world/run{r}/truth                           static LineStrips2D of every target (faint, labelled
                                                  1..T) + current true positions (Points2D per truth step)
    /world/run{r}/truth/path                      a segment per target and step, shown up to the cursor
    /world/run{r}/measurements/radar{n}           radar n's latest report of every target, converted
                                                  to x, y (radar position + range [cos, sin](azimuth));
                                                  biased, so offset from the truth
    /world/run{r}/measurements/all                every report of every radar, static and faint
    /world/run{r}/{v}/radar{n}/biased/track       radar n's biased local track of each kept target (the
                                                  variant's ``targets``): a segment per report, shown
                                                  up to the time cursor
    /world/run{r}/{v}/radar{n}/biased/estimate    at radar n's reports: the current track estimates
    /world/run{r}/{v}/radar{n}/biased/covariance  at radar n's reports: 2-sigma position ellipses (polylines)
    /world/run{r}/{v}/radar{n}/compensated/...    the same for X^b - G beta_hat (variants that estimate
                                                  biases only; for the local variant it equals biased)
    /bias/{v}/run{r}/radar{n}/{component}         the bias estimate after each report
    /bias/{v}/run{r}/radar{n}/{component}/plus_2sigma, /minus_2sigma   estimate +- 2 sigma
    /bias/{v}/run{r}/radar{n}/{component}/true    the true bias (constant)
    /metrics/{metric}/{v}                         Monte Carlo averages per truth step
    /metrics/{nees metric}/chi2/{mean,lower,upper}  expected NEES and the 95 % band of an n_runs mean
    /metrics/nis_s{n}/{v}, .../{v}_chi2_{lower,upper}  radar n's local-track NIS (mean over its targets
                                                  and the runs) and its 95 % band (the metrics'
                                                  nis_s{n}_lower / _upper, thin and lighter)
    /config                                       markdown: description, radars, true biases, config yaml
    /key/variants                                 colour key: variants, truth, radars (colours no variant has)
    /world/frames/north_up, /world/frames/target{m}_run{r}   frames the 2-D views look from (y up;
                                                  the latter centred on target m's true position)

Bias values (the series and the ``bias_rmse_*`` metrics) are in display units: range offset m,
azimuth offset mrad, range and azimuth scale ppm (1e-6); ``BIAS_DISPLAY`` lists them. Components
are ``filters.bias.BIAS_NAMES``. Variants whose bias is NaN throughout (local tracking) get no
``/bias`` series and no compensated tracks.

Every time-varying entity has the timelines ``time`` (duration, s) and ``step`` (sequence, the
index into the truth's time grid, as in the metrics) and is written with one ``send_columns``
call; only static things use ``log``. The blueprint shows the first recorded run. Rerun is
imported lazily.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from filters.bias import BIAS_NAMES, BiasRegistrationResult
from pipeline.data import Detections, Truth
from pipeline.views.blueprints import (fit_titles, key_view, log_path, no_legend, path_overrides,
    whole_run as whole_run_axis)
from pipeline.views.recording import (log_north_up, atomic_recording, checked_record_runs, covariance_ellipses,
    FRAMES_PATH, FUTURE_ALPHA, log_config, log_keys, log_metric_series, metric_time_series, NORTH_UP_FRAME,
    path_part, PATH_SAFE, time_columns, VARIANT_KEY, xy_index)
from pipeline.views.colours import lighter as lighter_colour, TRUTH_COLOUR, variant_colour

if TYPE_CHECKING:  # pragma: no cover
    import polars as pl

# component -> (display unit, factor from SI)
BIAS_DISPLAY = {"range_offset": ("m", 1.0), "azimuth_offset": ("mrad", 1e3), "range_scale": ("ppm", 1e6),
                "azimuth_scale": ("ppm", 1e6)}
BIAS_LABELS = {"range_offset": "range offset b_r", "azimuth_offset": "azimuth offset b_θ",
               "range_scale": "range scale ε_r", "azimuth_scale": "azimuth scale ε_θ"}
BIAS_SYMBOLS = {"range_offset": "b_r", "azimuth_offset": "b_θ", "range_scale": "ε_r", "azimuth_scale": "ε_θ"}
KINDS = ("biased", "compensated")
# radars in colours no variant has (pipeline.views.colours: blue, orange, green, red, ... are the variants')
_RADAR_COLOURS = [(245, 215, 70), (235, 100, 235), (120, 235, 215), (255, 160, 130)]
_TIME_TOLERANCE = 1e-6                   # [s] a report time matches a truth time this close
_BIAS_RMSE = re.compile(r"^bias_rmse_(?P<component>.+)_s(?P<radar>\d+)$")
_TRACK_METRIC = re.compile(r"^(?P<quantity>position_rmse|velocity_rmse|track_nees)_s(?P<radar>\d+)_t(?P<target>\d+)"
                           r"(?P<compensated>_compensated)?$")
_NEES = re.compile(r"^bias_nees(_s(?P<radar>\d+))?$")
TAB_WIDTH = 1600.0 * 2.0 / 5.0           # the bottom right tabs' width on the 1600 px window [px]


def radar_colour(n: int) -> tuple[int, int, int]:
    """Colour of radar index n (0-based): its marker, measurements and tracks."""
    return _RADAR_COLOURS[n] if n < len(_RADAR_COLOURS) else variant_colour(n + 3)


def _dim(colour: Sequence[int], amount: float = 0.45) -> tuple[int, int, int]:
    return tuple(int(round(c * (1.0 - amount))) for c in colour)  # type: ignore[return-value]


def _grid_steps(grid: np.ndarray, times: np.ndarray, what: str) -> np.ndarray:
    """Index of each time in the truth's time grid (every report time must be a truth time)."""
    times = np.asarray(times, dtype=np.float64)
    index = np.clip(np.searchsorted(grid, times - _TIME_TOLERANCE), 0, max(grid.size - 1, 0))
    off = np.abs(grid[index] - times) > _TIME_TOLERANCE if grid.size else np.ones(times.shape, bool)
    if np.any(off):
        first = int(np.argmax(off))
        raise ValueError(f"{what}: time {times[first]:g} s is not on the truth's time grid "
                         f"({grid[0] if grid.size else 'empty'} .. {grid[-1] if grid.size else ''} s); "
                         f"the recording puts everything on the truth's steps")
    return index.astype(np.int64)


def _has_bias(est: BiasRegistrationResult, runs: Sequence[int]) -> bool:
    """Whether the variant estimates biases, read off the recorded ``runs`` (the only ones a recording
    holds: pipeline.storage.estimates)."""
    return any(bool(np.isfinite(np.asarray(est.bias[r])).any()) for r in runs)


def _check_inputs(truth: Truth, detections: Detections, estimates: Mapping[str, BiasRegistrationResult],
                  record_runs: Sequence[int], positions: np.ndarray, true_bias: np.ndarray) -> list[int]:
    R = truth.runs
    runs = checked_record_runs(record_runs, R)
    S = positions.shape[0]
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"sensor.positions: shape {positions.shape} must be (S, 2)")
    if true_bias.shape != (4 * S,):
        raise ValueError(f"sensor.true_bias_vector(): shape {true_bias.shape} must be (4S,) = ({4 * S},)")
    if detections.runs != R:
        raise ValueError(f"detections have {detections.runs} runs but the truth has {R}")
    T = truth.state.shape[2]
    if detections.z.shape[:1] + detections.z.shape[2:] != (R, T, 2):
        raise ValueError(f"detections.z: shape {detections.z.shape} must be (R, K, T, 2) = ({R}, K, {T}, 2): "
                         f"(range, azimuth) of every target")
    sensors = np.asarray(detections.sensor)
    if sensors.size and (sensors.min() < 0 or sensors.max() >= S):
        raise ValueError(f"detections.sensor: indices {np.unique(sensors).tolist()} but the network has {S} radars")
    for key, est in estimates.items():
        if not PATH_SAFE.match(key):
            raise ValueError(f"variant key {key!r} is not path-safe (allowed: letters, digits, '_', '-', '.')")
        K = est.time.shape[0]
        Tsel = np.asarray(est.targets).size
        expected = {"bias": (R, K, 4 * S), "bias_covariance": (R, K, 4 * S, 4 * S), "track_state": (R, K, Tsel, 4),
                    "track_covariance": (R, K, Tsel, 4, 4), "compensated_state": (R, K, Tsel, 4),
                    "compensated_covariance": (R, K, Tsel, 4, 4)}
        for name, shape in expected.items():
            if np.shape(getattr(est, name)) != shape:
                raise ValueError(f"estimate {key!r}: {name} has shape {np.shape(getattr(est, name))}, expected "
                                 f"{shape} (R runs, K reports, S = {S} radars, {Tsel} kept targets)")
        if np.shape(est.sensor) != (K,):
            raise ValueError(f"estimate {key!r}: sensor has shape {np.shape(est.sensor)}, expected ({K},)")
        targets = np.asarray(est.targets)
        if targets.size and (targets.min() < 0 or targets.max() >= T):
            raise ValueError(f"estimate {key!r}: targets {targets.tolist()} must be 0-based indices below {T}")
    return runs


def _bias_limits(estimates: Mapping[str, BiasRegistrationResult], keys: list[str], r: int, j: int,
                 true_value: float, factor: float) -> tuple[float, float] | None:
    """A y range for component j (SI index into the stacked bias) of run r that shows the estimates
    and their 2-sigma bounds after the first tenth of the run (the prior's bounds are orders of
    magnitude wider and would flatten everything), the true value and zero; shared by the variants."""
    values = [true_value * factor, 0.0]
    for key in keys:
        est = estimates[key]
        t = np.asarray(est.time, dtype=np.float64)
        if not t.size:
            continue
        late = t >= t[0] + 0.1 * (t[-1] - t[0])
        mean = np.asarray(est.bias[r, late, j], dtype=np.float64)
        sigma = np.sqrt(np.clip(np.asarray(est.bias_covariance[r, late, j, j], dtype=np.float64), 0.0, None))
        ok = np.isfinite(mean) & np.isfinite(sigma)
        if ok.any():
            values += [float(np.min(mean[ok] - 2 * sigma[ok])) * factor,
                       float(np.max(mean[ok] + 2 * sigma[ok])) * factor]
    lo, hi = min(values), max(values)
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return None
    pad = 0.08 * (hi - lo)
    return lo - pad, hi + pad


def _styled_metric_series(metric_series: dict) -> dict:
    """Bias RMSE in display units; track metrics named and shaded biased / compensated."""
    out = {}
    for (metric, key), (steps, t, values, name, colour) in metric_series.items():
        m = _BIAS_RMSE.match(str(metric))
        if m and m["component"] in BIAS_DISPLAY:
            values = values * BIAS_DISPLAY[m["component"]][1]
        m = _TRACK_METRIC.match(str(metric))
        if m:
            if m["compensated"]:
                name = f"{name} · compensated"
            else:
                name, colour = f"{name} · biased", lighter_colour(colour, 0.5)
        out[(metric, key)] = (steps, t, values, name, colour)
    return out


def _nees_dof(metric: str, S: int) -> int | None:
    m = _NEES.match(metric)
    if m:
        return 4 if m["radar"] else 4 * S
    m = _TRACK_METRIC.match(metric)
    return 4 if m and m["quantity"] == "track_nees" else None


def _chi2_bands(metrics, metric_series: dict, S: int) -> dict:
    """metric -> (steps, time, mean, lower, upper) of the NEES metrics: the expected value (dof) and
    the 95 % band of a mean over n_runs runs (chi2(n dof) / n)."""
    if metrics is None or not metric_series:
        return {}
    from scipy.stats import chi2

    runs = int(metrics["n_runs"].max()) if "n_runs" in metrics.columns and metrics.height else 1
    runs = max(runs, 1)
    out = {}
    for (metric, _), (steps, t, _, _, _) in metric_series.items():
        dof = _nees_dof(str(metric), S)
        if dof is None or metric in out or not steps.size:
            continue
        first, last = int(np.argmin(steps)), int(np.argmax(steps))
        idx = np.unique([first, last])
        lo, hi = chi2.ppf([0.025, 0.975], runs * dof) / runs
        out[metric] = (steps[idx], t[idx], np.full(idx.size, float(dof)), np.full(idx.size, lo), np.full(idx.size, hi))
    return out


def _radar_table(names: Sequence[str], positions: np.ndarray, noise_std: np.ndarray | None,
                 biases: np.ndarray) -> str:
    head = "| radar | position [m] | σ_r [m], σ_θ [mrad] | " + " | ".join(
        f"{BIAS_LABELS[c]} [{BIAS_DISPLAY[c][0]}]" for c in BIAS_NAMES) + " |"
    rows = [head, "|" + "---|" * (3 + len(BIAS_NAMES))]
    for n, name in enumerate(names):
        noise = "" if noise_std is None else f"{noise_std[n, 0]:g}, {1e3 * noise_std[n, 1]:g}"
        values = " | ".join(f"{biases[n, c] * BIAS_DISPLAY[comp][1]:g}" for c, comp in enumerate(BIAS_NAMES))
        rows.append(f"| {n + 1}: {name} | ({positions[n, 0]:g}, {positions[n, 1]:g}) | {noise} | {values} |")
    return "\n".join(rows)


def write_bias_recording(path: Path, *, experiment: str, truth: Truth, detections: Detections,
                         estimates: Mapping[str, BiasRegistrationResult], display_names: Mapping[str, str],
                         metrics: "pl.DataFrame | None", record_runs: Sequence[int], sensor,
                         config_text: str = "", description: str = "") -> None:
    """Write ``path`` (an ``.rrd`` with its default blueprint) for the runs in ``record_runs``.

    ``truth``: state (R, Kt, T, 4) (x, y, vx, vy) on the time grid the metrics use;
    ``detections``: z (R, K, T, 2) biased (range, azimuth) relative to the reporting radar
    ``detections.sensor`` (0-based), at report times on the truth's grid; ``estimates``: variant key
    (path-safe) -> :class:`filters.bias.BiasRegistrationResult`, in display order; ``metrics``: the
    long metrics frame (variant_key, metric, step, time, value, ...) or None; ``sensor``: the radar
    network (``names``, ``positions`` (S, 2), ``noise_std`` (S, 2), ``biases`` (S, 4),
    ``true_bias_vector()`` (4S,)). The file is written to a temporary name beside ``path`` and moved
    onto it only once complete. See the module docstring for the entity tree.
    """
    path = Path(path)
    positions = np.asarray(sensor.positions, dtype=np.float64)
    true_bias = np.asarray(sensor.true_bias_vector(), dtype=np.float64).reshape(-1)
    record_runs = _check_inputs(truth, detections, estimates, record_runs, positions, true_bias)
    S = positions.shape[0]
    names = [str(n) for n in getattr(sensor, "names", [f"radar{n + 1}" for n in range(S)])]
    noise_std = getattr(sensor, "noise_std", None)
    noise_std = None if noise_std is None else np.asarray(noise_std, dtype=np.float64)
    truth_xy = xy_index(truth.state_names, "truth")
    grid = np.asarray(truth.time, dtype=np.float64)
    det_steps = _grid_steps(grid, detections.time, "detections")
    est_steps = {key: _grid_steps(grid, est.time, f"estimate {key!r}") for key, est in estimates.items()}

    variant_keys = list(estimates)
    colours = {key: variant_colour(i) for i, key in enumerate(variant_keys)}
    display = {key: str(display_names.get(key, key)) for key in variant_keys}
    bias_keys = [key for key in variant_keys if _has_bias(estimates[key], record_runs)]
    metric_series = _styled_metric_series(metric_time_series(metrics, experiment, variant_keys, display, colours))
    bands = _chi2_bands(metrics, metric_series, S)

    import rerun as rr  # lazily: ~0.6 s
    import rerun.blueprint as rrb

    blueprint = _bias_blueprint(rrb, truth, truth_xy, positions, names, record_runs, estimates, display,
                                bias_keys, metric_series, bands, true_bias)
    radar_doc = _radar_table(names, positions, noise_std, true_bias.reshape(S, 4))
    doc = (f"{description.strip()}\n\n" if description else "") + f"Radars and their true biases:\n\n{radar_doc}\n"

    with atomic_recording(rr, path, experiment, blueprint) as rec:
        times = time_columns(rr)
        ui = rr.Radius.ui_points
        flip = np.array([1.0, -1.0, 1.0])
        log_north_up(rr, rec)
        rec.log("/world/radars", rr.Points2D(positions, colors=[radar_colour(n) for n in range(S)], radii=ui(8.0),
                                             labels=[f"{n + 1}: {name}" for n, name in enumerate(names)],
                                             show_labels=True, draw_order=50.0), static=True)
        for r in record_runs:
            _log_run(rr, rec, times, ui, r, truth, truth_xy, detections, det_steps, estimates, est_steps,
                     positions, names, colours, display, true_bias, flip, bias_keys)
        log_metric_series(rr, rec, times, metric_series)
        log_keys(rr, rec, variant_keys, display, colours, extra=key_extra(names))
        for metric, (steps, t, mean, lo, hi) in bands.items():
            base = f"/metrics/{path_part(metric)}/chi2"
            for part, values, label, width in (("mean", mean, "χ² mean (dof)", 1.5),
                                               ("lower", lo, "χ² 95 % band", 1.0),
                                               ("upper", hi, "χ² 95 % band", 1.0)):
                rec.log(f"{base}/{part}", rr.SeriesLines(names=label, colors=(200, 200, 200), widths=width),
                        static=True)
                rec.send_columns(f"{base}/{part}", indexes=times(t, steps), columns=rr.Scalars.columns(scalars=values))
        log_config(rr, rec, experiment, doc, config_text, record_runs, truth.runs)


def _log_run(rr, rec, times, ui, r: int, truth: Truth, truth_xy: list[int], detections: Detections,
             det_steps: np.ndarray, estimates: Mapping[str, BiasRegistrationResult], est_steps: dict,
             positions: np.ndarray, names: list[str], colours: dict, display: dict, true_bias: np.ndarray,
             flip: np.ndarray, bias_keys: list[str]) -> None:
    world = f"/world/run{r}"
    grid = np.asarray(truth.time, dtype=np.float64)
    S = positions.shape[0]

    # ---- truth: every target's trajectory (static, labelled 1..T) + current positions ----------
    xy = np.asarray(truth.state[r], dtype=np.float64)[..., truth_xy]                # (Kt, T, 2)
    T = xy.shape[1]
    strips = [xy[:, t][np.isfinite(xy[:, t]).all(-1)] for t in range(T)]
    # the whole trajectories faint (labelled), the paths up to now (time-ranged in the views)
    rec.log(f"{world}/truth", rr.LineStrips2D(strips, colors=(*TRUTH_COLOUR, FUTURE_ALPHA), radii=ui(0.5),
                                              labels=[str(t + 1) for t in range(T)], show_labels=True,
                                              draw_order=12.0), static=True)
    rec.log(f"{world}/truth", rr.Points2D.from_fields(colors=TRUTH_COLOUR, radii=ui(3.0), draw_order=30.0),
            static=True)
    ok = np.isfinite(xy).all(-1)                                                   # (Kt, T)
    log_path(rr, rec, times, f"{world}/truth/path", grid, np.arange(grid.size), xy, ok, colour=TRUTH_COLOUR,
             radius=0.75, draw_order=16.0)
    steps = np.nonzero(ok.any(-1))[0]
    rec.send_columns(f"{world}/truth", indexes=times(grid[steps], steps),
                     columns=rr.Points2D.columns(positions=xy[ok]).partition(ok[steps].sum(-1)))
    # frames centred on each kept target's true position (y up) for the zoomed views
    kept = sorted({int(t) for est in estimates.values() for t in np.asarray(est.targets).tolist()})
    for t in kept:
        steps = np.nonzero(ok[:, t])[0]
        if steps.size:
            rec.send_columns(
                f"{FRAMES_PATH}/target{t + 1}_run{r}", indexes=times(grid[steps], steps),
                columns=rr.Transform3D.columns(
                    translation=np.c_[xy[steps, t], np.zeros(steps.size)], scale=np.tile(flip, (steps.size, 1)),
                    parent_frame=["tf#/world"] * steps.size, child_frame=[target_frame(t, r)] * steps.size))

    # ---- measurements: each radar's latest report, converted to x, y; all reports faint --------
    z = np.asarray(detections.z[r], dtype=np.float64)                              # (K, T, 2)
    sensor_of = np.asarray(detections.sensor, dtype=np.int64)
    origin = positions[sensor_of][:, None, :]                                      # (K, 1, 2)
    meas = origin + z[..., :1] * np.stack([np.cos(z[..., 1]), np.sin(z[..., 1])], axis=-1)
    seen = np.asarray(detections.detected[r], dtype=bool) & np.isfinite(meas).all(-1)
    for n in range(S):
        entity = f"{world}/measurements/radar{n + 1}"
        rows = np.nonzero((sensor_of == n) & seen.any(-1))[0]
        rec.log(entity, rr.Points2D.from_fields(colors=radar_colour(n), radii=ui(2.5), draw_order=20.0), static=True)
        if rows.size:
            rec.send_columns(entity, indexes=times(grid[det_steps[rows]], det_steps[rows]),
                             columns=rr.Points2D.columns(positions=meas[rows][seen[rows]])
                             .partition(seen[rows].sum(-1)))
    faint = np.array([_dim(radar_colour(n), 0.55) for n in range(S)], dtype=np.uint8)
    rec.log(f"{world}/measurements/all", rr.Points2D(
        meas[seen], colors=faint[np.broadcast_to(sensor_of[:, None], seen.shape)[seen]], radii=ui(1.0),
        draw_order=5.0), static=True)

    # ---- per variant and radar: biased / compensated tracks of the kept targets ---------------
    for key, est in estimates.items():
        steps_of = est_steps[key]
        has_bias = key in bias_keys
        for n in range(S):
            rows = np.nonzero(np.asarray(est.sensor) == n)[0]
            if not rows.size:
                continue
            for kind in KINDS if has_bias else KINDS[:1]:
                state = est.track_state if kind == "biased" else est.compensated_state
                cov = est.track_covariance if kind == "biased" else est.compensated_covariance
                pos = np.asarray(state[r, rows], dtype=np.float64)[..., :2]           # (kn, Tsel, 2)
                P = np.asarray(cov[r, rows], dtype=np.float64)[..., :2, :2]            # (kn, Tsel, 2, 2)
                good = np.isfinite(pos).all(-1) & np.isfinite(P).all((-1, -2))       # (kn, Tsel)
                colour = radar_colour(n) if kind == "compensated" else _dim(radar_colour(n))
                base = f"{world}/{key}/radar{n + 1}/{kind}"
                # the tracks up to now: a segment per report of this radar and kept target
                log_path(rr, rec, times, f"{base}/track", grid[steps_of[rows]], steps_of[rows], pos, good,
                         colour=colour, radius=1.5 if kind == "compensated" else 1.0,
                         draw_order=35.0 if kind == "compensated" else 33.0)
                rec.log(f"{base}/estimate", rr.Points2D.from_fields(colors=colour, radii=ui(3.5),
                                                                    draw_order=40.0), static=True)
                rec.log(f"{base}/covariance", rr.LineStrips2D.from_fields(colors=colour, radii=ui(1.0),
                                                                          draw_order=36.0), static=True)
                any_good = good.any(-1)
                if not any_good.any():
                    continue
                at = steps_of[rows[any_good]]
                counts = good[any_good].sum(-1)
                rec.send_columns(f"{base}/estimate", indexes=times(grid[at], at),
                                 columns=rr.Points2D.columns(positions=pos[good]).partition(counts))
                rec.send_columns(f"{base}/covariance", indexes=times(grid[at], at),
                                 columns=rr.LineStrips2D.columns(strips=covariance_ellipses(pos[good], P[good]))
                                 .partition(counts))

        # ---- bias estimates +- 2 sigma against the true biases ------------------------------
        if not has_bias:
            continue
        colour = colours[key]
        for n in range(S):
            for c, component in enumerate(BIAS_NAMES):
                j = 4 * n + c
                unit, factor = BIAS_DISPLAY[component]
                mean = np.asarray(est.bias[r, :, j], dtype=np.float64)
                sigma = np.sqrt(np.clip(np.asarray(est.bias_covariance[r, :, j, j], dtype=np.float64), 0.0, None))
                good = np.isfinite(mean) & np.isfinite(sigma)
                if not good.any():
                    continue
                at = steps_of[good]
                entity = f"/bias/{key}/run{r}/radar{n + 1}/{component}"
                parts = (("", mean[good], f"{display[key]} estimate [{unit}]", colour, 2.0),
                         ("/plus_2sigma", mean[good] + 2 * sigma[good], f"{display[key]} +2σ", lighter_colour(colour), 1.0),
                         ("/minus_2sigma", mean[good] - 2 * sigma[good], f"{display[key]} −2σ", lighter_colour(colour),
                          1.0),
                         ("/true", np.full(at.size, true_bias[j]), "true", TRUTH_COLOUR, 1.5))
                for suffix, values, label, col, width in parts:
                    rec.log(entity + suffix, rr.SeriesLines(names=label, colors=col, widths=width), static=True)
                    rec.send_columns(entity + suffix, indexes=times(grid[at], at),
                                     columns=rr.Scalars.columns(scalars=values * factor))


def key_extra(names: Sequence[str]) -> list:
    """Key entries beside the variants: the truth and each radar (its reports and local tracks)."""
    return [("truth", TRUTH_COLOUR)] + [(f"radar {n + 1} ({name})", radar_colour(n)) for n, name in enumerate(names)]


def target_frame(target: int, run: int) -> str:
    """Named frame centred on target ``target`` (0-based) of run ``run``, y (north) up."""
    return f"target{target + 1}_run{run}"


def _bias_blueprint(rrb, truth: Truth, truth_xy: list[int], positions: np.ndarray, names: list[str],
                    record_runs: list[int], estimates: Mapping[str, BiasRegistrationResult], display: dict,
                    bias_keys: list[str], metric_series: dict, bands: dict, true_bias: np.ndarray):
    """Top: the whole scene (radars, all targets, measurements, tracks) beside, per variant that
    estimates biases (else per variant), zoomed views centred on each kept target (biased and
    compensated tracks with their ellipses). Bottom left: tabs per radar with a grid of the bias
    estimates, one row per variant and one column per component, on one y range per column. Bottom
    right: tabs with the bias RMSE (one line per variant), NEES, the local tracks' NIS per radar
    (each variant's line with its 95 % band as thin lighter lines), track RMSE and the config."""
    r0 = record_runs[0] if record_runs else None
    variant_keys = list(estimates)
    S = positions.shape[0]
    whole_run = whole_run_axis(rrb)
    legend = no_legend(rrb)            # the colour key names the variants (and the radars, the truth)
    rows, shares = [], []

    if r0 is not None:
        world = f"/world/run{r0}"

        def tracks(keys):               # the track entities of these variants (time-ranged: up to now)
            return [f"{world}/{k}/radar{n + 1}/{kind}/track" for k in keys for n in range(S)
                    for kind in (KINDS if k in bias_keys else KINDS[:1])]

        xy = np.concatenate([np.asarray(truth.state[r0], dtype=np.float64)[..., truth_xy].reshape(-1, 2), positions])
        xy = xy[np.isfinite(xy).all(-1)]
        lo, hi = xy.min(0), xy.max(0)
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 100.0) * 1.15   # room for the radars' labels
        overview = rrb.Spatial2DView(
            origin="/world", name=f"run {r0}: radars, {truth.state.shape[2]} targets, measurements, tracks",
            contents=["/world/radars", f"{world}/truth/**", f"{world}/measurements/**"]
            + [f"{world}/{k}/**" for k in variant_keys],
            overrides=path_overrides(rrb, [f"{world}/truth/path"] + tracks(variant_keys)),
            spatial_information=rrb.SpatialInformation(target_frame=NORTH_UP_FRAME),
            visual_bounds=rrb.VisualBounds2D(x_range=[centre[0] - half[0], centre[0] + half[0]],
                                             y_range=[-centre[1] - half[1], -centre[1] + half[1]]))
        columns = [overview]
        zoomed = bias_keys or variant_keys
        options = {(key, t): [f"{display[key]} · target {t + 1}: biased (dim) vs compensated",
                              f"{display[key]} · target {t + 1}: biased vs compensated", f"{display[key]} · target {t + 1}"]
                   for key in zoomed for t in np.asarray(estimates[key].targets, dtype=np.int64).tolist()}
        titles = dict(zip(options, fit_titles(1600.0 / (2.0 + len(zoomed)), list(options.values()))))
        for key in zoomed:
            est = estimates[key]
            views = []
            targets = np.asarray(est.targets, dtype=np.int64).tolist()
            for t in targets:
                title = titles[key, t]
                h = _zoom_half(truth, truth_xy, estimates, r0, t)
                views.append(rrb.Spatial2DView(
                    origin="/world", name=title,
                    contents=[f"{world}/truth/**", f"{world}/measurements/**", f"{world}/{key}/**"],
                    overrides=path_overrides(rrb, [f"{world}/truth/path"] + tracks([key])),
                    spatial_information=rrb.SpatialInformation(target_frame=target_frame(t, r0)),
                    visual_bounds=rrb.VisualBounds2D(x_range=[-h, h], y_range=[-h, h])))
            if views:
                columns.append(rrb.Vertical(*views, name=display[key]))
        rows.append(rrb.Horizontal(*columns, column_shares=[2.0] + [1.0] * (len(columns) - 1)))
        shares.append(5.0)
    rows.append(key_view(rrb, VARIANT_KEY, [display[k] for k in variant_keys] + [label for label, _ in key_extra(names)]))
    shares.append(0.5)

    bottom, bottom_shares = [], []
    if r0 is not None and bias_keys:
        tabs = []
        for n in range(S):
            axes = {}
            for c, component in enumerate(BIAS_NAMES):
                limits = _bias_limits(estimates, bias_keys, r0, 4 * n + c, true_bias[4 * n + c],
                                      BIAS_DISPLAY[component][1])
                axes[component] = rrb.ScalarAxis(range=limits) if limits is not None else None
            # one row per variant, one column per component: the variants' views of a component are
            # aligned (same time axis, same y range) one above the other
            titles = fit_titles(1600.0 * 0.6 / len(BIAS_NAMES), [
                [f"{display[key]} · {BIAS_SYMBOLS[c]} [{BIAS_DISPLAY[c][0]}] ±2σ",
                 f"{display[key]} {BIAS_SYMBOLS[c]} [{BIAS_DISPLAY[c][0]}]", f"{BIAS_SYMBOLS[c]} [{BIAS_DISPLAY[c][0]}]"]
                for key in bias_keys for c in BIAS_NAMES])
            views = [rrb.TimeSeriesView(
                origin=f"/bias/{key}/run{r0}/radar{n + 1}/{component}", axis_x=whole_run, axis_y=axes[component],
                plot_legend=legend, name=titles[i * len(BIAS_NAMES) + c])
                for i, key in enumerate(bias_keys) for c, component in enumerate(BIAS_NAMES)]
            tabs.append(rrb.Grid(*views, grid_columns=len(BIAS_NAMES),
                                 name=f"bias estimates · radar {n + 1} ({names[n]}) · run {r0}"))
        bottom.append(rrb.Tabs(*tabs, active_tab=0))
        bottom_shares.append(3.0)

    present = {m for m, _ in metric_series}
    tabs = []
    rmse = []
    chosen = [(component, n) for component in BIAS_NAMES for n in range(S)
              if f"bias_rmse_{component}_s{n + 1}" in present]
    titles = fit_titles(1600.0 * 0.4 / max(S, 1), [
        [f"RMSE {BIAS_LABELS[c]} · radar {n + 1} [{BIAS_DISPLAY[c][0]}]",
         f"RMSE {BIAS_SYMBOLS[c]} · radar {n + 1} [{BIAS_DISPLAY[c][0]}]", f"{BIAS_SYMBOLS[c]} s{n + 1}"]
        for c, n in chosen])
    for (component, n), title in zip(chosen, titles):
        rmse.append(rrb.TimeSeriesView(origin=f"/metrics/bias_rmse_{component}_s{n + 1}", axis_x=whole_run,
                                       plot_legend=legend, name=title))
    if rmse:
        tabs.append(rrb.Grid(*rmse, grid_columns=S, name="bias RMSE (all runs)"))
    nees_metrics = [m for m in ["bias_nees"] + [f"bias_nees_s{n + 1}" for n in range(S)] if m in present]
    grid = int(np.ceil(np.sqrt(len(nees_metrics)))) if nees_metrics else 1
    titles = fit_titles(TAB_WIDTH / grid, [[f"{m} (χ² {_nees_dof(m, S)} dof; band: mean of the runs)",
                                            f"{m} (χ² {_nees_dof(m, S)} dof, 95 % band)", m] for m in nees_metrics])
    nees = [rrb.TimeSeriesView(origin=f"/metrics/{m}", axis_x=whole_run, plot_legend=legend, name=title)
            for m, title in zip(nees_metrics, titles)]
    if nees:
        tabs.append(rrb.Grid(*nees, name="bias NEES"))
    # the local tracks are the same in every variant, so the variants' NIS lines coincide
    radars = [n for n in range(S) if f"nis_s{n + 1}" in present]
    grid = int(np.ceil(np.sqrt(len(radars)))) if radars else 1
    titles = fit_titles(TAB_WIDTH / grid, [[f"nis_s{n + 1}: radar {n + 1} local tracks (mean; thin: 95 % band)",
                                            f"nis_s{n + 1}: radar {n + 1} local tracks", f"nis_s{n + 1}"] for n in radars])
    nis = [rrb.TimeSeriesView(origin=f"/metrics/nis_s{n + 1}", axis_x=whole_run, plot_legend=legend, name=title)
           for n, title in zip(radars, titles)]
    if nis:
        tabs.append(rrb.Grid(*nis, name="local-track NIS"))
    track = _track_metric_views(rrb, metric_series, variant_keys, bias_keys, whole_run)
    if track:
        tabs.append(rrb.Grid(*track, grid_columns=3, name="tracks: biased (light) vs compensated"))
    tabs.append(rrb.TextDocumentView(origin="/config", name="Config"))
    bottom.append(rrb.Tabs(*tabs, active_tab=0))
    bottom_shares.append(2.0)
    rows.append(rrb.Horizontal(*bottom, column_shares=bottom_shares))
    shares.append(4.0)
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares),
                         rrb.TimePanel(state="collapsed", timeline="time"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def _track_metric_views(rrb, metric_series: dict, variant_keys: list[str], bias_keys: list[str],
                        whole_run) -> list:
    """One view per (quantity, radar, target): the biased track's line once (the local variant's, or
    the first variant's: the biased local tracks are the same in every variant) and the compensated
    line of every variant that estimates biases."""
    groups: dict[tuple[str, int, int], list[str]] = {}
    reference = next((k for k in variant_keys if k not in bias_keys), variant_keys[0] if variant_keys else None)
    for metric, key in metric_series:
        m = _TRACK_METRIC.match(str(metric))
        if not m:
            continue
        keep = key in bias_keys if m["compensated"] else key == reference
        if m["quantity"] == "track_nees":
            keep = key in bias_keys
        if keep:
            groups.setdefault((m["quantity"], int(m["radar"]), int(m["target"])), []).append(
                f"/metrics/{path_part(metric)}/{key}")
    order = {"position_rmse": 0, "velocity_rmse": 1, "track_nees": 2}
    short = {"position_rmse": "pos [m]", "velocity_rmse": "vel [m/s]", "track_nees": "NEES"}   # 3 a row: short
    views = []
    for (quantity, n, t), contents in sorted(groups.items(), key=lambda g: (order[g[0][0]], g[0][1], g[0][2])):
        if quantity == "track_nees":
            contents = contents + [f"/metrics/{quantity}_s{n}_t{t}_compensated/chi2/**"]
        # small views: the legend would cover the lines (the tab's name says which is which)
        views.append(rrb.TimeSeriesView(origin="/metrics", contents=contents, axis_x=whole_run,
                                        plot_legend=rrb.PlotLegend(visible=False),
                                        name=f"s{n} t{t} {short[quantity]}"))
    return views


def _zoom_half(truth: Truth, truth_xy: list[int], estimates: Mapping[str, BiasRegistrationResult], r: int,
               target: int) -> float:
    """Half width [m] of a view centred on ``target``: twice the 90th percentile of its biased tracks'
    position error (the bias offset plus the noise), so truth, measurements, biased and compensated
    tracks and their ellipses are all in view."""
    errors = []
    for est in estimates.values():
        where = np.nonzero(np.asarray(est.targets) == target)[0]
        if not where.size:
            continue
        steps = _grid_steps(np.asarray(truth.time, dtype=np.float64), est.time, "estimate")
        true_xy = np.asarray(truth.state[r][steps, target], dtype=np.float64)[:, truth_xy]
        e = np.linalg.norm(np.asarray(est.track_state[r, :, where[0], :2], dtype=np.float64) - true_xy, axis=-1)
        errors.append(e[np.isfinite(e)])
    e = np.concatenate(errors) if errors else np.empty(0)
    if not e.size:
        return 300.0
    return float(np.clip(2.0 * np.quantile(e, 0.9), 60.0, 5000.0))
