"""Issue 38, the ADS-B points: a user's own flight given the documented way
(``experiment=adsb_jet scenario.flight=<file>``) meets a radar near it or is refused naming the site;
the default window and its refusals; the cleaning thresholds as keys; what cleaning and smoothing
did, and the truth's own uncertainty, as summary rows and in the report."""

from __future__ import annotations

import json
import shutil

import numpy as np
import polars as pl
import pymap3d
import pytest
from pymap3d.vincenty import vdist

from filters.smoothing import constant_acceleration_transition, smooth_with_covariance, white_jerk_process_noise
from pipeline.errors import ConfigError
from pipeline.studies.adsb.flight import build_flight
from pipeline.studies.adsb.reading import FOOT, find_flight_file, load_flight
from pipeline.studies.adsb.scenario import RecordedFlight
from tests.helpers.config import composed_config
from tests.helpers.processes import run_pipeline
from tests.helpers.runs import run_in_process

EPOCH = 1_600_000_000.0
SITE = (45.0, 7.0, 0.0)
ADSB_JET_SITE = ("scenario.site_latitude=32.3568", "scenario.site_longitude=-117.5671")   # adsb_jet's old pin


def _frame(time_s, east, north, up=None) -> pl.DataFrame:
    """An OpenSky-schema table of ENU points at SITE (time in s, positions in m)."""
    time_s = np.asarray(time_s, float)
    up = np.full(time_s.size, 3000.0) if up is None else np.asarray(up, float)
    lat, lon, height = pymap3d.enu2geodetic(np.asarray(east, float), np.asarray(north, float), up, *SITE)
    return pl.DataFrame({"timestamp": np.round((EPOCH + time_s) * 1000).astype(np.int64), "latitude": lat,
                         "longitude": lon, "altitude": np.asarray(height) / FOOT})


def _copy_of(tmp_path, sample="rega_sg"):
    path = tmp_path / "my_flight.parquet"
    shutil.copy(find_flight_file(sample), path)
    return path


# ---- 1. the site, placed relative to the flight ---------------------------------------------------
def test_a_flight_given_by_its_file_gets_a_radar_near_it(tmp_path):
    """adsb_jet pinned its radar off San Diego: a flight near St. Gallen was tracked from 9 200 km away
    (raw radar error ~65 km, printed as a result). Now the site is 30 km south of the window's median."""
    flight = _copy_of(tmp_path)
    out, ctx = run_in_process(tmp_path, "own", "experiment=adsb_jet", f"scenario.flight={flight}",
                              "scenario.start=285", "scenario.duration=60", "mc.runs=2", "variants=[kf_cv]")
    truth = pl.read_parquet(ctx.run_dir / "truth.parquet")
    xyz = np.stack(truth["x"].to_numpy())[:, :3]
    distance = np.linalg.norm(xyz, axis=1)                                  # the radar is at the ENU origin
    assert 25e3 < distance.min() and distance.max() < 40e3, (distance.min(), distance.max())
    radar = out.summary.filter(pl.col("series") == "radar_position_rmse")["value"][0]
    assert radar < 400.0, radar                                             # it was ~65 000 m
    # the header describes the flight that ran, not adsb_jet's default (a jet off San Diego)
    status = json.loads((ctx.run_dir / "status.json").read_text())
    assert str(flight) in status["scenario"] and "30 km at bearing 180 deg" in status["scenario"]
    assert "San Diego" not in status["scenario"] and "shipped sample" not in status["scenario"]
    report_txt = (ctx.run_dir / "report.txt").read_text()
    assert f"scenario: flight {flight}" in report_txt.splitlines()[1]
    from pipeline.results.report import write_run_report
    header = write_run_report(ctx.run_dir).path.read_text().split("## Reproduction targets")[0]
    assert f"Scenario: flight {flight}" in header and "San Diego" not in header and "aircraft carrier" not in header


def test_the_site_is_the_bearing_and_distance_from_the_window_median():
    scenario = RecordedFlight("rega_sg", start=285.0, duration=60.0, site_bearing_deg=90.0, site_distance=40_000.0)
    cleaned = load_flight("rega_sg")
    first, stop = cleaned.segments[1]
    t = cleaned.time[first:stop] - cleaned.time[0]
    inside = (t >= 285.0) & (t <= 345.0)
    median = (np.median(cleaned.latitude[first:stop][inside]), np.median(cleaned.longitude[first:stop][inside]))
    distance, bearing = vdist(*median, *scenario.flight.site[:2])
    assert float(distance) == pytest.approx(40_000.0, abs=0.01) and float(bearing) == pytest.approx(90.0, abs=1e-6)
    # a pinned site wins over bearing and distance, and says so
    pinned = RecordedFlight("rega_sg", start=285.0, duration=60.0, site_latitude=47.2, site_longitude=9.1)
    assert pinned.flight.site[:2] == (47.2, 9.1)
    assert "pinned by site_latitude and site_longitude" in pinned.describe()
    with pytest.raises(ValueError, match="site_longitude: null while site_latitude is given"):
        RecordedFlight("rega_sg", start=285.0, duration=60.0, site_latitude=47.2)


def test_a_radar_beyond_its_range_is_refused_before_any_stage(tmp_path):
    flight = _copy_of(tmp_path)
    overrides = ("experiment=adsb_jet", f"scenario.flight={flight}", "scenario.start=285", "scenario.duration=60",
                 "mc.runs=2", "variants=[kf_cv]", *ADSB_JET_SITE)
    with pytest.raises(ConfigError) as refused:
        run_in_process(tmp_path, "far", *overrides)
    text = str(refused.value)
    assert text.startswith("sensors.max_range: the radar site at latitude 32.356800 deg, longitude -117.567100 deg")
    assert "pinned by site_latitude and site_longitude" in text and "beyond its range of 463 km" in text
    distance = float(text.split("the target is ")[1].split(" km")[0])
    assert 8500 < distance < 9500, text                                    # San Diego to St. Gallen
    assert "\n" not in text and not (tmp_path / "cache").exists() and not (tmp_path / "runs" / "far").exists()
    # a site placed relative to the flight but still out of range: the advice is the window or the range
    from pipeline.sensors import Radar3D
    from pipeline.studies.adsb.adapter import FlightStudy
    far = RecordedFlight("rega_sg", start=285.0, duration=60.0, site_distance=500_000.0)
    with pytest.raises(ConfigError, match=r"500 km at bearing 180 deg .* beyond its range of 463 km .* shorter window"):
        FlightStudy().check(far, Radar3D(max_range=463_000.0), {})
    FlightStudy().check(far, Radar3D(), {})                                 # no max_range: no limit
    proc = run_pipeline(*overrides, artifacts=tmp_path)                                        # the command line: exit 2, no traceback
    assert proc.returncode == 2 and "sensors.max_range: the radar site" in proc.stderr
    assert "Traceback" not in proc.stderr


# ---- 2. the default window -------------------------------------------------------------------------
def _many_segments(tmp_path):
    """15 segments (gaps of 60 s), each longer than the one before: the longest is the last."""
    times, t0 = [], 0.0
    for i in range(15):
        length = 20.0 + 10.0 * i
        times.append(t0 + np.arange(0.0, length + 1))
        t0 += length + 60.0
    t = np.concatenate(times)
    path = tmp_path / "segments.csv"
    _frame(t, 0 * t, 100.0 * t).write_csv(path)
    return path, (t0 - 60.0 - 160.0, t0 - 60.0)


def test_a_window_longer_than_the_flight_lists_its_longest_segments_and_null_takes_the_longest(tmp_path):
    path, longest = _many_segments(tmp_path)
    with pytest.raises(ConfigError) as refused:                             # the default 900 s window
        run_in_process(tmp_path, "short", "experiment=adsb_jet", f"scenario.flight={path}", "mc.runs=2")
    text = str(refused.value)
    assert "has 15 segment(s)" in text and "and 3 shorter" in text and "duration=null" in text
    listed = text.split("the longest, at [start, end] s from its first kept point: ")[1]
    assert listed.startswith(f"[{longest[0]:g}, {longest[1]:g}] (160 s)"), listed   # the 15th, not the first 12
    flight = build_flight(str(path), duration=None, site_latitude=SITE[0], site_longitude=SITE[1])
    assert (flight.time[0], flight.time[-1]) == (0.0, 160.0)
    assert flight.provenance["window"].startswith(f"[{longest[0]:g}, {longest[1]:g}] s of segment 14")


# ---- 3. the cleaning thresholds are keys ------------------------------------------------------------
def test_the_cleaning_thresholds_are_keys_of_the_scenario(tmp_path):
    path, _ = _many_segments(tmp_path)
    cfg = composed_config("experiment=adsb_jet", f"scenario.flight={path}", "scenario.max_gap=60",
                      "scenario.max_speed=400", "scenario.max_vertical_speed=100", "scenario.turn_threshold=2",
                      "scenario.climb_threshold=3", "scenario.duration=null")
    from pipeline.run.config import build
    scenario = build(cfg.scenario, "scenario")
    assert scenario.flight.cleaning.max_gap == 60.0 and len(scenario.flight.cleaning.segments) == 1
    assert len(scenario.flight.time) == int(scenario.flight.cleaning.time[-1] - scenario.flight.cleaning.time[0]) + 1


# ---- 4. what cleaning removed ---------------------------------------------------------------------
def test_a_window_over_a_gap_says_what_cleaning_removed_there(tmp_path):
    t = np.arange(0.0, 101.0)
    table = _frame(t, 0 * t, 100.0 * t)
    nan_block = table.with_columns(pl.when((pl.col("timestamp") > (EPOCH + 30.5) * 1000)
                                           & (pl.col("timestamp") < (EPOCH + 69.5) * 1000))
                                   .then(None).otherwise(pl.col("latitude")).alias("latitude"))
    path = tmp_path / "nan_block.csv"
    nan_block.write_csv(path)
    with pytest.raises(ValueError, match=r"spans the gap between 30 s and 70 s \(between 30 s and 70 s cleaning "
                                         r"removed 39 of 39 points without a position"):
        build_flight(str(path), start=10.0, duration=70.0)
    # a block written out of time order: its points come after the later ones in the file
    late = table.filter((pl.col("timestamp") > (EPOCH + 30.5) * 1000) & (pl.col("timestamp") < (EPOCH + 69.5) * 1000))
    shuffled = pl.concat([table.join(late, on="timestamp", how="anti"), late])
    path = tmp_path / "out_of_order.csv"
    shuffled.write_csv(path)
    with pytest.raises(ValueError, match=r"cleaning removed 39 of 39 points out of time order"):
        build_flight(str(path), start=10.0, duration=70.0)


def test_the_cleaning_the_residual_and_the_truths_uncertainty_are_summary_rows_and_in_the_report(tmp_path):
    out, ctx = run_in_process(tmp_path, "rows", "experiment=adsb_helicopter", "scenario.duration=60", "mc.runs=2",
                              "variants=[kf_cv,imm_cv_ct]")
    summary = out.summary.filter(pl.col("variant_key") == "kf_cv")
    value = dict(zip(summary["series"].to_list(), summary["value"].to_list()))
    cleaned = load_flight("rega_sg")
    assert value["points_read"] == cleaned.read and value["points_kept"] == len(cleaned.time)
    assert value["segments"] == len(cleaned.segments)
    for reason in ("missing_position", "duplicate_time", "non_increasing_time", "stale_position", "jump",
                   "stale_altitude", "altitude_jump"):
        assert value[f"dropped_{reason}"] == cleaned.dropped[reason], reason
    assert value["dropped_stale_position"] == 126
    scenario = RecordedFlight("rega_sg", start=285.0, duration=60.0)
    for axis, residual in zip(("east", "north", "up"), scenario.flight.smoothing_residual):
        assert value[f"smoothing_residual_{axis}"] == pytest.approx(residual)
    rows = out.summary.filter(pl.col("window") == "all")
    by = {(k, s): v for k, s, v in rows.select("variant_key", "series", "value").iter_rows()}
    std = np.sqrt(np.sum(scenario.flight.position_std[2:] ** 2, axis=1)).mean()   # the 'all' window: scans 2..
    assert by[("kf_cv", "truth_position_std")] == pytest.approx(std) and 0 < std < 50
    best = min(by[("kf_cv", "position_rmse")], by[("imm_cv_ct", "position_rmse")])
    assert by[("imm_cv_ct", "truth_std_to_best_rmse")] == pytest.approx(std / best)
    assert by[("kf_cv", "truth_uncertain")] == float(std / best > 1 / 3)
    assert "truth std" in (ctx.run_dir / "report.txt").read_text()
    from pipeline.results.report import write_run_report
    text = write_run_report(ctx.run_dir).path.read_text()
    assert f"all: truth std {std:.1f} m vs the best RMSE {best:.1f} m" in text
    assert f"read {cleaned.read}, kept {len(cleaned.time)} in 2 segment(s); dropped " in text
    assert "stale_position 126" in text


# ---- 5. the truth's uncertainty ---------------------------------------------------------------------
def test_the_smoothers_covariance_is_the_spread_of_its_errors():
    """White-jerk trajectories drawn from the smoother's own model, sampled every 5 s with noise: the RMS
    of smoothed minus true position at 1 s steps (between samples too) is the std the covariance gives."""
    rng = np.random.default_rng(7)
    axes, steps, jerk, noise = 400, 301, 0.5, 20.0
    dt = np.ones(steps - 1)
    F, Q = constant_acceleration_transition(dt), white_jerk_process_noise(dt, jerk)
    state = np.zeros((steps, axes, 3))
    state[0] = rng.standard_normal((axes, 3)) * [1e3, 300.0, 50.0]
    for k in range(1, steps):
        w = rng.standard_normal((axes, 3)) @ np.linalg.cholesky(Q[k - 1]).T
        state[k] = state[k - 1] @ F[k - 1].T + w
    samples = state[:, :, 0] + noise * rng.standard_normal((steps, axes))
    samples[np.arange(steps) % 5 != 0] = np.nan                             # a sample every 5 s
    smoothed, covariance = smooth_with_covariance(np.arange(steps, dtype=float), samples,
                                                  np.full(axes, noise), jerk)
    error = smoothed[10:-10, :, 0] - state[10:-10, :, 0]
    predicted = np.sqrt(covariance[10:-10, :, 0, 0]).mean(axis=1)
    measured = np.sqrt(np.mean(error ** 2, axis=1))
    ratio = measured / predicted
    assert 0.9 < np.median(ratio) < 1.1 and np.all((ratio > 0.7) & (ratio < 1.3)), (np.median(ratio), ratio.min(),
                                                                                    ratio.max())
    dense = np.where(np.isnan(samples), state[:, :, 0] + noise * rng.standard_normal((steps, axes)), samples)
    _, every_second = smooth_with_covariance(np.arange(steps, dtype=float), dense, np.full(axes, noise), jerk)
    assert np.sqrt(every_second[10:-10, :, 0, 0]).mean() < 0.8 * predicted.mean()   # sparser samples: less sure
