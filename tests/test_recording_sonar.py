"""pipeline.studies.sonar.recording: study 003's .rrd has the entity tree, values and blueprint the viewer
layout relies on. A tiny synthetic encounter (2 runs, 60 scans, active in [0, 15) and [30, 40) s)
run through the real sonar and trackers, read back with rerun.chunk.RrdReader (no viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from filters.mgekf import KFPlusMGEKF, OnlyMGEKF
from pipeline.data import Truth
from pipeline.studies.sonar.scenario import SonarEncounter
from pipeline.studies.sonar.sensor import ActivePassiveSonar
from pipeline.evaluation.evaluate import metrics_frame
from pipeline.contract import RecordingInputs
from pipeline.studies.sonar.adapter import SonarStudy
from tests.helpers.rrd_reading import assert_complete_recording, entity_index, read_chunks, rows, temporal

RUNS, RECORD = 2, [1]
VARIANTS = {"kf_mgekf": "KF + MGEKF", "only_mgekf": "only MGEKF"}
INTERVALS = [[0.0, 15.0], [30.0, 40.0]]
STRIDE = 10
K = 60


@pytest.fixture(scope="module")
def case():
    truth = SonarEncounter(duration=K - 1, ownship_leg=20.0, target_offset=(2000.0, 3000.0)).generate(RUNS, 0)
    sensor = ActivePassiveSonar(INTERVALS, bearing_std_deg=1.0, range_std=10.0)
    det = sensor.measure(truth, seed=3)
    study = SonarStudy()
    reports = study.track_input(truth, det, sensor, seed=3)
    estimates = {"kf_mgekf": KFPlusMGEKF(sigma_m=0.01).run(reports), "only_mgekf": OnlyMGEKF(sigma_m=0.01).run(reports)}
    per_variant = {k: (VARIANTS[k], study.per_step_metrics(truth, est, sensor)) for k, est in estimates.items()}
    metrics = metrics_frame(truth.time, per_variant, RUNS)
    active = sensor.is_active(truth.time)
    return dict(truth=truth, det=det, sensor=sensor, estimates=estimates, metrics=metrics, active=active)


def _write(case, path: Path, record_runs=RECORD, truth=None) -> None:
    # through the study adapter, as the runner calls it
    SonarStudy().record(path, RecordingInputs(
        experiment="sonar tiny", truth=truth or case["truth"], detections=case["det"], estimates=case["estimates"],
        display_names=VARIANTS, metrics=case["metrics"], record_runs=record_runs, sensor=case["sensor"],
        estimators={}, track_input=None, seed=0, config_text="study: 003\n",
        description="A tiny study 003 for the test.", options={"ellipse_stride": STRIDE}))


@pytest.fixture(scope="module")
def rrd(case, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "sonar.rrd"
    _write(case, path)
    return path


@pytest.fixture(scope="module")
def chunks(rrd):
    return read_chunks(rrd)


@pytest.fixture(scope="module")
def entities(chunks):
    return entity_index(chunks)


def test_file_is_complete_and_atomic(rrd):
    assert_complete_recording(rrd, "sonar_tiny")


def test_entity_tree(entities):
    for name in ("ownship", "target"):
        e = temporal(entities, f"/world/run1/{name}", "Points2D:positions")
        assert "LineStrips2D:strips" in e["static"] and e["rows"] == K      # the whole track faint
        assert temporal(entities, f"/world/run1/{name}/path", "LineStrips2D:strips")["rows"] == K - 1
    temporal(entities, "/world/run1/measurements/bearing", "LineStrips2D:strips")
    temporal(entities, "/world/run1/measurements/fix", "Points2D:positions")
    for key in VARIANTS:
        base = f"/world/run1/{key}"
        assert temporal(entities, f"{base}/track", "LineStrips2D:strips")["rows"] == K - 1
        assert temporal(entities, f"{base}/estimate", "Points2D:positions")["rows"] == K
        temporal(entities, f"{base}/covariance", "LineStrips2D:strips")
        for axis in ("x", "y"):
            assert temporal(entities, f"/errors/run1/{axis}/{key}", "Scalars:scalars")["rows"] == K
        for metric in ("position_rmse", "position_rmse_x", "position_rmse_y", "velocity_rmse", "nees"):
            e = temporal(entities, f"/metrics/{metric}/{key}", "Scalars:scalars")
            assert {"SeriesLines:names", "SeriesLines:colors"} <= e["static"]
    temporal(entities, "/world/frames/target_run1", "Transform3D:translation")
    assert "Transform3D:scale" in entities["/world/frames/north_up"]["static"]
    temporal(entities, "/sensor/mode", "StateChange:state")
    assert "StateConfiguration:values" in entities["/sensor/mode"]["static"]
    temporal(entities, "/sensor/active", "Scalars:scalars")
    temporal(entities, "/sensor/events", "TextLog:text")
    assert "TextDocument:text" in entities["/config"]["static"]
    assert not any(p.startswith(("/world/run0", "/errors/run0")) for p in entities), "run 0 was not asked for"


def test_estimated_target_is_ownship_plus_relative_estimate(chunks, case):
    own = case["truth"].labels["ownship"][1, :, 0, :2]
    for key, est in case["estimates"].items():
        got = rows(chunks, f"/world/run1/{key}/estimate", "Points2D:positions")
        for k in (0, 17, 45, K - 1):
            np.testing.assert_allclose(got[k][0], own[k] + est.state[1, k, :2], rtol=1e-6, atol=1e-3)
    # and the true target is own-ship + relative truth
    target = rows(chunks, "/world/run1/target", "Points2D:positions")
    rel = case["truth"].state[1, :, 0, :2]
    np.testing.assert_allclose(np.asarray([target[k][0] for k in range(K)]), own + rel, rtol=1e-6, atol=1e-3)


def test_bearing_lines_only_when_passive_and_fixes_only_when_active(chunks, case):
    active, det = case["active"], case["det"]
    assert active[:15].all() and not active[15:30].any() and active[30:40].all() and not active[40:].any()
    own = case["truth"].labels["ownship"][1, :, 0, :2]
    lines = rows(chunks, "/world/run1/measurements/bearing", "LineStrips2D:strips")
    fixes = rows(chunks, "/world/run1/measurements/fix", "Points2D:positions")
    with_line = {k for k, v in lines.items() if v}
    with_fix = {k for k, v in fixes.items() if v}
    assert with_line == set(np.nonzero(~active)[0].tolist())
    assert with_fix == set(np.nonzero(active)[0].tolist())
    # the other mode's first scan clears them
    assert {k for k, v in lines.items() if not v} == {30}
    assert {k for k, v in fixes.items() if not v} == {15, 40}
    beta, r = det.z[1, 20, 0]
    line = np.asarray(lines[20][0])
    np.testing.assert_allclose(line[0], own[20], atol=1e-3)
    d = line[1] - line[0]
    assert np.arctan2(d[0], d[1]) == pytest.approx(beta, abs=1e-6)
    assert np.hypot(*d) == pytest.approx(1.2 * np.hypot(*case["truth"].state[1, 20, 0, :2]), rel=1e-6)
    beta, r = det.z[1, 33, 0]
    np.testing.assert_allclose(fixes[33][0], own[33] + r * np.array([np.sin(beta), np.cos(beta)]), atol=1e-2)


def test_mode_series_matches_the_schedule(chunks, case):
    active = case["active"]
    scalar = rows(chunks, "/sensor/active", "Scalars:scalars")
    assert [scalar[k][0] for k in range(K)] == active.astype(float).tolist()
    states = rows(chunks, "/sensor/mode", "StateChange:state")
    assert {k: v[0] for k, v in states.items()} == {0: "active", 15: "passive", 30: "active", 40: "passive"}
    text = rows(chunks, "/sensor/events", "TextLog:text")
    assert sorted(text) == [0, 15, 30, 40] and text[15][0].startswith("passive") and text[30][0].startswith("active")


def test_covariance_ellipses_decimated_and_2_sigma(chunks, case):
    own = case["truth"].labels["ownship"][1, :, 0, :2]
    est = case["estimates"]["kf_mgekf"]
    strips = rows(chunks, "/world/run1/kf_mgekf/covariance", "LineStrips2D:strips")
    assert sorted(strips) == [0, 10, 15, 20, 30, 40, 50, K - 1]        # every 10th, each switch, the last
    k = 20
    ellipse = np.asarray(strips[k][0])
    m, P = own[k] + est.state[1, k, :2], est.covariance[1, k, :2, :2]
    d = ellipse - m
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, np.linalg.inv(P), d), 4.0, rtol=2e-3)


def test_errors_are_estimate_minus_truth(chunks, case):
    est = case["estimates"]["only_mgekf"]
    truth = case["truth"].state[1, :, 0]
    for i, axis in enumerate(("x", "y")):
        got = rows(chunks, f"/errors/run1/{axis}/only_mgekf", "Scalars:scalars")
        for k in (1, 25, 50):
            assert got[k][0] == pytest.approx(est.state[1, k, i] - truth[k, i], rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("bad", [[2], [-1], [0, 0]])
def test_bad_record_runs_raise(case, tmp_path, bad):
    with pytest.raises(ValueError, match=r"record\.runs"):
        _write(case, tmp_path / "bad.rrd", record_runs=bad)
    assert not any(tmp_path.iterdir()), "nothing may be written for a bad request"


def test_truth_without_ownship_raises(case, tmp_path):
    t = case["truth"]
    with pytest.raises(ValueError, match="ownship"):
        _write(case, tmp_path / "bad.rrd", truth=Truth(t.time, t.state, t.state_names, {}))
    assert not any(tmp_path.iterdir())


# ---- issue 19: what the viewer shows (the blueprint and the data, without pixels) ---------------
from tests.helpers.recording_checks import (blueprint, recording_variants, write_recording,  # noqa: E402,F401
                                            test_every_title_fits_its_view, test_no_viewer_warning_while_writing_quiet,
                                            test_plots_have_no_legend_and_the_key_names_the_variants,
                                            test_tracks_are_drawn_up_to_now)
from tests.helpers.rrd_reading import blueprint_views  # noqa: E402


def test_sonar_mode_timeline_has_short_labels_and_room(blueprint, chunks):
    views = list(blueprint_views(blueprint))
    timeline = [v for v, _, _ in views if v.class_identifier == "StateTimeline"]
    assert [str(v.origin) for v in timeline] == ["/sensor/mode"]
    labels = next(df for p, static, _, df in chunks if p == "/sensor/mode" and static)["StateConfiguration:labels"]
    assert labels.explode().to_list() == ["active", "passive"]         # they fit a 500 s band of a 10 000 s run
    root = blueprint.root_container
    shares = list(root.row_shares)
    row = next(i for i, item in enumerate(root.contents) if getattr(item, "class_identifier", "") == "StateTimeline")
    assert shares[row] / sum(shares) * 835 >= 95, "one lane of a state timeline needs ~95 px"


def test_covariance_ellipse_in_the_target_centred_views(blueprint):
    """The ellipses are in each target-centred view and drawn above the bearing lines and tracks
    (in passive phases they are needles along the bearing and hid under them)."""
    centred = [v for v, _, _ in blueprint_views(blueprint) if v.class_identifier == "2D"
               and "target_run" in str(v.properties.get("SpatialInformation"))]
    assert len(centred) == len(VARIANTS)
    for view, key in zip(centred, VARIANTS):
        assert f"/world/run1/{key}/**" in [str(c) for c in view.contents]
