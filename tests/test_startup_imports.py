"""Start-up: the default job does not import heavy modules it does not use.

Each is imported where it is needed (a lazy import inside the function, with a comment why):
matplotlib (the report's figures), numba (only a job whose filters or large tables run compiled),
rerun (only when a recording is written), stonesoup (its experiments), optuna and submitit (Hydra's
sweeper and launcher plugins, the [tune] and [slurm] extras), tqdm (a progress bar on a terminal).
Each test runs a fresh interpreter, since this test session has imported most of them already.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from tests.helpers.processes import run_code


NOT_AT_IMPORT = ["scipy", "matplotlib", "numba", "rerun", "stonesoup", "optuna", "submitit", "tqdm"]
# a job without a recording on no terminal. It imports numba: study 001's IMMs run compiled
# (filters/imm/kernel.py; ~0.6-1 s of numba's start, which a 20-run job does not win back, a 100-run
# one does). It does import scipy.stats (~0.9 s on the 2-core machine):
# its intervals and paired tests are scipy.stats' (t, chi-square, Clopper-Pearson, Wilcoxon), kept
# as the library's rather than re-derived here to save that second
NOT_IN_A_JOB = ["matplotlib", "rerun", "stonesoup", "optuna", "submitit", "tqdm"]

_LOADED = "import json, sys; print(json.dumps(sorted(m for m in {names!r} if m in sys.modules)))"


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    # the progress mode as the user's shell sets it (MTT_PROGRESS=off could spare an import this test looks for)
    return run_code(code, cwd=cwd, timeout=300, env={"HYDRA_FULL_ERROR": "1", "MTT_PROGRESS": os.environ.get("MTT_PROGRESS")})


def test_importing_the_runner_and_the_app_loads_none_of_the_heavy_modules(tmp_path):
    proc = _python("import pipeline.run.runner, pipeline.__main__\n" + _LOADED.format(names=NOT_AT_IMPORT), tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == []


def test_the_default_job_without_a_recording_loads_none_of_them(tmp_path):
    code = ("import runpy, sys\n"
            f"sys.argv = ['pipeline', 'paths.artifacts={tmp_path.as_posix()}', 'mc.runs=3', 'record.enabled=false']\n"
            "try:\n"
            "    runpy.run_module('pipeline', run_name='__main__', alter_sys=True)\n"
            "finally:\n"
            "    " + _LOADED.format(names=NOT_IN_A_JOB) + "\n")
    proc = _python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "FSIMM" in proc.stdout                       # the job ran: its summary table
    assert (next((tmp_path / "runs" / "ao_vsimm_s1").iterdir()) / "summary.parquet").is_file()
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == []
