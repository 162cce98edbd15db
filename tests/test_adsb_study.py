"""The ADS-B study (issue 17) at reduced size on the shipped real flights: every flight's experiment
runs through the framework contract, the filters beat the raw radar, the maneuver-class metrics add
up, and a flight file's bytes are part of the cache key."""

from __future__ import annotations

import shutil

import numpy as np
import polars as pl
import pytest

from pipeline.errors import ConfigError
from pipeline.studies.adsb.flight import MANEUVER_NAMES
from tests.helpers.runs import run_in_process

FLIGHTS = ("adsb_jet", "adsb_zero_gravity", "adsb_calibration", "adsb_helicopter")


def rows(summary: pl.DataFrame, series: str) -> dict[str, float]:
    chosen = summary.filter(pl.col("series") == series)
    return dict(zip(chosen["variant_key"].to_list(), chosen["value"].to_list()))


@pytest.mark.full
@pytest.mark.parametrize("experiment", FLIGHTS)
def test_every_flight_runs_and_the_filters_beat_the_raw_radar(tmp_path, experiment):
    out, ctx = run_in_process(tmp_path, experiment, f"experiment={experiment}", "mc.runs=3", "scenario.duration=120")
    summary = out.summary
    truth = pl.read_parquet(ctx.run_dir / "truth.parquet")
    detections = pl.read_parquet(ctx.run_dir / "detections.parquet")
    # the raw radar's position error, converted to Cartesian (study 000's sensor at the ENU origin)
    from pipeline.sensors import cartesian
    z = np.stack(detections.sort("run", "step")["z"].to_numpy())
    x = np.stack(truth.sort("run", "step")["x"].to_numpy())[:, :3]
    raw = float(np.sqrt(np.mean(np.sum((cartesian(z) - x) ** 2, axis=-1))))       # one detection per scan
    overall = dict(zip(*summary.filter((pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
                       .select("variant_key", "value").to_dict(as_series=False).values()))
    for key in ("kf_cv", "imm_cv_ct"):             # the report's target: the filters beat the raw radar
        assert overall[key] < 0.8 * raw, f"{experiment}: {key} {overall[key]:.1f} m vs the raw radar {raw:.1f} m"
    # each maneuver class's scans add up to the counted scans (2..K-1), and each class that occurs has an RMSE
    scans = {name: rows(summary, f"scans_{name}")["kf_cv"] for name in MANEUVER_NAMES}
    assert sum(scans.values()) == truth.filter(pl.col("run") == 0).height - 2
    for name, count in scans.items():
        value = rows(summary, f"position_rmse_{name}")["kf_cv"]
        assert (value is not None and np.isfinite(value)) == (count > 0), (name, count, value)
    band = rows(summary, "nees_position_velocity_in_band")
    assert set(band) == {"kf_cv", "kf_ca", "kf_singer", "imm_cv_ct", "mie_a", "mie_b", "mie_c"} and all(0 <= v <= 1 for v in band.values())


def test_the_flight_file_bytes_are_in_the_cache_key(tmp_path, caplog):
    """An edited flight file under the same name must be read again, never served from the cache."""
    caplog.set_level("INFO", logger="pipeline")
    from pipeline.studies.adsb.reading import find_flight_file
    flight = tmp_path / "flight.parquet"
    shutil.copy(find_flight_file("rega_sg"), flight)
    overrides = ("experiment=adsb_helicopter", f"scenario.flight={flight}", "scenario.duration=60", "mc.runs=2",
                 "variants=[kf_cv]")
    run_in_process(tmp_path, "a", *overrides)
    caplog.clear()
    run_in_process(tmp_path, "b", *overrides)
    assert "[scenario] reused cached" in caplog.text
    table = pl.read_parquet(flight)
    table.with_columns(pl.col("latitude") + 1e-4).write_parquet(flight)     # the same name, other positions
    caplog.clear()
    run_in_process(tmp_path, "c", *overrides)
    assert "[scenario] computed" in caplog.text and "[scenario] reused" not in caplog.text


def test_a_window_over_a_gap_is_refused_naming_the_segments(tmp_path):
    with pytest.raises(ConfigError, match=r"scenario.*spans the gap"):
        run_in_process(tmp_path, "gap", "experiment=adsb_helicopter", "scenario.start=0", "scenario.duration=600",
                       "mc.runs=2")
    assert not (tmp_path / "cache").exists()


def test_a_noisy_recording_is_cleaned_and_counted():
    """traffic's noisy/ samples: spoofed positions and time-stamp errors are dropped and counted."""
    from pipeline.studies.adsb.reading import load_flight
    spoofed = load_flight("noisy_spoofing")
    assert spoofed.dropped["jump"] > 100 and np.all(np.diff(spoofed.time) > 0)
    shifted = load_flight("noisy_time_issue")
    assert shifted.dropped["stale_position"] > 0 and np.all(np.diff(shifted.time) > 0)


def test_study_001s_imms_track_a_real_flight_on_the_horizontal_plane(tmp_path):
    """FSIMM and AO-VSIMM take 2-D positions: the radar's plots cut to the horizontal plane
    (HorizontalRadar) with a horizontal truth in study 001's layout."""
    out, ctx = run_in_process(tmp_path, "plane", "experiment=adsb_jet_horizontal", "mc.runs=3", "scenario.duration=120")
    summary = out.summary
    overall = rows(summary.filter(pl.col("window") == "all"), "position_rmse")
    radar = rows(summary, "radar_position_rmse")["fsimm"]
    assert set(overall) == {"kf_cv", "imm_cv_ct", "fsimm", "ao_vsimm"}
    assert all(value < 0.8 * radar for value in overall.values()), (overall, radar)
    models = rows(summary.filter(pl.col("window") == "all"), "models_evaluated")
    assert models["ao_vsimm"] < models["fsimm"] == 13.0

    # the report: its target passes, and every finding says something (a class with no scans says so)
    from pipeline.results.report import write_run_report
    report = write_run_report(ctx.run_dir)
    assert [t.verdict for t in report.targets] == ["PASS"]
    text = report.path.read_text()
    assert "no value" not in text and "no turning scans in this window" in text
