"""``RecordedFlight``: a recorded ADS-B flight as the truth of every Monte Carlo run.

State per scan, in this order: x, y, z [m], vx, vy, vz [m/s], ax, ay, az [m/s^2] in the radar
site's local east-north-up frame (study 000's layout). The runs differ only in the measurement noise
drawn later: the flight is the same for all of them, so ``generate`` ignores the seed.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np

from pipeline.run.checks import finite, non_negative, positive
from pipeline.data import Truth
from pipeline.studies.adsb.flight import MANEUVER_NAMES, STATE_NAMES, Flight, build_flight
from pipeline.studies.adsb.reading import find_flight_file, sample_description


HORIZONTAL_STATE_NAMES = ("x", "vx", "y", "vy")      # study 001's layout (horizontal=True)


class RecordedFlight:
    """A window of one recorded flight, smoothed into a truth (pipeline.studies.adsb.flight).

    Parameters
    ----------
    flight : a shipped sample name ("aircraft_carrier", "zero_gravity", "munich", "rega_sg", ...),
        another traffic 2.13 sample with the ``adsb`` extra, or the path of a Parquet/CSV/JSON(.gz) file
    scan_period : time between scans [s]
    start : window start [s from the flight's first kept point]; it picks the segment (gaps split one)
    duration : window length [s]; None: the longest segment, whole (start 0). A window over a gap is
        refused, naming the longest segments and what cleaning removed in the gap
    site_bearing_deg, site_distance : the radar site, placed this far [m] along the geodesic at this
        bearing [deg clockwise from north] from the window's median point (default 30 km south: no
        flight given by its file alone meets a radar on another continent); 0 m: at the median point
    site_latitude, site_longitude : the radar site pinned [deg]; both or neither; when given they win
        over site_bearing_deg and site_distance
    site_height : the site's height above the WGS-84 ellipsoid [m]
    horizontal_noise_std, vertical_noise_std : the smoother's std of one ADS-B position, east/north
        and up [m]
    jerk_psd : the smoother's white-jerk power spectral density [m^2/s^5]
    max_gap : a longer time between kept points splits the flight into segments [s]
    max_speed, max_vertical_speed : speeds beyond these mark position / altitude jumps [m/s]
    turn_threshold : normal horizontal acceleration above which a scan is a turn [m/s^2]
    climb_threshold : |vertical rate| above which a scan is a climb or descent [m/s]
    horizontal : the truth on the horizontal plane, in study 001's layout (x, vx, y, vy), with the
        height as the label ``up`` (for 2-D filters behind HorizontalRadar)
    """

    maneuver_names = MANEUVER_NAMES

    def __init__(self, flight: str = "aircraft_carrier", scan_period: float = 1.0, start: float = 0.0,
                 duration: float | None = None, site_latitude: float | None = None,
                 site_longitude: float | None = None, site_height: float = 0.0,
                 horizontal_noise_std: float = 25.0, vertical_noise_std: float = 5.0, jerk_psd: float = 1.0,
                 max_gap: float = 20.0, max_speed: float = 600.0, max_vertical_speed: float = 150.0,
                 turn_threshold: float = 1.5, climb_threshold: float = 2.5, horizontal: bool = False,
                 site_bearing_deg: float = 180.0, site_distance: float = 30_000.0) -> None:
        if not isinstance(horizontal, bool):
            raise ValueError(f"horizontal: {horizontal!r} must be true or false")
        self.horizontal = horizontal
        if not isinstance(flight, str) or not flight.strip():
            raise ValueError(f"flight: {flight!r} must be a sample name or the path of a file")
        positive("scan_period", scan_period, "s")
        non_negative("start", start, "s")
        if duration is not None:
            positive("duration", duration, "s")
        for key, value, limit in (("site_latitude", site_latitude, 90.0), ("site_longitude", site_longitude, 180.0)):
            if value is not None and not abs(finite(key, value, "deg")) <= limit:
                raise ValueError(f"{key}: {value!r} must be within [-{limit:g}, {limit:g}] deg")
        finite("site_height", site_height, "m")
        finite("site_bearing_deg", site_bearing_deg, "deg")
        non_negative("site_distance", site_distance, "m")
        for key, value, unit in (("horizontal_noise_std", horizontal_noise_std, "m"),
                                 ("vertical_noise_std", vertical_noise_std, "m"), ("jerk_psd", jerk_psd, "m^2/s^5"),
                                 ("max_gap", max_gap, "s"), ("max_speed", max_speed, "m/s"),
                                 ("max_vertical_speed", max_vertical_speed, "m/s"),
                                 ("turn_threshold", turn_threshold, "m/s^2"),
                                 ("climb_threshold", climb_threshold, "m/s")):
            positive(key, value, unit)
        self.flight: Flight = build_flight(
            flight, scan_period=float(scan_period), start=float(start),
            duration=None if duration is None else float(duration),
            site_latitude=site_latitude, site_longitude=site_longitude, site_height=float(site_height),
            horizontal_noise_std=float(horizontal_noise_std), vertical_noise_std=float(vertical_noise_std),
            jerk_psd=float(jerk_psd), max_gap=float(max_gap), max_speed=float(max_speed),
            max_vertical_speed=float(max_vertical_speed), turn_threshold=float(turn_threshold),
            climb_threshold=float(climb_threshold), site_bearing_deg=float(site_bearing_deg),
            site_distance=float(site_distance))
        self.dt = float(scan_period)
        self.source = find_flight_file(flight)
        # what the cleaning dropped and the smoothing residual, to set beside the radar's noise
        logging.getLogger("pipeline").info("[scenario] %s", self.flight.describe())

    def data_fingerprint(self) -> str:
        """SHA-256 of the flight's file: part of the scenario stage's cache key (pipeline.run.stages), so
        an edited or replaced file under the same name is never served from the cache."""
        return hashlib.sha256(Path(self.source).read_bytes()).hexdigest()

    def generate(self, runs: int, seed: int) -> Truth:
        """The flight for every run: labels acceleration (R, K, 1, 3) and maneuver (R, K, 1) int8."""
        flight = self.flight
        K = len(flight.time)
        state = np.broadcast_to(flight.state, (runs, K, len(STATE_NAMES)))[:, :, None, :].copy()
        maneuver = np.broadcast_to(flight.maneuver, (runs, K))[:, :, None].copy()
        # the ENU origin (latitude, longitude [deg], height [m]) per scan: the recording's map needs it
        site = np.broadcast_to(np.asarray(flight.site, dtype=np.float64), (runs, K, 1, 3)).copy()
        # the truth's own uncertainty: the smoother's position std per ENU axis (the adapter reports it)
        std = np.broadcast_to(flight.position_std, (runs, K, 3))[:, :, None, :].copy()
        if self.horizontal:          # study 001's layout; the height stays as a label for the radar
            plane = [STATE_NAMES.index(n) for n in HORIZONTAL_STATE_NAMES]
            return Truth(flight.time.copy(), state[..., plane].copy(), HORIZONTAL_STATE_NAMES,
                         {"acceleration": state[..., 6:8].copy(), "maneuver": maneuver, "site": site,
                          "up": state[..., 2:3].copy(), "position_std": std[..., :2].copy()})
        return Truth(flight.time.copy(), state, STATE_NAMES,
                     {"acceleration": state[..., 6:9].copy(), "maneuver": maneuver, "site": site,
                      "position_std": std})

    def describe(self) -> str:
        """The flight that runs, for the report's header: its file (and what it is, for a shipped
        sample), aircraft, window and scans, and the radar site with how it was placed."""
        flight = self.flight
        p = flight.provenance
        about = sample_description(self.source)
        aircraft = ", ".join(f"{k} {p[k]}" for k in ("icao24", "callsign") if p.get(k))
        return (f"flight {p['source']}" + (f" ({about})" if about else "") + (f", {aircraft}" if aircraft else "")
                + f"; window {p['window']}, {len(flight.time)} scans of {self.dt:g} s; radar site {p['site']}")
