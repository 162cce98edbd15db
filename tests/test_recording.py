"""pipeline.views.recording: the .rrd written for an experiment has the entity tree, timelines and
blueprint the viewer layout relies on. Read back with rerun.chunk.RrdReader (no viewer)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from filters.base import MeasurementSeries
from filters.imm import AOVSIMM, FSIMM
from pipeline.views.recording import recording_id
from pipeline.views.single_target import write_recording
from pipeline.studies.ao_vsimm.sensor import PositionSensor

ROOT = Path(__file__).resolve().parents[1]
RUNS, STEPS = 3, 29                      # scans k = 0..29
RECORD = [0, 2]
VARIANTS = {"fsimm": "FSIMM", "ao_vsimm": "AO-VSIMM"}
METRICS = ("position_rmse", "acceleration_rmse_x", "acceleration_rmse_y", "models_evaluated")


def _rmse(err: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.mean(np.sum(err**2, axis=-1), axis=0))   # NaN where no estimate yet


@pytest.fixture(scope="module")
def case():
    models = instantiate(OmegaConf.load(ROOT / "conf/models/acceleration13.yaml"))
    scen_cfg = OmegaConf.load(ROOT / "conf/scenario/ao_vsimm_s1.yaml")
    scen_cfg.steps = STEPS
    # S1's first manoeuvre (20 m/s^2 in x) moved into the short horizon, so a group switch happens
    scen_cfg.segments = [[5, 15, 20, 0], [16, 22, 0, 20]]
    truth = instantiate(scen_cfg).generate(RUNS, 7)
    det = PositionSensor(20.0).measure(truth, 7)
    ms = MeasurementSeries(det.time, det.z[:, :, 0], 400 * np.eye(2), det.detected[:, :, 0], det.sensor)
    estimates = {"fsimm": FSIMM(models, name="FSIMM").run(ms), "ao_vsimm": AOVSIMM(models, name="AO-VSIMM").run(ms)}
    rows = []
    for key, est in estimates.items():
        err = est.state - truth.state[:, :, 0]
        acc_err = est.extras["acceleration"] - truth.labels["acceleration"][:, :, 0]
        values = {"position_rmse": _rmse(err[..., [0, 2]]), "acceleration_rmse_x": _rmse(acc_err[..., :1]),
                  "acceleration_rmse_y": _rmse(acc_err[..., 1:]),
                  "models_evaluated": est.extras["models_evaluated"].mean(axis=0).astype(float)}
        for metric, v in values.items():
            rows.append(pl.DataFrame({
                "run_id": "test", "experiment": "s1 tiny", "variant": VARIANTS[key], "variant_key": key,
                "series": metric, "step": np.arange(truth.time.size, dtype=np.int32), "time": truth.time,
                "value": v, "n_runs": np.full(truth.time.size, RUNS, dtype=np.int32)}))
    return dict(models=models, truth=truth, det=det, estimates=estimates, metrics=pl.concat(rows))


def _write(case, path: Path, record_runs=RECORD) -> None:
    models = case["models"]
    write_recording(path, experiment="s1 tiny", truth=case["truth"], detections=case["det"],
                    estimates=case["estimates"], display_names=VARIANTS, metrics=case["metrics"],
                    record_runs=record_runs, model_names=models.names, group_names=models.group_names,
                    config_text="scenario: ao_vsimm_s1\nruns: 3\n", description="A tiny S1 for the test.")


@pytest.fixture(scope="module")
def rrd(case, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "s1.rrd"
    _write(case, path)
    return path


@pytest.fixture(scope="module")
def entities(rrd):
    """entity path -> {"static": set of columns, "temporal": set of columns, "timelines": set, "rows": int}"""
    from rerun.chunk import RrdReader

    out: dict = defaultdict(lambda: {"static": set(), "temporal": set(), "timelines": set(), "rows": 0})
    for chunk in RrdReader(rrd).stream().to_chunks():
        e = out[chunk.entity_path]
        cols = {c for c in chunk.to_record_batch().schema.names if ":" in c}
        if chunk.is_static:
            e["static"] |= cols
        else:
            e["temporal"] |= cols
            e["timelines"] |= set(chunk.timeline_names)
            e["rows"] += chunk.num_rows
    return dict(out)


def _time_varying(entities, path: str, column: str) -> dict:
    assert path in entities, f"{path} missing; have {sorted(entities)}"
    e = entities[path]
    assert column in e["temporal"], f"{path}: {column} not time-varying; temporal={e['temporal']}"
    assert {"time", "step"} <= e["timelines"], f"{path}: timelines {e['timelines']}"
    return e


def test_file_is_complete_and_atomic(rrd):
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    recs = reader.recordings()
    assert [(r.application_id, r.recording_id) for r in recs] == [("mtt", recording_id("s1 tiny"))] \
        == [("mtt", "s1_tiny")]
    assert reader.store() is not None          # raises "Legacy RRD without footer" if not finalised
    assert reader.blueprints(), "no blueprint stored in the .rrd"
    assert [p.name for p in rrd.parent.iterdir()] == ["s1.rrd"], "temporary file left behind"


def test_world_entities(entities, case):
    K = case["truth"].time.size
    for r in RECORD:
        world = f"/world/run{r}"
        truth = _time_varying(entities, f"{world}/truth", "Points2D:positions")
        assert "LineStrips2D:strips" in truth["static"]             # the whole trajectory, faint
        assert truth["rows"] == K
        assert _time_varying(entities, f"{world}/truth/path", "LineStrips2D:strips")["rows"] == K - 1
        assert _time_varying(entities, f"{world}/measurements", "Points2D:positions")["rows"] == K
        assert _time_varying(entities, f"{world}/measurements/all", "Points2D:positions")["rows"] == K
        for key in VARIANTS:
            track = _time_varying(entities, f"{world}/{key}/track", "LineStrips2D:strips")
            assert "LineStrips2D:strips" not in track["static"], "a static track shows the future"
            assert track["rows"] == K - 2                              # estimates from scan 1: segments from 2
            est = _time_varying(entities, f"{world}/{key}/estimate", "Points2D:positions")
            assert est["rows"] == K - 1            # no estimate at scan 0
            _time_varying(entities, f"{world}/{key}/covariance", "LineStrips2D:strips")
    assert not any(p.startswith("/world/run1/") for p in entities), "run 1 was not asked for"


def test_variant_series(entities, case):
    models = case["models"]
    for r in RECORD:
        for key in VARIANTS:
            base = f"/variants/{key}/run{r}"
            for name in models.names:
                e = _time_varying(entities, f"{base}/mode_probability/{name}", "Scalars:scalars")
                assert "SeriesLines:names" in e["static"]
        # AO-VSIMM has groups; FSIMM runs every model and logs no group series
        for what in ("active_group", "candidate_group"):
            _time_varying(entities, f"/variants/ao_vsimm/run{r}/{what}", "Scalars:scalars")
            assert f"/variants/fsimm/run{r}/{what}" not in entities
        _time_varying(entities, f"/variants/ao_vsimm/run{r}/events", "TextLog:text")


def test_event_lines_and_group_numbers(rrd):
    from rerun.chunk import RrdReader

    texts, groups = [], []
    for chunk in RrdReader(rrd).stream().to_chunks():
        if chunk.entity_path == "/variants/ao_vsimm/run0/events":
            texts += pl.from_arrow(chunk.to_record_batch())["TextLog:text"].explode().to_list()
        if chunk.entity_path == "/variants/ao_vsimm/run0/active_group" and not chunk.is_static:
            groups += pl.from_arrow(chunk.to_record_batch())["Scalars:scalars"].explode().to_list()
    assert texts[0] == "start: M1"
    assert all(" -> " in t for t in texts[1:])
    assert groups[0] == 1.0 and min(groups) >= 1.0          # 1-based: M1 = 1


def test_metrics_and_config(entities):
    for metric in METRICS:
        for key in VARIANTS:
            e = _time_varying(entities, f"/metrics/{metric}/{key}", "Scalars:scalars")
            assert {"SeriesLines:names", "SeriesLines:colors"} <= e["static"]
    assert "TextDocument:text" in entities["/config"]["static"]


def test_metric_colour_and_name_per_variant(rrd):
    from rerun.chunk import RrdReader

    style = defaultdict(set)
    for chunk in RrdReader(rrd).stream().to_chunks():
        if chunk.entity_path.startswith("/metrics/") and chunk.is_static:
            df = pl.from_arrow(chunk.to_record_batch())
            key = chunk.entity_path.rsplit("/", 1)[1]
            style[key].add((df["SeriesLines:names"].explode()[0], df["SeriesLines:colors"].explode()[0]))
    assert {k: {n for n, _ in v} for k, v in style.items()} == {k: {v} for k, v in VARIANTS.items()}
    assert all(len(v) == 1 for v in style.values()), "one colour per variant across all metric views"
    assert len({next(iter(v))[1] for v in style.values()}) == len(VARIANTS)


@pytest.mark.parametrize("bad", [[3], [-1], [0, 5]])
def test_out_of_range_record_run_raises(case, tmp_path, bad):
    with pytest.raises(ValueError, match=r"record\.runs") as info:
        _write(case, tmp_path / "bad.rrd", record_runs=bad)
    assert "0..2" in str(info.value)
    assert not any(tmp_path.iterdir()), "nothing may be written for a bad request"


# ---------------------------------------------------------------------------------------------------
# 3-D (study 000): a target with a z state, a radar at the origin with polar detections
# ---------------------------------------------------------------------------------------------------

RUNS_3D, K_3D = 3, 30                     # scans k = 0..29
RECORD_3D = [0, 2]
VARIANTS_3D = {"a": "A", "c": "C"}        # C reports per-LOS-axis detections
STATE_3D = ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")
POLAR_VAR = np.array([100.0, 4.9e-5, 3.6e-5])
CLEAN = (0, 7)                            # (run, step) of a noise-free detection
DETECTED = {"a": [11, 12, 20], "c": [11, 20]}   # run 0; C: x at 11, y and z at 20
METRICS_3D = ("position_rmse", "velocity_rmse", "acceleration_rmse", "input_level_x", "input_level_y",
              "input_level_z", "detections", "nees")


def _polar(p: np.ndarray) -> np.ndarray:
    return np.stack([np.linalg.norm(p, axis=-1), np.arctan2(p[..., 1], p[..., 0]),
                     np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1]))], axis=-1)


@pytest.fixture(scope="module")
def case3d():
    from filters.base import TrackEstimate
    from pipeline.data import Detections, Truth

    rng = np.random.default_rng(0)
    t = np.arange(K_3D, dtype=float)
    p = np.array([8000.0, 4000.0, 2000.0]) + np.outer(t, [-150.0, 50.0, 50.0])    # constant velocity
    x = np.concatenate([p, np.tile([-150.0, 50.0, 50.0], (K_3D, 1)), np.zeros((K_3D, 3))], axis=-1)
    state = np.broadcast_to(x[None, :, None], (RUNS_3D, K_3D, 1, 9)).copy()
    truth = Truth(t, state, STATE_3D, {"acceleration": np.zeros((RUNS_3D, K_3D, 1, 3))})
    z = _polar(state[..., :3]) + rng.normal(size=(RUNS_3D, K_3D, 1, 3)) * np.sqrt(POLAR_VAR)
    z[CLEAN[0], CLEAN[1], 0] = _polar(p[CLEAN[1]])
    det = Detections(t, np.zeros(K_3D, dtype=np.int64), z,
                     np.broadcast_to(np.diag(POLAR_VAR), (RUNS_3D, K_3D, 1, 3, 3)).copy(),
                     np.zeros((RUNS_3D, K_3D, 1), dtype=np.int64), np.ones((RUNS_3D, K_3D, 1), dtype=bool),
                     ("range", "azimuth", "elevation"))
    estimates, rows = {}, []
    for key in VARIANTS_3D:
        est_state = state[:, :, 0] + rng.normal(size=(RUNS_3D, K_3D, 9)) * 20.0
        A = rng.normal(size=(RUNS_3D, K_3D, 9, 9))
        cov = A @ np.swapaxes(A, -1, -2) * 100.0 + 10.0 * np.eye(9)                 # SPD, correlated
        est_state[:, 0], cov[:, 0] = np.nan, np.nan
        detected = np.zeros((RUNS_3D, K_3D), dtype=np.int8)
        detected[0, DETECTED[key]] = 1
        onset = np.where(detected == 1, np.arange(K_3D) - 3, -1)
        stat = np.where(np.arange(K_3D) >= 5, rng.chisquare(3, size=(RUNS_3D, K_3D)), np.nan)
        stat[detected == 1] = 30.0
        u = np.zeros((RUNS_3D, K_3D, 3))
        u[:, 0] = np.nan
        u[:, 12:20] = [15.0, -10.0, -5.0]
        extras = {"input_level": u, "maneuver_detected": detected, "test_statistic": stat, "onset_step": onset}
        if key == "c":
            axis = np.zeros((RUNS_3D, K_3D, 3), dtype=np.int8)
            axis[0, 11, 0] = 1
            axis[0, 20, 1:] = 1
            extras["maneuver_detected_axis"] = axis
        estimates[key] = TrackEstimate(t, est_state, cov, extras)
        err = est_state - state[:, :, 0]
        values = {"position_rmse": _rmse(err[..., :3]), "velocity_rmse": _rmse(err[..., 3:6]),
                  "acceleration_rmse": _rmse(err[..., 6:]), "detections": detected.sum(0).astype(float),
                  "nees": np.full(K_3D, 9.0), **{f"input_level_{a}": u[..., i].mean(0) for i, a in enumerate("xyz")}}
        if key == "c":
            values.update({f"detections_axis_{a}": axis[..., i].sum(0).astype(float) for i, a in enumerate("xyz")})
        for metric, v in values.items():
            rows.append(pl.DataFrame({
                "run_id": "test", "experiment": "mie tiny", "variant": VARIANTS_3D[key], "variant_key": key,
                "series": metric, "step": np.arange(K_3D, dtype=np.int32), "time": t, "value": v,
                "n_runs": np.full(K_3D, RUNS_3D, dtype=np.int32)}))
    return dict(truth=truth, det=det, estimates=estimates, metrics=pl.concat(rows), position=p)


def _write3d(case3d, path: Path, record_runs=RECORD_3D, detections=None) -> None:
    write_recording(path, experiment="mie tiny", truth=case3d["truth"], detections=detections or case3d["det"],
                    estimates=case3d["estimates"], display_names=VARIANTS_3D, metrics=case3d["metrics"],
                    record_runs=record_runs, config_text="study: 000\n", description="A tiny 3-D case.")


@pytest.fixture(scope="module")
def rrd3d(case3d, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec3d") / "mie.rrd"
    _write3d(case3d, path)
    return path


@pytest.fixture(scope="module")
def entities3d(rrd3d):
    return entities.__wrapped__(rrd3d)


def _temporal_rows(rrd: Path, entity: str, column: str) -> dict[int, list]:
    """step -> the values of ``column`` logged at that step on ``entity``."""
    from rerun.chunk import RrdReader

    out: dict[int, list] = {}
    for chunk in RrdReader(rrd).stream().to_chunks():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        df = pl.from_arrow(chunk.to_record_batch())
        if column in df.columns:
            for step, value in zip(df["step"].to_list(), df[column].to_list()):
                out[step] = value
    return out


def test_3d_file_is_complete_and_has_a_blueprint(rrd3d):
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd3d)
    assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("mtt", "mie_tiny")]
    assert reader.store() is not None
    assert reader.blueprints(), "no blueprint stored in the .rrd"
    assert [p.name for p in rrd3d.parent.iterdir()] == ["mie.rrd"], "temporary file left behind"


def test_3d_world_entities(entities3d):
    K = K_3D
    assert "Points3D:positions" in entities3d["/world/radar"]["static"]
    for r in RECORD_3D:
        world = f"/world/run{r}"
        truth = _time_varying(entities3d, f"{world}/truth", "Points3D:positions")
        assert "LineStrips3D:strips" in truth["static"] and truth["rows"] == K
        assert _time_varying(entities3d, f"{world}/truth/path", "LineStrips3D:strips")["rows"] == K - 1
        assert _time_varying(entities3d, f"{world}/measurements", "Points3D:positions")["rows"] == K
        assert _time_varying(entities3d, f"{world}/measurements/all", "Points3D:positions")["rows"] == K
        for key in VARIANTS_3D:
            track = _time_varying(entities3d, f"{world}/{key}/track", "LineStrips3D:strips")
            assert "LineStrips3D:strips" not in track["static"], "a static track shows the future"
            assert _time_varying(entities3d, f"{world}/{key}/estimate", "Points3D:positions")["rows"] == K - 1
            cov = _time_varying(entities3d, f"{world}/{key}/covariance", "Ellipsoids3D:half_sizes")
            assert {"Ellipsoids3D:quaternions", "Ellipsoids3D:centers"} <= cov["temporal"]
            assert cov["rows"] == K - 1
            base = f"/variants/{key}/run{r}"
            for a in "xyz":
                _time_varying(entities3d, f"{base}/input_level/{a}", "Scalars:scalars")
            _time_varying(entities3d, f"{base}/test_statistic", "Scalars:scalars")
    # detections only in run 0; no LOS-axis arrows for A, which has no per-axis flags
    for key in VARIANTS_3D:
        e = _time_varying(entities3d, f"/world/run0/{key}/detections", "TextLog:text")
        assert "Points3D:positions" in e["temporal"]
        assert f"/world/run2/{key}/detections" not in entities3d
    for a in "xyz":
        _time_varying(entities3d, f"/world/run0/c/detections/{a}", "Arrows3D:vectors")
        assert f"/world/run0/a/detections/{a}" not in entities3d
    assert not any(p.startswith("/world/run1/") for p in entities3d), "run 1 was not asked for"
    two_d = {p for p, e in entities3d.items() if any("2D:" in c for c in e["static"] | e["temporal"])
             and not p.startswith("/key/")}               # the colour key is a 2-D strip of labelled points
    assert not two_d, f"2-D archetypes in a 3-D recording: {sorted(two_d)}"


def test_3d_metrics_and_config(entities3d):
    for metric in METRICS_3D:
        for key in VARIANTS_3D:
            e = _time_varying(entities3d, f"/metrics/{metric}/{key}", "Scalars:scalars")
            assert {"SeriesLines:names", "SeriesLines:colors"} <= e["static"]
    for a in "xyz":
        _time_varying(entities3d, f"/metrics/detections_axis_{a}/c", "Scalars:scalars")
        _time_varying(entities3d, f"/truth/run0/acceleration/{a}", "Scalars:scalars")
    assert "TextDocument:text" in entities3d["/config"]["static"]


def test_3d_ellipsoid_is_the_2_sigma_position_covariance(rrd3d, case3d):
    from scipy.spatial.transform import Rotation

    k = 9
    P = case3d["estimates"]["a"].covariance[0, k, :3, :3]
    half = np.asarray(_temporal_rows(rrd3d, "/world/run0/a/covariance", "Ellipsoids3D:half_sizes")[k][0])
    quat = np.asarray(_temporal_rows(rrd3d, "/world/run0/a/covariance", "Ellipsoids3D:quaternions")[k][0])
    centre = np.asarray(_temporal_rows(rrd3d, "/world/run0/a/covariance", "Ellipsoids3D:centers")[k][0])
    np.testing.assert_allclose(np.sort(half), 2.0 * np.sqrt(np.linalg.eigvalsh(P)), rtol=1e-5)
    # orientation: rotating the axis-aligned ellipsoid by the quaternion (xyzw) gives back P
    Rm = Rotation.from_quat(quat).as_matrix()
    np.testing.assert_allclose(Rm @ np.diag((half / 2.0) ** 2) @ Rm.T, P, rtol=1e-4, atol=1e-3 * np.abs(P).max())
    np.testing.assert_allclose(centre, case3d["estimates"]["a"].state[0, k, :3], rtol=1e-6)


def test_3d_measurement_conversion(rrd3d, case3d):
    run, k = CLEAN
    assert run == 0
    measured = _temporal_rows(rrd3d, "/world/run0/measurements", "Points3D:positions")
    np.testing.assert_allclose(np.asarray(measured[k][0]), case3d["position"][k], rtol=1e-6, atol=1e-2)
    # a noisy scan is near, not on, the truth (cross-range noise ~ 60 m at this range)
    assert 0.0 < np.linalg.norm(np.asarray(measured[k + 1][0]) - case3d["position"][k + 1]) < 1000.0


def test_3d_detection_log_and_markers(rrd3d, case3d):
    for key, steps in DETECTED.items():
        entity = f"/world/run0/{key}/detections"
        texts = _temporal_rows(rrd3d, entity, "TextLog:text")
        assert sorted(texts) == steps
        for k in steps:
            assert texts[k][0].startswith("maneuver detected")
            assert f"onset n = {k - 3}" in texts[k][0] and "statistic 30" in texts[k][0]
        markers = _temporal_rows(rrd3d, entity, "Points3D:positions")
        est = case3d["estimates"][key].state[0]
        for k in steps:
            np.testing.assert_allclose(np.asarray(markers[k]), est[[k], :3], rtol=1e-6)
        cleared = [k for k, v in markers.items() if not v]
        assert cleared and all(k - 1 in steps and k not in steps for k in cleared), "marker shown at its step only"
    texts = _temporal_rows(rrd3d, "/world/run0/c/detections", "TextLog:text")
    assert "on LOS x," in texts[11][0] and "on LOS y, z," in texts[20][0]
    arrows = _temporal_rows(rrd3d, "/world/run0/c/detections/x", "Arrows3D:vectors")
    assert len(arrows[11]) == 1 and not arrows.get(20)
    # the LOS x arrow points along the line of sight (away from the radar at the origin)
    los = case3d["estimates"]["c"].state[0, 11, :3]
    cos = np.dot(arrows[11][0], los) / (np.linalg.norm(arrows[11][0]) * np.linalg.norm(los))
    assert cos == pytest.approx(1.0, abs=1e-6)


def test_3d_input_level_series(rrd3d, case3d):
    u = case3d["estimates"]["c"].extras["input_level"][2]
    for i, a in enumerate("xyz"):
        rows = _temporal_rows(rrd3d, f"/variants/c/run2/input_level/{a}", "Scalars:scalars")
        assert sorted(rows) == list(range(1, K_3D))            # NaN at k = 0 is left out
        np.testing.assert_allclose([rows[k][0] for k in range(1, K_3D)], u[1:, i])


def test_3d_bad_measurement_names_raise(case3d, tmp_path):
    from dataclasses import replace

    det = replace(case3d["det"], measurement_names=("r", "b", "e"))
    with pytest.raises(ValueError, match="measurement_names"):
        _write3d(case3d, tmp_path / "bad.rrd", detections=det)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("bad", [[3], [0, 0]])
def test_3d_record_runs_validated(case3d, tmp_path, bad):
    with pytest.raises(ValueError, match=r"record\.runs"):
        _write3d(case3d, tmp_path / "bad.rrd", record_runs=bad)
    assert not any(tmp_path.iterdir())


# ---- issue 19: what the viewer shows (checked on the blueprint and the data, without pixels) ------
from pipeline.views.blueprints import title_chars                                     # noqa: E402
from pipeline.views.colours import model_colour, variant_colour                            # noqa: E402
from tests.helpers.rrd_reading import (blueprint_views, capture_blueprint, legend_visible, read_chunks,  # noqa: E402
                                       rows as chunk_rows, up_to_now)


@pytest.fixture(scope="module")
def blueprint2d(case, tmp_path_factory):
    return capture_blueprint(lambda: _write(case, tmp_path_factory.mktemp("bp") / "s1.rrd"))


@pytest.fixture(scope="module")
def blueprint3d(case3d, tmp_path_factory):
    return capture_blueprint(lambda: _write3d(case3d, tmp_path_factory.mktemp("bp3") / "mie.rrd"))


def _kinds(parents) -> list[str]:
    return [str(p.kind) for p in parents]


def test_mode_probabilities_of_every_variant_side_by_side(blueprint2d):
    modes = [(v, parents) for v, parents, _ in blueprint_views(blueprint2d)
             if str(v.origin).endswith("/mode_probability")]
    assert [str(v.origin) for v, _ in modes] == [f"/variants/{k}/run0/mode_probability" for k in VARIANTS]
    assert all("Tabs" not in _kinds(parents) for _, parents in modes), "a mode view sits in a tab: one at a time"
    assert len({id(parents[-1]) for _, parents in modes}) == 1 and str(modes[0][1][-1].kind) == "Horizontal"


def test_plots_have_no_legend_and_the_keys_name_the_colours(blueprint2d, rrd, case):
    plots = [v for v, _, _ in blueprint_views(blueprint2d) if v.class_identifier == "TimeSeries"]
    assert plots and all(legend_visible(v) is False for v in plots), \
        [str(v.name) for v in plots if legend_visible(v) is not False]
    chunks = read_chunks(rrd)
    key = {p: df for p, static, _, df in chunks if p.startswith("/key/") and static}
    labels = key["/key/variants"]["Points2D:labels"].explode().to_list()
    colours = key["/key/variants"]["Points2D:colors"].explode().to_list()
    assert labels == list(VARIANTS.values())
    assert [((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for c in colours] == \
        [variant_colour(i) for i in range(len(VARIANTS))]
    names = list(case["models"].names)
    assert key["/key/models"]["Points2D:labels"].explode().to_list() == names
    # the mode lines are in the key's colours
    style = {p.rsplit("/", 1)[1]: df["SeriesLines:colors"].explode()[0] for p, static, _, df in chunks
             if static and p.startswith("/variants/fsimm/run0/mode_probability/")}
    assert {n: ((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for n, c in style.items()} == \
        {n: model_colour(i, len(names)) for i, n in enumerate(names)}


@pytest.mark.parametrize("which", ["2d", "3d"])
def test_every_title_fits_its_view(which, blueprint2d, blueprint3d):
    blueprint = blueprint2d if which == "2d" else blueprint3d
    too_long = [(str(v.name), round(w)) for v, _, w in blueprint_views(blueprint)
                if v.name is not None and v.titlebar is None and len(str(v.name)) > title_chars(w)]
    assert not too_long, too_long


def test_spatial_views_draw_paths_up_to_now(blueprint2d, blueprint3d):
    for blueprint, keys, runs in ((blueprint2d, VARIANTS, RECORD), (blueprint3d, VARIANTS_3D, [RECORD_3D[0]])):
        spatial = [v for v, _, _ in blueprint_views(blueprint) if v.class_identifier in ("2D", "3D")
                   and not str(v.origin).startswith("/key")]
        assert spatial
        for view in spatial:
            contents = " ".join(str(c) for c in (view.contents or []))
            for r in runs:
                for key in keys:
                    if f"/world/run{r}/{key}/**" in contents:
                        assert up_to_now(view, f"/world/run{r}/{key}/track"), (view.name, key)
                if f"/world/run{r}/truth/**" in contents:
                    assert up_to_now(view, f"/world/run{r}/truth/path"), view.name


def test_track_segments_end_at_their_step(rrd, case):
    """A track is one segment per step from the previous estimate to this step's: shown up to the
    cursor, it is the track so far and nothing of the future."""
    chunks = read_chunks(rrd)
    for key in VARIANTS:
        pos = case["estimates"][key].state[0][:, [0, 2]]
        segments = chunk_rows(chunks, f"/world/run0/{key}/track", "LineStrips2D:strips")
        assert sorted(segments) == list(range(2, pos.shape[0]))
        for k, strips in segments.items():
            assert np.allclose(np.asarray(strips[0]), pos[k - 1:k + 1], atol=1e-3)


@pytest.mark.parametrize("which", ["2d", "3d"])
def test_no_viewer_warning_while_writing(which, case, case3d, tmp_path, capfd):
    (_write if which == "2d" else _write3d)(case if which == "2d" else case3d, tmp_path / "quiet.rrd")
    err = capfd.readouterr().err
    assert "Dropping chunk" not in err and "WARN" not in err, err
