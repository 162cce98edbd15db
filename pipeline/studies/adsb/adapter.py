"""The ADS-B study: recorded flights (pipeline.studies.adsb.scenario.RecordedFlight) seen by study
000's 3-D radar, tracked by every filter family that takes its range/azimuth/elevation measurements.

Beyond the shared per-step metrics (position, velocity, acceleration RMSE, NEES, NIS):

- ``nees_position_velocity`` with its 95 % band: the NEES of the position-velocity block (6 dof; 4 on
  the horizontal plane),
  the one block every family estimates (a CV filter has no acceleration, so its full-state NEES is
  undefined and would drop it from the comparison);

and in the summary, per variant:

- ``position_rmse_by_maneuver`` / ``velocity_rmse_by_maneuver`` with ``component`` the maneuver
  class of the truth (straight, turn, climb_descent, turn_climb_descent): the RMS error over all runs
  and over the scans of that class (scans from ``first_scan`` on, when every filter has started);
- ``nees_position_velocity_in_band``: the share of scans whose run-averaged 6-dof NEES lies inside
  its 95 % band (about 0.95 for a consistent filter);
- ``scans_by_maneuver`` (component = class): how many scans of the window have that label;
- ``radar_position_rmse``: the raw radar's RMS position error at the true positions,
  sqrt(mean trace(J R_p J')) with J the polar-to-Cartesian Jacobian (first order): what a filter must
  beat to be worth running (the same for every variant);

and, the same for every variant, what the truth is made of (the flight, not the filter):

- ``truth_position_std`` (per scan, so per window like the RMSE beside it, and per maneuver class
  ``truth_position_std_<class>``, pooled like ``position_rmse_<class>``): the smoother's own position
  std sqrt(trace P) of the truth (filters.smoothing.smooth_with_covariance), how far the truth itself
  may be from the aircraft; ``truth_std_to_best_rmse`` per window: its ratio to the lowest position
  RMSE of the variants there, and ``truth_uncertain`` 1 where that ratio exceeds ``truth_std_limit``
  (default 1/3: with the truth's error adding in quadrature, the best filter's own error is then
  below sqrt(1 - 1/9) = 0.94 of its measured RMSE, about 6 %, the size of the differences the
  tables are read for), else 0;
- ``points_read``, ``points_kept``, ``segments`` and ``dropped_<reason>`` (component = reason,
  pipeline.studies.adsb.reading: missing_position, on_ground, duplicate_time, non_increasing_time,
  stale_position, jump; and the altitudes not used, stale_altitude, altitude_jump): the cleaning;
- ``smoothing_residual_east/north/up``: RMS of smoothed minus raw position over the window's points.

``check`` refuses, before any stage, a radar farther than its ``max_range`` from the flight at any scan.
"""

from __future__ import annotations

import numpy as np

from pipeline.contract import JobInputs, VariantInputs
from pipeline.evaluation.bounds import PerTruth
from pipeline.evaluation.evaluate import consistency, resolved, summary_row
from pipeline.evaluation.uncertainty import RunValues, WindowStatistic
from pipeline.evaluation.metrics import BAND, Metric, nees, register, unit_of
from pipeline.errors import ConfigError
from pipeline.studies.adsb.flight import MANEUVER_NAMES
from pipeline.studies.adsb.reading import DROP_REASONS
from pipeline.studies.single_target import SingleTargetStudy

POSITION_VELOCITY = ("x", "y", "z", "vx", "vy", "vz")
CLEANING_COUNTS = (*DROP_REASONS, "stale_altitude", "altitude_jump")
ENU_AXES = ("east", "north", "up")
TRUTH_STD_LIMIT = 1.0 / 3.0

register(
    Metric("nees_position_velocity", "1 (chi2 dof = 6; 4 on the horizontal plane)", "-", label="NEES p,v",
           dof="position-velocity block size"),
    Metric("nees_position_velocity_lower", BAND, "-"), Metric("nees_position_velocity_upper", BAND, "-"),
    Metric("nees_position_velocity_in_band", "fraction of scans", "fraction", label="in band", decimals=2),
    *[Metric(f"position_rmse_{name}", "m", quantity="position_rmse_by_maneuver", component=name,
             label=f"pos RMSE {name.replace('_', '/')}") for name in MANEUVER_NAMES],
    *[Metric(f"velocity_rmse_{name}", "m/s", quantity="velocity_rmse_by_maneuver", component=name)
      for name in MANEUVER_NAMES],
    *[Metric(f"scans_{name}", "scans", quantity="scans_by_maneuver", component=name) for name in MANEUVER_NAMES],
    Metric("radar_position_rmse", "m", label="radar RMSE"),
    Metric("truth_position_std", "m", label="truth std"),
    *[Metric(f"truth_position_std_{name}", "m", quantity="truth_position_std_by_maneuver", component=name)
      for name in MANEUVER_NAMES],
    Metric("truth_std_to_best_rmse", "fraction (truth_position_std / the lowest position_rmse of the window)",
           "fraction"),
    Metric("truth_uncertain", "1 where truth_std_to_best_rmse > truth_std_limit, else 0", "flag"),
    Metric("points_read", "points", aggregation="sum"), Metric("points_kept", "points", aggregation="sum"),
    Metric("segments", "segments", aggregation="sum"),
    *[Metric(f"dropped_{reason}", "points", aggregation="sum", quantity="points_dropped", component=reason)
      for reason in CLEANING_COUNTS],
    *[Metric(f"smoothing_residual_{axis}", "m", quantity="smoothing_residual", component=axis)
      for axis in ENU_AXES],
)


def radar_position_rmse(truth, sensor, first_scan: int) -> float | None:
    """sqrt(mean over runs and scans >= first_scan of trace(J R_p J')), J at the true (r, az, el)."""
    from pipeline.sensors import conversion_jacobian, spherical
    if not (hasattr(sensor, "position") and hasattr(sensor, "noise_covariance")):
        return None
    names = truth.state_names
    if "z" in names:
        xyz = truth.state[:, first_scan:, 0, [names.index(n) for n in ("x", "y", "z")]]
        kept = 3
    else:                     # a horizontal truth (HorizontalRadar): the height from its label, the error in x, y
        xyz = np.concatenate([truth.state[:, first_scan:, 0, [names.index(n) for n in ("x", "y")]],
                              np.asarray(truth.labels["up"])[:, first_scan:, 0]], axis=-1)
        kept = 2
    J = conversion_jacobian(spherical(xyz - np.asarray(sensor.position)))[..., :kept, :]
    return float(np.sqrt(np.mean(np.einsum("...ij,jk,...ik->...", J, sensor.noise_covariance, J))))


class FlightStudy(SingleTargetStudy):
    """SingleTargetStudy with the maneuver-class and position-velocity consistency metrics above.

    Parameters: first_scan, the first scan every family has an estimate at (two-point starts: 1;
    the MIE filters' input estimate: 2) [scans]; windows, the summary's windows (name -> [first, last]
    scans; conf/study/adsb.yaml: ${metrics.windows}) the truth's uncertainty is judged over (None:
    'all' from first_scan); truth_std_limit, the ratio of the truth's position std to the best
    position RMSE above which a window is flagged ``truth_uncertain`` (module doc)."""

    def __init__(self, first_scan: int = 2, windows: Mapping[str, Any] | None = None,
                 truth_std_limit: float = TRUTH_STD_LIMIT) -> None:
        super().__init__()
        if isinstance(first_scan, bool) or not isinstance(first_scan, int) or first_scan < 0:
            raise ValueError(f"first_scan: {first_scan!r} must be an integer >= 0")
        if isinstance(truth_std_limit, bool) or not isinstance(truth_std_limit, (int, float)) \
                or not np.isfinite(truth_std_limit) or truth_std_limit <= 0:
            raise ValueError(f"truth_std_limit: {truth_std_limit!r} must be a number > 0 (a ratio, e.g. 0.333)")
        self.first_scan = first_scan
        self.windows = {"all": [first_scan, 10**9]} if windows is None else \
            {str(k): [int(v[0]), int(v[1])] for k, v in dict(windows).items()}
        self.truth_std_limit = float(truth_std_limit)
        self._radar = PerTruth()           # the radar's own RMSE: once per truth, not once per variant
        self._flight = None                # the scenario's Flight (check): the cleaning and residual rows

    def check(self, scenario, sensor, estimators) -> None:
        """A radar farther than its ``max_range`` from the flight at any scan is refused here, before any
        stage (a flight given by its file alone with a site pinned for another flight: thousands of km)."""
        flight = getattr(scenario, "flight", None)
        if flight is None or not hasattr(flight, "cleaning"):
            return
        self._flight = flight
        if getattr(sensor, "max_range", None) is None or not hasattr(sensor, "check_range"):
            return
        try:
            sensor.check_range(flight.state[:, :3], flight.time)
        except ValueError as exc:
            reason = str(exc).removeprefix("max_range: ")
            advice = ("A pinned site (scenario.site_latitude and scenario.site_longitude) wins over "
                      "scenario.site_bearing_deg and scenario.site_distance: set both to null to place the radar "
                      "relative to the flight (30 km south of the window's median point by default), pin a site "
                      "near it, or raise sensors.max_range."
                      if "pinned" in flight.provenance["site"] else
                      "The window reaches that far from its own median point: choose a shorter window "
                      "(scenario.start, scenario.duration), or raise sensors.max_range.")
            raise ConfigError(
                f"sensors.max_range: the radar site at {flight.provenance['site']} is too far from the flight "
                f"{flight.provenance['source']}: {reason} (sensors.max_range). {advice}") from None

    def record(self, path, inputs) -> None:
        """Study 000's 3-D recording plus the maneuver class on the timeline and a map of run 0 (the
        truth's ``site`` label gives the ENU origin's latitude, longitude and height)."""
        from pipeline.views.single_target import write_recording
        truth = inputs.truth
        to_geodetic = None
        if "site" in truth.labels:
            import pymap3d
            latitude, longitude, height = (float(v) for v in np.asarray(truth.labels["site"])[0, 0, 0])

            def to_geodetic(xyz: np.ndarray) -> np.ndarray:
                lat, lon, _ = pymap3d.enu2geodetic(xyz[..., 0], xyz[..., 1], xyz[..., 2], latitude, longitude, height)
                return np.stack([lat, lon], axis=-1)
        where = getattr(inputs.sensor, "position", None)
        located = {} if where is None else {"sensor_position": [float(v) for v in where]}
        write_recording(path, maneuver_names=MANEUVER_NAMES, to_geodetic=to_geodetic, **inputs.common(), **located)

    def per_step_metrics(self, truth, estimate, sensor) -> dict[str, np.ndarray]:
        out = super().per_step_metrics(truth, estimate, sensor)
        if "position_std" in truth.labels:     # the truth's own uncertainty, per scan like the RMSE beside it
            # a fixed (K,) series (the same in every run): a value per window, no interval, no paired difference
            out["truth_position_std"] = np.sqrt(np.mean(_truth_variance(truth), axis=0))
        index = [truth.state_names.index(n) for n in POSITION_VELOCITY if n in truth.state_names]
        error = estimate.state[..., index] - truth.state[:, :, 0, index]
        covariance = estimate.covariance[..., index, :][..., :, index]
        out.update(consistency("nees_position_velocity", nees(error, covariance), len(index)))
        return out

    def variant_summary(self, inputs: VariantInputs) -> list[dict]:
        truth, key, display, estimate = inputs.truth, inputs.key, inputs.display, inputs.estimate
        runs, sensor, metrics = inputs.runs, inputs.sensor, inputs.metrics
        labels = np.asarray(truth.labels["maneuver"])[0, :, 0]
        counted = np.arange(labels.size) >= self.first_scan
        names = truth.state_names
        position = [names.index(n) for n in ("x", "y", "z") if n in names]
        velocity = [names.index(n) for n in ("vx", "vy", "vz") if n in names]
        rows: list[dict] = []
        radar = self._radar.get(truth, sensor, "radar", lambda: radar_position_rmse(truth, sensor, self.first_scan))

        def add(series: str, value: float | None) -> None:
            rows.append({"variant": display, "variant_key": key, "series": series, "window": None,
                         "value": None if value is None or not np.isfinite(value) else float(value),
                         "unit": unit_of(series), "n_runs": runs})

        add("radar_position_rmse", radar)
        flight = self._flight
        if flight is not None:                 # what the truth is made of: the cleaning and the smoothing
            cleaning = flight.cleaning
            add("points_read", float(cleaning.read))
            add("points_kept", float(len(cleaning.time)))
            add("segments", float(len(cleaning.segments)))
            for reason in CLEANING_COUNTS:
                add(f"dropped_{reason}", float(cleaning.dropped.get(reason, 0)))
            for axis, value in zip(ENU_AXES, flight.smoothing_residual):
                add(f"smoothing_residual_{axis}", float(value))
        variance = _truth_variance(truth) if "position_std" in truth.labels else None
        squared = {
            "position": np.sum((estimate.state[..., position] - truth.state[:, :, 0, position]) ** 2, axis=-1),
            "velocity": np.sum((estimate.state[..., velocity] - truth.state[:, :, 0, velocity]) ** 2, axis=-1),
        }
        for code, name in enumerate(MANEUVER_NAMES):
            scans = counted & (labels == code)
            add(f"scans_{name}", float(scans.sum()))
            for quantity, values in squared.items():
                # pooled over the runs and the class's scans (None when the flight has none)
                statistic = WindowStatistic(RunValues(values, "rms"), np.nonzero(scans)[0], "pool")
                rows.append(summary_row(key, display, f"{quantity}_rmse_{name}", None, None, runs,
                                        statistic if scans.any() else None))
            if variance is not None:           # the truth's std over the class's scans, pooled like the RMSE
                add(f"truth_position_std_{name}", float(np.sqrt(np.mean(variance[:, scans]))) if scans.any() else None)
        per_step = resolved({f"nees_position_velocity{s}": metrics[f"nees_position_velocity{s}"]
                             for s in ("", "_lower", "_upper")})
        mean, lower, upper = (per_step[f"nees_position_velocity{s}"][counted] for s in ("", "_lower", "_upper"))
        valid = np.isfinite(mean)
        inside = (mean >= lower) & (mean <= upper)
        add("nees_position_velocity_in_band", float(inside[valid].mean()) if valid.any() else None)
        return rows

    def extra_summary(self, inputs: JobInputs) -> list[dict]:
        """Per window: the truth's std over the lowest position RMSE of the variants, and whether it is
        above ``truth_std_limit`` (``truth_uncertain``), on every variant's rows."""
        truth, runs, per_variant = inputs.truth, inputs.runs, inputs.per_variant
        if "position_std" not in truth.labels:
            return []
        K = truth.time.size
        std = np.sqrt(np.mean(_truth_variance(truth), axis=0))          # (K,) the same in every run
        rows = []
        for name, (first, last) in self.windows.items():
            steps = np.arange(first, min(last, K - 1) + 1)
            best = [_window_mean(values["position_rmse"], steps) for _, values in per_variant.values()
                    if "position_rmse" in values]
            best = [b for b in best if np.isfinite(b)]
            truth_std = _window_mean(std, steps)
            ratio = truth_std / min(best) if best and min(best) > 0 and np.isfinite(truth_std) else None
            for key, (shown, _) in per_variant.items():
                rows.append(summary_row(key, shown, "truth_std_to_best_rmse", name, ratio, runs))
                rows.append(summary_row(key, shown, "truth_uncertain", name,
                                        None if ratio is None else float(ratio > self.truth_std_limit), runs))
        return rows


def _truth_variance(truth) -> np.ndarray:
    """(R, K) the truth's position variance summed over its position axes (the smoother's, label
    ``position_std``: E, N, U; E, N on the horizontal plane)."""
    return np.sum(np.asarray(truth.labels["position_std"], dtype=float)[:, :, 0, :] ** 2, axis=-1)


def _window_mean(values: np.ndarray, steps: np.ndarray) -> float:
    """The summary's value of a per-step series over a window: the mean of its finite values."""
    chosen = np.asarray(values, dtype=float)[steps] if steps.size else np.empty(0)
    chosen = chosen[np.isfinite(chosen)]
    return float(chosen.mean()) if chosen.size else float("nan")
