"""pipeline.studies.sonobuoy.recording: study 004's .rrd has the entity tree, values and blueprint the viewer
layout relies on. A tiny synthetic case (2 runs, 15 scans, a right turn from 30 s, misses and
clutter) from the real scenario and sensor, with hand-made estimates: one particle filter that
kept a cloud for the recorded run, one that did not, and an EKF; read back with
rerun.chunk.RrdReader (no viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from filters.base import TrackEstimate
from pipeline.studies.sonobuoy.recording import BEARING_LINE_SCALE, MODE_COLOURS, nees_band, write_sonobuoy_recording
from pipeline.studies.sonobuoy.scenario import SonobuoyField
from pipeline.studies.sonobuoy.sensor import SonobuoyBearings
from pipeline.evaluation.evaluate import metrics_frame
from pipeline.contract import RecordingInputs
from pipeline.studies.sonobuoy.adapter import MODE_NAMES, SonobuoyStudy
from tests.helpers.rrd_reading import assert_complete_recording, entity_index, read_chunks, rows, temporal

RUNS, RECORD = 2, [1]
K, P = 15, 30
VARIANTS = {"ammpf": "AMMPF", "sir_mm": "SIR-MM", "ekf": "EKF"}
BUOY_XY = [(4 + 4 * i, 5 + 4 * i) for i in range(4)]


def _estimate(truth, rng, offset: float, extras: dict) -> TrackEstimate:
    state = truth.state[:, :, 0] + offset + rng.normal(0.0, 20.0, truth.state[:, :, 0].shape)
    A = rng.normal(0.0, 1.0, (RUNS, K, 20, 20))
    cov = np.einsum("rkij,rklj->rkil", A, A) * 50.0 + np.eye(20) * 400.0         # full, positive definite
    return TrackEstimate(truth.time.copy(), state, cov, extras)


def _modes(rng) -> np.ndarray:
    mu = rng.random((RUNS, K, 3))
    return mu / mu.sum(-1, keepdims=True)


@pytest.fixture(scope="module")
def case():
    truth = SonobuoyField(duration=(K - 1) * 5.0, target_turn_start=30.0).generate(RUNS, 0)
    sensor = SonobuoyBearings(miss_probability=0.2, clutter_probability=0.5)
    det = sensor.measure(truth, seed=4)
    rng = np.random.default_rng(7)
    # the cloud: kept for the recorded run 1 only (NaN rows and modes -1 for run 0), per the contract
    particles = np.full((RUNS, K, P, 20), np.nan, dtype=np.float32)
    particles[1] = truth.state[1, :, 0][:, None] + rng.normal(0.0, 300.0, (K, P, 20))
    particle_modes = np.full((RUNS, K, P), -1, dtype=np.int8)
    particle_modes[1] = rng.integers(0, 3, (K, P))
    estimates = {
        "ammpf": _estimate(truth, rng, 50.0, {"mode_probabilities": _modes(rng), "ess": rng.uniform(10, 30, (RUNS, K)),
                                              "particles": particles, "particle_modes": particle_modes}),
        "sir_mm": _estimate(truth, rng, -80.0, {"mode_probabilities": _modes(rng),
                                                "ess": rng.uniform(10, 30, (RUNS, K))}),
        "ekf": _estimate(truth, rng, 120.0, {}),
    }
    per_variant = {k: (VARIANTS[k], SonobuoyStudy().per_step_metrics(truth, est, sensor)) for k, est in estimates.items()}
    metrics = metrics_frame(truth.time, per_variant, RUNS)
    return dict(truth=truth, det=det, sensor=sensor, estimates=estimates, metrics=metrics)


def _write(case, path: Path, record_runs=RECORD, estimates=None, **kwargs) -> None:
    # through the study adapter, as the runner calls it
    SonobuoyStudy().record(path, RecordingInputs(
        experiment="sonobuoy tiny", truth=case["truth"], detections=case["det"],
        estimates=estimates or case["estimates"], display_names=VARIANTS, metrics=case["metrics"],
        record_runs=record_runs, sensor=case["sensor"], estimators={}, track_input=None, seed=0,
        config_text="study: 004\n", description="A tiny study 004 for the test.", options=kwargs))


@pytest.fixture(scope="module")
def rrd(case, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "sonobuoy.rrd"
    _write(case, path)
    return path


@pytest.fixture(scope="module")
def chunks(rrd):
    return read_chunks(rrd)


@pytest.fixture(scope="module")
def entities(chunks):
    return entity_index(chunks)


def _texts(chunks, entity: str) -> list[str]:
    """Every TextLog body on ``entity`` (several rows may share a step)."""
    return [str(t) for path, static, _, df in chunks if path == entity and "TextLog:text" in df.columns
            for row in df["TextLog:text"].to_list() for t in row]


def _static(chunks, entity: str, column: str):
    for path, static, _, df in chunks:
        if path == entity and static and column in df.columns and df[column][0] is not None:
            return df[column][-1]
    raise AssertionError(f"{entity}: no static {column}")


def _rgba(packed: int) -> tuple[int, int, int, int]:
    return tuple(int(packed) >> s & 0xFF for s in (24, 16, 8, 0))


def test_file_is_complete_and_atomic(rrd):
    assert_complete_recording(rrd, "sonobuoy_tiny")


def test_entity_tree(entities):
    assert "Points2D:positions" in entities["/world/observer"]["static"]
    for name in ["truth"] + [f"buoys/{i}" for i in range(1, 5)]:
        e = temporal(entities, f"/world/run1/{name}", "Points2D:positions")
        assert "LineStrips2D:strips" in e["static"] and e["rows"] == K      # the whole track faint
        assert temporal(entities, f"/world/run1/{name}/path", "LineStrips2D:strips")["rows"] == K - 1
    for family in ("target", "buoys"):
        for kind in ("nominal", "clutter"):
            assert temporal(entities, f"/world/run1/bearings/{family}/{kind}", "LineStrips2D:strips")["rows"] == K
    for key in VARIANTS:
        base = f"/world/run1/{key}"
        assert temporal(entities, f"{base}/track", "LineStrips2D:strips")["rows"] == K - 1
        assert temporal(entities, f"{base}/buoys/track", "LineStrips2D:strips")["rows"] == K - 1
        assert temporal(entities, f"{base}/estimate", "Points2D:positions")["rows"] == K
        temporal(entities, f"{base}/covariance", "LineStrips2D:strips")
        temporal(entities, f"{base}/buoys", "Points2D:positions")
        temporal(entities, f"{base}/buoys/covariance", "LineStrips2D:strips")
        for metric in ("position_rmse", "position_median_error", "buoy_position_rmse", "nees_position"):
            e = temporal(entities, f"/metrics/{metric}/{key}", "Scalars:scalars")
            assert {"SeriesLines:names", "SeriesLines:colors"} <= e["static"]
    for key in ("ammpf", "sir_mm"):
        for mode in MODE_NAMES:
            temporal(entities, f"/variants/{key}/run1/mode_probability/{mode}", "Scalars:scalars")
            temporal(entities, f"/metrics/mode_probability_{mode}/{key}", "Scalars:scalars")
        temporal(entities, f"/variants/{key}/run1/ess", "Scalars:scalars")
        temporal(entities, f"/metrics/ess/{key}", "Scalars:scalars")
    assert not any(p.startswith("/variants/ekf") for p in entities), "the EKF has no mode probabilities"
    temporal(entities, "/truth/run1/turning", "Scalars:scalars")
    for side in ("lower", "upper"):
        temporal(entities, f"/reference/nees_position/{side}", "Scalars:scalars")
    temporal(entities, "/notes", "TextLog:text")
    assert "TextDocument:text" in entities["/config"]["static"]
    assert "Transform3D:scale" in entities["/world/frames/north_up"]["static"]
    assert not any("run0" in p for p in entities), "run 0 was not asked for"


def test_particle_cloud_only_where_kept(entities, chunks, case):
    clouds = sorted(p for p in entities if "/particles" in p)
    assert clouds == ["/world/run1/ammpf/particles", "/world/run1/ammpf/particles/buoys"]
    est = case["estimates"]["ammpf"]
    X, modes = est.extras["particles"][1], est.extras["particle_modes"][1]
    positions = rows(chunks, "/world/run1/ammpf/particles", "Points2D:positions")
    colours = rows(chunks, "/world/run1/ammpf/particles", "Points2D:colors")
    assert sorted(positions) == list(range(K))
    for k in (0, 7, K - 1):
        np.testing.assert_allclose(np.asarray(positions[k]), X[k, :, :2], rtol=1e-6)
        assert [_rgba(c)[:3] for c in colours[k]] == [MODE_COLOURS[MODE_NAMES[m]] for m in modes[k]]
    buoys = rows(chunks, "/world/run1/ammpf/particles/buoys", "Points2D:positions")
    np.testing.assert_allclose(np.asarray(buoys[5]), X[5][:, np.array(BUOY_XY)].reshape(-1, 2), rtol=1e-6)
    text = "\n".join(_texts(chunks, "/notes"))
    assert "SIR-MM: no particle cloud drawn" in text and "EKF: no particle cloud (not a particle filter)" in text
    assert "AMMPF" not in text


def test_bearing_lines_nominal_and_clutter_apart(chunks, case):
    det, truth = case["det"], case["truth"]
    ok = det.detected[1] & np.isfinite(det.z[1, ..., 0])
    clutter = det.target[1] == -1
    observer = case["sensor"].observer_position
    true = truth.state[1, :, 0]
    counts = {}
    for family, slots in (("target", range(0, 4)), ("buoys", range(4, 8))):
        for kind, mask in (("nominal", ok & ~clutter), ("clutter", ok & clutter)):
            entity = f"/world/run1/bearings/{family}/{kind}"
            lines = rows(chunks, entity, "LineStrips2D:strips")
            assert sorted(lines) == list(range(K)), "a row at every scan (clears the previous scan's lines)"
            assert len(lines[0]) == 0, "scan 0 has no measurement"
            for k in range(K):
                wanted = [s for s in slots if mask[k, s]]
                assert len(lines[k]) == len(wanted), (entity, k)
                for line, s in zip(lines[k], wanted):
                    line = np.asarray(line)
                    i = s % 4
                    start = true[k, BUOY_XY[i]] if family == "target" else observer
                    end = true[k, :2] if family == "target" else true[k, BUOY_XY[i]]
                    np.testing.assert_allclose(line[0], start, atol=1e-2)
                    d = line[1] - line[0]
                    assert np.arctan2(d[0], d[1]) == pytest.approx(det.z[1, k, s, 0], abs=1e-5)
                    assert np.hypot(*d) == pytest.approx(BEARING_LINE_SCALE * np.hypot(*(end - start)), rel=1e-5)
            counts[family, kind] = sum(len(v) for v in lines.values())
    assert all(counts.values()), f"the case needs nominal and clutter returns of both kinds: {counts}"
    colour = {kind: _rgba(_static(chunks, f"/world/run1/bearings/target/{kind}", "LineStrips2D:colors")[0])
              for kind in ("nominal", "clutter")}
    assert colour["nominal"] != colour["clutter"]
    assert colour["clutter"][0] > colour["clutter"][1], "clutter lines are red"
    assert _static(chunks, "/world/run1/bearings/buoys/clutter", "LineStrips2D:colors")[0] == \
        _static(chunks, "/world/run1/bearings/target/clutter", "LineStrips2D:colors")[0]


def test_estimates_and_two_sigma_ellipses(chunks, case):
    est = case["estimates"]["sir_mm"]
    got = rows(chunks, "/world/run1/sir_mm/estimate", "Points2D:positions")
    np.testing.assert_allclose(np.asarray([got[k][0] for k in range(K)]), est.state[1, :, :2], rtol=1e-6)
    k = 9
    ellipse = np.asarray(rows(chunks, "/world/run1/sir_mm/covariance", "LineStrips2D:strips")[k][0])
    d = ellipse - est.state[1, k, :2]
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, np.linalg.inv(est.covariance[1, k, :2, :2]), d), 4.0,
                               rtol=2e-3)
    buoys = np.asarray(rows(chunks, "/world/run1/sir_mm/buoys", "Points2D:positions")[k])
    np.testing.assert_allclose(buoys, est.state[1, k][np.array(BUOY_XY)], rtol=1e-6)
    ellipses = rows(chunks, "/world/run1/sir_mm/buoys/covariance", "LineStrips2D:strips")[k]
    assert len(ellipses) == 4
    for i, (a, b) in enumerate(BUOY_XY):
        d = np.asarray(ellipses[i]) - est.state[1, k, [a, b]]
        Pb = est.covariance[1, k][np.ix_([a, b], [a, b])]
        np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, np.linalg.inv(Pb), d), 4.0, rtol=2e-3)


def test_mode_probability_series(chunks, case):
    for key in ("ammpf", "sir_mm"):
        mu = case["estimates"][key].extras["mode_probabilities"]
        for m, mode in enumerate(MODE_NAMES):
            run = rows(chunks, f"/variants/{key}/run1/mode_probability/{mode}", "Scalars:scalars")
            np.testing.assert_allclose([run[k][0] for k in range(K)], mu[1, :, m], rtol=1e-12)
            mean = rows(chunks, f"/metrics/mode_probability_{mode}/{key}", "Scalars:scalars")
            np.testing.assert_allclose([mean[k][0] for k in range(K)], mu[:, :, m].mean(0), rtol=1e-12)
            # the Monte Carlo mean in the mode's colour, the run lighter
            assert _rgba(_static(chunks, f"/metrics/mode_probability_{mode}/{key}", "SeriesLines:colors")[0])[:3] == \
                MODE_COLOURS[mode]
    turning = rows(chunks, "/truth/run1/turning", "Scalars:scalars")
    expected = (case["truth"].labels["turn_mode"][1, :, 0] == 3).astype(float)
    assert [turning[k][0] for k in range(K)] == expected.tolist() and 0 < expected.sum() < K


def test_nees_band(chunks):
    # scipy.stats.chi2.ppf([0.025, 0.975], 2 R) / R
    assert nees_band(1) == pytest.approx((0.0506356160, 7.3777589082), rel=1e-8)
    assert nees_band(100) == pytest.approx((1.6272798250, 2.4105789551), rel=1e-8)
    lo, hi = nees_band(RUNS)
    assert (lo, hi) == pytest.approx((0.2422092785, 5.5716433909), rel=1e-8)
    assert rows(chunks, "/reference/nees_position/lower", "Scalars:scalars")[3][0] == pytest.approx(lo)
    assert rows(chunks, "/reference/nees_position/upper", "Scalars:scalars")[3][0] == pytest.approx(hi)


def test_cloud_of_the_recorded_runs_only_and_thinned(case, tmp_path):
    """A cloud kept for the recorded runs only (R' = len(record_runs), in that order), more particles
    than drawn: the recording takes max_particles of them, evenly spaced."""
    est = case["estimates"]["ammpf"]
    extras = {**est.extras, "particles": est.extras["particles"][[1]],
              "particle_modes": est.extras["particle_modes"][[1]]}
    estimates = {"ammpf": TrackEstimate(est.time, est.state, est.covariance, extras)}
    path = tmp_path / "thin.rrd"
    write_sonobuoy_recording(path, experiment="thin", truth=case["truth"], detections=case["det"],
                             estimates=estimates, display_names=VARIANTS, metrics=None, record_runs=[1],
                             sensor=case["sensor"], max_particles=10)
    got = rows(read_chunks(path), "/world/run1/ammpf/particles", "Points2D:positions")
    keep = np.linspace(0, P - 1, 10).round().astype(int)
    np.testing.assert_allclose(np.asarray(got[4]), est.extras["particles"][1, 4, keep, :2], rtol=1e-6)


@pytest.mark.parametrize("bad", [[2], [-1], [0, 0]])
def test_bad_record_runs_raise(case, tmp_path, bad):
    with pytest.raises(ValueError, match=r"record\.runs"):
        _write(case, tmp_path / "bad.rrd", record_runs=bad)
    assert not any(tmp_path.iterdir()), "nothing may be written for a bad request"


def test_half_a_cloud_raises(case, tmp_path):
    est = case["estimates"]["ammpf"]
    extras = {k: v for k, v in est.extras.items() if k != "particle_modes"}
    with pytest.raises(ValueError, match="particle_modes"):
        _write(case, tmp_path / "bad.rrd", estimates={"ammpf": TrackEstimate(est.time, est.state, est.covariance,
                                                                             extras)})
    assert not any(tmp_path.iterdir())


def test_no_viewer_warning_while_writing(case, tmp_path, capfd):
    """A blueprint property given without any component (an empty rrb.ScalarAxis() on the RMSE and
    bound view, which a run with the PCRLB metrics gets) made Rerun print an ANSI-coloured 'Dropping
    chunk without components ... /view/<uuid>/ScalarAxis' warning on every sonobuoy run."""
    import polars as pl

    rmse = case["metrics"].filter(pl.col("series") == "position_rmse")
    bounds = [rmse.with_columns(pl.lit(name).alias("series"), pl.lit(name).alias("metric"))
              for name in ("position_bound", "position_rmse_over_bound")]
    _write(dict(case, metrics=pl.concat([case["metrics"], *bounds], how="diagonal_relaxed")), tmp_path / "quiet.rrd")
    err = capfd.readouterr().err
    assert "Dropping chunk" not in err and "WARN" not in err, err


# ---- issue 19: what the viewer shows (the blueprint and the data, without pixels) ---------------
from tests.helpers.recording_checks import (blueprint, recording_variants, write_recording,  # noqa: E402,F401
                                            test_every_title_fits_its_view, test_no_viewer_warning_while_writing_quiet,
                                            test_plots_have_no_legend_and_the_key_names_the_variants,
                                            test_tracks_are_drawn_up_to_now)
from tests.helpers.rrd_reading import blueprint_views  # noqa: E402


def test_mode_probabilities_side_by_side(blueprint):
    modes = [(v, parents) for v, parents, _ in blueprint_views(blueprint) if "P(mode)" in str(v.name)]
    assert [str(v.name).split(":")[0] for v, _ in modes] == ["AMMPF", "SIR-MM"]
    assert all("Tabs" not in [str(p.kind) for p in parents] for _, parents in modes)
    assert len({id(parents[-1]) for _, parents in modes}) == 1
