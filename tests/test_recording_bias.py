"""pipeline.studies.async_bias.recording: study 002's .rrd has the entity tree, values and blueprint the viewer
layout relies on. A tiny synthetic case (2 radars, 3 targets, 20 reports) run through the real
bias-registration filters, read back with rerun.chunk.RrdReader (no viewer)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import polars as pl
import pytest

from filters.bias import EXXRegistration, LocalTracking, PseudoBiasRegistration, RadarReports, TrackStart
from pipeline.data import Detections, Truth
from pipeline.studies.async_bias.recording import BIAS_DISPLAY, write_bias_recording
from pipeline.studies.async_bias.adapter import bias_study_metrics
from pipeline.evaluation.evaluate import metrics_frame
from tests.helpers.rrd_reading import assert_complete_recording, entity_index, read_chunks, rows, temporal

RUNS, TARGETS = 2, 3
RECORD = [0]
VARIANTS = {"local": "local", "proposed": "proposed", "exx": "EXX"}
KEPT = (1, 3)                                   # target numbers kept by the filters (1-based)
BIASES = np.array([[20.0, 0.002, 3e-5, 2e-4], [-15.0, -0.001, 1e-5, 1e-4]])
POSITIONS = np.array([[0.0, 0.0], [10000.0, 0.0]])
NOISE = np.array([[10.0, 0.001], [10.0, 0.001]])


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(3)
    grid = np.arange(21) * 0.5                                            # truth: 0, 0.5, ..., 10 s
    start = np.array([[5000.0, 5000.0, 20.0, 20.0], [15000.0, 5000.0, 20.0, 20.0], [40000.0, 20000.0, 20.0, 20.0]])
    state = start[None, None] + grid[None, :, None, None] * np.array([0, 0, 0, 0])
    state = np.broadcast_to(state, (RUNS, grid.size, TARGETS, 4)).copy()
    state[..., :2] += grid[None, :, None, None] * start[None, None, :, 2:]
    truth = Truth(grid, state, ("x", "y", "vx", "vy"))
    steps = np.arange(1, 21)                                              # reports at 0.5..10 s
    time, sensor = grid[steps], np.where(steps % 2 == 0, 0, 1)            # radar 2 at 0.5 s, radar 1 at 1 s
    rel = state[:, steps, :, :2] - POSITIONS[sensor][None, :, None]
    r, theta = np.hypot(rel[..., 0], rel[..., 1]), np.arctan2(rel[..., 1], rel[..., 0])
    b = BIASES[sensor]
    z = np.stack([(1 + b[:, 2, None]) * r + b[:, 0, None], (1 + b[:, 3, None]) * theta + b[:, 1, None]], -1)
    z += rng.standard_normal(z.shape) * NOISE[sensor][None, :, None]
    K = steps.size
    cov = np.zeros((RUNS, K, TARGETS, 2, 2))
    cov[..., 0, 0], cov[..., 1, 1] = 100.0, 1e-6
    det = Detections(time, sensor, z, cov, np.broadcast_to(np.arange(TARGETS), (RUNS, K, TARGETS)).copy(),
                     np.ones((RUNS, K, TARGETS), dtype=bool), ("range", "azimuth"), ("m", "rad"))
    P0 = np.diag([100.0, 100.0, 25.0, 25.0])
    start_state = state[:, 0][:, None] + rng.standard_normal((RUNS, 2, TARGETS, 4)) * np.sqrt(np.diag(P0))
    reports = RadarReports(time, sensor, z, POSITIONS, NOISE, TrackStart(0.0, start_state, P0))
    estimates = {"local": LocalTracking(output_targets=KEPT).run(reports),
                 "proposed": PseudoBiasRegistration(output_targets=KEPT).run(reports),
                 "exx": EXXRegistration(output_targets=KEPT).run(reports)}
    network = SimpleNamespace(names=("radar1", "radar2"), positions=POSITIONS, noise_std=NOISE, biases=BIASES,
                              true_bias_vector=lambda: BIASES.reshape(-1).copy())
    per_variant = {k: (VARIANTS[k], bias_study_metrics(truth, est, network.true_bias_vector()))
                   for k, est in estimates.items()}
    metrics = metrics_frame(grid, per_variant, RUNS).with_columns(pl.lit("bias tiny").alias("experiment"))
    return dict(truth=truth, det=det, estimates=estimates, network=network, metrics=metrics, steps=steps)


def _write(case, path: Path, record_runs=RECORD) -> None:
    write_bias_recording(path, experiment="bias tiny", truth=case["truth"], detections=case["det"],
                         estimates=case["estimates"], display_names=VARIANTS, metrics=case["metrics"],
                         record_runs=record_runs, sensor=case["network"], config_text="study: 002\n",
                         description="A tiny study 002 for the test.")


@pytest.fixture(scope="module")
def rrd(case, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "bias.rrd"
    _write(case, path)
    return path


@pytest.fixture(scope="module")
def chunks(rrd):
    return read_chunks(rrd)


@pytest.fixture(scope="module")
def entities(chunks):
    return entity_index(chunks)


def test_file_is_complete_and_atomic(rrd):
    assert_complete_recording(rrd, "bias_tiny")


def test_world_entities(entities, case):
    assert "Points2D:positions" in entities["/world/radars"]["static"]
    truth = temporal(entities, "/world/run0/truth", "Points2D:positions")
    assert "LineStrips2D:strips" in truth["static"] and truth["rows"] == case["truth"].time.size
    for n in (1, 2):
        meas = temporal(entities, f"/world/run0/measurements/radar{n}", "Points2D:positions")
        assert meas["rows"] == 10                                          # each radar reports 10 times
    assert "Points2D:positions" in entities["/world/run0/measurements/all"]["static"]
    temporal(entities, "/world/run0/truth/path", "LineStrips2D:strips")
    for key in VARIANTS:
        kinds = ("biased",) if key == "local" else ("biased", "compensated")
        for n in (1, 2):
            for kind in kinds:
                base = f"/world/run0/{key}/radar{n}/{kind}"
                assert temporal(entities, f"{base}/track", "LineStrips2D:strips")["rows"] == 9   # 10 reports
                assert temporal(entities, f"{base}/estimate", "Points2D:positions")["rows"] == 10
                temporal(entities, f"{base}/covariance", "LineStrips2D:strips")
        assert f"/world/run0/{key}/radar1/compensated/track" in entities or key == "local"
    assert "/world/run0/local/radar1/compensated/track" not in entities
    for t in KEPT:
        temporal(entities, f"/world/frames/target{t}_run0", "Transform3D:translation")
    assert not any(p.startswith("/world/run1") for p in entities), "run 1 was not asked for"


def test_measurements_are_converted_to_xy(chunks, case):
    det = case["det"]
    k = 3                                                                  # report at 2 s, radar 1
    n = int(det.sensor[k])
    got = np.asarray(rows(chunks, f"/world/run0/measurements/radar{n + 1}", "Points2D:positions")[case["steps"][k]])
    z = det.z[0, k]
    expected = POSITIONS[n] + z[:, :1] * np.stack([np.cos(z[:, 1]), np.sin(z[:, 1])], -1)
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # biased: near the truth, not on it
    truth = case["truth"].state[0, case["steps"][k], :, :2]
    assert np.all(np.linalg.norm(got - truth, axis=-1) < 500.0)


def test_bias_series_equal_the_estimates(chunks, entities, case):
    est = case["estimates"]
    for key in ("proposed", "exx"):
        for n in (1, 2):
            for c, component in enumerate(BIAS_DISPLAY):
                entity = f"/bias/{key}/run0/radar{n}/{component}"
                for part in ("", "/plus_2sigma", "/minus_2sigma", "/true"):
                    e = temporal(entities, entity + part, "Scalars:scalars")
                    assert "SeriesLines:names" in e["static"]
                factor = BIAS_DISPLAY[component][1]
                j = 4 * (n - 1) + c
                mean = rows(chunks, entity, "Scalars:scalars")
                upper = rows(chunks, entity + "/plus_2sigma", "Scalars:scalars")
                true = rows(chunks, entity + "/true", "Scalars:scalars")
                for k in (0, 7, 19):
                    step = int(case["steps"][k])
                    sigma = np.sqrt(est[key].bias_covariance[0, k, j, j])
                    assert mean[step][0] == pytest.approx(est[key].bias[0, k, j] * factor, rel=1e-9, abs=1e-12)
                    assert upper[step][0] == pytest.approx((est[key].bias[0, k, j] + 2 * sigma) * factor, rel=1e-9)
                    assert true[step][0] == pytest.approx(BIASES[n - 1, c] * factor)
    assert not any(p.startswith("/bias/local") for p in entities), "the local variant estimates no bias"


def test_covariance_ellipse_is_2_sigma(chunks, case):
    est = case["estimates"]["proposed"]
    k = 11                                                                 # radar 1's report at 6 s
    assert est.sensor[k] == 0
    strips = rows(chunks, "/world/run0/proposed/radar1/compensated/covariance", "LineStrips2D:strips")
    ellipse = np.asarray(strips[int(case["steps"][k])][1])                # second kept target
    m, P = est.compensated_state[0, k, 1, :2], est.compensated_covariance[0, k, 1, :2, :2]
    d = ellipse - m
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, np.linalg.inv(P), d), 4.0, rtol=2e-3)   # float32 at 40 km


def test_metrics_and_config(entities):
    for key in ("proposed", "exx"):
        for metric in ("bias_rmse_range_offset_s1", "bias_rmse_azimuth_scale_s2", "bias_nees", "bias_nees_s1",
                       "position_rmse_s1_t3_compensated", "track_nees_s2_t1_compensated"):
            e = temporal(entities, f"/metrics/{metric}/{key}", "Scalars:scalars")
            assert {"SeriesLines:names", "SeriesLines:colors"} <= e["static"]
    temporal(entities, "/metrics/position_rmse_s1_t1/local", "Scalars:scalars")
    assert "/metrics/bias_rmse_range_offset_s1/local" not in entities
    for part in ("mean", "lower", "upper"):
        temporal(entities, f"/metrics/bias_nees/chi2/{part}", "Scalars:scalars")
    assert "TextDocument:text" in entities["/config"]["static"]


def test_bias_rmse_metric_in_display_units(chunks, case):
    expected = case["metrics"].filter((pl.col("series") == "bias_rmse_azimuth_offset_s1")
                                      & (pl.col("variant_key") == "proposed") & (pl.col("step") == 20))
    got = rows(chunks, "/metrics/bias_rmse_azimuth_offset_s1/proposed", "Scalars:scalars")[20]
    assert got[0] == pytest.approx(expected["value"][0] * 1e3)


@pytest.mark.parametrize("bad", [[2], [-1]])
def test_out_of_range_record_run_raises(case, tmp_path, bad):
    with pytest.raises(ValueError, match=r"record\.runs"):
        _write(case, tmp_path / "bad.rrd", record_runs=bad)
    assert not any(tmp_path.iterdir()), "nothing may be written for a bad request"


# ---- issue 19: what the viewer shows (the blueprint and the data, without pixels) ---------------
from tests.helpers.recording_checks import (blueprint, recording_variants, write_recording,  # noqa: E402,F401
                                            test_every_title_fits_its_view, test_no_viewer_warning_while_writing_quiet,
                                            test_plots_have_no_legend_and_the_key_names_the_variants,
                                            test_tracks_are_drawn_up_to_now)
