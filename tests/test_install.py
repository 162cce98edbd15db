"""Issue 36: the install. No module imports another package's private or vendored internals, every
package the code imports is declared, the locks pin what pyproject.toml allows, a single job does not
depend on what only sweeps use, and each run records the versions it ran with."""

from __future__ import annotations

import ast
import json
import re
import sys
import tomllib
from pathlib import Path

import pytest

from pipeline.run import environment
from tests.helpers.processes import run_code

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [p for d in ("pipeline", "filters", "hydra_plugins", "benchmarks", "tools", "tests")
           for p in sorted((ROOT / d).rglob("*.py"))]
OURS = {"pipeline", "filters", "hydra_plugins", "benchmarks", "tools", "tests"}
# import name -> distribution, where they differ
DISTRIBUTION = {"yaml": "pyyaml", "hydra": "hydra-core", "rerun": "rerun-sdk", "rerun_cli": "rerun-sdk",
                "stonesoup": "stonesoup", "sklearn": "scikit-learn", "mlflow": "mlflow-skinny"}


def _imports(path: Path) -> list[tuple[int, str, str | None]]:
    """``(line, module, name imported from it or None)`` for every absolute import in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: list[tuple[int, str, str | None]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found += [(node.lineno, node.module, alias.name) for alias in node.names]
    return found


def _third_party(module: str) -> bool:
    top = module.split(".", 1)[0]
    return top not in OURS and top not in sys.stdlib_module_names and top != "__future__"


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports(paths: list[Path]) -> list[str]:
    bad = []
    for path in paths:
        for line, module, name in _imports(path):
            if not _third_party(module):
                continue
            parts = module.split(".")[1:] + ([name] if name else [])
            if any(_private(p) for p in parts) or {"externals", "vendor", "_vendor", "vendored"} & set(parts):
                bad.append(f"{path.relative_to(ROOT)}:{line}: {module}{'.' + name if name else ''}")
    return bad


@pytest.mark.smoke
def test_no_module_imports_a_private_or_vendored_module_of_another_package():
    """``joblib.externals.cloudpickle`` went away in joblib 1.6 and took every job down with it; a
    private module (a ``_`` name) or a vendored copy can change in any release."""
    bad = private_imports(SOURCES)
    assert not bad, "private or vendored imports:\n" + "\n".join(bad)


def test_the_private_import_check_finds_what_issue_36_found(tmp_path):
    (tmp_path / "old.py").write_text("from joblib.externals import cloudpickle\nfrom hydra._internal.utils import _locate\n"
                                     "from numba.np.random._constants import fi_float\nimport numpy as np\n"
                                     "from hydra.utils import get_object\nfrom joblib import Parallel\n")
    global ROOT
    saved, ROOT = ROOT, tmp_path
    try:
        assert [b.split(": ", 1)[1] for b in private_imports([tmp_path / "old.py"])] == [
            "joblib.externals.cloudpickle", "hydra._internal.utils._locate", "numba.np.random._constants.fi_float"]
    finally:
        ROOT = saved


def _declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values() for r in extra]
    return {environment.canonical(re.split(r"[\s;<>=!~\[(]", r, maxsplit=1)[0]) for r in names}


@pytest.mark.smoke
def test_every_package_the_code_imports_is_declared():
    declared = _declared()
    missing = []
    for path in SOURCES:
        for line, module, _ in _imports(path):
            if _third_party(module):
                top = module.split(".", 1)[0]
                name = environment.canonical(DISTRIBUTION.get(top, top))
                if name not in declared:
                    missing.append(f"{path.relative_to(ROOT)}:{line}: {top} ({name})")
    assert not missing, "imported but not declared in pyproject.toml:\n" + "\n".join(sorted(set(missing)))


def _requirement_names(extras: tuple[str, ...] = ()) -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = list(project["dependencies"]) + [r for e in extras for r in project["optional-dependencies"][e]]
    return {environment.canonical(re.split(r"[\s;<>=!~\[(]", r, maxsplit=1)[0]) for r in names}


@pytest.mark.smoke
@pytest.mark.parametrize("lock, extras", [("core", ()), ("ci", ("test", "distributed", "tune", "slurm", "stonesoup")),
                                          ("bench", ("bench",)), ("adsb", ("adsb",))])
def test_each_lock_pins_every_requirement_and_agrees_with_the_ci_lock(lock, extras):
    """A lock a README command installs from pins every direct requirement, and a package two locks
    share has one version: the one CI tested (every lock is resolved against lock/ci.txt)."""
    pins = environment.read_lock(ROOT / "lock" / f"{lock}.txt")
    assert not (_requirement_names(extras) - set(pins)), f"lock/{lock}.txt lacks {_requirement_names(extras) - set(pins)}"
    ci = environment.read_lock(ROOT / "lock" / "ci.txt")
    disagree = {n: (v, ci[n]) for n, v in pins.items() if n in ci and v != ci[n]}
    assert not disagree, f"lock/{lock}.txt and lock/ci.txt disagree: {disagree}"


@pytest.mark.smoke
def test_the_readme_commands_install_from_the_locks():
    readme = (ROOT / "README.md").read_text()
    for marker, lock in (("main-command", "lock/core.txt"), ("test-command", "lock/ci.txt")):
        block = readme.split(f"<!-- {marker} -->", 1)[1].split("```", 2)[1]
        assert f"-c {lock}" in block, f"the README's {marker} does not install from {lock}: {block}"


def test_the_lock_reader_and_the_drift_report(tmp_path):
    lock = tmp_path / "lock.txt"
    lock.write_text("# a comment\nNumPy==2.4.6 ; python_full_version < '3.12'  # via scipy\n"
                    "numpy==2.5.5 ; python_full_version >= '3.12'\nPyYAML==6.0.4\n    # via hydra\n")
    pins = environment.read_lock(lock)
    assert pins == {"numpy": {"2.4.6", "2.5.5"}, "pyyaml": {"6.0.4"}}
    assert environment.differences({"numpy": "2.5.5", "pyyaml": "6.0.3", "tqdm": "4.0", "gone": None}, pins) == {
        "pyyaml": {"installed": "6.0.3", "lock": "6.0.4"}, "tqdm": {"installed": "4.0", "lock": None},
        "gone": {"installed": None, "lock": None}}


@pytest.mark.smoke
def test_a_run_records_the_lock_and_the_versions_it_ran_with(smoke_runs):
    _, ctx = smoke_runs("ao_vsimm_s1")
    smoke_run = ctx.run_dir
    status = json.loads((smoke_run / "status.json").read_text())
    env = status["environment"]
    assert env["lock"]["file"] == "lock/ci.txt" and len(env["lock"]["sha256"]) == 64
    for name in ("numpy", "polars", "hydra-core", "numba", "cloudpickle"):
        assert env["distributions"][name]
    assert isinstance(env["differs_from_lock"], dict)
    import polars as pl
    meta = pl.read_parquet_metadata(smoke_run / "summary.parquet")
    assert meta["mtt.lock"] == env["lock"]["sha256"][:16] and meta["mtt.environment"] == env["hash"]


BLOCKER = """
import importlib.abc, sys
class Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('cloudpickle', 'joblib'):
            raise ImportError(f'{name} is blocked: a single job must not need it')
sys.meta_path.insert(0, Blocked())
"""


@pytest.mark.smoke
def test_a_single_job_runs_without_the_sweep_launchers_dependencies(tmp_path):
    """Before issue 36 ``python -m pipeline`` imported the isolated launcher (and joblib's vendored
    cloudpickle) for every job: a package only sweeps use took the default job down."""
    code = BLOCKER + (
        "import runpy\n"
        f"sys.argv = ['pipeline', 'paths.artifacts={tmp_path.as_posix()}', 'mc.runs=2', 'scenario.steps=20', "
        "'record.enabled=false']\n"
        "runpy.run_module('pipeline', run_name='__main__', alter_sys=True)\n")
    proc = run_code(code, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "FSIMM" in proc.stdout


def test_only_a_sweep_registers_the_isolated_launcher():
    from pipeline.__main__ import is_sweep
    assert is_sweep(["-m", "mc.seed=1,2"]) and is_sweep(["--multirun"]) and is_sweep(["hydra.mode=MULTIRUN"])
    assert not is_sweep(["mc.runs=3", "hydra/launcher=isolated"]) and not is_sweep(["experiment=sonar_case1"])
