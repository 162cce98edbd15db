"""pipeline.recording: the .rrd written for an experiment has the entity tree, timelines and
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
from pipeline.recording import recording_id, write_recording
from pipeline.sensors.position import PositionSensor

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
                "metric": metric, "step": np.arange(truth.time.size, dtype=np.int32), "time": truth.time,
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
        assert "LineStrips2D:strips" in truth["static"]
        assert truth["rows"] == K
        assert _time_varying(entities, f"{world}/measurements", "Points2D:positions")["rows"] == K
        for key in VARIANTS:
            assert "LineStrips2D:strips" in entities[f"{world}/{key}/track"]["static"]
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
