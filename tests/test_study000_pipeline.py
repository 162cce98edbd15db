"""Study 000 plumbing (spec 000, MIE in LOS coordinates): the 3-D scenario, the 3-D radar, the new
metrics and summary windows, and the Table 1 report, driven through the runner with a stand-in
estimator (the MIE filters are written elsewhere; the stub honours their output contract).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict

from filters.base import MeasurementSeries, TrackEstimate
from pipeline.storage import schemas
from pipeline.errors import ConfigError
from pipeline.run.runner import RunContext, run_experiment
from pipeline.studies.mie_los.scenario import PiecewiseAcceleration3D
from pipeline.sensors import Radar3D, cartesian, conversion_jacobian, wrap_angle
from pipeline.evaluation.metrics import is_count
from pipeline.views.tables import BinnedTable, ReportContext, format_summary
from tests.helpers.config import CONF

A = np.array([15.0, -10.0, -5.0])
P0 = np.array([8000.0, 4000.0, 2000.0])
V0 = np.array([-150.0, 50.0, 50.0])
STATE_NAMES = ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")


def study_scenario(**overrides) -> PiecewiseAcceleration3D:
    node = OmegaConf.load(CONF / "scenario" / "mie_los.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


def study_radar(**overrides) -> Radar3D:
    node = OmegaConf.load(CONF / "sensors" / "mie_los.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


# ---- the stand-in estimator --------------------------------------------------------------------
class StubEstimator:
    """A 9-state constant-acceleration KF on converted measurements (white-noise jerk of PSD ``q``),
    in the truth's order x, y, z, vx, vy, vz, ax, ay, az; NaN at k = 0, two-point start at k = 1.

    Extras follow the MIE contract: ``input_level`` = the estimated acceleration; a known detection
    pattern: ``maneuver_detected`` = 1 in every run at ``detect_steps``; ``maneuver_detected_axis``
    axis a at detect_steps + axis_lag[a]; ``test_statistic`` NaN until k = 5; ``onset_step`` k - 3
    where detected, else -1.
    """

    def __init__(self, name: str = "stub", q: float = 0.01, detect_steps=(43, 63), axis_lag=(0, 1, 2)) -> None:
        self.name = name
        self.q = float(q)
        self.detect_steps = [int(s) for s in detect_steps]
        self.axis_lag = [int(a) for a in axis_lag]

    def run(self, m: MeasurementSeries) -> TrackEstimate:
        started = time.perf_counter()
        R, K, _ = m.z.shape
        dt = float(m.time[1] - m.time[0])
        Rp = np.asarray(m.noise_covariance)
        zc = cartesian(m.z)
        J = conversion_jacobian(m.z)
        Rc = J @ Rp @ np.swapaxes(J, -1, -2)                                 # (R, K, 3, 3)
        I3 = np.eye(3)
        F = np.kron(np.array([[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]]), I3)
        Q = self.q * np.kron(np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                                       [dt**3 / 6, dt**2 / 2, dt]]), I3)
        H = np.hstack([I3, np.zeros((3, 6))])
        x = np.full((R, K, 9), np.nan)
        P = np.full((R, K, 9, 9), np.nan)
        x[:, 1] = np.concatenate([zc[:, 1], (zc[:, 1] - zc[:, 0]) / dt, np.zeros((R, 3))], axis=-1)
        P1 = np.zeros((R, 9, 9))
        P1[:, :3, :3] = Rc[:, 1]
        P1[:, :3, 3:6] = P1[:, 3:6, :3] = Rc[:, 1] / dt
        P1[:, 3:6, 3:6] = (Rc[:, 1] + Rc[:, 0]) / dt**2
        P1[:, 6:, 6:] = 100.0 * I3
        P[:, 1] = P1
        for k in range(2, K):
            xp = x[:, k - 1] @ F.T
            Pp = F @ P[:, k - 1] @ F.T + Q
            S = H @ Pp @ H.T + Rc[:, k]
            G = Pp @ H.T @ np.linalg.inv(S)
            x[:, k] = xp + np.einsum("rij,rj->ri", G, zc[:, k] - xp[:, :3])
            Pk = (np.eye(9) - G @ H) @ Pp
            P[:, k] = 0.5 * (Pk + np.swapaxes(Pk, -1, -2))
        detected = np.zeros((R, K), dtype=np.int8)
        per_axis = np.zeros((R, K, 3), dtype=np.int8)
        onset = np.full((R, K), -1, dtype=np.int64)
        for s in self.detect_steps:
            if s < K:
                detected[:, s] = 1
                onset[:, s] = s - 3
            for a, lag in enumerate(self.axis_lag):
                if s + lag < K:
                    per_axis[:, s + lag, a] = 1
        statistic = np.where(np.arange(K) >= 5, 1.0, np.nan) * np.ones((R, 1))
        extras = {"input_level": x[..., 6:9].copy(), "maneuver_detected": detected,
                  "maneuver_detected_axis": per_axis, "test_statistic": statistic, "onset_step": onset}
        return TrackEstimate(m.time, x, P, extras, time.perf_counter() - started)


# ---- scenario ----------------------------------------------------------------------------------
def test_scenario_kinematics_match_the_hand_computed_positions():
    truth = study_scenario(acceleration_at_scan="in_force").generate(2, seed=3)
    assert truth.state_names == STATE_NAMES
    assert truth.state.shape == (2, 101, 1, 9) and np.array_equal(truth.time, np.arange(101.0))
    s = truth.state[0, :, 0]
    np.testing.assert_allclose(s[0, :6], np.r_[P0, V0])
    # no acceleration before 40 s: p(40) = p0 + 40 v0
    np.testing.assert_allclose(s[40, :3], [2000.0, 6000.0, 4000.0], atol=1e-9)
    np.testing.assert_allclose(s[40, 3:6], V0, atol=1e-12)
    # the first interval of the maneuver, (40, 41]
    np.testing.assert_allclose(s[41, :3], [2000 - 150 + 7.5, 6000 + 50 - 5, 4000 + 50 - 2.5], atol=1e-9)
    # accelerating during [40, 60): p(60) = p(40) + 20 v0 + 200 a, v(60) = v0 + 20 a
    np.testing.assert_allclose(s[60, :3], [2000.0, 5000.0, 4000.0], atol=1e-9)
    np.testing.assert_allclose(s[60, 3:6], [150.0, -150.0, -50.0], atol=1e-9)
    np.testing.assert_allclose(s[100, :3], [8000.0, -1000.0, 2000.0], atol=1e-9)
    # the acceleration label is the one in force at each scan, and the state's ax..az equal it
    acc = truth.labels["acceleration"]
    assert acc.shape == (2, 101, 1, 3)
    np.testing.assert_array_equal(acc[0, :40, 0], 0.0)
    np.testing.assert_array_equal(acc[0, 40:60, 0], np.broadcast_to(A, (20, 3)))
    np.testing.assert_array_equal(acc[0, 60:, 0], 0.0)
    np.testing.assert_array_equal(truth.state[..., 6:9], acc)
    np.testing.assert_array_equal(truth.state[0], truth.state[1])       # deterministic by default
    # the other reading: the acceleration applied over (k-1, k]; the same kinematics
    lagged = study_scenario(acceleration_at_scan="last_interval").generate(1, seed=0)
    np.testing.assert_array_equal(lagged.state[0, :, 0, :6], s[:, :6])
    acc = lagged.labels["acceleration"][0, :, 0]
    np.testing.assert_array_equal(acc[:41], 0.0)
    np.testing.assert_array_equal(acc[41:61], np.broadcast_to(A, (20, 3)))
    np.testing.assert_array_equal(acc[61:], 0.0)
    np.testing.assert_array_equal(lagged.state[0, :, 0, 6:], acc)


def test_scenario_exact_kinematics_and_process_noise():
    # exact constant acceleration over each interval, also at dt = 0.5 (t = 40 lands on scan 80)
    truth = study_scenario(dt=0.5).generate(1, seed=0)
    s = truth.state[0, :, 0]
    assert s.shape[0] == 201
    np.testing.assert_allclose(s[120, :3], [2000.0, 5000.0, 4000.0], atol=1e-9)
    # process noise: per run, deterministic per seed, the kinematics follow the applied acceleration
    noisy = study_scenario(process_noise_std=2.0, acceleration_at_scan="in_force")
    a, b = noisy.generate(400, seed=5), noisy.generate(400, seed=5)
    np.testing.assert_array_equal(a.state, b.state)
    w = a.state[:, :, 0, 6:9] - study_scenario(acceleration_at_scan="in_force").acceleration
    assert abs(w.std() - 2.0) < 0.05 and abs(w.mean()) < 0.02
    p, v, acc = a.state[:, :, 0, :3], a.state[:, :, 0, 3:6], a.state[:, :, 0, 6:9]
    np.testing.assert_allclose(p[:, 1:], p[:, :-1] + v[:, :-1] + 0.5 * acc[:, :-1], atol=1e-8)
    np.testing.assert_array_equal(a.labels["acceleration"][:, :, 0], acc)


@pytest.mark.parametrize("kwargs, message", [
    ({"initial_position": [1.0, 2.0]}, "initial_position: [1.0, 2.0] must be [x, y, z]"),
    ({"initial_velocity": [1.0, 2.0, 3.0, 4.0]}, "initial_velocity: [1.0, 2.0, 3.0, 4.0] must be [vx, vy, vz]"),
    ({"segments": [[40, 60, 15, -10]]}, "segments[0]: [40, 60, 15, -10] must be [t_start, t_end, ax, ay, az]"),
    ({"segments": [[60, 40, 1, 1, 1]]}, "segments[0]: times 60..40 must satisfy 0 <= t_start < t_end"),
    ({"segments": [[10, 30, 1, 1, 1], [20, 40, 1, 1, 1]]}, "segments[0] and segments[1]"),
    ({"duration": 10.5}, "duration: 10.5 s is not a whole number of scan periods"),
    ({"duration": 1.0}, "duration: 1.0 s must be >= 2 dt"),
    ({"dt": 0.0}, "dt: 0.0 must be > 0 s"),
    ({"process_noise_std": -1.0}, "process_noise_std: -1.0 must be >= 0"),
    ({"acceleration_at_scan": "now"}, "acceleration_at_scan: 'now' is not one of ['in_force', 'last_interval']"),
])
def test_scenario_rejects_bad_arguments_by_name(kwargs, message):
    args = {"initial_position": list(P0), "initial_velocity": list(V0), "segments": [[40, 60, *A]], **kwargs}
    with pytest.raises(ValueError) as info:
        PiecewiseAcceleration3D(**args)
    assert message in str(info.value)


# ---- radar -------------------------------------------------------------------------------------
def test_radar_noise_statistics_over_many_runs():
    truth = study_scenario().generate(400, seed=1)
    radar = study_radar()
    det = radar.measure(truth, seed=11)
    assert det.measurement_names == ("range", "azimuth", "elevation")
    assert det.z.shape == (400, 101, 1, 3) and det.detected.all() and (det.target == 0).all()
    np.testing.assert_allclose(det.noise_covariance[0, 0, 0], np.diag([100.0, 4.9e-5, 3.6e-5]), rtol=1e-12)
    p = truth.state[..., :3]
    true = np.stack([np.linalg.norm(p, axis=-1), np.arctan2(p[..., 1], p[..., 0]),
                     np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1]))], axis=-1)
    err = det.z - true
    err[..., 1] = wrap_angle(err[..., 1])
    err = err.reshape(-1, 3)
    std = np.array([10.0, 0.007, 0.006])
    n = err.shape[0]
    assert (np.abs(err.mean(axis=0)) < 4 * std / np.sqrt(n)).all(), err.mean(axis=0)
    np.testing.assert_allclose(err.std(axis=0), std, rtol=0.02)
    assert abs(np.corrcoef(err.T)[0, 1]) < 0.02                            # independent channels
    # run r's noise does not depend on how many runs there are
    det3 = radar.measure(study_scenario().generate(3, seed=1), seed=11)
    np.testing.assert_array_equal(det3.z, det.z[:3])


def test_noise_free_radar_gives_the_atan2_forms_and_wraps_azimuth():
    truth = study_scenario().generate(1, seed=0)
    p = truth.state[0, :, 0, :3]
    det = Radar3D(range_std=0.0, azimuth_std=0.0, elevation_std=0.0).measure(truth, seed=0)
    z = det.z[0, :, 0]
    np.testing.assert_allclose(z[:, 0], np.sqrt((p**2).sum(-1)), rtol=1e-14)
    np.testing.assert_allclose(z[:, 1], np.arctan2(p[:, 1], p[:, 0]), atol=1e-15)
    np.testing.assert_allclose(z[:, 2], np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])), atol=1e-15)
    # the Cartesian view for the recording returns the positions
    view = Radar3D(range_std=0.0, azimuth_std=0.0, elevation_std=0.0).to_cartesian(det)
    np.testing.assert_allclose(view.z[0, :, 0], p, atol=1e-8)
    assert view.measurement_names == ("x", "y", "z")

    # a radar behind the target (target at azimuth pi at t = 0): the measured azimuth stays in
    # (-pi, pi] and its wrapped error has the configured std
    position = [10000.0, 4000.0, 0.0]
    det = Radar3D(position=position).measure(study_scenario().generate(2000, seed=0), seed=4)
    az = det.z[:, 0, 0, 1]
    assert (az > -np.pi).all() and (az <= np.pi).all()
    assert (az > 3).any() and (az < -3).any()                            # both sides of the cut
    assert abs(wrap_angle(az - np.pi).std() - 0.007) < 0.0005
    rel = truth.state[0, :, 0, :3] - position
    free = Radar3D(position=position, range_std=0.0, azimuth_std=0.0, elevation_std=0.0).measure(truth, 0)
    np.testing.assert_allclose(free.z[0, :, 0, 1], np.arctan2(rel[:, 1], rel[:, 0]), atol=1e-15)


def test_radar_detections_round_trip_with_their_units():
    det = study_radar().measure(study_scenario().generate(2, seed=0), seed=0)
    df, meta = schemas.detections_to_frame(det)
    assert "range: m, azimuth: rad, elevation: rad" in meta[schemas.META_UNITS]
    back = schemas.detections_from_frame(df, meta)
    np.testing.assert_array_equal(back.z, det.z)
    assert back.measurement_names == det.measurement_names and back.measurement_units == ("m", "rad", "rad")


@pytest.mark.parametrize("kwargs, message", [
    ({"position": [0.0, 0.0]}, "position: [0.0, 0.0] must be a finite [x, y, z]"),
    ({"range_std": -1.0}, "range_std: -1.0 must be a finite standard deviation >= 0 m"),
    ({"azimuth_std": float("nan")}, "azimuth_std: nan must be"),
])
def test_radar_rejects_bad_arguments_by_name(kwargs, message):
    with pytest.raises(ValueError) as info:
        Radar3D(**kwargs)
    assert message in str(info.value)


# ---- the pipeline with the stub ----------------------------------------------------------------
def compose_study(tmp_path: Path, *overrides: str, variants=("a", "b", "c")):
    package = StubEstimator.__module__.split(".")[0]          # the stub's own package may be named (item 5)
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=mie_los", f"paths.artifacts={tmp_path}",
                                           "record.enabled=false", f"plugins.packages=[{package}]", *overrides])
    target = f"{StubEstimator.__module__}.StubEstimator"
    with open_dict(cfg):
        cfg.filters = {v: {"_target_": target, "name": v.upper()} for v in variants}
    return cfg


def run_study(tmp_path: Path, name: str, *overrides: str, variants=("a", "b", "c")):
    cfg = compose_study(tmp_path, *overrides, variants=variants)
    ctx = RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))
    return run_experiment(cfg, ctx), ctx


def test_experiment_composes_with_the_variants_and_the_paper_table():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=mie_los"])
    assert cfg.experiment_name == "mie_los"
    assert list(cfg.filters) == ["a", "a_full", "b", "c", "b_nocomp"]       # the paper's four + the control
    assert cfg.filters.b_nocomp.compensate is False and cfg.filters.b_nocomp.test == "pooled"
    assert cfg.filters.a._target_ == "filters.input_estimation.InertialMIE"
    assert cfg.filters.c._target_ == "filters.input_estimation.LOSMIE" and cfg.filters.c.test == "per_axis"
    assert cfg.metrics.reference_variant == "a"
    table = instantiate(cfg.report.tables.table1, _convert_="all")
    labels = [r.label for r in table.rows]
    assert labels == ["1-40"] + [str(t) for t in range(41, 75)] + ["75-100"]
    refs = {r.label: r.reference for r in table.rows}
    assert refs["1-40"] == (4, 1, 0, 2, 0) and refs["43"] == (73, 53, 50, 11, 0)
    assert refs["63"] == (43, 57, 55, 5, 0) and refs["75-100"] == (192, 55, 42, 47, 69)


@pytest.fixture(scope="module")
def study_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mie_los")
    out, ctx = run_study(tmp, "first", "mc.runs=4")
    return tmp, out, ctx


def test_pipeline_with_the_stub_writes_the_new_metrics(study_run):
    tmp, out, ctx = study_run
    for name in ("truth.parquet", "detections.parquet", "estimates/a.parquet", "estimates/c.parquet",
                 "metrics.parquet", "summary.parquet", "report.txt", "status.json"):
        assert (ctx.run_dir / name).is_file(), name
    truth = pl.read_parquet(ctx.run_dir / "truth.parquet")
    assert truth.height == 4 * 101 and truth.schema["x"] == pl.Array(pl.Float64, 9)
    est = pl.read_parquet(ctx.run_dir / "estimates/c.parquet")
    assert est.schema["maneuver_detected_axis"] == pl.Array(pl.Int64, 3) and est.schema["P"] == pl.Array(pl.Float64, 81)

    metrics = pl.read_parquet(ctx.run_dir / "metrics.parquet")
    expected = {"position_rmse", "velocity_rmse", "acceleration_rmse", "nees", "nees_lower", "nees_upper",
                "input_level_x", "input_level_y",
                "input_level_z", "detections", "detections_axis_x", "detections_axis_y", "detections_axis_z",
                "position_bound", "position_rmse_over_bound",          # the stub exports no NIS
                "position_bound_model", "position_rmse_over_bound_model"}
    assert set(metrics["series"]) == expected

    def series(metric, variant="b"):
        rows = metrics.filter((pl.col("series") == metric) & (pl.col("variant_key") == variant)).sort("step")
        return rows["value"].to_numpy()

    det = series("detections")
    assert det.shape == (101,) and det[43] == 4 and det[63] == 4 and det.sum() == 8      # a count over runs
    assert series("detections_axis_y")[44] == 4 and series("detections_axis_z")[65] == 4
    assert np.isnan(series("position_rmse")[0]) and np.isfinite(series("position_rmse")[1:]).all()
    # Fig 4: the mean input level follows the maneuver's x acceleration (stub: the CA filter's estimate)
    level_x = series("input_level_x")
    assert level_x[50:60].mean() > 5 and abs(level_x[20:40].mean()) < 3
    # NEES over the 9-state: a consistent-ish CA filter before the maneuver averages near 9, not 4
    assert 5 < np.nanmean(series("nees")[5:40]) < 20

    summary = pl.read_parquet(ctx.run_dir / "summary.parquet")

    def value(metric, window, variant="b"):
        hit = summary.filter((pl.col("series") == metric) & (pl.col("variant_key") == variant)
                             & (pl.col("window") == window))["value"]
        assert hit.len() == 1, (metric, window, variant)
        return hit[0]

    # count windows: the coarse bins of Table 1, summed over steps and runs
    assert [value("detections", w) for w in ("t1-40", "t41-60", "t61-74", "t75-100")] == [0, 4, 4, 0]
    assert [value(f"detections_axis_{a}", "t61-74", "c") for a in "xyz"] == [4, 4, 4]
    assert value("detections", "all") == 8                    # counts are summed in every window
    assert summary.filter((pl.col("window") == "t41-60") & pl.col("series").is_in(["position_rmse"])).height == 0
    # RMS errors time-averaged over the windows
    rmse = series("position_rmse")
    assert value("position_rmse", "maneuver") == pytest.approx(rmse[41:61].mean())
    assert value("position_rmse", "before") == pytest.approx(rmse[2:41].mean())
    units = dict(zip(summary["series"], summary["unit"]))
    assert units["detections"].startswith("count") and units["acceleration_rmse"] == "m/s^2"
    # compute time per variant and as % of A; the report node is not a config column
    pct = summary.filter(pl.col("series") == "compute_pct_of_reference")
    assert dict(zip(pct["variant_key"], pct["value"]))["a"] == pytest.approx(100.0)
    assert summary.filter(pl.col("series") == "compute_seconds").height == 3
    assert "scenario.initial_position" in summary.columns and not any(c.startswith("report") for c in summary.columns)
    assert is_count("detections") and is_count("detections_axis_x") and not is_count("position_rmse")


def test_table1_report_prints_ours_beside_the_paper(study_run):
    tmp, out, ctx = study_run
    text = out.table
    assert text.startswith("mie_los: 4 Monte Carlo runs")            # the usual summary first ...
    assert "window: maneuver" in text and "window: t75-100" in text and "acc RMSE" in text
    head, table = text.split("Table 1 (seed 000)")                   # ... then Table 1
    assert "ours: 4 Monte Carlo runs; paper: 100 runs" in table
    lines = table.splitlines()
    header = next(line for line in lines if line.startswith("t [s]"))
    assert header.split() == ["t", "[s]", "ours", "A", "paper", "A", "ours", "B", "paper", "B", "ours", "C", "x/y/z",
                              "paper", "C", "x/y/z"]
    rows = {line.split()[0]: line.split()[1:] for line in lines if line[:1].isdigit() or line.startswith("total")}
    assert list(rows)[:3] == ["1-40", "41", "42"] and list(rows)[-2:] == ["75-100", "total"]
    assert len(rows) == 1 + 34 + 1 + 1
    assert rows["1-40"] == ["0", "4", "0", "1", "0/0/0", "0/2/0"]
    assert rows["43"] == ["4", "73", "4", "53", "4/0/0", "50/11/0"]
    assert rows["44"] == ["0", "14", "0", "40", "0/4/0", "44/28/0"]
    assert rows["63"] == ["4", "43", "4", "57", "4/0/0", "55/5/0"]
    assert rows["75-100"] == ["0", "192", "0", "55", "0/0/0", "42/47/69"]
    assert rows["total"][:2] == ["8", str(4 + 2 + 9 + 73 + 14 + 2 + 0 + 2 + 4 + 27 + 17 + 4 + 0 + 2 + 5 + 8 + 7 + 2 + 3
                                         + 1 + 7 + 8 + 31 + 43 + 9 + 2 + 7 + 7 + 19 + 26 + 8 + 7 + 5 + 7 + 8 + 192)]
    assert (ctx.run_dir / "report.txt").read_text() == text + "\n"


def test_cached_estimates_with_int8_extras_give_the_same_report(study_run, caplog):
    import logging
    tmp, out, _ = study_run
    caplog.set_level(logging.INFO, logger="pipeline")
    again, _ = run_study(tmp, "again", "mc.runs=4")
    assert caplog.text.count("[track] reused cached") == 3
    table = lambda t: t.split("Table 1 (seed 000)")[1]  # noqa: E731 (compute times differ, counts must not)
    assert table(again.table) == table(out.table)


def test_report_with_a_variant_not_run_and_the_recording_in_3d(tmp_path):
    out, ctx = run_study(tmp_path, "ab", "mc.runs=2", "variants=[a,b]", "record.enabled=true")
    assert (ctx.run_dir / "recording.rrd").stat().st_size > 0
    table = out.table.split("Table 1 (seed 000)")[1]
    assert "not run here: c (shown as -)" in table
    row43 = next(line for line in table.splitlines() if line.startswith("43 "))
    assert row43.split() == ["43", "2", "73", "2", "53", "-", "50/11/0"]


@pytest.mark.parametrize("overrides, message", [
    (["metrics.count_windows.t1-40=[40,1]"], "metrics.count_windows.t1-40: [40, 1] must be [first_step, last_step]"),
    (["+metrics.count_windows.all=[1,2]"], "metrics.count_windows.all: the name is also a key of metrics.windows"),
    (["report.tables.table1.columns.0.variant=zz"], "report.tables.table1: names variant(s) ['zz']"),
    (["report.tables.table1.rows.1.reference=[1,2]"],
     "report.tables.table1: rows[1].reference: [1, 2] holds 2 values; the columns ['A', 'B', 'C'] have 5 metrics"),
    (["report.tables.table1.aggregate=max"], "report.tables.table1: aggregate: 'max' is not one of ['sum', 'mean']"),
])
def test_bad_study_config_is_rejected_before_any_stage(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as info:
        run_study(tmp_path, "bad", "mc.runs=2", *overrides)
    assert message in str(info.value)
    assert not (tmp_path / "cache").exists()


def test_binned_table_is_generic_means_and_missing_metrics():
    metrics = pl.DataFrame({"variant_key": ["v"] * 6, "series": ["m"] * 6, "step": list(range(6)),
                            "value": [np.nan, 1.0, 2.0, 3.0, 4.0, 5.0]})
    table = BinnedTable(title="T", aggregate="mean", reference_label="ref", row_header="k", note="a note",
                        columns=[{"label": "V", "variant": "v", "metrics": ["m", "absent"], "parts": ["m", "a"]}],
                        rows=[{"steps": [0, 2], "reference": [1.5, None]}, {"steps": 9}])
    text = table.render(ReportContext("e", 3, {"v": "V"}, metrics, pl.DataFrame()))
    lines = text.splitlines()
    assert lines[:3] == ["T", "ours: 3 Monte Carlo runs", "a note"]
    assert lines[4].split() == ["k", "ours", "V", "m/a", "ref", "V", "m/a"]
    assert lines[6].split() == ["0-2", "1.50/-", "1.50/-"] and lines[7].split() == ["9", "-", "-"]
    assert "total" not in text                                            # no totals of means


# ---- study 001 is untouched ----------------------------------------------------------------------
# format_summary of a study-001 summary, as printed before study 000 was added (golden text).
# fractions below 1 print with three significant digits (pipeline.evaluation.metrics.format_value)
GOLDEN_001 = """\
ao_vsimm_s2: 7 Monte Carlo runs

window: all
variant   acc RMSE X  acc RMSE Y  pos RMSE  vel RMSE  NEES  models/step  models %  reached  compute s  compute %
--------  ----------  ----------  --------  --------  ----  -----------  --------  -------  ---------  ---------
FSIMM           1.00        2.13      3.26      4.39  5.52         6.65     100.0     0.00      0.123      100.0
VSIMM           1.37        2.50      3.63      4.76  5.89         7.02      80.0    0.250      0.247      200.0
AO-VSIMM        1.74        2.87      4.00      5.13  6.26         7.39      60.0    0.500      0.370      300.0

window: after_switch
variant   acc RMSE X  acc RMSE Y  pos RMSE  vel RMSE  NEES  models/step  models %  reached  compute s  compute %
--------  ----------  ----------  --------  --------  ----  -----------  --------  -------  ---------  ---------
FSIMM           1.50        2.63      3.76      4.89  6.02         7.15     100.0     0.00      0.123      100.0
VSIMM           1.87        3.00      4.13      5.26  6.39         7.52      80.0    0.250      0.247      200.0
AO-VSIMM        2.24        3.37      4.50      5.63  6.76         7.89      60.0    0.500      0.370      300.0"""


def test_study_001_printed_table_is_unchanged(tmp_path):
    rows = []
    metrics = ["acceleration_rmse_x", "acceleration_rmse_y", "position_rmse", "velocity_rmse", "nees",
               "models_evaluated"]
    for i, (key, display) in enumerate([("fsimm", "FSIMM"), ("vsimm", "VSIMM"), ("ao_vsimm", "AO-VSIMM")]):
        for w in ("all", "after_switch"):
            for j, m in enumerate(metrics):
                rows.append((display, key, m, w, 1.0 + 0.37 * i + 1.13 * j + (0.5 if w == "after_switch" else 0)))
            rows.append((display, key, "models_pct_of_reference", w, 100.0 - 20 * i))
        rows.append((display, key, "compute_seconds", None, 0.1234 * (i + 1)))
        rows.append((display, key, "group_reached_fraction", "M3 by step 80", 0.25 * i))
        rows.append((display, key, "compute_pct_of_reference", None, 100.0 * (i + 1)))
    df = pl.DataFrame(rows, schema=["variant", "variant_key", "series", "window", "value"], orient="row")
    assert format_summary(df, "ao_vsimm_s2", 7) == GOLDEN_001

    # a real study-001 run: the same metrics and windows as before, and after the summary only the
    # paired comparisons with the reference variant
    from tests.helpers.runs import run_in_process
    out, ctx = run_in_process(tmp_path, "s1", "mc.runs=2", "scenario.steps=30")
    assert out.table == format_summary(out.summary, "ao_vsimm_s1", 2, out.comparisons)
    assert set(out.metrics["series"]) == {"acceleration_rmse_x", "acceleration_rmse_y", "position_rmse",
                                          "velocity_rmse", "nees", "nees_lower", "nees_upper", "models_evaluated",
                                          "nis", "nis_lower", "nis_upper", "position_bound",
                                          "position_rmse_over_bound", "position_bound_model",
                                          "position_rmse_over_bound_model"}
    # after_switch (steps 57-200) holds no step of a 30-step run: left out with a warning, no NaN rows
    assert set(out.summary["window"].drop_nulls()) == {"all"}
    header = next(line for line in out.table.splitlines() if line.startswith("variant"))
    assert header.split("  ") and [c.strip() for c in header.split("  ") if c.strip()] == [
        "variant", "acc RMSE X", "acc RMSE Y", "pos RMSE", "vel RMSE", "NEES", "models/step", "models % of FSIMM",
        "compute s", "compute % of FSIMM"]                  # each percentage names its reference (issue 19)
