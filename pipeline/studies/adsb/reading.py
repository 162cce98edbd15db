"""Reading recorded ADS-B flights (OpenSky / traffic column schema) and cleaning what real data need.

The schema is that of the OpenSky Network's state vectors as the ``traffic`` package keeps them:
``timestamp`` (ms since the Unix epoch), ``latitude``, ``longitude`` (deg, WGS-84), ``altitude``
(barometric, ft), and optionally ``groundspeed`` (kt), ``track`` (deg), ``vertical_rate`` (ft/min),
``onground``, ``icao24``, ``callsign``. Files: Parquet, CSV, JSON (records, pandas' column
orientation, or JSON lines), each optionally gzipped.

Cleaning, in this order, each dropped point counted under its reason (``CleanFlight.dropped``):

1. ``missing_position``: no timestamp, latitude, longitude or altitude;
2. ``on_ground``: ``onground`` is true (surface movement is not the airborne target we track);
3. ``duplicate_time`` / ``non_increasing_time``: a time stamp equal to / earlier than the latest
   kept one, in file order (re-sent blocks, clock errors); the first occurrence is kept;
4. ``stale_position``: latitude and longitude identical to the previous kept point. OpenSky samples
   the last known position every second, so a repeat is no new position but an old one with a new
   time stamp; kept, it would show a moving aircraft stopping for a second;
5. ``jump``: positions that cannot be reached from the previous kept one without a 3-D speed above
   ``max_speed`` (spoofing, decoding errors), kept greedily outwards from the start of the longest
   run of points that never imply such a speed. The default 600 m/s is about twice a subsonic
   aircraft's ground speed: OpenSky stamps a position with the second it was sampled, not received,
   so one second can show up to about two seconds of motion.

An altitude can be stale while the position is new (the zero_gravity sample holds its altitude for
10-15 s during the parabolas, then jumps 400 m): a repeated altitude is marked stale
(``CleanFlight.fresh_altitude`` False, counted as ``stale_altitude``) when the slowest vertical rate
reported since the value first appeared, times the time since, says it should have changed by more
than ``STALE_ALTITUDE_CHANGE`` (two 25 ft quanta). Of the other altitudes, those that cannot be reached
from the previous one without a vertical speed above ``max_vertical_speed`` (default 150 m/s,
30 000 ft/min, beyond any climb or dive in these samples) are glitches (``altitude_jump``), chosen
like position jumps. Such points keep their horizontal position; only the altitude is not used.

Then the kept points are split into segments wherever two consecutive ones are more than
``max_gap`` apart: a truth is only built within one segment (pipeline.studies.adsb.flight).
"""

from __future__ import annotations

import gzip
import importlib.util
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import polars as pl
import pymap3d

from pipeline.errors import ConfigError

SAMPLES_DIR = Path(__file__).parent / "samples"
TABLE_SUFFIXES = (".parquet", ".csv", ".json", ".jsonl", ".gz")
REQUIRED_COLUMNS = {"timestamp": "ms since the Unix epoch (or a date-time)", "latitude": "deg",
                    "longitude": "deg", "altitude": "barometric altitude in ft"}
OPTIONAL_COLUMNS = {"groundspeed": "kt", "track": "deg", "vertical_rate": "ft/min", "onground": "bool",
                    "icao24": "text", "callsign": "text"}
DROP_REASONS = ("missing_position", "on_ground", "duplicate_time", "non_increasing_time", "stale_position", "jump")
# what each reason means to a reader of a refusal ("370 of 378 points out of time order")
DROP_WORDS = {"missing_position": "without a position (NaN or missing time, latitude, longitude or altitude)",
              "on_ground": "on the ground", "duplicate_time": "with a repeated time stamp",
              "non_increasing_time": "out of time order", "stale_position": "repeating the previous position",
              "jump": "out of reach (a jump faster than max_speed)"}

FOOT = 0.3048                       # m, exactly
KNOT = 1852.0 / 3600.0              # m/s, exactly
FOOT_PER_MINUTE = FOOT / 60.0       # m/s
STALE_ALTITUDE_CHANGE = 2 * 25 * FOOT   # m
SECONDS_THRESHOLD = 1e11            # a numeric time stamp below this is in s (OpenSky's own tables), else ms


def feet_to_metres(value: np.ndarray | float) -> np.ndarray:
    return np.asarray(value, dtype=float) * FOOT


def knots_to_metres_per_second(value: np.ndarray | float) -> np.ndarray:
    return np.asarray(value, dtype=float) * KNOT


def feet_per_minute_to_metres_per_second(value: np.ndarray | float) -> np.ndarray:
    return np.asarray(value, dtype=float) * FOOT_PER_MINUTE


# ---- finding and reading a table ---------------------------------------------------------------
def shipped_samples() -> list[str]:
    """Names of the flights shipped with the project (pipeline/studies/adsb/samples/*.parquet)."""
    return sorted(p.stem for p in SAMPLES_DIR.glob("*.parquet"))


# what each shipped sample is (PROVENANCE.md's table): said in a report's header only when the file that
# ran is that sample, so a flight given by its path is never described as the experiment's default one
SAMPLE_DESCRIPTIONS = {
    "aircraft_carrier": "shipped sample: a US Navy jet near an aircraft carrier off San Diego, climbs, descents and turns",
    "zero_gravity": "shipped sample: parabolic (zero-gravity) flights over the Bay of Biscay",
    "belevingsvlucht": "shipped sample: an airliner's sightseeing flight over the Netherlands",
    "rega_sg": "shipped sample: a Rega rescue helicopter near St. Gallen, slow, tight turns and climbs",
    "munich": "shipped sample: a radio-aid calibration flight near Munich, circles and racetracks",
    "sisteron": "shipped sample: a glider thermalling near Sisteron",
    "noisy_spoofing": "shipped sample: GNSS spoofing, positions frozen then jumping",
    "noisy_time_issue": "shipped sample: time-stamp errors, positions held and released in steps",
}


def sample_description(path: Path | str) -> str:
    """What the flight file ``path`` is when it is a shipped sample, else ''."""
    path = Path(path)
    shipped = SAMPLES_DIR / f"{path.stem}.parquet"
    try:
        same = shipped.is_file() and path.resolve() == shipped.resolve()
    except OSError:
        same = False
    return SAMPLE_DESCRIPTIONS.get(path.stem, "") if same else ""


def _traffic_samples_dir() -> Path | None:
    """traffic's sample folder when the package is installed (the ``adsb`` extra), without importing it
    (importing traffic loads pandas and more: seconds we need not spend to find a file)."""
    try:
        spec = importlib.util.find_spec("traffic")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(list(spec.submodule_search_locations)[0]) / "data" / "samples"
    return folder if folder.is_dir() else None


def find_flight_file(flight: str) -> Path:
    """The file of ``flight``: an existing path, a shipped sample name ("aircraft_carrier", also as
    "military/aircraft_carrier"), or a sample of the installed traffic package."""
    path = Path(flight).expanduser()
    if path.is_file():
        return path
    if path.suffix.lower() in TABLE_SUFFIXES or path.is_dir():
        raise ConfigError(f"flight: {flight!r} is not a readable file. Give the path of a Parquet, CSV or JSON(.gz) "
                          f"table of ADS-B positions, or a sample name: {', '.join(shipped_samples())}.")
    name = flight.strip("/").rsplit("/", 1)[-1]
    shipped = SAMPLES_DIR / f"{name}.parquet"
    if shipped.is_file():
        return shipped
    traffic_dir = _traffic_samples_dir()
    if traffic_dir is not None:
        category = flight.strip("/").rsplit("/", 1)[0] if "/" in flight.strip("/") else None
        found = sorted(p for pattern in (f"**/{name}.json.gz", f"**/{name}.jsonl") for p in traffic_dir.glob(pattern)
                       if category is None or p.parent.name == category)
        if found:
            return found[0]
    where = (f"nor one of the installed traffic package's samples ({traffic_dir})" if traffic_dir else
             "and the traffic package, which has the other samples of traffic 2.13, is not installed (pip install "
             "'mtt-experiments[adsb]')")
    raise ConfigError(f"flight: {flight!r} is not a file, not a sample shipped with the project "
                      f"({', '.join(shipped_samples())}), {where}.")


def _expected() -> str:
    required = ", ".join(f"{c} ({u})" for c, u in REQUIRED_COLUMNS.items())
    optional = ", ".join(f"{c} ({u})" for c, u in OPTIONAL_COLUMNS.items())
    return (f"Expected a table of ADS-B positions in the OpenSky/traffic schema (Parquet, CSV, or JSON records, "
            f"optionally gzipped) with the columns {required}, and optionally {optional}")


def _json_frame(data: object) -> pl.DataFrame:
    """A frame from parsed JSON: a list of records, or pandas' column orientation {column: {row: value}}."""
    if isinstance(data, list) and all(isinstance(row, dict) for row in data):
        return pl.from_dicts(data, infer_schema_length=None, strict=False)
    if isinstance(data, dict) and data and all(isinstance(v, (dict, list)) for v in data.values()):
        first = next(iter(data.values()))
        rows = list(first.keys()) if isinstance(first, dict) else range(len(first))
        columns = {name: [values.get(r) for r in rows] if isinstance(values, dict) else list(values)
                   for name, values in data.items()}
        return pl.DataFrame(columns, strict=False)
    raise ValueError("the JSON is neither a list of records nor a mapping of columns")


def read_opensky_table(path: Path | str) -> pl.DataFrame:
    """The rows of ``path`` as they are, with the required columns checked (a ConfigError otherwise)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or type(exc).__name__}). "
                          f"{_expected()}.") from None
    try:
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        if raw[:4] == b"PAR1":
            frame = pl.read_parquet(io.BytesIO(raw))
        elif raw.lstrip()[:1] in (b"[", b"{"):
            text = raw.decode("utf-8")
            try:
                frame = _json_frame(json.loads(text))
            except json.JSONDecodeError:                              # JSON lines: one record a line
                frame = _json_frame([json.loads(line) for line in text.splitlines() if line.strip()])
        else:
            frame = pl.read_csv(io.BytesIO(raw), infer_schema_length=None)
    except Exception as exc:                                          # any parser's refusal: one paragraph
        reason = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"{path}: is not a readable table ({type(exc).__name__}: {reason}). "
                          f"{_expected()}.") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in frame.columns]
    if missing:
        found = ", ".join(frame.columns[:20]) or "none"
        raise ConfigError(f"{path}: has no column {', '.join(repr(c) for c in missing)}; it has {found}. "
                          f"{_expected()}.")
    return frame


# ---- cleaning ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CleanFlight:
    """The kept points of a recorded flight in SI units, in time order.

    time (N,) s since the Unix epoch, strictly increasing; latitude, longitude (N,) deg;
    altitude (N,) m (barometric: the pressure altitude, used as the height); fresh_altitude (N,) bool,
    False where the altitude is a stale repeat (module doc); groundspeed (N,) m/s, track (N,) deg,
    vertical_rate (N,) m/s (NaN where the file has none); dropped: points dropped per reason, and
    ``stale_altitude``, ``altitude_jump``: altitudes not used (their points are kept); segments: index
    ranges [first, stop) of the kept points between gaps longer than max_gap.
    """

    source: str
    icao24: str
    callsign: str
    time: np.ndarray
    latitude: np.ndarray
    longitude: np.ndarray
    altitude: np.ndarray
    fresh_altitude: np.ndarray
    groundspeed: np.ndarray
    track: np.ndarray
    vertical_rate: np.ndarray
    read: int
    dropped: Mapping[str, int]
    segments: tuple[tuple[int, int], ...]
    max_gap: float = field(default=20.0)
    # every row of the file: its time stamp [s since the epoch; NaN where it has none] and what became of
    # it (0 kept, i + 1 dropped for DROP_REASONS[i]), so a refusal can say what cleaning removed where
    raw_time: np.ndarray = field(default_factory=lambda: np.empty(0))
    raw_reason: np.ndarray = field(default_factory=lambda: np.empty(0, np.int8))

    def segment_times(self) -> list[tuple[float, float]]:
        """(start, end) of every segment in s from the first kept point."""
        t = self.time - self.time[0]
        return [(float(t[a]), float(t[b - 1])) for a, b in self.segments]

    def removed_between(self, start: float, end: float) -> str:
        """What cleaning removed of the file's rows stamped strictly between ``start`` and ``end`` [s from
        the first kept point] (a gap), in words: "370 of 378 points out of time order, 8 without a
        position", or that the file has no point there."""
        t = self.raw_time - self.time[0]
        inside = (t > start + 1e-9) & (t < end - 1e-9)
        if not inside.any():
            return f"the file has no point between {start:g} s and {end:g} s"
        counts = np.bincount(self.raw_reason[inside], minlength=len(DROP_REASONS) + 1)
        total = int(inside.sum())
        parts = [f"{int(counts[i + 1])} of {total} points {DROP_WORDS[reason]}"
                 for i, reason in sorted(enumerate(DROP_REASONS), key=lambda item: -counts[item[0] + 1])
                 if counts[i + 1]]
        return f"between {start:g} s and {end:g} s cleaning removed {', '.join(parts)}"

    def describe(self) -> str:
        """One line: points read, dropped per reason, kept, segments."""
        dropped = ", ".join(f"{k} {v}" for k, v in self.dropped.items() if k in DROP_REASONS)
        return (f"{self.source}: {self.read} points read; dropped {dropped}; kept {len(self.time)} in "
                f"{len(self.segments)} segment(s) (gaps > {self.max_gap:g} s); altitude not used at "
                f"{self.dropped['stale_altitude']} (stale) + {self.dropped['altitude_jump']} (jump)")


def _first_text(frame: pl.DataFrame, column: str) -> str:
    if column not in frame.columns:
        return ""
    values = frame[column].drop_nulls()
    return str(values[0]).strip() if len(values) else ""


def _milliseconds(column: pl.Series) -> np.ndarray:
    """Time stamps as float ms since the epoch from numbers (ms, or s below 1e11), date-times or ISO text."""
    if column.dtype == pl.String:
        column = column.str.to_datetime(strict=False, time_zone="UTC")
    if isinstance(column.dtype, pl.Datetime):
        return column.dt.epoch("ms").cast(pl.Float64).fill_null(np.nan).to_numpy()
    values = column.cast(pl.Float64, strict=False).fill_null(np.nan).to_numpy()
    finite = values[np.isfinite(values)]
    return values * 1000.0 if finite.size and np.nanmedian(np.abs(finite)) < SECONDS_THRESHOLD else values


def _numbers(frame: pl.DataFrame, column: str) -> np.ndarray:
    if column not in frame.columns:
        return np.full(frame.height, np.nan)
    return frame[column].cast(pl.Float64, strict=False).fill_null(np.nan).to_numpy()


def _jump_free(position: np.ndarray, time: np.ndarray, max_speed: float) -> np.ndarray:
    """Which points to keep so that every kept one is reachable from the previous kept one within
    ``max_speed`` (module doc, 5): greedy outwards from an anchor, the first point of the longest run of
    points that never imply such a speed (so a bad first point cannot reject the whole flight). One
    point at a time, so a jittered time stamp costs one point, not the rest of a run."""
    def reachable(i: int, j: int) -> bool:
        distance = sum((p - q) ** 2 for p, q in zip(points[i], points[j]))
        return distance <= (max_speed * (seconds[j] - seconds[i])) ** 2

    n = len(time)
    if n < 2:
        return np.ones(n, bool)
    points, seconds = position.reshape(n, -1).tolist(), time.tolist()
    too_fast = np.sum(np.diff(position.reshape(n, -1), axis=0) ** 2, axis=1) > (max_speed * np.diff(time)) ** 2
    starts = np.concatenate([[0], np.flatnonzero(too_fast) + 1])
    stops = np.append(starts[1:], n)
    anchor = int(starts[np.argmax(stops - starts)])
    keep = np.zeros(n, bool)
    keep[anchor] = True
    for order in (range(anchor + 1, n), range(anchor - 1, -1, -1)):
        last = anchor
        for i in order:
            if reachable(min(last, i), max(last, i)):
                keep[i], last = True, i
    return keep


def stale_altitudes(time: np.ndarray, altitude: np.ndarray, vertical_rate: np.ndarray) -> np.ndarray:
    """(N,) True where an altitude repeats the previous one although the slowest vertical rate reported
    since that value first appeared, times the time since, says it changed by more than
    STALE_ALTITUDE_CHANGE (module doc). The slowest rate: a cruise whose rate flickers by one 64 ft/min
    quantum, or a level-off whose rate decays to 0, keeps its altitude; a parabola at 100 m/s does not."""
    changed = np.concatenate([[True], np.diff(altitude) != 0])
    first_of_value = np.flatnonzero(changed)[np.cumsum(changed) - 1]
    rates = pl.DataFrame({"value": first_of_value, "rate": np.abs(np.nan_to_num(vertical_rate))})
    slowest = rates.select(pl.col("rate").cum_min().over("value"))["rate"].to_numpy()
    return ~changed & (slowest * (time - time[first_of_value]) > STALE_ALTITUDE_CHANGE)


def clean_flight(frame: pl.DataFrame, source: str, max_gap: float = 20.0, max_speed: float = 600.0,
                 max_vertical_speed: float = 150.0) -> CleanFlight:
    """Drop what cannot be a new airborne position (module doc), convert to SI units, split at gaps."""
    read = frame.height
    time_ms = _milliseconds(frame["timestamp"])
    lat, lon = _numbers(frame, "latitude"), _numbers(frame, "longitude")
    alt = feet_to_metres(_numbers(frame, "altitude"))
    dropped: dict[str, int] = {}
    reason = np.zeros(read, np.int8)                                       # 0: kept (CleanFlight.raw_reason)
    code = {name: np.int8(i + 1) for i, name in enumerate(DROP_REASONS)}
    keep = np.isfinite(time_ms) & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
    keep &= (np.abs(lat) <= 90) & (np.abs(lon) <= 180)
    dropped["missing_position"] = int(read - keep.sum())
    reason[~keep] = code["missing_position"]
    if "onground" in frame.columns:
        on_ground = frame["onground"].cast(pl.Boolean, strict=False).fill_null(False).to_numpy() & keep
        dropped["on_ground"] = int(on_ground.sum())
        keep &= ~on_ground
        reason[on_ground] = code["on_ground"]
    else:
        dropped["on_ground"] = 0
    index = np.flatnonzero(keep)
    t = time_ms[index]
    latest = np.maximum.accumulate(np.concatenate([[-np.inf], t]))[:-1]      # the latest time before each
    dropped["duplicate_time"] = int(np.sum(t == latest))
    dropped["non_increasing_time"] = int(np.sum(t < latest))
    reason[index[t == latest]] = code["duplicate_time"]
    reason[index[t < latest]] = code["non_increasing_time"]
    index = index[t > latest]
    if index.size == 0:
        raise ConfigError(f"{source}: none of its {read} points is an airborne position with a time stamp "
                          f"(dropped: {', '.join(f'{k} {v}' for k, v in dropped.items())}). {_expected()}.")
    stale = np.concatenate([[False], (np.diff(lat[index]) == 0) & (np.diff(lon[index]) == 0)])
    dropped["stale_position"] = int(stale.sum())
    reason[index[stale]] = code["stale_position"]
    index = index[~stale]
    seconds = time_ms[index] / 1000.0
    ecef = np.stack(pymap3d.geodetic2ecef(lat[index], lon[index], alt[index]), axis=-1)
    kept = _jump_free(ecef, seconds, max_speed)
    dropped["jump"] = int(np.sum(~kept))
    reason[index[~kept]] = code["jump"]
    index, seconds = index[kept], seconds[kept]                            # the anchor is always kept
    vertical_rate = feet_per_minute_to_metres_per_second(_numbers(frame, "vertical_rate")[index])
    fresh_altitude = ~stale_altitudes(seconds, alt[index], vertical_rate)
    dropped["stale_altitude"] = int(np.sum(~fresh_altitude))
    fresh = np.flatnonzero(fresh_altitude)
    altitude_jump = fresh[~_jump_free(alt[index][fresh], seconds[fresh], max_vertical_speed)]
    fresh_altitude[altitude_jump] = False
    dropped["altitude_jump"] = int(altitude_jump.size)
    cuts = np.flatnonzero(np.diff(seconds) > max_gap) + 1
    bounds = np.concatenate([[0], cuts, [index.size]])
    return CleanFlight(
        source=source, icao24=_first_text(frame, "icao24"), callsign=_first_text(frame, "callsign"),
        time=seconds, latitude=lat[index], longitude=lon[index], altitude=alt[index], fresh_altitude=fresh_altitude,
        groundspeed=knots_to_metres_per_second(_numbers(frame, "groundspeed")[index]),
        track=_numbers(frame, "track")[index], vertical_rate=vertical_rate,
        read=read, dropped=dropped, segments=tuple((int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])),
        max_gap=float(max_gap), raw_time=time_ms / 1000.0, raw_reason=reason)


def load_flight(flight: str, max_gap: float = 20.0, max_speed: float = 600.0,
                max_vertical_speed: float = 150.0) -> CleanFlight:
    """Find, read and clean ``flight`` (a sample name or a path)."""
    path = find_flight_file(flight)
    return clean_flight(read_opensky_table(path), str(path), max_gap, max_speed, max_vertical_speed)
