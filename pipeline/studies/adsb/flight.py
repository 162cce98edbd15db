"""A truth from a recorded flight: local ENU at a radar site, RTS-smoothed, resampled to the scan period.

Why smoothing: ADS-B positions are quantised (CPR, ~5 m), jittered in time (OpenSky stamps the
second it sampled a position) and altitudes come in 25 ft steps. Finite differences of them give
velocities and accelerations far noisier than the aircraft's. The fixed-interval smoother
(filters.smoothing) over a white-jerk constant-acceleration model on each ENU axis gives a
trajectory whose position, velocity and acceleration agree with each other (the Monte Carlo
measurements are drawn from this truth, so the tracking errors are exact for it). How far it is
from the raw positions is reported per axis (``Flight.smoothing_residual``): compare it with the
radar's noise before drawing conclusions at that level.

Maneuver labels per scan, from the truth (bits, so both may hold):

- ``turn``: horizontal acceleration normal to the horizontal velocity above ``turn_threshold``
  (default 1.5 m/s^2, about 0.15 g: a bank of ~9 deg; a standard-rate turn at 250 kt is ~6.7 m/s^2);
  not evaluated below 5 m/s of ground speed (no direction to turn from);
- ``climb_descent``: |vertical velocity| above ``climb_threshold`` (default 2.5 m/s, ~500 ft/min);
  "horizontal" and "vertical" are those of the aircraft's own position (``local_up``), not the site's;
- ``straight``: neither (speed changes along the track count as straight).
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Mapping

import numpy as np
import pymap3d

from filters.smoothing import smooth_with_covariance
from pipeline.studies.adsb.reading import CleanFlight, find_flight_file, load_flight

STATE_NAMES = ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")   # ENU east, north, up; study 000's layout
MANEUVER_NAMES = ("straight", "turn", "climb_descent", "turn_climb_descent")
TURN, CLIMB_DESCENT = 1, 2                                          # bits of the maneuver label
MIN_TURN_SPEED = 5.0                                                # m/s


@dataclass(frozen=True)
class Flight:
    """One recorded flight as a truth over a window of one segment.

    time (K,) s from the window start, scan_period apart; state (K, 9) in STATE_NAMES order, ENU at
    the site [m, m/s, m/s^2]; maneuver (K,) int8 index into maneuver_names; smoothing_residual (3,)
    RMS of smoothed minus raw position per ENU axis over the window's raw points [m];
    measured_time (M,), measured_position (M, 3): those raw points (ENU; up NaN where the altitude
    was stale); cleaning: what was dropped;
    provenance: file, aircraft, window (UTC), site (and how it was placed); position_std (K, 3): the
    smoother's own position std per axis at each scan (the truth's uncertainty given the samples) [m].
    """

    time: np.ndarray
    state: np.ndarray
    maneuver: np.ndarray
    smoothing_residual: np.ndarray
    measured_time: np.ndarray
    measured_position: np.ndarray
    cleaning: CleanFlight
    provenance: Mapping[str, str]
    state_names: tuple[str, ...] = STATE_NAMES
    maneuver_names: tuple[str, ...] = MANEUVER_NAMES
    site: tuple[float, float, float] = (float("nan"), float("nan"), float("nan"))   # the ENU origin: lat, lon [deg], h [m]
    position_std: np.ndarray | None = None     # (K, 3) the smoother's position std per ENU axis at each scan [m]

    def maneuver_shares(self) -> dict[str, float]:
        """Share of scans per maneuver label."""
        counts = np.bincount(self.maneuver, minlength=len(self.maneuver_names))
        return {name: float(c) / len(self.maneuver) for name, c in zip(self.maneuver_names, counts)}

    def describe(self) -> str:
        """One paragraph: the cleaning, the window, the residual, the maneuver shares."""
        shares = ", ".join(f"{k} {v:.0%}" for k, v in self.maneuver_shares().items())
        residual = ", ".join(f"{a} {r:.1f}" for a, r in zip("ENU", self.smoothing_residual))
        std = "" if self.position_std is None else \
            f"; truth position std RMS {float(np.sqrt(np.mean(np.sum(self.position_std ** 2, axis=1)))):.1f} m"
        return (f"{self.cleaning.describe()}. Window {self.provenance['window']}: {len(self.time)} scans; "
                f"smoothing residual RMS [m] {residual}{std}; maneuvers {shares}.")


def geodetic_to_enu(latitude: np.ndarray, longitude: np.ndarray, height: np.ndarray,
                    site: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) east, north, up [m] at ``site`` (latitude, longitude [deg], height [m]) of WGS-84 points."""
    return np.stack(pymap3d.geodetic2enu(latitude, longitude, height, *site), axis=-1)


def local_up(position: np.ndarray, site: tuple[float, float, float]) -> np.ndarray:
    """(K, 3) unit vectors of the local vertical at ENU ``position`` (K, 3), in the site's ENU axes.

    Why: the site's "up" is not the aircraft's. 100 km from the site the two differ by 0.9 deg, so
    a level flight at 250 m/s shows ~4 m/s of ENU vz; vertical rate and the horizontal plane of a
    turn are taken at the aircraft."""
    lat, lon, _ = pymap3d.enu2geodetic(position[:, 0], position[:, 1], position[:, 2], *site)
    lat, lon = np.radians(lat), np.radians(lon)
    up_ecef = (np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat))
    return np.stack(pymap3d.ecef2enuv(*up_ecef, site[0], site[1]), axis=-1)


def maneuver_labels(state: np.ndarray, up: np.ndarray, turn_threshold: float, climb_threshold: float) -> np.ndarray:
    """(K,) int8 labels (module doc) from states (K, 9) in STATE_NAMES order and the local vertical ``up`` (K, 3)."""
    velocity, acceleration = state[:, 3:6], state[:, 6:9]
    vertical_rate = np.sum(velocity * up, axis=1)
    horizontal_velocity = velocity - vertical_rate[:, None] * up
    horizontal_acceleration = acceleration - np.sum(acceleration * up, axis=1)[:, None] * up
    speed = np.linalg.norm(horizontal_velocity, axis=1)
    normal = np.linalg.norm(np.cross(horizontal_velocity, horizontal_acceleration), axis=1)
    turn = (speed >= MIN_TURN_SPEED) & (normal > turn_threshold * np.maximum(speed, MIN_TURN_SPEED))
    return (TURN * turn + CLIMB_DESCENT * (np.abs(vertical_rate) > climb_threshold)).astype(np.int8)


LISTED_SEGMENTS = 12      # a refusal lists this many of the longest segments


def segment_listing(cleaned: CleanFlight) -> str:
    """The flight's segments for a refusal: how many, and the longest ones first (a flight of 300
    segments is chosen from by its longest, not by its first twelve)."""
    spans = cleaned.segment_times()
    longest = sorted(range(len(spans)), key=lambda i: (-(spans[i][1] - spans[i][0]), i))[:LISTED_SEGMENTS]
    listing = ", ".join(f"[{spans[i][0]:g}, {spans[i][1]:g}] ({spans[i][1] - spans[i][0]:g} s)" for i in longest)
    more = f" and {len(spans) - len(longest)} shorter" if len(spans) > len(longest) else ""
    return (f"{cleaned.source} has {len(spans)} segment(s) between gaps of more than {cleaned.max_gap:g} s; the "
            f"longest, at [start, end] s from its first kept point: {listing}{more}")


def _window(cleaned: CleanFlight, start: float, duration: float | None) -> tuple[int, float, float]:
    """(segment index, window start, window end) in s from the first kept point; ValueError naming the key
    when the window is not inside one segment. ``duration`` None: the longest segment, whole (the first
    of equally long ones), which needs ``start`` 0."""
    spans = cleaned.segment_times()
    if duration is None:
        segment = int(np.argmax([b - a for a, b in spans]))
        if start != 0:
            raise ValueError(f"start: {start:g} s with duration null: a null duration takes the longest segment "
                             f"whole, [{spans[segment][0]:g}, {spans[segment][1]:g}] s; give a duration to start "
                             f"elsewhere. {segment_listing(cleaned)}")
        return segment, spans[segment][0], spans[segment][1]
    inside = [i for i, (a, b) in enumerate(spans) if a <= start <= b]
    if not inside:
        raise ValueError(f"start: {start:g} s is not inside a segment of the flight; {segment_listing(cleaned)}. "
                         f"duration=null takes the longest segment")
    segment = inside[0]
    seg_end = spans[segment][1]
    end = start + duration
    if end > seg_end + 1e-9:
        following = [a for a, _ in spans[segment + 1:] if a <= end]
        crossing = (f"spans the gap between {seg_end:g} s and {spans[segment + 1][0]:g} s ("
                    f"{cleaned.removed_between(seg_end, spans[segment + 1][0])})" if following
                    else f"runs past the end of the flight's segment at {seg_end:g} s")
        raise ValueError(f"duration: the window [{start:g}, {end:g}] s {crossing}; a truth needs positions "
                         f"throughout its window. Choose start and duration within one segment, or duration=null "
                         f"for the longest segment: {segment_listing(cleaned)}")
    return segment, start, end


def site_of(latitude: float, longitude: float, site_latitude: float | None, site_longitude: float | None,
            bearing_deg: float, distance: float) -> tuple[tuple[float, float], str]:
    """The radar site (latitude, longitude [deg]) and how it was placed: pinned (``site_latitude`` and
    ``site_longitude`` given: they win), else ``distance`` [m] along the WGS-84 geodesic at
    ``bearing_deg`` (clockwise from north) from the window's median point (``latitude``, ``longitude``)."""
    if (site_latitude is None) != (site_longitude is None):
        given, missing = ("site_latitude", "site_longitude") if site_longitude is None else ("site_longitude",
                                                                                            "site_latitude")
        raise ValueError(f"{missing}: null while {given} is given; a pinned site needs both (they then win over "
                         f"site_bearing_deg and site_distance), or neither to place it relative to the flight")
    if site_latitude is not None and site_longitude is not None:
        return (float(site_latitude), float(site_longitude)), "pinned by site_latitude and site_longitude"
    if distance == 0:
        return (latitude, longitude), "at the window's median point"
    from pymap3d.vincenty import vreckon
    lat, lon = vreckon(latitude, longitude, distance, bearing_deg % 360.0)
    lon = (float(lon) + 180.0) % 360.0 - 180.0                               # vreckon gives [0, 360)
    return (float(lat), lon), f"{distance / 1000:g} km at bearing {bearing_deg % 360.0:g} deg from the window's median point"


# Flights built in this process, by file (path, modification time, size) and every argument: a
# scenario is built for each config a process checks or runs (a sweep's jobs in one process, the
# tests), and reading, cleaning and smoothing a flight took 0.04-0.44 s each time (the four shipped
# ADS-B experiments; 0.2-0.3 ms from here). Read-only arrays,
# so no holder can change what the next one gets.
_BUILT: "OrderedDict[tuple, Flight]" = OrderedDict()
_BUILT_KEPT = 16


def build_flight(flight: str, scan_period: float = 1.0, start: float = 0.0, duration: float | None = None,
                 site_latitude: float | None = None, site_longitude: float | None = None, site_height: float = 0.0,
                 horizontal_noise_std: float = 25.0, vertical_noise_std: float = 5.0, jerk_psd: float = 1.0,
                 max_gap: float = 20.0, max_speed: float = 600.0, max_vertical_speed: float = 150.0,
                 turn_threshold: float = 1.5, climb_threshold: float = 2.5, site_bearing_deg: float = 180.0,
                 site_distance: float = 30_000.0) -> Flight:
    """Read, clean and smooth ``flight`` into a truth at ``scan_period`` over [start, start + duration] s
    from its first kept point (duration None: the longest segment, whole).

    The site (``site_of``): ``site_distance`` [m] at ``site_bearing_deg`` from the median latitude and
    longitude of the window's points (default 30 km south, so the flight does not pass overhead), at
    ``site_height``; ``site_latitude`` and ``site_longitude``, when both given, pin it. Noise stds are those the
    smoother assumes for one ADS-B position (east and north, up) [m]; ``jerk_psd`` [m^2/s^5] sets how
    fast it lets the acceleration change. The whole segment is smoothed, so the window's first and
    last scans are smoothed with data on both sides like the others.

    The same file (unchanged: path, modification time and size) with the same arguments gives the
    Flight this process built before, its arrays read-only.
    """
    path = find_flight_file(flight)
    status = path.stat()
    arguments = (scan_period, start, duration, site_latitude, site_longitude, site_height, horizontal_noise_std,
                 vertical_noise_std, jerk_psd, max_gap, max_speed, max_vertical_speed, turn_threshold, climb_threshold,
                 site_bearing_deg, site_distance)
    key = (str(path.resolve()), status.st_mtime_ns, status.st_size, *(repr(a) for a in arguments))
    built = _BUILT.get(key)
    if built is None:
        built = _read_only(_build_flight(str(path), *arguments))
        _BUILT[key] = built
        while len(_BUILT) > _BUILT_KEPT:
            _BUILT.popitem(last=False)
    _BUILT.move_to_end(key)
    return built


def _read_only(built: Flight) -> Flight:
    for holder in (built, built.cleaning):
        for field in dataclasses.fields(holder):
            value = getattr(holder, field.name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
    return built


def _build_flight(flight: str, scan_period: float, start: float, duration: float | None, site_latitude: float | None,
                  site_longitude: float | None, site_height: float, horizontal_noise_std: float,
                  vertical_noise_std: float, jerk_psd: float, max_gap: float, max_speed: float,
                  max_vertical_speed: float, turn_threshold: float, climb_threshold: float, site_bearing_deg: float,
                  site_distance: float) -> Flight:
    cleaned = load_flight(flight, max_gap, max_speed, max_vertical_speed)
    segment, t_start, t_end = _window(cleaned, start, duration)
    steps = int(np.floor((t_end - t_start) / scan_period + 1e-9))
    if steps < 2:
        raise ValueError(f"duration: the window [{t_start:g}, {t_end:g}] s holds {steps + 1} scan(s) of "
                         f"scan_period {scan_period:g} s; a truth needs at least 3")
    first, stop = cleaned.segments[segment]
    t = cleaned.time[first:stop] - cleaned.time[0]
    in_window = (t >= t_start - 1e-9) & (t <= t_end + 1e-9)
    lat, lon, alt = cleaned.latitude[first:stop], cleaned.longitude[first:stop], cleaned.altitude[first:stop]
    (site_lat, site_lon), placed = site_of(float(np.median(lat[in_window])), float(np.median(lon[in_window])),
                                           site_latitude, site_longitude, site_bearing_deg, site_distance)
    site = (site_lat, site_lon, float(site_height))
    enu = geodetic_to_enu(lat, lon, alt, site)
    samples = enu.copy()
    fresh = cleaned.fresh_altitude[first:stop]
    if fresh.any():                                                        # a stale altitude is no sample of up
        samples[~fresh, 2] = np.nan
    scan_time = t_start + scan_period * np.arange(steps + 1)
    # the scans are inserted as steps without data; a scan at a sample's time comes after it (stable sort)
    all_time = np.concatenate([t, scan_time])
    order = np.argsort(all_time, kind="stable")
    positions = np.concatenate([samples, np.full((scan_time.size, 3), np.nan)])[order]
    noise = np.array([horizontal_noise_std, horizontal_noise_std, vertical_noise_std])
    smoothed, covariance = smooth_with_covariance(all_time[order], positions, noise, jerk_psd)
    at = np.empty(order.size, int)
    at[order] = np.arange(order.size)
    at_samples, at_scans = at[:t.size], at[t.size:]
    state = smoothed[at_scans].transpose(0, 2, 1).reshape(-1, 9)          # (K, [p, v, a] x [E, N, U])
    residual = smoothed[at_samples[in_window], :, 0] - samples[in_window]
    absolute_start = cleaned.time[0] + t_start
    provenance = {
        "source": cleaned.source, "icao24": cleaned.icao24, "callsign": cleaned.callsign,
        "window": f"[{t_start:g}, {t_end:g}] s of segment {segment} (UTC "
                  f"{datetime.fromtimestamp(absolute_start, timezone.utc):%Y-%m-%d %H:%M:%S} + {t_end - t_start:g} s)",
        "site": f"latitude {site[0]:.6f} deg, longitude {site[1]:.6f} deg, height {site[2]:g} m (WGS-84), {placed}",
    }
    return Flight(time=scan_time - t_start, state=state,
                  maneuver=maneuver_labels(state, local_up(state[:, :3], site), turn_threshold, climb_threshold),
                  smoothing_residual=np.sqrt(np.nanmean(residual ** 2, axis=0)),
                  measured_time=t[in_window] - t_start, measured_position=samples[in_window],
                  cleaning=cleaned, provenance=provenance, site=site,
                  position_std=np.sqrt(covariance[at_scans, :, 0, 0]))
