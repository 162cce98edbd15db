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
  beat to be worth running (the same for every variant).
"""

from __future__ import annotations

import numpy as np

from pipeline.contract import VariantInputs
from pipeline.evaluation.bounds import PerTruth
from pipeline.evaluation.evaluate import consistency, resolved, summary_row
from pipeline.evaluation.uncertainty import RunValues, WindowStatistic
from pipeline.evaluation.metrics import BAND, Metric, nees, register, unit_of
from pipeline.studies.adsb.flight import MANEUVER_NAMES
from pipeline.studies.single_target import SingleTargetStudy

POSITION_VELOCITY = ("x", "y", "z", "vx", "vy", "vz")

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
    the MIE filters' input estimate: 2) [scans]."""

    def __init__(self, first_scan: int = 2) -> None:
        super().__init__()
        if isinstance(first_scan, bool) or not isinstance(first_scan, int) or first_scan < 0:
            raise ValueError(f"first_scan: {first_scan!r} must be an integer >= 0")
        self.first_scan = first_scan
        self._radar = PerTruth()           # the radar's own RMSE: once per truth, not once per variant

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
        per_step = resolved({f"nees_position_velocity{s}": metrics[f"nees_position_velocity{s}"]
                             for s in ("", "_lower", "_upper")})
        mean, lower, upper = (per_step[f"nees_position_velocity{s}"][counted] for s in ("", "_lower", "_upper"))
        valid = np.isfinite(mean)
        inside = (mean >= lower) & (mean <= upper)
        add("nees_position_velocity_in_band", float(inside[valid].mean()) if valid.any() else None)
        return rows
