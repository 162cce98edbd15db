"""tools/new_study.py (issue 39, "a contract a researcher can fill in"): the scaffold writes a study
package outside the project that runs through every stage and the report unchanged."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import polars as pl
import pytest

from tests.helpers.processes import ROOT, run_module, run_pipeline

sys.path.insert(0, str(ROOT / "tools"))
new_study = importlib.import_module("new_study")


def test_the_scaffold_writes_a_package_and_the_five_config_groups(tmp_path):
    files = new_study.write("my_study", tmp_path)
    names = sorted(str(f.relative_to(tmp_path)) for f in files)
    assert names == ["my_study/__init__.py", "my_study/conf/experiment/my_study.yaml",
                     "my_study/conf/metrics/my_study.yaml", "my_study/conf/report/my_study.yaml",
                     "my_study/conf/scenario/my_study.yaml", "my_study/conf/sensors/my_study.yaml",
                     "my_study/scenario.py", "my_study/sensor.py"]
    for f in files:                                         # every template was filled in
        assert "{name}" not in f.read_text() and "{{" not in f.read_text()


def test_the_scaffolded_scenario_and_sensor_keep_the_contract(tmp_path, monkeypatch):
    new_study.write("shaped_study", tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    scenario = importlib.import_module("shaped_study.scenario").ConstantVelocityScenario(
        [0.0, 100.0, 0.0, 50.0], steps=10, acceleration_std=0.0)
    truth = scenario.generate(3, seed=1)
    assert truth.state.shape == (3, 11, 1, 4) and truth.state_names == ("x", "vx", "y", "vy")
    # no acceleration noise: the hand-worked straight line x = 100 t, y = 50 t
    assert truth.state[1, 10, 0].tolist() == pytest.approx([1000.0, 100.0, 500.0, 50.0])
    # run r's randomness does not depend on how many runs there are
    noisy = type(scenario)([0.0, 100.0, 0.0, 50.0], steps=10, acceleration_std=1.0)
    assert (noisy.generate(2, seed=4).state == noisy.generate(5, seed=4).state[:2]).all()
    sensor = importlib.import_module("shaped_study.sensor").NoisyPositions(noise_std=20.0)
    detections = sensor.measure(truth, seed=1)
    assert detections.z.shape == (3, 11, 1, 2) and sensor.produces == "position_xy"
    assert abs(float((detections.z - truth.state[..., [0, 2]]).std()) - 20.0) < 5.0


@pytest.mark.parametrize("name, says", [
    ("My-Study", "is not allowed"), ("class", "is not allowed"), ("", "is not allowed"),
    ("numpy", "already an importable package"), ("pipeline", "already an importable package"),
])
def test_a_name_that_cannot_be_a_study_package_is_refused_and_nothing_written(tmp_path, name, says):
    proc = run_module("new_study", name, "--into", str(tmp_path), cwd=tmp_path, paths=[ROOT / "tools"])
    assert proc.returncode == 2 and says in proc.stderr and "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_is_never_overwritten(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("my notes")
    proc = run_module("new_study", "mine", "--into", str(tmp_path), cwd=tmp_path, paths=[ROOT / "tools"])
    assert proc.returncode == 2 and "already exists" in proc.stderr
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]


@pytest.mark.full
def test_the_scaffolded_study_runs_every_stage_and_its_report_target_passes(tmp_path):
    made = run_module("new_study", "my_study", "--into", str(tmp_path), cwd=tmp_path, paths=[ROOT / "tools"])
    assert made.returncode == 0, made.stderr
    command = made.stdout.splitlines()[-1].split()            # the line the scaffold prints
    assert command[:3] == ["python", "-m", "pipeline"]
    args = [a.strip("'") for a in command[3:]]
    proc = run_pipeline(*args, "mc.runs=4", "record.enabled=false", artifacts=tmp_path / "artifacts",
                        cwd=tmp_path, paths=[tmp_path], timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    [run] = (tmp_path / "artifacts" / "runs" / "my_study").iterdir()
    summary = pl.read_parquet(run / "summary.parquet")
    assert set(summary["variant"]) == {"KF-CV matched", "IMM-CV/CT"}
    report = run_module("pipeline.report", str(run), "--check", cwd=tmp_path, paths=[tmp_path])
    assert report.returncode == 0 and "1/1 targets pass" in report.stdout + report.stderr, report.stderr[-2000:]
