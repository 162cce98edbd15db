"""Issue 17, data half: reading recorded ADS-B flights, cleaning them, and the truth built from them."""

from __future__ import annotations

import gzip
import importlib
import json
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pymap3d
import pytest
from omegaconf import OmegaConf

from filters.smoothing import smooth_constant_acceleration
from pipeline.run.config import build
from pipeline.errors import ConfigError
from pipeline.studies.adsb.flight import (CLIMB_DESCENT, MANEUVER_NAMES, STATE_NAMES, TURN, build_flight,
                                          geodetic_to_enu)
from pipeline.studies.adsb.reading import (DROP_REASONS, FOOT, clean_flight, feet_per_minute_to_metres_per_second,
                                           feet_to_metres, find_flight_file, knots_to_metres_per_second,
                                           load_flight, read_opensky_table, shipped_samples)
from pipeline.studies.adsb.scenario import RecordedFlight

SITE = (45.0, 7.0, 0.0)
SCENARIO = "pipeline.studies.adsb.scenario.RecordedFlight"
EPOCH = 1_600_000_000.0                                                   # s, 2020-09-13: real stamps are epoch ms


def _frame(time_s, east, north, up, **extra) -> pl.DataFrame:
    """An OpenSky-schema table of ENU points at SITE (time in s, positions in m)."""
    lat, lon, height = pymap3d.enu2geodetic(np.asarray(east, float), np.asarray(north, float),
                                            np.asarray(up, float), *SITE)
    columns = {"timestamp": np.round((EPOCH + np.asarray(time_s, float)) * 1000).astype(np.int64), "latitude": lat,
               "longitude": lon, "altitude": np.asarray(height) / FOOT, "icao24": ["abc123"] * len(lat),
               "callsign": ["TEST1"] * len(lat)}
    return pl.DataFrame({**columns, **extra})


def _straight(times, speed=100.0) -> pl.DataFrame:
    times = np.asarray(times, float)
    return _frame(times, 0 * times, speed * times, 3000 + 0 * times)


# ---- units and frames --------------------------------------------------------------------------
def test_unit_conversions_by_hand():
    assert feet_to_metres(1000.0) == pytest.approx(304.8, abs=1e-12)
    assert knots_to_metres_per_second(100.0) == pytest.approx(100 * 1852 / 3600, abs=1e-12)   # 51.444 m/s
    assert knots_to_metres_per_second(1.0) == pytest.approx(0.514444, abs=1e-6)
    assert feet_per_minute_to_metres_per_second(1000.0) == pytest.approx(5.08, abs=1e-12)


def test_enu_of_a_point_due_north_and_round_trip():
    # 0.01 deg due north at 45 deg: meridian radius a(1-e^2)/(1-e^2 sin^2)^1.5 = 6 367 381 m, so
    # 1111.33 m north, and the Earth's curvature drops it d^2 / 2R = 0.097 m below the site's horizon
    enu = geodetic_to_enu(np.array([45.01]), np.array([7.0]), np.array([0.0]), SITE)[0]
    assert abs(enu[0]) < 1e-6
    assert enu[1] == pytest.approx(6367381.0 * np.radians(0.01), abs=0.05)
    assert enu[2] == pytest.approx(-(enu[1] ** 2) / (2 * 6367381.0), abs=0.01)
    points = np.array([[12000.0, -8000.0, 9000.0], [-150000.0, 40000.0, 11000.0]])
    lat, lon, h = pymap3d.enu2geodetic(points[:, 0], points[:, 1], points[:, 2], *SITE)
    assert np.allclose(geodetic_to_enu(lat, lon, h, SITE), points, atol=1e-6)


# ---- the smoother --------------------------------------------------------------------------------
def _constant_turn(t, speed=150.0, rate_deg=3.0, climb=5.0):
    w = np.radians(rate_deg)
    r = speed / w
    position = np.stack([r * np.sin(w * t), r * (1 - np.cos(w * t)), 3000 + climb * t], axis=1)
    velocity = np.stack([speed * np.cos(w * t), speed * np.sin(w * t), climb + 0 * t], axis=1)
    acceleration = np.stack([-speed * w * np.sin(w * t), speed * w * np.cos(w * t), 0 * t], axis=1)
    return position, velocity, acceleration


def test_smoother_recovers_a_constant_turn_from_quantised_noisy_positions():
    rng = np.random.default_rng(7)
    sample_time = np.cumsum(rng.choice([1.0, 1.0, 2.0], 300))              # irregular, like stale-free ADS-B
    truth, _, _ = _constant_turn(sample_time)
    quantum = np.array([5.0, 5.0, 25 * FOOT])                              # CPR ~5 m, altitude 25 ft
    samples = np.round((truth + rng.normal(0, [3.0, 3.0, 0.0], truth.shape)) / quantum) * quantum
    scans = np.arange(20.0, sample_time[-1] - 20.0, 4.8)                   # scans between samples
    time = np.concatenate([sample_time, scans])
    order = np.argsort(time, kind="stable")
    position = np.concatenate([samples, np.full((scans.size, 3), np.nan)])[order]
    smoothed = smooth_constant_acceleration(time[order], position, np.array([5.0, 5.0, 3.0]), 0.5)
    at_scans = smoothed[np.argsort(order)[sample_time.size:]]
    p, v, a = _constant_turn(scans)
    errors = {name: np.sqrt(np.mean((at_scans[:, :, i] - want) ** 2, axis=0))
              for i, (name, want) in enumerate((("p", p), ("v", v), ("a", a)))}
    message = f"RMS error per axis at the scans: {errors}"
    assert np.all(errors["p"] < 3.0), message
    assert np.all(errors["v"] < 1.0), message
    assert np.all(errors["a"] < 0.4), message                              # of 7.85 m/s^2 in the turn


def test_flight_from_a_synthetic_turn_file_gives_the_turn_in_si_units(tmp_path):
    """End to end through the file: ft, ms, degrees in; ENU metres, the turn and its label out."""
    t = np.arange(0.0, 241.0)
    p = _constant_turn(t)[0]
    table = _frame(t, p[:, 0], p[:, 1], np.round(p[:, 2] / (25 * FOOT)) * 25 * FOOT,
                   groundspeed=np.full(t.size, 150.0 / (1852 / 3600)), vertical_rate=np.full(t.size, 5.0 / FOOT * 60))
    path = tmp_path / "turn.csv"
    table.write_csv(path)
    flight = build_flight(str(path), scan_period=2.0, start=20.0, duration=200.0, site_latitude=SITE[0],
                          site_longitude=SITE[1], site_height=SITE[2], horizontal_noise_std=5.0, jerk_psd=0.5)
    want = np.concatenate(_constant_turn(flight.time + 20.0), axis=1)
    error = np.abs(flight.state - want).max(axis=0)
    assert np.all(error[:3] < 1.5) and np.all(error[3:6] < 0.5) and np.all(error[6:] < 0.2), error   # 25 ft steps in up
    assert np.all(flight.maneuver == TURN | CLIMB_DESCENT), flight.maneuver_shares()   # 7.85 m/s^2, 5 m/s up
    assert flight.state_names == STATE_NAMES


def test_a_flight_is_built_once_per_file_and_arguments_and_again_when_the_file_changes(tmp_path):
    """A process keeps the flights it built (a sweep's jobs, every config a test checks): the same
    unchanged file with the same arguments gives the same Flight, read-only; other arguments or a
    rewritten file give a new one, from the file's new content."""
    import os

    path = tmp_path / "straight.csv"
    _straight(np.arange(0.0, 121.0)).write_csv(path)
    kwargs = dict(scan_period=2.0, duration=100.0, site_latitude=SITE[0], site_longitude=SITE[1])
    first = build_flight(str(path), **kwargs)
    assert build_flight(str(path), **kwargs) is first
    assert build_flight(str(path), **{**kwargs, "duration": 80.0}) is not first
    with pytest.raises(ValueError, match="read-only"):
        first.state[0, 0] = 1.0
    _straight(np.arange(0.0, 121.0), speed=150.0).write_csv(path)
    stamp = path.stat().st_mtime_ns + 1_000_000_000                       # a rewrite within the clock's tick
    os.utime(path, ns=(stamp, stamp))
    rebuilt = build_flight(str(path), **kwargs)
    assert rebuilt is not first
    np.testing.assert_allclose(rebuilt.state[:, 4], 150.0, atol=0.5)        # north velocity of the new file
    np.testing.assert_allclose(first.state[:, 4], 100.0, atol=0.5)


# ---- cleaning ------------------------------------------------------------------------------------
def test_cleaning_drops_and_counts_each_kind_of_bad_point():
    north = 100.0 * np.arange(12.0)                                       # 100 m/s due north
    time = np.arange(12.0)
    table = _frame(time, 0 * north, north, 3000 + 0 * north, onground=[False] * 12).to_dicts()
    table[2]["latitude"] = None                                           # missing position
    table[3]["onground"] = True                                           # on the ground
    table[5]["latitude"] += 1.0                                           # 111 km off: a spoofed jump
    stale = dict(table[6], timestamp=table[6]["timestamp"] + 500)         # same position half a second later
    duplicate = dict(table[7], latitude=table[7]["latitude"] + 1e-4)      # the same time stamp again
    backwards = dict(table[4], timestamp=table[4]["timestamp"] - 1500)    # earlier than the latest kept
    rows = table[:7] + [stale] + table[7:8] + [duplicate] + table[8:9] + [backwards] + table[9:]
    cleaned = clean_flight(pl.from_dicts(rows), "hand-built")
    assert cleaned.read == 15
    assert {k: cleaned.dropped[k] for k in DROP_REASONS} == {
        "missing_position": 1, "on_ground": 1, "duplicate_time": 1, "non_increasing_time": 1,
        "stale_position": 1, "jump": 1}, cleaned.describe()
    assert np.array_equal(cleaned.time - EPOCH, [0, 1, 4, 6, 7, 8, 9, 10, 11])
    assert np.all(np.diff(cleaned.time) > 0)
    assert cleaned.altitude[0] == pytest.approx(3000.0, abs=1e-6)       # ft -> m on the way in (at the site)


def test_a_held_altitude_is_stale_in_a_climb_but_not_in_a_cruise():
    t = np.arange(12.0)
    climb = np.where(t < 6, 3000.0, 3300.0)                               # held 6 s while climbing 50 m/s
    cruise = np.full(12, 3000.0)                                          # level, rate flickering by 64 ft/min
    for up, rate, stale in ((climb, np.full(12, 50.0), [1, 2, 3, 4, 5, 7, 8, 9, 10, 11]),
                            (cruise, np.where(t % 2 == 0, 0.0, 64 * FOOT / 60), [])):
        table = _frame(t, 0 * t, 100 * t, 0 * t, vertical_rate=rate / FOOT * 60).with_columns(
            altitude=pl.Series(up / FOOT))
        cleaned = clean_flight(table, "held-altitude")
        assert np.flatnonzero(~cleaned.fresh_altitude).tolist() == stale
        assert cleaned.dropped["stale_altitude"] == len(stale) and len(cleaned.time) == 12   # points kept


def test_a_bad_first_point_does_not_reject_the_flight():
    table = _straight(np.arange(30.0)).to_dicts()
    table[0]["longitude"] += 2.0                                          # the very first point is off
    cleaned = clean_flight(pl.from_dicts(table), "first-point")
    assert cleaned.dropped["jump"] == 1 and cleaned.time[0] == EPOCH + 1.0


def test_a_gap_splits_segments_and_a_window_over_it_is_refused(tmp_path):
    path = tmp_path / "gap.parquet"
    _straight(np.concatenate([np.arange(0.0, 31.0), np.arange(70.0, 101.0)])).write_parquet(path)
    cleaned = load_flight(str(path))
    assert cleaned.segment_times() == [(0.0, 30.0), (70.0, 100.0)]
    with pytest.raises(ValueError, match=r"duration: the window \[10, 80\] s spans the gap between 30 s and 70 s"):
        build_flight(str(path), start=10.0, duration=70.0)
    with pytest.raises(ValueError, match=r"start: 50 s is not inside a segment"):
        build_flight(str(path), start=50.0, duration=10.0)
    assert len(build_flight(str(path), start=70.0, duration=30.0).time) == 31     # the whole second segment
    with pytest.raises(ConfigError, match=r"^scenario: duration: .* spans the gap") as refused:
        build(OmegaConf.create({"_target_": SCENARIO, "flight": str(path), "duration": 70.0}), "scenario")
    assert "\n" not in str(refused.value)


def test_missing_column_and_non_table_give_one_paragraph_naming_file_and_column(tmp_path):
    no_latitude = tmp_path / "no_latitude.csv"
    _straight(np.arange(5.0)).drop("latitude").write_csv(no_latitude)
    with pytest.raises(ConfigError) as missing:
        read_opensky_table(no_latitude)
    text = str(missing.value)
    assert str(no_latitude) in text and "'latitude'" in text and "latitude (deg)" in text and "\n" not in text
    for name, content in (("picture.parquet", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4),
                          ("scalar.json", b'{"timestamp": 5}'), ("empty.json.gz", gzip.compress(b""))):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ConfigError) as refused:
            load_flight(str(path))
        text = str(refused.value)
        assert str(path) in text and "Expected a table of ADS-B positions" in text and "\n" not in text, text
    no_position = tmp_path / "no_position.csv"
    _straight(np.arange(5.0)).with_columns(pl.lit(None, pl.Float64).alias("latitude")).write_csv(no_position)
    with pytest.raises(ConfigError, match=r"none of its 5 points is an airborne position .*missing_position 5"):
        load_flight(str(no_position))
    with pytest.raises(ConfigError, match=r"^scenario: flight: 'no_such_flight' is not a file, not a sample"):
        build(OmegaConf.create({"_target_": SCENARIO, "flight": "no_such_flight"}), "scenario")


def test_json_records_columns_lines_and_gzip_read_alike(tmp_path):
    table = _straight(np.arange(10.0))
    records = table.to_dicts()
    columns = {c: {str(i): v for i, v in enumerate(table[c].to_list())} for c in table.columns}   # pandas' orient
    texts = {"records.json": json.dumps(records), "columns.json.gz": json.dumps(columns),
             "lines.jsonl": "\n".join(json.dumps(r) for r in records)}
    for name, text in texts.items():
        data = text.encode()
        (tmp_path / name).write_bytes(gzip.compress(data) if name.endswith(".gz") else data)
        read = read_opensky_table(tmp_path / name)
        assert read["latitude"].to_list() == table["latitude"].to_list(), name
        assert read["timestamp"].to_list() == table["timestamp"].to_list(), name
    # a CSV as traffic writes it: ISO date-times; and OpenSky's own tables: time in s
    iso = table.with_columns(pl.from_epoch("timestamp", time_unit="ms").dt.replace_time_zone("UTC").cast(pl.String))
    iso.write_csv(tmp_path / "iso.csv")
    table.with_columns(pl.col("timestamp") // 1000).write_parquet(tmp_path / "seconds.parquet")
    for name in ("iso.csv", "seconds.parquet"):
        assert np.array_equal(load_flight(str(tmp_path / name)).time, EPOCH + np.arange(10.0)), name


# ---- finding samples -----------------------------------------------------------------------------
def test_a_sample_not_shipped_is_found_in_an_installed_traffic(tmp_path, monkeypatch):
    samples = tmp_path / "site" / "traffic" / "data" / "samples" / "gliders"
    samples.mkdir(parents=True)
    (samples.parents[2] / "__init__.py").write_text("raise ImportError('never imported to find a file')\n")
    (samples / "luberon.json.gz").write_bytes(gzip.compress(json.dumps(_straight(np.arange(5.0)).to_dicts()).encode()))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    importlib.invalidate_caches()
    monkeypatch.delitem(sys.modules, "traffic", raising=False)
    assert find_flight_file("luberon") == samples / "luberon.json.gz"
    assert find_flight_file("gliders/luberon") == samples / "luberon.json.gz"
    assert find_flight_file("aircraft_carrier").suffix == ".parquet"     # shipped ones come first
    assert load_flight("luberon").read == 5


# ---- the shipped flights -------------------------------------------------------------------------
def test_the_issue_names_ship_within_two_megabytes():
    names = set(shipped_samples())
    assert {"aircraft_carrier", "zero_gravity", "munich", "rega_sg", "noisy_spoofing"} <= names
    folder = Path(find_flight_file("aircraft_carrier")).parent
    assert sum(p.stat().st_size for p in folder.glob("*.parquet")) < 2 * 1024 * 1024
    assert (folder / "PROVENANCE.md").is_file()


@pytest.mark.parametrize("name", shipped_samples())
def test_every_shipped_flight_gives_a_finite_truth(name):
    cleaned = load_flight(name)
    spans = cleaned.segment_times()
    longest = int(np.argmax([b - a for a, b in spans]))
    start, end = spans[longest]
    flight = build_flight(name, scan_period=1.0, start=start, duration=min(end - start, 1800.0))
    report = flight.describe()
    assert np.all(np.isfinite(flight.state)), report
    assert np.all(np.isfinite(flight.smoothing_residual)) and np.all(flight.smoothing_residual < 100.0), report
    assert cleaned.read == sum(v for k, v in cleaned.dropped.items() if k in DROP_REASONS) + len(cleaned.time)
    # units and axes: the truth's speed is the reported ground speed (kt -> m/s), within the
    # smoothing of corners (munich's 5 s samples) and the time-stamp jitter
    first, stop = cleaned.segments[longest]
    t = cleaned.time[first:stop] - cleaned.time[0] - start
    inside = t <= flight.time[-1]
    speed = np.interp(t[inside], flight.time, np.hypot(flight.state[:, 3], flight.state[:, 4]))
    difference = np.nanmedian(np.abs(speed - cleaned.groundspeed[first:stop][inside]))
    assert difference < 10.0, f"median |truth speed - ground speed| {difference:.1f} m/s; {report}"
    print(report)


def test_the_spoofed_flight_keeps_no_impossible_step():
    cleaned = load_flight("noisy_spoofing")
    assert cleaned.dropped["jump"] > 0 and cleaned.dropped["stale_position"] > 0, cleaned.describe()
    ecef = np.stack(pymap3d.geodetic2ecef(cleaned.latitude, cleaned.longitude, cleaned.altitude), axis=-1)
    speed = np.linalg.norm(np.diff(ecef, axis=0), axis=1) / np.diff(cleaned.time)
    assert speed.max() <= 600.0, cleaned.describe()


def test_the_calibration_turn_is_labelled_turn():
    # munich, 3600-3800 s: a straight leg, then a 180 deg standard-rate turn (3 deg/s at 83 m/s,
    # ~4.3 m/s^2) from ~3650 to ~3715 s, seen in the raw positions' course
    flight = build_flight("munich", scan_period=5.0, start=3600.0, duration=200.0)
    t = flight.time + 3600.0
    turning = (flight.maneuver & TURN) > 0
    assert turning[(t >= 3660) & (t <= 3705)].all(), dict(zip(t.tolist(), flight.maneuver.tolist()))
    assert not turning[t <= 3640].any(), dict(zip(t.tolist(), flight.maneuver.tolist()))
    assert set(flight.maneuver_shares()) == set(MANEUVER_NAMES)


# ---- the scenario --------------------------------------------------------------------------------
def test_generate_gives_the_same_flight_for_every_run():
    scenario = RecordedFlight("rega_sg", scan_period=4.8, start=200.0, duration=480.0)
    truth = scenario.generate(3, seed=11)
    K = len(scenario.flight.time)
    assert K == 101 and truth.state.shape == (3, K, 1, 9) and truth.state_names == STATE_NAMES
    assert truth.labels["acceleration"].shape == (3, K, 1, 3) and truth.labels["maneuver"].shape == (3, K, 1)
    assert np.issubdtype(truth.labels["maneuver"].dtype, np.integer)
    for r in (1, 2):
        assert np.array_equal(truth.state[r], truth.state[0])
        assert np.array_equal(truth.labels["maneuver"][r], truth.labels["maneuver"][0])
    assert np.array_equal(truth.labels["acceleration"][0, :, 0], scenario.flight.state[:, 6:9])
    assert np.allclose(np.diff(truth.time), 4.8)


def test_state_layout_is_study_000s():
    from pipeline.studies.mie_los.scenario import STATE_NAMES as STUDY_000

    assert STATE_NAMES == STUDY_000


@pytest.mark.parametrize("key, value, says", [
    ("scan_period", 0.0, "scan_period: 0.0 must be > 0 s"),
    ("start", -5.0, "start: -5.0 must be >= 0 s"),
    ("site_latitude", 91.0, "site_latitude: 91.0 must be within [-90, 90] deg"),
    ("jerk_psd", -1.0, "jerk_psd: -1.0 must be > 0 m^2/s^5"),
])
def test_out_of_range_values_are_refused_naming_the_key(key, value, says):
    with pytest.raises(ConfigError) as refused:
        build(OmegaConf.create({"_target_": SCENARIO, "flight": "rega_sg", key: value}), "scenario")
    assert f"scenario: {says}" in str(refused.value)
