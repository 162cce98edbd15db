"""The stage cache cannot serve results of code that has changed (pipeline.storage.fingerprint).

Reported: a filter in the user's own package (``mytrack/cv.py``, named by ``_target_``) was
edited to add 100 m to every state; the re-run logged ``reused cached ...`` and printed the old
RMSE, because the fingerprint was a hand-kept list of this project's files.
"""

from __future__ import annotations

import ast
import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest

from pipeline.storage import fingerprint
from pipeline.storage import keys, store
from tests.helpers.processes import run_pipeline

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
    return run_pipeline("experiment=ao_vsimm_s1", "mc.runs=3", "scenario.steps=40", "record.enabled=false",
                        "+filters.cv={_target_: mytrack.cv.CV, name: CV}", "variants=[fsimm,cv]",
                        "plugins.packages=[mytrack]", artifacts=tmp_path / "artifacts", cwd=tmp_path, paths=[user],
                        timeout=180)


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
    """The scenarios and sensors import pipeline.run.seeding, checks and data; the filters' helpers."""
    scenario = fingerprint.closure_modules(["pipeline.studies.sonar.scenario"])
    assert {"pipeline.run.checks", "pipeline.data"} <= set(scenario)
    sensor = fingerprint.closure_modules(["pipeline.sensors"])
    assert "pipeline.run.seeding" in sensor
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
    that never calls the function must not pay its imports (pipeline.evaluation.kernels would bring numba)."""
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
    key = keys.stage_key("track", node, ("abc",))
    assert key == keys.stage_key("track", node, ("abc",))
    real = fingerprint._version_of
    monkeypatch.setattr(fingerprint, "_version_of", lambda top: "numpy==0.0" if top == "numpy" else real(top))
    assert keys.stage_key("track", node, ("abc",)) != key      # another numpy: recompute


def _kept_record(module_file: Path) -> Path:
    return fingerprint._kept_path(str(module_file), ".imports.json")


@pytest.fixture
def fresh_caches(monkeypatch):
    """Each test's own ``mytrack`` (under its tmp_path): the per-process caches of locations and
    parses, and the package an earlier test's ``find_spec`` imported, would point at an earlier test's."""
    for name in [m for m in sys.modules if m == "mytrack" or m.startswith("mytrack.")]:
        monkeypatch.delitem(sys.modules, name)
    fingerprint._location.cache_clear()
    fingerprint._parsed.cache_clear()
    yield
    fingerprint._location.cache_clear()
    fingerprint._parsed.cache_clear()


def test_a_fresh_process_reads_the_kept_imports_instead_of_parsing(tmp_path, monkeypatch, fresh_caches):
    """A file's imports are kept beside its bytecode under its content hash; the next process (a
    cleared cache here) takes them from there without parsing, and finds the same closure."""
    write_package(tmp_path, 0.0)
    monkeypatch.syspath_prepend(str(tmp_path))
    fingerprint._parsed.cache_clear()
    closure = fingerprint.closure_modules(["mytrack.cv"])
    before = fingerprint.source_fingerprint(["mytrack.cv"])
    record = _kept_record(tmp_path / "mytrack" / "cv.py")
    assert record.parent == tmp_path / "mytrack" / "__pycache__" and record.is_file()
    kept = json.loads(record.read_text())
    assert ["filters.kalman", 0] in kept["imports"] and ["tuning", 1] in kept["imports"]

    fingerprint._parsed.cache_clear()
    monkeypatch.setattr(fingerprint.ast, "parse", lambda *a, **k: pytest.fail("parsed a file whose imports are kept"))
    assert fingerprint.closure_modules(["mytrack.cv"]) == closure
    assert fingerprint.source_fingerprint(["mytrack.cv"]) == before


def test_kept_imports_of_other_content_or_unreadable_are_not_trusted(tmp_path, monkeypatch, fresh_caches):
    """An edit that adds an import is followed although the kept record (of the old content) does
    not have it; a corrupt record is parsed over and replaced; an unwritable place only costs a parse."""
    write_package(tmp_path, 0.0)
    monkeypatch.syspath_prepend(str(tmp_path))
    fingerprint._parsed.cache_clear()
    assert "mytrack.extra" not in fingerprint.closure_modules(["mytrack.cv"])
    (tmp_path / "mytrack" / "extra.py").write_text("VALUE = 1\n")
    tuning = tmp_path / "mytrack" / "tuning.py"
    tuning.write_text("from . import extra\nPOSITION_OFFSET = 0.0\nACCELERATION_STD = 20.0\n")
    fingerprint._parsed.cache_clear()
    assert "mytrack.extra" in fingerprint.closure_modules(["mytrack.cv"])

    record = _kept_record(tuning)
    record.write_text('{"format": 1, "sha256": ')                  # a torn write
    fingerprint._parsed.cache_clear()
    assert "mytrack.extra" in fingerprint.closure_modules(["mytrack.cv"])
    assert json.loads(record.read_text())["sha256"] == hashlib.sha256(tuning.read_bytes()).hexdigest()

    blocked = tmp_path / "not_a_folder"
    blocked.write_text("")
    monkeypatch.setattr(fingerprint, "_kept_path", lambda path, suffix: blocked / f"x{suffix}")
    fingerprint._parsed.cache_clear()
    assert "mytrack.extra" in fingerprint.closure_modules(["mytrack.cv"])
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]       # no temp file left


def test_kept_imports_follow_the_bytecode_prefix(tmp_path, monkeypatch, fresh_caches):
    """``sys.pycache_prefix`` (PYTHONPYCACHEPREFIX) moves the records with the bytecode, out of the source tree."""
    write_package(tmp_path / "src", 0.0)
    monkeypatch.syspath_prepend(str(tmp_path / "src"))
    monkeypatch.setattr(sys, "pycache_prefix", str(tmp_path / "prefix"))
    fingerprint._parsed.cache_clear()
    fingerprint.closure_modules(["mytrack.cv"])
    assert list((tmp_path / "prefix").glob("**/cv.*imports.json"))
    assert not (tmp_path / "src" / "mytrack" / "__pycache__").exists()


def test_the_map_of_installed_distributions_is_kept_until_what_is_installed_changes(tmp_path, monkeypatch):
    """A fresh process takes the import-name -> distribution map from its record; installing a
    distribution (a new ``*.dist-info`` on sys.path) makes it read the metadata again."""
    monkeypatch.setattr(fingerprint, "_kept_path", lambda path, suffix: tmp_path / f"kept{suffix}")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    (tmp_path / "site").mkdir()
    fingerprint._distributions.cache_clear()
    real = fingerprint._distributions()
    assert "numpy" in real["numpy"]
    calls = []
    monkeypatch.setattr(fingerprint.importlib.metadata, "packages_distributions",
                        lambda: calls.append(1) or {"numpy": ["numpy"], "newpkg": ["newpkg"]})
    try:
        fingerprint._distributions.cache_clear()
        assert fingerprint._distributions() == real and not calls       # read from the record
        (tmp_path / "site" / "newpkg-1.0.dist-info").mkdir()              # 'pip install newpkg'
        fingerprint._distributions.cache_clear()
        assert fingerprint._distributions()["newpkg"] == ["newpkg"] and calls == [1]
    finally:
        fingerprint._distributions.cache_clear()


def test_a_compiled_kernel_module_imports_nothing_of_the_project():
    """numba's cache (cache=True) re-validates a compiled function by its own file only (numba issue
    #1833): a kernel that called a compiled function, or read a constant, from another project
    module kept running the old code after that module was edited (found when kalman_kernel's
    positive-definite check reached the CV/CT IMM loop, then in its own module, only after its
    cache was cleared), while the stage key, which follows the imports, recomputed with it."""
    kernels = sorted((ROOT / "filters").glob("*/kernel.py")) + [ROOT / "pipeline" / "evaluation" / "kernels.py"]
    assert len(kernels) >= 7
    for path in kernels:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
                assert node.level == 0, f"{path.name}: relative import"
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            for name in names:
                top = name.partition(".")[0]
                assert top in ("__future__", "math", "numpy", "numba", "llvmlite"), f"{path.name} imports {name}"
