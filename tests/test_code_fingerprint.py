"""The stage cache cannot serve results of code that has changed (pipeline.fingerprint).

Reported: a filter in the user's own package (``mytrack/cv.py``, named by ``_target_``) was
edited to add 100 m to every state; the re-run logged ``reused cached ...`` and printed the old
RMSE, because the fingerprint was a hand-kept list of this project's files.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import polars as pl

from pipeline import fingerprint, store

ROOT = Path(__file__).resolve().parents[1]

USER_FILTER = '''
"""A user's constant-velocity Kalman filter on 2-D position measurements (state x, vx, y, vy)."""
import time

import numpy as np

from filters.base import TrackEstimate
from filters.kalman import kalman_filter
from filters.models import constant_velocity_transition, position_measurement_matrix

from .tuning import POSITION_OFFSET, ACCELERATION_STD


class CV:
    def __init__(self, name: str = "CV"):
        self.name = name

    def run(self, measurements):
        started = time.perf_counter()
        dt = float(measurements.time[1] - measurements.time[0])
        F = constant_velocity_transition(dt)
        G = np.kron(np.eye(2), np.array([[dt * dt / 2], [dt]]))
        Q = ACCELERATION_STD**2 * G @ G.T
        H = position_measurement_matrix()
        R = np.asarray(measurements.noise_covariance)
        z = measurements.z
        x0 = np.zeros((z.shape[0], 4))
        x0[:, 0::2] = z[:, 0]
        P0 = np.broadcast_to(np.kron(R, np.diag([1.0, 0.0])) + np.kron(np.eye(2), np.diag([0.0, 400.0**2])),
                             (z.shape[0], 4, 4)).copy()
        state, covariance = kalman_filter(z, x0, P0, F, Q, H, R)
        state[..., 0::2] += POSITION_OFFSET
        return TrackEstimate(measurements.time, state, covariance, {}, time.perf_counter() - started)
'''


def write_package(where: Path, offset: float) -> None:
    package = where / "mytrack"
    package.mkdir(parents=True, exist_ok=True)
    (package / "__init__.py").write_text("")
    (package / "cv.py").write_text(USER_FILTER)
    (package / "tuning.py").write_text(f"POSITION_OFFSET = {offset!r}\nACCELERATION_STD = 20.0\n")


def run_cli(tmp_path: Path, user: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONPATH": f"{user}{os.pathsep}{ROOT}"}
    return subprocess.run([sys.executable, "-m", "pipeline", f"paths.artifacts={tmp_path / 'artifacts'}",
                           "experiment=ao_vsimm_s1", "mc.runs=3", "scenario.steps=40", "record.enabled=false",
                           "+filters.cv={_target_: mytrack.cv.CV, name: CV}", "variants=[fsimm,cv]",
                           "plugins.packages=[mytrack]"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=180, env=env)


def cv_position_rmse(tmp_path: Path) -> float:
    newest = max((tmp_path / "artifacts" / "runs" / "ao_vsimm_s1").iterdir())
    summary = pl.read_parquet(newest / "summary.parquet")
    row = summary.filter((pl.col("variant_key") == "cv") & (pl.col("series") == "position_rmse")
                         & (pl.col("window") == "all"))
    return float(row["value"][0])


def test_editing_a_users_filter_package_recomputes_its_track_stage(tmp_path):
    user = tmp_path / "user"
    write_package(user, 0.0)
    first = run_cli(tmp_path, user)
    assert first.returncode == 0, first.stderr
    assert re.search(r"\[track\] computed CV", first.stderr), first.stderr
    before = cv_position_rmse(tmp_path)

    unchanged = run_cli(tmp_path, user)                     # nothing edited: everything is reused
    assert unchanged.returncode == 0, unchanged.stderr
    assert "[track] reused cached" in unchanged.stderr and "[track] computed" not in unchanged.stderr

    # the edit is in a module the filter imports, not in the module _target_ names
    (user / "mytrack" / "tuning.py").write_text("POSITION_OFFSET = 100.0\nACCELERATION_STD = 20.0\n")
    edited = run_cli(tmp_path, user)
    assert edited.returncode == 0, edited.stderr
    assert re.search(r"\[track\] computed CV", edited.stderr), edited.stderr
    assert re.search(r"\[track\] reused cached \S+ \(key \w+\) FSIMM", edited.stderr), edited.stderr
    assert "[scenario] reused cached" in edited.stderr and "[measure] reused cached" in edited.stderr
    after = cv_position_rmse(tmp_path)
    assert after > before + 50.0, (before, after)          # 100 m on both axes: the new code's numbers


def test_the_closure_follows_imports_the_old_list_missed():
    """The scenarios and sensors import pipeline.seeding, checks and data; the filters' helpers."""
    scenario = fingerprint.closure_modules(["pipeline.studies.sonar.scenario"])
    assert {"pipeline.checks", "pipeline.data"} <= set(scenario)
    sensor = fingerprint.closure_modules(["pipeline.studies.mie_los.sensor"])
    assert "pipeline.seeding" in sensor
    mie = fingerprint.closure_modules(["filters.input_estimation"])
    assert {"filters.kalman", "filters.coordinates", "filters.models", "filters.base"} <= set(mie)
    assert not any(m.startswith(("numpy", "scipy", "polars")) for m in mie)


def test_relative_imports_and_edits_change_the_fingerprint(tmp_path, monkeypatch):
    write_package(tmp_path, 0.0)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert {"mytrack", "mytrack.cv", "mytrack.tuning", "filters.kalman"} <= set(
        fingerprint.closure_modules(["mytrack.cv"]))
    before = fingerprint.source_fingerprint(["mytrack.cv"])
    assert fingerprint.source_fingerprint(["mytrack.cv"]) == before
    (tmp_path / "mytrack" / "tuning.py").write_text("POSITION_OFFSET = 0.0\nACCELERATION_STD = 21.0\n")
    assert fingerprint.source_fingerprint(["mytrack.cv"]) != before


def test_fingerprinting_imports_nothing_a_function_imports_lazily(tmp_path, monkeypatch):
    """A module's ``from pkg.module import name`` inside a function is followed (module's source is
    hashed and its edits change the key) without importing the module: the stage key of a job
    that never calls the function must not pay its imports (pipeline.kernels would bring numba)."""
    package = tmp_path / "lazyuser"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "front.py").write_text("def run():\n    from lazyuser.heavy import compute\n    return compute()\n")
    (package / "heavy.py").write_text("raise RuntimeError('imported by the fingerprint')\ndef compute():\n    return 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "lazyuser.heavy" in fingerprint.closure_modules(["lazyuser.front"])
    before = fingerprint.source_fingerprint(["lazyuser.front"])
    assert "lazyuser.heavy" not in sys.modules
    (package / "heavy.py").write_text("raise RuntimeError('imported by the fingerprint')\ndef compute():\n    return 2\n")
    fingerprint._location.cache_clear()
    assert fingerprint.source_fingerprint(["lazyuser.front"]) != before


def test_a_stage_key_covers_every_target_in_its_config_and_the_library_versions(monkeypatch):
    node = {"_target_": "filters.imm.FSIMM", "models": {"_target_": "filters.models.AccelerationModelSet.from_config"}}
    assert fingerprint.producers(node) == ["filters.imm", "filters.models"]
    key = store.stage_key("track", node, ("abc",))
    assert key == store.stage_key("track", node, ("abc",))
    real = fingerprint._version_of
    monkeypatch.setattr(fingerprint, "_version_of", lambda top: "numpy==0.0" if top == "numpy" else real(top))
    assert store.stage_key("track", node, ("abc",)) != key      # another numpy: recompute
